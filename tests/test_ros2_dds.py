"""The ROS 2 backend on real DDS: a Cyclone DDS participant in another process
(``tests/ros2_dds_peer.py``, its own IDL classes named as ROS 2 names them) receives a
simulated flight from the gateway as a ROS 2 node would.

Traffic stays on loopback: every test runs with a ``CYCLONEDDS_URI`` naming ``lo`` only, no
multicast, peer 127.0.0.1; each on a domain of its own (tests run in parallel).
"""

from __future__ import annotations

import itertools
import json
import random
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import DEADLINE_S, ROOT, HeldLoop, Running, wait_for
from rosbags.typesys import Stores, get_typestore

from gateway.model import SmUpdate, Status
from gateway.outcome import Outcome

PEER = [sys.executable, str(ROOT / "tests" / "ros2_dds_peer.py")]
FLIGHT_S = 60.0
LOOPBACK_ONLY = """<CycloneDDS><Domain id="any">
  <General><Interfaces><NetworkInterface name="lo"/></Interfaces>
    <AllowMulticast>false</AllowMulticast></General>
  <Discovery><ParticipantIndex>auto</ParticipantIndex>
    <MaxAutoParticipantIndex>20</MaxAutoParticipantIndex>
    <Peers><Peer address="127.0.0.1"/></Peers></Discovery>
</Domain></CycloneDDS>"""
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
_used_domains: set[int] = set()


@pytest.fixture(autouse=True)
def domain(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> int:
    """A domain of this test's own, on loopback only (``ROS_DOMAIN_ID``, ``CYCLONEDDS_URI``)."""
    config = tmp_path / "cyclonedds.xml"
    config.write_text(LOOPBACK_ONLY)
    monkeypatch.setenv("CYCLONEDDS_URI", config.as_uri())
    rng = random.SystemRandom()
    d = rng.randrange(1, 230)
    while d in _used_domains:
        d = rng.randrange(1, 230)
    _used_domains.add(d)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(d))
    return d


class Peer:
    """The subscriber process: its JSON lines, parsed."""

    def __init__(self, domain: int) -> None:
        self.proc = Running(str(domain), str(FLIGHT_S), cmd=PEER, timeout=FLIGHT_S)
        assert self.proc.wait_line("stdout", lambda ln: '"ready"' in ln, DEADLINE_S), \
            self.proc.text("stderr")

    def records(self) -> list[dict[str, Any]]:
        with self.proc.cond:
            lines = list(self.proc.lines["stdout"])
        return [json.loads(ln) for ln in lines if ln.startswith("{")]

    def values(self, topic: str) -> list[Any]:
        return [r for r in self.records() if r.get("topic") == topic]

    def wait_state(self, name: str, timeout: float) -> bool:
        return self.proc.wait_line("stdout", lambda ln: '"state"' in ln and f'"{name}"' in ln,
                                   timeout)

    def stop(self) -> None:
        self.proc.stop()


@pytest.fixture
def peers() -> Iterator[list[Peer]]:
    started: list[Peer] = []
    yield started
    for p in started:
        p.stop()


def _report(gw: Running) -> tuple[list[str], float]:
    """The states and the max altitude of the gateway's flight summary."""
    text = gw.text("stdout") + gw.text("stderr")
    m = re.search(r"flight rocket1: .*max altitude ([\d.]+) m.*; states ([A-Z ]+)", text)
    assert m, text
    return m[2].split(), float(m[1])


