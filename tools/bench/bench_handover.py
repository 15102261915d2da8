"""Benchmark: what each backend behind a hand-over costs per update, and its lossless ceiling.

For each backend that does its work off the dispatcher's thread (MAVLink, UAVTalk, Zenoh,
Foxglove), one run: a fresh backend behind a real :class:`~gateway.dispatcher.Dispatcher`, its
queue deep enough for the whole run, fed SmUpdates decoded from real frames (a STATUS every
tenth): a warm-up of 1000 (links up, streams going), then three phases of ``--updates``, each
waited for until the backend has handled all of it:

1. paced at ``--rate`` updates/s in 1 ms batches, as a source delivers them:
   **CPU µs/update** — this process's CPU (``time.process_time``: the dispatcher's thread,
   the backend's loop or worker, a library's threads) from the first dispatch until the last
   update is handled, per update;
2. flat out, not counted: the backend settles into that regime (how producer and consumer
   share the interpreter changes the cost per update by up to 2×, the same in both trees);
3. flat out: **flat-out CPU**, **caller µs/update** (what the dispatch costs the caller: the
   hand-over) and the **ceiling**: updates handled per second of wall time.  Producer and
   backend share the interpreter, as a source and a backend do in the gateway: offered more
   slowly than this, the queue does not grow, so nothing is dropped — the lossless ceiling.

**out/upd**: what the backend put out per update in phase 1 (MAVLink frames, Zenoh
publications, Foxglove channel messages; UAVTalk 0 with no GCS), so runs doing different work
show.  Drops are printed (there should be none: the queue holds the run).

Peers: MAVLink sends to a UDP socket of this process (never read: the kernel drops what
overflows), UAVTalk serves a TCP port nobody connects to (the vehicle's objects are updated,
no packets), Zenoh publishes as a peer with nobody subscribed, Foxglove serves with no client.
``--backends ros2`` (not run by default: the ``ros2`` extra, and a tree before it has none)
writes on a DDS domain of its own with nobody subscribed, on loopback only (a
``CYCLONEDDS_URI`` naming ``lo`` unless one is set).

``--compare BEFORE_TREE`` runs this script under each tree's own ``.venv`` (the checkout it
lives in and BEFORE_TREE), alternately, ``--repeat`` times, and prints medians side by side:
before and after in one run.  The script only uses what both trees have (the dispatcher, the
backends' constructors, ``stats()``).  Prints figures; asserts nothing about time.

Run: ``.venv/bin/python tools/bench/bench_handover.py [--updates N] [--repeat N]
[--compare /path/to/old/checkout] [--backends mavlink,uavtalk,zenoh,foxglove]``
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pacing import paced_batches  # tools/bench/pacing.py, beside this script

HERE = Path(__file__).resolve()
ROOT = HERE.parents[2]
BACKENDS = ("mavlink", "uavtalk", "zenoh", "foxglove")
WARM_UP = 1000
#: Cyclone DDS on loopback only, no multicast (the ros2 backend's runs)
LOOPBACK_DDS = ("<CycloneDDS><Domain id='any'><General><Interfaces><NetworkInterface name='lo'/>"
                "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery>"
                "<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>20"
                "</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers>"
                "</Discovery></Domain></CycloneDDS>")


def _messages(n: int) -> list[Any]:
    from gateway import wire
    from gateway.model import SmUpdate, Status

    frames = []
    for k in range(n):
        if k % 10 == 9:
            frames.append(wire.encode(Status(10 * k, 3, 0, 0x1E)))
        else:
            frames.append(wire.encode(SmUpdate(
                10 * k, 3, True, 0, 0.5 * k, 9.8, -9.8, 30.0 - 0.001 * k, 0.01 * k, 0.1,
                -0.02 * k)))
    msgs = wire.Decoder("bench-serial", vehicle="bench").feed(b"".join(frames))
    assert len(msgs) == n
    return msgs


def _free_zenoh_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _build(name: str, n: int) -> tuple[Any, Callable[[], int], list[Any]]:
    """The backend, its count of work done (``_units`` per message), what to close after;
    built from a configuration table, which both trees' ``from_config`` take."""
    extra: list[Any] = []
    if name == "mavlink":
        import backends.mavlink.backend as mb

        sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sink.bind(("127.0.0.1", 0))
        extra.append(sink)
        mb.INBOX_DEPTH = n + 1  # type: ignore[misc]  # both trees read it
        b: Any = mb.MavlinkBackend.from_config(
            {"endpoints": [f"udpout:127.0.0.1:{sink.getsockname()[1]}"]})
        # SmUpdate and Status both count as the vehicle's updates
        return b, lambda: int(b.vehicle.stats.updates), extra
    if name == "uavtalk":
        from backends.uavtalk.backend import UavtalkBackend

        b = UavtalkBackend.from_config({"endpoints": ["tcpin:127.0.0.1:0"],
                                        "inbox_depth": min(n + 1, 65536)})
        return b, lambda: int(b.stats()["messages"]), extra
    if name == "zenoh":
        from backends.zenoh.backend import ZenohBackend

        b = ZenohBackend.from_config({"listen": [_free_zenoh_endpoint()], "queue_depth": n + 1,
                                      "stats_interval_s": 0})
        return b, lambda: int(b.processed), extra
    if name == "foxglove":
        from backends.foxglove.backend import FoxgloveBackend

        b = FoxgloveBackend.from_config({"host": "127.0.0.1", "port": 0, "queue_depth": n + 1})
        return b, lambda: int(b.stats()["sent"]), extra
    if name == "ros2":  # (not in BACKENDS: --backends ros2; needs the 'ros2' extra)
        import os
        import random
        import tempfile

        if not os.environ.get("CYCLONEDDS_URI"):  # loopback only, never the field network
            cfg = Path(tempfile.mkdtemp(prefix="bench-dds-")) / "cyclonedds.xml"
            cfg.write_text(LOOPBACK_DDS)
            os.environ["CYCLONEDDS_URI"] = cfg.as_uri()
        from backends.ros2.backend import Ros2Backend

        b = Ros2Backend.from_config({"queue_depth": n + 1,
                                     "domain_id": random.SystemRandom().randrange(100, 230)})
        return b, lambda: int(b.processed), extra
    raise SystemExit(f"unknown backend {name!r}")


