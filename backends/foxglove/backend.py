"""Foxglove live backend: serves the flight on the Foxglove WebSocket protocol
(``foxglove.websocket.v1``) with ``foxglove-sdk``'s own server, so the Foxglove app (or any
client of that protocol) plots it live.

Channels (one :class:`foxglove.Context` per backend: two gateways in one process share
nothing):

``/aurora/state``     JSON: state name and number, armed, sm_type, flight time
``/aurora/altitude``  JSON: altitude, vertical velocity, accelerations (plottable)
``/aurora/attitude``  ``foxglove.FrameTransform`` (protobuf): parent ``world``, child
                      ``rocket``, rotation from roll/pitch/yaw (Z-Y-X), z = altitude
``/aurora/position``  ``foxglove.LocationFix`` (protobuf), when a Position arrives
``/aurora/link``      JSON: LinkStats fields (``null`` = not reported)
``/aurora/status``    JSON: STATUS flags byte and the named health booleans

The dispatcher hands each message over to the backend's :class:`~gateway.io.ioloop.IoLoop`
(:class:`~gateway.handover.Handover`: bounded by ``queue_depth``, full: ``QUEUE_FULL``,
counted); there the message's own handler encodes it and logs it to its channels, and the
SDK's own threads serve the clients.  The log time is the wall-clock time the backend handled
the update (its hand-over adds well under a millisecond to its arrival; the flight computer's
clock counts from its boot: it is in the messages as ``timestamp_ms``).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, ClassVar

import foxglove
import orjson
from foxglove.channels import FrameTransformChannel, LocationFixChannel
from foxglove.messages import FrameTransform, LocationFix, Quaternion, Timestamp, Vector3
from foxglove.websocket import ServerListener

from backends.foxglove.options import FoxgloveOptions
from gateway.attitude import quaternion_xyzw
from gateway.backend import Backend, BackendError, Routes
from gateway.handover import Handover
from gateway.io.ioloop import IoLoop, Timer
from gateway.model import LinkStats, Position, SmUpdate, Status

log = logging.getLogger(__name__)

TOPIC_STATE = "/aurora/state"
TOPIC_ALTITUDE = "/aurora/altitude"
TOPIC_ATTITUDE = "/aurora/attitude"
TOPIC_POSITION = "/aurora/position"
TOPIC_LINK = "/aurora/link"
TOPIC_STATUS = "/aurora/status"
TOPIC_BACKENDS = "/aurora/backends"
#: Seconds between two logs of the gateway's counters on ``/aurora/backends``.
COUNTERS_INTERVAL_S = 1.0
CLOSE_TIMEOUT_S = 0.5

#: Frames of the attitude transform (the 3D panel's display frame is ``world``).
PARENT_FRAME = "world"
CHILD_FRAME = "rocket"


def _object(title: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": props}


_NUM = {"type": "number"}
_OPT_NUM = {"type": ["number", "null"]}
_OPT_INT = {"type": ["integer", "null"]}

#: The JSON channels' schemas (JSON Schema; the title is the schema name clients see).
JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    TOPIC_STATE: _object("aurora.State", {
        "timestamp_ms": {"type": "integer", "description": "flight computer time since boot"},
        "state": {"type": "integer"}, "state_name": {"type": "string"},
        "armed": {"type": "boolean"}, "sm_type": {"type": "integer"}}),
    TOPIC_ALTITUDE: _object("aurora.Altitude", {
        "timestamp_ms": {"type": "integer"}, "altitude_m": _NUM, "velocity_mps": _NUM,
        "acceleration_mps2": _NUM, "accel_vert_mps2": _NUM}),
    TOPIC_LINK: _object("aurora.LinkStats", {
        "rssi_dbm": _OPT_NUM, "link_quality_pct": _OPT_INT, "snr_db": _OPT_NUM,
        "tx_power_mw": _OPT_INT, "downlink_rssi_dbm": _OPT_NUM,
        "downlink_link_quality_pct": _OPT_INT, "downlink_snr_db": _OPT_NUM,
        "rf_mode": _OPT_INT, "antenna": _OPT_INT, "origin": {"type": "string"}}),
    TOPIC_STATUS: _object("aurora.Status", {
        "timestamp_ms": {"type": "integer"}, "state": {"type": "integer"},
        "state_name": {"type": "string"}, "sm_type": {"type": "integer"},
        "flags": {"type": "integer"}, "armed": {"type": "boolean"},
        "imu_ok": {"type": "boolean"}, "baro_ok": {"type": "boolean"},
        "calibrated": {"type": "boolean"}, "log_ready": {"type": "boolean"}}),
    TOPIC_BACKENDS: _object("aurora.GatewayCounters", {
        "backends": {"type": "object", "description": "each backend's stats(): sent, "
                     "dropped, errors, link, its own counters"},
        "sources": {"type": "object", "description": "each source's stats()"}}),
}


def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, float, float,
                                                                         float]:
    """(x, y, z, w) of the rotation yaw about Z, then pitch about Y, then roll about X
    (aerospace Z-Y-X order: body → world): FrameTransform's order."""
    return quaternion_xyzw(roll, pitch, yaw)


