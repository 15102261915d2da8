"""A ROS 2-style DDS subscriber in a process of its own, for tests/test_ros2_dds.py: what a
ROS 2 node on a DDS RMW would declare, written independently of the gateway (its own IDL
classes, named as ROS 2's DDS IDL names them; Cyclone DDS's own deserializer).

    python tests/ros2_dds_peer.py DOMAIN SECONDS

Prints one JSON object per line on stdout: ``{"ready": true}`` once its readers exist, then
each sample of ``rt/aurora/rocket1/altitude``, ``…/state`` (reliable, transient local: a late
joiner gets the current one) and ``rt/tf``, and each publication discovered on ``rt/…`` with
its type name, USER_DATA and durability (the DCPSPublication builtin topic), and each
participant's announcement of its nodes on ``ros_discovery_info`` (the ROS 2 graph).  Ends after
SECONDS (or when terminated).
"""

import json
import sys
import time
from dataclasses import dataclass

from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t
from cyclonedds.idl.annotations import final
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@final
@dataclass
class Float64(IdlStruct, typename="std_msgs::msg::dds_::Float64_"):
    data_: t.float64


@final
@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data_: str


@final
@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec_: t.int32
    nanosec_: t.uint32


@final
@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp_: Time
    frame_id_: str


@final
@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x_: t.float64
    y_: t.float64
    z_: t.float64


@final
@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x_: t.float64
    y_: t.float64
    z_: t.float64
    w_: t.float64


@final
@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation_: Vector3
    rotation_: Quaternion


@final
@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header_: Header
    child_frame_id_: str
    transform_: Transform


@final
@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms_: t.sequence[TransformStamped]


@final
@dataclass
class Gid(IdlStruct, typename="rmw_dds_common::msg::dds_::Gid_"):
    data_: t.array[t.byte, 16]


@final
@dataclass
class NodeEntitiesInfo(IdlStruct, typename="rmw_dds_common::msg::dds_::NodeEntitiesInfo_"):
    node_namespace_: t.bounded_str[256]
    node_name_: t.bounded_str[256]
    reader_gid_seq_: t.sequence[Gid]
    writer_gid_seq_: t.sequence[Gid]


@final
@dataclass
class ParticipantEntitiesInfo(IdlStruct,
                              typename="rmw_dds_common::msg::dds_::ParticipantEntitiesInfo_"):
    gid_: Gid
    node_entities_info_seq_: t.sequence[NodeEntitiesInfo]


def emit(obj: dict) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def main() -> None:
    domain, seconds = int(sys.argv[1]), float(sys.argv[2])
    dp = DomainParticipant(domain)
    reliable = Policy.Reliability.Reliable(duration(seconds=1))
    altitude = DataReader(dp, Topic(dp, "rt/aurora/rocket1/altitude", Float64),
                          Qos(reliable, Policy.History.KeepLast(1000)))
    state = DataReader(dp, Topic(dp, "rt/aurora/rocket1/state", String),
                       Qos(reliable, Policy.Durability.TransientLocal,
                           Policy.History.KeepLast(100)))
    tf = DataReader(dp, Topic(dp, "rt/tf", TFMessage), Qos(reliable, Policy.History.KeepLast(1000)))
    graph = DataReader(dp, Topic(dp, "ros_discovery_info", ParticipantEntitiesInfo),
                       Qos(reliable, Policy.Durability.TransientLocal, Policy.History.KeepLast(1)))
    pubs = BuiltinDataReader(dp, BuiltinTopicDcpsPublication)
    waitset = WaitSet(dp)
    for reader in (altitude, state, tf, graph, pubs):
        waitset.attach(ReadCondition(reader, SampleState.Any | ViewState.Any
                                     | InstanceState.Any))
    emit({"ready": True})
    end = time.monotonic() + seconds
    seen: set[str] = set()
    while time.monotonic() < end:
        for s in altitude.take(N=1000):
            if s.sample_info.valid_data:
                emit({"topic": "altitude", "data": s.data_,
                      "ts": s.sample_info.source_timestamp})
        for s in state.take(N=100):
            if s.sample_info.valid_data:
                emit({"topic": "state", "data": s.data_, "ts": s.sample_info.source_timestamp})
        for s in tf.take(N=1000):
            if not s.sample_info.valid_data:
                continue
            for x in s.transforms_:
                r = x.transform_.rotation_
                stamp = x.header_.stamp_.sec_ * 1_000_000_000 + x.header_.stamp_.nanosec_
                emit({"topic": "tf", "parent": x.header_.frame_id_,
                      "child": x.child_frame_id_, "z": x.transform_.translation_.z_,
                      "q": [r.x_, r.y_, r.z_, r.w_], "stamp": stamp,
                      "ts": s.sample_info.source_timestamp})
        for g in graph.take(N=10):
            if g.sample_info.valid_data:
                emit({"graph": bytes(g.gid_.data_).hex(),
                      "nodes": [{"namespace": n.node_namespace_, "name": n.node_name_,
                                 "writers": [bytes(w.data_).hex() for w in n.writer_gid_seq_]}
                                for n in g.node_entities_info_seq_]})
        for p in pubs.take(N=100):
            if not p.sample_info.valid_data or not p.topic_name.startswith("rt/"):
                continue
            if str(p.key) in seen:
                continue
            seen.add(str(p.key))
            qos = p.qos  # (a Qos, no dict: no get())
            user_data = qos[Policy.Userdata] if Policy.Userdata in qos else None  # noqa: SIM401
            durability = (qos[Policy.Durability]  # noqa: SIM401
                          if Policy.Durability in qos else None)
            emit({"publication": p.topic_name, "type_name": p.type_name,
                  "key": p.key.bytes.hex(), "participant": p.participant_key.bytes.hex(),
                  "user_data": user_data.data.decode() if user_data else None,
                  "transient_local": durability == Policy.Durability.TransientLocal})
        waitset.wait(duration(milliseconds=100))  # until a reader has data


if __name__ == "__main__":
    main()
