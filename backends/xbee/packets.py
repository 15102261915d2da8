"""The XBee link's compact packets (seed 004), sans-I/O: typed records, encoders, decoders.

A packet is what one side puts in an XBee RF payload (the ``data`` of a 0x10 / 0x90 frame,
see :mod:`backends.xbee.frames`).  Network byte order, smallest possible packets.  The first
byte is the type; the second byte of every packet is the *header*, ``seq << 3 | power``:

* ``seq`` (5 bits, 0..31): for a command, the seed's sequence number (bumped when the values
  change, repeated on a resend, acked by the air side); for an ACK, the acknowledged command's
  sequence; for every other type, the sender's running counter of packets of that type
  (:func:`next_seq`), so the receiver can count losses with :func:`seq_gap`;
* ``power`` (3 bits, 0..4): the XBee power level (PL) the packet went out at — the receiver
  cannot tell it from the RSSI alone.  5..7 are rejected.

==========  ========  =====  ==================================================================
type byte   record    bytes  layout after the type byte (all big-endian)
==========  ========  =====  ==================================================================
0x00..0x3F  Command   2..10  the type byte is the bitmask of servos present (bit i = servo i,
                             0..5); then an MSB-first bit stream: seq (5), power (3), each
                             present servo's value (10 bits, 0..1023, ascending index), zero
                             padding to a whole byte.  Mask 0 (``00 hdr``) is the keep-alive.
                             Servos 0 = 0x123 and 2 = 0x234, seq 0, power 2: ``05 02 48 e3 40``
0x40        Ack       2      hdr (seq = the acknowledged command's sequence, power = the
                             power of the packet being acked, as received)
0x41        Ping      2      hdr (power = the PL it went out at; the receiver notes the RSSI
                             it arrived with against that power)
0x42        Stats     15     hdr, present u8, rssi u8 (−dBm), rx_errors u16 (ER),
                             good_packets u16 (GD), tx_errors u16 (TR), ack_failures u16
                             (EA), duty_cycle u8 (%, DC), commands_rx u16 (command packets
                             received, mod 65536).  ``present`` bit 0..5 = the six module
                             values in that order; an absent one is None and zero on the wire
0x43        SmTelem   24     hdr, timestamp_ms u32, state u8, sm_type u8, flags u8 (bit 0 =
                             armed, others zero), altitude i24 (0.1 m), velocity i16
                             (0.1 m/s), acceleration i16 (0.1 m/s²), vertical acceleration
                             i16 (0.1 m/s²), roll, pitch, yaw i16 each (0.0001 rad)
0x44        StatTelem 9      hdr, timestamp_ms u32, state u8, sm_type u8, flags u8 (the
                             rocket's STATUS flags, as in :mod:`gateway.model`)
0x45..0xFF  —                unknown: rejected (:class:`UnknownPacketType`)
==========  ========  =====  ==================================================================

Every type's length follows from its type byte, so several packets can share one RF payload
(the seed: "group information into one packet"; packets that are not urgent can wait for one
going out at the same power): :func:`group` packs encoded packets into payloads no larger than
NP, :func:`iter_decode` splits a payload back.

Telemetry resolutions (``SmTelem`` = :class:`SmTelemetry`, one 24-byte packet per SM update):
altitude 0.1 m in 24 bits (±838 km: any sounding rocket; finer than barometric noise);
velocity 0.1 m/s in 16 bits (±3276 m/s, about Mach 9); accelerations 0.1 m/s² (0.01 g) in 16
bits (±334 g); angles 0.0001 rad (0.006°) in 16 bits (±3.2767 rad: an angle beyond that is
wrapped to [−π, π] first, one within it is carried as it is); the timestamp and the integers
exactly.  Values are rounded half away from zero and clamped to the field; NaN goes on the
wire as the field's minimum (−2ⁿ⁻¹), which no number produces, and decodes back to NaN.  So
decode(encode(x)) is within half a step of ``x``, and encode(decode(b)) == b for every valid
packet ``b``.

Decoders validate type, length and every field and raise a :class:`PacketError` (ValueError)
subclass with a clear message: :class:`UnknownPacketType`, :class:`BadPacketLength`,
:class:`BadPacketField`; the caller counts and skips.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import NamedTuple

from gateway.model import SmUpdate, Status

TYPE_COMMAND_MAX = 0x3F  # type bytes 0x00..0x3F: a command, the byte is the servo mask
TYPE_ACK = 0x40
TYPE_PING = 0x41
TYPE_STATS = 0x42
TYPE_SM_TELEMETRY = 0x43
TYPE_STATUS_TELEMETRY = 0x44

SERVOS = 6  # mask bits 0..5
SERVO_MAX = 0x3FF  # 10-bit values
SEQ_MOD = 32  # 5-bit sequence numbers
POWER_MAX = 4  # XBee PL 0..4 (the 3-bit field's 5..7 are invalid)

ALTITUDE_PER_M = 10  # 0.1 m
VELOCITY_PER_MPS = 10  # 0.1 m/s
ACCEL_PER_MPS2 = 10  # 0.1 m/s²
ANGLE_PER_RAD = 10000  # 0.0001 rad

STATS_RSSI = 0x01
STATS_RX_ERRORS = 0x02
STATS_GOOD_PACKETS = 0x04
STATS_TX_ERRORS = 0x08
STATS_ACK_FAILURES = 0x10
STATS_DUTY_CYCLE = 0x20
_STATS_ALL = 0x3F

SM_FLAG_ARMED = 0x01


class PacketError(ValueError):
    """A link packet that does not decode (or a record that cannot be encoded)."""


class UnknownPacketType(PacketError):
    """The type byte is not one of this module's."""


