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

The gateway records off its hot path: :meth:`Recorder.submit` only puts the message on a
bounded queue (a full queue drops it, counted) and the recorder's writer thread writes it and
fsyncs the file on a timer, idle or not.  What is recorded is the wire frame: the one a
message arrived in (``raw``), else the frame :func:`gateway.wire.encode` makes of it (an
``SmUpdate``/``Status``/``RawFrame`` from a MAVLink or Zenoh-JSON source).  Messages with no
Aurora wire form (vehicle state, position, battery from a MAVLink vehicle) cannot be
recorded: they are counted per kind (``not_recordable``) and named once in a warning.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import struct
import threading
import time
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gateway.counters import Counters
from gateway.model import kind
from gateway.wire import encode

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
class ReadStats(Counters):
    """What reading a recording met: records returned, a torn last record, corrupt stretches
    skipped (and their bytes)."""

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


def check_header(data: bytes, path: object) -> None:
    """RecordingError unless ``data`` starts with a recording header of this version
    (``path`` names the file in the message)."""
    if len(data) < len(HEADER) or data[: len(MAGIC)] != MAGIC:
        raise RecordingError(f"{path}: not an Aurora recording (bad magic)")
    (version,) = struct.unpack_from("<H", data, len(MAGIC))
    if version != VERSION:
        raise RecordingError(f"{path}: recording format version {version}; this gateway "
                             f"reads version {VERSION}")


