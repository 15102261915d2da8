"""The ROS 2 message types the gateway publishes, with the names and hashes ROS 2 gives them.

Each :class:`RosType` carries the ROS name (``std_msgs/msg/Float64``), the DDS type name ROS 2's
IDL generator gives it (``std_msgs::msg::dds_::Float64_``: every RMW on DDS registers that
name, and rmw_zenoh puts it in its key expressions) and its REP-2011 type description hash
(``RIHS01_`` + 64 hex), which ROS 2 (Iron and later) puts in each endpoint's USER_DATA
(``typehash=…;``) and rmw_zenoh in its keys.  Only standard ROS 2 types: a ROS user needs no
package of ours.

The hashes are constants: they are the same in Humble, Iron, Jazzy and Kilted (none of these
types or their nested types changed); ``tests/test_ros2_types.py`` recomputes each of them
independently (``rosbags``' type store).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_ROS_NAME = re.compile(r"^([a-z][a-z0-9_]*)/msg/([A-Z][A-Za-z0-9]*)$")
_RIHS01 = re.compile(r"^RIHS01_[0-9a-f]{64}$")


@dataclass(frozen=True)
class RosType:
    """A ROS 2 message type: ``name`` ``pkg/msg/Type``, ``dds_name``
    ``pkg::msg::dds_::Type_``, ``rihs01`` its REP-2011 hash ``RIHS01_<64 hex>``."""

    name: str
    dds_name: str
    rihs01: str

    @classmethod
    def of(cls, name: str, rihs01: str) -> RosType:
        """The type named ``name`` (``pkg/msg/Type``), its DDS name derived as ROS 2 does."""
        m = _ROS_NAME.match(name)
        if m is None:
            raise ValueError(f"not a ROS 2 message type name: {name!r}")
        if _RIHS01.match(rihs01) is None:
            raise ValueError(f"not a RIHS01 hash: {rihs01!r}")
        return cls(name, f"{m[1]}::msg::dds_::{m[2]}_", rihs01)

    @property
    def user_data(self) -> bytes:
        """The USER_DATA QoS value a ROS 2 endpoint of this type carries: ``typehash=…;``."""
        return f"typehash={self.rihs01};".encode("ascii")


STRING = RosType.of(
    "std_msgs/msg/String",
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
BOOL = RosType.of(
    "std_msgs/msg/Bool",
    "RIHS01_feb91e995ff9ebd09c0cb3d2aed18b11077585839fb5db80193b62d74528f6c9")
FLOAT64 = RosType.of(
    "std_msgs/msg/Float64",
    "RIHS01_705ba9c3d1a09df43737eb67095534de36fd426c0587779bda2bc51fe790182a")
IMU = RosType.of(
    "sensor_msgs/msg/Imu",
    "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b")
TF_MESSAGE = RosType.of(
    "tf2_msgs/msg/TFMessage",
    "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087")
NAV_SAT_FIX = RosType.of(
    "sensor_msgs/msg/NavSatFix",
    "RIHS01_62223ab3fe210a15976021da7afddc9e200dc9ec75231c1b6a557fc598a65404")
BATTERY_STATE = RosType.of(
    "sensor_msgs/msg/BatteryState",
    "RIHS01_4bee5dfce981c98faa6828b868307a0a73f992ed0789f374ee96c8f840e69741")
DIAGNOSTIC_ARRAY = RosType.of(
    "diagnostic_msgs/msg/DiagnosticArray",
    "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e")

#: What a ROS 2 participant announces its nodes with (``ros_discovery_info``; Iron and later:
#: Humble's Gid is 24 bytes, a type of another hash).
PARTICIPANT_ENTITIES_INFO = RosType.of(
    "rmw_dds_common/msg/ParticipantEntitiesInfo",
    "RIHS01_e725f4a506958c79f95dd693b965722c57b19cd18e7eff984f49561b93dc985d")

#: Every type the gateway publishes on its topics.
ALL_TYPES: tuple[RosType, ...] = (STRING, BOOL, FLOAT64, IMU, TF_MESSAGE, NAV_SAT_FIX,
                                  BATTERY_STATE, DIAGNOSTIC_ARRAY)
