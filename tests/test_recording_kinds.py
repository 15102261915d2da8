"""A recording holds every message kind (issue 24): the message records' documented layout,
every kind recorded by the recorder and read back equal (NaN and unknown fields included),
readers of frames only passing them over, malformed bodies skipped and counted; and the
recordings of the previous release (tests/data, written by main's recorder before the
change: tests/data/make_fixtures.py) reading as they did."""

from __future__ import annotations

import csv
import io
import json
import math
import re
import signal
import socket
import struct
import subprocess
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import pytest
from helpers import GATEWAY, ROOT, Running, wait_for
from test_recording import DOC_HEADER, doc_name, doc_record

from gateway import config, recording
from gateway.app import Gateway
from gateway.backend import Backend, Routes
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    RawFrame,
    RcChannels,
    SmUpdate,
    Status,
    VehicleState,
)
from gateway.recorder import Recorder
from gateway.wire import decode_all, encode

DATA = Path(__file__).resolve().parent / "data"
T0 = 1_790_000_000.0

#: one message of every kind recorded as its fields, as a MAVLink source makes them
KINDS = [
    Position(47.397742, 8.545594, 488.123, 12.5, 3.25, 271.5, 11, 3, origin="mav",
             vehicle="drone"),
    Battery(12.587, 1.25, 350.0, 87, 0, origin="mav", vehicle="drone"),
    VehicleState(True, "GUIDED", 4, 0.125, -0.25, math.nan, 12.0, None, origin="mav",
                 vehicle="drone"),
    RcChannels((1500, None, 2000, 988), 7, origin="crsf", vehicle="drone"),
    LinkStats(rssi_dbm=-61.0, link_quality_pct=99, snr_db=8.5, origin="crsf", vehicle="drone"),
    LinkEvent("mav", False, 3.0, vehicle="drone"),
]


def doc_message(rtype: int, t: float, fields: dict, vehicle: int = 0xFFFF,
                source: int = 0xFFFF) -> bytes:
    """A message record exactly as documented: type, f64 time, u16 body length, u16 vehicle
    and source indexes, the fields as one JSON object, CRC-32 over all before."""
    body = struct.pack("<HH", vehicle, source) + json.dumps(fields, separators=(",", ":")).encode()
    head = bytes([rtype]) + struct.pack("<dH", t, len(body)) + body
    return head + struct.pack("<I", zlib.crc32(head))


def same(a: object, b: object) -> bool:
    """Equal, NaN equal to NaN (a recorded NaN reads back as NaN)."""
    return repr(a) == repr(b)


def test_every_kind_is_recorded_and_reads_back_equal(tmp_path: Path) -> None:
    path = tmp_path / "kinds.aur"
    frame = encode(SmUpdate(1000, 2, True, 0, 10.0, 9.8, 9.7, 1.0, 0.0, 0.0, 0.0))
    rec = Recorder(path)
    for i, msg in enumerate([*KINDS, frame]):
        assert rec.submit(msg, t=T0 + i)
    rec.close()
    assert rec.not_recordable == {}
    stats = recording.ReadStats()
    got = list(recording.read_records(path, stats, messages=True))
    assert [r.t for r in got] == [T0 + i for i in range(len(KINDS) + 1)]
    for r, sent in zip(got, KINDS, strict=False):
        assert isinstance(r, recording.MessageRecord)
        assert (r.vehicle, r.source) == (sent.vehicle, sent.origin)
        assert same(r.message, sent), (r.message, sent)
    assert got[-1] == recording.Record(T0 + len(KINDS), frame)
    assert (stats.records, stats.messages, stats.bad_messages) == (1, len(KINDS), 0)


