"""Recording onto a full disk (issue 23): no file that holds nothing is left behind, every frame
not written is counted (``dropped_disk_full``, ``dropped_write_error``) and logged once per
failing stretch, and when space returns the recording goes on as whole, readable records.

The disk is a real one: a small tmpfs mounted for the test (root only: CI runs as root; the
tests skip, saying why, where ``mount`` is refused), filled with a filler file and freed by
deleting it; ``/dev/full`` and a file-size limit (``RLIMIT_FSIZE``) give the kernel's own
ENOSPC and EFBIG without a mount.  Expected figures come from the recorder's own return
values and the file read back, never from the counters under test alone.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import wait_for
from test_recording import tframe
from test_recording_vehicles import T0, _update

from dialects.states import SimpleState
from gateway import recording
from gateway.recorder import DirectoryRecorder, Recorder
from gateway.wire import frame

CONSOLE_SCRIPT = Path(sys.executable).parent / "aurora-gateway"
TIMEOUT_S = 30.0
FS_KIB = 64
INODES = 8


@contextlib.contextmanager
def tmpfs(where: Path, options: str) -> Iterator[Path]:
    """A tmpfs mounted at ``where`` (made) with ``options`` for the block, unmounted after it;
    the test skips, saying why, where it cannot be mounted."""
    if os.geteuid() != 0:
        pytest.skip("a real full filesystem needs a tmpfs mount, which needs root (CI is root)")
    where.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)],
                       capture_output=True, text=True, check=False)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip() or r.returncode}")
    try:
        yield where
    finally:
        if subprocess.run(["umount", str(where)], check=False).returncode != 0:
            subprocess.run(["umount", "-l", str(where)], check=False)


@pytest.fixture
def small_fs(tmp_path: Path) -> Iterator[Path]:
    """A tmpfs of :data:`FS_KIB` KiB mounted for the test."""
    with tmpfs(tmp_path / "disk", f"size={FS_KIB}k") as where:
        yield where


@pytest.fixture
def few_inodes_fs(tmp_path: Path) -> Iterator[Path]:
    """A tmpfs with room for data but for :data:`INODES` files and directories only."""
    with tmpfs(tmp_path / "disk", f"size=1m,nr_inodes={INODES}") as where:
        yield where


def fill_inodes(fs: Path) -> list[Path]:
    """Make empty files in ``fs`` until the kernel says ENOSPC; returns them."""
    made = []
    for i in range(INODES + 1):
        try:
            (fs / f"inode{i}").touch()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc
            return made
        made.append(fs / f"inode{i}")
    raise AssertionError(f"{INODES + 1} files made on a tmpfs of {INODES} inodes")


def fill(fs: Path, leave: int = 0) -> Path:
    """Fill ``fs`` with a filler file until the kernel says ENOSPC, then give ``leave`` bytes
    (whole pages) back; returns the filler (delete it to free the space)."""
    filler = fs / "filler"
    with filler.open("wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 4096)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC, exc
    if leave:
        os.truncate(filler, filler.stat().st_size - leave)
    assert os.statvfs(fs).f_bavail * os.statvfs(fs).f_frsize == leave
    return filler


def big_frame(i: int) -> bytes:
    """A frame of about 200 bytes (records do not fit the free space evenly)."""
    return frame(0x40 + i % 3, i.to_bytes(4, "little") * 50)


def messages(caplog: pytest.LogCaptureFixture, text: str) -> list[str]:
    return [r.getMessage() for r in caplog.records if text in r.getMessage()]


def test_a_recording_on_a_full_disk_leaves_no_file_and_counts_every_frame(
        small_fs: Path, caplog: pytest.LogCaptureFixture) -> None:
    fill(small_fs)
    path = small_fs / "flight.aur"
    with caplog.at_level(logging.INFO, logger="gateway.recorder"):
        rec = Recorder(path)
        rec.WRITE_RETRY_S = 0.0  # every frame meets the full disk
        for i in range(50):
            rec.write(tframe(i), t=T0 + i, vehicle="alpha", source="serial")
        rec.close()
    assert not path.exists() and rec.paths == [] and rec.records == 0
    assert sorted(os.listdir(small_fs)) == ["filler"]
    st = rec.stats()
    assert (st["dropped_disk_full"], st["dropped_write_error"], st["write_errors"]) == (50, 0, 50)
    (failed,) = messages(caplog, "cannot write")
    assert str(path) in failed and os.strerror(errno.ENOSPC) in failed
    (closed,) = messages(caplog, "closed;")
    assert "50 frames not written" in closed and "no file" in closed
    # with --log-format json the figures are keys of their own
    (record,) = [r for r in caplog.records if "closed;" in r.getMessage()]
    assert getattr(record, "fields", None) == {"recording": str(path), "reason": "disk_full",
                                               "frames_not_written": 50}


def test_while_writes_fail_they_are_tried_again_later_not_per_frame(small_fs: Path) -> None:
    fill(small_fs)
    rec = Recorder(small_fs / "flight.aur")
    rec.WRITE_RETRY_S = 3600.0
    for i in range(100):
        rec.write(tframe(i), t=T0 + i)
    rec.close()
    assert rec.stats()["write_errors"] == 1  # one attempt
    assert rec.stats()["dropped_disk_full"] == 100  # every frame counted


@pytest.mark.parametrize("resume_after_s", [0.0, 3600.0])  # said at once; said at close
def test_when_space_returns_the_recording_goes_on_whole_and_readable(
        small_fs: Path, caplog: pytest.LogCaptureFixture, resume_after_s: float) -> None:
    filler = fill(small_fs, leave=3 * 4096)
    path = small_fs / "flight.aur"
    written: list[recording.Record] = []
    with caplog.at_level(logging.INFO, logger="gateway.recorder"):
        rec = Recorder(path)
        rec.WRITE_RETRY_S = 0.0
        rec.RESUME_AFTER_S = resume_after_s
        i = 0

        def put() -> bool:
            nonlocal i
            before = rec.records
            rec.write(big_frame(i), t=T0 + i, vehicle="alpha", source="serial")
            if rec.records > before:
                written.append(recording.Record(T0 + i, big_frame(i), "alpha", "serial"))
            i += 1
            return rec.records > before

        while put():  # until the disk is full
            assert i < 1000
        full_at = len(written)
        # what is on the disk now is whole records only: the torn one was cut off
        stats = recording.ReadStats()
        assert list(recording.read_records(path, stats)) == written
        assert stats.torn_tail_bytes == 0
        assert path.stat().st_size == len(recording.HEADER) + rec.bytes
        for _ in range(20):
            assert not put()
        filler.unlink()  # space is back
        for _ in range(30):
            assert put()
        rec.close()
    stats = recording.ReadStats()
    assert list(recording.read_records(path, stats)) == written  # names bound again too
    assert (stats.torn_tail_bytes, stats.corrupt_skips, stats.unnamed) == (0, 0, 0)
    assert len(written) == full_at + 30 == rec.records
    assert rec.stats()["dropped_disk_full"] == 21  # the one that did not fit, and 20
    assert len(messages(caplog, "cannot write")) == 1
    (again,) = messages(caplog, "writing again")
    assert str(path) in again and "21 frames not written" in again
    assert not messages(caplog, "closed;")  # nothing was failing at close


def test_record_dir_on_a_full_disk_makes_no_file_per_flight_then_records_when_space_returns(
        small_fs: Path, caplog: pytest.LogCaptureFixture) -> None:
    filler = fill(small_fs)
    d = small_fs / "flights"
    with caplog.at_level(logging.INFO, logger="gateway.recorder"):
        rec = DirectoryRecorder(d)
        rec.WRITE_RETRY_S = 0.0
        for k in range(10):  # ten flights of five messages on a full disk
            for j in range(5):
                assert rec.submit(_update("alpha", SimpleState.ARMED, 1000 * k + j, 1.0),
                                  t=T0 + k, new_flight=j == 0)
        assert wait_for(lambda: rec.dropped_disk_full == 50)
        assert list(d.iterdir()) == []  # not one empty file
        filler.unlink()
        assert rec.submit(_update("alpha", SimpleState.ARMED, 20_000, 1.0), t=T0 + 20,
                          new_flight=True)
        assert wait_for(lambda: rec.records == 1)
        rec.close(5.0)
    (path,) = rec.paths
    assert list(d.iterdir()) == [path]
    assert [r.vehicle for r in recording.read_records(path)] == ["alpha"]
    assert len(messages(caplog, "cannot write")) == 1  # not one per flight
    assert rec.stats()["dropped_disk_full"] == 50


def test_no_inode_left_is_a_full_disk_too_and_no_configuration_error(
        few_inodes_fs: Path, caplog: pytest.LogCaptureFixture) -> None:
    fillers = fill_inodes(few_inodes_fs)
    path = few_inodes_fs / "flight.aur"
    d = few_inodes_fs / "flights"
    with caplog.at_level(logging.ERROR, logger="gateway.recorder"):
        one = Recorder(path)  # no file can be made: counted, not refused
        many = DirectoryRecorder(d)
    one.WRITE_RETRY_S = 0.0
    many.OPEN_RETRY_S = 0.0
    try:
        for i in range(10):
            one.write(tframe(i), t=T0 + i)
            assert many.submit(_update("alpha", SimpleState.ARMED, i, 1.0), t=T0 + i)
        assert wait_for(lambda: many.dropped_disk_full == 10)
        assert one.dropped_disk_full == 10 and many.dropped_open_failed == 0
        assert not path.exists() and not d.exists()
        for f in fillers[:3]:
            f.unlink()  # a file for each, and the directory
        one.write(tframe(10), t=T0 + 10)
        assert many.submit(_update("alpha", SimpleState.ARMED, 10, 1.0), t=T0 + 10)
        assert wait_for(lambda: many.records == 1)
    finally:
        one.close()
        many.close(5.0)
    assert list(recording.read(path)) == [(T0 + 10, tframe(10))]
    (flight,) = many.paths
    assert [r.vehicle for r in recording.read_records(flight)] == ["alpha"]
    assert len(messages(caplog, "cannot create the directory yet")) == 1


def test_dev_full_counts_disk_full_without_a_mount(caplog: pytest.LogCaptureFixture) -> None:
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full here")
    with caplog.at_level(logging.ERROR, logger="gateway.recorder"):
        rec = Recorder("/dev/full")
        rec.WRITE_RETRY_S = 0.0
        for i in range(5):
            rec.write(tframe(i), t=T0 + i)
        rec.close()
    assert os.path.exists("/dev/full")  # never removed: this recorder did not create it
    assert (rec.dropped_disk_full, rec.dropped_write_error, rec.records) == (5, 0, 0)
    assert len(messages(caplog, "cannot write")) == 1


_LIMITED_WRITER = """
import json, resource, sys
from gateway.recorder import Recorder
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
rec = Recorder(sys.argv[1])
rec.WRITE_RETRY_S = 0.0
for i in range(100):
    rec.write(bytes.fromhex(sys.argv[2]), t=1.0 + i)
