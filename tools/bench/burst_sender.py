#!/usr/bin/env python3
"""The burst sender of ``bench_route_bursts.py --sender-process``, in a process of its own (so
it shares no interpreter lock with the bench's receiver): ``--burst`` ATTITUDE datagrams back to
back every ``--burst`` / ``--rate`` seconds to 127.0.0.1:PORT, for ``--seconds``.  It prints
``ready`` once its frames are built, starts at a line on stdin, and prints the seconds it took.
Standard library and pymavlink only (it imports none of the gateway).

    python tools/bench/burst_sender.py PORT --rate 10000 --burst 20 --seconds 6
"""

from __future__ import annotations

import argparse
import socket
import sys
import time

from bench_route_bursts import frames  # (this directory: the script's own)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("port", type=int)
    p.add_argument("--rate", type=float, default=10_000.0)
    p.add_argument("--burst", type=int, default=20)
    p.add_argument("--seconds", type=float, default=6.0)
    args = p.parse_args()
    payload = frames(int(args.rate * args.seconds))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.connect(("127.0.0.1", args.port))
    send = tx.send
    period = args.burst / args.rate
    print("ready", flush=True)
    sys.stdin.readline()
    t0 = time.monotonic()
    nxt = t0
    for i in range(0, len(payload), args.burst):
        for f in payload[i:i + args.burst]:
            send(f)
        nxt += period
        delay = nxt - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    print(f"{time.monotonic() - t0:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
