"""Benchmark: the XBee link between two gateways over the emulated pair (``tests/xbee_pair.py``)
— ack latency, air time used, and the power the ground chooses against the loss per level.

Two gateways in this process, as ``run`` builds them: the air (``sim`` at real time, 10 Hz SM
updates and 1 Hz STATUS → ``xbee`` backend) and the ground (``xbee`` source); per loss table,
``--seconds`` of flight, then figures from the gateways' own counters and the emulator's log:
the ground's median ack latency, the bytes/s each side put on the air (telemetry, link
packets), and the share of the ground's packets at each power level after its first 10 s.

Run: ``.venv/bin/python tools/bench/bench_xbee.py [--seconds 30] [--api 2]``
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
for path in (ROOT, ROOT / "tests"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from xbee_pair import XBeePair  # noqa: E402

from backends.xbee import packets as p  # noqa: E402
from gateway import config  # noqa: E402
from gateway.app import Gateway  # noqa: E402

RSSI = (-95.0, -90.0, -84.0, -78.0, -72.0)
TABLES = {
    "good at PL 2 (-84 dBm ≥ -85)": (0.6, 0.3, 0.05, 0.0, 0.0),
    "every level clean": (0.0, 0.0, 0.0, 0.0, 0.0),
    "lossy low levels": (0.9, 0.7, 0.4, 0.05, 0.0),
}


def gateway(sources: list[dict[str, Any]], backends: dict[str, Any]) -> Gateway:
    cfg = config.parse({"gateway": {"status_interval_s": 0.0}, "sources": sources,
                        "backends": backends})
    return Gateway(cfg)


def run(loss: tuple[float, ...], seconds: float, api: int) -> dict[str, Any]:
    with XBeePair(api, api, loss=loss, rssi=RSSI, seed=11) as pair:
        air = gateway([{"type": "sim", "rate_hz": 10.0, "status_hz": 1.0}],
                      {"xbee": {"url": pair.url_a, "api_mode": api}})
        ground = gateway([{"type": "xbee", "url": pair.url_b, "api_mode": api,
                           "name": "ground"}], {})
        air.start()
        ground.start()
        t0 = time.monotonic()
        time.sleep(seconds)  # a fixed window of flight is what is measured
        src = ground.sources[0]
        stats = src.stats()
        events = pair.event_list()
        ground.stop()
        air.stop()
    window = time.monotonic() - t0
    air_bytes: collections.Counter[str] = collections.Counter()
    for e in events:
        if e.src == "a" and e.kind == "data":
            for pk in p.iter_decode(e.payload):
                kind = ("telemetry" if isinstance(pk, p.SmTelemetry | p.StatusTelemetry)
                        else "link")
                air_bytes[kind] += len(p.encode(pk))
    ground_bytes = sum(len(e.payload) for e in events if e.src == "b" and e.kind == "data")
    late = [e.power for e in events if e.src == "b" and e.kind == "data"
            and e.t_sent >= t0 + 10.0]
    share = {lvl: late.count(lvl) / len(late) for lvl in range(5)} if late else {}
    return {"ack_ms": stats.get("ack_latency_ms"), "telemetry_Bps": air_bytes["telemetry"] / window,
            "air_link_Bps": air_bytes["link"] / window, "ground_Bps": ground_bytes / window,
            "share": share, "sm_received": stats.get("ground_telemetry_rx")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--api", type=int, choices=(1, 2), default=2)
    args = ap.parse_args()
    print(f"XBee pair emulator, API {args.api}, RSSI per PL {RSSI} dBm, threshold -85 dBm, "
          f"{args.seconds:g} s each, SM 10 Hz + STATUS 1 Hz")
    for label, loss in TABLES.items():
        r = run(loss, args.seconds, args.api)
        share = "  ".join(f"PL{lvl} {r['share'].get(lvl, 0):4.0%}" for lvl in range(5))
        print(f"\n[{label}] loss per PL {loss}")
        print(f"  ack latency (median)         {r['ack_ms']} ms")
        print(f"  air → ground telemetry       {r['telemetry_Bps']:7.0f} B/s")
        print(f"  air → ground acks/pings/stats{r['air_link_Bps']:7.0f} B/s")
        print(f"  ground → air commands        {r['ground_Bps']:7.0f} B/s")
        print(f"  ground power after 10 s      {share}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
