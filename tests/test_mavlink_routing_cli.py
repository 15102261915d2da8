"""``run --source mavlink:ENDPOINT --mavlink ENDPOINT`` as a MAVProxy / mavlink-router user
types it: a pymavlink vehicle (ArduPilot-like, system 1) and a pymavlink ground station see
each other through the gateway's command line, and the gateway's own messages never use an id
that a system routed through it uses.

The gateway runs as its console command does (``python -m gateway run …``, a process of
its own); the vehicle and the ground station are :class:`mavlink_peer.MavPeer`s on loopback
UDP, parsing with pymavlink's upstream dialect.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import wait_for
from mavlink_peer import MavPeer, running_backend, upstream_dialect

ROOT = Path(__file__).resolve().parents[1]
WAIT = 15.0  # a cold start imports pymavlink's dialect: generous, never slept
ROUTER_ONLY = ["--disable", "console", "--disable", "crsf", "--disable", "zenoh"]

dev = upstream_dialect()
ROCKET = dev.MAV_TYPE_ROCKET


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Vehicle(MavPeer):
    """An ArduCopter-like system 1: heartbeats (10 Hz here, to be quick), answers every
    COMMAND_LONG addressed to it with COMMAND_ACK(ACCEPTED), as ArduPilot does."""

    def __init__(self, sysid: int = 1, dest: Any = None) -> None:
        super().__init__(sysid, 1, dest=dest)
        self.commands: list[Any] = []  # every COMMAND_LONG received, in order
        self._beat = threading.Event()
        self._beater = threading.Thread(target=self._heartbeats, daemon=True)
        self._beater.start()

    def heartbeat(self) -> Any:
        return dev.MAVLink_heartbeat_message(dev.MAV_TYPE_QUADROTOR,
                                             dev.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                             dev.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 5,
                                             dev.MAV_STATE_STANDBY, 3)

    def _heartbeats(self) -> None:
        while not self._beat.wait(0.1):
            with contextlib.suppress(OSError):
                self.send(self.heartbeat())
            for m in self.messages("COMMAND_LONG")[len(self.commands):]:
                self.commands.append(m)
                if m.target_system == self.mav.srcSystem:
                    self.send(dev.MAVLink_command_ack_message(
                        m.command, dev.MAV_RESULT_ACCEPTED, 0, 0, m.get_srcSystem(),
                        m.get_srcComponent()))

    def from_gcs(self) -> list[Any]:
        """The commands a ground station (system 255) sent."""
        return [m for m in self.commands if m.get_srcSystem() == 255]

    def close(self) -> None:
        self._beat.set()
        self._beater.join(1.0)
        super().close()


@contextlib.contextmanager
def gateway(log: Path, *args: str) -> Iterator[subprocess.Popen[bytes]]:
    """``aurora-gateway run ARGS`` in a process of its own, its stderr to ``log``; stopped
    with SIGINT (as Ctrl-C)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with open(log, "wb") as err:
        proc = subprocess.Popen([sys.executable, "-m", "gateway", "run",
                                 "--status-interval", "0", "--log-level", "info", *args],
                                cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=err)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.fixture
def peers() -> Iterator[tuple[Vehicle, MavPeer, int]]:
    """The vehicle (sending to the gateway's udpin port) and the ground station (where the
    gateway's udpout sends)."""
    port = free_udp_port()
    vehicle = Vehicle(dest=("127.0.0.1", port))
    gcs = MavPeer(255, 190)
    try:
        yield vehicle, gcs, port
    finally:
        vehicle.close()
        gcs.close()


def heartbeats(peer: MavPeer, sysid: int | None = None, mtype: int | None = None) -> list[Any]:
    return peer.messages("HEARTBEAT", lambda m: (sysid is None or m.get_srcSystem() == sysid)
                         and (mtype is None or m.type == mtype))


def test_vehicle_and_ground_station_see_each_other_through_the_command_line(
        peers: tuple[Vehicle, MavPeer, int], tmp_path: Path) -> None:
    vehicle, gcs, port = peers
    with gateway(tmp_path / "log", "--source", f"mavlink:udpin:127.0.0.1:{port}",
                 "--mavlink", f"udpout:127.0.0.1:{gcs.port}", *ROUTER_ONLY) as proc:
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=WAIT), \
            "the vehicle's heartbeat was not forwarded"
        # Telemetry down: 3000 frames, every one arrives.  At most 100 in flight, so no
        # socket buffer on the way (the peers' are the system's default) can overflow.
        sent = set()
        for i in range(3000):
            vehicle.send(dev.MAVLink_attitude_message(100_000 + i, 0.1, 0.2, 0.3, 0, 0, 0))
            sent.add(100_000 + i)
            if i % 50 == 49:
                assert gcs.wait_until(lambda n=i: len(gcs.messages("ATTITUDE")) > n - 100,
                                      WAIT), f"{len(gcs.messages('ATTITUDE'))} of {i + 1}"
        assert gcs.wait_until(lambda: len(gcs.messages("ATTITUDE")) >= 3000, WAIT)
        got = {m.time_boot_ms for m in gcs.messages("ATTITUDE")}
        assert got == sent
        assert all(m.get_srcSystem() == 1 for m in gcs.messages("ATTITUDE"))

        # Commands up, acknowledgements back: from the vehicle, never from the gateway.
        for i in range(20):
            gcs.command((1, 1), dev.MAV_CMD_DO_SET_MODE, 1, 4 + i)
        assert wait_for(lambda: len(vehicle.from_gcs()) >= 20, WAIT), \
            f"the vehicle received {len(vehicle.from_gcs())} of 20 commands"
        assert gcs.wait_for("COMMAND_ACK", count=20, timeout=WAIT)
        acks = gcs.messages("COMMAND_ACK")
        assert len(acks) == 20
        assert {(m.get_srcSystem(), m.get_srcComponent(), m.result) for m in acks} == {
            (1, 1, dev.MAV_RESULT_ACCEPTED)}
        assert [m.param2 for m in vehicle.from_gcs()] == [4 + i for i in range(20)]
        # Router only: the rocket has nothing to say, so it never shows itself; whatever the
        # ground station heard as system 1 is the vehicle.
        assert not heartbeats(gcs, mtype=ROCKET)
        assert {m.type for m in heartbeats(gcs, 1)} == {dev.MAV_TYPE_QUADROTOR}
        assert proc.poll() is None


