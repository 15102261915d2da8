"""ROS 2 backend: the flight on DDS as ROS 2 nodes see it, with Eclipse Cyclone DDS.

A ROS 2 node on any DDS RMW (Fast DDS, Cyclone DDS) receives it with no bridge and no package
of ours, because every writer follows ROS 2's conventions:

* topic ``rt`` + the ROS name (``rt/aurora/rocket1/altitude``, ``rt/tf``);
* type ``<pkg>::msg::dds_::<Type>_`` as ROS's DDS IDL declares it (:mod:`backends.ros2.idl`),
  final, plain CDR (XCDR1: the DataRepresentation QoS says so); the bytes are
  :mod:`backends.ros2.cdr`'s, the same the rmw_zenoh publication and the rosbag2 export carry;
* ``typehash=RIHS01_…;`` in each writer's USER_DATA (Iron and later check it) and
  ``enclave=/;`` in the participant's, as a ROS 2 participant has;
* the node: the writers belong to the ROS 2 node ``node`` (``/aurora_gateway``), announced
  on ``ros_discovery_info`` as an Iron-or-later participant does (``ros2 node list``,
  ``ros2 topic info -v``, rqt_graph);
* QoS: state and armed reliable, transient local (a late joiner gets the current state at
  once, and only it: the durability service keeps the last one; a reader already there gets
  every change, up to 100 unacknowledged); the others ROS 2's default, reliable, volatile,
  keep last 10 (a reliable writer matches both reliable and best-effort readers:
  ``ros2 topic echo``, rviz2, PlotJuggler);
* the domain: ``domain_id``, else ``ROS_DOMAIN_ID``, else 0; Cyclone DDS reads its own
  configuration (network interface, peers) from ``CYCLONEDDS_URI``.

What is published (:mod:`backends.ros2.topics`): per vehicle (``msg.vehicle``)
``/aurora/<vehicle>/{altitude,imu,state,armed,fix,battery}``, and ``/tf`` (``world`` →
``<vehicle>``) and ``/diagnostics`` for all.  A message naming no vehicle is the vehicle's of
the source its ``origin`` names, else the first configured source's.

The handlers never block the dispatcher: messages are handed over (:class:`Handover`, bounded
by ``queue_depth``; ``dropped_queue_full`` past it) to the backend's own loop, which encodes
and writes them (a reliable write may wait there, up to ``MAX_BLOCKING_S``, for a slow
reader; a write that fails is counted in ``write_errors``).  Writers are created as their
topics first appear: at most ``MAX_VEHICLES`` vehicles (``dropped_vehicle_limit``).
"""

from __future__ import annotations

import logging
import os
import threading
from typing import Any, ClassVar

from cyclonedds.core import DDSException
from cyclonedds.domain import DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from backends.ros2 import idl, rmw_zenoh
from backends.ros2.options import Ros2Options
from backends.ros2.topics import LATCHED_LEAVES, RosTopics, Sample, dds_topic
from backends.ros2.types import PARTICIPANT_ENTITIES_INFO, RosType
from gateway.backend import Backend, BackendError, GatewayContext, Routes
from gateway.config import ConfigError
from gateway.handover import Handover
from gateway.io.burstlog import BurstLog
from gateway.io.ioloop import IoLoop
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    SmUpdate,
    Status,
    VehicleState,
)
from gateway.vehicles import SERVICE as VEHICLES_SERVICE

log = logging.getLogger(__name__)

#: Vehicles published at most (each has six writers of its own).
MAX_VEHICLES = 64
#: How long a reliable write may wait for a slow reader's acknowledgements.
MAX_BLOCKING_S = 0.05
CLOSE_TIMEOUT_S = 0.5
URI_ENV = "CYCLONEDDS_URI"
#: ROS 2's default history depth (rmw_qos_profile_default).
DEPTH = 10
#: A latched topic's history for the readers already there: every state change reaches them
#: even when one acknowledges slowly (a late joiner gets the last one only: the durability
#: service's depth, 1).
LATCHED_DEPTH = 100
#: What a ROS 2 participant's USER_DATA says (rmw_dds_common): the security enclave.
PARTICIPANT_USER_DATA = b"enclave=/;"
#: The ROS 2 graph's topic: each participant's nodes and their readers' and writers' gids.
DISCOVERY_TOPIC = "ros_discovery_info"
#: The message types that have ROS topics (:class:`RosTopics`).
ROUTED = (SmUpdate, Status, Position, Battery, LinkStats, LinkEvent, VehicleState)


