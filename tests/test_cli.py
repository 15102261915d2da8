"""``aurora-gateway`` as a user runs it: in a subprocess, through ``python -m gateway`` or
the installed console script.

Waits are on the processes' own output (reader threads set events) or ``Popen.wait`` with a
timeout; every process is killed in ``finally``.
"""

from __future__ import annotations

import argparse
import io
import itertools
import json
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from helpers import Running

from dialects.states import state_name
from gateway import config, recording
from gateway.app import STOP_BUDGET_S, Gateway
from gateway.commands import cli
from gateway.flight import FlightModel, FlightProfile
from gateway.model import SmUpdate, VehicleState
from gateway.recorder import Recorder
from gateway.sources.sim import flight_frames
from gateway.wire import decode_all, frame, to_wire_dict

ROOT = Path(__file__).resolve().parents[1]
VECTORS = Path(__file__).resolve().parents[1].parent / "shared" / "vectors" / "aurora-wire.json"
GATEWAY = [sys.executable, "-m", "gateway"]
CONSOLE_SCRIPT = Path(sys.executable).parent / "aurora-gateway"
TIMEOUT_S = 20.0
STOP_SLACK_S = 1.5  # scheduling slack for a loaded 2-core CI machine, on top of the 1 s budget

SPEC_SM_FIELDS = ("timestamp_ms", "state", "armed", "sm_type", "altitude", "acceleration",
                  "accel_vert", "velocity", "roll", "pitch", "yaw")
SPEC_STATUS_FIELDS = ("timestamp_ms", "state", "sm_type", "flags")
STATUS_LINE = re.compile(r"^\[\s*(\d+\.\d)s\] in (\d+) \(sm \d+ st \d+ raw \d+\)")


def own_lines(stderr: str) -> list[str]:
    """stderr without the registry's warnings about plug-ins that fail to import (entry points
    of backends not present in this checkout: an environment matter, not the error under
    test)."""
    return [ln for ln in stderr.splitlines() if ln.strip() and " failed to import: " not in ln]


def gw(*args: str, stdin: bytes | None = None, timeout: float = TIMEOUT_S,
       cmd: Sequence[str] = GATEWAY) -> subprocess.CompletedProcess[str]:
    """Run the gateway to completion; stdin as bytes, stdout/stderr as text."""
    r = subprocess.run([*cmd, *args], cwd=ROOT, input=stdin if stdin is not None else b"",
                       capture_output=True, timeout=timeout)
    return subprocess.CompletedProcess(r.args, r.returncode, r.stdout.decode(),
                                       r.stderr.decode())


@pytest.fixture(scope="module")
def wire_vectors() -> dict:
    return json.loads(VECTORS.read_text())


# -- many short runs, started together -------------------------------------------------------------
# Each of these is a separate process (~0.3 s of start-up); they run four at a time in a
# module-scoped fixture and each parametrized test checks its own result.

def _subcommands() -> list[str]:
    parser = cli.build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sorted({"run", "decode", "simulate", "record", "replay", *subs.choices})


HELP_CASES = [None, *_subcommands()]

BAD_FLAGS = [
    (["run", "--sim-speed", "x"], "--sim-speed"),
    (["run", "--status-interval", "nan"], "--status-interval"),
    (["run", "--link-timeout", "0"], "--link-timeout"),
    (["run", "--disable", "no-such-backend"], "--disable"),
    (["run", "--only", "no-such-backend"], "--only"),
    (["run", "--only", "hc12"], "--only hc12: not configured"),  # no default, no --hc12
    (["run", "--source", "replay:"], "--source"),
    (["run", "--no-such-flag"], "--no-such-flag"),
    (["simulate", "--out", "loop://", "--revision", "48"], "--revision"),
    (["simulate", "--out", "loop://", "--rate-hz", "0"], "--rate-hz"),
    (["replay", "/no/such/file.agrec"], "no recording"),
    (["decode", "/no/such/capture.bin"], "/no/such/capture.bin"),
    (["--duration", "soon"], "--duration"),  # the default command is run
    (["run", "--crsf-baud", "-5"], "--crsf"),  # a backend's flag: the key and the flag
    # a flag of a backend that --only leaves out would be ignored: refused, naming both
    (["run", "--only", "mavlink", "--zenoh-connect", "tcp/127.0.0.1:9"],
     "--zenoh-connect: backend zenoh is left out by --only"),
]

