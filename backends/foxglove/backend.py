"""Foxglove live backend: serves the flight on the Foxglove WebSocket protocol with
``foxglove-sdk``'s own server, so the Foxglove app, Lichtblick (or any client of that
protocol) plots it live.  Clients of both generations connect: the public port is a
:class:`~backends.foxglove.relay.ProtocolRelay` in front of the SDK's server (which listens on
a loopback port of its own), renaming ``foxglove.websocket.v1`` to the SDK's
``foxglove.sdk.v1`` in the handshake, holding clients to the listener limits and logging them
once per burst; the SDK's own per-client lines are kept out (:mod:`backends.foxglove.sdklog`).

Channels, per vehicle (``<vehicle>``: the vehicle's name, e.g. ``sim`` or ``alpha``; one
:class:`foxglove.Context` per backend: two gateways in one process share nothing):

``/aurora/<vehicle>/state``     JSON: state name and number, armed, sm_type, flight time
``/aurora/<vehicle>/altitude``  JSON: altitude, vertical velocity, accelerations (plottable)
``/aurora/<vehicle>/attitude``  ``foxglove.FrameTransform`` (protobuf): parent ``world``,
                                child ``<vehicle>``, rotation from roll/pitch/yaw (Z-Y-X),
                                z = altitude
``/aurora/<vehicle>/position``  ``foxglove.LocationFix`` (protobuf, frame ``<vehicle>``),
                                when a Position arrives
``/aurora/<vehicle>/link``      JSON: LinkStats fields (``null`` = not reported)
``/aurora/<vehicle>/status``    JSON: STATUS flags byte and the named health booleans

and, for the whole gateway, ``/aurora/backends`` (JSON: every backend's and source's
counters, once a second).  A vehicle's channels are created when its first message is
handled (a message without a vehicle is the first configured source's); at most
:data:`MAX_VEHICLES` vehicles get channels, the messages of any further one are counted
(``vehicles_refused``) and dropped: a peer cannot grow the server by inventing names.

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
from foxglove.channels import FrameTransformChannel, LocationFixChannel
from foxglove.messages import FrameTransform, LocationFix, Quaternion, Timestamp, Vector3
from foxglove.websocket import ServerListener

from backends.foxglove import handshake, sdklog
from backends.foxglove.options import FoxgloveOptions
from backends.foxglove.relay import ProtocolRelay
from gateway.attitude import quaternion_xyzw
from gateway.backend import Backend, BackendError, Routes
from gateway.handover import Handover
from gateway.io.burstlog import BURST_LOG_S
from gateway.io.ioloop import IoLoop, Timer
from gateway.io.server import ClientLimits, server_stats
from gateway.io.transport import TransportError, open_tcp_listener
from gateway.model import LinkStats, Position, SmUpdate, Status
from gateway.signals import held
from gateway.vehicles import SERVICE as VEHICLES_SERVICE

with held():  # a Ctrl-C inside orjson's module init crashes it (gateway/signals.py)
    import orjson

log = logging.getLogger(__name__)

#: The last level of a vehicle's topics (``/aurora/<vehicle>/<leaf>``, see :func:`topic`).
TOPIC_STATE = "state"
TOPIC_ALTITUDE = "altitude"
TOPIC_ATTITUDE = "attitude"
TOPIC_POSITION = "position"
TOPIC_LINK = "link"
TOPIC_STATUS = "status"
#: The gateway's counters (one topic for the whole gateway).
TOPIC_BACKENDS = "/aurora/backends"
#: Vehicles given channels at most; the messages of any further vehicle are counted, dropped.
MAX_VEHICLES = 256
#: The vehicle of a message without one when no source is configured (tests, tools).
UNNAMED = "vehicle"
#: Seconds between two logs of the gateway's counters on ``/aurora/backends``.
COUNTERS_INTERVAL_S = 1.0
CLOSE_TIMEOUT_S = 0.5
#: Where foxglove-sdk's own server listens (any free port): only the relay connects to it.
SDK_HOST = "127.0.0.1"

#: The parent frame of every vehicle's attitude transform (its child: the vehicle's name).
PARENT_FRAME = "world"


def topic(vehicle: str, leaf: str) -> str:
    """A vehicle's topic: ``/aurora/<vehicle>/<leaf>``."""
    return f"/aurora/{vehicle}/{leaf}"


