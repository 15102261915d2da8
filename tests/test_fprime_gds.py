"""End to end with the real F´ ground system: ``aurora-gateway run --source sim --fprime
tcpin:…`` served to a headless ``fprime-gds`` (``-n -g none --ip-client``) started with the
dictionary ``aurora-gateway fprime-dictionary`` wrote, in both framings; fprime-gds's own
Python API (``tests/fprime_peer.py``) reads the channels it decoded and sends the gateway's
NO_OP command.  Every value is checked against the gateway's own recording of the flight,
matched by the flight computer's uptime; the command's answer is the gateway's event."""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import GATEWAY, ROOT, Running

from dialects.states import SimpleState
from gateway import recording
from gateway.model import SmUpdate
from gateway.wire import decode_all

FPRIME_GDS = str(Path(sys.executable).with_name("fprime-gds"))
SELECTION = {"ccsds": "space-packet-space-data-link", "fprime": "fprime"}
PEER = [sys.executable, str(ROOT / "tests" / "fprime_peer.py")]
FLIGHT = "Aurora.flight."


def f32(x: float) -> float:
    return float(struct.unpack(">f", struct.pack(">f", x))[0])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def recorded_updates(path: Path) -> dict[int, SmUpdate]:
    frames = b"".join(frame for _, frame in recording.read(path))
    return {m.timestamp_ms: m for m in decode_all(frames) if isinstance(m, SmUpdate)}


@pytest.fixture
def workdir() -> Iterator[Path]:
    # fprime-gds's ZMQ ipc:// paths must be short (a Unix socket path holds ~107 bytes)
    path = Path(tempfile.mkdtemp(prefix="fgds-"))
    try:
        yield path
    finally:
        shutil.rmtree(path, ignore_errors=True)


