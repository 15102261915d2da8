"""Gateway messages → ROS 2 samples: topics, types, values (decoded with ``rosbags``), what is
latched, what is sent only on change, and per-vehicle state."""

from __future__ import annotations

import math
from typing import Any

import pytest
from rosbags.typesys import Stores, get_typestore

from backends.ros2 import types
from backends.ros2.topics import (
    LINK_DIAGNOSTICS_INTERVAL_NS,
    RosTopics,
    Sample,
    dds_topic,
    ros_token,
    vehicle_topics,
)
from gateway.attitude import quaternion_xyzw
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    RawFrame,
    SmUpdate,
    Status,
    VehicleState,
)

TS = get_typestore(Stores.ROS2_JAZZY)
NS = 1_764_100_000_000_000_000


def update(state: int = 0, alt: float = 0.0, armed: bool = False, vehicle: str = "rocket1",
           t_ms: int = 1000) -> SmUpdate:
    return SmUpdate(t_ms, state, armed, 0, alt, 9.8, 9.5, 0.0, 0.1, -0.2, 0.3, vehicle=vehicle)


def decode(s: Sample) -> Any:
    return TS.deserialize_cdr(s.cdr, s.type.name)


def by_topic(samples: list[Sample]) -> dict[str, Sample]:
    out = {s.topic: s for s in samples}
    assert len(out) == len(samples), "one sample per topic"
    return out


def test_an_update_gives_altitude_tf_imu_and_the_first_state_and_armed() -> None:
    got = by_topic(RosTopics().samples(update(state=2, alt=123.5, armed=True), NS))
    assert set(got) == {"/aurora/rocket1/altitude", "/tf", "/aurora/rocket1/imu",
                        "/aurora/rocket1/state", "/aurora/rocket1/armed"}
    assert decode(got["/aurora/rocket1/altitude"]).data == 123.5
    assert got["/aurora/rocket1/altitude"].type is types.FLOAT64
    assert decode(got["/aurora/rocket1/state"]).data == "BOOST"
    assert decode(got["/aurora/rocket1/armed"]).data is True
    assert {t for t, s in got.items() if s.latched} == {"/aurora/rocket1/state",
                                                         "/aurora/rocket1/armed"}
    assert all(s.stamp_ns == NS for s in got.values())

    (tf,) = decode(got["/tf"]).transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("world", "rocket1")
    assert tf.header.stamp.sec == NS // 1_000_000_000
    assert tf.transform.translation.z == 123.5
    q = tf.transform.rotation
    assert (q.x, q.y, q.z, q.w) == pytest.approx(quaternion_xyzw(0.1, -0.2, 0.3))

    imu = decode(got["/aurora/rocket1/imu"])
    assert imu.header.frame_id == "rocket1"
    assert (imu.orientation.x, imu.orientation.y, imu.orientation.z, imu.orientation.w) == (
        q.x, q.y, q.z, q.w)
    assert imu.linear_acceleration.z == 9.5
    assert imu.angular_velocity_covariance[0] == -1.0


def test_state_and_armed_are_sent_when_they_change() -> None:
    topics = RosTopics()
    flight = [(0, False), (0, False), (1, True), (2, True), (2, True), (3, True), (4, True),
              (5, True), (7, False), (7, False)]
    states: list[str] = []
    armed: list[bool] = []
    for state, arm in flight:
        for s in topics.samples(update(state=state, armed=arm), NS):
            if s.topic == "/aurora/rocket1/state":
                states.append(decode(s).data)
            elif s.topic == "/aurora/rocket1/armed":
                armed.append(decode(s).data)
    assert states == ["IDLE", "ARMED", "BOOST", "BURNOUT", "APOGEE", "MAIN", "LANDED"]
    assert armed == [False, True, False]


def test_vehicles_are_kept_apart() -> None:
    topics = RosTopics()
    a = by_topic(topics.samples(update(state=2, alt=10.0, vehicle="alpha"), NS))
    b = by_topic(topics.samples(update(state=2, alt=20.0, vehicle="beta"), NS))
    assert decode(a["/aurora/alpha/altitude"]).data == 10.0
    assert decode(b["/aurora/beta/altitude"]).data == 20.0
    assert "/aurora/beta/state" in b  # beta's first state, although alpha's is the same
    assert decode(b["/tf"]).transforms[0].child_frame_id == "beta"
    assert topics.vehicles == ["alpha", "beta"]


def test_vehicle_names_become_ros_name_tokens() -> None:
    topics = RosTopics()
    got = by_topic(topics.samples(update(vehicle="drone-1"), NS))
    assert "/aurora/drone_1/altitude" in got
    assert decode(got["/tf"]).transforms[0].child_frame_id == "drone-1"  # the frame: its name
    assert decode(got["/aurora/drone_1/imu"]).header.frame_id == "drone-1"
    # another vehicle of the same token is told apart
    assert "/aurora/drone_1_2/altitude" in by_topic(topics.samples(update(vehicle="drone_1"),
                                                                   NS))
    assert dict(topics.topics_of("drone_1"))["/aurora/drone_1_2/state"] is types.STRING
    assert ros_token("a--b__c") == "a_b_c"
    assert dict(vehicle_topics("sim-2"))["/aurora/sim_2/armed"] is types.BOOL


