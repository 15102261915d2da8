"""The Foxglove backend's front door: :class:`ProtocolRelay`, a TCP relay on the public port in
front of foxglove-sdk's server (which listens on a loopback port of its own).

It lets clients of both generations in (:mod:`backends.foxglove.handshake`: a client that
offers only ``foxglove.websocket.v1`` has its handshake renamed both ways) and holds every
client to the gateway's listener limits (:class:`~gateway.io.server.PortServer`: a client
cap, a listen backlog, a request that stays incomplete or a client that stops reading for
``client_timeout_s`` is cut), and it logs what clients do once per burst with their real
addresses (the SDK sees only the relay's).  After the handshake each connection copies bytes
both ways unchanged, with back-pressure: at most :data:`HIGH_WATER` bytes wait per direction,
then the relay stops reading the other side — a slow client's backlog is then the SDK's,
which drops its oldest messages (``backlog``).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import selectors
import socket
import struct
import time
from collections.abc import Callable
from typing import Any, cast

from backends.foxglove import handshake
from gateway.io.burstlog import BurstLog
from gateway.io.ioloop import IoLoop, Timer
from gateway.io.port import PortEngine
from gateway.io.server import ClientLimits, PortServer
from gateway.io.transport import open_tcp_listener

log = logging.getLogger(__name__)

READ_SIZE = 65536
#: Bytes waiting in one direction before the relay stops reading the side they come from.
HIGH_WATER = 256 * 1024
#: A side that has ended its half: how long the other may take to end its own.
FINISH_S = 2.0
_READ = selectors.EVENT_READ
_WRITE = selectors.EVENT_WRITE
_GONE = (ConnectionError, TimeoutError)
# the relay's states
_REQUEST, _ANSWER, _RELAY = 0, 1, 2


def _refusal(code: bytes, text: bytes) -> bytes:
    return (b"HTTP/1.1 " + code + b"\r\nContent-Type: text/plain\r\nContent-Length: "
            + str(len(text)).encode() + b"\r\nConnection: close\r\n\r\n" + text)


#: A request head past MAX_HEAD.
TOO_LARGE = _refusal(b"431 Request Header Fields Too Large", b"request head too large\n")
#: A client past the cap.
TOO_MANY = _refusal(b"503 Service Unavailable", b"too many clients\n")


def has_request(sock: socket.socket) -> bool:
    """Does ``sock`` already hold a whole request head (looked at, not read)?"""
    try:
        data = sock.recv(handshake.MAX_HEAD, socket.MSG_PEEK | socket.MSG_DONTWAIT)
    except OSError:
        return False
    return handshake.END in data


class ProtocolRelay:
    """Listens on ``host:port`` and relays each client to the SDK's server at ``upstream``
    (a loopback address), on ``loop``; see the module doc."""

    def __init__(self, listener: socket.socket, upstream: tuple[str, int], *, loop: IoLoop,
                 name: str, limits: ClientLimits | None = None) -> None:
        self.name = name
        self.loop = loop
        self.upstream = upstream
        self.address: tuple[Any, ...] = listener.getsockname()
        pending = [listener]
        host, port = self.address[0], self.address[1]

        def opener() -> socket.socket:  # bound again on the same port after a failure
            return pending.pop() if pending else open_tcp_listener(host, port)

        self.server = PortServer(
            opener, self._on_client, loop=loop, name=name, limits=limits, refusal=TOO_MANY,
            ready=has_request)
        #: the connections open (the loop's thread only)
        self.connections: set[_Connection] = set()
        self.served = {handshake.SDK: 0, handshake.LEGACY: 0}  # handshakes done, by name
        self.refused = 0  # handshakes the SDK refused (or too large)
        self.closing = False
        self.connected_log = BurstLog(loop, f"{name}: client connected", level=logging.INFO,
                                      logger=log)
        self.left_log = BurstLog(loop, f"{name}: client left", level=logging.INFO, logger=log)
        self.refused_log = BurstLog(
            loop, f"{name}: handshake refused (a Foxglove client offers "
            f"{' or '.join(handshake.ACCEPTED)})", logger=log)

    def start(self) -> None:
        self.server.start()

    def close(self) -> None:
        """Stop listening and close every connection (the loop's thread, or after it has
        stopped); safe twice."""
        self.closing = True
        self.server.close()
        for conn in list(self.connections):
            conn.close()
        for burst in (self.connected_log, self.left_log, self.refused_log):
            burst.cancel()

    def _on_client(self, sock: socket.socket, addr: Any) -> PortEngine:
        conn = _Connection(self, sock, addr)
        self.connections.add(conn)
        # The server holds it to its limits through the attributes it reads of an engine.
        return cast(PortEngine, conn)

    def stats(self) -> dict[str, int]:
        return {"connections": len(self.connections),
                "served_sdk": self.served[handshake.SDK],
                "served_legacy": self.served[handshake.LEGACY],
                "handshakes_refused": self.refused}


class _Connection:
    """One client and its connection to the SDK's server.  It offers what
    :class:`~gateway.io.server.PortServer` reads of a served client: ``name``, ``alive``,
    ``partial_since``, ``port.sock``, ``stalled_for(now)``, ``cut(why)``."""

    def __init__(self, relay: ProtocolRelay, sock: socket.socket, addr: Any) -> None:
        self.relay = relay
        self.loop = relay.loop
        self.peer = f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr)
        self.name = f"{relay.name} {self.peer}"
        self.sock = sock
        self.port = self  # (the server looks at ``engine.port.sock``)
        self.alive = True
        self.partial_since: float | None = time.monotonic()  # the request is not whole yet
        self.protocol = ""  # the name it is served under (or what it offered)
        self.served = False  # the SDK took its handshake
        self.since = time.monotonic()
        self.up: socket.socket | None = None
        self._state = _REQUEST
        self._connecting = False
        self._head = bytearray()  # the request head, then the answer head, being read
        self._to_up = bytearray()
        self._to_client = bytearray()
        self._client_eof = self._up_eof = False
        self._client_shut = self._up_shut = False
        self._interest: dict[socket.socket, int] = {}
        self._blocked_since: float | None = None
        self._finish: Timer | None = None
        sock.setblocking(False)
        with contextlib.suppress(OSError):  # relay each message as it comes (no Nagle wait)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._update()

    # -- what the server reads -----------------------------------------------------------------

    def stalled_for(self, now: float) -> float:
        """How long bytes for the client have waited without it taking any."""
        since = self._blocked_since
        return 0.0 if since is None else now - since

    def cut(self, why: str) -> None:
        """Close at once; the client gets a reset (what it did not read is dropped)."""
        log.debug("%s: cut (%s)", self.name, why)
        with contextlib.suppress(OSError):
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.close()

    # -- events ----------------------------------------------------------------------------------

    def _on_client(self, mask: int) -> None:
        try:
            if mask & _WRITE:
                self._send(self.sock, self._to_client)
            if mask & _READ:
                self._read_client()
        except OSError as exc:
            self._gone(exc)
            return
        self._update()

    def _on_up(self, mask: int) -> None:
        up = self.up
        if up is None:
            return
        try:
            if self._connecting and mask & (_READ | _WRITE):
                err = up.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
                if err:
                    raise OSError(err, f"the SDK's server: {errno.errorcode.get(err, err)}")
                self._connecting = False
            if mask & _WRITE:
                self._send(up, self._to_up)
            if mask & _READ:
                self._read_up()
        except OSError as exc:
            self._gone(exc)
            return
        self._update()

    def _read_client(self) -> None:
        data = self.sock.recv(READ_SIZE)
        if not data:
            self._client_eof = True
            if self._state == _REQUEST:
                self.close()  # left before asking for anything
            return
        if self._state == _REQUEST:
            self._request(data)
        elif self.up is None or self._up_shut or self._up_eof:
            return  # the SDK's side has ended: what the client says is dropped
        else:
            self._forward(self.up, self._to_up, data)

    def _request(self, data: bytes) -> None:
        self._head += data
        end = self._head.find(handshake.END)
        if end < 0:
            if len(self._head) > handshake.MAX_HEAD:
                self._refuse(TOO_LARGE, "request head too large")
            return
        head, rest = bytes(self._head[:end]), bytes(self._head[end + 4:])
        self._head.clear()
        self.partial_since = None
        names = handshake.offered(head)
        self.protocol = handshake.served_as(names) or ", ".join(names) or "no subprotocol"
        if self.protocol == handshake.LEGACY:
            head = handshake.to_sdk(head)
        self._to_up += head + handshake.END + rest
        self._state = _ANSWER
        up = self.up = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        up.setblocking(False)
        up.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._connecting = True
        err = up.connect_ex(self.relay.upstream)
        if err not in (0, errno.EINPROGRESS, errno.EAGAIN):
            raise OSError(err, f"cannot reach the SDK's server: {errno.errorcode.get(err)}")

    def _read_up(self) -> None:
        assert self.up is not None
        data = self.up.recv(READ_SIZE)
        if not data:
            self._up_eof = True
            return
        if self._state == _ANSWER:
            self._head += data
            end = self._head.find(handshake.END)
            if end < 0:
                if len(self._head) > handshake.MAX_HEAD:
                    raise OSError(errno.EPROTO, "the SDK's answer head is too large")
                return
            head, rest = bytes(self._head[:end]), bytes(self._head[end + 4:])
            self._head.clear()
            self._answered(head)
            if self.protocol == handshake.LEGACY:
                head = handshake.to_legacy(head)
            data = head + handshake.END + rest
            self._state = _RELAY
        if not self._client_shut:
            self._forward(self.sock, self._to_client, data)

    def _answered(self, head: bytes) -> None:
        relay = self.relay
        code = handshake.status(head)
        if code == 101 and self.protocol in relay.served:
            self.served = True
            relay.served[self.protocol] += 1
            relay.connected_log.event(f"{self.peer} ({self.protocol})")
        else:
            relay.refused += 1
            relay.refused_log.event(f"{self.peer} offered {self.protocol}: HTTP {code}")

    def _refuse(self, answer: bytes, why: str) -> None:
        self.relay.refused += 1
        self.relay.refused_log.event(f"{self.peer}: {why}")
        self.partial_since = None
        self._state = _RELAY
        self._up_eof = True  # nothing comes from the SDK: answer, then finish
        self._to_client += answer
        self._send(self.sock, self._to_client)

    # -- writing, interest, the end ------------------------------------------------------------

    def _forward(self, sock: socket.socket, buf: bytearray, data: bytes) -> None:
        """Send ``data`` on ``sock`` now if nothing waits before it; what it does not take
        waits in ``buf``."""
        if buf or (sock is self.up and self._connecting):
            buf += data
            return
        try:
            n = sock.send(data)
        except (BlockingIOError, InterruptedError):
            n = 0
        if n < len(data):
            buf += memoryview(data)[n:]
            if buf is self._to_client:  # (nothing waited before: it starts waiting now)
                self._blocked_since = time.monotonic()
        elif buf is self._to_client:
            self._blocked_since = None

    def _send(self, sock: socket.socket, buf: bytearray) -> None:
        if not buf or (sock is self.up and self._connecting):
            return
        try:
            n = sock.send(buf)
        except (BlockingIOError, InterruptedError):
            n = 0
        if buf is self._to_client:
            if n:
                self._blocked_since = None  # it reads: not stalled (slow, maybe)
            if n < len(buf) and self._blocked_since is None:
                self._blocked_since = time.monotonic()
        del buf[:n]

    def _update(self) -> None:
        """The end of each event: half-closes, the end, and what each socket waits for."""
        if not self.alive:
            return
        up = self.up
        if self._client_eof and not self._to_up and up is not None and not self._up_shut \
                and not self._connecting:
            self._up_shut = True
            self._shutdown(up)
        if self._up_eof and not self._to_client and not self._client_shut:
            self._client_shut = True
            self._shutdown(self.sock)
        if self._client_shut and (self._client_eof or self._up_shut):
            self.close()  # both halves ended (or the client's end is pending: FINISH_S)
            return
        if (self._client_shut or self._up_shut) and self._finish is None:
            self._finish = self.loop.call_later(FINISH_S, self.close)
        client = 0
        if not self._client_eof and len(self._to_up) < HIGH_WATER:
            client |= _READ
        if self._to_client:
            client |= _WRITE
        self._want(self.sock, client, self._on_client)
        if up is not None:
            events = 0
            if self._connecting or self._to_up:
                events |= _WRITE
            if not self._connecting and not self._up_eof and len(self._to_client) < HIGH_WATER:
                events |= _READ
            self._want(up, events, self._on_up)

    def _want(self, sock: socket.socket, events: int,
              callback: Callable[[int], Any]) -> None:
        now = self._interest.get(sock, 0)
        if events == now:
            return
        if not events:
            self.loop.unregister(sock)
        elif not now:
            self.loop.register(sock, events, callback)
        else:
            self.loop.modify(sock, events, callback)
        self._interest[sock] = events

    @staticmethod
    def _shutdown(sock: socket.socket) -> None:
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_WR)

    def _gone(self, exc: OSError) -> None:
        if not isinstance(exc, _GONE):
            log.debug("%s: %s", self.name, exc)
        self.close()

    def close(self) -> None:
        """Close both sockets (the loop's thread); safe twice."""
        if not self.alive:
            return
        self.alive = False
        self.partial_since = None
        if self._finish is not None:
            self._finish.cancel()
        for sock in (self.sock, self.up):
            if sock is None:
                continue
            if self._interest.pop(sock, 0):
                self.loop.unregister(sock)
            with contextlib.suppress(OSError):
                sock.close()
        relay = self.relay
        relay.connections.discard(self)
        if self.served and not relay.closing:
            relay.left_log.event(f"{self.peer} after {time.monotonic() - self.since:.1f} s")
