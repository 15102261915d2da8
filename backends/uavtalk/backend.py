"""The UAVTalk backend: the gateway plays a LibrePilot 16.09 flight controller to ground stations.

Endpoints (``endpoints``, ``--uavtalk``, repeatable):

==========================  ==============================================================
``tcpin:HOST:PORT``         a TCP server (the LibrePilot GCS connects as a client); every
                            accepted client has its own engine and :class:`FlightSession`
``tcp:HOST:PORT``           a TCP client, reconnected with backoff
``serial:DEVICE[,BAUD]``    a serial port or radio (default 57600 baud); also a bare
                            ``/dev/…`` / ``COMn`` or a pyserial URL (``socket://…``)
==========================  ==============================================================

Every port is a :class:`gateway.io.port.PortEngine` and all of them share one
:class:`gateway.io.ioloop.IoLoop` (one thread).  A link is its engine's protocol object: bytes go
through its :class:`~.codec.Decoder` into its session's ``receive``; its replies are written at
once, and a timer (``tick_s``) calls every session's ``tick(now)`` then writes its
``outgoing()`` with ``engine.submit`` — never blocking: a client that does not read fills its
own queue and loses packets (``dropped``), nobody else waits.  A stream link (``tcp:``,
serial) starts a fresh session each time its port comes up.

A TCP client is logged when it connects and leaves (once per burst); the GCS is logged as
connected when its handshake completes (GCSTelemetryStats HandshakeReq → FlightTelemetryStats
HandshakeAck → GCSTelemetryStats Connected) and as disconnected when that ends (its own
Disconnected, 8 s of silence, or its link gone), each once per burst with a count
(:class:`~gateway.io.burstlog.BurstLog`): a peer looping through handshakes costs a few lines.

One :class:`~.telemetry.ObjectStore` (the vehicle) serves every session; it is filled from
the gateway's messages by :class:`~.translate.Vehicle` on the loop's thread: the routes run on
the loop through the gateway's :class:`~gateway.handover.Handover` (bounded, ``inbox_depth``;
full: ``QUEUE_FULL``, counted), and the objects a batch of messages changed are stored once
after the batch.

The flight side plays one flight controller, so it serves one vehicle: the one named by
``vehicle`` in ``[backends.uavtalk]``, or else the first source's
(:class:`gateway.vehicles.VehicleSelector`); every handler first drops another vehicle's
message (counted as ``other_vehicles``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any, ClassVar

from gateway.backend import Backend, BackendError, GatewayContext, Outcome, Routes
from gateway.handover import Handover
from gateway.io.burstlog import BurstLog
from gateway.io.endpoints import Endpoint
from gateway.io.ioloop import IoLoop, Timer
from gateway.io.links import (
    LinkSet,
    parse_stream_endpoint,
)
from gateway.io.port import PortEngine
from gateway.io.server import ClientLimits
from gateway.model import Battery, Position, SmUpdate, Status
from gateway.vehicles import VehicleSelector

from .codec import Decoder, DecoderStats
from .objects import ObjectSet
from .options import DEFAULT_SERIAL_BAUD, UavtalkOptions
from .telemetry import FlightSession, ObjectStore
from .telemetry import Status as Handshake
from .translate import Vehicle

log = logging.getLogger(__name__)

#: Received packets handled between two writes of a link's replies (well under the session's
#: priority queue of 32).
FLUSH_EVERY = 16
_ACCEPTED = Outcome.ACCEPTED


def parse_endpoint(text: str) -> Endpoint:
    """Parse one endpoint (:mod:`gateway.io.endpoints`); raises its EndpointError."""
    return parse_stream_endpoint(text, default_baud=DEFAULT_SERIAL_BAUD)


class Link:
    """One UAVTalk peer: its engine's protocol object, its decoder and its session."""

    def __init__(self, name: str, backend: UavtalkBackend, spec: Any = None) -> None:
        self.name = name
        self.backend = backend
        self.engine: PortEngine | None = None
        self.decoder = Decoder(backend.objects.data_length)
        self.session = self._new_session()
        self.sent = 0
        self.dropped = 0
        self.sessions = 1
        self.old_drops = 0

    # -- the engine's protocol (loop thread) -----------------------------------------------

    def feed(self, data: bytes) -> tuple[()]:
        now = self.backend.clock()
        session = self.session
        for i, packet in enumerate(self.decoder.feed(data), 1):
            session.receive(packet, now)
            if i % FLUSH_EVERY == 0:  # a flood of requests: answers overflow the engine's
                self.flush_out(now)   # queue (counted), not the session's
        self.flush_out(now)
        return ()

    def flush(self) -> tuple[()]:
        """The stream broke: a packet it was in the middle of will not complete."""
        old = self.decoder
        self.decoder = Decoder(self.backend.objects.data_length)
        self.decoder.stats = old.stats
        old.stats.bytes_skipped += old.pending
        return ()

    def _new_session(self) -> FlightSession:
        session = self.backend.new_session()
        session.on_state = self._state_changed
        return session

    def _state_changed(self, old: Handshake, new: Handshake) -> None:
        """The handshake with this link's GCS completed, or the connection it made ended."""
        if new == Handshake.CONNECTED:
            self.backend.gcs_connected_log.event(
                f"{self.name} (handshake {self.session.stats.handshake_ms} ms)")
        elif old == Handshake.CONNECTED:
            self.backend.gcs_disconnected_log.event(self.name)

    def ended(self, why: str) -> None:
        """The link itself is gone: a GCS connected over it is disconnected."""
        if self.session.state == Handshake.CONNECTED:
            self.backend.gcs_disconnected_log.event(f"{self.name} ({why})")

    def on_link(self, up: bool) -> None:
        """A stream's port went up or down: the next peer starts a session of its own."""
        if not up:
            self.ended("link lost")
        if self.session.stats.rx_bytes:
            self.old_drops += self._session_drops()
            self.session = self._new_session()  # a new peer: a new handshake
            self.sessions += 1

    def _session_drops(self) -> int:
        st = self.session.stats
        return st.priority_drops + st.regular_drops

    @property
    def total_dropped(self) -> int:
        """Packets refused by the engine (queue full, port down) or by the session's queues."""
        return self.dropped + self.old_drops + self._session_drops()

    # -- the timer (loop thread) ----------------------------------------------------------------

    def flush_out(self, now: float) -> None:
        engine = self.engine
        session = self.session
        session.tick(now)
        for data in session.outgoing():
            if engine is None:
                self.dropped += 1
                continue
            outcome = engine.submit(data, rate_limited=False)
            if outcome is _ACCEPTED:
                self.sent += 1
            else:
                self.dropped += 1

    def updated(self, name: str, now: float) -> None:
        self.session.updated(name, now)

    def stats(self) -> dict[str, Any]:
        s = self.session
        st = s.stats
        d: dict[str, Any] = {
            "state": s.state.name.lower(), "handshake_ms": st.handshake_ms,
            "packets": self.decoder.stats.packets, "nacks": st.tx_nack,
            "sent": self.sent, "dropped": self.total_dropped, "sessions": self.sessions,
            "rx_garbage_bytes": self.decoder.stats.bytes_skipped,
            # its CRC failures: the backend's crc_failures is the table's one CRC counter
            "corrupt_packets": self.decoder.stats.bad_crc, "unknown_object": st.rx_unknown,
            "retries": st.retries, "failures": st.failures, "connects": st.connects,
            "disconnects": st.disconnects,
        }
        if self.engine is not None:
            d["link"] = int(self.engine.connected)
            d["queue_full"] = self.engine.stats.dropped_queue_full
        return d


