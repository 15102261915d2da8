"""MAVLink in: a MAVLink vehicle (ArduPilot, PX4, or another Aurora gateway) as a source.

The source runs a small router (:mod:`.router`) whose local node is :class:`VehicleListener`,
a ground-station-like component that decodes only what it uses from the vehicles it hears —
their heartbeats, attitude, altitude, position and battery — and turns it into gateway
messages, one gateway vehicle per MAVLink system (``<the source's vehicle>-<system id>``):

* :class:`~gateway.model.VehicleState` (armed, mode name, attitude, altitude, climb);
* :class:`~gateway.model.Position` (GLOBAL_POSITION_INT, with GPS_RAW_INT's fix and satellites);
* :class:`~gateway.model.Battery` (BATTERY_STATUS, else SYS_STATUS's battery fields);
* :class:`~gateway.model.SmUpdate` / :class:`~gateway.model.Status` from AURORA_SM_UPDATE /
  AURORA_STATUS, so one gateway can feed another over MAVLink losslessly.

Mode names come from the vehicle's own AVAILABLE_MODES answers (what QGroundControl uses),
else from the classic ArduPilot/PX4 tables, else ``MODE_<n>``.  Extra ``endpoints`` are
routed to and from the vehicle, so a ground station can share the link.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from backends.mavlink import signing
from backends.mavlink.dialect import mav
from backends.mavlink.endpoints import Endpoint, parse_endpoint
from backends.mavlink.hub import GCS, VEHICLE, MavlinkHub
from backends.mavlink.options import MAV_COMP_ID_ONBOARD_COMPUTER, MavlinkSourceOptions
from backends.mavlink.router import Router
from backends.mavlink.translate import (
    VIA_MAVLINK,
    RateGate,
    sm_update_from_mavlink,
    status_from_mavlink,
)
from gateway import vehicles
from gateway.backend import GatewayContext
from gateway.io.ioloop import IoLoop, Timer
from gateway.model import Battery, Position, VehicleState
from gateway.sources import Sink, Source

log = logging.getLogger(__name__)

#: The listener's preferred system id: not 255, the ground stations' (ArduPilot's GCS
#: failsafe counts any heartbeat from SYSID_MYGCS, so ours must not keep it quiet when the
#: real ground station is gone); downwards from here to the first one nobody uses.
AUTO_SYSID = 250
_GCS_TYPES = frozenset({mav.MAV_TYPE_GCS, mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_TYPE_GIMBAL,
                        mav.MAV_TYPE_ADSB, mav.MAV_TYPE_CAMERA, mav.MAV_TYPE_ANTENNA_TRACKER})

# Classic custom_mode tables (for firmware that does not answer AVAILABLE_MODES).
_ARDUCOPTER = {0: "STABILIZE", 1: "ACRO", 2: "ALT_HOLD", 3: "AUTO", 4: "GUIDED", 5: "LOITER",
               6: "RTL", 7: "CIRCLE", 9: "LAND", 11: "DRIFT", 13: "SPORT", 14: "FLIP",
               15: "AUTOTUNE", 16: "POSHOLD", 17: "BRAKE", 18: "THROW", 19: "AVOID_ADSB",
               20: "GUIDED_NOGPS", 21: "SMART_RTL", 22: "FLOWHOLD", 23: "FOLLOW", 24: "ZIGZAG",
               25: "SYSTEMID", 26: "AUTOROTATE", 27: "AUTO_RTL"}
_ARDUPLANE = {0: "MANUAL", 1: "CIRCLE", 2: "STABILIZE", 3: "TRAINING", 4: "ACRO", 5: "FBWA",
              6: "FBWB", 7: "CRUISE", 8: "AUTOTUNE", 10: "AUTO", 11: "RTL", 12: "LOITER",
              13: "TAKEOFF", 14: "AVOID_ADSB", 15: "GUIDED", 17: "QSTABILIZE", 18: "QHOVER",
              19: "QLOITER", 20: "QLAND", 21: "QRTL", 22: "QAUTOTUNE", 23: "QACRO",
              24: "THERMAL", 25: "LOITER_ALT_QLAND"}
_ARDUROVER = {0: "MANUAL", 1: "ACRO", 3: "STEERING", 4: "HOLD", 5: "LOITER", 6: "FOLLOW",
              7: "SIMPLE", 8: "DOCK", 9: "CIRCLE", 10: "AUTO", 11: "RTL", 12: "SMART_RTL",
              15: "GUIDED"}
_PX4_MAIN = {1: "MANUAL", 2: "ALTCTL", 3: "POSCTL", 4: "AUTO", 5: "ACRO", 6: "OFFBOARD",
             7: "STABILIZED", 8: "RATTITUDE"}
_PX4_AUTO = {1: "AUTO_READY", 2: "AUTO_TAKEOFF", 3: "AUTO_LOITER", 4: "AUTO_MISSION",
             5: "AUTO_RTL", 6: "AUTO_LAND", 8: "AUTO_FOLLOW", 9: "AUTO_PRECLAND"}
_PLANES = frozenset({mav.MAV_TYPE_FIXED_WING, mav.MAV_TYPE_VTOL_DUOROTOR,
                     mav.MAV_TYPE_VTOL_QUADROTOR, mav.MAV_TYPE_VTOL_TILTROTOR})
_ROVERS = frozenset({mav.MAV_TYPE_GROUND_ROVER, mav.MAV_TYPE_SURFACE_BOAT})


def classic_mode_name(autopilot: int, vehicle_type: int, base_mode: int, custom_mode: int) -> str:
    """A mode name from the well-known ArduPilot and PX4 tables; ``MODE_<n>`` otherwise."""
    if base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        if autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA:
            table = (_ARDUPLANE if vehicle_type in _PLANES
                     else _ARDUROVER if vehicle_type in _ROVERS else _ARDUCOPTER)
            name = table.get(custom_mode)
            if name:
                return name
        elif autopilot == mav.MAV_AUTOPILOT_PX4:
            main = (custom_mode >> 16) & 0xFF
            sub = (custom_mode >> 24) & 0xFF
            if main == 4 and sub in _PX4_AUTO:
                return _PX4_AUTO[sub]
            if main in _PX4_MAIN:
                return _PX4_MAIN[main]
    return f"MODE_{custom_mode}"


#: At most this many vehicles followed by one source; the systems heard beyond it are ignored
#: (counted ``systems_ignored``).
MAX_SYSTEMS = 32


class FollowedSystem:
    """What the listener knows of one vehicle it follows (a MAVLink system), and the gateway
    vehicle it is (``<source's vehicle>-<system id>``)."""

    def __init__(self, sysid: int, vehicle: str, rate_hz: float) -> None:
        self.sysid = sysid
        self.vehicle = vehicle
        #: ``via`` of every message about it: the vehicle's MAVLink system
        self.via = f"{VIA_MAVLINK}{sysid}"
        self.vehicle_type = 0
        self.autopilot = 0
        self.base_mode = 0
        self.custom_mode: int | None = None
        self.armed = False
        self.mode_names: dict[int, str] = {}
        self.attitude: tuple[float, float, float] | None = None
        self.altitude_m: float | None = None
        self.climb_mps: float | None = None
        self.gps: Any = None
        self.saw_battery_status = False
        self.requested = False
        self.heard = 0
        self.state_gate = RateGate(rate_hz)
        self.position_gate = RateGate(rate_hz)

    def mode_name(self) -> str:
        cm = self.custom_mode or 0
        name = self.mode_names.get(cm)
        if name:
            return name
        return classic_mode_name(self.autopilot, self.vehicle_type, self.base_mode, cm)


class VehicleListener:
    """The source's local MAVLink node: decodes the telemetry of the vehicles it hears into
    gateway messages, one gateway vehicle per MAVLink system (sans-I/O: messages go to
    ``emit``; requests to the vehicles are returned as replies).

    A system is followed from its first autopilot HEARTBEAT (component 1, not a ground
    station's or a peripheral's type): every one (``target_system`` 0, at most
    :data:`MAX_SYSTEMS`) or only ``target_system``.  Each is kept apart (state, mode names,
    rate limits) and named :func:`gateway.vehicles.system_vehicle` of ``stem`` and its id.

    What must not be missed is decoded as it arrives (``CONSUMED``: heartbeats, mode names,
    batteries, the Aurora messages); the telemetry that is only ever shown at ``rate_hz`` is
    read from the router's mailbox (``LATEST``): the latest of each, a few times a second."""

    CONSUMED: frozenset[int] = frozenset({
        mav.MAVLINK_MSG_ID_HEARTBEAT, mav.MAVLINK_MSG_ID_AVAILABLE_MODES,
        mav.MAVLINK_MSG_ID_BATTERY_STATUS,
        mav.MAVLINK_MSG_ID_AURORA_SM_UPDATE, mav.MAVLINK_MSG_ID_AURORA_STATUS,
    })
    LATEST: frozenset[int] = frozenset({
        mav.MAVLINK_MSG_ID_SYS_STATUS, mav.MAVLINK_MSG_ID_ATTITUDE,
        mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, mav.MAVLINK_MSG_ID_VFR_HUD,
        mav.MAVLINK_MSG_ID_ALTITUDE, mav.MAVLINK_MSG_ID_GPS_RAW_INT,
    })
    _ANY_COMPONENT = frozenset({mav.MAVLINK_MSG_ID_AURORA_SM_UPDATE,
                                mav.MAVLINK_MSG_ID_AURORA_STATUS})
    #: Our HEARTBEAT's type (the router tells our own frames coming back by it).
    heartbeat_type = mav.MAV_TYPE_ONBOARD_CONTROLLER

    def __init__(self, emit: Callable[[Any], None], origin: str, *, sysid: int = AUTO_SYSID,
                 compid: int = MAV_COMP_ID_ONBOARD_COMPUTER, target_system: int = 0,
                 rate_hz: float = 10.0, request_streams: bool = True,
                 clock: Callable[[], float] = time.monotonic, stem: str = "") -> None:
        self.emit = emit
        self.origin = origin
        self.sysid = sysid
        self.compid = compid
        self.consumed = self.CONSUMED
        self.latest = self.LATEST
        self.target_system = target_system  # 0: every autopilot heard
        self.request_streams = request_streams
        self.clock = clock
        self.rate_hz = rate_hz
        #: the stem of the vehicles' names (the source's vehicle)
        self.stem = stem or vehicles.derive_name(origin, fallback="mavlink")
        self.systems: dict[int, FollowedSystem] = {}
        self.systems_ignored = 0
        self.heard = 0

    def _system(self, sysid: int, compid: int, msg: Any) -> FollowedSystem | None:
        """The followed system a message is from (None: not one we follow)."""
        s = self.systems.get(sysid)
        if s is None:
            if (self.target_system and sysid != self.target_system) or not (
                    msg.get_msgId() == mav.MAVLINK_MSG_ID_HEARTBEAT and compid == 1
                    and msg.type not in _GCS_TYPES
                    and msg.autopilot != mav.MAV_AUTOPILOT_INVALID):
                return None
            if len(self.systems) >= MAX_SYSTEMS:
                self.systems_ignored += 1
                return None
            s = self.systems[sysid] = FollowedSystem(
                sysid, vehicles.system_vehicle(self.stem, sysid), self.rate_hz)
            log.info("%s: following vehicle %d as %s", self.origin, sysid, s.vehicle)
        if compid == 1 or msg.get_msgId() in self._ANY_COMPONENT:  # a gateway's Aurora part
            return s
        return None

    def handle(self, msg: Any, src_sysid: int, src_compid: int) -> list[Any]:
        s = self._system(src_sysid, src_compid, msg)
        if s is None:
            return []
        self.heard += 1
        s.heard += 1
        name = _HANDLERS.get(msg.get_msgId())
        if name is None:
            return []
        result: list[Any] = getattr(self, name)(s, msg)
        return result

    # -- per message -----------------------------------------------------------------------------

    def _heartbeat(self, s: FollowedSystem, m: Any) -> list[Any]:
        changed = (m.custom_mode != s.custom_mode
                   or bool(m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED) != s.armed)
        s.vehicle_type, s.autopilot = m.type, m.autopilot
        s.base_mode, s.custom_mode = m.base_mode, m.custom_mode
        s.armed = bool(m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
        if changed:
            self._emit_state(s, force=True)
        if s.requested or not self.request_streams:
            return []
        s.requested = True
        t, c = s.sysid, 1
        return [
            # Ask for the mode table (newer ArduPilot and PX4 answer; others ACK unsupported).
            mav.MAVLink_command_long_message(t, c, mav.MAV_CMD_REQUEST_MESSAGE, 0,
                                             mav.MAVLINK_MSG_ID_AVAILABLE_MODES, 0, 0, 0, 0, 0,
                                             0),
            # ArduPilot streams on request (SRx rates); PX4 ignores it and streams anyway.
            mav.MAVLink_request_data_stream_message(t, c, mav.MAV_DATA_STREAM_ALL, 10, 1),
        ]

    def _available_modes(self, s: FollowedSystem, m: Any) -> list[Any]:
        name = m.mode_name if isinstance(m.mode_name, str) else m.mode_name.decode(errors="replace")
        if name:
            s.mode_names[m.custom_mode] = name
        return []

    def _attitude(self, s: FollowedSystem, m: Any) -> list[Any]:
        s.attitude = (m.roll, m.pitch, m.yaw)
        self._emit_state(s)
        return []

    def _emit_state(self, s: FollowedSystem, force: bool = False) -> None:
        if s.custom_mode is None:
            return  # no heartbeat yet: armed and mode unknown
        if not s.state_gate.ready(self.clock()) and not force:
            return
        r, p, y = s.attitude if s.attitude is not None else (None, None, None)
        self.emit(VehicleState(s.armed, s.mode_name(), s.custom_mode, r, p, y,
                               s.altitude_m, s.climb_mps, origin=self.origin, via=s.via,
                               vehicle=s.vehicle))

    def _altitude(self, s: FollowedSystem, m: Any) -> list[Any]:
        if math.isfinite(m.altitude_relative):
            s.altitude_m = m.altitude_relative
        return []

    def _vfr_hud(self, s: FollowedSystem, m: Any) -> list[Any]:
        s.climb_mps = m.climb
        return []

    def _gps_raw_int(self, s: FollowedSystem, m: Any) -> list[Any]:
        s.gps = m
        return []

    def _global_position_int(self, s: FollowedSystem, m: Any) -> list[Any]:
        s.altitude_m = m.relative_alt / 1000.0
        if s.climb_mps is None:
            s.climb_mps = -m.vz / 100.0
        if not s.position_gate.ready(self.clock()):
            return []
        gs = math.hypot(m.vx, m.vy) / 100.0
        course = (m.hdg / 100.0) if m.hdg != 0xFFFF else None
        g = s.gps
        self.emit(Position(m.lat / 1e7, m.lon / 1e7, m.alt / 1000.0, m.relative_alt / 1000.0, gs,
                           course, g.satellites_visible if g is not None else None,
                           g.fix_type if g is not None else None, origin=self.origin, via=s.via,
                           vehicle=s.vehicle))
        return []

    def _battery_status(self, s: FollowedSystem, m: Any) -> list[Any]:
        s.saw_battery_status = True
        cells = [v for v in m.voltages if v != 0xFFFF]
        ext = [v for v in getattr(m, "voltages_ext", []) or [] if v]
        volts = (sum(cells) + sum(ext)) / 1000.0 if cells else math.nan
        self.emit(Battery(volts,
                          m.current_battery / 100.0 if m.current_battery != -1 else None,
                          float(m.current_consumed) if m.current_consumed != -1 else None,
                          m.battery_remaining if m.battery_remaining != -1 else None,
                          m.id, origin=self.origin, via=s.via, vehicle=s.vehicle))
        return []

    def _sys_status(self, s: FollowedSystem, m: Any) -> list[Any]:
        if s.saw_battery_status or m.voltage_battery == 0xFFFF:
            return []
        self.emit(Battery(m.voltage_battery / 1000.0,
                          m.current_battery / 100.0 if m.current_battery != -1 else None, None,
                          m.battery_remaining if m.battery_remaining != -1 else None, 0,
                          origin=self.origin, via=s.via, vehicle=s.vehicle))
        return []

    def _aurora_sm_update(self, s: FollowedSystem, m: Any) -> list[Any]:
        self.emit(sm_update_from_mavlink(m, self.origin)._replace(via=s.via, vehicle=s.vehicle))
        return []

    def _aurora_status(self, s: FollowedSystem, m: Any) -> list[Any]:
        self.emit(status_from_mavlink(m, self.origin)._replace(via=s.via, vehicle=s.vehicle))
        return []


_HANDLERS = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: "_heartbeat",
    mav.MAVLINK_MSG_ID_AVAILABLE_MODES: "_available_modes",
    mav.MAVLINK_MSG_ID_ATTITUDE: "_attitude",
    mav.MAVLINK_MSG_ID_ALTITUDE: "_altitude",
    mav.MAVLINK_MSG_ID_VFR_HUD: "_vfr_hud",
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: "_gps_raw_int",
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "_global_position_int",
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: "_battery_status",
    mav.MAVLINK_MSG_ID_SYS_STATUS: "_sys_status",
    mav.MAVLINK_MSG_ID_AURORA_SM_UPDATE: "_aurora_sm_update",
    mav.MAVLINK_MSG_ID_AURORA_STATUS: "_aurora_status",
}


class MavlinkSource(Source):
    """A MAVLink vehicle as a gateway source (``[[sources]] type = "mavlink"``).

    The vehicle's endpoint (``url``) and any extra ``endpoints`` share the gateway's MAVLink
    router with the MAVLink backend's endpoints (see :mod:`.hub`): the vehicle's traffic is
    routed to every ground station and theirs back, by mavlink-router's rules."""

    NAME = "mavlink"
    OPTIONS = MavlinkSourceOptions
    NAME_FORMAT = "mavlink:{url}"
    YIELDS_SYSTEMS = True  # one vehicle per system heard, <vehicle>-<system id>

    @classmethod
    def works_alone(cls, options: dict[str, Any]) -> bool:
        """With ``endpoints`` it routes the vehicle to them: a router needs no backend."""
        return bool(options.get("endpoints"))

    def __init__(self, options: MavlinkSourceOptions, name: str | None = None) -> None:
        super().__init__(name)
        self.vehicle_spec = parse_endpoint(options.url)
        self.extra_specs = [parse_endpoint(e) for e in options.endpoints]
        self.heartbeat_hz = options.heartbeat_hz
        self.rate_hz = options.rate_hz
        self.queue_depth = options.queue_depth
        self.signing_key: bytes | None = None
        if options.signing_key_file:
            self.signing_key = signing.key_from_file(options.signing_key_file)
        elif options.signing_passphrase:
            self.signing_key = signing.key_from_passphrase(options.signing_passphrase)
        self._pending: deque[Any] = deque()
        self._emit_scheduled = False
        self.listener = VehicleListener(self._queue, self.name,
                                        sysid=options.sysid or AUTO_SYSID,
                                        compid=options.compid,
                                        target_system=options.target_system,
                                        rate_hz=options.rate_hz,
                                        request_streams=options.request_streams)
        self.hub: MavlinkHub | None = None
        self.router: Router | None = None
        self.loop: IoLoop | None = None
        self.endpoints: list[Endpoint] = []
        self.emitted = 0
        self.started = threading.Event()
        self.start_error: str | None = None
        self._timers: list[Timer] = []

    def attach(self, context: GatewayContext) -> None:
        super().attach(context)
        hub = MavlinkHub.of(context)
        hub.expect(VEHICLE)  # before the backend's first tick
        hub.stems.add(self.vehicle)  # one vehicle per system heard: none of its own

    def _queue(self, msg: Any) -> None:  # the loop thread, under the router lock
        self._pending.append(msg)
        if not self._emit_scheduled and self.loop is not None:
            self._emit_scheduled = True
            self.loop.call_soon(self._emit_pending)  # outside the router lock

    def _emit_pending(self) -> None:  # the loop thread
        self._emit_scheduled = False
        pending = self._pending
        while pending:
            self.emit(pending.popleft())
            self.emitted += 1

    def _heartbeat(self) -> None:
        router = self.router
        if router is not None:
            router.broadcast([mav.MAVLink_heartbeat_message(
                mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0,
                mav.MAV_STATE_ACTIVE, 3)], self.listener)

    def _collect(self) -> None:
        router = self.router
        if router is not None:
            router.collect(self.listener)

    # -- life cycle: the endpoints' engines and timers run on the hub's loop; messages are
    # -- emitted from its thread (the sink never blocks) ------------------------------------------

    def start(self, sink: Sink) -> None:
        if self._sink is not None:
            return
        self._sink = sink
        hub = MavlinkHub.of(self.context)
        listener = self.listener
        listener.stem = self.vehicle  # (named by the gateway after construction)
        try:
            hub.join(listener, VEHICLE, step=-1, signing_key=self.signing_key)
        except ValueError as exc:
            self._fail(str(exc))
            return
        self.hub, self.loop, self.router = hub, hub.loop, hub.router
        try:
            self.endpoints = hub.open([self.vehicle_spec], VEHICLE, self.queue_depth)
            self.endpoints += hub.open(self.extra_specs, GCS, self.queue_depth)
        except OSError as exc:
            self._fail(str(exc))
            return
        loop = hub.loop
        self._timers.append(loop.call_every(1.0 / self.rate_hz, self._collect))
        if self.heartbeat_hz > 0:
            self._timers.append(loop.call_every(1.0 / self.heartbeat_hz, self._heartbeat))
        log.info("source %s: following the vehicle on %s as system %d", self.name,
                 self.vehicle_spec.text, hub.router.claim(listener))
        self.started.set()

    def _fail(self, why: str) -> None:
        self.start_error = why
        log.error("source %s: %s", self.name, why)
        self._shut_down()
        self.started.set()

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        self._shut_down(timeout)

    def halt(self) -> None:
        """(request_stop) Nothing here: the endpoints live on the hub's loop; stop() leaves."""

    def _shut_down(self, timeout: float = 1.0) -> None:
        hub, self.hub = self.hub, None
        self.loop = None
        if hub is not None:
            for t in self._timers:
                t.cancel()
            hub.leave(self.listener, self.endpoints, timeout)
        self.done.set()

    def stats(self) -> dict[str, Any]:
        router = self.router
        with router.lock if router is not None else contextlib.nullcontext():
            eps = {ep.name: ep.stats() for ep in self.endpoints}
            systems = {str(s.sysid): s.vehicle for s in self.listener.systems.values()}
        return {"emitted": self.emitted, "target_system": self.listener.target_system,
                "sysid": self.listener.sysid, "systems": systems,
                "systems_ignored": self.listener.systems_ignored, "endpoints": eps}
