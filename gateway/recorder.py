"""The gateway's recorders: what writes a recording (:mod:`gateway.recording`) as the
messages pass.

The gateway records off its hot path: :meth:`Recorder.submit` only puts the message on a
bounded queue (a full queue drops it, counted) and the recorder's writer thread writes it and
fsyncs the file on a timer, idle or not.  An Aurora message is recorded as its wire frame:
the one it arrived in (``raw``), else the frame :func:`gateway.wire.encode` makes of it (an
``SmUpdate``/``Status``/``RawFrame`` from a MAVLink or Zenoh-JSON source); every other kind
the gateway has (position, battery, vehicle state, RC channels, link statistics, link
events) as a message record of its fields (:func:`gateway.recording.message_payload`); each
with the message's ``vehicle`` and ``origin``.  A kind the format has no record for (one a
backend package defines) is counted per kind (``not_recordable``) and named once in a
warning.  :class:`DirectoryRecorder` (``record_dir``)
writes one file per vehicle per flight, created and closed by its writer thread.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import queue
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from gateway.model import kind
from gateway.recording import (
    DISK_FULL,
    FRAME,
    MAX_FRAME,
    MESSAGE_TYPES,
    WRITE_ERROR,
    RecordingError,
    RecordingFile,
    WriteFailure,
    encode_record,
    message_payload,
)
from gateway.wire import encode

log = logging.getLogger(__name__)

_WAKE = object()
_DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
Frame = bytes  # (the recorder's ``bytes`` counter hides the type in its class)


def _fields(f: RecordingFile, reason: str, lost: int) -> dict[str, Any]:
    """A write-failure line's figures, as keys of their own with ``--log-format json``."""
    return {"fields": {"recording": str(f.path), "reason": reason, "frames_not_written": lost}}