def writer_qos(ros_type: RosType, latched: bool) -> Qos:
    """A ROS 2 writer's QoS: latched (state, armed) reliable + transient local, the last
    value kept for late joiners (durability service history 1; the history for the readers
    already there: ``LATCHED_DEPTH``), else ROS 2's default (reliable, volatile, keep last
    10); XCDR1; the type hash."""
    reliable = Policy.Reliability.Reliable(duration(seconds=MAX_BLOCKING_S))
    common = (Policy.DataRepresentation(use_cdrv0_representation=True),
              Policy.Userdata(ros_type.user_data))
    if latched:
        last = Policy.DurabilityService(cleanup_delay=0, history=Policy.History.KeepLast(1),
                                        max_samples=-1, max_instances=-1,
                                        max_samples_per_instance=-1)
        return Qos(reliable, Policy.Durability.TransientLocal,
                   Policy.History.KeepLast(LATCHED_DEPTH), last, *common)
    return Qos(reliable, Policy.Durability.Volatile, Policy.History.KeepLast(DEPTH), *common)


def discovery_qos() -> Qos:
    """``ros_discovery_info``'s QoS (rmw_dds_common): reliable, transient local, keep last 1."""
    return Qos(Policy.Reliability.Reliable(duration(seconds=MAX_BLOCKING_S)),
               Policy.Durability.TransientLocal, Policy.History.KeepLast(1),
               Policy.DataRepresentation(use_cdrv0_representation=True),
               Policy.Userdata(PARTICIPANT_ENTITIES_INFO.user_data))


class _Writer:
    """One topic's writer and the sample object it is handed (its CDR set per write)."""

    __slots__ = ("carrier", "writer")

    def __init__(self, writer: DataWriter[Any], carrier: Any) -> None:
        self.writer = writer
        self.carrier = carrier


