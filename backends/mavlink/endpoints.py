"""MAVLink endpoints in the vocabulary MAVLink users know, each a :class:`~.router.Link`.

==========================  ==============================================================
``udpout:HOST:PORT``        send to HOST:PORT (QGroundControl listens on 14550); replies to
                            our socket are received and routed
``udpin:HOST:PORT``         listen on HOST:PORT (``udp:`` is the same, as in MAVProxy);
                            send to every peer that has sent to us (the last 16)
``tcpin:HOST:PORT``         TCP server; every client is a link of its own
``tcp:HOST:PORT``           TCP client, reconnecting with backoff
``serial:DEVICE[,BAUD]``    a serial port or telemetry radio (default 57600 baud); also a
                            bare ``/dev/…``/``COMn`` or a pyserial URL (``socket://…``,
                            ``rfc2217://…``, ``loop://``), with an optional ``,BAUD``
==========================  ==============================================================

Nothing here blocks the caller: UDP and TCP-server sockets are non-blocking and owned by the
router's I/O loop (a TCP client too slow to read gets a bounded buffer, then drops, counted);
serial ports and TCP clients write through a :class:`~gateway.link.LinkEngine` (bounded
queue, worker thread, reconnect with backoff) and are read by a reader thread of their own.
"""

from __future__ import annotations

import contextlib
import logging
import re
import selectors
import socket
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, NamedTuple

from backends.mavlink.ioloop import IoLoop
from backends.mavlink.router import Link, Router
from gateway.backend import Outcome
from gateway.backoff import Backoff
from gateway.link import LinkEngine
from gateway.transport import TransportError, open_serial

log = logging.getLogger(__name__)

DEFAULT_SERIAL_BAUD = 57600
MAX_UDP_PEERS = 16
TCP_OUT_CAP = 256 * 1024
SOCKET_BUFFER = 4 * 1024 * 1024
READ_BATCH = 64
_COM = re.compile(r"^COM\d+$", re.IGNORECASE)

KINDS = ("udpout", "udpin", "tcpin", "tcp", "serial")
USAGE = ("use udpout:HOST:PORT, udpin:HOST:PORT, tcpin:HOST:PORT, tcp:HOST:PORT or "
         "serial:DEVICE[,BAUD]")


class EndpointSpec(NamedTuple):
    kind: str
    host: str = ""
    port: int = 0
    device: str = ""
    baudrate: int = 0
    text: str = ""


def _host_port(rest: str, text: str, kind: str) -> tuple[str, int]:
    host, sep, port_s = rest.rpartition(":")
    if not sep:
        raise ValueError(f"{text!r}: expected {kind}:HOST:PORT")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not host:
        host = "0.0.0.0" if kind in ("udpin", "tcpin") else "127.0.0.1"
    try:
        port = int(port_s)
    except ValueError:
        raise ValueError(f"{text!r}: port {port_s!r} is not a number") from None
    lowest = 0 if kind in ("udpin", "tcpin") else 1  # 0: let the system pick (tests)
    if not lowest <= port <= 65535:
        raise ValueError(f"{text!r}: port must be {lowest}..65535")
    return host, port


def _device_baud(rest: str, text: str) -> tuple[str, int]:
    device, sep, baud_s = rest.rpartition(",")
    if not sep:
        return rest, DEFAULT_SERIAL_BAUD
    try:
        baud = int(baud_s)
    except ValueError:
        raise ValueError(f"{text!r}: baud rate {baud_s!r} is not a number") from None
    if baud < 50:
        raise ValueError(f"{text!r}: baud rate must be at least 50")
    return device, baud


def parse_endpoint(text: str) -> EndpointSpec:
    """Parse an endpoint string; raises ValueError naming it and the accepted forms."""
    t = text.strip()
    if not t:
        raise ValueError(f"empty MAVLink endpoint; {USAGE}")
    scheme, sep, rest = t.partition(":")
    s = scheme.lower()
    if sep and s in ("udpout", "udpin", "udp", "tcpin", "tcp") and not rest.startswith("//"):
        kind = "udpin" if s == "udp" else s
        host, port = _host_port(rest, t, kind)
        return EndpointSpec(kind, host, port, text=t)
    if sep and s == "serial":
        device, baud = _device_baud(rest, t)
    elif t.startswith("/dev/") or _COM.match(t.partition(",")[0]) or "://" in t:
        device, baud = _device_baud(t, t)
    else:
        raise ValueError(f"{text!r}: not a MAVLink endpoint; {USAGE}")
    if not device:
        raise ValueError(f"{text!r}: no serial device; {USAGE}")
    return EndpointSpec("serial", device=device, baudrate=baud, text=t)


