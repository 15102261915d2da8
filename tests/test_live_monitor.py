"""``aurora-gateway monitor`` (gateway/commands/live.py, gateway/commands/monitor.py).

The view model is fed the simulator's flight and rendered into a fixed-size console; the
expected numbers come from the messages themselves and the flight model's own figures, never
from the monitor.  The command runs as the console script, stdout a pipe, with a fake
``espeak-ng`` on PATH that records what it is asked to say.
"""

from __future__ import annotations

import errno
import fcntl
import os
import pty
import re
import select
import signal
import stat
import struct
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path

import pytest
from rich.console import Console

from dialects.states import SimpleState
from gateway.commands.live import (
    EndpointRow,
    LiveState,
    RateMeter,
    Speaker,
    endpoint_row,
    plain_line,
    plain_lines,
    render,
)
from gateway.commands.monitor import read_keys
from gateway.flight import FlightModel, FlightProfile
from gateway.model import Battery, LinkEvent, Position, SmUpdate, Status
from gateway.sources.sim import flight_messages

CONSOLE = Path(sys.executable).with_name("aurora-gateway")
ANSI = re.compile(r"\x1b\[")


def one_flight() -> tuple[FlightModel, list[tuple[float, SmUpdate | Status]]]:
    model = FlightModel(FlightProfile())
    return model, list(flight_messages(model, rate_hz=10.0, status_hz=1.0, cycles=1))


def feed_until(state: LiveState, msgs: list[tuple[float, SmUpdate | Status]],
               stop_state: SimpleState) -> tuple[float, SmUpdate]:
    """Feed messages (their simulated time as ``now``) up to the first SM update in
    ``stop_state``; returns its time and the update."""
    for t, msg in msgs:
        state.feed(msg, t)
        state.set_counters(t, state.messages, 0)
        if isinstance(msg, SmUpdate) and msg.state == stop_state:
            return t, msg
    raise AssertionError(f"the flight never reached {stop_state.name}")


def screen(state: LiveState, now: float) -> str:
    console = Console(width=100, height=30, record=True, force_terminal=False,
                      color_system=None, file=open(os.devnull, "w"))  # noqa: SIM115
    try:
        console.print(render(state, now))
        return console.export_text()
    finally:
        console.file.close()


def test_view_shows_the_flight_in_main() -> None:
    model, msgs = one_flight()
    state = LiveState(link_timeout_s=3.0)
    t, last = feed_until(state, msgs, SimpleState.MAIN)
    fed = [m for tm, m in msgs if tm <= t and isinstance(m, SmUpdate)]
    top = max(m.altitude_m for m in fed)
    assert abs(top - model.apogee_altitude_m) < 1.0  # the samples see the model's apogee
    text = screen(state, t)
    assert "MAIN" in text
    assert f"{last.altitude_m:.1f} m" in text
    assert re.search(rf"max altitude\s+{top:.1f} m", text)
    assert f"{last.velocity_mps:.1f} m/s" in text
    assert re.search(r"link\s+up", text)
    assert re.search(r"last update\s+0\.0 s ago", text)
    assert len(text.splitlines()) == 30


def test_silence_takes_the_link_down_and_link_events_name_sources() -> None:
    _, msgs = one_flight()
    state = LiveState(link_timeout_s=3.0)
    t, _ = feed_until(state, msgs, SimpleState.BOOST)
    assert re.search(r"link\s+DOWN", screen(state, t + 3.5))
    assert re.search(r"last update\s+3\.5 s ago", screen(state, t + 3.5))
    state.feed(LinkEvent("radio", True), t)
    assert re.search(r"radio\s+up", screen(state, t))
    state.feed(LinkEvent("radio", False, 3.0), t + 3)
    text = screen(state, t + 3)
    assert re.search(r"link\s+DOWN", text) and re.search(r"radio\s+DOWN", text)


def test_announcements_follow_the_state_changes_with_the_apogee_altitude() -> None:
    _, msgs = one_flight()
    said: list[str] = []
    state = LiveState(on_announce=said.append)
    expected: list[str] = []
    prev: SmUpdate | None = None
    top = float("-inf")
    for t, msg in msgs:
        state.feed(msg, t)
        if not isinstance(msg, SmUpdate):
            continue
        top = max(top, msg.altitude_m)
        if prev is not None and prev.state != msg.state:
            name = SimpleState(msg.state).name.lower()
            expected.append(f"apogee, {top:.0f} meters" if name == "apogee" else name)
        prev = msg
    assert said == expected
    assert said[:3] == ["armed", "boost", "burnout"] and said[-1] == "idle"
    assert "landed" in said and "main" in said


