"""Benchmark: the Zenoh backend's throughput, its losses at saturation, and end-to-end latency.

Three parts, each repeated ``--repeat`` times (medians printed, with min and max):

1. **Throughput.**  A :class:`ZenohBackend` (peer, loopback) publishes ``--updates``
   SM_UPDATEs of the simulated flight; a subscriber in *another process* counts them and the
   gaps in their sequence numbers.  The hand-off queue is deep enough for all of them.  With
   congestion control DROP: updates/s published (first hook → last put) and how many the
   subscriber missed; with BLOCK: updates/s delivered (nothing is lost; the slower of
   publisher and subscriber sets the pace).  Cases: JSON only (``raw = false``), the default
   (JSON + the raw frame: two puts per update), packed.  The same run times a bare Zenoh
   publisher putting the same, already encoded, JSON payloads in a loop (no encoding, no
   queue): the ratio ours/bare shows what the gateway's Python costs on top of Zenoh.

2. **Saturation.**  The default queue (1024) and a producer calling the hook flat out: how
   many updates the hook refused (counted QUEUE_FULL), how many the backend published, how
   many the subscriber lost inside Zenoh (sequence gaps + missing tail), for congestion
   control DROP and BLOCK.

3. **Latency.**  ``aurora-gateway run`` (another process) reads a pty as its serial source,
   with only the Zenoh backend; this script writes a wire frame into the pty every 10 ms
   (100 Hz) and a subscriber here timestamps each update's arrival: wire frame written →
   subscriber callback, for the JSON document (``sm_update``) and the raw frame (``raw/1``).
   The peer, in the same runs: half a period after each frame, a bare Zenoh session of this
   process puts a probe to the same subscriber (Python put → Zenoh → Python callback, no
   gateway), so a load spike on the shared machine shows in both.  p50/p99 per run.

Prints figures; asserts nothing about time.  The machine is shared: trust medians and ratios.

Run: ``.venv/bin/python tools/bench/bench_zenoh.py [--updates N] [--repeat N]
[--latency-s S] [--only throughput,saturation,latency]``
"""

from __future__ import annotations

import argparse
import gc
import itertools
import json
import os
import statistics
import subprocess
import sys
import threading
import time
import tty
from importlib.metadata import version
from pathlib import Path
from typing import Any

from pacing import paced_batches  # tools/bench/pacing.py, beside this script

from backends.zenoh.options import ZenohOptions

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # run as a script from anywhere, without installing
    sys.path.insert(0, str(ROOT))
if str(ROOT / "tests") not in sys.path:  # the Zenoh test helpers (zenoh_peer)
    sys.path.insert(0, str(ROOT / "tests"))

import zenoh  # noqa: E402
from zenoh_peer import (  # noqa: E402
    free_endpoint,
    peer_config,
    read_line,
    serving,
    stop_process,
    wait_for_gateway,
)

from backends.zenoh import encoding as enc  # noqa: E402
from backends.zenoh.backend import ZenohBackend  # noqa: E402
from backends.zenoh.keys import SeqTracker, make_attachment, parse_attachment  # noqa: E402
from gateway import wire  # noqa: E402
from gateway.dispatcher import Dispatcher  # noqa: E402
from gateway.flight import FlightModel  # noqa: E402
from gateway.model import SmUpdate  # noqa: E402
from gateway.sources.sim import flight_messages  # noqa: E402

VEHICLE = "bench"
END_KEY = f"aurora/{VEHICLE}/end"
PROBE_KEY = "aurora/probe/latency"
PROBE = "bare Zenoh hop (peer)"
TARGET_UPDATES_S = 20_000
TARGET_P99_MS = 5.0
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def updates(n: int) -> list[SmUpdate]:
    """``n`` SM_UPDATEs of the simulated flight at 100 Hz, decoded from their frames."""
    out = []
    for _, m in flight_messages(FlightModel(), 100.0, 0.0, 0):
        out.append(wire.decode_all(wire.encode(m), origin="bench", vehicle=VEHICLE)[0])
        if len(out) == n:
            return out
    return out


def med(values: list[float]) -> str:
    return f"{statistics.median(values):10.1f}  (min {min(values):.1f}, max {max(values):.1f})"


