"""Benchmark: Aurora frames over ``socket://`` through a running gateway's backends.

A TCP server in this process sends the simulated flight's wire frames (SM_UPDATE at the
rate, STATUS at 10 Hz) to ``aurora-gateway run --source socket://127.0.0.1:PORT`` paced in
1 ms steps for ``--duration`` seconds, then interrupts it (SIGINT) once it has read every
byte and takes its stop report (``--log-format json``).  Per run:

* **lossless**: every frame sent came in (``messages_in``) and every backend's ``dropped``
  counter is 0;
* **CPU µs per update**: the gateway process's CPU time (``/proc/PID/task/*/stat``) while
  the frames flow, divided by the frames sent; per thread (by ``comm``) as well.

Cases (``--case``): ``all`` — the embedded default backends (console, crsf, mavlink, zenoh)
plus ``--http`` with a viewer (the page's ``/events`` stream read, ``/status.json`` polled
twice a second); ``none`` — the console alone, printing state changes only (the
source, decode and ingest; a run needs one backend); ``only:NAME`` — one backend.  A
backend's cost per update is its ``only:`` case's minus ``none``'s, both taken in the same
round.  With several ``--rate``, the lossless ceiling is printed: per tree and case, the
highest rate up to which every run was lossless.

``--tree DIR`` (repeatable) runs another checkout's gateway (``PYTHONPATH=DIR``, this
venv's interpreter) side by side: rounds alternate the trees, so a change of load on the
shared machine hits them alike; medians over ``--repeat`` rounds are printed, ratios taken
within a round.  Prints figures; asserts nothing about time.

Run: ``.venv/bin/python tools/bench/bench_fanout_live.py [--rate 25000] [--duration 30]
[--repeat 3] [--case all] [--tree /work/wt-fan-before]``
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from gateway.flight import FlightModel, FlightProfile  # noqa: E402
from gateway.sources.sim import flight_frames  # noqa: E402

TICKS = os.sysconf("SC_CLK_TCK")
STATUS_HZ = 10.0
DEFAULT_BACKENDS = ("console", "crsf", "mavlink", "zenoh", "http")


def flight_stream(rate: float, duration: float) -> tuple[bytes, list[int]]:
    """The frames of ``duration`` s of flight at ``rate`` SM_UPDATEs/s: one blob and the end
    offset of each frame."""
    blob = bytearray()
    ends: list[int] = []
    model = FlightModel(FlightProfile())
    for t, frame in flight_frames(model, rate, STATUS_HZ):
        if t >= duration:
            break
        blob += frame
        ends.append(len(blob))
    return bytes(blob), ends


def cpu_by_thread(pid: int) -> dict[str, float]:
    """CPU seconds per thread (``comm/tid``) of process ``pid`` so far."""
    out: dict[str, float] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except OSError:
            continue
        comm = stat[stat.index("(") + 1:stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2:].split()
        out[f"{comm}/{tid}"] = (int(fields[11]) + int(fields[12])) / TICKS
    return out


@dataclass
class Run:
    tree: str
    case: str
    sent: int = 0
    received: int = 0
    cpu_s: float = 0.0
    wall_s: float = 0.0
    threads: dict[str, float] = field(default_factory=dict)
    dropped: dict[str, dict[str, int]] = field(default_factory=dict)
    error: str = ""
    viewer: str = ""

    @property
    def lossless(self) -> bool:
        return not self.error and self.received == self.sent and not any(
            self.dropped.values())

    @property
    def us_per_update(self) -> float:
        return self.cpu_s / self.sent * 1e6 if self.sent else float("nan")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Viewer:
    """A status-page viewer: the page's event stream (``/events``) read as it comes, and
    ``/status.json`` fetched twice a second, as a browser and a dashboard would."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.stop = threading.Event()
        self.event_bytes = 0
        self.polls = 0
        self.threads = [threading.Thread(target=self._events, daemon=True),
                        threading.Thread(target=self._poll, daemon=True)]
        for t in self.threads:
            t.start()

    def _events(self) -> None:
        while not self.stop.is_set():
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=1) as c:
                    c.sendall(b"GET /events HTTP/1.1\r\nHost: bench\r\n\r\n")
                    while not self.stop.is_set():
                        try:
                            data = c.recv(65536)
                        except TimeoutError:
                            continue
                        if not data:
                            break
                        self.event_bytes += len(data)
            except OSError:
                self.stop.wait(0.1)

    def _poll(self) -> None:
        while not self.stop.wait(0.5):
            try:
                with urllib.request.urlopen(
                        f"http://127.0.0.1:{self.port}/status.json", timeout=2) as r:
                    r.read()
                self.polls += 1
            except OSError:
                pass

    def close(self) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(3)


