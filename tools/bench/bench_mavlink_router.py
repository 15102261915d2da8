"""Benchmark: lossless MAVLink forwarding through the gateway's router, beside MAVProxy.

Harness (the same for every router under test, each in its own process):

    this process ──UDP──► router  udpin:127.0.0.1:A ──► udpout:127.0.0.1:B ──UDP──► this process
     (sender)                                                                     (receiver)

The sender sends MAVLink 2 ATTITUDE frames (39 bytes, one per datagram, as autopilots and
MAVProxy send them) from system 7, keeping at most ``--window`` frames in flight: it sends
while fewer than that are unaccounted for and otherwise reads what came out.  Nothing
overflows a socket buffer that way, so a correct router loses nothing; the run checks it
(every frame must come out, in order by sequence number) and reports any loss.  The rate is
frames received / wall time; the router's CPU is its process's user+system time over the same
interval (from ``/proc``), as a percentage of one core.

Routers: ``ours`` (a MavlinkBackend with those two endpoints, routing on, its own streams on,
in a subprocess) and ``mavproxy`` (``mavproxy.py --master=udpin:… --out=udpout:…
--default-modules=output --daemon --non-interactive --no-state``) when it is installed.
Each figure is the median of ``--repeat`` runs; the ratio is taken per repetition (ours and
MAVProxy run back to back, so they saw the same machine load) and its median printed.
Prints figures; asserts nothing about time.

Run: ``.venv/bin/python tools/bench/bench_mavlink_router.py [--messages N] [--repeat N]
[--window N] [--no-mavproxy]``
"""

from __future__ import annotations

import argparse
import contextlib
import os
import platform
import select
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

TARGET_RATIO = 3.0  # the issue: at least 3x MAVProxy
REFERENCE_MAVLINK_ROUTER = 64_000  # msg/s, mavlink-router (C++) on this kind of machine
REFERENCE_CPU = 0.38  # … at this share of one core (shared/specs/mavlink.md)
SENDER_SYSID = 7
TICKS = os.sysconf("SC_CLK_TCK")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _frames() -> list[bytes]:
    from dialects import aurora_mavlink as mav

    m = mav.MAVLink(None, SENDER_SYSID, 1)
    out = []
    for i in range(256):
        m.seq = i
        out.append(mav.MAVLink_attitude_message(i * 10, 0.1, 0.2, 0.3, 0.01, 0.02, 0.03).pack(m))
    return out


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / TICKS  # utime, stime


# -- the routers under test ---------------------------------------------------------------------

def serve_ours(port_in: int, port_out: int) -> int:
    """Run a MavlinkBackend routing udpin → udpout until stdin closes (subprocess mode)."""
    from backends.mavlink import MavlinkBackend
    from gateway.dispatcher import Dispatcher

    b = MavlinkBackend(endpoints=[f"udpin:127.0.0.1:{port_in}", f"udpout:127.0.0.1:{port_out}"])
    d = Dispatcher([b])
    failures = d.start()
    if failures:
        print(f"failed: {failures}", flush=True)
        return 1
    print("ready", flush=True)
    sys.stdin.read()
    d.close()
    return 0


