"""``aurora-gateway export REC --format rosbag2 -o DIR``: a recording as a rosbag2 directory
(``metadata.yaml`` and MCAP storage) for ``ros2 bag play``, rviz2, PlotJuggler and Foxglove.

The topics, types and CDR bytes are the live ``ros2`` backend's
(:class:`backends.ros2.topics.RosTopics`: one altitude, one ``/tf`` and one imu message per
SM update; state and armed when they change; fix, battery and ``/diagnostics`` when known),
each message stamped — its header and its bag time both — with the time the gateway received
the frame that carried it.  Written by ``rosbags`` (the ``ros2`` extra): the bag's message
definitions and RIHS01 hashes are its type store's (ROS 2 Jazzy's), and the offered QoS of
each topic is what the live backend offers (state and armed transient local, so ``ros2 bag
play`` latches them).  Metadata version 8: what Jazzy's and Kilted's ``ros2 bag`` read.
"""

from __future__ import annotations

import contextlib
import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from backends.ros2.rmw_zenoh import LATCHED, STREAM, Qos
from backends.ros2.topics import RosTopics

#: rosbag2's metadata version written: Jazzy writes 8 and Kilted reads it
BAG_VERSION: Literal[8] = 8
#: rmw's infinite duration, as ``ros2 bag record`` writes it
_INFINITE = (9223372036, 854775807)


class BagError(Exception):
    """The bag cannot be written; the text is one line (e.g. the directory exists)."""


@dataclass
class Written:
    """What :func:`write` wrote: messages per topic, and the type of each topic."""

    counts: Counter[str] = field(default_factory=Counter)
    types: dict[str, str] = field(default_factory=dict)

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def _offered_qos(qos: Qos) -> Any:
    from rosbags.interfaces import (
        Qos as BagQos,
    )
    from rosbags.interfaces import (
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    infinite = QosTime(*_INFINITE)
    return BagQos(
        history=QosHistory.KEEP_LAST, depth=qos.depth,
        reliability=QosReliability.RELIABLE if qos.reliable else QosReliability.BEST_EFFORT,
        durability=(QosDurability.TRANSIENT_LOCAL if qos.transient_local
                    else QosDurability.VOLATILE),
        deadline=infinite, lifespan=infinite, liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=infinite, avoid_ros_namespace_conventions=False)


def time_ns(t: float) -> int:
    """Seconds since the epoch as integer ns (exact in the integer part, which
    ``round(t * 1e9)`` is not at today's epoch); 0 for a negative or NaN time."""
    if not t > 0:
        return 0
    whole = math.floor(t)
    return whole * 1_000_000_000 + round((t - whole) * 1e9)


def check_target(directory: str | Path) -> Path:
    """The bag's directory, which must not exist yet; :class:`BagError` otherwise."""
    path = Path(directory)
    if path.exists() or path.is_symlink():
        raise BagError(f"{path} exists: a rosbag2 export creates its directory (give a new "
                       "name, or remove it)")
    if not path.parent.is_dir():
        raise BagError(f"{path.parent} is not a directory")
    return path


def write(messages: Iterable[tuple[float, Any]], directory: str | Path,
          vehicles: list[str] | None = None,
          custom_data: dict[str, str] | None = None) -> Written:
    """Write the ROS samples of ``messages`` (``(receive time s, message)`` in recording
    order) as a new rosbag2 directory; ``vehicles`` names the vehicle of a message that
    names none (the first); ``custom_data`` goes into the bag's metadata (``ros2 bag info``
    shows it).  :class:`BagError` when the directory exists; OSError when it cannot be written
    (a half-written directory is removed)."""
    from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
    from rosbags.typesys import Stores, get_typestore

    path = check_target(directory)
    typestore = get_typestore(Stores.ROS2_JAZZY)
    topics = RosTopics(vehicles[0]) if vehicles else RosTopics()
    written = Written()
    connections: dict[str, Any] = {}
    try:
        writer = Writer(path, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        for key, value in (custom_data or {}).items():
            writer.set_custom_data(key, value)
    except WriterError as exc:  # (the directory appeared since: not ours to remove)
        raise BagError(str(exc)) from None
    opened = False  # (then the directory is the bag's, made by open)
    try:
        with writer:
            opened = True
            for t, msg in messages:
                stamp_ns = time_ns(t)
                for sample in topics.samples(msg, stamp_ns):
                    conn = connections.get(sample.topic)
                    if conn is None:
                        conn = connections[sample.topic] = writer.add_connection(
                            sample.topic, sample.type.name, typestore=typestore,
                            offered_qos_profiles=[
                                _offered_qos(LATCHED if sample.latched else STREAM)])
                        written.types[sample.topic] = sample.type.name
                    writer.write(conn, stamp_ns, sample.cdr)
                    written.counts[sample.topic] += 1
    except WriterError as exc:
        if opened:
            _remove_partial(path)
        raise BagError(str(exc)) from None
    except BaseException:
        if opened:
            _remove_partial(path)
        raise
    return written


def _remove_partial(path: Path) -> None:
    """Remove what a failed export left (only the files a bag has)."""
    if not path.is_dir():
        return
    for child in path.iterdir():
        if child.name == "metadata.yaml" or child.suffix == ".mcap":
            child.unlink(missing_ok=True)
    with contextlib.suppress(OSError):  # something else is in it: leave it
        path.rmdir()
