"""MAVLink endpoints in the vocabulary MAVLink users know, each a :class:`~.router.Link`.

==========================  ==============================================================
``udpout:[HOST:]PORT``      send to HOST:PORT (QGroundControl listens on 14550); replies to
                            our socket are received and routed
``udpin:[HOST:]PORT``       listen on HOST:PORT (``udp:`` is the same, as in MAVProxy);
                            send to every peer that has sent to us (the last 16)
``tcpin:[HOST:]PORT``       TCP server; every client is a link of its own
``tcp:[HOST:]PORT``         TCP client, reconnecting with backoff
``serial:DEVICE[,BAUD]``    a serial port or telemetry radio (default 57600 baud); also a
                            bare ``/dev/…``/``COMn`` or a pyserial URL (``socket://…``,
                            ``rfc2217://…``, ``loop://``), with an optional ``,BAUD``
==========================  ==============================================================

The grammar (a HOST left out, IPv6 as ``[::1]:PORT``, the error texts) is
:mod:`gateway.io.endpoints`'s, the same for every backend and source.

Every port belongs to a :class:`gateway.io.port.PortEngine`, and all the engines of one router
share one :class:`gateway.io.ioloop.IoLoop` (one thread, passed to :meth:`Endpoint.start`).  A
link is its engine's protocol object: what the port yields goes straight into
:meth:`.Router.receive` (the router frames it); every :meth:`PortLink.send` is a non-blocking
``engine.submit`` (a full queue drops the frame, counted ``tx_dropped``; a port that is down
counts ``tx_not_up``).  Serial ports, TCP clients and UDP sockets that fail are reopened with
backoff; a ``tcpin`` listener is bound again; an accepted TCP client that leaves is removed
from the router.  Nothing here blocks the loop: sockets are non-blocking, and serial writes
never wait for room (the engine keeps the unwritten tail until the port can take it).

UDP sockets and TCP listeners are opened in :meth:`Endpoint.start`, so an address that cannot
be bound fails the start at once, with the endpoint's name in the message.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from backends.mavlink.frames import StreamFramer
from backends.mavlink.lane import lane_runner
from backends.mavlink.router import Link, Router
from gateway.io.burstlog import BurstLog
from gateway.io.endpoints import KINDS, usage
from gateway.io.endpoints import Endpoint as EndpointSpec
from gateway.io.endpoints import parse_endpoint as _parse
from gateway.io.ioloop import IoLoop
from gateway.io.port import PortEngine
from gateway.io.server import ClientLimits, PortServer, server_stats
from gateway.io.transport import (
    SocketPort,
    TransportError,
    UdpPort,
    open_serial_nonblocking,
    open_tcp_client,
    open_tcp_listener,
    open_udp,
)
from gateway.outcome import Outcome

log = logging.getLogger(__name__)
ACCEPTED = Outcome.ACCEPTED  # bound once: the router calls send() per frame
NOT_READY = Outcome.NOT_READY

DEFAULT_SERIAL_BAUD = 57600
DEFAULT_QUEUE_DEPTH = 256
START_WAIT_S = 2.0  # for the engine to take a socket opened in start()
CLOSE_TIMEOUT_S = 0.5
USAGE = usage(KINDS)


def parse_endpoint(text: str) -> EndpointSpec:
    """Parse a MAVLink endpoint (every kind of :mod:`gateway.io.endpoints`, ``udp:`` as
    ``udpin:``); raises its EndpointError naming the mistake and the accepted forms."""
    return _parse(text, KINDS, default_baud=DEFAULT_SERIAL_BAUD)


def _add_ints(total: dict[str, Any], more: dict[str, Any]) -> None:
    for k, v in more.items():
        if isinstance(v, int):
            total[k] = total.get(k, 0) + v


class Endpoint:
    """A configured endpoint: starts its link(s) on a router and reports their counters."""

    def __init__(self, spec: EndpointSpec, group: str = "") -> None:
        self.spec = spec
        self.name = spec.text
        self.group = group  # the side it is on: see Link.group

    def start(self, loop: IoLoop, router: Router) -> None:
        """Open (or start opening) on ``loop`` (running); raises OSError naming the endpoint
        when it cannot be opened at all."""
        raise NotImplementedError

    def close(self, timeout: float = CLOSE_TIMEOUT_S) -> None:
        """Write what is queued, close and leave the router; safe twice, any thread."""
        raise NotImplementedError

    def links(self) -> list[Link]:
        raise NotImplementedError

    def stats(self) -> dict[str, Any]:
        total: dict[str, Any] = {}
        for link in self.links():
            _add_ints(total, link.stats())
        return total


# -- a link on a port engine -------------------------------------------------------------------

class PortLink(Link):
    """A :class:`~.router.Link` whose port is a :class:`~gateway.io.port.PortEngine`'s; the link is
    the engine's protocol object (it hands what the port yields to the router)."""

    def __init__(self, name: str, group: str = "") -> None:
        super().__init__(name, group)
        self.engine: PortEngine | None = None

    def make_engine(self, opener: Callable[[], Any], loop: IoLoop, *, queue_depth: int,
                    reopen: bool = True, on_link: Callable[[bool], Any] | None = None,
                    ) -> PortEngine:
        self.engine = PortEngine(opener, name=self.name, protocol=self, loop=loop,
                                 queue_depth=queue_depth, reopen=reopen, on_link=on_link)
        return self.engine

    # -- the engine's protocol (the loop thread) -------------------------------------------

    def feed(self, data: bytes) -> tuple[()]:
        self.router.receive(self, data)  # type: ignore[union-attr]
        return ()

    def flush(self) -> tuple[()]:
        """The stream broke: a frame it was in the middle of will not complete."""
        framer, router = self.framer, self.router
        if framer is not None and router is not None:
            with router.lock:
                fresh = StreamFramer()
                fresh.stats = framer.stats
                fresh.stats.bytes_skipped += framer.pending()
                self.framer = fresh
        return ()

    # -- the router's side ---------------------------------------------------------------------

    @property
    def up(self) -> bool:
        engine = self.engine
        return engine is not None and engine.connected

    def send(self, data: bytes) -> bool:
        outcome = self.engine.submit(data, rate_limited=False)  # type: ignore[union-attr]
        c = self.counters
        if outcome is ACCEPTED:
            c.tx_frames += 1
            c.tx_bytes += len(data)
            return True
        if outcome is NOT_READY:
            c.tx_not_up += 1  # the port is down: frames are not kept for when it is back
        else:
            c.tx_dropped += 1  # the port does not keep up: its queue is full
        return False

    def close_engine(self, timeout: float) -> None:
        engine, router = self.engine, self.router
        if engine is not None:
            engine.close(timeout)
        if router is not None:
            router.remove_link(self)

    def stats(self) -> dict[str, Any]:
        d = Link.stats(self)
        engine = self.engine
        if engine is not None:
            es = engine.stats
            d.update(connects=es.connects, connect_failures=es.connect_failures,
                     disconnects=es.disconnects, write_errors=es.write_errors,
                     read_errors=es.read_errors, link=int(engine.connected))
            d["tx_errors"] += es.write_errors  # the OS refused a write (then: reopened)
        return d