class Endpoint:
    """A configured endpoint: starts its link(s) on a router and reports their counters."""

    def __init__(self, spec: EndpointSpec) -> None:
        self.spec = spec
        self.name = spec.text

    def start(self, loop: IoLoop, router: Router) -> None:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def links(self) -> list[Link]:
        raise NotImplementedError

    def stats(self) -> dict[str, Any]:
        total: dict[str, Any] = {}
        for link in self.links():
            for k, v in link.stats().items():
                if isinstance(v, int):
                    total[k] = total.get(k, 0) + v
        return total


# -- UDP ----------------------------------------------------------------------------------------

class UdpEndpoint(Endpoint, Link):
    """``udpout:`` (fixed destination) or ``udpin:`` (reply to the peers that talk to us)."""

    datagram = True

    def __init__(self, spec: EndpointSpec) -> None:
        Endpoint.__init__(self, spec)
        Link.__init__(self, spec.text)
        self.sock: socket.socket | None = None
        self.dest: Any = None
        self.peers: OrderedDict[Any, float] = OrderedDict()
        self._router: Router | None = None

    def start(self, loop: IoLoop, router: Router) -> None:
        spec = self.spec
        try:
            infos = socket.getaddrinfo(spec.host, spec.port, type=socket.SOCK_DGRAM)
        except socket.gaierror as exc:
            raise OSError(f"{spec.text}: cannot resolve {spec.host!r}: {exc}") from None
        family, _, _, _, addr = infos[0]
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setblocking(False)
            for opt in (socket.SO_RCVBUF, socket.SO_SNDBUF):
                with contextlib.suppress(OSError):
                    sock.setsockopt(socket.SOL_SOCKET, opt, SOCKET_BUFFER)
            if spec.kind == "udpin":
                sock.bind(addr)
            else:
                sock.bind(("::", 0) if family == socket.AF_INET6 else ("0.0.0.0", 0))
                self.dest = addr
        except OSError as exc:
            sock.close()
            raise OSError(f"{spec.text}: {exc.strerror or exc}") from None
        self.sock = sock
        self._router = router
        loop.register(sock, selectors.EVENT_READ, self._on_readable)
        router.add_link(self)

    @property
    def address(self) -> Any:
        """The local address (the bound port of ``udpin:HOST:0``)."""
        return self.sock.getsockname() if self.sock is not None else None

    @property
    def up(self) -> bool:
        return self.sock is not None and (self.dest is not None or bool(self.peers))

    def _on_readable(self, mask: int) -> None:
        sock = self.sock
        if sock is None:
            return
        batch: list[bytes] = []
        is_in = self.dest is None
        peers = self.peers
        for _ in range(READ_BATCH):
            try:
                data, addr = sock.recvfrom(65536)
            except BlockingIOError:
                break
            except ConnectionRefusedError:  # ICMP for an earlier send: nobody listens there
                self.counters.tx_errors += 1
                continue
            except OSError:
                break
            if is_in:
                if addr in peers:
                    peers.move_to_end(addr)
                else:
                    peers[addr] = time.monotonic()
                    log.info("%s: peer %s", self.name, addr)
                    if len(peers) > MAX_UDP_PEERS:
                        peers.popitem(last=False)
            batch.append(data)
        if batch:
            self._router.receive_many(self, batch)  # type: ignore[union-attr]

    def send(self, data: bytes) -> bool:
        sock = self.sock
        c = self.counters
        dests = (self.dest,) if self.dest is not None else tuple(self.peers)
        if sock is None or not dests:
            c.tx_not_up += 1  # closed, or udpin: nobody has talked to us yet
            return False
        ok = False
        for d in dests:
            try:
                sock.sendto(data, d)
            except BlockingIOError:
                c.tx_dropped += 1
                continue
            except OSError:
                c.tx_errors += 1
                continue
            c.tx_frames += 1
            c.tx_bytes += len(data)
            ok = True
        return ok

    def close(self) -> None:
        sock, self.sock = self.sock, None
        if sock is not None:
            if self._router is not None:
                self._router.remove_link(self)
            sock.close()

    def links(self) -> list[Link]:
        return [self]

    def stats(self) -> dict[str, Any]:
        d = Link.stats(self)
        if self.dest is None:
            d["peers"] = len(self.peers)
        return d


# -- TCP server -----------------------------------------------------------------------------------

