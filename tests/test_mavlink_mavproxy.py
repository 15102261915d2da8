"""What a stock ground station sees: MAVProxy 1.8.75 from PyPI against ``aurora-gateway run``.

A real MAVProxy (daemon, non-interactive, its home and logs in a temporary directory, the mode
map installed there by ``aurora-gateway mavlink-modes --install``) listens on a UDP port; the
gateway's simulated flight streams to it (``--mavlink udpout:…``).  Its own output says what a
user sees: ``link`` (packet loss, counted per system/component from sequence numbers by
pymavlink), its spoken alarms ("fence breach") and its prompt (the mode name).  Skipped when
MAVProxy is not installed: its PyPI requirements pull vtk, opencv-python and matplotlib
(~240 MB) that ``--daemon`` never uses, so it is not a test extra; install it with
``pip install --no-deps mavproxy==1.8.75 defusedxml pynmeagps``.

The mode map and SYS_STATUS are also checked without MAVProxy: the map with pymavlink's own
``mavutil`` in a subprocess (it reads the map at import and rewrites the environment), the
SYS_STATUS bits on :class:`~backends.mavlink.translate.AuroraVehicle` directly.
"""

from __future__ import annotations

import enum
import importlib.util
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from backends.mavlink import modes
from backends.mavlink.translate import AuroraVehicle
from dialects import aurora_mavlink as aurora
from dialects import states
from dialects.states import SimpleState
from gateway.commands import cli
from gateway.model import Battery, Position, Status

WAIT = 60.0  # deadline for the whole session (a few seconds when the machine is idle)
SIM_SPEED = 4  # the flight (pad → landed) in ~8 s
MIN_PACKETS = 300
GEOFENCE = aurora.MAV_SYS_STATUS_GEOFENCE
NOT_FAILED = aurora.MAV_SYS_STATUS_EXTENSION_USED - 1  # every subsystem bit

HAVE_MAVPROXY = importlib.util.find_spec("MAVProxy") is not None
needs_mavproxy = pytest.mark.skipif(
    not HAVE_MAVPROXY, reason="MAVProxy not installed (pip install --no-deps mavproxy==1.8.75 "
    "defusedxml pynmeagps)")

LINK_LINE = re.compile(r"link 1 (OK|DOWN) \((\d+) packets, \d+ bytes, [-\d.]+s delay, "
                       r"(\d+) lost, ([\d.]+)% loss")
HEALTH = re.compile(r"SYS_STATUS \{.*?onboard_control_sensors_health : (\d+)")


def _env(home: Path) -> dict[str, str]:
    return {**os.environ, "HOME": str(home), "PYTHONUNBUFFERED": "1"}


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Output:
    """A subprocess's stdout, read by a thread as it comes (MAVProxy's prompt has no newline);
    :meth:`wait_for` waits for a pattern with a deadline."""

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        assert proc.stdout is not None
        self._fd = proc.stdout.fileno()
        self._text = ""
        self._eof = False
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, name="mavproxy-out", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while chunk := os.read(self._fd, 4096):
            with self._cond:
                self._text += chunk.decode("utf-8", "replace")
                self._cond.notify_all()
        with self._cond:
            self._eof = True
            self._cond.notify_all()

    @property
    def text(self) -> str:
        with self._cond:
            return self._text

    def wait_for(self, pattern: str, deadline: float, start: int = 0) -> re.Match[str] | None:
        """The first match of ``pattern`` at or after offset ``start``, or None at the
        deadline (a ``time.monotonic()`` value) or when the process closed its output."""
        rx = re.compile(pattern)
        with self._cond:
            while True:
                m = rx.search(self._text, start)
                left = deadline - time.monotonic()
                if m or left <= 0 or self._eof:
                    return m
                self._cond.wait(left)

    def join(self, timeout: float) -> None:
        self._thread.join(timeout)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@dataclass
class Session:
    text: str  # MAVProxy's output up to the end of the watched flight (before shutdown)
    finished: bool  # the flight was watched to LANDED and one more `link` line
    gateway_log: Path

    def why(self) -> str:
        state = "" if self.finished else "(deadline passed before LANDED) "
        log = self.gateway_log.read_text(errors="replace") if self.gateway_log.exists() else ""
        return f"{state}MAVProxy said:\n{self.text[-6000:]}\ngateway:\n{log[-2000:]}"


