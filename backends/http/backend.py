"""The HTTP backend: a live status page and Prometheus metrics, read-only.

``run --http [HOST:]PORT`` (off by default; HOST defaults to loopback) serves, on the
gateway's port engine (one :class:`~gateway.io.ioloop.IoLoop` thread, an h11 parser per
connection: :mod:`backends.http.connection`; no thread per connection):

``/``
    a small page (no framework): one card per vehicle (state, armed, altitude, max altitude,
    link, age of its last update) and a table of every backend's counters, kept live by an
    ``EventSource``;
``/events``
    Server-Sent Events: one ``data: <JSON>`` event per ``event_interval_s`` with the latest
    values (the same JSON as ``/status.json``);
``/status.json``
    that JSON once: ``vehicles``, one entry per vehicle keyed by its name (see
    :meth:`HttpBackend.vehicle_entry`; in the order of :meth:`HttpBackend.ordered`), the
    gateway-wide fields beside it (uptime, links per source, messages in, every backend's
    and source's counters) and ``vehicle``, the entry of the first vehicle
    (:meth:`HttpBackend.primary`: a single-vehicle view, as before);
``/metrics``
    Prometheus text format, written by ``prometheus-client`` from a collector of our own:
    gauges for altitude, max altitude, state, armed and link and messages in per kind, each
    with a ``vehicle`` label; counters per backend (sent / dropped / errors, label
    ``backend``).

The state is kept per vehicle (``msg.vehicle``; a message without one is the first
configured source's vehicle), a dict lookup per message; at most :data:`MAX_VEHICLES`
vehicles are kept, the messages of any further one are counted (``vehicles_refused``), not
kept: a peer cannot grow the table by inventing names.

Only ``GET`` and ``HEAD``; any other method is 405, any other path 404.  Nothing changes
the gateway's state.

The hot path is O(1) and never blocks: a handler stores the message as the latest of its
kind and counts it; nothing is queued, so nothing is dropped there.  The loop reads those
values when it answers.  The listener is a :class:`~gateway.io.server.PortServer`: at most
``max_clients`` connections at once (more are answered ``503`` and closed), a request not
complete within ``client_timeout_s`` is cut, and a client that leaves an answer unread for
``client_timeout_s`` is cut.  An event stream's events go through the same bounded queue
(a full one drops them, counted); a stream lasts ``client_timeout_s`` and then ends, the
viewer's EventSource reconnecting by itself (:data:`RETRY`), so a viewer that stopped
reading holds its slot no longer than that.  :meth:`HttpBackend.close` ends everything
within a second.

Counters: ``sent`` (responses and events written), ``dropped`` (clients refused or cut, and
events a full queue dropped), ``errors`` (failed requests), ``link`` (1 while serving),
``clients`` (connections now), ``streams`` (event streams now), ``clients_refused``,
``clients_cut_stalled``, ``clients_cut_partial``, ``accept_errors``, ``events_dropped``,
``bad_requests``, ``streams_renewed`` (streams ended for the viewer to reconnect),
``vehicles`` (vehicles kept), ``vehicles_refused`` (messages of vehicles past the cap).
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from http import HTTPStatus
from typing import Any, ClassVar

from backends.http.options import HttpOptions
from gateway.backend import STATS_KEYS, Backend, BackendError, Routes
from gateway.io.ioloop import IoLoop, Timer
from gateway.io.port import PortEngine
from gateway.io.server import ClientLimits, PortServer, server_stats
from gateway.io.transport import SocketPort, TransportError, open_tcp_listener
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    SmUpdate,
    Status,
    VehicleState,
    kind,
    own_fields,
)
from gateway.outcome import Outcome
from gateway.vehicles import SERVICE as VEHICLES_SERVICE

from .connection import TEXT, HttpClient, has_request, refusal

log = logging.getLogger(__name__)

_CLOSE_S = 0.8  # close(): what closing the connections on the loop may take
#: Events waiting per viewer before they are dropped (a viewer that stops reading).
EVENTS_QUEUED = 4
#: The send buffer of a connection: small, so that a viewer that stops reading is seen
#: (and cut) within seconds rather than after megabytes of events.
SEND_BUFFER = 8192
#: Vehicles kept at most; the messages of any further vehicle are counted, not kept.
MAX_VEHICLES = 256
#: The vehicle of a message without one when no source is configured (tests, tools).
UNNAMED = "vehicle"
#: The kinds kept as a vehicle's latest values (besides its updates).
_EXTRA_KINDS = ("position", "battery", "link_stats")


class VehicleView:
    """What the backend keeps of one vehicle: its latest message of each kind, the highest
    altitude seen, messages per kind, the source it is heard from, when it was last heard.
    Written by the dispatcher's thread only."""

    __slots__ = ("heard_at", "latest", "max_altitude", "messages_in", "name", "origin")

    def __init__(self, name: str) -> None:
        self.name = name
        self.latest: dict[str, Any] = {}
        self.max_altitude: float | None = None
        self.messages_in: Counter[str] = Counter()
        self.origin = ""
        self.heard_at: float | None = None


