"""Recordings of several vehicles (issue 22): the version 2 format's name table (its
documented layout, its repeat after damage, records of unknown types, append), one file per
vehicle per flight in ``record_dir``, replay giving each recorded vehicle back under its
name, and decode / export / MCAP / plot per vehicle; version 1 files still read.

The two-vehicle recordings are written by a running gateway fed by two sources (rocket
"alpha" near 100 m, "beta" near 500 m) and read back with the real reader and the real
commands; expected values come from what the sources sent."""

from __future__ import annotations

import csv
import io
import json
import logging
import struct
import threading
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest
from helpers import wait_for
from test_recording import DOC_HEADER, doc_name, doc_record, doc_record_v1, tframe

from dialects.states import SM_TYPE_SIMPLE, SimpleState
from gateway import config, recording
from gateway.app import Gateway
from gateway.backend import Backend, Routes
from gateway.commands.cli import main
from gateway.flight_summary import FlightSummary, summary_lines
from gateway.model import SmUpdate, Status
from gateway.recorder import DirectoryRecorder, Recorder
from gateway.recording import RecordingError
from gateway.sources import Source
from gateway.wire import decode_all, encode

T0 = 1_790_000_000.0
BASE = {"alpha": 100.0, "beta": 500.0}  # each rocket's altitude, m (plus up to 9 m)
HEALTH = {"alpha": 0x02, "beta": 0x04}  # each rocket's STATUS flags: IMU ok / baro ok only


# -- the format ------------------------------------------------------------------------------

def test_names_are_bound_once_before_first_use_as_documented(tmp_path: Path) -> None:
    path = tmp_path / "names.aur"
    f1, f2, f3 = tframe(1), tframe(2), tframe(3)
    rec = Recorder(path)
    rec.write(f1, t=10.0, vehicle="alpha", source="alpha")  # one name serves both
    rec.write(f2, t=11.0, vehicle="beta", source="serial-b")
    rec.write(f3, t=12.0, vehicle="alpha", source="alpha")  # bound already
    rec.write(f1, t=13.0)  # no names
    rec.close()
    assert path.read_bytes() == (
        DOC_HEADER + doc_name(10.0, 0, "alpha") + doc_record(10.0, f1, 0, 0)
        + doc_name(11.0, 1, "beta") + doc_name(11.0, 2, "serial-b")
        + doc_record(11.0, f2, 1, 2) + doc_record(12.0, f3, 0, 0)
        + doc_record(13.0, f1))
    got = list(recording.read_records(path))
    assert got == [recording.Record(10.0, f1, "alpha", "alpha"),
                   recording.Record(11.0, f2, "beta", "serial-b"),
                   recording.Record(12.0, f3, "alpha", "alpha"),
                   recording.Record(13.0, f1, "", "")]
    assert rec.records == 4  # frames; the name records are not counted as records
    # the frame-only reader of version 1 times still gives every frame
    assert list(recording.read(path)) == [(10.0, f1), (11.0, f2), (12.0, f3), (13.0, f1)]


def test_a_damaged_name_record_costs_at_most_the_frames_until_its_repeat(
        tmp_path: Path) -> None:
    path = tmp_path / "repeat.aur"
    n = 2 * recording.NAME_REPEAT + 500
    rec = Recorder(path)
    for i in range(n):
        rec.write(tframe(i), t=float(i), vehicle="alpha", source="src")
    rec.close()
    data = bytearray(path.read_bytes())
    first_name = len(DOC_HEADER)
    assert data[first_name] == 2  # a name record opens the file
    data[first_name + 14] ^= 0xFF  # inside "alpha": its CRC fails, the binding is lost
    path.write_bytes(bytes(data))
    stats = recording.ReadStats()
    got = list(recording.read_records(path, stats))
    assert [r.frame for r in got] == [tframe(i) for i in range(n)]  # no frame lost
    named = [r.vehicle == "alpha" for r in got]
    first = named.index(True)
    assert 0 < first <= recording.NAME_REPEAT
    assert not any(named[:first]) and all(named[first:])
    assert stats.unnamed == first and stats.corrupt_skips == 1
    assert all(r.source == "src" for r in got[first:])


