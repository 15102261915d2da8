"""Ports for :class:`gateway.io.port.PortEngine`.

Serial goes through pyserial's ``serial_for_url``, so ``/dev/ttyUSB0``, a pty's path,
``loop://``, ``socket://host:port``, ``rfc2217://host:port`` and ``spy://…`` all work with the
same code; TCP clients, accepted TCP connections and UDP sockets are ports here too."""

from __future__ import annotations

import contextlib
import functools
import ipaddress
import select
import socket
import struct
import time
from collections import OrderedDict
from typing import TYPE_CHECKING, Any, Protocol

from gateway.io import mmsg

if TYPE_CHECKING:  # pyserial is imported by the first serial port opened (~2 ms of a start)
    import serial

READ_SIZE = 65536

DEFAULT_READ_TIMEOUT_S = 0.05


class Transport(Protocol):
    """What the link engine and the sources need of a port."""

    def write(self, data: bytes, /) -> int | None: ...
    def read(self, size: int = 1, /) -> bytes: ...
    def close(self) -> None: ...


class TransportError(OSError):
    """A port could not be opened or used."""


@functools.cache
def socket_serial() -> type:
    """``SocketSerial``: pyserial's ``socket://`` port, whose ``close()`` does not sleep:
    pyserial's sleeps 0.3 s after closing ("in case of quick reconnects"), on the thread that
    closes it — a shared loop's, held 0.3 s per TCP source at every stop (four sources: 1.2
    s, past the gateway's one-second stop budget).  Reopens are paced by the port engine's
    back-off.  A class made on first use: pyserial is imported only with a serial port."""
    from serial.urlhandler import protocol_socket

    class SocketSerial(protocol_socket.Serial):
        __doc__ = socket_serial.__doc__

        def close(self) -> None:
            sock: socket.socket | None = getattr(self, "_socket", None)
            self._socket = None
            if sock is not None:
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
            self.is_open = False

    return SocketSerial


def open_serial(
    url: str,
    baudrate: int = 115200,
    *,
    timeout: float | None = DEFAULT_READ_TIMEOUT_S,
    write_timeout: float | None = 1.0,
    exclusive: bool | None = None,
) -> serial.SerialBase:
    """Open a pyserial port or URL; raises :class:`TransportError` with the URL in the text."""
    import serial

    if url.startswith("rfc2217://"):
        write_timeout = None  # pyserial's RFC 2217 client refuses any write timeout
    kwargs: dict = {"baudrate": baudrate, "timeout": timeout, "write_timeout": write_timeout}
    if exclusive is not None:
        kwargs["exclusive"] = exclusive
    try:
        if url.startswith("socket://"):
            port: serial.SerialBase = socket_serial()(url, **kwargs)
            return port
        return serial.serial_for_url(url, **kwargs)
    except (serial.SerialException, OSError, ValueError, NotImplementedError) as exc:
        raise TransportError(f"cannot open {url}: {exc}") from exc


class NonBlockingSerial:
    """A pyserial port for a shared loop (a router's or a backend's): writes never wait for
    room.

    pyserial's own non-blocking write spins while the port's buffer is full (a radio that has
    stopped reading would hold the loop), so a port with a descriptor is asked first whether
    it can take anything; when it cannot, nothing is written and the engine waits for room."""

    def __init__(self, port: Any) -> None:
        self.serial = port
        try:
            self._fd: int | None = port.fileno()
        except Exception:  # loop://, rfc2217://: polled by the engine, written directly
            self._fd = None

    def fileno(self) -> int:
        if self._fd is None:
            raise OSError("no file descriptor")
        return self._fd

    def read(self, size: int = 1) -> bytes:
        return bytes(self.serial.read(size))

    def write(self, data: bytes) -> int | None:
        fd = self._fd
        if fd is not None and not select.select((), (fd,), (), 0)[1]:
            return 0
        n = self.serial.write(data)
        return n if isinstance(n, int) else None

    def close(self) -> None:
        self.serial.close()


def open_serial_nonblocking(url: str, baudrate: int) -> NonBlockingSerial:
    """:func:`open_serial` for a port engine on a shared loop (see :class:`NonBlockingSerial`)."""
    return NonBlockingSerial(open_serial(url, baudrate, timeout=0, write_timeout=0))


# -- sockets as ports (for gateway.io.port.PortEngine) ---------------------------------------

TCP_OUT_CAP = 256 * 1024
SOCKET_BUFFER = 4 * 1024 * 1024
#: A UDP socket's receive buffer: what may wait for the reader.  The kernel counts a few
#: hundred bytes per datagram whatever its size, so this holds ~600 small MAVLink frames,
#: ~60 ms at 10k msg/s: enough for a scheduling hiccup, and a reader that falls behind for
#: longer drops early instead of forwarding seconds-old frames (4 MiB held ~1 s of them).
#: mavlink-router keeps the system's default (208 KiB), the same order.
UDP_RCVBUF = 256 * 1024
MAX_UDP_PEERS = 16
#: Connections the kernel queues for a listener before we accept them: a burst of connects
#: waits here (for the loop to accept or refuse them) rather than having its SYNs dropped and
#: retried a second later.  (The kernel caps it at net.core.somaxconn, 4096 by default.)
LISTEN_BACKLOG = 1024