def test_position_and_battery_when_present() -> None:
    state = LiveState()
    assert "position" not in screen(state, 0.0) and "battery" not in screen(state, 0.0)
    state.feed(Position(47.123456, 8.654321, satellites=9), 0.0)
    state.feed(Battery(7.42, remaining_pct=81), 0.0)
    text = screen(state, 0.0)
    assert "47.123456, 8.654321" in text and re.search(r"satellites\s+9", text)
    assert "7.42 V 81%" in text
    fields = dict(tok.split("=", 1) for tok in plain_line(state, 0.0).split(" "))
    assert (fields["lat"], fields["lon"], fields["batt_v"]) == ("47.123456", "8.654321", "7.42")


def test_plain_line_is_key_value_without_escapes() -> None:
    _, msgs = one_flight()
    state = LiveState()
    t, last = feed_until(state, msgs, SimpleState.APOGEE)
    line = plain_line(state, t)
    assert not ANSI.search(line)
    fields = dict(tok.split("=", 1) for tok in line.split(" "))
    assert fields["state"] == "APOGEE" and fields["armed"] == "yes"
    assert float(fields["alt_m"]) == pytest.approx(last.altitude_m, abs=0.05)
    assert fields["link"] == "up" and fields["crc_errors"] == "0"
    # 10 SM updates + 1 STATUS per simulated second, sampled every message
    assert float(fields["updates_per_s"]) == pytest.approx(10.0, rel=0.1)


def test_rate_meter_over_its_window() -> None:
    r = RateMeter(window_s=2.0)
    assert r.rate(0.0) is None
    for i in range(11):  # 5 events per second for 10 s
        r.sample(i * 1.0, i * 5)
    assert r.rate(10.0) == pytest.approx(5.0)
    assert r.rate(20.0) is None  # nobody sampled for longer than the window


def test_endpoint_rows_from_stats() -> None:
    row = endpoint_row("zenoh", {"received": 7, "lost": 2, "dropped_queue_full": 1,
                                 "crc_failures": 0})
    assert row == EndpointRow("zenoh", received=7, dropped=3, errors=0)
    row = endpoint_row("mavlink", {"sent": 10, "dropped": 1, "errors": 2, "link": 1,
                                   "clients": 3})
    assert (row.sent, row.dropped, row.errors, row.clients, row.link) == (10, 1, 2, 3, True)
    state = LiveState()
    state.set_endpoints([row])
    assert re.search(r"mavlink\s+–\s+10\s+1\s+2\s+3\s+up", screen(state, 0.0))


def open_gate(gate: Path, proc: subprocess.Popen[bytes]) -> None:
    """Let the fake speaker reading ``gate`` (a FIFO) finish: open and close the writing end
    once it has opened its reading end (within a deadline, while it is alive)."""
    deadline = time.monotonic() + 5.0
    while True:
        try:
            fd = os.open(gate, os.O_WRONLY | os.O_NONBLOCK)
        except OSError as exc:  # ENXIO: the script has not opened its end yet
            if exc.errno != errno.ENXIO or proc.poll() is not None:
                raise
            assert time.monotonic() < deadline, "the fake speaker never opened its gate"
            threading.Event().wait(0.01)
            continue
        os.close(fd)
        return


def test_speaker_drops_while_busy(tmp_path: Path) -> None:
    gate = tmp_path / "gate"
    os.mkfifo(gate)
    script = tmp_path / "say"
    script.write_text(f"#!/bin/sh\nread x < {gate}\n")  # speaks until the gate opens
    script.chmod(script.stat().st_mode | stat.S_IXUSR)
    sp = Speaker(str(script))
    assert sp.say("boost") is True
    assert sp.say("burnout") is False and sp.dropped == 1
    proc = sp._proc
    assert proc is not None
    open_gate(gate, proc)
    proc.wait(timeout=5)
    assert sp.say("apogee") is True and sp.spoken == 2
    proc = sp._proc
    assert proc is not None
    open_gate(gate, proc)
    proc.wait(timeout=5)


