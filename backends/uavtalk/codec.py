"""Sans-I/O UAVTalk packet codec (LibrePilot 16.09 framing): bytes in, packets out.

A packet, little-endian (``../shared/specs/uavtalk.md``)::

    sync 0x3C | type | size u16 | object id u32 | instance id u16 | [timestamp u16] | data | CRC

``size`` counts everything from the sync byte to the end of the data (the timestamp too, as the
firmware's ``uavtalk.c`` does), never the CRC; 10 ≤ size ≤ 266.  The CRC is CRC-8 polynomial 0x07,
init 0, over every byte before it.  Type bit 0x80 marks the timestamped variants (only OBJ and
OBJ_ACK have them in 16.09); a 16.09 GCS rejects those, so :func:`encode` never produces them,
while :class:`Decoder` decodes and counts them.

The project's one resync rule: find the sync byte (``bytes.find``), check the type, the size
bounds and — before waiting for the rest — the data length against the object's known length
(the firmware checks it at the same point); wait for the whole packet; check the CRC.  On any
failure drop *one* byte and rescan, never the claimed size.  Corruption is counted, never raised.
The retained buffer never exceeds one maximal packet (267 bytes).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

from gateway import crc as _crc
from gateway.counters import Counters
from gateway.resync import BAD, WAIT, ResyncDecoder

SYNC = 0x3C
HEADER_LENGTH = 10  # sync, type, size, object id, instance id
TIMESTAMP_LENGTH = 2
MIN_SIZE = HEADER_LENGTH
MAX_SIZE = 266  # the 16.09 GCS: header 10 + max payload 256
MAX_DATA_LENGTH = MAX_SIZE - HEADER_LENGTH
MAX_PACKET_LENGTH = MAX_SIZE + 1  # with the CRC byte
TIMESTAMPED = 0x80
ALL_INSTANCES = 0xFFFF

_SYNC_BYTE = bytes((SYNC,))
_HEADER = struct.Struct("<BBHIH")  # sync, type, size, object id, instance id
_TIMESTAMP = struct.Struct("<H")


class PacketType(IntEnum):
    """The five UAVTalk packet types (without the timestamp bit)."""

    OBJ = 0x20
    OBJ_REQ = 0x21
    OBJ_ACK = 0x22
    ACK = 0x23
    NACK = 0x24


_NO_DATA = frozenset((PacketType.OBJ_REQ, PacketType.ACK, PacketType.NACK))


class Packet(NamedTuple):
    """One UAVTalk packet; ``timestamp`` is set only on a received timestamped variant."""

    type: PacketType
    object_id: int
    instance_id: int = 0
    data: bytes = b""
    timestamp: int | None = None


def _type_table() -> tuple[tuple[PacketType, int, bool] | None, ...]:
    """Per type byte: (packet type, header length, carries data), or None for an invalid byte."""
    table: list[tuple[PacketType, int, bool] | None] = [None] * 256
    for t in PacketType:
        table[t] = (t, HEADER_LENGTH, t not in _NO_DATA)
    for t in (PacketType.OBJ, PacketType.OBJ_ACK):  # uavtalk_priv.h: OBJ_TS and OBJ_ACK_TS only
        table[t | TIMESTAMPED] = (t, HEADER_LENGTH + TIMESTAMP_LENGTH, True)
    return tuple(table)


_TYPES = _type_table()


def _make_crc8() -> Callable[[bytes], int]:
    """fastcrc's SMBus CRC-8 is poly 0x07, init 0, no reflection, no xorout: use it if it checks."""
    smbus = _crc.smbus
    if smbus is not None and smbus(b"123456789") == 0xF4:
        return smbus
    table = []
    for byte in range(256):
        c = byte
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
        table.append(c)

    def crc8_table(data: bytes) -> int:
        c = 0
        for b in data:
            c = table[c ^ b]
        return c

    return crc8_table


_crc8 = _make_crc8()


def crc8(data: bytes) -> int:
    """CRC-8, polynomial 0x07, init 0, no reflection, no xorout (``crc8(b"123456789") == 0xF4``)."""
    return _crc8(data)


