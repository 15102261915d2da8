"""``--source tlog:F.tlog``: a MAVLink telemetry log replayed as the vehicles it recorded — in
process (the gateway's messages), through the command line to the status page, and to a
pymavlink ground station at the recorded rate.

The logs are written here, in the ``.tlog`` format MAVProxy and QGroundControl write: each
frame (packed by pymavlink) after its 8-byte big-endian UNIX time in microseconds."""

from __future__ import annotations

import itertools
import json
import socket
import struct
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from helpers import Running, wait_for
from mavlink_peer import MavPeer, upstream_dialect
from test_mavlink_mavproxy import Output, needs_mavproxy
from test_mavlink_mavproxy import _env as mavproxy_env
from test_mavlink_mavproxy import _stop as stop_mavproxy

from backends.mavlink.dialect import mav
from backends.mavlink.options import TlogSourceOptions
from backends.mavlink.tlog_source import TlogError, TlogSource, check_file
from backends.mavlink.translate import aurora_sm_update
from gateway.model import Battery, Position, SmUpdate, VehicleState

dev = upstream_dialect()
WAIT = 15.0
T0_US = 1_764_000_000_000_000  # 2025-11-24: a UNIX time in microseconds


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class TlogWriter:
    """Frames of one MAVLink system (``dialect``'s packer) as records of a ``.tlog``."""

    def __init__(self, dialect: Any = dev, sysid: int = 1) -> None:
        self.mav = dialect.MAVLink(None, sysid, 1)
        self.data = bytearray()
        self.frames = 0
        self.offsets: list[int] = []  # where each record starts

    def add(self, t_us: int, msg: Any) -> bytes:
        frame = bytes(msg.pack(self.mav))
        self.offsets.append(len(self.data))
        self.mav.seq = (self.mav.seq + 1) % 256
        self.data += struct.pack(">Q", t_us) + frame
        self.frames += 1
        return frame


def copter_flight(seconds: float = 3.0, hz: int = 10, sysid: int = 1) -> TlogWriter:
    """An ArduCopter-like flight: HEARTBEAT at 1 Hz (armed after the first), and at ``hz``
    GLOBAL_POSITION_INT climbing 1 m per sample, ATTITUDE and SYS_STATUS (12.6 V)."""
    w = TlogWriter(sysid=sysid)
    for i in range(round(seconds * hz) + 1):
        t = T0_US + i * 1_000_000 // hz
        if i % hz == 0:
            armed = dev.MAV_MODE_FLAG_SAFETY_ARMED if i else 0
            w.add(t, dev.MAVLink_heartbeat_message(
                dev.MAV_TYPE_QUADROTOR, dev.MAV_AUTOPILOT_ARDUPILOTMEGA,
                dev.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | armed, 5, dev.MAV_STATE_ACTIVE, 3))
        w.add(t, dev.MAVLink_global_position_int_message(
            i * 100, 473_977_000 + i, 85_455_000, 500_000 + i * 1000, i * 1000, 0, 0, -100,
            9000))
        w.add(t, dev.MAVLink_attitude_message(i * 100, 0.1, 0.2, 0.3, 0, 0, 0))
        w.add(t, dev.MAVLink_sys_status_message(0, 0, 0, 500, 12600, -1, 80, 0, 0, 0, 0, 0, 0))
    return w


class Collected:
    """The source's sink: every message kept."""

    def __init__(self) -> None:
        self.got: list[Any] = []
        self.lock = threading.Lock()

    def __call__(self, msg: Any) -> None:
        with self.lock:
            self.got.append(msg)

    def of(self, kind: type) -> list[Any]:
        with self.lock:
            return [m for m in self.got if isinstance(m, kind)]


def replayed(path: Path, **options: Any) -> tuple[TlogSource, Collected]:
    """Replay ``path`` in process (as fast as possible unless told) to its end."""
    source = TlogSource(TlogSourceOptions(path=str(path), speed=options.pop("speed", 0.0),
                                          **options))
    source.vehicle = "flight"
    sink = Collected()
    source.start(sink)
    try:
        assert source.done.wait(WAIT), "the replay did not end at the end of the file"
    finally:
        source.stop()
    return source, sink


