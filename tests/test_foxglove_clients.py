"""Foxglove clients of both generations, and what clients can make the backend do.

* the npm ``@foxglove/ws-protocol`` client (the older generation: it offers only
  ``foxglove.websocket.v1``), run with node against a real ``aurora-gateway run`` of a
  simulated flight, receives ``/aurora/sim/altitude`` (skipped, saying why, without node and
  npm or when npm cannot install it);
* the handshake rewrite on real request and answer heads;
* the relay's limits (a client cap, a client that stops reading is cut) and its log: clients
  that come and go, leave abruptly or offer a wrong name are at most one line per interval,
  never an ERROR (foxglove-sdk's own per-client lines are kept out and counted).
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import math
import os
import re
import shutil
import socket
import struct
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from helpers import Running, wait_for
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect
from websockets.typing import Subprotocol

from backends.foxglove import handshake, sdklog
from backends.foxglove.backend import FoxgloveBackend
from backends.foxglove.options import FoxgloveOptions
from gateway.backend import Outcome
from gateway.dispatcher import Dispatcher
from gateway.io.burstlog import BURST_LOG_S
from gateway.model import SmUpdate

HERE = Path(__file__).resolve().parent
DEADLINE_S = 10.0
#: The npm client's versions (the newest at the time of writing; the protocol is frozen).
WS_PROTOCOL_VERSION = "0.8.0"
WS_VERSION = "8.23.0"


# --- the npm client ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def npm_client(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A directory with @foxglove/ws-protocol and ws installed, and our client script."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("the @foxglove/ws-protocol client needs node and npm "
                    "(Debian/Ubuntu: apt-get install nodejs npm)")
    where = tmp_path_factory.mktemp("npm-client")
    (where / "package.json").write_text('{"private": true}\n')
    try:
        proc = subprocess.run(
            [npm, "install", "--no-audit", "--no-fund", "--loglevel=error",
             f"@foxglove/ws-protocol@{WS_PROTOCOL_VERSION}", f"ws@{WS_VERSION}"],
            cwd=where, capture_output=True, text=True, timeout=300, check=False)
    except subprocess.TimeoutExpired:
        pytest.skip("npm install @foxglove/ws-protocol took over 300 s (no registry?)")
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        pytest.skip(f"npm cannot install @foxglove/ws-protocol (no registry?): {last}")
    shutil.copy(HERE / "foxglove_ws_client.js", where)
    return where


def test_the_npm_ws_protocol_client_receives_the_altitude_of_a_flight(
        npm_client: Path) -> None:
    """``aurora-gateway run --source sim --foxglove …``: the npm client, offering only
    foxglove.websocket.v1, is served under that name, sees the vehicle's topics and receives
    /aurora/sim/altitude as the simulated rocket climbs."""
    gateway = Running("run", "--only", "foxglove", "--source", "sim", "--sim-speed", "10",
                      "--foxglove", "127.0.0.1:0", "--duration", "60")
    try:
        pattern = re.compile(r"Foxglove WebSocket server on ws://127\.0\.0\.1:(\d+)")
        assert gateway.wait_line("stderr", lambda ln: pattern.search(ln) is not None), \
            gateway.text("stderr")
        match = pattern.search(gateway.text("stderr"))
        assert match is not None
        url = f"ws://127.0.0.1:{match.group(1)}"
        # 400 updates at 100 Hz (the simulated 10 Hz, ten times faster): the pad, the launch
        # (15 s simulated) and the climb
        proc = subprocess.run(["node", "foxglove_ws_client.js", url, "/aurora/sim/altitude",
                               "400", "30"], cwd=npm_client, capture_output=True, text=True,
                              timeout=60, check=False)
        assert proc.returncode == 0, proc.stderr
        lines = [json.loads(ln) for ln in proc.stdout.splitlines()]
        assert lines[0] == {"subprotocol": handshake.LEGACY}
        topics = {t for ln in lines for t in ln.get("topics", ())}
        assert {f"/aurora/sim/{leaf}" for leaf in ("altitude", "state", "attitude")} <= topics
        data = [ln["data"] for ln in lines if "data" in ln]
        assert len(data) == 400
        stamps = [d["timestamp_ms"] for d in data]
        assert stamps == sorted(stamps) and len(set(stamps)) == 400  # each update once
        assert max(d["altitude_m"] for d in data) > 10.0  # it flew
        assert all(int(ln["timestamp"]) > 0 for ln in lines if "timestamp" in ln)
        assert gateway.wait_line(
            "stderr", lambda ln: "client connected: 127.0.0.1:" in ln
            and handshake.LEGACY in ln)
    finally:
        assert gateway.stop() == 0
    assert "ERROR" not in gateway.text("stderr")


# --- the handshake rewrite --------------------------------------------------------------------

def _request(*protocol_lines: str) -> bytes:
    return ("GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\n"
            "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
            + "".join(f"{line}\r\n" for line in protocol_lines)
            + "Sec-WebSocket-Version: 13").encode()


def test_the_offered_names_are_read_from_every_protocol_line() -> None:
    assert handshake.offered(_request("Sec-WebSocket-Protocol: foxglove.websocket.v1")) == [
        handshake.LEGACY]
    both = _request("sec-websocket-protocol: foxglove.websocket.v1 , x",
                    "Sec-WebSocket-Protocol:foxglove.sdk.v1")
    assert handshake.offered(both) == [handshake.LEGACY, "x", handshake.SDK]
    assert handshake.served_as(handshake.offered(both)) == handshake.SDK
    assert handshake.served_as(["Foxglove.Websocket.V1"]) is None  # names are exact
    assert handshake.offered(_request()) == []


def test_a_legacy_request_and_its_answer_are_renamed_and_nothing_else() -> None:
    request = _request("Sec-WebSocket-Protocol: foxglove.websocket.v1, other")
    renamed = handshake.to_sdk(request)
    assert handshake.offered(renamed) == [handshake.SDK]
    keep = [ln for ln in request.split(b"\r\n") if not ln.lower().startswith(b"sec-websocket-p")]
    assert [ln for ln in renamed.split(b"\r\n")
            if not ln.lower().startswith(b"sec-websocket-p")] == keep
    answer = (b"HTTP/1.1 101 Switching Protocols\r\nconnection: Upgrade\r\nupgrade: websocket"
              b"\r\nsec-websocket-accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n"
              b"sec-websocket-protocol: foxglove.sdk.v1")
    legacy = handshake.to_legacy(answer)
    assert handshake.offered(legacy) == [handshake.LEGACY]
    assert b"sec-websocket-accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=" in legacy
    assert handshake.status(legacy) == 101
    refusal = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0"
    assert handshake.to_legacy(refusal) == refusal and handshake.status(refusal) == 400
    assert handshake.status(b"junk") == 0


# --- limits and the log -------------------------------------------------------------------------

def _handshake(port: int, protocol: str = handshake.SDK, rcvbuf: int = 0) -> socket.socket:
    """A raw client: the opening handshake done, the answer head read."""
    sock = socket.socket()
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.settimeout(DEADLINE_S)
    sock.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(f"GET / HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                 f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                 f"Sec-WebSocket-Protocol: {protocol}\r\n\r\n".encode())
    head = b""
    while b"\r\n\r\n" not in head:
        chunk = sock.recv(1)
        assert chunk, head
        head += chunk
    assert handshake.status(head) == 101, head
    return sock


def _reset(sock: socket.socket) -> None:
    """Leave abruptly: a reset, no closing handshake (a browser tab killed, a cable pulled)."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