def test_message_records_have_the_documented_layout(tmp_path: Path) -> None:
    path = tmp_path / "layout.aur"
    pos = KINDS[0]
    rec = Recorder(path)
    rec.write(encode(Status(5, 1, 0, 3)), t=T0, vehicle="drone", source="mav")
    rec.close()
    # a position after the frame, by the queue (names already bound)
    rec = Recorder(path)
    rec.submit(pos, t=T0 + 1)
    rec.close()
    data = path.read_bytes()
    frame = encode(Status(5, 1, 0, 3))
    fields = {"lat_deg": 47.397742, "lon_deg": 8.545594, "alt_amsl_m": 488.123,
              "relative_alt_m": 12.5, "ground_speed_mps": 3.25, "course_deg": 271.5,
              "satellites": 11, "fix_type": 3}
    prefix = DOC_HEADER + doc_name(T0, 0, "drone") + doc_name(T0, 1, "mav") + \
        doc_record(T0, frame, 0, 1)
    assert data.startswith(prefix)
    rest = data[len(prefix):]
    # appending binds the names again (a new writer), then the position, type 3
    assert rest == doc_name(T0 + 1, 0, "drone") + doc_name(T0 + 1, 1, "mav") + \
        doc_message(3, T0 + 1, fields, 0, 1)


def test_a_hand_made_record_of_each_type_reads_as_its_kind(tmp_path: Path) -> None:
    """The documented type numbers, written from the docstring, not by the writer; a field
    a later version adds is ignored, one left out takes its default."""
    path = tmp_path / "hand.aur"
    bodies = [
        (3, {"lat_deg": 1.5, "lon_deg": -2, "future_field": [1, 2]}),
        (4, {"voltage_v": 11.1, "remaining_pct": 40}),
        (5, {"armed": False, "mode": "LOITER", "custom_mode": 5}),
        (6, {"channels_us": [1000, None]}),
        (7, {"rssi_dbm": -90}),
        (8, {"source": "s", "up": True}),
    ]
    path.write_bytes(DOC_HEADER + doc_name(T0, 0, "copter") + b"".join(
        doc_message(rt, T0 + i, body, 0) for i, (rt, body) in enumerate(bodies)))
    got = [r.message for r in recording.read_records(path, messages=True)]
    assert got == [
        Position(1.5, -2.0, vehicle="copter"), Battery(11.1, remaining_pct=40, vehicle="copter"),
        VehicleState(False, "LOITER", 5, vehicle="copter"),
        RcChannels((1000, None), vehicle="copter"), LinkStats(-90.0, vehicle="copter"),
        LinkEvent("s", True, vehicle="copter")]
    assert type(got[1].voltage_v) is float and type(got[4].rssi_dbm) is float


def test_malformed_message_bodies_are_skipped_and_counted(tmp_path: Path) -> None:
    path = tmp_path / "bad.aur"
    good = doc_message(4, T0 + 9, {"voltage_v": 12.0})
    raw_bad = struct.pack("<HH", 0xFFFF, 0xFFFF) + b"{not json"
    head = bytes([3]) + struct.pack("<dH", T0, len(raw_bad)) + raw_bad
    path.write_bytes(DOC_HEADER + head + struct.pack("<I", zlib.crc32(head))
                     + doc_message(3, T0, [1, 2])  # not an object
                     + doc_message(3, T0, {"lon_deg": 1.0})  # lat_deg missing
                     + doc_message(4, T0, {"voltage_v": "12 V"})  # a string for a float
                     + doc_message(5, T0, {"armed": 1, "mode": "X"})  # an int for a bool
                     + doc_message(6, T0, {"channels_us": [1500.5]})
                     + good)
    stats = recording.ReadStats()
    got = list(recording.read_records(path, stats, messages=True))
    assert [r.message for r in got] == [Battery(12.0)]
    assert (stats.messages, stats.bad_messages, stats.corrupt_skips) == (7, 6, 0)


def test_readers_of_frames_only_pass_message_records_over(tmp_path: Path) -> None:
    path = tmp_path / "mixed.aur"
    frame = encode(Status(5, 1, 0, 3))
    rec = Recorder(path)
    rec.submit(KINDS[0], t=T0)
    rec.submit(frame, t=T0 + 1)
    rec.submit(KINDS[1], t=T0 + 2)
    rec.close()
    stats = recording.ReadStats()
    assert list(recording.read(path, stats)) == [(T0 + 1, frame)]
    assert (stats.records, stats.messages, stats.unknown_records) == (1, 2, 0)