def test_a_copter_flight_replays_as_its_positions_states_and_battery(tmp_path: Path) -> None:
    path = tmp_path / "flight.tlog"
    path.write_bytes(copter_flight().data)
    source, sink = replayed(path)
    positions = sink.of(Position)
    assert positions, sink.got
    assert {p.vehicle for p in sink.got} == {"flight-1"}  # <vehicle>-<system id>
    first, last = positions[0], positions[-1]
    assert first.lat_deg == pytest.approx(47.3977) and first.lon_deg == pytest.approx(8.5455)
    assert last.relative_alt_m == pytest.approx(30.0)  # the last sample is always delivered
    assert [p.relative_alt_m for p in positions] == sorted(p.relative_alt_m for p in positions)
    assert len(positions) >= 20  # 10 Hz of flight time, however fast the replay
    states = sink.of(VehicleState)
    assert states[0].armed is False and states[-1].armed is True
    assert states[-1].mode == "LOITER"  # ArduCopter's custom mode 5
    assert states[-1].roll_rad == pytest.approx(0.1)
    batteries = sink.of(Battery)
    assert batteries and batteries[-1].voltage_v == pytest.approx(12.6)
    st = source.stats()
    assert st["records"] == st["frames"] == 31 * 3 + 4
    assert st["corrupt_skips"] == st["torn_tail_bytes"] == 0
    assert st["systems"] == {"1": "flight-1"}


def test_a_rocket_flight_replays_its_aurora_messages(tmp_path: Path) -> None:
    """A log of the project's dialect (what the MAVLink backend sends for a rocket) gives the
    state machine's updates back, field for field."""
    w = TlogWriter(mav)
    sent = []
    for i in range(20):
        t = T0_US + i * 50_000
        if i % 10 == 0:
            w.add(t, mav.MAVLink_heartbeat_message(mav.MAV_TYPE_ROCKET, mav.MAV_AUTOPILOT_GENERIC,
                                                   mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 3,
                                                   mav.MAV_STATE_ACTIVE, 3))
        u = SmUpdate(i * 50, 3 + (i >= 10), True, 0, 100.0 * i, 20.0, 19.5, 50.0 - i, 0.0,
                     1.5, 0.25)
        sent.append(u)
        w.add(t, aurora_sm_update(u))
    path = tmp_path / "rocket.tlog"
    path.write_bytes(w.data)
    _, sink = replayed(path)
    got = sink.of(SmUpdate)
    assert [(m.timestamp_ms, m.state, m.altitude_m, m.velocity_mps) for m in got] == \
        [(u.timestamp_ms, u.state, u.altitude_m, u.velocity_mps) for u in sent]
    assert {m.vehicle for m in got} == {"flight-1"}


