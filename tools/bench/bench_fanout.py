"""Benchmark: the cost of one SM update through :class:`gateway.dispatcher.Dispatcher`.

Measures, in µs per update (and updates/s), ``Dispatcher.dispatch(msg)`` with

* 1 trivial backend (``send_sm_update`` returns None),
* 8 trivial backends,
* 8 backends that return ``Outcome.ACCEPTED`` (the outcome is compared, not just ``is None``),
  once bound to a module constant and once written ``return Outcome.ACCEPTED`` in the hook
  (on CPython 3.11 that enum attribute lookup alone costs about 0.2 µs per call),

against the floor: the same 1 or 8 bound hooks called in a plain ``for`` loop, with no
locking, outcome bookkeeping or exception guard.  The messages are real decoded SmUpdates
(``raw`` and ``origin`` set), a few thousand distinct ones cycled through.

The machine is shared and noisy: each case runs ``--repeat`` times (plus one warm-up), every
repetition cut into blocks timed in turn across the cases; the median (min, max) is printed,
and the dispatcher/floor ratios are taken within each repetition before their median is
printed.  The cyclic garbage collector is off while the clock runs, as in :mod:`timeit`.
Prints figures; asserts nothing about time.

``--ros2`` adds the ROS 2 backend's cost (it needs the ``ros2`` extra): the CPU time of the
whole process (every thread: the dispatcher's, the backend's loop, Cyclone DDS's own) per
update, for the same updates dispatched to one trivial backend, then to it and the ROS 2
backend, blocks of each in turn; each chunk of ``ROS2_CHUNK`` updates (within the backend's
queue) is waited for before the next, so nothing is dropped and every update is written.
The updates are a flight's (the state changes every 500 updates, not at each: state and
armed are published when they change).  DDS stays on loopback (``CYCLONEDDS_URI`` naming
``lo``, unless one is set) on a domain of its own; ``--ros2-reader`` adds a Cyclone DDS
subscriber in another process (``tests/ros2_dds_peer.py``), so the writes go somewhere.

Run: ``.venv/bin/python tools/bench/bench_fanout.py [--updates N] [--repeat N] [--ros2
[--ros2-reader]]``
"""

from __future__ import annotations

import argparse
import gc
import itertools
import platform
import random
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script from anywhere, without installing
    sys.path.insert(0, str(ROOT))

from gateway import wire  # noqa: E402
from gateway.backend import Outcome, Routes  # noqa: E402
from gateway.dispatcher import Dispatcher  # noqa: E402
from gateway.model import SmUpdate  # noqa: E402

DISTINCT = 4096  # distinct decoded messages cycled through (they all stay in cache)
BLOCKS = 20  # blocks per repetition, timed in turn across the cases


