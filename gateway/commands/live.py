"""The live monitor's view model and its rendering (``aurora-gateway monitor``).

:class:`LiveState` is fed every message the sources produce and keeps what the view shows,
per vehicle (:class:`VehicleLive`, by ``msg.vehicle``: at most :data:`MAX_VEHICLES`, the
messages of any further one counted): the latest snapshot, the highest altitude seen, the
update rate over a short window and the age of the last update; and for the whole gateway
the frame rate, each source's link and the counters of every source, backend or endpoint the
command knows about.  One vehicle is *selected* (:meth:`LiveState.select`): the view shows a
row per vehicle and the detail of the selected one.  It is thread-safe (sources feed it from
their threads, the view reads it from the main thread) and takes ``now`` from its caller, so
it can be tested without a clock.

:func:`render` turns a state into a ``rich`` renderable for a terminal of any size;
:func:`plain_lines` into one ``key=value`` line per vehicle for a pipe or a log (no escape
codes).
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


#: Vehicles the monitor keeps at most; the messages of any further one are counted.
MAX_VEHICLES = 256
#: The name shown for messages that name no vehicle (none does from a gateway's sources).
UNNAMED = "vehicle"


class VehicleLive:
    """What the view knows of one vehicle (written under :class:`LiveState`'s lock)."""

    def __init__(self, name: str, window_s: float = RATE_WINDOW_S) -> None:
        self.name = name
        self.sm: SmUpdate | None = None
        self.status: Status | None = None
        self.vehicle: VehicleState | None = None
        self.position: Position | None = None
        self.battery: Battery | None = None
        self.link_stats: LinkStats | None = None
        self.max_altitude_m: float | None = None
        self.apogee_altitude_m: float | None = None
        self.updates = 0
        self.messages = 0
        self.last_update_at: float | None = None
        #: the source it is heard from (its link is that source's)
        self.origin = ""
        self.updates_rate = RateMeter(window_s)

    def altitude_m(self) -> float | None:
        sm, veh = self.sm, self.vehicle
        return sm.altitude_m if sm is not None else (veh.altitude_m if veh is not None else None)

    def climb_mps(self) -> float | None:
        sm, veh = self.sm, self.vehicle
        return sm.velocity_mps if sm is not None else (veh.climb_mps if veh is not None
                                                       else None)


class LiveState:
    """What the monitor shows, fed message by message (see the module docstring)."""

    def __init__(self, link_timeout_s: float = 3.0, window_s: float = RATE_WINDOW_S,
                 on_announce: Callable[[str], Any] | None = None) -> None:
        self.link_timeout_s = link_timeout_s
        self.on_announce = on_announce
        self.window_s = window_s
        self._lock = threading.Lock()
        #: name → what is known of it, in the order first heard
        self.vehicles: dict[str, VehicleLive] = {}
        self.vehicles_refused = 0
        self.selected: str | None = None  # None: the first vehicle
        self._rank: dict[str, int] = {}  # configured vehicle → its place (set_order)
        self.links: dict[str, bool] = {}
        self.messages = 0
        self.frames = 0
        self.crc_errors = 0
        self.endpoints: list[EndpointRow] = []
        #: the backends and sources of the gateways being followed, by gateway id
        self.remote: dict[str, list[EndpointRow]] = {}
        self.notes: deque[str] = deque(maxlen=NOTES_KEPT)
        self.title = "aurora-gateway monitor"
        self.sources_done = False
        self._frames_rate = RateMeter(window_s)

    # -- feeding (any thread) ---------------------------------------------------------------

    def feed(self, msg: Any, now: float) -> None:
        """Take one message received at ``now`` (monotonic seconds)."""
        said: list[str] = []
        with self._lock:
            self.messages += 1
            if isinstance(msg, LinkEvent):
                self.links[msg.source] = msg.up
            else:
                v = self._vehicle(msg)
                if v is not None:
                    self._take(v, msg, now, said)
            several = len(self.vehicles) > 1
        for text in said:
            if several:
                text = f"{msg.vehicle or UNNAMED} {text}"
            self.note(text)
            if self.on_announce is not None:
                self.on_announce(text)

    def _vehicle(self, msg: Any) -> VehicleLive | None:
        name = getattr(msg, "vehicle", "") or UNNAMED
        v = self.vehicles.get(name)
        if v is None:
            if len(self.vehicles) >= MAX_VEHICLES:
                self.vehicles_refused += 1
                return None
            v = self.vehicles[name] = VehicleLive(name, self.window_s)
        v.origin = getattr(msg, "origin", "") or v.origin
        return v

    @staticmethod
    def _take(v: VehicleLive, msg: Any, now: float, said: list[str]) -> None:
        v.messages += 1
        if isinstance(msg, SmUpdate):
            _take_sm(v, msg, now, said)
        elif isinstance(msg, Status):
            v.status = msg
        elif isinstance(msg, VehicleState):
            _take_vehicle(v, msg, now)
        elif isinstance(msg, Position):
            v.position = msg
        elif isinstance(msg, Battery):
            v.battery = msg
        elif isinstance(msg, LinkStats):
            v.link_stats = msg

    def set_counters(self, now: float, frames: int, crc_errors: int) -> None:
        """The wire decoders' totals (frames decoded, CRC failures) at ``now``."""
        with self._lock:
            self.frames = frames
            self.crc_errors = crc_errors
            self._frames_rate.sample(now, frames)
            for v in self.vehicles.values():
                v.updates_rate.sample(now, v.updates)

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

    # -- selecting (the view's thread) --------------------------------------------------------

    def set_order(self, configured: Iterable[str]) -> None:
        """The configured sources' vehicles, in order: they are listed first, in that order."""
        with self._lock:
            self._rank = {name: i for i, name in enumerate(configured)}

    def vehicle_list(self) -> list[VehicleLive]:
        """Every vehicle: the configured ones in their order (:meth:`set_order`), then the
        others in the order first heard."""
        with self._lock:
            rank, last = self._rank, len(self._rank)
            return sorted(self.vehicles.values(), key=lambda v: rank.get(v.name, last))

    def current(self) -> VehicleLive:
        """The selected vehicle (the first listed until one is selected; before any, an
        empty one)."""
        with self._lock:
            v = self.vehicles.get(self.selected) if self.selected is not None else None
        if v is None:
            v = next(iter(self.vehicle_list()), None)
        return v if v is not None else VehicleLive("–", self.window_s)

    def select(self, step: int) -> str:
        """Select the vehicle ``step`` rows down (negative: up), wrapping; its name."""
        names = [v.name for v in self.vehicle_list()]
        if not names:
            return "–"
        cur = self.current().name
        i = names.index(cur) if cur in names else 0
        self.selected = names[(i + step) % len(names)]
        return self.selected

    # -- reading -----------------------------------------------------------------------------

    def link_age_s(self, now: float, v: VehicleLive | None = None) -> float | None:
        """Seconds since the vehicle's (default: the selected one's) last update; None
        before the first."""
        v = v or self.current()
        return None if v.last_update_at is None else max(0.0, now - v.last_update_at)

    def link_up(self, now: float, v: VehicleLive | None = None) -> bool | None:
        """A vehicle's (default: the selected one's) link: its source's link by the link
        events, else (before any) up when an update came within the link timeout; None
        before anything was heard."""
        v = v or self.current()
        with self._lock:
            up = self.links.get(v.origin) if v.origin else None
            links = dict(self.links)
        if up is not None:
            return up
        if links and not v.origin:  # (a vehicle of no known source: every link)
            return all(links.values())
        age = self.link_age_s(now, v)
        return None if age is None else age < self.link_timeout_s

    def updates_per_s(self, now: float, v: VehicleLive | None = None) -> float | None:
        return (v or self.current()).updates_rate.rate(now)

    def frames_per_s(self, now: float) -> float | None:
        return self._frames_rate.rate(now)


def _take_sm(v: VehicleLive, msg: SmUpdate, now: float, said: list[str]) -> None:
    prev = v.sm
    v.sm = msg
    v.updates += 1
    v.last_update_at = now
    alt = msg.altitude_m
    if math.isfinite(alt) and (v.max_altitude_m is None or alt > v.max_altitude_m):
        v.max_altitude_m = alt
    if prev is not None and (prev.state, prev.sm_type) != (msg.state, msg.sm_type):
        name = msg.state_name
        text = name.lower().replace("_", " ")
        if name == "APOGEE" and v.max_altitude_m is not None:
            v.apogee_altitude_m = v.max_altitude_m
            text = f"apogee, {v.max_altitude_m:.0f} meters"
        said.append(text)


def _take_vehicle(v: VehicleLive, msg: VehicleState, now: float) -> None:
    v.vehicle = msg
    v.updates += 1
    v.last_update_at = now
    alt = msg.altitude_m
    if alt is not None and math.isfinite(alt) and (
            v.max_altitude_m is None or alt > v.max_altitude_m):
        v.max_altitude_m = alt


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


def _state_of(v: VehicleLive) -> tuple[str, bool | None]:
    if v.sm is not None:
        return v.sm.state_name, v.sm.armed
    if v.vehicle is not None:
        return v.vehicle.mode or "?", v.vehicle.armed
    if v.status is not None:
        return v.status.state_name, v.status.armed
    return "–", None


def _yes_no(v: bool | None) -> str:
    return "–" if v is None else ("yes" if v else "no")


def _link_text(up: bool | None) -> str:
    return "–" if up is None else ("up" if up else "DOWN")


def plain_line(state: LiveState, now: float, v: VehicleLive | None = None) -> str:
    """One ``key=value`` status line of a vehicle (default: the selected one), no escape
    codes, for a pipe or a log; it starts with ``vehicle=NAME``."""
    v = v or state.current()
    name, armed = _state_of(v)
    sm = v.sm
    parts = [f"vehicle={v.name}", f"state={name}", f"armed={_yes_no(armed)}",
             f"alt_m={_num(v.altitude_m())}", f"max_alt_m={_num(v.max_altitude_m)}",
             f"vs_mps={_num(v.climb_mps())}"]
    if sm is not None:
        parts += [f"acc_mps2={_num(sm.acceleration_mps2)}",
                  f"acc_vert_mps2={_num(sm.accel_vert_mps2)}"]
    if v.position is not None:
        p = v.position
        parts += [f"lat={p.lat_deg:.6f}", f"lon={p.lon_deg:.6f}"]
    if v.battery is not None:
        parts.append(f"batt_v={v.battery.voltage_v:.2f}")
    parts += [f"link={_link_text(state.link_up(now, v))}",
              f"age_s={_num(state.link_age_s(now, v))}",
              f"updates_per_s={_num(state.updates_per_s(now, v))}",
              f"frames_per_s={_num(state.frames_per_s(now))}",
              f"crc_errors={state.crc_errors}"]
    return " ".join(parts)


def plain_lines(state: LiveState, now: float) -> list[str]:
    """One :func:`plain_line` per vehicle, in :meth:`LiveState.vehicle_list`'s order (before
    any: one line of an empty vehicle, ``vehicle=–``)."""
    vehicles = state.vehicle_list() or [state.current()]
    return [plain_line(state, now, v) for v in vehicles]


def _vehicle_table(v: VehicleLive) -> Table:
    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold")
    t.add_column()
    name, armed = _state_of(v)
    t.add_row("state", Text(name, style="bold cyan"))
    t.add_row("armed", _yes_no(armed))
    sm, veh = v.sm, v.vehicle
    if sm is not None:
        t.add_row("altitude", _num(sm.altitude_m, unit=" m"))
        t.add_row("max altitude", _num(v.max_altitude_m, unit=" m"))
        if v.apogee_altitude_m is not None:
            t.add_row("apogee", _num(v.apogee_altitude_m, unit=" m"))
        t.add_row("vertical speed", _num(sm.velocity_mps, unit=" m/s"))
        t.add_row("acceleration", _num(sm.acceleration_mps2, unit=" m/s²"))
        t.add_row("vertical accel.", _num(sm.accel_vert_mps2, unit=" m/s²"))
        t.add_row("roll / pitch / yaw",
                  f"{_deg(sm.roll_rad)} / {_deg(sm.pitch_rad)} / {_deg(sm.yaw_rad)}")
    elif veh is not None:
        t.add_row("altitude", _num(veh.altitude_m, unit=" m"))
        t.add_row("max altitude", _num(v.max_altitude_m, unit=" m"))
        t.add_row("vertical speed", _num(veh.climb_mps, unit=" m/s"))
        t.add_row("roll / pitch / yaw",
                  f"{_deg(veh.roll_rad)} / {_deg(veh.pitch_rad)} / {_deg(veh.yaw_rad)}")
    if v.status is not None:
        h = v.status.health()
        ok = " ".join(k for k, on in h.items() if on and k != "armed") or "none"
        t.add_row("health", Text(ok, no_wrap=True, overflow="ellipsis"))
    if v.position is not None:
        p = v.position
        t.add_row("position", f"{p.lat_deg:.6f}, {p.lon_deg:.6f}")
        if p.satellites is not None:
            t.add_row("satellites", str(p.satellites))
    if v.battery is not None:
        b = v.battery
        extra = f" {b.remaining_pct}%" if b.remaining_pct is not None else ""
        t.add_row("battery", f"{b.voltage_v:.2f} V{extra}")
    return t


def _link_table(state: LiveState, v: VehicleLive, now: float) -> Table:
    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold")
    t.add_column()
    up = state.link_up(now, v)
    t.add_row("link", Text(_link_text(up), style="green" if up else "bold red"))
    t.add_row("last update", _num(state.link_age_s(now, v), unit=" s ago"))
    t.add_row("updates/s", _num(state.updates_per_s(now, v)))
    t.add_row("frames/s", _num(state.frames_per_s(now)))
    t.add_row("frames", str(state.frames))
    t.add_row("CRC errors", Text(str(state.crc_errors),
                                 style="bold red" if state.crc_errors else ""))
    with state._lock:
        links = dict(state.links)
    for name, ok in links.items():
        t.add_row(f"  {name}", _link_text(ok))
    ls = v.link_stats
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


#: Rows of the vehicles table shown at most (a window around the selected vehicle).
VEHICLE_ROWS = 8


def _vehicles_table(state: LiveState, selected: VehicleLive, now: float) -> Table:
    """A row per vehicle (at most :data:`VEHICLE_ROWS`, around the selected one, which is
    marked ``▶``)."""
    t = Table(expand=True, box=None, header_style="bold", pad_edge=False)
    for col, just in (("", "left"), ("vehicle", "left"), ("state", "left"),
                      ("armed", "left"), ("alt m", "right"), ("max m", "right"),
                      ("v/s m/s", "right"), ("link", "right"), ("age s", "right")):
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    vehicles = state.vehicle_list()
    i = next((k for k, v in enumerate(vehicles) if v is selected), 0)
    first = max(0, min(i - VEHICLE_ROWS // 2, len(vehicles) - VEHICLE_ROWS))
    for v in vehicles[first:first + VEHICLE_ROWS]:
        name, armed = _state_of(v)
        mark = v is selected
        t.add_row("▶" if mark else "", v.name, name, _yes_no(armed), _num(v.altitude_m()),
                  _num(v.max_altitude_m), _num(v.climb_mps()),
                  _link_text(state.link_up(now, v)), _num(state.link_age_s(now, v)),
                  style="bold" if mark and len(vehicles) > 1 else None)
    return t


def _vehicles_title(state: LiveState) -> str:
    n = len(state.vehicles)
    more = f", {state.vehicles_refused} messages of more refused" if state.vehicles_refused \
        else ""
    shown = f" (rows around the selected one of {n})" if n > VEHICLE_ROWS else ""
    return f"vehicles{shown}{more} · ↑/↓ or tab selects"


def render(state: LiveState, now: float) -> RenderableType:
    """The whole view at ``now``: a row per vehicle, the selected vehicle's detail and link
    side by side, then the table of sources, backends and endpoints, then the notes."""
    rows = state.table_rows()
    with state._lock:
        notes = list(state.notes)
    if state.sources_done:
        notes.append("the sources ended")
    v = state.current()
    vehicles = _vehicles_table(state, v, now)
    detail = _vehicle_table(v)
    link = _link_table(state, v, now)
    layout = Layout()
    layout.split_column(
        Layout(Text(f"{state.title}   (q quits)", style="bold", no_wrap=True,
                    overflow="ellipsis"), name="head", size=1),
        Layout(Panel(vehicles, title=_vehicles_title(state)), name="vehicles",
               size=vehicles.row_count + 3),
        Layout(name="top", size=max(detail.row_count, link.row_count) + 2),
        Layout(Panel(_endpoints_table(rows), title="sources · backends · endpoints"),
               name="table", size=len(rows) + 3),
        Layout(Panel(Text("\n".join(notes), no_wrap=True, overflow="ellipsis"),
                     title="events"), name="events"),
    )
    layout["top"].split_row(
        Layout(Panel(detail, title=f"vehicle {v.name}"), name="vehicle", ratio=3),
        Layout(Panel(link, title="link"), name="link", ratio=2),
    )
    return layout


def render_compact(state: LiveState, now: float) -> RenderableType:
    """The same content as :func:`render`, stacked, at its natural height (for printing
    once, or a console without a fixed height)."""
    rows = state.table_rows()
    v = state.current()
    return Group(Panel(_vehicles_table(state, v, now), title=_vehicles_title(state)),
                 Panel(_vehicle_table(v), title=f"vehicle {v.name}"),
                 Panel(_link_table(state, v, now), title="link"),
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