# Flag values the file's own keys refuse: one line naming the flag and what is allowed, even
# when nothing would use the value (no serial source for --baud, no sim for --sim-speed).
RANGE_FLAGS = [
    (["run", "--link-timeout", "0.01"], "--link-timeout", "≥ 0.05"),
    (["run", "--baud", "-5", "--duration", "5"], "--baud", "≥ 50"),
    (["run", "--source", "loop://", "--sim-speed", "-1", "--duration", "5"], "--sim-speed",
     "≥ 0"),
    (["run", "--status-interval", "-1"], "--status-interval", "≥ 0"),
    (["run", "--duration", "-1"], "--duration", "≥ 0"),
    (["run", "--log-level", "loud"], "--log-level", "'warning'"),
    (["record", "/nonexistent/x.agrec", "--sim-speed", "fast"], "--sim-speed", "≥ 0"),
    (["record", "/nonexistent/x.agrec", "--baud", "9600.5"], "--baud", "an integer"),
    (["replay", "/nonexistent/x.agrec", "--speed", "-2"], "--speed", "≥ 0"),
    (["simulate", "--out", "loop://", "--cycles", "-1"], "--cycles", "≥ 0"),
    (["simulate", "--out", "loop://", "--baud", "0"], "--baud", "≥ 50"),
    (["simulate", "--out", "loop://", "--status-hz", "1000"], "--status-hz", "from 0 to 100"),
    # a URL scheme pyserial has no handler for: refused, not retried for ever
    (["run", "--source", "nosuch://x"], "--source", "unknown URL scheme 'nosuch'"),
    (["record", "/nonexistent/x.agrec", "--source", "nosuch://x"], "--source",
     "unknown URL scheme"),
    (["simulate", "--out", "nosuch://x", "--cycles", "1"], "--out", "unknown URL scheme"),
]

BAD_TOML = [
    ('[gateway]\nstatus_interval_s = "x"\n', "gateway.status_interval_s"),
    ("[gateway]\nstatus_interval = 1\n", "gateway.status_interval"),
    ("[gatway]\n", "gatway"),
    ('[[sources]]\ntype = "sim"\nspeed = "fast"\n', "sources[0].speed"),
    ('[[sources]]\ntype = "sim"\nwarp = 9\n', "sources[0].warp"),
    ('[[sources]]\ntype = "warp-drive"\n', "sources[0].type"),
    ("[backends.console]\ninterval_s = -1\n", "backends.console.interval_s"),
    ("[gateway\n", "not valid TOML"),
]


@pytest.fixture(scope="module")
def short_runs(tmp_path_factory: pytest.TempPathFactory
               ) -> dict[tuple, subprocess.CompletedProcess[str]]:
    d = tmp_path_factory.mktemp("cfg")
    jobs: dict[tuple, list[str]] = {}
    for command in HELP_CASES:
        jobs[("help", command)] = [*([command] if command else []), "--help"]
    for args, _ in BAD_FLAGS:
        jobs[("flag", *args)] = args
    for args, _, _ in RANGE_FLAGS:
        jobs[("flag", *args)] = args
    for i, (toml, _) in enumerate(BAD_TOML):
        path = d / f"bad{i}.toml"
        path.write_text(toml)
        jobs[("toml", toml)] = ["run", "--config", str(path), "--duration", "5"]
    with ThreadPoolExecutor(max_workers=4) as pool:
        futures = {k: pool.submit(gw, *args) for k, args in jobs.items()}
        return {k: f.result() for k, f in futures.items()}


# -- --help ------------------------------------------------------------------------------------

@pytest.mark.parametrize("command", HELP_CASES)
def test_help_exits_0_for_every_subcommand(short_runs: dict, command: str | None) -> None:
    r = short_runs[("help", command)]
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("usage: aurora-gateway")


def test_the_console_script_is_installed_and_runs() -> None:
    assert CONSOLE_SCRIPT.exists(), "pip install -e . creates .venv/bin/aurora-gateway"
    r = gw("--version", cmd=[str(CONSOLE_SCRIPT)])
    assert r.returncode == 0
    compiled = ("MAVLink routing, recvmmsg/sendmmsg" if sys.platform == "linux"
                and sys.implementation.name == "cpython" else r"[^\n]*")
    assert re.fullmatch(rf"aurora-gateway \d+\.\d+\.\d+\S*; compiled: {compiled}\n",
                        r.stdout), r.stdout


# -- usage errors: one line naming the key, exit 2 ------------------------------------------------

@pytest.mark.parametrize(("args", "key"), BAD_FLAGS)
def test_a_bad_flag_value_is_one_line_naming_it_and_exit_2(short_runs: dict, args: list[str],
                                                           key: str) -> None:
    r = short_runs[("flag", *args)]
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = own_lines(r.stderr)
    assert len(lines) == 1, lines
    assert key in lines[0]
    assert "Traceback" not in r.stderr
    assert r.stdout == ""


@pytest.mark.parametrize(("args", "flag", "allowed"), RANGE_FLAGS)
def test_a_flag_value_is_checked_by_the_key_it_sets_whether_used_or_not(
        short_runs: dict, args: list[str], flag: str, allowed: str) -> None:
    r = short_runs[("flag", *args)]
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = own_lines(r.stderr)
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"aurora-gateway: {flag}"), lines[0]
    assert allowed in lines[0], lines[0]
    assert "Traceback" not in r.stderr and r.stdout == ""


def _bad_value(key: config.Key) -> object:
    """A value ``key`` refuses: outside its range or its choices."""
    if key.choices is not None:
        return "no-such-choice"
    assert key.minimum is not None, "a key with nothing to refuse"
    return key.minimum - 1


