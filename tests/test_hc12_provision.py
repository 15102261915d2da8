"""Provisioning the HC-12 against the emulator: every command, the host baud rate restored on
every failure the emulator can inject (and on a real Ctrl-C), the safety rules (SET wiring,
IDLE, --bench), invalid arguments sending nothing, AT never interleaved with frames, and the
command line against a running gateway."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import wait_for
from test_hc12_support import (
    DEADLINE_S,
    ROOT,
    FakeClock,
    emu_mod,
    sm,
    status,
    write_settings,
)

from backends.hc12 import cli, control
from backends.hc12.backend import Hc12Backend
from backends.hc12.options import Hc12Options
from backends.hc12.port import open_port
from backends.hc12.provision import run_request
from backends.hc12.setline import BENCH_HINT, GpioSetLine, SetLineSpec
from gateway import config
from gateway.app import Gateway
from gateway.io.ioloop import IoLoop
from gateway.outcome import Outcome
from gateway.wire import decode_all, encode

BASE = ["--set-line", "rts", "--listen", "0", "--bench", "--baud", "19200"]

pytest_plugins = ["test_hc12_support"]  # the emulator and settings_file fixtures


@pytest.fixture(autouse=True)
def private_runtime_dir(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """Control sockets go to the test's own (short: Unix socket paths are limited to 107
    bytes) directory, never the user's."""
    d = Path(tempfile.mkdtemp(prefix="hc12-"))
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(d))
    try:
        yield d
    finally:
        shutil.rmtree(d, ignore_errors=True)