class TrivialBackend:
    """A backend whose hook does nothing and returns None (counted as accepted)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.send_sm_update)

    def send_sm_update(self, msg: SmUpdate) -> None:
        return None


ACCEPTED = Outcome.ACCEPTED


class AcceptingBackend:
    """A backend whose hook returns ``Outcome.ACCEPTED``, bound once at module level."""

    def __init__(self, name: str) -> None:
        self.name = name

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.send_sm_update)

    def send_sm_update(self, msg: SmUpdate) -> Outcome:
        return ACCEPTED


class LookupAcceptingBackend:
    """The same, written ``return Outcome.ACCEPTED``: an enum attribute lookup per call."""

    def __init__(self, name: str) -> None:
        self.name = name

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.send_sm_update)

    def send_sm_update(self, msg: SmUpdate) -> Outcome:
        return Outcome.ACCEPTED


def decoded_updates(count: int, seed: int) -> list[SmUpdate]:
    """``count`` SmUpdates as a source hands them over: decoded from frames, origin set."""
    rng = random.Random(seed)
    frames = []
    for k in range(count):
        frames.append(wire.encode(SmUpdate(
            10 * k, rng.randrange(8), rng.random() < 0.5, 0, rng.uniform(0, 3000),
            rng.uniform(-5, 60), rng.uniform(-12, 50), rng.uniform(-50, 300),
            rng.uniform(-3.1, 3.1), rng.uniform(-1.5, 1.5), rng.uniform(-3.1, 3.1))))
    msgs = wire.Decoder("bench-serial").feed(b"".join(frames))
    assert len(msgs) == count and all(isinstance(m, SmUpdate) and m.raw for m in msgs)
    return msgs  # type: ignore[return-value]


def dispatcher_with(backends: Sequence[Any]) -> Dispatcher:
    disp = Dispatcher(backends)
    failures = disp.start()
    if failures:
        sys.exit(f"backends failed to start: {failures}")
    return disp


def run_dispatch(disp: Dispatcher, msgs: Sequence[SmUpdate]) -> None:
    dispatch = disp.dispatch
    for m in msgs:
        dispatch(m)


def run_floor(hooks: Sequence[Callable[[Any], Any]], msgs: Sequence[SmUpdate]) -> None:
    for m in msgs:
        for fn in hooks:
            fn(m)


ROS2_CHUNK = 256  # updates dispatched before waiting for the ROS 2 backend's loop
_LOOPBACK_DDS = ("<CycloneDDS><Domain id='any'><General><Interfaces><NetworkInterface name='lo'/>"
                 "</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery>"
                 "<ParticipantIndex>auto</ParticipantIndex><MaxAutoParticipantIndex>20"
                 "</MaxAutoParticipantIndex><Peers><Peer address='127.0.0.1'/></Peers>"
                 "</Discovery></Domain></CycloneDDS>")


def flight_updates(count: int, seed: int) -> list[SmUpdate]:
    """``count`` decoded SmUpdates of a flight: random values, the state changing every 500
    updates (armed from the second state on)."""
    rng = random.Random(seed)
    frames = []
    for k in range(count):
        state = k // 500 % 8
        frames.append(wire.encode(SmUpdate(
            10 * k, state, state > 0, 0, rng.uniform(0, 3000), rng.uniform(-5, 60),
            rng.uniform(-12, 50), rng.uniform(-50, 300), rng.uniform(-3.1, 3.1),
            rng.uniform(-1.5, 1.5), rng.uniform(-3.1, 3.1))))
    msgs = wire.Decoder("bench-serial").feed(b"".join(frames))
    assert len(msgs) == count
    return [m._replace(vehicle="rocket1") for m in msgs]  # type: ignore[attr-defined]


def ros2_cpu(args: argparse.Namespace) -> int:
    """The ROS 2 backend's cost: process CPU µs per update with and without it (see the
    module docstring)."""
    import os
    import subprocess
    import tempfile

    if not os.environ.get("CYCLONEDDS_URI"):  # never the field network from a benchmark
        cfg = Path(tempfile.mkdtemp(prefix="bench-dds-")) / "cyclonedds.xml"
        cfg.write_text(_LOOPBACK_DDS)
        os.environ["CYCLONEDDS_URI"] = cfg.as_uri()
    domain = random.SystemRandom().randrange(100, 230)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    from backends.ros2.backend import Ros2Backend

    reader = None
    if args.ros2_reader:
        reader = subprocess.Popen([sys.executable, str(ROOT / "tests" / "ros2_dds_peer.py"),
                                   str(domain), "3600"], stdout=subprocess.DEVNULL)
    try:
        msgs = flight_updates(min(args.updates, 20_000), args.seed)
        base = dispatcher_with([TrivialBackend("t0")])
        ros2 = Ros2Backend()
        with_ros2 = dispatcher_with([TrivialBackend("t1"), ros2])
        handover = ros2.handover

        def run_base(ms: Sequence[SmUpdate]) -> None:
            run_dispatch(base, ms)

        def run_ros2(ms: Sequence[SmUpdate]) -> None:
            for i in range(0, len(ms), ROS2_CHUNK):
                run_dispatch(with_ros2, ms[i:i + ROS2_CHUNK])
                if not handover.barrier(60):
                    sys.exit("the ROS 2 backend's loop did not catch up")

        cases = [("1 trivial backend", run_base), ("1 trivial + ros2 backend", run_ros2)]
        bounds = [len(msgs) * b // BLOCKS for b in range(BLOCKS + 1)]
        blocks = [msgs[lo:hi] for lo, hi in itertools.pairwise(bounds) if hi > lo]
        cpu: list[list[float]] = [[] for _ in cases]
        for rep in range(args.repeat + 1):
            spent = [0.0] * len(cases)
            gc.collect()
            gc.disable()
            try:
                for b, block in enumerate(blocks):
                    for j in range(len(cases)):
                        k = (j + b + rep) % len(cases)
                        t0 = time.process_time()
                        cases[k][1](block)
                        spent[k] += time.process_time() - t0
            finally:
                gc.enable()
            if rep:
                for k, t in enumerate(spent):
                    cpu[k].append(t)
        stats = ros2.stats()
        base.close()
        with_ros2.close()
    finally:
        if reader is not None:
            reader.terminate()
            reader.wait(10)
    n = len(msgs)
    print(f"ROS 2 backend: {n} flight SmUpdates per run, {args.repeat} repetitions (+1 "
          f"warm-up), process CPU time (all threads), DDS domain {domain} on loopback, "
          f"{'a subscriber in another process' if reader else 'no subscriber'}")
    print(f"{'case':<36}{'CPU µs/update':>14}{'min':>8}{'max':>8}")
    for (name, _fn), ts in zip(cases, cpu, strict=True):
        print(f"{name:<36}{statistics.median(ts) / n * 1e6:>14.2f}"
              f"{min(ts) / n * 1e6:>8.2f}{max(ts) / n * 1e6:>8.2f}")
    extra = statistics.median((y - x) / n * 1e6 for x, y in zip(*cpu, strict=True))
    print(f"the ros2 backend's cost (median of the per-repetition differences): "
          f"{extra:.2f} µs CPU per update")
    print(f"its counters: sent {stats['sent']} samples, dropped {stats['dropped']}, "
          f"errors {stats['errors']}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--updates", type=int, default=200_000, help="updates per run (200000)")
    ap.add_argument("--repeat", type=int, default=7, help="repetitions; medians reported (7)")
    ap.add_argument("--seed", type=int, default=2024, help="message seed (2024)")
    ap.add_argument("--ros2", action="store_true",
                    help="only the ROS 2 backend's CPU cost per update (the 'ros2' extra)")
    ap.add_argument("--ros2-reader", action="store_true",
                    help="with --ros2: a DDS subscriber in another process")
    args = ap.parse_args(argv)
    if args.updates < 1 or args.repeat < 1:
        ap.error("--updates and --repeat must be positive")
    if args.ros2:
        return ros2_cpu(args)

    distinct = decoded_updates(min(DISTINCT, args.updates), args.seed)
    msgs = (distinct * (args.updates // len(distinct) + 1))[:args.updates]

    trivial1 = [TrivialBackend("t0")]
    trivial8 = [TrivialBackend(f"t{k}") for k in range(8)]
    accept8 = [AcceptingBackend(f"a{k}") for k in range(8)]
    lookup8 = [LookupAcceptingBackend(f"l{k}") for k in range(8)]
    d1, d8, d8a, d8l = (dispatcher_with(b) for b in (trivial1, trivial8, accept8, lookup8))
    floor1 = [b.send_sm_update for b in trivial1]
    floor8 = [b.send_sm_update for b in trivial8]

    cases: list[tuple[str, Callable[[Sequence[SmUpdate]], None]]] = [
        ("dispatcher, 1 backend (None)", lambda ms: run_dispatch(d1, ms)),
        ("dispatcher, 8 backends (None)", lambda ms: run_dispatch(d8, ms)),
        ("dispatcher, 8 backends (ACCEPTED)", lambda ms: run_dispatch(d8a, ms)),
        ("dispatcher, 8 (Outcome.ACCEPTED)", lambda ms: run_dispatch(d8l, ms)),
        ("floor: 1 hook, plain loop", lambda ms: run_floor(floor1, ms)),
        ("floor: 8 hooks, plain loop", lambda ms: run_floor(floor8, ms)),
    ]
    # Each repetition runs every case over all the updates, cut into BLOCKS blocks timed in
    # turn (case order rotating), so a change of machine load hits every case alike.
    bounds = [len(msgs) * b // BLOCKS for b in range(BLOCKS + 1)]
    blocks = [msgs[lo:hi] for lo, hi in itertools.pairwise(bounds) if hi > lo]
    times: list[list[float]] = [[] for _ in cases]
    clock = time.perf_counter
    for rep in range(args.repeat + 1):  # repetition 0 warms up and is not counted
        spent = [0.0] * len(cases)
        gc.collect()
        gc.disable()
        try:
            for b, block in enumerate(blocks):
                for j in range(len(cases)):
                    k = (j + b + rep) % len(cases)
                    t0 = clock()
                    cases[k][1](block)
                    spent[k] += clock() - t0
        finally:
            gc.enable()
        if rep:
            for k, t in enumerate(spent):
                times[k].append(t)

    # Every backend saw every update, and all were counted as accepted.
    runs = args.repeat + 1
    for disp in (d1, d8, d8a, d8l):
        for rec in disp.records:
            got = rec.outcomes[Outcome.ACCEPTED]
            if got != runs * args.updates or sum(rec.outcomes.values()) != got:
                sys.exit(f"{rec.name}: outcomes {rec.outcomes}, expected "
                         f"{runs * args.updates} accepted")

    print(f"Python {platform.python_version()} ({platform.python_implementation()}), "
          f"{platform.machine()}")
    print(f"{args.updates} SmUpdates per run ({len(distinct)} distinct, decoded from frames), "
          f"{args.repeat} repetitions (+1 warm-up), cyclic GC off while timing")
    print()
    print(f"{'case':<36}{'µs/update':>10}{'min':>8}{'max':>8}{'updates/s':>12}")
    n = args.updates
    for (name, _fn), ts in zip(cases, times, strict=True):
        med, lo, hi = statistics.median(ts), min(ts), max(ts)
        print(f"{name:<36}{med / n * 1e6:>10.3f}{lo / n * 1e6:>8.3f}{hi / n * 1e6:>8.3f}"
              f"{n / med:>12,.0f}")
    print()

    def ratio(a: int, b: int) -> str:
        rs = [x / y for x, y in zip(times[a], times[b], strict=True)]
        return f"{statistics.median(rs):.2f}x (min {min(rs):.2f}, max {max(rs):.2f})"

    def per_hook(a: int, floor: int, hooks: int) -> float:
        return statistics.median(
            (x - y) / n / hooks * 1e6 for x, y in zip(times[a], times[floor], strict=True))

    print(f"dispatcher / floor, 1 backend        : {ratio(0, 4)}")
    print(f"dispatcher / floor, 8 backends       : {ratio(1, 5)}")
    print(f"ACCEPTED / None, 8 backends          : {ratio(2, 1)}")
    print(f"Outcome.ACCEPTED / ACCEPTED, 8       : {ratio(3, 2)}")
    print(f"dispatcher cost above the floor, 8 backends (median): "
          f"{per_hook(1, 5, 8):.3f} µs per backend call")
    return 0


if __name__ == "__main__":
    sys.exit(main())
