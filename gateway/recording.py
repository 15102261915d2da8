"""The recording format: every received message, with its receive time, its vehicle and its
source; Aurora wire frames untouched.

File layout, version 2 (all integers little-endian)::

    header  8 bytes   89 41 55 52 0D 0A 1A 0A   ("\\x89AUR\\r\\n\\x1a\\n": binary, and mangled
                                                 visibly by any text-mode transfer)
            2 bytes   format version (2)
            2 bytes   reserved (0)
    record  1 byte    record type (below)
            8 bytes   time, f64 seconds since the Unix epoch
            2 bytes   N, body length (at most 4096)
            N bytes   body
            4 bytes   CRC-32 (ISO-HDLC, zlib's) over the 11 + N bytes before it

    type 1, frame   2 bytes   vehicle: index into the file's name table (FFFF: none)
                    2 bytes   source: index into the name table (FFFF: none)
                    M bytes   the wire frame exactly as received (A5 5A … CRC), M ≤ 261;
                              the time is its receive time
    type 2, name    2 bytes   index (0 … FFFE)
                    K bytes   the name, UTF-8, 1 ≤ K ≤ 255; binds the index to it for the
                              rest of the file; the time is when it was written
    types 3 … 8     2 bytes   vehicle, as in a frame record
    (a message)     2 bytes   source, as in a frame record
                    J bytes   the message's own fields (:func:`gateway.model.own_fields`)
                              as one JSON object, UTF-8, named as in :mod:`gateway.model`;
                              the time is its receive time.  By type:
                              3 position (``Position``: lat_deg, lon_deg, alt_amsl_m,
                              relative_alt_m, ground_speed_mps, course_deg, satellites,
                              fix_type), 4 battery (``Battery``), 5 vehicle state
                              (``VehicleState``), 6 RC channels (``RcChannels``:
                              channels_us a list), 7 link statistics (``LinkStats``),
                              8 link event (``LinkEvent``)

Every record type that carries a message starts its body with those two indexes
(:func:`encode_message`).  SmUpdate, Status and RawFrame are recorded as the wire frame they
arrived in (type 1: byte-exact, so a replay reproduces the frames that arrived); every other
kind as a message record.  In its JSON, ``null`` is a field not known (``None``), NaN and
the infinities are the tokens ``NaN``, ``Infinity``, ``-Infinity`` (Python's :mod:`json`),
floats are written in their shortest round-trip form: a message reads back equal to the one
recorded.  A reader takes the fields it knows (a later version may add some: the others
are ignored; one missing takes the field's default) and skips, counted (``bad_messages``),
a message record whose body is not such an object or whose fields have the wrong types.

A name (a vehicle's or a source's: one table for both) is bound before the first frame that
uses it, in the same ``write``; an index is bound to one name per file (appending continues
the file's table), and the writer binds its names again every :data:`NAME_REPEAT` frames,
so a damaged name record costs at most that many frames their names (read as "").  A
reader skips records of a type it does not know (counted): new kinds of record extend the
format without a new version.  Per frame the overhead is 19 bytes.

Version 1 (still read; no longer written; appending to one is refused) had no record type
and no names: ``time f64, length u16, frame, CRC-32 over the 10 + length bytes``.  Its
frames have no vehicle: ``decode``/``export``/``plot`` name it after the file
(:func:`file_vehicle`), a replay after the replay source.

Each record (with the names it needs) is written with one unbuffered ``write`` call, so a
``kill -9`` leaves at most the last record torn.  The reader checks every record's CRC and
skips what fails: a torn tail ends the replay cleanly, and corruption mid-file is passed by
rescanning one byte at a time (the same resync rule as the wire decoder).  Opening an
existing recording for append cuts a torn tail off first, so new records never follow
garbage.  A file exists from its first record on (the header goes out with it) and a write
that fails part-way (a full disk) is cut off again (:class:`RecordingFile`): no recording is
empty, a bare header, or torn before its end by the writer itself.

The writers, :class:`gateway.recorder.Recorder` (one file) and
:class:`gateway.recorder.DirectoryRecorder` (``record_dir``: a file per vehicle per flight),
append through :class:`RecordingFile`.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import struct
import time
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple, get_type_hints

from gateway.counters import Counters
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    RcChannels,
    VehicleState,
    own_fields,
)
from gateway.vehicles import derive_name

log = logging.getLogger(__name__)

MAGIC = b"\x89AUR\r\n\x1a\n"
VERSION = 2
#: the versions this gateway reads
READ_VERSIONS = (1, 2)
HEADER = MAGIC + struct.pack("<HH", VERSION, 0)
HEADER_V1 = MAGIC + struct.pack("<HH", 1, 0)
MAX_FRAME = 261
#: the longest body a record may have (a longer length field is corruption)
MAX_BODY = 4096
MAX_NAME = 255
#: a frame record's vehicle or source index when it has none
NO_NAME = 0xFFFF
#: the writer binds its names again every this many frames
NAME_REPEAT = 1000
#: record types
FRAME, NAME = 1, 2
POSITION, BATTERY, VEHICLE_STATE, RC_CHANNELS, LINK_STATS, LINK_EVENT = range(3, 9)
#: the message record type of each message kind recorded as its fields (not as a frame)
MESSAGE_TYPES: dict[type, int] = {
    Position: POSITION, Battery: BATTERY, VehicleState: VEHICLE_STATE,
    RcChannels: RC_CHANNELS, LinkStats: LINK_STATS, LinkEvent: LINK_EVENT,
}
_MESSAGE_CLASSES = {rtype: cls for cls, rtype in MESSAGE_TYPES.items()}
#: the most RC channels a record holds (CRSF has 16, MAVLink 18)
MAX_CHANNELS = 32

_REC_HEAD = struct.Struct("<BdH")
_FRAME_HEAD = struct.Struct("<HH")
_INDEX = struct.Struct("<H")
_V1_HEAD = struct.Struct("<dH")
_CRC = struct.Struct("<I")
#: bytes a frame record adds to its frame
REC_OVERHEAD = _REC_HEAD.size + _FRAME_HEAD.size + _CRC.size
_V1_OVERHEAD = _V1_HEAD.size + _CRC.size
_FILE_STAMP = re.compile(r"\d{4}-\d\d-\d\dT\d\d-\d\d-\d\d-(.+)")


class RecordingError(ValueError):
    """The file is not a recording of a version this gateway reads."""


class Record(NamedTuple):
    """One frame of a recording: its receive time, the frame, its vehicle and its source
    ("" when the record names none: every version 1 record)."""

    t: float
    frame: bytes
    vehicle: str = ""
    source: str = ""


class MessageRecord(NamedTuple):
    """One message record (a kind with no wire frame): its receive time, the message (its
    ``vehicle`` and ``origin`` those of the record), its vehicle and its source.  The same
    shape as :class:`Record`, the message in place of the frame."""

    t: float
    message: Any
    vehicle: str = ""
    source: str = ""


@dataclass
class ReadStats(Counters):
    """What reading a recording met: frame records returned, a torn last record, corrupt
    stretches skipped (and their bytes), records of an unknown type skipped, frames (and
    messages) whose name record was lost (read with no name), message records read and
    the ones skipped as malformed."""

    records: int = 0
    torn_tail_bytes: int = 0
    corrupt_skips: int = 0
    bytes_skipped: int = 0
    unknown_records: int = 0
    unnamed: int = 0
    #: message records read (returned only when asked for: :func:`records`)
    messages: int = 0
    #: message records of a known type whose body did not make a message (skipped)
    bad_messages: int = 0


def _record(rtype: int, t: float, body: bytes) -> bytes:
    head = _REC_HEAD.pack(rtype, t, len(body)) + body
    return head + _CRC.pack(zlib.crc32(head))


def encode_message(rtype: int, t: float, payload: bytes, vehicle: int = NO_NAME,
                   source: int = NO_NAME) -> bytes:
    """A record of type ``rtype`` carrying a message: the vehicle's and the source's
    name-table indexes, then ``payload``."""
    if len(payload) + _FRAME_HEAD.size > MAX_BODY:
        raise ValueError(f"a {len(payload)}-byte payload is longer than a record body holds")
    return _record(rtype, t, _FRAME_HEAD.pack(vehicle, source) + payload)


def encode_record(t: float, frame: bytes, vehicle: int = NO_NAME, source: int = NO_NAME) -> bytes:
    """One frame record's bytes (``vehicle``/``source``: name-table indexes).  Frames longer
    than a wire frame can be (:data:`MAX_FRAME`) are refused: the reader would never return
    them."""
    if len(frame) > MAX_FRAME:
        raise ValueError(f"a {len(frame)}-byte frame is longer than a wire frame "
                         f"({MAX_FRAME} bytes)")
    return encode_message(FRAME, t, frame, vehicle, source)


def _json_default(v: Any) -> Any:
    if isinstance(v, tuple):
        return list(v)
    raise TypeError(f"{type(v).__name__} is not recordable")


def message_payload(msg: Any) -> tuple[int, bytes]:
    """(record type, payload) of a message recorded as its fields (a kind in
    :data:`MESSAGE_TYPES`); TypeError for any other kind, ValueError when it is too long
    for a record."""
    rtype = MESSAGE_TYPES.get(type(msg))
    if rtype is None:
        raise TypeError(f"{type(msg).__name__} has no message record type")
    payload = json.dumps(own_fields(msg), separators=(",", ":"), ensure_ascii=False,
                         default=_json_default).encode("utf-8")
    if len(payload) + _FRAME_HEAD.size > MAX_BODY:
        raise ValueError(f"a {len(payload)}-byte message is longer than a record body holds")
    return rtype, payload


def _field_checks(cls: type) -> dict[str, tuple[Any, Any]]:
    """Per field of a message class: (the types a recorded value may have, its default or
    :data:`_REQUIRED`)."""
    hints = get_type_hints(cls)
    defaults = getattr(cls, "_field_defaults", {})
    return {name: (str(hints[name]), defaults.get(name, _REQUIRED))
            for name in getattr(cls, "_fields", ()) if name not in _PROVENANCE}


_REQUIRED = object()
_PROVENANCE = ("raw", "origin", "via", "vehicle")


def _value_ok(spec: str, v: Any) -> Any:
    """``v`` (from JSON) checked against a field's type hint ``spec``; returns the value
    to use (an int where a float is meant becomes a float); raises ValueError."""
    if v is None:
        if "None" in spec:
            return None
        raise ValueError("null")
    if isinstance(v, bool):
        if "bool" in spec:
            return v
        raise ValueError("bool")
    if spec.startswith("tuple"):
        if not isinstance(v, list) or len(v) > MAX_CHANNELS or \
                not all(c is None or (type(c) is int) for c in v):
            raise ValueError("channels")
        return tuple(v)
    if isinstance(v, int) and ("int" in spec or "float" in spec):
        return float(v) if "int" not in spec else v
    if isinstance(v, float) and "float" in spec:
        return v
    if isinstance(v, str) and "str" in spec:
        return v
    raise ValueError(type(v).__name__)


_CHECKS: dict[int, dict[str, tuple[Any, Any]]] = {}


def decode_message(rtype: int, payload: bytes, vehicle: str = "", source: str = "") -> Any:
    """The message of a message record (type ``rtype``, its JSON ``payload``), with
    ``vehicle`` and ``source`` (as ``origin``); ValueError when the payload does not make
    one (KeyError: not a message record type)."""
    cls = _MESSAGE_CLASSES[rtype]
    checks = _CHECKS.get(rtype)
    if checks is None:
        checks = _CHECKS[rtype] = _field_checks(cls)
    try:
        body = json.loads(payload)
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"not JSON: {exc}") from None
    if not isinstance(body, dict):
        raise ValueError("not a JSON object")
    values: dict[str, Any] = {}
    for name, (spec, default) in checks.items():
        if name in body:
            values[name] = _value_ok(spec, body[name])
        elif default is _REQUIRED:
            raise ValueError(f"no {name}")
    return cls(**values, origin=source, vehicle=vehicle)


def encode_name(t: float, index: int, name: str) -> bytes:
    """One name record's bytes: binds ``index`` to ``name`` (at most :data:`MAX_NAME` bytes of
    UTF-8: longer names are cut at a character boundary)."""
    raw = name.encode("utf-8")[:MAX_NAME].decode("utf-8", "ignore").encode("utf-8")
    if not raw or not 0 <= index < NO_NAME:
        raise ValueError(f"cannot bind index {index} to {name!r}")
    return _record(NAME, t, _INDEX.pack(index) + raw)


def encode_record_v1(t: float, frame: bytes) -> bytes:
    """One version 1 record (for tests and tools that make old files)."""
    body = _V1_HEAD.pack(t, len(frame)) + frame
    return body + _CRC.pack(zlib.crc32(body))


def check_header(data: bytes, path: object) -> int:
    """The version of the recording header ``data`` starts with; RecordingError unless it is
    one this gateway reads (``path`` names the file in the message)."""
    if len(data) < len(HEADER) or data[: len(MAGIC)] != MAGIC:
        raise RecordingError(f"{path}: not an Aurora recording (bad magic)")
    (version,) = struct.unpack_from("<H", data, len(MAGIC))
    if version not in READ_VERSIONS:
        raise RecordingError(f"{path}: recording format version {version}; this gateway "
                             f"reads versions {', '.join(map(str, READ_VERSIONS))}")
    return int(version)


def check_file(path: str | Path) -> None:
    """ValueError (a RecordingError for a bad header) unless ``path`` is a readable recording
    of a version this gateway reads: the replay source's ``path`` key checks it before
    anything starts."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"no recording at {path}")
    try:
        with p.open("rb") as f:
            head = f.read(len(HEADER))
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    check_header(head, path)


