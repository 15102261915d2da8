"""End to end, the issue's "done when": ``aurora-gateway simulate`` writes one flight to a
serial link, ``aurora-gateway run --source <link> --record FILE`` reads it, and the recording
holds exactly the frames the simulator sent, which ``aurora-gateway decode FILE`` reproduces.

The serial link, without socat (not installed):

* ``pty`` — the gateway reads the *slave* of a pty pair the test creates (``/dev/pts/N``):
  a real tty, opened and configured (termios, raw mode, flush on open) by pyserial exactly as
  a USB-serial adapter would be.  A pty's master side has no path another process could
  open, so ``simulate`` writes to ``socket://127.0.0.1:P`` (pyserial's TCP URL handler) and a
  small relay thread in the test copies every byte it receives into the master fd.
* ``tcp`` — the gateway reads ``socket://127.0.0.1:Q`` (a ser2net-style serial-over-TCP link)
  from the test's listener, and the relay copies the simulator's connection into it.

Ordering, by events and output rather than sleeps: pyserial discards what is pending when it
opens a port, so ``simulate`` starts only once the gateway has logged that its port is open;
the gateway is stopped (SIGINT) only once its status line reports every frame recorded.
Every wait has a deadline and every process is killed in ``finally``.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from helpers import Running

from gateway import recording, vehicles
from gateway.flight import FlightModel, FlightProfile
from gateway.sources.sim import flight_frames
from gateway.wire import decode_all, to_wire_dict

ROOT = Path(__file__).resolve().parents[1]
GATEWAY = [sys.executable, "-m", "gateway"]
TIMEOUT_S = 30.0
SPEED = 20.0


def expected_frames() -> list[bytes]:
    """What ``simulate --cycles 1`` sends with its defaults (10 Hz, STATUS 1 Hz, 64 bytes)."""
    return [f for _, f in flight_frames(FlightModel(FlightProfile()), 10, 1, cycles=1)]


class Relay(threading.Thread):
    """Accepts one connection on ``listener`` and copies everything it receives to
    ``forward`` until the peer closes; keeps a copy of the bytes."""

    def __init__(self, listener: socket.socket, forward: Callable[[bytes], None]) -> None:
        super().__init__(name="relay", daemon=True)
        self.listener = listener
        self.forward = forward
        self.data = bytearray()
        self.error: BaseException | None = None
        self.done = threading.Event()

    def run(self) -> None:
        try:
            conn, _ = self.listener.accept()
            with conn:
                conn.settimeout(TIMEOUT_S)
                while chunk := conn.recv(65536):
                    self.data += chunk
                    self.forward(chunk)
        except BaseException as exc:  # reported by the test
            self.error = exc
        finally:
            self.done.set()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _listener() -> socket.socket:
    srv = socket.create_server(("127.0.0.1", 0))
    srv.settimeout(TIMEOUT_S)
    return srv


@pytest.fixture(params=["pty", "tcp"])
def link(request: pytest.FixtureRequest) -> Iterator[tuple[str, Callable[[], Callable]]]:
    """(gateway source URL, connect) — ``connect()`` is called once the gateway runs and
    returns the function that delivers bytes to the gateway's end of the link."""
    if request.param == "pty":
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo or line editing before pyserial configures the port
        try:
            yield os.ttyname(slave), lambda: (lambda b: _write_all(master, b))
        finally:
            os.close(master)
            os.close(slave)
    else:
        srv = _listener()
        conns: list[socket.socket] = []

        def connect() -> Callable[[bytes], None]:
            conn, _ = srv.accept()
            conns.append(conn)
            return conn.sendall

        try:
            yield f"socket://127.0.0.1:{srv.getsockname()[1]}", connect
        finally:
            for c in conns:
                c.close()
            srv.close()


def test_simulate_into_run_records_exactly_the_frames_sent(
        tmp_path: Path, link: tuple[str, Callable[[], Callable]]) -> None:
    url, connect = link
    expected = expected_frames()
    rec_path = tmp_path / "flight.agrec"
    console_only = tmp_path / "gw.toml"
    console_only.write_text("[gateway]\nstatus_interval_s = 0.2\n\n[backends.console]\n")
    sim_in = _listener()
    gateway = simulate = None
    try:
        gateway = Running("run", "--config", str(console_only), "--source", url,
                          "--record", str(rec_path), "--duration", "60", timeout=TIMEOUT_S)
        forward = connect()  # tcp: the gateway's connection; pty: the master fd
        assert gateway.wait_line("stderr", lambda ln: f"{url} open" in ln), \
            gateway.text("stderr")
        relay = Relay(sim_in, forward)
        relay.start()
        t_start = time.time()
        simulate = Running("simulate", "--out", f"socket://127.0.0.1:{sim_in.getsockname()[1]}",
                           "--speed", str(SPEED), "--cycles", "1", timeout=TIMEOUT_S)
        assert simulate.finish(TIMEOUT_S) == 0, simulate.text("stderr")
        assert f"simulate: {len(expected)} frames written" in simulate.text("stderr")
        assert relay.done.wait(TIMEOUT_S) and relay.error is None, relay.error
        assert bytes(relay.data) == b"".join(expected)  # what the simulator sent

        def all_recorded(ln: str) -> bool:
            m = re.search(r"\| rec (\d+)$", ln)
            return m is not None and int(m.group(1)) >= len(expected)

        assert gateway.wait_line("stderr", all_recorded, 15), gateway.text("stderr")[-2000:]
        gateway.proc.send_signal(signal.SIGINT)
        assert gateway.finish(10) == 130, gateway.text("stderr")[-2000:]  # Ctrl-C: 130
        t_end = time.time()
    finally:
        for p in (simulate, gateway):
            if p is not None:
                p.kill()
        sim_in.close()

    err = gateway.text("stderr")
    assert f"{len(expected)} messages recorded" in err, err[-2000:]
    assert "Traceback" not in err
    out = gateway.text("stdout")
    assert f"*** link {url} UP" in out and "state LANDED" in out, out[-2000:]

    # The recording holds exactly the frames the simulator sent, in order, with their times.
    stats = recording.ReadStats()
    records = list(recording.read(rec_path, stats))
    assert [f for _, f in records] == expected
    assert (stats.torn_tail_bytes, stats.corrupt_skips) == (0, 0)
    times = [t for t, _ in records]
    assert times == sorted(times)
    assert t_start <= times[0] and times[-1] <= t_end
    flight_span = (len([f for f in expected if f[2] == 1]) - 1) / 10.0
    assert times[-1] - times[0] >= 0.9 * flight_span / SPEED  # paced at --speed, not dumped

    # decode reproduces them: one JSON object per frame, with the receive time.
    r = subprocess.run([*GATEWAY, "decode", str(rec_path)], cwd=ROOT, capture_output=True,
                       text=True, timeout=TIMEOUT_S)
    assert r.returncode == 0, r.stderr
    got = [json.loads(ln) for ln in r.stdout.splitlines()]
    # each frame with its source (the URL names it) and that source's vehicle
    vehicle = vehicles.derive_name(url)
    want = [{"rx_time": t, "vehicle": vehicle, "source": url,
             **json.loads(json.dumps(to_wire_dict(m)))}
            for t, m in zip(times, decode_all(b"".join(expected)), strict=True)]
    assert got == want
    assert [o["state_name"] for o in got if o["type"] == 1][-1] == "IDLE"
