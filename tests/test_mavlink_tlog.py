"""MAVLink telemetry logs out: ``run --tlog DIR`` and ``export --format tlog``, read back by
pymavlink's own ``mavlogdump.py`` (the script the pymavlink wheel installs), not by our code.

The gateway runs as its console command does (a process of its own); the vehicle and the
ground station are :class:`mavlink_peer.MavPeer`s on loopback UDP.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections import Counter
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
    assert by_type[(1, "COMMAND_ACK")] == 10
    assert by_type[(1, "HEARTBEAT")] > 0
    assert any(src not in (1, 255) and t == "HEARTBEAT" for src, t in by_type), by_type
    positions = [m["data"]["relative_alt"] for m in dumped
                 if m["meta"]["type"] == "GLOBAL_POSITION_INT"]
    assert positions == [20_000] * 40
