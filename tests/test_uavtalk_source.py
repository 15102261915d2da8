"""The GCS-side UAVTalk source against a flight-controller simulator written from the spec
(``../shared/specs/uavtalk.md``) on a real TCP listener, plus unit tests of its wiring."""

from __future__ import annotations

import contextlib
import math
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest

from backends.uavtalk.codec import Decoder, Packet, PacketType, encode
from backends.uavtalk.objects import ObjectSet
from backends.uavtalk.options import UavtalkSourceOptions
from backends.uavtalk.source import UavtalkSource, parse_url
from backends.uavtalk.telemetry import Status
from gateway import config
from gateway.config import ConfigError
from gateway.model import Battery, Position, VehicleState
from gateway.sources import parse_source_url

OBJECTS = ObjectSet.load()
DISCONNECTED, HANDSHAKE_REQ, HANDSHAKE_ACK, CONNECTED = 0, 1, 2, 3
MODES = OBJECTS.by_name("FlightStatus").field("FlightMode").options


def _values() -> dict[str, dict[str, Any]]:
    return {
        "FirmwareIAPObj": {"BoardType": 9},
        "FlightStatus": {"Armed": 2, "FlightMode": MODES.index("Stabilized2")},
        "AttitudeState": {"q1": 1.0, "Roll": 10.0, "Pitch": -5.0, "Yaw": 90.0},
        "BaroSensor": {"Altitude": 123.5, "Temperature": 20.0, "Pressure": 99000.0},
        "GPSPositionSensor": {"Latitude": 473977418, "Longitude": 85455939, "Altitude": 488.0,
                              "Heading": 45.0, "Groundspeed": 3.5, "Satellites": 11,
                              "Status": 3},
        "FlightBatteryState": {"Voltage": 11.1, "Current": 4.5, "ConsumedEnergy": 250.0},
    }


