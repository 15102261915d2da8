"""Serve rockets' wire frames on TCP ports, one rocket per port, each holding near an altitude.

What a test bench with several flight computers on TCP serial servers looks like to the
gateway (``--source NAME=socket://HOST:PORT``).  Each port sends SM_UPDATE at ``--rate`` Hz
and STATUS at 1 Hz to whoever connects (every client gets the stream; a client that stops
reading is dropped)::

    python tools/feed_rockets.py 5761:100 5762:500 &
    aurora-gateway run --source alpha=socket://127.0.0.1:5761 \\
                       --source beta=socket://127.0.0.1:5762

Altitudes wander ±5 % around the given value, so each rocket's values stay recognisable.
"""

from __future__ import annotations

import argparse
import math
import selectors
import socket
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dialects.states import SimpleState
from gateway.model import SmUpdate, Status
from gateway.wire import encode


def frames(altitude_m: float, t: float, n: int) -> bytes:
    """The frames of one tick: an SM_UPDATE near ``altitude_m`` (and a STATUS every 10th)."""
    alt = altitude_m * (1 + 0.05 * math.sin(t))
    ms = int(t * 1000) & 0xFFFFFFFF
    out = encode(SmUpdate(ms, int(SimpleState.BURNOUT), True, 0, alt, 0.5, -0.2,
                          5 * math.cos(t), 0.01, 0.02, 0.03))
    if n % 10 == 0:
        out += encode(Status(ms, int(SimpleState.BURNOUT), 0, Status.make_flags(
            armed=True, imu_ok=True, baro_ok=True, calibrated=True, log_ready=True)))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("feeds", nargs="+", metavar="PORT:ALTITUDE",
                   help="a TCP port to serve and the altitude (m) its rocket holds near")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--rate", type=float, default=10.0, help="SM_UPDATE per second (10)")
    p.add_argument("--duration", type=float, default=None, help="seconds, then stop")
    args = p.parse_args(argv)
    sel = selectors.DefaultSelector()
    feeds: list[tuple[socket.socket, float, list[socket.socket]]] = []
    for text in args.feeds:
        port_text, _, alt_text = text.partition(":")
        try:
            port, alt = int(port_text), float(alt_text)
        except ValueError:
            p.error(f"{text!r}: expected PORT:ALTITUDE")
        srv = socket.create_server((args.host, port))
        srv.setblocking(False)
        clients: list[socket.socket] = []
        sel.register(srv, selectors.EVENT_READ, clients)
        feeds.append((srv, alt, clients))
        print(f"rocket near {alt:g} m on tcp {args.host}:{port}", file=sys.stderr)
    start = time.monotonic()
    period = 1.0 / args.rate
    n = 0
    next_tick = start
    try:
        while args.duration is None or time.monotonic() - start < args.duration:
            for key, _ in sel.select(max(0.0, next_tick - time.monotonic())):
                conn, _addr = key.fileobj.accept()  # type: ignore[union-attr]
                conn.setblocking(False)
                key.data.append(conn)
            if time.monotonic() < next_tick:
                continue
            t = next_tick - start
            for _srv, alt, clients in feeds:
                data = frames(alt, t, n)
                for c in list(clients):
                    try:
                        c.send(data)
                    except OSError:  # gone, or not reading: dropped
                        clients.remove(c)
                        c.close()
            n += 1
            next_tick += period
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
