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

The dispatcher's thread only stamps the message with the wall clock and puts it in a bounded
queue (full: dropped, counted); the backend's worker thread encodes and logs it to the
channels, and the SDK's own threads serve the clients.  The log time is the wall-clock time
the update reached the gateway (the flight computer's clock counts from its boot: it is in the
messages as ``timestamp_ms``).
"""

from __future__ import annotations

import contextlib
import logging
import queue
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
from gateway.backend import Backend, BackendError, Outcome, Routes
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
_IDLE: tuple[int, Any] = (0, None)  # the worker woke for the counters, not for a message

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
        self._queue: queue.Queue[tuple[int, Any] | None] = queue.Queue(maxsize=options.queue_depth)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}
        self._listener = _Listener()
        self._running = False
        self.sent = 0
        self.errors = 0
        self.dropped_queue_full = 0
        self.dropped_not_ready = 0

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
        self._stop.clear()
        self._thread = threading.Thread(target=self._work, name=f"{self.name}-worker",
                                        daemon=True)
        self._running = True
        self._thread.start()
        log.info("%s: Foxglove WebSocket server on ws://%s:%d", self.name, self.host,
                 self.port)

    def close(self) -> None:
        self._running = False
        self._stop.set()
        with contextlib.suppress(queue.Full):  # wake the worker; if full, the event ends it
            self._queue.put_nowait(None)
        if self._thread is not None:
            self._thread.join(0.5)
            self._thread = None
        if self._server is not None:
            server, self._server = self._server, None
            server.stop()
        self._close_channels()

    def _close_channels(self) -> None:
        for ch in self._channels.values():
            ch.close()
        self._channels.clear()
        self._context = None

    # --- the dispatcher's side: never blocks --------------------------------------------------

    def routes(self) -> Routes:
        return (Routes().on(SmUpdate, self.send_sm_update).on(Status, self.send_status)
                .on(Position, self.send_position).on(LinkStats, self.send_link_stats))

    def _enqueue(self, msg: Any) -> Outcome:
        if not self._running:
            self.dropped_not_ready += 1
            return Outcome.NOT_READY
        try:
            self._queue.put_nowait((time.time_ns(), msg))
        except queue.Full:
            self.dropped_queue_full += 1
            return Outcome.QUEUE_FULL
        return Outcome.ACCEPTED

    def send_sm_update(self, msg: SmUpdate) -> Outcome:
        return self._enqueue(msg)

    def send_status(self, msg: Status) -> Outcome:
        return self._enqueue(msg)

    def send_position(self, msg: Position) -> Outcome:
        return self._enqueue(msg)

    def send_link_stats(self, msg: LinkStats) -> Outcome:
        return self._enqueue(msg)

    # --- the worker ---------------------------------------------------------------------------

    def _work(self) -> None:
        due = time.monotonic() + COUNTERS_INTERVAL_S
        while not self._stop.is_set():
            try:
                item = self._queue.get(timeout=max(0.0, due - time.monotonic()))
            except queue.Empty:
                item = _IDLE  # only the counters are due
            if time.monotonic() >= due:
                due = time.monotonic() + COUNTERS_INTERVAL_S
                self._log_counters()
            if item is None:
                return
            if item is _IDLE:
                continue
            log_time, msg = item
            try:
                self.sent += self._log(msg, log_time)
            except Exception:
                self.errors += 1
                log.exception("%s: cannot log %s", self.name, type(msg).__name__)

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

    def _log(self, msg: Any, log_time: int) -> int:
        """Log ``msg`` on its channels; returns how many channel messages it made."""
        if isinstance(msg, SmUpdate):
            self._json(TOPIC_STATE, {"timestamp_ms": msg.timestamp_ms, "state": msg.state,
                                     "state_name": msg.state_name, "armed": msg.armed,
                                     "sm_type": msg.sm_type}, log_time)
            self._json(TOPIC_ALTITUDE, {"timestamp_ms": msg.timestamp_ms,
                                        "altitude_m": msg.altitude_m,
                                        "velocity_mps": msg.velocity_mps,
                                        "acceleration_mps2": msg.acceleration_mps2,
                                        "accel_vert_mps2": msg.accel_vert_mps2}, log_time)
            x, y, z, w = quaternion_from_euler(msg.roll_rad, msg.pitch_rad, msg.yaw_rad)
            stamp = Timestamp(log_time // 1_000_000_000, log_time % 1_000_000_000)
            self._channels[TOPIC_ATTITUDE].log(FrameTransform(
                timestamp=stamp, parent_frame_id=PARENT_FRAME, child_frame_id=CHILD_FRAME,
                translation=Vector3(x=0.0, y=0.0, z=msg.altitude_m),
                rotation=Quaternion(x=x, y=y, z=z, w=w)), log_time=log_time)
            return 3
        if isinstance(msg, Status):
            self._json(TOPIC_STATUS, {"timestamp_ms": msg.timestamp_ms, "state": msg.state,
                                      "state_name": msg.state_name, "sm_type": msg.sm_type,
                                      "flags": msg.flags, **msg.health()}, log_time)
            return 1
        if isinstance(msg, Position):
            stamp = Timestamp(log_time // 1_000_000_000, log_time % 1_000_000_000)
            alt = msg.alt_amsl_m if msg.alt_amsl_m is not None else 0.0
            self._channels[TOPIC_POSITION].log(LocationFix(
                timestamp=stamp, frame_id=CHILD_FRAME, latitude=msg.lat_deg,
                longitude=msg.lon_deg, altitude=alt), log_time=log_time)
            return 1
        if isinstance(msg, LinkStats):
            self._json(TOPIC_LINK, {**msg.fields(), "origin": msg.origin}, log_time)
            return 1
        return 0

    def wait_subscriptions(self, count: int, timeout: float) -> bool:
        """Wait until clients hold exactly ``count`` channel subscriptions in all; False on
        timeout (tools and tests: data logged before a client subscribes is not sent to it)."""
        return self._listener.wait(count, timeout)

    # --- counters -----------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        return {"sent": self.sent, "dropped": self.dropped_queue_full + self.dropped_not_ready,
                "errors": self.errors, "link": int(self._server is not None),
                "clients": self._listener.clients(),
                "dropped_queue_full": self.dropped_queue_full,
                "dropped_not_ready": self.dropped_not_ready,
                "port": self.port}