class FlightSim:
    """A LibrePilot flight controller from the spec's rules, one TCP client at a time:
    Disconnected + GCS HandshakeReq → HandshakeAck; HandshakeAck + GCS Connected → Connected;
    HandshakeAck + GCS Disconnected → Disconnected; Connected + GCS not Connected →
    Disconnected; FlightTelemetryStats on every change.  OBJ_REQ → OBJ of a held object, else
    NACK.  While connected, AttitudeState every 50 ms.  ``silent``: reads and sends nothing
    (and, as a silent link would have timed out on the flight side too, starts over
    Disconnected when it speaks again)."""

    def __init__(self, port: int = 0) -> None:
        self.values = _values()
        self.listener = socket.create_server(("127.0.0.1", port))
        self.port = self.listener.getsockname()[1]
        self.state = DISCONNECTED
        self.silent = threading.Event()
        self.quiet = threading.Event()
        self.nacked: list[str] = []
        self.requested: list[str] = []
        self.gcs_stats = 0
        self.changed = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name="flight-sim")
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.listener.close()

    def wait(self, predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
        with self.changed:
            return self.changed.wait_for(predicate, timeout)

    def _obj(self, name: str) -> bytes:
        obj = OBJECTS.by_name(name)
        return encode(Packet(PacketType.OBJ, obj.id, 0, obj.pack(self.values[name])))

    def _set(self, conn: socket.socket, state: int) -> None:
        with self.changed:
            self.state = state
            self.changed.notify_all()
        obj = OBJECTS.by_name("FlightTelemetryStats")
        conn.sendall(encode(Packet(PacketType.OBJ, obj.id, 0, obj.pack({"Status": state}))))

    def _run(self) -> None:
        self.listener.settimeout(0.05)
        while not self._stop.is_set():
            try:
                conn, _ = self.listener.accept()
            except TimeoutError:
                continue
            with conn, contextlib.suppress(ConnectionError):  # the gateway hung up: normal
                self._serve(conn)
            self.state = DISCONNECTED

    def _serve(self, conn: socket.socket) -> None:
        decoder = Decoder(OBJECTS.data_length)
        next_attitude = time.monotonic()
        was_silent = False
        while not self._stop.is_set():
            readable, _, _ = select.select([conn], [], [], 0.02)
            data = b""
            if readable:
                data = conn.recv(4096)
                if not data:
                    return
            if self.silent.is_set():
                was_silent = True
                self.quiet.set()  # from here on nothing more is sent
                continue
            if was_silent:
                was_silent = False
                self.state = DISCONNECTED
            for p in decoder.feed(data):
                self._handle(conn, p)
            now = time.monotonic()
            if self.state == CONNECTED and now >= next_attitude:
                next_attitude = now + 0.05
                conn.sendall(self._obj("AttitudeState"))

    def _handle(self, conn: socket.socket, p: Packet) -> None:
        obj = OBJECTS.by_id(p.object_id)
        if p.type == PacketType.OBJ_REQ:
            name = obj.name if obj is not None else hex(p.object_id)
            self.requested.append(name)
            if name in self.values:
                conn.sendall(self._obj(name))
            else:
                self.nacked.append(name)
                conn.sendall(encode(Packet(PacketType.NACK, p.object_id, p.instance_id)))
            return
        if p.type != PacketType.OBJ or obj is None or obj.name != "GCSTelemetryStats":
            return
        self.gcs_stats += 1
        gcs = obj.unpack(p.data)["Status"]
        if self.state == DISCONNECTED and gcs in (HANDSHAKE_REQ, HANDSHAKE_ACK):
            self._set(conn, HANDSHAKE_ACK)
        elif self.state == HANDSHAKE_ACK and gcs == CONNECTED:
            self._set(conn, CONNECTED)
        elif (self.state == HANDSHAKE_ACK and gcs == DISCONNECTED) or \
                (self.state == CONNECTED and gcs != CONNECTED):
            self._set(conn, DISCONNECTED)


class Collector:
    """The source's sink: every message, and a wait for one that matches."""

    def __init__(self) -> None:
        self.messages: list[Any] = []
        self.cond = threading.Condition()

    def __call__(self, msg: Any) -> None:
        with self.cond:
            self.messages.append(msg)
            self.cond.notify_all()

    def wait_for(self, predicate: Callable[[Any], bool], timeout: float = 5.0) -> Any:
        found: list[Any] = []

        def match() -> bool:
            found[:] = [m for m in self.messages if predicate(m)]
            return bool(found)

        with self.cond:
            assert self.cond.wait_for(match, timeout), \
                f"no matching message in {self.messages[-5:]!r}"
        return found[-1]


def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
    """Poll a condition the source exposes only as state (no event): 10 ms steps, deadline."""
    deadline = time.monotonic() + timeout
    ev = threading.Event()
    while not predicate():
        if time.monotonic() >= deadline:
            return False
        ev.wait(0.01)
    return True


class SkewClock:
    """time.monotonic() plus an offset a test moves forward (the 8 s silence without waiting)."""

    def __init__(self) -> None:
        self.offset = 0.0

    def __call__(self) -> float:
        return time.monotonic() + self.offset


@pytest.fixture
def sim() -> Any:
    s = FlightSim()
    yield s
    s.close()


# -- against the simulator, over TCP ---------------------------------------------------------


def test_connects_and_emits_vehicle_position_battery(sim: FlightSim) -> None:
    got = Collector()
    src = UavtalkSource(UavtalkSourceOptions(url=f"tcp:127.0.0.1:{sim.port}", rate_hz=20.0))
    src.vehicle = "revo"  # the gateway names it from the configuration
    src.start(got)
    try:
        assert wait_until(lambda: src.state == Status.CONNECTED, 5.0), src.stats()
        assert sim.wait(lambda: sim.state == CONNECTED)
        state = got.wait_for(lambda m: isinstance(m, VehicleState) and m.roll_rad is not None)
        assert state.armed is True
        assert state.mode == "Stabilized2" and state.custom_mode == MODES.index("Stabilized2")
        assert state.roll_rad == pytest.approx(math.radians(10.0))
        assert state.pitch_rad == pytest.approx(math.radians(-5.0))
        assert state.yaw_rad == pytest.approx(math.radians(90.0))
        pos = got.wait_for(lambda m: isinstance(m, Position))
        assert pos.lat_deg == pytest.approx(47.3977418)
        assert pos.lon_deg == pytest.approx(8.5455939)
        assert pos.alt_amsl_m == pytest.approx(488.0)
        assert pos.ground_speed_mps == pytest.approx(3.5)
        assert pos.course_deg == pytest.approx(45.0)
        assert (pos.satellites, pos.fix_type) == (11, 3)
        bat = got.wait_for(lambda m: isinstance(m, Battery))
        assert bat.voltage_v == pytest.approx(11.1, rel=1e-6)
        assert bat.current_a == pytest.approx(4.5)
        assert bat.consumed_mah == pytest.approx(250.0)
        assert wait_until(lambda: src.session.walk_done)
        # BaroSensor comes after FlightStatus in the walk: a later state carries its altitude
        alt = got.wait_for(lambda m: isinstance(m, VehicleState) and m.altitude_m is not None)
        assert alt.altitude_m == pytest.approx(123.5)
        assert "SystemAlarms" in sim.nacked and src.session.walk_nacked == ["SystemAlarms"]
        with got.cond:
            msgs = list(got.messages)
        assert all(m.origin == src.name and m.via == "uavtalk" for m in msgs)
        assert {m.vehicle for m in msgs} == {"revo"}  # one flight controller: one vehicle
        st = src.stats()
        assert st["connects"] == 1 and st["state"] == "connected" and st["link"] == 1
        assert st["bad_objects"] == 0 and st["rx_obj"] > 0 and st["tx_obj_req"] >= 7
    finally:
        src.stop()
    assert src.done.is_set()


def test_vehicle_state_is_rate_limited(sim: FlightSim) -> None:
    got = Collector()
    src = UavtalkSource(UavtalkSourceOptions(url=f"tcp:127.0.0.1:{sim.port}", rate_hz=2.0))
    src.start(got)
    try:
        got.wait_for(lambda m: isinstance(m, VehicleState) and m.roll_rad is not None)
        # ~20 AttitudeState a second arrive; 2 Hz lets one through every 500 ms
        rx0, n0, t0 = src.stats()["rx_obj"], src.counts["vehicle_states"], time.monotonic()
        assert wait_until(lambda: src.stats()["rx_obj"] >= rx0 + 40, 10.0)
        emitted = src.counts["vehicle_states"] - n0
        assert 1 <= emitted <= 2.0 * (time.monotonic() - t0) + 2, emitted
    finally:
        src.stop()


def test_silence_disconnects_and_a_new_handshake_reconnects(sim: FlightSim) -> None:
    clock = SkewClock()
    got = Collector()
    src = UavtalkSource(UavtalkSourceOptions(url=f"tcp:127.0.0.1:{sim.port}"), clock=clock)
    src.start(got)
    try:
        assert wait_until(lambda: src.state == Status.CONNECTED, 5.0)
        sim.silent.set()
        assert sim.quiet.wait(2.0)

        def nine_seconds_later() -> bool:
            # 9 s of the flight controller's silence on the session's clock per look (a packet
            # still in flight when the simulator fell quiet only restarts the count)
            clock.offset += 9.0
            return src.state != Status.CONNECTED

        assert wait_until(nine_seconds_later, 2.0)
        assert src.stats()["disconnects"] == 1
        with got.cond:
            n = len(got.messages)
        sim.silent.clear()
        # the next HandshakeReq (every 2 s) reconnects, on the same TCP connection
        assert wait_until(lambda: src.state == Status.CONNECTED, 5.0), src.stats()
        st = src.stats()
        assert st["connects"] == 2 and st["opens"] == 1 and st["state_changes"] >= 4
        got.wait_for(lambda m: isinstance(m, VehicleState)
                     and got.messages.index(m) >= n)
    finally:
        src.stop()


def test_a_closed_connection_is_reopened_with_a_fresh_handshake() -> None:
    sim = FlightSim()
    port = sim.port
    src = UavtalkSource(UavtalkSourceOptions(url=f"tcp:127.0.0.1:{port}", reconnect_max_s=0.2))
    got = Collector()
    src.start(got)
    try:
        assert wait_until(lambda: src.state == Status.CONNECTED, 5.0)
        sim.close()  # the flight controller goes away (its connection and listener)
        # the link goes down, and then (on_link(False), on the loop's thread, a moment after
        # the engine clears its link) the session of the lost connection is gone
        assert wait_until(lambda: src.stats()["link"] == 0, 5.0)
        assert wait_until(lambda: src.state != Status.CONNECTED, 5.0)
        sim2 = FlightSim(port)  # it comes back on the same port
        try:
            assert wait_until(lambda: src.state == Status.CONNECTED, 5.0), src.stats()
            st = src.stats()
            assert st["opens"] == 2 and st["connects"] == 2 and st["link_changes"] >= 3
        finally:
            sim2.close()
    finally:
        src.stop()


# -- the wiring, without a port -----------------------------------------------------------


def _packet(name: str, values: dict[str, Any]) -> bytes:
    obj = OBJECTS.by_name(name)
    return encode(Packet(PacketType.OBJ, obj.id, 0, obj.pack(values)))


def test_objects_become_messages_and_a_bad_one_is_counted() -> None:
    now = [100.0]
    src = UavtalkSource(UavtalkSourceOptions(url="tcp:127.0.0.1:9"), objects=OBJECTS,
                        clock=lambda: now[0])
    assert src.feed(_packet("AttitudeState", {"Roll": 1.0})) == []  # no FlightStatus yet
    out = src.feed(_packet("FlightStatus", {"Armed": 0, "FlightMode": 0}))
    assert [type(m) for m in out] == [VehicleState]
    assert (out[0].armed, out[0].mode) == (False, "Manual")
    assert out[0].roll_rad == pytest.approx(math.radians(1.0))
    # rate limit: more attitude at the same instant is held back; arming forces one out
    assert src.feed(_packet("AttitudeState", {"Roll": 2.0})) == []
    out = src.feed(_packet("FlightStatus", {"Armed": 2, "FlightMode": 0}))
    assert out[0].armed is True and out[0].roll_rad == pytest.approx(math.radians(2.0))
    now[0] += 0.2
    out = src.feed(_packet("PositionState", {"Down": -42.0}) + _packet("AttitudeState", {}))
    assert out[0].altitude_m == pytest.approx(42.0)
    # no fix: no position; NaN voltage: counted, not raised
    assert src.feed(_packet("GPSPositionSensor", {"Status": 1})) == []
    assert src.feed(_packet("FlightBatteryState", {"Voltage": math.nan})) == []
    st = src.stats()
    assert st["no_fix"] == 1 and st["bad_objects"] == 1 and st["objects"] == 8
    # one message of each kind split byte by byte
    now[0] += 1.0
    stream = _packet("GPSPositionSensor", _values()["GPSPositionSensor"]) + \
        _packet("FlightBatteryState", {"Voltage": 12.0})
    out = [m for b in stream for m in src.feed(bytes((b,)))]
    assert [type(m) for m in out] == [Position, Battery]


def test_url_parsing_and_config() -> None:
    def fields(url: str) -> tuple[str, int, str]:
        e = parse_url(url)
        return e.kind, e.port or e.baudrate, e.host or e.device

    assert fields("tcp:127.0.0.1:5760") == ("tcp", 5760, "127.0.0.1")
    assert fields("/dev/ttyACM0,115200") == ("serial", 115200, "/dev/ttyACM0")
    assert fields("loop://") == ("serial", 0, "loop://")
    assert fields("serial:/dev/ttyUSB1,57600") == ("serial", 57600, "/dev/ttyUSB1")
    assert fields("tcp::5760") == ("tcp", 5760, "127.0.0.1")  # no HOST: the grammar's default
    for bad in ("tcp:host", "tcp:h:99999", "/dev/x,fast", "nosuch://x", ""):
        with pytest.raises(ValueError):
            parse_url(bad)
    assert parse_source_url("uavtalk:tcp:h:1") == ("uavtalk", {"url": "tcp:h:1"})
    kind, opts = parse_source_url("uavtalk:")  # the url key refuses the empty endpoint
    with pytest.raises(ConfigError, match=r"--source\[0\]\.url: empty endpoint; expected tcp:"):
        config.make_source(kind, opts, None, "--source[0]")
    opts = UavtalkSource.CONFIG.validate({"url": "/dev/ttyUSB0,57600"}, "sources[0]")
    assert opts["rate_hz"] == 10.0
    src = UavtalkSource(UavtalkSourceOptions(**opts))
    assert (src.kind, src.device, src.baudrate) == ("serial", "/dev/ttyUSB0", 57600)
    with pytest.raises(config.ConfigError, match="url"):
        UavtalkSource.CONFIG.validate({"url": "tcp:nohost"}, "sources[0].url")


# -- end to end: the gateway's UAVTalk backend (a simulated flight) as the flight controller --


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_simulated_flight_served_over_uavtalk_arrives_as_vehicle_states() -> None:
    pytest.importorskip("backends.uavtalk.backend")
    from helpers import Running

    port = _free_port()
    flight = Running("run", "--source", "sim", "--sim-speed", "4", "--only", "uavtalk",
                     "--uavtalk", f"tcpin:127.0.0.1:{port}", "--status-interval", "0",
                     "--duration", "30")
    got = Collector()
    src = UavtalkSource(UavtalkSourceOptions(url=f"tcp:127.0.0.1:{port}", reconnect_max_s=0.2))
    src.start(got)  # retried with backoff until the gateway listens
    try:
        assert wait_until(lambda: src.state == Status.CONNECTED, 10.0), flight.text("stderr")
        armed = got.wait_for(lambda m: isinstance(m, VehicleState) and m.armed
                             and m.roll_rad is not None, 15.0)
        assert armed.mode in MODES and armed.origin == src.name and armed.via == "uavtalk"
        assert all(math.isfinite(a) for a in (armed.roll_rad, armed.pitch_rad, armed.yaw_rad))
        # the flight leaves the pad: the backend's mode for BOOST/BURNOUT (AutoTakeoff/Cruise)
        got.wait_for(lambda m: isinstance(m, VehicleState)
                     and m.mode in ("AutoTakeoff", "AutoCruise"), 15.0)
        assert src.session.walk_done and src.stats()["bad_objects"] == 0
    finally:
        src.stop()
        flight.kill()


def test_uavtalk_in_mavlink_out_two_gateways() -> None:
    """``run --source sim --uavtalk tcpin:…`` and ``run --source uavtalk:tcp:… --only mavlink
    --mavlink udpout:…``, a pymavlink ground station on the second's output."""
    pytest.importorskip("backends.uavtalk.backend")
    from helpers import Running
    from mavlink_peer import MavPeer

    port = _free_port()
    peer = MavPeer()
    flight = Running("run", "--source", "sim", "--sim-speed", "4", "--only", "uavtalk",
                     "--uavtalk", f"tcpin:127.0.0.1:{port}", "--status-interval", "0",
                     "--duration", "40")
    gcs = Running("run", "--source", f"uavtalk:tcp:127.0.0.1:{port}", "--only", "mavlink",
                  "--mavlink", f"udpout:127.0.0.1:{peer.port}", "--status-interval", "0",
                  "--duration", "12")
    try:
        assert gcs.wait_line("stderr", lambda ln: "connected: handshake" in ln, 10.0), \
            gcs.text("stderr")
        # the flight side says so too, once the handshake is done (not at the TCP accept)
        assert flight.wait_line("stderr", lambda ln: "uavtalk: GCS connected:" in ln, 5.0), \
            flight.text("stderr")
        assert len(peer.wait_for("HEARTBEAT", count=2, timeout=5.0)) >= 2
        assert peer.wait_for("ATTITUDE", timeout=8.0), "no ATTITUDE from the UAVTalk vehicle"
        assert peer.wait_for("HEARTBEAT", lambda m: m.base_mode & 128, timeout=10.0), \
            "the flight never showed as armed"
        assert gcs.finish() == 0
        report = gcs.text("stderr")
        assert "vehicle_state" in report, report
    finally:
        gcs.kill()
        flight.kill()
        peer.close()