class HttpBackend(Backend):
    """Serves the status page, ``/status.json``, ``/events`` and ``/metrics`` (see the
    module docstring)."""

    NAME = "http"
    OPTIONS = HttpOptions
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None  # it listens on a port: opt in

    def __init__(self, options: HttpOptions | None = None, name: str | None = None) -> None:
        super().__init__(name)
        options = options or HttpOptions()
        self.host = options.host
        self.port = options.port
        self.max_clients = options.max_clients
        self.event_interval_s = options.event_interval_s
        self.client_timeout_s = options.client_timeout_s
        #: name → its view, in the order first heard (written by the dispatcher's thread)
        self.vehicles: dict[str, VehicleView] = {}
        self.vehicles_refused = 0
        self._unnamed = UNNAMED  # the vehicle of a message without one (see init)
        self._first = ""  # the first configured source's vehicle (see primary)
        self._rank: dict[str, int] = {}  # configured vehicle → its place (see ordered)
        self._links: dict[str, bool] = {}  # source → up, from LinkEvents
        self.messages_in: Counter[str] = Counter()
        self.limits = ClientLimits.of(options, EVENTS_QUEUED)
        self.sent = 0  # these counters are written on the loop's thread only
        self.errors = 0
        self.requests = 0
        self.bad_requests = 0
        self.events_dropped = 0
        self.streams_renewed = 0
        self.streams: set[HttpClient] = set()
        self.loop: IoLoop | None = None
        self._server: PortServer | None = None
        self._served: PortServer | None = None  # kept after close(): its counters
        self._listener: socket.socket | None = None
        self._ticker: Timer | None = None
        self._started = time.monotonic()
        self._collector: _Collector | None = None
        self._registry: Any = None

    # -- the hot path (the dispatcher's thread) -------------------------------------------------

    def routes(self) -> Routes:
        return (Routes().on(SmUpdate, self.on_sm_update).on(Status, self._store)
                .on(LinkEvent, self.on_link_event).on(LinkStats, self._store)
                .on(Position, self._store).on(Battery, self._store)
                .on(VehicleState, self.on_vehicle_state))

    def _new_view(self, name: str) -> VehicleView | None:
        """A view for a vehicle first heard (None past the cap: counted, logged once)."""
        if len(self.vehicles) >= MAX_VEHICLES:
            self.vehicles_refused += 1
            if self.vehicles_refused == 1:
                log.warning("%s: more than %d vehicles: the messages of the others are "
                            "counted (vehicles_refused), not shown", self.name, MAX_VEHICLES)
            return None
        view = self.vehicles[name] = VehicleView(name)
        return view

    def _store(self, msg: Any) -> None:
        self._keep(msg)

    def _keep(self, msg: Any) -> VehicleView | None:
        """Keep ``msg`` as its vehicle's latest of its kind, count it; its vehicle's view."""
        k = kind(msg)
        self.messages_in[k] += 1
        name = msg.vehicle or self._unnamed
        view = self.vehicles.get(name) or self._new_view(name)
        if view is not None:
            view.origin = msg.origin
            view.heard_at = _monotonic()
            view.latest[k] = msg
            view.messages_in[k] += 1
        return view

    def on_sm_update(self, msg: SmUpdate) -> None:
        view = self._keep(msg)
        alt = msg.altitude_m
        if view is not None and alt == alt and (view.max_altitude is None
                                                or alt > view.max_altitude):
            view.max_altitude = alt  # alt == alt: NaN never becomes the maximum

    def on_vehicle_state(self, msg: VehicleState) -> None:
        view = self._keep(msg)
        alt = msg.altitude_m
        if view is not None and alt is not None and alt == alt and (
                view.max_altitude is None or alt > view.max_altitude):
            view.max_altitude = alt

    def on_link_event(self, msg: LinkEvent) -> None:
        """A source's link (per source: a vehicle's link is its source's)."""
        self._links[msg.source] = msg.up
        self.messages_in[kind(msg)] += 1

    # -- what the server answers ------------------------------------------------------------------

    def primary(self) -> VehicleView:
        """The vehicle of the single-vehicle view (``vehicle`` in ``/status.json``): the
        first configured source's vehicle once heard, else the first vehicle heard (an
        empty view before any)."""
        vehicles = self.vehicles
        view = vehicles.get(self._first) or vehicles.get(self._unnamed)
        if view is None:
            view = next(iter(vehicles.copy().values()), None)
        return view if view is not None else VehicleView(self._first or self._unnamed)

    def vehicle(self, view: VehicleView | None = None) -> dict[str, Any]:
        """A vehicle (default: :meth:`primary`) as its latest messages show it
        (``None`` = not heard yet)."""
        if view is None:
            view = self.primary()
        latest = view.latest
        sm: SmUpdate | None = latest.get("sm_update")
        vs: VehicleState | None = latest.get("vehicle_state")
        st: Status | None = latest.get("status")
        out: dict[str, Any] = {"state": None, "state_id": None, "armed": None,
                               "altitude_m": None, "max_altitude_m": view.max_altitude,
                               "velocity_mps": None, "timestamp_ms": None, "health": None}
        if sm is not None:
            out.update(state=sm.state_name, state_id=sm.state, armed=bool(sm.armed),
                       altitude_m=sm.altitude_m, velocity_mps=sm.velocity_mps,
                       timestamp_ms=sm.timestamp_ms)
        elif vs is not None:
            out.update(state=vs.mode, state_id=vs.custom_mode, armed=bool(vs.armed),
                       altitude_m=vs.altitude_m, velocity_mps=vs.climb_mps)
        if st is not None:
            out["health"] = st.health()
            if out["armed"] is None:
                out["armed"] = st.armed
        return out

    def ordered(self) -> list[VehicleView]:
        """Every vehicle: the configured sources' in their order, then the others in the
        order first heard (the page's cards keep their places from one run to the next)."""
        rank, last = self._rank, len(self._rank)
        return sorted(self.vehicles.copy().values(), key=lambda v: rank.get(v.name, last))

    def vehicle_link(self, view: VehicleView) -> bool | None:
        """The link of the source ``view`` is heard from (None: no link event of it yet)."""
        return self._links.get(view.origin)

    def vehicle_entry(self, view: VehicleView, now: float) -> dict[str, Any]:
        """One vehicle's entry in ``/status.json``: :meth:`vehicle`'s fields, ``name``,
        ``source`` (the source it is heard from), ``link`` (that source's link: true, false
        or null), ``age_s`` (seconds since its last message), its latest ``position``,
        ``battery`` and ``link_stats`` (null until heard) and ``messages_in`` per kind."""
        out = self.vehicle(view)
        latest = view.latest
        out.update(name=view.name, source=view.origin or None,
                   link=self.vehicle_link(view),
                   age_s=None if view.heard_at is None else round(now - view.heard_at, 3))
        for k in _EXTRA_KINDS:
            msg = latest.get(k)
            out[k] = own_fields(msg) if msg is not None else None
        out["messages_in"] = dict(view.messages_in)
        return _jsonable(out)

    def link_up(self) -> bool:
        """True when a source's link is up (by its LinkEvents)."""
        return any(self._links.values())

    def gateway_stats(self) -> dict[str, Any]:
        """The gateway's ``gateway.stats`` service (every backend's and source's stats),
        or empty when it runs without one."""
        service: Callable[[], dict[str, Any]] | None = self.context.services.get(
            "gateway.stats")
        if service is None:
            return {"backends": {self.name: self.stats()}, "sources": {}}
        try:
            return service()
        except Exception:
            log.exception("%s: the gateway's stats failed", self.name)
            return {"backends": {}, "sources": {}}

    def status(self) -> dict[str, Any]:
        """What ``/status.json`` and every event carry (see the module doc)."""
        stats = self.gateway_stats()
        backends = {name: _counters(st) for name, st in stats.get("backends", {}).items()}
        sources = {name: _counters(st) for name, st in stats.get("sources", {}).items()}
        now = time.monotonic()
        vehicles = {view.name: self.vehicle_entry(view, now) for view in self.ordered()}
        primary = self.primary()
        return {
            "time": time.time(),
            "uptime_s": round(now - self._started, 3),
            "vehicles": vehicles,
            "vehicle": vehicles.get(primary.name) or self.vehicle_entry(primary, now),
            "vehicles_refused": self.vehicles_refused,
            "link": {"up": self.link_up(), "sources": dict(self._links)},
            "messages_in": dict(self.messages_in),
            "backends": backends,
            "sources": sources,
        }

    def status_bytes(self) -> bytes:
        return json.dumps(self.status(), separators=(",", ":"), allow_nan=False).encode()

    def metrics(self) -> tuple[bytes, str]:
        """``/metrics``: the body and its content type."""
        from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
        return generate_latest(self._registry), CONTENT_TYPE_LATEST

    # -- life cycle ------------------------------------------------------------------------------

    def init(self) -> None:
        configured = self.context.services.get(VEHICLES_SERVICE) or ()
        if configured:
            self._first = self._unnamed = configured[0].vehicle or UNNAMED
        self._rank = {sv.vehicle: i for i, sv in enumerate(configured)}
        try:
            from prometheus_client import CollectorRegistry
        except ImportError as exc:
            raise BackendError("the http backend needs prometheus-client: "
                               "pip install 'aurora-gateway[http]'") from exc
        self._registry = CollectorRegistry(auto_describe=False)
        self._collector = _Collector(self)
        self._registry.register(self._collector)
        try:
            self._listener = open_tcp_listener(self.host, self.port)
        except TransportError as exc:
            raise BackendError(str(exc)) from None
        loop = self.loop = IoLoop(self.name)
        pending = [self._listener]
        bound_port = self._listener.getsockname()[1]

        def opener() -> socket.socket:  # bound again on the same port after a failure
            return pending.pop() if pending else open_tcp_listener(self.host, bound_port)

        self._server = self._served = PortServer(
            opener, self._on_client, loop=loop, name=f"{self.name} http", limits=self.limits,
            refusal=refusal(), ready=has_request)
        loop.start()
        self._server.start()
        self._ticker = loop.call_every(self.event_interval_s, self._tick,
                                       first=self.event_interval_s)
        host, port = self.address()
        log.info("%s: status page on http://%s:%d/", self.name,
                 f"[{host}]" if ":" in host else host, port)

    def address(self) -> tuple[str, int]:
        """The bound (host, port) (the port chosen when ``port`` is 0)."""
        if self._server is None or self._listener is None:
            raise BackendError(f"{self.name} is not serving")
        addr = self._listener.getsockname()
        return str(addr[0]), int(addr[1])

    def close(self) -> None:
        server, self._server = self._server, None
        loop, self.loop = self.loop, None
        if server is None or loop is None:
            return
        server.close()
        done = threading.Event()

        def close_all() -> None:
            if self._ticker is not None:
                self._ticker.cancel()
            for engine in list(server.clients):
                engine.close(0.1)
            done.set()

        loop.call_soon(close_all)
        done.wait(_CLOSE_S)
        loop.stop(0.2)
        loop.close()

    @property
    def serving(self) -> bool:
        return self._server is not None

    def stats(self) -> dict[str, Any]:
        served = self._served
        listener = server_stats((served,) if served is not None else ())
        cut = listener["clients_cut_stalled"] + listener["clients_cut_partial"]
        return {"sent": self.sent,
                "dropped": listener["clients_refused"] + cut + self.events_dropped,
                "errors": self.errors, "link": int(self.serving),
                "clients": served.client_count if self.serving and served else 0,
                "streams": len(self.streams), "requests": self.requests, **listener,
                "events_dropped": self.events_dropped, "bad_requests": self.bad_requests,
                "streams_renewed": self.streams_renewed, "vehicles": len(self.vehicles),
                "vehicles_refused": self.vehicles_refused}

    # -- the loop's thread -------------------------------------------------------------------------

    def _on_client(self, sock: socket.socket, addr: Any) -> PortEngine:
        name = f"{self.name} <{addr[0]}:{addr[1]}>"
        client = HttpClient(self, name)
        engine = PortEngine(_not_reopened, name=name, protocol=client, loop=self.loop,
                            queue_depth=EVENTS_QUEUED, reopen=False,
                            hangup_level=logging.DEBUG)
        client.attach(engine)
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        engine.start_with(SocketPort(sock, name))
        return engine

    def answer(self, client: HttpClient, method: str, path: str) -> None:
        """Answer one request (see the module doc)."""
        self.requests += 1
        if method not in ("GET", "HEAD"):
            client.respond(HTTPStatus.METHOD_NOT_ALLOWED, b"read-only: GET or HEAD\n", TEXT,
                           extra=(("Allow", "GET, HEAD"),))
            self.sent += 1
            return
        head = method == "HEAD"
        try:
            if path in ("/", "/index.html"):
                client.respond(200, PAGE.encode(), "text/html; charset=utf-8", head=head)
            elif path == "/status.json":
                client.respond(200, self.status_bytes(), "application/json", head=head)
            elif path == "/metrics":
                body, ctype = self.metrics()
                client.respond(200, body, ctype, head=head)
            elif path == "/events":
                client.start_stream(RETRY + self._event(), head=head)
                if not head:
                    self.streams.add(client)
            else:
                client.respond(404, b"not found\n", TEXT, head=head)
        except Exception:
            log.exception("%s: %s failed", self.name, path)
            self.errors += 1
            client.respond(500, b"internal error\n", TEXT, head=head)
        self.sent += 1

    def bad_request(self) -> None:
        self.bad_requests += 1

    def stream_closed(self, client: HttpClient) -> None:
        self.streams.discard(client)
        self.events_dropped += client.events_dropped

    def _event(self) -> bytes:
        return b"data: " + self.status_bytes() + b"\n\n"

    def _tick(self) -> None:
        """One event to every stream (computed once for all); a stream older than
        ``client_timeout_s`` is ended (see :data:`RETRY`)."""
        if not self.streams:
            return
        event = self._event()
        oldest = time.monotonic() - self.client_timeout_s
        for client in list(self.streams):
            if client.stream_started <= oldest:
                self.streams_renewed += 1
                client.end_stream()
            elif client.send_event(event) is _ACCEPTED:
                self.sent += 1


