"""Sans-I/O codec for the Aurora telemetry wire frame.

``A5 5A | type | len | payload[len] | crc16 (LE)`` with the CRC over type, len and payload.
The CRC is Zephyr's ``crc16_ccitt(0xFFFF, …)``, which is the catalogue's CRC-16/MCRF4XX
(reflected 0x1021, init 0xFFFF, no final XOR; check value 0x6F91), *not* CRC-16/CCITT-FALSE
despite the firmware documentation's name for it.  See ``shared/specs/aurora-wire.md``.

:class:`Decoder` takes bytes and returns messages; :func:`encode` turns a message back into a
frame.  No I/O, clocks or threads here; corruption never raises, it is counted.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from gateway.counters import Counters
from gateway.crc import mcrf4xx
from gateway.model import (
    SM_UPDATE_F32_LEN,
    SM_UPDATE_F64_LEN,
    RawFrame,
    SmUpdate,
    Status,
)
from gateway.resync import BufferedDecoder

MAGIC = b"\xa5\x5a"
TYPE_SM_UPDATE = 0x01
TYPE_STATUS = 0x02
STATUS_LEN = 8
HEADER_LEN = 4
CRC_LEN = 2
OVERHEAD = HEADER_LEN + CRC_LEN
MAX_PAYLOAD = 255
MAX_FRAME = OVERHEAD + MAX_PAYLOAD

_SM_F32 = struct.Struct("<IBBBB7f")
_SM_F64 = struct.Struct("<IBBBB7d")
_STATUS = struct.Struct("<IBBBB")
_crc = mcrf4xx
# The decoder's view: "?" unpacks ``armed`` straight to a bool (any non-zero byte is True).
_SM_F64_IN = struct.Struct("<IB?BB7d")
_SM_F32_IN = struct.Struct("<IB?BB7f")
# The CRC register value that the two magic bytes turn into 0xFFFF: the CRC of a whole frame
# from this value equals the CRC of type..crc from 0xFFFF, so no second slice is needed
# (mcrf4xx(MAGIC, _CRC_BEFORE_MAGIC) == 0xFFFF).
_CRC_BEFORE_MAGIC = 0xA984
_new = tuple.__new__


def crc(data: bytes) -> int:
    """The frame CRC (CRC-16/MCRF4XX) of ``data``."""
    return _crc(data)


@dataclass
class DecoderStats(Counters):
    """What a decoder has seen.  ``bytes_skipped`` counts every byte not inside a valid frame."""

    bytes_in: int = 0
    frames: int = 0
    crc_failures: int = 0
    bytes_skipped: int = 0
    unknown_types: int = 0
    bad_lengths: int = 0



class Decoder(BufferedDecoder[SmUpdate | Status | RawFrame]):
    """Turns a byte stream into messages, resynchronising after any corruption.

    One resync rule: find the magic, wait for the claimed length, check the CRC; on failure
    drop *one* byte and rescan (never the claimed length, so a frame hiding behind a
    corrupted length byte is still found).  A false sync claiming a long payload holds the
    frames behind it back until enough bytes arrive to refute it, or until :meth:`flush`
    at end of input rescans them.  The retained buffer never exceeds one maximal frame
    (261 bytes): everything before a pending sync is decided at once.
    """

    __slots__ = ("origin", "stats", "vehicle", "via")

    def __init__(self, origin: str = "", via: str = "", vehicle: str = "") -> None:
        super().__init__()
        self.origin = origin
        self.via = via  # stamped on every message (see gateway.model)
        self.vehicle = vehicle
        self.stats = DecoderStats()

    def _decode(self, buf: bytes, bytes_in: int, eof: bool) -> list[SmUpdate | Status | RawFrame]:
        self.stats.bytes_in += bytes_in
        out: list[SmUpdate | Status | RawFrame] = []
        self._buf = self._scan(buf, out, eof)
        return out

    def _scan(self, buf: bytes, out: list, eof: bool) -> bytes:
        stats = self.stats
        origin = self.origin
        via = self.via
        vehicle = self.vehicle
        n = len(buf)
        pos = 0
        skipped = crc_failures = unknown = bad_len = 0
        first = len(out)
        find = buf.find
        append = out.append
        crc_ = _crc
        new = _new
        sm_update = SmUpdate
        unpack64 = _SM_F64_IN.unpack_from
        unpack32 = _SM_F32_IN.unpack_from
        while True:
            # Fast path (same result as find): a frame is usually followed at once by the next.
            i = (pos if pos + 1 < n and buf[pos] == 0xA5 and buf[pos + 1] == 0x5A
                 else find(MAGIC, pos))
            if i < 0:
                # Keep a trailing 0xA5: it may be the first half of the next magic.
                keep = 1 if (not eof and n > pos and buf[n - 1] == 0xA5) else 0
                skipped += n - keep - pos
                pos = n - keep
                break
            if i + HEADER_LEN <= n:
                length = buf[i + 3]
                end = i + OVERHEAD + length
            else:
                length = end = n + 1
            if end > n:
                if not eof:
                    skipped += i - pos
                    pos = i
                    break
                # End of input: this sync can never complete; drop one byte and rescan.
                skipped += i + 1 - pos
                pos = i + 1
                continue
            raw = buf[i:end]
            # A good frame's CRC over type..crc leaves residue 0 (see _CRC_BEFORE_MAGIC).
            if crc_(raw, _CRC_BEFORE_MAGIC):
                crc_failures += 1
                skipped += i + 1 - pos
                pos = i + 1
                continue
            skipped += i - pos
            pos = end
            ftype = buf[i + 2]
            if ftype == TYPE_SM_UPDATE and length == SM_UPDATE_F64_LEN:
                ts, st, armed, smt, rsv, a, b, c, d, e, f, g = unpack64(buf, i + 4)
                append(new(sm_update, (ts, st, armed, smt, a, b, c, d, e, f, g,
                                       SM_UPDATE_F64_LEN, rsv, raw, origin, via, vehicle)))
            elif ftype == TYPE_SM_UPDATE and length == SM_UPDATE_F32_LEN:
                ts, st, armed, smt, rsv, a, b, c, d, e, f, g = unpack32(buf, i + 4)
                append(new(sm_update, (ts, st, armed, smt, a, b, c, d, e, f, g,
                                       SM_UPDATE_F32_LEN, rsv, raw, origin, via, vehicle)))
            elif ftype == TYPE_STATUS and length == STATUS_LEN:
                append(new(Status, (*_STATUS.unpack_from(buf, i + 4), raw, origin, via, vehicle)))
            else:
                if ftype in (TYPE_SM_UPDATE, TYPE_STATUS):
                    bad_len += 1
                else:
                    unknown += 1
                append(new(RawFrame, (ftype, raw[4:-2], raw, origin, via, vehicle)))
        stats.frames += len(out) - first
        stats.bytes_skipped += skipped
        stats.crc_failures += crc_failures
        stats.unknown_types += unknown
        stats.bad_lengths += bad_len
        return buf[pos:]


def decode_all(data: bytes, origin: str = "",
               vehicle: str = "") -> list[SmUpdate | Status | RawFrame]:
    """Decode a complete byte string (feed and flush); convenience for files and tests."""
    dec = Decoder(origin, vehicle=vehicle)
    return dec.feed(data) + dec.flush()


def frame(ftype: int, payload: bytes) -> bytes:
    """Wrap ``payload`` in a wire frame of type ``ftype``."""
    if not 0 <= ftype <= 0xFF:
        raise ValueError(f"frame type {ftype} is not a byte")
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = bytes((ftype, len(payload))) + payload
    return MAGIC + body + _crc(body).to_bytes(2, "little")


def encode(msg: SmUpdate | Status | RawFrame) -> bytes:
    """Encode a message as a wire frame (the revision ``SmUpdate.payload_len`` names).

    Raises ValueError for a field that does not fit its wire type (a state above 255, say);
    ``timestamp_ms`` keeps its low 32 bits, as the firmware's uptime counter does.
    """
    try:
        return _encode(msg)
    except struct.error as exc:
        raise ValueError(f"{type(msg).__name__} does not fit the wire format: {exc}") from None


def _encode(msg: SmUpdate | Status | RawFrame) -> bytes:
    if isinstance(msg, SmUpdate):
        if msg.payload_len == SM_UPDATE_F64_LEN:
            packer = _SM_F64
        elif msg.payload_len == SM_UPDATE_F32_LEN:
            packer = _SM_F32
        else:
            raise ValueError(f"SmUpdate.payload_len must be 36 or 64, not {msg.payload_len}")
        payload = packer.pack(
            msg.timestamp_ms & 0xFFFFFFFF, msg.state, 1 if msg.armed else 0, msg.sm_type,
            msg.reserved, msg.altitude_m, msg.acceleration_mps2, msg.accel_vert_mps2,
            msg.velocity_mps, msg.roll_rad, msg.pitch_rad, msg.yaw_rad,
        )
        return frame(TYPE_SM_UPDATE, payload)
    if isinstance(msg, Status):
        payload = _STATUS.pack(msg.timestamp_ms & 0xFFFFFFFF, msg.state, msg.sm_type,
                               msg.flags, msg.reserved)
        return frame(TYPE_STATUS, payload)
    if isinstance(msg, RawFrame):
        return frame(msg.type, msg.payload)
    raise TypeError(f"no wire encoding for {type(msg).__name__}")


def to_wire_dict(msg: SmUpdate | Status | RawFrame) -> dict:
    """The message under the spec's wire field names (as ``aurora-gateway decode`` prints)."""
    if isinstance(msg, SmUpdate):
        return {
            "type": TYPE_SM_UPDATE,
            "payload_len": msg.payload_len,
            "timestamp_ms": msg.timestamp_ms,
            "state": msg.state,
            "state_name": msg.state_name,
            "armed": int(msg.armed),
            "sm_type": msg.sm_type,
            "altitude": msg.altitude_m,
            "acceleration": msg.acceleration_mps2,
            "accel_vert": msg.accel_vert_mps2,
            "velocity": msg.velocity_mps,
            "roll": msg.roll_rad,
            "pitch": msg.pitch_rad,
            "yaw": msg.yaw_rad,
        }
    if isinstance(msg, Status):
        return {
            "type": TYPE_STATUS,
            "payload_len": STATUS_LEN,
            "timestamp_ms": msg.timestamp_ms,
            "state": msg.state,
            "state_name": msg.state_name,
            "sm_type": msg.sm_type,
            "flags": msg.flags,
            **msg.health(),
        }
    return {"type": msg.type, "payload_len": len(msg.payload), "payload_hex": msg.payload.hex()}
