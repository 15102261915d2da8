"""``python -m backends.crsf.monitor URL``: watch a CRSF stream as an EdgeTX radio shows it.

Attach it to the pty the CRSF backend prints (or to the other end of a serial link): it
decodes every frame and shows the EdgeTX sensors (``FM``, ``Alt``, ``VSpd``, ``Ptch`` …)
with EdgeTX's units and precision.  ``--summary`` prints, at the end, what each sensor showed
in each flight phase (each flight-mode text, in order).  ``--link-stats-hz`` makes it play the
receiver too, sending link-statistics frames back to the gateway.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from backends.crsf.decoder import Decoder
from backends.crsf.frames import (
    AccelGyro,
    Airspeed,
    Attitude,
    BaroAltitude,
    Battery,
    FlightMode,
    Gps,
    LinkStatistics,
    Record,
    Temperatures,
    Vario,
    Voltages,
    encode,
)
from gateway.io.transport import TransportError, open_serial
from gateway.signals import Stopper


def _trunc_div(a: int, b: int) -> int:
    """C integer division (truncates toward zero), as EdgeTX computes."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b > 0) else -q


def _q(x: float, scale: float) -> int:
    return math.floor(x * scale + 0.5) if x >= 0 else -math.floor(-x * scale + 0.5)



def _known(*sensors: tuple[str, float | None, str]) -> Iterator[tuple[str, float, str]]:
    """The (name, value, unit) sensors whose value is known (not None)."""
    for name, value, unit in sensors:
        if value is not None:
            yield name, value, unit

def edgetx_sensors(rec: Record) -> Iterator[tuple[str, float | str, str]]:
    """(sensor name, value, unit) as EdgeTX displays the fields of ``rec`` (fields that are
    unknown on the wire, all-0xFF, are skipped as EdgeTX skips them)."""
    if isinstance(rec, FlightMode):
        yield "FM", rec.text, ""
    elif isinstance(rec, Attitude):
        for name, v in (("Ptch", rec.pitch_rad), ("Roll", rec.roll_rad), ("Yaw", rec.yaw_rad)):
            if v is not None:  # wire: 100 µrad; EdgeTX: value / 10 → mrad, shown as rad
                yield name, _trunc_div(_q(v, 10000), 10) / 1000, "rad"
    elif isinstance(rec, BaroAltitude):
        yield from _known(("Alt", rec.altitude_m, "m"), ("VSpd", rec.vspeed_mps, "m/s"))
    elif isinstance(rec, Vario):
        yield from _known(("VSpd", rec.vspeed_mps, "m/s"))
    elif isinstance(rec, Gps):
        yield from _known(("GPS lat", rec.lat_deg, "deg"), ("GPS lon", rec.lon_deg, "deg"),
                          ("GSpd", rec.groundspeed_kmh, "km/h"), ("Hdg", rec.heading_deg, "°"),
                          ("GAlt", rec.altitude_m, "m"), ("Sats", rec.satellites, ""))
    elif isinstance(rec, Battery):
        yield from _known(("RxBt", rec.voltage_v, "V"), ("Curr", rec.current_a, "A"),
                          ("Capa", rec.capacity_mah, "mAh"), ("Bat%", rec.remaining_pct, "%"))
    elif isinstance(rec, Airspeed):
        yield from _known(("ASpd", rec.speed_kmh, "km/h"))
    elif isinstance(rec, Voltages):
        for i, v in enumerate(rec.volts):
            if v is not None:
                yield f"Volt{rec.source_id}.{i}", v, "V"
    elif isinstance(rec, Temperatures):
        for i, v in enumerate(rec.temps_c):
            if v is not None:
                yield f"Tmp{rec.source_id}.{i}", v, "°C"
    elif isinstance(rec, AccelGyro):
        yield "IMU", "(not shown by EdgeTX)", ""


_PRECISION = {"rad": 3, "m": 2, "m/s": 2, "km/h": 1, "V": 2, "A": 1, "°": 2, "°C": 1,
              "deg": 6}


def fmt(value: float | str, unit: str) -> str:
    if isinstance(value, str):
        return value
    p = _PRECISION.get(unit, 0)
    return f"{value:.{p}f}{unit and ' ' + unit}"


#: Flight phases kept for the summary; a stream whose flight-mode text changes more often
#: than that runs on in the last one (counted in ``RadioView.phases_merged``).
MAX_PHASES = 1000


@dataclass
class Shown:
    """What one sensor showed in a phase: its last value, and its numeric range."""

    last: float | str
    lo: float = math.inf
    hi: float = -math.inf

    def add(self, value: float | str) -> None:
        self.last = value
        if not isinstance(value, str):
            self.lo = min(self.lo, value)
            self.hi = max(self.hi, value)


@dataclass
class Phase:
    """What the sensors showed while the flight mode read ``mode`` (a range per sensor, not
    every value: a monitor left running for hours keeps the same memory)."""

    mode: str
    values: dict[str, Shown] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    frames: int = 0


