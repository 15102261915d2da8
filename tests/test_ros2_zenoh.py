"""The ROS 2 topics on Zenoh as rmw_zenoh carries them (backends/ros2/rmw_zenoh.py,
docs/rmw-zenoh.md): the wire conventions against the facts, then the zenoh backend's session
carrying them to a real Zenoh subscriber — keys, CDR payloads (decoded by ``rosbags``),
attachments (decoded by Zenoh's own deserializer), liveliness tokens, and the latched state a
late joiner gets from the publisher's cache."""

from __future__ import annotations

import os
import random
import re
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers import ROOT, post
from zenoh.ext import (
    HistoryConfig,
    Int64,
    declare_advanced_subscriber,
    z_deserialize,
    z_serialize,
)
from zenoh_peer import free_endpoint, peer_config, serving, wait_for_gateway, wait_until

xxhash = pytest.importorskip("xxhash")  # (the ros2 extra)
typesys = pytest.importorskip("rosbags.typesys")

from backends.ros2 import rmw_zenoh  # noqa: E402
from backends.ros2.topics import RosTopics  # noqa: E402
from backends.ros2.types import FLOAT64, STRING  # noqa: E402
from backends.zenoh.backend import ZenohBackend  # noqa: E402
from backends.zenoh.keys import DEFAULT_PREFIX  # noqa: E402
from backends.zenoh.options import ZenohOptions  # noqa: E402
from gateway import wire  # noqa: E402
from gateway.flight import FlightModel  # noqa: E402
from gateway.model import SmUpdate  # noqa: E402
from gateway.sources.sim import flight_messages  # noqa: E402

VEHICLE = "rocket1"
TYPESTORE = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


# -- the wire conventions ------------------------------------------------------------------------

def test_a_topic_key_is_domain_topic_type_and_hash() -> None:
    assert rmw_zenoh.topic_key(0, "/aurora/rocket1/altitude", FLOAT64.dds_name,
                               FLOAT64.rihs01) == (
        "0/aurora/rocket1/altitude/std_msgs::msg::dds_::Float64_/" + FLOAT64.rihs01)
    assert rmw_zenoh.topic_key(7, "/tf", "tf2_msgs::msg::dds_::TFMessage_", "RIHS01_x") == \
        "7/tf/tf2_msgs::msg::dds_::TFMessage_/RIHS01_x"


def test_qos_chunks_leave_rmw_zenohs_defaults_empty() -> None:
    assert rmw_zenoh.qos_text(rmw_zenoh.Qos()) == "::,10:,:,:,,"
    assert rmw_zenoh.qos_text(rmw_zenoh.LATCHED) == ":1:,1:,:,:,,"
    assert rmw_zenoh.qos_text(rmw_zenoh.Qos(reliable=False, depth=5)) == "2::,5:,:,:,,"
    assert rmw_zenoh.qos_text(rmw_zenoh.Qos(depth=42)) == "::,:,:,:,,"


def _read_qos(text: str) -> dict[str, int]:
    """A QoS chunk read back as rmw_zenoh's ``keyexpr_to_qos`` does: six ``:`` parts; history,
    deadline and lifespan two ``,`` parts each, liveliness three; an empty value is the
    default (reliable 1, volatile 2, keep last 1, depth 42)."""
    parts = text.split(":")
    assert len(parts) == 6, text
    history, deadline, lifespan = (p.split(",") for p in parts[2:5])
    liveliness = parts[5].split(",")
    assert len(history) == len(deadline) == len(lifespan) == 2 and len(liveliness) == 3, text
    assert not any(deadline + lifespan + liveliness), text  # all defaults (infinite, automatic)
    return {"reliability": int(parts[0] or 1), "durability": int(parts[1] or 2),
            "history": int(history[0] or 1), "depth": int(history[1] or 42)}


def test_qos_chunks_read_back_as_rmw_zenoh_reads_them() -> None:
    assert _read_qos(rmw_zenoh.qos_text(rmw_zenoh.STREAM)) == {
        "reliability": 1, "durability": 2, "history": 1, "depth": 10}
    assert _read_qos(rmw_zenoh.qos_text(rmw_zenoh.LATCHED)) == {
        "reliability": 1, "durability": 1, "history": 1, "depth": 1}
    assert _read_qos(rmw_zenoh.qos_text(rmw_zenoh.Qos(reliable=False, depth=42))) == {
        "reliability": 2, "durability": 2, "history": 1, "depth": 42}


