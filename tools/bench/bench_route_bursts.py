"""Benchmark: MAVLink routing CPU with a bursty sender, the gateway beside mavlink-router.

A second harness next to ``bench_mavlink_router.py`` (whose sender paces one datagram at a
time): here the sender writes bursts — ``--burst`` datagrams back to back every
``--burst`` / ``--rate`` seconds, one MAVLink 2 frame per datagram (a telemetry radio's bridge
or a companion computer flushing its queue does this) — and a receiver counts what comes out.
Each router runs as its own process, ``udpin`` on one port, ``udpout`` to the receiver; its
CPU is read from ``/proc/PID/stat`` (user + system) across the measured phase.  Routers run
in turn, ``--repeat`` times each, interleaved; the table gives medians and the ratio of ours to
mavlink-router's inside each repetition.

    python tools/bench/bench_route_bursts.py --mavlink-routerd PATH [--rate 10000] [--burst 20]
        [--floor]

``--floor`` adds ``route_floor.py``: the same system calls as the gateway's router, with its
1 ms hold (``--floor-hold`` to change it), and no other work — where the gateway's cost would
be with no Python per datagram.

Besides the CPU per 100k datagrams, each line splits it: user and system seconds (from
``/proc/PID/stat``, the whole process) and the context switches the router's threads made,
voluntary (it waited: one per wake-up, about) and involuntary (it was preempted: by the
sender or the receiver it woke, mid-work), summed over ``/proc/PID/task/*/status``.
``--sender-process`` sends the same bursts from ``burst_sender.py``, a process of its own: the
sender then shares no interpreter lock with the receiver thread (a second harness's view).

``mavlink-routerd`` is built by ``tools/bench/build_mavlink_router.sh``.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench_mavlink_router import _cpu_s as cpu_s  # (this directory: the script's own)
from bench_mavlink_router import _free_udp_port as free_udp_port
from pymavlink.dialects.v20 import common

TICKS = os.sysconf("SC_CLK_TCK")


def proc_split(pid: int) -> tuple[float, float, int, int]:
    """User and system CPU seconds of process ``pid`` (its threads, ended ones too), and the
    voluntary and involuntary context switches of its live threads."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    user, system = int(fields[11]) / TICKS, int(fields[12]) / TICKS
    vol = invol = 0
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/status") as f:
                for line in f:
                    if line.startswith("voluntary_ctxt_switches:"):
                        vol += int(line.split()[1])
                    elif line.startswith("nonvoluntary_ctxt_switches:"):
                        invol += int(line.split()[1])
        except OSError:  # (a thread that ended meanwhile)
            continue
    return user, system, vol, invol


def frames(n: int) -> list[bytes]:
    """``n`` ATTITUDE frames of system 1, each with its own time_boot_ms and sequence."""
    mav = common.MAVLink(None, 1, 1)
    out = []
    for i in range(n):
        out.append(common.MAVLink_attitude_message(i, 0.1, 0.2, 0.3, 0, 0, 0).pack(mav))
        mav.seq = (mav.seq + 1) & 0xFF
    return out


def argv_of(router: str, args: argparse.Namespace, port_in: int, port_out: int,
            tmp: str) -> list[str]:
    if router == "mavlink-router":
        conf = Path(tmp) / "main.conf"
        conf.write_text("[General]\nTcpServerPort = 0\n")
        return [args.mavlink_routerd, "-t", "0", "-c", str(conf), "-e",
                f"127.0.0.1:{port_out}", f"127.0.0.1:{port_in}"]
    if router == "floor":
        hold = [] if args.floor_hold is None else ["--hold", str(args.floor_hold)]
        return [sys.executable, str(Path(__file__).with_name("route_floor.py")), str(port_in),
                str(port_out), *hold]
    return [args.aurora_gateway, "run", "--only", "mavlink", "--status-interval", "0",
            "--source", f"mavlink:udpin:127.0.0.1:{port_in}",
            "--mavlink", f"udpout:127.0.0.1:{port_out}"]


