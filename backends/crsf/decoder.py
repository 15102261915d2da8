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



class Decoder:
    """Turns a CRSF byte stream into records, resynchronising after any corruption."""

    __slots__ = ("_buf", "_find_sync", "stats")

    def __init__(self, syncs: Iterable[int] = SYNC_BYTES) -> None:
        sync_set = sorted(set(syncs))
        if not sync_set or any(not 0 <= s <= 0xFF for s in sync_set):
            raise ValueError("sync bytes must be a non-empty set of byte values")
        self._find_sync = re.compile(b"[" + b"".join(re.escape(bytes((s,))) for s in sync_set)
                                     + b"]").search
        self._buf = b""
        self.stats = DecoderStats()

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[Record]:
        """Add bytes; return every record completed by them, in stream order."""
        self.stats.bytes_in += len(data)
        buf = self._buf + bytes(data) if self._buf else bytes(data)
        out: list[Record] = []
        self._buf = self._scan(buf, out, eof=False)
        return out

    def flush(self) -> list[Record]:
        """End of input: rescan what is held back; an incomplete tail is counted as skipped."""
        out: list[Record] = []
        if self._buf:
            self._buf = self._scan(self._buf, out, eof=True)
        return out

    def _scan(self, buf: bytes, out: list[Record], eof: bool) -> bytes:
        st = self.stats
        n = len(buf)
        pos = 0
        find = self._find_sync
        while True:
            m = find(buf, pos)
            if m is None:
                st.bytes_skipped += n - pos
                return b""
            i = m.start()
            if i + 1 >= n:  # the length byte has not arrived
                if eof:
                    st.bytes_skipped += n - pos
                    return b""
                st.bytes_skipped += i - pos
                return buf[i:]
            length = buf[i + 1]
            if not MIN_LEN <= length <= MAX_LEN:
                st.bad_lengths += 1
                st.bytes_skipped += i + 1 - pos
                pos = i + 1
                continue
            end = i + 2 + length
            if end > n:
                if not eof:
                    st.bytes_skipped += i - pos
                    return buf[i:]
                st.bytes_skipped += i + 1 - pos  # can never complete: drop one, rescan
                pos = i + 1
                continue
            if crc(buf[i + 2:end]):  # CRC over type..crc leaves residue 0 on a good frame
                st.crc_failures += 1
                st.bytes_skipped += i + 1 - pos
                pos = i + 1
                continue
            st.bytes_skipped += i - pos
            pos = end
            st.frames += 1
            ftype = buf[i + 2]
            st.by_type[ftype] += 1
            payload = buf[i + 3:end - 1]
            rec = decode_payload(ftype, payload)
            if rec is None:
                st.bad_payloads += 1
                rec = UnknownFrame(ftype, payload)
            out.append(rec)


def decode_all(data: bytes) -> list[Record]:
    """Decode a complete byte string (feed, then flush)."""
    dec = Decoder()
    return dec.feed(data) + dec.flush()
