"""The recording format (gateway/recording.py): layout, round trip, kill -9 survival, torn
tails, mid-file corruption, append after a crash, and the header checks."""

from __future__ import annotations

import logging
import os
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway import recording
from gateway.flight import FlightModel, FlightProfile
from gateway.recording import Recorder, RecordingError
from gateway.sources.sim import flight_frames
from gateway.wire import MAX_PAYLOAD, frame

ROOT = Path(__file__).resolve().parents[1]

# The header exactly as the module docstring documents it, written out independently.
DOC_HEADER = bytes.fromhex("89 41 55 52 0D 0A 1A 0A") + b"\x01\x00" + b"\x00\x00"


def doc_record(t: float, fr: bytes) -> bytes:
    """A record exactly as documented: f64 time, u16 length, frame, CRC-32 over all before."""
    body = struct.pack("<d", t) + struct.pack("<H", len(fr)) + fr
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


def tframe(i: int) -> bytes:
    """A distinct, valid wire frame per ``i`` (varying type and length, empty payloads too)."""
    return frame(0x40 + i % 3, i.to_bytes(4, "little") * (i % 7))


def frames(n: int) -> list[bytes]:
    return [tframe(i) for i in range(n)]


def write_file(path: Path, items: list[tuple[float, bytes]]) -> bytes:
    data = DOC_HEADER + b"".join(doc_record(t, f) for t, f in items)
    path.write_bytes(data)
    return data


def read_all(path: Path) -> tuple[list[tuple[float, bytes]], recording.ReadStats]:
    stats = recording.ReadStats()
    return list(recording.read(path, stats)), stats


# -- the documented layout ---------------------------------------------------------------------

def test_file_layout_is_the_documented_one(tmp_path: Path) -> None:
    path = tmp_path / "a.agrec"
    f1, f2 = frame(0x01, b"\x11" * 36), frame(0x7F, b"")
    rec = Recorder(path)
    rec.write(f1, t=1_700_000_000.25)
    rec.write(f2, t=1_700_000_001.5)
    rec.close()
    assert path.read_bytes() == (DOC_HEADER + doc_record(1_700_000_000.25, f1)
                                 + doc_record(1_700_000_001.5, f2))
    assert rec.records == 2
    assert rec.bytes == len(doc_record(0, f1)) + len(doc_record(0, f2))


def test_reader_reads_a_file_built_from_the_documentation(tmp_path: Path) -> None:
    items = [(1000.0 + i / 8, f) for i, f in enumerate(frames(20))]
    write_file(tmp_path / "doc.agrec", items)
    got, stats = read_all(tmp_path / "doc.agrec")
    assert got == items
    assert (stats.records, stats.torn_tail_bytes, stats.corrupt_skips) == (20, 0, 0)


def test_write_n_frames_and_read_them_back_with_their_times(tmp_path: Path) -> None:
    path = tmp_path / "rt.agrec"
    sim64 = [f for _, f in flight_frames(FlightModel(FlightProfile()), 10, 1, cycles=1)][:150]
    sim36 = [f for _, f in flight_frames(FlightModel(FlightProfile(revision=36)), 10, 1,
                                         cycles=1)][:50]
    biggest = frame(0x33, bytes(range(MAX_PAYLOAD)))
    all_frames = [*sim64, *sim36, *frames(40), biggest]
    items = [(1_700_000_000.0 + 0.1 * i, f) for i, f in enumerate(all_frames)]
    rec = Recorder(path)
    for t, f in items:
        rec.write(f, t=t)
    before = time.time()
    rec.write(b"\xa5\x5a\x10\x00\x29\x65")  # t defaults to the wall clock
    after = time.time()
    rec.close()
    got, stats = read_all(path)
    assert got[:-1] == items
    t_now, f_now = got[-1]
    assert f_now == b"\xa5\x5a\x10\x00\x29\x65"
    assert before <= t_now <= after
    assert stats.records == len(items) + 1 and stats.torn_tail_bytes == 0


def test_a_frame_longer_than_a_wire_frame_is_refused_not_written_unreadable(
        tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "long.agrec")
    with pytest.raises(ValueError):
        rec.write(b"\xa5\x5a" + bytes(recording.MAX_FRAME - 1), t=1.0)
    rec.write(b"\x00" * recording.MAX_FRAME, t=2.0)  # the longest frame still round trips
    rec.close()
    got, stats = read_all(tmp_path / "long.agrec")
    assert got == [(2.0, b"\x00" * recording.MAX_FRAME)]
    assert stats.corrupt_skips == stats.torn_tail_bytes == 0


