"""Benchmark: from spawning ``aurora-gateway run`` to its first MAVLink datagram, per install.

Each ``--gateway`` (an ``aurora-gateway`` executable: ``.venv-run/bin/aurora-gateway`` of
``make run``, ``.venv/bin/aurora-gateway`` of ``make test``, a wheel installed elsewhere) runs
from ``/tmp``, in each ``--case`` (repeatable; default ``sim``):

``sim``      ``run --source sim --only mavlink --mavlink udpout:127.0.0.1:PORT``: the first
             datagram on PORT;
``route``    ``run --only mavlink --source mavlink:udpin:127.0.0.1:IN --mavlink
             udpout:127.0.0.1:PORT`` while a vehicle sends a HEARTBEAT to IN every
             millisecond: the first of them forwarded to PORT (issue 26: ≤ 0.1 s);
``default``  ``run --mavlink udpout:127.0.0.1:PORT`` (the embedded default, every backend):
             the first HEARTBEAT on PORT (issue 26: ≤ 0.3 s).

The installs take turns within each repetition (one uncounted warm-up round first: the
bytecode caches), so a load change on the shared machine hits them alike; the median (min,
max) of ``--repeat`` (7) rounds is printed, with the installed distributions' count.  Prints
figures; asserts nothing.

Run: ``python3 tools/bench/bench_first_frame.py --gateway .venv-run/bin/aurora-gateway
--gateway .venv/bin/aurora-gateway --case route --case default``
"""

from __future__ import annotations

import argparse
import signal
import socket
import statistics
import subprocess
import threading
import time
from pathlib import Path

TIMEOUT_S = 20.0


#: A vehicle's MAVLink 2 HEARTBEAT, system 1 component 1 (quadrotor, ArduPilot, custom mode 4,
#: active), as pymavlink packs it (CRC included).
HEARTBEAT = bytes.fromhex("fd0900000001010000000400000002035103037e22")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def first_frame(gateway: str, case: str = "sim") -> float | None:
    """Seconds from the spawn to the first datagram the case waits for (None: none within
    TIMEOUT_S)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", 0))
        port = rx.getsockname()[1]
        rx.settimeout(TIMEOUT_S)
        out = f"udpout:127.0.0.1:{port}"
        common = ["--status-interval", "0", "--log-level", "warning"]
        stop = threading.Event()
        wanted: bytes | None = None
        if case == "route":
            wanted = HEARTBEAT
            inport = _free_udp_port()
            args = ["--only", "mavlink", "--source", f"mavlink:udpin:127.0.0.1:{inport}",
                    "--mavlink", out]

            def vehicle() -> None:
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                    while not stop.wait(0.001):
                        tx.sendto(wanted, ("127.0.0.1", inport))  # type: ignore[arg-type]

            threading.Thread(target=vehicle, daemon=True).start()
        elif case == "default":
            args = ["--mavlink", out]
        else:
            args = ["--source", "sim", "--only", "mavlink", "--mavlink", out]
        t0 = time.monotonic()
        proc = subprocess.Popen([gateway, "run", *args, *common],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                cwd="/tmp")
        took: float | None = None
        try:
            while True:
                data = rx.recv(65536)
                if case == "route" and data != wanted:
                    continue  # the gateway's own node, not the vehicle's frame
                if case == "default" and not (len(data) > 9 and data[0] == 0xFD
                                              and data[7:10] == b"\0\0\0"):
                    continue  # not a HEARTBEAT
                took = time.monotonic() - t0
                break
        except TimeoutError:
            took = None
        finally:
            stop.set()
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return took


def distributions(gateway: str) -> int:
    """Distributions installed beside ``gateway`` (-1: no ``python`` next to it)."""
    python = Path(gateway).with_name("python")
    try:
        out = subprocess.run([str(python), "-c", "import importlib.metadata as m; "
                              "print(len(list(m.distributions())))"],
                             capture_output=True, text=True, check=False)
    except OSError:
        return -1
    return int(out.stdout) if out.returncode == 0 else -1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gateway", action="append", required=True, metavar="PATH")
    ap.add_argument("--case", action="append", choices=("sim", "route", "default"),
                    help="what to time (repeatable; default sim): see the module docstring")
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    gateways = [str(Path(g).absolute()) for g in args.gateway]
    cases = args.case or ["sim"]
    times: dict[tuple[str, str], list[float]] = {(c, g): [] for c in cases for g in gateways}
    for rnd in range(args.repeat + 1):
        for c in cases:
            for g in gateways:
                took = first_frame(g, c)
                if rnd and took is not None:  # round 0: the warm-up
                    times[(c, g)].append(took)
    for (c, g), values in times.items():
        figure = (f"{statistics.median(values):.3f} s ({min(values):.3f}, {max(values):.3f})"
                  if values else "no frame")
        print(f"{c}: {g}: first frame {figure}, {len(values)} runs; "
              f"{distributions(g)} distributions installed")


if __name__ == "__main__":
    main()
