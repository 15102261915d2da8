"""The DDS types of :mod:`backends.ros2.types` as ROS 2's own DDS IDL declares them, for
Cyclone DDS's Python binding (``cyclonedds``): the type names ``<pkg>::msg::dds_::<Type>_``,
every member with a trailing underscore (``data_``), final extensibility, and ROS's IDL
mapping of the primitives (``rosidl_generator_dds_idl``: ``int8``, ``uint8`` and ``byte`` are
``octet``; ``float64`` is ``double``, ``int32`` ``long`` …).  What a ROS 2 node on a DDS RMW
discovers is therefore the type it knows.

The gateway never has these classes serialize anything: the CDR comes from
:mod:`backends.ros2.cdr` (one encoder for DDS, rmw_zenoh and rosbag2): the published classes'
``serialize`` returns the bytes set on the instance a writer is given (:func:`carrier`).
Imported only by the DDS backend (it needs ``cyclonedds``).

(No ``from __future__ import annotations`` here: cyclonedds reads the members' annotations
as objects.)
"""

from dataclasses import dataclass
from typing import Any

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.idl.annotations import final

from backends.ros2 import types


def _prebuilt(self: Any, buffer: Any = None, endianness: Any = None,
              use_version_2: Any = None) -> bytes:
    """``serialize`` of a published type: the bytes set beforehand (:func:`carrier`)."""
    cdr: bytes = self._cdr
    return cdr


# builtin_interfaces, std_msgs ----------------------------------------------------------------

@final
@dataclass
class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec_: t.int32
    nanosec_: t.uint32


@final
@dataclass
class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp_: Time_
    frame_id_: str


@final
@dataclass
class String_(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data_: str


@final
@dataclass
class Bool_(IdlStruct, typename="std_msgs::msg::dds_::Bool_"):
    data_: bool


@final
@dataclass
class Float64_(IdlStruct, typename="std_msgs::msg::dds_::Float64_"):
    data_: t.float64


# geometry_msgs, tf2_msgs ---------------------------------------------------------------------

@final
@dataclass
class Vector3_(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x_: t.float64
    y_: t.float64
    z_: t.float64


@final
@dataclass
class Quaternion_(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x_: t.float64
    y_: t.float64
    z_: t.float64
    w_: t.float64


@final
@dataclass
class Transform_(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation_: Vector3_
    rotation_: Quaternion_


@final
@dataclass
class TransformStamped_(IdlStruct,
                        typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header_: Header_
    child_frame_id_: str
    transform_: Transform_


@final
@dataclass
class TFMessage_(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms_: t.sequence[TransformStamped_]


# sensor_msgs ---------------------------------------------------------------------------------

@final
@dataclass
class Imu_(IdlStruct, typename="sensor_msgs::msg::dds_::Imu_"):
    header_: Header_
    orientation_: Quaternion_
    orientation_covariance_: t.array[t.float64, 9]
    angular_velocity_: Vector3_
    angular_velocity_covariance_: t.array[t.float64, 9]
    linear_acceleration_: Vector3_
    linear_acceleration_covariance_: t.array[t.float64, 9]


@final
@dataclass
class NavSatStatus_(IdlStruct, typename="sensor_msgs::msg::dds_::NavSatStatus_"):
    status_: t.byte
    service_: t.uint16


@final
@dataclass
class NavSatFix_(IdlStruct, typename="sensor_msgs::msg::dds_::NavSatFix_"):
    header_: Header_
    status_: NavSatStatus_
    latitude_: t.float64
    longitude_: t.float64
    altitude_: t.float64
    position_covariance_: t.array[t.float64, 9]
    position_covariance_type_: t.byte


@final
@dataclass
class BatteryState_(IdlStruct,
                    typename="sensor_msgs::msg::dds_::BatteryState_"):
    header_: Header_
    voltage_: t.float32
    temperature_: t.float32
    current_: t.float32
    charge_: t.float32
    capacity_: t.float32
    design_capacity_: t.float32
    percentage_: t.float32
    power_supply_status_: t.byte
    power_supply_health_: t.byte
    power_supply_technology_: t.byte
    present_: bool
    cell_voltage_: t.sequence[t.float32]
    cell_temperature_: t.sequence[t.float32]
    location_: str
    serial_number_: str


# diagnostic_msgs -----------------------------------------------------------------------------

@final
@dataclass
class KeyValue_(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key_: str
    value_: str


@final
@dataclass
class DiagnosticStatus_(IdlStruct,
                        typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level_: t.byte
    name_: str
    message_: str
    hardware_id_: str
    values_: t.sequence[KeyValue_]


@final
@dataclass
class DiagnosticArray_(IdlStruct,
                       typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header_: Header_
    status_: t.sequence[DiagnosticStatus_]


# rmw_dds_common: the ROS 2 graph (ros_discovery_info), serialized by the binding itself -----

@final
@dataclass
class Gid_(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data_: t.array[t.byte, 16]


@final
@dataclass
class NodeEntitiesInfo_(IdlStruct,
                        typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace_: t.bounded_str[256]
    node_name_: t.bounded_str[256]
    reader_gid_seq_: t.sequence[Gid_]
    writer_gid_seq_: t.sequence[Gid_]


@final
@dataclass
class ParticipantEntitiesInfo_(IdlStruct,
                               typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    gid_: Gid_
    node_entities_info_seq_: t.sequence[NodeEntitiesInfo_]


def gid(guid: Any) -> Gid_:
    """A DDS entity's GUID (``uuid.UUID``, 16 bytes) as ROS 2's Gid."""
    return Gid_(list(guid.bytes))


def participant_entities_info(participant: Any, namespace: str, node: str,
                              writers: list[Any]) -> ParticipantEntitiesInfo_:
    """What ``ros_discovery_info`` says of a participant (its GUID) with one node, its
    writers (their GUIDs) and no reader."""
    return ParticipantEntitiesInfo_(
        gid(participant), [NodeEntitiesInfo_(namespace, node, [], [gid(w) for w in writers])])


#: The class of each published type, by ROS name.
CLASSES: dict[str, type[IdlStruct]] = {
    types.STRING.name: String_, types.BOOL.name: Bool_, types.FLOAT64.name: Float64_,
    types.IMU.name: Imu_, types.TF_MESSAGE.name: TFMessage_, types.NAV_SAT_FIX.name: NavSatFix_,
    types.BATTERY_STATE.name: BatteryState_, types.DIAGNOSTIC_ARRAY.name: DiagnosticArray_,
}

# A published type serializes nothing itself: set on the classes, not a base class (the
# binding's type-object builder walks every base).
for _cls in CLASSES.values():
    _cls.serialize = _prebuilt  # type: ignore[method-assign]


def carrier(cls: type[IdlStruct]) -> Any:
    """An instance of ``cls`` to hand a writer: set its ``_cdr`` (the serialized sample,
    encapsulation header included) before each write; its members are never read."""
    return object.__new__(cls)
