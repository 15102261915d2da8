"""Byte-stream peers of a backend that plays the flight side to ground tools (UAVTalk, F´):
one endpoint syntax and one set of links on one :class:`~gateway.io.ioloop.IoLoop`.

==========================  ==============================================================
``tcpin:[HOST:]PORT``       a TCP server (the ground tool connects as a client); every
                            accepted client is a link of its own, with its own engine
``tcp:[HOST:]PORT``         a TCP client, reconnected with backoff
``serial:DEVICE[,BAUD]``    a serial port or radio; also a bare ``/dev/…`` / ``COMn`` or a
                            pyserial URL (``socket://…``, ``loop://``)
==========================  ==============================================================

The grammar (IPv6 in brackets, the error texts) is :mod:`gateway.io.endpoints`.

A link is the backend's own object (its engine's protocol: ``feed(data)`` returns events,
optionally ``flush()``; ``on_link(up)`` is called when a stream's port goes up or down) with an
``engine`` attribute that :class:`LinkSet` sets.  Every engine shares the set's loop (one
thread); a client that leaves is closed and handed to ``on_closed`` so the backend can keep
its counters.  Every ``tcpin`` listener is a :class:`~gateway.io.server.PortServer` held to
the backend's :class:`~gateway.io.server.ClientLimits` (``max_clients``,
``client_timeout_s``): :meth:`LinkSet.server_stats` counts its refusals and cuts.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, Generic, Protocol, TypeVar

from gateway.io.burstlog import BurstLog
from gateway.io.endpoints import STREAM_KINDS, Endpoint, parse_endpoint
from gateway.io.ioloop import IoLoop
from gateway.io.port import PortEngine
from gateway.io.server import ClientLimits, PortServer, server_stats
from gateway.io.transport import (
    SocketPort,
    open_serial_nonblocking,
    open_tcp_client,
    open_tcp_listener,
)

log = logging.getLogger(__name__)

CLOSE_TIMEOUT_S = 0.5


def parse_stream_endpoint(text: str, *, default_baud: int) -> Endpoint:
    """One ``tcpin:``/``tcp:``/serial endpoint; raises ``EndpointError``."""
    return parse_endpoint(text, STREAM_KINDS, default_baud=default_baud)



class StreamLink(Protocol):
    name: str
    engine: PortEngine | None

    def feed(self, data: bytes, /) -> Any: ...


L = TypeVar("L", bound=StreamLink)


class LinkSet(Generic[L]):
    """The links of ``specs``: listeners bound by :meth:`bind` (so a busy port refuses the
    start), everything served from :meth:`start` on ``loop`` (already running)."""

    def __init__(self, name: str, specs: list[Endpoint], *, loop: IoLoop,
                 new_link: Callable[[str, Endpoint], L], queue_depth: int,
                 on_closed: Callable[[L], Any] | None = None,
                 label: str = "client", limits: ClientLimits | None = None) -> None:
        self.name = name
        self.specs = specs
        self.loop = loop
        self.new_link = new_link
        self.queue_depth = queue_depth
        self.on_closed = on_closed
        self.label = label
        self.limits = limits or ClientLimits(queue_depth=queue_depth)
        self.links: list[L] = []  # mutated on the loop thread only; read anywhere as a copy
        self.servers: list[tuple[Endpoint, PortServer]] = []
        self.addresses: dict[str, Any] = {}  # tcpin endpoint text → bound (host, port)
        self._listeners: list[tuple[Endpoint, Any]] = []
        self._running = False
        self._bursts: dict[str, BurstLog] = {}

    def bind(self) -> None:
        """Bind every ``tcpin`` listener now; raises OSError (and binds none) on failure."""
        try:
            for spec in self.specs:
                if spec.kind == "tcpin":
                    self._listeners.append((spec, open_tcp_listener(spec.host, spec.port)))
        except OSError:
            for _, sock in self._listeners:
                sock.close()
            self._listeners.clear()
            raise
        for spec, sock in self._listeners:
            self.addresses[spec.text] = sock.getsockname()[:2]

    @property
    def running(self) -> bool:
        """Serving: between :meth:`start` (or :meth:`open`) and :meth:`close`."""
        return self._running

    def open(self, refusal: type[Exception] = OSError,
             on_loop: Callable[[], Any] | None = None) -> None:
        """A backend's start: :meth:`bind` (a listener that cannot be bound raises
        ``refusal`` naming the set, with nothing started), start the loop, call ``on_loop``
        (e.g. open a hand-over onto it), then :meth:`start`."""
        try:
            self.bind()
        except OSError as exc:
            raise refusal(f"{self.name}: {exc}") from exc
        self.loop.start()
        if on_loop is not None:
            on_loop()
        self.start()

    def shut(self) -> None:
        """A backend's close, after :meth:`open`: :meth:`close`, then stop and close the
        loop; a second call does nothing."""
        if not self._running:
            return
        self.close()
        if self.loop.stop(1.0):
            self.loop.close()

    def start(self) -> None:
        self._running = True
        for spec, sock in self._listeners:
            self._serve(spec, sock)
        self._listeners.clear()
        for spec in self.specs:
            if spec.kind != "tcpin":
                self._stream(spec)

    def address(self, endpoint: str | None = None) -> Any:
        """The bound (host, port) of a tcpin endpoint (the first when None)."""
        if endpoint is None:
            return next(iter(self.addresses.values()), None)
        return self.addresses.get(endpoint)

    def _serve(self, spec: Endpoint, first: Any) -> None:
        pending = [first]
        address = self.addresses[spec.text]

        def opener() -> Any:  # bound again on the same port after a failure
            return pending.pop() if pending else open_tcp_listener(spec.host, address[1])

        server = PortServer(opener, lambda sock, addr: self._on_client(spec, sock, addr),
                            loop=self.loop, name=f"{self.name} {spec.text}",
                            limits=self.limits)
        self.servers.append((spec, server))
        server.start()

    def server_stats(self) -> dict[str, int]:
        """The listeners' refusals and cuts (see :func:`gateway.io.server.server_stats`)."""
        return server_stats(server for _, server in self.servers)

    def _on_client(self, spec: Endpoint, sock: Any,
                   addr: Any) -> PortEngine | None:  # loop thread
        name = f"{spec.text}<{addr[0]}:{addr[1]}>"
        if not self._running:
            sock.close()
            return None
        link = self.new_link(name, spec)

        def on_link(up: bool) -> None:
            if not up:
                self.loop.call_soon(lambda: self._client_closed(link))

        def no_reopen() -> Any:
            raise OSError("an accepted client is not reopened")

        link.engine = PortEngine(no_reopen, name=name, protocol=link, loop=self.loop,
                                 queue_depth=self.queue_depth, reopen=False, on_link=on_link)
        self.links.append(link)
        link.engine.start_with(SocketPort(sock, name))
        self._burst("joins", f"{self.label} connected").event(f"{addr[0]}:{addr[1]}")
        return link.engine

    def _client_closed(self, link: L) -> None:
        if link not in self.links:
            return
        self.links.remove(link)
        if link.engine is not None:
            link.engine.close(CLOSE_TIMEOUT_S)
        if self.on_closed is not None:
            self.on_closed(link)
        self._burst("leaves", f"{self.label} left").event(link.name)

    def _burst(self, kind: str, text: str) -> BurstLog:
        """Clients coming and going, logged once per burst (a peer can connect in a loop)."""
        burst = self._bursts.get(kind)
        if burst is None:
            burst = self._bursts[kind] = BurstLog(self.loop, f"{self.name}: {text}",
                                                  level=logging.INFO, logger=log)
        return burst

    def _stream(self, spec: Endpoint) -> None:
        link = self.new_link(spec.text, spec)

        def opener() -> Any:
            if spec.kind == "tcp":
                return open_tcp_client(spec.host, spec.port)
            return open_serial_nonblocking(spec.device, spec.baudrate)

        on_link = getattr(link, "on_link", None)
        link.engine = PortEngine(opener, name=spec.text, protocol=link, loop=self.loop,
                                 queue_depth=self.queue_depth, on_link=on_link)
        self.links.append(link)
        link.engine.start()

    def close(self, timeout: float = 2.0) -> None:
        """Stop listening and close every link (from any thread but the loop's)."""
        if not self._running:
            for _, sock in self._listeners:
                sock.close()
            self._listeners.clear()
            return
        self._running = False
        done = threading.Event()

        def stop() -> None:
            for _, server in self.servers:
                server.close()
            for link in list(self.links):
                if link.engine is not None:
                    link.engine.close(CLOSE_TIMEOUT_S)
            done.set()

        self.loop.call_soon(stop)
        done.wait(timeout)