def encode(p: Packet) -> bytes:
    """The wire bytes of ``p``.  ValueError for what a 16.09 peer would not accept: a timestamp,
    data on OBJ_REQ/ACK/NACK, more than 256 data bytes, ids out of range."""
    if p.timestamp is not None:
        raise ValueError("timestamped UAVTalk packets are never sent (a 16.09 GCS rejects them)")
    ptype = PacketType(p.type)
    data = bytes(p.data)
    if ptype in _NO_DATA and data:
        raise ValueError(f"{ptype.name} carries no data ({len(data)} bytes given)")
    if len(data) > MAX_DATA_LENGTH:
        raise ValueError(f"{len(data)} data bytes exceed UAVTalk's {MAX_DATA_LENGTH}")
    if not 0 <= p.object_id <= 0xFFFFFFFF:
        raise ValueError(f"object id {p.object_id:#x} is not a u32")
    if not 0 <= p.instance_id <= 0xFFFF:
        raise ValueError(f"instance id {p.instance_id} is not a u16")
    body = _HEADER.pack(SYNC, ptype, HEADER_LENGTH + len(data), p.object_id, p.instance_id) + data
    return body + bytes((_crc8(body),))


@dataclass
class DecoderStats(Counters):
    """What a decoder has seen.

    ``packets`` counts every packet returned (``timestamped`` and ``unknown_object`` ones too);
    ``bad_size`` a size outside 10..266; ``bad_length`` a data length that differs from the known
    object's (or any data on OBJ_REQ/ACK/NACK); ``bytes_skipped`` every byte outside a returned
    packet (a sync byte followed by an invalid type byte is just skipped).
    """

    packets: int = 0
    bad_crc: int = 0
    bad_size: int = 0
    unknown_object: int = 0
    bad_length: int = 0
    bytes_skipped: int = 0
    timestamped: int = 0


class Decoder(ResyncDecoder[Packet]):
    """Turns a UAVTalk byte stream into :class:`Packet` s, resynchronising after any corruption.

    ``data_length(object_id)`` gives a known object's data length (None: unknown object); without
    it no lengths are checked and nothing is counted as unknown.  Packets of unknown objects that
    pass the CRC are returned (and counted) so that a session can NACK them.
    """

    __slots__ = ("_data_length", "stats")

    def __init__(self, data_length: Callable[[int], int | None] | None = None) -> None:
        super().__init__()
        self._data_length = data_length
        self.stats = DecoderStats()

    def _find_start(self, buf: bytes, pos: int) -> int:
        return buf.find(_SYNC_BYTE, pos)

    def _frame_at(self, buf: bytes, i: int, out: list[Packet]) -> int:
        st = self.stats
        avail = len(buf) - i
        if avail < 2:
            return WAIT
        info = _TYPES[buf[i + 1]]
        if info is None:  # not a packet start: skip the sync byte
            return BAD
        ptype, hlen, has_data = info
        if avail < 4:
            return WAIT
        size = buf[i + 2] | buf[i + 3] << 8
        if not hlen <= size <= MAX_SIZE:
            st.bad_size += 1
            return BAD
        if not has_data and size != hlen:
            st.bad_length += 1
            return BAD
        if avail < HEADER_LENGTH:
            return WAIT
        _, _, _, object_id, instance_id = _HEADER.unpack_from(buf, i)
        known = True
        if self._data_length is not None:
            expected = self._data_length(object_id)
            if expected is None:
                known = False
            elif has_data and size - hlen != expected:
                st.bad_length += 1
                return BAD
        end = i + size + 1
        if end > len(buf):
            return WAIT
        if _crc8(buf[i:end]):  # no reflection, no xorout: a good packet leaves residue 0
            st.bad_crc += 1
            return BAD
        st.packets += 1
        if not known:
            st.unknown_object += 1
        if hlen == HEADER_LENGTH:
            out.append(Packet(ptype, object_id, instance_id, buf[i + HEADER_LENGTH:end - 1]))
        else:
            st.timestamped += 1
            (stamp,) = _TIMESTAMP.unpack_from(buf, i + HEADER_LENGTH)
            out.append(Packet(ptype, object_id, instance_id, buf[i + hlen:end - 1], stamp))
        return end

    def _count(self, bytes_in: int, skipped: int) -> None:
        self.stats.bytes_skipped += skipped  # the bytes fed are not counted here