# -- the previous release's recordings -------------------------------------------------------

def test_the_previous_releases_recordings_read_as_they_did() -> None:
    """flight-v1.aur (version 1) and flight-v2.aur (version 2 before issue 24: frames of
    alpha, and of beta every other one): every frame reads, names as written."""
    v1 = list(recording.read_records(DATA / "flight-v1.aur", messages=True))
    v2 = list(recording.read_records(DATA / "flight-v2.aur", messages=True))
    assert len(v1) == 102 and len(v2) == 102 + 51
    assert all(isinstance(r, recording.Record) and r.vehicle == "" for r in v1)
    alpha = [r for r in v2 if r.vehicle == "alpha"]
    beta = [r for r in v2 if r.vehicle == "beta"]
    assert [r.frame for r in alpha] == [r.frame for r in v1]
    assert [r.t for r in alpha] == [r.t for r in v1]
    assert [r.frame for r in beta] == [r.frame for r in v1][::2]
    assert {r.source for r in beta} == {"serial-b"}
    msgs = [m for r in v1 for m in decode_all(r.frame)]  # type: ignore[union-attr]
    assert {type(m) for m in msgs} == {SmUpdate, Status}


# -- done when: a MAVLink vehicle's flight recorded and exported ---------------------------------

def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_mavlink_vehicles_positions_batteries_and_states_are_recorded_and_exported(
        tmp_path: Path) -> None:
    """``record --source mavlink:udpin:…`` while a pymavlink vehicle sends HEARTBEAT,
    GLOBAL_POSITION_INT, ATTITUDE, SYS_STATUS and BATTERY_STATUS: ``export --format csv``
    of the recording shows the positions, batteries and vehicle states that were sent, each
    row's values those of a message sent (every message sent carries values of its own)."""
    from mavlink_peer import MavPeer, upstream_dialect

    dev = upstream_dialect()
    port = _free_udp_port()
    out = tmp_path / "drone.aur"
    p = Running("record", str(out), "--source", f"mavlink:udpin:127.0.0.1:{port}",
                "--status-interval", "0.1", "--duration", "60")
    veh = MavPeer(1, 1, dest=("127.0.0.1", port))
    armed = dev.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | dev.MAV_MODE_FLAG_SAFETY_ARMED
    positions: dict[int, tuple[float, ...]] = {}  # lat e7 -> (lat, lon, alt, rel alt)
    attitudes: set[tuple[float, float]] = set()
    volts: set[float] = set()

    def recorded(ln: str) -> bool:
        m = re.search(r"\| rec (\d+)$", ln)
        return m is not None and int(m.group(1)) >= 40

    try:
        deadline = time.monotonic() + 30
        k = 0
        while not p.wait_line("stderr", recorded, 0.05):
            assert time.monotonic() < deadline, p.text("stderr")[-2000:]
            k += 1
            veh.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_QUADROTOR,
                                                   dev.MAV_AUTOPILOT_ARDUPILOTMEGA, armed, 4,
                                                   dev.MAV_STATE_ACTIVE, 3))
            roll, pitch = 0.001 * k, -0.002 * k  # f32 on the wire: kept as sent below
            veh.send(dev.MAVLink_attitude_message(k, roll, pitch, 1.5, 0, 0, 0))
            attitudes.add((struct.unpack("<f", struct.pack("<f", roll))[0],
                           struct.unpack("<f", struct.pack("<f", pitch))[0]))
            lat, lon = 473977420 + 10 * k, 85455940 - 10 * k
            veh.send(dev.MAVLink_global_position_int_message(
                k, lat, lon, 500000 + k, 20000 + k, 300, -400, -250, 9000))
            positions[lat] = (lat / 1e7, lon / 1e7, (500000 + k) / 1000, (20000 + k) / 1000)
            veh.send(dev.MAVLink_sys_status_message(0, 0, 0, 0, 11000 + k, 1500, 80, 0, 0, 0,
                                                    0, 0, 0))
            volts.add(round((11000 + k) / 1000, 6))
            veh.send(dev.MAVLink_battery_status_message(
                0, 0, 0, 0x7FFF, [4100 + k] * 3 + [0xFFFF] * 7, 1530, 420, -1, 76))
            volts.add(round(3 * (4100 + k) / 1000, 6))
        p.proc.send_signal(signal.SIGINT)
        assert p.finish(10) == 130, p.text("stderr")[-2000:]
    finally:
        veh.close()
        p.kill()
    assert "not recorded" not in p.text("stderr")
    done = subprocess.run([*GATEWAY, "export", str(out), "--format", "csv"], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    rows = list(csv.DictReader(io.StringIO(done.stdout)))
    by_kind: dict[str, list[dict[str, str]]] = {}
    for row in rows:
        by_kind.setdefault(row["kind"], []).append(row)
    assert {"position", "battery", "vehicle_state"} <= set(by_kind), done.stdout[:500]
    for row in by_kind["position"]:
        lat, lon, alt, rel = positions[round(float(row["lat"]) * 1e7)]
        assert (float(row["lat"]), float(row["lon"])) == pytest.approx((lat, lon), abs=1e-9)
        assert (float(row["alt_amsl"]), float(row["relative_alt"])) == pytest.approx(
            (alt, rel))
        assert row["ground_speed"] and float(row["ground_speed"]) == pytest.approx(5.0)
    for row in by_kind["battery"]:
        assert round(float(row["voltage"]), 6) in volts, row
        # SYS_STATUS's (80 %, 15.0 A), BATTERY_STATUS's (76 %, 15.3 A)
        assert (row["remaining"], row["current"]) in {("80", "15.0"), ("76", "15.3")}, row
    for row in by_kind["vehicle_state"]:
        assert (row["armed"], row["mode"], row["custom_mode"]) == ("1", "GUIDED", "4")
        if row["roll_deg"]:
            got = (math.radians(float(row["roll_deg"])), math.radians(float(row["pitch_deg"])))
            assert any(got == pytest.approx(a, abs=1e-12) for a in attitudes), got
    assert any(r["roll_deg"] for r in by_kind["vehicle_state"])
    assert len({r["vehicle"] for r in rows}) == 1 and rows[0]["vehicle"]
    assert len(by_kind["position"]) >= 2 and len(by_kind["battery"]) >= 10
    assert f"position {len(by_kind['position'])}" in done.stderr


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*GATEWAY, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)


