"""Routing between endpoints, as mavlink-router does it, with real pymavlink peers on UDP, TCP
and a serial port (a pty pair)."""

from __future__ import annotations

import contextlib
import itertools
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest
from helpers import wait_for
from mavlink_peer import MavPeer, running_backend, upstream_dialect

WAIT = 10.0
dev = upstream_dialect()


class StreamPeer:
    """A pymavlink peer on a byte stream (a TCP socket or a pty master fd)."""

    def __init__(self, sysid: int, compid: int, *, sock: socket.socket | None = None,
                 fd: int | None = None) -> None:
        self.mav = dev.MAVLink(None, sysid, compid)
        self.mav.robust_parsing = True
        self.sock, self.fd = sock, fd
        self.raw = bytearray()
        self.received: list[Any] = []
        self.cond = threading.Condition()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._rx, daemon=True)
        self.thread.start()

    def _read(self) -> bytes | None:
        if self.sock is not None:
            try:
                return self.sock.recv(65536)
            except TimeoutError:
                return None
            except OSError:
                return b""
        r, _, _ = select.select([self.fd], [], [], 0.05)
        if not r:
            return None
        try:
            return os.read(self.fd, 65536)  # type: ignore[arg-type]
        except OSError:
            return b""

    def _rx(self) -> None:
        while not self.stop.is_set():
            data = self._read()
            if data is None:
                continue
            if not data:
                return
            msgs = self.mav.parse_buffer(data) or []
            with self.cond:
                self.raw += data
                self.received += [m for m in msgs if m.get_type() != "BAD_DATA"]
                self.cond.notify_all()

    def send(self, msg: Any) -> bytes:
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self.send_raw(buf)
        return buf

    def send_raw(self, data: bytes) -> None:
        if self.sock is not None:
            self.sock.sendall(data)
        else:
            os.write(self.fd, data)  # type: ignore[arg-type]

    def wait(self, pred: Any, timeout: float = WAIT) -> list[Any]:
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                found = [m for m in self.received if pred(m)]
                if found or time.monotonic() > deadline:
                    return found
                self.cond.wait(0.1)

    def close(self) -> None:
        self.stop.set()
        if self.sock is not None:
            with contextlib.suppress(OSError):
                self.sock.close()
        self.thread.join(1.0)


def heartbeat(t: int = dev.MAV_TYPE_GCS) -> Any:
    return dev.MAVLink_heartbeat_message(t, dev.MAV_AUTOPILOT_INVALID, 0, 0, 4, 3)


def text(s: str) -> Any:
    return dev.MAVLink_statustext_message(6, s.encode(), 0, 0)


def src(m: Any) -> tuple[int, int]:
    return m.get_srcSystem(), m.get_srcComponent()


backend = running_backend