def hc12(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = cli.main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def per_connection(model: Any) -> list[list[tuple[str, Any]]]:
    """The host's baud-rate and SET changes, one list per connection to the emulator."""
    out: list[list[tuple[str, Any]]] = []
    with model.cond:
        events = list(model.events)
    for _, kind, value in events:
        if kind == "connect":
            out.append([])
        elif kind in ("baud", "set") and out:
            out[-1].append((kind, value))
    return out


SWITCHED = [("baud", 19200), ("baud", 9600), ("set", True), ("set", False), ("baud", 19200)]


# -- every command ---------------------------------------------------------------------------------


def test_every_command_against_the_emulator(capsys: pytest.CaptureFixture[str], emulator: Any,
                                            settings_file: Path) -> None:
    url = emulator.url
    model = emulator.model

    rc, out, err = hc12(capsys, "info", "--port", url, *BASE)
    assert rc == 0, err
    assert "FU3" in out and "9600" in out and "channel  1 (433.4 MHz)" in out
    assert "8 (+20 dBm)" in out
    # On the wire: host 19200 → 9600, SET low, command, SET high, → 19200.
    seq = [(k, v) for _, k, v in model.events if k in ("baud", "set", "at", "reply")]
    assert seq == [("baud", 19200), ("baud", 9600), ("set", True), ("at", "AT+RX"),
                   ("reply", b"OK+FU3\r\nOK+B9600\r\nOK+C001\r\nOK+RP:+20dBm\r\n"),
                   ("set", False), ("baud", 19200)]

    rc, out, err = hc12(capsys, "channel", "42", "--port", url, *BASE)
    assert rc == 0, err
    assert "channel set to 42 (449.8 MHz)" in out
    assert json.loads(settings_file.read_text())["channel"] == 42

    rc, out, err = hc12(capsys, "power", "5", "--port", url, *BASE)
    assert rc == 0 and "power set to 5 (+11 dBm)" in out

    rc, out, err = hc12(capsys, "mode", "4", "--port", url, *BASE)
    assert rc == 0, err
    assert "mode set to FU4" in out and "baud     1200" in out  # read back: FU4 forces 1200
    assert "host side must follow" in err and "baudrate = 1200" in err

    rc, out, err = hc12(capsys, "reset", "--port", url, *BASE)
    assert rc == 0, err
    assert "factory defaults restored" in out and "FU3" in out and "channel  1" in out

    rc, out, err = hc12(capsys, "baud", "19200", "--port", url, *BASE[:-2], "--baud", "9600")
    assert rc == 0, err
    assert "module UART rate set to 19200" in out
    assert "host side must follow" in err and "baudrate = 19200" in err

    rc, out, err = hc12(capsys, "at", "AT+RX", "--json", "--port", url, *BASE)
    assert rc == 0
    assert json.loads(out)["replies"] == [["OK+FU3", "OK+B19200", "OK+C001", "OK+RP:+20dBm"]]

    rc, out, err = hc12(capsys, "at", "AT+V", "--port", url, *BASE)
    assert rc == 0 and "HC-12_V2.4" in out

    assert model.at_commands == ["AT+RX", "AT+C042", "AT+P5", "AT+FU4", "AT+RX", "AT+DEFAULT",
                                 "AT+RX", "AT+B19200", "AT+RX", "AT+V"]
    # Every run switched to 9600 for AT and left the host at its own rate again (the `baud`
    # run was already at 9600).
    runs = per_connection(model)
    assert runs == [SWITCHED] * 5 + [[("baud", 9600), ("set", True), ("set", False)]] + \
        [SWITCHED] * 2
    # Settings survive a power cycle (the emulator's flash is the file).
    model.power_cycle()
    assert (model.settings.baud, model.settings.channel, model.settings.mode) == (19200, 1, 3)


# -- failure paths -------------------------------------------------------------------------------


@pytest.mark.parametrize(("fault", "delay", "words"), [
    ("silent", 0.0, "no answer to AT+RX within 0.4 s"),
    ("garbage", 0.0, "garbled reply"),
    ("slow", 1.5, "no answer to AT+RX within 0.4 s"),
])
def test_failures_restore_the_host_baud_and_release_set(
        capsys: pytest.CaptureFixture[str], emulator: Any, fault: str, delay: float,
        words: str) -> None:
    emulator.model.set_fault(fault, delay)
    rc, _, err = hc12(capsys, "info", "--port", emulator.url, "--timeout", "0.4", *BASE)
    assert rc == 1
    assert words in err and err.count("\n") == 1
    model = emulator.model
    assert per_connection(model) == [SWITCHED]
    assert model.at_commands == ["AT+RX"]
    assert model.settings.baud == 9600  # nothing changed


def test_a_slow_answer_within_the_timeout_is_fine_and_config_files_are_read(
        capsys: pytest.CaptureFixture[str], settings_file: Path, tmp_path: Path) -> None:
    """SET on DTR this time, and port, wiring and timeout from the gateway's config file."""
    emu = emu_mod.Hc12Emulator(settings_file, set_line="dtr").start()
    try:
        emu.model.set_fault("slow", 0.3)
        cfg = tmp_path / "gateway.toml"
        cfg.write_text(f'[backends.radio]\ntype = "hc12"\nurl = "{emu.url}"\n'
                       f'set_line = "dtr"\nreply_timeout_s = 2.0\n', encoding="utf-8")
        rc, _, err = hc12(capsys, "channel", "7", "--config", str(cfg), "--backend", "radio",
                          "--bench", "--listen", "0")
        assert rc == 0, err
        assert emu.model.settings.channel == 7
        assert emu.model.event_values("set") == [True, False]
    finally:
        emu.stop()


def test_a_set_line_that_fails_on_entry_still_restores(emulator: Any) -> None:
    """The SET line refuses after the baud switch (a GPIO that cannot be requested): the host
    rate comes back all the same."""
    port = open_port(emulator.url, 19200, SetLineSpec("none"))
    try:
        res = run_request(port, GpioSetLine("gpiochip-that-does-not-exist", 3), "info", None,
                          host_baud=19200)
        assert port.baudrate == 19200
    finally:
        port.close()
    assert not res.ok and res.kind == "failed" and "cannot enter AT mode" in res.error
    assert emulator.model.event_values("baud") == [19200, 9600, 19200]
    assert emulator.model.at_commands == []


def test_a_port_that_dies_mid_exchange_is_a_clear_error(emulator: Any) -> None:
    emulator.model.set_fault("slow", 30.0)
    spec = SetLineSpec("rts")
    port = open_port(emulator.url + "?timeout=0.5", 19200, spec)  # RFC 2217 network timeout
    from backends.hc12.provision import Timing
    from backends.hc12.setline import make_set_line

    def kill_after_command() -> None:
        if emulator.model.wait_for(lambda: emulator.model.at_commands, DEADLINE_S):
            emulator.unplug()

    killer = threading.Thread(target=kill_after_command)
    killer.start()
    try:
        res = run_request(port, make_set_line(spec, port), "info", None, host_baud=19200,
                          timing=Timing(reply_timeout_s=10.0))
    finally:
        killer.join()
        port.close()
    assert not res.ok and res.kind == "failed"
    assert "port failed during the exchange" in res.error or "could not restore" in res.error


def test_ctrl_c_mid_exchange_restores_the_port(emulator: Any, private_runtime_dir: Path) -> None:
    """A real SIGINT to the command while it waits for a (slow) answer."""
    emulator.model.set_fault("slow", 30.0)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(private_runtime_dir), "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "backends.hc12.cli", "info", "--port", emulator.url,
         "--timeout", "20", *BASE], cwd=ROOT, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    try:
        assert emulator.model.wait_for(lambda: emulator.model.at_commands == ["AT+RX"], 20.0)
        proc.send_signal(signal.SIGINT)
        _out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert per_connection(emulator.model) == [SWITCHED]