def _decoder_errors(ds: DecoderStats) -> int:
    return ds.bad_crc + ds.bad_size + ds.bad_length


def _errors(link: Link) -> int:
    """Corrupt packets and read/write failures of one link."""
    engine = link.engine
    return _decoder_errors(link.decoder.stats) + (engine.stats.errors if engine else 0)


class UavtalkBackend(Backend):
    """Serves the rocket as a LibrePilot 16.09 flight controller (see the module docstring)."""

    NAME = "uavtalk"
    OPTIONS = UavtalkOptions
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None  # it listens on a port: opt in

    def __init__(self, options: UavtalkOptions, name: str | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(name)
        self.specs = [parse_endpoint(e) for e in options.endpoints]
        self.options = options  # validated; read where it is used
        self.clock = clock
        self.objects = ObjectSet.load()
        self.vehicle = Vehicle(self.objects, options.board_type)
        self.store = ObjectStore(self.vehicle.defaults())
        self.loop = IoLoop(self.name)
        self.linkset: LinkSet[Link] = LinkSet(
            self.name, self.specs, loop=self.loop, new_link=lambda n, spec: Link(n, self, spec),
            queue_depth=options.queue_depth, on_closed=self._retire, label="TCP client",
            limits=ClientLimits.of(options, options.queue_depth))
        self.handover = Handover(self.name, options.inbox_depth, after_batch=self._store_changes)
        # a GCS that completes the handshake (Disconnected → HandshakeReq → HandshakeAck →
        # Connected), and one that stops being connected: a peer can do either in a loop
        self.gcs_connected_log = BurstLog(self.loop, f"{self.name}: GCS connected",
                                          level=logging.INFO, logger=log)
        self.gcs_disconnected_log = BurstLog(self.loop, f"{self.name}: GCS disconnected",
                                             level=logging.INFO, logger=log)
        self._changed: dict[str, dict[str, Any]] = {}
        self._timer: Timer | None = None
        self._closed_totals = {"sent": 0, "dropped": 0, "errors": 0, "clients_closed": 0,
                              "garbage_bytes": 0, "crc_failures": 0}
        self.messages = 0
        #: the vehicle this flight controller is
        self.selector = VehicleSelector(options.vehicle)
        self.other_vehicles = 0

    # -- sessions --------------------------------------------------------------------------------

    def new_session(self) -> FlightSession:
        return FlightSession(self.objects, self.store, board_type=self.options.board_type)

    # -- life cycle ------------------------------------------------------------------------------

    @property
    def links(self) -> list[Link]:
        """Every link now (the loop thread mutates the list)."""
        return self.linkset.links

    def attach(self, context: GatewayContext) -> None:
        """Learn which vehicle is served by default (the first source's)."""
        super().attach(context)
        self.selector.attach(context, f"backends.{self.name}")

    def init(self) -> None:
        self.linkset.open(BackendError, on_loop=lambda: self.handover.open(self.loop))
        self._timer = self.loop.call_every(self.options.tick_s, self._tick)

    def _retire(self, link: Link) -> None:
        link.ended("connection closed")
        t = self._closed_totals
        t["sent"] += link.sent
        t["dropped"] += link.total_dropped
        t["errors"] += _errors(link)
        t["garbage_bytes"] += link.decoder.stats.bytes_skipped
        t["crc_failures"] += link.decoder.stats.bad_crc
        t["clients_closed"] += 1

    def close(self) -> None:
        if not self.linkset.running:
            return
        self.handover.close()
        if self._timer is not None:
            self._timer.cancel()
        self.linkset.shut()

    # -- the loop's work -------------------------------------------------------------------------

    def _tick(self) -> None:
        now = self.clock()
        for link in self.links:
            link.flush_out(now)

    def _store_changes(self) -> None:
        """After a batch of messages: the objects they changed, stored once each."""
        changed, self._changed = self._changed, {}
        now = self.clock()
        for name, values in changed.items():
            if self.store.get(name) == values:
                continue  # an on-change object goes out when it changes, not per message
            self.store.set(name, values)
            for link in self.links:
                link.updated(name, now)

    # -- routes (handlers on the loop, handed over by the dispatcher) ----------------------------

    def routes(self) -> Routes:
        return (Routes(handover=self.handover).on(SmUpdate, self.send_sm_update)
                .on(Status, self.send_status).on(Position, self.send_position)
                .on(Battery, self.send_battery))

    def send_sm_update(self, msg: SmUpdate) -> None:
        if not self.selector.accepts(msg):
            self.other_vehicles += 1
            return
        self.messages += 1
        self._changed.update(self.vehicle.sm_update(msg))

    def send_status(self, msg: Status) -> None:
        if not self.selector.accepts(msg):
            self.other_vehicles += 1
            return
        self.messages += 1
        self._changed.update(self.vehicle.status(msg))

    def send_position(self, msg: Position) -> None:
        if not self.selector.accepts(msg):
            self.other_vehicles += 1
            return
        self.messages += 1
        self._changed.update(self.vehicle.position(msg))

    def send_battery(self, msg: Battery) -> None:
        if not self.selector.accepts(msg):
            self.other_vehicles += 1
            return
        self.messages += 1
        self._changed.update(self.vehicle.battery(msg))

    # -- stats -----------------------------------------------------------------------------------

    def address(self, endpoint: str | None = None) -> Any:
        """The bound (host, port) of a tcpin endpoint (the first when None)."""
        return self.linkset.address(endpoint)

    def stats(self) -> dict[str, Any]:
        t = self._closed_totals
        links = list(self.links)
        per = {link.name: link.stats() for link in links}
        sent = t["sent"] + sum(d["sent"] for d in per.values())
        h = self.handover
        dropped = t["dropped"] + sum(d["dropped"] for d in per.values()) + h.dropped
        errors = t["errors"] + sum(_errors(link) for link in links) + h.handler_errors
        garbage = t["garbage_bytes"] + sum(d["rx_garbage_bytes"] for d in per.values())
        connected = sum(1 for d in per.values() if d["state"] == "connected")
        return {"sent": sent, "dropped": dropped, "errors": errors,
                "link": int(connected > 0), "dropped_queue_full": h.dropped_queue_full,
                "dropped_not_ready": h.dropped_not_ready, "dropped_closed": h.dropped_closed,
                "dropped_queue": sum(d["dropped"] for d in per.values()) + t["dropped"],
                "messages": self.messages, "other_vehicles": self.other_vehicles,
                "clients": len(links), "connected": connected,
                "clients_closed": t["clients_closed"], "rx_garbage_bytes": garbage,
                "crc_failures": t["crc_failures"] + sum(d["corrupt_packets"]
                                                         for d in per.values()),
                "gcs_connects": self.gcs_connected_log.events,
                "gcs_disconnects": self.gcs_disconnected_log.events,
                **self.linkset.server_stats(), "links": per}
