"""The running gateway: sources → ingest (record, monitor, count) → dispatcher → backends."""

from __future__ import annotations

import logging
import sys
import threading
import time
from collections import Counter
from typing import TYPE_CHECKING, Any, TextIO

from gateway import logjson, vehicles
from gateway.backend import GatewayContext
from gateway.config import ConfigError, GatewayConfig, Part
from gateway.dispatcher import Dispatcher
from gateway.flight_summary import FlightSummary, crc_errors
from gateway.io.ioloop import IoLoop
from gateway.link_monitor import LinkMonitor
from gateway.model import kind
from gateway.sources import SourceInbox

if TYPE_CHECKING:  # imported when a run records (Gateway.start): ~2 ms of every other start
    from gateway.recorder import Recorder

log = logging.getLogger(__name__)

STOP_BUDGET_S = 0.9  # SIGINT/SIGTERM must end everything within a second


def _build(part: Part, where: str) -> Any:
    try:
        plugin = part.cls.from_config(dict(part.options), name=part.name)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if part.vehicle:  # a source: its vehicle, named or derived by the configuration
        plugin.vehicle = part.vehicle
        plugin.mavlink_sysid = part.mavlink_sysid
    return plugin


class Gateway:
    """Builds and runs sources and backends from a validated configuration."""

    def __init__(self, cfg: GatewayConfig, status_out: TextIO | None = None) -> None:
        self.cfg = cfg
        self.status_out = status_out if status_out is not None else sys.stderr
        self.dispatcher = Dispatcher()
        self.context = GatewayContext(emit=self.ingest)
        self.context.services["gateway.stats"] = self.counters
        self.monitor = LinkMonitor(self._link_changed, cfg.gateway["link_timeout_s"])
        self.counts: Counter[str] = Counter()
        #: the recording (``record``: one file for every vehicle; ``record_dir``: one per
        #: vehicle per flight, :class:`DirectoryRecorder`)
        self.recorder: Recorder | None = None
        #: the loop the sources share (their timers, ports and callbacks)
        self.loop = IoLoop("sources")
        self.flights = FlightSummary()
        self.sources = [_build(p, f"sources.{p.name}") for p in cfg.sources]
        #: a source's vehicle, stamped on a message that comes without one
        self._vehicle_of = {s.name: getattr(s, "vehicle", "") for s in self.sources}
        self.context.services[vehicles.SERVICE] = [
            vehicles.SourceVehicle(s.name, getattr(s, "vehicle", ""),
                                   getattr(s, "mavlink_sysid", None),
                                   bool(getattr(s, "YIELDS_SYSTEMS", False)))
            for s in self.sources]
        for p in cfg.backends:
            self.dispatcher.add(_build(p, f"backends.{p.name}"))
        for src in self.sources:  # a source that also takes messages (commands to send up)
            if len(src.routes()):
                self.dispatcher.add(SourceInbox(src))
        self.started_at: float | None = None
        self.stop_event = threading.Event()

    # -- the hot path ------------------------------------------------------------------------

    def ingest(self, msg: Any) -> None:
        """Everything a source produces comes through here (from the sources' loop, or the
        thread a source's library calls back on)."""
        self.dispatcher.dispatch(self._take(msg))

    def ingest_batch(self, msgs: list[Any]) -> None:
        """:meth:`ingest` for what one read of a source decoded: dispatched as one batch."""
        take = self._take
        self.dispatcher.dispatch_batch([take(m) for m in msgs])

    def _take(self, msg: Any) -> Any:
        """Stamp, record, monitor and count a message before it is dispatched."""
        if getattr(msg, "vehicle", None) == "":  # (a message type without one keeps none)
            vehicle = self._vehicle_of.get(msg.origin)
            if vehicle:
                msg = msg._replace(vehicle=vehicle)
        new_flight = self.flights.feed(msg)
        rec = self.recorder
        if rec is not None:
            # never waits on disk: a bounded queue to the writer thread, which also opens a
            # vehicle's next flight's file (record_dir)
            rec.submit(msg, new_flight=new_flight)
        if msg.origin:
            self.monitor.frame_seen(msg.origin, msg.via, getattr(msg, "vehicle", ""))
        self.counts[kind(msg)] += 1
        return msg

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> list[tuple[str, str]]:
        """Open the recorder, start the backends, then the sources; returns backend failures.

        The recorder comes first: a recording that cannot be opened (no such directory, not
        a recording) is a configuration error, raised as :class:`ConfigError` before any
        thread runs."""
        self.started_at = time.monotonic()
        path = self.cfg.gateway.get("record")
        directory = self.cfg.gateway.get("record_dir")
        if directory or path:
            from gateway.recorder import DirectoryRecorder, Recorder
            from gateway.recording import RecordingError
        if directory:
            try:
                self.recorder = DirectoryRecorder(directory)
            except OSError as exc:
                raise ConfigError(f"gateway.record_dir: cannot create a recording in "
                                  f"{directory}: {exc.strerror or exc}") from None
        elif path:
            try:
                self.recorder = Recorder(path)
            except RecordingError as exc:
                raise ConfigError(f"gateway.record: {exc}") from None
            except OSError as exc:
                raise ConfigError(f"gateway.record: cannot open {path}: "
                                  f"{exc.strerror or exc}") from None
        for backend in self.dispatcher.backends():
            backend.attach(self.context)
        for src in self.sources:  # every plugin knows the others' shared services first
            src.attach(self.context)
            use_loop = getattr(src, "use_loop", None)  # (optional in the contract)
            if use_loop is not None:
                use_loop(self.loop)
        failures = self.dispatcher.start()
        self.loop.start()
        for src in self.sources:
            if hasattr(src, "batch_sink"):  # (a Source: it may hand over what a read decoded)
                src.batch_sink = self.ingest_batch
            src.start(self.ingest)
        return failures

    def run(self, duration_s: float | None = None) -> None:
        """Check links and print status lines until stopped, ``duration_s`` passes, or every
        source is done."""
        interval = self.cfg.gateway["status_interval_s"]
        start = time.monotonic()
        next_status = start + interval if interval else None
        while not self.stop_event.is_set():
            now = time.monotonic()
            if duration_s is not None and now - start >= duration_s:
                break
            if self.sources and all(s.done.is_set() for s in self.sources):
                break
            self.monitor.check()
            if next_status is not None and now >= next_status:
                text, fields = self.status()
                logjson.say(text, self.status_out, fields=fields)
                next_status += interval
                if next_status < now:
                    next_status = now + interval
            self.stop_event.wait(0.05)

    def stop(self) -> dict[str, Any]:
        """Stop sources, backends and the recorder within about a second; returns the summary."""
        deadline = time.monotonic() + STOP_BUDGET_S
        for src in self.sources:
            src.request_stop()  # all wind down together
        for src in self.sources:
            src.stop(max(0.05, (deadline - time.monotonic()) / 2))
        self.dispatcher.close()
        rec = self.recorder
        if rec is not None:
            rec.close(max(0.1, deadline - time.monotonic()))
        if self.loop.stop(max(0.05, deadline - time.monotonic())):
            self.loop.close()
        return self.summary()

    # -- reporting ---------------------------------------------------------------------------

    def counters(self) -> dict[str, Any]:
        """Every backend's and source's ``stats()`` now (what a Zenoh backend publishes for a
        monitor following this gateway)."""
        return {"backends": self.dispatcher.stats(),
                "sources": {s.name: s.stats() for s in self.sources}}

    def summary(self) -> dict[str, Any]:
        """What the run did (counters per source, link, backend, recording and blocking call)
        and what it saw of each vehicle (``flights``: :class:`FlightSummary`)."""
        sources = {s.name: s.stats() for s in self.sources}
        backends = self.dispatcher.stats()
        rec = self.recorder
        return {
            "uptime_s": round(time.monotonic() - (self.started_at or time.monotonic()), 3),
            "messages_in": dict(self.counts),
            "sources": sources,
            "links": self.monitor.states(),
            "backends": backends,
            "recorded": rec.records if rec is not None else None,
            "recorder": rec.stats() if rec is not None else None,
            "recordings": [str(p) for p in rec.paths] if rec is not None else [],
            "flights": self.flights.as_dict(),
            "crc_errors": crc_errors(sources, backends),
            # the process's pool of blocking calls (opens, closes): bounded, counted
            "blocking_calls": self.loop.blocking.stats(),
        }

    def _link_changed(self, ev: Any) -> None:
        """A link went up or down: every backend hears it; a JSON log gets a line of it too
        (the plain log leaves that to the console backend)."""
        if logjson.json_mode():
            state = "up" if ev.up else f"down after {ev.silence_s:.1f} s of silence"
            logjson.say(f"link {ev.vehicle or ev.source} {state}", self.status_out,
                        fields={"event": "link", "source": ev.source, "vehicle": ev.vehicle,
                                "up": ev.up, "silence_s": round(ev.silence_s, 3),
                                "via": ev.via})
        self.dispatcher.dispatch(ev)

    def status_line(self) -> str:
        """The per-second status line."""
        return self.status()[0]

    def status(self) -> tuple[str, dict[str, Any]]:
        """The per-second status line and its figures (the fields of its JSON form)."""
        up = time.monotonic() - (self.started_at or time.monotonic())
        c = self.counts
        parts = [f"[{up:7.1f}s] in {sum(c.values())} "
                 f"(sm {c['sm_update']} st {c['status']} raw {c['raw']})"]
        links = self.monitor.states()
        for name, state in links.items():
            parts.append(f"{name} {'up' if state else 'DOWN'}")
        backends: dict[str, Any] = {}
        for name, st in self.dispatcher.stats().items():
            if "init_error" in st:
                parts.append(f"{name} FAILED")
                backends[name] = {"failed": st["init_error"]}
                continue
            sent = st.get("sent", st.get("accepted", 0))
            dropped = st.get("dropped", st.get("queue-full", 0) + st.get("not-ready", 0))
            parts.append(f"{name} sent {sent} dropped {dropped}")
            backends[name] = {"sent": sent, "dropped": dropped}
        fields: dict[str, Any] = {"event": "status", "uptime_s": round(up, 3),
                                  "messages_in": dict(c), "links": links,
                                  "backends": backends}
        if self.recorder is not None:
            rec = self.recorder
            lost = {k: v for k, v in rec.dropped.items() if v}
            parts.append(f"rec {rec.records}" + (" dropped " + " ".join(
                f"{k.replace('_', '-')} {v}" for k, v in lost.items()) if lost else ""))
            fields["recorded"] = rec.records
            fields["recorder_dropped"] = lost
        return " | ".join(parts), fields
