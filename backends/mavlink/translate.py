"""The rocket as a MAVLink vehicle: the gateway's messages in, MAVLink messages out (sans-I/O).

:class:`AuroraVehicle` keeps what it has heard of the rocket and builds pymavlink message
objects; it never touches a socket or a thread.  Three kinds of entry point, all returning the
messages to send:

* :meth:`AuroraVehicle.on_sm_update`, :meth:`~AuroraVehicle.on_status`,
  :meth:`~AuroraVehicle.on_position` … (one per gateway message type) — a message arrived:
  the event-driven streams (ATTITUDE, ALTITUDE, VFR_HUD, NAMED_VALUE_FLOAT, the
  dialect's AURORA_* messages, STATUSTEXT on a state change), each capped at its rate;
* :meth:`AuroraVehicle.poll` — the periodic streams due now (HEARTBEAT, SYS_STATUS,
  EXTENDED_SYS_STATE, AVAILABLE_MODES_MONITOR after a change of state machine);
* :meth:`AuroraVehicle.handle` — a request from a ground station (commands, mission and
  parameter protocol): the answers, for the link it came from.

QGroundControl requests no streams from a generic vehicle, so everything is streamed
unprompted; see ``shared/specs/mavlink.md`` for what QGC does with each message.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from backends.mavlink.dialect import mav
from backends.mavlink.options import DEFAULT_RATES
from dialects.states import ERROR_STATE, IN_FLIGHT, ON_PAD, SimpleState, state_name, state_names
from gateway.counters import Counters
from gateway.model import (
    Battery,
    LinkStats,
    Position,
    RcChannels,
    SmUpdate,
    Status,
    VehicleState,
)

MAV_COMP_ID_AUTOPILOT1 = 1
#: The component the AURORA_* dialect messages come from, with its own sequence numbers: a
#: ground station without the dialect skips them, and would count each one as a lost packet
#: of the autopilot component if they shared its sequence (MAV_COMP_ID_USER1).
AURORA_COMPID = 25
_AURORA_IDS = frozenset({mav.MAVLINK_MSG_ID_AURORA_SM_UPDATE, mav.MAVLINK_MSG_ID_AURORA_STATUS})
UINT8_MAX = 0xFF
UINT16_MAX = 0xFFFF
RC_CHANNELS_MAX = 18  # RC_CHANNELS carries chan1..chan18

# SYS_STATUS sensor bits the STATUS flags map to.
SENSORS_IMU = mav.MAV_SYS_STATUS_SENSOR_3D_GYRO | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
SENSORS_BARO = mav.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
SENSORS_LOG = mav.MAV_SYS_STATUS_LOGGING
SENSORS_PREARM = mav.MAV_SYS_STATUS_PREARM_CHECK
SENSORS_ALL = SENSORS_IMU | SENSORS_BARO | SENSORS_LOG | SENSORS_PREARM
# ... and those the rocket has once the gateway hears its position / its battery.
SENSORS_GPS = mav.MAV_SYS_STATUS_SENSOR_GPS
SENSORS_BATTERY = mav.MAV_SYS_STATUS_SENSOR_BATTERY
#: Every subsystem bit of MAV_SYS_STATUS_SENSOR (not EXTENSION_USED, a flag): health carries
#: each one that has not failed, as ArduPilot sets it, so a subsystem the rocket does not have
#: (a geofence: MAVProxy says "fence breach" when its health bit is clear) never reads failed.
SENSORS_NOT_FAILED = sum(
    bit for bit in mav.enums["MAV_SYS_STATUS_SENSOR"]
    if bit < mav.MAV_SYS_STATUS_EXTENSION_USED and bit & (bit - 1) == 0)

#: Messages whose rate ``MAV_CMD_SET_MESSAGE_INTERVAL`` may change (id → config key).
STREAMS: dict[int, str] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: "heartbeat_hz",
    mav.MAVLINK_MSG_ID_SYS_STATUS: "sys_status_hz",
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: "extended_sys_state_hz",
    mav.MAVLINK_MSG_ID_ATTITUDE: "attitude_hz",
    mav.MAVLINK_MSG_ID_ALTITUDE: "altitude_hz",
    mav.MAVLINK_MSG_ID_VFR_HUD: "vfr_hud_hz",
    mav.MAVLINK_MSG_ID_NAMED_VALUE_FLOAT: "named_value_hz",
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: "position_hz",
    mav.MAVLINK_MSG_ID_BATTERY_STATUS: "battery_hz",
    mav.MAVLINK_MSG_ID_AURORA_SM_UPDATE: "aurora_sm_update_hz",
    mav.MAVLINK_MSG_ID_AURORA_STATUS: "aurora_status_hz",
}


#: Messages a ground station may ask for with MAV_CMD_REQUEST_MESSAGE.
_REQUESTABLE = frozenset({
    mav.MAVLINK_MSG_ID_HEARTBEAT, mav.MAVLINK_MSG_ID_SYS_STATUS,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, mav.MAVLINK_MSG_ID_ATTITUDE,
    mav.MAVLINK_MSG_ID_ALTITUDE, mav.MAVLINK_MSG_ID_VFR_HUD,
    mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, mav.MAVLINK_MSG_ID_AVAILABLE_MODES,
    mav.MAVLINK_MSG_ID_AURORA_SM_UPDATE, mav.MAVLINK_MSG_ID_AURORA_STATUS,
})

_FLIGHT_SW_TYPE_OFFICIAL = 255  # FIRMWARE_VERSION_TYPE_OFFICIAL
_REORDER_WINDOW_MS = 5000


#: the gates an SM update passes (see AuroraVehicle.on_sm_update)
_SM_UPDATE_GATES = ("attitude_hz", "altitude_hz", "vfr_hud_hz", "named_value_hz",
                    "aurora_sm_update_hz")
#: RateGate.opens_at errs early by this much (a float's rounding never skips a send)
_GATE_EPS_S = 1e-6


class RateGate:
    """Lets events through at most ``hz`` times a second on average (0 = never): a token
    bucket holding 200 ms worth of tokens (at least 3), so updates bunched by scheduling
    jitter still all pass when they arrive no faster than ``hz`` over time."""

    __slots__ = ("_last", "_tokens", "burst", "hz")

    def __init__(self, hz: float) -> None:
        self.hz = 0.0
        self.burst = 3.0
        self._last: float | None = None
        self.set_rate(hz)
        self._tokens = self.burst

    def set_rate(self, hz: float) -> None:
        self.hz = max(0.0, hz)
        self.burst = max(3.0, 0.2 * self.hz)

    @property
    def enabled(self) -> bool:
        return self.hz > 0

    def opens_at(self) -> float:
        """When :meth:`ready` will next say yes (as of its last call; ``inf``: never).  A
        call before then says no and changes nothing that a later call would not: the
        tokens grow linearly up to ``burst``, so callers may skip it until then."""
        if self.hz <= 0:
            return math.inf
        if self._tokens >= 1.0 or self._last is None:
            return -math.inf
        return self._last + (1.0 - self._tokens) / self.hz - _GATE_EPS_S

    def advance(self, now: float) -> None:
        """What calls of :meth:`ready` skipped until ``now`` (all saying no) would have done:
        the tokens they would have added, at the rate they would have added them."""
        last = self._last
        if self.hz > 0 and last is not None and now > last:
            self._tokens = min(self.burst, self._tokens + (now - last) * self.hz)
            self._last = now

    def ready(self, now: float) -> bool:
        if self.hz <= 0:
            return False
        last, self._last = self._last, now
        if last is not None:
            self._tokens = min(self.burst, self._tokens + (now - last) * self.hz)
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False


class Periodic:
    """A fixed-rate schedule that does not drift (next = previous + period)."""

    __slots__ = ("next", "period")

    def __init__(self, hz: float, start: float) -> None:
        self.period = (1.0 / hz) if hz > 0 else math.inf
        self.next = start

    def set_rate(self, hz: float, now: float) -> None:
        self.period = (1.0 / hz) if hz > 0 else math.inf
        self.next = now

    def due(self, now: float) -> bool:
        if now < self.next:
            return False
        self.next += self.period
        if self.next < now:  # we were late (or the rate changed): restart from now
            self.next = now + self.period
        return True


_FLT_MAX = 3.4028234663852886e38


def f32(x: float) -> float:
    """``x`` made packable as a MAVLink ``float``: beyond float32's range it becomes ±inf
    (what a float32 conversion gives), instead of making the whole message fail to pack."""
    if x > _FLT_MAX or x < -_FLT_MAX:
        return math.copysign(math.inf, x)
    return x


def _version_word(version: str) -> int:
    parts = [int(p) if p.isdigit() else 0 for p in version.split(".")[:3]]
    parts += [0] * (3 - len(parts))
    major, minor, patch = (min(p, 255) for p in parts)
    return (major << 24) | (minor << 16) | (patch << 8) | _FLIGHT_SW_TYPE_OFFICIAL


def _text(s: str, n: int) -> bytes:
    return s.encode("ascii", "replace")[:n]


def landed_state(sm_type: int, state: int) -> int:
    """EXTENDED_SYS_STATE.landed_state for a state of the machine."""
    if sm_type == 0:
        s = state
        if s in (SimpleState.IDLE, SimpleState.ARMED, SimpleState.LANDED):
            return mav.MAV_LANDED_STATE_ON_GROUND
        if s == SimpleState.BOOST:
            return mav.MAV_LANDED_STATE_TAKEOFF
        if s in (SimpleState.BURNOUT, SimpleState.APOGEE):
            return mav.MAV_LANDED_STATE_IN_AIR
        if s in (SimpleState.MAIN, SimpleState.REDUNDANT):
            return mav.MAV_LANDED_STATE_LANDING
        return mav.MAV_LANDED_STATE_UNDEFINED
    if state in ON_PAD.get(sm_type, ()):
        return mav.MAV_LANDED_STATE_ON_GROUND
    if state in IN_FLIGHT.get(sm_type, ()):
        return mav.MAV_LANDED_STATE_IN_AIR
    return mav.MAV_LANDED_STATE_UNDEFINED


def system_status(sm_type: int, state: int, armed: bool, stale: bool) -> int:
    """HEARTBEAT.system_status: standby on the pad (and after landing), active in flight,
    emergency in the machine's ERROR state, uninitialised (state unknown) when no update has
    arrived for a while or ever."""
    if stale:
        return mav.MAV_STATE_UNINIT
    if ERROR_STATE.get(sm_type) == state:
        return mav.MAV_STATE_EMERGENCY
    if state in IN_FLIGHT.get(sm_type, ()):
        return mav.MAV_STATE_ACTIVE
    if sm_type in IN_FLIGHT:  # a known machine, not in flight: on the pad or landed
        return mav.MAV_STATE_STANDBY
    return mav.MAV_STATE_ACTIVE if armed else mav.MAV_STATE_STANDBY


@dataclass
class VehicleStats(Counters):
    """What the vehicle saw: gateway messages taken in, state changes, and what a GCS sent
    (commands, unsupported ones apart; parameter requests ignored; mission requests; RC
    overrides)."""

    updates: int = 0
    state_changes: int = 0
    commands: int = 0
    commands_unsupported: int = 0
    param_requests_ignored: int = 0
    mission_requests: int = 0
    rc_overrides: int = 0


class AuroraVehicle:
    """One rocket seen as a MAVLink system (``sysid``, component ``compid``)."""

    #: Message ids this node decodes when addressed to it (everything else is only routed).
    CONSUMED: frozenset[int] = frozenset({
        mav.MAVLINK_MSG_ID_COMMAND_LONG, mav.MAVLINK_MSG_ID_COMMAND_INT,
        mav.MAVLINK_MSG_ID_PARAM_REQUEST_LIST, mav.MAVLINK_MSG_ID_PARAM_REQUEST_READ,
        mav.MAVLINK_MSG_ID_PARAM_SET,
        mav.MAVLINK_MSG_ID_MISSION_REQUEST_LIST, mav.MAVLINK_MSG_ID_MISSION_COUNT,
        mav.MAVLINK_MSG_ID_MISSION_CLEAR_ALL, mav.MAVLINK_MSG_ID_MISSION_ACK,
        mav.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE, mav.MAVLINK_MSG_ID_MANUAL_CONTROL,
        mav.MAVLINK_MSG_ID_PING,
    })

    #: Our HEARTBEAT's type: how the router tells our own frames coming back from another
    #: vehicle that uses our system id.
    heartbeat_type = mav.MAV_TYPE_ROCKET

    def component_of(self, msg: Any) -> int:
        """The component a message of ours is sent from."""
        return AURORA_COMPID if msg.get_msgId() in _AURORA_IDS else self.compid

    def __init__(
        self,
        sysid: int = 1,
        compid: int = MAV_COMP_ID_AUTOPILOT1,
        rates: dict[str, float] | None = None,
        stale_after_s: float = 3.0,
        pad_altitude_amsl_m: float = 0.0,
        version: str = "0.0.0",
        clock: Callable[[], float] = time.monotonic,
        vehicle: str = "",
    ) -> None:
        self.sysid = sysid
        self.compid = compid
        #: the gateway's name of the vehicle this system is ("" for a backend on its own)
        self.vehicle = vehicle
        #: on the air: its id is claimed (see the backend)
        self.spoken = False
        self.consumed = self.CONSUMED
        self.stale_after_s = stale_after_s
        self.pad_altitude_amsl_m = pad_altitude_amsl_m
        self.version_word = _version_word(version)
        self.clock = clock
        self.stats = VehicleStats()
        self.default_rates = {**DEFAULT_RATES, **(rates or {})}
        #: called with the channels (µs, None = not given) of a ground station's RC override
        self.on_rc: Callable[[tuple[int | None, ...]], Any] | None = None
        self.rates = dict(self.default_rates)
        now = clock()
        self._start = now
        # state heard from the rocket
        self.sm: SmUpdate | None = None
        self.status: Status | None = None
        self.position: Position | None = None
        self.batteries: dict[int, Battery] = {}
        self.sm_type = 0
        self.state = 0
        self.armed = False
        self._state_key: tuple[int, int] | None = None
        self._state_ts: int | None = None
        self._last_heard: float | None = None
        self.modes_seq = 0
        self.vehicle_mode = ""  # the mode of a non-Aurora vehicle (VehicleState), by name
        # schedules
        r = self.rates
        self._heartbeat = Periodic(r["heartbeat_hz"], now)
        self._sys_status = Periodic(r["sys_status_hz"], now)
        self._ext_state = Periodic(r["extended_sys_state_hz"], now)
        self._modes_monitor = Periodic(0.3, now)
        self._gates = {key: RateGate(r[key]) for key in (
            "attitude_hz", "altitude_hz", "vfr_hud_hz", "named_value_hz", "position_hz",
            "battery_hz", "aurora_sm_update_hz", "aurora_status_hz", "radio_status_hz",
            "rc_channels_hz")}
        #: before this time none of an update's gates (_SM_UPDATE_GATES) can open: an update
        #: then only moves the state (the gates' calls, skipped, would change nothing)
        self._sm_gates_shut_until = -math.inf
        self._sm_at = -math.inf  # the last SM update's time

    # -- what we know ------------------------------------------------------------------------

    @property
    def stale(self) -> bool:
        return self._last_heard is None or self.clock() - self._last_heard > self.stale_after_s

    def _boot_ms(self) -> int:
        if self.sm is not None:
            return self.sm.timestamp_ms & 0xFFFFFFFF
        if self.status is not None:
            return self.status.timestamp_ms & 0xFFFFFFFF
        return int((self.clock() - self._start) * 1000) & 0xFFFFFFFF

    # -- periodic streams --------------------------------------------------------------------

    def heartbeat(self) -> Any:
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if self.armed:
            base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
        return mav.MAVLink_heartbeat_message(
            mav.MAV_TYPE_ROCKET, mav.MAV_AUTOPILOT_GENERIC, base, self.state & 0xFFFFFFFF,
            system_status(self.sm_type, self.state, self.armed, self.stale), 3)

    def sys_status(self) -> Any:
        """SYS_STATUS true to the rocket: present = what it has (the STATUS flags' sensors,
        GPS and battery once heard of), enabled = what it uses (the flags' sensors once a
        STATUS told their state: before that nothing is enabled, so nothing shows failed),
        health = every subsystem bit but those that failed."""
        present, enabled, failed = SENSORS_ALL, 0, 0
        st = self.status
        if st is not None:
            enabled = SENSORS_ALL
            failed = ((0 if st.imu_ok else SENSORS_IMU) | (0 if st.baro_ok else SENSORS_BARO)
                      | (0 if st.log_ready else SENSORS_LOG)
                      | (0 if (st.calibrated and st.imu_ok and st.baro_ok) else SENSORS_PREARM))
        if self.position is not None:
            present |= SENSORS_GPS
            enabled |= SENSORS_GPS
            fix = self.position.fix_type
            if fix is not None and fix < mav.GPS_FIX_TYPE_2D_FIX:
                failed |= SENSORS_GPS
        voltage_mv, current_ca, remaining = UINT16_MAX, -1, -1
        bat = self.batteries.get(0)
        if bat is not None:
            present |= SENSORS_BATTERY
            enabled |= SENSORS_BATTERY
            voltage_mv = min(round(bat.voltage_v * 1000), UINT16_MAX - 1)
            if bat.current_a is not None:
                current_ca = max(-1, min(round(bat.current_a * 100), 32767))
            if bat.remaining_pct is not None:
                remaining = max(-1, min(int(bat.remaining_pct), 100))
        return mav.MAVLink_sys_status_message(
            present, enabled, SENSORS_NOT_FAILED & ~failed, 0, voltage_mv, current_ca,
            remaining, 0, 0, 0, 0, 0, 0, 0, 0, 0)

    def extended_sys_state(self) -> Any:
        landed = (mav.MAV_LANDED_STATE_UNDEFINED if self._state_key is None
                  else landed_state(self.sm_type, self.state))
        return mav.MAVLink_extended_sys_state_message(mav.MAV_VTOL_STATE_UNDEFINED, landed)

    def poll(self) -> list[Any]:
        """Periodic messages due now (call often: every few tens of milliseconds)."""
        now = self.clock()
        out: list[Any] = []
        if self._heartbeat.due(now):
            out.append(self.heartbeat())
        if self._sys_status.due(now):
            out.append(self.sys_status())
        if self._ext_state.due(now):
            out.append(self.extended_sys_state())
        if self.modes_seq and self._modes_monitor.due(now):
            out.append(mav.MAVLink_available_modes_monitor_message(self.modes_seq & 0xFF))
        return out

    # -- event-driven streams ----------------------------------------------------------------

    # One entry point per gateway message type (the backend routes each type to its own):
    # each takes the message in and returns the messages it triggers now.

    def on_rc_channels(self, rc: RcChannels) -> list[Any]:
        """Commands the rocket's link received (an XBee air link's servo values): RC_CHANNELS,
        so a ground station shows what the rocket was told."""
        if not self._gates["rc_channels_hz"].ready(self.clock()):
            return []
        raw = [UINT16_MAX if v is None else max(0, min(UINT16_MAX - 1, v))
               for v in rc.channels_us[:RC_CHANNELS_MAX]]
        count = max((i + 1 for i, v in enumerate(rc.channels_us[:RC_CHANNELS_MAX])
                     if v is not None), default=0)
        raw += [UINT16_MAX] * (RC_CHANNELS_MAX - len(raw))
        return [mav.MAVLink_rc_channels_message(self._boot_ms(), count, *raw, UINT8_MAX)]

    def on_vehicle_state(self, v: VehicleState) -> list[Any]:
        """A vehicle that is not an Aurora state machine (e.g. a LibrePilot flight controller
        through the UAVTalk source) shown as this system: arming, its mode by name (spoken),
        attitude and altitude."""
        self.stats.updates += 1
        self._last_heard = now = self.clock()
        out: list[Any] = []
        if v.mode != self.vehicle_mode:
            self.vehicle_mode = v.mode
            out.append(mav.MAVLink_statustext_message(mav.MAV_SEVERITY_NOTICE,
                                                      _text(f"#{v.mode}", 50), 0, 0))
        if v.armed != self.armed:
            self.armed = v.armed
            out.append(self.heartbeat())
        g = self._gates
        if (v.roll_rad is not None and v.pitch_rad is not None and v.yaw_rad is not None
                and g["attitude_hz"].ready(now)):
            out.append(mav.MAVLink_attitude_message(self._boot_ms(), f32(v.roll_rad),
                                                    f32(v.pitch_rad), f32(v.yaw_rad),
                                                    0.0, 0.0, 0.0))
        if v.altitude_m is not None and g["altitude_hz"].ready(now):
            alt = f32(v.altitude_m)
            out.append(mav.MAVLink_altitude_message(self._boot_ms() * 1000, alt,
                                                    f32(alt + self.pad_altitude_amsl_m), alt,
                                                    alt, -1001.0, -1.0))
        return out

    def _set_state(self, sm_type: int, state: int, armed: bool, ts_ms: int,
                   out: list[Any]) -> None:
        self._last_heard = self.clock()
        last = self._state_ts
        if last is not None:
            behind = (last - ts_ms) & 0xFFFFFFFF
            if 0 < behind <= _REORDER_WINDOW_MS:
                return  # a little older than what we know (STATUS and SM_UPDATE interleave);
                # further back than the window means the flight computer rebooted: accept
        self._state_ts = ts_ms & 0xFFFFFFFF
        if self._state_key is not None and sm_type != self.sm_type:
            self.modes_seq += 1  # the mode table changed: ground stations re-request it
            out.append(mav.MAVLink_available_modes_monitor_message(self.modes_seq & 0xFF))
        key = (sm_type, state)
        changed = key != self._state_key
        armed_changed = armed != self.armed
        self.sm_type, self.state, self.armed = sm_type, state, armed
        if changed:
            self._state_key = key
            self.stats.state_changes += 1
            out.append(self.statustext_for_state())
        if changed or armed_changed:  # ground stations see the new mode/arming at once
            out.append(self.heartbeat())
        if changed and self._ext_state.period != math.inf:
            out.append(self.extended_sys_state())

    def statustext_for_state(self) -> Any:
        name = state_name(self.sm_type, self.state)
        severity = (mav.MAV_SEVERITY_CRITICAL if ERROR_STATE.get(self.sm_type) == self.state
                    else mav.MAV_SEVERITY_NOTICE)
        # A leading '#' makes QGroundControl speak the text (without the '#').
        return mav.MAVLink_statustext_message(severity, _text(f"#{name}", 50), 0, 0)

    def on_sm_update(self, m: SmUpdate) -> list[Any]:
        self.stats.updates += 1
        self.sm = m
        out: list[Any] = []
        self._set_state(m.sm_type, m.state, bool(m.armed), m.timestamp_ms, out)
        now = self._sm_at = self.clock()
        if now < self._sm_gates_shut_until:  # at 25k updates/s, all but ~100 a second
            return out
        g = self._gates
        t_ms = m.timestamp_ms & 0xFFFFFFFF
        if g["attitude_hz"].ready(now):
            out.append(mav.MAVLink_attitude_message(t_ms, f32(m.roll_rad), f32(m.pitch_rad),
                                                    f32(m.yaw_rad), 0.0, 0.0, 0.0))
        if g["altitude_hz"].ready(now):
            out.append(self.altitude())
        if g["vfr_hud_hz"].ready(now):
            out.append(self.vfr_hud())
        if g["named_value_hz"].ready(now):
            out.append(mav.MAVLink_named_value_float_message(t_ms, b"accel",
                                                             f32(m.acceleration_mps2)))
            out.append(mav.MAVLink_named_value_float_message(t_ms, b"accel_vert",
                                                             f32(m.accel_vert_mps2)))
        if g["aurora_sm_update_hz"].ready(now):
            out.append(aurora_sm_update(m))
        self._sm_gates_shut_until = min(g[key].opens_at() for key in _SM_UPDATE_GATES)
        return out

    def altitude(self) -> Any:
        m = self.sm
        alt = f32(m.altitude_m) if m is not None else math.nan
        t_us = (m.timestamp_ms * 1000) if m is not None else 0
        return mav.MAVLink_altitude_message(t_us, alt, f32(alt + self.pad_altitude_amsl_m), alt,
                                            alt, -1001.0, -1.0)

    def vfr_hud(self) -> Any:
        m = self.sm
        if m is None:
            return mav.MAVLink_vfr_hud_message(0.0, 0.0, 0, 0, math.nan, math.nan)
        heading = round(math.degrees(m.yaw_rad)) % 360 if math.isfinite(m.yaw_rad) else 0
        throttle = 100 if (m.sm_type == 0 and m.state == SimpleState.BOOST) else 0
        speed = f32(abs(m.velocity_mps)) if math.isfinite(m.velocity_mps) else 0.0
        return mav.MAVLink_vfr_hud_message(speed, 0.0, heading, throttle,
                                           f32(m.altitude_m + self.pad_altitude_amsl_m),
                                           f32(m.velocity_mps))

    def on_status(self, m: Status) -> list[Any]:
        self.stats.updates += 1
        self.status = m
        out: list[Any] = []
        self._set_state(m.sm_type, m.state, m.armed, m.timestamp_ms, out)
        if self._sys_status.period != math.inf:
            out.append(self.sys_status())  # health changes show at once, not up to 1 s later
        if self._gates["aurora_status_hz"].ready(self.clock()):
            out.append(aurora_status(m))
        return out

    def on_position(self, p: Position) -> list[Any]:
        self.position = p
        if not self._gates["position_hz"].ready(self.clock()):
            return []
        out = [self.global_position_int()]
        if p.fix_type is not None or p.satellites is not None:
            out.append(self.gps_raw_int())
        return out

    def global_position_int(self) -> Any:
        p = self.position
        assert p is not None
        m = self.sm
        rel = p.relative_alt_m if p.relative_alt_m is not None else (
            m.altitude_m if m is not None else 0.0)
        amsl = p.alt_amsl_m if p.alt_amsl_m is not None else rel + self.pad_altitude_amsl_m
        vz = -m.velocity_mps if (m is not None and math.isfinite(m.velocity_mps)) else 0.0
        vx = vy = 0.0
        if p.ground_speed_mps is not None and p.course_deg is not None:
            c = math.radians(p.course_deg)
            vx, vy = p.ground_speed_mps * math.cos(c), p.ground_speed_mps * math.sin(c)
        hdg = round(p.course_deg * 100) % 36000 if p.course_deg is not None else UINT16_MAX
        return mav.MAVLink_global_position_int_message(
            self._boot_ms(), _e7(p.lat_deg), _e7(p.lon_deg), _mm(amsl), _mm(rel), _cm(vx),
            _cm(vy), _cm(vz), hdg)

    def gps_raw_int(self) -> Any:
        p = self.position
        assert p is not None
        fix = p.fix_type if p.fix_type is not None else mav.GPS_FIX_TYPE_3D_FIX
        vel = (min(round(p.ground_speed_mps * 100), UINT16_MAX - 1)
               if p.ground_speed_mps is not None else UINT16_MAX)
        cog = (round(p.course_deg * 100) % 36000 if p.course_deg is not None
               else UINT16_MAX)
        sats = p.satellites if p.satellites is not None else 255
        alt = p.alt_amsl_m if p.alt_amsl_m is not None else 0.0
        return mav.MAVLink_gps_raw_int_message(
            self._boot_ms() * 1000, fix, _e7(p.lat_deg), _e7(p.lon_deg), _mm(alt), UINT16_MAX,
            UINT16_MAX, vel, cog, sats, 0, 0, 0, 0, 0, 0)

    def on_battery(self, b: Battery) -> list[Any]:
        self.batteries[b.battery_id] = b
        if not self._gates["battery_hz"].ready(self.clock()):
            return []
        return [battery_status(b)]

    def on_link_stats(self, ls: LinkStats) -> list[Any]:
        if not self._gates["radio_status_hz"].ready(self.clock()):
            return []
        return [radio_status(ls)]

    # -- requests from ground stations ------------------------------------------------------

    def handle(self, msg: Any, src_sysid: int, src_compid: int) -> list[Any]:
        """Answers to one decoded request addressed to this vehicle (or broadcast)."""
        mid = msg.get_msgId()
        if mid in (mav.MAVLINK_MSG_ID_COMMAND_LONG, mav.MAVLINK_MSG_ID_COMMAND_INT):
            if msg.target_system == 0 and _discovery(msg):
                # every system answers who it is (each of the gateway's vehicles, from its id)
                return self._command(msg, src_sysid, src_compid)
            if msg.target_system != self.sysid or msg.target_component not in (0, self.compid):
                return []  # other broadcast commands are not acknowledged by every system
            return self._command(msg, src_sysid, src_compid)
        if mid == mav.MAVLINK_MSG_ID_PING:
            if msg.target_system != 0 or msg.target_component != 0:
                return []  # an answer to somebody's ping, or a ping for another system
            return [mav.MAVLink_ping_message(msg.time_usec, msg.seq, src_sysid, src_compid)]
        if mid == mav.MAVLINK_MSG_ID_MISSION_REQUEST_LIST:
            if not self._mine(msg):
                return []
            self.stats.mission_requests += 1
            return [mav.MAVLink_mission_count_message(src_sysid, src_compid, 0,
                                                      msg.mission_type)]
        if mid in (mav.MAVLINK_MSG_ID_MISSION_COUNT, mav.MAVLINK_MSG_ID_MISSION_CLEAR_ALL):
            if not self._mine(msg):
                return []
            # No missions on a rocket: refuse uploads and clears, honestly.
            return [mav.MAVLink_mission_ack_message(src_sysid, src_compid,
                                                    mav.MAV_MISSION_UNSUPPORTED,
                                                    msg.mission_type)]
        if mid == mav.MAVLINK_MSG_ID_RC_CHANNELS_OVERRIDE:
            if self._mine(msg):
                self._rc_in(rc_from_override(msg))
            return []
        if mid == mav.MAVLINK_MSG_ID_MANUAL_CONTROL:
            if msg.target == self.sysid:
                self._rc_in(rc_from_manual_control(msg))
            return []
        if mid in (mav.MAVLINK_MSG_ID_PARAM_REQUEST_LIST, mav.MAVLINK_MSG_ID_PARAM_REQUEST_READ,
                   mav.MAVLINK_MSG_ID_PARAM_SET):
            # The parameter protocol: a component without parameters ignores the request.
            if self._mine(msg):
                self.stats.param_requests_ignored += 1
            return []
        return []  # MISSION_ACK (end of QGC's mission download) and the like: nothing to say

    def _rc_in(self, channels: tuple[int | None, ...]) -> None:
        """A ground station's sticks for the rocket: handed to the gateway (``on_rc``), e.g.
        for an XBee ground link to send up."""
        self.stats.rc_overrides += 1
        if self.on_rc is not None:
            self.on_rc(channels)

    def _mine(self, msg: Any) -> bool:
        return msg.target_system == self.sysid and msg.target_component in (0, self.compid)

    def _ack(self, command: int, result: int, sysid: int, compid: int) -> Any:
        return mav.MAVLink_command_ack_message(command, result, 0, 0, sysid, compid)

    def _command(self, msg: Any, sysid: int, compid: int) -> list[Any]:
        self.stats.commands += 1
        cmd = msg.command
        ack = self._ack
        if cmd == mav.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(int(msg.param1), msg.param2, sysid, compid)
        if cmd == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return [ack(cmd, mav.MAV_RESULT_ACCEPTED, sysid, compid), self.autopilot_version()]
        if cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            return [ack(cmd, self._set_interval(int(msg.param1), msg.param2), sysid, compid)]
        if cmd == mav.MAV_CMD_GET_MESSAGE_INTERVAL:
            msg_id = int(msg.param1)
            if msg_id not in STREAMS:
                return [ack(cmd, mav.MAV_RESULT_DENIED, sysid, compid)]
            hz = self.rates[STREAMS[msg_id]]
            interval = round(1e6 / hz) if hz > 0 else -1
            return [ack(cmd, mav.MAV_RESULT_ACCEPTED, sysid, compid),
                    mav.MAVLink_message_interval_message(msg_id, interval)]
        self.stats.commands_unsupported += 1
        return [ack(cmd, mav.MAV_RESULT_UNSUPPORTED, sysid, compid)]

    def _request_message(self, msg_id: int, param2: float, sysid: int, compid: int) -> list[Any]:
        cmd = mav.MAV_CMD_REQUEST_MESSAGE
        accepted = self._ack(cmd, mav.MAV_RESULT_ACCEPTED, sysid, compid)
        if msg_id not in _REQUESTABLE:
            self.stats.commands_unsupported += 1
            return [self._ack(cmd, mav.MAV_RESULT_UNSUPPORTED, sysid, compid)]
        if msg_id == mav.MAVLINK_MSG_ID_AVAILABLE_MODES:
            modes = self.available_modes()
            if not modes:  # a state machine whose states we cannot name
                return [self._ack(cmd, mav.MAV_RESULT_DENIED, sysid, compid)]
            index = int(param2)
            if index == 0:
                return [accepted, *modes]
            if 1 <= index <= len(modes):
                return [accepted, modes[index - 1]]
            return [self._ack(cmd, mav.MAV_RESULT_DENIED, sysid, compid)]
        build = {
            mav.MAVLINK_MSG_ID_HEARTBEAT: self.heartbeat,
            mav.MAVLINK_MSG_ID_SYS_STATUS: self.sys_status,
            mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: self.extended_sys_state,
            mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION: self.autopilot_version,
        }.get(msg_id)
        if build is not None:
            return [accepted, build()]
        m = self.sm
        if msg_id == mav.MAVLINK_MSG_ID_AURORA_STATUS:
            if self.status is None:
                return [self._ack(cmd, mav.MAV_RESULT_TEMPORARILY_REJECTED, sysid, compid)]
            return [accepted, aurora_status(self.status)]
        if m is None:  # nothing heard yet: the message does not exist yet
            return [self._ack(cmd, mav.MAV_RESULT_TEMPORARILY_REJECTED, sysid, compid)]
        if msg_id == mav.MAVLINK_MSG_ID_ATTITUDE:
            reply = mav.MAVLink_attitude_message(m.timestamp_ms & 0xFFFFFFFF, f32(m.roll_rad),
                                                 f32(m.pitch_rad), f32(m.yaw_rad), 0.0, 0.0, 0.0)
        elif msg_id == mav.MAVLINK_MSG_ID_ALTITUDE:
            reply = self.altitude()
        elif msg_id == mav.MAVLINK_MSG_ID_VFR_HUD:
            reply = self.vfr_hud()
        else:
            reply = aurora_sm_update(m)
        return [accepted, reply]

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        key = STREAMS.get(msg_id)
        if key is None:
            return mav.MAV_RESULT_DENIED
        if interval_us == 0:
            hz = self.default_rates[key]
        elif interval_us < 0:
            hz = 0.0
        else:
            hz = 1e6 / interval_us
        self.rates[key] = hz
        now = self.clock()
        if key == "heartbeat_hz":
            self._heartbeat.set_rate(hz, now)
        elif key == "sys_status_hz":
            self._sys_status.set_rate(hz, now)
        elif key == "extended_sys_state_hz":
            self._ext_state.set_rate(hz, now)
        else:
            gate = self._gates[key]
            if key in _SM_UPDATE_GATES:  # the updates it skipped, at the rate they came at
                gate.advance(self._sm_at)
            gate.set_rate(hz)
            self._sm_gates_shut_until = -math.inf
        return mav.MAV_RESULT_ACCEPTED

    def autopilot_version(self) -> Any:
        return mav.MAVLink_autopilot_version_message(
            mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2, self.version_word, 0, 0, 0,
            [0] * 8, [0] * 8, [0] * 8, 0, 0, 0, [0] * 18)

    def available_modes(self) -> list[Any]:
        """One AVAILABLE_MODES per state of the active state machine, none selectable."""
        names = state_names(self.sm_type)
        n = len(names)
        return [mav.MAVLink_available_modes_message(
            n, i + 1, mav.MAV_STANDARD_MODE_NON_STANDARD, number,
            mav.MAV_MODE_PROPERTY_NOT_USER_SELECTABLE, _text(name, 35))
            for i, (number, name) in enumerate(names)]


def _discovery(msg: Any) -> bool:
    """A broadcast command every system answers: who are you (AUTOPILOT_VERSION)."""
    cmd = msg.command
    return cmd == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES or (
        cmd == mav.MAV_CMD_REQUEST_MESSAGE
        and int(msg.param1) == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)


def aurora_sm_update(m: SmUpdate) -> Any:
    """AURORA_SM_UPDATE carrying every field of ``m`` (f64, so both revisions are exact)."""
    return mav.MAVLink_aurora_sm_update_message(
        m.timestamp_ms & 0xFFFFFFFF, m.state & 0xFF, 1 if m.armed else 0, m.sm_type & 0xFF,
        m.reserved & 0xFF, m.altitude_m, m.acceleration_mps2, m.accel_vert_mps2, m.velocity_mps,
        m.roll_rad, m.pitch_rad, m.yaw_rad, m.payload_len & 0xFF)


def aurora_status(m: Status) -> Any:
    return mav.MAVLink_aurora_status_message(m.timestamp_ms & 0xFFFFFFFF, m.state & 0xFF,
                                             m.sm_type & 0xFF, m.flags & 0xFF, m.reserved & 0xFF)


#: ``via`` of a message that came in over MAVLink: ``mavlink:<system id>`` (gateway.model).
VIA_MAVLINK = "mavlink:"


def sm_update_from_mavlink(msg: Any, origin: str = "") -> SmUpdate:
    """The :class:`SmUpdate` an AURORA_SM_UPDATE carries (the inverse of
    :func:`aurora_sm_update`)."""
    return SmUpdate(msg.timestamp_ms, msg.state, bool(msg.armed), msg.sm_type, msg.altitude,
                    msg.acceleration, msg.accel_vert, msg.velocity, msg.roll, msg.pitch, msg.yaw,
                    payload_len=msg.payload_len, reserved=msg.reserved, origin=origin)


def status_from_mavlink(msg: Any, origin: str = "") -> Status:
    return Status(msg.timestamp_ms, msg.state, msg.sm_type, msg.flags, reserved=msg.reserved,
                  origin=origin)


def battery_status(b: Battery) -> Any:
    mv = round(b.voltage_v * 1000) if math.isfinite(b.voltage_v) else UINT16_MAX
    voltages = [min(max(mv, 0), UINT16_MAX - 1)] + [UINT16_MAX] * 9
    current = (max(-1, min(round(b.current_a * 100), 32767))
               if b.current_a is not None else -1)
    consumed = round(b.consumed_mah) if b.consumed_mah is not None else -1
    remaining = max(-1, min(int(b.remaining_pct), 100)) if b.remaining_pct is not None else -1
    return mav.MAVLink_battery_status_message(
        b.battery_id & 0xFF, mav.MAV_BATTERY_FUNCTION_UNKNOWN, mav.MAV_BATTERY_TYPE_UNKNOWN,
        0x7FFF, voltages, current, consumed, -1, remaining, 0, 0, [0] * 4, 0, 0)


def _dbm_byte(dbm: float | None) -> int:
    """A dBm figure as RADIO_STATUS carries it for a non-SiK radio: a signed byte (QGC reads
    ``rssi``/``remrssi``/``noise`` as int8); 255 (UINT8_MAX) when unknown, so a real value
    stops at −2 dBm."""
    if dbm is None or not math.isfinite(dbm):
        return UINT8_MAX
    return max(-128, min(round(dbm), -2)) & 0xFF


def radio_status(ls: LinkStats) -> Any:
    """RADIO_STATUS from a receiver's link statistics (e.g. CRSF 0x14): local = uplink RSSI
    and the noise floor it implies (RSSI − SNR), remote = downlink; no TX buffer to report
    (100 % free) and no error counters (0)."""
    def noise(rssi: float | None, snr: float | None) -> int:
        return _dbm_byte(None if rssi is None or snr is None else rssi - snr)

    return mav.MAVLink_radio_status_message(
        _dbm_byte(ls.rssi_dbm), _dbm_byte(ls.downlink_rssi_dbm), 100,
        noise(ls.rssi_dbm, ls.snr_db), noise(ls.downlink_rssi_dbm, ls.downlink_snr_db), 0, 0)


def _e7(deg: float) -> int:
    return round(deg * 1e7)


def _mm(m: float) -> int:
    return max(-(2 ** 31), min(round(m * 1000), 2 ** 31 - 1)) if math.isfinite(m) else 0


def _cm(v: float) -> int:
    return max(-32768, min(round(v * 100), 32767)) if math.isfinite(v) else 0


def rc_from_override(msg: Any) -> tuple[int | None, ...]:
    """RC_CHANNELS_OVERRIDE's channels in µs; 0 (release) and UINT16_MAX (ignore) are None
    (MAVLink 2's chan9..18 use 0 and UINT16_MAX - 1 the same way)."""
    out: list[int | None] = []
    for i in range(1, RC_CHANNELS_MAX + 1):
        v = getattr(msg, f"chan{i}_raw", 0)
        out.append(None if v in (0, UINT16_MAX) or (i > 8 and v == UINT16_MAX - 1) else int(v))
    while out and out[-1] is None:
        out.pop()
    return tuple(out)


def rc_from_manual_control(msg: Any) -> tuple[int | None, ...]:
    """MANUAL_CONTROL's axes as AETR channels in µs: roll (y), pitch (x), throttle (z), yaw (r);
    x, y, r −1000..1000 → 1000..2000, z 0..1000 → 1000..2000 (an invalid axis, INT16_MAX, is
    None)."""
    def axis(v: int) -> int | None:
        return None if v == 0x7FFF else 1500 + max(-1000, min(1000, v)) // 2

    z = msg.z
    throttle = None if z == 0x7FFF else 1000 + max(0, min(1000, z))
    return (axis(msg.y), axis(msg.x), throttle, axis(msg.r))

