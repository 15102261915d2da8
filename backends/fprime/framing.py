"""F´ framings (sans-I/O): F´ packets to bytes on the wire, and the ground's uplink back.

Two framings, as fprime-gds 4.4.1 names them (``--framing-selection``):

``fprime`` (:class:`FprimeFramer`, :class:`FprimeDeframer`)
    ``DEADBEEF | U32 length | packet | CRC-32``, big-endian, the CRC-32 as zlib computes it over
    the start word, the length and the packet.  One frame per packet, both ways.

``ccsds`` (:class:`CcsdsFramer`, :class:`TcDeframer`; F´ v4's default stack and fprime-gds's
default ``space-packet-space-data-link``)
    Down: each packet in a CCSDS Space Packet (version 0, type TM, no secondary header,
    APID = the packet's U16 descriptor, sequence flags ``0b11``, a 14-bit count per APID,
    length field = data length - 1); the Space Packets back to back in fixed-size TM Transfer
    Frames: a 6-byte header (version 0, SCID 10 bits, VCID 3 bits, no OCF; master and virtual
    channel frame counts, 8 bits each; data field status ``0b00011`` + the 11-bit First Header
    Pointer), the data field, a CRC-16/CCITT-FALSE trailer over the rest of the frame.
    Up: fprime-gds sends each command in a TC frame (5-byte header: version 0, bypass flag,
    SCID, VCID 6 bits, 10-bit frame length - 1, sequence number; then a TC Space Packet; then
    a CRC-16/CCITT-FALSE).

Choices:

- Packets span TM frames; the First Header Pointer is the offset of the first packet header that
  starts in a frame's data field (``0x7FF`` when none does), which is how fprime-gds reassembles
  them.  :meth:`CcsdsFramer.frame` returns whole frames only: the last one is completed with an
  idle Space Packet (APID ``0x7FF``, data bytes ``0x44`` as F´'s TmFramer fills).  When the room
  left is 1..6 bytes, less than an idle packet (6-byte header + at least one data byte), the idle
  packet starts there and fills the whole of one more frame, whose pointer is then ``0x7FF``:
  no packet header is ever cut short, and fprime-gds drops the idle packet after reassembling it.
- fprime-gds completes a packet that spans frames only when a later frame's pointer shows where
  the next packet starts.  So a call whose last frame would hold nothing but the tail of a
  spanning packet (it ends exactly at the frame's end) gets one more frame holding an idle
  packet: every call's packets reach the ground with that call's frames, none waits for the next.
- Counts run on across calls (frame counts wrap at 256, sequence counts at 16384), so a ground
  deframer that checks them sees no gap; each peer needs its own framer.
- Frames are at most 2048 bytes (the CCSDS TM limit, which keeps every data field offset below
  the pointer's reserved values ``0x7FE``/``0x7FF``).  A packet is refused (``ValueError``,
  before any count moves) when it is shorter than its descriptor, its descriptor is not an APID
  below ``0x7FF``, or it is longer than a Space Packet holds (65536 bytes).
- Deframers never raise: they find the sync, check the length bound, check the CRC, and on a
  failure drop **one** byte and rescan (the gateway's resync rule).  Dropped bytes are counted in
  ``garbage_bytes``; fprime-gds's ip adapter keep-alive (the unframed bytes ``sitting well``,
  sent every 0.5 s in both framings) is recognised and counted in ``keepalives`` instead.
  Partial input is kept between calls; the buffer never holds more than one frame's worth.
"""

from __future__ import annotations

import re
import struct
import zlib
from collections.abc import Sequence
from typing import NamedTuple, Protocol

from gateway.crc import ibm_3740

__all__ = [
    "DEFAULT_FRAMING", "FRAMINGS", "KEEPALIVE", "CcsdsFramer", "Deframer", "FprimeDeframer",
    "FprimeFramer", "Framer", "Framing", "TcDeframer", "crc16_ccitt", "make_deframer",
    "make_framer",
]

#: What fprime-gds's ip adapter writes up, unframed, every ``--keepalive-interval`` (0.5 s).
KEEPALIVE = b"sitting well"

FPRIME_START = b"\xde\xad\xbe\xef"
_FP_HEADER = struct.Struct(">4sI")
#: fprime-gds's ``FpFramerDeframer.MAXIMUM_DATA_SIZE``: it takes no longer packet either.
FPRIME_MAX_PACKET = 4095

