"""The gateway's messages as F´ telemetry channels: one table, read by the packet builder and
by the dictionary generator, so the two can never disagree.

Every channel is ``<DEPLOYMENT>.<component>.<Name>`` with the id ``base + offset`` (``base``
defaults to :data:`DEFAULT_ID_BASE`, 0x100; components take blocks of 16):

=============  ======  =============================================================
component      offset  written from
=============  ======  =============================================================
``flight``     0x00    SM_UPDATE (and STATUS: state, armed; a MAVLink vehicle's state)
``status``     0x10    STATUS flags
``link``       0x20    link up/down, link statistics of a radio
``gps``        0x30    position
``battery``    0x40    battery
``vehicle``    0x50    a vehicle that is not an Aurora state machine (mode)
=============  ======  =============================================================

Values the message does not carry (``None``, NaN, infinity) are not written: F´ channels keep their
last value.  Angles are degrees (F´ ground tools show numbers as they arrive).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from dialects.states import SimpleState
from gateway.model import Battery, LinkEvent, LinkStats, Position, SmUpdate, Status, VehicleState

DEPLOYMENT = "Aurora"
DEFAULT_ID_BASE = 0x100
#: The F´ enum of the flight state (representation U8, as the wire carries it).
STATE_ENUM = f"{DEPLOYMENT}.FlightState"
STATE_ENUM_CONSTANTS: tuple[tuple[str, int], ...] = tuple((s.name, int(s)) for s in SimpleState)
MODE_STRING_SIZE = 32
FW_TRUE = 0xFF  # F´ serializes a bool as one byte, TRUE = 0xFF (fprime-gds rejects 1)


@dataclass(frozen=True)
class FType:
    """An F´ type as the JSON dictionary describes it, and its big-endian serialization."""

    name: str  # F32, U8, bool, string, or the qualified name of an enum
    kind: str  # float | integer | bool | string | qualifiedIdentifier
    size: int  # bits (bytes of text for a string)
    fmt: str = ""  # struct format of the value ("" for a string)
    signed: bool = False

    def descriptor(self) -> dict[str, Any]:
        """The dictionary's type descriptor."""
        d: dict[str, Any] = {"name": self.name, "kind": self.kind}
        if self.kind != "qualifiedIdentifier":
            d["size"] = self.size
        if self.kind == "integer":
            d["signed"] = self.signed
        return d


F32 = FType("F32", "float", 32, "f")
F64 = FType("F64", "float", 64, "d")
U8 = FType("U8", "integer", 8, "B")
U16 = FType("U16", "integer", 16, "H")
U32 = FType("U32", "integer", 32, "I")
BOOL = FType("bool", "bool", 8, "B")
STATE = FType(STATE_ENUM, "qualifiedIdentifier", 8, "B")
MODE = FType("string", "string", MODE_STRING_SIZE)


@dataclass(frozen=True)
class Channel:
    """One channel: its name in its component, id offset, type and meaning."""

    component: str
    name: str
    offset: int
    type: FType
    annotation: str
    fmt: str | None = None  # the dictionary's display format, e.g. "{.1f}"

    def full_name(self) -> str:
        return f"{DEPLOYMENT}.{self.component}.{self.name}"


def _c(component: str, name: str, offset: int, t: FType, note: str,
       fmt: str | None = None) -> Channel:
    return Channel(component, name, offset, t, note, fmt)


ALTITUDE = _c("flight", "Altitude", 0x00, F32, "Altitude above the pad, m", "{.1f}")
STATE_CH = _c("flight", "State", 0x01, STATE, "Flight state (state machine SIMPLE)")
ARMED = _c("flight", "Armed", 0x02, BOOL, "Pyro channels armed")
VELOCITY = _c("flight", "VerticalVelocity", 0x03, F32, "Vertical velocity, m/s, up", "{.2f}")
ACCEL = _c("flight", "Acceleration", 0x04, F32, "Total acceleration, m/s²", "{.2f}")
ACCEL_VERT = _c("flight", "VerticalAcceleration", 0x05, F32,
                "Body-vertical acceleration, m/s²", "{.2f}")
ROLL = _c("flight", "Roll", 0x06, F32, "Roll, degrees", "{.1f}")
PITCH = _c("flight", "Pitch", 0x07, F32, "Pitch, degrees", "{.1f}")
YAW = _c("flight", "Yaw", 0x08, F32, "Yaw, degrees", "{.1f}")
UPTIME = _c("flight", "Uptime", 0x09, U32, "Flight computer time since boot, ms")
SM_TYPE = _c("flight", "SmType", 0x0A, U8, "State machine (0 = SIMPLE)")

FLAGS = _c("status", "Flags", 0x10, U8,
           "STATUS flags: bit0 ARMED, bit1 IMU_OK, bit2 BARO_OK, bit3 CALIBRATED, bit4 LOG_READY")
