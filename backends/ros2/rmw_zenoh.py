"""The ROS 2 topics on Zenoh as rmw_zenoh carries them (the facts, with where they come from:
docs/rmw-zenoh.md): a ROS 2 node on ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` sees them with no
bridge.

Two layers:

* the wire conventions, pure functions: :func:`topic_key` (where a topic's samples go),
  :func:`node_token` / :func:`publisher_token` (the liveliness tokens of the graph),
  :func:`entity_gid` and :func:`attachment` / :func:`parse_attachment` (what every sample
  carries), :func:`qos_text` (a token's QoS);
* :class:`RmwZenoh`, the publisher: bound to a Zenoh session (the ``zenoh`` backend's, on that
  backend's loop: it follows its endpoints, reconnects and hand-over), it turns each gateway
  message into ROS samples (:class:`backends.ros2.topics.RosTopics`, the same CDR bytes the DDS
  side publishes) and puts them, declaring a node token and one publisher (with its token) per
  topic on first use.  Topics are bounded (:data:`MAX_TOPICS`, counted beyond).

The ``ros2`` backend asks for it with :func:`request` in its ``attach`` (the domain id); the
``zenoh`` backend finds the request with :func:`bridge_for` in its ``init``.  Either alone does
nothing here: without the ``zenoh`` backend the ROS topics are on DDS only.
"""

from __future__ import annotations

import contextlib
import logging
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)

#: The admin space of rmw_zenoh's liveliness tokens
ADMIN_SPACE = "@ros2_lv"
#: The gateway's ROS node: its name, namespace and enclave (rcl's defaults for the last two)
NODE_NAME = "aurora_gateway"
NODE_NAMESPACE = "/"
ENCLAVE = "/"
#: RMW_GID_STORAGE_SIZE (Iron and later)
GID_SIZE = 16
#: rmw_zenoh's default QoS (what a token leaves empty): reliable, volatile, keep last 42
DEFAULT_DEPTH = 42
#: The most topics one gateway puts (per vehicle seven, plus /tf and /diagnostics): beyond, the
#: samples are counted (``dropped_topic_limit``), not published
MAX_TOPICS = 2048
#: A reliable transient-local publisher's sporadic heartbeat (rmw_zenoh's 500 ms): how a
#: subscriber notices it missed the last sample and fetches it from the cache
HEARTBEAT_S = 0.5
#: The context key under which the ros2 backend asks for the rmw_zenoh topics
SERVICE = "ros2.rmw_zenoh"

_SEQ_TS = struct.Struct("<qq")
#: rmw's enum values a QoS chunk names (rmw/types.h)
_BEST_EFFORT = 2
_TRANSIENT_LOCAL = 1


