"""What a run saw of each vehicle, kept as the messages pass, and per-flight recording names.

:class:`FlightSummary` is fed every message by :meth:`gateway.app.Gateway.ingest` (in the
sources' threads) and keeps, per vehicle (see :mod:`gateway.vehicles`): the states
seen in order, the launches, the highest altitude and when it was reached (apogee) — on the
flight computer's clock after liftoff and as the wall time it passed the gateway.  Only
``SmUpdate`` counts for the figures; a vehicle heard only in other telemetry (STATUS, relayed
frames, a MAVLink vehicle's state, position, battery) is listed with none, so the report
names every vehicle; anything else costs one type check.  At most :data:`MAX_VEHICLES`
vehicles are kept (the rest are counted in ``FlightSummary.others``).  Nothing re-reads the
recording.

A *flight* begins at liftoff (the first in-flight state after one that is not).  A vehicle
that arms on the pad again after a flight (LANDED or IDLE → ARMED) starts the next flight's
recording: :meth:`FlightSummary.feed` returns True for that update, and a gateway recording
into a directory starts that vehicle's next file (named by :func:`recording_name`) with it.
"""

from __future__ import annotations

import math
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gateway.model import Battery, Position, RawFrame, SmUpdate, Status, VehicleState

RECORDING_SUFFIX = ".aur"
#: the most vehicles a summary keeps (a source hearing many systems cannot grow it further)
MAX_VEHICLES = 256
#: telemetry that shows a vehicle is there (SmUpdate aside)
_HEARD = frozenset({Status, RawFrame, Position, Battery, VehicleState})
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


@dataclass
class VehicleSummary:
    """One vehicle's flight figures (altitudes in m; ``*_ms`` on the flight computer's clock)."""

    updates: int = 0
    states: list[str] = field(default_factory=list)  # in the order first seen
    launches: int = 0
    max_altitude_m: float | None = None
    apogee_wall: float | None = None  # Unix time the highest update passed the gateway
    apogee_after_launch_s: float | None = None  # None: reached before any liftoff was seen
    # -- tracking
    _state: tuple[int, int] | None = None
    _in_flight: bool = False
    _armed_on_pad: bool = False
    _flown_since_arm: bool = False
    _launch_ms: int | None = None

    def as_dict(self) -> dict[str, Any]:
        """The figures as JSON-friendly values."""
        return {"updates": self.updates, "states": list(self.states),
                "launches": self.launches, "max_altitude_m": self.max_altitude_m,
                "apogee_time": utc_iso(self.apogee_wall),
                "apogee_after_launch_s": self.apogee_after_launch_s}


class FlightSummary:
    """Flight figures per vehicle, fed message by message; cheap enough for the hot path."""

    def __init__(self, clock: Any = time.time) -> None:
        self.vehicles: dict[str, VehicleSummary] = {}
        #: messages of vehicles beyond :data:`MAX_VEHICLES`, not summarised
        self.others = 0
        self._clock = clock

    def _new(self, name: str) -> VehicleSummary | None:
        if len(self.vehicles) >= MAX_VEHICLES:
            self.others += 1
            return None
        v = self.vehicles[name] = VehicleSummary()
        return v

    def feed(self, msg: Any) -> bool:
        """Take one message; True when it is a vehicle arming on the pad after a flight (the
        start of its next flight's recording)."""
        if type(msg) is not SmUpdate:
            if type(msg) in _HEARD:
                name = msg.vehicle or msg.origin
                if name and name not in self.vehicles:
                    self._new(name)
            return False
        name = msg.vehicle or msg.origin
        v = self.vehicles.get(name)
        if v is None:
            v = self._new(name)
            if v is None:
                return False
        v.updates += 1
        key = (msg.sm_type, msg.state)
        new_flight = False
        if key != v._state:
            v._state = key
            name = msg.state_name
            if name not in v.states:
                v.states.append(name)
            in_flight = msg.in_flight
            if in_flight and not v._in_flight:
                v.launches += 1
                v._launch_ms = msg.timestamp_ms
                v._flown_since_arm = True
            v._in_flight = in_flight
        armed_on_pad = msg.armed and msg.on_pad
        if armed_on_pad and not v._armed_on_pad:
            new_flight = v._flown_since_arm
            v._flown_since_arm = False
        v._armed_on_pad = armed_on_pad
        alt = msg.altitude_m
        if (v.max_altitude_m is None or alt > v.max_altitude_m) and math.isfinite(alt):
            v.max_altitude_m = alt
            v.apogee_wall = self._clock()
            v.apogee_after_launch_s = (None if v._launch_ms is None
                                       else (msg.timestamp_ms - v._launch_ms) / 1000.0)
        return new_flight

    def as_dict(self) -> dict[str, Any]:
        """Every vehicle's figures, keyed by its name (in the order first heard)."""
        return {name: v.as_dict() for name, v in self.vehicles.items()}