_ACCEPTED = Outcome.ACCEPTED
_monotonic = time.monotonic
#: An event stream lasts ``client_timeout_s``; then it ends and the viewer's EventSource
#: reconnects after this many milliseconds.  A viewer that stopped reading is so let go
#: within that time: a server cannot see it otherwise, as the viewer's kernel keeps taking
#: events into its buffers for a minute or more (measured on loopback: a full window at
#: 2.4 KB/s of events after 30 s) before a write would wait.
RETRY = b"retry: 250\n\n"


def _not_reopened() -> Any:
    raise OSError("an accepted connection is not reopened")


def _counters(stats: dict[str, Any]) -> dict[str, Any]:
    """The counters the page shows of one backend or source (numbers only)."""
    out: dict[str, Any] = {}
    for key in (*STATS_KEYS, "clients"):
        v = stats.get(key)
        if isinstance(v, int | float) and not isinstance(v, bool):
            out[key] = v
    if "init_error" in stats:
        out["init_error"] = str(stats["init_error"])
    return out


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    """NaN and infinities as null (JSON has neither); tuples as lists."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, float) and (v != v or v in (float("inf"), float("-inf"))):
            v = None
        elif isinstance(v, dict):
            v = _jsonable(v)
        elif isinstance(v, bytes):
            v = v.hex()
        out[k] = v
    return out


class _Collector:
    """The gateway's values as Prometheus metric families, read when scraped."""

    def __init__(self, backend: HttpBackend) -> None:
        self.backend = backend

    def collect(self) -> Iterator[Any]:
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        b = self.backend
        views = b.ordered()
        gauges = {name: GaugeMetricFamily(name, doc, labels=["vehicle"]) for name, doc in (
            ("aurora_altitude_meters", "altitude of the vehicle"),
            ("aurora_max_altitude_meters", "highest altitude seen"),
            ("aurora_armed", "1 when the vehicle is armed"),
            ("aurora_link_up", "1 while the link of the vehicle's source is up"))}
        state = GaugeMetricFamily("aurora_state", "the vehicle's state (its number; label: "
                                  "its name)", labels=["vehicle", "state"])
        messages = CounterMetricFamily("aurora_messages_in", "messages this backend took, "
                                       "per vehicle and kind", labels=["vehicle", "kind"])
        for view in views:
            v = b.vehicle(view)
            label = [view.name]
            for name, value in (("aurora_altitude_meters", v["altitude_m"]),
                                ("aurora_max_altitude_meters", v["max_altitude_m"]),
                                ("aurora_armed", v["armed"]),
                                ("aurora_link_up", b.vehicle_link(view))):
                if value is not None and value == value:
                    gauges[name].add_metric(label, float(value))
            if v["state_id"] is not None:
                state.add_metric([view.name, str(v["state"])], float(v["state_id"]))
            for k, n in sorted(view.messages_in.copy().items()):
                messages.add_metric([view.name, k], float(n))
        yield from gauges.values()
        yield state
        yield messages
        yield CounterMetricFamily("aurora_link_events", "link up/down events of the sources",
                                  value=float(b.messages_in.get("link", 0)))
        yield GaugeMetricFamily("aurora_vehicles", "vehicles shown", value=float(len(views)))
        yield CounterMetricFamily("aurora_vehicles_refused", "messages of vehicles past the "
                                  "cap (not shown)", value=float(b.vehicles_refused))
        stats = b.gateway_stats().get("backends", {})
        for key in ("sent", "dropped", "errors"):
            c = CounterMetricFamily(f"aurora_backend_{key}", f"{key} per backend",
                                    labels=["backend"])
            for name, st in stats.items():
                n = st.get(key)
                if isinstance(n, int | float) and not isinstance(n, bool):
                    c.add_metric([name], float(n))
            yield c
        links = GaugeMetricFamily("aurora_backend_link", "1 while a backend's link is up",
                                  labels=["backend"])
        for name, st in stats.items():
            n = st.get("link")
            if isinstance(n, int | float) and not isinstance(n, bool):
                links.add_metric([name], float(n))
        yield links


PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>Aurora Gateway</title>
<style>
body{font-family:system-ui,sans-serif;margin:1.5em;background:#10141a;color:#e6e6e6}
h1{font-size:1.3em;margin:0 0 .8em}
h2{font-size:1.05em;margin:0 0 .5em}
.vehicles{display:flex;flex-wrap:wrap;gap:1em;margin-bottom:1.2em}
.vehicle{background:#161c24;border-radius:10px;padding:.8em 1em}
.cards{display:flex;flex-wrap:wrap;gap:.8em}
.card{background:#1c232d;border-radius:8px;padding:.7em 1em;min-width:8em}
.card .k{font-size:.8em;color:#9aa7b5}.card .v{font-size:1.6em;font-variant-numeric:tabular-nums}
.up{color:#5fd35f}.down{color:#ff6b6b}
table{border-collapse:collapse;font-variant-numeric:tabular-nums}
th,td{padding:.3em .9em;text-align:right;border-bottom:1px solid #2a3440}
th:first-child,td:first-child{text-align:left}
#conn,.age{font-size:.8em;color:#9aa7b5}
</style></head><body>
<h1>Aurora Gateway <span id="conn">connecting…</span></h1>
<div class="vehicles" id="vehicles"></div>
<table><thead><tr><th>backend</th><th>sent</th><th>dropped</th><th>errors</th><th>link</th>
<th>clients</th></tr></thead><tbody id="backends"></tbody></table>
<script>
"use strict";
const FIELDS = [["state", "state"], ["armed", "armed"], ["altitude", "altitude (m)"],
                ["max_altitude", "max altitude (m)"], ["link", "link"]];
function num(v, d) { return v === null || v === undefined ? "—" : Number(v).toFixed(d); }
function text(id, v) { document.getElementById(id).textContent = v; }
function el(tag, cls, content) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (content !== undefined) e.textContent = content;
  return e;
}
const cards = new Map();  // vehicle name → {field: its value element}
function card(name) {
  let c = cards.get(name);
  if (c) return c;
  c = {};
  const box = el("div", "vehicle");
  box.dataset.vehicle = name;
  const title = el("h2", "", name + " ");
  c.age = el("span", "age", "");
  title.appendChild(c.age);
  box.appendChild(title);
  const row = el("div", "cards");
  for (const [key, label] of FIELDS) {
    const f = el("div", "card");
    f.appendChild(el("div", "k", label));
    c[key] = el("div", "v", "—");
    c[key].dataset.field = key;
    f.appendChild(c[key]);
    row.appendChild(f);
  }
  box.appendChild(row);
  document.getElementById("vehicles").appendChild(box);
  cards.set(name, c);
  return c;
}
function show(s) {
  const names = Object.keys(s.vehicles);
  if (names.length === 0) card(s.vehicle.name);  // nothing heard yet: the empty card
  for (const name of names) {
    const v = s.vehicles[name], c = card(name);
    c.state.textContent = v.state === null ? "—" : v.state;
    c.armed.textContent = v.armed === null ? "—" : (v.armed ? "ARMED" : "safe");
    c.altitude.textContent = num(v.altitude_m, 1);
    c.max_altitude.textContent = num(v.max_altitude_m, 1);
    const up = v.link === null ? s.link.up : v.link;
    c.link.textContent = up ? "up" : "down";
    c.link.className = "v " + (up ? "up" : "down");
    c.age.textContent = v.age_s === null ? "" : num(v.age_s, 1) + " s ago";
  }
  const body = document.getElementById("backends");
  body.replaceChildren();
  for (const [name, c] of Object.entries(s.backends)) {
    const tr = document.createElement("tr");
    for (const cell of [name, c.sent, c.dropped, c.errors, c.link, c.clients]) {
      tr.appendChild(el("td", "", cell === undefined ? "" : String(cell)));
    }
    body.appendChild(tr);
  }
}
const events = new EventSource("events");
let lost = null;  // a stream ends every few seconds and reconnects: say so only if it stays off
events.onopen = () => { clearTimeout(lost); text("conn", "live"); };
events.onerror = () => {
  clearTimeout(lost);
  lost = setTimeout(() => text("conn", "reconnecting…"), 2000);
};
events.onmessage = (e) => show(JSON.parse(e.data));
</script>
</body></html>
"""
