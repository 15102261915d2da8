"""The rocket as LibrePilot 16.09 objects: gateway messages in, UAVTalk object values out.

Sans-I/O: :class:`Vehicle` keeps what it has heard of the rocket and answers, per message, the
objects it changed and their new values (field names as in the XMLs; enums as option names).

======================  ====================================================================
AttitudeState           roll/pitch/yaw of every SM_UPDATE in degrees, and the quaternion
                        q1..q4 (q1 the scalar part, q1 ≥ 0) of the same Z-Y-X rotation, as
                        LibrePilot's ``RPY2Quaternion`` computes it
FlightStatus            Armed: ``Armed`` / ``Disarmed`` (the SM_UPDATE's flag, or STATUS's);
                        FlightMode: :data:`FLIGHT_MODES` (the rocket's state)
SystemAlarms            from the STATUS flags (see :meth:`Vehicle.status`); GPS and Battery
                        ``OK`` once a position or a battery reading arrived
BaroSensor              Altitude from the SM_UPDATE; Pressure from the ISA standard atmosphere
                        at that altitude; Temperature 15 °C (not measured)
GPSPositionSensor       every Position (only once one has arrived)
FlightBatteryState      every Battery (only once one has arrived)
FirmwareIAPObj          BoardType (nonzero: the 16.09 GCS waits for it), a description
======================  ====================================================================

Flight modes (:data:`FLIGHT_MODES`, SIMPLE state machine; any other state → ``Manual``):

=========  ===========  ==================================================================
state      FlightMode   why
=========  ===========  ==================================================================
IDLE       Manual       on the pad, nothing automatic
ARMED      Manual       on the pad, armed (FlightStatus.Armed says so)
BOOST      AutoTakeoff  the motor climbs
BURNOUT    AutoCruise   coasting up, unpowered
APOGEE     PositionHold the top of the arc
MAIN       Land         descending under the main parachute
REDUNDANT  Land         descending under the redundant deployment
LANDED     Manual       on the ground
ERROR      Manual       and SystemAlarms.SystemConfiguration ``Critical``
=========  ===========  ==================================================================
"""

from __future__ import annotations

import math
from typing import Any

from dialects.states import SM_TYPE_SIMPLE, SimpleState
from gateway.attitude import quaternion_wxyz
from gateway.model import (
    STATUS_ARMED,
    STATUS_BARO_OK,
    STATUS_CALIBRATED,
    STATUS_IMU_OK,
    Battery,
    Position,
    SmUpdate,
    Status,
)

from .objects import ObjectSet

__all__ = ["FLIGHT_MODES", "Vehicle", "flight_mode", "quaternion"]

#: SIMPLE state → FlightStatus.FlightMode option (see the module docstring).
FLIGHT_MODES: dict[int, str] = {
    SimpleState.IDLE: "Manual",
    SimpleState.ARMED: "Manual",
    SimpleState.BOOST: "AutoTakeoff",
    SimpleState.BURNOUT: "AutoCruise",
    SimpleState.APOGEE: "PositionHold",
    SimpleState.MAIN: "Land",
    SimpleState.REDUNDANT: "Land",
    SimpleState.LANDED: "Manual",
    SimpleState.ERROR: "Manual",
}
DEFAULT_MODE = "Manual"
SEA_LEVEL_PA = 101325.0
ISA_TEMPERATURE_C = 15.0
_INT32 = (1 << 31) - 1
FIX_STATUS = {0: "NoFix", 1: "NoFix", 2: "Fix2D"}  # MAVLink GPS_FIX_TYPE; 3 and up: Fix3D


def quaternion(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, ...]:
    """(q1, q2, q3, q4) of the Z-Y-X (yaw, pitch, roll) rotation, scalar first, q1 ≥ 0."""
    q = quaternion_wxyz(roll_rad, pitch_rad, yaw_rad)
    return tuple(-v for v in q) if q[0] < 0 else q


def flight_mode(sm_type: int, state: int) -> str:
    """The FlightMode option shown for ``state`` (see :data:`FLIGHT_MODES`)."""
    if sm_type == SM_TYPE_SIMPLE:
        return FLIGHT_MODES.get(state, DEFAULT_MODE)
    return DEFAULT_MODE


def _pressure(altitude_m: float) -> float:
    base = max(0.0, 1.0 - 2.25577e-5 * altitude_m)
    return SEA_LEVEL_PA * base ** 5.25588


def _f(value: float | None) -> float:
    return 0.0 if value is None or not math.isfinite(value) else float(value)


def _finite(value: float) -> float:
    return float(value) if math.isfinite(value) else 0.0