def file_vehicle(path: str | Path) -> str:
    """The vehicle a version 1 recording is about, from its file name: a ``record_dir`` name
    loses its UTC stamp (``2026-11-23T14-02-11-rocket1.aur`` → ``rocket1``), then
    :func:`gateway.vehicles.derive_name` (``flight.aur`` → ``flight``)."""
    stem = Path(path).name.partition(".")[0] or "recording"
    m = _FILE_STAMP.match(stem)
    return derive_name(m.group(1) if m else stem, fallback="recording")


def _version_of(data: bytes) -> int:
    if data[: len(MAGIC)] == MAGIC and len(data) >= len(HEADER):
        (version,) = struct.unpack_from("<H", data, len(MAGIC))
        if version in READ_VERSIONS:
            return int(version)
    return VERSION


def _intact(data: bytes, stats: ReadStats, start: int,
            version: int) -> Iterator[tuple[int, int, int, float, int, int]]:
    """(offset, end, type, time, body start, body end) of every intact record from ``start``;
    version 1 records are type :data:`FRAME` with the frame as their body.  Bytes that are not
    an intact record are skipped one at a time until one is found; the ones after the last
    intact record are the torn tail."""
    n = len(data)
    pos = start
    skipping_from: int | None = None
    v1 = version == 1
    head = _V1_HEAD if v1 else _REC_HEAD
    overhead = _V1_OVERHEAD if v1 else _REC_HEAD.size + _CRC.size
    limit = MAX_FRAME if v1 else MAX_BODY
    crc_at = _CRC.unpack_from
    view = memoryview(data)  # the CRC without copying each record
    while pos < n:
        found = None
        if pos + overhead <= n:
            if v1:
                t, length = head.unpack_from(data, pos)
                rtype = FRAME
            else:
                rtype, t, length = head.unpack_from(data, pos)
            end = pos + head.size + length
            if length <= limit and end + _CRC.size <= n and \
                    crc_at(data, end)[0] == zlib.crc32(view[pos:end]):
                found = (rtype, t, pos + head.size, end)
        if found is not None:
            if skipping_from is not None:
                stats.corrupt_skips += 1
                stats.bytes_skipped += pos - skipping_from
                skipping_from = None
            rtype, t, body, end = found
            yield pos, end + _CRC.size, rtype, t, body, end
            pos = end + _CRC.size
            continue
        if skipping_from is None:
            skipping_from = pos
        pos += 1
    if skipping_from is not None:
        stats.torn_tail_bytes = n - skipping_from


