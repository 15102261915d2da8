"""MAVLink in: a vehicle (a pymavlink stand-in for ArduPilot) as a gateway source, and one
gateway feeding another over MAVLink losslessly."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from helpers import wait_for
from mavlink_peer import MavPeer, upstream_dialect

from backends.mavlink.backend import MavlinkBackend
from backends.mavlink.options import MavlinkOptions, MavlinkSourceOptions
from backends.mavlink.source import MavlinkSource, classic_mode_name
from gateway import config
from gateway.backend import Backend, Routes
from gateway.dispatcher import Dispatcher
from gateway.model import Battery, Position, SmUpdate, Status, VehicleState

WAIT = 10.0
dev = upstream_dialect()


class Sink:
    """Where the source's messages go: a real Dispatcher with a backend that keeps what the
    other backends (CRSF, Zenoh, HC-12) would be handed."""

    class Keeper(Backend):
        NAME = "keeper"

        def __init__(self) -> None:
            super().__init__()
            self.got: list[Any] = []
            self.cond = threading.Condition()

        def routes(self) -> Routes:
            routes = Routes()
            for kind in (VehicleState, Position, Battery, SmUpdate, Status):
                routes.on(kind, self._keep)
            return routes

        def _keep(self, msg: Any) -> None:
            with self.cond:
                self.got.append(msg)
                self.cond.notify_all()

    def __init__(self) -> None:
        self.keeper = self.Keeper()
        self.dispatcher = Dispatcher([self.keeper])
        self.dispatcher.start()

    def __call__(self, msg: Any) -> None:
        self.dispatcher.dispatch(msg)

    def wait(self, kind: type, pred: Any = None, timeout: float = WAIT) -> list[Any]:
        deadline = time.monotonic() + timeout
        k = self.keeper
        with k.cond:
            while True:
                found = [m for m in k.got if isinstance(m, kind) and (pred is None or pred(m))]
                if found or time.monotonic() > deadline:
                    return found
                k.cond.wait(0.1)


def started(source: MavlinkSource, sink: Sink) -> MavlinkSource:
    source.start(sink)
    assert source.started.wait(WAIT) and source.start_error is None, source.start_error
    return source


def test_an_ardupilot_vehicle_feeds_the_model() -> None:
    sink = Sink()
    src = started(MavlinkSource(MavlinkSourceOptions(url="udpin:127.0.0.1:0"), name="copter"), sink)
    veh = MavPeer(1, 1, dest=src.endpoints[0].address)
    try:
        armed_loiter = dev.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | dev.MAV_MODE_FLAG_SAFETY_ARMED
        veh.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_QUADROTOR,
                                               dev.MAV_AUTOPILOT_ARDUPILOTMEGA, armed_loiter, 5,
                                               dev.MAV_STATE_ACTIVE, 3))
        # the source introduces itself and asks for the mode table and the streams
        req = veh.wait_for("COMMAND_LONG", timeout=WAIT)
        streams = veh.wait_for("REQUEST_DATA_STREAM", timeout=WAIT)
        assert veh.wait_for("HEARTBEAT", timeout=WAIT)
        veh.send(dev.MAVLink_attitude_message(1000, 0.1, -0.2, 1.5, 0, 0, 0))
        veh.send(dev.MAVLink_vfr_hud_message(12.0, 11.0, 86, 40, 120.5, 2.5))
        veh.send(dev.MAVLink_gps_raw_int_message(0, 3, 473977420, 85455940, 500000, 90, 120,
                                                 1100, 9000, 14, 0, 0, 0, 0, 0, 0))
        veh.send(dev.MAVLink_global_position_int_message(
            1100, 473977420, 85455940, 500000, 20500, 300, -400, -250, 9000))
        veh.send(dev.MAVLink_battery_status_message(
            0, 0, 0, 0x7FFF, [4100, 4100, 4100] + [0xFFFF] * 7, 1530, 420, -1, 76, 0, 0,
            [0] * 4, 0, 0))
        pos = sink.wait(Position)
        bat = sink.wait(Battery)
        vs = sink.wait(VehicleState, lambda m: m.roll_rad is not None)
        # the vehicle answers the mode table: its own names win over the classic table
        veh.send(dev.MAVLink_available_modes_message(1, 1, 0, 5, 0, b"LOITER_NAMED"))
        veh.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_QUADROTOR,
                                               dev.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                               dev.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 5,
                                               dev.MAV_STATE_STANDBY, 3))
        disarmed = sink.wait(VehicleState, lambda m: not m.armed)
    finally:
        veh.close()
        src.stop()
        sink.dispatcher.close()
    assert (req[0].command, req[0].param1, req[0].target_system) == (
        dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_AVAILABLE_MODES, 1)
    assert streams[0].start_stop == 1
    v = vs[0]
    assert (v.armed, v.mode, v.custom_mode, v.origin) == (True, "LOITER", 5, "copter")
    assert (v.roll_rad, v.pitch_rad, v.yaw_rad) == pytest.approx((0.1, -0.2, 1.5), abs=1e-6)
    p = pos[0]
    assert (p.lat_deg, p.lon_deg) == pytest.approx((47.397742, 8.545594))
    assert (p.alt_amsl_m, p.relative_alt_m) == pytest.approx((500.0, 20.5))
    assert p.ground_speed_mps == pytest.approx(5.0)
    assert (p.course_deg, p.satellites, p.fix_type) == (pytest.approx(90.0), 14, 3)
    b = bat[0]
    assert (b.voltage_v, b.current_a, b.consumed_mah, b.remaining_pct) == pytest.approx(
        (12.3, 15.3, 420.0, 76))
    assert disarmed[-1].mode == "LOITER_NAMED"


def test_only_the_followed_vehicle_counts() -> None:
    sink = Sink()
    src = started(MavlinkSource(MavlinkSourceOptions(url="udpin:127.0.0.1:0",
                                                     target_system=3), name="v3"),
                  sink)
    other = MavPeer(4, 1, dest=src.endpoints[0].address)
    mine = MavPeer(3, 1, dest=src.endpoints[0].address)
    try:
        for peer, mode in ((other, 2), (mine, 4)):
            peer.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_GROUND_ROVER,
                                                    dev.MAV_AUTOPILOT_ARDUPILOTMEGA, 1, mode,
                                                    4, 3))
        got = sink.wait(VehicleState)
    finally:
        other.close()
        mine.close()
        src.stop()
        sink.dispatcher.close()
    assert [(m.mode, m.custom_mode) for m in got] == [("HOLD", 4)]  # Rover numbering


def test_one_gateway_feeds_another_losslessly_over_mavlink() -> None:
    sink = Sink()
    src = started(MavlinkSource(MavlinkSourceOptions(url="udpin:127.0.0.1:0"), name="upstream"),
                  sink)
    _, port = src.endpoints[0].address
    b = MavlinkBackend(MavlinkOptions(endpoints=[f"udpout:127.0.0.1:{port}"]))
    d = Dispatcher([b])
    assert d.start() == []
    sent = [SmUpdate(5000 + i, 2, True, 0, 100.0 + i / 3, 30.1, 29.9, 80.25, 0.1, 1.4, 0.6,
                     payload_len=64) for i in range(5)]
    st = Status(5100, 2, 0, 0x1F, reserved=3)
    try:
        for m in sent:
            d.dispatch(m)
        d.dispatch(st)
        got = sink.wait(SmUpdate, lambda m: m.timestamp_ms == sent[-1].timestamp_ms)
        got_st = sink.wait(Status)
        relayed = [m for m in sink.keeper.got if isinstance(m, SmUpdate)]
    finally:
        d.close()
        src.stop()
        sink.dispatcher.close()
    assert got and got_st
    assert [m.fields() for m in relayed] == [m.fields() for m in sent]
    assert all(m.origin == "upstream" and m.via.startswith("mavlink:") for m in relayed)
    assert got_st[0].fields() == st.fields()


def test_the_backend_does_not_echo_a_mavlink_sources_position() -> None:
    gcs = MavPeer(255, 190)
    b = MavlinkBackend(MavlinkOptions(endpoints=[f"udpout:127.0.0.1:{gcs.port}"]))
    d = Dispatcher([b])
    assert d.start() == []
    try:
        # from a MAVLink vehicle (as a MAVLink source stamps it): it speaks for itself
        d.dispatch(Position(47.0, 8.0, 500.0, origin="copter-x", via="mavlink:1"))
        d.dispatch(Battery(12.0, origin="copter-x", via="mavlink:1"))
        d.dispatch(Position(46.5, 7.5, 600.0, 10.0, 3.0, 45.0, 9, 3, origin="gps"))
        d.dispatch(Battery(7.4, 1.2, 100.0, 80, origin="gps"))
        pos = gcs.wait_for("GLOBAL_POSITION_INT", timeout=WAIT)
        assert gcs.wait_for("BATTERY_STATUS", timeout=WAIT)
        assert gcs.wait_for("GPS_RAW_INT", timeout=WAIT)
    finally:
        d.close()
        gcs.close()
    assert [(p.lat, p.lon, p.alt) for p in gcs.messages("GLOBAL_POSITION_INT")] == [
        (465000000, 75000000, 600000)]
    assert pos[0].relative_alt == 10000
    bs = gcs.messages("BATTERY_STATUS")[0]
    assert (bs.voltages[0], bs.current_battery, bs.battery_remaining) == (7400, 120, 80)


def test_config_and_mode_names() -> None:
    part = config.make_source("mavlink", {"url": "udpin:0.0.0.0:14551"}, None, "sources[0]")
    assert part.cls is MavlinkSource and part.options["sysid"] == 0  # automatic
    assert part.name == "mavlink:udpin:0.0.0.0:14551"
    with pytest.raises(ValueError, match="'bogus': not an endpoint; expected tcpin:"):
        MavlinkSource(MavlinkSourceOptions(url="bogus"))
    custom = dev.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert classic_mode_name(dev.MAV_AUTOPILOT_ARDUPILOTMEGA, dev.MAV_TYPE_FIXED_WING, custom,
                             10) == "AUTO"
    assert classic_mode_name(dev.MAV_AUTOPILOT_PX4, dev.MAV_TYPE_QUADROTOR, custom,
                             (4 << 16) | (4 << 24)) == "AUTO_MISSION"
    assert classic_mode_name(dev.MAV_AUTOPILOT_GENERIC, 9, custom, 3) == "MODE_3"


def test_each_system_heard_is_a_vehicle_of_its_own() -> None:
    """Two autopilots (and a ground station, which is no vehicle) on one link: one gateway
    vehicle each, ``<source's vehicle>-<system id>``, each with its own state."""
    from backends.mavlink import source as mavsource

    sink = Sink()
    src = MavlinkSource(MavlinkSourceOptions(url="udpin:127.0.0.1:0"), name="mavlink:x")
    src.vehicle = "drone"  # as the gateway names it (--source drone=mavlink:…)
    started(src, sink)
    dest = src.endpoints[0].address
    peers = [MavPeer(i, 1, dest=dest) for i in (3, 4)]
    gcs = MavPeer(255, 190, dest=dest)
    try:
        gcs.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_GCS, dev.MAV_AUTOPILOT_INVALID, 0, 0,
                                               4, 3))
        for peer, mode in zip(peers, (4, 10), strict=True):
            peer.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_GROUND_ROVER,
                                                    dev.MAV_AUTOPILOT_ARDUPILOTMEGA, 1, mode,
                                                    4, 3))
        got = sink.wait(VehicleState, lambda m: m.vehicle == "drone-4")
        assert got and sink.wait(VehicleState, lambda m: m.vehicle == "drone-3")
        for peer, alt in zip(peers, (20.5, 77.25), strict=True):
            peer.send(dev.MAVLink_global_position_int_message(
                1100, 473977420, 85455940, 500000, round(alt * 1000), 0, 0, 0, 9000))
        pos = {p.vehicle: p for p in
               [*sink.wait(Position, lambda m: m.vehicle == "drone-3"),
                *sink.wait(Position, lambda m: m.vehicle == "drone-4")]}
        # more systems than the bound: the extra ones are ignored, counted
        extra = [MavPeer(10 + i, 1, dest=dest) for i in range(mavsource.MAX_SYSTEMS)]
        for peer in extra:
            peer.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_QUADROTOR,
                                                    dev.MAV_AUTOPILOT_ARDUPILOTMEGA, 1, 0, 4, 3))
        assert wait_for(lambda: src.stats()["systems_ignored"] == 2, WAIT)
        for peer in extra:
            peer.close()
        stats = src.stats()
    finally:
        for p in [*peers, gcs]:
            p.close()
        src.stop()
        sink.dispatcher.close()
    states = {m.vehicle: m for m in sink.keeper.got if isinstance(m, VehicleState)}
    assert {v: (m.mode, m.via, m.origin) for v, m in states.items()
            if v in ("drone-3", "drone-4")} == {
        "drone-3": ("HOLD", "mavlink:3", "mavlink:x"),
        "drone-4": ("AUTO", "mavlink:4", "mavlink:x")}
    assert {v: p.relative_alt_m for v, p in pos.items()} == {"drone-3": 20.5, "drone-4": 77.25}
    assert len(stats["systems"]) == mavsource.MAX_SYSTEMS
    assert stats["systems"]["3"] == "drone-3"

