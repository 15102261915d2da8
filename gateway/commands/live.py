"""The live monitor's view model and its rendering (``aurora-gateway monitor``).

:class:`LiveState` is fed every message the sources produce and keeps what the view shows:
the latest vehicle snapshot, the highest altitude seen, update and frame rates over a short
window, each link's state and the age of the last update, and the counters of every source,
backend or endpoint the command knows about.  It is thread-safe (sources feed it from their
threads, the view reads it from the main thread) and takes ``now`` from its caller, so it
can be tested without a clock.

:func:`render` turns a state into a ``rich`` renderable for a terminal of any size;
:func:`plain_line` into one ``key=value`` line for a pipe or a log (no escape codes).
:class:`Speaker` says state changes aloud through ``espeak-ng`` without ever waiting for it.
"""

from __future__ import annotations

import logging
import math
import subprocess
import threading
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from rich.console import Group, RenderableType
from rich.layout import Layout
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    SmUpdate,
    Status,
    VehicleState,
)

RATE_WINDOW_S = 3.0
#: How many log lines and announcements the view keeps.
NOTES_KEPT = 8


class RateMeter:
    """Events per second over the last ``window_s`` seconds, from a running total."""

    __slots__ = ("_samples", "window_s")

    def __init__(self, window_s: float = RATE_WINDOW_S) -> None:
        self.window_s = window_s
        self._samples: deque[tuple[float, int]] = deque()

    def sample(self, now: float, total: int) -> None:
        """Record the running total at ``now``."""
        s = self._samples
        s.append((now, total))
        while len(s) > 2 and now - s[1][0] >= self.window_s:
            s.popleft()

    def rate(self, now: float) -> float | None:
        """Events per second across the window; None before two samples."""
        s = self._samples
        if len(s) < 2:
            return None
        (t0, n0), (t1, n1) = s[0], s[-1]
        if t1 <= t0 or now - t1 > self.window_s:  # no span, or nobody sampled lately
            return None
        return (n1 - n0) / (t1 - t0)


@dataclass(frozen=True)
class EndpointRow:
    """One line of the backends/endpoints table; None = not known for this one."""

    name: str
    received: int | None = None
    sent: int | None = None
    dropped: int | None = None
    errors: int | None = None
    clients: int | None = None
    link: bool | None = None


def _first_int(st: Mapping[str, Any], keys: Iterable[str]) -> int | None:
    for k in keys:
        v = st.get(k)
        if isinstance(v, bool):
            return int(v)
        if isinstance(v, int):
            return v
    return None


def endpoint_row(name: str, st: Mapping[str, Any]) -> EndpointRow:
    """A table row from a plug-in's ``stats()`` (the counters every backend reports, see
    :mod:`gateway.backend`, and the usual names sources and endpoints use); ``dropped`` is
    the plug-in's own total, else the sum of its ``dropped_<reason>`` counters and ``lost``."""
    dropped = _first_int(st, ("dropped",))
    if dropped is None:  # a source's reasons, and what a Zenoh source lost on the way
        parts = [v for k, v in st.items() if isinstance(v, int) and not isinstance(v, bool)
                 and (k.startswith("dropped_") or k == "lost")]
        dropped = sum(parts) if parts else None
    link = st.get("link")
    return EndpointRow(
        name=name,
        received=_first_int(st, ("received", "frames", "messages", "emitted", "rx")),
        sent=_first_int(st, ("sent", "tx")),
        dropped=dropped,
        errors=_first_int(st, ("errors", "crc_failures", "put_errors")),
        clients=_first_int(st, ("clients", "connected", "peers")),
        link=None if link is None else bool(link),
    )