def test_clients_coming_and_going_are_one_line_per_interval_and_never_an_error(
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0))
    backend.init()
    started = time.monotonic()
    try:
        for i in range(20):  # left abruptly, closed properly, never finished its request
            sock = _handshake(backend.port, (handshake.SDK, handshake.LEGACY)[i % 2])
            _reset(sock)
            with connect(f"ws://127.0.0.1:{backend.port}", open_timeout=DEADLINE_S,
                         subprotocols=[Subprotocol(handshake.SDK)]):
                pass
            with socket.create_connection(("127.0.0.1", backend.port)) as junk:
                junk.sendall(b"GET / HTTP/1.1\r\n")
            with pytest.raises(InvalidStatus), connect(
                    f"ws://127.0.0.1:{backend.port}", open_timeout=DEADLINE_S,
                    subprotocols=[Subprotocol("nope")]):
                pass
        assert wait_for(lambda: backend.stats()["connections"] == 0)
        s = backend.stats()
        assert (s["served_sdk"], s["served_legacy"], s["handshakes_refused"]) == (30, 10, 20)
    finally:
        backend.close()
    # each kind: its first line, then one with the count per BURST_LOG_S while it lasts
    most = 1 + math.ceil((time.monotonic() - started) / BURST_LOG_S)
    records = [r for r in caplog.records if r.name.startswith(("foxglove", "backends"))]
    assert [r.getMessage() for r in records if r.levelno >= logging.ERROR] == []
    relay_lines = [r.getMessage() for r in records if r.name == "backends.foxglove.relay"]
    for kind in ("client connected", "client left", "handshake refused"):
        assert 1 <= sum(kind in line for line in relay_lines) <= most, relay_lines
    assert not [r for r in records if r.name.startswith("foxglove.websocket")
                and sdklog.kind_of(r.getMessage()) is not None]