class BadPacketLength(PacketError):
    """The packet is shorter or longer than its type requires."""


class BadPacketField(PacketError):
    """A field out of its range (power 5..7, reserved bits or padding set, …)."""


# -- records ----------------------------------------------------------------------------------

class Command(NamedTuple):
    """Servo values (type byte < 0x40): ``values`` are the present servos' in ascending index."""

    seq: int
    power: int
    mask: int = 0
    values: tuple[int, ...] = ()

    @classmethod
    def from_servos(cls, servos: Mapping[int, int], seq: int, power: int) -> Command:
        """A command carrying ``servos`` (index 0..5 → value 0..1023)."""
        mask = 0
        for index in servos:
            if not 0 <= index < SERVOS:
                raise BadPacketField(f"servo index {index}: must be 0..{SERVOS - 1}")
            mask |= 1 << index
        return cls(seq, power, mask, tuple(servos[i] for i in sorted(servos)))

    @property
    def servos(self) -> dict[int, int]:
        """Servo index → value."""
        return dict(zip((i for i in range(SERVOS) if self.mask >> i & 1), self.values,
                        strict=False))


class Ack(NamedTuple):
    """0x40: ``seq`` is the acknowledged command's sequence, ``power`` that command's power."""

    seq: int
    power: int


class Ping(NamedTuple):
    """0x41: sent at rotating power; ``power`` is the PL it went out at."""

    seq: int
    power: int


class Stats(NamedTuple):
    """0x42: the sender's module counters (None = not read) and command packets received."""

    seq: int
    power: int
    rssi_dbm: int | None = None  # DB of the last packet received, −255..0
    rx_errors: int | None = None  # ER
    good_packets: int | None = None  # GD
    tx_errors: int | None = None  # TR
    ack_failures: int | None = None  # EA
    duty_cycle_pct: int | None = None  # DC, 0..100
    commands_rx: int = 0  # command packets received, mod 65536