def test_concurrent_writers_never_interleave_records(tmp_path: Path) -> None:
    path = tmp_path / "mt.agrec"
    rec = Recorder(path)
    n_threads, per_thread = 4, 250
    barrier = threading.Barrier(n_threads)

    def writer(k: int) -> None:
        barrier.wait(5)
        for i in range(per_thread):
            rec.write(frame(0x50 + k, i.to_bytes(2, "little") * (1 + i % 40)), t=float(i))

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(n_threads)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(10)
    rec.close()
    got, stats = read_all(path)
    assert stats.records == n_threads * per_thread
    assert stats.corrupt_skips == stats.torn_tail_bytes == 0
    for k in range(n_threads):  # each writer's records, in its own order
        mine = [(t, f) for t, f in got if f[2] == 0x50 + k]
        assert mine == [(float(i), frame(0x50 + k, i.to_bytes(2, "little") * (1 + i % 40)))
                        for i in range(per_thread)]


def test_close_is_safe_twice_and_writes_after_close_are_ignored(tmp_path: Path) -> None:
    path = tmp_path / "c.agrec"
    rec = Recorder(path)
    rec.write(tframe(1), t=1.0)
    rec.close()
    rec.close()
    rec.write(tframe(2), t=2.0)
    assert rec.records == 1
    assert read_all(path)[0] == [(1.0, tframe(1))]


# -- kill -9 -----------------------------------------------------------------------------------

CHILD = r"""
import os, sys
from gateway.recording import Recorder
from gateway.wire import frame
rec = Recorder(sys.argv[1])
i = 0
while True:
    rec.write(frame(0x40 + i % 3, i.to_bytes(4, "little") * (i % 7)), t=1000.0 + i)
    i += 1
    os.write(1, b"%d\n" % i)  # reported only once the record's write() has returned
"""


def test_a_recorder_killed_with_sigkill_leaves_every_record_but_at_most_the_last(
        tmp_path: Path) -> None:
    path = tmp_path / "killed.agrec"
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    last = [0]
    enough = threading.Event()

    def reader() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            last[0] = int(line)
            if last[0] >= 2000:
                enough.set()

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    try:
        ok = enough.wait(20)
        proc.send_signal(signal.SIGKILL)  # mid-stream: the child is writing in a tight loop
        assert proc.wait(10) == -signal.SIGKILL
        assert ok, f"child wrote only {last[0]} records: {proc.stderr.read()!r}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    th.join(10)
    confirmed = last[0]
    got, stats = read_all(path)  # must not raise
    n = len(got)
    # Every record whose write() returned is there; at most one more (written, not yet told).
    assert confirmed <= n <= confirmed + 1
    assert got == [(1000.0 + i, tframe(i)) for i in range(n)]
    assert stats.corrupt_skips == 0
    assert stats.torn_tail_bytes < len(doc_record(0.0, tframe(n)))


# -- torn tails --------------------------------------------------------------------------------

def test_every_truncation_inside_the_last_record_is_a_torn_tail_that_is_skipped(
        tmp_path: Path) -> None:
    items = [(2000.0 + i, f) for i, f in enumerate(frames(12))]
    data = write_file(tmp_path / "full.agrec", items)
    last_len = len(doc_record(*items[-1]))
    whole = len(data) - last_len
    path = tmp_path / "torn.agrec"
    for kept in range(1, last_len):
        path.write_bytes(data[:whole + kept])
        got, stats = read_all(path)
        assert got == items[:-1], kept
        assert stats.torn_tail_bytes == kept > 0
        assert stats.corrupt_skips == 0


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 15), cut_back=st.integers(0, 400), seed=st.integers(0, 1000))
def test_any_truncation_yields_exactly_the_whole_records_before_it(n: int, cut_back: int,
                                                                    seed: int) -> None:
    items = [(float(seed + i), tframe(seed + i)) for i in range(n)]
    data = DOC_HEADER + b"".join(doc_record(t, f) for t, f in items)
    cut = max(len(DOC_HEADER), len(data) - cut_back)
    stats = recording.ReadStats()
    got = [(t, f) for _, t, f in recording.scan(data[:cut], stats)]
    ends, pos = [], len(DOC_HEADER)
    for t, f in items:
        pos += len(doc_record(t, f))
        ends.append(pos)
    whole = sum(1 for e in ends if e <= cut)
    assert got == items[:whole]
    assert stats.torn_tail_bytes == cut - (ends[whole - 1] if whole else len(DOC_HEADER))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600))
def test_arbitrary_bytes_never_raise_in_the_scanner(data: bytes) -> None:
    stats = recording.ReadStats()
    for _ in recording.scan(DOC_HEADER + data, stats):
        pass
    assert stats.torn_tail_bytes <= len(data)


# -- corruption in the middle --------------------------------------------------------------------