class Vehicle:
    """What the gateway has heard of the rocket, as object values (see the module doc)."""

    def __init__(self, objects: ObjectSet, board_type: int = 0x09) -> None:
        self.board_type = board_type
        self._alarm_names = objects.by_name("SystemAlarms").field("Alarm").element_names
        self.armed = False
        self.sm_type = SM_TYPE_SIMPLE
        self.state = int(SimpleState.IDLE)
        self.flags: int | None = None
        self.has_gps = False
        self.has_battery = False

    def defaults(self) -> dict[str, dict[str, Any]]:
        """The objects served before any message arrived."""
        return {
            "FirmwareIAPObj": {"BoardType": self.board_type, "BoardRevision": 1,
                               "Description": list(b"Aurora Gateway".ljust(100, b"\0"))},
            "AttitudeState": self.attitude(0.0, 0.0, 0.0),
            "FlightStatus": self.flight_status(),
            "SystemAlarms": self.alarms(),
            "BaroSensor": self.baro(0.0),
        }

    # --- per object ---------------------------------------------------------------------------

    @staticmethod
    def attitude(roll_rad: float, pitch_rad: float, yaw_rad: float) -> dict[str, Any]:
        r, p, y = _finite(roll_rad), _finite(pitch_rad), _finite(yaw_rad)
        q1, q2, q3, q4 = quaternion(r, p, y)
        return {"q1": q1, "q2": q2, "q3": q3, "q4": q4, "Roll": math.degrees(r),
                "Pitch": math.degrees(p), "Yaw": math.degrees(y)}

    def flight_status(self) -> dict[str, Any]:
        return {"Armed": "Armed" if self.armed else "Disarmed",
                "FlightMode": flight_mode(self.sm_type, self.state)}

    def alarms(self) -> dict[str, Any]:
        """SystemAlarms.Alarm: Attitude from IMU_OK; Sensors from IMU_OK and BARO_OK;
        SystemConfiguration from CALIBRATED (``Warning`` if not; ``Critical`` in the ERROR
        state); Telemetry ``OK`` once a STATUS arrived; GPS, Battery ``OK`` once heard.
        Anything not known stays ``Uninitialised``."""
        alarm: dict[str, str] = {}
        flags = self.flags
        if flags is not None:
            imu, baro = bool(flags & STATUS_IMU_OK), bool(flags & STATUS_BARO_OK)
            alarm["Attitude"] = "OK" if imu else "Critical"
            alarm["Sensors"] = "OK" if imu and baro else "Critical"
            alarm["SystemConfiguration"] = "OK" if flags & STATUS_CALIBRATED else "Warning"
            alarm["Telemetry"] = "OK"
        if self.sm_type == SM_TYPE_SIMPLE and self.state == SimpleState.ERROR:
            alarm["SystemConfiguration"] = "Critical"
        if self.has_gps:
            alarm["GPS"] = "OK"
        if self.has_battery:
            alarm["Battery"] = "OK"
        return {"Alarm": [alarm.get(name, "Uninitialised") for name in self._alarm_names]}

    @staticmethod
    def baro(altitude_m: float) -> dict[str, Any]:
        alt = _finite(altitude_m)
        return {"Altitude": alt, "Pressure": _pressure(alt), "Temperature": ISA_TEMPERATURE_C}

    # --- per message --------------------------------------------------------------------------

    def sm_update(self, msg: SmUpdate) -> dict[str, dict[str, Any]]:
        """The objects an SM_UPDATE sets."""
        self.armed = bool(msg.armed)
        changed_state = (msg.sm_type, msg.state) != (self.sm_type, self.state)
        self.sm_type, self.state = msg.sm_type, msg.state
        out = {"AttitudeState": self.attitude(msg.roll_rad, msg.pitch_rad, msg.yaw_rad),
               "FlightStatus": self.flight_status(),
               "BaroSensor": self.baro(msg.altitude_m)}
        if changed_state:
            out["SystemAlarms"] = self.alarms()
        return out

    def status(self, msg: Status) -> dict[str, dict[str, Any]]:
        """The objects a STATUS sets."""
        self.flags = msg.flags
        self.armed = bool(msg.flags & STATUS_ARMED)
        self.sm_type, self.state = msg.sm_type, msg.state
        return {"SystemAlarms": self.alarms(), "FlightStatus": self.flight_status()}

    def position(self, msg: Position) -> dict[str, dict[str, Any]]:
        """GPSPositionSensor (and SystemAlarms the first time)."""
        first = not self.has_gps
        self.has_gps = True
        fix = msg.fix_type
        sats = msg.satellites
        out = {"GPSPositionSensor": {
            "Status": "Fix3D" if fix is None or fix >= 3 else FIX_STATUS.get(fix, "NoFix"),
            "Latitude": max(-_INT32, min(_INT32, round(_f(msg.lat_deg) * 1e7))),
            "Longitude": max(-_INT32, min(_INT32, round(_f(msg.lon_deg) * 1e7))),
            "Altitude": _f(msg.alt_amsl_m),
            "Heading": _f(msg.course_deg),
            "Groundspeed": _f(msg.ground_speed_mps),
            "Satellites": -1 if sats is None else max(0, min(127, sats)),
        }}
        if first:
            out["SystemAlarms"] = self.alarms()
        return out

    def battery(self, msg: Battery) -> dict[str, dict[str, Any]]:
        """FlightBatteryState (and SystemAlarms the first time)."""
        first = not self.has_battery
        self.has_battery = True
        out = {"FlightBatteryState": {"Voltage": _f(msg.voltage_v), "Current": _f(msg.current_a),
                                      "ConsumedEnergy": _f(msg.consumed_mah)}}
        if first:
            out["SystemAlarms"] = self.alarms()
        return out