def _watch_flight(home: Path) -> Session:
    """Install the mode map in ``home``, start MAVProxy there and the gateway streaming to it;
    return MAVProxy's output once it has shown the flight to LANDED (or the deadline passed).
    Both processes are stopped before returning, whatever happens."""
    installed = subprocess.run(
        [sys.executable, "-m", "gateway", "mavlink-modes", "--install"], env=_env(home),
        capture_output=True, text=True, timeout=60, check=False)
    assert installed.returncode == 0, installed.stderr
    port = _free_udp_port()
    mavproxy = subprocess.Popen(
        [sys.executable, "-m", "MAVProxy.mavproxy", f"--master=udpin:127.0.0.1:{port}",
         "--daemon", "--non-interactive", "--cmd",
         "repeat add 1 link;repeat add 1 status SYS_STATUS"],
        cwd=home, env=_env(home), stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT)
    gateway_log = home / "gateway.log"
    gateway: subprocess.Popen[bytes] | None = None
    out = Output(mavproxy)
    try:
        deadline = time.monotonic() + WAIT
        assert out.wait_for(r"Waiting for heartbeat", deadline), out.text
        with gateway_log.open("wb") as log:
            gateway = subprocess.Popen(
                [sys.executable, "-m", "gateway", "run", "--mavlink",
                 f"udpout:127.0.0.1:{port}", "--sim-speed", str(SIM_SPEED),
                 "--disable", "zenoh", "--disable", "crsf", "--disable", "hc12",
                 "--disable", "console", "--status-interval", "0", "--duration", str(WAIT)],
                cwd=home, env=_env(home), stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        landed = out.wait_for(r"LANDED> ", deadline)
        last = landed and out.wait_for(LINK_LINE.pattern, deadline, landed.end())
        # taken before shutdown, when MAVProxy prints "Unloading module fence" and the like
        return Session(out.text, bool(last), gateway_log)
    finally:
        for proc in (gateway, mavproxy):
            if proc is not None:
                _stop(proc)
        out.join(5)
        if mavproxy.stdout is not None:
            mavproxy.stdout.close()


@pytest.fixture(scope="module")
def seen(tmp_path_factory: pytest.TempPathFactory) -> Session:
    """One flight watched by MAVProxy, shared by the checks below."""
    if not HAVE_MAVPROXY:
        pytest.skip("MAVProxy not installed")
    return _watch_flight(tmp_path_factory.mktemp("mavproxy-home"))


@needs_mavproxy
def test_mavproxy_counts_no_packet_loss_on_loopback(seen: Session) -> None:
    links = [(int(m[2]), int(m[3]), float(m[4])) for m in LINK_LINE.finditer(seen.text)]
    assert seen.finished, seen.why()
    assert links[-1][0] >= MIN_PACKETS, seen.why()
    # every line: a dialect message sharing the autopilot's sequence shows up as "lost" here
    assert [(lost, loss) for _, lost, loss in links] == [(0, 0.0)] * len(links), seen.why()


@needs_mavproxy
def test_mavproxy_raises_no_fence_alarm(seen: Session) -> None:
    assert seen.finished, seen.why()
    healths = [int(h) for h in HEALTH.findall(seen.text)]
    assert len(healths) >= 3, seen.why()  # MAVProxy did take in SYS_STATUS, several times
    assert all(h & GEOFENCE for h in healths), seen.why()
    assert "fence" not in seen.text.lower(), seen.why()  # "fence breach", "status FEN"…


@needs_mavproxy
def test_mavproxy_shows_the_rocket_s_mode_names_with_the_shipped_map(seen: Session) -> None:
    assert seen.finished, seen.why()
    prompts = [p for p in re.findall(r"(\S+)> ", seen.text) if p != "MAV"]  # MAVProxy's own
    flight = [p for i, p in enumerate(prompts) if i == 0 or prompts[i - 1] != p]
    names = [s.name for s in SimpleState if s is not SimpleState.ERROR]
    assert [p for p in flight if p in names] == flight, seen.why()  # nothing but state names
    assert flight.index("BOOST") < flight.index("APOGEE") < flight.index("LANDED"), seen.why()
    assert "Mode(" not in seen.text, seen.why()
    assert "AP: #BOOST" in seen.text, seen.why()  # the names stay in STATUSTEXT too


# -- the mode map, without MAVProxy ----------------------------------------------------------

def test_the_mode_map_is_the_state_tables() -> None:
    assert modes.MAV_TYPE_ROCKET == aurora.MAV_TYPE_ROCKET  # what our HEARTBEAT says
    assert modes.rocket_modes() == {int(s): s.name for s in SimpleState}
    assert modes.custom_mode_map() == {"9": {str(int(s)): s.name for s in SimpleState}}


class _OtherState(enum.IntEnum):
    IDLE = 0
    PAD = 1
    BOOST = 2
    COAST = 3


def test_a_number_two_machines_name_differently_is_named_both(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(states.STATE_MACHINES, 7, _OtherState)
    both = modes.rocket_modes()
    assert both[0] == "IDLE" and both[2] == "BOOST"  # the machines agree: one name
    assert both[1] == "ARMED/PAD" and both[3] == "BURNOUT/COAST"
    assert both[8] == "ERROR"  # only one machine has it
    assert modes.rocket_modes(7) == {0: "IDLE", 1: "PAD", 2: "BOOST", 3: "COAST"}


def test_install_merges_without_clobbering_other_vehicle_types(tmp_path: Path) -> None:
    path = tmp_path / ".pymavlink" / "custom_mode_map.json"
    path.parent.mkdir()
    theirs = {"1": {"0": "MANUAL", "15": "GUIDED"}, "9": {"0": "OLD", "42": "STALE"}}
    path.write_text(json.dumps(theirs))
    assert modes.install(path) == path
    merged = json.loads(path.read_text())
    assert merged == {"1": theirs["1"], **modes.custom_mode_map()}
    assert modes.install(path) == path  # again: the same file
    assert json.loads(path.read_text()) == merged
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left


def test_install_refuses_a_file_it_cannot_read_and_leaves_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "map.json"
    path.write_text("{not json")
    # a foreign file: bad input, 2 (issue 23's exit-code table)
    assert cli.main(["mavlink-modes", "--install", "--file", str(path)]) == 2
    assert "not valid JSON" in capsys.readouterr().err
    assert path.read_text() == "{not json"
    path.write_text("[1, 2]")
    assert cli.main(["mavlink-modes", "--install", "--file", str(path)]) == 2
    assert path.read_text() == "[1, 2]"


def test_the_command_prints_the_map(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["mavlink-modes"]) == 0
    assert json.loads(capsys.readouterr().out) == modes.custom_mode_map()


def test_pymavlink_names_the_rocket_s_modes_from_the_installed_map(tmp_path: Path) -> None:
    """``mavutil`` (what MAVProxy and the other pymavlink tools name modes with) in a
    subprocess whose HOME has the map installed by the command."""
    env = _env(tmp_path)
    done = subprocess.run([sys.executable, "-m", "gateway", "mavlink-modes", "--install"],
                          env=env, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / ".pymavlink" / "custom_mode_map.json").exists()
    probe = (
        "from pymavlink import mavutil\n"
        "m = mavutil.mavlink\n"
        "for state in range(10):\n"
        "    hb = m.MAVLink_heartbeat_message(m.MAV_TYPE_ROCKET, m.MAV_AUTOPILOT_GENERIC,\n"
        "        m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, state, m.MAV_STATE_STANDBY, 3)\n"
        "    print(mavutil.mode_string_v10(hb))\n")
    shown = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                           text=True, timeout=60, check=False)
    assert shown.returncode == 0, shown.stderr
    assert shown.stdout.split() == [s.name for s in SimpleState] + ["Mode(9)"]


# -- SYS_STATUS, without MAVProxy -------------------------------------------------------------

IMU = aurora.MAV_SYS_STATUS_SENSOR_3D_GYRO | aurora.MAV_SYS_STATUS_SENSOR_3D_ACCEL
BARO = aurora.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
LOG = aurora.MAV_SYS_STATUS_LOGGING
PREARM = aurora.MAV_SYS_STATUS_PREARM_CHECK
GPS = aurora.MAV_SYS_STATUS_SENSOR_GPS
BATTERY = aurora.MAV_SYS_STATUS_SENSOR_BATTERY
ROCKET = IMU | BARO | LOG | PREARM
ALL_OK = Status.make_flags(imu_ok=True, baro_ok=True, calibrated=True, log_ready=True)


def _bits(v: AuroraVehicle) -> tuple[int, int, int]:
    s = v.sys_status()
    return (s.onboard_control_sensors_present, s.onboard_control_sensors_enabled,
            s.onboard_control_sensors_health)


def test_sys_status_before_any_status_shows_nothing_failed() -> None:
    assert _bits(AuroraVehicle()) == (ROCKET, 0, NOT_FAILED)


def test_sys_status_health_is_every_bit_but_the_failed_ones() -> None:
    v = AuroraVehicle()
    v.on_status(Status(1000, SimpleState.IDLE, 0, ALL_OK))
    assert _bits(v) == (ROCKET, ROCKET, NOT_FAILED)  # geofence, RC … healthy: not failed
    v.on_status(Status(2000, SimpleState.IDLE, 0, Status.make_flags(imu_ok=True, calibrated=True)))
    present, enabled, health = _bits(v)
    assert (present, enabled) == (ROCKET, ROCKET)
    assert health == NOT_FAILED & ~(BARO | LOG | PREARM)
    assert health & GEOFENCE


def test_sys_status_adds_gps_and_battery_once_the_rocket_has_them() -> None:
    v = AuroraVehicle()
    v.on_status(Status(1000, SimpleState.IDLE, 0, ALL_OK))
    v.on_battery(Battery(7.9, battery_id=0))
    assert _bits(v) == (ROCKET | BATTERY, ROCKET | BATTERY, NOT_FAILED)
    v.on_position(Position(47.0, 8.0, fix_type=aurora.GPS_FIX_TYPE_3D_FIX))
    assert _bits(v) == (ROCKET | BATTERY | GPS, ROCKET | BATTERY | GPS, NOT_FAILED)
    v.on_position(Position(47.0, 8.0, fix_type=aurora.GPS_FIX_TYPE_NO_FIX))
    assert _bits(v)[2] == NOT_FAILED & ~GPS