class SmTelemetry(NamedTuple):
    """0x43: one SM update (see :class:`gateway.model.SmUpdate`), fixed point on the wire."""

    seq: int
    power: int
    timestamp_ms: int
    state: int
    sm_type: int
    armed: bool
    altitude_m: float
    velocity_mps: float
    acceleration_mps2: float
    accel_vert_mps2: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float

    @classmethod
    def from_sm_update(cls, msg: SmUpdate, seq: int = 0, power: int = 0) -> SmTelemetry:
        """The packet for ``msg`` (its values are quantised when encoded)."""
        return cls(seq, power, msg.timestamp_ms, msg.state, msg.sm_type, bool(msg.armed),
                   msg.altitude_m, msg.velocity_mps, msg.acceleration_mps2,
                   msg.accel_vert_mps2, msg.roll_rad, msg.pitch_rad, msg.yaw_rad)

    def to_sm_update(self, origin: str = "", via: str = "") -> SmUpdate:
        """The gateway message (f64 revision, reserved 0, no raw frame)."""
        return SmUpdate(self.timestamp_ms, self.state, self.armed, self.sm_type,
                        self.altitude_m, self.acceleration_mps2, self.accel_vert_mps2,
                        self.velocity_mps, self.roll_rad, self.pitch_rad, self.yaw_rad,
                        origin=origin, via=via)


class StatusTelemetry(NamedTuple):
    """0x44: the rocket's STATUS (see :class:`gateway.model.Status`)."""

    seq: int
    power: int
    timestamp_ms: int
    state: int
    sm_type: int
    flags: int

    @classmethod
    def from_status(cls, msg: Status, seq: int = 0, power: int = 0) -> StatusTelemetry:
        """The packet for ``msg`` (its ``reserved`` byte is not carried)."""
        return cls(seq, power, msg.timestamp_ms, msg.state, msg.sm_type, msg.flags)

    def to_status(self, origin: str = "", via: str = "") -> Status:
        """The gateway message (reserved 0, no raw frame)."""
        return Status(self.timestamp_ms, self.state, self.sm_type, self.flags,
                      origin=origin, via=via)


Packet = Command | Ack | Ping | Stats | SmTelemetry | StatusTelemetry


# -- sequence numbers -------------------------------------------------------------------------

def next_seq(seq: int) -> int:
    """The sequence number after ``seq`` (mod 32)."""
    return (seq + 1) % SEQ_MOD


def seq_gap(prev: int, now: int) -> int:
    """Packets missed between ``prev`` and ``now`` of a running counter (0 = none; a repeat
    or a jump of 32 or more is indistinguishable and reads as 31)."""
    return (now - prev - 1) % SEQ_MOD


# -- fields -----------------------------------------------------------------------------------

def _check(name: str, value: int, lo: int, hi: int) -> int:
    if not isinstance(value, int) or not lo <= value <= hi:
        raise BadPacketField(f"{name} {value!r}: must be an integer {lo}..{hi}")
    return value


def _header(seq: int, power: int) -> int:
    return _check("seq", seq, 0, SEQ_MOD - 1) << 3 | _check("power", power, 0, POWER_MAX)


def _split_header(byte: int) -> tuple[int, int]:
    power = byte & 7
    if power > POWER_MAX:
        raise BadPacketField(f"power {power} in the header: must be 0..{POWER_MAX}")
    return byte >> 3, power


def _round(x: float) -> int:
    """Round half away from zero (Python's round() is half-even)."""
    return math.floor(x + 0.5) if x >= 0 else -math.floor(-x + 0.5)


def quantize(value: float, scale: int, bits: int) -> int:
    """``value × scale`` rounded and clamped to a signed ``bits`` field; NaN → the minimum."""
    lo = -(1 << (bits - 1))
    if value != value:
        return lo
    x = value * scale
    hi = -lo - 1
    if x <= lo + 1:
        return lo + 1
    if x >= hi:
        return hi
    return _round(x)


def dequantize(k: int, scale: int, bits: int) -> float:
    """The value of field code ``k`` (the minimum → NaN)."""
    return math.nan if k == -(1 << (bits - 1)) else k / scale


_ANGLE_FIELD_MAX = 0x7FFF / ANGLE_PER_RAD  # 3.2767 rad


