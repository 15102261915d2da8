#!/usr/bin/env python3
"""Ctrl-C (or SIGTERM) at random moments of the long-running commands' start-up, many times:
the exit statuses each command ended with, counted.  Every one should be 130 (0 for SIGTERM);
a negative status is a crash (-11: SIGSEGV).  tests/test_exit_codes.py samples three moments
per command on every run; this samples hundreds, to find the rare ones.

    python tools/stress_signals.py --runs 200 --max-delay 0.6 [--signal TERM] [COMMAND ...]
"""

from __future__ import annotations

import argparse
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: what a quiet stop never prints (tests/test_exit_codes.py's list)
NOISE = ("Traceback", "KeyboardInterrupt", "Exception ignored", "Fatal Python error")
STOP_TIMEOUT_S = 20.0  # the commands run 60 s: a signal lost shows, a hang too


def commands(tmp: Path) -> dict[str, list[str]]:
    return {
        "run": ["run", "--only", "console", "--duration", "60"],
        "record": ["record", str(tmp / "stress.aur"), "--source", "sim", "--duration", "60"],
        "monitor": ["monitor", "--source", "sim", "--duration", "60"],
        "listen": ["listen", "--connect", "tcp/127.0.0.1:9", "--duration", "60"],
        "simulate": ["simulate", "--out", "loop://"],
        "decode": ["decode", "-"],
        "run-all": ["run", "--duration", "60"],  # the embedded default: every backend
    }


def runs_our_code(pid: int) -> bool:
    """True once the entry point has caught SIGTERM, its first act (gateway/__main__.py):
    a signal before that is the interpreter's own start-up, not the gateway's."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True
    m = re.search(r"^SigCgt:\s*([0-9a-f]+)$", status, re.M)
    return m is not None and bool(int(m.group(1), 16) >> (signal.SIGTERM - 1) & 1)


def once(exe: list[str], args: list[str], at_s: float, sig: int) -> tuple[int, str]:
    """Start the command, signal it ``at_s`` after start (or once its code runs, if later)."""
    proc = subprocess.Popen([*exe, *args], cwd=ROOT, stdin=subprocess.PIPE,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(at_s)
    while not runs_our_code(proc.pid):
        time.sleep(0.001)
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGABRT)  # with PYTHONFAULTHANDLER=1: every thread's stack
        _, err = proc.communicate()
        return -999, f"did not stop within {STOP_TIMEOUT_S:.0f} s\n{err}"
    return proc.returncode, err


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", nargs="*", help="the commands to try (default: all)")
    ap.add_argument("--runs", type=int, default=100, help="tries per command")
    ap.add_argument("--max-delay", type=float, default=0.6, help="latest moment, s")
    ap.add_argument("--signal", choices=("INT", "TERM"), default="INT")
    ap.add_argument("--verbose", action="store_true", help="print a stuck command's stacks")
    ap.add_argument("--jobs", type=int, default=2, help="commands started at once")
    ap.add_argument("--exe", default=shutil.which("aurora-gateway") or "",
                    help="the command (default: aurora-gateway on PATH, else python -m gateway)")
    a = ap.parse_args()
    sig = signal.SIGINT if a.signal == "INT" else signal.SIGTERM
    want = 130 if sig == signal.SIGINT else 0
    exe = [a.exe] if a.exe else [sys.executable, "-m", "gateway"]
    bad = 0
    with tempfile.TemporaryDirectory() as tmp:
        table = commands(Path(tmp))
        for name in a.command or list(table):
            moments = [random.uniform(0.0, a.max_delay) for _ in range(a.runs)]
            with ThreadPoolExecutor(a.jobs) as pool:
                args = table[name]
                results = list(pool.map(lambda at, args=args: once(exe, args, at, sig), moments))
            counts = Counter(status for status, _ in results)
            odd = [(round(at, 3), status, err.strip().splitlines()[-1:])
                   for at, (status, err) in zip(moments, results, strict=True)
                   if status != want or any(n in err for n in NOISE)]
            bad += len(odd)
            print(f"{name:9s} {dict(sorted(counts.items()))}", flush=True)
            for row in odd[:5]:
                print(f"          at {row[0]} s: status {row[1]} {row[2]}")
            for (status, err) in results:
                if status == -999 and a.verbose:
                    print(err)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