def measure(router: str, args: argparse.Namespace, payload: list[bytes]) -> dict[str, float]:
    port_in = free_udp_port()
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(0.2)
    got = [0]
    stop = threading.Event()

    def receive() -> None:
        while not stop.is_set():
            try:
                data = rx.recv(65536)
            except TimeoutError:
                continue
            if len(data) > 10 and data[7] | data[8] << 8 | data[9] << 16 == 30:  # ATTITUDE
                got[0] += 1

    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.Popen(argv_of(router, args, port_in, rx.getsockname()[1], tmp),
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        t = threading.Thread(target=receive, daemon=True)
        t.start()
        try:
            deadline = time.monotonic() + 10
            while got[0] == 0 and time.monotonic() < deadline:  # until it forwards
                tx.sendto(payload[0], ("127.0.0.1", port_in))
                time.sleep(0.01)
            if got[0] == 0:
                raise SystemExit(f"{router}: forwarded nothing in 10 s")
            time.sleep(0.3)
            got[0] = 0
            period = args.burst / args.rate
            sender = None
            if args.sender_process:  # the same bursts from a process of its own
                sender = subprocess.Popen(
                    [sys.executable, str(Path(__file__).with_name("burst_sender.py")),
                     str(port_in), "--rate", str(args.rate), "--burst", str(args.burst),
                     "--seconds", str(args.seconds)],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
                assert sender.stdin is not None and sender.stdout is not None
                if sender.stdout.readline().strip() != "ready":
                    raise SystemExit("burst_sender.py did not start")
            c0, t0, s0 = cpu_s(proc.pid), time.monotonic(), proc_split(proc.pid)
            nxt = t0
            if sender is not None:
                sender.stdin.write("go\n")  # type: ignore[union-attr]
                sender.stdin.flush()  # type: ignore[union-attr]
                sender.wait()
            else:
                for i in range(0, len(payload), args.burst):
                    for f in payload[i:i + args.burst]:
                        tx.sendto(f, ("127.0.0.1", port_in))
                    nxt += period
                    delay = nxt - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
            time.sleep(0.3)  # the last ones out
            c1, t1, s1 = cpu_s(proc.pid), time.monotonic(), proc_split(proc.pid)
        finally:
            stop.set()
            proc.terminate()
            proc.wait(10)
            t.join(2)
            rx.close()
            tx.close()
    n = len(payload)
    per = 100_000 / n
    user, system, vol, invol = ((b - a) * per for a, b in zip(s0, s1, strict=True))
    return {"cpu_per_100k_s": (c1 - c0) * per, "lost_pct": 100 * (n - got[0]) / n,
            "rate": n / (t1 - t0 - 0.3), "user_s": user, "sys_s": system,
            "voluntary": vol, "involuntary": invol}


def split_text(r: dict[str, float]) -> str:
    """The CPU's split, per 100k datagrams."""
    return (f"user {r['user_s']:.2f} s, system {r['sys_s']:.2f} s, "
            f"switches {r['voluntary']:,.0f} waited / {r['involuntary']:,.0f} preempted")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mavlink-routerd", required=True)
    p.add_argument("--aurora-gateway",
                   default=str(Path(sys.executable).with_name("aurora-gateway")))
    p.add_argument("--rate", type=float, default=10_000.0, help="datagrams per second")
    p.add_argument("--burst", type=int, default=20, help="datagrams per burst")
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--floor", action="store_true",
                   help="also run route_floor.py: recvmmsg → sendmmsg and nothing else")
    p.add_argument("--floor-hold", type=float, metavar="SECONDS",
                   help="route_floor.py's hold between reads in a stream (default: the "
                        "gateway's COALESCE_S; 0: none)")
    p.add_argument("--sender-process", action="store_true",
                   help="send from burst_sender.py, a process of its own (no lock shared "
                        "with the receiver thread; its start-up is in the measured phase)")
    args = p.parse_args()
    payload = frames(int(args.rate * args.seconds))
    results: dict[str, list[dict[str, float]]] = {"mavlink-router": [], "aurora-gateway": []}
    if args.floor:
        results["floor"] = []
    for i in range(args.repeat):
        for router in results:
            r = measure(router, args, payload)
            results[router].append(r)
            print(f"[{i + 1}/{args.repeat}] {router}: CPU {r['cpu_per_100k_s']:.2f} s per 100k, "
                  f"lost {r['lost_pct']:.2f} %, {r['rate']:.0f} msg/s; {split_text(r)}",
                  flush=True)
    ratios = [a["cpu_per_100k_s"] / m["cpu_per_100k_s"]
              for a, m in zip(results["aurora-gateway"], results["mavlink-router"], strict=True)]
    print(f"\nbursts of {args.burst} at {args.rate:.0f} datagrams/s, {args.seconds:.0f} s, "
          f"{args.repeat} repetitions (medians):")
    for router, rs in results.items():
        med = {k: statistics.median(r[k] for r in rs) for k in rs[0]}
        print(f"  {router}: CPU {med['cpu_per_100k_s']:.2f} s per 100k, lost "
              f"{med['lost_pct']:.2f} %; {split_text(med)}")
    print(f"  ratio ours / mavlink-router's, per repetition: "
          f"{', '.join(f'{x:.2f}' for x in ratios)}; median {statistics.median(ratios):.2f}×")
    if args.floor:
        floor = [f["cpu_per_100k_s"] / m["cpu_per_100k_s"]
                 for f, m in zip(results["floor"], results["mavlink-router"], strict=True)]
        print(f"  ratio floor / mavlink-router's, per repetition: "
              f"{', '.join(f'{x:.2f}' for x in floor)}; median {statistics.median(floor):.2f}×")
    return 0


if __name__ == "__main__":
    sys.exit(main())