def test_three_endpoints_route_like_mavlink_router() -> None:
    gcs = MavPeer(255, 190)  # on udpout: like QGC
    with backend("udpin:127.0.0.1:0", f"udpout:127.0.0.1:{gcs.port}", "tcpin:127.0.0.1:0",
                 heartbeat_hz=5) as b:
        ep_in, _, ep_tcp = b.endpoints
        veh = MavPeer(7, 1, dest=ep_in.address)  # an autopilot on udpin
        tcp = StreamPeer(42, 1, sock=socket.create_connection(ep_tcp.address, timeout=WAIT))
        tcp.sock.settimeout(0.05)  # type: ignore[union-attr]
        try:
            assert gcs.wait_for("HEARTBEAT", timeout=WAIT)
            veh_hb = veh.send(heartbeat(dev.MAV_TYPE_QUADROTOR))
            gcs.send(heartbeat())
            tcp.send(heartbeat(dev.MAV_TYPE_ONBOARD_CONTROLLER))
            # everyone hears everyone else's broadcasts, and the rocket (1/1)
            assert gcs.wait_for("HEARTBEAT", lambda m: src(m) == (7, 1), timeout=WAIT)
            assert gcs.wait_for("HEARTBEAT", lambda m: src(m) == (42, 1), timeout=WAIT)
            assert tcp.wait(lambda m: m.get_type() == "HEARTBEAT" and src(m) == (7, 1))
            assert tcp.wait(lambda m: m.get_type() == "HEARTBEAT" and src(m) == (255, 190))
            assert veh.wait_for("HEARTBEAT", lambda m: src(m) == (255, 190), timeout=WAIT)
            assert veh.wait_for("HEARTBEAT", lambda m: src(m) == (42, 1), timeout=WAIT)
            for peer in (gcs, veh):
                assert peer.wait_for("HEARTBEAT", lambda m: src(m) == (1, 1), timeout=WAIT)
            assert tcp.wait(lambda m: m.get_type() == "HEARTBEAT" and src(m) == (1, 1))
            # forwarded as the bytes that arrived, not re-encoded
            assert veh_hb in gcs.raw_received
            assert veh_hb in bytes(tcp.raw)

            # targeted: to the vehicle only, to the TCP system only, to nobody
            gcs.command((7, 1), dev.MAV_CMD_NAV_TAKEOFF, 1)
            gcs.command((42, 0), dev.MAV_CMD_DO_SET_MODE, 2)
            gcs.send(dev.MAVLink_param_request_list_message(99, 1))
            # an id no dialect here knows, and a corrupted frame, from the vehicle
            unknown = (bytes([0xFD, 3, 0, 0, veh.mav.seq, 7, 1]) + (50500).to_bytes(3, "little")
                       + b"xyz" + b"\x01\x02")
            veh.mav.seq += 1
            veh.send_raw(unknown)
            bad = bytearray(veh.pack(text("corrupt")))
            bad[-3] ^= 0xFF
            veh.send_raw(bytes(bad))
            veh.mav.seq = (veh.mav.seq + 4) % 256  # four frames "lost" on the way (+ the bad)
            # markers: whatever was routed before them has arrived when they have
            gcs.send(text("gcs-done"))
            veh.send(text("veh-done"))
            for marker in ("gcs-done", "veh-done"):
                assert tcp.wait(lambda m, s=marker: getattr(m, "text", "") == s)
            assert gcs.wait_for("STATUSTEXT", lambda m: m.text == "veh-done", timeout=WAIT)
            assert veh.wait_for("STATUSTEXT", lambda m: m.text == "gcs-done", timeout=WAIT)

            takeoffs = veh.messages("COMMAND_LONG")
            assert [(c.command, c.target_system) for c in takeoffs] == [
                (dev.MAV_CMD_NAV_TAKEOFF, 7)]
            tcp_cmds = [m for m in tcp.received if m.get_type() == "COMMAND_LONG"]
            assert [(c.command, c.target_system) for c in tcp_cmds] == [
                (dev.MAV_CMD_DO_SET_MODE, 42)]
            assert veh.messages("PARAM_REQUEST_LIST") == []
            assert not any(m.get_type() == "PARAM_REQUEST_LIST" for m in tcp.received)
            assert unknown in gcs.raw_received and unknown in bytes(tcp.raw)
            assert not any(getattr(m, "text", "") == "corrupt" for m in gcs.messages())
            # never back where it came from
            assert not veh.messages(where=lambda m: src(m) == (7, 1))
            assert not gcs.messages(where=lambda m: src(m) == (255, 190))
            assert not [m for m in tcp.received if src(m) == (42, 1)]
            # each link has its own sequence numbers: ours arrive at the GCS without gaps
            own = [m.get_seq() for m in gcs.messages(where=lambda m: src(m) == (1, 1))]
            assert all((b_ - a_) % 256 == 1 for a_, b_ in itertools.pairwise(own))

            st = b.stats()
            eps = st["endpoints"]
            ins = eps[ep_in.name]
            assert ins["crc_errors"] == 1 and ins["unknown_ids"] == 1
            assert ins["seq_lost"] == 5
            assert ins["peers"] == 1 and ins["systems"] == ["7/1"]
            assert eps[ep_tcp.name]["clients"] == 1
            assert st["router"]["unroutable"] >= 1
            assert st["router"]["forwarded"] >= 10
        finally:
            veh.close()
            tcp.close()
            gcs.close()


