"""MAVLink telemetry logs out: ``run --tlog DIR`` and ``export --format tlog``, read back by
pymavlink's own ``mavlogdump.py`` (the script the pymavlink wheel installs), not by our code.

The gateway runs as its console command does (a process of its own); the vehicle and the
ground station are :class:`mavlink_peer.MavPeer`s on loopback UDP.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from collections import Counter
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
from helpers import wait_for
from mavlink_peer import MavPeer
from test_mavlink_routing_cli import WAIT, Vehicle, dev, free_udp_port, gateway

from backends.mavlink import tlog
from backends.mavlink.frames import FramerStats, split_datagram

ROOT = Path(__file__).resolve().parents[1]
MAVLOGDUMP = Path(sys.executable).parent / "mavlogdump.py"


def mavlogdump(path: Path, *args: str, env: dict[str, str] | None = None) -> list[dict[str, Any]]:
    """``mavlogdump.py --format json --show-source PATH``: every message it prints."""
    out = subprocess.run([sys.executable, str(MAVLOGDUMP), "--format", "json", "--show-source",
                          *args, str(path)], capture_output=True, text=True, timeout=120,
                         check=True, env={**os.environ, **(env or {})})
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def frames_of(datagrams: list[bytes]) -> list[bytes]:
    stats = FramerStats()
    return [f.raw for d in datagrams for f in split_datagram(d, stats)]


def msgid(frame: bytes) -> int:
    return int.from_bytes(frame[7:10], "little") if frame[0] == 0xFD else frame[5]


def sysid(frame: bytes) -> int:
    return frame[5] if frame[0] == 0xFD else frame[3]


def test_run_tlog_holds_every_frame_that_crossed_the_gateway_once(tmp_path: Path) -> None:
    port = free_udp_port()
    logs = tmp_path / "tlogs"
    vehicle = Vehicle(dest=("127.0.0.1", port))
    gcs = MavPeer(255, 190)
    sent_by_vehicle: list[bytes] = []
    sent_by_gcs: list[bytes] = []
    try:
        with gateway(tmp_path / "log", "--only", "mavlink",
                     "--source", f"mavlink:udpin:127.0.0.1:{port}",
                     "--mavlink", f"udpout:127.0.0.1:{gcs.port}", "--tlog", str(logs)) as proc:
            assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
            for i in range(40):  # telemetry down: each frame unique
                sent_by_vehicle += [
                    vehicle.send(dev.MAVLink_global_position_int_message(
                        1000 + i, 473977420, 85455940, 500_000 + i, 20_000, 0, 0, 0, 0)),
                    vehicle.send(dev.MAVLink_attitude_message(1000 + i, 0.1, 0.2, 0.3, 0, 0,
                                                              0)),
                    vehicle.send(dev.MAVLink_sys_status_message(
                        0, 0, 0, 500, 12_000 + i, -1, -1, 0, 0, 0, 0, 0, 0)),
                    vehicle.send(dev.MAVLink_battery_status_message(
                        0, 0, 0, 2500, [4000 + i] + [65535] * 9, 120, -1, -1, 80)),
                ]
                if i % 10 == 9:
                    assert gcs.wait_until(
                        lambda n=i: len(gcs.messages("ATTITUDE")) > n - 5, WAIT)
            for i in range(10):  # commands up, acknowledgements back
                sent_by_gcs.append(gcs.command((1, 1), dev.MAV_CMD_DO_SET_MODE, 1, 4 + i))
            assert wait_for(lambda: len(vehicle.from_gcs()) >= 10, WAIT)
            assert gcs.wait_for("COMMAND_ACK", count=10, timeout=WAIT)
            assert gcs.wait_until(lambda: len(gcs.messages("ATTITUDE")) >= 40, WAIT)
            # the gateway's own heartbeat (its MAVLink source's, to the vehicle) has gone out
            assert vehicle.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() not in (1, 255),
                                    timeout=WAIT)
            assert proc.poll() is None
        assert proc.returncode in (0, 130), (tmp_path / "log").read_text()
    finally:
        vehicle.close()
        gcs.close()

    files = sorted(logs.glob("*.tlog"))
    assert len(files) == 1, files
    records = tlog.read(files[0])
    assert records and len(records) * 8 + sum(len(f) for _, f in records) == \
        files[0].stat().st_size  # every byte is a whole record
    logged = Counter(f for _, f in records)
    times = [t for t, _ in records]
    assert times == sorted(times)
    # each frame the peers sent or received through the gateway is in it, exactly once:
    # a routed frame is logged as it came in, not again as it went out
    unique = sent_by_vehicle + sent_by_gcs + [
        f for f in frames_of(gcs.raw_received) + frames_of(vehicle.raw_received)
        if msgid(f) != 0]  # (not HEARTBEAT: those repeat byte for byte)
    assert unique
    missing = [f for f in unique if logged[f] != 1]
    assert not missing, f"{len(missing)} of {len(unique)} frames not logged once"
    # the gateway's own frames too: the MAVLink source's heartbeats and requests to the vehicle
    own = {sysid(f) for f in frames_of(vehicle.raw_received)} - {255}
    assert own, "the vehicle heard nothing of the gateway's own"

    # pymavlink's mavlogdump.py reads it all, in order
    dumped = mavlogdump(files[0])
    assert len(dumped) == len(records)
    stamps = [m["meta"]["timestamp"] for m in dumped]
    assert stamps == sorted(stamps)
    assert stamps == pytest.approx(times, abs=1e-6)
    by_type = Counter((m["meta"]["srcSystem"], m["meta"]["type"]) for m in dumped)
    for mtype in ("GLOBAL_POSITION_INT", "ATTITUDE", "SYS_STATUS", "BATTERY_STATUS"):
        assert by_type[(1, mtype)] == 40, (mtype, by_type)
    assert by_type[(255, "COMMAND_LONG")] == 10
    acks = [m for m in dumped if m["meta"]["type"] == "COMMAND_ACK"
            and m["data"]["target_system"] == 255]
    assert len(acks) == 10 and {m["meta"]["srcSystem"] for m in acks} == {1}
    assert by_type[(1, "HEARTBEAT")] > 0
    assert any(src not in (1, 255) and t == "HEARTBEAT" for src, t in by_type), by_type
    positions = [m["data"]["relative_alt"] for m in dumped
                 if m["meta"]["type"] == "GLOBAL_POSITION_INT"]
    assert positions == [20_000] * 40


def aurora_dialect_env(tmp_path: Path) -> dict[str, str]:
    """The project's dialect where pymavlink's tools look for one by name
    (``--dialect aurora_mavlink``): its generated module as ``pymavlink.dialects.v10/v20``'s
    ``aurora_mavlink``, through a ``sitecustomize`` on PYTHONPATH (what the README's
    one-line install does in the real package directory)."""
    from dialects import aurora_mavlink

    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(
        "import importlib.util, sys\n"
        f"spec = importlib.util.spec_from_file_location('aurora_mavlink', "
        f"{aurora_mavlink.__file__!r})\n"
        "mod = importlib.util.module_from_spec(spec)\n"
        "spec.loader.exec_module(mod)\n"
        "for v in ('v10', 'v20'):\n"
        "    sys.modules[f'pymavlink.dialects.{v}.aurora_mavlink'] = mod\n"
        "    __import__(f'pymavlink.dialects.{v}')\n"
        "    setattr(sys.modules[f'pymavlink.dialects.{v}'], 'aurora_mavlink', mod)\n")
    return {"PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}


def test_export_tlog_of_a_simulated_flight(tmp_path: Path) -> None:
    rec = tmp_path / "flight.aur"
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[gateway]\nrecord = "{rec}"\nstatus_interval_s = 0\n'
                   '[[sources]]\ntype = "sim"\nspeed = 8\ncycles = 1\npad_idle_s = 1\n'
                   'pad_armed_s = 1\n')
    gw = [sys.executable, "-m", "gateway"]
    r = subprocess.run([*gw, "run", "-c", str(cfg), "--duration", "60"],
                       cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = tmp_path / "flight.tlog"
    r = subprocess.run([*gw, "export", str(rec), "-o", str(out)], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "as tlog" in r.stderr
    assert "faster than real time" in r.stderr  # (8 times: said, with the figures)
    assert "translated at the flight's own pace" in r.stderr

    from gateway import recording
    rx = [rec_.t for rec_ in recording.read_records(rec)]
    dumped = mavlogdump(out, "--dialect", "aurora_mavlink", env=aurora_dialect_env(tmp_path))
    assert len(dumped) == len(tlog.read(out))
    stamps = [m["meta"]["timestamp"] for m in dumped]
    assert stamps == sorted(stamps)
    assert rx[0] - 1e-6 <= stamps[0] and stamps[-1] <= rx[-1] + 1e-6  # the recording's times
    types = Counter(m["meta"]["type"] for m in dumped)
    assert "BAD_DATA" not in types, types
    for t in ("HEARTBEAT", "ATTITUDE", "ALTITUDE", "SYS_STATUS",
              "STATUSTEXT", "AURORA_SM_UPDATE", "AURORA_STATUS"):
        assert types[t] > 0, (t, types)
    assert {m["meta"]["srcSystem"] for m in dumped} == {1}

    # ALTITUDE rises to the apogee, then falls
    alt = [m["data"]["altitude_relative"] for m in dumped if m["meta"]["type"] == "ALTITUDE"]
    top = alt.index(max(alt))
    assert max(alt) > 10 and 0 < top < len(alt) - 1
    assert alt[0] < 1 and alt[-1] < max(alt) / 10
    assert sum(b >= a for a, b in pairwise(alt[:top + 1])) > 0.9 * top
    assert sum(b <= a for a, b in pairwise(alt[top:])) > 0.9 * (len(alt) - top - 1)

    # HEARTBEAT's custom mode follows the flight's states, in the order the recording's updates
    # gave them; periodic at 1 Hz of the recording's clock (plus one at each change)
    from gateway.commands.export import load

    def runs(xs: list[int]) -> list[int]:
        return [x for i, x in enumerate(xs) if i == 0 or xs[i - 1] != x]

    states = runs([row["state"] for row in load(rec).rows])
    beats = [m for m in dumped if m["meta"]["type"] == "HEARTBEAT"]
    modes = runs([b["data"]["custom_mode"] for b in beats])
    assert len(modes) >= 4, modes
    it = iter(states)
    assert all(m in it for m in modes), (str(modes), str(states))
    # 1 Hz of the flight's own pace: the recording was made 8 times faster than real time,
    # so it is translated on the flight computer's clock (stamps stay the receive times)
    rows = load(rec).rows
    flight_s = (rows[-1]["timestamp_ms"] - rows[0]["timestamp_ms"]) / 1000
    span = beats[-1]["meta"]["timestamp"] - beats[0]["meta"]["timestamp"]
    assert span >= 5 and flight_s - 2 <= len(beats) <= flight_s + 2 + len(states), (
        len(beats), flight_s, span)


def custom_modes(path: Path) -> list[int]:
    """The HEARTBEAT custom modes in a telemetry log, as mavlogdump.py prints them."""
    return [m["data"]["custom_mode"] for m in mavlogdump(path, "--types", "HEARTBEAT")]


def test_run_tlog_starts_a_new_file_when_a_vehicle_starts_a_new_flight(tmp_path: Path) -> None:
    from test_recording_vehicles import _flight, _update

    from backends.mavlink.backend import MavlinkBackend
    from backends.mavlink.options import MavlinkOptions
    from dialects.states import SimpleState
    from gateway.dispatcher import Dispatcher

    logs = tmp_path / "tlogs"
    with MavPeer(255, 190) as gcs:
        b = MavlinkBackend(MavlinkOptions(endpoints=[f"udpout:127.0.0.1:{gcs.port}"],
                                          tlog=str(logs)))
        d = Dispatcher([b])
        assert d.start() == []
        try:
            for msg in _flight("alpha", 0, 300.0):
                def state(m: Any, s: int = int(msg.state)) -> bool:
                    return bool(m.custom_mode == s)

                before = len(gcs.messages("HEARTBEAT", state))
                d.dispatch(msg)
                assert len(gcs.wait_for("HEARTBEAT", state, count=before + 1,
                                        timeout=WAIT)) > before
            # armed on the pad again after a flight: the next flight's file
            def armed(m: Any) -> bool:
                return bool(m.custom_mode == SimpleState.ARMED)

            before = len(gcs.messages("HEARTBEAT", armed))
            d.dispatch(_update("alpha", SimpleState.ARMED, 10_000, 0.0))
            assert len(gcs.wait_for("HEARTBEAT", armed, count=before + 1,
                                    timeout=WAIT)) > before
            assert wait_for(lambda: len(b.tlog.paths) == 2 if b.tlog else False, WAIT)
        finally:
            d.close()
    first, second = (Path(p) for p in b.stats()["tlog"]["files"])  # in the order opened
    assert set(logs.glob("*.tlog")) == {first, second}
    assert runs_of(custom_modes(first))[-1] == SimpleState.IDLE
    assert SimpleState.APOGEE in custom_modes(first)
    assert custom_modes(second)[0] == SimpleState.ARMED  # the new flight's frames only
    assert SimpleState.APOGEE not in custom_modes(second)
    assert b.stats()["tlog"]["dropped_disk_full"] == 0


def runs_of(xs: list[int]) -> list[int]:
    return [x for i, x in enumerate(xs) if i == 0 or xs[i - 1] != x]


def test_tlog_on_a_full_disk_leaves_no_file_counts_and_goes_on_when_space_returns(
        tmp_path: Path) -> None:
    from test_recording_full_disk import fill, tmpfs

    with tmpfs(tmp_path / "disk", "size=64k") as fs:
        filler = fill(fs)
        d = fs / "tlogs"
        w = tlog.TlogWriter(d)
        w.WRITE_RETRY_S = 0.0
        frames = [dev.MAVLink_heartbeat_message(6, 8, 0, i, 4, 3).pack(
            dev.MAVLink(None, 1, 1)) for i in range(60)]
        for f in frames[:50]:
            assert w.submit(f, t=1_790_000_000.0)
        assert wait_for(lambda: w.dropped_disk_full == 50, WAIT)
        assert list(d.iterdir()) == []  # not one empty file
        filler.unlink()
        for i, f in enumerate(frames[50:]):
            assert w.submit(f, t=1_790_000_001.0 + i)
        assert wait_for(lambda: w.records == 10, WAIT)
        w.close(5.0)
        (path,) = w.paths
        assert list(d.iterdir()) == [path] and path.suffix == ".tlog"
        assert [f for _, f in tlog.read(path)] == frames[50:]
        assert path.stat().st_size == sum(8 + len(f) for f in frames[50:])
        assert w.stats()["dropped_disk_full"] == 50 and w.stats()["bytes"] == path.stat().st_size
        assert [m["data"]["custom_mode"] for m in mavlogdump(path)] == list(range(50, 60))


def test_run_tlog_on_a_full_disk_reports_the_frames_not_written(tmp_path: Path) -> None:
    from test_recording_full_disk import fill, tmpfs

    with tmpfs(tmp_path / "disk", "size=64k") as fs, MavPeer(255, 190) as gcs:
        fill(fs)
        d = fs / "tlogs"
        r = subprocess.run([sys.executable, "-m", "gateway", "run", "--source", "sim",
                            "--sim-speed", "4", "--duration", "2", "--only", "mavlink",
                            "--mavlink", f"udpout:127.0.0.1:{gcs.port}", "--tlog", str(d),
                            "--status-interval", "0"],
                           capture_output=True, text=True, timeout=60, cwd=ROOT)
        assert r.returncode == 0, r.stderr  # the run worked; the log is what failed
        assert list(d.iterdir()) == []
        (dropped,) = [ln for ln in r.stderr.splitlines() if ln.startswith("dropped: ")]
        n = int(re.search(r"mavlink .*\bdropped_disk_full=(\d+)", dropped).group(1))  # type: ignore[union-attr]
        assert n >= len(gcs.messages()) > 0  # every frame the ground station got: not logged
