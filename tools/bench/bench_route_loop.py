"""Benchmark: the router's batch loop in-process, compiled against pure Python, side by side.

No sockets: ``Router.receive_many`` on batches of ATTITUDE frames of one vehicle, forwarded to
one link that takes batches, with and without a node that keeps ATTITUDE in its mailbox (the
``run --source mavlink:…`` case). It prints µs per message for each path, as the median of
``--repeat`` passes (and the fastest), and the ratio of the two.

    python tools/bench/bench_route_loop.py [--frames 20000] [--batch 20] [--repeat 7]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout's packages

from pymavlink.dialects.v20 import common

import backends.mavlink.router as router_mod
from backends.mavlink.router import Link, Router


class BatchLink(Link):
    """A link that takes a batch, as a UDP endpoint does (what it is given is dropped)."""

    datagram = True

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self._batch: list[bytes] | None = None
        self.count = 0

    def start_batch(self) -> None:
        self._batch = []

    def batch_sink(self) -> list[bytes] | None:
        return self._batch

    def flush_batch(self) -> None:
        self.count += len(self._batch or ())
        self._batch = None

    def send(self, data: bytes) -> bool:
        self.count += 1
        return True


class MailboxNode:
    sysid, compid = 200, 191
    consumed: frozenset[int] = frozenset()
    latest = frozenset({30})  # ATTITUDE

    def handle(self, msg: Any, src_sysid: int, src_compid: int) -> list[Any]:
        return []


def measure(speedups: Any, mailbox: bool, args: argparse.Namespace) -> list[float]:
    router_mod._speedups = speedups
    router = Router()
    src, out = BatchLink("in"), BatchLink("out")
    router.add_link(src)
    router.add_link(out)
    node = MailboxNode()
    if mailbox:
        router.add_node(node)
        router.claim(node)
    mav = common.MAVLink(None, 1, 1)
    frames = []
    for i in range(args.frames):
        frames.append(common.MAVLink_attitude_message(i, 0.1, 0.2, 0.3, 0, 0, 0).pack(mav))
        mav.seq = (mav.seq + 1) & 0xFF
    router.receive(src, frames[0])  # the vehicle is seen: the rest is the common case
    batches = [frames[i:i + args.batch] for i in range(0, len(frames), args.batch)]
    per_msg = []
    for _ in range(args.repeat):
        t = time.perf_counter()
        for b in batches:
            router.receive_many(src, b)
        per_msg.append((time.perf_counter() - t) / len(frames) * 1e6)
        if mailbox:
            router.collect(node)
    return per_msg


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=20000)
    p.add_argument("--batch", type=int, default=20)
    p.add_argument("--repeat", type=int, default=7)
    args = p.parse_args()
    compiled = router_mod._speedups
    if compiled is None:
        print("the compiled loop is not built (or AURORA_NO_SPEEDUPS is set): Python only")
    print(f"batches of {args.batch}, {args.frames} frames, {args.repeat} passes: µs per message"
          " (median, fastest)")
    for mailbox in (False, True):
        label = "into a mailbox" if mailbox else "forwarded only"
        py = measure(None, mailbox, args)
        line = f"  {label:15s} python {statistics.median(py):.2f} ({min(py):.2f})"
        if compiled is not None:
            c = measure(compiled, mailbox, args)
            line += (f"   compiled {statistics.median(c):.2f} ({min(c):.2f})"
                     f"   python / compiled {statistics.median(py) / statistics.median(c):.1f}×")
        print(line)
    router_mod._speedups = compiled
    return 0


if __name__ == "__main__":
    sys.exit(main())
