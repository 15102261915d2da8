"""``export REC --format rosbag2 -o DIR``: the bag read back with ``rosbags``' own reader and
CDR deserializer — its topics and types, one altitude and one ``/tf`` per SM update, values
and stamps equal to the recording's (read by the csv/jsonl export's loader) — and the usage
errors (an existing directory, stdout, the missing extra) as one line, exit 2."""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from decimal import ROUND_HALF_EVEN, Decimal
from pathlib import Path
from typing import Any

import pytest
from helpers import ROOT

rosbag2_reader = pytest.importorskip("rosbags.rosbag2")
typesys = pytest.importorskip("rosbags.typesys")

from gateway.commands.cli import main  # noqa: E402
from gateway.commands.export import load  # noqa: E402

DATA = ROOT / "tests" / "data"
RECORDING = DATA / "flight-v2.aur"
TYPESTORE = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)


def _ns(t: float) -> int:
    """The float's exact value in ns, rounded half-even (independent of the export's way)."""
    return int((Decimal(t) * 10**9).to_integral_value(ROUND_HALF_EVEN))


@pytest.fixture(scope="module")
def bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("rosbag2") / "flight"
    assert main(["export", str(RECORDING), "--format", "rosbag2", "-o", str(out)]) == 0
    return out


def _read(bag: Path) -> tuple[dict[str, str], dict[str, list[tuple[int, Any]]]]:
    """The bag's topic → type, and topic → [(bag time, message)] in bag order."""
    messages: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    with rosbag2_reader.Reader(bag) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, t, raw in reader.messages():
            messages[conn.topic].append((t, TYPESTORE.deserialize_cdr(raw, conn.msgtype)))
    return types, messages


def test_the_bag_is_a_rosbag2_directory_with_mcap_storage(bag: Path) -> None:
    names = sorted(p.name for p in bag.iterdir())
    assert names == ["flight.mcap", "metadata.yaml"]
    meta = (bag / "metadata.yaml").read_text()
    assert "storage_identifier: mcap" in meta
    assert "version: 8" in meta


def test_topics_and_types_per_vehicle(bag: Path) -> None:
    types, _ = _read(bag)
    vehicles = load(RECORDING).vehicles
    assert vehicles == ["alpha", "beta"]
    expected = {"/tf": "tf2_msgs/msg/TFMessage",
                "/diagnostics": "diagnostic_msgs/msg/DiagnosticArray"}
    for v in vehicles:
        expected |= {f"/aurora/{v}/altitude": "std_msgs/msg/Float64",
                     f"/aurora/{v}/imu": "sensor_msgs/msg/Imu",
                     f"/aurora/{v}/state": "std_msgs/msg/String",
                     f"/aurora/{v}/armed": "std_msgs/msg/Bool"}
    assert types == expected
    with rosbag2_reader.Reader(bag) as reader:
        # the hashes in the bag's metadata are the ones ROS 2 computes (rosbags' type store)
        for conn in reader.connections:
            assert conn.digest == TYPESTORE.hash_rihs01(conn.msgtype)
            qos = conn.ext.offered_qos_profiles[0]
            latched = conn.topic.rsplit("/", 1)[-1] in ("state", "armed")
            assert (qos.durability.name == "TRANSIENT_LOCAL") == latched, conn.topic


def test_one_altitude_and_one_tf_per_update_with_the_recordings_values_and_stamps(
        bag: Path) -> None:
    _, messages = _read(bag)
    rows = [r for r in load(RECORDING).rows if r["kind"] == "sm_update"]
    assert rows
    tf = messages["/tf"]
    assert len(tf) == len(rows)
    for row, (t, msg) in zip(rows, tf, strict=True):
        assert t == _ns(row["rx_time"])
        (transform,) = msg.transforms
        assert transform.header.frame_id == "world"
        assert transform.child_frame_id == row["vehicle"]
        assert transform.transform.translation.z == row["altitude_m"]
        stamp = transform.header.stamp
        assert stamp.sec * 10**9 + stamp.nanosec == t
    for vehicle in ("alpha", "beta"):
        mine = [r for r in rows if r["vehicle"] == vehicle]
        altitude = messages[f"/aurora/{vehicle}/altitude"]
        assert [(t, m.data) for t, m in altitude] == [
            (_ns(r["rx_time"]), r["altitude_m"]) for r in mine]
        imu = messages[f"/aurora/{vehicle}/imu"]
        assert len(imu) == len(mine)
        assert all(m.header.frame_id == vehicle for _, m in imu)
        # the state when it changes: the names of the recording's states, in order
        changes = [r["state_name"] for i, r in enumerate(mine)
                   if i == 0 or r["state_name"] != mine[i - 1]["state_name"]]
        assert [m.data for _, m in messages[f"/aurora/{vehicle}/state"]] == changes


