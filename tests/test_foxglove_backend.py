"""The Foxglove live backend against a Foxglove WebSocket client written here with the
``websockets`` library (the protocol's ``foxglove.websocket.v1``: serverInfo, advertise,
subscribe, binary messageData).  Protobuf channels are decoded with the field numbers read
from the advertised schema (a FileDescriptorSet), by a small wire-format reader of our own."""

from __future__ import annotations

import argparse
import base64
import contextlib
import json
import math
import socket
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import wait_for
from hypothesis import given, settings
from hypothesis import strategies as st
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from backends.foxglove.backend import (
    MAX_VEHICLES,
    UNNAMED,
    FoxgloveBackend,
    quaternion_from_euler,
)
from backends.foxglove.options import FoxgloveOptions
from gateway import config, registry
from gateway.backend import GatewayContext, Outcome
from gateway.dispatcher import Dispatcher
from gateway.model import LinkStats, Position, SmUpdate, Status
from gateway.vehicles import SERVICE as VEHICLES
from gateway.vehicles import SourceVehicle

DEADLINE_S = 5.0
# The protocol's name since foxglove-sdk 0.15-ish, and the older one (the messages are the
# same): the backend serves clients offering either (test_a_client_offering_only_the_legacy_
# name_is_served).
SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
LEAVES = ("state", "altitude", "attitude", "position", "link", "status")
BACKENDS = "/aurora/backends"


def topics(vehicle: str) -> set[str]:
    """A vehicle's topics."""
    return {f"/aurora/{vehicle}/{leaf}" for leaf in LEAVES}


def one_source(name: str = "sim") -> GatewayContext:
    """The context of a gateway with one source, ``name`` (its vehicle has that name)."""
    ctx = GatewayContext()
    ctx.services[VEHICLES] = [SourceVehicle(name, name)]
    return ctx
ROOT = Path(__file__).resolve().parents[1]


# --- a minimal protobuf wire reader (varint, fixed64, length-delimited, fixed32) -------------

def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, i


def wire_fields(buf: bytes) -> Iterator[tuple[int, int, Any]]:
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        num, wt = key >> 3, key & 7
        val: Any
        if wt == 0:
            val, i = _varint(buf, i)
        elif wt == 1:
            val, i = buf[i:i + 8], i + 8
        elif wt == 2:
            n, i = _varint(buf, i)
            val, i = buf[i:i + n], i + n
        elif wt == 5:
            val, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"wire type {wt}")
        yield num, wt, val


def descriptor_messages(fds: bytes) -> dict[str, dict[int, tuple[str, int, str]]]:
    """Full message name → {field number: (name, type, type_name)} from a FileDescriptorSet."""
    out: dict[str, dict[int, tuple[str, int, str]]] = {}
    for num, _, file_bytes in wire_fields(fds):
        assert num == 1  # FileDescriptorSet.file
        package = ""
        messages = []
        for fnum, _, val in wire_fields(file_bytes):
            if fnum == 2:  # FileDescriptorProto.package
                package = val.decode()
            elif fnum == 4:  # message_type
                messages.append(val)
        for msg in messages:
            name, fields = "", {}
            for mnum, _, mval in wire_fields(msg):
                if mnum == 1:
                    name = mval.decode()
                elif mnum == 2:  # FieldDescriptorProto: name 1, number 3, type 5, type_name 6
                    f = {n: v for n, _, v in wire_fields(mval)}
                    fields[f[3]] = (f[1].decode(), f.get(5, 0), f.get(6, b"").decode())
            out[f"{package}.{name}" if package else name] = fields
    return out


def decode_proto(buf: bytes, name: str, msgs: dict[str, dict[int, tuple[str, int, str]]]
                 ) -> dict[str, Any]:
    fields = msgs[name]
    out: dict[str, Any] = {}
    for num, _, val in wire_fields(buf):
        fname, ftype, tname = fields[num]
        if ftype == 1:  # double
            out[fname] = struct.unpack("<d", val)[0]
        elif ftype == 9:  # string
            out[fname] = val.decode()
        elif ftype == 11 and tname.lstrip(".") in msgs:  # message
            out[fname] = decode_proto(val, tname.lstrip("."), msgs)
        else:
            out[fname] = val
    return out


# --- the client -------------------------------------------------------------------------------