# -- the subscriber process ------------------------------------------------------------------

def subscriber_main(endpoint: str, slow_s: float = 0.0) -> int:
    """Child process: count samples per key and their sequence gaps until the end marker;
    ``slow_s`` of busy work per sample makes it a slow dashboard."""
    tracker = SeqTracker()
    state = {"n": 0, "first": None, "last": None, "expected": None}
    done = threading.Event()

    def on_sample(sample: Any) -> None:
        key = str(sample.key_expr)
        if key == END_KEY:
            state["expected"] = json.loads(sample.payload.to_bytes())
            done.set()
            return
        now = time.monotonic()
        if state["first"] is None:
            state["first"] = now
        state["last"] = now
        state["n"] += 1
        att = sample.attachment
        gw, seq = parse_attachment(att.to_bytes() if att is not None else None)
        tracker.see(gw, key, seq)
        if slow_s:
            until = time.perf_counter() + slow_s
            while time.perf_counter() < until:
                pass

    with zenoh.open(peer_config(connect=[endpoint])) as s:
        s.declare_subscriber(f"aurora/{VEHICLE}/**", on_sample)
        wait_for_gateway(s, "aurora", VEHICLE, timeout=60)
        print("ready", flush=True)
        done.wait(600)
    span = (state["last"] or 0) - (state["first"] or 0)
    print(json.dumps({"received": state["n"], "gaps": tracker.lost, "span_s": span,
                      "expected": state["expected"]}), flush=True)
    return 0


class Subscriber:
    """The counting subscriber, in its own process."""

    def __init__(self, endpoint: str, slow_s: float = 0.0) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, __file__, "_subscriber", endpoint, str(slow_s)], cwd=ROOT, env=ENV,
            stdout=subprocess.PIPE, text=True)
        line = read_line(self.proc, 60)
        if line.strip() != "ready":
            stop_process(self.proc)
            raise RuntimeError(f"subscriber did not start: {line!r}")

    def result(self) -> dict[str, Any]:
        line = read_line(self.proc, 120)
        stop_process(self.proc)
        return json.loads(line)


def end_marker(session: Any, published: dict[str, int]) -> None:
    """Sent after the last update, on the same session and link, never dropped."""
    session.put(END_KEY, json.dumps(published).encode(),
                congestion_control=zenoh.CongestionControl.BLOCK)


# -- 1. throughput ----------------------------------------------------------------------------

def offer(send: Any, msgs: list[SmUpdate], rate: float) -> list[Any]:
    """Call the hook for every message at ``rate`` per second (0 = flat out), in 1 ms batches
    — between batches the producer waits, as a source waits for its port."""
    return [send(m) for batch in paced_batches(msgs, rate) for m in batch]


def run_backend(msgs: list[SmUpdate], *, depth: int, congestion: str = "drop",
                encoding: str = "json", raw: bool = False, rate: float = 0.0,
                slow_s: float = 0.0) -> dict[str, Any]:
    """Publish ``msgs`` through a fresh backend to a subscriber process; the figures."""
    ep = free_endpoint()
    b = serving(ZenohBackend(ZenohOptions(listen=[ep], encoding=encoding, raw=raw,
                                          queue_depth=depth, congestion_control=congestion,
                                          liveliness=True)), VEHICLE, source="bench")
    dispatcher = Dispatcher([b])  # the hook is what the dispatcher calls (a hand-over)
    dispatcher.start()
    dispatch = dispatcher.dispatch
    if not b.wait_ready(30):
        raise RuntimeError("backend session did not open")
    sub = Subscriber(ep, slow_s)
    try:
        gc.collect()
        gc.disable()
        t0 = time.monotonic()
        outcomes = offer(dispatch, msgs, rate)
        if not b.wait_idle(600):
            raise RuntimeError("backend did not drain")
        t1 = time.monotonic()
        gc.enable()
        st = b.stats()
        end_marker(b._session, {"puts": st["puts"]})
        res = sub.result()
    finally:
        gc.enable()
        b.close()
    accepted = sum(1 for o in outcomes if o == 0)
    per_update = 2 if raw else 1
    return {
        "offered": len(msgs), "accepted": accepted, "queue_full": st["dropped_queue_full"],
        "published": st["sent"], "puts": st["puts"], "publish_s": t1 - t0,
        "received_puts": res["received"],
        "received": res["received"] // per_update,
        "zenoh_lost": st["puts"] - res["received"],
        "gaps": res["gaps"], "rx_span_s": res["span_s"],
    }