class TcpConnection(Link):
    """One accepted TCP client of a ``tcpin:`` endpoint."""

    def __init__(self, name: str, sock: socket.socket, loop: IoLoop, router: Router,
                 on_close: Callable[[TcpConnection], None]) -> None:
        super().__init__(name)
        self.sock: socket.socket | None = sock
        self._loop = loop
        self._router = router
        self._on_close = on_close
        self._out = bytearray()
        self._want_write = False

    @property
    def up(self) -> bool:
        return self.sock is not None

    def send(self, data: bytes) -> bool:  # called with the router lock held
        c = self.counters
        sock = self.sock
        if sock is None:
            c.tx_not_up += 1
            return False
        if self._out:
            if len(self._out) + len(data) > TCP_OUT_CAP:
                c.tx_dropped += 1  # the client does not keep up: drop whole frames
                return False
            self._out += data
        else:
            try:
                n = sock.send(data)
            except BlockingIOError:
                n = 0
            except OSError:
                c.tx_errors += 1
                self._loop.call_soon(self.close)
                return False
            if n < len(data):
                self._out += data[n:]
        c.tx_frames += 1
        c.tx_bytes += len(data)
        if self._out and not self._want_write:
            self._want_write = True
            self._loop.call_soon(self._watch_writes)
        return True

    def _watch_writes(self) -> None:
        if self.sock is not None:
            self._loop.modify(self.sock, selectors.EVENT_READ | selectors.EVENT_WRITE,
                              self._on_event)

    def _on_event(self, mask: int) -> None:
        sock = self.sock
        if sock is None:
            return
        if mask & selectors.EVENT_READ:
            try:
                data = sock.recv(65536)
            except BlockingIOError:
                data = None
            except OSError:
                data = b""
            if data == b"":
                self.close()
                return
            if data:
                self._router.receive(self, data)
        if mask & selectors.EVENT_WRITE:
            with self._router.lock:
                try:
                    n = sock.send(self._out)
                except BlockingIOError:
                    n = 0
                except OSError:
                    self.counters.tx_errors += 1
                    self.close()
                    return
                del self._out[:n]
                if not self._out:
                    self._want_write = False
                    self._loop.modify(sock, selectors.EVENT_READ, self._on_event)

    def close(self) -> None:
        sock, self.sock = self.sock, None
        if sock is None:
            return
        self._loop.unregister(sock)
        self._router.remove_link(self)
        with contextlib.suppress(OSError):
            sock.close()
        log.info("%s: disconnected", self.name)
        self._on_close(self)


class TcpServerEndpoint(Endpoint):
    """``tcpin:HOST:PORT``: accepts any number of clients, each routed as its own link."""

    def __init__(self, spec: EndpointSpec) -> None:
        super().__init__(spec)
        self.sock: socket.socket | None = None
        self.clients: list[TcpConnection] = []
        self.accepted = 0
        self._closed_stats: dict[str, int] = {}
        self._loop: IoLoop | None = None
        self._router: Router | None = None

    def start(self, loop: IoLoop, router: Router) -> None:
        spec = self.spec
        try:
            infos = socket.getaddrinfo(spec.host, spec.port, type=socket.SOCK_STREAM)
            family, _, _, _, addr = infos[0]
            sock = socket.socket(family, socket.SOCK_STREAM)
        except (socket.gaierror, OSError) as exc:
            raise OSError(f"{spec.text}: {exc}") from None
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(addr)
            sock.listen(16)
            sock.setblocking(False)
        except OSError as exc:
            sock.close()
            raise OSError(f"{spec.text}: {exc.strerror or exc}") from None
        self.sock = sock
        self._loop, self._router = loop, router
        loop.register(sock, selectors.EVENT_READ, self._on_accept)

    @property
    def address(self) -> Any:
        return self.sock.getsockname() if self.sock is not None else None

    def _on_accept(self, mask: int) -> None:
        if self.sock is None:
            return
        try:
            conn, addr = self.sock.accept()
        except (BlockingIOError, OSError):
            return
        conn.setblocking(False)
        with contextlib.suppress(OSError):
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.accepted += 1
        link = TcpConnection(f"{self.name}<{addr[0]}:{addr[1]}>", conn, self._loop,  # type: ignore[arg-type]
                             self._router, self._client_closed)  # type: ignore[arg-type]
        self.clients.append(link)
        self._router.add_link(link)  # type: ignore[union-attr]
        self._loop.register(conn, selectors.EVENT_READ, link._on_event)  # type: ignore[union-attr]
        log.info("%s: client %s:%s connected", self.name, addr[0], addr[1])

    def _client_closed(self, link: TcpConnection) -> None:
        if link in self.clients:
            self.clients.remove(link)
            for k, v in link.stats().items():
                if isinstance(v, int):
                    self._closed_stats[k] = self._closed_stats.get(k, 0) + v

    def links(self) -> list[Link]:
        return list(self.clients)

    def stats(self) -> dict[str, Any]:
        d = dict(self._closed_stats)
        for k, v in super().stats().items():
            d[k] = d.get(k, 0) + v
        d["clients"] = len(self.clients)
        d["accepted"] = self.accepted
        return d

    def close(self) -> None:
        for c in list(self.clients):
            c.close()
        sock, self.sock = self.sock, None
        if sock is not None:
            if self._loop is not None:
                self._loop.unregister(sock)
            sock.close()