class FoxgloveClient:
    """Collects the advertised channels, subscribes, reads messageData frames."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[str, dict[str, Any]] = {}  # topic → advertised channel
        self.by_sub: dict[int, str] = {}
        self.subscribed: set[str] = set()
        self.wait_topics({BACKENDS})

    def wait_topics(self, wanted: set[str]) -> None:
        """Read the server's messages until ``wanted`` topics are advertised."""
        deadline = time.monotonic() + DEADLINE_S
        while self.server_info is None or not set(self.channels) >= wanted:
            msg = self.ws.recv(timeout=max(0.0, deadline - time.monotonic()))
            assert isinstance(msg, str), "binary data before any subscription"
            op = json.loads(msg)
            if op["op"] == "serverInfo":
                self.server_info = op
            elif op["op"] == "advertise":
                for ch in op["channels"]:
                    self.channels[ch["topic"]] = ch

    def subscribe_all(self) -> int:
        """Subscribe to every advertised channel not subscribed yet; the subscriptions held."""
        subs = []
        for topic, ch in sorted(self.channels.items()):
            if topic not in self.subscribed:
                sub_id = len(self.by_sub) + 1
                self.by_sub[sub_id] = topic
                self.subscribed.add(topic)
                subs.append({"id": sub_id, "channelId": ch["id"]})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        return len(self.subscribed)

    def read(self, want: dict[str, int]) -> dict[str, list[tuple[int, bytes]]]:
        """messageData per topic (log time ns, payload) until ``want`` counts arrived."""
        got: dict[str, list[tuple[int, bytes]]] = {t: [] for t in want}
        deadline = time.monotonic() + DEADLINE_S
        while any(len(got[t]) < n for t, n in want.items()):
            msg = self.ws.recv(timeout=max(0.0, deadline - time.monotonic()))
            if isinstance(msg, str):
                continue  # status, (un)advertise…
            assert msg[0] == 0x01  # messageData
            sub_id, log_time = struct.unpack_from("<IQ", msg, 1)
            topic = self.by_sub[sub_id]
            if topic in got:
                got[topic].append((log_time, bytes(msg[13:])))
        return got



@contextlib.contextmanager
def foxglove_client(port: int) -> Iterator[FoxgloveClient]:
    """A client offering both names of the protocol, as the Foxglove app and Lichtblick 1.22
    do (here the older first: the SDK's is chosen all the same)."""
    with connect(f"ws://127.0.0.1:{port}", open_timeout=DEADLINE_S,
                 subprotocols=[Subprotocol(LEGACY_SUBPROTOCOL), Subprotocol(SUBPROTOCOL)]
                 ) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        yield FoxgloveClient(ws)


def sm(i: int) -> SmUpdate:
    return SmUpdate(timestamp_ms=1000 + 50 * i, state=2 + (i % 3), armed=i % 2 == 0, sm_type=0,
                    altitude_m=10.5 * i, acceleration_mps2=-9.81 + i, accel_vert_mps2=0.25 * i,
                    velocity_mps=3.0 * i - 1.0, roll_rad=0.1 * i, pitch_rad=-0.2 + 0.05 * i,
                    yaw_rad=1.0 - 0.3 * i)


def rotate(q: dict[str, float], v: tuple[float, float, float]) -> tuple[float, ...]:
    """v rotated by quaternion q (q v q*), written from the Hamilton product."""
    w, x, y, z = (q.get(k, 0.0) for k in ("w", "x", "y", "z"))

    def mul(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, ...]:
        aw, ax, ay, az = a
        bw, bx, by, bz = b
        return (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)

    r = mul(mul((w, x, y, z), (0.0, *v)), (w, -x, -y, -z))
    return r[1:]


def euler_matrix(roll: float, pitch: float, yaw: float) -> list[list[float]]:
    """Rz(yaw) · Ry(pitch) · Rx(roll): the aerospace Z-Y-X rotation (body → world)."""
    def matmul(a: list[list[float]], b: list[list[float]]) -> list[list[float]]:
        return [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    rz = [[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]]
    ry = [[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]]
    rx = [[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]]
    return matmul(rz, matmul(ry, rx))


def assert_same_rotation(q: dict[str, float], roll: float, pitch: float, yaw: float) -> None:
    m = euler_matrix(roll, pitch, yaw)
    for col, axis in enumerate(((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))):
        got = rotate(q, axis)
        want = [m[row][col] for row in range(3)]
        assert got == pytest.approx(want, abs=1e-9)


# --- tests ------------------------------------------------------------------------------------

def test_a_client_sees_the_channels_and_the_flight() -> None:
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0))
    backend.attach(one_source("sim"))  # a message without a vehicle: the source's, sim
    dispatcher = Dispatcher([backend])
    assert dispatcher.start() == []
    try:
        with foxglove_client(backend.port) as client:
            check_a_flight(backend, dispatcher, client)
            assert backend.stats()["clients"] == 1
        # the server reports the subscriptions of a client that left as unsubscribed
        assert backend.wait_subscriptions(0, DEADLINE_S)
        assert backend.stats()["clients"] == 0
    finally:
        dispatcher.close()
    assert backend.stats()["link"] == 0