def test_the_sdks_per_client_lines_are_kept_out_and_counted(
        caplog: pytest.LogCaptureFixture) -> None:
    """Through the SDK's own loggers (as pyo3-log hands its records over; whether the SDK
    logs at all depends on its level, fixed at its first use in the process)."""
    caplog.set_level(logging.INFO)
    sdklog.install()
    sdklog.take_counts()
    server = logging.getLogger("foxglove.websocket.server")
    poller = logging.getLogger("foxglove.websocket.connected_client.poller")
    for _ in range(50):
        server.error("Dropping client 127.0.0.1:40000: handshake failed")
        poller.error("Error receiving from client 127.0.0.1:40002: IO error: Connection reset "
                     "by peer (os error 104)")
        logging.getLogger("foxglove.websocket.connected_client").error(
            "Invalid message from 127.0.0.1:40004: expected value at line 1 column 1")
        logging.getLogger("foxglove.websocket.connected_client.send_lossy").info(
            "outbox for client 127.0.0.1:40006 full")
    server.error("Server does not support time capability")  # not a client's: it passes
    assert [r.getMessage() for r in caplog.records if r.name.startswith("foxglove")] == [
        "Server does not support time capability"]
    counts = dict(sdklog._FILTER.counts)
    assert counts == {"connection": 100, "bad_messages": 50, "dropped_slow": 50}
    assert sdklog.summary(counts) == ("50 client messages the SDK could not use, "
                                      "50 messages dropped for slow clients")
    caplog.clear()
    FoxgloveBackend()._log_sdk_lines()  # what the backend logs of them, once per interval
    FoxgloveBackend()._log_sdk_lines()  # (nothing new: no line)
    assert [r.getMessage() for r in caplog.records] == [
        "foxglove: in the last 10 s: 50 client messages the SDK could not use, 50 messages "
        "dropped for slow clients"]
    assert sdklog.take_counts() == {}
    caplog.clear()
    caplog.set_level(logging.DEBUG, logger=poller.name)  # asked for: they pass, as DEBUG
    poller.info("Connection closed by client 127.0.0.1:40002")
    assert [(r.levelno, r.getMessage()) for r in caplog.records] == [
        (logging.DEBUG, "Connection closed by client 127.0.0.1:40002")]


