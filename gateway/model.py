"""The gateway's messages: small, immutable, typed records.

Messages are ``NamedTuple`` classes rather than frozen dataclasses: they are just as
immutable and typed, and about eight times cheaper to build, which is what lets the wire
decoder keep several times ahead of pymavlink (see ``tools/bench/bench_decode.py``).

Every message carries provenance besides its fields:

``raw``
    (wire-decoded kinds) the untouched frame it was decoded from (empty when it was built in
    memory), so a relay or recorder can pass on exactly what arrived;
``origin``
    the name of the source (or backend) of *this* gateway that produced it, so a backend can
    refuse to send a message back where it came from;
``via``
    "" when the message came from the rocket's own link (serial, simulation, replay);
    otherwise the network and the system it came from, ``<protocol>:<id>`` —
    ``zenoh:<gateway id>``, ``mavlink:<system id>`` — so loop prevention between chained
    gateways reads the message, never a process-wide registry;
``vehicle``
    the name of the vehicle it is about (``[A-Za-z][A-Za-z0-9_-]*``, see
    :mod:`gateway.vehicles`): a source's own name for the rocket it hears, or one per system
    for a source that hears several (MAVLink, Zenoh, UAVTalk); backends keep their state per
    vehicle.  "" only on what a backend emits itself (a ground link's commands).

Provenance takes part in equality like every other field; compare :meth:`fields` to ignore
it.  Routing is by type (see :class:`gateway.backend.Routes`); :func:`kind` names a message's
type in counters, recordings and publications.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from dialects.states import is_in_flight, is_on_pad, state_name

STATUS_ARMED = 0x01
STATUS_IMU_OK = 0x02
STATUS_BARO_OK = 0x04
STATUS_CALIBRATED = 0x08
STATUS_LOG_READY = 0x10

SM_UPDATE_F32_LEN = 36
SM_UPDATE_F64_LEN = 64


class SmUpdate(NamedTuple):
    """A state-machine snapshot (wire type 0x01), either revision.

    ``payload_len`` remembers the revision that arrived (36: f32 fields, 64: f64 fields) and
    ``reserved`` the byte the firmware leaves zero, so re-encoding reproduces the frame.
    """

    timestamp_ms: int
    state: int
    armed: bool
    sm_type: int
    altitude_m: float
    acceleration_mps2: float
    accel_vert_mps2: float
    velocity_mps: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    payload_len: int = SM_UPDATE_F64_LEN
    reserved: int = 0
    raw: bytes = b""
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    @property
    def state_name(self) -> str:
        return state_name(self.sm_type, self.state)

    @property
    def in_flight(self) -> bool:
        return is_in_flight(self.sm_type, self.state)

    @property
    def on_pad(self) -> bool:
        return is_on_pad(self.sm_type, self.state)

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)


class Status(NamedTuple):
    """The low-rate health heartbeat (wire type 0x02); flags decode to named booleans."""

    timestamp_ms: int
    state: int
    sm_type: int
    flags: int
    reserved: int = 0
    raw: bytes = b""
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    @property
    def armed(self) -> bool:
        return bool(self.flags & STATUS_ARMED)

    @property
    def imu_ok(self) -> bool:
        return bool(self.flags & STATUS_IMU_OK)

    @property
    def baro_ok(self) -> bool:
        return bool(self.flags & STATUS_BARO_OK)

    @property
    def calibrated(self) -> bool:
        return bool(self.flags & STATUS_CALIBRATED)

    @property
    def log_ready(self) -> bool:
        return bool(self.flags & STATUS_LOG_READY)

    @property
    def state_name(self) -> str:
        return state_name(self.sm_type, self.state)

    def health(self) -> dict[str, bool]:
        """The flags as named booleans."""
        return {
            "armed": self.armed,
            "imu_ok": self.imu_ok,
            "baro_ok": self.baro_ok,
            "calibrated": self.calibrated,
            "log_ready": self.log_ready,
        }

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)

    @staticmethod
    def make_flags(
        *,
        armed: bool = False,
        imu_ok: bool = False,
        baro_ok: bool = False,
        calibrated: bool = False,
        log_ready: bool = False,
    ) -> int:
        """Build a flags byte from named booleans."""
        return (
            (STATUS_ARMED if armed else 0)
            | (STATUS_IMU_OK if imu_ok else 0)
            | (STATUS_BARO_OK if baro_ok else 0)
            | (STATUS_CALIBRATED if calibrated else 0)
            | (STATUS_LOG_READY if log_ready else 0)
        )


class RawFrame(NamedTuple):
    """A frame nobody decodes (unknown type, or type 0x01 of an unknown length): kept whole."""

    type: int
    payload: bytes
    raw: bytes = b""
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)


class LinkEvent(NamedTuple):
    """A source's link went up (first valid frame) or down (silence past the timeout)."""

    source: str
    up: bool
    silence_s: float = 0.0
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)