def _stamp(log_time_ns: int) -> Timestamp:
    return Timestamp(log_time_ns // 1_000_000_000, log_time_ns % 1_000_000_000)


class _Listener(ServerListener):
    """Counts the clients' subscriptions (the SDK calls it from its own threads)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._subs: dict[int, set[int]] = {}

    def on_subscribe(self, client: Any, channel: Any) -> None:
        with self._cond:
            self._subs.setdefault(client.id, set()).add(channel.id)
            self._cond.notify_all()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        with self._cond:
            chans = self._subs.get(client.id)
            if chans is not None:
                chans.discard(channel.id)
                if not chans:
                    del self._subs[client.id]
            self._cond.notify_all()

    def clients(self) -> int:
        """Clients subscribed to at least one channel."""
        with self._cond:
            return len(self._subs)

    def subscriptions(self) -> int:
        with self._cond:
            return sum(len(c) for c in self._subs.values())

    def wait(self, count: int, timeout: float) -> bool:
        """Wait until there are exactly ``count`` subscriptions; False on timeout."""
        with self._cond:
            return self._cond.wait_for(
                lambda: sum(len(c) for c in self._subs.values()) == count, timeout)


class FoxgloveBackend(Backend):
    """Serves the rocket's channels to Foxglove (see the module docstring)."""

    NAME = "foxglove"
    OPTIONS = FoxgloveOptions
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None  # it listens on a port: opt in

    def __init__(self, options: FoxgloveOptions | None = None, name: str | None = None) -> None:
        super().__init__(name)
        options = options or FoxgloveOptions()
        self.host = options.host
        self.port = options.port
        self.backlog = options.backlog
        self.handover = Handover(self.name, options.queue_depth)
        self._loop: IoLoop | None = None
        self._counters: Timer | None = None
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._listener = _Listener()
        self.sent = 0
        self.errors = 0

    # --- life cycle -------------------------------------------------------------------------

    def init(self) -> None:
        self._context = foxglove.Context()
        ctx = self._context
        for topic, schema in JSON_SCHEMAS.items():
            self._channels[topic] = foxglove.Channel(
                topic, message_encoding="json", context=ctx,
                schema=foxglove.Schema(name=schema["title"], encoding="jsonschema",
                                       data=orjson.dumps(schema)))
        self._channels[TOPIC_ATTITUDE] = FrameTransformChannel(TOPIC_ATTITUDE, context=ctx)
        self._channels[TOPIC_POSITION] = LocationFixChannel(TOPIC_POSITION, context=ctx)
        try:
            self._server = foxglove.start_server(
                name=f"aurora-gateway {self.name}", host=self.host, port=self.port,
                context=ctx, server_listener=self._listener,
                message_backlog_size=self.backlog)
        except Exception as exc:
            self._close_channels()
            raise BackendError(f"{self.name}: cannot serve on {self.host}:{self.port}: "
                               f"{exc}") from exc
        self.port = self._server.port  # the one bound, when 0 asked for any
        self._loop = loop = IoLoop(self.name)
        loop.start()
        self._counters = loop.call_every(COUNTERS_INTERVAL_S, self._log_counters,
                                         first=COUNTERS_INTERVAL_S)
        self.handover.open(loop)
        log.info("%s: Foxglove WebSocket server on ws://%s:%d", self.name, self.host,
                 self.port)

    def close(self) -> None:
        """Log what is queued (within 0.5 s), then stop the server; safe twice."""
        self.handover.close(CLOSE_TIMEOUT_S)
        if self._counters is not None:
            self._counters.cancel()
            self._counters = None
        loop, self._loop = self._loop, None
        if loop is not None and loop.stop(CLOSE_TIMEOUT_S):
            loop.close()
        if self._server is not None:
            server, self._server = self._server, None
            server.stop()
        self._close_channels()

    def _close_channels(self) -> None:
        for ch in self._channels.values():
            ch.close()
        self._channels.clear()
        self._context = None

    # --- the handlers (on the backend's loop, handed over by the dispatcher) -------------------

    def routes(self) -> Routes:
        return (Routes(handover=self.handover).on(SmUpdate, self.send_sm_update)
                .on(Status, self.send_status).on(Position, self.send_position)
                .on(LinkStats, self.send_link_stats))

    def send_sm_update(self, msg: SmUpdate) -> None:
        log_time = time.time_ns()
        self._json(TOPIC_STATE, {"timestamp_ms": msg.timestamp_ms, "state": msg.state,
                                 "state_name": msg.state_name, "armed": msg.armed,
                                 "sm_type": msg.sm_type}, log_time)
        self._json(TOPIC_ALTITUDE, {"timestamp_ms": msg.timestamp_ms,
                                    "altitude_m": msg.altitude_m,
                                    "velocity_mps": msg.velocity_mps,
                                    "acceleration_mps2": msg.acceleration_mps2,
                                    "accel_vert_mps2": msg.accel_vert_mps2}, log_time)
        x, y, z, w = quaternion_from_euler(msg.roll_rad, msg.pitch_rad, msg.yaw_rad)
        self._channels[TOPIC_ATTITUDE].log(FrameTransform(
            timestamp=_stamp(log_time), parent_frame_id=PARENT_FRAME,
            child_frame_id=CHILD_FRAME, translation=Vector3(x=0.0, y=0.0, z=msg.altitude_m),
            rotation=Quaternion(x=x, y=y, z=z, w=w)), log_time=log_time)
        self.sent += 3

    def send_status(self, msg: Status) -> None:
        self._json(TOPIC_STATUS, {"timestamp_ms": msg.timestamp_ms, "state": msg.state,
                                  "state_name": msg.state_name, "sm_type": msg.sm_type,
                                  "flags": msg.flags, **msg.health()}, time.time_ns())
        self.sent += 1

    def send_position(self, msg: Position) -> None:
        log_time = time.time_ns()
        alt = msg.alt_amsl_m if msg.alt_amsl_m is not None else 0.0
        self._channels[TOPIC_POSITION].log(LocationFix(
            timestamp=_stamp(log_time), frame_id=CHILD_FRAME, latitude=msg.lat_deg,
            longitude=msg.lon_deg, altitude=alt), log_time=log_time)
        self.sent += 1

    def send_link_stats(self, msg: LinkStats) -> None:
        self._json(TOPIC_LINK, {**msg.fields(), "origin": msg.origin}, time.time_ns())
        self.sent += 1

    def _log_counters(self) -> None:
        """The gateway's backends' and sources' counters on ``/aurora/backends``."""
        counters = self.context.services.get("gateway.stats")
        if counters is None:
            return
        try:
            data = orjson.dumps(counters(), default=str, option=orjson.OPT_NON_STR_KEYS)
            self._channels[TOPIC_BACKENDS].log(data, log_time=time.time_ns())
            self.sent += 1
        except Exception:
            self.errors += 1
            log.exception("%s: cannot log the gateway's counters", self.name)

    def _json(self, topic: str, data: dict[str, Any], log_time: int) -> None:
        self._channels[topic].log(orjson.dumps(data), log_time=log_time)

    def wait_idle(self, timeout: float) -> bool:
        """Wait until every update handed over so far is logged (for tools and benchmarks)."""
        return self.handover.barrier(timeout)

    def wait_subscriptions(self, count: int, timeout: float) -> bool:
        """Wait until clients hold exactly ``count`` channel subscriptions in all; False on
        timeout (tools and tests: data logged before a client subscribes is not sent to it)."""
        return self._listener.wait(count, timeout)

    # --- counters -----------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        h = self.handover
        return {"sent": self.sent, "dropped": h.dropped,
                "errors": self.errors + h.handler_errors, "link": int(self._server is not None),
                "clients": self._listener.clients(), **h.stats(), "port": self.port}
