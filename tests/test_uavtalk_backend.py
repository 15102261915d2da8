"""The UAVTalk backend (flight side) against a GCS simulator written from the spec, over real
TCP on loopback.

:class:`SpecGcs` follows ``../shared/specs/uavtalk.md`` and nothing of ``telemetry.py``:
GCSTelemetryStats(HandshakeReq) every ``handshake_s`` (2 s in 16.09; shorter here) until the
flight side answers HandshakeAck, then GCSTelemetryStats(Connected) and the OBJ_REQ walk, one
object at a time, each retried twice 250 ms apart.  Object ids are the spec's; packets are
built and checked here byte by byte (CRC-8 0x07 written out again), not with the codec.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import subprocess
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from helpers import GATEWAY, ROOT, wait_for

from backends.uavtalk.backend import UavtalkBackend, parse_endpoint
from backends.uavtalk.objects import ObjectSet
from backends.uavtalk.options import UavtalkOptions
from backends.uavtalk.translate import FLIGHT_MODES, Vehicle, quaternion
from dialects.states import SimpleState
from gateway import config
from gateway.backend import STATS_KEYS, GatewayContext, Outcome
from gateway.config import ConfigError
from gateway.dispatcher import Dispatcher
from gateway.model import Battery, Position, SmUpdate, Status

# --- the spec's ids and packet rules ---------------------------------------------------------

FLIGHT_STATS = 0x6737BB5A
GCS_STATS = 0xCAD1DC0A
ATTITUDE = 0xD7E0D964
FLIGHT_STATUS = 0x24D25E28
SYSTEM_ALARMS = 0x20E6CAAC
GPS_POSITION = 0x9DF1F67A
FIRMWARE = 0x8328F252
UNKNOWN_ID = 0x12345678
OBJ, OBJ_REQ, OBJ_ACK, ACK, NACK = 0x20, 0x21, 0x22, 0x23, 0x24
DISCONNECTED, HANDSHAKE_REQ, HANDSHAKE_ACK, CONNECTED = range(4)
STATS_SIZE = 37
FIRMWARE_SIZE = 123
BOARD_TYPE_OFFSET = 4 + 2 + 2 + 100 + 12  # crc u32, Command, BoardRevision u16, 100 + 12 u8
DEADLINE_S = 5.0


def crc8(data: bytes) -> int:
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def packet(ptype: int, object_id: int, data: bytes = b"", instance: int = 0) -> bytes:
    body = struct.pack("<BBHIH", 0x3C, ptype, 10 + len(data), object_id, instance) + data
    return body + bytes((crc8(body),))


def gcs_stats(status: int) -> bytes:
    return packet(OBJ, GCS_STATS, bytes(STATS_SIZE - 1) + bytes((status,)))


def test_spec_vectors_of_the_simulator() -> None:
    assert crc8(b"123456789") == 0xF4
    assert gcs_stats(HANDSHAKE_REQ) == bytes.fromhex("3c202f000adcd1ca0000") + bytes(36) + \
        bytes.fromhex("0196")
    assert packet(OBJ_REQ, FLIGHT_STATS) == bytes.fromhex("3c210a005abb3767000006")


class SpecGcs:
    """A ground station from the spec's rules, driven by the test thread (see the module)."""

    def __init__(self, address: Any, *, handshake_s: float = 0.1,
                 walk: tuple[int, ...] = (FIRMWARE, FLIGHT_STATUS, ATTITUDE, SYSTEM_ALARMS),
                 rcvbuf: int | None = None, sock: socket.socket | None = None) -> None:
        if sock is None:  # (given: a connection the flight side made to us)
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            if rcvbuf is not None:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            sock.connect(address)
        self.sock = sock
        self.sock.settimeout(0.01)
        self.handshake_s = handshake_s
        self.state = DISCONNECTED
        self.buf = b""
        self.received: dict[int, list[tuple[float, bytes]]] = defaultdict(list)
        self.nacks: list[int] = []
        self.acks: list[int] = []
        self.bad_crc = 0
        self.walk = list(walk)
        self.walk_started = False
        self.request: tuple[int, float, int] | None = None  # (id, deadline, retries left)
        self.walked: dict[int, bytes | None] = {}  # id → data (None: NACK or no answer)
        self.next_handshake = 0.0
        self.connected_at: float | None = None
        self.started = time.monotonic()

    def close(self) -> None:
        self.sock.close()

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    # -- receiving ---------------------------------------------------------------------------

    def _packets(self) -> Iterator[tuple[int, int, bytes]]:
        buf = self.buf
        while True:
            start = buf.find(b"\x3c")
            if start < 0:
                buf = b""
                break
            buf = buf[start:]
            if len(buf) < 10:
                break
            ptype, size, oid = struct.unpack_from("<BHI", buf, 1)
            if not 10 <= size <= 266:
                buf = buf[1:]
                continue
            if len(buf) < size + 1:
                break
            if crc8(buf[:size]) != buf[size]:
                self.bad_crc += 1
                buf = buf[1:]
                continue
            yield ptype, oid, bytes(buf[10:size])
            buf = buf[size + 1:]
        self.buf = buf

    def _handle(self, ptype: int, oid: int, data: bytes, now: float) -> None:
        if ptype == NACK:
            self.nacks.append(oid)
        elif ptype == ACK:
            self.acks.append(oid)
        elif ptype in (OBJ, OBJ_ACK):
            self.received[oid].append((now, data))
            if ptype == OBJ_ACK:
                self.send(packet(ACK, oid))
        if oid == FLIGHT_STATS and ptype == OBJ:
            flight = data[-1]
            if self.state == HANDSHAKE_REQ and flight == HANDSHAKE_ACK:
                self.state = CONNECTED
                self.connected_at = now
                self.send(gcs_stats(CONNECTED))
            elif self.state == CONNECTED and flight == DISCONNECTED:
                self.state = DISCONNECTED
        if self.request is not None and oid == self.request[0] and ptype in (OBJ, NACK):
            self.walked[oid] = data if ptype == OBJ else None
            self.request = None

    # -- the monitor ---------------------------------------------------------------------------

    def step(self) -> None:
        """Read what arrived (≤ 10 ms wait) and run the handshake, retries and the walk."""
        now = time.monotonic()
        if self.state != CONNECTED and now >= self.next_handshake:
            self.state = HANDSHAKE_REQ
            self.send(gcs_stats(HANDSHAKE_REQ))
            self.next_handshake = now + self.handshake_s
        if self.state == CONNECTED:
            self._walk(now)
        try:
            data = self.sock.recv(65536)
        except TimeoutError:
            return
        if not data:
            raise ConnectionError("the flight side closed the connection")
        self.buf += data
        now = time.monotonic()
        for ptype, oid, payload in self._packets():
            self._handle(ptype, oid, payload, now)

    def _walk(self, now: float) -> None:
        if self.request is not None:
            oid, deadline, left = self.request
            if now < deadline:
                return
            if left > 0:
                self.send(packet(OBJ_REQ, oid))
                self.request = (oid, now + 0.25, left - 1)
                return
            self.walked[oid] = None
            self.request = None
        if self.walk:
            oid = self.walk.pop(0)
            self.send(packet(OBJ_REQ, oid))
            self.request = (oid, now + 0.25, 2)

    def run_until(self, cond: Callable[[], bool], timeout: float = DEADLINE_S) -> bool:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                return False
            self.step()
        return True

    def latest(self, oid: int) -> bytes | None:
        got = self.received.get(oid)
        return got[-1][1] if got else None