class LinkStats(NamedTuple):
    """Radio link quality as a receiver reports it (e.g. CRSF 0x14); ``None`` = not reported.

    RSSI in dBm (negative), link quality in percent, SNR in dB, TX power in mW.
    """

    rssi_dbm: float | None = None
    link_quality_pct: int | None = None
    snr_db: float | None = None
    tx_power_mw: int | None = None
    downlink_rssi_dbm: float | None = None
    downlink_link_quality_pct: int | None = None
    downlink_snr_db: float | None = None
    rf_mode: int | None = None
    antenna: int | None = None
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)


class Position(NamedTuple):
    """A GNSS fix: WGS-84 degrees, altitude above mean sea level; ``None`` = not known."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float | None = None
    relative_alt_m: float | None = None
    ground_speed_mps: float | None = None
    course_deg: float | None = None
    satellites: int | None = None
    fix_type: int | None = None
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)


class Battery(NamedTuple):
    """A battery's state; ``None`` = not measured."""

    voltage_v: float
    current_a: float | None = None
    consumed_mah: float | None = None
    remaining_pct: int | None = None
    battery_id: int = 0
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)


class VehicleState(NamedTuple):
    """A vehicle that is not an Aurora state machine (e.g. a MAVLink autopilot): armed,
    mode and attitude/altitude as it reports them; ``None`` = not reported."""

    armed: bool
    mode: str
    custom_mode: int | None = None
    roll_rad: float | None = None
    pitch_rad: float | None = None
    yaw_rad: float | None = None
    altitude_m: float | None = None
    climb_mps: float | None = None
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)


class RcChannels(NamedTuple):
    """Pilot or servo commands from a ground link (an RC receiver's channels, an XBee command
    packet, a ground station's RC override): pulse widths in µs, 1000..2000 nominal, channel
    ``i`` at index ``i``; ``None`` = not sent (a channel the sender leaves alone).
    ``seq``: the sender's sequence number, when its protocol has one."""

    channels_us: tuple[int | None, ...]
    seq: int | None = None
    origin: str = ""
    via: str = ""
    vehicle: str = ""

    def fields(self) -> dict[str, Any]:
        """The message's own fields, without its provenance (see :func:`own_fields`)."""
        return own_fields(self)


#: The name of each message type in counters, recordings and publications.  A backend package
#: may define more message types (routing is by type); they are named by :func:`kind` too.
KINDS: dict[type, str] = {
    SmUpdate: "sm_update", Status: "status", RawFrame: "raw", LinkEvent: "link",
    LinkStats: "link_stats", Position: "position", Battery: "battery",
    VehicleState: "vehicle_state", RcChannels: "rc_channels",
}

#: The message classes defined here.
MESSAGE_TYPES: tuple[type, ...] = tuple(KINDS)


class GatewayStats(NamedTuple):
    """Another gateway's counters, as its Zenoh backend publishes them (``gateway_stats``):
    ``backends`` and ``sources`` map each name to its ``stats()``."""

    gateway: str
    backends: dict[str, Any]
    sources: dict[str, Any]
    origin: str = ""
    via: str = ""

_PROVENANCE = ("raw", "origin", "via", "vehicle")


def kind(msg: object) -> str:
    """The name of ``msg``'s type (``"sm_update"``, ``"status"`` …); a type defined outside
    this module is named by its class name in lower case."""
    cls = type(msg)
    name = KINDS.get(cls)
    return name if name is not None else cls.__name__.lower()


def own_fields(msg: Any) -> dict[str, Any]:
    """A message's fields as a dict, without its provenance (``raw``, ``origin``, ``via``,
    ``vehicle``)."""
    d: dict[str, Any] = msg._asdict()
    for key in _PROVENANCE:
        d.pop(key, None)
    return d

Message = (SmUpdate | Status | RawFrame | LinkEvent | LinkStats | Position | Battery
           | VehicleState | RcChannels)