def test_a_ros_2_subscriber_receives_the_flight(domain: int, peers: list[Peer]) -> None:
    peers.append(Peer(domain))
    early = peers[0]
    gw = Running("run", "--only", "ros2", "--source", "rocket1=sim", "--sim-speed", "10",
                 "--ros2", "--status-interval", "0", "--duration", str(FLIGHT_S),
                 timeout=FLIGHT_S)
    try:
        assert early.wait_state("LANDED", FLIGHT_S), gw.text("stderr")
        # a subscriber joining now gets the current state at once (transient local)
        peers.append(Peer(domain))
        assert peers[1].wait_state("LANDED", DEADLINE_S)
        assert [r["data"] for r in peers[1].values("state")] == ["LANDED"]
    finally:
        gw.proc.send_signal(2)  # SIGINT: the stop report
        gw.finish()
    states, apogee = _report(gw)

    # the states in order, each once
    assert [r["data"] for r in early.values("state")] == states
    assert states[0] == "IDLE" and states[-1] == "LANDED" and "APOGEE" in states

    # the altitude rises to the apogee
    alts = [r["data"] for r in early.values("altitude")]
    top = alts.index(max(alts))
    assert max(alts) == pytest.approx(apogee, abs=0.05)
    assert top > 0 and all(a <= b for a, b in itertools.pairwise(alts[:top + 1]))

    # /tf: world → rocket1, z = the altitude of the same update (same source timestamp),
    # its header stamped with that time
    tf_by_ts = {r["ts"]: r for r in early.values("tf")}
    for r in early.values("altitude"):
        tf = tf_by_ts[r["ts"]]
        assert (tf["parent"], tf["child"]) == ("world", "rocket1")
        assert tf["z"] == r["data"]
        assert tf["stamp"] == r["ts"]

    # every writer's USER_DATA names its type's RIHS01 hash; state and armed are latched
    typestore = get_typestore(Stores.ROS2_JAZZY)
    pubs = {r["publication"]: r for r in early.records() if "publication" in r}
    assert {"rt/aurora/rocket1/altitude", "rt/aurora/rocket1/state", "rt/aurora/rocket1/armed",
            "rt/aurora/rocket1/imu", "rt/tf", "rt/diagnostics"} <= set(pubs)
    for topic, p in pubs.items():
        pkg, _, _, name = p["type_name"].split("::")
        expected = typestore.hash_rihs01(f"{pkg}/msg/{name.rstrip('_')}")
        assert p["user_data"] == f"typehash={expected};", topic
        assert p["transient_local"] is topic.endswith(("/state", "/armed")), topic
    assert pubs["rt/aurora/rocket1/state"]["user_data"] == f"typehash={STRING_HASH};"

    # the ROS 2 graph: one node, /aurora_gateway, owning every writer of the gateway's
    graphs = [r for r in early.records() if "graph" in r]
    assert graphs, "nothing on ros_discovery_info"
    latest = graphs[-1]
    (node,) = latest["nodes"]
    assert (node["namespace"], node["name"]) == ("/", "aurora_gateway")
    ours = {p["key"] for p in pubs.values() if p["participant"] == latest["graph"]}
    assert ours and ours == {p["key"] for p in pubs.values()}
    assert ours <= set(node["writers"])
    assert pubs["rt/aurora/rocket1/altitude"]["type_name"] == "std_msgs::msg::dds_::Float64_"


def test_domain_id_key_overrides_ros_domain_id(domain: int, peers: list[Peer],
                                               tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    from backends.ros2.backend import Ros2Backend
    from backends.ros2.options import Ros2Options

    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain + 1 if domain < 229 else domain - 1))
    backend = Ros2Backend(Ros2Options(domain_id=domain, node=""))  # no node announced
    peers.append(Peer(domain))
    backend.init()
    try:
        assert backend.stats()["domain_id"] == domain
        handler = dict(backend.routes())[SmUpdate]

        def got_altitude() -> bool:
            return peers[0].proc.wait_line(
                "stdout", lambda ln: '"topic": "altitude"' in ln, 0.1)

        # a volatile topic's first samples may go before the writer has matched the reader
        posted = 0
        while not got_altitude():
            posted += 1
            assert posted < 100, "no altitude received"
            backend.handover.post(handler, SmUpdate(posted, 4, True, 0, 10.0 + posted, 0, 0,
                                                    0, 0, 0, 0, vehicle="rocket1"))
        assert peers[0].wait_state("APOGEE", DEADLINE_S)
        got = [r["data"] for r in peers[0].values("altitude")]
        assert got and set(got) <= {10.0 + i for i in range(1, posted + 1)}
    finally:
        backend.close()
    assert backend.stats()["sent"] == 3 * posted + 2  # altitude, tf, imu; state, armed once
    assert backend.stats()["announcements"] == 0
    assert not [r for r in peers[0].records() if "graph" in r]
    assert backend.stats()["link"] == 0


