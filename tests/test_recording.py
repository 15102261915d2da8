"""The recording format (gateway/recording.py): layout, round trip, kill -9 survival, torn
tails, mid-file corruption, append after a crash, and the header checks; the recorder
(gateway/recorder.py) off the gateway's hot path (a bounded queue, a writer thread, fsync on
a timer, drops counted) and what it does with messages that arrived without a wire frame."""

from __future__ import annotations

import io
import logging
import os
import selectors
import signal
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from helpers import run_within, wait_for
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway import config, recording
from gateway.app import Gateway
from gateway.flight import FlightModel, FlightProfile
from gateway.model import GatewayStats, Position, RawFrame, SmUpdate, Status, VehicleState
from gateway.recorder import Recorder
from gateway.recording import RecordingError
from gateway.sources import Source
from gateway.sources.sim import flight_frames
from gateway.wire import MAX_PAYLOAD, decode_all, encode, frame

ROOT = Path(__file__).resolve().parents[1]

# The headers exactly as the module docstring documents them, written out independently.
DOC_HEADER = bytes.fromhex("89 41 55 52 0D 0A 1A 0A") + b"\x02\x00" + b"\x00\x00"
DOC_HEADER_V1 = bytes.fromhex("89 41 55 52 0D 0A 1A 0A") + b"\x01\x00" + b"\x00\x00"


def _crc(body: bytes) -> bytes:
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


def doc_record(t: float, fr: bytes, vehicle: int = 0xFFFF, source: int = 0xFFFF) -> bytes:
    """A version 2 frame record exactly as documented: type 1, f64 time, u16 body length,
    u16 vehicle index, u16 source index, frame, CRC-32 over all before."""
    body = struct.pack("<HH", vehicle, source) + fr
    return _crc(b"\x01" + struct.pack("<d", t) + struct.pack("<H", len(body)) + body)


def doc_name(t: float, index: int, name: str) -> bytes:
    """A version 2 name record as documented: type 2, time, length, u16 index, UTF-8 name."""
    body = struct.pack("<H", index) + name.encode()
    return _crc(b"\x02" + struct.pack("<d", t) + struct.pack("<H", len(body)) + body)


def doc_record_v1(t: float, fr: bytes) -> bytes:
    """A version 1 record as documented: f64 time, u16 length, frame, CRC-32 over all before."""
    return _crc(struct.pack("<d", t) + struct.pack("<H", len(fr)) + fr)


#: the two layouts the reader reads: (header, frame record)
LAYOUTS = {"v1": (DOC_HEADER_V1, doc_record_v1), "v2": (DOC_HEADER, doc_record)}


def tframe(i: int) -> bytes:
    """A distinct, valid wire frame per ``i`` (varying type and length, empty payloads too)."""
    return frame(0x40 + i % 3, i.to_bytes(4, "little") * (i % 7))


def frames(n: int) -> list[bytes]:
    return [tframe(i) for i in range(n)]


def write_file(path: Path, items: list[tuple[float, bytes]], layout: str = "v2") -> bytes:
    header, record = LAYOUTS[layout]
    data = header + b"".join(record(t, f) for t, f in items)
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


@pytest.mark.parametrize("layout", LAYOUTS)
def test_reader_reads_a_file_built_from_the_documentation(tmp_path: Path, layout: str) -> None:
    items = [(1000.0 + i / 8, f) for i, f in enumerate(frames(20))]
    write_file(tmp_path / "doc.agrec", items, layout)
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
from gateway.recorder import Recorder
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

@pytest.mark.parametrize("layout", LAYOUTS)
def test_every_truncation_inside_the_last_record_is_a_torn_tail_that_is_skipped(
        tmp_path: Path, layout: str) -> None:
    items = [(2000.0 + i, f) for i, f in enumerate(frames(12))]
    data = write_file(tmp_path / "full.agrec", items, layout)
    last_len = len(LAYOUTS[layout][1](*items[-1]))
    whole = len(data) - last_len
    path = tmp_path / "torn.agrec"
    for kept in range(1, last_len):
        path.write_bytes(data[:whole + kept])
        got, stats = read_all(path)
        assert got == items[:-1], kept
        assert stats.torn_tail_bytes == kept > 0
        assert stats.corrupt_skips == 0


@pytest.mark.parametrize("layout", LAYOUTS)
@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 15), cut_back=st.integers(0, 400), seed=st.integers(0, 1000))
def test_any_truncation_yields_exactly_the_whole_records_before_it(layout: str, n: int,
                                                                    cut_back: int,
                                                                    seed: int) -> None:
    header, doc_record = LAYOUTS[layout]
    items = [(float(seed + i), tframe(seed + i)) for i in range(n)]
    data = header + b"".join(doc_record(t, f) for t, f in items)
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