def _name_of(data: bytes, body: int, body_end: int) -> tuple[int, str]:
    (index,) = _INDEX.unpack_from(data, body)
    return index, data[body + _INDEX.size:body_end].decode("utf-8", "replace")


def _records(data: bytes, stats: ReadStats, start: int, names: dict[int, str] | None = None,
             messages: bool = False) -> Iterator[tuple[int, int, Record | MessageRecord]]:
    """(offset, end, record) of every frame record (and, ``messages``, every message
    record), names resolved through the file's table (``names``, filled as name records
    pass)."""
    version = _version_of(data)
    table: dict[int, str] = {} if names is None else names
    lookup = {**table, NO_NAME: ""}  # the table, and "no name" for NO_NAME
    frame_head = _FRAME_HEAD.size
    unpack_head = _FRAME_HEAD.unpack_from
    for pos, end, rtype, t, body, body_end in _intact(data, stats, start, version):
        if version == 1:
            stats.records += 1
            yield pos, end, Record(t, data[body:body_end])
        elif rtype == FRAME and frame_head <= body_end - body <= frame_head + MAX_FRAME:
            vi, si = unpack_head(data, body)
            vehicle, source = lookup.get(vi), lookup.get(si)
            if vehicle is None or source is None:  # its name record was lost
                stats.unnamed += 1
            stats.records += 1
            yield pos, end, Record(t, data[body + frame_head:body_end], vehicle or "",
                                   source or "")
        elif rtype == NAME and body_end - body > _INDEX.size:
            index, name = _name_of(data, body, body_end)
            if index != NO_NAME:
                table[index] = lookup[index] = name
        elif rtype in _MESSAGE_CLASSES and body_end - body > frame_head:
            stats.messages += 1
            if not messages:
                continue
            vi, si = unpack_head(data, body)
            vehicle, source = lookup.get(vi), lookup.get(si)
            if vehicle is None or source is None:
                stats.unnamed += 1
            try:
                msg = decode_message(rtype, data[body + frame_head:body_end], vehicle or "",
                                     source or "")
            except ValueError:
                stats.bad_messages += 1
                continue
            yield pos, end, MessageRecord(t, msg, vehicle or "", source or "")
        else:
            stats.unknown_records += 1