class Ros2Backend(Backend):
    """Publishes the flight on ROS 2 topics over DDS; see the module docstring and
    README.md."""

    NAME = "ros2"
    OPTIONS = Ros2Options
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None

    def __init__(self, options: Ros2Options | None = None, name: str | None = None) -> None:
        super().__init__(name)
        self.options = options = options or Ros2Options()
        self.domain_id: int | None = None
        self.topics = RosTopics(max_vehicles=MAX_VEHICLES)
        self._ready = threading.Event()
        self.handover = Handover(self.name, options.queue_depth, ready=self._ready.is_set)
        self._loop: IoLoop | None = None
        self._participant: DomainParticipant | None = None
        self._topics: dict[str, Topic[Any]] = {}
        self._writers: dict[str, _Writer] = {}
        self._source_vehicle: dict[str, str] = {}
        self._write_log: BurstLog | None = None
        self._discovery: DataWriter[Any] | None = None
        # counters
        self.sent = 0          # samples written
        self.messages = 0      # gateway messages turned into samples
        self.write_errors = 0
        self.writer_errors = 0  # topics whose writer could not be created
        self.announcements = 0  # the node's, on ros_discovery_info

    # -- life cycle --------------------------------------------------------------------------

    def attach(self, context: GatewayContext) -> None:
        super().attach(context)
        configured = [sv for sv in context.services.get(VEHICLES_SERVICE) or []
                      if sv.vehicle and not sv.systems]
        self._source_vehicle = {sv.source: sv.vehicle for sv in configured}
        if configured:
            self.topics.default_vehicle = configured[0].vehicle
        # the same topics on rmw_zenoh, through the zenoh backend's session if it runs
        rmw_zenoh.request(context, self.options.domain, self.options.node)

    def init(self) -> None:
        """Join the domain, declare the configured vehicles' writers, start the loop."""
        if self._loop is not None:
            return
        try:
            self.domain_id = self.options.domain()
        except ConfigError as exc:
            raise BackendError(f"{self.name}: {exc}") from None
        try:
            self._participant = DomainParticipant(
                self.domain_id, qos=Qos(Policy.Userdata(PARTICIPANT_USER_DATA)))
        except DDSException:
            uri = os.environ.get(URI_ENV)
            raise BackendError(
                f"{self.name}: cannot join DDS domain {self.domain_id}"
                + (f" with {URI_ENV}={uri!r}" if uri else "")
                + ": Cyclone DDS refused (its reason is the line it wrote before)") from None
        if self.options.node:
            try:
                self._discovery = DataWriter(
                    self._participant, Topic(self._participant, DISCOVERY_TOPIC,
                                             idl.ParticipantEntitiesInfo_), discovery_qos())
            except DDSException as exc:  # the topics work without: only the graph misses it
                log.warning("ros2 %s: cannot announce node %s: %s", self.name,
                            self.options.node, exc)
        for vehicle in dict.fromkeys(self._source_vehicle.values()):
            for topic, ros_type in self.topics.topics_of(vehicle):
                self._writer(topic, ros_type, topic.rsplit("/", 1)[-1] in LATCHED_LEAVES,
                             announce=False)
        self._announce()
        self._loop = loop = IoLoop(f"ros2-{self.name}")
        self._write_log = BurstLog(loop, f"ros2 {self.name}: a DDS write failed", logger=log)
        loop.start()
        self.handover.open(loop)
        self._ready.set()
        log.info("ros2 %s: publishing /aurora/<vehicle>/… and /tf on DDS domain %d (Cyclone "
                 "DDS)", self.name, self.domain_id)

    def close(self) -> None:
        """Write what is queued (within 0.5 s), then leave the domain; safe twice."""
        self.handover.close(CLOSE_TIMEOUT_S)
        self._ready.clear()
        loop, self._loop = self._loop, None
        if loop is not None and loop.stop(CLOSE_TIMEOUT_S):
            loop.close()
        self._writers.clear()
        self._topics.clear()
        self._discovery = None
        participant, self._participant = self._participant, None
        del participant  # the last reference: its writers and topics go with it

    # -- the loop ----------------------------------------------------------------------------

    def routes(self) -> Routes:
        routes = Routes(handover=self.handover)
        for cls in ROUTED:
            routes.on(cls, self.publish)
        return routes

    def publish(self, msg: Any) -> None:
        """One gateway message: its ROS samples, each written on its topic (the loop's
        thread)."""
        if not msg.vehicle:  # a backend's own (a radio's link stats), or a link event
            source = msg.source if type(msg) is LinkEvent else msg.origin
            vehicle = self._source_vehicle.get(source)
            if vehicle:
                msg = msg._replace(vehicle=vehicle)
        samples = self.topics.samples(msg)
        if samples:
            self.messages += 1
        for s in samples:
            self._write(s)

    def _write(self, s: Sample) -> None:
        w = self._writers.get(s.topic)
        if w is None:
            w = self._writer(s.topic, s.type, s.latched)
            if w is None:
                return
        w.carrier._cdr = s.cdr
        try:
            w.writer.write(w.carrier, timestamp=s.stamp_ns)
        except DDSException as exc:
            self.write_errors += 1
            if self._write_log is not None:
                self._write_log.event(f"{dds_topic(s.topic)}: {exc}")
            return
        self.sent += 1

    def _writer(self, topic: str, ros_type: RosType, latched: bool,
                announce: bool = True) -> _Writer | None:
        """The writer of ``topic`` (created on first use, and announced as the node's; None
        if it cannot be, counted)."""
        w = self._writers.get(topic)
        if w is not None or self._participant is None:
            return w
        cls = idl.CLASSES[ros_type.name]
        try:
            t = self._topics.get(topic)
            if t is None:
                t = self._topics[topic] = Topic(self._participant, dds_topic(topic), cls)
            w = _Writer(DataWriter(self._participant, t, writer_qos(ros_type, latched)),
                        idl.carrier(cls))
        except DDSException as exc:
            self.writer_errors += 1
            log.warning("ros2 %s: no writer for %s: %s", self.name, dds_topic(topic), exc)
            return None
        self._writers[topic] = w
        if announce:
            self._announce()
        return w

    def _announce(self) -> None:
        """The node and its writers on ``ros_discovery_info`` (at start, then at each new
        writer): what ``ros2 node list`` and ``ros2 topic info -v`` read."""
        if self._discovery is None or self._participant is None:
            return
        info = idl.participant_entities_info(
            self._participant.guid, "/", self.options.node,
            [w.writer.guid for w in self._writers.values()])
        try:
            self._discovery.write(info)
            self.announcements += 1
        except DDSException as exc:
            self.write_errors += 1
            log.warning("ros2 %s: cannot announce node %s: %s", self.name,
                        self.options.node, exc)

    # -- status ------------------------------------------------------------------------------

    @property
    def ready(self) -> bool:
        return self._ready.is_set()

    @property
    def processed(self) -> int:
        """Messages handled so far (for tools and tests)."""
        return self.handover.handled

    def stats(self) -> dict[str, Any]:
        h = self.handover
        return {"sent": self.sent, "dropped": h.dropped + self.topics.dropped_vehicle_limit,
                "errors": self.write_errors + self.writer_errors + h.handler_errors,
                "link": int(self._participant is not None), **h.stats(),
                "messages": self.messages, "write_errors": self.write_errors,
                "writer_errors": self.writer_errors, "writers": len(self._writers),
                "announcements": self.announcements,
                "vehicles": len(self.topics.vehicles),
                "dropped_vehicle_limit": self.topics.dropped_vehicle_limit,
                "domain_id": self.domain_id}
