"""Benchmark: the F´ backend at 100 Hz SM updates — what goes on the wire, and what it costs.

1. **On the wire** (per framing): ``aurora-gateway run`` as a process of its own, the simulated
   flight at ``--rate`` SM updates a second (real time, STATUS at 1 Hz), ``--only fprime``; a
   ground connection reads for ``--seconds`` and fprime-gds's own deframer counts what came:
   SM updates/s, telemetry packets/s, frames/s and bytes/s.  The gateway process's CPU time
   over the same window (``/proc``) is divided by the updates it served; the same process with
   no backend, measured in the same run, gives the F´ backend's share.
2. **Per update, in one process, side by side** (per framing): the gateway's work for one SM
   update (channel entries, packet, frame) against fprime-gds 4.4.1's work for the same bytes
   on the ground (deframe, then decode the channels with the dictionary) — the peer's cost for
   exactly the same data, measured in the same run.

Prints medians of ``--repeat`` repetitions (min–max); asserts nothing about time.

Run: ``.venv/bin/python tools/bench/bench_fprime.py [--repeat 5] [--seconds 5] [--rate 100]``
"""

from __future__ import annotations

import argparse
import logging
import os
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from importlib.metadata import version
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from backends.fprime.channels import ALTITUDE, DEFAULT_ID_BASE, codecs  # noqa: E402
from backends.fprime.dictionary import write_dictionary  # noqa: E402
from backends.fprime.framing import make_framer  # noqa: E402
from backends.fprime.packets import TlmPacker, UpdateClock  # noqa: E402
from gateway.model import SmUpdate  # noqa: E402

FRAMINGS = ("ccsds", "fprime")
CLK_TCK = os.sysconf("SC_CLK_TCK")
ALTITUDE_ID = (DEFAULT_ID_BASE + ALTITUDE.offset).to_bytes(4, "big")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK  # utime + stime


def ground_deframer(framing: str) -> Any:
    from fprime_gds.common.communication.ccsds.chain import (
        SpacePacketSpaceDataLinkFramerDeframer,
    )
    from fprime_gds.common.communication.framing import FpFramerDeframer

    if framing == "ccsds":
        return SpacePacketSpaceDataLinkFramerDeframer(scid=None, vcid=1, frame_size=None)
    return FpFramerDeframer()


def wire(framing: str, seconds: float, rate: float) -> dict[str, float]:
    """One run of the gateway process; figures per second of the read window."""
    port = _free_port()
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "bench.toml"
        cfg.write_text(
            "[gateway]\nstatus_interval_s = 0\n"
            f"[[sources]]\ntype = \"sim\"\nrate_hz = {rate}\nstatus_hz = 1.0\n"
            f"[backends.fprime]\nendpoints = [\"tcpin:127.0.0.1:{port}\"]\n"
            f"framing = \"{framing}\"\n")
        proc = subprocess.Popen(
            [sys.executable, "-m", "gateway", "run", "--config", str(cfg),
             "--only", "fprime"], cwd=ROOT, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL)
        try:
            deadline = time.monotonic() + 10
            while True:
                try:
                    sock = socket.create_connection(("127.0.0.1", port), timeout=1.0)
                    break
                except OSError:
                    if time.monotonic() > deadline:
                        raise
                    time.sleep(0.05)
            sock.settimeout(0.5)
            deframer = ground_deframer(framing)
            time.sleep(1.0)  # the flight and the connection settle; then measure a window
            pending = b""
            while True:  # discard what queued meanwhile
                try:
                    sock.setblocking(False)
                    if not sock.recv(1 << 20):
                        break
                except BlockingIOError:
                    break
            sock.setblocking(True)
            sock.settimeout(0.5)
            n_bytes = 0
            updates = packets = 0
            cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
            while time.monotonic() - t0 < seconds:
                try:
                    data = sock.recv(1 << 16)
                except TimeoutError:
                    continue
                n_bytes += len(data)
                got, pending, _ = deframer.deframe_all(pending + data, no_copy=False)
                for p in got:
                    packets += 1
                    updates += p[2:6] == ALTITUDE_ID  # an SM update's packet starts with it
            wall = time.monotonic() - t0
            cpu = _cpu_s(proc.pid) - cpu0
            sock.close()
        finally:
            proc.terminate()
            proc.wait(10)
    frame_bytes = {"ccsds": 1024, "fprime": 0}[framing]
    return {"updates_s": updates / wall, "packets_s": packets / wall,
            "frames_s": n_bytes / frame_bytes / wall if frame_bytes else packets / wall,
            "bytes_s": n_bytes / wall, "cpu_us_per_update": cpu / max(1, updates) * 1e6}