def test_records_of_an_unknown_type_are_skipped_and_counted(tmp_path: Path) -> None:
    def unknown(rtype: int, body: bytes) -> bytes:
        head = bytes([rtype]) + struct.pack("<dH", 5.0, len(body)) + body
        import zlib
        return head + struct.pack("<I", zlib.crc32(head))

    path = tmp_path / "future.aur"
    path.write_bytes(DOC_HEADER + doc_name(1.0, 0, "alpha") + unknown(0x30, b"x" * 300)
                     + doc_record(2.0, tframe(1), 0, 0xFFFF) + unknown(0x31, b"")
                     + doc_record(3.0, tframe(2), 0, 0xFFFF))
    stats = recording.ReadStats()
    got = list(recording.read_records(path, stats))
    assert got == [recording.Record(2.0, tframe(1), "alpha", ""),
                   recording.Record(3.0, tframe(2), "alpha", "")]
    assert (stats.unknown_records, stats.corrupt_skips, stats.torn_tail_bytes) == (2, 0, 0)


def test_appending_continues_the_files_name_table(tmp_path: Path) -> None:
    path = tmp_path / "append.aur"
    rec = Recorder(path)
    rec.write(tframe(1), t=1.0, vehicle="alpha")
    rec.write(tframe(2), t=2.0, vehicle="beta")
    rec.close()
    rec = Recorder(path)
    rec.write(tframe(3), t=3.0, vehicle="beta")
    rec.write(tframe(4), t=4.0, vehicle="gamma")
    rec.close()
    assert [(r.t, r.vehicle) for r in recording.read_records(path)] == [
        (1.0, "alpha"), (2.0, "beta"), (3.0, "beta"), (4.0, "gamma")]
    # every index is bound to one name in the whole file
    bindings: dict[int, set[str]] = defaultdict(set)
    data = path.read_bytes()
    pos = len(DOC_HEADER)
    while pos < len(data):
        rtype, _, length = struct.unpack_from("<BdH", data, pos)
        body = data[pos + 11:pos + 11 + length]
        if rtype == 2:
            bindings[struct.unpack_from("<H", body)[0]].add(body[2:].decode())
        pos += 11 + length + 4
    assert dict(bindings) == {0: {"alpha"}, 1: {"beta"}, 2: {"gamma"}}


def test_version_1_reads_but_is_not_appended_to(tmp_path: Path) -> None:
    path = tmp_path / "2026-04-26T10-00-00-rocket1.aur"
    v1 = (recording.HEADER_V1 + doc_record_v1(1.0, tframe(1)) + doc_record_v1(2.0, tframe(2)))
    path.write_bytes(v1)
    assert list(recording.read_records(path)) == [recording.Record(1.0, tframe(1)),
                                                   recording.Record(2.0, tframe(2))]
    with pytest.raises(RecordingError, match="version 1"):
        Recorder(path)
    assert path.read_bytes() == v1
    assert recording.file_vehicle(path) == "rocket1"
    assert recording.file_vehicle("flight.aur") == "flight"
    assert recording.file_vehicle("/x/2026-04-26T10-00-00-replay_a.aur") == "replay_a"
    assert recording.file_vehicle("42.aur") == "recording"