class LiveState:
    """What the monitor shows, fed message by message (see the module docstring)."""

    def __init__(self, link_timeout_s: float = 3.0, window_s: float = RATE_WINDOW_S,
                 on_announce: Callable[[str], Any] | None = None) -> None:
        self.link_timeout_s = link_timeout_s
        self.on_announce = on_announce
        self._lock = threading.Lock()
        self.sm: SmUpdate | None = None
        self.status: Status | None = None
        self.vehicle: VehicleState | None = None
        self.position: Position | None = None
        self.battery: Battery | None = None
        self.link_stats: LinkStats | None = None
        self.links: dict[str, bool] = {}
        self.max_altitude_m: float | None = None
        self.apogee_altitude_m: float | None = None
        self.updates = 0
        self.messages = 0
        self.frames = 0
        self.crc_errors = 0
        self.last_update_at: float | None = None
        self.endpoints: list[EndpointRow] = []
        #: the backends and sources of the gateways being followed, by gateway id
        self.remote: dict[str, list[EndpointRow]] = {}
        self.notes: deque[str] = deque(maxlen=NOTES_KEPT)
        self.title = "aurora-gateway monitor"
        self.sources_done = False
        self._updates_rate = RateMeter(window_s)
        self._frames_rate = RateMeter(window_s)

    # -- feeding (any thread) ---------------------------------------------------------------

    def feed(self, msg: Any, now: float) -> None:
        """Take one message received at ``now`` (monotonic seconds)."""
        said: list[str] = []
        with self._lock:
            self.messages += 1
            if isinstance(msg, SmUpdate):
                self._take_sm(msg, now, said)
            elif isinstance(msg, Status):
                self.status = msg
            elif isinstance(msg, LinkEvent):
                self.links[msg.source] = msg.up
            elif isinstance(msg, VehicleState):
                self._take_vehicle(msg, now)
            elif isinstance(msg, Position):
                self.position = msg
            elif isinstance(msg, Battery):
                self.battery = msg
            elif isinstance(msg, LinkStats):
                self.link_stats = msg
        for text in said:
            self.note(text)
            if self.on_announce is not None:
                self.on_announce(text)

    def _take_sm(self, msg: SmUpdate, now: float, said: list[str]) -> None:
        prev = self.sm
        self.sm = msg
        self.updates += 1
        self.last_update_at = now
        alt = msg.altitude_m
        if math.isfinite(alt) and (self.max_altitude_m is None or alt > self.max_altitude_m):
            self.max_altitude_m = alt
        if prev is not None and (prev.state, prev.sm_type) != (msg.state, msg.sm_type):
            name = msg.state_name
            text = name.lower().replace("_", " ")
            if name == "APOGEE" and self.max_altitude_m is not None:
                self.apogee_altitude_m = self.max_altitude_m
                text = f"apogee, {self.max_altitude_m:.0f} meters"
            said.append(text)

    def _take_vehicle(self, msg: VehicleState, now: float) -> None:
        self.vehicle = msg
        self.updates += 1
        self.last_update_at = now
        alt = msg.altitude_m
        if alt is not None and math.isfinite(alt) and (
                self.max_altitude_m is None or alt > self.max_altitude_m):
            self.max_altitude_m = alt

    def set_counters(self, now: float, frames: int, crc_errors: int) -> None:
        """The wire decoders' totals (frames decoded, CRC failures) at ``now``."""
        with self._lock:
            self.frames = frames
            self.crc_errors = crc_errors
            self._frames_rate.sample(now, frames)
            self._updates_rate.sample(now, self.updates)

    def set_endpoints(self, rows: Iterable[EndpointRow]) -> None:
        with self._lock:
            self.endpoints = list(rows)

    def set_remote(self, gateway: str, backends: Mapping[str, Any],
                   sources: Mapping[str, Any]) -> None:
        """A followed gateway's counters (its Zenoh backend publishes them): a row per source
        and backend, under the gateway's id."""
        rows = [EndpointRow(f"gateway {gateway}")]
        for group in (sources, backends):
            rows += [endpoint_row(f"  {name}", st) for name, st in group.items()
                     if isinstance(st, Mapping)]
        with self._lock:
            self.remote[gateway] = rows

    def table_rows(self) -> list[EndpointRow]:
        """This monitor's own rows, then every followed gateway's."""
        with self._lock:
            return list(self.endpoints) + [r for rows in self.remote.values() for r in rows]

    def note(self, text: str) -> None:
        """A line for the view's notes (a warning, what was said)."""
        with self._lock:
            self.notes.append(text)

    # -- reading -----------------------------------------------------------------------------

    def link_age_s(self, now: float) -> float | None:
        """Seconds since the last vehicle update; None before the first."""
        return None if self.last_update_at is None else max(0.0, now - self.last_update_at)

    def link_up(self, now: float) -> bool | None:
        """Up when every source's link is up (or, before any link event, an update came
        within the link timeout); None before anything was heard."""
        with self._lock:
            links = dict(self.links)
        if links:
            return all(links.values())
        age = self.link_age_s(now)
        return None if age is None else age < self.link_timeout_s

    def updates_per_s(self, now: float) -> float | None:
        return self._updates_rate.rate(now)

    def frames_per_s(self, now: float) -> float | None:
        return self._frames_rate.rate(now)


# -- formatting ---------------------------------------------------------------------------------