def wrap_angle(a: float) -> float:
    """``a`` as the angle field carries it: unchanged when it fits (±3.2767 rad), else
    wrapped to [−π, π]; ±inf becomes NaN."""
    if -_ANGLE_FIELD_MAX <= a <= _ANGLE_FIELD_MAX or a != a:
        return a
    return math.remainder(a, 2 * math.pi) if math.isfinite(a) else math.nan


# -- per-type codecs --------------------------------------------------------------------------

def command_length(mask: int) -> int:
    """Bytes of a command packet whose type byte is ``mask``."""
    return 1 + (8 + 10 * mask.bit_count() + 7) // 8


def _enc_command(p: Command) -> bytes:
    mask = _check("mask", p.mask, 0, TYPE_COMMAND_MAX)
    values = tuple(p.values)
    if len(values) != mask.bit_count():
        raise BadPacketField(f"mask 0x{mask:02X} has {mask.bit_count()} servos, "
                             f"{len(values)} values given")
    acc = _header(p.seq, p.power)
    for v in values:
        acc = acc << 10 | _check("servo value", v, 0, SERVO_MAX)
    nbits = 8 + 10 * len(values)
    pad = -nbits % 8
    return bytes((mask,)) + (acc << pad).to_bytes((nbits + pad) // 8, "big")


def _dec_command(d: bytes) -> Command:
    mask = d[0]
    n = mask.bit_count()
    nbits = 8 + 10 * n
    pad = -nbits % 8
    acc = int.from_bytes(d[1:], "big")
    if acc & ((1 << pad) - 1):
        raise BadPacketField("command padding bits are not zero")
    acc >>= pad
    values = tuple((acc >> (10 * (n - 1 - k))) & SERVO_MAX for k in range(n))
    seq, power = _split_header(acc >> (10 * n))
    return Command(seq, power, mask, values)


def _enc_ack(p: Ack) -> bytes:
    return bytes((TYPE_ACK, _header(p.seq, p.power)))


def _dec_ack(d: bytes) -> Ack:
    return Ack(*_split_header(d[1]))


def _enc_ping(p: Ping) -> bytes:
    return bytes((TYPE_PING, _header(p.seq, p.power)))


def _dec_ping(d: bytes) -> Ping:
    return Ping(*_split_header(d[1]))


_STATS = struct.Struct(">BBBBHHHHBH")  # type, hdr, present, rssi, ER, GD, TR, EA, DC, commands
_STATS_FIELDS = (  # (name, present bit, lo, hi) of the optional module values, wire order
    ("rx_errors", STATS_RX_ERRORS, 0, 0xFFFF),
    ("good_packets", STATS_GOOD_PACKETS, 0, 0xFFFF),
    ("tx_errors", STATS_TX_ERRORS, 0, 0xFFFF),
    ("ack_failures", STATS_ACK_FAILURES, 0, 0xFFFF),
    ("duty_cycle_pct", STATS_DUTY_CYCLE, 0, 100),
)


def _enc_stats(p: Stats) -> bytes:
    present = 0
    rssi = 0
    if p.rssi_dbm is not None:
        rssi = -_check("rssi_dbm", p.rssi_dbm, -255, 0)
        present |= STATS_RSSI
    vals = []
    for name, bit, lo, hi in _STATS_FIELDS:
        v = getattr(p, name)
        if v is None:
            vals.append(0)
        else:
            vals.append(_check(name, v, lo, hi))
            present |= bit
    commands = _check("commands_rx", p.commands_rx, 0, 0xFFFF)
    return _STATS.pack(TYPE_STATS, _header(p.seq, p.power), present, rssi, *vals, commands)


def _dec_stats(d: bytes) -> Stats:
    _, hdr, present, rssi, er, gd, tr, ea, dc, commands = _STATS.unpack(d)
    if present & ~_STATS_ALL:
        raise BadPacketField(f"stats present bits 0x{present:02X}: only 0x3F are defined")
    raw = (rssi, er, gd, tr, ea, dc)
    bits = (STATS_RSSI, STATS_RX_ERRORS, STATS_GOOD_PACKETS, STATS_TX_ERRORS,
            STATS_ACK_FAILURES, STATS_DUTY_CYCLE)
    opt: list[int | None] = []
    for v, bit in zip(raw, bits, strict=True):
        if present & bit:
            opt.append(v)
        elif v:
            raise BadPacketField(f"stats value {v} sent with its present bit 0x{bit:02X} clear")
        else:
            opt.append(None)
    if opt[5] is not None and opt[5] > 100:
        raise BadPacketField(f"duty cycle {opt[5]} %: must be 0..100")
    seq, power = _split_header(hdr)
    rssi_dbm = None if opt[0] is None else -opt[0]
    return Stats(seq, power, rssi_dbm, opt[1], opt[2], opt[3], opt[4], opt[5], commands)


# type, hdr, timestamp, state, sm_type, flags, altitude (3 bytes, sliced apart), 6 × i16
_SM_HEAD = struct.Struct(">BBIBBB")
_SM_TAIL = struct.Struct(">6h")
_SM_LEN = _SM_HEAD.size + 3 + _SM_TAIL.size


def _enc_sm(p: SmTelemetry) -> bytes:
    head = _SM_HEAD.pack(TYPE_SM_TELEMETRY, _header(p.seq, p.power),
                         _check("timestamp_ms", p.timestamp_ms, 0, 0xFFFFFFFF),
                         _check("state", p.state, 0, 0xFF), _check("sm_type", p.sm_type, 0, 0xFF),
                         SM_FLAG_ARMED if p.armed else 0)
    alt = quantize(p.altitude_m, ALTITUDE_PER_M, 24).to_bytes(3, "big", signed=True)
    tail = _SM_TAIL.pack(
        quantize(p.velocity_mps, VELOCITY_PER_MPS, 16),
        quantize(p.acceleration_mps2, ACCEL_PER_MPS2, 16),
        quantize(p.accel_vert_mps2, ACCEL_PER_MPS2, 16),
        quantize(wrap_angle(p.roll_rad), ANGLE_PER_RAD, 16),
        quantize(wrap_angle(p.pitch_rad), ANGLE_PER_RAD, 16),
        quantize(wrap_angle(p.yaw_rad), ANGLE_PER_RAD, 16),
    )
    return head + alt + tail


def _dec_sm(d: bytes) -> SmTelemetry:
    _, hdr, ts, state, sm_type, flags = _SM_HEAD.unpack_from(d)
    if flags & ~SM_FLAG_ARMED:
        raise BadPacketField(f"SM telemetry flags 0x{flags:02X}: only bit 0 (armed) is defined")
    alt = int.from_bytes(d[_SM_HEAD.size:_SM_HEAD.size + 3], "big", signed=True)
    vel, acc, acc_v, roll, pitch, yaw = _SM_TAIL.unpack_from(d, _SM_HEAD.size + 3)
    seq, power = _split_header(hdr)
    return SmTelemetry(
        seq, power, ts, state, sm_type, bool(flags & SM_FLAG_ARMED),
        dequantize(alt, ALTITUDE_PER_M, 24),
        dequantize(vel, VELOCITY_PER_MPS, 16),
        dequantize(acc, ACCEL_PER_MPS2, 16),
        dequantize(acc_v, ACCEL_PER_MPS2, 16),
        dequantize(roll, ANGLE_PER_RAD, 16),
        dequantize(pitch, ANGLE_PER_RAD, 16),
        dequantize(yaw, ANGLE_PER_RAD, 16),
    )


_STATUS = struct.Struct(">BBIBBB")


def _enc_status(p: StatusTelemetry) -> bytes:
    return _STATUS.pack(TYPE_STATUS_TELEMETRY, _header(p.seq, p.power),
                        _check("timestamp_ms", p.timestamp_ms, 0, 0xFFFFFFFF),
                        _check("state", p.state, 0, 0xFF), _check("sm_type", p.sm_type, 0, 0xFF),
                        _check("flags", p.flags, 0, 0xFF))


def _dec_status(d: bytes) -> StatusTelemetry:
    _, hdr, ts, state, sm_type, flags = _STATUS.unpack(d)
    seq, power = _split_header(hdr)
    return StatusTelemetry(seq, power, ts, state, sm_type, flags)


_ENCODERS: dict[type, Callable[..., bytes]] = {
    Command: _enc_command,
    Ack: _enc_ack,
    Ping: _enc_ping,
    Stats: _enc_stats,
    SmTelemetry: _enc_sm,
    StatusTelemetry: _enc_status,
}

# type byte (≥ 0x40) → (length, decoder, name)
_FIXED: dict[int, tuple[int, Callable[[bytes], Packet], str]] = {
    TYPE_ACK: (2, _dec_ack, "ack"),
    TYPE_PING: (2, _dec_ping, "ping"),
    TYPE_STATS: (_STATS.size, _dec_stats, "stats"),
    TYPE_SM_TELEMETRY: (_SM_LEN, _dec_sm, "SM telemetry"),
    TYPE_STATUS_TELEMETRY: (_STATUS.size, _dec_status, "status telemetry"),
}

#: The longest packet (SM telemetry, 24 bytes).
MAX_PACKET = max(max(n for n, _, _ in _FIXED.values()), command_length(TYPE_COMMAND_MAX))


# -- public API -------------------------------------------------------------------------------

def packet_length(type_byte: int) -> int:
    """The length of a packet starting with ``type_byte``; UnknownPacketType if none."""
    if type_byte <= TYPE_COMMAND_MAX:
        return command_length(type_byte)
    spec = _FIXED.get(type_byte)
    if spec is None:
        raise UnknownPacketType(f"unknown packet type 0x{type_byte:02X}")
    return spec[0]


def encode(packet: Packet) -> bytes:
    """``packet`` as bytes; BadPacketField (a ValueError) for a field out of range."""
    enc = _ENCODERS.get(type(packet))
    if enc is None:
        raise PacketError(f"not a link packet record: {type(packet).__name__}")
    return enc(packet)


def decode(data: bytes) -> Packet:
    """The record of exactly one packet; a :class:`PacketError` subclass if it is not one."""
    data = bytes(data)
    if not data:
        raise BadPacketLength("empty packet")
    t = data[0]
    want = packet_length(t)
    if len(data) != want:
        name = "command" if t <= TYPE_COMMAND_MAX else _FIXED[t][2]
        raise BadPacketLength(f"{name} packet (type 0x{t:02X}) of {len(data)} bytes: "
                              f"must be {want}")
    if t <= TYPE_COMMAND_MAX:
        return _dec_command(data)
    return _FIXED[t][1](data)


def iter_decode(payload: bytes) -> Iterator[Packet]:
    """The packets of one RF payload, in order.

    Raises the :class:`PacketError` of the first bad packet when it is reached (the packets
    before it have been yielded); an unknown type ends the payload since its length is
    unknown.
    """
    payload = bytes(payload)
    pos = 0
    n = len(payload)
    while pos < n:
        want = packet_length(payload[pos])
        if pos + want > n:
            raise BadPacketLength(f"packet type 0x{payload[pos]:02X} needs {want} bytes, "
                                  f"{n - pos} left in the payload")
        yield decode(payload[pos:pos + want])
        pos += want


def encode_many(packets: Iterable[Packet]) -> bytes:
    """Several packets in one payload (they split again with :func:`iter_decode`)."""
    return b"".join(encode(p) for p in packets)


def group(chunks: Iterable[bytes], max_payload: int) -> list[bytes]:
    """Encoded packets packed in order into as few payloads of ≤ ``max_payload`` as a greedy
    fill gives; ValueError if one packet alone is too big."""
    if max_payload < 1:
        raise ValueError(f"max_payload {max_payload}: must be ≥ 1")
    out: list[bytes] = []
    cur = b""
    for c in chunks:
        if len(c) > max_payload:
            raise ValueError(f"a {len(c)}-byte packet exceeds the {max_payload}-byte payload")
        if len(cur) + len(c) > max_payload:
            out.append(cur)
            cur = b""
        cur += c
    if cur:
        out.append(cur)
    return out