def prime(dispatcher: Dispatcher, vehicle: str = "") -> None:
    """One message of each kind, all logged (before any subscription: nobody gets them): a
    vehicle's channels are created at its first message."""
    for msg in (sm(0), Position(lat_deg=0.0, lon_deg=0.0), Status(0, 0, 0, 0), LinkStats()):
        assert dispatcher.dispatch(msg._replace(vehicle=vehicle)) == Outcome.ACCEPTED
    for backend in dispatcher.backends():
        assert isinstance(backend, FoxgloveBackend) and backend.wait_idle(DEADLINE_S)


def check_a_flight(backend: FoxgloveBackend, dispatcher: Dispatcher,
                   client: FoxgloveClient, vehicle: str = "sim") -> None:
    assert client.server_info is not None
    assert set(client.channels) == {BACKENDS}  # no vehicle heard yet: no vehicle channel
    prime(dispatcher)
    client.wait_topics(topics(vehicle))
    assert set(client.channels) == {BACKENDS} | topics(vehicle)
    chans = client.channels
    t = {leaf: f"/aurora/{vehicle}/{leaf}" for leaf in LEAVES}
    for leaf in ("state", "altitude", "link", "status"):
        assert chans[t[leaf]]["encoding"] == "json"
        assert chans[t[leaf]]["schemaEncoding"] == "jsonschema"
        assert json.loads(chans[t[leaf]]["schema"])["type"] == "object"
    assert chans[t["attitude"]]["schemaName"] == "foxglove.FrameTransform"
    assert chans[t["position"]]["schemaName"] == "foxglove.LocationFix"
    for leaf in ("attitude", "position"):
        assert chans[t[leaf]]["encoding"] == "protobuf"
    assert backend.wait_subscriptions(client.subscribe_all(), DEADLINE_S)
    assert backend.stats()["clients"] == 1
    primed = 3 + 3

    updates = [sm(i) for i in range(5)]
    pos = Position(lat_deg=46.5191, lon_deg=6.5668, alt_amsl_m=412.5)
    status = Status(timestamp_ms=4321, state=3, sm_type=0,
                    flags=Status.make_flags(armed=True, baro_ok=True, log_ready=True))
    link = LinkStats(rssi_dbm=-71.0, link_quality_pct=98, snr_db=7.5)
    before = time.time_ns()
    for msg in (*updates, pos, status, link):
        assert dispatcher.dispatch(msg) == Outcome.ACCEPTED
    got = client.read({t["state"]: 5, t["altitude"]: 5, t["attitude"]: 5,
                       t["position"]: 1, t["status"]: 1, t["link"]: 1})
    got = {leaf: got[t[leaf]] for leaf in LEAVES}
    after = time.time_ns()

    for u, (log_time, data) in zip(updates, got["state"], strict=True):
        assert before <= log_time <= after  # log time: when the update reached the gateway
        assert json.loads(data) == {"timestamp_ms": u.timestamp_ms, "state": u.state,
                                    "state_name": u.state_name, "armed": u.armed,
                                    "sm_type": u.sm_type}
    for u, (_, data) in zip(updates, got["altitude"], strict=True):
        d = json.loads(data)
        assert (d["altitude_m"], d["velocity_mps"], d["acceleration_mps2"],
                d["accel_vert_mps2"]) == (u.altitude_m, u.velocity_mps, u.acceleration_mps2,
                                          u.accel_vert_mps2)

    fds = base64.b64decode(chans[t["attitude"]]["schema"])
    msgs = descriptor_messages(fds)
    for u, (_, data) in zip(updates, got["attitude"], strict=True):
        tf = decode_proto(data, "foxglove.FrameTransform", msgs)
        assert (tf["parent_frame_id"], tf["child_frame_id"]) == ("world", vehicle)
        assert tf.get("translation", {}).get("z", 0.0) == u.altitude_m
        assert_same_rotation(tf["rotation"], u.roll_rad, u.pitch_rad, u.yaw_rad)

    msgs = descriptor_messages(base64.b64decode(chans[t["position"]]["schema"]))
    fix = decode_proto(got["position"][0][1], "foxglove.LocationFix", msgs)
    assert fix["frame_id"] == vehicle
    assert (fix["latitude"], fix["longitude"], fix["altitude"]) == (46.5191, 6.5668, 412.5)

    st_ = json.loads(got["status"][0][1])
    assert st_["flags"] == status.flags and st_["state"] == 3
    assert (st_["armed"], st_["imu_ok"], st_["baro_ok"], st_["calibrated"],
            st_["log_ready"]) == (True, False, True, False, True)
    lk = json.loads(got["link"][0][1])
    assert (lk["rssi_dbm"], lk["link_quality_pct"], lk["snr_db"]) == (-71.0, 98, 7.5)
    assert lk["tx_power_mw"] is None

    # the worker counts a message once logged: the client may see it a moment before
    assert wait_for(lambda: backend.stats()["sent"] == primed + 5 * 3 + 3)
    s = backend.stats()
    assert s["dropped"] == 0 and s["errors"] == 0
    assert s["link"] == 1


