"""Gateway messages → ROS 2 samples: the topics a ROS 2 user sees, per vehicle.

``RosTopics().samples(msg)`` turns one gateway message into the samples (topic, type, CDR
bytes, stamp) it publishes; the DDS backend, the rmw_zenoh publication and the rosbag2 export
all send what it returns, so the three carry the same topics, types and bytes.

===================================  ===============================  =========================
topic                                type                             from
===================================  ===============================  =========================
``/aurora/<vehicle>/altitude``       ``std_msgs/msg/Float64``         each SM update (metres)
``/tf``                              ``tf2_msgs/msg/TFMessage``       each SM update: ``world``
                                                                      → ``<vehicle>``, z =
                                                                      altitude, the attitude
``/aurora/<vehicle>/imu``            ``sensor_msgs/msg/Imu``          each SM update
``/aurora/<vehicle>/state``          ``std_msgs/msg/String``          the state's name, when it
                                                                      changes (latched)
``/aurora/<vehicle>/armed``          ``std_msgs/msg/Bool``            when it changes (latched)
``/aurora/<vehicle>/fix``            ``sensor_msgs/msg/NavSatFix``    each Position
``/aurora/<vehicle>/battery``        ``sensor_msgs/msg/BatteryState`` each Battery
``/diagnostics``                     ``diagnostic_msgs/msg/           each STATUS, each link
                                     DiagnosticArray``                event, link stats (≤ 1/s)
===================================  ===============================  =========================

"Latched" samples (:attr:`Sample.latched`) are for reliable, transient-local writers: a late
joiner gets the current state and armed at once.  A MAVLink autopilot's
:class:`~gateway.model.VehicleState` gives the same topics: its mode is its state, its
attitude and altitude (when reported) its ``/tf``, ``imu`` and ``altitude``.

Stamps: every header stamp and :attr:`Sample.stamp_ns` is the time the message was handled
(``stamp_ns`` given to :meth:`RosTopics.samples`, e.g. a recording's receive time; else the
clock now), in ns since the epoch, as ROS time is: the flight computer's ``timestamp_ms``
counts from its boot, and tf2 and rviz2 would take such stamps for ancient.

Conventions (REP-103, REP-145): the Imu's ``orientation`` is the attitude (roll, pitch, yaw,
Z-Y-X) with its covariance unknown (zeros); ``linear_acceleration`` z is the body-vertical
acceleration (x and y are not measured by the wire format: zeros); ``angular_velocity`` is not
provided (covariance element 0 = -1).  NavSatFix altitude is the fix's altitude above mean
sea level (NaN when unknown; ROS asks for the ellipsoid height, which the sources do not
give).  BatteryState's current is negative when discharging, ``percentage`` 0..1, NaN for what
is not measured.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

from backends.ros2 import cdr
from backends.ros2.types import (
    BATTERY_STATE,
    BOOL,
    DIAGNOSTIC_ARRAY,
    FLOAT64,
    IMU,
    NAV_SAT_FIX,
    STRING,
    TF_MESSAGE,
    RosType,
)
from gateway.attitude import quaternion_xyzw
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    SmUpdate,
    Status,
    VehicleState,
)

TF = "/tf"
DIAGNOSTICS = "/diagnostics"
PARENT_FRAME = "world"
DEFAULT_VEHICLE = "rocket1"
#: Vehicles kept at most; a further vehicle's messages give no samples (counted).
MAX_VEHICLES = 256
#: Link statistics refresh ``/diagnostics`` at most this often per vehicle.
LINK_DIAGNOSTICS_INTERVAL_NS = 1_000_000_000

_NAN = math.nan


class Sample(NamedTuple):
    """One ROS 2 message to publish: ``topic`` (the ROS name, ``/aurora/rocket1/altitude``,
    ``/tf``), its ``type``, ``cdr`` (serialized, with the 4-byte encapsulation header),
    ``stamp_ns`` (ns since the epoch) and ``latched`` (True: publish reliable and transient
    local, so a late joiner gets the last one)."""

    topic: str
    type: RosType
    cdr: bytes
    stamp_ns: int
    latched: bool = False


def vehicle_topic(vehicle: str, leaf: str) -> str:
    """``/aurora/<vehicle>/<leaf>``."""
    return f"/aurora/{vehicle}/{leaf}"


def dds_topic(ros_name: str) -> str:
    """The DDS topic name ROS 2 gives a topic: ``rt`` + the ROS name (``/tf`` → ``rt/tf``)."""
    return "rt" + ros_name if ros_name.startswith("/") else "rt/" + ros_name


#: Every (topic, type) of one vehicle's, in the table's order (with the shared /tf and
#: /diagnostics): what a writer set or a bag declares up front.
def vehicle_topics(vehicle: str) -> list[tuple[str, RosType]]:
    """The topics of ``vehicle`` and their types, the shared ``/tf`` and ``/diagnostics``
    included."""
    return [(vehicle_topic(vehicle, "altitude"), FLOAT64), (TF, TF_MESSAGE),
            (vehicle_topic(vehicle, "imu"), IMU), (vehicle_topic(vehicle, "state"), STRING),
            (vehicle_topic(vehicle, "armed"), BOOL), (vehicle_topic(vehicle, "fix"), NAV_SAT_FIX),
            (vehicle_topic(vehicle, "battery"), BATTERY_STATE), (DIAGNOSTICS, DIAGNOSTIC_ARRAY)]


#: Which topics are latched (reliable + transient local), by leaf.
LATCHED_LEAVES = frozenset({"state", "armed"})


class _Vehicle:
    """One vehicle's topic names and the last state, armed and health it published."""

    __slots__ = ("altitude", "armed", "armed_topic", "battery", "fix", "flags", "imu",
                 "last_link_diag_ns", "link", "name", "state", "state_topic")

    def __init__(self, name: str) -> None:
        self.name = name
        self.altitude = vehicle_topic(name, "altitude")
        self.imu = vehicle_topic(name, "imu")
        self.state_topic = vehicle_topic(name, "state")
        self.armed_topic = vehicle_topic(name, "armed")
        self.fix = vehicle_topic(name, "fix")
        self.battery = vehicle_topic(name, "battery")
        self.state: object = None       # (sm_type, state) of an SM update, or a mode string
        self.armed: bool | None = None
        self.flags: Status | None = None
        self.link: dict[str, str] = {}  # the link's last values, as diagnostics key/values
        self.last_link_diag_ns = 0