def test_speaker_survives_a_program_that_cannot_start(tmp_path: Path) -> None:
    sp = Speaker(str(tmp_path / "missing"))
    assert sp.say("boost") is False and sp.failed == 1


def two_rockets(state: LiveState) -> None:
    """alpha near 100 m and beta near 500 m, from sources a-src and b-src (beta's link down)."""
    state.feed(LinkEvent("a-src", True), 0.0)
    state.feed(LinkEvent("b-src", False, 3.0), 0.0)
    for i in range(10):
        for name, alt, st in (("alpha", 100.0, SimpleState.BOOST),
                              ("beta", 500.0, SimpleState.APOGEE)):
            state.feed(SmUpdate(timestamp_ms=100 * i, state=st, armed=True, sm_type=0,
                                altitude_m=alt + i, acceleration_mps2=0.0,
                                accel_vert_mps2=0.0, velocity_mps=float(i), roll_rad=0.0,
                                pitch_rad=0.0, yaw_rad=0.0, origin=name[0] + "-src",
                                vehicle=name), 0.1 * i)
    state.feed(Battery(7.9, vehicle="beta"), 1.0)


def test_a_row_per_vehicle_and_the_detail_of_the_selected_one() -> None:
    state = LiveState()
    two_rockets(state)
    text = screen(state, 1.0)
    assert re.search(r"▶\s+alpha\s+BOOST\s+yes\s+109\.0\s+109\.0\s+9\.0\s+up\s+0\.1", text)
    assert re.search(r"│\s+beta\s+APOGEE\s+yes\s+509\.0\s+509\.0\s+9\.0\s+DOWN\s+0\.1", text)
    # the detail: the first vehicle heard until another is selected
    assert "vehicle alpha" in text and "vehicle beta" not in text
    assert re.search(r"altitude\s+109\.0 m", text) and "7.90 V" not in text
    assert state.select(1) == "beta"
    text = screen(state, 1.0)
    assert "vehicle beta" in text and re.search(r"altitude\s+509\.0 m", text)
    assert "7.90 V" in text and re.search(r"▶\s+beta", text)
    assert state.select(1) == "alpha" and state.select(-1) == "beta"  # wrapping
    state.set_order(["beta", "alpha"])  # the configured sources' order comes first
    assert [v.name for v in state.vehicle_list()] == ["beta", "alpha"]
    assert re.search(r"▶\s+beta\s+APOGEE.*\n.*alpha\s+BOOST", screen(state, 1.0))


def test_plain_lines_one_per_vehicle_with_its_own_values() -> None:
    state = LiveState()
    two_rockets(state)
    lines = plain_lines(state, 1.0)
    fields = [dict(tok.split("=", 1) for tok in line.split(" ")) for line in lines]
    assert [f["vehicle"] for f in fields] == ["alpha", "beta"]
    assert [f["alt_m"] for f in fields] == ["109.0", "509.0"]
    assert [f["link"] for f in fields] == ["up", "DOWN"]
    assert "batt_v" not in fields[0] and fields[1]["batt_v"] == "7.90"
    assert plain_lines(LiveState(), 0.0)[0].startswith("vehicle=– state=–")  # nothing yet


def test_announcements_name_the_vehicle_when_there_are_several() -> None:
    said: list[str] = []
    state = LiveState(on_announce=said.append)
    two_rockets(state)
    state.feed(SmUpdate(2000, SimpleState.APOGEE, True, 0, 110.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                        vehicle="alpha"), 2.0)
    assert said == ["alpha apogee, 110 meters"]


def test_vehicles_past_the_cap_are_counted_not_kept() -> None:
    from gateway.commands.live import MAX_VEHICLES

    state = LiveState()
    for i in range(MAX_VEHICLES + 5):
        state.feed(Battery(7.0, vehicle=f"v{i}"), 0.0)
    assert len(state.vehicles) == MAX_VEHICLES and state.vehicles_refused == 5
    assert "5 messages of more refused" in screen(state, 0.0)


def test_keys_select_and_quit() -> None:
    assert read_keys(b"\x1b[B\x1b[Aj\tk\x1b[Zxq") == [1, -1, 1, 1, -1, -1, None]
    assert read_keys(b"\x1bOB") == [1] and read_keys(b"zz") == []