IMU_OK = _c("status", "ImuOk", 0x11, BOOL, "IMU healthy")
BARO_OK = _c("status", "BaroOk", 0x12, BOOL, "Barometer healthy")
CALIBRATED = _c("status", "Calibrated", 0x13, BOOL, "Sensors calibrated")
LOG_READY = _c("status", "LogReady", 0x14, BOOL, "Flight log ready")

LINK_UP = _c("link", "Up", 0x20, BOOL, "The rocket's link is up (frames arriving)")
RSSI = _c("link", "Rssi", 0x21, F32, "Uplink RSSI, dBm", "{.0f}")
LQ = _c("link", "LinkQuality", 0x22, U8, "Uplink link quality, %")
SNR = _c("link", "Snr", 0x23, F32, "Uplink SNR, dB", "{.0f}")
TX_POWER = _c("link", "TxPower", 0x24, U16, "Transmit power, mW")
DL_RSSI = _c("link", "DownlinkRssi", 0x25, F32, "Downlink RSSI, dBm", "{.0f}")
DL_LQ = _c("link", "DownlinkLinkQuality", 0x26, U8, "Downlink link quality, %")
DL_SNR = _c("link", "DownlinkSnr", 0x27, F32, "Downlink SNR, dB", "{.0f}")
RF_MODE = _c("link", "RfMode", 0x28, U8, "Radio's RF mode (packet rate index)")
ANTENNA = _c("link", "Antenna", 0x29, U8, "Active antenna")

LAT = _c("gps", "Latitude", 0x30, F64, "Latitude, degrees (WGS-84)", "{.7f}")
LON = _c("gps", "Longitude", 0x31, F64, "Longitude, degrees (WGS-84)", "{.7f}")
ALT_MSL = _c("gps", "AltitudeMsl", 0x32, F32, "Altitude above mean sea level, m", "{.1f}")
REL_ALT = _c("gps", "RelativeAltitude", 0x33, F32, "Altitude above home, m", "{.1f}")
SPEED = _c("gps", "GroundSpeed", 0x34, F32, "Ground speed, m/s", "{.1f}")
COURSE = _c("gps", "Course", 0x35, F32, "Course over ground, degrees", "{.0f}")
SATS = _c("gps", "Satellites", 0x36, U8, "Satellites used")
FIX = _c("gps", "FixType", 0x37, U8, "Fix type (0 none, 2 2D, 3 3D …)")

VOLTAGE = _c("battery", "Voltage", 0x40, F32, "Battery voltage, V", "{.2f}")
CURRENT = _c("battery", "Current", 0x41, F32, "Battery current, A", "{.2f}")
CONSUMED = _c("battery", "Consumed", 0x42, F32, "Charge consumed, mAh", "{.0f}")
REMAINING = _c("battery", "Remaining", 0x43, U8, "Charge remaining, %")

MODE_CH = _c("vehicle", "Mode", 0x50, MODE, "Flight mode of a vehicle that is not an Aurora "
             "state machine (e.g. a MAVLink autopilot)")
CUSTOM_MODE = _c("vehicle", "CustomMode", 0x51, U32, "That vehicle's custom mode number")

CHANNELS: tuple[Channel, ...] = (
    ALTITUDE, STATE_CH, ARMED, VELOCITY, ACCEL, ACCEL_VERT, ROLL, PITCH, YAW, UPTIME, SM_TYPE,
    FLAGS, IMU_OK, BARO_OK, CALIBRATED, LOG_READY,
    LINK_UP, RSSI, LQ, SNR, TX_POWER, DL_RSSI, DL_LQ, DL_SNR, RF_MODE, ANTENNA,
    LAT, LON, ALT_MSL, REL_ALT, SPEED, COURSE, SATS, FIX,
    VOLTAGE, CURRENT, CONSUMED, REMAINING,
    MODE_CH, CUSTOM_MODE,
)


def _bool(v: bool) -> int:
    return FW_TRUE if v else 0


def _deg(rad: float) -> float:
    return math.degrees(rad)


def _u8(v: int | None) -> int | None:
    return None if v is None else max(0, min(0xFF, int(v)))


def _u16(v: float | None) -> int | None:
    return None if v is None else max(0, min(0xFFFF, int(v)))


Getter = Callable[[Any], Any]