def _file_error(section: str, key: str, value: object) -> str:
    table = ({"gateway": {key: value}} if section == "gateway"
             else {"sources": [{"type": section, key: value,
                                **({"url": "loop://"} if section == "serial" else {})}]})
    with pytest.raises(config.ConfigError) as info:
        config.parse(table)
    return str(info.value)


def _flag_error(argv: list[str]) -> str:
    args = cli.build_parser(backend_flags=False).parse_args(argv)
    with pytest.raises(config.ConfigError) as info:
        cli.config_from_args(args)
    return str(info.value)


@pytest.mark.parametrize(("dest", "flag", "key"), [
    f for f in cli.GATEWAY_FLAGS  # the keys that refuse some value (not record: any path)
    if config.GATEWAY_SCHEMA.keys[f[2]].choices or config.GATEWAY_SCHEMA.keys[f[2]].minimum
    is not None])
def test_a_gateway_flag_is_refused_exactly_as_its_file_key(dest: str, flag: str,
                                                          key: str) -> None:
    spec = config.GATEWAY_SCHEMA.keys[key]
    bad = _bad_value(spec)
    from_file = _file_error("gateway", key, bad)
    from_flag = _flag_error(["run", flag, str(bad)])
    assert from_file.startswith(f"gateway.{key}: ")
    assert from_flag.startswith(f"{flag} (gateway.{key}): ")
    assert from_flag.split(": ", 1)[1] == from_file.split(": ", 1)[1]  # the same judgement


@pytest.mark.parametrize(("dest", "flag", "source_type", "key"), cli.SOURCE_FLAGS)
def test_a_source_flag_is_refused_exactly_as_its_file_key(dest: str, flag: str,
                                                         source_type: str, key: str) -> None:
    spec = config.registry.load(config.registry.SOURCE_GROUP, source_type).CONFIG.keys[key]
    bad = _bad_value(spec)
    from_file = _file_error(source_type, key, bad)
    # the flag is checked with no source of that type configured at all
    other = "sim" if source_type != "sim" else "loop://"
    from_flag = _flag_error(["run", "--source", other, flag, str(bad)])
    assert from_file.startswith(f"sources[0].{key}: ")
    assert from_flag.startswith(f"{flag} (")
    assert from_flag.split(": ", 1)[1] == from_file.split(": ", 1)[1]


def test_a_flag_sets_the_key_a_file_would_on_every_source_of_its_type(tmp_path: Path) -> None:
    path = tmp_path / "two.toml"
    path.write_text('[[sources]]\ntype = "serial"\nurl = "loop://"\n\n'
                    '[[sources]]\ntype = "serial"\nname = "b"\nurl = "/dev/ttyNOPE9"\n'
                    'baudrate = 9600\n\n[gateway]\nlink_timeout_s = 5\n')
    args = cli.build_parser(backend_flags=False).parse_args(
        ["run", "-c", str(path), "--baud", "57600", "--link-timeout", "0.5"])
    cfg = cli.config_from_args(args)
    assert [p.options["baudrate"] for p in cfg.sources] == [57600, 57600]
    assert cfg.gateway["link_timeout_s"] == 0.5 and type(cfg.gateway["link_timeout_s"]) is float


# -- Ctrl-C during start-up ------------------------------------------------------------------------

# Runs the console script's entry point with an import hook that sends the process a real
# SIGINT the moment a given module is imported: Ctrl-C pressed at exactly that point.
CTRL_C_AT_IMPORT = r"""
import importlib.abc, os, signal, sys

class CtrlC(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == TARGET:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None

TARGET = sys.argv[1]
sys.argv = ["aurora-gateway", *sys.argv[2:]]
sys.meta_path.insert(0, CtrlC())
from gateway.__main__ import main  # the console script's entry point
main()
"""