@pytest.mark.parametrize("layout", LAYOUTS)
@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600))
def test_arbitrary_bytes_never_raise_in_the_scanner(layout: str, data: bytes) -> None:
    stats = recording.ReadStats()
    for _ in recording.records(LAYOUTS[layout][0] + data, stats):
        pass
    assert stats.torn_tail_bytes <= len(data)


# -- corruption in the middle --------------------------------------------------------------------

@pytest.mark.parametrize("layout", LAYOUTS)
def test_a_flipped_byte_anywhere_in_one_record_skips_that_record_only(tmp_path: Path,
                                                                      layout: str) -> None:
    header, doc_record = LAYOUTS[layout]
    items = [(3000.0 + i, f) for i, f in enumerate(frames(9))]
    data = write_file(tmp_path / "ok.agrec", items, layout)
    k = 4
    start = len(header) + sum(len(doc_record(t, f)) for t, f in items[:k])
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


@pytest.mark.parametrize("layout", LAYOUTS)
def test_two_damaged_records_and_inserted_garbage_are_all_passed(tmp_path: Path,
                                                                 layout: str) -> None:
    header, doc_record = LAYOUTS[layout]
    items = [(4000.0 + i, f) for i, f in enumerate(frames(10))]
    recs = [doc_record(t, f) for t, f in items]
    recs[2] = recs[2][:5] + bytes([recs[2][5] ^ 0xFF]) + recs[2][6:]
    recs[7] = recs[7][:-1] + bytes([recs[7][-1] ^ 1])
    garbage = b"\xa5\x5a\x01\xff" + b"\x89AUR" + bytes(range(40))
    data = header + b"".join(recs[:5]) + garbage + b"".join(recs[5:])
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


@pytest.mark.parametrize("version", [0, 3, 0xFFFF])
def test_an_unknown_version_is_a_recording_error(tmp_path: Path, version: int) -> None:
    path = tmp_path / "v.agrec"
    content = DOC_HEADER[:8] + struct.pack("<HH", version, 0) + doc_record(1.0, tframe(1))
    path.write_bytes(content)
    with pytest.raises(RecordingError, match="version"):
        list(recording.read(path))
    with pytest.raises(RecordingError, match="version"):
        Recorder(path)
    assert path.read_bytes() == content


def test_a_recording_holds_whole_records_from_its_first_one_or_does_not_exist(
        tmp_path: Path) -> None:
    # (issue 23: no empty or header-only files; this test pinned a header-only file before)
    path = tmp_path / "new.agrec"
    rec = Recorder(path)
    assert not path.exists()  # created by its first record
    rec.close()
    assert not path.exists() and rec.paths == []
    touched = tmp_path / "empty.agrec"
    touched.touch()  # somebody else's empty file: left as it was
    Recorder(touched).close()
    assert touched.read_bytes() == b""
    rec = Recorder(touched)
    rec.write(tframe(1), t=1.0)
    rec.close()
    assert touched.read_bytes() == DOC_HEADER + doc_record(1.0, tframe(1))
    assert os.path.getsize(touched) == 12 + len(doc_record(1.0, tframe(1)))


# -- off the hot path: submit() never waits on disk ---------------------------------------------

def _sm_update(t_ms: int, altitude_m: float) -> SmUpdate:
    """An SM_UPDATE built in memory, as a MAVLink or Zenoh-JSON source builds it: no raw."""
    return SmUpdate(t_ms, 3, True, 0, altitude_m, 1.0, 2.0, 3.0, 0.1, 0.2, 0.3)


@pytest.fixture
def fifo(tmp_path: Path) -> Iterator[Path]:
    """A named pipe nobody reads: a "disk" whose writes block once 64 KiB are pending."""
    path = tmp_path / "stalled.agrec"
    os.mkfifo(path)
    yield path


