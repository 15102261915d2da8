"""Console backend: one human-readable line per update, rate-limited, for people watching.

Lines go through a :class:`~gateway.io.port.PortEngine`, so a stalled terminal or a full pipe
never blocks the dispatcher: lines are dropped (and counted) instead.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.backend import Backend, Outcome, Routes
from gateway.io.port import PortEngine
from gateway.model import LinkEvent, RawFrame, SmUpdate, Status
from gateway.options import Flag, Options, option


class _StreamTransport:
    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def write(self, data: bytes) -> None:
        self._stream.write(data)
        self._stream.flush()

    def read(self, size: int = 1) -> bytes:
        return b""

    def close(self) -> None:
        pass  # never close the process's stdout


#: vehicles whose last state and line time are kept (more: printed unthrottled, a bound on what
#: a source naming vehicles at will can make the console keep)
MAX_VEHICLES = 256


def format_sm_update(m: SmUpdate) -> str:
    return (
        f"t={m.timestamp_ms / 1000:10.3f}s {m.state_name:<10} {'ARMED' if m.armed else 'safe '}"
        f" alt {m.altitude_m:8.1f} m  vel {m.velocity_mps:7.1f} m/s"
        f"  acc {m.acceleration_mps2:6.1f} m/s²  rpy {math.degrees(m.roll_rad):6.1f}"
        f" {math.degrees(m.pitch_rad):6.1f} {math.degrees(m.yaw_rad):6.1f}°"
    )


def format_status(m: Status) -> str:
    bad = [k for k, ok in m.health().items() if not ok and k != "armed"]
    health = "all ok" if not bad else "NOT " + ",".join(bad)
    return f"t={m.timestamp_ms / 1000:10.3f}s STATUS {m.state_name:<10} {health}"


@dataclass(frozen=True, kw_only=True)
class ConsoleOptions(Options):
    """``[backends.console]`` (this module is light: it is also where the flags come from)."""

    TITLE: ClassVar[str] = "console backend"
    interval_s: float = option(1.0, "least time between update lines (state changes always "
                               "print)", minimum=0,
                               flag=Flag("--console-interval", metavar="S"))
    stream: str = option("stdout", "where lines go", choices=("stdout", "stderr"))
    status: bool = option(False, "print STATUS heartbeats too")


class ConsoleBackend(Backend):
    NAME = "console"
    OPTIONS = ConsoleOptions
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = {}

    def __init__(self, options: ConsoleOptions | None = None, name: str | None = None,
                 out: Any = None) -> None:
        super().__init__(name)
        options = options or ConsoleOptions()
        self.interval_s = options.interval_s
        self.show_status = options.status
        self._out = out if out is not None else getattr(sys, options.stream).buffer
        #: per vehicle: (its last state, when its last update line was printed)
        self._last: dict[str, tuple[tuple[int, int] | None, float]] = {}
        self.engine = PortEngine(lambda: _StreamTransport(self._out), name=self.name,
                                 queue_depth=64)

    def init(self) -> None:
        self.engine.start()
        self.engine.wait_connected(1.0)

    def close(self) -> None:
        self.engine.drain(0.3)
        self.engine.close(0.3)

    def _line(self, text: str) -> Outcome:
        return self.engine.submit((text + "\n").encode())

    def routes(self) -> Routes:
        return (Routes().on(SmUpdate, self.send_sm_update).on(Status, self.send_status)
                .on(RawFrame, self.send_raw).on(LinkEvent, self.on_link))

    def send_sm_update(self, msg: SmUpdate) -> Outcome:
        """One line per vehicle per ``interval_s`` (and at each of its state changes), led by
        the vehicle's name."""
        now = time.monotonic()
        key = (msg.sm_type, msg.state)
        vehicle = msg.vehicle or msg.origin
        last_state, last_line = self._last.get(vehicle, (None, -math.inf))
        if key == last_state and now - last_line < self.interval_s:
            return Outcome.THROTTLED
        if key != last_state and last_state is not None:
            self._line(f"--- {vehicle}: state {msg.state_name}")
        if len(self._last) < MAX_VEHICLES or vehicle in self._last:
            self._last[vehicle] = (key, now)
        return self._line(f"{vehicle} {format_sm_update(msg)}")

    def send_status(self, msg: Status) -> Outcome:
        return (self._line(f"{msg.vehicle or msg.origin} {format_status(msg)}")
                if self.show_status else Outcome.ACCEPTED)

    def send_raw(self, msg: RawFrame) -> Outcome:
        return self._line(f"frame type 0x{msg.type:02X} len {len(msg.payload)} from "
                          f"{msg.vehicle or msg.origin}: {msg.payload[:16].hex()}")

    def on_link(self, ev: LinkEvent) -> Outcome:
        if ev.up:
            return self._line(f"*** link {ev.source} UP")
        return self._line(f"*** link {ev.source} DOWN after {ev.silence_s:.1f} s of silence")

    def stats(self) -> dict[str, Any]:
        s = self.engine.stats
        return {"sent": s.sent_frames, "dropped": s.dropped, "errors": s.errors,
                "link": int(self.engine.connected),
                "dropped_queue_full": s.dropped_queue_full,
                "dropped_not_ready": s.dropped_not_ready}
