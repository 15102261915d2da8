"""Issue 23: one exit-status table (:mod:`gateway.exits`) for every command, walked command by
command.

- the table is in every command's ``--help`` and in the README;
- bad input (a missing, empty or foreign file, a bad flag value, an unknown vehicle, a
  listener flag with a bad address, a configuration that is empty, binary, or has an unknown
  key or a wrong type) is one line on stderr and status 2, for every command: in process
  (many cases, cheap) and through the installed console script (one case per command, run
  side by side);
- SIGINT at 0.05 s, 0.2 s and 1 s after start of each long-running command is quiet (no
  traceback) and status 130; SIGTERM of a running gateway is 0.
"""

from __future__ import annotations

import argparse
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from gateway import exits, recording
from gateway.commands import cli

ROOT = Path(__file__).resolve().parents[1]
CONSOLE_SCRIPT = Path(sys.executable).parent / "aurora-gateway"
COMMAND = [str(CONSOLE_SCRIPT)] if CONSOLE_SCRIPT.exists() else [sys.executable, "-m", "gateway"]
TIMEOUT_S = 30.0
NOISE = ("Traceback", "KeyboardInterrupt", "Exception ignored", "Fatal Python error")

#: every command the table covers
COMMANDS = ("run", "record", "replay", "decode", "simulate", "export", "plot", "check-config",
            "monitor", "listen", "hc12", "fprime-dictionary", "mavlink-modes")


def own_lines(stderr: str) -> list[str]:
    """stderr without the registry's warnings about plug-ins that fail to import (an
    environment matter, not the error under test)."""
    return [ln for ln in stderr.splitlines() if ln.strip() and " failed to import: " not in ln]


# -- the table -------------------------------------------------------------------------------

def test_the_table_is_declared_once_with_the_issues_statuses() -> None:
    assert (exits.OK, exits.FAILED, exits.USAGE, exits.INTERRUPTED) == (0, 1, 2, 130)
    assert exits.REFUSED == 3  # hc12's addition
    assert exits.after_stop(signal.SIGINT) == 130
    assert exits.after_stop(signal.SIGTERM) == 0 and exits.after_stop(None) == 0
    for code in (0, 1, 2, 130):
        assert re.search(rf"^  {code} +\S", exits.HELP, re.M), code


def test_every_commands_help_ends_with_the_table() -> None:
    parser = cli.build_parser(backend_flags=False, plugin_command=None)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(COMMANDS) <= set(sub.choices), sorted(sub.choices)
    assert parser.format_help().endswith(exits.HELP)
    for name in COMMANDS:
        assert sub.choices[name].format_help().endswith(exits.HELP), name


def test_the_readme_shows_the_table() -> None:
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Service on a companion computer", 1)[1].split("\n## ", 1)[0]
    rows = dict(re.findall(r"^\| (\d+) \| (.+) \|$", section, re.M))
    assert {int(c) for c in rows} == {0, 1, 2, 130}
    assert "SIGTERM" in rows["0"] and "SIGINT" in rows["130"]
    assert "`hc12` exits 3" in section
    commands = readme.split("## Command line", 1)[1].split("\n## ", 1)[0]
    assert "#exit-status" in commands  # the command section points at it


# -- bad input: one line, status 2 -------------------------------------------------------------

@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    d = tmp_path_factory.mktemp("bad")
    made = {"missing.aur": None, "empty.aur": b"", "foreign.aur": b"hello, not a recording\n",
            "header.aur": recording.HEADER, "missing.toml": None, "empty.toml": b"",
            "junk.toml": bytes(range(256)) * 2, "unknown.toml": b"[gateway]\nnosuch = 1\n",
            "wrongtype.toml": b'[gateway]\nstatus_interval_s = "soon"\n',
            "notjson.json": b"{not json"}
    for name, content in made.items():
        if content is not None:
            (d / name).write_bytes(content)
    out = {name: str(d / name) for name in made}
    out["dir"] = str(d)
    return out