def _drain_until(path: Path, done: threading.Event) -> bytes:
    """Read the pipe until ``done`` is set (the recorder's writer finished)."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    out = bytearray()
    try:
        sel = selectors.DefaultSelector()
        sel.register(fd, selectors.EVENT_READ)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            sel.select(0.05)
            try:
                chunk = os.read(fd, 1 << 16)
            except BlockingIOError:
                chunk = b""
            out += chunk
            if not chunk and done.is_set():
                break
        sel.close()
    finally:
        os.close(fd)
    return bytes(out)


def test_submit_never_blocks_on_a_stalled_disk_and_counts_what_it_drops(fifo: Path) -> None:
    rec = Recorder(fifo, queue_depth=1000)
    n = 3000  # 220 bytes a record: the queue alone holds three times what the pipe takes
    sent = [frame(0x40 + i % 3, i.to_bytes(4, "little") * 50) for i in range(n)]
    try:
        accepted = run_within(lambda: [rec.submit(f, t=float(i)) for i, f in enumerate(sent)],
                              timeout=10)
        assert wait_for(lambda: rec.records > 0)  # the writer is writing (then stuck)
        took = run_within(lambda: _timed(lambda: rec.close(0.3)), timeout=5)
        assert took < 1.0, f"close took {took:.2f} s with the writer stuck"
        assert not rec.finished.is_set()  # still stuck in write(): left to finish on its own
    finally:
        data = _drain_until(fifo, rec.finished)
    assert rec.finished.is_set()
    assert accepted.count(False) == rec.dropped_queue_full > 0
    stats = recording.ReadStats()
    got = [(t, f) for _, t, f in recording.scan(data, stats)]
    assert data.startswith(DOC_HEADER)
    assert stats.corrupt_skips == stats.torn_tail_bytes == 0
    assert len(got) == rec.records
    kept = [(float(i), f) for i, (f, ok) in enumerate(zip(sent, accepted, strict=True)) if ok]
    assert got == kept[:len(got)]  # what was written is what was accepted, in order
    assert rec.records + rec.dropped_at_close == accepted.count(True)


def _timed(fn: Callable[[], object]) -> float:
    t0 = time.monotonic()
    fn()
    return time.monotonic() - t0


def test_the_writer_fsyncs_on_its_timer_when_no_more_frames_arrive(tmp_path: Path) -> None:
    path = tmp_path / "idle.agrec"
    rec = Recorder(path, fsync_interval_s=0.05)
    try:
        assert rec.syncs == 0
        rec.submit(tframe(1), t=1.0)  # one frame, then silence
        assert wait_for(lambda: rec.syncs >= 1), "no fsync while idle"
        assert read_all(path)[0] == [(1.0, tframe(1))]
        synced = rec.syncs
        rec.submit(tframe(2), t=2.0)
        assert wait_for(lambda: rec.syncs > synced)
    finally:
        rec.close()
    assert read_all(path)[0] == [(1.0, tframe(1)), (2.0, tframe(2))]


def test_close_writes_everything_queued_before_it(tmp_path: Path) -> None:
    path = tmp_path / "drain.agrec"
    rec = Recorder(path, fsync_interval_s=0)
    items = [(100.0 + i, tframe(i)) for i in range(500)]
    for t, f in items:
        assert rec.submit(f, t=t)
    rec.close(5.0)
    assert rec.finished.is_set()
    assert read_all(path)[0] == items
    assert rec.stats()["records"] == 500 and rec.dropped_at_close == 0
    assert not rec.submit(tframe(9))  # closed: refused, file unchanged
    assert read_all(path)[0] == items


def test_messages_without_a_frame_are_encoded_recorded_as_fields_or_counted(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """(Issue 24 changed this: vehicle states and positions were counted not_recordable;
    they are message records now.  A kind the format has no record for still is.)"""
    path = tmp_path / "mixed.agrec"
    sm = _sm_update(1234, 56.5)
    st = Status(1240, 3, 0, 1)
    relay = RawFrame(0x42, b"relay me")
    decoded = decode_all(encode(_sm_update(99, 1.0)))[0]  # carries its raw frame
    others = [VehicleState(True, "AUTO"), Position(47.1, 8.5), VehicleState(False, "RTL")]
    foreign = GatewayStats("gw2", {}, {})
    with caplog.at_level(logging.WARNING, logger="gateway.recorder"):
        rec = Recorder(path)
        for i, m in enumerate([sm, others[0], st, others[1], relay, decoded, others[2],
                               foreign, foreign]):
            rec.submit(m, t=10.0 + i)
        rec.close()
    got = [f for _, f in read_all(path)[0]]
    assert got == [encode(sm), encode(st), encode(relay), decoded.raw]
    assert decode_all(b"".join(got))[0].fields() == sm.fields()
    assert [r.message for r in recording.read_records(path, messages=True)
            if isinstance(r, recording.MessageRecord)] == others
    assert rec.not_recordable == {"gatewaystats": 2}
    warned = [r.getMessage() for r in caplog.records if "not recorded" in r.getMessage()]
    assert len(warned) == 1 and "gatewaystats" in warned[0], warned  # once a kind


KILLED_SUBMITTER = r"""
import os, sys, threading
from gateway.recorder import Recorder
from gateway.wire import frame
rec = Recorder(sys.argv[1], fsync_interval_s=0.01, queue_depth=1 << 20)
told = False
for i in range(200_000):  # fewer than the queue holds: nothing is dropped
    rec.submit(frame(0x40 + i % 3, i.to_bytes(4, "little") * (i % 7)), t=1000.0 + i)
    if not told and rec.records >= 2000:  # the writer thread is well under way
        os.write(1, b"ready\n")
        told = True