def test_tokens_name_the_node_and_each_publisher_with_slashes_mangled() -> None:
    zid = "1f2e3d4c5b6a"
    assert rmw_zenoh.node_token(0, zid, 0) == f"@ros2_lv/0/{zid}/0/0/NN/%/%/aurora_gateway"
    assert rmw_zenoh.publisher_token(0, zid, 0, 3, "/aurora/rocket1/state", STRING.dds_name,
                                     STRING.rihs01, rmw_zenoh.LATCHED) == (
        f"@ros2_lv/0/{zid}/0/3/MP/%/%/aurora_gateway/%aurora%rocket1%state/"
        f"std_msgs::msg::dds_::String_/{STRING_HASH}/:1:,1:,:,:,,")
    # every chunk is non-empty and one chunk (rmw_zenoh splits the token on '/')
    token = rmw_zenoh.publisher_token(5, zid, 0, 1, "/tf", "a::b", "RIHS01_y", rmw_zenoh.Qos())
    assert len(token.split("/")) == 13 and all(token.split("/"))


def test_the_gid_is_xxh3_128_low_half_first() -> None:
    """XXH3-128 of the empty input is 0x99aa06d3014798d8_6001c324468d497f (xxHash's test
    vector): the GID holds the low 64 bits then the high, each little endian."""
    assert rmw_zenoh.entity_gid("") == bytes.fromhex("7f498d4624c30160d8984701d306aa99")
    assert len(rmw_zenoh.entity_gid("@ros2_lv/0/x/0/0/NN/%/%/n")) == 16


def test_the_attachment_is_what_zenohs_serializer_reads_as_int64_int64_16_bytes() -> None:
    gid = bytes(range(16))
    att = rmw_zenoh.attachment(7, 1_790_000_000_123_456_789, gid)
    assert z_deserialize(tuple[Int64, Int64, bytes],
                                   zenoh.ZBytes(att)) == (7, 1_790_000_000_123_456_789, gid)
    # and what Zenoh's serializer writes for those three values, byte for byte
    assert z_serialize((Int64(7), Int64(1_790_000_000_123_456_789),
                                  gid)).to_bytes() == att
    assert rmw_zenoh.parse_attachment(att) == (7, 1_790_000_000_123_456_789, gid)
    with pytest.raises(ValueError):
        rmw_zenoh.parse_attachment(att[:-1])
    with pytest.raises(ValueError):
        rmw_zenoh.attachment(1, 2, b"short")


# -- through the zenoh backend's session ----------------------------------------------------------

def _flight(n: int) -> list[Any]:
    """The first ``n`` messages of the simulated flight as the gateway decodes them."""
    out = []
    for _, m in flight_messages(FlightModel(), 10.0, 1.0, 1):
        out.append(wire.decode_all(wire.encode(m), origin="sim", vehicle=VEHICLE)[0])
        if len(out) == n:
            break
    return out


class _Samples:
    """What a subscriber got: (key, payload, attachment), with a condition to wait on."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes, bytes]] = []
        self.cond = threading.Condition()

    def __call__(self, sample: Any) -> None:
        att = sample.attachment
        with self.cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes(),
                               b"" if att is None else att.to_bytes()))
            self.cond.notify_all()

    def wait(self, n: int, timeout: float = 20.0) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: len(self.items) >= n, timeout)


def _tokens(session: Any) -> list[str]:
    """The ROS graph's liveliness tokens on domain 0 that ``session`` reaches."""
    out = []
    for reply in session.liveliness().get("@ros2_lv/0/**", timeout=10):
        assert reply.ok is not None
        out.append(str(reply.ok.key_expr))
    return out


@pytest.fixture
def endpoint() -> str:
    return free_endpoint()


def _backend(endpoint: str, ros: bool = True) -> ZenohBackend:
    b = serving(ZenohBackend(ZenohOptions(listen=[endpoint], gateway_id="gw-ros")), VEHICLE,
                source="sim")
    if ros:
        rmw_zenoh.request(b.context, 0)  # what the ros2 backend does in its attach
    b.init()
    assert b.wait_ready(20), "the session did not open"
    return b