SP_HEADER = struct.Struct(">HHH")  # packet id, sequence control, data length - 1
SP_HEADER_SIZE = SP_HEADER.size
SP_MAX_DATA = 65536
IDLE_APID = 0x7FF
IDLE_FILL = 0x44  # F´ TmFramer's IDLE_DATA_PATTERN
SEQ_FLAGS_UNSEGMENTED = 0b11 << 14
SEQ_COUNT_MODULO = 1 << 14
TYPE_TC = 1 << 12

TM_HEADER = struct.Struct(">HBBH")  # frame id, MC count, VC count, data field status
TM_HEADER_SIZE = TM_HEADER.size
CRC_SIZE = 2
TM_MAX_FRAME = 2048
#: The smallest TM frame that holds a header, one 1-byte Space Packet and the CRC.
TM_MIN_FRAME = TM_HEADER_SIZE + SP_HEADER_SIZE + 1 + CRC_SIZE
DFS_SEGMENT_LENGTH_ID = 0b11 << 11
FHP_NO_PACKET_START = 0x7FF

TC_HEADER = struct.Struct(">HHB")  # version/bypass/control/SCID, VCID/length - 1, sequence
TC_HEADER_SIZE = TC_HEADER.size
TC_MAX_FRAME = 1024
TC_MIN_FRAME = TC_HEADER_SIZE + SP_HEADER_SIZE + 1 + CRC_SIZE


