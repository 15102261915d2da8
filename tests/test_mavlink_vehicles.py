"""Many vehicles in one gateway, as a MAVLink ground station sees them (issue 22).

Two rockets feed ``aurora-gateway run`` over TCP (``socket://`` sources, Aurora wire frames
from the test's listeners), one near 100 m and one near 500 m; a pymavlink listener on the
``udpout:`` port sees two systems, each with its own HEARTBEAT (component 1,
``MAV_TYPE_ROCKET``) and its own sequence numbers, and each system's ALTITUDE only ever
carries its own rocket's values.  Run with ``-s`` to print what the listener saw.

In process: which node answers a command (the one it addresses; broadcast discovery every
one), where the ground station's RC goes (the addressed vehicle), and how system ids are
assigned (source order, fixed ``mavlink_sysid``, a vehicle first heard later).
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import wait_for
from mavlink_peer import MavPeer, upstream_dialect
from test_mavlink_routing_cli import ROUTER_ONLY, gateway

from backends.mavlink.backend import MavlinkBackend
from backends.mavlink.options import MavlinkOptions
from backends.mavlink.translate import AURORA_COMPID
from dialects import aurora_mavlink as aurora
from gateway import vehicles
from gateway.backend import Backend, GatewayContext, Routes
from gateway.dispatcher import Dispatcher
from gateway.model import RcChannels, SmUpdate, Status
from gateway.wire import encode

WAIT = 15.0
dev = upstream_dialect()
ROCKET = dev.MAV_TYPE_ROCKET
ALTITUDE_NEAR = {"alpha": 100.0, "beta": 500.0}
SPREAD = 5.0  # each rocket's altitude stays within ± this of its own


class Feed(threading.Thread):
    """A rocket on a TCP link: accepts the gateway's ``socket://`` connection and sends Aurora
    wire frames (SmUpdate at 20 Hz, a STATUS every 10th) until stopped; its altitude stays
    near ``altitude``."""

    def __init__(self, altitude: float) -> None:
        super().__init__(name="feed", daemon=True)
        self.altitude = altitude
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(WAIT)
        self.stop_event = threading.Event()
        self.sent = 0
        self.error: BaseException | None = None

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.server.getsockname()[1]}"

    def run(self) -> None:
        try:
            conn, _ = self.server.accept()
            with conn:
                i = 0
                while not self.stop_event.wait(0.05):  # a 20 Hz rocket: paced, not a sync
                    alt = self.altitude + SPREAD * ((i % 20) / 10.0 - 1.0)
                    t = 10_000 + 50 * i
                    conn.sendall(encode(SmUpdate(t, 1, True, 0, alt, 9.8, 9.7, 0.5, 0.01,
                                                 0.02, 0.03)))
                    if i % 10 == 0:
                        conn.sendall(encode(Status(t, 1, 0, 0x1F)))
                    i += 1
                    self.sent += 1
        except (BrokenPipeError, ConnectionResetError):
            return  # the gateway stopped first
        except BaseException as exc:  # reported by the test
            self.error = exc

    def close(self) -> None:
        self.stop_event.set()
        self.join(WAIT)
        self.server.close()


def seqs_continuous(msgs: list[Any]) -> bool:
    """Every message follows the previous one's sequence number (mod 256)."""
    seqs = [m.get_seq() for m in msgs]
    return all((b - a) & 0xFF == 1 for a, b in itertools.pairwise(seqs))


def summary(gcs: MavPeer) -> dict[int, dict[str, Any]]:
    """Per system: how many of each message the listener saw, the range of the altitudes
    its ALTITUDE and AURORA_SM_UPDATE carried."""
    out: dict[int, dict[str, Any]] = {}
    for m in gcs.messages():
        s = out.setdefault(m.get_srcSystem(), {"counts": {}, "altitude": None})
        s["counts"][m.get_type()] = s["counts"].get(m.get_type(), 0) + 1
        if m.get_type() in ("ALTITUDE", "AURORA_SM_UPDATE"):
            alt = m.altitude_relative if m.get_type() == "ALTITUDE" else m.altitude
            lo, hi = s["altitude"] or (alt, alt)
            s["altitude"] = (min(lo, alt), max(hi, alt))
    return out


