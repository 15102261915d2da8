#!/usr/bin/env python3
"""The wheel as a user installs it: build, install outside the checkout, run from elsewhere.

``python3 tools/check_wheel.py`` (``make wheel-check``; ``.ci/run`` runs it after the tests)
builds the project's wheel (``pip wheel --no-deps``, from a copy of the tracked files),
checks that it holds every data file of the packages, installs it into two new virtual
environments in a temporary directory outside the checkout, and from a directory of their own
runs:

* with the ``all`` extra: ``run --duration 2`` with every backend's flag at once (loopback
  ports; pseudo-terminals for the serial ones) recording the flight, exit 0 and no backend
  that failed to start; ``run --log-format json --duration 3``, every stderr line a JSON
  object; the files installed for the user (``share/aurora-gateway/``: the
  Foxglove layout, the example configuration, the systemd unit); ``check-config`` of
  ``examples/gateway.toml`` (a copy);
  ``fprime-dictionary``; ``mavlink-modes``; ``export --format mcap``, ``export --format
  rosbag2`` and ``plot`` of the recording;
* without extras: ``record`` a flight; ``--foxglove``, ``--http``, ``--ros2``, ``plot``,
  ``export --format mcap`` and ``export --format rosbag2`` of it each one line on stderr
  naming the extra, exit 2; ``check-config examples/gateway.toml`` exit 0 (its optional
  backends are disabled, so checked by their options alone); the embedded default runs (it
  leaves out the backends whose extra is missing).

Standard library only (it runs before any environment exists).  Prints one line per check
with its duration; exit status 0 when every check passed, 1 otherwise.  ``--keep`` leaves the
temporary directory (its path is printed).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pty
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
import zipfile
from collections.abc import Iterator, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DIST = "aurora-gateway"
PACKAGES = ("gateway", "backends", "dialects")
MCAP_MAGIC = b"\x89MCAP0\r\n"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
#: what a backend that failed, or an unexpected error, writes on stderr
FAILURE_MARKS = ("did not start", "Traceback", "failed to start")
STEP_TIMEOUT_S = 600

PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())

failures: list[str] = []


def say(text: str) -> None:
    print(text, flush=True)


def check(name: str, ok: bool, detail: str = "", started: float | None = None) -> None:
    took = f" ({time.monotonic() - started:.1f} s)" if started is not None else ""
    say(f"{'ok  ' if ok else 'FAIL'} {name}{took}" + (f": {detail}" if detail and not ok
                                                     else ""))
    if not ok:
        failures.append(name)


def sh(args: Sequence[str | Path], cwd: Path, **kw: object) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(a) for a in args], cwd=cwd, capture_output=True, text=True,
                          timeout=STEP_TIMEOUT_S, check=False, **kw)  # type: ignore[call-overload]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextlib.contextmanager
def ptys(count: int) -> Iterator[list[str]]:
    """``count`` pseudo-terminals (their device paths), their controller sides drained."""
    pairs = [pty.openpty() for _ in range(count)]
    stop = threading.Event()

    def drain(fd: int) -> None:
        os.set_blocking(fd, False)
        while not stop.is_set():
            try:
                os.read(fd, 65536)
            except BlockingIOError:
                stop.wait(0.02)
            except OSError:
                return

    threads = [threading.Thread(target=drain, args=(m,), daemon=True) for m, _ in pairs]
    for t in threads:
        t.start()
    try:
        yield [os.ttyname(s) for _, s in pairs]
    finally:
        stop.set()
        for t in threads:
            t.join(2)
        for m, s in pairs:
            os.close(m)
            os.close(s)


def build_wheel(out: Path) -> Path:
    """The wheel of the checkout's tracked files as they are in the work tree, built from a
    copy of them (pip builds in the tree: a checkout's ``build/`` from an earlier build could
    put a deleted module back in the wheel)."""
    started = time.monotonic()
    src = out / "src"
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True,
                             check=True).stdout.decode().split("\0")
    for name in filter(None, tracked):
        if (ROOT / name).is_file():  # (a file deleted in the work tree is left out)
            (src / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, src / name)
    r = sh([sys.executable, "-m", "pip", "wheel", "--quiet", "--disable-pip-version-check",
            "--no-deps", "-w", out, src], cwd=out)
    wheels = sorted(out.glob("aurora_gateway-*.whl"))
    check("build the wheel", r.returncode == 0 and len(wheels) == 1, r.stderr[-2000:], started)
    if not wheels:
        raise SystemExit(1)
    return wheels[0]


def data_files() -> list[str]:
    """Every file of the packages that is not Python source, as the repository has them (a
    README beside a backend's modules is documentation, not package data)."""
    r = subprocess.run(["git", "ls-files", *PACKAGES], cwd=ROOT, capture_output=True,
                       text=True, check=True)
    return [p for p in r.stdout.split() if not p.endswith((".py", ".c"))
            and not (p.endswith("README.md") and not p.startswith("dialects/"))]


def check_contents(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = [p for p in data_files() if p not in names]
    xml = sum(1 for n in names if n.startswith("dialects/uavtalk/") and n.endswith(".xml"))
    check(f"the wheel holds every data file of the packages ({xml} UAVTalk objects)",
          not missing and xml > 0, f"missing {missing[:10]}")
    # the compiled fast paths, built from their C sources (pyproject's ext-modules)
    exts = [e["name"] for e in PYPROJECT["tool"]["setuptools"]["ext-modules"]]
    built = [e for e in exts if any(n.startswith(e.replace(".", "/") + ".") and
                                    n.endswith(".so") for n in names)]
    check(f"the wheel holds the compiled modules ({', '.join(built) or 'none'})",
          built == exts, f"missing {sorted(set(exts) - set(built))}")


def make_venv(where: Path, wheel: Path, extras: str) -> Path:
    started = time.monotonic()
    r = sh([sys.executable, "-m", "venv", where], cwd=where.parent)
    if r.returncode == 0:
        r = sh([where / "bin" / "python", "-m", "pip", "install", "--quiet",
                "--disable-pip-version-check", f"{wheel}{extras}"], cwd=where.parent)
    check(f"install {wheel.name}{extras} into a new venv", r.returncode == 0,
          r.stderr[-2000:], started)
    if r.returncode != 0:
        raise SystemExit(1)
    return where / "bin" / "aurora-gateway"


#: Cyclone DDS on loopback only, no multicast: the ros2 backend's run here (never the network)
LOOPBACK_DDS = ("<CycloneDDS><Domain id='any'><General><Interfaces><NetworkInterface name='lo'/>"
                "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery>"
                "<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>20"
                "</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers>"
                "</Discovery></Domain></CycloneDDS>")


def loopback_dds_env(work: Path) -> dict[str, str]:
    """The environment with DDS (the ros2 backend) on loopback, on a domain of its own."""
    cfg = work / "cyclonedds.xml"
    cfg.write_text(LOOPBACK_DDS)
    return {**os.environ, "CYCLONEDDS_URI": cfg.as_uri(),
            "ROS_DOMAIN_ID": str(100 + os.getpid() % 100)}


def run_all(exe: Path, work: Path) -> None:
    """Every backend's flag at once, for 2 s, recording; then the commands around it."""
    recording = work / "flight.aur"
    with ptys(3) as (crsf, hc12, xbee):
        started = time.monotonic()
        r = sh([exe, "run", "--duration", "2", "--source", "sim", "--sim-speed", "10",
                "--record", recording, "--status-interval", "1",
                "--mavlink", f"udpout:127.0.0.1:{free_port()}",
                "--mavlink", f"tcpin:127.0.0.1:{free_port()}",
                "--crsf", crsf, "--hc12", hc12, "--xbee", xbee,
                "--zenoh-mode", "peer", "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}",
                "--uavtalk", f"tcpin:127.0.0.1:{free_port()}",
                "--fprime", f"tcpin:127.0.0.1:{free_port()}",
                "--foxglove", f"127.0.0.1:{free_port()}",
                "--http", f"127.0.0.1:{free_port()}", "--ros2"], cwd=work,
               env=loopback_dds_env(work))
    started_line = next((ln for ln in r.stderr.splitlines() if ": sources " in ln), "")
    want = ("console", "mavlink", "crsf", "zenoh", "hc12", "uavtalk", "fprime", "xbee",
            "foxglove", "http", "ros2")
    missing = [b for b in want if b not in started_line]
    bad = [ln for ln in r.stderr.splitlines() if any(m in ln for m in FAILURE_MARKS)]
    check("run --duration 2 with every backend's flag: exit 0, every backend started",
          r.returncode == 0 and not missing and not bad and _size(recording) > 0,
          f"exit {r.returncode}; not started: {missing}; {bad[:5]}; stderr tail:\n"
          + r.stderr[-3000:], started)

    started = time.monotonic()
    r = sh([exe, "run", "--log-format", "json", "--duration", "3"], cwd=work)
    lines = r.stderr.splitlines()
    text = [ln for ln in lines if not _json_object(ln)]
    check(f"run --log-format json --duration 3: every stderr line a JSON object ({len(lines)})",
          r.returncode == 0 and bool(lines) and not text,
          f"exit {r.returncode}; not JSON: {text[:5]}", started)

    share = exe.parent.parent / "share" / DIST  # the files for the user (data-files)
    shared = {"foxglove-layout.json": ROOT / "docs" / "foxglove-layout.json",
              "gateway.toml": ROOT / "examples" / "gateway.toml",
              "aurora-gateway.service": ROOT / "examples" / "aurora-gateway.service"}
    differ = [n for n, src in shared.items()
              if not (share / n).is_file() or (share / n).read_bytes() != src.read_bytes()]
    check(f"the install's share/{DIST}/ holds the layout, the example and the unit",
          not differ, f"missing or different: {differ}")
    example = work / "gateway.toml"
    shutil.copy(ROOT / "examples" / "gateway.toml", example)
    expect_ok(exe, work, ["check-config", example.name], "check-config examples/gateway.toml")

    started = time.monotonic()
    r = sh([exe, "fprime-dictionary", "-o", "dictionary.json"], cwd=work)
    try:
        channels = len(json.loads((work / "dictionary.json").read_text())["telemetryChannels"])
    except (OSError, ValueError, KeyError):
        channels = 0
    check(f"fprime-dictionary ({channels} channels)", r.returncode == 0 and channels > 0,
          r.stderr[-2000:], started)
    expect_ok(exe, work, ["mavlink-modes"], "mavlink-modes")
    started = time.monotonic()
    r = sh([exe, "--version"], cwd=work)
    check("--version: the compiled MAVLink routing and recvmmsg/sendmmsg are in use",
          r.returncode == 0 and "compiled: MAVLink routing, recvmmsg/sendmmsg\n" in r.stdout,
          f"exit {r.returncode}: {r.stdout!r}", started)
    expect_ok(exe, work, ["export", recording.name, "--format", "mcap", "-o", "flight.mcap"],
              "export --format mcap", work / "flight.mcap", MCAP_MAGIC)
    expect_ok(exe, work, ["export", recording.name, "--format", "rosbag2", "-o", "flight_bag"],
              "export --format rosbag2", work / "flight_bag" / "flight_bag.mcap", MCAP_MAGIC)
    expect_ok(exe, work, ["plot", recording.name, "-o", "flight.png"], "plot",
              work / "flight.png", PNG_MAGIC)


def _size(path: Path) -> int:
    return path.stat().st_size if path.exists() else 0


def _json_object(line: str) -> bool:
    try:
        return isinstance(json.loads(line), dict)
    except ValueError:
        return False


def expect_ok(exe: Path, work: Path, args: list[str], name: str, output: Path | None = None,
              magic: bytes = b"") -> None:
    started = time.monotonic()
    r = sh([exe, *args], cwd=work)
    ok = r.returncode == 0
    if output is not None:
        ok = ok and output.exists() and output.read_bytes()[:len(magic)] == magic
    check(name, ok, f"exit {r.returncode}: {r.stderr[-2000:]}", started)


def run_base(exe: Path, work: Path) -> None:
    """Without extras: each optional piece is one line naming its extra, exit 2."""
    recording = work / "flight.aur"
    started = time.monotonic()
    r = sh([exe, "record", recording.name, "--source", "sim", "--sim-speed", "10",
            "--duration", "1"], cwd=work)
    check("base install: record", r.returncode == 0 and _size(recording) > 0,
          f"exit {r.returncode}: {r.stderr[-2000:]}", started)
    cases = [
        ("run --foxglove", ["run", "--duration", "1", "--foxglove", f"127.0.0.1:{free_port()}"],
         "foxglove"),
        ("run --http", ["run", "--duration", "1", "--http", f"127.0.0.1:{free_port()}"], "http"),
        ("run --ros2", ["run", "--duration", "1", "--ros2"], "ros2"),
        ("plot", ["plot", str(recording), "-o", "flight.png"], "plot"),
        ("export --format mcap", ["export", str(recording), "--format", "mcap", "-o",
                                  "flight.mcap"], "mcap"),
        ("export --format rosbag2", ["export", str(recording), "--format", "rosbag2", "-o",
                                     "flight_bag"], "ros2"),
    ]
    for label, args, extra in cases:
        started = time.monotonic()
        r = sh([exe, *args], cwd=work)
        lines = r.stderr.splitlines()
        ok = (r.returncode == 2 and len(lines) == 1
              and f"pip install '{DIST}[{extra}]'" in lines[0])
        check(f"base install: {label}: one line naming the {extra!r} extra, exit 2", ok,
              f"exit {r.returncode}, stderr: {r.stderr[-1500:]!r}", started)
    example = work / "gateway.toml"
    shutil.copy(ROOT / "examples" / "gateway.toml", example)
    expect_ok(exe, work, ["check-config", example.name],
              "base install: check-config examples/gateway.toml (optional backends disabled)")
    started = time.monotonic()
    r = sh([exe, "run", "--duration", "1"], cwd=work)
    bad = [ln for ln in r.stderr.splitlines() if any(m in ln for m in FAILURE_MARKS)]
    check("base install: run (embedded default) exit 0", r.returncode == 0 and not bad,
          f"exit {r.returncode}: {r.stderr[-2000:]}", started)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory")
    args = ap.parse_args()
    t0 = time.monotonic()
    version = PYPROJECT["project"]["version"]
    tmp = Path(tempfile.mkdtemp(prefix="aurora-wheel-"))
    say(f"check_wheel: {DIST} {version} in {tmp}")
    try:
        wheel = build_wheel(tmp)
        check_contents(wheel)
        full = tmp / "work-all"
        base = tmp / "work-base"
        full.mkdir()
        base.mkdir()
        run_all(make_venv(tmp / "venv-all", wheel, "[all]"), full)
        run_base(make_venv(tmp / "venv-base", wheel, ""), base)
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    say(f"check_wheel: {'FAILED: ' + ', '.join(failures) if failures else 'all passed'} "
        f"in {time.monotonic() - t0:.0f} s")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