def attitude(data: bytes) -> tuple[float, ...]:
    return struct.unpack("<7f", data)


def euler_deg(q: tuple[float, ...]) -> tuple[float, float, float]:
    """Roll, pitch, yaw (degrees) of a scalar-first quaternion (Z-Y-X), written out again."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return math.degrees(roll), math.degrees(pitch), math.degrees(yaw)


# --- fixtures -----------------------------------------------------------------------------------

ROLL, PITCH, YAW = math.radians(10), math.radians(-5), math.radians(90)


def sm(state: int = SimpleState.BOOST, armed: bool = True, t: int = 0) -> SmUpdate:
    return SmUpdate(timestamp_ms=t, state=state, armed=armed, sm_type=0, altitude_m=1234.5,
                    acceleration_mps2=30.0, accel_vert_mps2=29.0, velocity_mps=150.0,
                    roll_rad=ROLL, pitch_rad=PITCH, yaw_rad=YAW)


STATUS_OK = Status(timestamp_ms=0, state=SimpleState.BOOST, sm_type=0,
                   flags=Status.make_flags(armed=True, imu_ok=True, baro_ok=True,
                                           calibrated=True, log_ready=True))


class Feed:
    """SM_UPDATEs (and a STATUS every 10th) into a real Dispatcher every 20 ms, like SimSource,
    in a thread of its own until stopped."""

    def __init__(self, dispatcher: Dispatcher) -> None:
        self.dispatcher = dispatcher
        self.stop = threading.Event()
        self.outcomes: list[Outcome] = []
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        k = 0
        while not self.stop.wait(0.02):
            self.outcomes.append(self.dispatcher.dispatch(sm(t=k * 20)))
            if k % 10 == 0:
                self.outcomes.append(self.dispatcher.dispatch(STATUS_OK))
            k += 1
            self.updates = k

    updates = 0  # SM_UPDATEs dispatched so far (20 ms of the flight each)

    def __enter__(self) -> Feed:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(2.0)


@pytest.fixture
def gateway() -> Iterator[tuple[Dispatcher, UavtalkBackend]]:
    d = Dispatcher()
    b = UavtalkBackend(UavtalkOptions(endpoints=["tcpin:127.0.0.1:0"]))
    b.attach(GatewayContext(emit=d.dispatch))
    d.add(b)
    d.start()
    try:
        yield d, b
    finally:
        d.close()


def link_stats(b: UavtalkBackend, gcs: SpecGcs) -> dict[str, Any]:
    port = gcs.sock.getsockname()[1]
    found = [v for k, v in b.stats()["links"].items() if k.endswith(f":{port}>")]
    return found[0] if found else {}


# --- configuration ----------------------------------------------------------------------------

def test_endpoints_parse_and_bad_ones_are_refused() -> None:
    assert parse_endpoint("tcpin:127.0.0.1:9000")[:3] == ("tcpin", "127.0.0.1", 9000)
    assert parse_endpoint("tcp::9000")[:3] == ("tcp", "127.0.0.1", 9000)
    assert parse_endpoint("/dev/ttyUSB0,115200")[3:5] == ("/dev/ttyUSB0", 115200)
    assert parse_endpoint("serial:loop://")[3:5] == ("loop://", 57600)
    for bad in ("udpin:1.2.3.4:5", "tcp:host", "tcpin:h:99999", "nonsense"):
        with pytest.raises(ValueError):
            parse_endpoint(bad)
    with pytest.raises(ConfigError, match="endpoints"):
        config.parse({"backends": {"uavtalk": {"endpoints": ["udpout:1.2.3.4:5"]}}})


def test_run_flags_and_off_by_default() -> None:
    from gateway.commands.cli import build_parser, config_from_args

    assert UavtalkBackend.EMBEDDED_DEFAULT is None
    assert "uavtalk" not in {p.name for p in config.embedded_default().backends}
    args = build_parser().parse_args(["run", "--uavtalk", "tcpin:127.0.0.1:9000",
                                      "--uavtalk", "/dev/ttyUSB3"])
    parts = {p.name: p for p in config_from_args(args).backends}
    assert parts["uavtalk"].options["endpoints"] == ["tcpin:127.0.0.1:9000", "/dev/ttyUSB3"]


def test_objects_from_messages() -> None:
    objects = ObjectSet.load()
    v = Vehicle(objects, board_type=0x09)
    for name, values in v.defaults().items():
        objects.by_name(name).pack(values)  # every default packs
    out = v.sm_update(sm())
    att = out["AttitudeState"]
    assert (att["Roll"], att["Pitch"], att["Yaw"]) == pytest.approx((10, -5, 90))
    q = (att["q1"], att["q2"], att["q3"], att["q4"])
    assert sum(c * c for c in q) == pytest.approx(1)
    assert euler_deg(q) == pytest.approx((10, -5, 90), abs=1e-6)
    assert quaternion(0, 0, 0) == (1, 0, 0, 0)
    assert out["FlightStatus"] == {"Armed": "Armed", "FlightMode": "AutoTakeoff"}
    assert out["BaroSensor"]["Altitude"] == 1234.5
    assert 80_000 < out["BaroSensor"]["Pressure"] < 90_000
    alarms = objects.by_name("SystemAlarms")
    names = alarms.field("Alarm").element_names
    al = dict(zip(names, alarms.unpack(alarms.pack(v.status(STATUS_OK)["SystemAlarms"]))["Alarm"],
                  strict=True))
    assert al["Attitude"] == al["Sensors"] == al["SystemConfiguration"] == 1  # OK
    bad = STATUS_OK._replace(flags=Status.make_flags(imu_ok=False, baro_ok=True))
    al = dict(zip(names, alarms.unpack(alarms.pack(v.status(bad)["SystemAlarms"]))["Alarm"],
                  strict=True))
    assert al["Attitude"] == al["Sensors"] == 3 and al["SystemConfiguration"] == 2
    gps = v.position(Position(lat_deg=47.1234567, lon_deg=-122.5, alt_amsl_m=80.0,
                              satellites=9, fix_type=3))
    objects.by_name("GPSPositionSensor").pack(gps["GPSPositionSensor"])
    assert gps["GPSPositionSensor"]["Latitude"] == 471234567
    bat = v.battery(Battery(voltage_v=8.2, current_a=1.5))
    objects.by_name("FlightBatteryState").pack(bat["FlightBatteryState"])
    assert FLIGHT_MODES[SimpleState.MAIN] == "Land"
    for state in SimpleState:  # every state maps to an option of 16.09's FlightMode
        assert FLIGHT_MODES[state] in objects.by_name("FlightStatus").field("FlightMode").options


# --- against the simulated GCS over TCP -----------------------------------------------------

def test_gcs_connects_reads_board_type_attitude_armed_and_nack(gateway: Any) -> None:
    d, b = gateway
    assert d.dispatch(Battery(voltage_v=8.0)) is Outcome.ACCEPTED
    gcs: SpecGcs | None = None
    try:
        with Feed(d) as feed:
            assert wait_for(lambda: b.stats()["messages"] > 1)  # the rocket is armed
            gcs = SpecGcs(b.address(), walk=(FIRMWARE, FLIGHT_STATUS, ATTITUDE, SYSTEM_ALARMS,
                                             ATTITUDE + 1, GPS_POSITION, UNKNOWN_ID))
            g = gcs
            assert g.run_until(lambda: g.state == CONNECTED, 3.0)
            assert g.connected_at is not None and g.connected_at - g.started < 3.0
            assert g.run_until(lambda: not g.walk and g.request is None)
            fw = g.walked[FIRMWARE]
            assert fw is not None and len(fw) == FIRMWARE_SIZE and fw[BOARD_TYPE_OFFSET] != 0
            status = g.walked[FLIGHT_STATUS]
            assert status is not None and status[0] == 2  # Armed
            meta = g.walked[ATTITUDE + 1]
            assert meta is not None and len(meta) == 8
            assert g.walked[UNKNOWN_ID] is None and UNKNOWN_ID in g.nacks
            assert g.walked[GPS_POSITION] is None  # no position yet: NACK
            # AttitudeState at ≥ 5 Hz, consistent, in degrees
            first = len(g.received[ATTITUDE])
            t0 = time.monotonic()
            assert g.run_until(lambda: time.monotonic() - t0 >= 2.0, 3.0)
            rate = (len(g.received[ATTITUDE]) - first) / (time.monotonic() - t0)
            assert rate >= 5.0
            q1, q2, q3, q4, roll, pitch, yaw = attitude(g.latest(ATTITUDE) or b"")
            assert (roll, pitch, yaw) == pytest.approx((10, -5, 90), abs=1e-4)
            assert euler_deg((q1, q2, q3, q4)) == pytest.approx((roll, pitch, yaw), abs=1e-3)
            assert Outcome.ACCEPTED in feed.outcomes
        assert g.bad_crc == 0
        # a position arrives: GPSPositionSensor is served from then on
        applied = b.stats()["messages"]
        assert d.dispatch(Position(lat_deg=47.0, lon_deg=8.0, alt_amsl_m=500.0)) is \
            Outcome.ACCEPTED
        assert wait_for(lambda: b.stats()["messages"] > applied)  # the loop has applied it
        g.walk = [GPS_POSITION]
        assert g.run_until(lambda: g.walked.get(GPS_POSITION) is not None)
        st = b.stats()
        assert set(STATS_KEYS) <= set(st) and st["link"] == 1 and st["sent"] > 20
        ls = link_stats(b, g)
        assert ls["state"] == "connected" and ls["nacks"] >= 2 and ls["packets"] > 5
        assert ls["handshake_ms"] < 3000
    finally:
        if gcs is not None:
            gcs.close()


def test_two_gcs_each_have_their_own_state(gateway: Any) -> None:
    _, b = gateway
    a = SpecGcs(b.address())
    c = SpecGcs(b.address())
    try:
        assert a.run_until(lambda: a.state == CONNECTED)
        c.send(gcs_stats(HANDSHAKE_REQ))  # its HandshakeReq, the answer left unread for now
        c.state, c.next_handshake = HANDSHAKE_REQ, time.monotonic() + 60
        assert wait_for(lambda: link_stats(b, c).get("state") == "handshake_ack")
        assert link_stats(b, a)["state"] == "connected"
        assert b.stats()["clients"] == 2 and b.stats()["connected"] == 1
        t0 = time.monotonic()  # c answers HandshakeAck late: its handshake takes ≥ 0.3 s
        assert a.run_until(lambda: time.monotonic() - t0 >= 0.3)
        assert c.run_until(lambda: c.state == CONNECTED)
        assert wait_for(lambda: b.stats()["connected"] == 2)  # (its Connected is on its way)
        assert link_stats(b, c)["handshake_ms"] >= 300 > link_stats(b, a)["handshake_ms"]
    finally:
        a.close()
        c.close()
    assert wait_for(lambda: b.stats()["clients"] == 0)
    assert b.stats()["clients_closed"] == 2


def test_a_client_that_never_reads_stalls_nobody(gateway: Any) -> None:
    d, b = gateway
    good = SpecGcs(b.address())
    sink = SpecGcs(b.address(), rcvbuf=4096)
    try:
        assert good.run_until(lambda: good.state == CONNECTED)
        assert sink.run_until(lambda: sink.state == CONNECTED)
        # small kernel buffers on both sides: the engine's queue fills after a few kB
        port = sink.sock.getsockname()[1]
        (link,) = [k for k in b.links if k.name.endswith(f":{port}>")]
        link.engine.port.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        flood = packet(OBJ_REQ, FIRMWARE) * 2000  # 2000 replies of 134 bytes a round
        sent = threading.Event()

        def flooding() -> None:
            for _ in range(3):
                sink.send(flood)  # and never read
            sent.set()

        with Feed(d) as feed:
            threading.Thread(target=flooding, daemon=True).start()
            assert wait_for(lambda: link_stats(b, sink).get("queue_full", 0) > 0)
            first, fed = len(good.received[ATTITUDE]), feed.updates
            # 1.5 s of the flight, timed by the feed (a busy machine slows the feed too: a
            # wall-clock rate measured the machine); a stalled good client gets next to none
            assert good.run_until(lambda: feed.updates - fed >= 75, 30.0)
            flight_s = (feed.updates - fed) * 0.02
            assert (len(good.received[ATTITUDE]) - first) / flight_s >= 5.0
            assert sent.wait(DEADLINE_S)
        assert link_stats(b, sink)["dropped"] > 0
        assert link_stats(b, good)["dropped"] == 0
        assert b.stats()["dropped"] >= link_stats(b, sink)["dropped"]
    finally:
        good.close()
        sink.close()


def _lines(caplog: Any, text: str) -> int:
    return sum(text in r.getMessage() for r in caplog.records)


def test_gcs_connected_is_logged_when_the_handshake_completes(gateway: Any, caplog: Any) -> None:
    caplog.set_level(logging.INFO)
    _, b = gateway
    gcs = SpecGcs(b.address(), walk=())
    try:
        # accepted, and the flight side's FlightTelemetryStats(Disconnected) sent: no
        # handshake yet — the GCS has sent nothing (a step of it would start the handshake,
        # which can complete within that step's read)
        assert wait_for(lambda: b.stats()["clients"] == 1 and link_stats(b, gcs)["sent"] > 0)
        assert wait_for(lambda: _lines(caplog, "TCP client connected") == 1)
        assert _lines(caplog, "GCS connected") == 0
        assert gcs.run_until(lambda: gcs.state == CONNECTED)
        assert wait_for(lambda: _lines(caplog, "GCS connected") == 1)
        assert _lines(caplog, "GCS disconnected") == 0 and b.stats()["gcs_connects"] == 1
    finally:
        gcs.close()
    assert wait_for(lambda: _lines(caplog, "GCS disconnected") == 1)
    assert b.stats()["gcs_disconnects"] == 1 and b.stats()["clients"] == 0


def test_gcs_handshaking_in_a_loop_costs_a_few_lines(gateway: Any, caplog: Any) -> None:
    caplog.set_level(logging.INFO)
    _, b = gateway
    n = 25
    for _ in range(n):  # connect, handshake, hang up: again and again
        gcs = SpecGcs(b.address(), walk=())
        try:
            assert gcs.run_until(lambda g=gcs: g.state == CONNECTED)  # type: ignore[misc]
            assert wait_for(lambda g=gcs: link_stats(b, g).get("state") == "connected")  # type: ignore[misc]
        finally:
            gcs.close()
    assert wait_for(lambda: b.stats()["gcs_disconnects"] == n and b.stats()["clients"] == 0)
    st = b.stats()
    assert st["gcs_connects"] == n and st["clients_closed"] == n  # every one counted
    # a line when a burst starts, then one with the count per 10 s: not one per handshake
    for text in ("GCS connected", "GCS disconnected", "TCP client connected", "TCP client left"):
        assert 1 <= _lines(caplog, text) <= 3, text


def test_silent_gcs_is_disconnected_after_8_s_and_reconnects() -> None:
    skew = [0.0]  # the backend's clock runs ahead of the GCS's by this much
    d = Dispatcher()
    b = UavtalkBackend(UavtalkOptions(endpoints=["tcpin:127.0.0.1:0"]),
                       clock=lambda: time.monotonic() + skew[0])
    d.add(b)
    d.start()
    gcs = SpecGcs(b.address(), walk=())  # connected, it sends nothing
    try:
        assert gcs.run_until(lambda: gcs.state == CONNECTED)
        assert wait_for(lambda: link_stats(b, gcs).get("state") == "connected")
        skew[0] = 9.0  # 9 s of the GCS's silence, as the flight side sees it
        assert gcs.run_until(lambda: gcs.state != CONNECTED)  # told so by FlightTelemetryStats
        assert gcs.run_until(lambda: gcs.state == CONNECTED)  # a new handshake, same link
        assert wait_for(lambda: link_stats(b, gcs).get("connects") == 2)
        assert link_stats(b, gcs)["disconnects"] == 1 and b.stats()["clients"] == 1
    finally:
        gcs.close()
        d.close()


def serve_one(b: UavtalkBackend, gcs: SpecGcs) -> None:
    assert gcs.run_until(lambda: gcs.state == CONNECTED)
    assert gcs.run_until(lambda: FIRMWARE in gcs.walked)
    assert gcs.walked[FIRMWARE] is not None
    assert wait_for(lambda: b.stats()["connected"] == 1)


def test_tcp_client_endpoint_reconnects_with_a_fresh_session() -> None:
    with socket.create_server(("127.0.0.1", 0)) as listener:
        listener.settimeout(DEADLINE_S)
        port = listener.getsockname()[1]
        b = UavtalkBackend(UavtalkOptions(endpoints=[f"tcp:127.0.0.1:{port}"]))
        b.init()
        try:
            for round_ in (1, 2):  # the second time after the GCS hung up
                conn, _ = listener.accept()
                gcs = SpecGcs(None, sock=conn, walk=(FIRMWARE,))
                try:
                    serve_one(b, gcs)
                finally:
                    gcs.close()
                # a session of its own for the next peer once the link is down
                assert wait_for(lambda r=round_: [v["sessions"] for v in  # type: ignore[misc]
                                                  b.stats()["links"].values()] == [r + 1])
                assert b.stats()["connected"] == 0
        finally:
            b.close()


def test_garbage_is_counted_and_the_link_goes_on(gateway: Any) -> None:
    _, b = gateway
    gcs = SpecGcs(b.address(), walk=())
    try:
        assert gcs.run_until(lambda: gcs.state == CONNECTED)
        broken = bytearray(packet(OBJ_REQ, FIRMWARE))
        broken[-1] ^= 0xFF  # wrong CRC
        gcs.send(b"\x00\xffnoise\x3c\x21" + bytes(broken) + b"\x3c\x99junk")
        gcs.walk = [FIRMWARE]
        assert gcs.run_until(lambda: gcs.walked.get(FIRMWARE) is not None)
        ls = link_stats(b, gcs)
        assert ls["corrupt_packets"] == 1 and ls["rx_garbage_bytes"] > 10
        assert b.stats()["crc_failures"] == 1
        assert b.stats()["errors"] >= 1 and ls["state"] == "connected"
        assert gcs.received[FIRMWARE] and len(gcs.received[FIRMWARE]) == 1
    finally:
        gcs.close()


def test_hooks_never_block_a_full_inbox_drops(gateway: Any) -> None:
    d, b = gateway
    release = threading.Event()
    busy = threading.Event()

    def hold() -> None:
        busy.set()
        release.wait(DEADLINE_S)

    b.loop.call_soon(hold)  # the loop is busy: nothing drains the inbox
    assert busy.wait(DEADLINE_S)
    try:
        outcomes = [d.dispatch(sm(t=k)) for k in range(b.options.inbox_depth + 5)]
    finally:
        release.set()
    assert outcomes.count(Outcome.ACCEPTED) == b.options.inbox_depth
    assert outcomes.count(Outcome.QUEUE_FULL) == 5 and b.stats()["dropped_queue_full"] == 5
    assert wait_for(lambda: b.stats()["messages"] == b.options.inbox_depth)


def test_not_ready_before_start_and_close_twice() -> None:
    b = UavtalkBackend(UavtalkOptions(endpoints=["tcpin:127.0.0.1:0"]))
    d = Dispatcher([b])
    post = b.handover.hook(b.send_status)  # what the dispatcher calls, before start
    assert post(STATUS_OK) is Outcome.NOT_READY
    assert d.start() == []
    assert d.dispatch(STATUS_OK) is Outcome.ACCEPTED
    b.close()
    b.close()
    assert d.dispatch(STATUS_OK) is Outcome.NOT_READY


# --- the command line -----------------------------------------------------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_cli_run_sim_reaches_connected_and_armed() -> None:
    port = _free_port()
    proc = subprocess.Popen([*GATEWAY, "run", "--source", "sim", "--sim-speed", "5", "--only",
                             "uavtalk", "--uavtalk", f"tcpin:127.0.0.1:{port}"], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    gcs: SpecGcs | None = None
    try:
        deadline = time.monotonic() + 10.0
        while gcs is None:  # the gateway starts listening when it has imported everything
            try:
                gcs = SpecGcs(("127.0.0.1", port))
            except ConnectionRefusedError:
                assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
                assert time.monotonic() < deadline, "the gateway never listened"
                assert not wait_for(lambda: proc.poll() is not None, 0.05)
        assert gcs.run_until(lambda: gcs.state == CONNECTED, 3.0)
        assert gcs.connected_at is not None and gcs.connected_at - gcs.started < 3.0
        assert gcs.run_until(lambda: not gcs.walk and gcs.request is None)
        fw = gcs.walked[FIRMWARE]
        assert fw is not None and fw[BOARD_TYPE_OFFSET] != 0
        # the simulated flight: IDLE 5 s, then ARMED (÷ 5): Armed within a few seconds
        assert gcs.run_until(lambda: any(data[0] == 2 for _, data in
                                         gcs.received[FLIGHT_STATUS]), 6.0)
    finally:
        if gcs is not None:
            gcs.close()
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
