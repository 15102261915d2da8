"""Sans-I/O CRSF frames: typed records in engineering units, their payloads, and the frame.

A frame is ``[sync][len][type][payload…][crc]``: ``len`` counts type + payload + crc (2..62),
the CRC is CRC-8/DVB-S2 (poly 0xD5, init 0) over type and payload, multi-byte fields are
big-endian.  See ``shared/specs/crsf.md``.

Every record is a ``NamedTuple``; its frame type is in :data:`FRAME_TYPES`.  :func:`encode` turns a
record into a frame and :func:`decode_payload` turns a payload back into a record, so the two
round-trip (to the field's resolution).  Conventions of every numeric field:

* values are rounded half away from zero and clamped to what the field holds;
* ``None`` (or NaN) means "not known" and goes on the wire as all-0xFF bytes, which EdgeTX
  ignores; a real value that would encode as all-0xFF is nudged one step (to the neighbour
  nearer the true value) so that it still shows.  Decoding maps all-0xFF back to ``None``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from gateway.crc import dvb_s2

SYNC_FC = 0xC8  # flight-controller address: what a receiver expects telemetry to carry
SYNC_RADIO = 0xEA  # radio transmitter (handset)
SYNC_RX = 0xEC  # receiver
SYNC_BYTES = frozenset({SYNC_FC, SYNC_RADIO, SYNC_RX})

MIN_LEN = 2  # type + crc
MAX_LEN = 62  # the len byte; a whole frame is at most 64 bytes
MAX_FRAME = MAX_LEN + 2
MAX_PAYLOAD = MAX_LEN - 2
EXTENDED_TYPE_MIN = 0x28  # types from here on carry [dest][origin] before the payload

FRAME_GPS = 0x02
FRAME_VARIO = 0x07
FRAME_BATTERY = 0x08
FRAME_BARO_ALTITUDE = 0x09
FRAME_AIRSPEED = 0x0A
FRAME_RPM = 0x0C
FRAME_TEMPERATURE = 0x0D
FRAME_VOLTAGES = 0x0E
FRAME_ACCEL_GYRO = 0x13
FRAME_LINK_STATISTICS = 0x14
FRAME_RC_CHANNELS = 0x16
FRAME_ATTITUDE = 0x1E
FRAME_FLIGHT_MODE = 0x21

#: EdgeTX displays at most this many characters of a flight-mode text.
FLIGHT_MODE_MAX_CHARS = 13
MAX_RPM_VALUES = 19
MAX_TEMPERATURES = 20
MAX_VOLTAGES = 29
RC_CHANNELS = 16
RC_CHANNEL_MAX = 0x7FF
#: Link-statistics TX power enum → mW (CRSF / ExpressLRS).
TX_POWER_MW = (0, 10, 25, 100, 500, 1000, 2000, 250, 50)

GYRO_DPS_PER_LSB = 2000.0 / 32767.0
ACCEL_G_PER_LSB = 16.0 / 32767.0
GPS_ALTITUDE_OFFSET_M = 1000
BARO_DM_OFFSET = 10000  # packed altitude, MSB clear: decimetres + 10000
BARO_METRES_FLAG = 0x8000  # packed altitude, MSB set: whole metres
BARO_MAX_DM_FORM = 0x7FFF - BARO_DM_OFFSET  # 22767 dm = 2276.7 m
BARO_MAX_METRES = 0x7FFE  # 0xFFFE: 32766 m (0xFFFF is "no value")

_crc8 = dvb_s2


def crc(data: bytes) -> int:
    """CRC-8/DVB-S2 of ``data`` (poly 0xD5, init 0, not reflected; check value 0xBC)."""
    return _crc8(data)


def build_frame(ftype: int, payload: bytes, sync: int = SYNC_FC) -> bytes:
    """Wrap ``payload`` in a CRSF frame; ValueError when it does not fit."""
    if not 0 <= ftype <= 0xFF:
        raise ValueError(f"frame type {ftype} is not a byte")
    if not 0 <= sync <= 0xFF:
        raise ValueError(f"sync {sync} is not a byte")
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = bytes((ftype,)) + payload
    return bytes((sync, len(body) + 1)) + body + bytes((_crc8(body),))


# -- numeric fields ---------------------------------------------------------------------------

def _round(x: float) -> int:
    """Round half away from zero (what C's lround does; Python's round() is half-even)."""
    return math.floor(x + 0.5) if x >= 0 else -math.floor(-x + 0.5)


def quantize(value: float | None, scale: float, nbytes: int, signed: bool,
             lo: int | None = None, hi: int | None = None) -> int:
    """``value × scale`` as the integer an ``nbytes`` field carries.

    Rounded, clamped to the field (and to ``lo``..``hi`` when given); ``None``/NaN gives the
    all-0xFF code (−1 signed, maximum unsigned), which no real value produces: an unsigned
    value stops one below it, a signed −1 moves to 0 or −2, whichever is nearer.
    """
    bits = 8 * nbytes
    if signed:
        fmin, fmax, none_code = -(1 << (bits - 1)), (1 << (bits - 1)) - 1, -1
    else:
        fmin, fmax, none_code = 0, (1 << bits) - 2, (1 << bits) - 1
    if lo is not None:
        fmin = max(fmin, lo)
    if hi is not None:
        fmax = min(fmax, hi)
    if value is None or value != value:
        return none_code
    x = value * scale
    k = fmin if x <= fmin else fmax if x >= fmax else _round(x)
    if k == -1 and signed:
        k = 0 if x > -1 else -2
    return k


def _pack(k: int, nbytes: int, signed: bool) -> bytes:
    return k.to_bytes(nbytes, "big", signed=signed)


def _field(value: float | None, scale: float, nbytes: int, signed: bool,
           lo: int | None = None, hi: int | None = None) -> bytes:
    return _pack(quantize(value, scale, nbytes, signed, lo, hi), nbytes, signed)


def _unpack(data: bytes, offset: int, nbytes: int, signed: bool) -> int | None:
    """The field at ``offset``; None when its bytes are all 0xFF (EdgeTX: no value)."""
    raw = data[offset:offset + nbytes]
    if raw == b"\xff" * nbytes:
        return None
    return int.from_bytes(raw, "big", signed=signed)


def _scaled(k: int | None, scale: float) -> float | None:
    return None if k is None else k / scale


def wrap_angle(a: float) -> float:
    """``a`` wrapped to [−π, π) (NaN stays NaN)."""
    if not math.isfinite(a):
        return a
    return (a + math.pi) % (2.0 * math.pi) - math.pi


# -- records ----------------------------------------------------------------------------------

class Gps(NamedTuple):
    """0x02: position, ground speed (km/h), course (°), altitude AMSL (m), satellites."""

    lat_deg: float | None
    lon_deg: float | None
    groundspeed_kmh: float | None = None
    heading_deg: float | None = None
    altitude_m: float | None = None
    satellites: int | None = None


class Vario(NamedTuple):
    """0x07: vertical speed, up positive."""

    vspeed_mps: float | None


class Battery(NamedTuple):
    """0x08: voltage (V), current (A), capacity used (mAh), remaining (%)."""

    voltage_v: float | None
    current_a: float | None = None
    capacity_mah: float | None = None
    remaining_pct: int | None = None


class BaroAltitude(NamedTuple):
    """0x09: barometric altitude (m), with vertical speed (ELRS 4-byte form) or without it
    (``vspeed_mps`` None: the 2-byte TBS form)."""

    altitude_m: float | None
    vspeed_mps: float | None = None


class Airspeed(NamedTuple):
    """0x0A: airspeed (km/h)."""

    speed_kmh: float | None


class Rpm(NamedTuple):
    """0x0C: 1..19 RPM values of one source."""

    source_id: int
    rpm: tuple[int | None, ...]


class Temperatures(NamedTuple):
    """0x0D: up to 20 temperatures (°C) of one source."""

    source_id: int
    temps_c: tuple[float | None, ...]


class Voltages(NamedTuple):
    """0x0E: up to 29 voltages (V, sent as mV) of one source."""

    source_id: int
    volts: tuple[float | None, ...]


class AccelGyro(NamedTuple):
    """0x13: one IMU sample: time (µs), gyro (°/s), accelerometer (g), temperature (°C)."""

    sample_time_us: int | None
    gyro_x_dps: float | None
    gyro_y_dps: float | None
    gyro_z_dps: float | None
    accel_x_g: float | None
    accel_y_g: float | None
    accel_z_g: float | None
    temp_c: float | None = None


class LinkStatistics(NamedTuple):
    """0x14: what a receiver reports about the radio link (RSSI in dBm, negative; the wire
    carries its magnitude).  The gateway reads these; it never sends them."""

    uplink_rssi_ant1_dbm: int
    uplink_rssi_ant2_dbm: int
    uplink_link_quality_pct: int
    uplink_snr_db: int
    active_antenna: int
    rf_mode: int
    uplink_tx_power: int  # enum index, see TX_POWER_MW
    downlink_rssi_dbm: int
    downlink_link_quality_pct: int
    downlink_snr_db: int

    @property
    def uplink_tx_power_mw(self) -> int | None:
        i = self.uplink_tx_power
        return TX_POWER_MW[i] if 0 <= i < len(TX_POWER_MW) else None

    @property
    def uplink_rssi_dbm(self) -> int:
        """RSSI of the active antenna."""
        return self.uplink_rssi_ant2_dbm if self.active_antenna == 1 else self.uplink_rssi_ant1_dbm


class RcChannels(NamedTuple):
    """0x16: 16 channels of 11 bits (172..1811 is 988..2012 µs)."""

    channels: tuple[int, ...]

    def microseconds(self) -> tuple[float, ...]:
        """The channels as servo pulse widths (EdgeTX/Betaflight scaling)."""
        return tuple(1500.0 + (v - 992) * 5.0 / 8.0 for v in self.channels)


class Attitude(NamedTuple):
    """0x1E: pitch, roll, yaw (rad), each wrapped to ±π before encoding."""

    pitch_rad: float | None
    roll_rad: float | None
    yaw_rad: float | None


class FlightMode(NamedTuple):
    """0x21: a short ASCII text (EdgeTX shows at most 13 characters)."""

    text: str


class UnknownFrame(NamedTuple):
    """A frame of a type not decoded here, or whose payload did not fit its type."""

    type: int
    payload: bytes
    dest: int | None = None  # extended-header frames (type ≥ 0x28) only
    origin: int | None = None


#: The frame type of each record.
FRAME_TYPES: dict[type, int] = {
    Gps: FRAME_GPS,
    Vario: FRAME_VARIO,
    Battery: FRAME_BATTERY,
    BaroAltitude: FRAME_BARO_ALTITUDE,
    Airspeed: FRAME_AIRSPEED,
    Rpm: FRAME_RPM,
    Temperatures: FRAME_TEMPERATURE,
    Voltages: FRAME_VOLTAGES,
    AccelGyro: FRAME_ACCEL_GYRO,
    LinkStatistics: FRAME_LINK_STATISTICS,
    RcChannels: FRAME_RC_CHANNELS,
    Attitude: FRAME_ATTITUDE,
    FlightMode: FRAME_FLIGHT_MODE,
}


Record = (Gps | Vario | Battery | BaroAltitude | Airspeed | Rpm | Temperatures | Voltages
          | AccelGyro | LinkStatistics | RcChannels | Attitude | FlightMode | UnknownFrame)


# -- payload encoders -------------------------------------------------------------------------

def _enc_gps(r: Gps) -> bytes:
    heading = r.heading_deg % 360.0 if r.heading_deg is not None and math.isfinite(
        r.heading_deg) else r.heading_deg
    alt = None if r.altitude_m is None else r.altitude_m + GPS_ALTITUDE_OFFSET_M
    return (_field(r.lat_deg, 1e7, 4, True) + _field(r.lon_deg, 1e7, 4, True)
            + _field(r.groundspeed_kmh, 10, 2, False)
            + _field(heading, 100, 2, False, hi=35999)
            + _field(alt, 1, 2, False)
            + _field(r.satellites, 1, 1, False))


def _enc_vario(r: Vario) -> bytes:
    return _field(r.vspeed_mps, 100, 2, True)


def _enc_battery(r: Battery) -> bytes:
    return (_field(r.voltage_v, 10, 2, False) + _field(r.current_a, 10, 2, False)
            + _field(r.capacity_mah, 1, 3, False) + _field(r.remaining_pct, 1, 1, False, hi=100))


def pack_baro_altitude(altitude_m: float | None) -> int:
    """The ELRS/Betaflight packed altitude: decimetres + 10000 up to 2276.7 m (MSB clear),
    whole metres with the MSB set above, up to 32766 m; −1000 m at the bottom."""
    if altitude_m is None or altitude_m != altitude_m:
        return 0xFFFF
    x = altitude_m * 10
    if x <= -BARO_DM_OFFSET:
        return 0
    if x < BARO_MAX_DM_FORM + 0.5:
        # Plain rounding: −1 dm packs as 9999, so the all-0xFF escape of quantize() must not
        # apply to this intermediate value.
        return _round(x) + BARO_DM_OFFSET
    return BARO_METRES_FLAG | quantize(altitude_m, 1, 2, False, hi=BARO_MAX_METRES)


def unpack_baro_altitude(packed: int) -> float:
    if packed & BARO_METRES_FLAG:
        return float(packed & 0x7FFF)
    return (packed - BARO_DM_OFFSET) / 10.0


def _enc_baro(r: BaroAltitude) -> bytes:
    alt = pack_baro_altitude(r.altitude_m).to_bytes(2, "big")
    if r.vspeed_mps is None:
        return alt
    return alt + _field(r.vspeed_mps, 100, 2, True)


def _enc_airspeed(r: Airspeed) -> bytes:
    return _field(r.speed_kmh, 10, 2, False)


def _enc_list(source_id: int, values: Sequence[float | None], scale: float, nbytes: int,
              signed: bool, limit: int, what: str, minimum: int = 0) -> bytes:
    if not 0 <= source_id <= 0xFF:
        raise ValueError(f"{what} source id {source_id} is not a byte")
    if not minimum <= len(values) <= limit:
        raise ValueError(f"{what}: {len(values)} values; a frame holds {minimum}..{limit}")
    return bytes((source_id,)) + b"".join(_field(v, scale, nbytes, signed) for v in values)


def _enc_rpm(r: Rpm) -> bytes:
    return _enc_list(r.source_id, r.rpm, 1, 3, True, MAX_RPM_VALUES, "rpm", minimum=1)


def _enc_temps(r: Temperatures) -> bytes:
    return _enc_list(r.source_id, r.temps_c, 10, 2, True, MAX_TEMPERATURES, "temperatures")


def _enc_volts(r: Voltages) -> bytes:
    return _enc_list(r.source_id, r.volts, 1000, 2, False, MAX_VOLTAGES, "voltages")


def _enc_accel_gyro(r: AccelGyro) -> bytes:
    t = None if r.sample_time_us is None else r.sample_time_us % (1 << 32)
    g, a = 1.0 / GYRO_DPS_PER_LSB, 1.0 / ACCEL_G_PER_LSB
    return (_field(t, 1, 4, False)
            + _field(r.gyro_x_dps, g, 2, True) + _field(r.gyro_y_dps, g, 2, True)
            + _field(r.gyro_z_dps, g, 2, True)
            + _field(r.accel_x_g, a, 2, True) + _field(r.accel_y_g, a, 2, True)
            + _field(r.accel_z_g, a, 2, True) + _field(r.temp_c, 100, 2, True))


def _byte(v: int, signed: bool = False) -> bytes:
    lo, hi = (-128, 127) if signed else (0, 255)
    return max(lo, min(hi, int(v))).to_bytes(1, "big", signed=signed)


def _enc_link_stats(r: LinkStatistics) -> bytes:
    return (_byte(-r.uplink_rssi_ant1_dbm) + _byte(-r.uplink_rssi_ant2_dbm)
            + _byte(r.uplink_link_quality_pct) + _byte(r.uplink_snr_db, True)
            + _byte(r.active_antenna) + _byte(r.rf_mode) + _byte(r.uplink_tx_power)
            + _byte(-r.downlink_rssi_dbm) + _byte(r.downlink_link_quality_pct)
            + _byte(r.downlink_snr_db, True))


def _enc_rc(r: RcChannels) -> bytes:
    if len(r.channels) != RC_CHANNELS:
        raise ValueError(f"RC channels: {len(r.channels)} values; the frame holds 16")
    bits = 0
    for i, v in enumerate(r.channels):
        if not 0 <= v <= RC_CHANNEL_MAX:
            raise ValueError(f"RC channel {i + 1} value {v} is not 11 bits")
        bits |= v << (11 * i)
    return bits.to_bytes(22, "little")


def _enc_attitude(r: Attitude) -> bytes:
    def angle(a: float | None) -> bytes:
        return _field(None if a is None else wrap_angle(a), 10000, 2, True)

    return angle(r.pitch_rad) + angle(r.roll_rad) + angle(r.yaw_rad)


def _enc_flight_mode(r: FlightMode) -> bytes:
    text = r.text.replace("\0", "").encode("ascii", "replace")
    if len(text) + 1 > MAX_PAYLOAD:
        raise ValueError(f"flight-mode text of {len(text)} characters does not fit a frame")
    return text + b"\0"


def _enc_unknown(r: UnknownFrame) -> bytes:
    if r.type >= EXTENDED_TYPE_MIN and r.dest is not None:
        return bytes((r.dest, r.origin or 0)) + r.payload
    return r.payload


_ENCODERS: dict[type, Callable[[Any], bytes]] = {
    Gps: _enc_gps, Vario: _enc_vario, Battery: _enc_battery, BaroAltitude: _enc_baro,
    Airspeed: _enc_airspeed, Rpm: _enc_rpm, Temperatures: _enc_temps, Voltages: _enc_volts,
    AccelGyro: _enc_accel_gyro, LinkStatistics: _enc_link_stats, RcChannels: _enc_rc,
    Attitude: _enc_attitude, FlightMode: _enc_flight_mode, UnknownFrame: _enc_unknown,
}


def encode_payload(record: Record) -> bytes:
    """The payload bytes of ``record`` (no sync, length, type or CRC)."""
    try:
        enc = _ENCODERS[type(record)]
    except KeyError:
        raise TypeError(f"not a CRSF record: {record!r}") from None
    return enc(record)


def encode(record: Record, sync: int = SYNC_FC) -> bytes:
    """``record`` as a complete CRSF frame."""
    ftype = record.type if isinstance(record, UnknownFrame) else FRAME_TYPES[type(record)]
    return build_frame(ftype, encode_payload(record), sync)


# -- payload decoders -------------------------------------------------------------------------

def _dec_gps(p: bytes) -> Gps | None:
    if len(p) != 15:
        return None
    alt = _unpack(p, 12, 2, False)
    return Gps(_scaled(_unpack(p, 0, 4, True), 1e7), _scaled(_unpack(p, 4, 4, True), 1e7),
               _scaled(_unpack(p, 8, 2, False), 10), _scaled(_unpack(p, 10, 2, False), 100),
               None if alt is None else float(alt - GPS_ALTITUDE_OFFSET_M),
               _unpack(p, 14, 1, False))


def _dec_vario(p: bytes) -> Vario | None:
    return Vario(_scaled(_unpack(p, 0, 2, True), 100)) if len(p) == 2 else None


def _dec_battery(p: bytes) -> Battery | None:
    if len(p) != 8:
        return None
    cap = _unpack(p, 4, 3, False)
    return Battery(_scaled(_unpack(p, 0, 2, False), 10), _scaled(_unpack(p, 2, 2, False), 10),
                   None if cap is None else float(cap), _unpack(p, 7, 1, False))


def _tbs_vario(k: int) -> float:
    """The TBS 3-byte baro frame's log-scaled int8 vertical speed (m/s), as EdgeTX expands
    it: (e^(0.026·|k|) − 1) × 100 cm/s."""
    sign = -1.0 if k < 0 else 1.0
    return sign * (math.exp(abs(k) * 0.026) - 1.0)


def _dec_baro(p: bytes) -> BaroAltitude | None:
    if len(p) not in (2, 3, 4):
        return None
    packed = _unpack(p, 0, 2, False)
    alt = None if packed is None else unpack_baro_altitude(packed)
    if len(p) == 4:
        return BaroAltitude(alt, _scaled(_unpack(p, 2, 2, True), 100))
    if len(p) == 3:
        return BaroAltitude(alt, _tbs_vario(int.from_bytes(p[2:3], "big", signed=True)))
    return BaroAltitude(alt, None)


def _dec_airspeed(p: bytes) -> Airspeed | None:
    return Airspeed(_scaled(_unpack(p, 0, 2, False), 10)) if len(p) == 2 else None


def _dec_list(p: bytes, nbytes: int, signed: bool, limit: int, minimum: int = 0
              ) -> tuple[int, tuple[int | None, ...]] | None:
    n, rest = divmod(len(p) - 1, nbytes)
    if len(p) < 1 or rest or not minimum <= n <= limit:
        return None
    return p[0], tuple(_unpack(p, 1 + i * nbytes, nbytes, signed) for i in range(n))


def _dec_rpm(p: bytes) -> Rpm | None:
    d = _dec_list(p, 3, True, MAX_RPM_VALUES, minimum=1)
    return None if d is None else Rpm(d[0], d[1])


def _dec_temps(p: bytes) -> Temperatures | None:
    d = _dec_list(p, 2, True, MAX_TEMPERATURES)
    return None if d is None else Temperatures(d[0], tuple(_scaled(k, 10) for k in d[1]))


def _dec_volts(p: bytes) -> Voltages | None:
    d = _dec_list(p, 2, False, MAX_VOLTAGES)
    return None if d is None else Voltages(d[0], tuple(_scaled(k, 1000) for k in d[1]))


def _dec_accel_gyro(p: bytes) -> AccelGyro | None:
    if len(p) != 18:
        return None
    g, a = 1.0 / GYRO_DPS_PER_LSB, 1.0 / ACCEL_G_PER_LSB
    gx, gy, gz = (_scaled(_unpack(p, 4 + 2 * i, 2, True), g) for i in range(3))
    ax, ay, az = (_scaled(_unpack(p, 10 + 2 * i, 2, True), a) for i in range(3))
    return AccelGyro(_unpack(p, 0, 4, False), gx, gy, gz, ax, ay, az,
                     _scaled(_unpack(p, 16, 2, True), 100))


def _dec_link_stats(p: bytes) -> LinkStatistics | None:
    if len(p) != 10:
        return None
    return LinkStatistics(-p[0], -p[1], p[2], int.from_bytes(p[3:4], "big", signed=True), p[4],
                          p[5], p[6], -p[7], p[8], int.from_bytes(p[9:10], "big", signed=True))


def _dec_rc(p: bytes) -> RcChannels | None:
    if len(p) != 22:
        return None
    bits = int.from_bytes(p, "little")
    return RcChannels(tuple((bits >> (11 * i)) & RC_CHANNEL_MAX for i in range(RC_CHANNELS)))


def _dec_attitude(p: bytes) -> Attitude | None:
    if len(p) != 6:
        return None
    return Attitude(*(_scaled(_unpack(p, 2 * i, 2, True), 10000) for i in range(3)))


def _dec_flight_mode(p: bytes) -> FlightMode | None:
    if not p:
        return None
    text = p.split(b"\0", 1)[0]
    return FlightMode(text.decode("ascii", "replace"))


_DECODERS: dict[int, Callable[[bytes], Any]] = {
    FRAME_GPS: _dec_gps, FRAME_VARIO: _dec_vario, FRAME_BATTERY: _dec_battery,
    FRAME_BARO_ALTITUDE: _dec_baro, FRAME_AIRSPEED: _dec_airspeed, FRAME_RPM: _dec_rpm,
    FRAME_TEMPERATURE: _dec_temps, FRAME_VOLTAGES: _dec_volts,
    FRAME_ACCEL_GYRO: _dec_accel_gyro, FRAME_LINK_STATISTICS: _dec_link_stats,
    FRAME_RC_CHANNELS: _dec_rc, FRAME_ATTITUDE: _dec_attitude,
    FRAME_FLIGHT_MODE: _dec_flight_mode,
}

#: Frame types :func:`decode_payload` turns into records.
DECODED_TYPES = frozenset(_DECODERS)


def decode_payload(ftype: int, payload: bytes) -> Record | None:
    """The record a frame of type ``ftype`` carries; an :class:`UnknownFrame` for other types;
    None when the payload does not fit its type (wrong length)."""
    dec = _DECODERS.get(ftype)
    if dec is not None:
        return dec(payload)
    if ftype >= EXTENDED_TYPE_MIN:
        if len(payload) < 2:
            return None
        return UnknownFrame(ftype, bytes(payload[2:]), payload[0], payload[1])
    return UnknownFrame(ftype, bytes(payload))


# -- flight-mode text -------------------------------------------------------------------------

def flight_mode_text(name: str, armed: bool, *, disarmed_suffix: str = "*", marker: str = "",
                     max_chars: int = FLIGHT_MODE_MAX_CHARS) -> str:
    """The text for the flight-mode sensor: ``name`` + ``marker`` + the disarmed suffix,
    at most ``max_chars`` long; the name is shortened first, so the suffix and marker always
    show (ArduPilot/ELRS/mLRS append ``*`` when disarmed)."""
    tail = marker + ("" if armed else disarmed_suffix)
    room = max(0, max_chars - len(tail))
    return (name[:room] + tail)[:max_chars]