def records(data: bytes, stats: ReadStats | None = None, start: int = len(HEADER),
            messages: bool = False) -> Iterator[Record | MessageRecord]:
    """Every intact frame record in ``data`` (a whole recording, header first) from
    ``start``, with its vehicle and source; with ``messages``, every message record too
    (a :class:`MessageRecord`), in file order.  (Without, message records are counted in
    ``stats.messages`` and passed over: callers that handle frames only see frames.)"""
    st = stats if stats is not None else ReadStats()
    for _, _, rec in _records(data, st, start, messages=messages):
        yield rec


def scan(data: bytes, stats: ReadStats | None = None,
         start: int = len(HEADER)) -> Iterator[tuple[int, float, bytes]]:
    """Yield (offset, time, frame) for every intact frame record in ``data`` (a whole
    recording, header first; the version is the header's) from ``start``."""
    st = stats if stats is not None else ReadStats()
    for pos, _, rec in _records(data, st, start):
        assert isinstance(rec, Record)
        yield pos, rec.t, rec.frame


def read_records(path: str | Path, stats: ReadStats | None = None,
                 messages: bool = False) -> Iterator[Record | MessageRecord]:
    """Every intact frame record of the recording at ``path`` (and, ``messages``, every
    message record: :func:`records`)."""
    data = Path(path).read_bytes()
    check_header(data, path)
    yield from records(data, stats, messages=messages)


