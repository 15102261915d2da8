#!/usr/bin/env python3
"""The floor under the gateway's MAVLink routing cost: a forwarder that does nothing but the
system calls the gateway's router makes — one ``epoll`` wait, one ``recvmmsg`` of everything
waiting, one ``sendmmsg`` of it all to one destination (gateway/io/mmsg.py) — with no
parsing, checking or routing, and the same hold: while reads find datagrams, it sleeps
``--hold`` seconds after each (the gateway's ``COALESCE_S``), then reads again; a read that
finds none goes back to the ``epoll`` wait.  ``bench_route_bursts.py --floor`` runs it beside
the gateway and mavlink-router: the gateway's cost above this line is its Python work per
datagram and per wake-up; this line above mavlink-router's is the price of the interpreter
and of the system calls' pattern.

    python tools/bench/route_floor.py IN_PORT OUT_PORT [--hold SECONDS]

``--hold 0``: read at each wake-up only (what the floor was before 2026-11-26).
"""

from __future__ import annotations

import argparse
import select
import signal
import socket
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout's gateway

from gateway.io.mmsg import AVAILABLE, MmsgSocket
from gateway.io.port import COALESCE_S


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("port_in", type=int)
    p.add_argument("port_out", type=int)
    p.add_argument("--hold", type=float, default=COALESCE_S,
                   help=f"seconds between reads while they find datagrams (default "
                        f"{COALESCE_S}, the gateway's; 0: none)")
    args = p.parse_args()
    if not AVAILABLE:
        print("route_floor: recvmmsg/sendmmsg are not available here", file=sys.stderr)
        return 2
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", args.port_in))
    rx.setblocking(False)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.setblocking(False)
    mrx, mtx = MmsgSocket(rx), MmsgSocket(tx)
    ep = select.epoll()
    ep.register(rx.fileno(), select.EPOLLIN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    dest = ("127.0.0.1", args.port_out)
    hold = args.hold
    while True:
        ep.poll(1.0)
        while True:
            data, _ = mrx.recv(False)
            if not data:
                break
            mtx.send(data, dest)
            if hold <= 0:
                break
            select.select((), (), (), hold)  # (the gateway's hold: sub-millisecond select)


if __name__ == "__main__":
    sys.exit(main())