@pytest.fixture
def feeds() -> Iterator[dict[str, Feed]]:
    f = {name: Feed(alt) for name, alt in ALTITUDE_NEAR.items()}
    for feed in f.values():
        feed.start()
    try:
        yield f
    finally:
        for feed in f.values():
            feed.close()


def test_two_rockets_are_two_systems_each_with_its_own_values(
        feeds: dict[str, Feed], tmp_path: Path) -> None:
    # parsing with the gateway's dialect (pymavlink-generated): the AURORA_* messages too
    with MavPeer(255, 190, dialect=aurora) as gcs, gateway(
            tmp_path / "log", "--source", f"alpha={feeds['alpha'].url}",
            "--source", f"beta={feeds['beta'].url}",
            "--mavlink", f"udpout:127.0.0.1:{gcs.port}", *ROUTER_ONLY) as proc:
        for sysid in (1, 2):
            assert gcs.wait_for("ALTITUDE", lambda m, s=sysid: m.get_srcSystem() == s,
                                count=40, timeout=WAIT), (tmp_path / "log").read_text()
            assert gcs.wait_for("HEARTBEAT", lambda m, s=sysid: m.get_srcSystem() == s,
                                count=2, timeout=WAIT)
        assert proc.poll() is None
    assert proc.returncode == 130  # stopped by SIGINT: "interrupted" (gateway.exits)
    report = (tmp_path / "log").read_text()
    assert "systems: mavlink alpha 1, beta 2" in report, report  # the stop report's
    assert "identity:" not in report  # nobody claimed their ids
    assert not any(f.error for f in feeds.values()), [f.error for f in feeds.values()]
    seen = summary(gcs)
    print("\nper system, as the pymavlink listener saw it:")
    for sysid, s in sorted(seen.items()):
        lo, hi = s["altitude"] or (float("nan"), float("nan"))
        print(f"  system {sysid}: altitude {lo:.1f} … {hi:.1f} m,"
              f" {dict(sorted(s['counts'].items()))}")
    assert set(seen) == {1, 2}
    for sysid, name in ((1, "alpha"), (2, "beta")):
        hbs = gcs.messages("HEARTBEAT", lambda m, s=sysid: m.get_srcSystem() == s)
        assert {(m.get_srcComponent(), m.type) for m in hbs} == {(1, ROCKET)}
        assert {m.custom_mode for m in hbs} <= {0, 1}  # the state (ARMED once heard)
        # its own sequence numbers: what each component of each system sent follows on
        for comp in (1, AURORA_COMPID):
            sent = gcs.messages(None, lambda m, s=sysid, c=comp: m.get_srcSystem() == s
                                and m.get_srcComponent() == c)
            assert len(sent) > 10 and seqs_continuous(sent), (sysid, comp)
        alts = [m.altitude_relative for m in gcs.messages(
            "ALTITUDE", lambda m, s=sysid: m.get_srcSystem() == s)]
        alts += [m.altitude for m in gcs.messages(
            "AURORA_SM_UPDATE", lambda m, s=sysid: m.get_srcSystem() == s)]
        near = ALTITUDE_NEAR[name]
        assert all(abs(a - near) <= SPREAD + 1e-3 for a in alts), (name, min(alts), max(alts))


# -- in process: who answers, who gets the sticks, which ids --------------------------------

class _Keep(Backend):
    """Keeps the RcChannels the gateway hands on (a real peer on the dispatcher)."""

    def __init__(self) -> None:
        super().__init__("keep")
        self.rc: list[RcChannels] = []

    def routes(self) -> Routes:
        return Routes().on(RcChannels, self.rc.append)


@contextlib.contextmanager
def fleet(port: int, configured: list[vehicles.SourceVehicle],
          **opts: Any) -> Iterator[tuple[MavlinkBackend, Dispatcher, _Keep]]:
    """A MAVLink backend of a gateway whose sources are ``configured``."""
    b = MavlinkBackend(MavlinkOptions(endpoints=[f"udpout:127.0.0.1:{port}"], **opts))
    keep = _Keep()
    d = Dispatcher([b, keep])
    b.attach(GatewayContext(emit=d.dispatch, services={vehicles.SERVICE: configured}))
    assert d.start() == []
    try:
        yield b, d, keep
    finally:
        d.close()