def resolve(host: str, port: int, kind: int) -> tuple[int, Any]:
    """(family, address) of ``host:port`` for a socket of ``kind``; TransportError if unknown."""
    try:  # an address literal needs no resolver (nor its IDNA codec: ~1 ms of a start)
        ip = None if "%" in host else ipaddress.ip_address(host)  # "%": a zone, resolved
    except ValueError:
        ip = None
    if ip is not None:
        if ip.version == 4:
            return socket.AF_INET, (host, port)
        return socket.AF_INET6, (host, port, 0, 0)
    try:
        family, _, _, _, addr = socket.getaddrinfo(host, port, type=kind)[0]
    except (socket.gaierror, UnicodeError) as exc:
        raise TransportError(f"cannot resolve {host!r}: {exc}") from None
    return family, addr


class SocketPort:
    """A connected TCP socket as a port: reads what is waiting, writes without blocking.

    A write the socket takes only in part returns the count (the engine keeps the rest and
    waits for room); the peer closing the connection is an error on the next read."""

    def __init__(self, sock: socket.socket, name: str = "") -> None:
        self.sock = sock
        self.name = name
        sock.setblocking(False)
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def fileno(self) -> int:
        return self.sock.fileno()

    def read(self, size: int = READ_SIZE) -> bytes:
        try:
            data = self.sock.recv(size)
        except (BlockingIOError, InterruptedError):
            return b""
        if not data:
            raise ConnectionError("connection closed by the peer")
        return data

    def write(self, data: bytes) -> int:
        try:
            return self.sock.send(data)
        except (BlockingIOError, InterruptedError):
            return 0

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()

    def abort(self) -> None:
        """Close with a reset, dropping what is unsent: a peer that stopped reading would
        otherwise hold the connection (and the kernel's buffers) open behind our close, its
        window shut to our FIN."""
        with contextlib.suppress(OSError):
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_RESET)
        self.sock.close()


_LINGER_RESET = struct.pack("ii", 1, 0)


def open_tcp_client(host: str, port: int, timeout: float = 2.0) -> SocketPort:
    """Connect to ``host:port`` (waiting up to ``timeout``); raises :class:`TransportError`."""
    try:
        sock = socket.create_connection((host, port), timeout=timeout)
    except OSError as exc:
        raise TransportError(f"cannot connect to {host}:{port}: {exc.strerror or exc}") from None
    return SocketPort(sock, f"{host}:{port}")