class RosTopics:
    """Turns gateway messages into ROS 2 samples (:meth:`samples`), keeping per vehicle (a
    dict by ``msg.vehicle``) what "when it changes" needs.  ``default_vehicle`` names the
    vehicle of a message that names none.  Not thread-safe: one caller (a backend's loop, an
    export)."""

    def __init__(self, default_vehicle: str = DEFAULT_VEHICLE,
                 max_vehicles: int = MAX_VEHICLES) -> None:
        self.default_vehicle = default_vehicle
        self.max_vehicles = max_vehicles
        self._vehicles: dict[str, _Vehicle] = {}
        #: messages of a vehicle past ``max_vehicles``: no samples
        self.dropped_vehicle_limit = 0
        self._handlers: dict[type, Callable[[Any, _Vehicle, int], list[Sample]]] = {
            SmUpdate: self._sm_update, Status: self._status, Position: self._position,
            Battery: self._battery, LinkStats: self._link_stats, LinkEvent: self._link_event,
            VehicleState: self._vehicle_state,
        }

    @property
    def vehicles(self) -> list[str]:
        """The vehicles seen so far, in order."""
        return list(self._vehicles)

    def samples(self, msg: object, stamp_ns: int | None = None) -> list[Sample]:
        """The ROS samples of ``msg`` (none for a kind that has no topic), stamped
        ``stamp_ns`` (ns since the epoch; default: now)."""
        handler = self._handlers.get(type(msg))
        if handler is None:
            return []
        name = getattr(msg, "vehicle", "") or self.default_vehicle
        v = self._vehicles.get(name)
        if v is None:
            if len(self._vehicles) >= self.max_vehicles:
                self.dropped_vehicle_limit += 1
                return []
            v = self._vehicles[name] = _Vehicle(name)
        return handler(msg, v, time.time_ns() if stamp_ns is None else stamp_ns)

    # -- the state machine ------------------------------------------------------------------

    def _state_armed(self, out: list[Sample], v: _Vehicle, key: object, msg: Any,
                     armed: bool, ns: int) -> None:
        """The state (named by ``msg.state_name``, or a mode by ``msg.mode``) when ``key``
        changes, and armed when it changes."""
        if key != v.state:
            v.state = key
            name = msg.mode if type(msg) is VehicleState else msg.state_name
            out.append(Sample(v.state_topic, STRING, cdr.string(name), ns, True))
        if armed is not v.armed:
            v.armed = armed
            out.append(Sample(v.armed_topic, BOOL, cdr.boolean(armed), ns, True))

    def _pose(self, out: list[Sample], v: _Vehicle, ns: int, altitude: float,
              rpy: tuple[float, float, float], accel_z: float) -> None:
        q = quaternion_xyzw(*rpy)
        out.append(Sample(v.altitude, FLOAT64, cdr.float64(altitude), ns))
        out.append(Sample(TF, TF_MESSAGE, cdr.tf_message(
            (cdr.Transform(ns, PARENT_FRAME, v.name, (0.0, 0.0, altitude), q),)), ns))
        out.append(Sample(v.imu, IMU, cdr.imu(ns, v.name, q, (0.0, 0.0, accel_z)), ns))

    def _sm_update(self, m: SmUpdate, v: _Vehicle, ns: int) -> list[Sample]:
        out: list[Sample] = []
        self._pose(out, v, ns, m.altitude_m, (m.roll_rad, m.pitch_rad, m.yaw_rad),
                   m.accel_vert_mps2)
        self._state_armed(out, v, (m.sm_type, m.state), m, bool(m.armed), ns)
        return out

    def _vehicle_state(self, m: VehicleState, v: _Vehicle, ns: int) -> list[Sample]:
        out: list[Sample] = []
        if m.roll_rad is not None and m.pitch_rad is not None and m.yaw_rad is not None:
            alt = m.altitude_m if m.altitude_m is not None else 0.0
            self._pose(out, v, ns, alt, (m.roll_rad, m.pitch_rad, m.yaw_rad), 0.0)
        elif m.altitude_m is not None:
            out.append(Sample(v.altitude, FLOAT64, cdr.float64(m.altitude_m), ns))
        self._state_armed(out, v, m.mode, m, bool(m.armed), ns)
        return out

    # -- health: /diagnostics ---------------------------------------------------------------

    def _status(self, m: Status, v: _Vehicle, ns: int) -> list[Sample]:
        v.flags = m
        out: list[Sample] = []
        self._state_armed(out, v, (m.sm_type, m.state), m, m.armed, ns)
        out.append(self._diagnostics(v, ns))
        return out

    def _link_event(self, m: LinkEvent, v: _Vehicle, ns: int) -> list[Sample]:
        v.link["up"] = "true" if m.up else "false"
        v.link["source"] = m.source
        if not m.up:
            v.link["silence_s"] = f"{m.silence_s:.1f}"
        else:
            v.link.pop("silence_s", None)
        return [self._diagnostics(v, ns)]

    def _link_stats(self, m: LinkStats, v: _Vehicle, ns: int) -> list[Sample]:
        for key, value in m.fields().items():
            if value is not None:
                v.link[key] = str(value)
        if ns - v.last_link_diag_ns < LINK_DIAGNOSTICS_INTERVAL_NS:
            return []
        return [self._diagnostics(v, ns)]

    def _diagnostics(self, v: _Vehicle, ns: int) -> Sample:
        v.last_link_diag_ns = ns
        statuses = []
        s = v.flags
        if s is not None:
            health = s.health()
            bad = [k for k in ("imu_ok", "baro_ok", "calibrated") if not health[k]]
            level = cdr.OK if not bad else cdr.WARN if len(bad) < 3 else cdr.ERROR
            message = "OK" if not bad else "not " + ", ".join(bad)
            values = (("state", s.state_name), ("flags", f"0x{s.flags:02x}"),
                      *((k, "true" if ok else "false") for k, ok in health.items()))
            statuses.append(cdr.DiagnosticStatus(level, f"aurora/{v.name}/flight_computer",
                                                 message, v.name, values))
        if v.link:
            up = v.link.get("up", "true") == "true"
            statuses.append(cdr.DiagnosticStatus(
                cdr.OK if up else cdr.ERROR, f"aurora/{v.name}/link", "up" if up else "down",
                v.name, tuple(v.link.items())))
        return Sample(DIAGNOSTICS, DIAGNOSTIC_ARRAY, cdr.diagnostic_array(ns, statuses), ns)

    # -- position, battery ------------------------------------------------------------------

    def _position(self, m: Position, v: _Vehicle, ns: int) -> list[Sample]:
        fix = m.fix_type
        status = (cdr.STATUS_FIX if fix is None or fix in (2, 3)
                  else cdr.STATUS_NO_FIX if fix < 2
                  else cdr.STATUS_SBAS_FIX if fix == 4 else cdr.STATUS_GBAS_FIX)
        alt = m.alt_amsl_m if m.alt_amsl_m is not None else _NAN
        return [Sample(v.fix, NAV_SAT_FIX, cdr.nav_sat_fix(ns, v.name, m.lat_deg, m.lon_deg,
                                                           alt, status=status), ns)]

    def _battery(self, m: Battery, v: _Vehicle, ns: int) -> list[Sample]:
        return [Sample(v.battery, BATTERY_STATE, cdr.battery_state(
            ns, v.name, m.voltage_v,
            current=-m.current_a if m.current_a is not None else _NAN,
            percentage=m.remaining_pct / 100.0 if m.remaining_pct is not None else _NAN,
            location=str(m.battery_id)), ns)]
