"""The HTTP backend: a live status page and Prometheus metrics, read-only.

``run --http [HOST:]PORT`` (off by default; HOST defaults to loopback) serves, on the
gateway's port engine (one :class:`~gateway.io.ioloop.IoLoop` thread, an h11 parser per
connection: :mod:`backends.http.connection`; no thread per connection):

``/``
    a small page (no framework) with the vehicle's state, armed, altitude, max altitude,
    link and a table of every backend's counters, kept live by an ``EventSource``;
``/events``
    Server-Sent Events: one ``data: <JSON>`` event per ``event_interval_s`` with the latest
    values (the same JSON as ``/status.json``);
``/status.json``
    that JSON once;
``/metrics``
    Prometheus text format, written by ``prometheus-client`` from a collector of our own:
    gauges for altitude, max altitude, state, armed and link, counters per backend
    (sent / dropped / errors, label ``backend``) and messages in per kind.

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
``bad_requests``, ``streams_renewed`` (streams ended for the viewer to reconnect).
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

from .connection import TEXT, HttpClient, has_request, refusal

log = logging.getLogger(__name__)

_CLOSE_S = 0.8  # close(): what closing the connections on the loop may take
#: Events waiting per viewer before they are dropped (a viewer that stops reading).
EVENTS_QUEUED = 4
#: The send buffer of a connection: small, so that a viewer that stops reading is seen
#: (and cut) within seconds rather than after megabytes of events.
SEND_BUFFER = 8192


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
        self._latest: dict[str, Any] = {}  # kind → latest message (written by one thread)
        self._links: dict[str, bool] = {}  # source → up, from LinkEvents
        self._max_altitude: float | None = None
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

    def _store(self, msg: Any) -> None:
        k = kind(msg)
        self._latest[k] = msg
        self.messages_in[k] += 1

    def on_sm_update(self, msg: SmUpdate) -> None:
        alt = msg.altitude_m
        if alt == alt and (self._max_altitude is None or alt > self._max_altitude):
            self._max_altitude = alt  # alt == alt: NaN never becomes the maximum
        self._store(msg)

    def on_vehicle_state(self, msg: VehicleState) -> None:
        alt = msg.altitude_m
        if alt is not None and alt == alt and (self._max_altitude is None
                                               or alt > self._max_altitude):
            self._max_altitude = alt
        self._store(msg)

    def on_link_event(self, msg: LinkEvent) -> None:
        self._links[msg.source] = msg.up
        self._store(msg)

    # -- what the server answers ------------------------------------------------------------------

    def vehicle(self) -> dict[str, Any]:
        """The vehicle as the latest messages show it (``None`` = not heard yet)."""
        sm: SmUpdate | None = self._latest.get("sm_update")
        vs: VehicleState | None = self._latest.get("vehicle_state")
        st: Status | None = self._latest.get("status")
        out: dict[str, Any] = {"state": None, "state_id": None, "armed": None,
                               "altitude_m": None, "max_altitude_m": self._max_altitude,
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
        """What ``/status.json`` and every event carry."""
        stats = self.gateway_stats()
        backends = {name: _counters(st) for name, st in stats.get("backends", {}).items()}
        sources = {name: _counters(st) for name, st in stats.get("sources", {}).items()}
        extra: dict[str, Any] = {}
        for k in ("position", "battery", "link_stats"):
            msg = self._latest.get(k)
            extra[k] = _jsonable(own_fields(msg)) if msg is not None else None
        return {
            "time": time.time(),
            "uptime_s": round(time.monotonic() - self._started, 3),
            "vehicle": _jsonable(self.vehicle()),
            "link": {"up": self.link_up(), "sources": dict(self._links)},
            **extra,
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
                "streams_renewed": self.streams_renewed}

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
        v = b.vehicle()
        for name, doc, value in (
            ("aurora_altitude_meters", "altitude of the vehicle", v["altitude_m"]),
            ("aurora_max_altitude_meters", "highest altitude seen", v["max_altitude_m"]),
            ("aurora_armed", "1 when the vehicle is armed", v["armed"]),
            ("aurora_link_up", "1 while a source's link is up", b.link_up()),
        ):
            if value is not None:
                yield GaugeMetricFamily(name, doc, value=float(value))
        if v["state_id"] is not None:
            g = GaugeMetricFamily("aurora_state", "the vehicle's state (its number; label: "
                                  "its name)", labels=["state"])
            g.add_metric([str(v["state"])], float(v["state_id"]))
            yield g
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
        m = CounterMetricFamily("aurora_messages_in", "messages this backend took, per kind",
                                labels=["kind"])
        for k, n in sorted(b.messages_in.items()):
            m.add_metric([k], float(n))
        yield m


PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>Aurora Gateway</title>
<style>
body{font-family:system-ui,sans-serif;margin:1.5em;background:#10141a;color:#e6e6e6}
h1{font-size:1.3em;margin:0 0 .8em}
.cards{display:flex;flex-wrap:wrap;gap:.8em;margin-bottom:1.2em}
.card{background:#1c232d;border-radius:8px;padding:.7em 1em;min-width:9em}
.card .k{font-size:.8em;color:#9aa7b5}.card .v{font-size:1.6em;font-variant-numeric:tabular-nums}
.up{color:#5fd35f}.down{color:#ff6b6b}
table{border-collapse:collapse;font-variant-numeric:tabular-nums}
th,td{padding:.3em .9em;text-align:right;border-bottom:1px solid #2a3440}
th:first-child,td:first-child{text-align:left}
#conn{font-size:.8em;color:#9aa7b5}
</style></head><body>
<h1>Aurora Gateway <span id="conn">connecting…</span></h1>
<div class="cards">
<div class="card"><div class="k">state</div><div class="v" id="state">—</div></div>
<div class="card"><div class="k">armed</div><div class="v" id="armed">—</div></div>
<div class="card"><div class="k">altitude (m)</div><div class="v" id="altitude">—</div></div>
<div class="card"><div class="k">max altitude (m)</div>
<div class="v" id="max_altitude">—</div></div>
<div class="card"><div class="k">link</div><div class="v" id="link">—</div></div>
</div>
<table><thead><tr><th>backend</th><th>sent</th><th>dropped</th><th>errors</th><th>link</th>
<th>clients</th></tr></thead><tbody id="backends"></tbody></table>
<script>
"use strict";
function num(v, d) { return v === null || v === undefined ? "—" : Number(v).toFixed(d); }
function text(id, v) { document.getElementById(id).textContent = v; }
function show(s) {
  const v = s.vehicle;
  text("state", v.state === null ? "—" : v.state);
  text("armed", v.armed === null ? "—" : (v.armed ? "ARMED" : "safe"));
  text("altitude", num(v.altitude_m, 1));
  text("max_altitude", num(v.max_altitude_m, 1));
  const link = document.getElementById("link");
  link.textContent = s.link.up ? "up" : "down";
  link.className = "v " + (s.link.up ? "up" : "down");
  const body = document.getElementById("backends");
  body.replaceChildren();
  for (const [name, c] of Object.entries(s.backends)) {
    const tr = document.createElement("tr");
    for (const cell of [name, c.sent, c.dropped, c.errors, c.link, c.clients]) {
      const td = document.createElement("td");
      td.textContent = cell === undefined ? "" : String(cell);
      tr.appendChild(td);
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