def run_bare(payloads: list[bytes], congestion: str) -> dict[str, Any]:
    """The peer: a bare Zenoh publisher putting pre-encoded payloads, same subscriber."""
    ep = free_endpoint()
    cc = getattr(zenoh.CongestionControl, congestion.upper())
    with zenoh.open(peer_config(listen=[ep])) as s:
        token = s.liveliness().declare_token(f"aurora/{VEHICLE}/gateway/bare")
        q = s.declare_queryable(f"aurora/{VEHICLE}/**", lambda query: query.drop())
        pub = s.declare_publisher(f"aurora/{VEHICLE}/sm_update", encoding=enc.JSON,
                                  congestion_control=cc)
        sub = Subscriber(ep)
        put = pub.put
        gc.collect()
        gc.disable()
        t0 = time.monotonic()
        for i, p in enumerate(payloads):
            put(p, attachment=make_attachment("bare", i))
        t1 = time.monotonic()
        gc.enable()
        end_marker(s, {"puts": len(payloads)})
        res = sub.result()
        q.undeclare()
        token.undeclare()
    return {"published": len(payloads), "publish_s": t1 - t0, "received": res["received"],
            "zenoh_lost": len(payloads) - res["received"], "rx_span_s": res["span_s"]}


def throughput(n: int, repeat: int) -> None:
    msgs = updates(n)
    payloads = [enc.to_json(m) for m in msgs]
    cases = [("JSON only (raw = false)", {"raw": False}),
             ("JSON + raw frame (default; 2 puts)", {"raw": True}),
             ("packed (raw = false)", {"encoding": "packed"})]
    print(f"\n1. Throughput: {n} SM_UPDATEs, subscriber in another process, hand-off queue deep "
          f"enough for all\n   ({repeat} runs; updates/s, medians (min–max)).  DROP: what the "
          f"publisher sustains, and what the\n   subscriber missed (it counts more slowly "
          f"than the publisher puts).  BLOCK: delivered, nothing lost.")
    print(f"  {'case':<36} {'DROP published/s':>22} {'DROP lost':>10} "
          f"{'BLOCK delivered/s':>22}")
    rows: dict[str, dict[str, list[float]]] = {}
    ratios: list[float] = []
    run_backend(msgs[: n // 10], depth=n)  # warm-up, not counted

    def rate(r: dict[str, Any]) -> float:
        return r["published"] / r["publish_s"]

    def delivered(r: dict[str, Any]) -> float:
        return r["received"] / r["rx_span_s"] if r["rx_span_s"] else 0.0

    for _ in range(repeat):
        label = "bare Zenoh put, pre-encoded (peer)"
        bd, bb = run_bare(payloads, "drop"), run_bare(payloads, "block")
        row = rows.setdefault(label, {"pub": [], "lost": [], "dlv": []})
        row["pub"].append(rate(bd))
        row["lost"].append(bd["zenoh_lost"])
        row["dlv"].append(delivered(bb))
        for label, kw in cases:
            rd = run_backend(msgs, depth=n, congestion="drop", **kw)
            rb = run_backend(msgs, depth=n, congestion="block", **kw)
            row = rows.setdefault(label, {"pub": [], "lost": [], "dlv": []})
            row["pub"].append(rate(rd))
            row["lost"].append(rd["zenoh_lost"])
            row["dlv"].append(delivered(rb))
            if label.startswith("JSON only"):
                ratios.append(rate(rd) / rate(bd))

    def cell(vals: list[float]) -> str:
        return f"{statistics.median(vals):.0f} ({min(vals):.0f}–{max(vals):.0f})"

    for label, row in rows.items():
        print(f"  {label:<36} {cell(row['pub']):>22} {statistics.median(row['lost']):>10.0f} "
              f"{cell(row['dlv']):>22}")
    print(f"  ours (JSON only) / bare put, DROP published/s, per run: median "
          f"{statistics.median(ratios):.3f}")
    best = statistics.median(rows["JSON only (raw = false)"]["pub"])
    dlv = statistics.median(rows["JSON only (raw = false)"]["dlv"])
    print(f"  target ≥ {TARGET_UPDATES_S} updates/s with JSON: "
          f"{'met' if min(best, dlv) >= TARGET_UPDATES_S else 'NOT met'} "
          f"({best:.0f} published, {dlv:.0f} delivered)")


# -- 2. saturation ----------------------------------------------------------------------------

def saturation(n: int, repeat: int, rate: float = 30_000, slow_us: float = 50.0) -> None:
    msgs = updates(n)
    print(f"\n2. Saturation: {n} SM_UPDATEs (JSON only) offered at {rate:.0f}/s to a slow "
          f"subscriber ({slow_us:.0f} µs per sample, ≈ {1e6 / slow_us:.0f}/s), queue_depth "
          f"1024 ({repeat} runs; medians)")
    print(f"  {'congestion':<10} {'offered':>8} {'queue-full':>11} {'published':>10} "
          f"{'lost in Zenoh':>14} {'received':>9} {'counted share of loss':>22}")
    for cc in ("drop", "block"):
        res = [run_backend(msgs, depth=1024, congestion=cc, rate=rate, slow_s=slow_us / 1e6)
               for _ in range(repeat)]

        def m(key: str, rs: list[dict[str, Any]] = res) -> float:
            return statistics.median(r[key] for r in rs)

        counted = statistics.median(
            r["queue_full"] / (r["queue_full"] + r["zenoh_lost"])
            if r["queue_full"] + r["zenoh_lost"] else 1.0 for r in res)
        print(f"  {cc:<10} {m('offered'):>8.0f} {m('queue_full'):>11.0f} {m('published'):>10.0f} "
              f"{m('zenoh_lost'):>14.0f} {m('received'):>9.0f} {counted:>21.0%}")
    print("  queue-full: refused by the hook and counted by the backend; lost in Zenoh: "
          "published but never\n  received — DROP's losses, invisible to the publisher "
          "(subscribers see them as seq gaps)")


# -- 3. latency -------------------------------------------------------------------------------

def percentile(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, round(q * (len(s) - 1)))]


def latency(seconds: float, repeat: int, rate_hz: float = 100.0) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    port = os.ttyname(slave)
    ep = free_endpoint()
    cfg = Path(f"/tmp/bench-zenoh-{os.getpid()}.toml")
    cfg.write_text(f'[gateway]\nstatus_interval_s = 0\nlog_level = "warning"\n\n'
                   f'[[sources]]\ntype = "serial"\nurl = "{port}"\nvehicle = "{VEHICLE}"\n\n'
                   f'[backends.zenoh]\nlisten = ["{ep}"]\n')
    gw_log = cfg.with_suffix(".log")
    with gw_log.open("w") as log:
        gw = subprocess.Popen([sys.executable, "-m", "gateway", "run", "-c", str(cfg)],
                              cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=log)
    print(f"\n3. Latency: wire frame written into the gateway's serial input (a pty) → "
          f"subscriber callback, {rate_hz:.0f} Hz, {seconds:.0f} s per run ({repeat} runs)")
    sent: dict[int, float] = {}
    probes: dict[int, float] = {}
    got: dict[str, dict[int, float]] = {"sm_update": {}, "raw/1": {}, PROBE: {}}
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        now = time.perf_counter()
        key = str(sample.key_expr)
        data = sample.payload.to_bytes()
        if key.endswith("/raw/1"):
            kind, ident = "raw/1", int.from_bytes(data[4:8], "little")
        elif key.endswith("/sm_update"):
            kind, ident = "sm_update", int(data[16:data.index(b",", 16)])  # {"timestamp_ms":N,
        elif key == PROBE_KEY:
            kind, ident = PROBE, int(data)
        else:
            return
        with lock:
            got[kind][ident] = now

    probe_ep = free_endpoint()
    try:
        with zenoh.open(peer_config(listen=[probe_ep])) as probe, \
                zenoh.open(peer_config(connect=[ep, probe_ep])) as s:
            s.declare_subscriber(f"aurora/{VEHICLE}/*", on_sample)
            s.declare_subscriber(f"aurora/{VEHICLE}/raw/1", on_sample)
            s.declare_subscriber(PROBE_KEY, on_sample)
            probe_pub = probe.declare_publisher(PROBE_KEY)
            template = updates(1)[0]
            ident = itertools.count(1)

            def write_frames(count: int) -> None:
                """A frame every period; a bare Zenoh probe half a period later."""
                period = 1.0 / rate_hz
                start = time.perf_counter()
                pause = threading.Event()
                for k in range(count):
                    i = next(ident)
                    frame = wire.encode(template._replace(timestamp_ms=i))
                    delay = start + k * period - time.perf_counter()
                    if delay > 0:
                        pause.wait(delay)
                    sent[i] = time.perf_counter()
                    os.write(master, frame)
                    delay = start + (k + 0.5) * period - time.perf_counter()
                    if delay > 0:
                        pause.wait(delay)
                    probes[i] = time.perf_counter()
                    probe_pub.put(str(i).encode())

            deadline = time.monotonic() + 60
            while not got["sm_update"] or not got[PROBE]:  # the gateway starts, connects
                if time.monotonic() > deadline:
                    raise RuntimeError("no update from the gateway within 60 s")
                write_frames(10)
            p50s: dict[str, list[float]] = {k: [] for k in got}
            p99s: dict[str, list[float]] = {k: [] for k in got}
            lost: list[int] = []
            for _ in range(repeat):
                with lock:
                    for d in got.values():
                        d.clear()
                sent.clear()
                probes.clear()
                n = round(seconds * rate_hz)
                write_frames(n)
                pause, until = threading.Event(), time.monotonic() + 2.0
                while time.monotonic() < until:  # let the last updates arrive
                    with lock:
                        if all(len(d) >= len(sent) for d in got.values()):
                            break
                    pause.wait(0.01)
                with lock:
                    for kind, d in got.items():
                        origin = probes if kind == PROBE else sent
                        lat = [(d[i] - t) * 1000 for i, t in origin.items() if i in d]
                        p50s[kind].append(percentile(lat, 0.50))
                        p99s[kind].append(percentile(lat, 0.99))
                    lost.append(len(sent) - len(got["sm_update"]))
            for kind in got:
                print(f"  {kind:<26} p50 ms {med(p50s[kind])}")
                print(f"  {kind:<26} p99 ms {med(p99s[kind])}")
            print(f"  updates not received: {lost}")
            p99 = statistics.median(p99s["sm_update"])
            print(f"  target p99 < {TARGET_P99_MS} ms at 100 Hz: "
                  f"{'met' if p99 < TARGET_P99_MS else 'NOT met'} ({p99:.2f} ms; the bare "
                  f"Zenoh hop's p99 in the same runs: {statistics.median(p99s[PROBE]):.2f} ms)")
    except Exception:
        print(gw_log.read_text(), file=sys.stderr)
        raise
    finally:
        stop_process(gw)
        os.close(master)
        os.close(slave)
        cfg.unlink(missing_ok=True)
        gw_log.unlink(missing_ok=True)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "_subscriber":
        return subscriber_main(argv[1], float(argv[2]))
    p = argparse.ArgumentParser(description="Zenoh backend throughput, saturation, latency")
    p.add_argument("--updates", type=int, default=100_000, metavar="N")
    p.add_argument("--repeat", type=int, default=3, metavar="N")
    p.add_argument("--latency-s", type=float, default=10.0, metavar="S")
    p.add_argument("--only", default="throughput,saturation,latency")
    args = p.parse_args(argv)
    parts = set(args.only.split(","))
    print(f"bench_zenoh: eclipse-zenoh {version('eclipse-zenoh')}, Python "
          f"{sys.version.split()[0]}, {os.cpu_count()} CPUs, load {os.getloadavg()[0]:.2f}")
    if "throughput" in parts:
        throughput(args.updates, args.repeat)
    if "saturation" in parts:
        saturation(args.updates, args.repeat)
    if "latency" in parts:
        latency(args.latency_s, args.repeat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