def sm(vehicle: str, alt: float, t: int = 1000) -> SmUpdate:
    return SmUpdate(t, 1, True, 0, alt, 9.8, 9.7, 0.5, 0.1, 0.2, 0.3, vehicle=vehicle)


def test_ids_in_source_order_fixed_ones_kept_and_later_vehicles_get_the_next_free() -> None:
    configured = [vehicles.SourceVehicle("a", "alpha"),
                  vehicles.SourceVehicle("b", "beta", 2),  # fixed: alpha must skip it
                  vehicles.SourceVehicle("c", "gamma")]
    with MavPeer(255, 190) as gcs, fleet(gcs.port, configured, sysid=2) as (b, d, _):
        # every configured vehicle heartbeats from the start, before any update
        for sysid in (2, 3, 4):
            assert gcs.wait_for("HEARTBEAT", lambda m, s=sysid: m.get_srcSystem() == s,
                                timeout=WAIT)
        d.dispatch(sm("zulu", 42.0))  # heard later (a source naming one vehicle per system)
        assert gcs.wait_for("ALTITUDE", lambda m: m.get_srcSystem() == 5, timeout=WAIT)
        d.dispatch(sm("", 7.0))  # no vehicle named: the first vehicle's
        assert gcs.wait_for("ALTITUDE", lambda m: m.get_srcSystem() == 3, timeout=WAIT)
        systems = b.stats()["systems"]
    assert {n: s["sysid"] for n, s in systems.items()} == {
        "alpha": 3, "beta": 2, "gamma": 4, "zulu": 5}
    assert {m.get_srcSystem() for m in gcs.messages("HEARTBEAT")} == {2, 3, 4, 5}
    assert [m.altitude_relative for m in gcs.messages("ALTITUDE")] == [42.0, 7.0]


def test_a_source_that_names_the_vehicles_it_hears_has_no_system_of_its_own() -> None:
    """E.g. a Zenoh source following another gateway: the first vehicle it names takes the
    system planned for the source (nobody heard of the source's own name), the next ones the
    next free ids."""
    configured = [vehicles.SourceVehicle("zenoh:far", "far")]
    with MavPeer(255, 190) as gcs, fleet(gcs.port, configured) as (b, d, _):
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        d.dispatch(sm("alpha", 100.0)._replace(origin="zenoh:far", via="zenoh:gw1"))
        d.dispatch(sm("beta", 500.0)._replace(origin="zenoh:far", via="zenoh:gw1"))
        assert gcs.wait_for("ALTITUDE", count=2, timeout=WAIT)
        systems = b.stats()["systems"]
    assert {n: s["sysid"] for n, s in systems.items()} == {"alpha": 1, "beta": 2}
    assert {(m.get_srcSystem(), m.altitude_relative) for m in gcs.messages("ALTITUDE")} == {
        (1, 100.0), (2, 500.0)}


