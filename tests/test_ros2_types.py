"""The ROS 2 types' names and REP-2011 hashes, checked against an independent computation
(``rosbags``' type store hashes each type from its own message definitions)."""

from __future__ import annotations

import pytest
from rosbags.typesys import Stores, get_typestore

from backends.ros2 import types
from backends.ros2.types import ALL_TYPES, RosType


@pytest.mark.parametrize("store", [Stores.ROS2_IRON, Stores.ROS2_JAZZY, Stores.ROS2_KILTED])
@pytest.mark.parametrize("ros_type", ALL_TYPES, ids=lambda t: t.name)
def test_hash_is_the_one_ros_2_computes(store: Stores, ros_type: RosType) -> None:
    assert ros_type.rihs01 == get_typestore(store).hash_rihs01(ros_type.name)


@pytest.mark.parametrize("store", [Stores.ROS2_IRON, Stores.ROS2_JAZZY, Stores.ROS2_KILTED])
def test_the_graph_announcement_s_hash_is_ros_2_s(store: Stores) -> None:
    info = types.PARTICIPANT_ENTITIES_INFO
    assert info.rihs01 == get_typestore(store).hash_rihs01(info.name)
    assert info.dds_name == "rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"


def test_string_hash_is_the_published_one() -> None:
    assert types.STRING.rihs01 == (
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")


@pytest.mark.parametrize(("ros_type", "dds_name"), [
    (types.STRING, "std_msgs::msg::dds_::String_"),
    (types.BOOL, "std_msgs::msg::dds_::Bool_"),
    (types.FLOAT64, "std_msgs::msg::dds_::Float64_"),
    (types.IMU, "sensor_msgs::msg::dds_::Imu_"),
    (types.TF_MESSAGE, "tf2_msgs::msg::dds_::TFMessage_"),
    (types.NAV_SAT_FIX, "sensor_msgs::msg::dds_::NavSatFix_"),
    (types.BATTERY_STATE, "sensor_msgs::msg::dds_::BatteryState_"),
    (types.DIAGNOSTIC_ARRAY, "diagnostic_msgs::msg::dds_::DiagnosticArray_"),
])
def test_dds_type_names_are_ros_2_s(ros_type: RosType, dds_name: str) -> None:
    assert ros_type.dds_name == dds_name


def test_user_data_names_the_hash() -> None:
    assert types.FLOAT64.user_data == (
        b"typehash=RIHS01_705ba9c3d1a09df43737eb67095534de36fd426c0587779bda2bc51fe790182a;")


@pytest.mark.parametrize(("name", "rihs01"), [
    ("std_msgs/String", types.STRING.rihs01),
    ("std_msgs/msg/string", types.STRING.rihs01),
    ("std_msgs/msg/String", "RIHS01_xyz"),
    ("std_msgs/msg/String", types.STRING.rihs01.upper()),
])
def test_malformed_names_and_hashes_are_refused(name: str, rihs01: str) -> None:
    with pytest.raises(ValueError):
        RosType.of(name, rihs01)