def _object(title: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": props}


_NUM = {"type": "number"}
_OPT_NUM = {"type": ["number", "null"]}
_OPT_INT = {"type": ["integer", "null"]}

#: The JSON channels' schemas (JSON Schema; the title is the schema name clients see), by
#: topic leaf (a vehicle's) or topic (the gateway's).
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
_SCHEMA_DATA = {key: orjson.dumps(schema) for key, schema in JSON_SCHEMAS.items()}


class VehicleChannels:
    """One vehicle's channels (created on the backend's loop when its first message comes)."""

    __slots__ = ("altitude", "attitude", "frame", "link", "name", "position", "state", "status")

    def __init__(self, name: str, context: Any) -> None:
        self.name = name
        self.frame = name  # the vehicle's frame: child of ``world`` in its transforms

        def json_channel(leaf: str) -> Any:
            return foxglove.Channel(
                topic(name, leaf), message_encoding="json", context=context,
                schema=foxglove.Schema(name=JSON_SCHEMAS[leaf]["title"], encoding="jsonschema",
                                       data=_SCHEMA_DATA[leaf]))

        self.state = json_channel(TOPIC_STATE)
        self.altitude = json_channel(TOPIC_ALTITUDE)
        self.link = json_channel(TOPIC_LINK)
        self.status = json_channel(TOPIC_STATUS)
        self.attitude = FrameTransformChannel(topic(name, TOPIC_ATTITUDE), context=context)
        self.position = LocationFixChannel(topic(name, TOPIC_POSITION), context=context)

    def close(self) -> None:
        for ch in (self.state, self.altitude, self.link, self.status, self.attitude,
                   self.position):
            ch.close()


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
    """Serves each vehicle's channels to Foxglove (see the module docstring)."""

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
        self._relay: ProtocolRelay | None = None
        self._sdk_lines: Timer | None = None
        self.limits = ClientLimits.of(options)
        self._context: Any = None
        self._counters_channel: Any = None
        #: name → its channels (written on the backend's loop only)
        self.vehicles: dict[str, VehicleChannels] = {}
        self.vehicles_refused = 0
        self._unnamed = UNNAMED
        self._listener = _Listener()
        self.sent = 0
        self.errors = 0

    # --- life cycle -------------------------------------------------------------------------

    def init(self) -> None:
        configured = self.context.services.get(VEHICLES_SERVICE) or ()
        if configured:
            self._unnamed = configured[0].vehicle or UNNAMED
        sdklog.install()
        try:
            listener = open_tcp_listener(self.host, self.port)
        except TransportError as exc:
            raise BackendError(f"{self.name}: {exc}") from None
        self._context = foxglove.Context()
        ctx = self._context
        self._counters_channel = foxglove.Channel(
            TOPIC_BACKENDS, message_encoding="json", context=ctx,
            schema=foxglove.Schema(name=JSON_SCHEMAS[TOPIC_BACKENDS]["title"],
                                   encoding="jsonschema", data=_SCHEMA_DATA[TOPIC_BACKENDS]))
        try:  # the SDK's server on a loopback port of its own, behind the relay
            self._server = foxglove.start_server(
                name=f"aurora-gateway {self.name}", host=SDK_HOST, port=0,
                context=ctx, server_listener=self._listener,
                message_backlog_size=self.backlog)
        except Exception as exc:
            listener.close()
            self._close_channels()
            raise BackendError(f"{self.name}: cannot start foxglove-sdk's server: "
                               f"{exc}") from exc
        self.port = listener.getsockname()[1]  # the one bound, when 0 asked for any
        self._loop = loop = IoLoop(self.name)
        self._relay = ProtocolRelay(listener, (SDK_HOST, self._server.port), loop=loop,
                                    name=self.name, limits=self.limits)
        loop.start()
        self._relay.start()
        self._counters = loop.call_every(COUNTERS_INTERVAL_S, self._log_counters,
                                         first=COUNTERS_INTERVAL_S)
        self._sdk_lines = loop.call_every(BURST_LOG_S, self._log_sdk_lines, first=BURST_LOG_S)
        self.handover.open(loop)
        host = f"[{self.host}]" if ":" in self.host else self.host
        log.info("%s: Foxglove WebSocket server on ws://%s:%d (clients offering %s)",
                 self.name, host, self.port, " or ".join(handshake.ACCEPTED))

    def close(self) -> None:
        """Log what is queued (within 0.5 s), then stop the server; safe twice."""
        self.handover.close(CLOSE_TIMEOUT_S)
        for timer in (self._counters, self._sdk_lines):
            if timer is not None:
                timer.cancel()
        self._counters = self._sdk_lines = None
        loop, self._loop = self._loop, None
        stopped = loop is not None and loop.stop(CLOSE_TIMEOUT_S)
        if self._relay is not None:  # (its loop has stopped: its sockets are ours to close)
            self._relay.close()
        if loop is not None and stopped:
            loop.close()
        if self._server is not None:
            server, self._server = self._server, None
            server.stop()
        self._close_channels()

    def _close_channels(self) -> None:
        for vehicle in self.vehicles.values():
            vehicle.close()
        self.vehicles.clear()
        if self._counters_channel is not None:
            self._counters_channel.close()
            self._counters_channel = None
        self._context = None

    def _vehicle(self, msg: Any) -> VehicleChannels | None:
        """The channels of ``msg``'s vehicle, created at its first message (None: past the
        cap, counted)."""
        name = msg.vehicle or self._unnamed
        channels = self.vehicles.get(name)
        if channels is None:
            if len(self.vehicles) >= MAX_VEHICLES or self._context is None:
                self.vehicles_refused += 1
                if self.vehicles_refused == 1:
                    log.warning("%s: more than %d vehicles: the messages of the others are "
                                "dropped (vehicles_refused)", self.name, MAX_VEHICLES)
                return None
            channels = self.vehicles[name] = VehicleChannels(name, self._context)
        return channels

    # --- the handlers (on the backend's loop, handed over by the dispatcher) -------------------

    def routes(self) -> Routes:
        return (Routes(handover=self.handover).on(SmUpdate, self.send_sm_update)
                .on(Status, self.send_status).on(Position, self.send_position)
                .on(LinkStats, self.send_link_stats))

    def send_sm_update(self, msg: SmUpdate) -> None:
        v = self._vehicle(msg)
        if v is None:
            return
        log_time = time.time_ns()
        _json(v.state, {"timestamp_ms": msg.timestamp_ms, "state": msg.state,
                        "state_name": msg.state_name, "armed": msg.armed,
                        "sm_type": msg.sm_type}, log_time)
        _json(v.altitude, {"timestamp_ms": msg.timestamp_ms, "altitude_m": msg.altitude_m,
                           "velocity_mps": msg.velocity_mps,
                           "acceleration_mps2": msg.acceleration_mps2,
                           "accel_vert_mps2": msg.accel_vert_mps2}, log_time)
        x, y, z, w = quaternion_from_euler(msg.roll_rad, msg.pitch_rad, msg.yaw_rad)
        v.attitude.log(FrameTransform(
            timestamp=_stamp(log_time), parent_frame_id=PARENT_FRAME,
            child_frame_id=v.frame, translation=Vector3(x=0.0, y=0.0, z=msg.altitude_m),
            rotation=Quaternion(x=x, y=y, z=z, w=w)), log_time=log_time)
        self.sent += 3

    def send_status(self, msg: Status) -> None:
        v = self._vehicle(msg)
        if v is None:
            return
        _json(v.status, {"timestamp_ms": msg.timestamp_ms, "state": msg.state,
                         "state_name": msg.state_name, "sm_type": msg.sm_type,
                         "flags": msg.flags, **msg.health()}, time.time_ns())
        self.sent += 1

    def send_position(self, msg: Position) -> None:
        v = self._vehicle(msg)
        if v is None:
            return
        log_time = time.time_ns()
        alt = msg.alt_amsl_m if msg.alt_amsl_m is not None else 0.0
        v.position.log(LocationFix(
            timestamp=_stamp(log_time), frame_id=v.frame, latitude=msg.lat_deg,
            longitude=msg.lon_deg, altitude=alt), log_time=log_time)
        self.sent += 1

    def send_link_stats(self, msg: LinkStats) -> None:
        v = self._vehicle(msg)
        if v is None:
            return
        _json(v.link, {**msg.fields(), "origin": msg.origin}, time.time_ns())
        self.sent += 1

    def _log_counters(self) -> None:
        """The gateway's backends' and sources' counters on ``/aurora/backends``."""
        counters = self.context.services.get("gateway.stats")
        if counters is None:
            return
        try:
            data = orjson.dumps(counters(), default=str, option=orjson.OPT_NON_STR_KEYS)
            self._counters_channel.log(data, log_time=time.time_ns())
            self.sent += 1
        except Exception:
            self.errors += 1
            log.exception("%s: cannot log the gateway's counters", self.name)

    def _log_sdk_lines(self) -> None:
        """What the SDK's per-client lines, kept out of the log, counted (one line per
        interval, when there were any it is the only one to see)."""
        said = sdklog.summary(sdklog.take_counts())
        if said:
            log.info("%s: in the last %.0f s: %s", self.name, BURST_LOG_S, said)

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
        relay = self._relay
        return {"sent": self.sent, "dropped": h.dropped,
                "errors": self.errors + h.handler_errors, "link": int(self._server is not None),
                "clients": self._listener.clients(), **h.stats(), "port": self.port,
                "vehicles": len(self.vehicles), "vehicles_refused": self.vehicles_refused,
                **(relay.stats() if relay is not None else {}),
                **server_stats((relay.server,) if relay is not None else ())}


def _json(channel: Any, data: dict[str, Any], log_time: int) -> None:
    channel.log(orjson.dumps(data), log_time=log_time)
