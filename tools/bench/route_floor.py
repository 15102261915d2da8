#!/usr/bin/env python3
"""The floor under the gateway's MAVLink routing cost: a forwarder that does nothing but the
system calls the gateway's router makes on a burst — one ``epoll`` wait, one ``recvmmsg`` of
everything waiting, one ``sendmmsg`` of it all to one destination (gateway/io/mmsg.py) — with
no parsing, checking or routing.  ``bench_route_bursts.py --floor`` runs it beside the
gateway and mavlink-router: the gateway's cost above this line is its Python work per
datagram and per wake-up; this line above mavlink-router's is the price of the interpreter.

    python tools/bench/route_floor.py IN_PORT OUT_PORT
"""

from __future__ import annotations

import select
import signal
import socket
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout's gateway

from gateway.io.mmsg import AVAILABLE, MmsgSocket


def main() -> int:
    if not AVAILABLE:
        print("route_floor: recvmmsg/sendmmsg are not available here", file=sys.stderr)
        return 2
    port_in, port_out = int(sys.argv[1]), int(sys.argv[2])
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", port_in))
    rx.setblocking(False)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.setblocking(False)
    mrx, mtx = MmsgSocket(rx), MmsgSocket(tx)
    ep = select.epoll()
    ep.register(rx.fileno(), select.EPOLLIN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    dest = ("127.0.0.1", port_out)
    while True:
        ep.poll(1.0)
        data, _ = mrx.recv(False)
        if data:
            mtx.send(data, dest)


if __name__ == "__main__":
    sys.exit(main())