def case_args(case: str, http_port: int) -> list[str]:
    if case == "all":  # (the console's flag only where it runs: --only refuses a left-out one)
        return ["--http", f"127.0.0.1:{http_port}", "--console-interval", "1"]
    if case == "none":  # the least a run can have: a console that prints state changes only
        return ["--only", "console", "--console-interval", "3600"]
    if case.startswith("only:"):
        name = case[5:]
        return ["--only", name] + (["--http", f"127.0.0.1:{http_port}"] if name == "http"
                                   else ["--console-interval", "1"] if name == "console"
                                   else [])
    raise SystemExit(f"--case: unknown case {case!r} (all, none, only:NAME)")


def one_run(tree: Path, case: str, blob: bytes, ends: list[int], rate: float,
            duration: float, profile: Path | None = None, extra: Sequence[str] = (),
            keep_log: Path | None = None) -> Run:
    run = Run(str(tree), case)
    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]
    http_port = free_port()
    viewer: Viewer | None = None
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "gateway", "run", "--source", f"socket://127.0.0.1:{port}",
           "--status-interval", "0", "--log-format", "json", *case_args(case, http_port),
           *extra]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, cwd="/tmp", env=env)
    err: list[str] = []
    reader = threading.Thread(target=lambda: err.extend(proc.stderr or ()), daemon=True)
    reader.start()
    try:
        srv.settimeout(30)
        conn, _ = srv.accept()
        conn.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
        # pyserial's socket:// drops what arrives before its open() returns: let it return
        time.sleep(0.5)
        if case in ("all", "only:http"):
            viewer = Viewer(http_port)
        spy = None
        if profile is not None:
            profile.mkdir(parents=True, exist_ok=True)
            out = profile / f"{tree.name}-{case.replace(':', '_')}-{time.time_ns()}.txt"
            spy = subprocess.Popen(
                [str(Path(sys.executable).parent / "py-spy"), "record", "-p", str(proc.pid),
                 "-d", str(max(1, int(duration))), "-r", "250", "--threads", "-f", "raw",
                 "--nonblocking", "-o", str(out)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        cpu0 = cpu_by_thread(proc.pid)
        t0 = time.monotonic()
        sent_frames = 0
        pos = 0
        total = len(ends)
        while sent_frames < total:
            now = time.monotonic() - t0
            due = min(total, int(now * (rate + STATUS_HZ)) + 1)
            if due > sent_frames:
                end = ends[due - 1]
                conn.sendall(blob[pos:end])
                pos = end
                sent_frames = due
            time.sleep(0.001)
        send_end = time.monotonic()
        run.wall_s = send_end - t0
        run.sent = sent_frames
        # let it read what is in flight, then take the CPU before stopping it
        time.sleep(0.5)
        cpu1 = cpu_by_thread(proc.pid)
        run.cpu_s = sum(cpu1.values()) - sum(cpu0.get(k, 0.0) for k in cpu1)
        run.threads = {k.split("/")[0]: 0.0 for k in cpu1}
        for k, v in cpu1.items():
            run.threads[k.split("/")[0]] += v - cpu0.get(k, 0.0)
        if spy is not None:
            spy.wait(30)
        if viewer is not None:
            viewer.close()
            run.viewer = f"viewer: {viewer.event_bytes} B of events, {viewer.polls} polls"
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
        conn.close()
    except Exception as exc:  # a failed run is reported, not fatal
        run.error = f"{type(exc).__name__}: {exc}"
        proc.kill()
        proc.wait()
    finally:
        srv.close()
    reader.join(5)
    if keep_log is not None:
        keep_log.mkdir(parents=True, exist_ok=True)
        (keep_log / f"{tree.name}-{case.replace(':', '_')}-{time.time_ns()}.log").write_text(
            "".join(err))
    for line in err:
        if '"event": "stop"' not in line:
            continue
        summary = json.loads(line)["summary"]
        run.received = sum(summary["messages_in"].values())
        for name, st in summary["backends"].items():
            run.dropped[name] = {k: v for k, v in st.items()
                                 if k.startswith("dropped") and isinstance(v, int) and v}
            if name == "zenoh":  # its peers: a subscriber elsewhere slows its puts
                run.viewer += f"{'; ' if run.viewer else ''}zenoh transports {st.get('connected')}"
        break
    else:
        run.error = run.error or "no stop report: " + "".join(err[-5:])[-500:]
    return run


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--rate", type=float, action="append",
                    help="SM_UPDATEs per second (repeatable; default 25000)")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of frames (30)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds (3)")
    ap.add_argument("--case", action="append",
                    help="all | none | only:NAME (repeatable; default all)")
    ap.add_argument("--tree", type=Path, action="append", default=[],
                    help="another checkout run side by side (repeatable)")
    ap.add_argument("--threads", action="store_true", help="print CPU per thread")
    ap.add_argument("--gateway-arg", action="append", default=[], metavar="ARG",
                    help="one more argument for every run (repeatable), e.g. "
                    "--gateway-arg=--status-interval=1")
    ap.add_argument("--keep-log", metavar="DIR", type=Path,
                    help="keep each run's standard error in DIR")
    ap.add_argument("--profile", metavar="DIR", type=Path,
                    help="record each run with py-spy (collapsed stacks per thread) into DIR")
    args = ap.parse_args(argv)
    rates = args.rate or [25000.0]
    cases = args.case or ["all"]
    trees = [ROOT, *args.tree]
    lossless_at: dict[tuple[str, str], list[float]] = {}
    for rate in rates:
        blob, ends = flight_stream(rate, args.duration)
        print(f"rate {rate:,.0f} SM_UPDATE/s + {STATUS_HZ:g} STATUS/s, {args.duration:g} s, "
              f"{len(ends)} frames ({len(blob) / len(ends):.1f} B/frame)", flush=True)
        results: dict[tuple[str, str], list[Run]] = {}
        for rnd in range(args.repeat):
            for case in cases:
                order = trees if rnd % 2 == 0 else trees[::-1]
                for tree in order:
                    r = one_run(tree, case, blob, ends, rate, args.duration, args.profile,
                                args.gateway_arg, args.keep_log)
                    results.setdefault((str(tree), case), []).append(r)
                    lost = {k: v for k, v in r.dropped.items() if v}
                    print(f"  round {rnd + 1} {tree.name:<16} {case:<14} "
                          f"{'lossless' if r.lossless else 'LOSSY   '} "
                          f"in {r.received}/{r.sent} cpu {r.us_per_update:6.1f} µs/update "
                          f"({r.cpu_s / max(r.wall_s, 1e-9) * 100:.0f} % of a core)"
                          f"{' ' + str(lost) if lost else ''}{' ' + r.error if r.error else ''}"
                          f"{'; ' + r.viewer if r.viewer else ''}", flush=True)
                    if args.threads:
                        for name, s in sorted(r.threads.items(), key=lambda kv: -kv[1]):
                            if s > 0.05:
                                print(f"      {name:<16} {s / r.sent * 1e6:6.1f} µs/update")
        print()
        print(f"{'tree':<18}{'case':<16}{'lossless':>9}{'µs/update':>11}{'min':>7}{'max':>7}")
        for (tree, case), runs in results.items():
            us = [r.us_per_update for r in runs]
            ok = sum(r.lossless for r in runs)
            print(f"{Path(tree).name:<18}{case:<16}{f'{ok}/{len(runs)}':>9}"
                  f"{statistics.median(us):>11.1f}{min(us):>7.1f}{max(us):>7.1f}")
        for case in cases:
            if case.startswith("only:") and all((str(t), "none") in results for t in trees):
                for t in trees:
                    own = [a.us_per_update - b.us_per_update for a, b in
                           zip(results[(str(t), case)], results[(str(t), "none")],
                               strict=False)]
                    print(f"{t.name:<18}{case[5:]:<16} backend's own cost "
                          f"{statistics.median(own):.1f} µs/update")
        if len(trees) > 1:
            for case in cases:
                rs = [a.us_per_update / b.us_per_update for a, b in
                      zip(results[(str(trees[0]), case)], results[(str(trees[1]), case)],
                          strict=False)]
                print(f"{case}: {trees[0].name} / {trees[1].name} CPU per update, median of "
                      f"rounds: {statistics.median(rs):.2f}x")
        for key, runs in results.items():
            if all(r.lossless for r in runs):
                lossless_at.setdefault(key, []).append(rate)
        print()
    if len(rates) > 1:  # the ceiling: the highest rate up to which every run was lossless
        ordered = sorted(rates)
        for tree in trees:
            for case in cases:
                ok = lossless_at.get((str(tree), case), [])
                ceiling = 0.0
                for rate in ordered:
                    if rate not in ok:
                        break
                    ceiling = rate
                shown = f"{ceiling:,.0f}" if ceiling else f"< {ordered[0]:,.0f}"
                tried = ", ".join(f"{r:,.0f}" for r in ordered)
                print(f"lossless ceiling {tree.name:<16} {case:<14} {shown} updates/s "
                      f"(rates tried: {tried})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