def test_a_version_1_recording_exports_and_decodes_under_its_files_vehicle(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "2026-04-26T10-00-00-rocket1.aur"
    ups = [SmUpdate(i, 0, False, 0, 10.0 + i, 0, 0, 0, 0, 0, 0) for i in range(5)]
    path.write_bytes(recording.HEADER_V1 + b"".join(doc_record_v1(T0 + i, encode(u))
                                                    for i, u in enumerate(ups)))
    assert main(["export", str(path)]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [(r["vehicle"], float(r["altitude_m"])) for r in rows] == [
        ("rocket1", 10.0 + i) for i in range(5)]
    assert main(["decode", str(path), "--vehicle", "rocket1"]) == 0
    objs = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert [(o["vehicle"], o["source"], o["altitude"]) for o in objs] == [
        ("rocket1", "", 10.0 + i) for i in range(5)]


# -- a gateway recording two rockets ------------------------------------------------------------

class Rocket(Source):
    """A rocket's receiver: wire frames (SM_UPDATE at its altitude, a STATUS every tenth) as
    a serial source would decode them, raw frame included."""

    NAME = "rocket"

    def __init__(self, name: str, updates: int = 60) -> None:
        super().__init__(name)
        self.vehicle = name
        self.updates = updates

    def run(self, stop: threading.Event) -> None:
        base = BASE[self.vehicle]
        for i in range(self.updates):
            frames = [encode(SmUpdate(1000 + 100 * i, int(SimpleState.BOOST), True,
                                      SM_TYPE_SIMPLE, base + i % 10, 1.0, 2.0, 3.0, 0.1, 0.2,
                                      0.3))]
            if i % 10 == 0:
                frames.append(encode(Status(1000 + 100 * i, int(SimpleState.BOOST),
                                            SM_TYPE_SIMPLE, HEALTH[self.vehicle])))
            for frame in frames:
                (msg,) = decode_all(frame)
                self.emit(msg._replace(origin=self.name, vehicle=self.vehicle))


class Seen(Backend):
    """Keeps every SM_UPDATE the dispatcher hands it."""

    def __init__(self) -> None:
        super().__init__("seen")
        self.updates: list[SmUpdate] = []
        self._lock = threading.Lock()

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self._update)

    def _update(self, msg: SmUpdate) -> None:
        with self._lock:
            self.updates.append(msg)


def _run(cfg: dict[str, Any], sources: list[Source] | None = None,
         backend: Backend | None = None) -> tuple[Gateway, dict[str, Any]]:
    gw = Gateway(config.parse({"gateway": {"status_interval_s": 0}, **cfg}),
                 status_out=io.StringIO())
    if sources is not None:
        gw.sources = sources
    if backend is not None:
        gw.dispatcher.add(backend)
    gw.start()
    try:
        assert all(s.done.wait(10) for s in gw.sources)
        if isinstance(backend, Seen):  # every replayed update reached the backend
            assert wait_for(lambda: len(backend.updates) >= 120)
    finally:
        summary = gw.stop()
    return gw, summary


@pytest.fixture(scope="module")
def two(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recording of alpha and beta, written by a gateway's ``record``."""
    path = tmp_path_factory.mktemp("two") / "two.aur"
    _, summary = _run({"gateway": {"record": str(path), "status_interval_s": 0}},
                      [Rocket("alpha"), Rocket("beta")])
    assert summary["recorded"] == 2 * (60 + 6)
    assert summary["recordings"] == [str(path)]
    return path


def test_one_file_holds_both_vehicles_with_their_own_frames(two: Path) -> None:
    by_vehicle: dict[str, list[Any]] = defaultdict(list)
    for rec in recording.read_records(two):
        assert rec.source == rec.vehicle
        by_vehicle[rec.vehicle] += decode_all(rec.frame)
    assert set(by_vehicle) == {"alpha", "beta"}
    for name, msgs in by_vehicle.items():
        alts = [m.altitude_m for m in msgs if isinstance(m, SmUpdate)]
        assert alts == [BASE[name] + i % 10 for i in range(60)], name
        assert {m.flags for m in msgs if isinstance(m, Status)} == {HEALTH[name]}


def test_decode_prints_each_frames_vehicle_and_keeps_one_on_request(
        two: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", str(two)]) == 0
    objs = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert len(objs) == 132
    for o in objs:
        if o["type"] == 1:
            assert BASE[o["vehicle"]] <= o["altitude"] < BASE[o["vehicle"]] + 10
    assert main(["decode", str(two), "--vehicle", "beta"]) == 0
    objs = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert len(objs) == 66 and {o["vehicle"] for o in objs} == {"beta"}
    assert main(["decode", str(two), "--vehicle", "gamma"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1
    assert "--vehicle" in err and "alpha, beta" in err


def test_export_has_a_vehicle_column_with_each_vehicles_values_and_health(
        two: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["export", str(two)]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert len(rows) == 120
    for name in BASE:
        mine = [r for r in rows if r["vehicle"] == name]
        assert [float(r["altitude_m"]) for r in mine] == [BASE[name] + i % 10
                                                          for i in range(60)]
        # health flags from the vehicle's own STATUS only (none before its first one)
        assert (mine[0]["imu_ok"], mine[0]["baro_ok"]) == ("", "")
        flags = {(r["imu_ok"], r["baro_ok"]) for r in mine[1:]}
        assert flags == ({("1", "0")} if name == "alpha" else {("0", "1")}), name
    assert main(["export", str(two), "--vehicle", "alpha", "-f", "jsonl"]) == 0
    objs = [json.loads(ln) for ln in capsys.readouterr().out.splitlines()]
    assert len(objs) == 60 and {o["vehicle"] for o in objs} == {"alpha"}
    assert main(["export", str(two), "--vehicle", "nope"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1
    assert "--vehicle" in err and "'nope'" in err and "alpha, beta" in err


def test_mcap_puts_each_vehicle_on_its_own_topics(two: Path, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    out = tmp_path / "two.mcap"
    assert main(["export", str(two), "-o", str(out)]) == 0
    alts: dict[str, list[float]] = defaultdict(list)
    frames: dict[str, set[str]] = defaultdict(set)
    topics = set()
    with out.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            topics.add(channel.topic)
            if channel.topic.endswith("/altitude"):
                alts[channel.topic].append(json.loads(message.data)["altitude_m"])
            if channel.topic.endswith("/attitude"):
                frames[channel.topic].add(json.loads(message.data)["child_frame_id"])
    assert {"/aurora/alpha/state", "/aurora/beta/state", "/aurora/alpha/status",
            "/aurora/beta/attitude", "/aurora/link_events"} <= topics
    assert not {"/aurora/state", "/aurora/altitude"} & topics
    for name in BASE:
        assert alts[f"/aurora/{name}/altitude"] == [BASE[name] + i % 10 for i in range(60)]
        assert frames[f"/aurora/{name}/attitude"] == {name}  # a frame per vehicle


def test_plot_draws_a_labelled_series_per_vehicle(two: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "two.png"
    assert main(["plot", str(two), "-o", str(out), "--all"]) == 0
    err = capsys.readouterr().err
    assert "2 vehicles (alpha, beta)" in err
    assert "alpha apogee 109.0 m" in err and "beta apogee 509.0 m" in err
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["plot", str(two), "-o", str(out), "--vehicle", "beta", "--all"]) == 0
    assert "of beta" in capsys.readouterr().err
    assert main(["plot", str(two), "-o", str(out), "--vehicle", "zeta"]) == 2
    assert "alpha, beta" in capsys.readouterr().err


def test_replay_gives_each_recorded_vehicle_back_under_its_name(two: Path) -> None:
    seen = Seen()
    _, summary = _run({"sources": [{"type": "replay", "path": str(two), "speed": 0}]},
                      backend=seen)
    got: dict[str, list[float]] = defaultdict(list)
    for m in seen.updates:
        got[m.vehicle].append(m.altitude_m)
    assert {k: sorted(v) for k, v in got.items()} == {
        name: sorted(BASE[name] + i % 10 for i in range(60)) for name in BASE}
    assert set(summary["flights"]) == {"alpha", "beta"}
    assert summary["flights"]["beta"]["max_altitude_m"] == 509.0
    assert [st["vehicles"] for st in summary["sources"].values()] == [2]


def test_a_version_1_recording_replays_as_the_replay_sources_vehicle(tmp_path: Path) -> None:
    path = tmp_path / "old.aur"
    frames = [encode(SmUpdate(i, 0, False, 0, 42.0 + i, 0, 0, 0, 0, 0, 0)) for i in range(120)]
    path.write_bytes(recording.HEADER_V1 + b"".join(doc_record_v1(T0 + i, f)
                                                    for i, f in enumerate(frames)))
    seen = Seen()
    _run({"sources": [{"type": "replay", "path": str(path), "speed": 0,
                       "vehicle": "veteran"}]}, backend=seen)
    assert {m.vehicle for m in seen.updates} == {"veteran"}
    assert [m.altitude_m for m in seen.updates] == [42.0 + i for i in range(120)]


# -- record_dir: a file per vehicle per flight ----------------------------------------------------

def _update(vehicle: str, state: SimpleState, t_ms: int, alt: float) -> SmUpdate:
    armed = SimpleState.ARMED <= state <= SimpleState.LANDED
    return SmUpdate(t_ms, int(state), armed, SM_TYPE_SIMPLE, alt, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                    origin=vehicle, vehicle=vehicle)


def _flight(vehicle: str, t0_ms: int, top: float) -> list[SmUpdate]:
    return [_update(vehicle, SimpleState.IDLE, t0_ms, 0.0),
            _update(vehicle, SimpleState.ARMED, t0_ms + 100, 0.0),
            _update(vehicle, SimpleState.BOOST, t0_ms + 200, top / 2),
            _update(vehicle, SimpleState.APOGEE, t0_ms + 300, top),
            _update(vehicle, SimpleState.LANDED, t0_ms + 400, 0.0),
            _update(vehicle, SimpleState.IDLE, t0_ms + 500, 0.0)]


def test_record_dir_rotates_only_the_file_of_the_vehicle_that_flies_again(
        tmp_path: Path) -> None:
    d = tmp_path / "flights"
    cfg = config.parse({"gateway": {"record_dir": str(d), "status_interval_s": 0}})
    gw = Gateway(cfg, status_out=io.StringIO())
    gw.start()
    a1, a2 = _flight("alpha", 0, 100.0), _flight("alpha", 10_000, 120.0)
    b1 = _flight("beta", 0, 500.0)
    beta_status = Status(50, 0, SM_TYPE_SIMPLE, 0x1E, origin="beta", vehicle="beta")
    try:
        # interleaved: beta's flight spans both of alpha's
        for msg in [*a1[:3], *b1[:3], *a1[3:], beta_status, *a2, *b1[3:]]:
            gw.ingest(msg)
    finally:
        summary = gw.stop()
    paths = [Path(p) for p in summary["recordings"]]
    assert sorted(p.name for p in d.iterdir()) == sorted(p.name for p in paths)
    names = [p.name for p in paths]
    assert len(names) == 3
    assert names[0].endswith("-alpha.aur") and names[1].endswith("-beta.aur")
    assert names[2].endswith(("-alpha.aur", "-alpha-2.aur"))  # alpha's second flight

    def content(p: Path) -> list[tuple[str, Any]]:
        return [(r.vehicle, m.fields()) for r in recording.read_records(p)
                for m in decode_all(r.frame)]

    assert content(paths[0]) == [("alpha", m.fields()) for m in a1 + a2[:1]]
    assert content(paths[1]) == [("beta", m.fields()) for m in [*b1[:3], beta_status, *b1[3:]]]
    assert content(paths[2]) == [("alpha", m.fields()) for m in a2[1:]]
    assert summary["recorded"] == len(a1) + len(a2) + len(b1) + 1


def test_record_dir_bounds_the_vehicles_it_opens_files_for(tmp_path: Path) -> None:
    rec = DirectoryRecorder(tmp_path / "many", max_vehicles=3)
    for i in range(5):
        rec.submit(_update(f"v{i}", SimpleState.IDLE, 0, 1.0), t=T0)
    rec.close(5.0)
    assert len(list((tmp_path / "many").iterdir())) == 3
    assert rec.stats()["dropped_vehicle_limit"] == 2
    # a vehicle flying again and again: at most max_files files, the rest in the last one
    rec = DirectoryRecorder(tmp_path / "often", max_files=3)
    for i in range(10):
        rec.submit(_update("alpha", SimpleState.ARMED, i, 1.0), t=T0 + i, new_flight=True)
    rec.close(5.0)
    assert len(rec.paths) == 3
    assert [len(list(recording.read_records(p))) for p in rec.paths] == [1, 1, 8]


def test_record_dir_tries_a_file_it_cannot_create_again_later_not_per_message(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    d = tmp_path / "flights"
    rec = DirectoryRecorder(d)
    rec.OPEN_RETRY_S = 0.2
    d.rmdir()
    d.write_bytes(b"")  # the directory is gone, a file in its place: no file can be made
    msg = _update("alpha", SimpleState.IDLE, 0, 1.0)
    try:
        with caplog.at_level(logging.ERROR, logger="gateway.recorder"):
            for _ in range(200):
                assert rec.submit(msg, t=T0)
            assert wait_for(lambda: rec.dropped_open_failed == 200)
        assert rec.open_errors == 1  # one attempt for 200 messages within the retry time
        assert len([r for r in caplog.records if "cannot open" in r.getMessage()]) == 1
        d.unlink()  # the disk is back
        assert wait_for(lambda: rec.submit(msg, t=T0) and rec.records > 0)
    finally:
        rec.close(5.0)
    (path,) = rec.paths
    assert path.parent == d and path.name.endswith("-alpha.aur")
    assert {r.vehicle for r in recording.read_records(path)} == {"alpha"}


# -- the stop report ----------------------------------------------------------------------------

def test_the_summary_lists_a_vehicle_heard_only_in_status() -> None:
    summary = FlightSummary()
    for m in _flight("alpha", 0, 100.0):
        summary.feed(m)
    summary.feed(Status(5, 0, SM_TYPE_SIMPLE, 0x1E, origin="beta", vehicle="beta"))
    flights = summary.as_dict()
    assert list(flights) == ["alpha", "beta"]
    assert flights["beta"]["updates"] == 0 and flights["beta"]["max_altitude_m"] is None
    lines = summary_lines(flights)
    assert lines[1].startswith("flight beta: 0 launches, no altitude, 0 updates")