def test_an_existing_directory_is_refused_with_one_line(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    target = tmp_path / "there"
    target.mkdir()
    assert main(["export", str(RECORDING), "--format", "rosbag2", "-o", str(target)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "exists" in err[0] and str(target) in err[0], err
    assert list(target.iterdir()) == []


def test_stdout_is_refused_with_one_line(capsys: pytest.CaptureFixture) -> None:
    assert main(["export", str(RECORDING), "--format", "rosbag2"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "-o DIR" in err[0], err


def test_without_rosbags_one_line_names_the_extra(tmp_path: Path) -> None:
    shim = ("import sys\n"
            "sys.modules['rosbags'] = None  # as on an install without the ros2 extra\n"
            "from gateway.commands.cli import console_main\n"
            "sys.argv = ['aurora-gateway', *sys.argv[1:]]\n"
            "console_main()\n")
    out = tmp_path / "bag"
    proc = subprocess.run([sys.executable, "-c", shim, "export", str(RECORDING), "--format",
                           "rosbag2", "-o", str(out)], cwd=tmp_path, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        "aurora-gateway: export needs the 'ros2' extra: pip install 'aurora-gateway[ros2]'"]
    assert not out.exists()


def test_fix_and_battery_when_the_recording_has_them(tmp_path: Path) -> None:
    from backends.ros2 import rosbag2
    from gateway.model import Battery, Position

    t0 = 1_790_000_000.25
    messages = [(t0, Position(52.5, 13.25, 40.0, 1.5, None, None, 9, 3, vehicle="gps1")),
                (t0 + 1, Battery(7.4, 1.25, None, 80, vehicle="gps1"))]
    written = rosbag2.write(messages, tmp_path / "bag", ["gps1"])
    assert written.types == {"/aurora/gps1/fix": "sensor_msgs/msg/NavSatFix",
                             "/aurora/gps1/battery": "sensor_msgs/msg/BatteryState"}
    types, got = _read(tmp_path / "bag")
    assert types == written.types
    (t, fix), = got["/aurora/gps1/fix"]
    assert t == _ns(t0)
    assert (fix.latitude, fix.longitude, fix.altitude) == (52.5, 13.25, 40.0)
    assert fix.header.frame_id == "gps1"
    (t, battery), = got["/aurora/gps1/battery"]
    assert t == _ns(t0 + 1)
    assert battery.voltage == pytest.approx(7.4)  # (float32)
    assert battery.current == pytest.approx(-1.25)  # ROS: negative while discharging


def test_vehicle_keeps_one_vehicles_topics(tmp_path: Path) -> None:
    out = tmp_path / "beta"
    assert main(["export", str(RECORDING), "--format", "rosbag2", "-o", str(out),
                 "--vehicle", "beta"]) == 0
    types, got = _read(out)
    assert not any(t.startswith("/aurora/alpha/") for t in types)
    rows = [r for r in load(RECORDING, "beta").rows if r["kind"] == "sm_update"]
    assert [m.data for _, m in got["/aurora/beta/altitude"]] == [r["altitude_m"] for r in rows]
    assert {m.transforms[0].child_frame_id for _, m in got["/tf"]} == {"beta"}


def test_the_bag_names_its_recording_in_custom_data(bag: Path) -> None:
    from ruamel.yaml import YAML  # (rosbags' own YAML library)

    meta = YAML(typ="safe").load((bag / "metadata.yaml").read_text())
    custom = meta["rosbag2_bagfile_information"]["custom_data"]
    assert custom["aurora_gateway.recording"] == RECORDING.name
    assert custom["aurora_gateway.version"]


def test_a_failed_export_leaves_no_half_bag(tmp_path: Path) -> None:
    from backends.ros2 import rosbag2

    def messages() -> Any:
        yield from load(RECORDING).messages[:50]
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        rosbag2.write(messages(), tmp_path / "bag")
    assert not (tmp_path / "bag").exists()
