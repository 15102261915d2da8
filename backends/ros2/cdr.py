"""Plain CDR (XCDR1, little endian) encoders for the ROS 2 types of :mod:`backends.ros2.types`.

Each encoder returns the serialized message *with* its 4-byte encapsulation header
(``00 01 00 00``: CDR, little endian), as rmw_zenoh carries it in a sample's payload, rosbag2
stores it and DDS sends it (a DDS writer adds the header itself: see
:func:`without_header`).  Alignment is CDR's: each primitive on a multiple of its size,
counted from the end of the header; strings are a ``uint32`` length counting a terminating
NUL, then the UTF-8 bytes and the NUL; sequences a ``uint32`` count, then the elements; fixed
arrays only the elements.

Hot path (an SM update becomes a Float64, an Imu and a TFMessage): each encoder is a few
precompiled :class:`struct.Struct` packs into one ``bytearray``, no reflection per call.
Independent check: ``tests/test_ros2_cdr.py`` decodes every encoder's output with
``rosbags``' CDR deserializer.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Sequence
from typing import NamedTuple

#: The encapsulation header of plain CDR, little endian (RTPS's CDR_LE).
ENCAPSULATION = b"\x00\x01\x00\x00"
_HEADER_LEN = len(ENCAPSULATION)

_U32 = struct.Struct("<I")
_F64 = struct.Struct("<d")
_TIME = struct.Struct("<iI")
_TRANSFORM = struct.Struct("<7d")
_D3 = struct.Struct("<3d")
_D4 = struct.Struct("<4d")
_D9 = struct.Struct("<9d")
_I8 = struct.Struct("<b")
_U16 = struct.Struct("<H")
_NAV_SAT_BODY = struct.Struct("<12dB")   # latitude, longitude, altitude, covariance[9], type
_BATTERY_BODY = struct.Struct("<7f4B")   # voltage … percentage; status, health, technology,
                                         # present
_NUL = b"\x00"
_ZEROS = bytes(8)

#: A covariance matrix all zeros: ROS's "covariance unknown" for a value that is known.
UNKNOWN_COVARIANCE: tuple[float, ...] = (0.0,) * 9
#: Element 0 = -1: ROS's "this value is not provided" (REP-145, sensor_msgs/Imu).
NOT_PROVIDED: tuple[float, ...] = (-1.0,) + (0.0,) * 8
_ZERO3 = (0.0, 0.0, 0.0)
_NAN = math.nan
_PACKED_COVARIANCE = {UNKNOWN_COVARIANCE: _D9.pack(*UNKNOWN_COVARIANCE),
                      NOT_PROVIDED: _D9.pack(*NOT_PROVIDED)}


class Transform(NamedTuple):
    """One ``geometry_msgs/msg/TransformStamped``: ``parent`` → ``child`` at ``stamp_ns``
    (ns since the epoch), ``translation`` (x, y, z) in metres, ``rotation`` (x, y, z, w)."""

    stamp_ns: int
    parent: str
    child: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]


class DiagnosticStatus(NamedTuple):
    """One ``diagnostic_msgs/msg/DiagnosticStatus``: ``level`` (OK 0, WARN 1, ERROR 2,
    STALE 3), ``name``, ``message``, ``hardware_id``, ``values`` (key, value) pairs."""

    level: int
    name: str
    message: str
    hardware_id: str
    values: tuple[tuple[str, str], ...] = ()


# Diagnostic levels (diagnostic_msgs/msg/DiagnosticStatus).
OK, WARN, ERROR, STALE = 0, 1, 2, 3


def _align(buf: bytearray, n: int) -> None:
    pad = -(len(buf) - _HEADER_LEN) % n
    if pad:
        buf += _ZEROS[:pad]


def _string(buf: bytearray, s: str) -> None:
    data = s.encode()
    _align(buf, 4)
    buf += _U32.pack(len(data) + 1)
    buf += data
    buf += _NUL


@functools.lru_cache(maxsize=1024)
def _strings_at(strings: tuple[str, ...], offset: int, align: int) -> bytes:
    """``strings`` serialized from ``offset`` (mod 8; a multiple of 4) on, then the padding
    to the next multiple of ``align``: the part of a message that depends only on its frame
    names, made once per name (the hot path's headers)."""
    buf = bytearray(ENCAPSULATION + bytes(offset))
    for s in strings:
        _string(buf, s)
    _align(buf, align)
    return bytes(buf[_HEADER_LEN + offset:])


def _covariance(values: Sequence[float]) -> bytes:
    packed = _PACKED_COVARIANCE.get(values) if isinstance(values, tuple) else None
    return packed if packed is not None else _D9.pack(*values)


def _header(buf: bytearray, stamp_ns: int, frame_id: str) -> None:
    """A ``std_msgs/msg/Header``: stamp (``builtin_interfaces/msg/Time``), frame_id."""
    _align(buf, 4)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    buf += _TIME.pack(sec, nanosec)
    _string(buf, frame_id)


def without_header(cdr: bytes) -> bytes:
    """The serialized data after the encapsulation header (what a DDS writer is given)."""
    return cdr[_HEADER_LEN:]


def string(data: str) -> bytes:
    """``std_msgs/msg/String``."""
    buf = bytearray(ENCAPSULATION)
    _string(buf, data)
    return bytes(buf)


def boolean(data: bool) -> bytes:
    """``std_msgs/msg/Bool``."""
    return ENCAPSULATION + (b"\x01" if data else b"\x00")


def float64(data: float) -> bytes:
    """``std_msgs/msg/Float64``."""
    return ENCAPSULATION + _F64.pack(data)


def imu(stamp_ns: int, frame_id: str,
        orientation: tuple[float, float, float, float],
        linear_acceleration: tuple[float, float, float],
        angular_velocity: tuple[float, float, float] | None = None,
        orientation_covariance: Sequence[float] = UNKNOWN_COVARIANCE,
        linear_acceleration_covariance: Sequence[float] = UNKNOWN_COVARIANCE) -> bytes:
    """``sensor_msgs/msg/Imu``: ``orientation`` (x, y, z, w); an ``angular_velocity`` of None
    is sent as zeros with its covariance marked not provided (element 0 = -1)."""
    if angular_velocity is None:
        angular_velocity, av_cov = _ZERO3, NOT_PROVIDED
    else:
        av_cov = UNKNOWN_COVARIANCE
    # header (time at 0, frame_id at 8), then doubles aligned on 8
    return b"".join((ENCAPSULATION, _TIME.pack(*divmod(stamp_ns, 1_000_000_000)),
                     _strings_at((frame_id,), 8, 8),
                     _D4.pack(*orientation), _covariance(orientation_covariance),
                     _D3.pack(*angular_velocity), _covariance(av_cov),
                     _D3.pack(*linear_acceleration),
                     _covariance(linear_acceleration_covariance)))


def tf_message(transforms: Sequence[Transform]) -> bytes:
    """``tf2_msgs/msg/TFMessage``: a sequence of ``geometry_msgs/msg/TransformStamped``."""
    parts = [ENCAPSULATION, _U32.pack(len(transforms))]
    offset = 4
    for t in transforms:  # each header (a time, then frame_id) starts on a multiple of 4
        names = _strings_at((t.parent, t.child), (offset + 8) % 8, 8)
        parts += (_TIME.pack(*divmod(t.stamp_ns, 1_000_000_000)), names,
                  _TRANSFORM.pack(*t.translation, *t.rotation))
        offset += 8 + len(names) + _TRANSFORM.size
    return b"".join(parts)


# sensor_msgs/msg/NavSatStatus
STATUS_NO_FIX, STATUS_FIX, STATUS_SBAS_FIX, STATUS_GBAS_FIX = -1, 0, 1, 2
SERVICE_GPS = 1
COVARIANCE_TYPE_UNKNOWN = 0


def nav_sat_fix(stamp_ns: int, frame_id: str, latitude: float, longitude: float,
                altitude: float, status: int = STATUS_FIX, service: int = SERVICE_GPS,
                position_covariance: Sequence[float] = UNKNOWN_COVARIANCE,
                position_covariance_type: int = COVARIANCE_TYPE_UNKNOWN) -> bytes:
    """``sensor_msgs/msg/NavSatFix``: degrees, altitude in metres above the WGS-84
    ellipsoid (NaN when unknown)."""
    buf = bytearray(ENCAPSULATION)
    _header(buf, stamp_ns, frame_id)
    buf += _I8.pack(status)  # NavSatStatus: int8 status, uint16 service
    _align(buf, 2)
    buf += _U16.pack(service)
    _align(buf, 8)
    buf += _NAV_SAT_BODY.pack(latitude, longitude, altitude, *position_covariance,
                              position_covariance_type)
    return bytes(buf)


# sensor_msgs/msg/BatteryState
POWER_SUPPLY_STATUS_UNKNOWN = 0
POWER_SUPPLY_HEALTH_UNKNOWN = 0
POWER_SUPPLY_TECHNOLOGY_UNKNOWN = 0


def battery_state(stamp_ns: int, frame_id: str, voltage: float, current: float = _NAN,
                  charge: float = _NAN, capacity: float = _NAN,
                  design_capacity: float = _NAN, percentage: float = _NAN,
                  temperature: float = _NAN, present: bool = True,
                  power_supply_status: int = POWER_SUPPLY_STATUS_UNKNOWN,
                  power_supply_health: int = POWER_SUPPLY_HEALTH_UNKNOWN,
                  power_supply_technology: int = POWER_SUPPLY_TECHNOLOGY_UNKNOWN,
                  location: str = "", serial_number: str = "") -> bytes:
    """``sensor_msgs/msg/BatteryState``: SI units (V, °C, A, Ah), ``percentage`` 0..1;
    NaN = not measured (as the message defines); no per-cell values."""
    buf = bytearray(ENCAPSULATION)
    _header(buf, stamp_ns, frame_id)
    _align(buf, 4)
    buf += _BATTERY_BODY.pack(voltage, temperature, current, charge, capacity,
                              design_capacity, percentage, power_supply_status,
                              power_supply_health, power_supply_technology, bool(present))
    buf += _U32.pack(0)  # cell_voltage: aligned (7 floats + 4 bytes)
    buf += _U32.pack(0)  # cell_temperature
    _string(buf, location)
    _string(buf, serial_number)
    return bytes(buf)


def diagnostic_array(stamp_ns: int, statuses: Sequence[DiagnosticStatus],
                     frame_id: str = "") -> bytes:
    """``diagnostic_msgs/msg/DiagnosticArray``."""
    buf = bytearray(ENCAPSULATION)
    _header(buf, stamp_ns, frame_id)
    _align(buf, 4)
    buf += _U32.pack(len(statuses))
    for s in statuses:
        buf.append(s.level & 0xFF)
        _string(buf, s.name)
        _string(buf, s.message)
        _string(buf, s.hardware_id)
        _align(buf, 4)
        buf += _U32.pack(len(s.values))
        for key, value in s.values:
            _string(buf, key)
            _string(buf, value)
    return bytes(buf)