@pytest.mark.parametrize("name", ["flight-v1", "flight-v2"])
def test_the_previous_releases_recordings_export_and_decode_unchanged(
        name: str, tmp_path: Path) -> None:
    """``export`` (csv, jsonl) and ``decode`` of the previous release's recordings give
    byte for byte what the previous release gave (tests/data/<name>.csv, .jsonl,
    .decode.jsonl, written by main's code before issue 24)."""
    src = tmp_path / f"{name}.aur"  # (a version 1 file's vehicle is named after the file)
    src.write_bytes((DATA / f"{name}.aur").read_bytes())
    for fmt in ("csv", "jsonl"):
        out = tmp_path / f"out.{fmt}"
        done = _cli("export", str(src), "--format", fmt, "-o", str(out))
        assert done.returncode == 0, done.stderr
        assert out.read_text() == (DATA / f"{name}.{fmt}").read_text(), fmt
        assert "skipped" not in done.stderr
    done = _cli("decode", str(src))
    assert done.returncode == 0, done.stderr
    assert done.stdout == (DATA / f"{name}.decode.jsonl").read_text()


class Kept(Backend):
    """Keeps every message of the kinds a recording holds, as the dispatcher hands them."""

    KINDS = (SmUpdate, Status, Position, Battery, VehicleState, RcChannels, LinkStats)

    def __init__(self) -> None:
        super().__init__("kept")
        self.got: list[Any] = []
        self._lock = threading.Lock()

    def routes(self) -> Routes:
        r = Routes()
        for cls in self.KINDS:
            r = r.on(cls, self._keep)
        return r

    def _keep(self, msg: Any) -> None:
        with self._lock:
            self.got.append(msg)

    def count(self) -> int:
        with self._lock:
            return len(self.got)