@pytest.fixture
def session(endpoint: str) -> Any:
    s = zenoh.open(peer_config(connect=[endpoint]))
    yield s
    s.close()


def _post_all(backend: ZenohBackend, msgs: list[Any]) -> None:
    """Hand every message over, a batch at a time so the bounded hand-over never drops."""
    for i in range(0, len(msgs), 50):
        for m in msgs[i:i + 50]:
            post(backend, m)
        assert backend.wait_idle(20)


def test_a_flight_reaches_an_rmw_zenoh_subscriber_with_its_attachments_and_tokens(
        endpoint: str, session: Any) -> None:
    backend = _backend(endpoint)
    try:
        got = _Samples()
        key = f"0/aurora/{VEHICLE}/altitude/std_msgs::msg::dds_::Float64_/RIHS01_$*"
        sub = session.declare_subscriber(key, got)
        wait_for_gateway(session, DEFAULT_PREFIX, VEHICLE)
        msgs = _flight(300)
        updates = [m for m in msgs if isinstance(m, SmUpdate)]
        _post_all(backend, msgs)
        assert got.wait(len(updates)), f"{len(got.items)} of {len(updates)} altitudes"
        sub.undeclare()

        keys = {k for k, _, _ in got.items}
        assert keys == {f"0/aurora/{VEHICLE}/altitude/std_msgs::msg::dds_::Float64_/"
                        + FLOAT64.rihs01}
        altitudes = [TYPESTORE.deserialize_cdr(p, "std_msgs/msg/Float64").data
                     for _, p, _ in got.items]
        assert altitudes == [u.altitude_m for u in updates]
        decoded = [z_deserialize(
            tuple[Int64, Int64, bytes], zenoh.ZBytes(a))
            for _, _, a in got.items]
        assert [seq for seq, _, _ in decoded] == list(range(1, len(updates) + 1))
        assert all(ts > 1_600_000_000 * 10**9 for _, ts, _ in decoded)
        gids = {gid for _, _, gid in decoded}
        assert len(gids) == 1

        # the graph: the node's token and the altitude publisher's, whose hash is the GID
        tokens = _tokens(session)
        zid = str(backend._session.info.zid())
        assert f"@ros2_lv/0/{zid}/0/0/NN/%/%/aurora_gateway" in tokens, tokens
        altitude_tokens = [t for t in tokens if re.fullmatch(
            rf"@ros2_lv/0/{zid}/0/\d+/MP/%/%/aurora_gateway/%aurora%{VEHICLE}%altitude/"
            rf"std_msgs::msg::dds_::Float64_/{FLOAT64.rihs01}/::,10:,:,:,,", t)]
        assert len(altitude_tokens) == 1, tokens
        assert rmw_zenoh.entity_gid(altitude_tokens[0]) == gids.pop()
        assert any("/MP/%/%/aurora_gateway/%tf/tf2_msgs::msg::dds_::TFMessage_/" in t
                   for t in tokens)
        assert any(f"/%aurora%{VEHICLE}%state/std_msgs::msg::dds_::String_/{STRING_HASH}/"
                   ":1:,1:,:,:,," in t for t in tokens)
        stats = backend.stats()
        assert stats["ros2_puts"] >= 3 * len(updates)
        assert stats["ros2_sample_errors"] == stats["ros2_put_errors"] == 0
    finally:
        backend.close()
    # closed: its tokens are gone
    assert wait_until(lambda: not list(session.liveliness().get("@ros2_lv/0/**", timeout=5)))


def test_a_late_joiner_gets_the_current_state_from_the_publishers_cache(
        endpoint: str, session: Any) -> None:
    """A transient-local subscription on rmw_zenoh is an advanced subscriber that queries
    the caches of the publishers it detects: the state topic's last value arrives at once."""
    backend = _backend(endpoint)
    try:
        wait_for_gateway(session, DEFAULT_PREFIX, VEHICLE)
        msgs = _flight(400)
        _post_all(backend, msgs)
        last_state = [m.state_name for m in msgs if isinstance(m, SmUpdate)][-1]
        got = _Samples()
        key = f"0/aurora/{VEHICLE}/state/std_msgs::msg::dds_::String_/{STRING_HASH}"
        sub = declare_advanced_subscriber(
            session, key, got,
            history=HistoryConfig(detect_late_publishers=True))
        assert got.wait(1), "no state from the cache"
        sub.undeclare()
        assert TYPESTORE.deserialize_cdr(got.items[-1][1], "std_msgs/msg/String").data == \
            last_state
        seq, _, _ = rmw_zenoh.parse_attachment(got.items[-1][2])
        assert seq >= 1
    finally:
        backend.close()