class UdpPort:
    """A UDP socket as a datagram port.

    With a destination (``udpout``) every write goes there; without one (``udpin``) it goes to
    every peer that has sent to us, the ``max_peers`` most recent.  UDP errors (nobody
    listening, no route) are counted, never a failure of the port."""

    datagram = True

    def __init__(self, sock: socket.socket, dest: Any = None,
                 max_peers: int = MAX_UDP_PEERS) -> None:
        self.sock = sock
        self.dest = dest
        self.max_peers = max_peers
        self.peers: OrderedDict[Any, float] = OrderedDict()
        self.last_peer: Any = None
        self.new_peers = 0
        self.send_errors = 0
        self.send_refused = 0  # "port unreachable": nobody listens there (yet); not an error
        self.send_dropped = 0
        self.not_sent = 0  # writes with nobody to send to (udpin before any peer)
        self.connected = False  # udpout from open_udp: connected, so refusals are reported
        self._buf = bytearray(65536)  # the largest datagram
        self._view = memoryview(self._buf)
        if dest is not None:
            with contextlib.suppress(OSError):
                self.connected = sock.getpeername() is not None
        #: recvmmsg/sendmmsg where the platform has them (see :mod:`gateway.io.mmsg`)
        self.mmsg: mmsg.MmsgSocket | None = mmsg.MmsgSocket(sock) if mmsg.AVAILABLE else None

    @property
    def destinations(self) -> tuple[Any, ...]:
        return (self.dest,) if self.dest is not None else tuple(self.peers)

    def fileno(self) -> int:
        return self.sock.fileno()

    def address(self) -> Any:
        return self.sock.getsockname()

    def read(self, size: int = 65536) -> bytes:
        buf = self._buf
        while True:
            try:  # into one buffer, then a copy of what came: no 64 KiB object per datagram
                n, addr = self.sock.recvfrom_into(buf)
            except (BlockingIOError, InterruptedError):
                return b""
            except ConnectionRefusedError:  # ICMP for an earlier send: nobody listens there
                self.send_refused += 1
                continue
            data = bytes(self._view[:n])
            if self.dest is None:
                self._saw_peer(addr)
            self.last_peer = addr
            return data

    def _saw_peer(self, addr: Any) -> None:
        """``addr`` sent a datagram: the most recent in the bounded peer table."""
        peers = self.peers
        if addr in peers:
            peers.move_to_end(addr)
        else:
            peers[addr] = time.monotonic()
            self.new_peers += 1
            if len(peers) > self.max_peers:
                peers.popitem(last=False)

    def read_many(self) -> list[bytes]:
        """Every datagram waiting, up to :data:`gateway.io.mmsg.BATCH` (one system call
        where ``recvmmsg`` exists); [] when there is none."""
        mm = self.mmsg
        if mm is None:
            out = []
            for _ in range(mmsg.BATCH):
                data = self.read()
                if not data:
                    break
                out.append(data)
            return out
        try:
            if self.dest is not None:
                return mm.recv(False)[0]
            datagrams, senders = mm.recv_senders()
        finally:
            if mm.refused:
                self.send_refused += mm.refused
                mm.refused = 0
        self.took(senders)
        return datagrams

    def took(self, senders: list[Any]) -> None:
        """The peer table after datagrams from ``senders`` (one per run from one sender, in
        order) were read."""
        # (a run from the latest peer again: it is last in the table already)
        if senders and (len(senders) > 1 or senders[0] != self.last_peer):
            for addr in senders:  # once per run of datagrams from one sender
                self._saw_peer(addr)
            self.last_peer = senders[-1]

    def write_many(self, datagrams: list[bytes], first: int | None = None) -> None:
        """:meth:`write` each of ``datagrams``, in order (one system call per destination
        where ``sendmmsg`` exists).  ``first``: see :meth:`MmsgSocket.send` (connected
        only)."""
        mm = self.mmsg
        if first is not None:
            assert mm is not None and self.connected
            refused, dropped, failed = mm.send(datagrams, None, first)
            self.send_refused += refused
            self.send_dropped += dropped
            self.send_errors += failed
            return
        if mm is None or (not self.connected and self.dest is not None):
            for data in datagrams:
                self.write(data)
            return
        dests: tuple[Any, ...] = (None,) if self.connected else tuple(self.peers)
        if not dests:
            self.not_sent += len(datagrams)
            return
        for d in dests:
            refused, dropped, failed = mm.send(datagrams, d)
            self.send_refused += refused
            self.send_dropped += dropped
            self.send_errors += failed

    def write(self, data: bytes) -> int:
        if self.connected:  # udpout (the router's per-frame path): one send, no lookups
            try:
                self.sock.send(data)
            except BlockingIOError:
                self.send_dropped += 1
            except ConnectionRefusedError:
                self.send_refused += 1
            except OSError:
                self.send_errors += 1
            return len(data)
        dests = self.destinations
        if not dests:
            self.not_sent += 1
            return len(data)
        for d in dests:
            try:
                self.sock.sendto(data, d)
            except BlockingIOError:
                self.send_dropped += 1
            except OSError:
                self.send_errors += 1
        return len(data)

    def close(self) -> None:
        self.sock.close()


def open_udp(host: str, port: int, *, listen: bool) -> UdpPort:
    """``listen``: bind ``host:port`` and answer the peers (udpin); otherwise send to
    ``host:port`` from an ephemeral port connected to it (udpout: what comes back from there
    is read).  Raises :class:`TransportError`."""
    family, addr = resolve(host, port, socket.SOCK_DGRAM)
    if listen:
        return UdpPort(_udp_socket(family, "bind", addr, host, port), None)
    try:
        # Connected: Linux reports "port unreachable" only on a connected UDP socket, so
        # "nobody listening" is seen and counted rather than silent.
        sock = _udp_socket(family, "connect", addr, host, port)
    except TransportError:  # no route yet, or a broadcast address: send unconnected
        any_addr = ("::", 0) if family == socket.AF_INET6 else ("0.0.0.0", 0)
        sock = _udp_socket(family, "bind", any_addr, host, port)
    return UdpPort(sock, addr)


def _udp_socket(family: int, how: str, addr: Any, host: str, port: int) -> socket.socket:
    sock = socket.socket(family, socket.SOCK_DGRAM)
    try:
        sock.setblocking(False)
        for opt, size in ((socket.SO_RCVBUF, UDP_RCVBUF), (socket.SO_SNDBUF, SOCKET_BUFFER)):
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, opt, size)
        if how == "connect":
            sock.connect(addr)
        else:
            sock.bind(addr)
    except OSError as exc:
        sock.close()
        raise TransportError(f"cannot {how} udp {host}:{port}: {exc.strerror or exc}") from None
    return sock


def open_tcp_listener(host: str, port: int, backlog: int = LISTEN_BACKLOG) -> socket.socket:
    """A non-blocking listening socket on ``host:port``; raises :class:`TransportError`."""
    family, addr = resolve(host, port, socket.SOCK_STREAM)
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(backlog)
        sock.setblocking(False)
    except OSError as exc:
        sock.close()
        raise TransportError(f"cannot listen on tcp {host}:{port}: "
                             f"{exc.strerror or exc}") from None
    return sock


def __getattr__(name: str) -> Any:
    """``SocketSerial``: the class :func:`socket_serial` makes, when first asked for."""
    if name == "SocketSerial":
        return socket_serial()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