def test_each_vehicle_has_its_topics_frame_and_own_values() -> None:
    """Two rockets, alpha near 100 m and beta near 500 m: each vehicle's channels carry its
    own rocket's values only, each transform its own frame (world → the vehicle)."""
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0))
    backend.attach(one_source("alpha"))
    dispatcher = Dispatcher([backend])
    assert dispatcher.start() == []
    base = {"alpha": 100.0, "beta": 500.0}
    try:
        with foxglove_client(backend.port) as client:
            for name in base:
                prime(dispatcher, name)
            client.wait_topics(topics("alpha") | topics("beta"))
            assert set(client.channels) == {BACKENDS} | topics("alpha") | topics("beta")
            assert backend.wait_subscriptions(client.subscribe_all(), DEADLINE_S)
            for i in range(10):
                for name, alt in base.items():
                    msg = sm(i)._replace(altitude_m=alt + i, vehicle=name)
                    assert dispatcher.dispatch(msg) == Outcome.ACCEPTED
            got = client.read({f"/aurora/{name}/{leaf}": 10 for name in base
                               for leaf in ("altitude", "attitude")})
            msgs = descriptor_messages(base64.b64decode(
                client.channels["/aurora/alpha/attitude"]["schema"]))
            for name, alt in base.items():
                alts = [json.loads(data)["altitude_m"]
                        for _, data in got[f"/aurora/{name}/altitude"]]
                assert alts == [alt + i for i in range(10)]
                for i, (_, data) in enumerate(got[f"/aurora/{name}/attitude"]):
                    tf = decode_proto(data, "foxglove.FrameTransform", msgs)
                    assert (tf["parent_frame_id"], tf["child_frame_id"]) == ("world", name)
                    assert tf["translation"]["z"] == alt + i
        assert backend.stats()["vehicles"] == 2
    finally:
        dispatcher.close()


def test_vehicles_past_the_cap_get_no_channels_and_are_counted() -> None:
    """A peer inventing vehicle names cannot grow the server: past MAX_VEHICLES vehicles,
    their messages are counted and dropped; the vehicles kept still get theirs."""
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0,
                                              queue_depth=MAX_VEHICLES + 100))
    dispatcher = Dispatcher([backend])
    assert dispatcher.start() == []
    try:
        for i in range(MAX_VEHICLES + 30):
            assert dispatcher.dispatch(sm(i)._replace(vehicle=f"v{i}")) == Outcome.ACCEPTED
        assert dispatcher.dispatch(sm(1)._replace(vehicle="v0")) == Outcome.ACCEPTED
        assert backend.wait_idle(DEADLINE_S * 4)
        s = backend.stats()
        assert (s["vehicles"], s["vehicles_refused"]) == (MAX_VEHICLES, 30)
        assert s["sent"] == 3 * (MAX_VEHICLES + 1) and s["errors"] == 0
        assert f"v{MAX_VEHICLES}" not in backend.vehicles and "v0" in backend.vehicles
    finally:
        dispatcher.close()