# -- the console script -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def monitor_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str, Path]:
    """One run of ``monitor --source sim --sim-speed 20 --speak`` into a pipe, with a fake
    espeak-ng that appends each text it is given to a file; (stdout, stderr, that file)."""
    bindir = tmp_path_factory.mktemp("bin")
    said = bindir / "said.txt"
    fake = bindir / "espeak-ng"
    fake.write_text(f'#!/bin/sh\nprintf "%s\\n" "$*" >> {said}\n')
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    env = {**os.environ, "PATH": f"{bindir}{os.pathsep}{os.environ.get('PATH', '')}"}
    proc = subprocess.run(
        [str(CONSOLE), "monitor", "--source", "sim", "--sim-speed", "20", "--speak",
         "--refresh", "0.25", "--duration", "1.8"],
        capture_output=True, text=True, env=env, timeout=30, check=False)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout, proc.stderr, said


def test_plain_lines_through_a_pipe(monitor_run: tuple[str, str, Path]) -> None:
    out, _, _ = monitor_run
    assert not ANSI.search(out)
    lines = out.splitlines()
    assert len(lines) >= 5
    names = {s.name for s in SimpleState}
    tops = []
    for line in lines:
        fields = dict(tok.split("=", 1) for tok in line.split(" "))
        assert fields["state"] in names
        assert fields["link"] == "up"
        assert fields["crc_errors"] == "0"
        tops.append(float(fields["max_alt_m"]))
    assert tops == sorted(tops)  # the highest altitude never goes down
    apogee = FlightModel(FlightProfile()).apogee_altitude_m
    assert tops[-1] == pytest.approx(apogee, abs=1.0)  # 1.8 s at 20× is past apogee (~0.9 s)


def test_speak_says_apogee(monitor_run: tuple[str, str, Path]) -> None:
    _, _, said = monitor_run
    deadline = time.monotonic() + 5.0  # the last fake speaker may still be writing
    text = ""
    while time.monotonic() < deadline:
        text = said.read_text() if said.exists() else ""
        if "apogee" in text:
            break
        threading.Event().wait(0.02)
    assert re.search(r"^apogee, \d+ meters$", text, re.M), text


def test_speak_without_espeak_is_one_warning(tmp_path: Path) -> None:
    env = {**os.environ, "PATH": str(tmp_path)}
    proc = subprocess.run([str(CONSOLE), "monitor", "--source", "sim", "--speak",
                           "--duration", "0"],
                          capture_output=True, text=True, env=env, timeout=30, check=False)
    assert proc.returncode == 0, proc.stderr
    warnings = [ln for ln in proc.stderr.splitlines() if "espeak-ng" in ln]
    assert warnings == ["aurora-gateway monitor: --speak: espeak-ng not found on PATH; "
                        "running without speech"]


def test_ctrl_c_stops_the_status_lines_cleanly() -> None:
    proc = subprocess.Popen([str(CONSOLE), "monitor", "--source", "sim", "--sim-speed", "20",
                             "--refresh", "0.1"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()  # running: its first status line (of its vehicle)
        assert first.startswith("vehicle=sim state=")
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=5) == 130  # Ctrl-C: "interrupted" (gateway.exits)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for f in (proc.stdout, proc.stderr):
            if f is not None:
                f.close()


#: a terminal's escape sequences (colours, cursor moves), to read the text between them
ANSI_BYTES = re.compile(rb"\x1b\[[0-9;?]*[A-Za-z]")


def read_until(fd: int, needle: bytes, deadline: float) -> bytes:
    """What the terminal shows until ``needle`` appears (or the deadline passes)."""
    seen = b""
    while needle not in seen:
        left = deadline - time.monotonic()
        assert left > 0, f"{needle!r} never appeared in {seen[-400:]!r}"
        ready, _, _ = select.select([fd], [], [], left)
        if ready:
            try:
                chunk = os.read(fd, 65536)
            except OSError:  # EIO: the other end closed
                break
            if not chunk:
                break
            seen += chunk
    return seen


def test_full_screen_on_a_terminal_and_q_quits() -> None:
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 100, 0, 0))
    env = {**os.environ, "TERM": "xterm-256color"}
    env.pop("COLUMNS", None)
    env.pop("LINES", None)
    proc = subprocess.Popen([str(CONSOLE), "monitor", "--source", "sim", "--sim-speed", "20"],
                            stdin=slave, stdout=slave, stderr=slave, env=env,
                            start_new_session=True)
    os.close(slave)
    try:
        shown = read_until(master, b"max altitude", time.monotonic() + 10)
        assert b"\x1b[?1049h" in shown  # the alternate screen: full screen, no scrollback
        os.write(master, b"q")
        assert proc.wait(timeout=5) == 0
        rest = read_until(master, b"\x1b[?1049l", time.monotonic() + 5)
        assert b"\x1b[?1049l" in rest  # the terminal is given back
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)