D = ("--duration", "5")
#: (id, command line with {file} placeholders); each is one line on stderr and status 2
BAD: list[tuple[str, tuple[str, ...]]] = [
    # run: every listener flag with a bad address, sources, flags, configuration files
    ("run-crsf", ("run", "--crsf", "nosuch://x", *D)),
    ("run-foxglove", ("run", "--foxglove", "host:notaport", *D)),
    ("run-fprime", ("run", "--fprime", "tcpin:1.2.3:99999", *D)),
    ("run-hc12", ("run", "--hc12", "nosuch://x", *D)),
    ("run-http", ("run", "--http", "x:99999", *D)),
    ("run-mavlink", ("run", "--mavlink", "udpin:nohost", *D)),
    ("run-uavtalk", ("run", "--uavtalk", "tcpin:1.2.3.4.5:x", *D)),
    ("run-xbee", ("run", "--xbee", "nosuch://x", *D)),
    ("run-zenoh-listen", ("run", "--zenoh-listen", "nosuch/1.2.3.4:1", *D)),
    ("run-zenoh-connect", ("run", "--zenoh-connect", "tcp/", *D)),
    ("run-source", ("run", "--source", "nosuch://x", *D)),
    ("run-source-name", ("run", "--source", "9x=sim", *D)),
    ("run-duration", ("run", "--duration", "soon")),
    ("run-baud", ("run", "--baud", "-5", *D)),
    ("run-log-format", ("run", "--log-format", "xml", *D)),
    ("run-only", ("run", "--only", "nosuch", *D)),
    ("run-unknown-flag", ("run", "--nosuch")),
    ("run-config-missing", ("run", "-c", "{missing.toml}", *D)),
    ("run-config-empty", ("run", "-c", "{empty.toml}", *D)),
    ("run-config-junk", ("run", "-c", "{junk.toml}", *D)),
    ("run-config-unknown-key", ("run", "-c", "{unknown.toml}", *D)),
    ("run-config-wrong-type", ("run", "-c", "{wrongtype.toml}", *D)),
    ("unknown-command", ("nosuch",)),
    # check-config
    ("check-config-empty", ("check-config", "{empty.toml}")),
    ("check-config-junk", ("check-config", "{junk.toml}")),
    ("check-config-unknown-key", ("check-config", "{unknown.toml}")),
    ("check-config-wrong-type", ("check-config", "{wrongtype.toml}")),
    ("check-config-missing", ("check-config", "{missing.toml}")),
    # the recording readers: a missing, empty and foreign file; an unknown vehicle
    ("decode-missing", ("decode", "{missing.aur}")),
    ("decode-empty-vehicle", ("decode", "{empty.aur}", "--vehicle", "alpha")),
    ("decode-header-unknown-vehicle", ("decode", "{header.aur}", "--vehicle", "alpha")),
    ("replay-missing", ("replay", "{missing.aur}", *D)),
    ("replay-empty", ("replay", "{empty.aur}", *D)),
    ("replay-foreign", ("replay", "{foreign.aur}", *D)),
    ("replay-speed", ("replay", "{header.aur}", "--speed", "fast")),
    ("export-missing", ("export", "{missing.aur}")),
    ("export-empty", ("export", "{empty.aur}")),
    ("export-foreign", ("export", "{foreign.aur}")),
    ("export-unknown-vehicle", ("export", "{header.aur}", "--vehicle", "alpha")),
    ("export-format", ("export", "{header.aur}", "--format", "xls")),
    ("export-mcap-to-stdout", ("export", "{header.aur}", "--format", "mcap")),
    ("plot-missing", ("plot", "{missing.aur}", "-o", "{dir}/x.png")),
    ("plot-empty", ("plot", "{empty.aur}", "-o", "{dir}/x.png")),
    ("plot-foreign", ("plot", "{foreign.aur}", "-o", "{dir}/x.png")),
    ("plot-no-updates", ("plot", "{header.aur}", "-o", "{dir}/x.png")),
    ("plot-size", ("plot", "{header.aur}", "-o", "{dir}/x.png", "--size", "big")),
    # record, monitor, simulate
    ("record-source", ("record", "{dir}/r.aur", "--source", "nosuch://x", *D)),
    ("record-duration", ("record", "{dir}/r.aur", "--duration", "-1")),
    ("record-into-a-directory", ("record", "{dir}", *D)),
    ("monitor-source", ("monitor", "--source", "nosuch://x", *D)),
    ("monitor-refresh", ("monitor", "--source", "sim", "--refresh", "0")),
    ("simulate-out", ("simulate", "--out", "nosuch://x", "--cycles", "1")),
    ("simulate-rate", ("simulate", "--out", "loop://", "--rate-hz", "x")),
    ("simulate-no-out", ("simulate",)),
    # the plug-in commands
    ("listen-key", ("listen", "a//b", "--duration", "1")),
    ("listen-connect", ("listen", "--connect", "nosuch/x", "--duration", "1")),
    ("listen-count", ("listen", "--count", "x")),
    ("listen-duration", ("listen", "--duration", "-1")),
    ("hc12-channel", ("hc12", "channel", "999", "--port", "loop://")),
    ("hc12-operation", ("hc12", "fly")),
    ("hc12-port", ("hc12", "info", "--port", "nosuch://x", "--bench")),
    ("hc12-config-missing", ("hc12", "info", "--config", "{missing.toml}")),
    ("fprime-dictionary-id-base", ("fprime-dictionary", "--id-base", "zz")),
    ("fprime-dictionary-scid", ("fprime-dictionary", "--scid", "5000")),
    ("mavlink-modes-sm-type", ("mavlink-modes", "--sm-type", "x")),
    ("mavlink-modes-foreign-file", ("mavlink-modes", "--install", "--file", "{notjson.json}")),
    ("mavlink-modes-directory", ("mavlink-modes", "--install", "--file", "{dir}")),
]


