"""``aurora-gateway export RECORDING -o FILE.mcap``:
a recording of the simulated flight is read back with the ``mcap`` library's own reader: the
channels and their JSON schemas, one message per SM update / STATUS with the decoded values,
receive times as log times, link up/down from the gaps; the attitude and position in
Foxglove's own JSON schemas; MCAP to stdout is refused."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys
from collections import defaultdict
from decimal import ROUND_HALF_EVEN, Decimal
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from gateway import recording
from gateway.commands.cli import main
from gateway.commands.export_mcap import McapExport
from gateway.flight import FlightModel, FlightProfile
from gateway.model import Battery, LinkStats, Position, RawFrame, SmUpdate, Status
from gateway.sources.sim import flight_messages
from gateway.wire import decode_all, encode

T0 = 1_790_000_000.123  # the recording's first receive time (Unix seconds)
GAP_AT = 20.0  # simulated time at which the link falls silent ...
GAP_S = 4.5  # ... for longer than the gateway's 3 s link timeout
LINK_TIMEOUT_S = 3.0  # README: "link-down silence (default 3 s)"
CONSOLE = Path(sys.executable).with_name("aurora-gateway")

# The channels, schema names and fields the export promises (its docstring; the live Foxglove
# backend's names; Foxglove's FrameTransform and LocationFix schemas), written out here.
CORE = {"/aurora/state", "/aurora/altitude", "/aurora/attitude", "/aurora/status",
        "/aurora/link_events"}
SCHEMA_NAMES = {"/aurora/state": "aurora.State", "/aurora/altitude": "aurora.Altitude",
                "/aurora/attitude": "foxglove.FrameTransform", "/aurora/status": "aurora.Status",
                "/aurora/link_events": "aurora.LinkEvent", "/aurora/link": "aurora.LinkStats",
                "/aurora/position": "foxglove.LocationFix", "/aurora/battery": "aurora.Battery"}
FIELDS = {
    "/aurora/state": {"state", "state_name", "armed", "sm_type", "timestamp_ms"},
    "/aurora/altitude": {"timestamp_ms", "altitude_m", "velocity_mps", "acceleration_mps2",
                         "accel_vert_mps2"},
    "/aurora/attitude": {"timestamp", "parent_frame_id", "child_frame_id", "translation",
                         "rotation"},
    "/aurora/status": {"state", "state_name", "sm_type", "flags", "armed", "imu_ok", "baro_ok",
                       "calibrated", "log_ready", "timestamp_ms"},
    "/aurora/link_events": {"source", "up", "silence_s"},
}
# STATUS flag bits (shared/specs/aurora-wire.md)
FLAG_BITS = {"armed": 0x01, "imu_ok": 0x02, "baro_ok": 0x04, "calibrated": 0x08,
             "log_ready": 0x10}


def _ns(t: float) -> int:
    """The float's exact value in ns, rounded half-even (independent of the product's way)."""
    return int((Decimal(t) * 10**9).to_integral_value(ROUND_HALF_EVEN))


def _write_recording(path: Path, revision: int = 64) -> list[tuple[float, Any]]:
    """A simulated flight with a silent stretch and one frame of an unknown type, as a
    recording; (receive time, decoded message) back."""
    decoded = []
    n = 0
    with path.open("wb") as f:
        f.write(recording.HEADER)
        msgs: list[tuple[float, Any]] = list(
            flight_messages(FlightModel(FlightProfile(revision=revision)), rate_hz=10.0,
                            status_hz=1.0, cycles=1))
        msgs.insert(5, (msgs[5][0], RawFrame(0x7E, b"\x01\x02")))
        for t, msg in msgs:
            if GAP_AT <= t < GAP_AT + GAP_S:
                continue
            if isinstance(msg, Status):  # every combination of the flags in turn
                msg = msg._replace(flags=n % 32)
                n += 1
            frame = encode(msg)
            f.write(recording.encode_record(T0 + t, frame))
            (back,) = decode_all(frame)
            decoded.append((T0 + t, back))
    return decoded


def _norm(topic: str, vehicle: str | None) -> str:
    """A vehicle's topic ``/aurora/<vehicle>/x`` as ``/aurora/x`` (the link events are on
    ``/aurora/link_events`` for all; any other topic is an error)."""
    if vehicle is None or topic == "/aurora/link_events":
        return topic
    prefix = f"/aurora/{vehicle}/"
    assert topic.startswith(prefix), topic
    return "/aurora/" + topic[len(prefix):]


def _read(path: Path, vehicle: str | None = None,
          ) -> tuple[Any, dict[str, list[tuple[Any, dict[str, Any]]]]]:
    """The file's summary, and per topic (message record, decoded JSON) in file order; with
    ``vehicle``, that vehicle's topics (every one but the link events') without it."""
    by_topic: dict[str, list[tuple[Any, dict[str, Any]]]] = defaultdict(list)
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            by_topic[_norm(channel.topic, vehicle)].append((message, json.loads(message.data)))
    return summary, by_topic


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[tuple[float, Any]], Path]:
    d = tmp_path_factory.mktemp("mcap")
    decoded = _write_recording(d / "flight.aur")
    out = d / "flight.mcap"
    assert main(["export", str(d / "flight.aur"), "-o", str(out)]) == 0  # .mcap picks MCAP
    return decoded, out


def _rotation_matrix(roll: float, pitch: float, yaw: float) -> list[list[float]]:
    """Rz(yaw) · Ry(pitch) · Rx(roll), built from the elementary rotations."""
    def mul(a: list[list[float]], b: list[list[float]]) -> list[list[float]]:
        return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch),
                              math.sin(pitch), math.cos(yaw), math.sin(yaw))
    rx = [[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]]
    ry = [[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]]
    rz = [[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]]
    return mul(rz, mul(ry, rx))


def _rotate(q: tuple[float, float, float, float], v: list[float]) -> list[float]:
    """v rotated by the unit quaternion q = (x, y, z, w): q v q*."""
    x, y, z, w = q
    def qmul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, ...]:
        ax, ay, az, aw = a
        bx, by, bz, bw = b
        return (aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
                aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz)
    r = qmul(qmul((x, y, z, w), (v[0], v[1], v[2], 0.0)), (-x, -y, -z, w))
    return list(r[:3])


def test_channels_and_their_json_schemas(exported: tuple[list[Any], Path]) -> None:
    _, out = exported
    summary, _ = _read(out, "flight")
    # a recording whose frames name no vehicle: named after the file, as the live backend
    # names a vehicle's topics
    assert {c.topic for c in summary.channels.values()} == {
        "/aurora/flight/state", "/aurora/flight/altitude", "/aurora/flight/attitude",
        "/aurora/flight/status", "/aurora/link_events"}
    channels = {_norm(c.topic, "flight"): c for c in summary.channels.values()}
    assert set(channels) == CORE  # no position or battery in a recording of the wire frames
    for topic, ch in channels.items():
        assert ch.message_encoding == "json"
        schema = summary.schemas[ch.schema_id]
        assert schema.encoding == "jsonschema"
        assert schema.name == SCHEMA_NAMES[topic]
        doc = json.loads(schema.data)
        assert doc["type"] == "object"
        assert set(doc["properties"]) == FIELDS[topic], topic


def test_one_message_per_update_and_status_with_the_decoded_values(
        exported: tuple[list[tuple[float, Any]], Path]) -> None:
    decoded, out = exported
    summary, got = _read(out, "flight")
    updates = [(t, m) for t, m in decoded if isinstance(m, SmUpdate)]
    statuses = [(t, m) for t, m in decoded if isinstance(m, Status)]
    assert len(updates) > 200 and len(statuses) > 20
    counts = {_norm(summary.channels[cid].topic, "flight"): n
              for cid, n in summary.statistics.channel_message_counts.items()}
    for topic in ("/aurora/state", "/aurora/altitude", "/aurora/attitude"):
        assert counts[topic] == len(got[topic]) == len(updates), topic
    assert counts["/aurora/status"] == len(got["/aurora/status"]) == len(statuses)
    for topic in ("/aurora/state", "/aurora/altitude", "/aurora/attitude"):
        for (rec, data), (t, m) in zip(got[topic], updates, strict=True):
            assert rec.log_time == rec.publish_time == _ns(t)
            assert set(data) == FIELDS[topic]
            if topic == "/aurora/state":
                assert data == {"state": m.state, "state_name": m.state_name,
                                "armed": m.armed, "sm_type": m.sm_type,
                                "timestamp_ms": m.timestamp_ms}
            elif topic == "/aurora/altitude":
                assert data == {k: getattr(m, k) for k in FIELDS[topic]}  # floats exact
            else:
                ns = _ns(t)
                assert data["timestamp"] == {"sec": ns // 10**9, "nsec": ns % 10**9}
                # a frame per vehicle, named after it
                assert (data["parent_frame_id"], data["child_frame_id"]) == ("world", "flight")
                assert data["translation"] == {"x": 0.0, "y": 0.0, "z": m.altitude_m}
                angles = (m.roll_rad, m.pitch_rad, m.yaw_rad)
                rot = data["rotation"]
                q = (rot["x"], rot["y"], rot["z"], rot["w"])
                assert math.fsum(c * c for c in q) == pytest.approx(1.0, abs=1e-12)
                r = _rotation_matrix(*angles)
                for axis in range(3):
                    e = [1.0 if i == axis else 0.0 for i in range(3)]
                    column = [r[i][axis] for i in range(3)]
                    assert _rotate(q, e) == pytest.approx(column, abs=1e-12)
        assert [rec.sequence for rec, _ in got[topic]] == list(range(len(updates)))
    for (rec, data), (t, st) in zip(got["/aurora/status"], statuses, strict=True):
        assert rec.log_time == _ns(t)
        assert data == {"state": st.state, "state_name": st.state_name, "sm_type": st.sm_type,
                        "flags": st.flags, "timestamp_ms": st.timestamp_ms,
                        **{k: bool(st.flags & bit) for k, bit in FLAG_BITS.items()}}
    assert summary.statistics.message_start_time == _ns(decoded[0][0])
    assert summary.statistics.message_end_time == _ns(decoded[-1][0])


def test_the_link_goes_down_after_the_timeout_and_up_at_the_next_frame(
        exported: tuple[list[tuple[float, Any]], Path]) -> None:
    decoded, out = exported
    _, got = _read(out, "flight")
    times = [t for t, _ in decoded]
    (before, after), = [(a, b) for a, b in itertools.pairwise(times)
                        if b - a >= LINK_TIMEOUT_S]
    link = [(rec.log_time, data) for rec, data in got["/aurora/link_events"]]
    source = "replay:flight.aur"
    assert link == [
        (_ns(times[0]), {"source": source, "up": True, "silence_s": 0.0}),
        (_ns(before + LINK_TIMEOUT_S), {"source": source, "up": False,
                                        "silence_s": LINK_TIMEOUT_S}),
        (_ns(after), {"source": source, "up": True, "silence_s": 0.0}),
    ]


def test_the_f32_revision_and_non_finite_values(tmp_path: Path) -> None:
    decoded = _write_recording(tmp_path / "f32.aur", revision=36)
    bad = SmUpdate(1, 2, True, 0, math.nan, math.inf, -math.inf, 0.5, 0.0, 0.0, 0.0)
    with (tmp_path / "f32.aur").open("ab") as f:
        f.write(recording.encode_record(T0 + 100.0, encode(bad)))
    out = tmp_path / "f32.bin"
    assert main(["export", str(tmp_path / "f32.aur"), "--format", "mcap", "-o", str(out)]) == 0
    _, got = _read(out, "f32")
    f32 = [m for _, m in decoded if isinstance(m, SmUpdate)]
    assert f32[0].payload_len == 36
    assert [d["altitude_m"] for _, d in got["/aurora/altitude"][:-1]] == [
        m.altitude_m for m in f32]
    assert got["/aurora/altitude"][-1][1] == {"timestamp_ms": 1, "altitude_m": None,
                                               "velocity_mps": 0.5,
                                               "acceleration_mps2": None,
                                               "accel_vert_mps2": None}


def test_position_battery_and_link_stats_get_their_channels_when_present(
        tmp_path: Path) -> None:
    out = tmp_path / "gps.mcap"
    with out.open("wb") as f:
        export = McapExport(f, source="gps")
        export.add(T0, Position(52.5, 13.25, 40.0, 1.5, None, None, 9, 3))
        export.add(T0 + 1, Battery(7.4, 1.25, None, 80))
        export.add(T0 + 2, RawFrame(0x7E, b""))
        export.add(T0 + 3, Position(52.5, 13.5, None))
        export.add(T0 + 4, LinkStats(-70.0, 99, origin="crsf"), frame=False)
        export.finish()
    summary, got = _read(out)
    assert {c.topic for c in summary.channels.values()} == CORE | {
        "/aurora/position", "/aurora/battery", "/aurora/link"}
    for ch in summary.channels.values():
        assert summary.schemas[ch.schema_id].name == SCHEMA_NAMES[ch.topic]
    ns = _ns(T0)
    # foxglove.LocationFix: an unknown altitude as 0 (as the live backend sends it)
    assert got["/aurora/position"][0][1] == {
        "timestamp": {"sec": ns // 10**9, "nsec": ns % 10**9}, "frame_id": "rocket",
        "latitude": 52.5, "longitude": 13.25, "altitude": 40.0,
        "position_covariance": [0.0] * 9, "position_covariance_type": 0}
    assert got["/aurora/position"][1][1]["altitude"] == 0.0
    assert [d for _, d in got["/aurora/link"]] == [
        {"rssi_dbm": -70.0, "link_quality_pct": 99, "snr_db": None, "tx_power_mw": None,
         "downlink_rssi_dbm": None, "downlink_link_quality_pct": None,
         "downlink_snr_db": None, "rf_mode": None, "antenna": None, "origin": "crsf"}]
    assert [d for _, d in got["/aurora/battery"]] == [
        {"voltage_v": 7.4, "current_a": 1.25, "consumed_mah": None, "remaining_pct": 80,
         "battery_id": 0}]
    assert got["/aurora/battery"][0][0].log_time == _ns(T0 + 1)
    assert export.skipped == {"RawFrame": 1}


@pytest.mark.parametrize("argv", [["--format", "mcap"], ["-f", "mcap", "-o", "-"]])
def test_mcap_to_stdout_is_refused_with_status_2(
        exported: tuple[list[Any], Path], argv: list[str],
        capsys: pytest.CaptureFixture[str]) -> None:
    _, out = exported
    recording_path = out.with_name("flight.aur")
    assert main(["export", str(recording_path), *argv]) == 2
    stdout, err = capsys.readouterr()
    assert stdout == ""
    assert len(err.strip().splitlines()) == 1 and "-o" in err


def test_the_console_script_writes_an_mcap(exported: tuple[list[Any], Path],
                                          tmp_path: Path) -> None:
    decoded, out = exported
    target = tmp_path / "console.mcap"
    done = subprocess.run([str(CONSOLE), "export", str(out.with_name("flight.aur")),
                           "-o", str(target)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout == ""
    updates = sum(isinstance(m, SmUpdate) for _, m in decoded)
    assert f"{updates} SM updates" in done.stderr and "mcap" in done.stderr
    data = target.read_bytes()
    assert data[:8] == data[-8:] == b"\x89MCAP0\r\n"  # the spec's magic at both ends
    _, got = _read(target, "flight")
    assert len(got["/aurora/state"]) == updates