def read(path: str | Path, stats: ReadStats | None = None) -> Iterator[tuple[float, bytes]]:
    """Yield (receive time, frame) for every intact record of the recording at ``path``."""
    for rec in read_records(path, stats):
        assert isinstance(rec, Record)
        yield rec.t, rec.frame


AnyRecord = Record | MessageRecord


def vehicles_in(recs: Iterable[AnyRecord]) -> list[str]:
    """The vehicles of ``recs`` in the order they first appear."""
    return list(dict.fromkeys(r.vehicle for r in recs))


def _named(r: AnyRecord, vehicle: str) -> AnyRecord:
    if isinstance(r, MessageRecord):
        return r._replace(vehicle=vehicle, message=r.message._replace(vehicle=vehicle))
    return r._replace(vehicle=vehicle)


def name_unnamed(recs: Iterable[AnyRecord], vehicle: str) -> list[AnyRecord]:
    """``recs`` with ``vehicle`` as the vehicle of those that name none (a version 1
    recording's: :func:`file_vehicle`)."""
    return [r if r.vehicle else _named(r, vehicle) for r in recs]


def only_vehicle(recs: list[AnyRecord], vehicle: str | None, path: object = "the recording",
                 flag: str = "--vehicle") -> list[AnyRecord]:
    """The records of ``vehicle`` (None: all); ValueError naming ``flag`` and the vehicles
    present when none is that vehicle's."""
    if vehicle is None:
        return recs
    kept = [r for r in recs if r.vehicle == vehicle]
    if not kept:
        present = ", ".join(v or '""' for v in vehicles_in(recs)) or "none"
        raise ValueError(f"{flag}: no vehicle {vehicle!r} in {path} (its vehicles: "
                         f"{present})")
    return kept