def _replay(path: Path, expected: int, **opts: Any) -> tuple[list[Any], dict[str, Any]]:
    kept = Kept()
    gw = Gateway(config.parse({"gateway": {"status_interval_s": 0},
                               "sources": [{"type": "replay", "path": str(path), "speed": 0,
                                            **opts}]}), status_out=io.StringIO())
    gw.dispatcher.add(kept)
    gw.start()
    try:
        assert all(s.done.wait(10) for s in gw.sources)
        assert wait_for(lambda: kept.count() >= expected)
    finally:
        summary = gw.stop()
    return kept.got, summary


def test_the_previous_releases_v2_recording_replays_unchanged() -> None:
    """Every frame of flight-v2.aur replays as the message it decodes to, under its
    recorded vehicle, in order."""
    recs = list(recording.read_records(DATA / "flight-v2.aur"))
    want = [(r.vehicle, m.fields()) for r in recs for m in decode_all(r.frame)]  # type: ignore[union-attr]
    got, _ = _replay(DATA / "flight-v2.aur", len(want))
    assert [(m.vehicle, m.fields()) for m in got] == want


def test_the_previous_releases_v1_recording_replays_as_the_sources_vehicle() -> None:
    recs = list(recording.read_records(DATA / "flight-v1.aur"))
    want = [m.fields() for r in recs for m in decode_all(r.frame)]  # type: ignore[union-attr]
    got, _ = _replay(DATA / "flight-v1.aur", len(want), vehicle="veteran")
    assert [m.fields() for m in got] == want and {m.vehicle for m in got} == {"veteran"}


def test_every_kind_replays_as_itself_of_its_vehicle(tmp_path: Path) -> None:
    """A Position replays as a Position of its vehicle (and so every kind), from the replay
    source; recorded link events are left to the replaying gateway's own link monitor
    (counted)."""
    path = tmp_path / "kinds.aur"
    frame = encode(SmUpdate(1000, 2, True, 0, 10.0, 9.8, 9.7, 1.0, 0.0, 0.0, 0.0))
    rec = Recorder(path)
    for i, msg in enumerate([frame, *KINDS]):
        rec.submit(msg, t=T0 + i * 0.01)
    rec.close()
    got, summary = _replay(path, len(KINDS))
    assert [type(m) for m in got] == [SmUpdate, *[type(m) for m in KINDS[:-1]]]
    for m, sent in zip(got[1:], KINDS[:-1], strict=True):
        assert same(m.fields(), sent.fields()) and m.vehicle == "drone"
        assert m.origin == "replay:kinds.aur"
    (st,) = summary["sources"].values()
    assert st["messages"] == len(KINDS) and st["link_events_skipped"] == 1


def _recording_of_every_kind(path: Path) -> bytes:
    """A recording of an SM update, a raw frame of no known type, then every other kind."""
    frame = encode(SmUpdate(1000, 2, True, 0, 10.0, 9.8, 9.7, 1.0, 0.0, 0.0, 0.0))
    raw = encode(RawFrame(0x42, b"who knows"))
    rec = Recorder(path)
    rec.write(frame, t=T0, vehicle="drone", source="mav")
    rec.write(raw, t=T0 + 0.5, vehicle="drone", source="mav")
    rec.close()
    rec = Recorder(path)
    for i, msg in enumerate(KINDS):
        rec.submit(msg, t=T0 + 1 + i)
    rec.close()
    return frame