def test_two_sources_two_rows_and_down_selects_the_second() -> None:
    """``monitor --source alpha=sim --source beta=sim`` on a terminal: a row per vehicle;
    the down arrow shows beta in detail."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 110, 0, 0))
    env = {**os.environ, "TERM": "xterm-256color"}
    env.pop("COLUMNS", None)
    env.pop("LINES", None)
    proc = subprocess.Popen([str(CONSOLE), "monitor", "--source", "alpha=sim", "--source",
                             "beta=sim", "--sim-speed", "5"],
                            stdin=slave, stdout=slave, stderr=slave, env=env,
                            start_new_session=True)
    os.close(slave)
    try:
        shown = read_until(master, b"vehicle alpha", time.monotonic() + 10)
        # beta's vehicle row, with its state, not just its name (the title and the sources
        # table show it from the start): the down arrow wraps round the vehicle rows there
        # are, and with alpha's alone it stays there
        beta_row = re.compile(rb"beta +[A-Z]")
        while not beta_row.search(ANSI_BYTES.sub(b"", shown)):
            shown += read_until(master, b"beta", time.monotonic() + 10)
        os.write(master, b"\x1b[B")  # down
        read_until(master, b"vehicle beta", time.monotonic() + 10)
        os.write(master, b"q")
        assert proc.wait(timeout=5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)


def test_plain_lines_of_two_sources() -> None:
    proc = subprocess.run([str(CONSOLE), "monitor", "--source", "alpha=sim", "--source",
                           "beta=sim", "--sim-speed", "20", "--refresh", "0.2",
                           "--duration", "1.5"],
                          capture_output=True, text=True, timeout=30, check=False)
    assert proc.returncode == 0, proc.stderr
    fields = [dict(tok.split("=", 1) for tok in line.split(" "))
              for line in proc.stdout.splitlines()]
    assert len(fields) >= 4
    assert {f["vehicle"] for f in fields} == {"alpha", "beta"}
    for name in ("alpha", "beta"):
        mine = [f for f in fields if f["vehicle"] == name]
        assert mine and all(f["link"] == "up" for f in mine[-1:])


def test_following_a_gateway_shows_its_backends_counters() -> None:
    """A gateway's Zenoh backend publishes every backend's and source's counters; a monitor
    following it (a Zenoh source and the monitor's feed, as ``monitor`` builds them) lists
    them under the gateway's id, with the numbers the gateway itself reports."""
    from zenoh_peer import free_endpoint

    from gateway import config as cfgmod
    from gateway.app import Gateway
    from gateway.commands.monitor import LiveFeed

    endpoint = free_endpoint()
    watched = Gateway(cfgmod.parse({
        "gateway": {"status_interval_s": 0.0},
        "sources": [{"type": "sim", "speed": 0.0, "cycles": 1, "rate_hz": 50.0,
                     "vehicle": "watched"}],
        "backends": {"zenoh": {"listen": [endpoint], "stats_interval_s": 0.2},
                     "console": {"enabled": False}}}))
    state = LiveState()
    monitor = Gateway(cfgmod.parse({
        "gateway": {"status_interval_s": 0.0},
        "sources": [{"type": "zenoh", "connect": [endpoint], "listen": [], "keys": "json",
                     "name": "zenoh"}]}))
    monitor.dispatcher.add(LiveFeed(state))
    watched.start()
    monitor.start()
    try:
        gw_id = watched.dispatcher.backends()[0].gateway_id

        def listed() -> bool:
            names = [r.name.strip() for r in state.table_rows()]
            return f"gateway {gw_id}" in names and "zenoh" in names and "sim" in names

        deadline = time.monotonic() + 20
        while not listed():
            assert time.monotonic() < deadline, [r.name for r in state.table_rows()]
            time.sleep(0.05)  # the view polls its state the same way
        rows = {r.name.strip(): r for r in state.remote[gw_id]}
        assert rows["zenoh"].sent is not None and rows["zenoh"].sent > 0
        assert rows["zenoh"].link is True
    finally:
        monitor.stop()
        watched.stop()