def check_file(path: str | Path) -> None:
    """ValueError (a RecordingError for a bad header) unless ``path`` is a readable recording
    of this version: the replay source's ``path`` key checks it before anything starts."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"no recording at {path}")
    try:
        with p.open("rb") as f:
            head = f.read(len(HEADER))
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    check_header(head, path)


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
    check_header(data, path)
    for _, t, frame in scan(data, stats):
        yield t, frame


_WAKE = object()


class Recorder:
    """Appends frames to a recording; thread-safe; every record reaches the OS in one write.

    :meth:`write` writes at once, in the caller's thread; :meth:`submit` (the gateway's hot
    path) never waits: it queues the message for the writer thread, or drops and counts it
    when ``queue_depth`` messages are already waiting.  The writer thread fsyncs every
    ``fsync_interval_s`` while there is something unsynced (0 = only on close).
    """

    def __init__(self, path: str | Path, fsync_interval_s: float = 1.0,
                 queue_depth: int = 4096) -> None:
        self.path = Path(path)
        self.records = 0
        self.bytes = 0
        self.errors = 0
        self.syncs = 0
        self.dropped_queue_full = 0
        self.dropped_at_close = 0
        self.not_recordable: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._drop_lock = threading.Lock()
        self._fsync_interval = fsync_interval_s
        self._dirty = False
        self._closed = False
        self._drain_deadline = 0.0
        self._queue: queue.Queue[Any] = queue.Queue(max(1, queue_depth))
        self._closing = threading.Event()
        #: set once the writer thread has written what it will and closed the file
        self.finished = threading.Event()
        self._fd = self._open()
        self._thread = threading.Thread(target=self._writer, name=f"recorder {self.path.name}",
                                        daemon=True)
        self._thread.start()

    def _open(self) -> int:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            size = os.fstat(fd).st_size
            if size == 0:
                os.write(fd, HEADER)
                return fd
            with open(self.path, "rb") as f:
                data = f.read()
            check_header(data, self.path)
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

    # -- the hot path ----------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called (it takes nothing more)."""
        return self._closed

    def submit(self, msg: Any, t: float | None = None) -> bool:
        """Queue a message (or a frame as bytes) received at ``t`` (default now) for the
        writer thread; never blocks.  False if it was dropped: queue full, or closed."""
        if self._closed:
            return False
        try:
            self._queue.put_nowait((time.time() if t is None else t, msg))
        except queue.Full:
            with self._drop_lock:
                self.dropped_queue_full += 1
            return False
        return True

    # -- writing -----------------------------------------------------------------------------

    def write(self, frame: bytes, t: float | None = None) -> None:
        """Write one record now (one ``write`` call); ignored after :meth:`close`."""
        rec = encode_record(time.time() if t is None else t, frame)
        with self._lock:
            if self._fd < 0 or self._closed:
                return
            self._write_locked(rec)

    def _write_locked(self, rec: bytes) -> None:
        try:
            os.write(self._fd, rec)
        except OSError as exc:
            self.errors += 1
            if self.errors == 1:
                log.error("%s: write failed: %s", self.path, exc)
            return
        self.records += 1
        self.bytes += len(rec)
        self._dirty = True

    def _frame_of(self, msg: Any) -> bytes | None:
        if isinstance(msg, bytes | bytearray):
            return bytes(msg)
        raw = getattr(msg, "raw", b"")
        if raw:
            return bytes(raw)
        try:
            return encode(msg)
        except (TypeError, ValueError) as exc:
            name = kind(msg)
            self.not_recordable[name] += 1
            if self.not_recordable[name] == 1:
                log.warning("%s: %s messages are not recorded (%s); counting them",
                            self.path, name, exc)
            return None

    def _record(self, t: float, msg: Any) -> None:
        frame = self._frame_of(msg)
        if frame is None:
            return
        try:
            rec = encode_record(t, frame)
        except ValueError:
            self.not_recordable["too_long"] += 1
            return
        with self._lock:
            if self._fd >= 0:
                self._write_locked(rec)

    def _sync(self) -> None:
        with self._lock:
            if self._fd < 0 or not self._dirty:
                return
            self._dirty = False
            try:
                os.fsync(self._fd)
            except OSError as exc:  # a pipe or a device that cannot sync
                log.debug("%s: fsync failed: %s", self.path, exc)
                return
            self.syncs += 1

    def _writer(self) -> None:
        q = self._queue
        interval = self._fsync_interval
        next_sync = time.monotonic() + interval if interval > 0 else None
        try:
            while not self._closing.is_set():
                timeout = None if next_sync is None else max(0.0, next_sync - time.monotonic())
                try:
                    item = q.get(timeout=timeout)
                except queue.Empty:
                    item = None
                if item is not None and item is not _WAKE:
                    self._record(*item)
                if next_sync is not None and time.monotonic() >= next_sync:
                    self._sync()
                    next_sync = time.monotonic() + interval
            # Closing: write what is queued until the drain deadline; count the rest.
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                if item is _WAKE:
                    continue
                if time.monotonic() < self._drain_deadline:
                    self._record(*item)
                else:
                    self.dropped_at_close += 1
        except Exception:
            log.exception("%s: recorder failed", self.path)
        finally:
            self._sync()
            with self._lock:
                if self._fd >= 0:
                    os.close(self._fd)
                    self._fd = -1
            self.finished.set()

    def close(self, timeout: float = 1.0) -> None:
        """Write what is queued (for up to ``timeout``), fsync and close; safe twice.  A
        writer stuck in a write that never returns (a stalled disk) is left to finish on its
        own; the call still returns within about ``timeout``."""
        first = not self._closed
        if first:
            self._closed = True
            self._drain_deadline = time.monotonic() + 0.8 * timeout
            self._closing.set()
            with contextlib.suppress(queue.Full):
                self._queue.put_nowait(_WAKE)
        self.finished.wait(timeout)
        if not first:
            return
        if not self.finished.is_set():
            log.warning("%s: the recorder is still writing after %.1f s", self.path, timeout)
        elif self.dropped_at_close:
            log.warning("%s: %d queued messages not written at close", self.path,
                        self.dropped_at_close)

    def stats(self) -> dict[str, Any]:
        return {"records": self.records, "bytes": self.bytes, "write_errors": self.errors,
                "syncs": self.syncs, "dropped_queue_full": self.dropped_queue_full,
                "dropped_at_close": self.dropped_at_close,
                "not_recordable": dict(self.not_recordable)}