def test_mcap_has_a_channel_for_every_kind_and_counts_what_it_skips(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    src, out = tmp_path / "kinds.aur", tmp_path / "kinds.mcap"
    _recording_of_every_kind(src)
    done = _cli("export", str(src), "-o", str(out))
    assert done.returncode == 0, done.stderr
    assert "skipped (no channel): RawFrame 1" in done.stderr
    got: dict[str, list[dict[str, Any]]] = {}
    with out.open("rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            got.setdefault(channel.topic, []).append(json.loads(message.data))
            assert schema is not None
    pos, = got["/aurora/drone/position"]
    assert (pos["latitude"], pos["longitude"], pos["altitude"]) == (47.397742, 8.545594,
                                                                     488.123)
    assert got["/aurora/drone/battery"][0]["voltage_v"] == 12.587
    state, = got["/aurora/drone/vehicle"]
    assert (state["armed"], state["mode"], state["roll_rad"], state["yaw_rad"]) == (
        True, "GUIDED", 0.125, None)  # (NaN: null in JSON)
    assert len(got["/aurora/drone/attitude"]) == 2  # the SM update's and the state's
    assert got["/aurora/drone/rc"] == [{"channels_us": [1500, None, 2000, 988], "seq": 7}]
    assert got["/aurora/drone/link"][0]["rssi_dbm"] == -61.0
    assert {"source": "mav", "up": False, "silence_s": 3.0} in got["/aurora/link_events"]


def test_csv_and_jsonl_show_every_kind_and_count_raw_frames_skipped(tmp_path: Path) -> None:
    src = tmp_path / "kinds.aur"
    _recording_of_every_kind(src)
    done = _cli("export", str(src), "--format", "csv")
    assert done.returncode == 0, done.stderr
    assert "skipped 1 frames of no known type (raw)" in done.stderr
    rows = list(csv.DictReader(io.StringIO(done.stdout)))
    assert [r["kind"] for r in rows] == ["sm_update", "position", "battery", "vehicle_state",
                                         "rc_channels", "link_stats", "link"]
    sm, pos, bat, vs, rc, ls, link = rows
    assert (sm["altitude_m"], sm["state_name"], sm["lat"]) == ("10.0", "BOOST", "")
    assert (pos["lat"], pos["lon"], pos["alt_amsl"], pos["satellites"]) == (
        "47.397742", "8.545594", "488.123", "11")
    assert (bat["voltage"], bat["current"], bat["consumed"], bat["remaining"]) == (
        "12.587", "1.25", "350.0", "87")
    assert (vs["armed"], vs["mode"], vs["yaw_deg"], vs["climb"]) == ("1", "GUIDED", "nan", "")
    assert float(vs["roll_deg"]) == pytest.approx(math.degrees(0.125))
    assert (rc["channels"], rc["seq"], ls["rssi_dbm"]) == ("1500 - 2000 988", "7", "-61.0")
    assert (link["link_source"], link["up"], link["silence_s"]) == ("mav", "0", "3.0")
    assert {r["vehicle"] for r in rows} == {"drone"} and pos["source"] == "mav"
    done = _cli("export", str(src), "--format", "jsonl", "--kind", "position",
                "--kind", "battery")
    lines = [json.loads(ln) for ln in done.stdout.splitlines()]
    assert [ln["kind"] for ln in lines] == ["position", "battery"]
    assert lines[0]["lat"] == 47.397742 and "altitude_m" not in lines[0]
    assert lines[1]["voltage"] == 12.587 and lines[1]["lat"] is None
    done = _cli("export", str(src), "--format", "csv", "--kind", "rc_channels")
    assert done.stdout.splitlines()[0] == "t_s,rx_time,vehicle,kind,source,channels,seq"


def test_plot_draws_the_sm_updates_and_counts_the_kinds_it_cannot_show(
        tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    src, png = tmp_path / "kinds.aur", tmp_path / "kinds.png"
    _recording_of_every_kind(src)
    done = _cli("plot", str(src), "-o", str(png), "--all")
    assert done.returncode == 0, done.stderr
    assert png.stat().st_size > 0
    assert ("not drawn: position 1, battery 1, vehicle_state 1, rc_channels 1, link_stats 1, "
            "link 1, raw 1") in done.stderr
    # a recording of a MAVLink vehicle alone: nothing to draw, said with what it holds
    only = tmp_path / "drone.aur"
    rec = Recorder(only)
    rec.submit(KINDS[0], t=T0)
    rec.close()
    done = _cli("plot", str(only), "-o", str(png))
    assert done.returncode == 2
    assert "no SM updates to plot (not drawn: position 1)" in done.stderr
