"""Sans-I/O CRSF stream decoder: bytes in, records out (link statistics, RC channels, and
every telemetry type :mod:`backends.crsf.frames` knows).

The project's one resync rule: find a sync byte (0xC8, 0xEA or 0xEC), check the length byte
(2..62), wait for the whole frame, check the CRC; on any failure drop *one* byte and rescan,
never the claimed length.  Corruption is counted, never raised.  The retained buffer never
exceeds one maximal frame (64 bytes).
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field

from backends.crsf.frames import (
    MAX_LEN,
    MIN_LEN,
    SYNC_BYTES,
    Record,
    UnknownFrame,
    crc,
    decode_payload,
)
from gateway.counters import Counters
from gateway.resync import BAD, WAIT, ResyncDecoder


@dataclass
class DecoderStats(Counters):
    """What a decoder has seen; ``bytes_skipped`` counts every byte outside a valid frame."""

    bytes_in: int = 0
    frames: int = 0
    crc_failures: int = 0
    bad_lengths: int = 0
    bad_payloads: int = 0
    bytes_skipped: int = 0
    by_type: Counter[int] = field(default_factory=Counter)


class Decoder(ResyncDecoder[Record]):
    """Turns a CRSF byte stream into records, resynchronising after any corruption."""

    __slots__ = ("_search_sync", "stats")

    def __init__(self, syncs: Iterable[int] = SYNC_BYTES) -> None:
        super().__init__()
        sync_set = sorted(set(syncs))
        if not sync_set or any(not 0 <= s <= 0xFF for s in sync_set):
            raise ValueError("sync bytes must be a non-empty set of byte values")
        self._search_sync = re.compile(
            b"[" + b"".join(re.escape(bytes((s,))) for s in sync_set) + b"]").search
        self.stats = DecoderStats()

    def _find_start(self, buf: bytes, pos: int) -> int:
        m = self._search_sync(buf, pos)
        return -1 if m is None else m.start()

    def _frame_at(self, buf: bytes, i: int, out: list[Record]) -> int:
        st = self.stats
        if i + 1 >= len(buf):  # the length byte has not arrived
            return WAIT
        length = buf[i + 1]
        if not MIN_LEN <= length <= MAX_LEN:
            st.bad_lengths += 1
            return BAD
        end = i + 2 + length
        if end > len(buf):
            return WAIT
        if crc(buf[i + 2:end]):  # CRC over type..crc leaves residue 0 on a good frame
            st.crc_failures += 1
            return BAD
        st.frames += 1
        ftype = buf[i + 2]
        st.by_type[ftype] += 1
        payload = buf[i + 3:end - 1]
        rec = decode_payload(ftype, payload)
        if rec is None:
            st.bad_payloads += 1
            rec = UnknownFrame(ftype, payload)
        out.append(rec)
        return end

    def _count(self, bytes_in: int, skipped: int) -> None:
        self.stats.bytes_in += bytes_in
        self.stats.bytes_skipped += skipped


def decode_all(data: bytes) -> list[Record]:
    """Decode a complete byte string (feed, then flush)."""
    dec = Decoder()
    return dec.feed(data) + dec.flush()