def _num(v: float | None, fmt: str = ".1f", unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    text = f"{v:{fmt}}"
    if text.startswith("-") and float(text) == 0:
        text = text[1:]  # -0.0: a rounded tiny negative reads as zero
    return text + unit


def _deg(rad: float | None) -> str:
    return "–" if rad is None else _num(math.degrees(rad), unit="°")


def _state_of(state: LiveState) -> tuple[str, bool | None]:
    if state.sm is not None:
        return state.sm.state_name, state.sm.armed
    if state.vehicle is not None:
        return state.vehicle.mode or "?", state.vehicle.armed
    if state.status is not None:
        return state.status.state_name, state.status.armed
    return "–", None


def _yes_no(v: bool | None) -> str:
    return "–" if v is None else ("yes" if v else "no")


def _link_text(up: bool | None) -> str:
    return "–" if up is None else ("up" if up else "DOWN")


def plain_line(state: LiveState, now: float) -> str:
    """One ``key=value`` status line (no escape codes), for a pipe or a log."""
    name, armed = _state_of(state)
    sm, veh = state.sm, state.vehicle
    alt = sm.altitude_m if sm is not None else (veh.altitude_m if veh is not None else None)
    vs = sm.velocity_mps if sm is not None else (veh.climb_mps if veh is not None else None)
    parts = [f"state={name}", f"armed={_yes_no(armed)}", f"alt_m={_num(alt)}",
             f"max_alt_m={_num(state.max_altitude_m)}", f"vs_mps={_num(vs)}"]
    if sm is not None:
        parts += [f"acc_mps2={_num(sm.acceleration_mps2)}",
                  f"acc_vert_mps2={_num(sm.accel_vert_mps2)}"]
    if state.position is not None:
        p = state.position
        parts += [f"lat={p.lat_deg:.6f}", f"lon={p.lon_deg:.6f}"]
    if state.battery is not None:
        parts.append(f"batt_v={state.battery.voltage_v:.2f}")
    parts += [f"link={_link_text(state.link_up(now))}",
              f"age_s={_num(state.link_age_s(now))}",
              f"updates_per_s={_num(state.updates_per_s(now))}",
              f"frames_per_s={_num(state.frames_per_s(now))}",
              f"crc_errors={state.crc_errors}"]
    return " ".join(parts)


def _vehicle_table(state: LiveState) -> Table:
    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold")
    t.add_column()
    name, armed = _state_of(state)
    t.add_row("state", Text(name, style="bold cyan"))
    t.add_row("armed", _yes_no(armed))
    sm, veh = state.sm, state.vehicle
    if sm is not None:
        t.add_row("altitude", _num(sm.altitude_m, unit=" m"))
        t.add_row("max altitude", _num(state.max_altitude_m, unit=" m"))
        if state.apogee_altitude_m is not None:
            t.add_row("apogee", _num(state.apogee_altitude_m, unit=" m"))
        t.add_row("vertical speed", _num(sm.velocity_mps, unit=" m/s"))
        t.add_row("acceleration", _num(sm.acceleration_mps2, unit=" m/s²"))
        t.add_row("vertical accel.", _num(sm.accel_vert_mps2, unit=" m/s²"))
        t.add_row("roll / pitch / yaw",
                  f"{_deg(sm.roll_rad)} / {_deg(sm.pitch_rad)} / {_deg(sm.yaw_rad)}")
    elif veh is not None:
        t.add_row("altitude", _num(veh.altitude_m, unit=" m"))
        t.add_row("max altitude", _num(state.max_altitude_m, unit=" m"))
        t.add_row("vertical speed", _num(veh.climb_mps, unit=" m/s"))
        t.add_row("roll / pitch / yaw",
                  f"{_deg(veh.roll_rad)} / {_deg(veh.pitch_rad)} / {_deg(veh.yaw_rad)}")
    if state.status is not None:
        h = state.status.health()
        ok = " ".join(k for k, v in h.items() if v and k != "armed") or "none"
        t.add_row("health", Text(ok, no_wrap=True, overflow="ellipsis"))
    if state.position is not None:
        p = state.position
        t.add_row("position", f"{p.lat_deg:.6f}, {p.lon_deg:.6f}")
        if p.satellites is not None:
            t.add_row("satellites", str(p.satellites))
    if state.battery is not None:
        b = state.battery
        extra = f" {b.remaining_pct}%" if b.remaining_pct is not None else ""
        t.add_row("battery", f"{b.voltage_v:.2f} V{extra}")
    return t


def _link_table(state: LiveState, now: float) -> Table:
    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold")
    t.add_column()
    up = state.link_up(now)
    t.add_row("link", Text(_link_text(up), style="green" if up else "bold red"))
    t.add_row("last update", _num(state.link_age_s(now), unit=" s ago"))
    t.add_row("updates/s", _num(state.updates_per_s(now)))
    t.add_row("frames/s", _num(state.frames_per_s(now)))
    t.add_row("frames", str(state.frames))
    t.add_row("CRC errors", Text(str(state.crc_errors),
                                 style="bold red" if state.crc_errors else ""))
    with state._lock:
        links = dict(state.links)
    for name, ok in links.items():
        t.add_row(f"  {name}", _link_text(ok))
    ls = state.link_stats
    if ls is not None:
        if ls.rssi_dbm is not None:
            t.add_row("RSSI", _num(ls.rssi_dbm, ".0f", " dBm"))
        if ls.link_quality_pct is not None:
            t.add_row("link quality", f"{ls.link_quality_pct} %")
    return t


def _endpoints_table(rows: list[EndpointRow]) -> Table:
    t = Table(expand=True, box=None, header_style="bold", pad_edge=False)
    for col, just in (("name", "left"), ("in", "right"), ("sent", "right"),
                      ("dropped", "right"), ("errors", "right"), ("clients", "right"),
                      ("link", "right")):
        t.add_column(col, justify=just)  # type: ignore[arg-type]

    def cell(v: int | None) -> str:
        return "–" if v is None else str(v)

    for r in rows:
        t.add_row(r.name, cell(r.received), cell(r.sent), cell(r.dropped), cell(r.errors),
                  cell(r.clients), _link_text(r.link))
    return t


def render(state: LiveState, now: float) -> RenderableType:
    """The whole view at ``now``: vehicle and link side by side, then the table of sources,
    backends and endpoints, then the notes."""
    rows = state.table_rows()
    with state._lock:
        notes = list(state.notes)
    if state.sources_done:
        notes.append("the sources ended")
    vehicle = _vehicle_table(state)
    link = _link_table(state, now)
    layout = Layout()
    layout.split_column(
        Layout(Text(f"{state.title}   (q quits)", style="bold", no_wrap=True,
                    overflow="ellipsis"), name="head", size=1),
        Layout(name="top", size=max(vehicle.row_count, link.row_count) + 2),
        Layout(Panel(_endpoints_table(rows), title="sources · backends · endpoints"),
               name="table", size=len(rows) + 3),
        Layout(Panel(Text("\n".join(notes), no_wrap=True, overflow="ellipsis"),
                     title="events"), name="events"),
    )
    layout["top"].split_row(
        Layout(Panel(vehicle, title="vehicle"), name="vehicle", ratio=3),
        Layout(Panel(link, title="link"), name="link", ratio=2),
    )
    return layout


def render_compact(state: LiveState, now: float) -> RenderableType:
    """The same content as :func:`render`, stacked, at its natural height (for printing
    once, or a console without a fixed height)."""
    rows = state.table_rows()
    return Group(Panel(_vehicle_table(state), title="vehicle"),
                 Panel(_link_table(state, now), title="link"),
                 Panel(_endpoints_table(rows), title="sources · backends · endpoints"))


# -- speech -------------------------------------------------------------------------------------

class Speaker:
    """Says short texts through a speech program (``espeak-ng TEXT``), one at a time.

    :meth:`say` starts the program and returns at once; while it is still speaking, a new
    text is dropped (counted), so a burst of state changes never queues up behind the voice
    and nothing waits for it."""

    def __init__(self, program: str,
                 popen: Callable[..., subprocess.Popen[bytes]] = subprocess.Popen) -> None:
        self.program = program
        self._popen = popen
        self._proc: subprocess.Popen[bytes] | None = None
        self._lock = threading.Lock()
        self.spoken = 0
        self.dropped = 0
        self.failed = 0

    def say(self, text: str) -> bool:
        """Start saying ``text``; False when busy (dropped) or the program failed to start."""
        with self._lock:
            proc = self._proc
            if proc is not None and proc.poll() is None:
                self.dropped += 1
                return False
            try:
                self._proc = self._popen([self.program, text], stdin=subprocess.DEVNULL,
                                         stdout=subprocess.DEVNULL,
                                         stderr=subprocess.DEVNULL)
            except OSError as exc:
                self.failed += 1
                if self.failed == 1:
                    logging.getLogger(__name__).warning("speech: %s: %s", self.program, exc)
                return False
            self.spoken += 1
            return True

    def close(self) -> None:
        """Reap a finished process; one still speaking is left to finish on its own."""
        with self._lock:
            if self._proc is not None:
                self._proc.poll()