def crc16_ccitt(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR)."""
    return ibm_3740(data)


class Framer(Protocol):
    """Downlink: F´ packets in, the bytes to write out."""

    frames: int
    packets: int

    def frame(self, packets: Sequence[bytes]) -> bytes: ...


class Deframer(Protocol):
    """Uplink: bytes in (any split), the F´ packets found so far out; never raises."""

    frames: int
    bad_crc: int
    garbage_bytes: int
    keepalives: int

    def feed(self, data: bytes) -> list[bytes]: ...


# --------------------------------------------------------------------------------------------
# downlink


class FprimeFramer:
    """``DEADBEEF | U32 length | packet | CRC-32`` per packet."""

    name = "fprime"

    def __init__(self) -> None:
        self.frames = 0
        self.packets = 0

    def frame(self, packets: Sequence[bytes]) -> bytes:
        """The frames of ``packets``, in order."""
        out = bytearray()
        for packet in packets:
            head = _FP_HEADER.pack(FPRIME_START, len(packet))
            out += head
            out += packet
            out += struct.pack(">I", zlib.crc32(packet, zlib.crc32(head)))
        self.frames += len(packets)
        self.packets += len(packets)
        return bytes(out)


class CcsdsFramer:
    """Space Packets in fixed-size TM Transfer Frames (see the module docstring)."""

    name = "ccsds"

    def __init__(self, scid: int = 0x44, vcid: int = 1, frame_size: int = 1024) -> None:
        if not 0 <= scid <= 0x3FF:
            raise ValueError(f"spacecraft id {scid} is not 10 bits (0..1023)")
        if not 0 <= vcid <= 7:
            raise ValueError(f"virtual channel id {vcid} is not 3 bits (0..7)")
        if not TM_MIN_FRAME <= frame_size <= TM_MAX_FRAME:
            raise ValueError(f"TM frame size {frame_size} is not within "
                             f"{TM_MIN_FRAME}..{TM_MAX_FRAME}")
        self.scid = scid
        self.vcid = vcid
        self.frame_size = frame_size
        self.field_size = frame_size - TM_HEADER_SIZE - CRC_SIZE
        self._frame_id = (scid << 4) | (vcid << 1)  # version 0, OCF flag 0
        self._seq: dict[int, int] = {}
        self._frame_count = 0  # master and virtual channel counts (one virtual channel)
        self.frames = 0
        self.packets = 0
        self.idle_bytes = 0  # whole idle packets, headers included

    def _space_packet(self, apid: int, data: bytes) -> bytes:
        count = self._seq.get(apid, 0)
        self._seq[apid] = (count + 1) % SEQ_COUNT_MODULO
        return SP_HEADER.pack(apid, SEQ_FLAGS_UNSEGMENTED | count, len(data) - 1) + data

    def frame(self, packets: Sequence[bytes]) -> bytes:
        """Whole TM frames carrying ``packets`` in order, the last one completed with idle."""
        for packet in packets:
            if len(packet) < 2:
                raise ValueError(f"a {len(packet)}-byte packet has no U16 descriptor")
            if len(packet) > SP_MAX_DATA:
                raise ValueError(f"a {len(packet)}-byte packet exceeds a Space Packet's "
                                 f"{SP_MAX_DATA} bytes")
            if (packet[0] << 8 | packet[1]) >= IDLE_APID:
                raise ValueError(f"descriptor {packet[0] << 8 | packet[1]:#x} is not an APID "
                                 f"below {IDLE_APID:#x}")
        if not packets:
            return b""
        stream = bytearray()
        starts: list[int] = []
        for packet in packets:
            starts.append(len(stream))
            stream += self._space_packet(packet[0] << 8 | packet[1], packet)
        room = -len(stream) % self.field_size
        if room == 0 and starts[-1] < len(stream) - self.field_size:
            room = self.field_size  # see the module docstring: a spanning packet ends the call
        if room:
            if room < SP_HEADER_SIZE + 1:  # the idle packet runs through one more frame
                room += self.field_size
            starts.append(len(stream))
            stream += self._space_packet(IDLE_APID, bytes([IDLE_FILL]) * (room - SP_HEADER_SIZE))
            self.idle_bytes += room
        out = bytearray()
        field_size = self.field_size
        i = 0
        for offset in range(0, len(stream), field_size):
            while i < len(starts) and starts[i] < offset:
                i += 1
            fhp = starts[i] - offset if i < len(starts) and starts[i] < offset + field_size \
                else FHP_NO_PACKET_START
            count = self._frame_count
            self._frame_count = (count + 1) & 0xFF
            body = TM_HEADER.pack(self._frame_id, count, count, DFS_SEGMENT_LENGTH_ID | fhp) \
                + stream[offset:offset + field_size]
            out += body
            out += crc16_ccitt(body).to_bytes(2, "big")
            self.frames += 1
        self.packets += len(packets)
        return bytes(out)


# --------------------------------------------------------------------------------------------
# uplink

_NEED_MORE = 0
_REJECT = -1
_BAD_CRC = -2


class _ScanningDeframer:
    """Find a candidate start, try a frame there; on failure drop one byte and rescan."""

    def __init__(self, candidates: re.Pattern[bytes]) -> None:
        self._candidates = candidates
        self._buf = bytearray()
        self.frames = 0
        self.bad_crc = 0
        self.garbage_bytes = 0
        self.keepalives = 0

    def feed(self, data: bytes) -> list[bytes]:
        """The F´ packets completed by ``data`` (partial input is kept for the next call)."""
        buf = self._buf
        buf += data
        out: list[bytes] = []
        pos = 0
        n = len(buf)
        while pos < n:
            m = self._candidates.search(buf, pos)
            start = n if m is None else m.start()
            if start > pos:
                self.garbage_bytes += start - pos
                pos = start
                continue
            if buf[pos] == KEEPALIVE[0]:
                end = min(n, pos + len(KEEPALIVE))
                if buf[pos:end] == KEEPALIVE[:end - pos]:
                    if end - pos < len(KEEPALIVE):
                        break  # maybe a keep-alive: wait for the rest
                    self.keepalives += 1
                    pos = end
                    continue
                result = _REJECT
            else:
                result = self._try(buf, pos, n, out)
            if result == _NEED_MORE:
                break
            if result > 0:
                self.frames += 1
                pos += result
                continue
            if result == _BAD_CRC:
                self.bad_crc += 1
            self.garbage_bytes += 1
            pos += 1
        del buf[:pos]
        return out

    def _try(self, buf: bytearray, pos: int, n: int, out: list[bytes]) -> int:
        """A frame's length if one is at ``pos`` (its packets appended to ``out``), or
        ``_NEED_MORE`` / ``_REJECT`` / ``_BAD_CRC``."""
        raise NotImplementedError


class FprimeDeframer(_ScanningDeframer):
    """Reads ``DEADBEEF`` frames (and skips keep-alives) from the ground's uplink."""

    name = "fprime"

    def __init__(self) -> None:
        super().__init__(re.compile(b"[" + re.escape(FPRIME_START[:1] + KEEPALIVE[:1]) + b"]"))
        self.packets = 0

    def _try(self, buf: bytearray, pos: int, n: int, out: list[bytes]) -> int:
        have = n - pos
        if buf[pos:pos + min(have, 4)] != FPRIME_START[:min(have, 4)]:
            return _REJECT
        if have < _FP_HEADER.size:
            return _NEED_MORE
        length = int.from_bytes(buf[pos + 4:pos + 8], "big")
        if length > FPRIME_MAX_PACKET:
            return _REJECT
        total = _FP_HEADER.size + length + 4
        if have < total:
            return _NEED_MORE
        end = pos + total - 4
        if zlib.crc32(buf[pos:end]) != int.from_bytes(buf[end:end + 4], "big"):
            return _BAD_CRC
        if length:
            out.append(bytes(buf[pos + _FP_HEADER.size:end]))
            self.packets += 1
        return total


