"""Benchmark: the delay the Foxglove backend's relay adds (issue 23: clients of both
generations connect through a relay in front of foxglove-sdk's server).

One backend, two clients at once subscribed to ``/aurora/vehicle/altitude``: one straight to
the SDK's loopback port, one through the relay's public port.  Updates are dispatched at
``--rate`` Hz; per message, the client's receipt time minus the message's log time (the
wall-clock time the backend logged it), in µs: median, 90th percentile, max per path.

Prints figures; asserts nothing about time.  The machine is shared: compare the two paths of
one run, not runs.

Run: ``.venv/bin/python tools/bench/bench_foxglove_relay.py [--host ::1] [--updates N]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import struct
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script from anywhere, without installing
    sys.path.insert(0, str(ROOT))

from websockets.sync.client import connect  # noqa: E402
from websockets.typing import Subprotocol  # noqa: E402

from backends.foxglove.backend import UNNAMED, FoxgloveBackend  # noqa: E402
from backends.foxglove.options import FoxgloveOptions  # noqa: E402
from gateway.dispatcher import Dispatcher  # noqa: E402
from gateway.model import SmUpdate  # noqa: E402

TOPIC = f"/aurora/{UNNAMED}/altitude"


def client(url: str, want: int, ready: threading.Event, out: list[float]) -> None:
    with connect(url, subprotocols=[Subprotocol("foxglove.sdk.v1")]) as ws:
        channels: dict[str, int] = {}
        while TOPIC not in channels:
            msg = json.loads(ws.recv(timeout=10))
            if msg["op"] == "advertise":
                channels.update({c["topic"]: c["id"] for c in msg["channels"]})
        ws.send(json.dumps({"op": "subscribe",
                            "subscriptions": [{"id": 1, "channelId": channels[TOPIC]}]}))
        ready.set()
        while len(out) < want:
            data = ws.recv(timeout=10)
            if isinstance(data, bytes):
                log_time = struct.unpack_from("<Q", data, 5)[0]
                out.append((time.time_ns() - log_time) / 1e3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--host", default="127.0.0.1", help="the relay's host (the SDK's is "
                    "127.0.0.1)")
    ap.add_argument("--updates", type=int, default=500)
    ap.add_argument("--rate", type=float, default=100.0)
    args = ap.parse_args()
    backend = FoxgloveBackend(FoxgloveOptions(host=args.host, port=0))
    dispatcher = Dispatcher([backend])
    dispatcher.start()
    update = SmUpdate(1000, 2, True, 0, 12.5, -9.8, 0.5, 3.0, 0.1, 0.2, 0.3)
    try:
        dispatcher.dispatch(update)  # the vehicle's channels
        backend.wait_idle(10.0)
        host = f"[{args.host}]" if ":" in args.host else args.host
        paths = {"direct to the SDK": f"ws://127.0.0.1:{backend._server.port}",
                 "through the relay": f"ws://{host}:{backend.port}"}
        results: dict[str, list[float]] = {name: [] for name in paths}
        threads = []
        for name, url in paths.items():
            ready = threading.Event()
            th = threading.Thread(target=client, args=(url, args.updates, ready,
                                                       results[name]), daemon=True)
            th.start()
            assert ready.wait(10.0), f"{name}: no subscription"
            threads.append(th)
        assert backend.wait_subscriptions(2, 10.0)
        for _ in range(args.updates):
            dispatcher.dispatch(update)
            time.sleep(1.0 / args.rate)
        for th in threads:
            th.join(20.0)
        print(f"{args.updates} updates at {args.rate:g} Hz; log time → client, µs")
        for name, lat in results.items():
            lat.sort()
            print(f"{name:<18} n={len(lat)} median {statistics.median(lat):.0f}  "
                  f"p90 {lat[int(0.9 * (len(lat) - 1))]:.0f}  max {lat[-1]:.0f}")
    finally:
        dispatcher.close()


if __name__ == "__main__":
    main()
