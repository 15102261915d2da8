"""Sans-I/O UAVTalk telemetry sessions (LibrePilot 16.09): transactions, queues and handshakes.

No sockets, threads or clocks: the caller passes received :class:`~.codec.Packet` s and the time
(seconds, any monotonic origin) in, calls :meth:`tick` on a timer and writes what
:meth:`outgoing` returns.  The rules are ``../shared/specs/uavtalk.md``'s and the seed's:

- **Transactions.**  An OBJ_REQ waits for the OBJ (or a NACK) of its object; an OBJ_ACK (an
  acked send) waits for the ACK (or a NACK).  Each waits 250 ms, is resent twice, then counts a
  failure.  One transaction is outstanding per session; packets that need no reply keep flowing
  past a waiting one.  A deadline starts from the last time passed in (``outgoing`` has no clock).
- **Two queues**, both bounded (newest dropped and counted when full): *priority* (replies,
  handshake, telemetry stats) is always drained first; *regular* (periodic and on-change
  updates) holds at most one entry per object, refreshed in place.
- **Flight side** (:class:`FlightSession`, one per GCS): Disconnected + GCS HandshakeReq →
  HandshakeAck; HandshakeAck + GCS Connected → Connected; HandshakeAck + GCS Disconnected →
  Disconnected; Connected → Disconnected when the GCS is not Connected or nothing arrived for
  8 s.  FlightTelemetryStats goes out on every change and every 5 s.  Data objects are sent per
  their XML ``telemetryflight`` mode once Connected.  Timestamped packets are never sent.
- **GCS side** (:class:`GcsSession`): GCSTelemetryStats(HandshakeReq) every 2 s while not
  connected; FlightTelemetryStats(HandshakeAck) → Connected (GCSTelemetryStats(Connected) at
  once, then every 4 s as the 16.09 GCS does); Disconnected when the flight side says so or
  after 8 s of silence; after connecting, the OBJ_REQ walk one object at a time (a NACK or a
  failure moves on).
- Stats objects carry their counters only while Connected (zeros otherwise, as in 16.09).
- Retries: 16.09's GCS sends a transaction 1 + 2 times; its firmware's loop sends 2 times in
  all.  Both sessions here follow the spec (1 + 2).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, NamedTuple

from gateway.counters import Counters

from .codec import ALL_INSTANCES, Packet, PacketType, encode
from .objects import MetaDef, ObjectDef, ObjectSet, UpdateMode

__all__ = [
    "DEFAULT_WALK",
    "FlightSession",
    "GcsSession",
    "ObjectStore",
    "Status",
    "TelemetryStats",
]

TRANSACTION_TIMEOUT = 0.25
"""Seconds a transaction waits for its reply before a retry."""
MAX_RETRIES = 2
CONNECTION_TIMEOUT = 8.0
"""Seconds without any received packet before a connected link drops."""
STATS_PERIOD = 5.0
"""FlightTelemetryStats, seconds (its XML ``telemetryflight`` period)."""
GCS_STATS_PERIOD = 4.0
"""GCSTelemetryStats once connected, seconds (the 16.09 GCS's ``STATS_UPDATE_PERIOD_MS``)."""
HANDSHAKE_PERIOD = 2.0
"""GCSTelemetryStats(HandshakeReq) while the GCS is not connected, seconds."""
PRIORITY_QUEUE_SIZE = 32
REGULAR_QUEUE_SIZE = 64
DEFAULT_BOARD_TYPE = 0x09
"""FirmwareIAPObj.BoardType served when the store has none (0x09: Revolution); the 16.09 GCS
reports a connection only once it reads a nonzero one."""

FLIGHT_STATS = "FlightTelemetryStats"
GCS_STATS = "GCSTelemetryStats"
FIRMWARE = "FirmwareIAPObj"

DEFAULT_WALK = ("FirmwareIAPObj", "FlightStatus", "AttitudeState", "SystemAlarms",
                "GPSPositionSensor", "FlightBatteryState", "BaroSensor")
"""The objects :class:`GcsSession` requests after connecting, in this order."""


class Status(IntEnum):
    """The ``Status`` enum of Flight/GCSTelemetryStats."""

    DISCONNECTED = 0
    HANDSHAKE_REQ = 1
    HANDSHAKE_ACK = 2
    CONNECTED = 3


@dataclass
class TelemetryStats(Counters):
    """One session's counters (``tx_*``/``rx_*`` per packet type; ``handshake_ms`` is the last
    time from the first HandshakeReq to Connected)."""

    tx_obj: int = 0
    tx_obj_req: int = 0
    tx_obj_ack: int = 0
    tx_ack: int = 0
    tx_nack: int = 0
    tx_bytes: int = 0
    rx_obj: int = 0
    rx_obj_req: int = 0
    rx_obj_ack: int = 0
    rx_ack: int = 0
    rx_nack: int = 0
    rx_bytes: int = 0
    rx_timestamped: int = 0
    rx_unknown: int = 0
    rx_bad_length: int = 0
    rx_unexpected: int = 0
    transactions: int = 0
    retries: int = 0
    failures: int = 0
    priority_drops: int = 0
    regular_drops: int = 0
    state_changes: int = 0
    connects: int = 0
    disconnects: int = 0
    handshake_ms: int = 0


_TX = {PacketType.OBJ: "tx_obj", PacketType.OBJ_REQ: "tx_obj_req",
       PacketType.OBJ_ACK: "tx_obj_ack", PacketType.ACK: "tx_ack", PacketType.NACK: "tx_nack"}
_RX = {PacketType.OBJ: "rx_obj", PacketType.OBJ_REQ: "rx_obj_req",
       PacketType.OBJ_ACK: "rx_obj_ack", PacketType.ACK: "rx_ack", PacketType.NACK: "rx_nack"}
_WIRE_OVERHEAD = 11  # header 10 + CRC


class ObjectStore:
    """The current values of the objects a flight side serves, by name (a copy is kept)."""

    def __init__(self, values: Mapping[str, Mapping[str, Any]] | None = None) -> None:
        self._values: dict[str, dict[str, Any]] = {}
        for name, v in (values or {}).items():
            self.set(name, v)

    def set(self, name: str, values: Mapping[str, Any]) -> None:
        """Replace ``name``'s values (missing fields take their defaults when packed)."""
        self._values[name] = dict(values)

    def get(self, name: str) -> dict[str, Any] | None:
        """A copy of ``name``'s values, None if the store does not hold it."""
        v = self._values.get(name)
        return None if v is None else dict(v)

    def names(self) -> list[str]:
        """The names held, in insertion order."""
        return list(self._values)

    def __contains__(self, name: object) -> bool:
        return name in self._values


class _Transaction(NamedTuple):
    packet: Packet
    reply: PacketType  # OBJ for an OBJ_REQ, ACK for an OBJ_ACK
    deadline: float
    retries_left: int


def _needs_reply(p: Packet) -> bool:
    return p.type in (PacketType.OBJ_REQ, PacketType.OBJ_ACK)


class _Session:
    """Queues, the one outstanding transaction and the counters (shared by both sides)."""

    def __init__(self, objects: ObjectSet) -> None:
        self.objects = objects
        self.stats = TelemetryStats()
        self.state = Status.DISCONNECTED
        self._now = 0.0
        self._priority: deque[Packet] = deque()
        self._regular: deque[Packet] = deque()
        self._retry: list[Packet] = []
        self._pending: _Transaction | None = None
        self._last_rx: float | None = None
        self._handshake_started: float | None = None
        #: called with (old, new) after every state change (a link logs its connections)
        self.on_state: Callable[[Status, Status], Any] | None = None

    # --- queues -----------------------------------------------------------------------------

    def _push_priority(self, p: Packet) -> bool:
        if len(self._priority) >= PRIORITY_QUEUE_SIZE:
            self.stats.priority_drops += 1
            return False
        self._priority.append(p)
        return True

    def _push_regular(self, p: Packet) -> bool:
        for i, q in enumerate(self._regular):  # one entry per object: refresh in place
            if q.object_id == p.object_id and q.instance_id == p.instance_id:
                self._regular[i] = p
                return True
        if len(self._regular) >= REGULAR_QUEUE_SIZE:
            self.stats.regular_drops += 1
            return False
        self._regular.append(p)
        return True

    @property
    def queued(self) -> int:
        """Packets waiting in both queues (a retry in flight not included)."""
        return len(self._priority) + len(self._regular)

    @property
    def transaction_pending(self) -> bool:
        """Whether a transaction is waiting for its reply."""
        return self._pending is not None

    def outgoing(self) -> list[bytes]:
        """Encoded packets to write now: retries, then the priority queue, then the regular one.
        A packet that needs a reply waits in its queue while another transaction is open."""
        out: list[Packet] = self._retry
        self._retry = []
        for queue in (self._priority, self._regular):
            held: deque[Packet] = deque()
            while queue:
                p = queue.popleft()
                if _needs_reply(p):
                    if self._pending is not None:
                        held.append(p)
                        continue
                    reply = PacketType.OBJ if p.type == PacketType.OBJ_REQ else PacketType.ACK
                    self._pending = _Transaction(p, reply, self._now + TRANSACTION_TIMEOUT,
                                                 MAX_RETRIES)
                    self.stats.transactions += 1
                out.append(p)
            queue.extend(held)
        wire = []
        for p in out:
            data = encode(p)
            setattr(self.stats, _TX[p.type], getattr(self.stats, _TX[p.type]) + 1)
            self.stats.tx_bytes += len(data)
            wire.append(data)
        return wire

    # --- transactions -----------------------------------------------------------------------

    def _check_transaction(self, now: float) -> None:
        t = self._pending
        if t is None or now < t.deadline:
            return
        if t.retries_left > 0:
            self.stats.retries += 1
            self._pending = t._replace(deadline=now + TRANSACTION_TIMEOUT,
                                       retries_left=t.retries_left - 1)
            self._retry.append(t.packet)
            return
        self.stats.failures += 1
        self._pending = None
        self._transaction_done(t.packet, False)

    def receive(self, packet: Packet, now: float) -> None:
        """Handle one packet from the peer: counted; an ACK/NACK completes the open
        transaction; anything else is decoded and handed to the session's ``_handle``."""
        self._count_rx(packet, now)
        if packet.type in (PacketType.ACK, PacketType.NACK):
            self._complete(packet)
            return
        obj, values = self._decode(packet)
        self._handle(packet, obj, values, now)

    def _handle(self, packet: Packet, obj: ObjectDef | None, values: dict[str, Any] | None,
                now: float) -> None:
        raise NotImplementedError

    def _complete(self, p: Packet) -> None:
        """End the open transaction if ``p`` answers it."""
        t = self._pending
        if t is None or p.object_id != t.packet.object_id:
            return
        if p.type == t.reply or p.type == PacketType.NACK:
            self._pending = None
            self._transaction_done(t.packet, p.type != PacketType.NACK)

    def _transaction_done(self, packet: Packet, ok: bool) -> None:
        """Hook: a transaction ended (``ok`` False: NACK or failure after the retries)."""

    # --- receiving --------------------------------------------------------------------------

    def _count_rx(self, p: Packet, now: float) -> None:
        self._now = now
        self._last_rx = now
        ptype = PacketType(p.type)
        setattr(self.stats, _RX[ptype], getattr(self.stats, _RX[ptype]) + 1)
        self.stats.rx_bytes += len(p.data) + _WIRE_OVERHEAD
        if p.timestamp is not None:
            self.stats.rx_timestamped += 1

    def _decode(self, p: Packet) -> tuple[ObjectDef | None, dict[str, Any] | None]:
        """The packet's object and values; counts unknown ids and wrong lengths."""
        obj = self.objects.by_id(p.object_id)
        if obj is None:
            self.stats.rx_unknown += 1
            return None, None
        if p.type in (PacketType.OBJ, PacketType.OBJ_ACK):
            if len(p.data) != obj.size:
                self.stats.rx_bad_length += 1
                return obj, None
            return obj, obj.unpack(p.data)
        return obj, None

    def _reply(self, ptype: PacketType, p: Packet) -> None:
        self._push_priority(Packet(ptype, p.object_id, p.instance_id))

    def _set_state(self, new: Status, now: float) -> None:
        if new == self.state:
            return
        self.stats.state_changes += 1
        if new == Status.CONNECTED:
            self.stats.connects += 1
            if self._handshake_started is not None:
                self.stats.handshake_ms = round((now - self._handshake_started) * 1000)
            self._handshake_started = None
        elif self.state == Status.CONNECTED:
            self.stats.disconnects += 1
            self._pending = None  # the link is gone: a late reply must not block the next one
            self._retry = []
        old = self.state
        self.state = new
        self._state_changed(now)
        if self.on_state is not None:
            self.on_state(old, new)

    def _state_changed(self, now: float) -> None:
        """Hook: ``self.state`` changed."""

    def _stats_values(self, status: Status) -> dict[str, Any]:
        """Flight/GCSTelemetryStats values: the counters only while connected, zeros otherwise
        (as 16.09's ``updateTelemetryStats`` and the GCS's monitor do)."""
        if self.state != Status.CONNECTED:
            return {"Status": int(status)}
        st = self.stats
        return {"TxBytes": st.tx_bytes & 0xFFFFFFFF, "RxBytes": st.rx_bytes & 0xFFFFFFFF,
                "TxFailures": st.failures & 0xFFFFFFFF, "TxRetries": st.retries & 0xFFFFFFFF,
                "RxFailures": (st.rx_unknown + st.rx_bad_length) & 0xFFFFFFFF,
                "Status": int(status)}


class FlightSession(_Session):
    """The gateway as the flight controller for one connected GCS.

    Serves the objects in ``store`` (and their metaobjects), FlightTelemetryStats,
    GCSTelemetryStats' metaobject and FirmwareIAPObj (``board_type`` when the store's BoardType
    is 0 or absent).  Anything else requested is NACKed.
    """

    def __init__(self, objects: ObjectSet, store: ObjectStore, *,
                 board_type: int = DEFAULT_BOARD_TYPE) -> None:
        super().__init__(objects)
        if not 0 < board_type <= 0xFF:
            raise ValueError(f"board_type must be 1..255, not {board_type}")
        self.store = store
        self.board_type = board_type
        self.gcs_status = Status.DISCONNECTED
        self._flight_stats = objects.by_name(FLIGHT_STATS)
        self._gcs_stats = objects.by_name(GCS_STATS)
        self._next_stats: float | None = None
        self._next_send: dict[str, float] = {}
        self._last_stats_time: float | None = None
        self._last_tx_bytes = 0
        self._last_rx_bytes = 0
        self._rates = (0.0, 0.0)

    # --- what we serve ----------------------------------------------------------------------

    def _serves(self, name: str) -> bool:
        return name in self.store or name in (FLIGHT_STATS, FIRMWARE)

    def _values(self, obj: ObjectDef) -> dict[str, Any] | None:
        if isinstance(obj, MetaDef):
            parent = obj.parent
            if self._serves(parent.name) or parent.name == GCS_STATS:
                return obj.defaults()
            return None
        if obj.name == FLIGHT_STATS:
            values = self._stats_values(self.state)
            if self.state == Status.CONNECTED:
                values["TxDataRate"], values["RxDataRate"] = self._rates
            return values
        stored = self.store.get(obj.name)
        if obj.name == FIRMWARE:
            stored = stored or {}
            if not stored.get("BoardType"):
                stored["BoardType"] = self.board_type
        return stored

    def _object_packet(self, obj: ObjectDef, ptype: PacketType = PacketType.OBJ,
                       instance_id: int = 0) -> Packet | None:
        values = self._values(obj)
        if values is None:
            return None
        try:
            data = obj.pack(values)
        except ValueError:
            return None
        return Packet(ptype, obj.id, instance_id, data)

    # --- input ------------------------------------------------------------------------------

    def _handle(self, packet: Packet, obj: ObjectDef | None, values: dict[str, Any] | None,
                now: float) -> None:
        """One packet from the GCS (not an ACK/NACK: :meth:`_Session.receive` did those)."""
        ptype = packet.type
        if ptype == PacketType.OBJ_REQ:
            reply = None
            if obj is not None and packet.instance_id in (0, ALL_INSTANCES):
                reply = self._object_packet(obj)
            if reply is None:
                self._reply(PacketType.NACK, packet)
            else:
                self._push_priority(reply)
            return
        if ptype == PacketType.OBJ_ACK:
            if values is None:
                self._reply(PacketType.NACK, packet)
                return
            self._reply(PacketType.ACK, packet)
        if obj is None or values is None:
            return
        self._complete(packet)
        if obj.name == GCS_STATS:
            status = values["Status"]
            self.gcs_status = Status(status) if status in Status._value2member_map_ else \
                Status.DISCONNECTED
            self._handshake(now)
        elif obj.name in self.store and not isinstance(obj, MetaDef):
            self.store.set(obj.name, values)  # the GCS wrote it, as the firmware unpacks

    def _handshake(self, now: float) -> None:
        gcs = self.gcs_status
        if self.state == Status.DISCONNECTED:
            if gcs == Status.HANDSHAKE_REQ:
                self._handshake_started = now
                self._set_state(Status.HANDSHAKE_ACK, now)
        elif self.state == Status.HANDSHAKE_ACK:
            if gcs == Status.CONNECTED:
                self._set_state(Status.CONNECTED, now)
            elif gcs == Status.DISCONNECTED:
                self._set_state(Status.DISCONNECTED, now)
        elif self.state == Status.CONNECTED and gcs != Status.CONNECTED:
            self._set_state(Status.DISCONNECTED, now)

    def _state_changed(self, now: float) -> None:
        self._send_stats(now)
        if self.state == Status.CONNECTED:
            self._next_send = {}
            for obj in self._periodic():
                self._next_send[obj.name] = now + obj.telemetry.flight.period_ms / 1000
        else:
            self._next_send = {}
            self._regular.clear()

    def _send_stats(self, now: float) -> None:
        if self._last_stats_time is not None and now > self._last_stats_time:
            dt = now - self._last_stats_time
            self._rates = ((self.stats.tx_bytes - self._last_tx_bytes) / dt,
                           (self.stats.rx_bytes - self._last_rx_bytes) / dt)
        self._last_stats_time = now
        self._last_tx_bytes, self._last_rx_bytes = self.stats.tx_bytes, self.stats.rx_bytes
        p = self._object_packet(self._flight_stats)
        assert p is not None
        self._push_priority(p)
        self._next_stats = now + STATS_PERIOD

    def _periodic(self) -> Iterable[ObjectDef]:
        for name in self.store.names():
            if name in self.objects and name != FLIGHT_STATS:
                obj = self.objects.by_name(name)
                spec = obj.telemetry.flight
                if spec.update_mode == UpdateMode.PERIODIC and spec.period_ms > 0:
                    yield obj

    def _send_update(self, obj: ObjectDef) -> None:
        ptype = PacketType.OBJ_ACK if obj.telemetry.flight.acked else PacketType.OBJ
        p = self._object_packet(obj, ptype)
        if p is not None:
            self._push_regular(p)

    def tick(self, now: float) -> None:
        """Timeouts, retries, the 8 s silence check, periodic updates and the 5 s stats."""
        self._now = now
        self._check_transaction(now)
        if self.state == Status.CONNECTED and (
                self._last_rx is None or now - self._last_rx >= CONNECTION_TIMEOUT):
            self.gcs_status = Status.DISCONNECTED
            self._set_state(Status.DISCONNECTED, now)
        if self._next_stats is None or now >= self._next_stats:
            self._send_stats(now)
        if self.state != Status.CONNECTED:
            return
        for obj in self._periodic():
            period = obj.telemetry.flight.period_ms / 1000
            due = self._next_send.get(obj.name)
            if due is None:
                self._next_send[obj.name] = now + period
            elif now >= due:
                self._send_update(obj)
                # next period from the schedule, never a burst to catch up
                self._next_send[obj.name] = max(due + period, now)

    def updated(self, name: str, now: float) -> None:
        """``name`` changed in the store: an on-change (or throttled) object is sent now."""
        self._now = now
        if self.state != Status.CONNECTED or name not in self.objects:
            return
        obj = self.objects.by_name(name)
        if obj.telemetry.flight.update_mode in (UpdateMode.ONCHANGE, UpdateMode.THROTTLED):
            self._send_update(obj)


class GcsSession(_Session):
    """The gateway as the ground station against one flight controller.

    ``on_object(name, values)`` is called for every object received (metaobjects as
    ``<name>Meta``); ``values`` holds the latest of each.
    """

    def __init__(self, objects: ObjectSet, *,
                 on_object: Callable[[str, dict[str, Any]], None] | None = None,
                 walk: Iterable[str] = DEFAULT_WALK) -> None:
        super().__init__(objects)
        self.on_object = on_object
        self.flight_status = Status.DISCONNECTED
        self.values: dict[str, dict[str, Any]] = {}
        self._walk_names = tuple(n for n in walk if n in objects)
        self._walk: deque[str] = deque()
        self._walk_current: str | None = None
        self.walk_done = False
        self.walk_nacked: list[str] = []
        self._gcs_stats = objects.by_name(GCS_STATS)
        self._next_stats: float | None = None

    def _send_stats(self, now: float, period: float) -> None:
        data = self._gcs_stats.pack(self._stats_values(self.state))
        self._push_priority(Packet(PacketType.OBJ, self._gcs_stats.id, 0, data))
        self._next_stats = now + period

    def tick(self, now: float) -> None:
        """Timeouts, retries, the 8 s silence check and the stats/handshake sends."""
        self._now = now
        self._check_transaction(now)
        if self.state == Status.CONNECTED and (
                self._last_rx is None or now - self._last_rx >= CONNECTION_TIMEOUT):
            self._set_state(Status.DISCONNECTED, now)
        if self.state == Status.DISCONNECTED:
            self._handshake_started = now
            self._set_state(Status.HANDSHAKE_REQ, now)
        elif self._next_stats is None or now >= self._next_stats:
            period = GCS_STATS_PERIOD if self.state == Status.CONNECTED else HANDSHAKE_PERIOD
            self._send_stats(now, period)

    def _state_changed(self, now: float) -> None:
        if self.state == Status.CONNECTED:
            self._send_stats(now, GCS_STATS_PERIOD)
            self._walk = deque(self._walk_names)
            self.walk_done = False
            self.walk_nacked = []
            self._walk_next()
        elif self.state == Status.HANDSHAKE_REQ:
            self._send_stats(now, HANDSHAKE_PERIOD)
        else:
            self._walk.clear()
            self._walk_current = None
            self._regular.clear()

    def _walk_next(self) -> None:
        if not self._walk:
            self._walk_current = None
            self.walk_done = True
            return
        name = self._walk.popleft()
        self._walk_current = name
        self._push_regular(Packet(PacketType.OBJ_REQ, self.objects.by_name(name).id))

    def _transaction_done(self, packet: Packet, ok: bool) -> None:
        obj = self.objects.by_id(packet.object_id)
        if packet.type == PacketType.OBJ_REQ and obj is not None \
                and obj.name == self._walk_current:
            if not ok:
                self.walk_nacked.append(obj.name)
            self._walk_next()

    def _handle(self, packet: Packet, obj: ObjectDef | None, values: dict[str, Any] | None,
                now: float) -> None:
        """One packet from the flight controller (not an ACK/NACK)."""
        ptype = packet.type
        if ptype == PacketType.OBJ_REQ:
            if obj is not None and obj.name == GCS_STATS:
                data = obj.pack(self._stats_values(self.state))
                self._push_priority(Packet(PacketType.OBJ, obj.id, 0, data))
            else:
                self._reply(PacketType.NACK, packet)
            return
        if ptype == PacketType.OBJ_ACK:
            self._reply(PacketType.NACK if values is None else PacketType.ACK, packet)
        if obj is None or values is None:
            return
        self.values[obj.name] = values
        if obj.name == FLIGHT_STATS:
            status = values["Status"]
            self.flight_status = Status(status) if status in Status._value2member_map_ else \
                Status.DISCONNECTED
            if self.state == Status.HANDSHAKE_REQ and self.flight_status == Status.HANDSHAKE_ACK:
                self._set_state(Status.CONNECTED, now)
            elif self.state == Status.CONNECTED and self.flight_status == Status.DISCONNECTED:
                self._set_state(Status.DISCONNECTED, now)
        self._complete(packet)
        if self.on_object is not None:
            self.on_object(obj.name, values)
