"""Benchmark: a TCP client floods the F´ backend with commands of distinct opcodes.

``aurora-gateway run --source sim --fprime tcpin:127.0.0.1:PORT --only fprime`` runs as a
process of its own (from ``--tree``, default this checkout, with that tree's ``.venv``); one
ground connection sends ``--opcodes`` command packets, each with a new opcode, paced evenly over
``--seconds`` (TC frames for ``ccsds``, DEADBEEF frames for ``fprime``) while a thread reads
(and throws away) what comes down.  Printed: the commands sent, the gateway's stderr lines and
bytes, its RSS before the flood, after it and ``--settle`` seconds later (``/proc``), and the
CPU time it used during the flood (and per command).

Asserts nothing; the figures of issue 23 ("600k distinct opcodes in 45 s: stderr < 100 lines,
RSS grows < 5 MB") come from the defaults.

Run: ``.venv/bin/python tools/bench/bench_fprime_flood.py [--opcodes 600000] [--seconds 45]
[--framing ccsds] [--tree /work/wt-prev]``
"""

from __future__ import annotations

import argparse
import os
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench_fprime import _cpu_s, _free_port  # (this directory: the script's own)

ROOT = Path(__file__).resolve().parents[2]
PAGE = os.sysconf("SC_PAGE_SIZE")
SCID = 0x44  # the backend's default spacecraft id
BATCH_S = 0.01  # commands go out in one write per this interval


def _rss_mib(pid: int) -> float:
    return int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE / 2**20


def _crc16_ccitt_false(data: bytes) -> int:
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def command_packet(opcode: int) -> bytes:
    """An F´ command packet: descriptor 0 (command), the opcode, no arguments."""
    return struct.pack(">HI", 0, opcode)


def tc_frame(packet: bytes, seq: int) -> bytes:
    """``packet`` in a Space Packet (TC, APID 0) in a TC frame (SCID 0x44, VCID 0)."""
    space = struct.pack(">HHH", 0x1000, 0xC000 | (seq & 0x3FFF), len(packet) - 1) + packet
    length = 5 + len(space) + 2
    head = struct.pack(">HHB", 0x2000 | SCID, (length - 1) & 0x3FF, seq & 0xFF)
    body = head + space
    return body + _crc16_ccitt_false(body).to_bytes(2, "big")


def fprime_frame(packet: bytes) -> bytes:
    head = b"\xde\xad\xbe\xef" + struct.pack(">I", len(packet))
    return head + packet + struct.pack(">I", zlib.crc32(packet, zlib.crc32(head)))


def _frame_fast(framing: str) -> Callable[[bytes, int], bytes]:
    """A framer for many frames: the TC CRC from a table (the loop above is too slow)."""
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else c << 1
        table.append(c & 0xFFFF)

    def crc(data: bytes) -> int:
        c = 0xFFFF
        for b in data:
            c = ((c << 8) & 0xFFFF) ^ table[(c >> 8) ^ b]
        return c

    def tc(packet: bytes, seq: int) -> bytes:
        space = struct.pack(">HHH", 0x1000, 0xC000 | (seq & 0x3FFF), len(packet) - 1) + packet
        length = 5 + len(space) + 2
        body = struct.pack(">HHB", 0x2000 | SCID, (length - 1) & 0x3FF, seq & 0xFF) + space
        return body + crc(body).to_bytes(2, "big")

    assert tc(b"\x00\x00\x00\x00\x00\x01", 3) == tc_frame(b"\x00\x00\x00\x00\x00\x01", 3)
    return tc if framing == "ccsds" else (lambda packet, _seq: fprime_frame(packet))