# -- UDP ----------------------------------------------------------------------------------------

class UdpEndpoint(Endpoint, PortLink):
    """``udpout:`` (fixed destination) or ``udpin:`` (reply to the peers that talk to us)."""

    datagram = True

    def __init__(self, spec: EndpointSpec, queue_depth: int = DEFAULT_QUEUE_DEPTH,
                 group: str = "") -> None:
        Endpoint.__init__(self, spec, group)
        PortLink.__init__(self, spec.text, group)
        self.queue_depth = queue_depth
        self.listen = spec.kind == "udpin"
        self.port: UdpPort | None = None
        self._bound_port = spec.port  # udpin:HOST:0 binds the same port again on a reopen
        self._new_peers = 0
        #: while the router routes a batch of datagrams: what is sent to this link meanwhile,
        #: written in one go by :meth:`flush_batch` (None: each send is written at once)
        self._batch: list[bytes] | None = None
        # from sockets reopened since
        self._closed_counts = {"tx_errors": 0, "tx_refused": 0, "tx_dropped": 0}

    def _open(self) -> UdpPort:
        spec = self.spec
        try:
            port = open_udp(spec.host, self._bound_port, listen=self.listen)
        except TransportError as exc:
            raise TransportError(f"{spec.text}: {exc}") from None
        if self.listen:
            self._bound_port = port.address()[1]
        old, self.port = self.port, port
        if old is not None:
            self._closed_counts["tx_errors"] += old.send_errors
            self._closed_counts["tx_refused"] += old.send_refused
            self._closed_counts["tx_dropped"] += old.send_dropped
        self._new_peers = 0
        return port

    def start(self, loop: IoLoop, router: Router) -> None:
        first = self._open()  # raises (TransportError is an OSError) naming us
        engine = self.make_engine(self._open, loop, queue_depth=self.queue_depth)
        router.add_link(self)
        engine.start_with(first)  # open already: attached on the loop, no worker round trip
        engine.wait_connected(START_WAIT_S)

    @property
    def address(self) -> Any:
        """The local address (the bound port of ``udpin:HOST:0``)."""
        port = self.port
        return port.address() if port is not None else None

    @property
    def up(self) -> bool:
        engine, port = self.engine, self.port
        return (engine is not None and engine.connected and port is not None
                and (not self.listen or bool(port.peers)))

    def feed(self, data: bytes) -> tuple[()]:
        return self.feed_many([data])

    def feed_many(self, datagrams: list[bytes]) -> tuple[()]:
        """What the engine read in one go (one router lock round trip for the lot)."""
        port = self.port
        if port is not None and port.new_peers != self._new_peers:
            self._new_peers = port.new_peers
            log.info("%s: peer %s", self.name, port.last_peer)
        self.router.receive_many(self, datagrams)  # type: ignore[union-attr]
        return ()

    def lane_for(self, engine: Any, port: Any,
                 feed: Callable[[list[bytes], list[Any]], None]
                 ) -> Callable[[Callable[[], None]], bool] | None:
        """The compiled lane for this endpoint's port (see backends/mavlink/lane.py)."""
        return lane_runner(self, engine, port, feed)

    def start_batch(self) -> None:
        """Keep what is sent from now on for :meth:`flush_batch` (the router's batches)."""
        if self._batch is None and self.port is not None and self.port.mmsg is not None:
            self._batch = []

    def batch_sink(self) -> list[bytes] | None:
        """Where :meth:`send` puts a datagram during a batch (the router appends to it
        directly; :meth:`flush_batch` counts and writes it), or None: call :meth:`send`."""
        batch, port = self._batch, self.port
        if batch is None or port is None or (self.listen and not port.peers):
            return None
        return batch

    def flush_batch(self, first: int | None = None) -> None:
        """Write what was kept since :meth:`start_batch`: one ``sendmmsg`` per destination
        when the engine can write now, else each through its queue.  ``first``: a compiled
        lane's call for the whole batch, already made (see ``MmsgSocket.send``)."""
        batch, self._batch = self._batch, None
        if not batch:
            return
        engine = self.engine
        c = self.counters
        if engine.send_datagrams(batch, first):  # type: ignore[union-attr]
            c.tx_frames += len(batch)
            c.tx_bytes += sum(map(len, batch))
            return
        for data in batch:
            outcome = engine.submit(data, rate_limited=False)  # type: ignore[union-attr]
            if outcome is ACCEPTED:
                c.tx_frames += 1
                c.tx_bytes += len(data)
            else:
                if outcome is NOT_READY:
                    c.tx_not_up += 1
                else:
                    c.tx_dropped += 1

    def send(self, data: bytes) -> bool:
        c = self.counters
        if self.listen:
            port = self.port
            if port is None or not port.peers:
                c.tx_not_up += 1  # udpin: nobody has talked to us yet
                return False
        batch = self._batch
        if batch is not None:
            batch.append(data)  # counted by flush_batch
            return True
        engine = self.engine
        if engine.send_datagram(data):  # type: ignore[union-attr]  # the router's hot path
            c.tx_frames += 1
            c.tx_bytes += len(data)
            return True
        outcome = engine.submit(data, rate_limited=False)  # type: ignore[union-attr]
        if outcome is ACCEPTED:
            c.tx_frames += 1
            c.tx_bytes += len(data)
            return True
        if outcome is NOT_READY:
            c.tx_not_up += 1
        else:
            c.tx_dropped += 1
        return False

    def close(self, timeout: float = CLOSE_TIMEOUT_S) -> None:
        self.close_engine(timeout)

    def links(self) -> list[Link]:
        return [self]

    def stats(self) -> dict[str, Any]:
        d = PortLink.stats(self)
        port = self.port
        closed = self._closed_counts
        errors, refused, dropped = closed["tx_errors"], closed["tx_refused"], closed["tx_dropped"]
        if port is not None:
            errors += port.send_errors
            refused += port.send_refused
            dropped += port.send_dropped
        d["tx_errors"] += errors  # the OS refused a datagram (no route, a bad address …)
        d["tx_refused"] = refused  # "port unreachable": nobody listens there (yet): not an error
        d["tx_dropped"] += dropped  # the socket buffer was full
        if self.listen:
            d["peers"] = len(port.peers) if port is not None else 0
        return d