@pytest.mark.parametrize("framing", ["ccsds", "fprime"])
def test_headless_fprime_gds_shows_the_simulated_flight(framing: str, workdir: Path) -> None:
    started = time.time()
    dictionary = workdir / "dict.json"
    subprocess.run([*GATEWAY, "fprime-dictionary", "-o", str(dictionary)], cwd=ROOT,
                   check=True, timeout=30)
    port = free_port()
    flight = workdir / "flight.aur"
    zmq = [f"ipc://{workdir}/in", f"ipc://{workdir}/out"]
    values: dict[float, dict[str, list[Any]]] = defaultdict(lambda: defaultdict(list))
    ready, flown = threading.Event(), threading.Event()
    events: list[dict[str, Any]] = []
    order = ["ARMED", "BOOST", "APOGEE"]  # a whole ascent, seen from the pad

    def read_peer(peer: subprocess.Popen[str]) -> None:
        assert peer.stdout is not None
        for line in peer.stdout:
            v = json.loads(line)
            ready.set()
            if "event" in v:
                events.append(v)
            if "name" in v:
                values[v["t"]][v["name"]].append(v["value"])
                if v["name"] == FLIGHT + "State" and order and v["value"] == order[0]:
                    order.pop(0)
                    if not order:
                        flown.set()

    with contextlib.ExitStack() as stack:  # everything started is stopped, whatever happens
        gds = Running("-n", "--dictionary", str(dictionary), "--ip-client", "--ip-address",
                      "127.0.0.1", "--ip-port", str(port), "-g", "none", "--framing-selection",
                      SELECTION[framing], "--logs", str(workdir / "logs"), "--log-directly",
                      "--zmq-transport", *zmq, cmd=[FPRIME_GDS], timeout=60, group=True)
        stack.callback(gds.stop)
        # its API client joins once the GDS serves (what a ZMQ client sends before the server
        # is bound is lost); the gateway last: fprime-gds retries its connection every second
        assert gds.wait_line("stdout", lambda line: "F prime is now running" in line), \
            gds.text("stdout") + gds.text("stderr")
        peer_err = stack.enter_context((workdir / "peer.err").open("w"))
        peer = subprocess.Popen(
            [*PEER, str(dictionary), *zmq, "120", str(workdir / "peer-logs"),
             "Aurora.gateway.NO_OP"], stdout=subprocess.PIPE, stderr=peer_err, text=True,
            bufsize=1)
        reader = threading.Thread(target=read_peer, args=(peer,), daemon=True)
        reader.start()
        stack.callback(reader.join, 10)
        stack.callback(peer.wait, 10)
        stack.callback(peer.kill)
        assert ready.wait(30), (workdir / "peer.err").read_text()
        gateway = Running("run", "--only", "fprime", "--source", "sim", "--sim-speed", "10",
                          "--fprime", f"tcpin:127.0.0.1:{port}", "--fprime-framing", framing,
                          "--record", str(flight), "--status-interval", "0", timeout=60)
        stack.callback(gateway.stop)
        assert flown.wait(90), (
            f"no flight seen\ngateway: {gateway.text('stderr')[-2000:]}\n"
            f"fprime-gds: {gds.text('stdout')[-2000:]} {gds.text('stderr')[-2000:]}\n"
            f"peer: {(workdir / 'peer.err').read_text()[-2000:]}")
    # the command went up through fprime-gds (in this framing) and the gateway's event came back
    assert [e["event"] for e in events] == ["Aurora.gateway.NoOpReceived"], events
    # fprime-gds decoded nothing wrong: no checksum warnings, no rejected packets
    gds_said = gds.text("stdout") + gds.text("stderr")
    logs = "".join(p.read_text(errors="replace") for p in (workdir / "logs").rglob("*.log"))
    for bad in ("Checksum validation failed", "out of range", "Traceback", "sequence count"):
        assert bad not in gds_said + logs, bad

    updates = recorded_updates(flight)
    # every SM update's packet (the last may have been cut short when the peer was stopped)
    seen = [(t, names) for t, names in sorted(values.items())
            if FLIGHT + "Altitude" in names and FLIGHT + "SmType" in names]
    assert len(seen) >= 20, "too few SM updates reached fprime-gds"
    states = set()
    last_t = seen[-1][0]
    for t, names in seen:
        # (an update's entries can span two packets: one missing says which, and whether the
        # gateway counted a drop — what a failure under heavy load needs to be told apart)
        missing = [c for c in ("Uptime", "Altitude", "VerticalVelocity", "State", "Armed", "Roll")
                   if FLIGHT + c not in names]
        assert not missing, (f"update at t={t} (the last: {t == last_t}) lacks {missing}; "
                             f"gateway: {gateway.text('stderr')[-1500:]}")
        (uptime,) = set(names[FLIGHT + "Uptime"])
        m = updates[uptime]  # the update the gateway received with this uptime
        assert names[FLIGHT + "Altitude"] == [f32(m.altitude_m)]
        assert names[FLIGHT + "VerticalVelocity"] == [f32(m.velocity_mps)]
        assert set(names[FLIGHT + "State"]) == {SimpleState(m.state).name}
        assert set(names[FLIGHT + "Armed"]) == {m.armed}
        assert names[FLIGHT + "Roll"] == [pytest.approx(math.degrees(m.roll_rad), abs=1e-4)]
        states.add(SimpleState(m.state).name)
    assert {"BOOST", "BURNOUT", "APOGEE"} <= states
    altitudes = [names[FLIGHT + "Altitude"][0] for _, names in seen
                 if set(names[FLIGHT + "State"]) <= {"BOOST", "BURNOUT"}]
    assert altitudes == sorted(altitudes) and altitudes[-1] > altitudes[0], "not climbing"
    # the time tags are the flight computer's, spaced as it stamped them (at 10x speed its
    # uptime runs ahead of the workstation's clock, from where it was first anchored)
    for (t0, n0), (t1, n1) in itertools.pairwise(seen):
        stamped = (n1[FLIGHT + "Uptime"][0] - n0[FLIGHT + "Uptime"][0]) / 1000
        assert t1 - t0 == pytest.approx(stamped, abs=1e-5)
    assert seen[0][0] >= started