# -- safety rules and invalid arguments ------------------------------------------------------------


def test_no_set_line_refuses_with_the_bench_hint(capsys: pytest.CaptureFixture[str],
                                                  emulator: Any) -> None:
    rc, _out, err = hc12(capsys, "info", "--port", emulator.url, "--bench", "--listen", "0")
    assert rc == 3
    assert BENCH_HINT in err
    assert emulator.connections == 0  # the port was never opened


def test_no_vehicle_heard_needs_bench(capsys: pytest.CaptureFixture[str], emulator: Any) -> None:
    rc, _out, err = hc12(capsys, "info", "--port", emulator.url, "--set-line", "rts",
                        "--listen", "0")
    assert rc == 3 and "no vehicle heard" in err and "--bench" in err
    assert emulator.connections == 0


@pytest.fixture
def vehicle_on_air(emulator: Any) -> Iterator[Any]:
    """Injects the vehicle's frames into the emulator's air side every 50 ms."""
    frames: list[bytes] = []
    stop = threading.Event()

    def run() -> None:
        while not stop.wait(0.05):
            for f in list(frames):
                emulator.model.air_inject(f)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield frames
    finally:
        stop.set()
        t.join(2.0)


def test_standalone_listens_and_refuses_an_armed_vehicle(
        capsys: pytest.CaptureFixture[str], emulator: Any, vehicle_on_air: list[bytes]) -> None:
    vehicle_on_air.append(encode(sm(1, armed=True)))
    rc, _out, err = hc12(capsys, "channel", "9", "--port", emulator.url, "--set-line", "rts",
                        "--listen", "0.5", "--bench")  # --bench does not override a live vehicle
    assert rc == 3 and "vehicle is ARMED" in err
    assert emulator.model.at_commands == [] and emulator.model.event_values("set") == []


def test_standalone_hears_an_idle_vehicle_and_proceeds(
        capsys: pytest.CaptureFixture[str], emulator: Any, vehicle_on_air: list[bytes]) -> None:
    vehicle_on_air.append(encode(status(0)))
    rc, _out, err = hc12(capsys, "channel", "9", "--port", emulator.url, "--set-line", "rts",
                        "--listen", "0.5")
    assert rc == 0, err
    assert emulator.model.settings.channel == 9