def test_commands_are_answered_by_the_system_they_address() -> None:
    configured = [vehicles.SourceVehicle("a", "alpha"), vehicles.SourceVehicle("b", "beta")]
    with MavPeer(255, 190) as gcs, fleet(gcs.port, configured) as (_b, _, keep):
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 2, timeout=WAIT)
        gcs.command((2, 1), dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_HEARTBEAT)
        assert gcs.wait_for("COMMAND_ACK", timeout=WAIT)
        gcs.send(dev.MAVLink_mission_request_list_message(1, 1, 0))
        assert gcs.wait_for("MISSION_COUNT", timeout=WAIT)
        # broadcast: discovery is answered by every system, other commands by none
        gcs.command((0, 0), dev.MAV_CMD_NAV_TAKEOFF)
        gcs.command((0, 0), dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert gcs.wait_for("AUTOPILOT_VERSION", count=2, timeout=WAIT)
        gcs.send(dev.MAVLink_ping_message(123456, 9, 0, 0))
        assert gcs.wait_for("PING", count=2, timeout=WAIT)
        # the sticks for system 2 are beta's
        gcs.send(dev.MAVLink_rc_channels_override_message(
            2, 1, 1100, 1900, 0, 0, 0, 0, 0, 0, *([0] * 10)))
        assert wait_for(lambda: len(keep.rc) == 1, WAIT)
        gcs.command((1, 1), dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_HEARTBEAT)  # marker
        assert gcs.wait_for("COMMAND_ACK", count=4, timeout=WAIT)
    acks = [(m.get_srcSystem(), m.command, m.result) for m in gcs.messages("COMMAND_ACK")]
    req, ok = dev.MAV_CMD_REQUEST_MESSAGE, dev.MAV_RESULT_ACCEPTED
    assert acks[0] == (2, req, ok) and acks[-1] == (1, req, ok)
    assert sorted(acks[1:3]) == [(1, req, ok), (2, req, ok)]  # the broadcast discovery
    assert [m.get_srcSystem() for m in gcs.messages("MISSION_COUNT")] == [1]
    assert sorted(m.get_srcSystem() for m in gcs.messages("AUTOPILOT_VERSION")) == [1, 2]
    pings = gcs.messages("PING")
    assert sorted(m.get_srcSystem() for m in pings) == [1, 2]
    assert {(m.seq, m.time_usec, m.target_system, m.target_component) for m in pings} == {
        (9, 123456, 255, 190)}
    assert [(r.vehicle, r.channels_us) for r in keep.rc] == [("beta", (1100, 1900))]


# -- identity: nobody can take a vehicle's id --------------------------------------------------

PASS = "correct horse battery staple"


def heartbeat_from(sysid: int, mtype: int = dev.MAV_TYPE_QUADROTOR) -> bytes:
    """An unsigned HEARTBEAT of system ``sysid`` component 1."""
    return dev.MAVLink_heartbeat_message(mtype, dev.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4,
                                         3).pack(dev.MAVLink(None, sysid, 1))


def send_paced(gcs: MavPeer, frames: list[bytes], arrived: Any, batch: int = 50) -> None:
    """Send ``frames`` through the ground station's socket, ``batch`` at a time, each batch
    once the gateway has counted the previous one (``arrived()``: how many so far), so no
    socket buffer on the way overflows."""
    base = arrived()
    for i in range(0, len(frames), batch):
        for f in frames[i:i + batch]:
            gcs.send_raw(f)
        n = min(i + batch, len(frames))
        assert wait_for(lambda n=n: arrived() - base >= n, WAIT), (arrived() - base, n)


def test_with_signing_unsigned_frames_never_take_the_rockets_id() -> None:
    key = hashlib.sha256(PASS.encode()).digest()
    with MavPeer(255, 190, signing_key=key, link_id=2) as gcs, \
            fleet(gcs.port, [vehicles.SourceVehicle("a", "alpha")],
                  signing_passphrase=PASS) as (b, d, _):
        d.dispatch(sm("alpha", 100.0))
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        router = b.router
        assert router is not None
        rx = b.stats  # frames the gateway's one endpoint read
        ep = f"udpout:127.0.0.1:{gcs.port}"

        def arrived() -> int:
            return int(rx()["endpoints"][ep]["rx_frames"])

        # 1000 unsigned HEARTBEATs carrying the rocket's id (its own type and component too)
        send_paced(gcs, [heartbeat_from(1, mtype) for mtype in (ROCKET, dev.MAV_TYPE_QUADROTOR)
                         for _ in range(500)], arrived)
        # then a flood from every id
        send_paced(gcs, [heartbeat_from(i) for i in range(1, 255)], arrived)
        assert b.vehicle is not None and b.vehicle.sysid == 1
        gcs.clear()
        d.dispatch(sm("alpha", 101.0, t=2000))
        assert gcs.wait_for("ALTITUDE", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        gcs.command((1, 1), dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_HEARTBEAT)
        assert gcs.wait_for("COMMAND_ACK", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        st = b.stats()
        new_system_lines = router.log_lines()["new"]
        impostor_lines = router.log_lines()["impostor"]
    r, sig = st["router"], st["signing"]
    assert r["impostor_frames"] == 1001  # the 1000, and the flood's system 1
    assert r["unverified_systems"] == 253  # the flood's others: not evidence of anything
    assert (r["id_changes"], r["sysid_conflicts"]) == (0, 0)
    assert sig["rejected_unsigned"] == 1254 and sig["good"] == 1  # (the signed command)
    assert st["endpoints"][ep]["rejected_signing"] == 1001
    assert (st["impostor_frames"], st["rejected_signing"], st["sysid_conflicts"]) == (1001, 1001, 0)
    assert impostor_lines == 1  # one line, then a count per interval while more come
    assert set(router.seen_at) == {255}  # only the signed ground station counts as seen
    assert {m.get_srcSystem() for m in gcs.messages("HEARTBEAT")} == {1}
    assert new_system_lines <= 2  # 254 new systems: one line, a count per interval


def test_without_signing_the_id_rule_holds_and_running_out_of_ids_never_raises() -> None:
    with MavPeer(255, 190) as gcs, \
            fleet(gcs.port, [vehicles.SourceVehicle("a", "alpha")]) as (b, d, _):
        d.dispatch(sm("alpha", 100.0))
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        rocket = b.vehicle
        assert rocket is not None
        ep = f"udpout:127.0.0.1:{gcs.port}"

        def arrived() -> int:
            return int(b.stats()["endpoints"][ep]["rx_frames"])

        # a quadrotor that is system 1 too: the rocket moves to the next free id (the rule)
        send_paced(gcs, [heartbeat_from(1)], arrived)
        assert rocket.sysid == 2
        # every other id in use, then one more taking the rocket's: it keeps its id, counted
        send_paced(gcs, [heartbeat_from(i) for i in range(3, 255)], arrived)
        send_paced(gcs, [heartbeat_from(2)], arrived)
        assert rocket.sysid == 2
        gcs.clear()
        d.dispatch(sm("alpha", 101.0, t=2000))
        assert gcs.wait_for("ALTITUDE", lambda m: m.get_srcSystem() == 2, timeout=WAIT)
        d.dispatch(sm("newcomer", 5.0))  # no id left for another vehicle: not shown, counted
        assert wait_for(lambda: b.stats()["vehicles_without_id"] >= 1, WAIT)
        st = b.stats()
        moves = b.router.log_lines()["move"] if b.router is not None else -1
    assert (st["router"]["id_changes"], st["router"]["sysid_conflicts"]) == (1, 1)
    assert set(st["systems"]) == {"alpha"}
    assert moves == 1


def test_a_silent_system_is_forgotten() -> None:
    with MavPeer(255, 190) as gcs, \
            fleet(gcs.port, [vehicles.SourceVehicle("a", "alpha")],
                  system_timeout_s=1.0) as (b, _, _):
        assert gcs.wait_for("HEARTBEAT", timeout=WAIT)
        router = b.router
        assert router is not None
        gcs.send_raw(heartbeat_from(9))
        assert wait_for(lambda: router.in_use(9), WAIT)
        # silent from now on: forgotten after the timeout (the backend sweeps every second)
        assert wait_for(lambda: 9 not in router.seen_at, WAIT)
        assert b.stats()["router"]["systems_forgotten"] >= 1
        assert not router.in_use(9)


def test_the_stop_report_counts_what_claimed_a_rockets_id(tmp_path: Path) -> None:
    """From the command line, with signing required: unsigned HEARTBEATs carrying the
    rocket's id leave it system 1, and the stop report's identity line counts them."""
    key = tmp_path / "key"
    key.write_text(hashlib.sha256(PASS.encode()).hexdigest())
    log = tmp_path / "log"
    with MavPeer(255, 190) as gcs, gateway(
            log, "--source", "alpha=sim", "--mavlink", f"udpout:127.0.0.1:{gcs.port}",
            "--mavlink-signing-key", str(key), *ROUTER_ONLY) as proc:
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        for _ in range(20):
            gcs.send_raw(heartbeat_from(1, ROCKET))
        assert wait_for(lambda: "not correctly signed" in log.read_text(), WAIT), log.read_text()
        gcs.clear()
        assert gcs.wait_for("HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=WAIT)
        assert proc.poll() is None
    assert proc.returncode == 130  # stopped by SIGINT: "interrupted" (gateway.exits)
    report = log.read_text()
    assert "systems: mavlink alpha 1" in report, report
    line = next(ln for ln in report.splitlines() if ln.startswith("identity: "))
    counts = dict(kv.split("=") for kv in line.removeprefix("identity: mavlink ").split())
    assert 1 <= int(counts["impostor_frames"]) <= 20, line
    assert int(counts["rejected_signing"]) == int(counts["impostor_frames"]), line
    assert "id_changes" not in counts and "sysid_conflicts" not in counts, line
