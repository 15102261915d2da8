"""Sans-I/O MAVLink framing for the router: split bytes into whole frames without decoding them.

Only the header is read: version, length, flags, sequence, source, message id, and, for
messages that have them, the target system/component bytes at their payload offsets.  A frame
stays the exact bytes that arrived (``raw``), so forwarding never re-encodes.

Validation follows the project's one resync rule: find a start marker (0xFD MAVLink 2, 0xFE
MAVLink 1), check the header (a MAVLink 2 frame with unknown incompatibility flags, or a
payload longer than its message allows, is not a frame), check the CRC (with the message's
CRC_EXTRA); on any failure drop **one** byte and look for the next marker.  A message id the
dialect does not know cannot have its CRC checked: like mavlink-router, such frames are
passed on unvalidated (and counted as ``unknown_ids``) rather than dropped — but only while
the framer is *in sync*: at the start of a datagram, or right after a frame that was
validated (or accepted) ended.  After skipped bytes (garbage, a CRC failure, the start of a
stream joined mid-frame) a frame with an unknown id could be anything, so the framer hunts
byte by byte until a frame with a valid CRC puts it back in sync.

:class:`StreamFramer` keeps a small buffer across reads (serial, TCP); :func:`split_datagram`
frames one UDP datagram (a frame never spans datagrams).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import NamedTuple

from backends.mavlink.dialect import MESSAGES
from gateway.counters import Counters
from gateway.crc import mcrf4xx

STX_V2 = 0xFD
STX_V1 = 0xFE
IFLAG_SIGNED = 0x01
HEADER_V2 = 10
HEADER_V1 = 6
SIGNATURE_LEN = 13
MAX_FRAME = HEADER_V2 + 255 + 2 + SIGNATURE_LEN  # 280
STREAM_BUFFER_CAP = 4 * MAX_FRAME

_MARKER = re.compile(rb"[\xfd\xfe]")

# id → (CRC_EXTRA as one byte, max payload length, target_system offset, target_comp offset)
INFO: dict[int, tuple[bytes, int, int, int]] = {
    i: (bytes((m.crc_extra,)), m.max_len, m.target_system_ofs, m.target_component_ofs)
    for i, m in MESSAGES.items()
}


class Frame(NamedTuple):
    """One MAVLink frame as it arrived.  ``target_system``/``target_component`` are -1 when
    the message has no such field (or its id is unknown), 0 for broadcast."""

    raw: bytes
    msgid: int
    sysid: int
    compid: int
    seq: int
    target_system: int
    target_component: int
    signed: bool
    version: int  # 1 or 2


#: A Frame from a tuple without the generated ``__new__``'s Python call (the router's hot path)
new_frame = tuple.__new__


@dataclass
class FramerStats(Counters):
    frames: int = 0
    bytes_in: int = 0
    crc_errors: int = 0
    bad_headers: int = 0
    bytes_skipped: int = 0
    unknown_ids: int = 0
    truncated: int = 0  # a datagram ended inside a frame



def split(buf: bytes | bytearray, stats: FramerStats, out: list[Frame],
          synced: bool = True) -> tuple[int, bool]:
    """Append every whole frame of ``buf`` to ``out``; return the offset of the first byte not
    consumed (the start of an incomplete frame, or ``len(buf)``) and whether the framer is
    in sync there (see the module docstring)."""
    n = len(buf)
    mv = memoryview(buf)
    info_of = INFO
    i = 0
    while i < n:
        b = buf[i]
        if b == STX_V2:
            if n - i < HEADER_V2:
                break
            inc = buf[i + 2]
            if inc & ~IFLAG_SIGNED:
                stats.bad_headers += 1
                i, synced = i + 1, False
                stats.bytes_skipped += 1
                continue
            msgid = buf[i + 7] | (buf[i + 8] << 8) | (buf[i + 9] << 16)
            signed = inc & IFLAG_SIGNED
            head, version, ids = HEADER_V2, 2, i + 4  # ids: seq, sysid, compid
            flen = HEADER_V2 + buf[i + 1] + 2 + (SIGNATURE_LEN if signed else 0)
        elif b == STX_V1:
            if n - i < HEADER_V1:
                break
            msgid = buf[i + 5]
            signed = 0
            head, version, ids = HEADER_V1, 1, i + 2
            flen = HEADER_V1 + buf[i + 1] + 2
        else:
            m = _MARKER.search(buf, i)
            j = m.start() if m is not None else n
            stats.bytes_skipped += j - i
            i = j
            synced = False
            continue
        plen = buf[i + 1]
        info = info_of.get(msgid)
        if info is not None and plen > info[1]:
            stats.bad_headers += 1
            i, synced = i + 1, False
            stats.bytes_skipped += 1
            continue
        if n - i < flen:
            break
        pstart = i + head
        crc_at = pstart + plen
        if info is not None:
            crc = mcrf4xx(info[0], initial=mcrf4xx(mv[i + 1:crc_at]))
            if crc != buf[crc_at] | (buf[crc_at + 1] << 8):
                stats.crc_errors += 1
                i, synced = i + 1, False
                stats.bytes_skipped += 1
                continue
            # Target fields cut off the end: MAVLink 2 trims trailing zeros (so they are 0);
            # a short MAVLink 1 payload simply has none.
            so, co = info[2], info[3]
            if so < 0 or (version == 1 and so >= plen):
                tsys = tcomp = -1
            else:
                tsys = buf[pstart + so] if so < plen else 0
                if co < 0:
                    tcomp = -1
                elif co < plen:
                    tcomp = buf[pstart + co]
                else:
                    tcomp = 0 if version == 2 else -1
            synced = True
        elif synced:
            stats.unknown_ids += 1
            tsys = tcomp = -1
        else:
            i, synced = i + 1, False
            stats.bytes_skipped += 1
            continue
        raw = buf if (i == 0 and flen == n and type(buf) is bytes) else bytes(mv[i:i + flen])
        out.append(Frame(raw, msgid, buf[ids + 1], buf[ids + 2], buf[ids], tsys, tcomp,
                         bool(signed), version))
        stats.frames += 1
        i += flen
    mv.release()
    return i, synced


def frame_v2(data: bytes | bytearray, msgid: int | None = None,
             info: tuple[bytes, int, int, int] | None = None) -> Frame:
    """The Frame of a datagram that is one whole MAVLink 2 frame of a known id, already
    checked (its id and ``INFO`` entry are found when not given)."""
    if msgid is None:
        msgid = data[7] | (data[8] << 8) | (data[9] << 16)
    if info is None:
        info = INFO[msgid]
    so, co = info[2], info[3]
    plen = data[1]
    if so < 0:
        tsys = tcomp = -1
    else:
        tsys = data[HEADER_V2 + so] if so < plen else 0
        tcomp = -1 if co < 0 else (data[HEADER_V2 + co] if co < plen else 0)
    return new_frame(Frame, (data, msgid, data[5], data[6], data[4], tsys, tcomp,
                             bool(data[2]), 2))


def split_datagram(data: bytes, stats: FramerStats) -> list[Frame]:
    """Every frame in one UDP datagram; a trailing partial frame is counted and dropped."""
    n = len(data)
    stats.bytes_in += n
    # The router's common case first: the datagram is one whole MAVLink 2 frame of a known id
    # with a good CRC (what autopilots and ground stations send).  Anything else, or any
    # doubt, takes the general path below, which counts what is wrong.
    if n > HEADER_V2 + 1 and data[0] == STX_V2 and not data[2] & ~IFLAG_SIGNED:
        plen = data[1]
        crc_at = HEADER_V2 + plen
        if crc_at + 2 + (SIGNATURE_LEN if data[2] else 0) == n:
            msgid = data[7] | (data[8] << 8) | (data[9] << 16)
            info = INFO.get(msgid)
            if (info is not None and plen <= info[1]
                    and mcrf4xx(data[1:crc_at] + info[0])  # one call: header, payload, extra
                    == data[crc_at] | (data[crc_at + 1] << 8)):
                stats.frames += 1
                return [frame_v2(data, msgid, info)]
    out: list[Frame] = []
    end, _ = split(data, stats, out)
    if end < len(data):
        stats.truncated += 1
        stats.bytes_skipped += len(data) - end
    return out


class StreamFramer:
    """Frames from a byte stream fed in arbitrary pieces (serial port, TCP connection)."""

    def __init__(self) -> None:
        self.stats = FramerStats()
        self._buf = bytearray()
        self._synced = False  # joined mid-stream: in sync after the first valid frame

    def feed(self, data: bytes) -> list[Frame]:
        """Whole frames completed by ``data``, in order."""
        self.stats.bytes_in += len(data)
        buf = self._buf
        buf += data
        out: list[Frame] = []
        end, self._synced = split(buf, self.stats, out, self._synced)
        if end:
            del buf[:end]
        if len(buf) > STREAM_BUFFER_CAP:  # cannot happen with a sane splitter; stay bounded
            self.stats.bytes_skipped += len(buf)
            buf.clear()
        return out

    def pending(self) -> int:
        """Bytes held back as the start of an incomplete frame."""
        return len(self._buf)