def baseline(seconds: float, rate: float) -> float:
    """The same gateway process with no backend: its CPU µs per SM update (the simulation,
    the wire codec, the dispatcher), to subtract from :func:`wire`'s figure."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = Path(tmp) / "bench.toml"
        cfg.write_text("[gateway]\nstatus_interval_s = 0\n"
                       f"[[sources]]\ntype = \"sim\"\nrate_hz = {rate}\nstatus_hz = 1.0\n")
        proc = subprocess.Popen([sys.executable, "-m", "gateway", "run", "--config",
                                 str(cfg)], cwd=ROOT, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        try:
            time.sleep(2.0)  # start-up (imports) is not what is measured
            cpu0, t0 = _cpu_s(proc.pid), time.monotonic()
            time.sleep(seconds)
            cpu, wall = _cpu_s(proc.pid) - cpu0, time.monotonic() - t0
        finally:
            proc.terminate()
            proc.wait(10)
    return cpu / (wall * rate) * 1e6


def per_update(framing: str, n: int, dictionary: Path) -> dict[str, float]:
    """Gateway: entries + packet + frame for ``n`` updates; fprime-gds: deframe + decode."""
    from fprime_gds.common.decoders.ch_decoder import ChDecoder
    from fprime_gds.common.distributor.distributor import Distributor
    from fprime_gds.common.handlers import DataHandler
    from fprime_gds.common.models.dictionaries import Dictionaries

    table = codecs()[SmUpdate]
    packer = TlmPacker()
    clock = UpdateClock()
    framer = make_framer(framing, scid=0x44, vcid=1, frame_size=1024)
    msgs = [SmUpdate(12_000 + 10 * i, 2, True, 0, 100.0 + i, 30.0, 29.0, 150.0, 0.1, -0.2,
                     1.5) for i in range(n)]
    out: list[bytes] = []
    t0 = time.process_time()
    for m in msgs:
        tag = clock.tag(m.timestamp_ms)
        entries = [e for codec, get in table if (e := codec.entry(get(m), tag)) is not None]
        out.append(framer.frame(packer.pack(entries)))
    ours = (time.process_time() - t0) / n * 1e6

    dictionaries = Dictionaries.load_dictionaries_into_config(str(dictionary))
    values = 0

    class Count(DataHandler):
        def data_callback(self, data: Any, sender: Any = None) -> None:
            nonlocal values
            values += 1

    distributor = Distributor()  # what fprime-gds's pipeline runs on each received packet
    decoder = ChDecoder(dictionaries.channel_id)
    decoder.register(Count())
    distributor.register("FW_PACKET_TELEM", decoder)
    deframer = ground_deframer(framing)
    t0 = time.process_time()
    pending = b""
    for data in out:
        packets, pending, _ = deframer.deframe_all(pending + data, no_copy=False)
        for p in packets:
            distributor.on_recv(struct.pack(">I", len(p)) + p)
    theirs = (time.process_time() - t0) / n * 1e6
    return {"gateway_us": ours, "fprime_gds_us": theirs, "values": values / n}


def _fmt(xs: list[float], unit: str = "") -> str:
    return f"{statistics.median(xs):10.1f}{unit} ({min(xs):.1f}–{max(xs):.1f})"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--rate", type=float, default=100.0, help="SM updates a second")
    ap.add_argument("--updates", type=int, default=5000, help="updates per in-process run")
    args = ap.parse_args()
    # a ground that joins mid-stream sees the Space Packet count start where the gateway is: the
    # deframer says so once per connection; not what is measured
    logging.getLogger("framing").setLevel(logging.ERROR)
    print(f"fprime-gds {version('fprime-gds')} · {args.rate:g} Hz SM updates + 1 Hz STATUS · "
          f"{args.repeat} runs, median (min–max)")
    base = [baseline(args.seconds, args.rate) for _ in range(args.repeat)]
    print(f"  {'no backend: CPU µs/update':28s}{_fmt(base)}")
    with tempfile.TemporaryDirectory() as tmp:
        dictionary = Path(tmp) / "dict.json"
        write_dictionary(str(dictionary))
        for framing in FRAMINGS:
            runs = [wire(framing, args.seconds, args.rate) for _ in range(args.repeat)]
            per = [per_update(framing, args.updates, dictionary) for _ in range(args.repeat)]
            print(f"\n[{framing}]")
            for key, label in (("updates_s", "SM updates/s seen"),
                               ("packets_s", "telemetry packets/s"),
                               ("frames_s", "frames/s"), ("bytes_s", "bytes/s"),
                               ("cpu_us_per_update", "gateway process CPU µs/update")):
                print(f"  {label:28s}{_fmt([r[key] for r in runs])}")
            added = [r["cpu_us_per_update"] - statistics.median(base) for r in runs]
            print(f"  {'  of which the F´ backend':28s}{_fmt(added)}")
            ours = [p["gateway_us"] for p in per]
            theirs = [p["fprime_gds_us"] for p in per]
            print(f"  {'pack+frame µs/update':28s}{_fmt(ours)}")
            print(f"  {'fprime-gds deframe+decode':28s}{_fmt(theirs)}  "
                  f"(ratio fprime-gds/gateway "
                  f"{statistics.median(t / o for t, o in zip(theirs, ours, strict=True)):.1f}×)")
            values = statistics.median(p["values"] for p in per)
            print(f"  {'channel values/update':28s}{values:10.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