def test_the_gateways_counters_every_second() -> None:
    counters = {"backends": {"mavlink": {"sent": 12, "dropped": 0, "errors": 1, "link": 1}},
                "sources": {"sim": {"frames": 40}}}
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0))
    backend.attach(GatewayContext(services={"gateway.stats": lambda: counters}))
    dispatcher = Dispatcher([backend])
    assert dispatcher.start() == []
    try:
        with foxglove_client(backend.port) as client:
            chans = client.channels
            assert chans[BACKENDS]["schemaName"] == "aurora.GatewayCounters"
            assert backend.wait_subscriptions(client.subscribe_all(), DEADLINE_S)
            got = client.read({"/aurora/backends": 2})  # one a second, without any update
            assert [json.loads(data) for _, data in got["/aurora/backends"]] == [counters] * 2
    finally:
        dispatcher.close()


def test_a_full_queue_drops_and_counts() -> None:
    b = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0, queue_depth=3))
    # what the dispatcher calls, before init
    assert b.handover.hook(b.send_sm_update)(sm(0)) == Outcome.NOT_READY
    entered, release = threading.Event(), threading.Event()
    real_send = b.send_sm_update

    def stalled(msg: SmUpdate) -> None:  # the loop stuck on the first message
        entered.set()
        release.wait(DEADLINE_S)
        real_send(msg)

    b.send_sm_update = stalled  # type: ignore[method-assign]
    d = Dispatcher([b])
    assert d.start() == []
    try:
        assert d.dispatch(sm(1)) == Outcome.ACCEPTED
        assert entered.wait(DEADLINE_S)
        outcomes = [d.dispatch(sm(i)) for i in range(2, 10)]
        assert outcomes == [Outcome.ACCEPTED] * 3 + [Outcome.QUEUE_FULL] * 5
        s = b.stats()
        assert (s["dropped"], s["dropped_queue_full"], s["dropped_not_ready"]) == (6, 5, 1)
    finally:
        release.set()
        d.close()


def test_close_is_quick_safe_twice_and_frees_the_port() -> None:
    b = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0))
    d = Dispatcher([b])
    assert d.start() == []
    port = b.port
    with foxglove_client(port) as client:
        prime(d)
        client.wait_topics(topics(UNNAMED))
        assert b.wait_subscriptions(client.subscribe_all(), DEADLINE_S)
        for i in range(200):
            d.dispatch(sm(i))
        t0 = time.monotonic()
        b.close()
        assert time.monotonic() - t0 < 1.0
        b.close()
        assert b.stats()["link"] == 0
        assert d.dispatch(sm(0)) == Outcome.NOT_READY
        # The server's listening socket goes: a connect is refused.  foxglove-sdk's stop()
        # closes it on the library's own runtime a moment later (up to ~3 ms measured), so
        # this waits for it, bounded by the close budget.  (Binding the port again would
        # prove less and race: once freed, it may be any process's ephemeral port.)
        assert wait_for(lambda: _refused(port), 1.0)
        with pytest.raises(ConnectionClosed):  # and the client was disconnected
            while True:
                client.ws.recv(timeout=DEADLINE_S)


def test_a_busy_port_is_a_backend_error_naming_it() -> None:
    from gateway.backend import BackendError
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        b = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=port))
        with pytest.raises(BackendError, match=f"127.0.0.1:{port}"):
            b.init()
        b.close()


def test_a_client_offering_only_the_legacy_name_is_served() -> None:
    """Clients of the older generation (Lichtblick up to 1.21, Foxglove Studio, the npm
    ws-protocol client) offer only foxglove.websocket.v1: answered under that name (a client
    must fail a connection named otherwise), the same flight on the same channels.  (Until
    issue 23 the SDK's server refused them with HTTP 400.)"""
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0))
    backend.attach(one_source("sim"))
    dispatcher = Dispatcher([backend])
    assert dispatcher.start() == []
    try:
        with connect(f"ws://127.0.0.1:{backend.port}", open_timeout=DEADLINE_S,
                     subprotocols=[Subprotocol(LEGACY_SUBPROTOCOL)]) as ws:
            assert ws.subprotocol == LEGACY_SUBPROTOCOL
            assert ws.response is not None
            assert ws.response.headers["Sec-WebSocket-Protocol"] == LEGACY_SUBPROTOCOL
            client = FoxgloveClient(ws)
            assert client.server_info is not None
            assert client.server_info["name"] == "aurora-gateway foxglove"
            check_a_flight(backend, dispatcher, client)
        s = backend.stats()
        assert (s["served_legacy"], s["served_sdk"], s["handshakes_refused"]) == (1, 0, 0)
    finally:
        dispatcher.close()


