"""Zenoh backend: every update the gateway handles, published on Zenoh.

The dispatcher hands each message over to the backend's :class:`~gateway.io.ioloop.IoLoop`
(:class:`~gateway.handover.Handover`, bounded by ``queue_s`` seconds of the update rate,
at least ``queue_depth`` updates; never blocking).  On that
loop the backend opens the session (retrying with backoff while, e.g., a client's router is
down), and its handler encodes and puts each message.  Where messages can be lost, and how
each loss is counted:

* the hand-over is full → ``dropped_queue_full`` (QUEUE_FULL);
* no session yet (router down at start-up) → ``dropped_not_ready`` (NOT_READY);
* closing: what could not be published within the close's time bound → ``dropped_closed``;
* ``congestion_control = "drop"`` (default): Zenoh drops inside its own transmit queue when
  the network cannot keep up; ``put`` does not report it, so the backend cannot count it.
  Subscribers can: every publication carries ``seq`` (per key) in its attachment, and
  ``aurora-gateway listen`` reports the gaps;
* ``congestion_control = "block"``: Zenoh never drops; the loop waits in ``put`` instead, the
  hand-over fills, and every loss is a counted ``dropped_queue_full``;
* the session has no connection at all (a client whose router is down, a peer nobody
  listens to): the put reaches no one outside this process; counted as ``unrouted`` (not a
  drop: with nobody listening there is nothing to lose).

Keys are per vehicle: each message is published under ``<prefix>/<msg.vehicle>/…``, its
vehicle's :class:`~backends.zenoh.keys.KeyLayout` built once and found by a dict lookup.  A
message without a vehicle (a backend's own: RC commands from CRSF; a link event) goes under
the vehicle of the source its ``origin`` (a link event: its ``source``) names, else under the
first configured source's (the vehicle a single-vehicle link serves by default); with no
source configured it is not published (``skipped_no_vehicle``).  At most
:data:`~backends.zenoh.keys.MAX_VEHICLES` vehicles: the messages of any further one are
counted (``dropped_vehicle_limit``), not published.

For each vehicle the session declares a liveliness token ``<prefix>/<vehicle>/gateway/<id>``:
at start for the configured sources' vehicles (the ``gateway.vehicles`` service), later for
each vehicle when it is first published; all undeclared at close.  One queryable on
``<prefix>/*/**`` answers a ``get`` with the latest value of each key of every vehicle it
matches, so late joiners need not wait for the next update (one, not one per vehicle: Zenoh
runs each Python callback on a thread of its own).  The gateway's own counters go on
``<prefix>/@gateways/<id>/stats`` (not a vehicle's: a verbatim chunk no wildcard matches).

ROS 2 over rmw_zenoh: when the ``ros2`` backend runs too (it asks with
:func:`backends.ros2.rmw_zenoh.request`), this backend's loop also puts each message's ROS
samples on this session as rmw_zenoh does (:class:`backends.ros2.rmw_zenoh.RmwZenoh`: its keys,
liveliness tokens and attachments), so a ROS 2 node on rmw_zenoh hears the rocket through this
backend's endpoints; its counters are this backend's ``ros2_…`` stats.

Loop prevention reads the message, not a registry: a message whose ``via`` says it came in
over Zenoh is never published again (``skipped_from_zenoh``); the attachment names this
gateway, and the id goes into the gateway's context so its own Zenoh sources ignore it.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from backends.zenoh import encoding as enc
from backends.zenoh.keys import (
    MAX_VEHICLES,
    SOURCES_SERVICE,
    VIA_ZENOH,
    KeyLayout,
    check_chunk,
    check_prefix,
    make_attachment,
    stats_key,
)
from backends.zenoh.options import ZenohOptions
from backends.zenoh.session import SessionOptions, zerror_text
from gateway.backend import Backend, GatewayContext, Routes
from gateway.config import ConfigError
from gateway.handover import Handover
from gateway.io.backoff import Backoff
from gateway.io.burstlog import BurstLog
from gateway.io.ioloop import IoLoop, Timer
from gateway.model import MESSAGE_TYPES, LinkEvent, RawFrame, SmUpdate, Status, kind
from gateway.vehicles import SERVICE as VEHICLES_SERVICE

log = logging.getLogger(__name__)

START_WAIT_S = 1.0  # init() waits this long for the session so the first updates are not lost
CLOSE_TIMEOUT_S = 0.5


class _Vehicle(KeyLayout):
    """One vehicle published: its keys, and the latest value of each (what its queryable
    answers)."""

    __slots__ = ("latest",)

    def __init__(self, prefix: str, vehicle: str) -> None:
        super().__init__(prefix, vehicle)
        self.latest: dict[str, tuple[bytes, Any, bytes]] = {}


class _Key:
    """One published key: its publisher, encoding, sequence counter and the attachment's
    head (``gw=<id>;seq=``: each put only appends its number)."""

    __slots__ = ("attachment_head", "encoding", "key", "publisher", "seq")

    def __init__(self, key: str, publisher: Any, encoding: Any = None,
                 gateway_id: str = "") -> None:
        self.key = key
        self.publisher = publisher
        self.encoding = encoding
        self.seq = 0
        self.attachment_head = make_attachment(gateway_id, 0)[:-1]


class ZenohBackend(Backend):
    """Publishes every message on Zenoh; see the module docstring and README.md."""

    NAME = "zenoh"
    OPTIONS = ZenohOptions
    EMBEDDED_DEFAULT = ZenohOptions.EMBEDDED_DEFAULT

    def __init__(self, options: ZenohOptions | None = None, name: str | None = None) -> None:
        super().__init__(name)
        options = options or ZenohOptions()
        self.prefix = check_prefix(options.prefix)
        #: every vehicle published so far: its keys and latest values (at most MAX_VEHICLES)
        self.vehicles: dict[str, _Vehicle] = {}
        #: a configured source's vehicle, by the source's name; and the first source's
        self._source_vehicle: dict[str, str] = {}
        self._first_vehicle = ""
        self._own_id = options.gateway_id
        self.gateway_id = self._own_id or self.context.gateway_id
        self.session_options = SessionOptions.from_options(options)
        self.options = options  # validated; read where it is used
        self.stats_published = 0

        self._stop = threading.Event()
        self._ready = threading.Event()
        self.handover = Handover(self.name, options.queue_depth, ready=self._ready.is_set,
                                 skip=self._loops, span_s=options.queue_s)
        self._loop: IoLoop | None = None
        self._transport_logs: dict[str, BurstLog] = {}  # (the loop's thread)
        self._timers: list[Timer] = []
        self._session: Any = None
        self._keys: dict[str, _Key] = {}
        self._encodings: dict[str, Any] = {}
        self._entities: list[Any] = []
        #: a vehicle's liveliness token, on the current session
        self._presence: dict[str, list[Any]] = {}
        #: the vehicles whose presence is declared on the current session: the hot path's
        #: one lookup per message
        self._declared: dict[str, _Vehicle] = {}
        self._backoff = Backoff(0.1, max(0.1, self.session_options.reconnect_max_s))
        # counters
        self.sent = 0
        self.puts = 0
        self.put_errors = 0
        self.publish_errors = 0
        self.skipped_from_zenoh = 0
        self.queries = 0
        self.session_opens = 0
        self.open_failures = 0
        self.transports = 0
        self.unrouted = 0
        self.skipped_no_vehicle = 0
        self.dropped_vehicle_limit = 0
        self.bad_vehicle_names = 0
        #: the rmw_zenoh topics (when the ros2 backend asked for them), on this loop
        self._ros: Any = None

    # -- configuration -----------------------------------------------------------------------

    # -- life cycle ------------------------------------------------------------------------------

    def attach(self, context: GatewayContext) -> None:
        """Publish under the gateway's id unless ``gateway_id`` was configured."""
        super().attach(context)
        if not self._own_id:
            self.gateway_id = context.gateway_id

    def init(self) -> None:
        """Start the backend's loop (it opens the session); wait briefly for the session."""
        if self._loop is not None:
            return
        self._learn_sources()
        from backends.ros2.rmw_zenoh import bridge_for
        self._ros = bridge_for(self.context, self.name)
        self.context.own_ids.add(self.gateway_id)  # this gateway's Zenoh sources skip it
        self._stop = threading.Event()
        self._loop = loop = IoLoop(f"zenoh-{self.name}")
        loop.start()
        self.handover.open(loop)
        loop.call_soon(self._connect)
        if self.options.stats_interval_s:
            self._timers.append(loop.call_every(self.options.stats_interval_s,
                                                self._publish_gateway_stats))
        self._ready.wait(START_WAIT_S)

    def _learn_sources(self) -> None:
        """The configured sources' vehicles (the ``gateway.vehicles`` service), but for the
        Zenoh sources' (another gateway's vehicles, never published here) and those of sources
        yielding one vehicle per system (a MAVLink source's ``drone-1``, declared when first
        heard; the stem ``drone`` is no vehicle): where a message
        without a vehicle goes, and whose presence is declared at start."""
        services = self.context.services
        relayed = services.get(SOURCES_SERVICE) or set()
        configured = [sv for sv in services.get(VEHICLES_SERVICE) or []
                      if sv.vehicle and sv.source not in relayed and not sv.systems]
        self._source_vehicle = {sv.source: sv.vehicle for sv in configured}
        self._first_vehicle = configured[0].vehicle if configured else ""

    def wait_ready(self, timeout: float) -> bool:
        """Block until the session is open (for tools and tests)."""
        return self._ready.wait(timeout)

    @property
    def ready(self) -> bool:
        return self._ready.is_set()

    def close(self, timeout: float = CLOSE_TIMEOUT_S) -> None:
        """Publish what is queued (within ``timeout``), then close the session; safe twice."""
        loop, self._loop = self._loop, None
        if loop is None:
            return
        self.handover.close(timeout)  # what it could not publish in time: dropped_closed
        self._stop.set()
        for timer in self._timers:
            timer.cancel()
        self._timers = []
        if loop.stop(timeout):
            loop.close()
        else:
            log.warning("zenoh %s: its loop still busy after %.1f s; closing the session "
                        "under it", self.name, timeout)
        self._close_session()
        self.context.own_ids.discard(self.gateway_id)

    def _close_session(self) -> None:
        self._ready.clear()
        session, self._session = self._session, None
        if session is None:
            return
        if self._ros is not None:
            self._ros.undeclare()
        entities = [e for ents in self._presence.values() for e in ents] + self._entities
        for ent in reversed(entities):
            try:
                ent.undeclare()
            except Exception:
                log.debug("zenoh %s: undeclare failed", self.name, exc_info=True)
        self._entities = []
        self._presence = {}
        self._declared = {}
        self._keys = {}
        try:
            session.close()
        except Exception:
            log.debug("zenoh %s: session close failed", self.name, exc_info=True)

    # -- handlers (on the backend's loop, handed over by the dispatcher) ------------------------

    def routes(self) -> Routes:
        routes = (Routes(handover=self.handover).on(RawFrame, self.send_raw)
                  .on(SmUpdate, self.send_framed).on(Status, self.send_framed))
        for cls in MESSAGE_TYPES:  # every other message of the model: its document
            if cls not in (RawFrame, SmUpdate, Status):
                routes.on(cls, self.publish)
        return routes

    def _loops(self, msg: Any) -> bool:
        """It came in over Zenoh: publishing it would loop (counted; the hand-over's ``skip``,
        in the dispatcher's thread)."""
        if msg.via.startswith(VIA_ZENOH):
            self.skipped_from_zenoh += 1
            return True
        return False

    def publish(self, msg: Any) -> None:
        """A message of the model: its document on its kind's key."""
        self._publish(msg, doc=True, raw=False)

    def send_framed(self, msg: SmUpdate | Status) -> None:
        """An SM update or STATUS: its document, and its wire frame on raw/<type> (if raw)."""
        self._publish(msg, doc=True, raw=self.options.raw)

    def send_raw(self, msg: RawFrame) -> None:
        """A frame nobody decodes: published on raw/<type> only (nothing if raw is off)."""
        if self.options.raw:
            self._publish(msg, doc=False, raw=True)

    @property
    def accepted(self) -> int:
        """Messages handed over so far (for tools and tests; see :attr:`processed`)."""
        return self.handover.posted

    @property
    def processed(self) -> int:
        """Messages handled so far (published, skipped or failed)."""
        return self.handover.handled

    # -- the loop ------------------------------------------------------------------------------

    def _connect(self) -> None:
        """Open the session (blocking this backend's loop only); on failure, again later."""
        loop = self._loop
        if self._session is not None or loop is None or self._stop.is_set():
            return
        if not self._open(self._stop):
            loop.call_later(self._backoff.next(), self._connect)

    def _publish_gateway_stats(self) -> None:
        """This gateway's counters on ``<prefix>/@gateways/<id>/stats`` every
        ``stats_interval_s`` (the loop's thread; the counters are read as the status line
        reads them)."""
        if self._session is None:
            return
        stats = self.context.services.get("gateway.stats")
        if stats is None:
            return
        try:
            payload = enc.stats_document(stats())
        except Exception:
            self.publish_errors += 1
            return
        if self._put(stats_key(self.prefix, self.gateway_id), payload, enc.JSON, None):
            self.stats_published += 1

    def _open(self, stop: threading.Event) -> bool:
        import zenoh

        try:
            session = self.session_options.open()
        except (zenoh.ZError, ConfigError) as exc:
            self.open_failures += 1
            if self.open_failures == 1 or self.session_opens:
                log.warning("zenoh %s: cannot open the session (%s): %s; retrying",
                            self.name, self.session_options.describe(), zerror_text(exc))
            return False
        if stop.is_set():  # close() gave up waiting while the session was opening
            session.close()
            return False
        try:
            self._declare(session)
        except Exception as exc:
            self.open_failures += 1
            log.warning("zenoh %s: declaring on the session failed: %s; retrying", self.name,
                        zerror_text(exc))
            self._entities = []
            session.close()
            return False
        self._session = session
        self._keys = {}
        self.session_opens += 1
        self._backoff.reset()
        self._ready.set()
        log.info("zenoh %s: publishing %s/<vehicle>/** as gateway %s (%s)", self.name,
                 self.prefix, self.gateway_id, self.session_options.describe())
        if self._ros is not None:
            log.info("zenoh %s: and the ROS 2 topics as rmw_zenoh carries them: domain %d, "
                     "node /%s", self.name, self._ros.domain_id, self._ros.node_name)
        return True

    def _declare(self, session: Any) -> None:
        import zenoh

        self._entities = []
        block = self.options.congestion_control == "block"
        self._congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._priority = getattr(zenoh.Priority, self.options.priority.upper())
        self._encodings = {s: zenoh.Encoding(s) for s in
                           (enc.JSON, enc.SM_UPDATE_PACKED, enc.STATUS_PACKED, enc.WIRE)}
        try:
            self._entities.append(session.info.declare_transport_events_listener(
                self._on_transport, history=True))
        except Exception:  # an observer only: never a reason not to publish
            log.debug("zenoh %s: no transport events", self.name, exc_info=True)
        if self.options.queryable:
            self._entities.append(session.declare_queryable(f"{self.prefix}/*/**",
                                                            self._on_query))
        self._presence = {}
        self._declared = {}
        for vehicle in [self._first_vehicle, *self._source_vehicle.values(), *self.vehicles]:
            layout = self._layout(vehicle) if vehicle else None
            if layout is not None:
                self._declare_presence(session, layout)
        if self._ros is not None:
            self._ros.declare(session)

    def _declare_presence(self, session: Any, layout: _Vehicle) -> None:
        """``layout``'s vehicle's liveliness token (once per session)."""
        if layout.vehicle in self._presence:
            return
        ents = self._presence[layout.vehicle] = []
        self._declared[layout.vehicle] = layout
        if self.options.liveliness:
            ents.append(session.liveliness().declare_token(layout.token(self.gateway_id)))

    def _layout(self, vehicle: str) -> _Vehicle | None:
        """The keys of ``vehicle``, made on its first message (None: not a key chunk, or
        beyond MAX_VEHICLES; counted)."""
        layout = self.vehicles.get(vehicle)
        if layout is not None:
            return layout
        if len(self.vehicles) >= MAX_VEHICLES:
            self.dropped_vehicle_limit += 1
            if self.dropped_vehicle_limit == 1:
                log.warning("zenoh %s: more than %d vehicles; %r and any further one not "
                            "published (dropped_vehicle_limit)", self.name, MAX_VEHICLES,
                            vehicle)
            return None
        try:
            layout = _Vehicle(self.prefix, check_chunk(vehicle, "vehicle"))
        except ValueError as exc:
            self.bad_vehicle_names += 1
            if self.bad_vehicle_names == 1:
                log.warning("zenoh %s: not published: %s", self.name, exc)
            return None
        self.vehicles[vehicle] = layout
        return layout

    def _vehicle_layout(self, msg: Any) -> _Vehicle | None:
        """The keys of ``msg``'s vehicle (see the module docstring for a message without
        one); declares its presence on its first message."""
        vehicle = msg.vehicle
        if not vehicle:
            source = msg.source if type(msg) is LinkEvent else msg.origin
            vehicle = self._source_vehicle.get(source) or self._first_vehicle
            if not vehicle:
                self.skipped_no_vehicle += 1
                return None
        layout = self._declared.get(vehicle)
        if layout is not None:
            return layout
        layout = self._layout(vehicle)
        if layout is not None and self._session is not None:
            try:
                self._declare_presence(self._session, layout)
            except Exception as exc:  # published all the same, without presence
                self._declared[vehicle] = layout
                log.warning("zenoh %s: cannot declare %s's presence: %s", self.name, vehicle,
                            zerror_text(exc))
        return layout

    def _key(self, key: str, encoding: str) -> _Key:
        k = self._keys.get(key)
        if k is None:
            pub = self._session.declare_publisher(
                key, encoding=self._encodings[encoding], congestion_control=self._congestion,
                priority=self._priority)
            self._entities.append(pub)
            k = self._keys[key] = _Key(key, pub, self._encodings[encoding], self.gateway_id)
        return k

    def _put(self, key: str, payload: bytes, encoding: str,
             latest: dict[str, tuple[bytes, Any, bytes]] | None) -> bool:
        """Put on ``key``; remember it in ``latest`` (a vehicle's, what its queryable
        answers)."""
        k = self._keys.get(key) or self._key(key, encoding)
        att = b"%b%d" % (k.attachment_head, k.seq)  # = make_attachment(gateway_id, seq)
        k.seq += 1
        try:
            k.publisher.put(payload, attachment=att)
        except Exception as exc:
            self.put_errors += 1
            if self.put_errors == 1:
                log.warning("zenoh %s: put on %s failed: %s", self.name, key, zerror_text(exc))
            return False
        self.puts += 1
        if not self.transports:
            self.unrouted += 1
        if latest is not None:
            latest[key] = (payload, k.encoding, att)
        return True

    def _publish(self, msg: Any, *, doc: bool, raw: bool) -> None:
        """Put ``msg``'s document and/or its wire frame; a message that cannot be encoded is
        skipped, counted (``publish_errors``)."""
        if self._ros is not None:
            self._ros.handle(msg)
        layout = self._declared.get(msg.vehicle)
        if layout is None:
            layout = self._vehicle_layout(msg)
            if layout is None:
                return
        try:
            ok = False
            if doc:
                payload, encoding = enc.encode(msg, self.options.encoding)
                ok = self._put(layout.kind(kind(msg)), payload, encoding, layout.latest)
            if raw:
                frame = enc.wire_frame(msg)
                ok = self._put(layout.raw(frame[2]), frame, enc.WIRE, layout.latest) or ok
        except Exception as exc:
            self.publish_errors += 1
            if self.publish_errors == 1:
                log.warning("zenoh %s: cannot publish %s: %s: %s", self.name,
                            type(msg).__name__, type(exc).__name__, exc)
            return
        if ok:
            self.sent += 1

    # -- zenoh callbacks (zenoh's threads) -------------------------------------------------------

    def _on_query(self, query: Any) -> None:
        """A ``get``: the latest values of the keys it names, of every vehicle it matches."""
        self.queries += 1
        with query:
            ke = query.key_expr
            for vehicle in list(self.vehicles.values()):
                if not ke.intersects(vehicle.everything):
                    continue
                for key, (payload, encoding, att) in vehicle.latest.copy().items():
                    if ke.intersects(key):
                        query.reply(key, payload, encoding=encoding, attachment=att)

    def _on_transport(self, event: Any) -> None:
        """Count connections; a router coming and going is news, a dashboard is not."""
        import zenoh

        t = event.transport
        router = t.whatami == zenoh.WhatAmI.ROUTER
        up = event.kind == zenoh.SampleKind.PUT
        if up:
            self.transports += 1
        else:
            self.transports = max(0, self.transports - 1)
        loop = self._loop
        if loop is None:
            return
        # logged on the loop, once per burst with a count: a remote that says it is a router
        # can come and go in a loop
        if router:
            kind, level = (("router up", logging.INFO) if up
                           else ("router lost", logging.WARNING))
            text = "connected to a router" if up else "lost a router (reconnecting)"
        else:
            kind, level = ("peer up", logging.DEBUG) if up else ("peer left", logging.DEBUG)
            text = "peer connected" if up else "peer left"
        detail = f"{t.whatami} {t.zid}"
        loop.call_soon(lambda: self._transport_log(kind, text, level).event(detail))

    def _transport_log(self, kind: str, text: str, level: int) -> BurstLog:
        burst = self._transport_logs.get(kind)
        loop = self._loop
        if burst is None or burst.loop is not loop:  # (a loop of a later start)
            assert loop is not None
            burst = self._transport_logs[kind] = BurstLog(loop, f"zenoh {self.name}: {text}",
                                                          level=level, logger=log)
        return burst

    # -- reporting ---------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        return {
            "sent": self.sent,
            "dropped": self.handover.dropped + self.put_errors + self.publish_errors,
            **self.handover.stats(),
            "errors": (self.put_errors + self.publish_errors + self.open_failures
                       + self.handover.handler_errors),
            "link": int(self._ready.is_set()),
            "put_errors": self.put_errors,
            "publish_errors": self.publish_errors,
            "puts": self.puts, "stats_published": self.stats_published,
            "unrouted": self.unrouted,
            "skipped_from_zenoh": self.skipped_from_zenoh,
            "vehicles": len(self.vehicles),
            "skipped_no_vehicle": self.skipped_no_vehicle,
            "dropped_vehicle_limit": self.dropped_vehicle_limit,
            "queries": self.queries,
            "connected": self.transports,
            "session_opens": self.session_opens,
            "open_failures": self.open_failures,
            **(self._ros.stats() if self._ros is not None else {}),
        }

    def latest(self) -> dict[str, bytes]:
        """The latest payload published on each key (what the queryables answer)."""
        return {k: v[0] for vehicle in list(self.vehicles.values())
                for k, v in vehicle.latest.copy().items()}

    def wait_idle(self, timeout: float) -> bool:
        """Wait until everything accepted so far is published (for tools and benchmarks)."""
        return self.handover.barrier(timeout)