rec.close()
print(json.dumps(rec.stats()))
"""


def test_another_write_error_is_counted_as_such(tmp_path: Path) -> None:
    # a file-size limit: the kernel refuses with EFBIG, a write error that is not a full disk
    path = tmp_path / "limited.aur"
    fr = big_frame(1)
    r = subprocess.run([sys.executable, "-c", _LIMITED_WRITER, str(path), fr.hex()],
                       capture_output=True, text=True, timeout=TIMEOUT_S, check=False)
    assert r.returncode == 0, r.stderr
    st = json.loads(r.stdout)
    kept = list(recording.read(path))
    assert 0 < len(kept) < 100 and path.stat().st_size <= 4096
    assert st["records"] == len(kept)
    assert (st["dropped_write_error"], st["dropped_disk_full"]) == (100 - len(kept), 0)
    assert os.strerror(errno.EFBIG) in r.stderr


# -- the command line ---------------------------------------------------------------------------

_STOPPED = re.compile(r"stopped after [\d.]+ s: (\d+) messages in .*; (\d+) messages recorded")


def _report_counts(stderr: str) -> tuple[int, int, dict[str, int]]:
    """(messages in, messages recorded, the recorder's drops) from a stop report."""
    (m,) = [m for ln in stderr.splitlines() if (m := _STOPPED.match(ln))]
    (dropped,) = [ln for ln in stderr.splitlines() if ln.startswith("dropped: ")]
    drops = {k: int(v) for k, v in re.findall(r"\bdropped_(\w+)=(\d+)", dropped.split(";")[0])}
    return int(m.group(1)), int(m.group(2)), drops


def test_run_record_dir_on_a_full_disk_leaves_no_file_and_reports_the_frames_not_written(
        small_fs: Path) -> None:
    fill(small_fs)
    d = small_fs / "flights"
    r = subprocess.run([str(CONSOLE_SCRIPT), "run", "--source", "sim", "--sim-speed", "0",
                        "--duration", "2", "--record-dir", str(d), "--only", "console",
                        "--console-interval", "100", "--status-interval", "0.5"],
                       capture_output=True, text=True, timeout=TIMEOUT_S, cwd=small_fs.parent)
    assert r.returncode == 0, r.stderr  # the run worked; the recording is what failed
    assert list(d.iterdir()) == []  # no empty file, for any of the flights
    ins, recorded, drops = _report_counts(r.stderr)
    assert ins > 0 and recorded == 0 and drops["disk_full"] > 0
    assert recorded + sum(drops.values()) == ins  # every message: written or counted
    assert "dropped: nothing" not in r.stderr
    status = [ln for ln in r.stderr.splitlines() if " | rec " in ln]
    assert status and all("disk-full" in ln for ln in status[1:]), status
    assert len([ln for ln in r.stderr.splitlines() if "cannot write" in ln]) == 1


def test_run_record_resumes_into_a_file_export_reads_whole(small_fs: Path) -> None:
    filler = fill(small_fs)
    path = small_fs / "flight.aur"
    proc = subprocess.Popen([str(CONSOLE_SCRIPT), "run", "--source", "sim", "--sim-speed", "20",
                             "--duration", "6", "--record", str(path), "--only", "console",
                             "--console-interval", "100", "--status-interval", "0"],
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
                            cwd=small_fs.parent)
    lines: list[str] = []
    failing, resumed = threading.Event(), threading.Event()

    def read() -> None:
        assert proc.stderr is not None
        for ln in proc.stderr:
            lines.append(ln.rstrip("\n"))
            if "cannot write" in ln:
                failing.set()
            if "writing again" in ln:
                resumed.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert failing.wait(TIMEOUT_S), lines
        assert not path.exists()
        filler.unlink()
        assert resumed.wait(TIMEOUT_S), lines
        assert proc.wait(TIMEOUT_S) == 0, lines
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(TIMEOUT_S)
    stderr = "\n".join(lines)
    ins, recorded, drops = _report_counts(stderr)
    assert drops["disk_full"] > 0 and recorded > 0
    assert recorded + sum(drops.values()) == ins
    stats = recording.ReadStats()
    assert len(list(recording.read_records(path, stats))) == recorded
    assert (stats.torn_tail_bytes, stats.corrupt_skips) == (0, 0)
    out = small_fs.parent / "flight.csv"
    e = subprocess.run([str(CONSOLE_SCRIPT), "export", str(path), "-o", str(out)],
                       capture_output=True, text=True, timeout=TIMEOUT_S, check=False)
    assert e.returncode == 0, e.stderr
    assert len(out.read_text().splitlines()) > 1