_ORDER = ("Alt", "VSpd", "Ptch", "Roll", "Yaw", "GPS lat", "GPS lon", "GSpd", "Hdg", "GAlt",
          "Sats", "RxBt", "Curr", "Capa", "Bat%", "ASpd")


def _order(name: str) -> tuple[int, str]:
    return (_ORDER.index(name) if name in _ORDER else len(_ORDER), name)


class RadioView:
    """The sensors an EdgeTX radio would show, per flight phase."""

    def __init__(self) -> None:
        self.current: dict[str, tuple[float | str, str]] = {}
        self.phases: list[Phase] = [Phase("(before the first flight mode)")]
        self.phases_merged = 0
        self.frames = 0

    def update(self, rec: Record) -> str | None:
        """Apply one record; returns the new flight-mode text when it changed."""
        self.frames += 1
        changed = None
        if isinstance(rec, FlightMode) and rec.text != self.phases[-1].mode:
            if len(self.phases) < MAX_PHASES:
                self.phases.append(Phase(rec.text))
            else:
                self.phases_merged += 1
            changed = rec.text
        phase = self.phases[-1]
        phase.frames += 1
        for name, value, unit in edgetx_sensors(rec):
            self.current[name] = (value, unit)
            if name != "FM":
                shown = phase.values.get(name)
                if shown is None:
                    shown = phase.values[name] = Shown(value)
                shown.add(value)
                phase.units[name] = unit
        return changed

    def line(self) -> str:
        return "  ".join(f"{k} {fmt(v, u)}" for k, (v, u) in self.current.items())

    def summary(self) -> str:
        rows = []
        for ph in self.phases:
            if not ph.frames:
                continue
            parts = []
            for name, shown in sorted(ph.values.items(), key=lambda kv: _order(kv[0])):
                unit = ph.units[name]
                if shown.lo > shown.hi:  # no number
                    parts.append(f"{name} {shown.last}")
                elif shown.lo == shown.hi:
                    parts.append(f"{name} {fmt(shown.lo, unit)}")
                else:
                    parts.append(f"{name} {fmt(shown.lo, unit)} … {fmt(shown.hi, unit)}")
            rows.append(f"FM {ph.mode:<14} ({ph.frames:3d} frames)  " + ", ".join(parts))
        if self.phases_merged:
            rows.append(f"({self.phases_merged} more flight-mode changes, beyond {MAX_PHASES} "
                        "phases, ran on in the last one)")
        return "\n".join(rows)


def _link_stats_frame() -> bytes:
    return encode(LinkStatistics(-52, -61, 100, 9, 0, 7, 3, -48, 100, 11))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m backends.crsf.monitor",
                                description="Show a CRSF telemetry stream as an EdgeTX radio "
                                "would (sensor names, units, precision).")
    p.add_argument("url", help="serial port or pyserial URL (e.g. the pty the backend logs)")
    p.add_argument("--baud", type=int, default=420000)
    p.add_argument("--duration", type=float, help="stop after S seconds")
    p.add_argument("--until", metavar="TEXT", action="append", default=[],
                   help="stop once the flight mode has shown TEXT this many times "
                        "(repeat the flag); e.g. --until IDLE* --until IDLE* for one flight")
    p.add_argument("--summary", action="store_true",
                   help="print what each sensor showed in each flight phase at the end")
    p.add_argument("--quiet", action="store_true", help="no live lines")
    p.add_argument("--link-stats-hz", type=float, default=0.0,
                   help="also send link statistics back at this rate (play the receiver)")
    args = p.parse_args(argv)
    try:
        port: Any = open_serial(args.url, args.baud, timeout=0.05)
    except TransportError as exc:
        print(f"monitor: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    stopper = Stopper(stop).install()
    dec, view = Decoder(), RadioView()
    start = last_line = last_stats = time.monotonic()
    until = list(args.until)
    try:
        while not stop.is_set():
            now = time.monotonic()
            if args.duration is not None and now - start >= args.duration:
                break
            if args.link_stats_hz > 0 and now - last_stats >= 1.0 / args.link_stats_hz:
                port.write(_link_stats_frame())
                last_stats = now
            for rec in dec.feed(port.read(max(1, port.in_waiting))):
                changed = view.update(rec)
                if changed is not None:
                    if not args.quiet:
                        print(f"[{now - start:7.2f}s] FM → {changed}", flush=True)
                    if until and changed == until[0]:
                        until.pop(0)
                        if not until:
                            stop.set()
            if not args.quiet and now - last_line >= 1.0 and view.current:
                print(f"[{now - start:7.2f}s] {view.line()}", flush=True)
                last_line = now
    finally:
        port.close()
        stopper.restore()
    if args.summary:
        print(view.summary())
    s = dec.stats
    print(f"monitor: {s.frames} frames, {s.crc_failures} CRC errors, {s.bad_lengths} bad "
          f"lengths, {s.bytes_skipped} bytes skipped", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