if not told:
    while rec.records < 2000:
        rec.finished.wait(0.001)
    os.write(1, b"ready\n")
threading.Event().wait()
"""


def test_a_gateway_recorder_killed_with_sigkill_leaves_a_readable_prefix(tmp_path: Path) -> None:
    """The writer thread writes each record in one write(): killing the process mid-stream
    leaves the records it wrote, in order, and at most a torn last one."""
    path = tmp_path / "killed-async.agrec"
    proc = subprocess.Popen([sys.executable, "-c", KILLED_SUBMITTER, str(path)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        assert proc.stdout is not None
        ready = run_within(proc.stdout.readline, timeout=20)
        proc.send_signal(signal.SIGKILL)
        assert proc.wait(10) == -signal.SIGKILL
        assert ready == b"ready\n", proc.stderr.read() if proc.stderr else ""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    got, stats = read_all(path)
    assert len(got) >= 2000
    assert got == [(1000.0 + i, tframe(i)) for i in range(len(got))]
    assert stats.corrupt_skips == 0
    assert stats.torn_tail_bytes < len(doc_record(0.0, tframe(len(got))))


# -- in the gateway --------------------------------------------------------------------------------

class _MixedSource(Source):
    """Emits what a MAVLink vehicle's source does: SM_UPDATEs built in memory (no frame) and
    vehicle state and positions, which have no wire form."""

    NAME = "mixed"

    def run(self, stop: threading.Event) -> None:
        for i in range(30):
            self.emit(_sm_update(1000 + i, float(i))._replace(origin=self.name))
            self.emit(VehicleState(True, "AUTO", origin=self.name))
            if i % 3 == 0:
                self.emit(Position(47.0, 8.0, origin=self.name))


def _gateway(cfg_dict: dict) -> Gateway:
    return Gateway(config.parse(cfg_dict), status_out=io.StringIO())


def test_fan_out_does_not_wait_for_a_stalled_recording(fifo: Path) -> None:
    """Five flights at full speed into a gateway whose recording is a pipe nobody reads: the
    source finishes (its messages reach the dispatcher) though the disk takes nothing."""
    gw = _gateway({"gateway": {"record": str(fifo), "status_interval_s": 0},
                   "sources": [{"type": "sim", "speed": 0, "cycles": 5}]})
    gw.start()
    rec = gw.recorder
    assert rec is not None
    try:
        src = gw.sources[0]
        assert src.done.wait(20), "the source was held up by the recorder"
        sent = src.stats()["sent"]
        assert sum(gw.counts.values()) == sent
        assert wait_for(lambda: rec.records > 0)
        assert rec.records < sent  # the pipe is full: the writer is stuck
        t0 = time.monotonic()
        summary = gw.stop()
        took = time.monotonic() - t0
        assert took < 1.0 + 0.5, took
    finally:
        data = _drain_until(fifo, rec.finished)
    assert summary["recorder"]["records"] <= sent
    stats = recording.ReadStats()
    assert len(list(recording.scan(data, stats))) == rec.records
    assert stats.corrupt_skips == 0


def test_the_gateway_records_encodable_messages_and_reports_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "mixed.agrec"
    gw = _gateway({"gateway": {"record": str(path), "status_interval_s": 0}})
    src = _MixedSource()
    gw.sources = [src]
    gw.start()
    try:
        assert src.done.wait(10)
    finally:
        summary = gw.stop()
    got = [f for _, f in read_all(path)[0]]
    assert got == [encode(_sm_update(1000 + i, float(i))) for i in range(30)]
    # (issue 24: the vehicle states and positions are recorded too, as message records)
    kinds = [type(r.message).__name__ for r in recording.read_records(path, messages=True)
             if isinstance(r, recording.MessageRecord)]
    assert kinds.count("VehicleState") == 30 and kinds.count("Position") == 10
    assert summary["recorded"] == 70
    assert summary["recorder"]["not_recordable"] == {}
