"""Benchmark: the UAVTalk flight side as a ground station sees it — handshake time, objects
served per second, AttitudeState rate.

Runs ``aurora-gateway run --source sim --only uavtalk --uavtalk tcpin:127.0.0.1:PORT`` (the
issue's command) as a process of its own, then, per repetition, connects a minimal ground
station written with the project's codec and object definitions:

* **handshake**: TCP connect → GCSTelemetryStats(HandshakeReq) → FlightTelemetryStats
  (HandshakeAck) received → GCSTelemetryStats(Connected) → FlightTelemetryStats(Connected);
  the time from connect to Connected;
* **objects served/s**: OBJ_REQ of AttitudeState, one outstanding at a time (as the GCS's
  transactions are), ``--requests`` of them, answered OBJs per second of wall time;
* **AttitudeState rate**: the periodic AttitudeState packets per second over ``--listen-s``.

Prints medians of ``--repeat`` repetitions (and min–max); asserts nothing about time.

Run: ``.venv/bin/python tools/bench/bench_uavtalk.py [--repeat N] [--requests N]``
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from backends.uavtalk.codec import Decoder, Packet, PacketType, encode  # noqa: E402
from backends.uavtalk.objects import ObjectSet  # noqa: E402

CONNECTED, HANDSHAKE_REQ, HANDSHAKE_ACK = 3, 1, 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Gcs:
    """A minimal ground station on one TCP connection."""

    def __init__(self, port: int, objects: ObjectSet) -> None:
        self.objects = objects
        self.gcs_stats = objects.by_name("GCSTelemetryStats")
        self.flight_stats = objects.by_name("FlightTelemetryStats")
        self.attitude = objects.by_name("AttitudeState")
        self.decoder = Decoder(objects.data_length)
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def send(self, p: Packet) -> None:
        self.sock.sendall(encode(p))

    def status(self, status: int) -> None:
        self.send(Packet(PacketType.OBJ, self.gcs_stats.id, 0,
                         self.gcs_stats.pack({"Status": status})))

    def packets(self, deadline: float) -> list[Packet]:
        self.sock.settimeout(max(0.001, deadline - time.monotonic()))
        try:
            data = self.sock.recv(65536)
        except TimeoutError:
            return []
        if not data:
            raise ConnectionError("the gateway closed the connection")
        return self.decoder.feed(data)

    def flight_status(self, p: Packet) -> int | None:
        if p.type == PacketType.OBJ and p.object_id == self.flight_stats.id:
            return int(self.flight_stats.unpack(p.data)["Status"])
        return None

    def handshake(self, timeout: float = 5.0) -> float:
        start = time.perf_counter()
        deadline = time.monotonic() + timeout
        self.status(HANDSHAKE_REQ)
        sent_connected = False
        while time.monotonic() < deadline:
            for p in self.packets(deadline):
                st = self.flight_status(p)
                if st == HANDSHAKE_ACK and not sent_connected:
                    self.status(CONNECTED)
                    sent_connected = True
                elif st == CONNECTED:
                    return time.perf_counter() - start
        raise TimeoutError("no Connected within the deadline")

    def requests(self, n: int) -> float:
        """OBJ_REQ AttitudeState n times, one outstanding; answered OBJs per second."""
        req = encode(Packet(PacketType.OBJ_REQ, self.attitude.id, 0))
        answered = 0
        start = time.perf_counter()
        deadline = time.monotonic() + 30.0
        for _ in range(n):
            self.sock.sendall(req)
            got = False
            while not got and time.monotonic() < deadline:
                for p in self.packets(deadline):
                    if p.type == PacketType.OBJ and p.object_id == self.attitude.id:
                        got = True  # (a periodic one counts too: the GCS cannot tell)
            answered += got
        return answered / (time.perf_counter() - start)

    def attitude_rate(self, seconds: float) -> float:
        n = 0
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            n += sum(1 for p in self.packets(end)
                     if p.type == PacketType.OBJ and p.object_id == self.attitude.id)
        return n / seconds

    def close(self) -> None:
        self.sock.close()


def _gateway() -> str:
    exe = Path(sys.executable).with_name("aurora-gateway")
    return str(exe) if exe.exists() else (shutil.which("aurora-gateway") or "aurora-gateway")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--requests", type=int, default=2000)
    ap.add_argument("--listen-s", type=float, default=3.0)
    args = ap.parse_args()
    objects = ObjectSet.load()
    port = _free_port()
    cmd = [_gateway(), "run", "--source", "sim", "--only", "uavtalk", "--uavtalk",
           f"tcpin:127.0.0.1:{port}", "--status-interval", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            env={**os.environ})
    try:
        deadline = time.monotonic() + 15.0
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                break
            except OSError:
                if time.monotonic() > deadline or proc.poll() is not None:
                    print("the gateway did not start listening", file=sys.stderr)
                    return 1
                time.sleep(0.05)
        hs, served, rates = [], [], []
        for i in range(args.repeat):
            gcs = Gcs(port, objects)
            try:
                hs.append(gcs.handshake())
                served.append(gcs.requests(args.requests))
                rates.append(gcs.attitude_rate(args.listen_s))
            finally:
                gcs.close()
            print(f"[{i + 1}/{args.repeat}] handshake {hs[-1] * 1000:.2f} ms, "
                  f"{served[-1]:.0f} objects/s, AttitudeState {rates[-1]:.1f}/s",
                  file=sys.stderr)
    finally:
        proc.terminate()
        proc.wait(5)

    def fig(xs: list[float], scale: float = 1.0, fmt: str = ".1f") -> str:
        return (f"{statistics.median(xs) * scale:{fmt}} "
                f"({min(xs) * scale:{fmt}}–{max(xs) * scale:{fmt}})")

    shown = [cmd[0], "run", "--source", "sim", "--only", "uavtalk", "--uavtalk",
             "tcpin:127.0.0.1:PORT"]
    print(f"Command: {' '.join(shown)}")
    print(f"Machine: {os.cpu_count()} cores, Python {sys.version.split()[0]}; "
          f"medians of {args.repeat} connections (min–max)")
    print("| metric | value |")
    print("|---|---|")
    print(f"| connect → Connected (handshake) | {fig(hs, 1000, '.2f')} ms |")
    print(f"| objects served (OBJ_REQ → OBJ, one outstanding) | {fig(served, 1, '.0f')} /s |")
    print(f"| AttitudeState, periodic | {fig(rates)} /s |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