def test_a_message_naming_no_vehicle_is_the_default_vehicle_s() -> None:
    got = by_topic(RosTopics(default_vehicle="zulu").samples(update(vehicle=""), NS))
    assert "/aurora/zulu/altitude" in got


def test_vehicles_past_the_limit_give_nothing_and_are_counted() -> None:
    topics = RosTopics(max_vehicles=2)
    assert topics.samples(update(vehicle="a"), NS)
    assert topics.samples(update(vehicle="b"), NS)
    assert topics.samples(update(vehicle="c"), NS) == []
    assert topics.dropped_vehicle_limit == 1
    assert topics.samples(update(vehicle="a"), NS)


def test_status_gives_diagnostics_with_the_flags() -> None:
    topics = RosTopics()
    flags = Status.make_flags(armed=True, imu_ok=True, baro_ok=False, calibrated=True)
    got = by_topic(topics.samples(Status(1000, 1, 0, flags, vehicle="rocket1"), NS))
    assert decode(got["/aurora/rocket1/state"]).data == "ARMED"
    assert decode(got["/aurora/rocket1/armed"]).data is True
    (fc,) = decode(got["/diagnostics"]).status
    assert fc.name == "aurora/rocket1/flight_computer"
    assert fc.hardware_id == "rocket1"
    assert fc.level == fc.WARN
    values = {kv.key: kv.value for kv in fc.values}
    assert values["baro_ok"] == "false" and values["imu_ok"] == "true"
    assert values["state"] == "ARMED"


def test_link_events_and_stats_go_into_diagnostics() -> None:
    topics = RosTopics()
    (down,) = topics.samples(LinkEvent("radio", False, 2.5, vehicle="rocket1"), NS)
    (link,) = decode(down).status
    assert (link.name, link.level, link.message) == ("aurora/rocket1/link", link.ERROR, "down")
    assert {kv.key: kv.value for kv in link.values}["silence_s"] == "2.5"
    # link statistics refresh the diagnostics at most once a second
    stats = LinkStats(rssi_dbm=-70.0, link_quality_pct=99, vehicle="rocket1")
    assert topics.samples(stats, NS + 1) == []
    (diag,) = topics.samples(stats, NS + LINK_DIAGNOSTICS_INTERVAL_NS)
    (link,) = decode(diag).status
    assert {kv.key: kv.value for kv in link.values}["rssi_dbm"] == "-70.0"


def test_position_gives_a_fix() -> None:
    (s,) = RosTopics().samples(Position(47.5, 8.25, 512.0, fix_type=3, vehicle="v"), NS)
    m = decode(s)
    assert s.topic == "/aurora/v/fix" and s.type is types.NAV_SAT_FIX
    assert (m.latitude, m.longitude, m.altitude) == (47.5, 8.25, 512.0)
    assert m.status.status == m.status.STATUS_FIX
    (s,) = RosTopics().samples(Position(47.5, 8.25, fix_type=1, vehicle="v"), NS)
    assert decode(s).status.status == decode(s).status.STATUS_NO_FIX
    assert math.isnan(decode(s).altitude)


def test_battery_gives_a_battery_state() -> None:
    (s,) = RosTopics().samples(Battery(7.5, current_a=2.0, remaining_pct=80, vehicle="v"), NS)
    m = decode(s)
    assert s.topic == "/aurora/v/battery" and s.type is types.BATTERY_STATE
    assert (m.voltage, m.current, m.percentage) == (7.5, -2.0, pytest.approx(0.8))
    (s,) = RosTopics().samples(Battery(7.5, vehicle="v"), NS)
    assert math.isnan(decode(s).current) and math.isnan(decode(s).percentage)


def test_an_autopilot_s_state_gives_the_same_topics() -> None:
    msg = VehicleState(True, "AUTO", roll_rad=0.0, pitch_rad=0.0, yaw_rad=0.0, altitude_m=42.0,
                       vehicle="copter")
    got = by_topic(RosTopics().samples(msg, NS))
    assert decode(got["/aurora/copter/state"]).data == "AUTO"
    assert decode(got["/aurora/copter/altitude"]).data == 42.0
    assert decode(got["/tf"]).transforms[0].transform.translation.z == 42.0


def test_kinds_without_a_topic_give_nothing() -> None:
    assert RosTopics().samples(RawFrame(9, b"x", vehicle="v"), NS) == []


def test_stamp_defaults_to_now() -> None:
    (s, *_) = RosTopics().samples(update(), None)
    assert s.stamp_ns > NS


def test_topic_names() -> None:
    assert dds_topic("/aurora/rocket1/altitude") == "rt/aurora/rocket1/altitude"
    assert dds_topic("/tf") == "rt/tf"
    listed = dict(vehicle_topics("rocket1"))
    assert listed["/aurora/rocket1/state"] is types.STRING
    assert listed["/tf"] is types.TF_MESSAGE
    assert len(listed) == 8
