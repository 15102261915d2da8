"""``export RECORDING --format tlog``: the MAVLink stream a ground station would have received
live for a recording, as a telemetry log (:mod:`.tlog`).

The MAVLink backend's own translator makes it: one :class:`~.translate.AuroraVehicle` per
vehicle, with the system ids the backend gives them (``sysid`` on, in the order the vehicles
first appear; component 1, the AURORA_* messages from component 25), fed every message of
the recording as the backend's handlers feed it (what came from a MAVLink system is skipped:
live, its own frames were routed, not translated).  Its clock is the recording's: each
frame is stamped with the receive time of the message that made it, and the periodic
streams (HEARTBEAT with the state as custom mode, SYS_STATUS, EXTENDED_SYS_STATE …) are
polled every :data:`~.backend.POLL_S` of recording time between messages, as the backend's
timer polls them live, so a silence in the recording shows as the backend showed it
(heartbeats going on, the system status turning "uninit" after ``stale_after_s``).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from typing import Any, BinaryIO

from backends.mavlink.backend import POLL_S
from backends.mavlink.dialect import mav
from backends.mavlink.options import MavlinkOptions
from backends.mavlink.tlog import stamp
from backends.mavlink.translate import VIA_MAVLINK, AuroraVehicle
from gateway import __version__
from gateway.model import (
    Battery,
    LinkStats,
    Position,
    RcChannels,
    SmUpdate,
    Status,
    VehicleState,
)

#: A silence longer than this in a recording is polled once a second, not every POLL_S (the
#: periodic streams are 1 Hz: the same frames, a bounded cost for a recording left running).
LONG_GAP_S = 10.0


#: What the MAVLink backend's routes hand each message type to, on the vehicle's node.
HANDLERS: dict[type, Callable[[AuroraVehicle, Any], list[Any]]] = {
    SmUpdate: AuroraVehicle.on_sm_update, Status: AuroraVehicle.on_status,
    Position: AuroraVehicle.on_position, Battery: AuroraVehicle.on_battery,
    VehicleState: AuroraVehicle.on_vehicle_state, LinkStats: AuroraVehicle.on_link_stats,
    RcChannels: AuroraVehicle.on_rc_channels,
}


def translate(node: AuroraVehicle, msg: Any) -> list[Any]:
    """What the MAVLink backend's handler for ``msg``'s type makes of it (its routes)."""
    if getattr(msg, "via", "").startswith(VIA_MAVLINK):
        return []  # a MAVLink system's own: routed live, not repeated (the backend's skip)
    handler = HANDLERS.get(type(msg))
    return handler(node, msg) if handler is not None else []


class TlogExport:
    """Writes one recording's MAVLink stream to ``out``; see the module docstring."""

    def __init__(self, out: BinaryIO, vehicles: Iterable[str] = (),
                 options: MavlinkOptions | None = None, stretch: float = 1.0) -> None:
        self.out = out
        self.options = options or MavlinkOptions()
        #: the translator's clock: the recording's receive time, or for a recording made
        #: faster than real time that time stretched ``stretch`` times from its first message
        #: (the flight's own pace), so its rate-limited streams hold what the backend sends
        #: of a flight received in real time; frames stay stamped with receive times
        self.now = 0.0
        self.stretch = stretch
        self._t0: float | None = None
        self.nodes: dict[str, AuroraVehicle] = {}
        self._order: list[AuroraVehicle] = []
        self._encoders: dict[int, Any] = {}
        self._wanted = list(vehicles)
        self._next_tick: float | None = None
        #: frames written, by message name
        self.counts: Counter[str] = Counter()
        self.frames = 0

    def _node(self, name: str) -> AuroraVehicle:
        node = self.nodes.get(name)
        if node is None:
            if not name and self._order:
                return self._order[0]  # (what comes without a name: the first vehicle's)
            o = self.options
            sysid = (o.sysid - 1 + len(self._order)) % 254 + 1
            node = AuroraVehicle(sysid, o.compid, rates=o.rates(), stale_after_s=o.stale_after_s,
                                 pad_altitude_amsl_m=o.pad_altitude_amsl_m,
                                 version=__version__, clock=lambda: self.now, vehicle=name)
            self.nodes[name] = node
            self._order.append(node)
        return node

    def _received(self, now: float) -> float:
        """The receive time of the translator's time ``now``."""
        t0 = self._t0
        return now if t0 is None or self.stretch == 1.0 else t0 + (now - t0) / self.stretch

    def _write(self, node: AuroraVehicle, msgs: list[Any]) -> None:
        head = stamp(self._received(self.now))
        for msg in msgs:
            compid = node.component_of(msg)
            key = (node.sysid << 8) | compid
            m = self._encoders.get(key)
            if m is None:
                m = self._encoders[key] = mav.MAVLink(None, node.sysid, compid)
            buf = msg.pack(m)
            m.seq = (m.seq + 1) & 0xFF
            self.out.write(head + buf)
            self.counts[msg.get_type()] += 1
            self.frames += 1

    def _poll_until(self, t: float) -> None:
        """Every periodic stream due up to ``t``, at the times the backend's timer polls."""
        tick = self._next_tick
        if tick is None:
            tick = t
            for name in self._wanted:  # the configured vehicles: on the air from the start
                self.now = t
                self._node(name)
        while tick <= t:
            self.now = tick
            for node in self._order:
                out = node.poll()
                if out:
                    self._write(node, out)
            step = POLL_S if t - tick < LONG_GAP_S else 1.0
            tick += step
        self._next_tick = tick

    def feed(self, t: float, msg: Any) -> None:
        """One message of the recording, received at UNIX time ``t`` (in recording order)."""
        if self._t0 is None:
            self._t0 = t
        t = self._t0 + (t - self._t0) * self.stretch
        t = max(t, self.now)  # (a recording's times never go back; a file's never do)
        self._poll_until(t)
        self.now = t
        node = self._node(getattr(msg, "vehicle", ""))
        out = translate(node, msg)
        if out:
            self._write(node, out)


