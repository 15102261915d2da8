"""Per-flight recordings (``--record-dir``) and the end-of-run flight summary (issue 15).

Expected figures come from the flight's own definition (a ballistic arc whose apogee is known
in closed form, the states in the order the test sends them) or from the recording read back
with :func:`gateway.recording.read` and the wire decoder — never from the summary under test.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from dialects.states import SM_TYPE_SIMPLE, SimpleState
from gateway import config, recording
from gateway.app import Gateway
from gateway.commands import cli
from gateway.config import ConfigError, GatewayConfig
from gateway.flight_summary import (
    FlightSummary,
    crc_errors,
    new_recording,
    recording_name,
    safe_name,
)
from gateway.model import SmUpdate, Status
from gateway.wire import Decoder

CONSOLE_SCRIPT = Path(sys.executable).parent / "aurora-gateway"
TIMEOUT_S = 30.0
NAME_RE = re.compile(r"^(\d{4}-\d\d-\d\dT\d\d-\d\d-\d\d)-(.+)\.aur$")

V0 = 50.0  # m/s at liftoff
G = 9.8
DT = 0.1  # s between updates


def _update(state: SimpleState, t_ms: int, alt: float, origin: str = "rocket1") -> SmUpdate:
    armed = SimpleState.ARMED <= state <= SimpleState.LANDED
    return SmUpdate(t_ms, int(state), armed, SM_TYPE_SIMPLE, alt, 0.0, 0.0, 0.0, 0.0, 0.0,
                    0.0, origin=origin)


def _flight(t0_ms: int, origin: str = "rocket1") -> list[SmUpdate]:
    """IDLE, ARMED, then a ballistic arc at V0 (BOOST until the top, APOGEE, MAIN down), LANDED,
    and IDLE again (disarmed): one update every DT from ``t0_ms``."""
    msgs = [_update(SimpleState.IDLE, t0_ms, 0.0, origin),
            _update(SimpleState.ARMED, t0_ms + 100, 0.0, origin),
            _update(SimpleState.ARMED, t0_ms + 200, 0.0, origin)]
    launch_ms = t0_ms + 300
    k = 0
    while True:
        t = k * DT
        alt = V0 * t - G * t * t / 2
        if alt < 0:
            break
        state = (SimpleState.BOOST if V0 - G * t > 0 else
                 SimpleState.APOGEE if alt > 0.9 * V0 * V0 / (2 * G) else SimpleState.MAIN)
        msgs.append(_update(state, launch_ms + round(t * 1000), alt, origin))
        k += 1
    end = launch_ms + round(k * DT * 1000)
    msgs += [_update(SimpleState.LANDED, end, 0.0, origin),
             _update(SimpleState.IDLE, end + 100, 0.0, origin)]
    return msgs


# -- the summary, from a known sequence --------------------------------------------------------

def test_max_altitude_and_apogee_time_of_a_ballistic_arc() -> None:
    now = [0.0]
    summary = FlightSummary(clock=lambda: now[0])
    msgs = _flight(10_000)
    for i, msg in enumerate(msgs):
        now[0] = 1_700_000_000.0 + i  # the wall time each update passes the gateway
        summary.feed(msg)
        summary.feed(Status(msg.timestamp_ms, msg.state, SM_TYPE_SIMPLE, 0, origin="rocket1"))
    v = summary.vehicles["rocket1"]
    # closed form: apogee at t = V0/G, height V0²/2G; sampled every DT, the best sample is
    # within DT/2 of it in time and below it by at most G (DT/2)² / 2
    t_top = V0 / G
    h_top = V0 * V0 / (2 * G)
    assert v.max_altitude_m is not None
    assert h_top - G * (DT / 2) ** 2 / 2 - 1e-9 <= v.max_altitude_m <= h_top
    assert v.apogee_after_launch_s is not None
    assert abs(v.apogee_after_launch_s - t_top) <= DT / 2 + 1e-9
    # the wall time of the very update that carried the highest altitude
    top = max(range(len(msgs)), key=lambda i: msgs[i].altitude_m)
    assert v.apogee_wall == 1_700_000_000.0 + top
    assert v.states == ["IDLE", "ARMED", "BOOST", "APOGEE", "MAIN", "LANDED"]
    assert v.launches == 1
    assert v.updates == len(msgs)  # STATUS is not an update


def test_a_new_flight_begins_when_the_vehicle_arms_again_after_flying() -> None:
    summary = FlightSummary()
    first = _flight(0)
    second = _flight(60_000)
    starts = [i for i, m in enumerate(first + second) if summary.feed(m)]
    # arming before the first flight is not a new one (the run's file holds it); arming after
    # it is, at the second flight's first ARMED update
    assert starts == [len(first) + 1]
    assert summary.vehicles["rocket1"].launches == 2


def test_vehicles_are_kept_apart_and_nan_altitude_is_ignored() -> None:
    summary = FlightSummary()
    summary.feed(_update(SimpleState.IDLE, 0, 5.0, "a"))
    summary.feed(_update(SimpleState.IDLE, 0, float("nan"), "a"))
    summary.feed(_update(SimpleState.IDLE, 0, 7.0, "b"))
    assert summary.vehicles["a"].max_altitude_m == 5.0
    assert summary.vehicles["b"].max_altitude_m == 7.0
    assert summary.vehicles["a"].apogee_after_launch_s is None  # never launched


def test_crc_errors_add_every_crc_counter_nested_or_not() -> None:
    stats: dict[str, dict[str, Any]] = {"serial": {"crc_failures": 3, "frames": 10},
             "mav": {"endpoints": {"a": {"crc_errors": 2}, "b": {"crc_errors": 1}}},
             "sim": {"sent": 5}}
    assert crc_errors(stats) == {"serial": 3, "mav": 3, "sim": 0}


def test_crc_errors_count_checksums_and_the_backends_that_check_frames() -> None:
    """XBee's API-frame checksum failures count as well as CRCs, and so do the backends that
    read frames (a CRSF receiver, MAVLink endpoints); a backend that checks none is left out,
    and one named like a source is told apart."""
    sources = {"xbee": {"link": {"bad_checksum": 58555}, "frames": 9},
               "crsf": {"crc_failures": 0}}
    backends = {"crsf": {"rx": {"crc_failures": 4}}, "mavlink": {"endpoints": {
        "udpout:x": {"crc_errors": 2}}}, "console": {"sent": 3}, "flag": {"crc_ok": True}}
    assert crc_errors(sources, backends) == {"xbee": 58555, "crsf": 0, "crsf (backend)": 4,
                                             "mavlink": 2}


# -- file names ---------------------------------------------------------------------------------

def test_recording_names_are_new_files_named_by_utc_start_and_source(tmp_path: Path) -> None:
    t = datetime(2026, 11, 23, 14, 2, 11, tzinfo=UTC).timestamp()
    d = tmp_path / "a" / "b"
    first = new_recording(d, t, "/dev/ttyUSB0")
    second = new_recording(d, t, "/dev/ttyUSB0")  # the same second: another file
    assert first.name == "2026-11-23T14-02-11-dev_ttyUSB0.aur"
    assert second.name == "2026-11-23T14-02-11-dev_ttyUSB0-2.aur"
    assert first.stat().st_size == 0 and second.stat().st_size == 0
    assert safe_name("mavlink:udpin:0.0.0.0:14551") == "mavlink_udpin_0.0.0.0_14551"
    assert recording_name(t, "replay:old.aur") == "2026-11-23T14-02-11-replay_old.aur"


def test_the_gateway_opens_a_new_recording_for_each_flight(tmp_path: Path) -> None:
    cfg = GatewayConfig()
    cfg.gateway.update(record_dir=str(tmp_path / "flights"), status_interval_s=0.0)
    gw = Gateway(cfg)
    gw.start()
    first, second = _flight(0), _flight(60_000)
    try:
        for msg in first + second:
            gw.ingest(msg)
    finally:
        summary = gw.stop()
    paths = [Path(p) for p in summary["recordings"]]
    assert len(paths) == 2
    # one file per vehicle per flight, named after the vehicle (issue 22: no longer a file
    # per run named after the sources, opened before any message)
    assert paths[0].name.endswith("-rocket1.aur")
    assert paths[1].name.endswith(("-rocket1.aur", "-rocket1-2.aur"))  # armed again
    assert sorted(p.name for p in (tmp_path / "flights").iterdir()) == sorted(
        p.name for p in paths)
    got = []
    for path in paths:
        dec = Decoder()
        got.append([m for _, frame in recording.read(path) for m in dec.feed(frame)])
    want = [[m.fields() for m in first + second[:1]], [m.fields() for m in second[1:]]]
    assert [[m.fields() for m in msgs] for msgs in got] == want
    assert summary["recorded"] == len(first) + len(second)


# -- the command line -----------------------------------------------------------------------------

def test_record_and_record_dir_together_are_one_line_and_status_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = cli.main(["run", "--only", "console", "--record", str(tmp_path / "f.aur"),
                     "--record-dir", str(tmp_path / "d")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "--record" in err and "--record-dir" in err, err
    assert not (tmp_path / "d").exists() and not (tmp_path / "f.aur").exists()
    with pytest.raises(ConfigError, match=r"gateway\.record, gateway\.record_dir"):
        config.parse({"gateway": {"record": "f.aur", "record_dir": "d"}})


def test_run_record_dir_writes_a_named_readable_recording_and_reports_the_flight(
        tmp_path: Path) -> None:
    d = tmp_path / "new" / "flights"
    before = time.time()
    r = subprocess.run([str(CONSOLE_SCRIPT), "run", "--source", "sim", "--sim-speed", "20",
                        "--duration", "1", "--record-dir", str(d), "--only", "console",
                        "--console-interval", "100", "--status-interval", "0"],
                       capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path)
    after = time.time()
    assert r.returncode == 0, r.stderr
    files = list(d.iterdir())
    assert len(files) == 1, files  # 1 s at 20× is 20 s of the sim: one flight at most
    m = NAME_RE.match(files[0].name)
    assert m is not None and m.group(2) == "sim", files[0].name
    started = datetime.strptime(m.group(1), "%Y-%m-%dT%H-%M-%S").replace(tzinfo=UTC)
    assert int(before) <= started.timestamp() <= after
    dec = Decoder()
    msgs = [msg for _, frame in recording.read(files[0]) for msg in dec.feed(frame)]
    updates = [msg for msg in msgs if isinstance(msg, SmUpdate)]
    assert updates and dec.stats.crc_failures == 0
    # the summary lines, against what the recording holds
    states: list[str] = []
    for u in updates:
        if u.state_name not in states:
            states.append(u.state_name)
    top = max(u.altitude_m for u in updates)
    lines = r.stderr.splitlines()
    flight = [ln for ln in lines if ln.startswith("flight sim: ")]
    assert len(flight) == 1, r.stderr
    assert f"max altitude {top:.1f} m" in flight[0]
    assert flight[0].endswith("states " + " ".join(states))
    assert f"{len(updates)} updates" in flight[0]
    assert "crc errors: 0 (sim 0)" in lines
    assert f"recording: {files[0]}" in lines
    stopped = [ln for ln in lines if ln.startswith("stopped after ")]
    assert len(stopped) == 1 and f"{len(msgs)} messages recorded" in stopped[0]
    assert "dropped: nothing" in lines


def test_run_record_dir_writes_a_file_per_vehicle_and_reports_each(tmp_path: Path) -> None:
    d = tmp_path / "flights"
    r = subprocess.run([str(CONSOLE_SCRIPT), "run", "--source", "alpha=sim", "--source",
                        "beta=sim", "--sim-speed", "20", "--duration", "1", "--record-dir",
                        str(d), "--only", "console", "--console-interval", "100",
                        "--status-interval", "0"],
                       capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    files = sorted(d.iterdir())
    names = [NAME_RE.match(f.name) for f in files]
    assert [m.group(2) if m else f.name for m, f in zip(names, files, strict=True)] == [
        "alpha", "beta"]
    lines = r.stderr.splitlines()
    for f, vehicle in zip(files, ("alpha", "beta"), strict=True):
        recs = list(recording.read_records(f))
        assert recs and {(x.vehicle, x.source) for x in recs} == {(vehicle, vehicle)}
        dec = Decoder()
        updates = [m for x in recs for m in dec.feed(x.frame) if isinstance(m, SmUpdate)]
        flight = [ln for ln in lines if ln.startswith(f"flight {vehicle}: ")]
        assert len(flight) == 1 and f"{len(updates)} updates" in flight[0], r.stderr
        assert f"recording: {f}" in lines


def test_the_json_stop_report_keys_each_flight_by_its_vehicle(tmp_path: Path) -> None:
    r = subprocess.run([str(CONSOLE_SCRIPT), "run", "--source", "alpha=sim", "--source",
                        "beta=sim", "--sim-speed", "20", "--duration", "1", "--only", "console",
                        "--console-interval", "100", "--status-interval", "0",
                        "--log-format", "json"],
                       capture_output=True, text=True, timeout=TIMEOUT_S, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    objs = [json.loads(ln) for ln in r.stderr.splitlines()]  # nothing but JSON
    stops = [o for o in objs if o.get("event") == "stop"]  # the stop report: one object
    assert len(stops) == 1, objs
    flights = stops[0]["summary"]["flights"]
    assert set(flights) == {"alpha", "beta"}
    for name, figures in flights.items():
        line = next(ln for ln in stops[0]["report"] if ln.startswith(f"flight {name}: "))
        assert figures["updates"] > 0 and f"{figures['updates']} updates" in line
        assert figures["states"][0] == "IDLE"