class Recorder:
    """Appends frames to a recording; thread-safe; every record reaches the OS in one write.

    :meth:`write` writes at once, in the caller's thread; :meth:`submit` (the gateway's hot
    path) never waits: it queues the message for the writer thread, or drops and counts it
    when ``queue_depth`` messages are already waiting.  The writer thread fsyncs every
    ``fsync_interval_s`` while there is something unsynced (0 = only on close).

    A write that fails (a full disk) drops its frame, counted by reason
    (``dropped_disk_full``, ``dropped_write_error``); it is logged once when a file's writes
    start failing and once when they have worked again for :data:`RESUME_AFTER_S` (with
    the count lost in between); while they fail, a write is tried again every
    :data:`WRITE_RETRY_S` (the frames in between are dropped without trying).  What a
    failed write left is cut off, so writing resumes on whole records; no file is left that
    holds nothing (:class:`gateway.recording.RecordingFile`).
    """

    #: seconds between attempts to write to a file whose writes fail
    WRITE_RETRY_S = 0.2
    #: seconds writes must work in a row before a file counts as writing again
    RESUME_AFTER_S = 2.0

    def __init__(self, path: str | Path, fsync_interval_s: float = 1.0,
                 queue_depth: int = 4096) -> None:
        self.path = Path(path)
        self.errors = 0
        self.syncs = 0
        self.dropped_queue_full = 0
        self.dropped_at_close = 0
        self.dropped_disk_full = 0
        self.dropped_write_error = 0
        self.not_recordable: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._drop_lock = threading.Lock()
        self._fsync_interval = fsync_interval_s
        self._closed = False
        self._drain_deadline = 0.0
        self._queue: queue.Queue[Any] = queue.Queue(max(1, queue_depth))
        self._closing = threading.Event()
        #: set once the writer thread has written what it will and closed the file(s)
        self.finished = threading.Event()
        #: every file written, in the order opened (the open ones included)
        self.files: list[RecordingFile] = []
        self._open_files()
        self._thread = threading.Thread(target=self._writer, name=f"recorder {self.path.name}",
                                        daemon=True)
        self._thread.start()

    def _open_files(self) -> None:
        self._file = RecordingFile(self.path)
        self.files.append(self._file)

    def _file_for(self, vehicle: str, t: float, new_flight: bool) -> RecordingFile | None:
        """The file a record of ``vehicle`` goes to (under the lock)."""
        return None if self._file.closed else self._file

    @property
    def paths(self) -> list[Path]:
        """Every file this recorder wrote (that holds records), in the order opened."""
        return [f.path for f in self.files if f.size]

    @property
    def dropped(self) -> dict[str, int]:
        """The messages not recorded, by reason (``disk_full`` …; the ones not recordable
        at all are in :attr:`not_recordable`)."""
        return {"queue_full": self.dropped_queue_full, "at_close": self.dropped_at_close,
                "disk_full": self.dropped_disk_full, "write_error": self.dropped_write_error}

    @property
    def records(self) -> int:
        return sum(f.records for f in self.files)

    @property
    def bytes(self) -> int:
        return sum(f.bytes for f in self.files)

    # -- the hot path ----------------------------------------------------------------------

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called (it takes nothing more)."""
        return self._closed

    def submit(self, msg: Any, t: float | None = None, new_flight: bool = False) -> bool:
        """Queue a message (or a frame as bytes) received at ``t`` (default now) for the
        writer thread; never blocks.  False if it was dropped: queue full, or closed.
        ``new_flight``: the message starts its vehicle's next flight (a
        :class:`DirectoryRecorder` starts that vehicle's next file with it)."""
        if self._closed:
            return False
        try:
            self._queue.put_nowait((time.time() if t is None else t, msg, new_flight))
        except queue.Full:
            with self._drop_lock:
                self.dropped_queue_full += 1
            return False
        return True

    # -- writing -----------------------------------------------------------------------------

    def write(self, frame: Frame, t: float | None = None, vehicle: str = "",
              source: str = "") -> None:
        """Write one record now (one ``write`` call); ignored after :meth:`close`.
        ValueError for a frame longer than a wire frame."""
        if len(frame) > MAX_FRAME:
            encode_record(0.0, frame)  # raises
        with self._lock:
            if self._closed:
                return
            self._write_locked(time.time() if t is None else t, frame, vehicle, source, False)

    def _write_locked(self, t: float, frame: Frame, vehicle: str, source: str,
                      new_flight: bool, rtype: int = FRAME) -> None:
        f = self._file_for(vehicle or source, t, new_flight)
        if f is None:
            return
        failure = f.failure
        if failure is not None and time.monotonic() < failure.retry_at:
            self._drop(failure.reason)
            failure.lost += 1
            return
        rec = f.encode(t, frame, vehicle, source, rtype)
        try:
            written = f.append(rec)
        except (OSError, RecordingError) as exc:
            self._write_failed(f, exc)
            return
        if failure is not None:
            self._written_while_failing(f, failure)
        f.records += 1
        f.bytes += written

    def _drop(self, reason: str) -> None:
        if reason == DISK_FULL:
            self.dropped_disk_full += 1
        else:
            self.dropped_write_error += 1

    def _write_failed(self, f: RecordingFile, exc: Exception) -> None:
        """A write to ``f`` failed: the frame is dropped, counted by reason; the first
        failure in a row is logged, and writes are tried again :data:`WRITE_RETRY_S` later
        (the frames meanwhile are dropped without trying)."""
        self.errors += 1
        reason = DISK_FULL if getattr(exc, "errno", None) in _DISK_FULL_ERRNOS else WRITE_ERROR
        self._drop(reason)
        failure = f.failure
        if failure is None:
            failure = f.failure = WriteFailure(reason)
            log.error("%s: cannot write: %s; counting the frames not written "
                      "(dropped_%s), trying again every %.1f s", f.path,
                      getattr(exc, "strerror", None) or exc, reason, self.WRITE_RETRY_S,
                      extra=_fields(f, reason, 1))
        failure.reason = reason
        failure.ok_since = None
        failure.lost += 1
        failure.retry_at = time.monotonic() + self.WRITE_RETRY_S

    def _written_while_failing(self, f: RecordingFile, failure: WriteFailure,
                               at_close: bool = False) -> None:
        """A write worked after failures: once writes have worked for
        :data:`RESUME_AFTER_S` in a row, say so (with the frames lost) and leave the failing
        state; a disk with a few bytes free now and then (a small record fits, the next
        does not) logs no pair of lines per frame.  ``at_close``: the file closes while
        writing again; say so now."""
        now = time.monotonic()
        if failure.ok_since is None:
            failure.ok_since = now
        elif at_close or now - failure.ok_since >= self.RESUME_AFTER_S:
            f.failure = None
            log.warning("%s: writing again; %d frames not written in the %.1f s before (%s)",
                        f.path, failure.lost, failure.ok_since - failure.since,
                        failure.reason.replace("_", " "),
                        extra=_fields(f, failure.reason, failure.lost))

    def _closing_file(self, f: RecordingFile) -> None:
        """Before ``f`` is closed: say what a write failure still going on cost."""
        failure = f.failure
        if failure is not None and failure.ok_since is not None:  # it was writing again
            self._written_while_failing(f, failure, at_close=True)
        elif failure is not None:
            f.failure = None
            log.warning("%s: closed; %d frames not written since writes started failing "
                        "%.1f s before (%s)%s", f.path, failure.lost,
                        time.monotonic() - failure.since, failure.reason.replace("_", " "),
                        "" if f.size else "; nothing was written: no file",
                        extra=_fields(f, failure.reason, failure.lost))

    def _payload_of(self, msg: Any) -> tuple[int, Frame] | None:
        """(record type, frame or message payload) of ``msg``; None: not recordable
        (counted)."""
        if isinstance(msg, bytes | bytearray):
            return FRAME, bytes(msg)
        raw = getattr(msg, "raw", b"")
        if raw:
            return FRAME, bytes(raw)
        try:
            if type(msg) in MESSAGE_TYPES:
                return message_payload(msg)
            return FRAME, encode(msg)
        except (TypeError, ValueError) as exc:
            name = "too_long" if isinstance(exc, ValueError) and type(msg) in MESSAGE_TYPES \
                else kind(msg)
            self.not_recordable[name] += 1
            if self.not_recordable[name] == 1:
                log.warning("%s: %s messages are not recorded (%s); counting them",
                            self.path, name, exc)
            return None

    def _record(self, t: float, msg: Any, new_flight: bool) -> None:
        got = self._payload_of(msg)
        if got is None:
            return
        rtype, payload = got
        if rtype == FRAME and len(payload) > MAX_FRAME:
            self.not_recordable["too_long"] += 1
            return
        with self._lock:
            self._write_locked(t, payload, getattr(msg, "vehicle", ""),
                               getattr(msg, "origin", ""), new_flight, rtype)

    def _sync_file(self, f: RecordingFile) -> None:
        if f.fd < 0 or not f.dirty:
            return
        f.dirty = False
        try:
            os.fsync(f.fd)
        except OSError as exc:  # a pipe or a device that cannot sync
            log.debug("%s: fsync failed: %s", f.path, exc)
            return
        self.syncs += 1

    def _sync(self) -> None:
        with self._lock:
            for f in self.files:
                self._sync_file(f)

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
                for f in self.files:
                    self._closing_file(f)
                    f.close()
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
                "syncs": self.syncs,
                **{f"dropped_{k}": v for k, v in self.dropped.items()},
                "not_recordable": dict(self.not_recordable)}