def test_corrupt_stretches_and_a_torn_tail_are_counted_and_skipped(tmp_path: Path) -> None:
    w = copter_flight(seconds=1.0)
    good = bytes(w.data)
    middle = w.offsets[len(w.offsets) // 2]
    garbage = b"\x00\xfd\xfe\x13garbage"  # (markers among it: false starts to refuse)
    path = tmp_path / "torn.tlog"
    path.write_bytes(good[:middle] + garbage + good[middle:] + good[:20])  # + a torn record
    source, sink = replayed(path)
    st = source.stats()
    assert st["corrupt_skips"] == 1 and st["bytes_skipped"] == len(garbage)
    assert st["torn_tail_bytes"] == 20
    assert st["crc_failures"] == 1  # (the stop report's "crc errors")
    assert st["records"] == w.frames  # every good record replayed
    assert sink.of(Position)[-1].relative_alt_m == pytest.approx(10.0)


def test_a_flipped_byte_costs_one_record_not_the_rest(tmp_path: Path) -> None:
    w = copter_flight(seconds=1.0)
    data = bytearray(w.data)
    data[8 + 12] ^= 0xFF  # inside the first frame's payload: its CRC fails
    path = tmp_path / "flipped.tlog"
    path.write_bytes(bytes(data))
    source, _ = replayed(path)
    st = source.stats()
    assert st["corrupt_skips"] == 1
    assert st["records"] == w.frames - 1


def test_a_missing_or_foreign_file_is_refused_by_the_path_key(tmp_path: Path) -> None:
    with pytest.raises(TlogError, match="no telemetry log"):
        check_file(tmp_path / "nothing.tlog")
    foreign = tmp_path / "notes.tlog"
    foreign.write_text("not a telemetry log at all, just some words\n" * 10)
    with pytest.raises(TlogError, match="not a MAVLink telemetry log"):
        check_file(foreign)
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    check_file(empty)  # a log with nothing in it: replays nothing
    r = Running("run", "--source", f"tlog:{foreign}", "--only", "console")
    assert r.finish() == 2
    err = [ln for ln in r.lines["stderr"] if ln.strip()]
    assert len(err) == 1 and "path" in err[0] and "not a MAVLink telemetry log" in err[0], err


def test_the_status_page_shows_the_replayed_flight(tmp_path: Path) -> None:
    """``run --source tlog:F --only http``: the replayed vehicle's position on /status.json."""
    path = tmp_path / "flight.tlog"
    path.write_bytes(copter_flight().data)
    port = free_port(socket.SOCK_STREAM)
    conf = tmp_path / "gateway.toml"
    conf.write_text(f'[[sources]]\ntype = "tlog"\npath = "{path}"\nloop = true\n')
    r = Running("run", "--config", str(conf), "--only", "http", "--http", f"127.0.0.1:{port}")
    found: dict[str, Any] = {}

    def shows_the_flight() -> bool:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/status.json",
                                        timeout=2) as resp:
                status = json.loads(resp.read())
        except OSError:
            return False  # (not listening yet)
        v = status["vehicles"].get("flight-1") or {}
        if v.get("position") and v.get("battery"):
            found.update(v)
        return bool(found)

    try:
        assert wait_for(shows_the_flight, WAIT, poll_s=0.1), r.text("stderr")
        pos = found["position"]
        assert pos["lat_deg"] == pytest.approx(47.3977, abs=1e-5)
        assert 0.0 <= pos["relative_alt_m"] <= 30.0
        assert found["battery"]["voltage_v"] == pytest.approx(12.6)
    finally:
        r.stop()


@pytest.mark.parametrize(("seconds", "speed"), [(3.0, 1.0), (6.0, 2.0)])
def test_a_ground_station_gets_the_flight_at_the_recorded_rate(
        tmp_path: Path, seconds: float, speed: float) -> None:
    """The issue's check: ``--source tlog:`` serves the flight to a pymavlink listener at the
    recorded rate within 5 % (the span of the frames received against the log's), or N times
    faster with ``--tlog-speed N`` (each a 3 s replay)."""
    flight = copter_flight(seconds=seconds)
    path = tmp_path / "flight.tlog"
    path.write_bytes(flight.data)
    with MavPeer(255, 190) as gcs:
        r = Running("run", "--source", f"tlog:{path}", "--only", "mavlink",
                    "--mavlink", f"udpout:127.0.0.1:{gcs.port}", "--tlog-speed", f"{speed:g}")
        try:
            assert r.finish(WAIT + 10) == 0, r.text("stderr")
        finally:
            r.stop()
        n = round(seconds * 10) + 1
        assert gcs.wait_until(lambda: len(gcs.timed("GLOBAL_POSITION_INT")) >= n, WAIT)
        timed = [(t, m) for t, m in gcs.timed("GLOBAL_POSITION_INT")
                 if m.get_srcSystem() == 1]
    assert [m.relative_alt for _, m in timed] == [i * 1000 for i in range(n)]  # as recorded
    span = timed[-1][0] - timed[0][0]
    assert span == pytest.approx(seconds / speed, rel=0.05)


def test_loop_starts_again_and_stop_ends_it(tmp_path: Path) -> None:
    """``loop``: the log again and again, flight time running on (the second pass's positions
    come through the rate limits like the first's); stop() ends it promptly."""
    w = copter_flight(seconds=1.0)
    path = tmp_path / "flight.tlog"
    path.write_bytes(w.data)
    source = TlogSource(TlogSourceOptions(path=str(path), speed=0.0, loop=True))
    sink = Collected()
    source.start(sink)
    try:
        assert wait_for(lambda: source.frames >= 3 * w.frames, WAIT)
        assert not source.done.is_set()
    finally:
        source.stop()
    assert source.done.is_set()
    alts = [p.relative_alt_m for p in sink.of(Position)]
    restarts = sum(1 for a, b in itertools.pairwise(alts) if b < a)
    assert restarts >= 2 and alts.count(10.0) >= 2  # every pass, to its end