class TcDeframer(_ScanningDeframer):
    """Reads TC frames carrying Space Packets (and skips keep-alives) from the ground's uplink.

    A frame is taken when its version is 0, it is a data frame (Type-D, FARM bypassed or not),
    its spacecraft id is ``scid`` (any virtual channel) and its CRC-16 holds; each non-idle
    Space Packet in its data field (version 0) gives its data, the F´ packet.  A frame whose
    data field is not whole Space Packets is counted in ``bad_packets``.
    """

    name = "ccsds"

    def __init__(self, scid: int = 0x44) -> None:
        if not 0 <= scid <= 0x3FF:
            raise ValueError(f"spacecraft id {scid} is not 10 bits (0..1023)")
        self.scid = scid
        first = scid >> 8
        super().__init__(re.compile(b"[" + re.escape(bytes([first, first | 0x20]) + KEEPALIVE[:1])
                                    + b"]"))
        self.packets = 0
        self.bad_packets = 0

    def _try(self, buf: bytearray, pos: int, n: int, out: list[bytes]) -> int:
        have = n - pos
        if have < 2:
            return _NEED_MORE
        word = buf[pos] << 8 | buf[pos + 1]
        if word & 0xDFFF != self.scid:  # version 0, Type-D, reserved 0, SCID; bypass either
            return _REJECT
        if have < TC_HEADER_SIZE:
            return _NEED_MORE
        total = ((buf[pos + 2] & 0x03) << 8 | buf[pos + 3]) + 1
        if total < TC_MIN_FRAME:
            return _REJECT
        if have < total:
            return _NEED_MORE
        end = pos + total - CRC_SIZE
        if crc16_ccitt(bytes(buf[pos:end])) != (buf[end] << 8 | buf[end + 1]):
            return _BAD_CRC
        self._packets(bytes(buf[pos + TC_HEADER_SIZE:end]), out)
        return total

    def _packets(self, field: bytes, out: list[bytes]) -> None:
        offset = 0
        while offset < len(field):
            if len(field) - offset < SP_HEADER_SIZE:
                self.bad_packets += 1
                return
            packet_id, _, length = SP_HEADER.unpack_from(field, offset)
            size = SP_HEADER_SIZE + length + 1
            if packet_id >> 13 != 0 or len(field) - offset < size:
                self.bad_packets += 1
                return
            if packet_id & IDLE_APID != IDLE_APID:
                out.append(field[offset + SP_HEADER_SIZE:offset + size])
                self.packets += 1
            offset += size


# --------------------------------------------------------------------------------------------
# selection


class Framing(NamedTuple):
    """One framing: its downlink framer and uplink deframer classes."""

    framer: type[FprimeFramer] | type[CcsdsFramer]
    deframer: type[FprimeDeframer] | type[TcDeframer]
    description: str


FRAMINGS: dict[str, Framing] = {
    "ccsds": Framing(CcsdsFramer, TcDeframer,
                     "Space Packets in TM frames (F´ v4, fprime-gds default)"),
    "fprime": Framing(FprimeFramer, FprimeDeframer,
                      "DEADBEEF frames (fprime-gds --framing-selection fprime)"),
}
#: What fprime-gds 4.4.1 selects when started without ``--framing-selection``.
DEFAULT_FRAMING = "ccsds"


def _check(name: str) -> None:
    if name not in FRAMINGS:
        raise ValueError(f"F´ framing {name!r}: use one of {', '.join(FRAMINGS)}")


def make_framer(name: str, *, scid: int = 0x44, vcid: int = 1,
                frame_size: int = 1024) -> FprimeFramer | CcsdsFramer:
    """A new downlink framer for ``name`` (``fprime`` ignores the CCSDS parameters)."""
    _check(name)
    if name == "ccsds":
        return CcsdsFramer(scid=scid, vcid=vcid, frame_size=frame_size)
    return FprimeFramer()


def make_deframer(name: str, *, scid: int = 0x44) -> FprimeDeframer | TcDeframer:
    """A new uplink deframer for ``name`` (``fprime`` ignores ``scid``)."""
    _check(name)
    if name == "ccsds":
        return TcDeframer(scid=scid)
    return FprimeDeframer()
