"""The recording format: every received frame, untouched, with its receive time.

File layout (all integers little-endian)::

    header  8 bytes   89 41 55 52 0D 0A 1A 0A   ("\\x89AUR\\r\\n\\x1a\\n": binary, and mangled
                                                 visibly by any text-mode transfer)
            2 bytes   format version (1)
            2 bytes   reserved (0)
    record  8 bytes   receive time, f64 seconds since the Unix epoch
            2 bytes   N, frame length
            N bytes   the wire frame exactly as received (A5 5A … CRC)
            4 bytes   CRC-32 (ISO-HDLC, zlib's) over the 10 + N bytes before it

Each record is written with one unbuffered ``write`` call, so a ``kill -9`` leaves at most the
last record torn.  The reader checks every record's CRC and skips what fails: a torn tail
ends the replay cleanly, and corruption mid-file is passed by rescanning one byte at a time
(the same resync rule as the wire decoder).  Opening an existing recording for append cuts a
torn tail off first, so new records never follow garbage.
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

MAGIC = b"\x89AUR\r\n\x1a\n"
VERSION = 1
HEADER = MAGIC + struct.pack("<HH", VERSION, 0)
_REC_HEAD = struct.Struct("<dH")
_CRC = struct.Struct("<I")
REC_OVERHEAD = _REC_HEAD.size + _CRC.size
MAX_FRAME = 261


class RecordingError(ValueError):
    """The file is not a recording of a version this gateway reads."""


@dataclass
class ReadStats:
    records: int = 0
    torn_tail_bytes: int = 0
    corrupt_skips: int = 0
    bytes_skipped: int = 0


def encode_record(t: float, frame: bytes) -> bytes:
    """One record's bytes.  Frames longer than a wire frame can be (:data:`MAX_FRAME`) are
    refused: the reader treats a longer record as corruption, so it could never be read."""
    if len(frame) > MAX_FRAME:
        raise ValueError(f"a {len(frame)}-byte frame is longer than a wire frame "
                         f"({MAX_FRAME} bytes)")
    body = _REC_HEAD.pack(t, len(frame)) + frame
    return body + _CRC.pack(zlib.crc32(body))


def _check_header(data: bytes, path: object) -> None:
    if len(data) < len(HEADER) or data[: len(MAGIC)] != MAGIC:
        raise RecordingError(f"{path}: not an Aurora recording (bad magic)")
    (version,) = struct.unpack_from("<H", data, len(MAGIC))
    if version != VERSION:
        raise RecordingError(f"{path}: recording format version {version}; this gateway "
                             f"reads version {VERSION}")


def scan(data: bytes, stats: ReadStats | None = None,
         start: int = len(HEADER)) -> Iterator[tuple[int, float, bytes]]:
    """Yield (offset, time, frame) for every intact record in ``data`` from ``start``.

    Bytes that are not an intact record are skipped one at a time until one is found; the
    ones after the last intact record are the torn tail.
    """
    st = stats if stats is not None else ReadStats()
    n = len(data)
    pos = start
    skipping_from: int | None = None
    while pos < n:
        ok = False
        if pos + REC_OVERHEAD <= n:
            t, length = _REC_HEAD.unpack_from(data, pos)
            end = pos + _REC_HEAD.size + length
            if length <= MAX_FRAME and end + _CRC.size <= n:
                ok = _CRC.unpack_from(data, end)[0] == zlib.crc32(data[pos:end])
        if ok:
            if skipping_from is not None:
                st.corrupt_skips += 1
                st.bytes_skipped += pos - skipping_from
                skipping_from = None
            st.records += 1
            yield pos, t, data[pos + _REC_HEAD.size:end]
            pos = end + _CRC.size
            continue
        if skipping_from is None:
            skipping_from = pos
        pos += 1
    if skipping_from is not None:
        st.torn_tail_bytes = n - skipping_from


def read(path: str | Path, stats: ReadStats | None = None) -> Iterator[tuple[float, bytes]]:
    """Yield (receive time, frame) for every intact record of the recording at ``path``."""
    data = Path(path).read_bytes()
    _check_header(data, path)
    for _, t, frame in scan(data, stats):
        yield t, frame


class Recorder:
    """Appends frames to a recording; thread-safe; every record reaches the OS at once."""

    def __init__(self, path: str | Path, fsync_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        self.records = 0
        self.bytes = 0
        self.errors = 0
        self._lock = threading.Lock()
        self._fsync_interval = fsync_interval_s
        self._last_fsync = time.monotonic()
        self._fd = self._open()

    def _open(self) -> int:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            size = os.fstat(fd).st_size
            if size == 0:
                os.write(fd, HEADER)
                return fd
            with open(self.path, "rb") as f:
                data = f.read()
            _check_header(data, self.path)
            end = len(HEADER)
            stats = ReadStats()
            for pos, _, frame in scan(data, stats):
                end = pos + REC_OVERHEAD + len(frame)
            if end < size:
                log.warning("%s: cutting %d torn bytes off the end before appending",
                            self.path, size - end)
                os.ftruncate(fd, end)
        except Exception:
            os.close(fd)
            raise
        return fd

    def write(self, frame: bytes, t: float | None = None) -> None:
        rec = encode_record(time.time() if t is None else t, frame)
        with self._lock:
            if self._fd < 0:
                return
            try:
                os.write(self._fd, rec)
            except OSError as exc:
                self.errors += 1
                if self.errors == 1:
                    log.error("%s: write failed: %s", self.path, exc)
                return
            self.records += 1
            self.bytes += len(rec)
            now = time.monotonic()
            if self._fsync_interval and now - self._last_fsync >= self._fsync_interval:
                self._last_fsync = now
                os.fsync(self._fd)

    def close(self) -> None:
        """Flush to disk and close; safe twice."""
        with self._lock:
            if self._fd < 0:
                return
            with contextlib.suppress(OSError):
                os.fsync(self._fd)
            os.close(self._fd)
            self._fd = -1