#: Message type → the channels it writes and how each value is read (None: not written).
WRITERS: dict[type, tuple[tuple[Channel, Getter], ...]] = {
    SmUpdate: (
        (ALTITUDE, lambda m: m.altitude_m),
        (STATE_CH, lambda m: m.state & 0xFF),
        (ARMED, lambda m: _bool(m.armed)),
        (VELOCITY, lambda m: m.velocity_mps),
        (ACCEL, lambda m: m.acceleration_mps2),
        (ACCEL_VERT, lambda m: m.accel_vert_mps2),
        (ROLL, lambda m: _deg(m.roll_rad)),
        (PITCH, lambda m: _deg(m.pitch_rad)),
        (YAW, lambda m: _deg(m.yaw_rad)),
        (UPTIME, lambda m: m.timestamp_ms & 0xFFFFFFFF),
        (SM_TYPE, lambda m: m.sm_type & 0xFF),
    ),
    Status: (
        (STATE_CH, lambda m: m.state & 0xFF),
        (ARMED, lambda m: _bool(m.armed)),
        (UPTIME, lambda m: m.timestamp_ms & 0xFFFFFFFF),
        (FLAGS, lambda m: m.flags & 0xFF),
        (IMU_OK, lambda m: _bool(m.imu_ok)),
        (BARO_OK, lambda m: _bool(m.baro_ok)),
        (CALIBRATED, lambda m: _bool(m.calibrated)),
        (LOG_READY, lambda m: _bool(m.log_ready)),
    ),
    LinkEvent: ((LINK_UP, lambda m: _bool(m.up)),),
    LinkStats: (
        (RSSI, lambda m: m.rssi_dbm),
        (LQ, lambda m: _u8(m.link_quality_pct)),
        (SNR, lambda m: m.snr_db),
        (TX_POWER, lambda m: _u16(m.tx_power_mw)),
        (DL_RSSI, lambda m: m.downlink_rssi_dbm),
        (DL_LQ, lambda m: _u8(m.downlink_link_quality_pct)),
        (DL_SNR, lambda m: m.downlink_snr_db),
        (RF_MODE, lambda m: _u8(m.rf_mode)),
        (ANTENNA, lambda m: _u8(m.antenna)),
    ),
    Position: (
        (LAT, lambda m: m.lat_deg),
        (LON, lambda m: m.lon_deg),
        (ALT_MSL, lambda m: m.alt_amsl_m),
        (REL_ALT, lambda m: m.relative_alt_m),
        (SPEED, lambda m: m.ground_speed_mps),
        (COURSE, lambda m: m.course_deg),
        (SATS, lambda m: _u8(m.satellites)),
        (FIX, lambda m: _u8(m.fix_type)),
    ),
    Battery: (
        (VOLTAGE, lambda m: m.voltage_v),
        (CURRENT, lambda m: m.current_a),
        (CONSUMED, lambda m: m.consumed_mah),
        (REMAINING, lambda m: _u8(m.remaining_pct)),
    ),
    VehicleState: (
        (ARMED, lambda m: _bool(m.armed)),
        (MODE_CH, lambda m: m.mode),
        (CUSTOM_MODE, lambda m: None if m.custom_mode is None else m.custom_mode & 0xFFFFFFFF),
        (ALTITUDE, lambda m: m.altitude_m),
        (VELOCITY, lambda m: m.climb_mps),
        (ROLL, lambda m: None if m.roll_rad is None else _deg(m.roll_rad)),
        (PITCH, lambda m: None if m.pitch_rad is None else _deg(m.pitch_rad)),
        (YAW, lambda m: None if m.yaw_rad is None else _deg(m.yaw_rad)),
    ),
}


@dataclass
class ChannelCodec:
    """Serializes one channel's entry, ``[id U32][time tag 11 B][value]``, for one id base."""

    channel: Channel
    id: int
    _struct: struct.Struct | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        fmt = self.channel.type.fmt
        self._struct = struct.Struct(">IHBII" + fmt) if fmt else None

    def entry(self, value: Any, time_tag: tuple[int, int, int, int]) -> bytes | None:
        """The serialized entry, or None when the value is missing or not representable."""
        if value is None:
            return None
        s = self._struct
        if s is None:  # a string: U16 length, then the bytes, cut to the channel's size
            text = str(value).encode("utf-8", "replace")[:self.channel.type.size]
            return (struct.pack(">IHBII", self.id, *time_tag)
                    + struct.pack(">H", len(text)) + text)
        if isinstance(value, float) and not math.isfinite(value):
            return None
        try:
            return s.pack(self.id, *time_tag, value)
        except struct.error:
            return None


def codecs(id_base: int = DEFAULT_ID_BASE) -> dict[type, tuple[tuple[ChannelCodec, Getter], ...]]:
    """:data:`WRITERS` with each channel's codec for ``id_base``."""
    made: dict[Channel, ChannelCodec] = {}

    def codec(ch: Channel) -> ChannelCodec:
        if ch not in made:
            made[ch] = ChannelCodec(ch, id_base + ch.offset)
        return made[ch]

    return {t: tuple((codec(ch), get) for ch, get in rows) for t, rows in WRITERS.items()}


def check_id_base(value: int) -> None:
    """Raise ValueError when ``value`` cannot hold every channel's id in a U32."""
    top = max(ch.offset for ch in CHANNELS)
    if not 0 <= value <= 0xFFFFFFFF - top:
        raise ValueError(f"{value} is not an id base: 0..{0xFFFFFFFF - top} (every channel "
                         "id, base + offset, is a U32)")