def test_clients_past_the_cap_are_refused_and_counted() -> None:
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0, max_clients=2))
    backend.init()
    try:
        kept = [_handshake(backend.port) for _ in range(2)]
        with socket.create_connection(("127.0.0.1", backend.port), timeout=DEADLINE_S) as s:
            s.sendall(_request(f"Sec-WebSocket-Protocol: {handshake.SDK}") + b"\r\n\r\n")
            answer = b""
            while chunk := s.recv(4096):
                answer += chunk
        assert answer.startswith(b"HTTP/1.1 503 ")
        assert backend.stats()["clients_refused"] == 1
        for sock in kept:
            sock.close()
        assert wait_for(lambda: backend.stats()["connections"] == 0)
        with connect(f"ws://127.0.0.1:{backend.port}", open_timeout=DEADLINE_S,
                     subprotocols=[Subprotocol(handshake.SDK)]) as ws:
            assert ws.subprotocol == handshake.SDK  # a slot is free again
    finally:
        backend.close()


def _subscribe_all(sock: socket.socket, count: int) -> None:
    """Read the advertisements until ``count`` channels, then subscribe to each (a masked
    text frame, as a client must send)."""
    channels: list[dict[str, Any]] = []
    buf = b""
    while len(channels) < count:
        buf += sock.recv(65536)
        while len(buf) >= 2:
            n, at = buf[1] & 0x7F, 2
            if n == 126:
                n, at = struct.unpack_from(">H", buf, 2)[0], 4
            elif n == 127:
                n, at = struct.unpack_from(">Q", buf, 2)[0], 10
            if len(buf) < at + n:
                break
            payload, buf = buf[at:at + n], buf[at + n:]
            op = json.loads(payload)
            if op["op"] == "advertise":
                channels.extend(op["channels"])
    text = json.dumps({"op": "subscribe", "subscriptions": [
        {"id": i, "channelId": ch["id"]} for i, ch in enumerate(channels)]}).encode()
    mask = os.urandom(4)
    head = bytes([0x81]) + (bytes([0x80 | 126]) + struct.pack(">H", len(text))
                            if len(text) >= 126 else bytes([0x80 | len(text)]))
    sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(text)))


def test_a_client_that_stops_reading_is_cut() -> None:
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0, client_timeout_s=0.3,
                                              backlog=16))
    dispatcher = Dispatcher([backend])
    assert dispatcher.start() == []
    try:
        update = SmUpdate(1000, 2, True, 0, 12.5, -9.8, 0.5, 3.0, 0.1, 0.2, 0.3)
        assert dispatcher.dispatch(update) == Outcome.ACCEPTED
        assert backend.wait_idle(DEADLINE_S)
        sock = _handshake(backend.port, rcvbuf=4096)
        _subscribe_all(sock, 1 + 6)
        assert backend.wait_subscriptions(7, DEADLINE_S)

        def flooded() -> bool:  # (the relay's socket buffers fill first: a few MB)
            for _ in range(500):
                dispatcher.dispatch(update)
            backend.wait_idle(DEADLINE_S)
            return backend.stats()["clients_cut_stalled"] == 1
        assert wait_for(flooded, DEADLINE_S * 3)
        assert wait_for(lambda: backend.stats()["connections"] == 0)
        sock.close()
    finally:
        dispatcher.close()


def test_a_request_left_incomplete_is_cut_and_a_huge_one_refused() -> None:
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0, client_timeout_s=0.3))
    backend.init()
    try:
        with socket.create_connection(("127.0.0.1", backend.port), timeout=DEADLINE_S) as slow:
            slow.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n")  # and nothing more
            assert wait_for(lambda: backend.stats()["clients_cut_partial"] == 1)
            with contextlib.suppress(ConnectionResetError):  # (a cut is a reset)
                assert slow.recv(100) == b""
        with socket.create_connection(("127.0.0.1", backend.port), timeout=DEADLINE_S) as big:
            big.sendall(b"GET / HTTP/1.1\r\n" + b"X-Junk: " + b"a" * handshake.MAX_HEAD)
            answer = b""
            while chunk := big.recv(4096):
                answer += chunk
            assert answer.startswith(b"HTTP/1.1 431 ")
        assert backend.stats()["handshakes_refused"] == 1
        assert wait_for(lambda: backend.stats()["connections"] == 0)
    finally:
        backend.close()