#: why a frame was not written: the disk (or the user's quota) is full, or any other error
DISK_FULL, WRITE_ERROR = "disk_full", "write_error"


@dataclass
class WriteFailure:
    """Writes to one file failing: why (:data:`DISK_FULL`, :data:`WRITE_ERROR`), since when
    (monotonic), the frames not written since, when to try again."""

    reason: str
    since: float = field(default_factory=time.monotonic)
    lost: int = 0
    retry_at: float = 0.0
    #: since when writes work again (None: the last one failed)
    ok_since: float | None = None


class RecordingFile:
    """One recording open for appending, with its name table: what the recorders write to.
    Not thread-safe: its recorder holds a lock around it.

    A file holds whole records only, from its first one on: a new file's header goes out with
    its first record, in the same ``write``; a file this object created is removed again
    while nothing of it is written (it exists once a record made it: a full disk leaves no
    empty or header-only file).  A write that fails (:meth:`append`) is cut off the file
    again, so whatever is written later follows whole records."""

    def __init__(self, path: str | Path, new: bool = False) -> None:
        """``new``: the caller has just created the (empty) file for this object, which then
        treats it as its own: it stays, holding the name, until the first write, and goes if
        that fails.  Any other file that does not exist yet is made by the first record."""
        self.path = Path(path)
        self.records = 0
        self.bytes = 0
        self.dirty = False
        #: bytes of whole records (and the header) in the file; 0: nothing written yet
        self.size = 0
        #: whether this object created the file (then it removes it while it is empty)
        self.created = new
        #: set by :meth:`close`
        self.closed = False
        #: while writes to it fail: why, since when, what it cost (set by the recorder)
        self.failure: WriteFailure | None = None
        self._index: dict[str, int] = {}  # the file's name table
        self._bound: set[str] = set()  # names bound since the last repeat
        self._since_repeat = 0
        self._next = 0  # the next free index
        try:
            self.fd = self._open()
        except OSError as exc:  # no inode left: as if created, and removed again
            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            self.fd = -1
        if not new:  # (created again by the first record; a new one keeps its name till then)
            self._unlink_if_empty()

    def _open(self) -> int:
        flags = os.O_RDWR | os.O_APPEND
        try:
            fd = os.open(self.path, flags | os.O_CREAT | os.O_EXCL, 0o644)
            self.created = True
            return fd
        except FileExistsError:
            fd = os.open(self.path, flags | os.O_CREAT, 0o644)
        try:
            size = os.fstat(fd).st_size
            if size == 0:
                return fd  # the header goes out with the first record
            with open(self.path, "rb") as f:
                data = f.read()
            if check_header(data, self.path) != VERSION:
                raise RecordingError(f"{self.path}: a version 1 recording; this gateway "
                                     f"appends to version {VERSION} ones only (record into a "
                                     "new file)")
            end = len(HEADER)
            table: dict[int, str] = {}
            for _, rec_end, rtype, _, body, body_end in _intact(data, ReadStats(), end,
                                                                VERSION):
                end = rec_end
                if rtype == NAME and body_end - body > _INDEX.size:
                    index, name = _name_of(data, body, body_end)
                    table[index] = name
            self._index = {name: i for i, name in table.items()}
            self._next = max(table, default=-1) + 1
            if end < size:
                log.warning("%s: cutting %d torn bytes off the end before appending",
                            self.path, size - end)
                os.ftruncate(fd, end)
            self.size = end
        except Exception:
            os.close(fd)
            raise
        return fd

    def _unlink_if_empty(self) -> None:
        """Close and remove the file if this object created it and nothing is in it."""
        if self.fd >= 0 and self.created and self.size == 0:
            os.close(self.fd)
            self.fd = -1
            with contextlib.suppress(OSError):
                self.path.unlink()

    def _name(self, name: str, t: float, out: list[bytes]) -> int:
        if not name:
            return NO_NAME
        index = self._index.get(name)
        if index is None:
            if self._next >= NO_NAME:  # the table is full: no name (bounded)
                return NO_NAME
            index = self._index[name] = self._next
            self._next += 1
        if name not in self._bound:
            out.append(encode_name(t, index, name))
            self._bound.add(name)
        return index

    def encode(self, t: float, frame: bytes, vehicle: str = "", source: str = "",
               rtype: int = FRAME) -> bytes:
        """A frame record (``rtype`` another type: a message record, ``frame`` its payload:
        :func:`message_payload`) with the name records it needs first (and the header, when
        the file holds nothing yet); ValueError: too long."""
        if rtype == FRAME and len(frame) > MAX_FRAME:
            encode_record(t, frame)  # raises
        self._since_repeat += 1
        if self._since_repeat >= NAME_REPEAT:
            self._since_repeat = 0
            self._bound.clear()
        out: list[bytes] = [HEADER] if self.size == 0 else []
        vi = self._name(vehicle, t, out)
        si = self._name(source, t, out)
        out.append(encode_record(t, frame, vi, si) if rtype == FRAME else
                   encode_message(rtype, t, frame, vi, si))
        return b"".join(out) if len(out) > 1 else out[0]

    def append(self, data: bytes) -> int:
        """Write ``data`` (what :meth:`encode` made just before) at the end of the file,
        creating it first if it does not exist yet; returns the bytes of records written (the
        header not counted).  On failure (OSError; RecordingError when another file took its
        place meanwhile) whatever a short write left is cut off again, every name is bound
        again before its next use, and a file holding nothing is removed."""
        if self.closed:
            raise ValueError(f"{self.path}: closed")
        header = len(HEADER) if self.size == 0 else 0
        if self.fd < 0:
            try:
                self.fd = self._open()
            except (OSError, RecordingError):
                self.forget_bindings()
                raise
            if self.size:  # not the file that went: its name table is not ours
                self.forget_bindings()
                raise RecordingError(f"{self.path}: another recording took its place")
        try:
            done = os.write(self.fd, data)
            while done < len(data):  # a short write: the disk filled up mid-record
                done += os.write(self.fd, memoryview(data)[done:])
        except OSError:
            self.forget_bindings()
            with contextlib.suppress(OSError):  # (else the reader resyncs past it)
                os.ftruncate(self.fd, self.size)
            self._unlink_if_empty()
            raise
        self.size += len(data)
        self.dirty = True
        return len(data) - header

    def forget_bindings(self) -> None:
        """After a failed write: bind every name again before its next use."""
        self._bound.clear()

    def close(self) -> None:
        """Close the file (removing it if this object created it and nothing made it in)."""
        self.closed = True
        self._unlink_if_empty()
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1
