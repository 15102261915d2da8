"""Two rockets through one gateway, seen from the far side of each protocol.

Serves two TCP feeds of Aurora wire frames (``tools/feed_rockets.py``: alpha near 100 m, beta
near 500 m), runs ``aurora-gateway run --source alpha=socket://… --source beta=socket://…``
with MAVLink (udpout), Zenoh and HTTP, and reports what a pymavlink listener, a Zenoh
subscriber and an HTTP client saw: per MAVLink system its HEARTBEATs, sequence numbers and
ALTITUDE range; per Zenoh key its altitude range; ``/status.json``; the stop report.  Exit 0
when each view kept the two rockets apart, 1 otherwise::

    python tools/check_two_rockets.py [--seconds 8] [--gateway aurora-gateway]
"""

from __future__ import annotations

import argparse
import json
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections import defaultdict
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
ROCKETS = {"alpha": 100.0, "beta": 500.0}


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def listen_mavlink(port: int, stop: threading.Event, out: dict[str, Any]) -> None:
    """Every frame received on UDP 127.0.0.1:PORT, parsed by pymavlink's generated parser
    for the project's dialect (common messages plus AURORA_*), per system."""
    sys.path.insert(0, str(ROOT))
    from dialects import aurora_mavlink

    parser = aurora_mavlink.MAVLink(None)
    parser.robust_parsing = True
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.2)
    systems: dict[int, dict[str, Any]] = defaultdict(lambda: {
        "frames": 0, "heartbeats": 0, "components": set(), "types": set(),
        "custom_modes": set(), "alt": [], "seq_gaps": 0, "last_seq": {}, "kinds": set()})
    while not stop.is_set():
        try:
            data = sock.recv(65536)
        except TimeoutError:
            continue
        for m in parser.parse_buffer(data) or ():
            if m.get_type() == "BAD_DATA":
                continue
            s = systems[m.get_srcSystem()]
            s["frames"] += 1
            s["kinds"].add(m.get_type())
            seq, comp = m.get_seq(), m.get_srcComponent()  # a sequence per component
            last = s["last_seq"].get(comp)
            if last is not None and seq != (last + 1) % 256:
                s["seq_gaps"] += 1
            s["last_seq"][comp] = seq
            if m.get_type() == "HEARTBEAT":
                s["heartbeats"] += 1
                s["components"].add(m.get_srcComponent())
                s["types"].add(m.type)
                s["custom_modes"].add(m.custom_mode)
            elif m.get_type() == "ALTITUDE":
                s["alt"].append(m.altitude_local)
    sock.close()
    out["mavlink"] = systems


def listen_zenoh(endpoint: str, stop: threading.Event, out: dict[str, Any]) -> None:
    """Every JSON sm_update the gateway publishes, per key."""
    import zenoh

    conf = zenoh.Config()  # a peer the gateway connects to (nothing else: no scouting)
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    alts: dict[str, list[float]] = defaultdict(list)
    with zenoh.open(conf) as session:
        def on_sample(sample: Any) -> None:
            try:
                doc = json.loads(bytes(sample.payload.to_bytes()))
            except ValueError:
                return
            alt = doc.get("altitude_m", doc.get("altitude"))
            if isinstance(alt, int | float):
                alts[str(sample.key_expr)].append(float(alt))

        sub = session.declare_subscriber("aurora/*/sm_update", on_sample)
        stop.wait()
        sub.undeclare()
    out["zenoh"] = alts