def test_standalone_port_lost_while_listening_is_a_clear_failure(
        capsys: pytest.CaptureFixture[str], emulator: Any,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The adapter vanishes during --listen: the engine sees it, the command stops listening
    at once and fails; nothing was sent."""
    engines: list[Any] = []
    make = cli._listening_engine

    def keep(*args: Any) -> Any:
        engines.append(make(*args))
        return engines[-1]

    monkeypatch.setattr(cli, "_listening_engine", keep)

    def pull() -> None:  # once the engine has the port (it is listening), pull the cable
        if wait_for(lambda: bool(engines)) and engines[0].wait_connected(DEADLINE_S):
            emulator.unplug()

    puller = threading.Thread(target=pull)
    puller.start()
    start = time.monotonic()
    try:
        rc, _out, err = hc12(capsys, "info", "--port", emulator.url, "--set-line", "rts",
                            "--listen", "60", "--bench")
    finally:
        puller.join()
    assert rc == 1 and "failed while listening" in err
    assert time.monotonic() - start < 30  # not the whole minute (generous for a loaded host)
    assert emulator.model.at_commands == [] and emulator.model.event_values("set") == []


INVALID = [
    (["channel", "0"], "channel: expected 1–127, got 0"),
    (["channel", "128"], "channel: expected 1–127, got 128"),
    (["channel", "five"], "channel: expected an integer from 1 to 127"),
    (["channel"], "channel: needs a channel 1–127"),
    (["baud", "9601"], "baud: expected one of 1200|2400|4800|9600|19200|38400|57600|115200"),
    (["power", "9"], "power: expected 1–8, got 9"),
    (["mode", "0"], "mode: expected 1–4, got 0"),
    (["info", "now"], "info: takes no argument"),
    (["at", "HELLO"], "at: a command starts with AT"),
    (["at", "AT+C001\nAT+P8"], "printable ASCII"),
]


def test_invalid_arguments_are_one_line_and_send_nothing(
        capsys: pytest.CaptureFixture[str], emulator: Any) -> None:
    for argv, words in INVALID:
        rc, out, err = hc12(capsys, *argv, "--port", emulator.url, *BASE)
        assert rc == 2, argv
        assert words in err and err.count("\n") == 1 and out == "", (argv, err)
    assert emulator.connections == 0 and emulator.model.events == []


# -- against a running gateway -------------------------------------------------------------------


def test_at_never_interleaves_with_frames_and_queued_frames_drain_after(
        settings_file: Path, private_runtime_dir: Path) -> None:
    """Frames stream while an AT exchange runs (slow answer): nothing but the command reaches
    the module in AT mode; frames submitted meanwhile wait for the lock and go out after."""
    write_settings(settings_file, baud=115200)
    emu = emu_mod.Hc12Emulator(settings_file, tx_buffer=1 << 20).start()
    b = Hc12Backend(Hc12Options(url=emu.url, baudrate=115200, air_baud=115200, utilisation_pct=100,
                                set_line="rts", control="off"))
    b.init()
    stop = threading.Event()
    accepted: list[tuple[float, bytes]] = []

    def feed() -> None:
        i = 0
        while not stop.wait(0.004):
            msg = decode_all(encode(sm(0, t_ms=i)), origin="sim")[0]
            i += 1
            if b.send_sm_update(msg) is Outcome.ACCEPTED:
                accepted.append((time.monotonic(), msg.raw))

    feeder = threading.Thread(target=feed)
    try:
        assert b.engine.wait_connected(DEADLINE_S)
        emu.model.set_fault("slow", 0.4)
        feeder.start()
        assert emu.model.wait_for(lambda: len(emu.model.air_out) > 500, DEADLINE_S)
        result = b.provision("info", bench=False)
        assert emu.model.wait_for(lambda: len(emu.model.air_out) > 0 and
                                  len(emu.model.rx_log) > 0, DEADLINE_S)
        time_after = time.monotonic()
        assert emu.model.wait_for(
            lambda: any(t > time_after for t, _ in accepted), DEADLINE_S)
        stop.set()
        feeder.join()
        assert b.engine.drain(DEADLINE_S)
        expected = b"".join(raw for _, raw in accepted)
        assert emu.model.wait_for(lambda: len(emu.model.air_out) >= len(expected), DEADLINE_S)
        stats = b.stats()
    finally:
        stop.set()
        if feeder.is_alive():
            feeder.join()
        b.close()
        emu.stop()
    assert result.ok, result.error
    m = emu.model
    assert bytes(m.at_rx) == b"AT+RX"  # the only bytes the module saw in AT mode
    assert bytes(m.air_out) == expected
    assert m.garbled_bytes == 0 and m.air_dropped == 0
    set_times = [t for t, k, v in m.events if k == "set"]
    t_low, t_high = set_times[0], set_times[1]
    during = [raw for t, raw in accepted if t_low < t < t_high]
    assert during, "no frame was submitted while the exchange held the port"
    first_after = next(t for t, _ in m.rx_log if t > t_low)
    assert first_after > t_high  # they waited for the lock and went out after
    assert stats["at_exchanges"] == 1 and stats["at_failures"] == 0


def test_provisioning_through_the_backend_follows_the_idle_rule(settings_file: Path) -> None:
    clock = FakeClock()
    emu = emu_mod.Hc12Emulator(settings_file).start()
    b = Hc12Backend(Hc12Options(url=emu.url, set_line="rts", control="off"), clock=clock)
    b.init()
    try:
        assert b.engine.wait_connected(DEADLINE_S)
        r = b.provision("power", "6")
        assert (r.ok, r.kind) == (False, "refused") and "no vehicle heard" in r.error
        assert b.provision("power", "6", bench=True).ok  # nothing heard + bench
        b.send_sm_update(sm(1, armed=True))
        r = b.provision("power", "7", bench=True)
        assert r.kind == "refused" and "ARMED" in r.error
        b.send_status(status(0))
        assert b.provision("power", "7").ok
        clock.advance(5.0)
        r = b.provision("power", "8")
        assert r.kind == "refused" and "5.0 s ago" in r.error
        r = b.provision("power", "12")
        assert r.kind == "usage" and "power: expected 1–8" in r.error
        b.send_status(status(0))
        r = b.provision("at", "AT+NOPE")
        assert (r.ok, r.kind, r.error) == (False, "failed",
                                           "the module answered ERROR to AT+NOPE")
        stats = b.stats()
    finally:
        b.close()
        emu.stop()
    assert emu.model.at_commands == ["AT+P6", "AT+P7", "AT+NOPE"]
    assert emu.model.settings.power == 7
    assert stats["at_refused"] == 3 and stats["at_failures"] == 1


def test_the_command_line_reaches_a_running_gateway(
        capsys: pytest.CaptureFixture[str], settings_file: Path,
        private_runtime_dir: Path) -> None:
    """`aurora-gateway run` with the simulated flight (IDLE on the pad) and the HC-12 backend
    on the emulator; `hc12 info` finds it from the port URL and runs the exchange inside it."""
    emu = emu_mod.Hc12Emulator(settings_file).start()
    cfg = config.parse({
        "gateway": {"status_interval_s": 0},
        "sources": [{"type": "sim", "pad_idle_s": 60.0}],
        "backends": {"hc12": {"url": emu.url, "set_line": "rts"}},
    })
    gw = Gateway(cfg)
    try:
        assert gw.start() == []
        backend = gw.dispatcher.backends()[0]
        path = control.socket_path_for(emu.url)
        assert backend.control_path == path and path.exists()
        assert oct(path.stat().st_mode & 0o777) == "0o600"
        assert emu.model.wait_for(lambda: len(emu.model.air_out) > 100, DEADLINE_S)
        rc, out, err = hc12(capsys, "info", "--port", emu.url)  # no --bench: IDLE was heard
        assert rc == 0, err
        assert "FU3" in out and "channel  1" in out
        rc, out, err = hc12(capsys, "channel", "12", "--gateway", str(path))
        assert rc == 0, err
        rc, out, err = hc12(capsys, "channel", "200", "--gateway", str(path))
        assert rc == 2 and "channel: expected 1–127" in err
        stats = gw.dispatcher.stats()["hc12"]
        # Served on the port engine's own loop: no thread of the backend's own.
        assert not [t.name for t in threading.enumerate() if "control" in t.name]
    finally:
        gw.stop()
        emu.stop()
    assert not path.exists()  # removed on close
    assert emu.connections == 1  # the command line never opened the port itself
    assert emu.model.at_commands == ["AT+RX", "AT+C012"]
    assert emu.model.settings.channel == 12
    assert stats["at_exchanges"] == 2 and stats["sent"] > 0
    assert stats["link"] == 1 and stats["errors"] == 0


def test_an_unreachable_gateway_socket_is_a_clear_error(
        capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    rc, _out, err = hc12(capsys, "info", "--port", "rfc2217://127.0.0.1:9",
                        "--gateway", str(tmp_path / "nobody.sock"))
    assert rc == 1 and "no gateway answers at" in err


# -- the port engine's part ------------------------------------------------------------------------


def test_what_an_exclusive_block_changes_is_put_back_and_frames_flow_after(
        settings_file: Path) -> None:
    """A block that leaves the port at the AT rate: the engine restores the host rate before it
    writes again, so the frames queued meanwhile are not garbled."""
    write_settings(settings_file, baud=19200)
    emu = emu_mod.Hc12Emulator(settings_file).start()
    b = Hc12Backend(Hc12Options(url=emu.url, baudrate=19200, air_baud=19200, control="off"))
    b.init()
    try:
        assert b.engine.wait_connected(DEADLINE_S)
        with b.engine.exclusive() as port:
            port.baudrate = 9600
            assert b.send_status(status(0)) is Outcome.ACCEPTED  # queued, not written
            assert b.engine.queued() == 1
        assert b.engine.drain(DEADLINE_S)
        assert emu.model.wait_for(lambda: len(emu.model.air_out) >= 14, DEADLINE_S)
        assert b.engine.port.baudrate == 19200
        stats = b.stats()
    finally:
        b.close()
        emu.stop()
    assert emu.model.event_values("baud") == [19200, 9600, 19200]
    assert bytes(emu.model.air_out) == encode(status(0)) and emu.model.garbled_bytes == 0
    assert stats["link"] == 1 and stats["errors"] == 0 and stats["sent"] == 1


def test_provisioning_a_port_that_is_down_sends_nothing() -> None:
    with socket.socket() as s:  # a free port with nobody listening
        s.bind(("127.0.0.1", 0))
        url = f"rfc2217://127.0.0.1:{s.getsockname()[1]}"
    b = Hc12Backend(Hc12Options(url=url, set_line="rts", control="off"))
    b.init()
    try:
        r = b.provision("info", bench=True)
        stats = b.stats()
    finally:
        b.close()
    assert (r.ok, r.kind) == (False, "failed") and "not available" in r.error
    assert "nothing was sent" in r.error
    assert stats["link"] == 0 and stats["at_exchanges"] == 0


# -- the control protocol --------------------------------------------------------------------------


def _events(chunks: list[bytes]) -> list[Any]:
    reader = control.JsonLines(64)
    out: list[Any] = []
    for chunk in chunks:
        out += reader.feed(chunk)
    out += reader.flush()
    return [e if isinstance(e, dict) else type(e) for e in out]


def test_control_lines_read_the_same_whole_or_byte_by_byte() -> None:
    """One reader for both ends: objects, bad lines and over-long lines, whatever the split;
    a last line without its newline still counts at the end of the stream."""
    bad = control.BadMessage
    stream = (b'{"op": "info"}\n[1, 2]\nnot json\n{"op": "at", "arg": "' + b"X" * 100
              + b'"}\n\n{"op": "power", "arg": "5"}')
    whole = _events([stream])
    assert whole == [{"op": "info"}, bad, bad, bad, bad, {"op": "power", "arg": "5"}]
    assert _events([stream[i:i + 1] for i in range(len(stream))]) == whole
    assert _events([stream[:30], stream[30:77], stream[77:]]) == whole
    assert _events([b""]) == [] and _events([b"\n"]) == [bad]


@pytest.fixture
def io_loop() -> Iterator[IoLoop]:
    loop = IoLoop("ctl-test")
    loop.start()
    try:
        yield loop
    finally:
        loop.stop()
        loop.close()


def test_the_control_server_runs_requests_on_its_loop(
        io_loop: IoLoop, private_runtime_dir: Path, monkeypatch: pytest.MonkeyPatch,
        caplog: pytest.LogCaptureFixture) -> None:
    """Requests run on the loop's thread; a probe, a bad request and a silent client are
    handled without a thread or a warning; a second server on the same socket refuses."""
    monkeypatch.setattr(control, "REQUEST_TIMEOUT_S", 0.2)
    caplog.set_level(logging.WARNING)
    path = private_runtime_dir / "ctl.sock"
    ran_on: list[str] = []

    def handler(request: dict[str, Any]) -> dict[str, Any]:
        ran_on.append(threading.current_thread().name)
        return {"ok": True, "op": request["op"], "echo": request.get("arg")}

    server = control.ControlServer(path, handler, io_loop, name="t")
    server.start()
    try:
        assert oct(path.stat().st_mode & 0o777) == "0o600"
        assert control.reachable(path)  # connects and leaves without a word
        reply = control.call(path, {"op": "info", "arg": "ü" * 500}, DEADLINE_S)
        assert reply == {"ok": True, "op": "info", "echo": "ü" * 500}
        assert ran_on == [f"io-{io_loop.name}"]
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(DEADLINE_S)
            s.connect(str(path))
            s.sendall(b"[1]\n")
            answer = json.loads(s.makefile("rb").readline())
        assert answer["kind"] == "usage" and "expected a JSON object" in answer["error"]
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(DEADLINE_S)
            s.connect(str(path))
            assert s.recv(100) == b""  # a client that says nothing is dropped
        with pytest.raises(OSError, match="served by another running gateway"):
            control.ControlServer(path, handler, io_loop, name="t2").start()
        assert server.requests == 1 and ran_on == [f"io-{io_loop.name}"]
    finally:
        server.close()
    assert not path.exists()
    assert [r.getMessage() for r in caplog.records] == []