def _argv(args: Sequence[str], files: dict[str, str]) -> list[str]:
    return [re.sub(r"\{([^}]+)\}", lambda m: files[m.group(1)], a) for a in args]


def _main_status(argv: list[str]) -> int:
    """:func:`cli.main` as the console script ends it: argparse's exits included."""
    try:
        return cli.main(argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 1


@pytest.mark.parametrize("args", [a for _, a in BAD], ids=[i for i, _ in BAD])
def test_bad_input_is_one_line_and_status_2(args: tuple[str, ...], files: dict[str, str],
                                            capsys: pytest.CaptureFixture[str]) -> None:
    status = _main_status(_argv(args, files))
    err = capsys.readouterr().err
    lines = own_lines(err)
    assert status == exits.USAGE, (status, err)
    assert len(lines) == 1 and lines[0].startswith("aurora-gateway"), lines
    assert not any(n in err for n in NOISE), err


def test_every_command_is_walked() -> None:
    walked = {args[0] for _, args in BAD}
    assert set(COMMANDS) <= walked, set(COMMANDS) - walked


#: one bad input per command, through the installed console script
BY_SCRIPT = {c: next(a for _, a in BAD if a[0] == c) for c in COMMANDS}


def test_bad_input_through_the_console_script_is_one_line_and_status_2(
        files: dict[str, str]) -> None:
    def one(args: tuple[str, ...]) -> subprocess.CompletedProcess[str]:
        return subprocess.run([*COMMAND, *_argv(args, files)], cwd=ROOT, capture_output=True,
                              text=True, timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)

    with ThreadPoolExecutor(4) as pool:
        results = dict(zip(BY_SCRIPT, pool.map(one, BY_SCRIPT.values()), strict=True))
    for name, r in results.items():
        lines = own_lines(r.stderr)
        assert r.returncode == exits.USAGE, (name, r.returncode, r.stderr)
        assert len(lines) == 1, (name, lines)
        assert not any(n in r.stderr for n in NOISE), (name, r.stderr)


# -- Ctrl-C at any moment: quiet, 130 -----------------------------------------------------------

MOMENTS_S = (0.05, 0.2, 1.0)


def _runs_our_code(pid: int) -> bool:
    """True once the process runs the command's own code: the entry point's first act is to
    catch SIGTERM (gateway/__main__.py).  Before that the interpreter is still starting (its
    site packages loading): a Ctrl-C there is Python's own, before any of ours can run."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True  # gone already: its status says the rest
    m = re.search(r"^SigCgt:\s*([0-9a-f]+)$", status, re.M)
    return m is not None and bool(int(m.group(1), 16) >> (signal.SIGTERM - 1) & 1)


def _interrupt(args: Sequence[str], at_s: float, sig: int = signal.SIGINT,
               stdin: int | None = subprocess.DEVNULL) -> tuple[int, str, float]:
    """Start the command, send ``sig`` ``at_s`` after the start (or as soon as the command's
    code runs, if later); its status, stderr and when the signal went."""
    t0 = time.monotonic()
    proc = subprocess.Popen([*COMMAND, *args], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, stdin=stdin, text=True)
    try:
        time.sleep(at_s)  # the moment under test is a time after start, not an event
        deadline = time.monotonic() + TIMEOUT_S
        while not _runs_our_code(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.002)
        sent = time.monotonic() - t0
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, err, sent


LONG_RUNNING: dict[str, Callable[[dict[str, str]], list[str]]] = {
    "run": lambda f: ["run", "--only", "console", "--duration", "60"],
    "record": lambda f: ["record", f["dir"] + "/sigint.aur", "--source", "sim",
                         "--duration", "60"],
    "replay": lambda f: ["replay", f["flight"], "--only", "console", "--loop",
                         "--duration", "60"],
    "monitor": lambda f: ["monitor", "--source", "sim", "--duration", "60"],
    "listen": lambda f: ["listen", "--connect", "tcp/127.0.0.1:9", "--duration", "60"],
    "simulate": lambda f: ["simulate", "--out", "loop://"],
    "decode": lambda f: ["decode", "-"],  # waiting for stdin
}


@pytest.fixture(scope="module")
def flight(files: dict[str, str]) -> dict[str, str]:
    """``files`` and a short recorded flight to replay."""
    from gateway.flight import FlightModel, FlightProfile
    from gateway.sources.sim import flight_frames

    path = Path(files["dir"]) / "flight.aur"
    frames = flight_frames(FlightModel(FlightProfile()), 10.0, 1.0, 1)
    data = b"".join(recording.encode_record(1.0 + t, f)
                    for _, (t, f) in zip(range(50), frames, strict=False))
    path.write_bytes(recording.HEADER + data)
    return {**files, "flight": str(path)}


@pytest.mark.parametrize("command", list(LONG_RUNNING))
def test_ctrl_c_at_any_moment_is_quiet_and_130(command: str, flight: dict[str, str]) -> None:
    args = LONG_RUNNING[command](flight)
    stdin = subprocess.PIPE if command == "decode" else subprocess.DEVNULL
    with ThreadPoolExecutor(len(MOMENTS_S)) as pool:
        results = list(pool.map(lambda at: _interrupt(args, at, stdin=stdin), MOMENTS_S))
    for at, (status, err, sent) in zip(MOMENTS_S, results, strict=True):
        assert status == exits.INTERRUPTED, (command, at, sent, status, err[-2000:])
        assert not any(n in err for n in NOISE), (command, at, sent, err[-2000:])


def test_sigterm_at_any_moment_is_a_quiet_0() -> None:
    """A service manager's stop: 0 (systemd's success), during start-up too."""
    args = ["run", "--only", "console", "--duration", "60"]
    with ThreadPoolExecutor(len(MOMENTS_S)) as pool:
        results = list(pool.map(lambda at: _interrupt(args, at, signal.SIGTERM), MOMENTS_S))
    for at, (status, err, sent) in zip(MOMENTS_S, results, strict=True):
        assert status == exits.OK, (at, sent, status, err[-2000:])
        assert not any(n in err for n in NOISE), (at, sent, err[-2000:])


@pytest.mark.parametrize(("raised", "status"), [
    (KeyboardInterrupt(), exits.INTERRUPTED), (SystemExit(0), exits.OK),
    (SystemExit(3), 3), (ValueError("x"), None)])
def test_a_signal_raised_while_a_class_is_created_is_still_the_signal(
        raised: BaseException, status: int | None) -> None:
    """A signal handler's exception raised inside ``__set_name__`` (a dataclass being
    created while the command line imports, as SIGTERM at 0.2 s once did) reaches the caller
    wrapped in a RuntimeError on Python 3.11: still a quiet 0 or 130, not a traceback."""

    class Trips:
        def __set_name__(self, owner: type, name: str) -> None:
            raise raised

    with pytest.raises(BaseException) as info:
        type("Options", (), {"field": Trips()})
    assert exits.signalled(info.value) == status