def _units(name: str, msgs: list[Any]) -> int:
    """The work count ``msgs`` make (Foxglove: channel messages, 3 per SmUpdate)."""
    if name != "foxglove":
        return len(msgs)
    return sum(3 if type(m).__name__ == "SmUpdate" else 1 for m in msgs)


def _wait(backend: Any, work: Callable[[], int], target: int, what: str) -> None:
    """Until ``work()`` reaches ``target`` and the loop has finished the callback that got it
    there (MAVLink counts an update as it takes it in and sends what a batch made after the
    batch: the sending must be inside the measurement)."""
    deadline = time.monotonic() + 120
    while work() < target:
        if time.monotonic() > deadline:
            raise SystemExit(f"{what}: not everything was handled within 120 s")
        time.sleep(0.0005)
    loop = getattr(backend, "loop", None)
    if loop is not None and hasattr(loop, "call_soon"):
        done = threading.Event()
        loop.call_soon(done.set)
        done.wait(60)


def _offer(dispatch: Callable[[Any], Any], msgs: list[Any], rate: float) -> int:
    """Dispatch ``msgs`` at ``rate`` per second in 1 ms batches (0: flat out), as a source
    would; how many were refused."""
    return sum(1 for batch in paced_batches(msgs, rate) for m in batch if dispatch(m))


def run_one(name: str, n: int, rate: float) -> dict[str, Any]:
    """One run of backend ``name`` (in this process, whichever tree it imports): a warm-up
    (1000 updates), ``n`` updates paced at ``rate`` (the CPU figure), ``n`` flat out (not
    counted: the backend settles into that regime), ``n`` flat out (caller time, ceiling)."""
    from gateway.dispatcher import Dispatcher

    everything = _messages(WARM_UP + 3 * n)
    parts = [everything[:WARM_UP]] + [everything[WARM_UP + k * n:WARM_UP + (k + 1) * n]
                                      for k in range(3)]
    backend, work, extra = _build(name, len(everything))
    d = Dispatcher([backend])
    failures = d.start()
    if failures:
        raise SystemExit(f"{name} failed to start: {failures}")
    try:
        if name == "zenoh" and not backend.wait_ready(30):
            raise SystemExit("the Zenoh session did not open")
        deadline = time.monotonic() + 30
        while not backend.stats().get("link"):  # e.g. MAVLink's UDP endpoint opening
            if name == "uavtalk" or time.monotonic() > deadline:
                break  # (UAVTalk's link is a connected GCS: there is none)
            time.sleep(0.005)
        dispatch = d.dispatch
        done = 0
        figures: list[tuple[float, float, float, int, float]] = []
        for k, (msgs, pace) in enumerate(zip(parts, (0.0, rate, 0.0, 0.0), strict=True)):
            done += _units(name, msgs)
            sent0 = _frames(backend)
            gc.collect()
            gc.disable()
            cpu0 = time.process_time()
            t0 = time.perf_counter()
            refused = _offer(dispatch, msgs, pace)
            caller_s = time.perf_counter() - t0
            _wait(backend, work, done, name)
            wall_s = time.perf_counter() - t0
            cpu_s = time.process_time() - cpu0
            gc.enable()
            if k:
                figures.append((cpu_s, caller_s, wall_s, refused,
                                (_frames(backend) - sent0) / len(msgs)))
        stats = backend.stats()
    finally:
        gc.enable()
        d.close()
        for x in extra:
            x.close()
    paced, _, flat = figures
    return {"backend": name, "updates": n, "rate": rate, "cpu_us": paced[0] / n * 1e6,
            "flat_cpu_us": flat[0] / n * 1e6, "caller_us": flat[1] / n * 1e6,
            "ceiling": n / flat[2], "refused": sum(f[3] for f in figures),
            "dropped": stats.get("dropped", 0), "out_per_update": paced[4]}


