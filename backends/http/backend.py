"""The HTTP backend: a live status page and Prometheus metrics, read-only.

``run --http [HOST:]PORT`` (off by default; HOST defaults to loopback) serves, from the
standard library's :class:`http.server.ThreadingHTTPServer` on a thread of its own:

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
kind and counts it; nothing is queued, so nothing is dropped there.  The server's threads
read those values when they answer.  At most ``max_clients`` event streams run at once (more
are refused with 503, counted in ``dropped``); a client that stops reading is cut when a
write waits ``client_timeout_s``.  :meth:`HttpBackend.close` ends everything within a
second.

Counters: ``sent`` (responses and events written), ``dropped`` (clients refused or cut),
``errors`` (failed requests), ``link`` (1 while serving), ``clients`` (event streams now).
"""

from __future__ import annotations

import json
import logging
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, ClassVar

from backends.http.options import HttpOptions
from gateway.backend import STATS_KEYS, Backend, BackendError, Routes
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

log = logging.getLogger(__name__)

_JOIN_S = 0.8  # close(): what the server thread may take to stop


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
        self._lock = threading.Lock()  # the counters the server's threads write
        self.sent = 0
        self.dropped = 0
        self.errors = 0
        self.clients = 0
        self.requests = 0
        self.dropped_clients_full = 0
        self.dropped_client_timeout = 0
        self._server: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
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
        server_cls = _Server6 if ":" in self.host else _Server
        try:
            server = server_cls((self.host, self.port), _make_handler(self))
        except OSError as exc:
            raise BackendError(f"cannot listen on {self.host}:{self.port}: "
                               f"{exc.strerror or exc}") from None
        self._server = server
        self._stop.clear()
        self._thread = threading.Thread(target=server.serve_forever, kwargs={
            "poll_interval": 0.1}, name=f"{self.name} http", daemon=True)
        self._thread.start()
        host, port = self.address()
        log.info("%s: status page on http://%s:%d/", self.name,
                 f"[{host}]" if ":" in host else host, port)

    def address(self) -> tuple[str, int]:
        """The bound (host, port) (the port chosen when ``port`` is 0)."""
        if self._server is None:
            raise BackendError(f"{self.name} is not serving")
        addr = self._server.server_address
        return str(addr[0]), int(addr[1])

    def close(self) -> None:
        server, self._server = self._server, None
        self._stop.set()  # event streams end at their next tick
        if server is None:
            return
        server.shutdown()  # serve_forever ends within its poll interval
        server.server_close()
        if self._thread is not None:
            self._thread.join(_JOIN_S)
            self._thread = None

    @property
    def serving(self) -> bool:
        return self._server is not None

    def stats(self) -> dict[str, Any]:
        return {"sent": self.sent, "dropped": self.dropped, "errors": self.errors,
                "link": int(self.serving), "clients": self.clients,
                "requests": self.requests,
                "dropped_clients_full": self.dropped_clients_full,
                "dropped_client_timeout": self.dropped_client_timeout}

    # -- the server's threads --------------------------------------------------------------------

    def count(self, **deltas: int) -> None:
        with self._lock:
            for name, n in deltas.items():
                setattr(self, name, getattr(self, name) + n)

    def open_stream(self) -> bool:
        """Take an event stream slot; False (counted) when all are taken."""
        with self._lock:
            if self.clients >= self.max_clients:
                self.dropped += 1
                self.dropped_clients_full += 1
                return False
            self.clients += 1
            return True

    def close_stream(self) -> None:
        with self._lock:
            self.clients -= 1

    def events(self) -> Iterator[bytes]:
        """The event stream: one event now, then one per interval until close()."""
        while True:
            yield b"data: " + self.status_bytes() + b"\n\n"
            if self._stop.wait(self.event_interval_s):
                return


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


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    block_on_close = False


class _Server6(_Server):
    address_family = socket.AF_INET6


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


def _make_handler(backend: HttpBackend) -> type[BaseHTTPRequestHandler]:
    class Handler(_Handler):
        pass

    Handler.backend = backend
    Handler.timeout = backend.client_timeout_s
    return Handler


class _Handler(BaseHTTPRequestHandler):
    backend: ClassVar[HttpBackend]
    server_version = "aurora-gateway"
    protocol_version = "HTTP/1.0"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("%s: %s %s", self.backend.name, self.address_string(), format % args)

    def _send(self, code: int, body: bytes, ctype: str, head: bool = False,
              extra: dict[str, str] | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        for k, val in (extra or {}).items():
            self.send_header(k, val)
        self.end_headers()
        if not head:
            self.wfile.write(body)
        self.backend.count(sent=1)

    def _get(self, head: bool) -> None:
        b = self.backend
        b.count(requests=1)
        path = self.path.split("?", 1)[0]
        try:
            if path in ("/", "/index.html"):
                self._send(200, PAGE.encode(), "text/html; charset=utf-8", head)
            elif path == "/status.json":
                self._send(200, b.status_bytes(), "application/json", head)
            elif path == "/metrics":
                body, ctype = b.metrics()
                self._send(200, body, ctype, head)
            elif path == "/events":
                self._stream(head)
            else:
                self._send(404, b"not found\n", "text/plain; charset=utf-8", head)
        except TimeoutError:  # a client that stopped reading: cut
            b.count(dropped=1, dropped_client_timeout=1)
        except ConnectionError:  # the client went away (closed its page)
            pass
        except Exception:
            log.exception("%s: %s failed", b.name, path)
            b.count(errors=1)

    def _stream(self, head: bool) -> None:
        b = self.backend
        if not b.open_stream():
            self._send(503, b"too many event streams\n", "text/plain; charset=utf-8", head,
                       {"Retry-After": "5"})
            return
        try:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            if head:
                return
            self.wfile.write(b"retry: 1000\n\n")
            for event in b.events():
                self.wfile.write(event)
                self.wfile.flush()
                b.count(sent=1)
        finally:
            b.close_stream()

    def do_GET(self) -> None:
        self._get(head=False)

    def do_HEAD(self) -> None:
        self._get(head=True)

    def _refuse(self) -> None:
        self.backend.count(requests=1)
        self._send(HTTPStatus.METHOD_NOT_ALLOWED, b"read-only: GET or HEAD\n",
                   "text/plain; charset=utf-8", extra={"Allow": "GET, HEAD"})

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse


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
events.onopen = () => text("conn", "live");
events.onerror = () => text("conn", "reconnecting…");
events.onmessage = (e) => show(JSON.parse(e.data));
</script>
</body></html>
"""