@dataclass(frozen=True)
class Qos:
    """A publisher's QoS as far as rmw_zenoh's graph tells it."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10


#: state and armed: a late joiner gets the current value at once
LATCHED = Qos(reliable=True, transient_local=True, depth=1)
#: every other topic: reliable, volatile, keep last 10 (rclcpp's default profile)
STREAM = Qos()


def mangle(name: str) -> str:
    """A ROS name as one key chunk: every ``/`` replaced by ``%`` (rmw_zenoh's mangling)."""
    return name.replace("/", "%")


def _strip_slashes(name: str) -> str:
    """The name without one leading and one trailing ``/`` (as rmw_zenoh strips a topic)."""
    if name.startswith("/"):
        name = name[1:]
    if name.endswith("/"):
        name = name[:-1]
    return name


def topic_key(domain_id: int, topic: str, dds_type: str, rihs01: str) -> str:
    """The key expression of a topic's samples: ``<domain>/<topic>/<type>/<hash>``."""
    return f"{domain_id}/{_strip_slashes(topic)}/{dds_type}/{rihs01}"


def qos_text(qos: Qos) -> str:
    """A token's QoS chunk: each policy's rmw enum number, empty where it is rmw_zenoh's
    default (``::,10:,:,:,,`` for reliable, volatile, keep last 10)."""
    reliability = "" if qos.reliable else str(_BEST_EFFORT)
    durability = str(_TRANSIENT_LOCAL) if qos.transient_local else ""
    depth = "" if qos.depth == DEFAULT_DEPTH else str(qos.depth)
    # history (keep last: the default), depth; deadline, lifespan (s, ns); liveliness (kind,
    # lease s, ns): all defaults
    return f"{reliability}:{durability}:,{depth}:,:,:,,"


def _node_part(domain_id: int, zid: str, node_id: int, entity_id: int, entity: str,
               node: str, namespace: str, enclave: str) -> str:
    return (f"{ADMIN_SPACE}/{domain_id}/{zid}/{node_id}/{entity_id}/{entity}/"
            f"{mangle(enclave)}/{mangle(namespace)}/{mangle(node)}")


def node_token(domain_id: int, zid: str, node_id: int, node: str = NODE_NAME,
               namespace: str = NODE_NAMESPACE, enclave: str = ENCLAVE) -> str:
    """A node's liveliness token (``NN``; the node's id is also its entity id)."""
    return _node_part(domain_id, zid, node_id, node_id, "NN", node, namespace, enclave)


def publisher_token(domain_id: int, zid: str, node_id: int, entity_id: int, topic: str,
                    dds_type: str, rihs01: str, qos: Qos, node: str = NODE_NAME,
                    namespace: str = NODE_NAMESPACE, enclave: str = ENCLAVE) -> str:
    """A publisher's liveliness token (``MP``)."""
    return (_node_part(domain_id, zid, node_id, entity_id, "MP", node, namespace, enclave)
            + f"/{mangle(topic)}/{mangle(dds_type)}/{mangle(rihs01)}/{qos_text(qos)}")


def entity_gid(token: str) -> bytes:
    """An entity's GID: the XXH3-128 hash of its liveliness token, low 64 bits first, each
    little endian (rmw_zenoh's ``Entity``)."""
    import xxhash

    return xxhash.xxh3_128_intdigest(token.encode()).to_bytes(GID_SIZE, "little")


def attachment(seq: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """A sample's attachment: sequence number and source timestamp (int64 little endian),
    then the GID as a Zenoh-serialized sequence of 16 bytes (length ``0x10``, the bytes)."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(gid)}")
    return _SEQ_TS.pack(seq, source_timestamp_ns) + bytes((GID_SIZE,)) + gid


def parse_attachment(data: bytes) -> tuple[int, int, bytes]:
    """``(sequence number, source timestamp ns, GID)`` of an attachment; ValueError when it is
    not one."""
    if len(data) != _SEQ_TS.size + 1 + GID_SIZE or data[_SEQ_TS.size] != GID_SIZE:
        raise ValueError(f"not an rmw_zenoh attachment ({len(data)} bytes)")
    seq, ts = _SEQ_TS.unpack_from(data)
    return seq, ts, bytes(data[_SEQ_TS.size + 1:])


# -- the request (ros2 backend → zenoh backend) -----------------------------------------------


@dataclass(frozen=True)
class Request:
    """What the ros2 backend asks of the zenoh backend's session: its domain (read when the
    zenoh backend starts: ``domain_id``, else ``ROS_DOMAIN_ID``, as the DDS side reads it) and
    its node's name."""

    domain: Callable[[], int]
    node: str = NODE_NAME


def request(context: Any, domain: int | Callable[[], int], node: str = "") -> None:
    """Ask for the rmw_zenoh topics on ``domain`` from the node ``node`` ("": the default,
    ``aurora_gateway``; rmw_zenoh's graph has no publisher without a node) — the ros2
    backend's ``attach``, with its options' ``domain`` and ``node``."""
    context.services[SERVICE] = Request(domain if callable(domain) else lambda: domain,
                                        node or NODE_NAME)


def bridge_for(context: Any, backend: str = "zenoh") -> RmwZenoh | None:
    """The publisher the ros2 backend asked for (None: it runs not, or found no request).
    A message naming no vehicle is the first configured source's vehicle's, as on DDS."""
    req = context.services.get(SERVICE)
    if req is None:
        return None
    try:
        domain_id = req.domain()
    except ValueError as exc:  # (ConfigError: a bad ROS_DOMAIN_ID, which the ros2 backend says)
        log.warning("zenoh %s: no ROS 2 topics on rmw_zenoh: %s", backend, exc)
        return None
    from backends.ros2.topics import RosTopics
    from gateway.vehicles import SERVICE as VEHICLES_SERVICE

    topics = RosTopics()
    configured = [sv.vehicle for sv in context.services.get(VEHICLES_SERVICE) or []
                  if sv.vehicle and not sv.systems]
    if configured:
        topics.default_vehicle = configured[0]
    return RmwZenoh(domain_id, name=backend, samples=topics.samples, node=req.node)


# -- the publisher ------------------------------------------------------------------------------


class _Topic:
    """One topic published: its key, publisher, token and attachment state."""

    __slots__ = ("gid_tail", "key", "publisher", "seq", "token")

    def __init__(self, key: str, publisher: Any, token: Any, gid: bytes) -> None:
        self.key = key
        self.publisher = publisher
        self.token = token
        self.gid_tail = bytes((GID_SIZE,)) + gid  # the attachment's constant end
        self.seq = 0


class RmwZenoh:
    """Puts the gateway's ROS samples on a Zenoh session as rmw_zenoh does (the module
    docstring).  Not thread-safe: one thread (the zenoh backend's loop) calls everything."""

    def __init__(self, domain_id: int = 0, *, name: str = "zenoh",
                 samples: Callable[[Any], Iterable[Any]] | None = None,
                 clock: Callable[[], int] = time.time_ns, node: str = NODE_NAME) -> None:
        if samples is None:
            from backends.ros2.topics import RosTopics

            samples = RosTopics().samples
        self.domain_id = domain_id
        self.name = name
        self.node_name = node
        self._samples = samples
        self._clock = clock
        self._session: Any = None
        self._zid = ""
        self._node_token: Any = None
        self._topics: dict[str, _Topic] = {}
        self._next_id = 0
        # counters
        self.puts = 0
        self.put_errors = 0
        self.sample_errors = 0
        self.declare_errors = 0
        self.dropped_topic_limit = 0
        self.dropped_no_session = 0

    #: the ROS node's id in the session (its name: ``node_name``)
    node_id = 0

    def declare(self, session: Any) -> None:
        """Take ``session``: declare the node's token (the topics' on their first sample)."""
        self.undeclare()
        self._session = session
        self._zid = str(session.info.zid())
        self._next_id = 1  # 0 is the node
        try:
            self._node_token = session.liveliness().declare_token(
                node_token(self.domain_id, self._zid, self.node_id, self.node_name))
        except Exception as exc:  # published all the same; the graph misses the node
            self.declare_errors += 1
            log.warning("zenoh %s: cannot declare the ROS node's token: %s", self.name, exc)

    def undeclare(self) -> None:
        """Undeclare every token and publisher (before the session closes); safe twice."""
        ents = [e for t in self._topics.values() for e in (t.token, t.publisher)]
        ents.append(self._node_token)
        for ent in ents:
            if ent is None:
                continue
            try:
                ent.undeclare()
            except Exception:
                log.debug("zenoh %s: undeclare failed", self.name, exc_info=True)
        self._topics = {}
        self._node_token = None
        self._session = None

    def handle(self, msg: Any) -> None:
        """Put ``msg``'s ROS samples (never raises: failures are counted)."""
        try:
            samples = self._samples(msg)
        except Exception as exc:
            self.sample_errors += 1
            if self.sample_errors == 1:
                log.warning("zenoh %s: no ROS samples of %s: %s: %s", self.name,
                            type(msg).__name__, type(exc).__name__, exc)
            return
        for sample in samples:
            self.put(sample)

    def put(self, sample: Any) -> bool:
        """Put one sample on its topic's key with its attachment."""
        topic = self._topics.get(sample.topic)
        if topic is None:
            topic = self._declare_topic(sample)
            if topic is None:
                return False
        topic.seq += 1
        att = _SEQ_TS.pack(topic.seq, self._clock()) + topic.gid_tail
        try:
            topic.publisher.put(sample.cdr, attachment=att)
        except Exception as exc:
            self.put_errors += 1
            if self.put_errors == 1:
                log.warning("zenoh %s: put on %s failed: %s", self.name, topic.key, exc)
            return False
        self.puts += 1
        return True

    def _declare_topic(self, sample: Any) -> _Topic | None:
        session = self._session
        if session is None:
            self.dropped_no_session += 1
            return None
        if len(self._topics) >= MAX_TOPICS:
            self.dropped_topic_limit += 1
            if self.dropped_topic_limit == 1:
                log.warning("zenoh %s: more than %d ROS topics; %s and any further one not "
                            "published (ros2_dropped_topic_limit)", self.name, MAX_TOPICS,
                            sample.topic)
            return None
        import zenoh
        import zenoh.ext

        rtype = sample.type
        qos = LATCHED if sample.latched else STREAM
        key = topic_key(self.domain_id, sample.topic, rtype.dds_name, rtype.rihs01)
        entity_id = self._next_id
        self._next_id += 1
        token_key = publisher_token(self.domain_id, self._zid, self.node_id, entity_id,
                                    sample.topic, rtype.dds_name, rtype.rihs01, qos,
                                    self.node_name)
        publisher = None
        try:
            if qos.transient_local:
                publisher = zenoh.ext.declare_advanced_publisher(
                    session, key, congestion_control=zenoh.CongestionControl.DROP,
                    reliability=zenoh.Reliability.RELIABLE,
                    cache=zenoh.ext.CacheConfig(qos.depth), publisher_detection=True,
                    sample_miss_detection=zenoh.ext.MissDetectionConfig(
                        heartbeat=None, sporadic_heartbeat=HEARTBEAT_S))
            else:
                publisher = session.declare_publisher(
                    key, congestion_control=zenoh.CongestionControl.DROP,
                    reliability=zenoh.Reliability.RELIABLE)
            token = session.liveliness().declare_token(token_key)
        except Exception as exc:
            if publisher is not None:  # (its token failed)
                with contextlib.suppress(Exception):
                    publisher.undeclare()
            self.declare_errors += 1
            if self.declare_errors == 1:
                log.warning("zenoh %s: cannot declare the ROS topic %s: %s", self.name,
                            sample.topic, exc)
            return None
        topic = self._topics[sample.topic] = _Topic(key, publisher, token,
                                                    entity_gid(token_key))
        return topic

    def stats(self) -> dict[str, int]:
        """Its counters, named for the zenoh backend's stats (``ros2_…``)."""
        return {
            "ros2_puts": self.puts,
            "ros2_topics": len(self._topics),
            "ros2_put_errors": self.put_errors,
            "ros2_sample_errors": self.sample_errors,
            "ros2_declare_errors": self.declare_errors,
            "ros2_dropped_topic_limit": self.dropped_topic_limit,
            "ros2_dropped_no_session": self.dropped_no_session,
        }
