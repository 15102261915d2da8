"""MAVLink telemetry logs (``.tlog``), as MAVProxy, mavlink-router and QGroundControl keep them.

A ``.tlog`` is a sequence of records, each an 8-byte big-endian UNIX time in microseconds
followed by one MAVLink frame exactly as it went on the wire (v1 or v2, signature included);
no header.  pymavlink's ``mavlogdump.py``, MAVExplorer and QGroundControl's Replay Flight Data
read it.

:class:`TlogWriter` is ``run --tlog DIR``'s writer: the gateway's recorder
(:class:`gateway.recorder.DirectoryRecorder`) writing this format instead — the router's
:attr:`~backends.mavlink.router.Router.tap` hands it each frame that crosses the gateway
(one bounded-queue put, never waiting on the disk), its writer thread writes and fsyncs on a
timer, a full disk drops frames (counted ``dropped_disk_full``) and leaves no empty file.
One file per run, ``<UTC time of its first frame>-<backend>.tlog``, and a new one each time a
vehicle starts a new flight (:meth:`TlogWriter.new_flight`).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path
from typing import Any

from gateway.recorder import DirectoryRecorder
from gateway.recording import HEADER, RecordingError, RecordingFile

#: The file name suffix.
SUFFIX = ".tlog"
#: Each record's time: UNIX microseconds, big-endian.
STAMP = struct.Struct(">Q")


def stamp(t: float) -> bytes:
    """The 8-byte time of a frame received (or sent) at UNIX time ``t``."""
    return STAMP.pack(max(0, round(t * 1e6)))


class TlogFile(RecordingFile):
    """One ``.tlog`` open for appending: the recording file's write, failure and clean-up
    rules (whole records only, no empty file left), without its header and name table."""

    def _open(self) -> int:
        flags = os.O_RDWR | os.O_APPEND
        try:
            fd = os.open(self.path, flags | os.O_CREAT | os.O_EXCL, 0o644)
            self.created = True
            return fd
        except FileExistsError:
            fd = os.open(self.path, flags)
        if os.fstat(fd).st_size:  # (ours are always new: another file took its place)
            os.close(fd)
            raise RecordingError(f"{self.path}: not appending to an existing telemetry log")
        return fd

    def encode(self, t: float, frame: bytes, vehicle: str = "", source: str = "",
               rtype: int = 0) -> bytes:
        return stamp(t) + frame  # (a frame is all a telemetry log holds)

    def append(self, data: bytes) -> int:
        first = self.size == 0
        n = super().append(data)
        return n + len(HEADER) if first else n  # (no header here: every byte is a record's)


class TlogWriter(DirectoryRecorder):
    """Writes the frames it is given (:meth:`frame`, from any thread, never blocking) into
    ``directory`` as telemetry logs; see the module docstring.  Times never go backwards in
    a file (a wall clock stepped back keeps the last time)."""

    def __init__(self, directory: str | Path, name: str = "mavlink",
                 fsync_interval_s: float = 1.0, queue_depth: int = 4096) -> None:
        self.name = name
        self._rotate = False
        self._last_t = 0.0
        super().__init__(directory, fsync_interval_s, queue_depth, max_vehicles=1)

    def frame(self, raw: bytes) -> None:
        """One frame that crossed the gateway now (the router's tap; the hot path)."""
        self.submit(raw)

    def new_flight(self) -> None:
        """A vehicle starts a new flight: the frames from now on go into a new file."""
        self.submit(None)

    def _new_file(self, t: float, name: str) -> RecordingFile:
        from gateway.flight_summary import new_recording

        return TlogFile(new_recording(self.path, t, name, SUFFIX), new=True)

    def _record(self, t: float, msg: Any, new_flight: bool) -> None:
        if msg is None:  # (a new flight: rides on the next frame)
            self._rotate = bool(self.files)
            return
        t = max(t, self._last_t)
        self._last_t = t
        rotate, self._rotate = self._rotate, False
        with self._lock:
            self._write_locked(t, msg, self.name, "", new_flight or rotate)


def frame_length(data: bytes, i: int) -> int:
    """The length of the MAVLink frame starting at ``data[i]`` (from its header), 0 if no
    frame starts there."""
    if i + 3 > len(data):
        return 0
    magic, n = data[i], data[i + 1]
    if magic == 0xFD:
        return n + 12 + (13 if data[i + 2] & 1 else 0)
    if magic == 0xFE:
        return n + 8
    return 0


def read(path: str | Path) -> list[tuple[float, bytes]]:
    """A telemetry log's records as (UNIX time, frame), up to the first damaged one (tests,
    tools)."""
    data = Path(path).read_bytes()
    out: list[tuple[float, bytes]] = []
    i = 0
    while i + STAMP.size < len(data):
        (us,) = STAMP.unpack_from(data, i)
        i += STAMP.size
        n = frame_length(data, i)
        if not n or i + n > len(data):
            break
        out.append((us / 1e6, data[i:i + n]))
        i += n
    return out