def span(values: list[float]) -> str:
    return f"{min(values):.1f}..{max(values):.1f} m" if values else "none"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--gateway", default=f"{shlex.quote(sys.executable)} -m gateway",
                   help="the command that runs the gateway (default: this Python's -m gateway)")
    args = p.parse_args(argv)
    feeds = {name: free_port() for name in ROCKETS}
    mav, http, zen = free_port(socket.SOCK_DGRAM), free_port(), free_port()
    feeder = subprocess.Popen([sys.executable, str(ROOT / "tools" / "feed_rockets.py"),
                               *(f"{feeds[n]}:{alt:g}" for n, alt in ROCKETS.items())],
                              stderr=subprocess.DEVNULL)
    stop = threading.Event()
    seen: dict[str, Any] = {}
    threads = [threading.Thread(target=listen_mavlink, args=(mav, stop, seen)),
               threading.Thread(target=listen_zenoh,
                                args=(f"tcp/127.0.0.1:{zen}", stop, seen))]
    # (the Zenoh subscriber listens and the gateway connects to it, retrying until it is up)
    for t in threads:
        t.start()
    cmd = [*shlex.split(args.gateway), "run",
           *(a for n in ROCKETS for a in ("--source", f"{n}=socket://127.0.0.1:{feeds[n]}")),
           "--only", "mavlink", "--only", "zenoh", "--only", "http",
           "--mavlink", f"udpout:127.0.0.1:{mav}", "--zenoh-connect", f"tcp/127.0.0.1:{zen}",
           "--http", f"127.0.0.1:{http}", "--status-interval", "0"]
    print("$", " ".join(shlex.quote(c) for c in cmd))
    gw = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
    status: Any = None
    try:
        time.sleep(args.seconds)
        with urllib.request.urlopen(f"http://127.0.0.1:{http}/status.json", timeout=5) as r:
            status = json.load(r)
    finally:
        gw.send_signal(signal.SIGINT)
        _, report = gw.communicate(timeout=10)
        stop.set()
        for t in threads:
            t.join(10)
        feeder.terminate()
        feeder.wait(5)
    ok = True
    print("\n== pymavlink-generated parser (project dialect) on UDP ==")
    systems = seen.get("mavlink", {})
    for sysid in sorted(systems):
        s = systems[sysid]
        print(f"system {sysid}: {s['frames']} frames, {s['heartbeats']} HEARTBEATs from "
              f"component(s) {sorted(s['components'])} (any frame: {sorted(s['last_seq'])}) "
              f"type(s) {sorted(s['types'])} "
              f"custom_mode {sorted(s['custom_modes'])}, sequence gaps {s['seq_gaps']}, "
              f"ALTITUDE {len(s['alt'])} × {span(s['alt'])}; "
              f"messages {', '.join(sorted(s['kinds']))}")
    ranges = sorted((min(s["alt"]), max(s["alt"])) for s in systems.values() if s["alt"])
    if len(ranges) != 2 or not (ranges[0][1] < 150 and ranges[1][0] > 400):
        ok = False
        print("!! expected two systems, one near 100 m and one near 500 m")
    print("\n== Zenoh subscriber (aurora/*/sm_update) ==")
    zenoh_alts = seen.get("zenoh", {})
    for key in sorted(zenoh_alts):
        print(f"{key}: {len(zenoh_alts[key])} × {span(zenoh_alts[key])}")
    for name, alt in ROCKETS.items():
        vals = zenoh_alts.get(f"aurora/{name}/sm_update", [])
        if not vals or min(vals) < alt * 0.9 or max(vals) > alt * 1.1:
            ok = False
            print(f"!! aurora/{name}/sm_update: expected values near {alt:g} m")
    print("\n== /status.json: its vehicles ==")
    entries = (status or {}).get("vehicles") or {}
    for name, v in entries.items():
        print(f"{name}: " + json.dumps({k: v.get(k) for k in (
            "altitude_m", "max_altitude_m", "state", "armed", "link", "source")}))
    for name, alt in ROCKETS.items():
        got = (entries.get(name) or {}).get("altitude_m")
        if not isinstance(got, int | float) or not alt * 0.9 <= got <= alt * 1.1:
            ok = False
            print(f"!! /status.json vehicles.{name}.altitude_m: expected near {alt:g} m")
    print("\n== stop report ==")
    print("\n".join(ln for ln in report.splitlines() if "INFO" not in ln))
    print("\nresult:", "each view kept the two rockets apart" if ok else "MIXED OR MISSING")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