class DirectoryRecorder(Recorder):
    """``record_dir``: one recording per vehicle per flight in ``directory``, named
    ``<UTC time of its first record>-<vehicle>.aur``
    (:func:`gateway.flight_summary.new_recording`).  The writer thread opens a vehicle's
    file at its first recordable message and its next one at a message submitted with
    ``new_flight`` (closing the previous one: a vehicle's new flight rotates only its own
    file).  The rotation rides on its message: if a full queue drops that message, the
    vehicle's next flight goes on in its old file.  At most ``max_vehicles`` files are open
    at once, and at most ``max_files`` are made in a run (a stream that flies and lands
    again and again cannot make files without end: the vehicle's next flights go on in its
    last file, warned about once); the messages of vehicles beyond these are dropped,
    counted (``dropped_vehicle_limit``) and warned about once.  A file that cannot be created (a
    full disk) is tried again :data:`OPEN_RETRY_S` later, not at every message; meanwhile
    the vehicle's messages go on into its old file, or are dropped and counted
    (``dropped_disk_full`` when the disk is full, else ``dropped_open_failed``); the error
    is logged once per vehicle.  A directory that cannot be made at start because the disk
    is full is made with the first file."""

    #: seconds before a vehicle's file that could not be created is tried again
    OPEN_RETRY_S = 5.0

    def __init__(self, directory: str | Path, fsync_interval_s: float = 1.0,
                 queue_depth: int = 4096, max_vehicles: int = 64,
                 max_files: int = 1000) -> None:
        self.max_vehicles = max_vehicles
        self.max_files = max_files
        self._files_full_warned = False
        self.dropped_vehicle_limit = 0
        self.dropped_open_failed = 0
        self.open_errors = 0
        self._open: dict[str, RecordingFile] = {}
        self._retry_at: dict[str, float] = {}  # vehicle -> when to try its file again
        self._full: set[str] = set()  # vehicles whose file could not be made: disk full
        self._failed: set[str] = set()  # vehicles whose file failed once (logged)
        super().__init__(directory, fsync_interval_s, queue_depth)

    def _open_files(self) -> None:
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:  # (the caller reports any but a full disk)
            if exc.errno not in _DISK_FULL_ERRNOS:
                raise
            # a full disk is no configuration error: the first recording makes it
            log.error("%s: cannot create the directory yet (%s); trying again with the "
                      "first recording", self.path, exc.strerror)
            return
        if not os.access(self.path, os.W_OK | os.X_OK):
            raise PermissionError(13, "Permission denied", str(self.path))

    def _file_for(self, vehicle: str, t: float, new_flight: bool) -> RecordingFile | None:
        name = vehicle or "gateway"
        f = self._open.get(name)
        if f is not None and not new_flight and name not in self._retry_at:
            return f  # (the hot case: one dict lookup, one miss)
        if name in self._retry_at:
            if time.monotonic() < self._retry_at[name]:
                if f is None:
                    self._drop_unopened(name)
                return f
            del self._retry_at[name]
        if len(self.files) >= self.max_files:
            if not self._files_full_warned:
                self._files_full_warned = True
                log.warning("%s: %d files made in this run; no more (new flights go on in "
                            "their vehicle's last file)", self.path, len(self.files))
            if f is None:
                self.dropped_vehicle_limit += 1
            return f
        if f is None and len(self._open) >= self.max_vehicles:
            self.dropped_vehicle_limit += 1
            if self.dropped_vehicle_limit == 1:
                log.warning("%s: recording %d vehicles already; not recording %s (nor "
                            "any further vehicle), counting", self.path, len(self._open),
                            name)
            return None
        return self._next_file(name, t, f)

    def _next_file(self, name: str, t: float, old: RecordingFile | None) -> RecordingFile | None:
        """Open ``name``'s next file (closing ``old``); on failure keep ``old`` and try
        again :data:`OPEN_RETRY_S` later."""
        try:
            new = self._new_file(t, name)
        except (OSError, RecordingError) as exc:
            self.open_errors += 1
            now = time.monotonic()
            if len(self._retry_at) >= self.max_vehicles:  # bounded: forget the expired
                self._retry_at = {k: v for k, v in self._retry_at.items() if v > now}
            if len(self._retry_at) < self.max_vehicles:
                self._retry_at[name] = now + self.OPEN_RETRY_S
            if name not in self._failed and len(self._failed) < self.max_vehicles:
                self._failed.add(name)
                log.error("%s: cannot open %s's recording (%s)%s; trying again every "
                          "%.0f s", self.path, name, exc,
                          f"; recording on into {old.path}" if old is not None else "",
                          self.OPEN_RETRY_S)
            if getattr(exc, "errno", None) in _DISK_FULL_ERRNOS:
                if len(self._full) < self.max_vehicles:
                    self._full.add(name)
            else:
                self._full.discard(name)
            if old is None:
                self._drop_unopened(name)
            return old
        if old is not None:
            self._sync_file(old)
            if old.failure is not None:  # writes failing go on failing: no new log lines
                new.failure, old.failure = old.failure, None
                new.failure.retry_at = 0.0  # (the new file is tried at once)
            old.close()
            log.log(logging.DEBUG if new.failure else logging.INFO,
                    "new flight of %s: recording into %s", name, new.path)
        self._open[name] = new
        self.files.append(new)
        return new

    def _new_file(self, t: float, name: str) -> RecordingFile:
        """A new, empty file for ``name`` from ``t`` on, named by
        :func:`~gateway.flight_summary.new_recording` (a subclass writing another format
        makes its own file here)."""
        from gateway.flight_summary import new_recording

        return RecordingFile(new_recording(self.path, t, name), new=True)

    def _drop_unopened(self, name: str) -> None:
        """A message of ``name``, whose file could not be made: disk full, or else."""
        if name in self._full:
            self.dropped_disk_full += 1
        else:
            self.dropped_open_failed += 1

    @property
    def dropped(self) -> dict[str, int]:
        return {**super().dropped, "vehicle_limit": self.dropped_vehicle_limit,
                "open_failed": self.dropped_open_failed}

    def stats(self) -> dict[str, Any]:
        return {**super().stats(), "dropped_vehicle_limit": self.dropped_vehicle_limit,
                "dropped_open_failed": self.dropped_open_failed,
                "open_errors": self.open_errors}