def test_without_the_ros2_backend_the_zenoh_backend_puts_no_ros_topic(
        endpoint: str, session: Any) -> None:
    backend = _backend(endpoint, ros=False)
    try:
        got = _Samples()
        sub = session.declare_subscriber("0/**", got)
        wait_for_gateway(session, DEFAULT_PREFIX, VEHICLE)
        _post_all(backend, _flight(20))
        assert not list(session.liveliness().get("@ros2_lv/**", timeout=2))
        sub.undeclare()
        assert got.items == []
        assert not any(k.startswith("ros2_") for k in backend.stats())
    finally:
        backend.close()


def test_a_message_naming_no_vehicle_is_the_first_configured_sources() -> None:
    """As on DDS: the request found in a context whose first source is vehicle ``alpha``."""
    from gateway import vehicles
    from gateway.backend import GatewayContext

    context = GatewayContext()
    assert rmw_zenoh.bridge_for(context) is None  # the ros2 backend asked for nothing
    context.services[vehicles.SERVICE] = [vehicles.SourceVehicle("sim", "alpha"),
                                          vehicles.SourceVehicle("sim-2", "beta")]
    rmw_zenoh.request(context, 3)
    bridge = rmw_zenoh.bridge_for(context)
    assert bridge is not None and bridge.domain_id == 3
    update = next(m for m in _flight(5) if isinstance(m, SmUpdate))._replace(vehicle="")
    assert {s.topic for s in bridge._samples(update)} >= {"/aurora/alpha/altitude", "/tf"}
    bridge.handle(update)  # no session yet: counted, not raised
    assert bridge.stats()["ros2_dropped_no_session"] >= 1


def test_topics_beyond_the_limit_are_counted_not_published(
        endpoint: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rmw_zenoh, "MAX_TOPICS", 2)
    s = zenoh.open(peer_config(listen=[endpoint]))
    bridge = rmw_zenoh.RmwZenoh(0)
    try:
        bridge.declare(s)
        updates = [m for m in _flight(30) if isinstance(m, SmUpdate)][:4]
        topics = RosTopics()
        samples = [s.topic for m in updates for s in topics.samples(m)]
        first_two = list(dict.fromkeys(samples))[:2]
        for m in updates:
            bridge.handle(m)
        stats = bridge.stats()
        assert stats["ros2_topics"] == 2
        assert stats["ros2_puts"] == sum(t in first_two for t in samples)
        assert stats["ros2_dropped_topic_limit"] == sum(t not in first_two for t in samples) > 0
        tokens = _tokens(s)
        assert sum("/MP/" in t for t in tokens) == 2 and sum("/NN/" in t for t in tokens) == 1
    finally:
        bridge.undeclare()
        s.close()


# -- the command line, as a user runs it ----------------------------------------------------------

