"""Two rockets through one gateway, seen by every view (issue 22, item 3): two TCP feeds of
Aurora wire frames (``socket://`` sources alpha and beta; alpha near 100 m, beta near
500 m) into ``aurora-gateway run`` with the HTTP and Foxglove backends, and into
``aurora-gateway monitor``.  Read back with real clients: ``http.client`` for
``/status.json`` and ``/metrics`` (parsed by prometheus-client), the Foxglove WebSocket
client of ``test_foxglove_backend``; each view must keep each vehicle's values apart."""

from __future__ import annotations

import http.client
import json
import re
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers import Running, wait_for
from prometheus_client.parser import text_string_to_metric_families
from test_foxglove_backend import foxglove_client, topics

from gateway import wire
from gateway.model import SmUpdate

#: each vehicle's altitudes: base + [0, SPAN)
BASE_M = {"alpha": 100.0, "beta": 500.0}
SPAN_M = 5.0
CONSOLE = Path(sys.executable).with_name("aurora-gateway")


def feed(srv: socket.socket, base: float, stop: threading.Event) -> None:
    """Accept the gateway's connection, then send an SM_UPDATE every 20 ms until ``stop``."""
    srv.settimeout(20)
    try:
        conn, _ = srv.accept()
    except OSError:
        return
    with conn:
        i = 0
        while not stop.is_set():
            msg = SmUpdate(timestamp_ms=20 * i, state=2, armed=True, sm_type=0,
                           altitude_m=base + SPAN_M * (i % 50) / 50, acceleration_mps2=1.0,
                           accel_vert_mps2=1.0, velocity_mps=3.0, roll_rad=0.0,
                           pitch_rad=0.0, yaw_rad=0.0)
            try:
                conn.sendall(wire.encode(msg))
            except OSError:
                return
            i += 1
            stop.wait(0.02)  # pacing the simulated rockets, not synchronising the test


@pytest.fixture
def feeds() -> Iterator[list[str]]:
    """``NAME=socket://127.0.0.1:P`` of the two rockets' feeds."""
    stop = threading.Event()
    servers = {name: socket.create_server(("127.0.0.1", 0)) for name in BASE_M}
    threads = [threading.Thread(target=feed, args=(srv, BASE_M[name], stop), daemon=True)
               for name, srv in servers.items()]
    for t in threads:
        t.start()
    try:
        yield [f"{name}=socket://127.0.0.1:{srv.getsockname()[1]}"
               for name, srv in servers.items()]
    finally:
        stop.set()
        for srv in servers.values():
            srv.close()
        for t in threads:
            t.join(5)


def get(port: int, path: str) -> bytes:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    try:
        conn.request("GET", path)
        r = conn.getresponse()
        assert r.status == 200
        return r.read()
    finally:
        conn.close()


def logged_port(gw: Running, pattern: str) -> int:
    assert gw.wait_line("stderr", lambda ln: re.search(pattern, ln) is not None), \
        gw.text("stderr")[-2000:]
    m = re.search(pattern, gw.text("stderr"))
    assert m is not None
    return int(m.group(1))


def in_range(name: str, alt: float | None) -> bool:
    return alt is not None and BASE_M[name] <= alt < BASE_M[name] + SPAN_M


def test_status_json_metrics_and_foxglove_keep_each_vehicle(feeds: list[str]) -> None:
    args = ["run", "--only", "http", "--only", "foxglove", "--http", "127.0.0.1:0",
            "--foxglove", "127.0.0.1:0", "--status-interval", "0"]
    for url in feeds:
        args += ["--source", url]
    gw = Running(*args)
    try:
        http_port = logged_port(gw, r"status page on http://127\.0\.0\.1:(\d+)/")
        fox_port = logged_port(gw, r"Foxglove WebSocket server on ws://127\.0\.0\.1:(\d+)")

        status: dict = {}

        def both_heard() -> bool:
            status.update(json.loads(get(http_port, "/status.json")))
            return set(status["vehicles"]) == set(BASE_M)

        assert wait_for(both_heard, timeout=15), status
        assert list(status["vehicles"]) == ["alpha", "beta"]  # the sources' order
        for name, entry in status["vehicles"].items():
            assert entry["name"] == name and entry["source"] == name
            assert in_range(name, entry["altitude_m"]), (name, entry)
            assert in_range(name, entry["max_altitude_m"]) and entry["link"] is True
            assert entry["state"] == "BOOST"
        assert status["vehicle"]["name"] == "alpha"  # the first configured source's
        assert status["link"]["sources"] == {"alpha": True, "beta": True}

        samples = {}
        for family in text_string_to_metric_families(get(http_port, "/metrics").decode()):
            for s in family.samples:
                if s.name == "aurora_altitude_meters":
                    samples[s.labels["vehicle"]] = s.value
        assert set(samples) == set(BASE_M)
        for name, alt in samples.items():
            assert in_range(name, alt), (name, alt)

        with foxglove_client(fox_port) as client:
            client.wait_topics(topics("alpha") | topics("beta"))
            client.subscribe_all()
            got = client.read({f"/aurora/{name}/altitude": 10 for name in BASE_M})
        for name in BASE_M:
            alts = [json.loads(data)["altitude_m"]
                    for _, data in got[f"/aurora/{name}/altitude"]]
            assert all(in_range(name, a) for a in alts), (name, alts)

        gw.proc.send_signal(signal.SIGINT)
        assert gw.finish(15) == 130, gw.text("stderr")[-2000:]  # Ctrl-C: 130 (gateway.exits)
    finally:
        gw.kill()
    err = gw.text("stderr")
    assert "Traceback" not in err
    for name in BASE_M:  # the stop report: each vehicle's own flight
        m = re.search(rf"flight {name}: .*max altitude ([\d.]+) m", err)
        assert m is not None and in_range(name, float(m.group(1))), err[-1500:]


def test_the_monitor_prints_a_line_per_vehicle(feeds: list[str]) -> None:
    args = [str(CONSOLE), "monitor", "--refresh", "0.2", "--duration", "3"]
    for url in feeds:
        args += ["--source", url]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=30, check=False)
    assert proc.returncode == 0, proc.stderr
    lines = [dict(tok.split("=", 1) for tok in line.split(" "))
             for line in proc.stdout.splitlines()]
    heard = [f for f in lines if f["alt_m"] != "–"]
    assert {f["vehicle"] for f in heard} == set(BASE_M), proc.stdout[-2000:]
    names = [f["vehicle"] for f in lines]
    assert names[-2:] == ["alpha", "beta"]  # each refresh: a line each, the sources' order
    for f in heard:
        assert in_range(f["vehicle"], float(f["alt_m"])), f
        assert in_range(f["vehicle"], float(f["max_alt_m"])), f