def test_a_full_hand_over_is_counted_never_waited_for() -> None:
    from backends.ros2.backend import Ros2Backend
    from backends.ros2.options import Ros2Options
    from gateway.dispatcher import Dispatcher

    backend = Ros2Backend(Ros2Options(queue_depth=8))
    d = Dispatcher([backend])
    assert d.start() == []
    try:
        handover = backend.routes().handover
        assert handover is not None and handover.loop is not None
        status = Status(1000, 1, 0, 0)
        assert wait_for(lambda: d.dispatch(status) is Outcome.ACCEPTED)
        assert handover.barrier(DEADLINE_S)
        with HeldLoop(handover.loop):
            outcomes = [d.dispatch(status) for _ in range(handover.depth + 3)]
        assert outcomes.count(Outcome.QUEUE_FULL) == 3
        stats = backend.stats()
        assert stats["dropped_queue_full"] == 3 and stats["dropped"] >= 3
        assert all(isinstance(stats[k], int) for k in ("sent", "dropped", "errors", "link"))
    finally:
        d.close()


@pytest.mark.parametrize("value", ["abc", "233", "-1"])
def test_a_bad_ros_domain_id_is_one_line_exit_2(value: str,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_DOMAIN_ID", value)
    gw = Running("run", "--only", "ros2", "--source", "sim", "--ros2", "--duration", "1")
    assert gw.finish() == 2
    err = gw.text("stderr").strip().splitlines()
    assert len(err) == 1 and "ROS_DOMAIN_ID" in err[0] and "Traceback" not in err[0], err


@pytest.mark.parametrize(("key", "value"), [("domain_id", "300"), ("node", '"1st"'),
                                             ("node", '"a-b"')])
def test_the_keys_are_checked_like_every_key(key: str, value: str, tmp_path: Path) -> None:
    cfg = tmp_path / "gw.toml"
    cfg.write_text(f'[[sources]]\ntype = "sim"\n[backends.ros2]\n{key} = {value}\n')
    gw = Running("run", "--config", str(cfg), "--duration", "1")
    assert gw.finish() == 2
    err = gw.text("stderr").strip().splitlines()
    assert len(err) == 1 and f"backends.ros2.{key}" in err[0], err


def test_an_empty_ros2_table_enables_the_backend(domain: int, peers: list[Peer],
                                                 tmp_path: Path) -> None:
    cfg = tmp_path / "gw.toml"
    cfg.write_text('[[sources]]\ntype = "sim"\nvehicle = "rocket1"\n\n[backends.ros2]\n')
    peers.append(Peer(domain))
    gw = Running("run", "--config", str(cfg), "--only", "ros2", "--duration", str(FLIGHT_S),
                 timeout=FLIGHT_S)
    try:
        assert peers[0].wait_state("IDLE", DEADLINE_S), gw.text("stderr")
    finally:
        gw.stop()


def test_messages_naming_no_vehicle_go_to_their_source_s(domain: int, peers: list[Peer]) -> None:
    """A message without a vehicle (a radio backend's link stats, a link event) is its
    source's vehicle's; the configured vehicle's writers exist from the start."""
    from backends.ros2.backend import Ros2Backend
    from gateway.backend import GatewayContext
    from gateway.model import LinkEvent
    from gateway.vehicles import SERVICE, SourceVehicle

    backend = Ros2Backend()
    backend.attach(GatewayContext(services={SERVICE: [SourceVehicle("radio", "rocket1"),
                                                      SourceVehicle("other", "rocket2")]}))
    peers.append(Peer(domain))
    backend.init()
    try:
        assert backend.stats()["writers"] == 2 + 2 * 6  # /tf, /diagnostics; 6 per vehicle
        assert backend.stats()["announcements"] == 1  # the node, with every writer so far
        handover = backend.handover
        routes = dict(backend.routes())
        handover.post(routes[LinkEvent], LinkEvent("other", up=True))
        handover.post(routes[SmUpdate], SmUpdate(1, 3, True, 0, 5.0, 0, 0, 0, 0, 0, 0,
                                                 origin="radio"))
        # the state is latched: it arrives even if written before the reader matched
        assert peers[0].wait_state("BURNOUT", DEADLINE_S)
        assert handover.barrier(DEADLINE_S)
        assert backend.topics.vehicles == ["rocket2", "rocket1"]
    finally:
        backend.close()


def test_a_configuration_cyclone_refuses_is_named(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from backends.ros2.backend import Ros2Backend
    from gateway.backend import BackendError

    missing = (tmp_path / "missing.xml").as_uri()
    monkeypatch.setenv("CYCLONEDDS_URI", missing)
    backend = Ros2Backend()
    with pytest.raises(BackendError, match=f"CYCLONEDDS_URI='{missing}'"):
        backend.init()
    backend.close()
    assert backend.stats()["link"] == 0