# -- TCP server -----------------------------------------------------------------------------------

def _not_reopened() -> Any:
    raise TransportError("an accepted client is not reopened")


class TcpServerEndpoint(Endpoint):
    """``tcpin:HOST:PORT``: accepts up to ``limits.max_clients`` clients (a
    :class:`~gateway.io.server.PortServer`), each routed as a link of its own (a
    :class:`PortLink` on an engine that is not reopened: a client that leaves is gone)."""

    def __init__(self, spec: EndpointSpec, queue_depth: int = DEFAULT_QUEUE_DEPTH,
                 group: str = "", limits: ClientLimits | None = None) -> None:
        super().__init__(spec, group)
        self.queue_depth = queue_depth
        self.limits = limits or ClientLimits(queue_depth=queue_depth)
        self.clients: list[PortLink] = []
        self.server: PortServer | None = None
        self.address: Any = None
        self._closed_stats: dict[str, int] = {}
        self._first: Any = None
        self._loop: IoLoop | None = None
        self._router: Router | None = None
        self._closing = False
        self._bursts: dict[str, BurstLog] = {}

    def _listen(self) -> Any:
        spec = self.spec
        port = self.address[1] if self.address is not None else spec.port
        try:
            sock = open_tcp_listener(spec.host, port)
        except TransportError as exc:
            raise TransportError(f"{spec.text}: {exc}") from None
        self.address = sock.getsockname()
        return sock

    def _opener(self) -> Any:
        first, self._first = self._first, None
        return first if first is not None else self._listen()

    def start(self, loop: IoLoop, router: Router) -> None:
        self._first = self._listen()  # raises (TransportError is an OSError) naming us
        self._loop, self._router = loop, router
        self.server = PortServer(self._opener, self._on_client, loop=loop, name=self.name,
                                 limits=self.limits)
        self.server.start()
        self.server.wait_bound(START_WAIT_S)

    @property
    def accepted(self) -> int:
        return self.server.accepted if self.server is not None else 0

    def _on_client(self, sock: Any, addr: Any) -> PortEngine | None:  # the loop thread
        loop, router = self._loop, self._router
        assert loop is not None and router is not None
        name = f"{self.name}<{addr[0]}:{addr[1]}>"
        if self._closing:
            sock.close()
            return None
        link = PortLink(name, self.group)

        def on_link(up: bool) -> None:
            if not up:
                loop.call_soon(lambda: self._client_closed(link))

        engine = link.make_engine(_not_reopened, loop, queue_depth=self.queue_depth,
                                  reopen=False, on_link=on_link)
        self.clients.append(link)
        router.add_link(link)
        engine.start_with(SocketPort(sock, name))  # up at once: routed frames are not refused
        self._burst("joins", "client connected").event(f"{addr[0]}:{addr[1]}")
        return engine

    def _client_closed(self, link: PortLink) -> None:
        if link not in self.clients:
            return
        self.clients.remove(link)
        link.close_engine(CLOSE_TIMEOUT_S)
        _add_ints(self._closed_stats, link.stats())
        self._burst("leaves", "client disconnected").event(link.name)

    def links(self) -> list[Link]:
        return list(self.clients)

    def _burst(self, kind: str, text: str) -> BurstLog:
        """Clients coming and going, logged once per burst (a peer can connect in a loop)."""
        burst = self._bursts.get(kind)
        if burst is None:
            assert self._loop is not None  # called on the loop, once started
            burst = self._bursts[kind] = BurstLog(self._loop, f"{self.name}: {text}",
                                                  level=logging.INFO, logger=log)
        return burst

    def stats(self) -> dict[str, Any]:
        d: dict[str, Any] = dict(self._closed_stats)
        _add_ints(d, super().stats())
        for k in ("link", "connects", "disconnects"):  # per client: not totals worth showing
            d.pop(k, None)
        d["clients"] = len(self.clients)
        d["accepted"] = self.accepted
        if self.server is not None:
            d.update(server_stats((self.server,)))
        return d

    def close(self, timeout: float = CLOSE_TIMEOUT_S) -> None:
        self._closing = True
        if self.server is not None:
            self.server.close()
        for link in list(self.clients):
            link.close_engine(timeout)