def utc_iso(t: float | None) -> str | None:
    """Unix time as ISO-8601 UTC to the millisecond (None stays None)."""
    if t is None:
        return None
    from datetime import UTC, datetime  # here: a start needs none of it (~1 ms)

    return datetime.fromtimestamp(t, tz=UTC).isoformat(timespec="milliseconds")


def summary_lines(flights: dict[str, Any]) -> list[str]:
    """The end-of-run report's lines for :meth:`FlightSummary.as_dict`'s figures."""
    lines = []
    for name, v in flights.items():
        alt = v["max_altitude_m"]
        if alt is None:
            text = "no altitude"
        else:
            text = f"max altitude {alt:.1f} m"
            after = v["apogee_after_launch_s"]
            when = (v["apogee_time"] or "")[11:19]
            text += (f" at T+{after:.1f} s ({when} UTC)" if after is not None
                     else f" at {when} UTC (before any liftoff)")
        lines.append(f"flight {name}: {v['launches']} launch{'es' if v['launches'] != 1 else ''}"
                     f", {text}, {v['updates']} updates; states "
                     f"{' '.join(v['states']) or 'none'}")
    return lines


#: what a counter of frames failing their check is called: ``crc_failures`` (the wire
#: decoder), ``crc_errors`` (MAVLink endpoints), ``bad_checksum`` (XBee API frames) …
_CHECK_WORDS = ("crc", "checksum")


def _check_failures(d: dict[str, Any]) -> int | None:
    """The sum of ``d``'s counters of frames failing their CRC or checksum, nested tables
    included; None when it has none."""
    n: int | None = None
    for k, v in d.items():
        if isinstance(v, dict):
            sub = _check_failures(v)
            if sub is not None:
                n = (n or 0) + sub
        elif any(w in k for w in _CHECK_WORDS) and isinstance(v, int) \
                and not isinstance(v, bool):
            n = (n or 0) + v
    return n


def crc_errors(sources: dict[str, dict[str, Any]],
               backends: dict[str, dict[str, Any]] | None = None) -> dict[str, int]:
    """Per link, the frames that failed their CRC or checksum: every source (0 when it counts
    none), then every backend that counts any (a CRSF receiver's, XBee's, MAVLink's
    endpoints'), a backend named like a source as ``NAME (backend)``."""
    out = {name: _check_failures(st) or 0 for name, st in sources.items()}
    for name, st in (backends or {}).items():
        n = _check_failures(st)
        if n is not None:
            out[f"{name} (backend)" if name in out else name] = n
    return out


def safe_name(name: str) -> str:
    """``name`` made safe for a file name: runs of other characters than letters, digits,
    ``.``, ``_`` and ``-`` become one ``_`` (``/dev/ttyUSB0`` → ``dev_ttyUSB0``)."""
    return _UNSAFE.sub("_", name).strip("_.") or "gateway"


def recording_name(started: float, name: str, suffix: str = RECORDING_SUFFIX) -> str:
    """``<UTC start, 2026-11-23T14-02-11>-<name>.aur`` (a replayed recording's name loses its
    own ``.aur``: ``replay:a.aur`` → ``…-replay_a.aur``); ``suffix``: another kind of file
    (``.tlog``)."""
    from datetime import UTC, datetime

    stamp = datetime.fromtimestamp(started, tz=UTC).strftime("%Y-%m-%dT%H-%M-%S")
    base = safe_name(name)
    if base.endswith(RECORDING_SUFFIX) and len(base) > len(RECORDING_SUFFIX):
        base = base[: -len(RECORDING_SUFFIX)]
    return f"{stamp}-{base}{suffix}"


def new_recording(directory: str | Path, started: float, name: str,
                  suffix: str = RECORDING_SUFFIX) -> Path:
    """Create ``directory`` (and its parents) and an empty, new recording file in it named by
    :func:`recording_name`; a name already taken (two runs in one second) gets ``-2``,
    ``-3`` … before the suffix.  The file is created exclusively, so no run appends to
    another's."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    base = recording_name(started, name, suffix)[: -len(suffix)]
    for n in range(1, 1000):
        path = d / (base + (f"-{n}" if n > 1 else "") + suffix)
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            continue
        os.close(fd)
        return path
    raise FileExistsError(f"{d}: every name for {base}{suffix} is taken")