# -- byte streams through the link engine: serial ports and TCP clients -------------------------

class _SocketTransport:
    """A connected TCP socket as a :class:`gateway.transport.Transport`."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        sock.settimeout(1.0)  # a write stuck this long is a dead peer: reconnect
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.in_waiting = 0

    def write(self, data: bytes) -> int:
        self.sock.sendall(data)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        try:
            data = self.sock.recv(max(size, 65536))
        except TimeoutError:
            return b""
        if not data:
            raise ConnectionError("connection closed by the peer")
        return data

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


class StreamEndpoint(Endpoint, Link):
    """``serial:`` and ``tcp:``: a LinkEngine writes, a reader thread reads, both reopen the
    port (with backoff) when it fails."""

    def __init__(self, spec: EndpointSpec, queue_depth: int = 256) -> None:
        Endpoint.__init__(self, spec)
        Link.__init__(self, spec.text)
        self._port: Any = None
        self._router: Router | None = None
        self._stop = threading.Event()
        self._reader: threading.Thread | None = None
        self.read_errors = 0
        self.engine = LinkEngine(self._open, name=spec.text, queue_depth=queue_depth,
                                 backoff=Backoff(0.1, 5.0))

    def _open(self) -> Any:
        spec = self.spec
        if spec.kind == "tcp":
            try:
                sock = socket.create_connection((spec.host, spec.port), timeout=2.0)
            except OSError as exc:
                raise TransportError(f"cannot connect to {spec.host}:{spec.port}: "
                                     f"{exc.strerror or exc}") from None
            port: Any = _SocketTransport(sock)
        else:
            port = open_serial(spec.device, spec.baudrate, timeout=0.05)
        self._port = port
        return port

    @property
    def up(self) -> bool:
        return self.engine.connected

    def start(self, loop: IoLoop, router: Router) -> None:
        self._router = router
        router.add_link(self)
        self.engine.start()
        self._reader = threading.Thread(target=self._read_loop, name=f"mavlink-rx-{self.name}",
                                        daemon=True)
        self._reader.start()

    def send(self, data: bytes) -> bool:
        c = self.counters
        outcome = self.engine.submit(data, rate_limited=False)
        if outcome is Outcome.ACCEPTED:
            c.tx_frames += 1
            c.tx_bytes += len(data)
            return True
        if outcome is Outcome.NOT_READY:
            c.tx_not_up += 1  # the port is down: frames are not kept for when it is back
        else:
            c.tx_dropped += 1
        return False

    def _read_loop(self) -> None:
        stop = self._stop
        router = self._router
        assert router is not None
        while not stop.is_set():
            port = self._port
            if port is None or not self.engine.connected:
                stop.wait(0.05)
                continue
            try:
                n = getattr(port, "in_waiting", 0)
                data = port.read(n if n > 0 else 1)
            except Exception as exc:
                if stop.is_set():
                    return
                self.read_errors += 1
                log.warning("%s: read failed (%s); reopening", self.name, exc)
                self._port = None
                self.engine.reconnect()  # the engine's worker closes the port and reopens it
                stop.wait(0.1)
                continue
            if data:
                router.receive(self, data)

    def close(self) -> None:
        self._stop.set()
        self.engine.close(0.5)
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()
        if self._reader is not None:
            self._reader.join(0.5)
        if self._router is not None:
            self._router.remove_link(self)

    def links(self) -> list[Link]:
        return [self]

    def stats(self) -> dict[str, Any]:
        d = Link.stats(self)
        es = self.engine.stats
        d.update(connects=es.connects, connect_failures=es.connect_failures,
                 write_errors=es.write_errors, read_errors=self.read_errors)
        return d


def make_endpoint(spec: EndpointSpec, queue_depth: int = 256) -> Endpoint:
    if spec.kind in ("udpout", "udpin"):
        return UdpEndpoint(spec)
    if spec.kind == "tcpin":
        return TcpServerEndpoint(spec)
    return StreamEndpoint(spec, queue_depth)