def test_a_flipped_byte_anywhere_in_one_record_skips_that_record_only(tmp_path: Path) -> None:
    items = [(3000.0 + i, f) for i, f in enumerate(frames(9))]
    data = write_file(tmp_path / "ok.agrec", items)
    k = 4
    start = len(DOC_HEADER) + sum(len(doc_record(t, f)) for t, f in items[:k])
    size = len(doc_record(*items[k]))
    path = tmp_path / "bad.agrec"
    for off in range(size):  # time, length, frame and CRC bytes alike
        bad = bytearray(data)
        bad[start + off] ^= 0xFF
        path.write_bytes(bytes(bad))
        got, stats = read_all(path)
        assert got == items[:k] + items[k + 1:], off
        assert stats.corrupt_skips == 1
        assert stats.bytes_skipped == size
        assert stats.torn_tail_bytes == 0


def test_two_damaged_records_and_inserted_garbage_are_all_passed(tmp_path: Path) -> None:
    items = [(4000.0 + i, f) for i, f in enumerate(frames(10))]
    recs = [doc_record(t, f) for t, f in items]
    recs[2] = recs[2][:5] + b"\x00" + recs[2][6:]
    recs[7] = recs[7][:-1] + bytes([recs[7][-1] ^ 1])
    garbage = b"\xa5\x5a\x01\xff" + b"\x89AUR" + bytes(range(40))
    data = DOC_HEADER + b"".join(recs[:5]) + garbage + b"".join(recs[5:])
    (tmp_path / "g.agrec").write_bytes(data)
    got, stats = read_all(tmp_path / "g.agrec")
    assert got == [items[i] for i in range(10) if i not in (2, 7)]
    assert stats.corrupt_skips == 3
    assert stats.bytes_skipped == len(recs[2]) + len(garbage) + len(recs[7])


# -- append --------------------------------------------------------------------------------------

def test_reopening_a_torn_file_for_append_cuts_the_tail_first(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    items = [(5000.0 + i, f) for i, f in enumerate(frames(8))]
    data = write_file(tmp_path / "full.agrec", items)
    last_len = len(doc_record(*items[-1]))
    for kept in (1, last_len // 2, last_len - 1):
        path = tmp_path / f"torn{kept}.agrec"
        path.write_bytes(data[:len(data) - last_len + kept])
        with caplog.at_level(logging.WARNING, logger="gateway.recording"):
            rec = Recorder(path)
        assert any("cutting" in r.getMessage() for r in caplog.records)
        caplog.clear()
        assert path.stat().st_size == len(data) - last_len  # cut at open, before any write
        new = [(6000.0 + i, frame(0x60, bytes([i]) * i)) for i in range(5)]
        for t, f in new:
            rec.write(f, t=t)
        rec.close()
        got, stats = read_all(path)
        assert got == items[:-1] + new
        assert (stats.torn_tail_bytes, stats.corrupt_skips) == (0, 0)


def test_appending_to_an_intact_recording_keeps_everything(tmp_path: Path) -> None:
    path = tmp_path / "app.agrec"
    a = [(1.0 + i, f) for i, f in enumerate(frames(5))]
    b = [(10.0 + i, frame(0x70, bytes([i]))) for i in range(5)]
    for part in (a, b):
        rec = Recorder(path)
        for t, f in part:
            rec.write(f, t=t)
        rec.close()
    got, stats = read_all(path)
    assert got == a + b
    assert stats.corrupt_skips == stats.torn_tail_bytes == 0
    assert path.read_bytes().count(DOC_HEADER) == 1


# -- header checks -------------------------------------------------------------------------------

@pytest.mark.parametrize("head", [
    b"",
    b"\x89AU",
    b"GIF89a\x00\x00\x00\x00\x00\x00",
    b"\x89AUR\n\n\x1a\n\x01\x00\x00\x00",  # what a text-mode transfer does to the magic
])
def test_bad_magic_is_a_recording_error(tmp_path: Path, head: bytes) -> None:
    path = tmp_path / "bad.agrec"
    path.write_bytes(head + doc_record(1.0, tframe(1)))
    with pytest.raises(RecordingError, match="magic"):
        list(recording.read(path))
    if head:  # an empty file is a new recording for the recorder
        with pytest.raises(RecordingError):
            Recorder(path)
        assert path.read_bytes() == head + doc_record(1.0, tframe(1))  # left untouched


@pytest.mark.parametrize("version", [0, 2, 0xFFFF])
def test_an_unknown_version_is_a_recording_error(tmp_path: Path, version: int) -> None:
    path = tmp_path / "v.agrec"
    content = DOC_HEADER[:8] + struct.pack("<HH", version, 0) + doc_record(1.0, tframe(1))
    path.write_bytes(content)
    with pytest.raises(RecordingError, match="version"):
        list(recording.read(path))
    with pytest.raises(RecordingError, match="version"):
        Recorder(path)
    assert path.read_bytes() == content


def test_a_new_recorder_writes_the_header_to_an_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.agrec"
    path.touch()
    Recorder(path).close()
    assert path.read_bytes() == DOC_HEADER
    assert os.path.getsize(path) == 12