def time_compression(messages: Iterable[tuple[float, Any]]) -> tuple[float, float] | None:
    """(receive-time span, flight-computer span) in s of the first vehicle's SM updates when
    the recording was made much faster than real time (a simulator at ``--sim-speed 0``, a
    replay sped up): its rate-limited streams then hold only what the live backend would have
    let through in that short receive time.  None for a recording made in real time."""
    first: tuple[float, int] | None = None
    last: tuple[float, int] | None = None
    vehicle: str | None = None
    for t, msg in messages:
        if type(msg) is SmUpdate and vehicle in (None, msg.vehicle):
            vehicle = msg.vehicle
            if first is None:
                first = (t, msg.timestamp_ms)
            last = (t, msg.timestamp_ms)
    if first is None or last is None:
        return None
    rx, fc = last[0] - first[0], (last[1] - first[1]) / 1000.0
    return (rx, fc) if fc > 2 * rx + 1.0 else None


def write(messages: Iterable[tuple[float, Any]], out: BinaryIO, vehicles: Iterable[str] = (),
          options: MavlinkOptions | None = None) -> TlogExport:
    """Write the MAVLink stream of ``messages`` ((receive time, message), in recording order)
    to ``out``; ``vehicles``: the recording's, in order (their system ids).  A recording made
    faster than real time (:func:`time_compression`) is translated at the flight's own pace
    (``TlogExport.stretch``), its frames stamped with their receive times.  Returns the
    exporter (its ``counts``)."""
    messages = list(messages)
    fast = time_compression(messages)
    export = TlogExport(out, vehicles, options,
                        stretch=fast[1] / max(fast[0], 1e-3) if fast is not None else 1.0)
    for t, msg in messages:
        export.feed(t, msg)
    return export