def run(args: argparse.Namespace) -> dict[str, Any]:
    tree = Path(args.tree).resolve()
    python = tree / ".venv" / "bin" / "python"
    port = _free_port()
    frame = _frame_fast(args.framing)
    first = 0x10000000  # far from the gateway's own opcodes (id base 0x10000 by default)
    # the frames are made before the clock starts: the bench's own CPU is not the gateway's
    frames = [frame(command_packet(first + i), i) for i in range(args.opcodes)]
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(
            [str(python), "-m", "gateway", "run", "--source", "sim", "--only", "fprime",
             "--fprime", f"tcpin:127.0.0.1:{port}", "--fprime-framing", args.framing,
             "--status-interval", "0", "--duration", str(args.seconds + args.settle + 30)],
            cwd=tree, stdout=subprocess.DEVNULL, stderr=err)
        try:
            deadline = time.monotonic() + 20
            while True:
                try:
                    sock = socket.create_connection(("127.0.0.1", port), timeout=1)
                    break
                except OSError:
                    if time.monotonic() > deadline or proc.poll() is not None:
                        raise SystemExit("the gateway did not listen") from None
                    time.sleep(0.1)
            sock.settimeout(None)
            received = [0]
            stop = threading.Event()

            def drain() -> None:
                while not stop.is_set():
                    try:
                        data = sock.recv(1 << 16)
                    except OSError:
                        return
                    if not data:
                        return
                    received[0] += len(data)

            reader = threading.Thread(target=drain, daemon=True)
            if not args.no_read:
                reader.start()
            time.sleep(1.0)  # connected, first telemetry out: the "before" figure
            err.seek(0, os.SEEK_END)
            lines_before = err.tell()
            rss_before = _rss_mib(proc.pid)
            cpu_before = _cpu_s(proc.pid)
            batches = max(1, round(args.seconds / BATCH_S))
            per = -(-len(frames) // batches)
            t0 = time.monotonic()
            for b in range(batches):
                chunk = frames[b * per:(b + 1) * per]
                if chunk:
                    sock.sendall(b"".join(chunk))
                wait = t0 + (b + 1) * BATCH_S - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            sent_s = time.monotonic() - t0
            time.sleep(0.5)
            cpu_flood = _cpu_s(proc.pid) - cpu_before
            rss_after = _rss_mib(proc.pid)
            time.sleep(args.settle)
            rss_settled = _rss_mib(proc.pid)
            stop.set()
            sock.close()
        finally:
            proc.terminate()
            proc.wait(10)
        err.seek(0)
        text = err.read()
        during = text[lines_before:]
    return {"opcodes": args.opcodes, "sent_s": sent_s, "stderr_lines": text.count(b"\n"),
            "stderr_lines_flood": during.count(b"\n"), "stderr_bytes": len(text),
            "rss_before_mib": rss_before, "rss_after_mib": rss_after,
            "rss_settled_mib": rss_settled, "cpu_s": cpu_flood,
            "cpu_us_per_command": cpu_flood / args.opcodes * 1e6,
            "downlink_bytes": received[0], "last_lines": text[-600:].decode(errors="replace")}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--opcodes", type=int, default=600_000)
    p.add_argument("--seconds", type=float, default=45.0)
    p.add_argument("--settle", type=float, default=3.0)
    p.add_argument("--framing", choices=("ccsds", "fprime"), default="ccsds")
    p.add_argument("--tree", default=str(ROOT), help="the checkout whose gateway runs")
    p.add_argument("--no-read", action="store_true", help="never read the downlink")
    args = p.parse_args()
    r = run(args)
    print(f"tree {args.tree}, framing {args.framing}")
    print(f"{r['opcodes']} distinct opcodes sent in {r['sent_s']:.1f} s")
    print(f"stderr: {r['stderr_lines']} lines ({r['stderr_lines_flood']} during the flood), "
          f"{r['stderr_bytes'] / 1e6:.2f} MB")
    print(f"RSS: {r['rss_before_mib']:.1f} MiB before, {r['rss_after_mib']:.1f} after "
          f"(+{r['rss_after_mib'] - r['rss_before_mib']:.1f}), "
          f"{r['rss_settled_mib']:.1f} after {args.settle:.0f} s more "
          f"(+{r['rss_settled_mib'] - r['rss_before_mib']:.1f})")
    print(f"CPU during the flood: {r['cpu_s']:.1f} s ({r['cpu_us_per_command']:.1f} µs per "
          f"command); downlink read: {r['downlink_bytes'] / 1e6:.1f} MB")
    print("stderr's end:\n" + r["last_lines"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