LOOPBACK_DDS = """<CycloneDDS><Domain id="any">
  <General><Interfaces><NetworkInterface name="lo"/></Interfaces>
    <AllowMulticast>false</AllowMulticast></General>
  <Discovery><Peers><Peer address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""
STATES = ["IDLE", "ARMED", "BOOST", "BURNOUT", "APOGEE", "MAIN", "REDUNDANT", "LANDED"]


@pytest.mark.parametrize("how", ["flags", "config"])
def test_run_ros2_puts_the_flight_on_rmw_zenoh_through_the_zenoh_backends_endpoints(
        tmp_path: Path, how: str) -> None:
    """``run --source rocket1=sim --ros2 --zenoh-connect …`` (or a file with
    ``[backends.ros2]`` and ``[backends.zenoh]``) with ``ROS_DOMAIN_ID`` set: a Zenoh peer the
    gateway connects to gets the altitudes to the apogee, the states in order (as a
    transient-local subscription: an advanced subscriber), the graph's tokens."""
    pytest.importorskip("cyclonedds")
    domain = random.SystemRandom().randrange(1, 230)
    dds = tmp_path / "cyclonedds.xml"
    dds.write_text(LOOPBACK_DDS)
    endpoint = free_endpoint()
    s = zenoh.open(peer_config(listen=[endpoint]))
    altitudes = _Samples()
    states = _Samples()
    tokens = _Samples()
    try:
        s.declare_subscriber(
            f"{domain}/aurora/rocket1/altitude/std_msgs::msg::dds_::Float64_/RIHS01_$*",
            altitudes)
        declare_advanced_subscriber(
            s, f"{domain}/aurora/rocket1/state/std_msgs::msg::dds_::String_/{STRING_HASH}",
            states, history=HistoryConfig(detect_late_publishers=True))
        s.liveliness().declare_subscriber(f"@ros2_lv/{domain}/**", tokens)
        env = {**os.environ, "ROS_DOMAIN_ID": str(domain), "CYCLONEDDS_URI": dds.as_uri(),
               "PYTHONPATH": str(ROOT)}
        if how == "flags":
            args = ["--source", "rocket1=sim", "--sim-speed", "20", "--ros2", "--zenoh-connect",
                    endpoint, "--only", "zenoh", "--only", "ros2", "--duration", "8"]
        else:
            (tmp_path / "gw.toml").write_text(
                '[[sources]]\ntype = "sim"\nvehicle = "rocket1"\nspeed = 20.0\ncycles = 1\n'
                f'[backends.zenoh]\nconnect = ["{endpoint}"]\n'
                '[backends.ros2]\nnode = "ground_station"\n')  # (its DDS node's name too)
            args = ["-c", "gw.toml", "--duration", "30"]  # (the flight ends it)
        proc = subprocess.run(
            [sys.executable, "-m", "gateway", "run", *args, "--status-interval", "0"],
            cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr
        apogee = float(re.search(r"max altitude (\S+) m", proc.stderr)[1])  # type: ignore[index]
        got = [TYPESTORE.deserialize_cdr(p, "std_msgs/msg/Float64").data
               for _, p, _ in altitudes.items]
        assert got and round(max(got), 1) == apogee
        top = got.index(max(got))
        assert got[0] < 1.0 and got[top // 2] < got[top]  # from the pad, rising to the apogee
        names = [TYPESTORE.deserialize_cdr(p, "std_msgs/msg/String").data
                 for _, p, _ in states.items]
        assert names[:len(STATES)] == STATES, names
        keys = {k for k, _, _ in tokens.items}
        node = "aurora_gateway" if how == "flags" else "ground_station"
        assert any(k.startswith(f"@ros2_lv/{domain}/") and f"/MP/%/%/{node}/"
                   "%aurora%rocket1%altitude/std_msgs::msg::dds_::Float64_/RIHS01_" in k
                   for k in keys), keys
        assert any(k.endswith(f"/NN/%/%/{node}") for k in keys), keys
    finally:
        s.close()


def test_a_new_session_gets_new_publishers_and_tokens(endpoint: str, session: Any) -> None:
    """What the zenoh backend does when its session is reopened (a router back): the old
    session's publishers are dropped, the new one's declared afresh, sequence numbers from 1."""
    got = _Samples()
    session.declare_subscriber("0/aurora/rocket1/altitude/**", got)
    first = zenoh.open(peer_config())  # reaches nobody
    second = zenoh.open(peer_config(listen=[endpoint]))
    bridge = rmw_zenoh.RmwZenoh(0)
    updates = [m for m in _flight(30) if isinstance(m, SmUpdate)][:4]
    try:
        bridge.declare(first)
        bridge.handle(updates[0])
        bridge.handle(updates[1])
        bridge.undeclare()
        first.close()
        bridge.declare(second)
        assert wait_until(lambda: any("/NN/" in t for t in _tokens(session)))
        for m in updates[2:]:
            bridge.handle(m)
        assert got.wait(2)
        assert [rmw_zenoh.parse_attachment(a)[0] for _, _, a in got.items] == [1, 2]
        assert [TYPESTORE.deserialize_cdr(p, "std_msgs/msg/Float64").data
                for _, p, _ in got.items] == [m.altitude_m for m in updates[2:]]
        zid = str(second.info.zid())
        assert all(f"/{zid}/" in t for t in _tokens(session))
    finally:
        bridge.undeclare()
        second.close()