# -- byte streams: serial ports and TCP clients -------------------------------------------------

class StreamEndpoint(Endpoint, PortLink):
    """``serial:`` and ``tcp:``: one engine, reopening the port with backoff when it fails."""

    def __init__(self, spec: EndpointSpec, queue_depth: int = DEFAULT_QUEUE_DEPTH,
                 group: str = "") -> None:
        Endpoint.__init__(self, spec, group)
        PortLink.__init__(self, spec.text, group)
        self.queue_depth = queue_depth

    def _open(self) -> Any:
        spec = self.spec
        if spec.kind == "tcp":
            return open_tcp_client(spec.host, spec.port)
        return open_serial_nonblocking(spec.device, spec.baudrate)

    def start(self, loop: IoLoop, router: Router) -> None:
        engine = self.make_engine(self._open, loop, queue_depth=self.queue_depth)
        router.add_link(self)
        engine.start()

    def close(self, timeout: float = CLOSE_TIMEOUT_S) -> None:
        self.close_engine(timeout)

    def links(self) -> list[Link]:
        return [self]

    stats = PortLink.stats


def make_endpoint(spec: EndpointSpec, queue_depth: int = DEFAULT_QUEUE_DEPTH,
                  group: str = "", limits: ClientLimits | None = None) -> Endpoint:
    """The endpoint for ``spec``; its links are in ``group`` (see :attr:`.router.Link.group`)."""
    if spec.kind in ("udpout", "udpin"):
        return UdpEndpoint(spec, queue_depth, group)
    if spec.kind == "tcpin":
        return TcpServerEndpoint(spec, queue_depth, group, limits)
    return StreamEndpoint(spec, queue_depth, group)