def test_stop_in_the_middle_of_a_real_time_replay(tmp_path: Path) -> None:
    path = tmp_path / "flight.tlog"
    path.write_bytes(copter_flight(seconds=60.0).data)
    source = TlogSource(TlogSourceOptions(path=str(path)))
    sink = Collected()
    source.start(sink)
    assert wait_for(lambda: bool(sink.of(Position)), WAIT)
    source.stop(timeout=1.0)
    assert source.done.is_set()
    frames = source.frames
    assert frames < copter_flight(seconds=60.0).frames  # not the whole minute
    assert not wait_for(lambda: source.frames > frames, 0.5)  # and nothing after the stop


@needs_mavproxy
def test_a_telemetry_log_written_by_mavproxy_replays_frame_for_frame(tmp_path: Path) -> None:
    """The field's own writer: a stock MAVProxy logs a pymavlink vehicle; that ``.tlog``
    served by ``--source tlog:`` reaches a ground station as pymavlink's own log reader
    (mavutil) reads the file, and its last position is the gateway's too."""
    from pymavlink import mavutil

    port = free_port()
    log_path = tmp_path / "mav.tlog"
    mavproxy = subprocess.Popen(
        [sys.executable, "-m", "MAVProxy.mavproxy", f"--master=udpin:127.0.0.1:{port}",
         "--daemon", "--non-interactive", f"--logfile={log_path}"],
        cwd=tmp_path, env=mavproxy_env(tmp_path), stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    out = Output(mavproxy)
    try:
        deadline = time.monotonic() + 60.0
        assert out.wait_for("Waiting for heartbeat", deadline), out.text
        with MavPeer(1, 1, dest=("127.0.0.1", port)) as vehicle:
            vehicle.send(dev.MAVLink_heartbeat_message(
                dev.MAV_TYPE_QUADROTOR, dev.MAV_AUTOPILOT_ARDUPILOTMEGA,
                dev.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 5, dev.MAV_STATE_ACTIVE, 3))
            for i in range(31):
                vehicle.send(dev.MAVLink_global_position_int_message(
                    i * 100, 473_977_000 + i, 85_455_000, 500_000 + i * 1000, i * 1000, 0, 0,
                    0, 9000))
            vehicle.send(dev.MAVLink_statustext_message(dev.MAV_SEVERITY_INFO, b"logged"))
            assert out.wait_for("logged", deadline), out.text  # (all before it, in order)
    finally:
        stop_mavproxy(mavproxy)  # it writes its log out as it exits
        out.join(5)
        if mavproxy.stdout is not None:
            mavproxy.stdout.close()
    reader = mavutil.mavlink_connection(str(log_path), dialect="development")
    in_file = []
    while (m := reader.recv_match()) is not None:
        if m.get_srcSystem() == 1:  # the vehicle's (MAVProxy's own are addressed to it)
            in_file.append(m.get_type())
    assert in_file.count("GLOBAL_POSITION_INT") == 31 and "STATUSTEXT" in in_file

    with MavPeer(255, 190) as gcs:
        r = Running("run", "--source", f"tlog:{log_path}", "--only", "mavlink", "--only",
                    "console", "--mavlink", f"udpout:127.0.0.1:{gcs.port}", "--tlog-speed", "0")
        try:
            assert r.finish(WAIT + 10) == 0, r.text("stderr")
        finally:
            r.stop()
        assert gcs.wait_until(lambda: len(gcs.messages("STATUSTEXT")) >= 1, WAIT)
        served = [m.get_type() for m in gcs.messages() if m.get_srcSystem() == 1]
        last = gcs.messages("GLOBAL_POSITION_INT")[-1]
    assert served == in_file
    assert last.relative_alt == 30_000
    assert "following vehicle 1 as mav-1" in r.text("stderr")
