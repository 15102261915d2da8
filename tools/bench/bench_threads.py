"""Benchmark: a running gateway's threads, its time to the first update and its stop time.

For each case an ``aurora-gateway run …`` process is started; the figures are

* **threads**: the entries of ``/proc/PID/task`` ``--sample-s`` (3) seconds after the start,
  with their names (``/proc/PID/task/TID/comm``: Python names threads there, 15 characters);
* **first update**: from the process's start to the first console line of the simulated
  flight (``[vehicle ]t= …``) on its standard output;
* **stop**: from SIGINT (sent ``--interrupt-s`` seconds after the start) to the process's exit.

Cases: the embedded default (``run --duration 6 --status-interval 0``: the simulated flight
through every default backend), and two and four simulated sources to the console only.  Each runs
``--repeat`` times; the median (min, max) is printed.  Prints figures; asserts nothing.

Run: ``.venv/bin/python tools/bench/bench_threads.py [--gateway PATH] [--repeat N]``
(``--gateway /work/wt-before/.venv/bin/aurora-gateway`` measures another checkout's).
"""

from __future__ import annotations

import argparse
import collections
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CASES = {
    "default": ["run", "--duration", "6", "--status-interval", "0"],
    "sim+sim console": ["run", "--source", "sim", "--source", "sim", "--only", "console",
                        "--duration", "6", "--status-interval", "0"],
    "4 sim console": ["run", *["--source", "sim"] * 4, "--only", "console",
                      "--duration", "6", "--status-interval", "0"],
}


def _threads(pid: int) -> list[str]:
    names = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            names.append(Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip())
        except OSError:
            continue  # ended meanwhile
    return names


def measure(gateway: str, args: list[str], sample_s: float,
            interrupt_s: float) -> tuple[int, list[str], float | None, float]:
    first: list[float] = []
    t0 = time.monotonic()
    proc = subprocess.Popen([gateway, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, cwd="/tmp")
    seen = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            if not first and " t=" in f" {line}":
                first.append(time.monotonic() - t0)
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    time.sleep(max(0.0, t0 + sample_s - time.monotonic()))
    names = _threads(proc.pid)
    time.sleep(max(0.0, t0 + interrupt_s - time.monotonic()))
    t_int = time.monotonic()
    proc.send_signal(signal.SIGINT)
    proc.wait(30)
    stop_s = time.monotonic() - t_int
    reader.join(5)
    return len(names), names, (first[0] if first else None), stop_s


def _fmt(values: list[float], unit: str, scale: float = 1.0) -> str:
    if not values:
        return "-"
    v = [x * scale for x in values]
    return f"{statistics.median(v):.0f} {unit} ({min(v):.0f}, {max(v):.0f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gateway", default=str(ROOT / ".venv" / "bin" / "aurora-gateway"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--sample-s", type=float, default=3.0)
    ap.add_argument("--interrupt-s", type=float, default=4.0)
    a = ap.parse_args()
    print(f"{a.gateway}; {a.repeat} runs per case; threads sampled at {a.sample_s} s, "
          f"SIGINT at {a.interrupt_s} s", file=sys.stderr)
    for case, args in CASES.items():
        counts: list[float] = []
        firsts: list[float] = []
        stops: list[float] = []
        names: collections.Counter[str] = collections.Counter()
        for _ in range(a.repeat):
            n, ns, first, stop = measure(a.gateway, args, a.sample_s, a.interrupt_s)
            counts.append(n)
            stops.append(stop)
            if first is not None:
                firsts.append(first)
            names = collections.Counter(ns)
        print(f"{case:16s} threads {_fmt(counts, '')}  first update {_fmt(firsts, 'ms', 1e3)}"
              f"  stop {_fmt(stops, 'ms', 1e3)}")
        print(f"{'':16s} last run's threads (/proc names): "
              + ", ".join(f"{k}×{v}" if v > 1 else k for k, v in sorted(names.items())))


if __name__ == "__main__":
    main()