def test_the_rocket_takes_an_id_the_vehicle_does_not_use(
        peers: tuple[Vehicle, MavPeer, int], tmp_path: Path) -> None:
    """A rocket (the simulated flight) and a MAVLink vehicle through one gateway: the rocket's
    messages use system 2, the vehicle's stay system 1, each answers only its own commands."""
    vehicle, gcs, port = peers
    with gateway(tmp_path / "log", "--source", "sim", "--sim-speed", "5",
                 "--source", f"mavlink:udpin:127.0.0.1:{port}",
                 "--mavlink", f"udpout:127.0.0.1:{gcs.port}", *ROUTER_ONLY) as proc:
        assert gcs.wait_for("HEARTBEAT", lambda m: m.type == ROCKET, timeout=WAIT)
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        rocket_ids = {m.get_srcSystem() for m in heartbeats(gcs, mtype=ROCKET)}
        assert rocket_ids == {2}
        assert {m.type for m in heartbeats(gcs, 1)} == {dev.MAV_TYPE_QUADROTOR}

        gcs.command((2, 1), dev.MAV_CMD_DO_SET_MODE, 1, 4)  # to the rocket: not supported
        gcs.command((1, 1), dev.MAV_CMD_DO_SET_MODE, 1, 4)  # to the vehicle: accepted
        assert gcs.wait_for("COMMAND_ACK", count=2, timeout=WAIT)
        acks = {(m.get_srcSystem(), m.result) for m in gcs.messages("COMMAND_ACK")}
        assert acks == {(2, dev.MAV_RESULT_UNSUPPORTED), (1, dev.MAV_RESULT_ACCEPTED)}
        assert wait_for(lambda: len(vehicle.from_gcs()) == 1, WAIT)
        # The vehicle's own telemetry reaches the ground station untouched.
        vehicle.send(dev.MAVLink_attitude_message(42, 0.5, 0.25, 0.125, 0, 0, 0))
        assert gcs.wait_for("ATTITUDE", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        assert proc.poll() is None
    assert proc.returncode == 130  # stopped by SIGINT (Ctrl-C): "interrupted" (gateway.exits)
    log = (tmp_path / "log").read_text()
    assert "system 1 is in use" in log and "takes system 2" in log  # said which, and why
    assert "moves to" not in log  # never spoke as system 1


# -- in process: the id rule when a system with our id shows up later -------------------------

def test_rocket_moves_when_another_system_uses_its_id(caplog: pytest.LogCaptureFixture) -> None:
    from gateway.model import SmUpdate

    caplog.set_level(logging.WARNING, "backends.mavlink.router")
    with MavPeer(255, 190) as gcs, running_backend("udpin:127.0.0.1:0") as b:
        gcs.dest = b.endpoints[0].address
        gcs.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_GCS, dev.MAV_AUTOPILOT_INVALID,
                                               0, 0, 0, 3))
        b.send_sm_update(SmUpdate(1000, 2, True, 0, 100.0, 12.0, 11.0, 40.0, 0.1, 0.2, 0.3))
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1 and m.type == ROCKET)
        # Our own frames echoed back (a loop in the network) are not another system.
        echo = gcs.raw_received[-1]
        gcs.send_raw(echo)
        assert wait_for(lambda: b.router.stats.own_id_seen >= 1)
        assert b.vehicle.sysid == 1
        # A quadrotor that is system 1 too: the rocket moves, says so, and speaks as 2.
        impostor = dev.MAVLink(None, 1, 1)
        gcs.send_raw(dev.MAVLink_heartbeat_message(
            dev.MAV_TYPE_QUADROTOR, dev.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0, 3).pack(impostor))
        assert wait_for(lambda: b.vehicle.sysid == 2)
        gcs.clear()
        assert gcs.wait_for("HEARTBEAT", lambda m: m.type == ROCKET)
        assert {m.get_srcSystem() for m in heartbeats(gcs, mtype=ROCKET)} == {2}
        assert b.stats()["router"]["id_changes"] == 1
        # Commands to system 1 are no longer ours to answer.  One thread handles both in
        # order: had the first been answered, its ACK would have come before the second's.
        gcs.command((1, 1), dev.MAV_CMD_DO_SET_MODE, 1, 4)
        gcs.command((2, 1), dev.MAV_CMD_DO_SET_MODE, 1, 4)
        assert gcs.wait_for("COMMAND_ACK")
        assert {m.get_srcSystem() for m in gcs.messages("COMMAND_ACK")} == {2}
    assert any("moves to system 2" in r.getMessage() for r in caplog.records)
