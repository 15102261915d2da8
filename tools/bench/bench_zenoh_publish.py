"""Benchmark: the Zenoh backend's per-message cost on its loop (encode, key lookup, two puts),
with the session open and nobody subscribed — the hot path without the network.

Calls the SM_UPDATE handler directly ``--updates`` times, ``--repeat`` runs, and prints the
best µs per update; ``--vehicles N`` spreads the updates over N vehicles (keys per vehicle);
``--ros2`` adds the rmw_zenoh topics the ros2 backend asks for (altitude, /tf and imu: three
more puts per update, their CDR made by :class:`backends.ros2.topics.RosTopics`).
Run: ``.venv/bin/python tools/bench/bench_zenoh_publish.py [--updates N] [--repeat N]
[--vehicles N] [--ros2]``.  Asserts nothing; the machine is shared: compare runs made together.
"""

from __future__ import annotations

import argparse
import socket
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script from anywhere, without installing
    sys.path.insert(0, str(ROOT))

from backends.zenoh.backend import ZenohBackend  # noqa: E402
from backends.zenoh.options import ZenohOptions  # noqa: E402
from gateway import wire  # noqa: E402
from gateway.model import SmUpdate  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--updates", type=int, default=40_000)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--vehicles", type=int, default=1)
    p.add_argument("--ros2", action="store_true", help="with the rmw_zenoh topics")
    args = p.parse_args(argv)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    b = ZenohBackend(ZenohOptions(listen=[f"tcp/127.0.0.1:{port}"], stats_interval_s=0))
    if args.ros2:
        from backends.ros2 import rmw_zenoh
        rmw_zenoh.request(b.context, 0)  # what the ros2 backend does in its attach
    b.init()
    if not b.wait_ready(30):
        raise SystemExit("the session did not open")
    frame = wire.encode(SmUpdate(1, 3, True, 0, 100.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0))
    msgs = [wire.decode_all(frame, origin="bench", vehicle=f"v{i}")[0]
            for i in range(args.vehicles)]
    batch = [msgs[i % len(msgs)] for i in range(args.updates)]
    best = float("inf")
    try:
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            for m in batch:
                b.send_framed(m)
            best = min(best, (time.perf_counter() - t0) / len(batch) * 1e6)
    finally:
        b.close()
    what = ("JSON + raw frame + rmw_zenoh altitude, /tf, imu: 5 puts" if args.ros2
            else "JSON + raw frame: 2 puts")
    print(f"{best:.2f} µs per SM_UPDATE ({what}), {args.vehicles} "
          f"vehicle(s), best of {args.repeat} × {args.updates}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
