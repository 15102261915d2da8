"""Benchmark: from spawning ``aurora-gateway run`` to its first MAVLink datagram, per install.

Each ``--gateway`` (an ``aurora-gateway`` executable: ``.venv-run/bin/aurora-gateway`` of
``make run``, ``.venv/bin/aurora-gateway`` of ``make test``, a wheel installed elsewhere) runs
``run --source sim --only mavlink --mavlink udpout:127.0.0.1:PORT`` from ``/tmp``; the time
from the spawn to the first datagram on PORT is taken, then the process is stopped.  The
installs take turns within each repetition (one uncounted warm-up round first: the bytecode
caches), so a load change on the shared machine hits them alike; the median (min, max) of
``--repeat`` (7) rounds is printed, with the installed distributions' count.  Prints figures;
asserts nothing.

Run: ``python3 tools/bench/bench_first_frame.py --gateway .venv-run/bin/aurora-gateway
--gateway .venv/bin/aurora-gateway``
"""

from __future__ import annotations

import argparse
import signal
import socket
import statistics
import subprocess
import time
from pathlib import Path

TIMEOUT_S = 20.0


def first_frame(gateway: str) -> float | None:
    """Seconds from the spawn to the first datagram (None: none within TIMEOUT_S)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        port = rx.getsockname()[1]
        rx.settimeout(TIMEOUT_S)
        t0 = time.monotonic()
        proc = subprocess.Popen([gateway, "run", "--source", "sim", "--only", "mavlink",
                                 "--mavlink", f"udpout:127.0.0.1:{port}",
                                 "--status-interval", "0", "--log-level", "warning"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                cwd="/tmp")
        try:
            rx.recv(65536)
            took: float | None = time.monotonic() - t0
        except TimeoutError:
            took = None
        finally:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return took


def distributions(gateway: str) -> int:
    python = Path(gateway).with_name("python")
    out = subprocess.run([str(python), "-c", "import importlib.metadata as m; "
                          "print(len(list(m.distributions())))"],
                         capture_output=True, text=True, check=False)
    return int(out.stdout) if out.returncode == 0 else -1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gateway", action="append", required=True, metavar="PATH")
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    gateways = [str(Path(g).absolute()) for g in args.gateway]
    times: dict[str, list[float]] = {g: [] for g in gateways}
    for rnd in range(args.repeat + 1):
        for g in gateways:
            took = first_frame(g)
            if rnd and took is not None:  # round 0: the warm-up
                times[g].append(took)
    for g, values in times.items():
        figure = (f"{statistics.median(values):.3f} s ({min(values):.3f}, {max(values):.3f})"
                  if values else "no frame")
        print(f"{g}: first frame {figure}, {len(values)} runs; "
              f"{distributions(g)} distributions installed")


if __name__ == "__main__":
    main()