def listener(port: int = 0) -> socket.socket:
    """A TCP server socket on 127.0.0.1 (``port`` again after a restart)."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", port))
    srv.listen(1)
    srv.settimeout(WAIT)
    return srv


def down_and_retried(b: Any, name: str) -> Callable[[], bool]:
    """The endpoint has seen its port go and has failed to reopen it at least once."""
    def check() -> bool:
        st = b.stats()["endpoints"][name]
        return st["link"] == 0 and st["connect_failures"] >= 1
    return check


def test_a_tcp_client_endpoint_reconnects_when_dropped_and_when_the_server_restarts() -> None:
    srv = listener()
    port = srv.getsockname()[1]
    name = f"tcp:127.0.0.1:{port}"
    try:
        with backend(name, heartbeat_hz=5) as b:
            for round_ in range(3):
                conn, _ = srv.accept()
                conn.settimeout(0.05)
                peer = StreamPeer(255, 190, sock=conn)
                try:
                    assert peer.wait(lambda m: m.get_type() == "HEARTBEAT" and src(m) == (1, 1))
                    peer.send(dev.MAVLink_command_long_message(
                        1, 1, dev.MAV_CMD_REQUEST_MESSAGE, 0, dev.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                        0, 0, 0, 0, 0, 0))
                    assert peer.wait(lambda m: m.get_type() == "AUTOPILOT_VERSION")
                finally:
                    peer.close()  # the server drops the gateway; it must come back
                if round_ == 1:  # then the server itself goes away for a while
                    srv.close()
                    assert wait_for(down_and_retried(b, name), WAIT)
                    srv = listener(port)
            stats = b.stats()["endpoints"][name]
    finally:
        srv.close()
    assert stats["connects"] == 3 and stats["disconnects"] >= 2
    assert stats["connect_failures"] >= 1


def test_a_serial_port_that_vanishes_is_reopened() -> None:
    """``serial:socket://…``: a radio behind a TCP serial server (ser2net) that goes away and
    comes back; traffic flows both ways again, through the same endpoint."""
    srv = listener()
    port = srv.getsockname()[1]
    name = f"serial:socket://127.0.0.1:{port}"
    gcs = MavPeer(255, 190)
    try:
        with backend(name, f"udpout:127.0.0.1:{gcs.port}", heartbeat_hz=5) as b:
            for round_ in range(2):
                conn, _ = srv.accept()
                conn.settimeout(0.05)
                radio = StreamPeer(9, 1, sock=conn)
                try:
                    assert radio.wait(lambda m: m.get_type() == "HEARTBEAT" and src(m) == (1, 1))
                    hb = radio.send(heartbeat(dev.MAV_TYPE_QUADROTOR))  # a vehicle behind it
                    assert gcs.wait_until(lambda b_=hb: b_ in gcs.raw_received, WAIT)
                    gcs.command((9, 1), dev.MAV_CMD_NAV_TAKEOFF, round_ + 1)
                    assert radio.wait(lambda m, r=round_: m.get_type() == "COMMAND_LONG"
                                      and m.target_system == 9 and m.param1 == r + 1)
                finally:
                    radio.close()
                if round_ == 0:
                    srv.close()  # the port vanishes (the server is gone), then comes back
                    assert wait_for(down_and_retried(b, name), WAIT)
                    srv = listener(port)
            stats = b.stats()["endpoints"][name]
    finally:
        srv.close()
        gcs.close()
    assert stats["connects"] == 2 and stats["disconnects"] >= 1
    assert stats["connect_failures"] >= 1


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pty pair")
def test_a_serial_radio_is_an_endpoint_too() -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    gcs = MavPeer(255, 190)
    radio = StreamPeer(9, 1, fd=master)
    try:
        with backend(f"serial:{path},57600", f"udpout:127.0.0.1:{gcs.port}", heartbeat_hz=5):
            assert radio.wait(lambda m: m.get_type() == "HEARTBEAT" and src(m) == (1, 1))
            hb = radio.send(heartbeat(dev.MAV_TYPE_QUADROTOR))  # a vehicle behind the radio
            assert gcs.wait_for("HEARTBEAT", lambda m: src(m) == (9, 1), timeout=WAIT)
            assert hb in gcs.raw_received
            gcs.command((9, 1), dev.MAV_CMD_NAV_TAKEOFF, 1)
            assert radio.wait(lambda m: m.get_type() == "COMMAND_LONG" and m.target_system == 9)
    finally:
        radio.close()
        gcs.close()
        os.close(slave)
        os.close(master)


def test_routing_can_be_switched_off() -> None:
    gcs = MavPeer(255, 190)
    try:
        with backend("udpin:127.0.0.1:0", f"udpout:127.0.0.1:{gcs.port}", route=False) as b:
            veh = MavPeer(7, 1, dest=b.endpoints[0].address)
            try:
                veh.send(heartbeat(dev.MAV_TYPE_QUADROTOR))
                veh.send(text("marker"))
                assert veh.wait_for("HEARTBEAT", lambda m: src(m) == (1, 1), timeout=WAIT)
                # (the ground station answers to where our first datagram came from)
                assert gcs.wait_for("HEARTBEAT", lambda m: src(m) == (1, 1), timeout=WAIT)
                gcs.send(heartbeat())
                name = b.endpoints[0].name
                assert gcs.wait_until(
                    lambda: b.stats()["endpoints"][name]["rx_frames"] == 2, WAIT)
                gcs.send(text("gcs-marker"))
                assert gcs.wait_until(lambda: b.stats()["endpoints"][
                    f"udpout:127.0.0.1:{gcs.port}"]["rx_frames"] == 2, WAIT)
            finally:
                veh.close()
        assert not gcs.messages(where=lambda m: src(m) == (7, 1))
    finally:
        gcs.close()


def test_a_tcp_client_that_stops_reading_loses_whole_frames_and_holds_up_nothing() -> None:
    """A bounded queue per client: once its socket is full, frames for it are dropped (whole,
    counted) while the loop carries on serving the others; when it reads again, what it gets
    is whole frames, never one cut by a partial write."""
    with backend("udpin:127.0.0.1:0", "tcpin:127.0.0.1:0", heartbeat_hz=10,
                 serial_queue_depth=8) as b:
        ep_in, ep_tcp = b.endpoints
        stalled = socket.socket()
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a small window
        stalled.connect(ep_tcp.address)
        veh = MavPeer(7, 1, dest=ep_in.address)
        try:
            assert wait_for(lambda: b.stats()["endpoints"][ep_tcp.name]["clients"] == 1, WAIT)
            big = veh.pack(dev.MAVLink_file_transfer_protocol_message(0, 0, 0, [0x55] * 251))
            deadline = time.monotonic() + WAIT
            while b.stats()["endpoints"][ep_tcp.name]["tx_dropped"] == 0:
                assert time.monotonic() < deadline, "nothing was ever dropped"
                for _ in range(100):
                    veh.send_raw(big)  # broadcast: forwarded to the TCP client
            # the loop is not stuck in a write: it still beats and answers on udpin
            beats = len(veh.messages("HEARTBEAT", lambda m: src(m) == (1, 1)))
            assert veh.wait_for("HEARTBEAT", lambda m: src(m) == (1, 1), count=beats + 3,
                                timeout=WAIT)
            veh.command((1, 1), dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
            assert veh.wait_for("AUTOPILOT_VERSION", timeout=WAIT)
            assert b.stats()["endpoints"][ep_tcp.name]["clients"] == 1  # still connected
            # it reads again: whole frames only, and fresh ones arrive
            parser = dev.MAVLink(None)
            parser.robust_parsing = True
            got: list[Any] = []
            stalled.settimeout(0.05)
            deadline = time.monotonic() + WAIT
            while sum(1 for m in got if m.get_type() == "HEARTBEAT") < 20:
                assert time.monotonic() < deadline, "the client's stream did not resume"
                try:
                    data = stalled.recv(65536)
                except TimeoutError:
                    continue
                assert data, "the gateway closed the connection"
                got += parser.parse_buffer(data) or []
        finally:
            veh.close()
            stalled.close()
    kinds = {m.get_type() for m in got}
    assert "BAD_DATA" not in kinds and "FILE_TRANSFER_PROTOCOL" in kinds
