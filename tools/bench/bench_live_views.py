"""Benchmark: what the live views cost per update (issue 16: "the added CPU per update").

Cases, each repeated ``--repeat`` times after one uncounted warm-up (median, min, max):

* ``off``: the dispatcher with no backend (the floor);
* ``foxglove``: the Foxglove backend on loopback, no client;
* ``foxglove+client``: the same with one client, in *another process*, subscribed to every
  channel and counting what arrives;
* ``http``: the status page and metrics backend on loopback (no client: its hook stores the
  latest message per kind);
* ``foxglove+http``: both live views on (MCAP is written offline by ``export``: no cost here).

Per case: the caller's time per dispatch (what the fan-out pays: the hook only queues), and
this process's CPU per update (``time.process_time``: the dispatcher's thread, the backend's
worker and the SDK's threads; the client's process is not counted) from the first dispatch
until the worker has logged everything.  The queue is as deep as the run, so nothing is
dropped (drops are printed anyway).

Prints figures; asserts nothing about time.  The machine is shared: trust medians and ratios.

Run: ``.venv/bin/python tools/bench/bench_live_views.py [--updates N] [--repeat N]``
"""

from __future__ import annotations

import argparse
import math
import statistics
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

from backends.foxglove.options import FoxgloveOptions
from backends.http.options import HttpOptions

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script from anywhere, without installing
    sys.path.insert(0, str(ROOT))

from backends.foxglove.backend import FoxgloveBackend  # noqa: E402
from backends.http.backend import HttpBackend  # noqa: E402
from gateway.dispatcher import Dispatcher  # noqa: E402
from gateway.model import SmUpdate  # noqa: E402

CHANNELS_PER_UPDATE = 3  # state, altitude, attitude

CLIENT = textwrap.dedent("""
    import json, sys
    from websockets.sync.client import connect
    port, want = int(sys.argv[1]), int(sys.argv[2])
    with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"]) as ws:
        chans = set()
        while len(chans) < 7:  # the vehicle's six and /aurora/backends
            m = json.loads(ws.recv(timeout=10))
            if m["op"] == "advertise":
                chans.update(c["id"] for c in m["channels"])
        ws.send(json.dumps({"op": "subscribe",
                            "subscriptions": [{"id": c, "channelId": c} for c in chans]}))
        print("subscribed", flush=True)
        got = 0
        try:
            while got < want:
                if isinstance(ws.recv(timeout=2), bytes):
                    got += 1
        except TimeoutError:
            pass
        print(got, flush=True)
""")


def updates(n: int) -> list[SmUpdate]:
    out = []
    for i in range(n):
        t = i * 0.01
        out.append(SmUpdate(timestamp_ms=i * 10, state=3, armed=True, sm_type=0,
                            altitude_m=300 * math.sin(t / 10), acceleration_mps2=9.8,
                            accel_vert_mps2=-9.8, velocity_mps=30 * math.cos(t / 10),
                            roll_rad=0.01 * i, pitch_rad=0.1, yaw_rad=-0.02 * i))
    return out


def run_case(case: str, msgs: list[SmUpdate]) -> dict[str, Any]:
    n = len(msgs)
    backend = None
    client = None
    backends: list[Any] = []
    if "foxglove" in case:
        backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0, queue_depth=n + 1))
        backends.append(backend)
    if "http" in case:
        backends.append(HttpBackend(HttpOptions(host="127.0.0.1", port=0)))
    dispatcher = Dispatcher(backends)
    dispatcher.start()
    try:
        primed = 0
        if backend is not None:  # a vehicle's channels come with its first message
            dispatcher.dispatch(msgs[0])
            assert backend.wait_idle(10.0)
            primed = CHANNELS_PER_UPDATE
        if backend is not None and case.endswith("+client"):
            client = subprocess.Popen([sys.executable, "-c", CLIENT, str(backend.port),
                                       str(n * CHANNELS_PER_UPDATE)],
                                      stdout=subprocess.PIPE, text=True)
            assert client.stdout is not None
            assert client.stdout.readline().strip() == "subscribed"
            assert backend.wait_subscriptions(7, 10.0), "the client did not subscribe"
        dispatch = dispatcher.dispatch
        cpu0 = time.process_time()
        t0 = time.perf_counter()
        for m in msgs:
            dispatch(m)
        caller_s = time.perf_counter() - t0
        if backend is not None:
            deadline = time.monotonic() + 60
            # the worker's backlog
            while backend.stats()["sent"] < n * CHANNELS_PER_UPDATE + primed:
                if time.monotonic() > deadline:
                    break
                time.sleep(0.001)
        cpu_s = time.process_time() - cpu0
        got = None
        if client is not None:
            out, _ = client.communicate(timeout=30)
            got = int(out.strip().splitlines()[-1])
        stats = backend.stats() if backend is not None else {}
        return {"caller_us": caller_s / n * 1e6, "cpu_us": cpu_s / n * 1e6,
                "dropped": stats.get("dropped", 0), "received": got}
    finally:
        dispatcher.close()
        if client is not None and client.poll() is None:
            client.kill()
            client.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--updates", type=int, default=5000)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    msgs = updates(args.updates)
    cases = ("off", "foxglove", "foxglove+client", "http", "foxglove+http")
    results: dict[str, list[dict[str, Any]]] = {c: [] for c in cases}
    for rep in range(args.repeat + 1):
        for case in cases:
            r = run_case(case, msgs)
            if rep:  # the first round warms up
                results[case].append(r)
    print(f"{args.updates} SM_UPDATEs per run, {args.repeat} runs; µs per update: "
          "median [min–max]")
    print(f"{'case':<18} {'caller (fan-out)':>24} {'process CPU':>24}  dropped  received")
    for case in cases:
        rs = results[case]

        def fmt(key: str, rs: list[dict[str, Any]] = rs) -> str:
            v = [r[key] for r in rs]
            return f"{statistics.median(v):7.2f} [{min(v):.2f}–{max(v):.2f}]"
        received = {r["received"] for r in rs} - {None}
        print(f"{case:<18} {fmt('caller_us'):>24} {fmt('cpu_us'):>24}  "
              f"{max(r['dropped'] for r in rs):7d}  "
              f"{'/'.join(map(str, sorted(received))) or '-'}")


if __name__ == "__main__":
    main()