def test_a_client_offering_neither_name_is_refused() -> None:
    backend = FoxgloveBackend(FoxgloveOptions(host="127.0.0.1", port=0))
    backend.init()
    try:
        for protocols in ([Subprotocol("foxglove.websocket.v2")], None):
            with pytest.raises(InvalidStatus, match="400"), connect(
                    f"ws://127.0.0.1:{backend.port}", open_timeout=DEADLINE_S,
                    subprotocols=protocols):
                pass
        assert wait_for(lambda: backend.stats()["handshakes_refused"] == 2)
        assert backend.stats()["served_legacy"] == backend.stats()["served_sdk"] == 0
    finally:
        backend.close()


@settings(max_examples=150, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-math.pi / 2, math.pi / 2),
       st.floats(-math.pi, math.pi))
def test_the_quaternion_is_the_zyx_rotation(roll: float, pitch: float, yaw: float) -> None:
    x, y, z, w = quaternion_from_euler(roll, pitch, yaw)
    assert x * x + y * y + z * z + w * w == pytest.approx(1.0)
    assert_same_rotation({"x": x, "y": y, "z": z, "w": w}, roll, pitch, yaw)


def _flags(*argv: str) -> dict[str, Any] | None:
    mod = registry.load_flags("foxglove")
    parser = argparse.ArgumentParser()
    mod.add_cli_arguments(parser)
    result: dict[str, Any] | None = mod.cli_options(parser.parse_args(list(argv)))
    return result


def test_run_flag_defaults_to_loopback() -> None:
    assert _flags() is None  # off by default
    assert _flags("--foxglove", "8765") == {"host": "127.0.0.1", "port": 8765}
    assert _flags("--foxglove", "0.0.0.0:9000") == {"host": "0.0.0.0", "port": 9000}
    assert _flags("--foxglove", "[::1]:8766") == {"host": "::1", "port": 8766}
    assert _flags("--foxglove", ":8765") == {"host": "127.0.0.1", "port": 8765}  # no HOST
    for bad in ("abc", "host:", "1.2.3.4:70000", "[::1]8765", "::1:8765", "300.1.1.1:1"):
        with pytest.raises(SystemExit):
            _flags("--foxglove", bad)


def test_the_backend_is_registered_with_its_defaults() -> None:
    assert registry.load(registry.BACKEND_GROUP, "foxglove") is FoxgloveBackend
    part = config.make_backend("foxglove", {"host": "127.0.0.1", "port": 9001}, "foxglove",
                               "backends.foxglove")
    assert part.options["port"] == 9001 and part.options["queue_depth"] == 1024


@pytest.mark.parametrize(("table", "key"), [
    ({"port": 70000}, "backends.foxglove.port"),
    ({"port": "8765"}, "backends.foxglove.port"),
    ({"queue_depth": 0}, "backends.foxglove.queue_depth"),
    ({"host": 1}, "backends.foxglove.host"),
    ({"hots": "x"}, "backends.foxglove.hots"),
])
def test_config_errors_name_the_key(table: dict[str, Any], key: str) -> None:
    with pytest.raises(config.ConfigError, match=key.replace(".", r"\.")):
        config.make_backend("foxglove", table, "foxglove", "backends.foxglove")


def test_the_shipped_layout_names_the_channels() -> None:
    layout = json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())
    text = json.dumps(layout["configById"])
    # the default run's vehicle (`run --source sim`: sim) and its frame
    for path in ("/aurora/sim/altitude.altitude_m", "/aurora/sim/altitude.velocity_mps",
                 "/aurora/sim/state", "/aurora/sim/position", "/aurora/sim/attitude"):
        assert path in text
    assert '"followTf": "sim"' in text and "/aurora/altitude" not in text
    assert "layout" in layout  # the panel tree refers to panels that are configured
    ids = set(layout["configById"])

    def leaves(node: Any) -> Iterator[str]:
        if isinstance(node, str):
            yield node
        else:
            yield from leaves(node["first"])
            yield from leaves(node["second"])
    assert set(leaves(layout["layout"])) == ids


def _refused(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.connect(("127.0.0.1", port))
        except ConnectionRefusedError:
            return True
    return False