@pytest.mark.parametrize(("module", "args"), [
    # while the command line itself imports (before console_main exists)
    ("gateway.options", ["run", "--duration", "5"]),
    # while the backends' flag modules import, building the parser
    ("backends.mavlink", ["run", "--duration", "5"]),
    # while the backends the configuration runs import (the MAVLink dialect is the slowest)
    ("dialects.aurora_mavlink", ["run", "--duration", "5"]),
    # while a command imports what it needs, before it handles signals itself
    ("gateway.flight", ["simulate", "--out", "loop://", "--cycles", "1"]),
])
def test_ctrl_c_during_start_up_ends_quietly_with_status_130(module: str,
                                                             args: list[str]) -> None:
    r = subprocess.run([sys.executable, "-c", CTRL_C_AT_IMPORT, module, *args], cwd=ROOT,
                       capture_output=True, text=True, timeout=TIMEOUT_S)
    assert r.returncode == 130, (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr and "KeyboardInterrupt" not in r.stderr, r.stderr
    assert own_lines(r.stderr) == [], r.stderr


@pytest.mark.parametrize(("toml", "key"), BAD_TOML)
def test_a_bad_config_file_key_is_one_line_naming_it_and_exit_2(short_runs: dict, toml: str,
                                                                 key: str) -> None:
    r = short_runs[("toml", toml)]
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = own_lines(r.stderr)
    assert len(lines) == 1, lines
    assert key in lines[0]
    assert r.stdout == ""


def test_a_record_file_that_cannot_be_opened_is_one_line_and_exit_2(tmp_path: Path) -> None:
    r = gw("run", "--record", str(tmp_path / "no" / "dir" / "x.agrec"), "--duration", "5")
    assert r.returncode == 2
    lines = own_lines(r.stderr)
    assert len(lines) == 1 and "record" in lines[0], lines
    notrec = tmp_path / "notes.txt"
    notrec.write_text("shopping list\n")
    r = gw("run", "--record", str(notrec), "--duration", "5")
    assert r.returncode == 2
    lines = own_lines(r.stderr)
    assert len(lines) == 1 and "record" in lines[0] and "magic" in lines[0], lines
    assert notrec.read_text() == "shopping list\n"  # never appended to


# -- decode --------------------------------------------------------------------------------------

def _check_decoded(obj: dict, vec: dict) -> None:
    if vec["kind"] == "sm_update":
        assert obj["type"] == 1
        assert obj["payload_len"] == vec["payload_len"]
        for k in SPEC_SM_FIELDS:
            assert obj[k] == vec["fields"][k], k
        assert obj["state_name"] == state_name(obj["sm_type"], obj["state"])
    elif vec["kind"] == "status":
        assert obj["type"] == 2
        assert obj["payload_len"] == 8
        for k in SPEC_STATUS_FIELDS:
            assert obj[k] == vec["fields"][k], k
        assert obj["state_name"] == state_name(obj["sm_type"], obj["state"])
        assert obj["armed"] == bool(vec["fields"]["flags"] & 1)
    else:
        assert obj == {"type": vec["type"], "payload_len": len(vec["payload_hex"]) // 2,
                       "payload_hex": vec["payload_hex"]}


def test_decode_prints_one_json_object_per_vector_frame(tmp_path: Path, wire_vectors: dict) -> None:
    cap = tmp_path / "capture.bin"
    cap.write_bytes(b"".join(bytes.fromhex(v["hex"]) for v in wire_vectors["frames"]))
    r = gw("decode", str(cap))
    assert r.returncode == 0, r.stderr
    objs = [json.loads(ln) for ln in r.stdout.splitlines()]
    assert len(objs) == len(wire_vectors["frames"])
    for obj, vec in zip(objs, wire_vectors["frames"], strict=True):
        _check_decoded(obj, vec)
    assert {"sm_update", "status", "unknown"} == {v["kind"] for v in wire_vectors["frames"]}
    assert f"decoded {len(objs)} frames" in r.stderr


def test_decode_reads_stdin_and_passes_the_intact_frames_of_a_damaged_stream(
        wire_vectors: dict) -> None:
    by_hex = {v["hex"]: v for v in wire_vectors["frames"]}
    for stream in wire_vectors["streams"]:
        r = gw("decode", "-", stdin=bytes.fromhex(stream["hex"]))
        assert r.returncode == 0, r.stderr
        objs = [json.loads(ln) for ln in r.stdout.splitlines()]
        assert len(objs) == len(stream["intact_frames"])
        for obj, hx in zip(objs, stream["intact_frames"], strict=True):
            _check_decoded(obj, by_hex[hx])
        assert "crc failures 1" in r.stderr


def test_decode_of_a_recording_adds_rx_time(tmp_path: Path, wire_vectors: dict) -> None:
    path = tmp_path / "v.agrec"
    rec = Recorder(path)
    times = [1_700_000_000.125 + 0.5 * i for i in range(len(wire_vectors["frames"]))]
    for t, v in zip(times, wire_vectors["frames"], strict=True):
        rec.write(bytes.fromhex(v["hex"]), t=t)
    rec.close()
    # a torn last record is skipped, and said so on stderr
    with path.open("ab") as f:
        f.write(recording.encode_record(9.0, bytes.fromhex(wire_vectors["frames"][0]["hex"]))[:-3])
    r = gw("decode", str(path))
    assert r.returncode == 0, r.stderr
    objs = [json.loads(ln) for ln in r.stdout.splitlines()]
    assert [o["rx_time"] for o in objs] == times
    for obj, vec in zip(objs, wire_vectors["frames"], strict=True):
        _check_decoded({k: v for k, v in obj.items()
                        if k not in ("rx_time", "vehicle", "source")}, vec)
        # written with no vehicle or source: the vehicle is named after the file
        assert (obj["vehicle"], obj["source"]) == ("v", "")
    assert "torn tail" in r.stderr


def test_decode_of_a_recording_of_another_version_is_one_line_and_exit_2(
        tmp_path: Path) -> None:
    path = tmp_path / "v9.agrec"
    path.write_bytes(recording.MAGIC + b"\x09\x00\x00\x00")
    r = gw("decode", str(path))
    assert r.returncode == 2
    lines = own_lines(r.stderr)
    assert len(lines) == 1 and "version 9" in lines[0], lines


# -- run: signals and the embedded default ------------------------------------------------------

@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_stops_the_gateway_within_a_second_with_a_report(sig: signal.Signals) -> None:
    p = Running("run", "--sim-speed", "10")
    try:
        assert p.wait_line("stderr", lambda ln: ": sources " in ln), p.text("stderr")
        assert p.wait_line("stdout", lambda ln: ln.startswith("sim t=")), p.text("stdout")
        t0 = time.monotonic()
        p.proc.send_signal(sig)
        rc = p.finish(timeout=10)
        took = time.monotonic() - t0
    finally:
        p.kill()
    err = p.text("stderr")
    assert rc == (130 if sig == signal.SIGINT else 0), err  # Ctrl-C: "interrupted" (exits)
    assert took < 1.0 + STOP_SLACK_S, f"{took:.2f} s from {sig.name} to exit"
    assert re.search(r"^stopped after \d+\.\d s: \d+ messages in", err, re.M), err
    assert re.search(r"^dropped: ", err, re.M), err
    assert "Traceback" not in err


@pytest.mark.usefixtures("capsys")  # the console backend's lines
def test_the_gateways_own_stop_path_is_bounded_by_its_budget() -> None:
    """The in-process half of the signal test: ``Gateway.stop`` with the embedded default
    (what SIGINT/SIGTERM call) takes at most the 1 s budget, whatever the machine's load does
    to process start-up and exit around it."""
    args = cli.build_parser().parse_args(["run", "--sim-speed", "10"])
    cfg = cli.config_from_args(args)
    g = Gateway(cfg, status_out=io.StringIO())
    done = threading.Event()
    orig = g.ingest

    def ingest(msg: object) -> None:
        orig(msg)
        if sum(g.counts.values()) >= 5:
            done.set()

    g.ingest = ingest  # type: ignore[method-assign]
    g.start()
    try:
        assert done.wait(TIMEOUT_S)
    finally:
        t0 = time.monotonic()
        summary = g.stop()
        took = time.monotonic() - t0
    assert took <= max(1.0, STOP_BUDGET_S), took
    assert summary["messages_in"]["sm_update"] >= 1
    assert all(s.done.is_set() for s in g.sources)
    assert not g.loop.alive  # the sources' loop ended with them


def test_the_embedded_default_prints_status_lines_and_console_lines() -> None:
    r = gw("run", "--duration", "3", "--sim-speed", "20", cmd=[str(CONSOLE_SCRIPT)])
    assert r.returncode == 0, r.stderr
    status = [STATUS_LINE.match(ln) for ln in r.stderr.splitlines()]
    status = [m for m in status if m]
    assert 2 <= len(status) <= 4, r.stderr  # one a second over 3 s
    ups = [float(m.group(1)) for m in status]
    counts = [int(m.group(2)) for m in status]
    assert ups == sorted(ups) and counts == sorted(counts) and counts[0] > 0
    assert ups[0] >= 0.9 and all(b > a for a, b in itertools.pairwise(ups)), ups
    out = r.stdout.splitlines()
    assert "*** link sim UP" in out
    assert any(ln.startswith("sim t=") and " m/s" in ln for ln in out), out
    assert any(ln.startswith("--- sim: state ") for ln in out), out
    assert re.search(r"^stopped after [34]\.\d s", r.stderr, re.M), r.stderr


def test_run_is_the_default_command() -> None:
    r = gw("--duration", "0.3", "--sim-speed", "50", "--status-interval", "0")
    assert r.returncode == 0, r.stderr
    assert "stopped after" in r.stderr


# -- record, replay, simulate ---------------------------------------------------------------------

def _sample_recording(path: Path, span_s: float) -> list[tuple[float, bytes]]:
    frames = [f for _, f in flight_frames(FlightModel(FlightProfile()), 10, 1, cycles=1)]
    frames = [*frames[150:180], frame(0x42, b"relay me")]
    items = [(1_700_000_000.0 + span_s * i / (len(frames) - 1), f)
             for i, f in enumerate(frames)]
    rec = Recorder(path)
    for t, f in items:
        rec.write(f, t=t)
    rec.close()
    return items


def test_replay_command_replays_into_a_new_recording(tmp_path: Path) -> None:
    src = tmp_path / "in.agrec"
    items = _sample_recording(src, span_s=600.0)
    no_backends = tmp_path / "quiet.toml"
    no_backends.write_text("[gateway]\nstatus_interval_s = 0\n")
    out = tmp_path / "out.agrec"
    r = gw("replay", str(src), "--speed", "0", "--config", str(no_backends),
           "--record", str(out))
    assert r.returncode == 0, r.stderr
    assert [f for _, f in recording.read(out)] == [f for _, f in items]
    assert f"{len(items)} messages recorded" in r.stderr


def test_record_command_records_what_its_source_receives(tmp_path: Path) -> None:
    src = tmp_path / "in.agrec"
    items = _sample_recording(src, span_s=0.2)
    out = tmp_path / "rec.agrec"
    r = gw("record", str(out), "--source", f"replay:{src}", "--duration", "15",
           "--status-interval", "0")
    assert r.returncode == 0, r.stderr
    assert [f for _, f in recording.read(out)] == [f for _, f in items]


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_record_from_a_mavlink_vehicle_records_its_sm_updates_and_reports_the_rest(
        tmp_path: Path) -> None:
    """A MAVLink source delivers AURORA_SM_UPDATEs (no wire frame: built from MAVLink
    fields) and vehicle states (no wire form).  The first are recorded as the frames they
    encode to; the others as message records (issue 24)."""
    from dialects import aurora_mavlink as mav

    port = _free_udp_port()
    out = tmp_path / "mav.agrec"
    node = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    heartbeat = node.heartbeat_encode(
        mav.MAV_TYPE_ROCKET, mav.MAV_AUTOPILOT_GENERIC,
        mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mav.MAV_MODE_FLAG_SAFETY_ARMED, 3, 4)
    sent: dict[int, tuple] = {}
    p = Running("record", str(out), "--source", f"mavlink:udpin:127.0.0.1:{port}",
                "--status-interval", "0.1", "--duration", "60")

    def recorded(ln: str) -> bool:
        m = re.search(r"\| rec (\d+)$", ln)
        # (records: the frames and, since issue 24, the vehicle states' message records)
        return m is not None and int(m.group(1)) >= 10

    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            deadline = time.monotonic() + TIMEOUT_S
            k = 0
            while not p.wait_line("stderr", recorded, 0.05):
                assert time.monotonic() < deadline, p.text("stderr")[-2000:]
                k += 1
                # values an f32 (MAVLink's float) holds exactly
                fields = (5000 + 100 * k, 3, 1, 0, 0, 100.0 + k, 9.5, -9.75, 12.25, 0.5, -0.25,
                          1.0, 64)
                sent[fields[0]] = fields
                tx.sendto(heartbeat.pack(node), ("127.0.0.1", port))
                tx.sendto(node.aurora_sm_update_encode(*fields).pack(node),
                          ("127.0.0.1", port))
        p.proc.send_signal(signal.SIGINT)
        assert p.finish(10) == 130, p.text("stderr")[-2000:]  # stopped cleanly, "interrupted"
    finally:
        p.kill()
    got = [m for _, f in recording.read(out) for m in decode_all(f)]
    assert len(got) >= 5
    for m in got:
        ts, state, armed, sm_type, reserved, *floats, plen = sent[m.timestamp_ms]
        want = SmUpdate(ts, state, bool(armed), sm_type, *floats, payload_len=plen,
                        reserved=reserved)
        assert m.fields() == want.fields()
    err = p.text("stderr")
    # (issue 24: the vehicle states are recorded too now, as message records)
    states = [r.message for r in recording.read_records(out, messages=True)
              if isinstance(r, recording.MessageRecord)]
    assert states and all(isinstance(m, VehicleState) and m.armed for m in states)
    assert "not recorded" not in err, err[-2000:]
    assert "Traceback" not in err


@pytest.fixture
def listener() -> Iterator[socket.socket]:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.settimeout(TIMEOUT_S)
    try:
        yield srv
    finally:
        srv.close()


def _receive_all(conn: socket.socket) -> bytes:
    conn.settimeout(TIMEOUT_S)
    chunks = []
    while data := conn.recv(65536):
        chunks.append(data)
    return b"".join(chunks)


def test_simulate_writes_exactly_the_flight_frames_and_retries_a_missing_port(
        listener: socket.socket) -> None:
    """The port has no listener when simulate starts: it retries, then writes every frame."""
    port = listener.getsockname()[1]
    p = Running("simulate", "--out", f"socket://127.0.0.1:{port}", "--speed", "0",
                "--cycles", "1", "--revision", "36", "--log-level", "warning")
    try:
        assert p.wait_line("stderr", lambda ln: "retrying" in ln), p.text("stderr")
        listener.listen(1)
        conn, _ = listener.accept()
        with conn:
            data = _receive_all(conn)
        assert p.finish() == 0, p.text("stderr")
    finally:
        p.kill()
    expected = [f for _, f in flight_frames(FlightModel(FlightProfile(revision=36)), 10, 1,
                                            cycles=1)]
    assert data == b"".join(expected)
    assert decode_all(data)[-1].state_name == "IDLE"
    assert f"simulate: {len(expected)} frames written" in p.text("stderr")


def test_decode_output_is_to_wire_dict_of_each_frame(tmp_path: Path) -> None:
    frames = [f for _, f in flight_frames(FlightModel(FlightProfile()), 10, 1, cycles=1)][:40]
    cap = tmp_path / "sim.bin"
    cap.write_bytes(b"".join(frames))
    r = gw("decode", str(cap))
    assert r.returncode == 0, r.stderr
    got = [json.loads(ln) for ln in r.stdout.splitlines()]
    assert got == [json.loads(json.dumps(to_wire_dict(m))) for m in decode_all(cap.read_bytes())]


def test_config_from_args_overrides_the_embedded_default() -> None:
    args = cli.build_parser().parse_args(["run", "--source", "sim", "--source", "loop://",
                                          "--baud", "9600", "--sim-speed", "3",
                                          "--status-interval", "0.5"])
    cfg = cli.config_from_args(args)
    assert [p.type for p in cfg.sources] == ["sim", "serial"]
    assert cfg.sources[0].options["speed"] == 3.0
    assert cfg.sources[1].options["baudrate"] == 9600
    assert cfg.gateway["status_interval_s"] == 0.5
    assert isinstance(cfg, config.GatewayConfig)


# -- run imports only the backends it runs ------------------------------------------------------

HEAVY = ("pymavlink", "dialects.aurora_mavlink", "zenoh", "backends.mavlink.backend",
         "backends.zenoh.backend", "cyclonedds", "foxglove", "backends.ros2.backend",
         "backends.foxglove.backend", "backends.http.backend")
# Ends as the console script does (os._exit): Zenoh's native threads can abort a normal
# interpreter teardown (see gateway.commands.cli.console_main).
IMPORT_CHECK = f"""
import json, os, sys
from gateway.commands import cli
try:
    code = cli.main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
loaded = [m for m in {HEAVY!r} if m in sys.modules]
sys.stdout.flush()
print("IMPORTS " + json.dumps({{"code": code, "loaded": loaded}}), file=sys.stderr, flush=True)
os._exit(0)
"""


def _imports_of(*argv: str) -> tuple[int, list[str], str]:
    """Exit status, which of HEAVY ``cli.main(argv)`` left imported, its stdout."""
    r = subprocess.run([sys.executable, "-c", IMPORT_CHECK, *argv], cwd=ROOT,
                       capture_output=True, text=True, timeout=TIMEOUT_S)
    line = next(ln for ln in r.stderr.splitlines() if ln.startswith("IMPORTS "))
    last = json.loads(line.removeprefix("IMPORTS "))
    return last["code"], last["loaded"], r.stdout


MAVLINK = {"dialects.aurora_mavlink", "backends.mavlink.backend"}
ZENOH = {"zenoh", "backends.zenoh.backend"}


@pytest.mark.parametrize(("argv", "loaded"), [
    (["run", "--duration", "0"], MAVLINK | ZENOH),  # not the backends the default leaves out
    (["run", "--disable", "mavlink", "--duration", "0"], ZENOH),
    (["run", "--only", "console", "--duration", "0"], set()),
    (["run", "--only", "mavlink", "--mavlink", "udpout:127.0.0.1:9", "--duration", "0"],
     MAVLINK),
    (["run", "--disable", "mavlink", "--disable", "zenoh", "--mavlink", "udpout:127.0.0.1:9",
      "--zenoh-mode", "client", "--duration", "0"], set()),
], ids=["embedded-default", "disable-mavlink", "only-console", "only-mavlink",
        "flags-of-left-out-backends"])
def test_run_imports_only_the_backends_it_runs(argv: list[str], loaded: set[str]) -> None:
    code, got, _ = _imports_of(*argv)
    assert code == 0
    assert set(got) - {"pymavlink"} == loaded  # the dialect itself needs no pymavlink
    if "dialects.aurora_mavlink" not in loaded:
        assert "pymavlink" not in got


OPTIONS_CHECK = IMPORT_CHECK.replace("if m in sys.modules", "if m in sys.modules or "
                                     "any(n.startswith(m) for n in sys.modules)")


def test_only_and_source_build_the_flags_of_what_they_name_alone() -> None:
    """``--only`` and ``--source`` narrow ``run``'s parser to the options of the backends and
    source types they name: no other backend's or source's options module is imported (each
    costs start-up time); their flags still work."""
    others = ("backends.zenoh", "backends.crsf", "backends.hc12", "backends.xbee",
              "backends.uavtalk", "backends.http", "gateway.sources.options")
    r = subprocess.run([sys.executable, "-c", OPTIONS_CHECK.replace(repr(HEAVY), repr(others)),
                        "run", "--only", "mavlink", "--source", "mavlink:udpin:127.0.0.1:0",
                        "--mavlink", "udpout:127.0.0.1:9", "--mavlink-sysid", "7",
                        "--duration", "0"],
                       cwd=ROOT, capture_output=True, text=True, timeout=TIMEOUT_S)
    line = next(ln for ln in r.stderr.splitlines() if ln.startswith("IMPORTS "))
    got = json.loads(line.removeprefix("IMPORTS "))
    assert got == {"code": 0, "loaded": []}, r.stderr


def test_a_flag_outside_the_narrowed_scope_is_read_by_the_whole_parser() -> None:
    """A source type's flag with no source of that type is checked and ignored, as before
    the narrowing (the whole parser reads it): a bad value is still refused."""
    ok = gw("run", "--only", "console", "--source", "sim", "--baud", "9600", "--duration", "0")
    assert ok.returncode == 0, ok.stderr
    bad = gw("run", "--only", "console", "--source", "sim", "--baud", "x", "--duration", "0")
    assert bad.returncode == 2
    assert own_lines(bad.stderr)[0].startswith("aurora-gateway: --baud"), bad.stderr


def test_run_help_lists_every_backends_flags_and_imports_none() -> None:
    code, got, out = _imports_of("run", "--help")
    assert code == 0
    assert got == []
    for flag in ("--mavlink", "--mavlink-sysid", "--crsf", "--crsf-baud", "--hc12-mode",
                 "--zenoh-connect", "--console-interval", "--only", "--disable"):
        assert f"{flag} " in out, flag


def test_only_runs_just_the_named_backends_with_their_flags() -> None:
    args = cli.build_parser().parse_args(["run", "--only", "console", "--only", "mavlink",
                                          "--mavlink", "udpout:127.0.0.1:9",
                                          "--crsf", "pty"])
    cfg = cli.config_from_args(args)
    assert sorted(p.name for p in cfg.backends) == ["console", "mavlink"]
    assert cfg.backends[[p.name for p in cfg.backends].index("mavlink")].options[
        "endpoints"] == ["udpout:127.0.0.1:9"]


def test_only_and_disable_leave_a_files_backend_unvalidated(tmp_path: Path) -> None:
    """A backend left out is dropped before its table is read (its class is not imported
    to validate it): like a table that is not there."""
    path = tmp_path / "g.toml"
    path.write_text("[backends.console]\n[backends.zenoh]\nmode = 'warp'\n")
    for extra in (["--only", "console"], ["--disable", "zenoh"]):
        args = cli.build_parser().parse_args(["run", "-c", str(path), *extra])
        assert [p.name for p in cli.config_from_args(args).backends] == ["console"]
    args = cli.build_parser().parse_args(["run", "-c", str(path)])
    with pytest.raises(config.ConfigError, match=r"^backends\.zenoh\.mode"):
        cli.config_from_args(args)


def test_the_light_options_modules_name_the_backends_own_defaults() -> None:
    from backends.crsf import backend as crsf
    from backends.crsf import options as crsf_options
    from backends.hc12 import backend as hc12
    from backends.hc12 import options as hc12_options
    from backends.mavlink import backend as mavlink
    from backends.mavlink import options as mavlink_options
    from backends.zenoh import options as zenoh_options
    from backends.zenoh import session as zenoh_session

    assert mavlink.MavlinkBackend.EMBEDDED_DEFAULT == {"endpoints": [mavlink_options.QGC_UDP]}
    assert crsf.CrsfBackend().baudrate == crsf_options.DEFAULT_BAUD
    assert hc12.Hc12Backend.OPTIONS.schema().keys["mode"].choices == hc12_options.MODES
    assert zenoh_options.MODES == zenoh_session.MODES


@pytest.mark.parametrize(("text", "error"), [
    ("", "sources: none configured; add a [[sources]] table"),
    ("[gateway]\nstatus_interval_s = 0\n", "sources: none configured"),
    ('[[sources]]\ntype = "sim"\n', "backends: none enabled; add a [backends.NAME] table"),
    ('[[sources]]\ntype = "sim"\n[backends.console]\nenabled = false\n', "backends: none"),
    ('[[sources]]\ntype = "mavlink"\nurl = "udpin:127.0.0.1:0"\n', "backends: none"),
])
def test_a_configuration_that_would_do_nothing_is_refused(tmp_path: Path, text: str,
                                                          error: str) -> None:
    """check-config and run refuse a file with no source or no backend (run idled for ever
    with one): one line naming what is missing, exit 2."""
    path = tmp_path / "c.toml"
    path.write_text(text)
    for args in (("check-config", str(path)), ("run", "-c", str(path), "--duration", "5")):
        r = gw(*args)
        assert r.returncode == 2, (args, r.stderr)
        assert error in r.stderr and len(r.stderr.splitlines()) == 1, r.stderr


def test_a_mavlink_router_config_needs_no_backend(tmp_path: Path) -> None:
    """A MAVLink source with more endpoints routes its vehicle to them (mavlink-router's
    job, the router bench's config form): a run of its own, no backend needed."""
    path = tmp_path / "c.toml"
    path.write_text('[gateway]\nstatus_interval_s = 0\n[[sources]]\ntype = "mavlink"\n'
                    'url = "udpin:127.0.0.1:0"\nendpoints = ["udpout:127.0.0.1:9"]\n')
    assert gw("check-config", str(path)).returncode == 0
    r = gw("run", "-c", str(path), "--duration", "0.5")
    assert r.returncode == 0, r.stderr


def test_a_recording_run_needs_no_backend(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text(f'[gateway]\nrecord = "{tmp_path / "r.aur"}"\nstatus_interval_s = 0\n'
                    '[[sources]]\ntype = "sim"\nspeed = 0\ncycles = 1\n')
    assert gw("check-config", str(path)).returncode == 0
    r = gw("run", "-c", str(path), "--duration", "20")
    assert r.returncode == 0, r.stderr