def start_ours(port_in: int, port_out: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, "--serve", str(port_in), str(port_out)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def mavproxy_path() -> str | None:
    found = shutil.which("mavproxy.py", path=str(Path(sys.executable).parent))
    return found or shutil.which("mavproxy.py")


def start_mavproxy(port_in: int, port_out: int, workdir: str) -> subprocess.Popen:
    exe = mavproxy_path()
    assert exe is not None
    return subprocess.Popen(
        [sys.executable, exe, f"--master=udpin:127.0.0.1:{port_in}",
         f"--out=udpout:127.0.0.1:{port_out}", "--default-modules=output", "--daemon",
         "--non-interactive", "--no-state", "--nowait", "--streamrate=-1"],
        stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        cwd=workdir)


# -- the harness --------------------------------------------------------------------------------

class Harness:
    def __init__(self, port_in: int) -> None:
        self.dest = ("127.0.0.1", port_in)
        self.tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for s in (self.tx, self.rx):
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        self.rx.bind(("127.0.0.1", 0))
        self.rx.setblocking(False)
        self.frames = _frames()

    @property
    def port_out(self) -> int:
        return self.rx.getsockname()[1]

    def _drain(self) -> list[int]:
        """Sequence numbers of the sender's frames waiting at the receiver."""
        seqs = []
        while True:
            try:
                data = self.rx.recv(65536)
            except BlockingIOError:
                return seqs
            if len(data) > 6 and data[0] == 0xFD and data[5] == SENDER_SYSID:
                seqs.append(data[4])

    def wait_ready(self, proc: subprocess.Popen, timeout: float = 60.0) -> bool:
        """Probe until a frame makes it through (the router is up and routing)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                return False
            self.tx.sendto(self.frames[0], self.dest)
            select.select([self.rx], [], [], 0.2)
            if self._drain():
                time.sleep(0.3)  # let start-up chatter settle
                self._drain()
                return True
        return False

    def run(self, n: int, window: int, pid: int) -> dict[str, float]:
        frames, tx, dest, rx = self.frames, self.tx, self.dest, self.rx
        sent = received = 0
        expected_seq = 0
        out_of_order = 0
        stall_s = 2.0
        cpu0 = _cpu_s(pid)
        t0 = time.perf_counter()
        last_progress = t0
        while received < n:
            while sent < n and sent - received < window:
                tx.sendto(frames[sent & 0xFF], dest)
                sent += 1
            r, _, _ = select.select([rx], [], [], 0.05)
            got = self._drain() if r else []
            if got:
                for s in got:
                    if s != expected_seq:
                        out_of_order += 1
                    expected_seq = (s + 1) & 0xFF
                received += len(got)
                last_progress = time.perf_counter()
            elif time.perf_counter() - last_progress > stall_s:
                break  # frames lost: they will not come any more
        t1 = time.perf_counter() - (stall_s if received < n else 0.0)
        cpu1 = _cpu_s(pid)
        wall = t1 - t0
        return {"rate": received / wall, "lost": n - received, "out_of_order": out_of_order,
                "cpu_pct": 100.0 * (cpu1 - cpu0) / wall, "wall": wall,
                "cpu_us": 1e6 * (cpu1 - cpu0) / max(received, 1)}

    def close(self) -> None:
        self.tx.close()
        self.rx.close()


def measure(name: str, n: int, window: int, repeat: int) -> list[dict[str, float]]:
    results = []
    for _ in range(repeat):
        port_in = _free_udp_port()
        h = Harness(port_in)
        with tempfile.TemporaryDirectory() as tmp:
            proc = (start_ours(port_in, h.port_out) if name == "ours"
                    else start_mavproxy(port_in, h.port_out, tmp))
            try:
                if name == "ours":
                    line = proc.stdout.readline().strip()  # type: ignore[union-attr]
                    if line != "ready":
                        raise RuntimeError(f"{name} did not start: {line!r}")
                if not h.wait_ready(proc):
                    raise RuntimeError(f"{name} forwarded nothing")
                h.run(min(2000, n), window, proc.pid)  # warm-up, not counted
                results.append(h.run(n, window, proc.pid))
            finally:
                with contextlib.suppress(Exception):
                    proc.stdin.close()  # type: ignore[union-attr]
                try:
                    proc.wait(5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(5)
                h.close()
    return results


def _fmt(rs: list[dict[str, float]], key: str) -> str:
    vals = [r[key] for r in rs]
    return f"{statistics.median(vals):9.0f} (min {min(vals):.0f}, max {max(vals):.0f})"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--messages", type=int, default=50_000, help="frames per run")
    p.add_argument("--repeat", type=int, default=5, help="runs per router (median printed)")
    p.add_argument("--window", type=int, default=128, help="frames in flight at most")
    p.add_argument("--no-mavproxy", action="store_true", help="measure only ours")
    p.add_argument("--serve", nargs=2, type=int, metavar=("PORT_IN", "PORT_OUT"),
                   help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.serve:
        return serve_ours(*args.serve)
    if not Path("/proc/self/stat").exists():
        print("needs /proc to measure CPU", file=sys.stderr)
        return 2
    print(f"# {platform.python_implementation()} {platform.python_version()}, "
          f"{os.cpu_count()} CPUs, {args.messages} ATTITUDE frames/run, window {args.window}, "
          f"{args.repeat} runs each")
    names = ["ours"]
    if not args.no_mavproxy:
        if mavproxy_path():
            names.append("mavproxy")
        else:
            print("# MAVProxy not installed (pip install MAVProxy): measuring ours only")
    per: dict[str, list[dict[str, float]]] = {n: [] for n in names}
    for _ in range(args.repeat):  # interleaved: each ratio compares runs under the same load
        for name in names:
            per[name] += measure(name, args.messages, args.window, 1)
    for name in names:
        rs = per[name]
        lost = sum(r["lost"] for r in rs)
        ooo = sum(r["out_of_order"] for r in rs)
        print(f"{name:9s} msgs/s {_fmt(rs, 'rate')}   CPU % of a core {_fmt(rs, 'cpu_pct')}"
              f"   CPU µs/msg {statistics.median(r['cpu_us'] for r in rs):5.1f}"
              f"   lost {lost}, out of order {ooo}")
    if "mavproxy" in per:
        ratios = [o["rate"] / m["rate"] for o, m in zip(per["ours"], per["mavproxy"],
                                                         strict=True)]
        med = statistics.median(ratios)
        print(f"ours/MAVProxy: {med:.2f}x (per-run {', '.join(f'{r:.2f}' for r in ratios)}; "
              f"target ≥ {TARGET_RATIO:.0f}x: {'met' if med >= TARGET_RATIO else 'NOT met'})")
    ours = statistics.median(r["rate"] for r in per["ours"])
    ours_us = statistics.median(r["cpu_us"] for r in per["ours"])
    ref_us = 1e6 * REFERENCE_CPU / REFERENCE_MAVLINK_ROUTER
    print(f"ours vs mavlink-router's ~{REFERENCE_MAVLINK_ROUTER} msg/s at ~{REFERENCE_CPU:.0%} "
          f"of a core (reference figures, not measured in this run): rate "
          f"{100 * ours / REFERENCE_MAVLINK_ROUTER:.0f} %, CPU per message {ours_us / ref_us:.1f}x "
          f"theirs ({ref_us:.1f} µs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