def _frames(backend: Any) -> int:
    """What the backend put out so far (MAVLink: frames; the others: their ``sent``)."""
    st = backend.stats()
    return int(st["sent"])


# -- the driver ----------------------------------------------------------------------------------

def _python_of(tree: Path) -> str:
    py = tree / ".venv" / "bin" / "python"
    return str(py) if py.exists() else sys.executable


def _run_in(tree: Path, name: str, n: int, rate: float) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run([_python_of(tree), str(HERE), "--tree", str(tree), "--one", name,
                          "--updates", str(n), "--rate", str(rate)],
                         capture_output=True, text=True, env=env,
                         cwd=tree, timeout=600, check=False)
    if out.returncode != 0:
        raise SystemExit(f"{tree} {name}: exit {out.returncode}\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _fmt(values: list[float], digits: int = 1) -> str:
    return (f"{statistics.median(values):.{digits}f} "
            f"({min(values):.{digits}f}–{max(values):.{digits}f})")


def compare(before: Path, names: list[str], n: int, repeat: int, rate: float) -> None:
    trees = {"before": before.resolve(), "after": ROOT}
    for label, tree in trees.items():
        head = subprocess.run(["git", "-C", str(tree), "log", "-1", "--format=%h %s"],
                              capture_output=True, text=True, check=False).stdout.strip()
        print(f"{label:6}: {tree} @ {head[:70]}")
    print(f"{n} updates per phase (SmUpdate, a STATUS every 10th), {repeat} runs per tree, "
          f"alternating; median (min–max).  CPU at {rate:.0f} updates/s, paced; caller, "
          "flat-out CPU and ceiling flat out\n")
    results: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for name in names:
        _run_in(ROOT, name, 1000, rate)  # warm-up (bytecode, caches), not counted
        for _ in range(repeat):
            for label, tree in trees.items():
                results.setdefault((name, label), []).append(_run_in(tree, name, n, rate))
    print(f"{'backend':9} {'tree':6} {'CPU µs/update':>18} {'flat-out CPU':>18} "
          f"{'caller µs/update':>18} {'ceiling updates/s':>24} {'out/upd':>7} {'dropped':>7}")
    for name in names:
        for label in trees:
            rs = results[(name, label)]
            print(f"{name:9} {label:6} {_fmt([r['cpu_us'] for r in rs]):>18} "
                  f"{_fmt([r['flat_cpu_us'] for r in rs]):>18} "
                  f"{_fmt([r['caller_us'] for r in rs], 2):>18} "
                  f"{_fmt([r['ceiling'] for r in rs], 0):>24} "
                  f"{statistics.median(r['out_per_update'] for r in rs):>7.2f} "
                  f"{max(r['dropped'] + r['refused'] for r in rs):>7}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--updates", type=int, default=20_000, help="updates per run (20000)")
    ap.add_argument("--repeat", type=int, default=3, help="runs per tree and backend (3)")
    ap.add_argument("--rate", type=float, default=5000.0,
                    help="updates/s of the paced phase, the CPU figure (5000)")
    ap.add_argument("--backends", default=",".join(BACKENDS), help="comma-separated")
    ap.add_argument("--compare", metavar="BEFORE_TREE", type=Path,
                    help="also run the checkout at BEFORE_TREE (its own .venv), alternately")
    ap.add_argument("--tree", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--one", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    names = [b for b in args.backends.split(",") if b]
    if args.one:  # a child run: one measurement, as JSON, of the tree on sys.path
        tree = str((args.tree or ROOT).resolve())
        sys.path.insert(0, tree)
        import logging
        logging.basicConfig(level=logging.ERROR)
        print(json.dumps(run_one(args.one, args.updates, args.rate)))
        return 0
    if args.compare:
        compare(args.compare, names, args.updates, args.repeat, args.rate)
        return 0
    sys.path.insert(0, str(ROOT))
    print(f"{args.updates} updates per phase, {args.repeat} runs; median (min–max)")
    for name in names:
        run_one(name, 1000, args.rate)  # warm-up
        rs = [run_one(name, args.updates, args.rate) for _ in range(args.repeat)]
        print(f"{name:9} CPU {_fmt([r['cpu_us'] for r in rs])} µs/update at "
              f"{args.rate:.0f}/s, flat out {_fmt([r['flat_cpu_us'] for r in rs])}, caller "
              f"{_fmt([r['caller_us'] for r in rs], 2)} µs/update, ceiling "
              f"{_fmt([r['ceiling'] for r in rs], 0)} updates/s, dropped "
              f"{max(r['dropped'] + r['refused'] for r in rs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
