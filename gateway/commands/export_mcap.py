"""A recording's messages as an MCAP file (``aurora-gateway export RECORDING -f mcap -o F``).

MCAP (https://mcap.dev) is the log container Foxglove and most robotics tools open: this
writes the flight on the same channels, with the same schema names and field names, as the
live Foxglove backend (``backends/foxglove``) publishes, so a recorded flight opens with the
same layout (``docs/foxglove-layout.json``) as a live one.  The native recording
(:mod:`gateway.recording`) stays the lossless format: it keeps every frame exactly as
received; the MCAP is a decoded view of it and cannot be replayed.

Every message is JSON (message encoding ``json``) with a JSON Schema (schema encoding
``jsonschema``); the attitude and the position use Foxglove's own schema names
(``foxglove.FrameTransform``, ``foxglove.LocationFix``) in their JSON form, which the 3D and
Map panels recognise (the live backend sends the same messages as protobuf).  Non-finite
floats are written as ``null`` (JSON has no NaN).

Each vehicle's messages are on its own channels, ``/aurora/<vehicle>/state`` and so on (as the
live backend names them); a message that names no vehicle goes on ``/aurora/state`` …; the
link events, a source's, are on ``/aurora/link_events`` for every vehicle.  In the table,
``/aurora/…/state`` stands for ``/aurora/<vehicle>/state``.

======================  ================  ==============================================
channel                 from              fields
======================  ================  ==============================================
``/aurora/…/state``     each SM_UPDATE    timestamp_ms, state, state_name, armed, sm_type
``/aurora/…/altitude``  each SM_UPDATE    timestamp_ms, altitude_m, velocity_mps,
                                          acceleration_mps2, accel_vert_mps2
``/aurora/…/attitude``  each SM_UPDATE    foxglove.FrameTransform: ``world`` → the vehicle,
                                          rotation = roll/pitch/yaw as a quaternion
                                          (Z-Y-X), translation z = altitude_m
``/aurora/…/status``    each STATUS       timestamp_ms, state, state_name, sm_type, flags,
                                          armed, imu_ok, baro_ok, calibrated, log_ready
``/aurora/link_events`` link up/down      source, up, silence_s
``/aurora/…/link``      each LinkStats    only when present: its fields and origin
``/aurora/…/position``  each Position     only when present: foxglove.LocationFix
``/aurora/…/battery``   each Battery      only when present: a battery's fields
``/aurora/…/vehicle``   each VehicleState only when present: armed, mode, custom_mode,
                                          roll/pitch/yaw_rad, altitude_m, climb_mps; and
                                          ``…/attitude`` too when it has an attitude
``/aurora/…/rc``        each RcChannels   only when present: channels_us, seq
======================  ================  ==============================================

Every channel's messages come from the recording's records: the first five channels (the
first four per vehicle) are in every export; the others when the recording holds such
messages (a MAVLink vehicle's positions, batteries and states, :mod:`gateway.recording`).
A recorded frame of no known type (a RawFrame) has no channel: it is skipped, counted in
``skipped`` (the command prints the count).  A recorded link event is written on
``/aurora/link_events`` as it was.  ``/aurora/link_events`` also replays the gateway's link rule
(:class:`gateway.link_monitor.LinkMonitor`) per recorded source on the receive times: up at
the first valid frame, down ``timeout_s`` after the last one when the next comes later than
that (``silence_s`` = the timeout), up again at the next frame.  Each message's log time and
publish time are its receive time in ns since the Unix epoch.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Iterable
from typing import IO, Any

from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import Writer

from gateway import __version__
from gateway.attitude import quaternion_xyzw
from gateway.link_monitor import DEFAULT_LINK_TIMEOUT_S, LinkMonitor
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    RcChannels,
    SmUpdate,
    Status,
    VehicleState,
)
from gateway.signals import held

with held():  # a Ctrl-C inside orjson's module init crashes it (gateway/signals.py)
    import orjson

STATE = "/aurora/state"
ALTITUDE = "/aurora/altitude"
ATTITUDE = "/aurora/attitude"
STATUS = "/aurora/status"
LINK = "/aurora/link"
LINK_EVENTS = "/aurora/link_events"
POSITION = "/aurora/position"
BATTERY = "/aurora/battery"
VEHICLE = "/aurora/vehicle"
RC = "/aurora/rc"

_NUM = {"type": "number"}
_NUM_OR_NULL = {"type": ["number", "null"]}
_INT = {"type": "integer"}
_INT_OR_NULL = {"type": ["integer", "null"]}
_BOOL = {"type": "boolean"}
_STR = {"type": "string"}
#: The frames of the attitude transform (as the live backend names them).
PARENT_FRAME = "world"
CHILD_FRAME = "rocket"


def child_frame(vehicle: str) -> str:
    """The frame of a vehicle's attitude and position: the vehicle's name (a frame per
    vehicle, so several rockets in one 3D panel do not share one), ``rocket`` when the
    message names none."""
    return vehicle or CHILD_FRAME
_TIME = {"type": "object", "properties": {"sec": _INT, "nsec": _INT},
         "required": ["sec", "nsec"]}


def _xyz(*axes: str) -> dict[str, Any]:
    return {"type": "object", "properties": dict.fromkeys(axes, _NUM_OR_NULL),
            "required": list(axes)}


def _object(title: str, description: str, properties: dict[str, dict[str, Any]],
            optional: tuple[str, ...] = ()) -> dict[str, Any]:
    return {"title": title, "description": description, "type": "object",
            "properties": properties,
            "required": [k for k in properties if k not in optional]}


#: topic -> (schema name, JSON schema); the channels in the order they are registered.
SCHEMAS: dict[str, tuple[str, dict[str, Any]]] = {
    STATE: ("aurora.State", _object(
        "aurora.State", "The flight computer's state machine (SM_UPDATE)",
        {"timestamp_ms": _INT, "state": _INT, "state_name": _STR, "armed": _BOOL,
         "sm_type": _INT})),
    ALTITUDE: ("aurora.Altitude", _object(
        "aurora.Altitude", "Altitude above the pad and vertical motion (SM_UPDATE)",
        {"timestamp_ms": _INT, "altitude_m": _NUM_OR_NULL, "velocity_mps": _NUM_OR_NULL,
         "acceleration_mps2": _NUM_OR_NULL, "accel_vert_mps2": _NUM_OR_NULL})),
    ATTITUDE: ("foxglove.FrameTransform", _object(
        "foxglove.FrameTransform", "The rocket's attitude (and altitude) as a transform",
        {"timestamp": _TIME, "parent_frame_id": _STR, "child_frame_id": _STR,
         "translation": _xyz("x", "y", "z"), "rotation": _xyz("x", "y", "z", "w")})),
    STATUS: ("aurora.Status", _object(
        "aurora.Status", "The health heartbeat (STATUS): flags byte and its named bits",
        {"timestamp_ms": _INT, "state": _INT, "state_name": _STR, "sm_type": _INT,
         "flags": _INT, "armed": _BOOL, "imu_ok": _BOOL, "baro_ok": _BOOL, "calibrated": _BOOL,
         "log_ready": _BOOL})),
    LINK_EVENTS: ("aurora.LinkEvent", _object(
        "aurora.LinkEvent", "A source's link came up (first valid frame) or went down (silence)",
        {"source": _STR, "up": _BOOL, "silence_s": _NUM})),
    LINK: ("aurora.LinkStats", _object(
        "aurora.LinkStats", "Radio link quality as the receiver reports it; null = not reported",
        {"rssi_dbm": _NUM_OR_NULL, "link_quality_pct": _INT_OR_NULL, "snr_db": _NUM_OR_NULL,
         "tx_power_mw": _INT_OR_NULL, "downlink_rssi_dbm": _NUM_OR_NULL,
         "downlink_link_quality_pct": _INT_OR_NULL, "downlink_snr_db": _NUM_OR_NULL,
         "rf_mode": _INT_OR_NULL, "antenna": _INT_OR_NULL, "origin": _STR})),
    POSITION: ("foxglove.LocationFix", _object(
        "foxglove.LocationFix", "A GNSS fix, WGS-84 degrees, altitude above mean sea level",
        {"timestamp": _TIME, "frame_id": _STR, "latitude": _NUM_OR_NULL,
         "longitude": _NUM_OR_NULL, "altitude": _NUM_OR_NULL,
         "position_covariance": {"type": "array", "items": _NUM, "minItems": 9,
                                 "maxItems": 9},
         "position_covariance_type": _INT})),
    BATTERY: ("aurora.Battery", _object(
        "aurora.Battery", "A battery's state; null = not measured",
        {"voltage_v": _NUM_OR_NULL, "current_a": _NUM_OR_NULL,
         "consumed_mah": _NUM_OR_NULL, "remaining_pct": _INT_OR_NULL,
         "battery_id": _INT})),
    VEHICLE: ("aurora.VehicleState", _object(
        "aurora.VehicleState", "A vehicle's state as its autopilot reports it (e.g. MAVLink "
        "HEARTBEAT, ATTITUDE); null = not reported",
        {"armed": _BOOL, "mode": _STR, "custom_mode": _INT_OR_NULL, "roll_rad": _NUM_OR_NULL,
         "pitch_rad": _NUM_OR_NULL, "yaw_rad": _NUM_OR_NULL, "altitude_m": _NUM_OR_NULL,
         "climb_mps": _NUM_OR_NULL})),
    RC: ("aurora.RcChannels", _object(
        "aurora.RcChannels", "Pilot or servo commands, pulse widths in µs; null = not sent",
        {"channels_us": {"type": "array", "items": _INT_OR_NULL}, "seq": _INT_OR_NULL})),
}
#: The channels every export has, even with no message on them (all but the link events
#: per vehicle).
CORE_TOPICS: tuple[str, ...] = (STATE, ALTITUDE, ATTITUDE, STATUS, LINK_EVENTS)
_PREFIX = "/aurora/"


def vehicle_topic(topic: str, vehicle: str) -> str:
    """``topic`` (one of the table's ``/aurora/<leaf>``) of ``vehicle``:
    ``/aurora/<vehicle>/<leaf>`` ("" or the link events: ``topic`` itself)."""
    if not vehicle or topic == LINK_EVENTS:
        return topic
    return f"{_PREFIX}{vehicle}/{topic[len(_PREFIX):]}"


def quaternion(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of the Z-Y-X rotation (:func:`gateway.attitude.quaternion_xyzw`), as
    FrameTransform carries it."""
    return quaternion_xyzw(roll, pitch, yaw)


def time_ns(t: float) -> int:
    """Seconds since the epoch as integer ns, rounded (exact for the integer part, unlike
    ``round(t * 1e9)``, which loses about 100 ns at today's epoch)."""
    if not t > 0:  # negative or NaN: MCAP times are unsigned
        return 0
    whole = math.floor(t)
    return whole * 1_000_000_000 + round((t - whole) * 1e9)


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def state_fields(m: SmUpdate) -> dict[str, Any]:
    """The ``/aurora/…/state`` message of an update."""
    return {"timestamp_ms": m.timestamp_ms, "state": m.state, "state_name": m.state_name,
            "armed": bool(m.armed), "sm_type": m.sm_type}


def altitude_fields(m: SmUpdate) -> dict[str, Any]:
    """The ``/aurora/…/altitude`` message of an update."""
    return {"timestamp_ms": m.timestamp_ms, "altitude_m": m.altitude_m,
            "velocity_mps": m.velocity_mps, "acceleration_mps2": m.acceleration_mps2,
            "accel_vert_mps2": m.accel_vert_mps2}


def attitude_fields(m: SmUpdate, ns: int) -> dict[str, Any]:
    """The ``/aurora/…/attitude`` message (a foxglove.FrameTransform) of an update received at
    ``ns``."""
    x, y, z, w = quaternion(m.roll_rad, m.pitch_rad, m.yaw_rad)
    return {"timestamp": _stamp(ns), "parent_frame_id": PARENT_FRAME,
            "child_frame_id": child_frame(m.vehicle),
            "translation": {"x": 0.0, "y": 0.0, "z": m.altitude_m},
            "rotation": {"x": x, "y": y, "z": z, "w": w}}


def status_fields(m: Status) -> dict[str, Any]:
    """The ``/aurora/…/status`` message of a STATUS."""
    return {"timestamp_ms": m.timestamp_ms, "state": m.state, "state_name": m.state_name,
            "sm_type": m.sm_type, "flags": m.flags, **m.health()}


def position_fields(m: Position, ns: int) -> dict[str, Any]:
    """The ``/aurora/…/position`` message (a foxglove.LocationFix) of a fix received at ``ns``
    (an unknown altitude as 0, as the live backend sends it)."""
    return {"timestamp": _stamp(ns), "frame_id": child_frame(m.vehicle), "latitude": m.lat_deg,
            "longitude": m.lon_deg,
            "altitude": m.alt_amsl_m if m.alt_amsl_m is not None else 0.0,
            "position_covariance": [0.0] * 9, "position_covariance_type": 0}


class McapExport:
    """Writes messages, each with its receive time, to an MCAP stream.

    Call :meth:`add` per message in time order (any message kind; the kinds without a
    channel are counted in ``skipped``), then :meth:`finish`.  ``source`` names the link on
    ``/aurora/link_events`` of messages that name no ``origin``.  ``vehicles``: the
    vehicles whose core channels are there even with no message (none: the unprefixed
    ones).  ``counts`` holds the messages written per topic.
    """

    def __init__(self, stream: IO[bytes], source: str = "recording",
                 link_timeout_s: float = DEFAULT_LINK_TIMEOUT_S,
                 metadata: dict[str, str] | None = None,
                 vehicles: Iterable[str] = ()) -> None:
        self.counts: Counter[str] = Counter()
        self.skipped: Counter[str] = Counter()
        self._writer = Writer(stream)
        self._writer.start(library=f"aurora-gateway {__version__}")
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        for vehicle in list(vehicles) or [""]:
            for topic in CORE_TOPICS:
                self._channel(vehicle_topic(topic, vehicle), topic)
        if metadata:
            self._writer.add_metadata("aurora.export", metadata)
        self._source = source
        self._now = 0.0
        self._link_timeout_s = link_timeout_s
        self._links = LinkMonitor(self._link_event, link_timeout_s, clock=lambda: self._now)
        self._up_last: dict[str, float] = {}  # the last frame of each source that is up
        self._routes: dict[type, Callable[[int, Any], None]] = {
            SmUpdate: self._sm_update, Status: self._status, Position: self._position,
            Battery: self._battery, LinkEvent: self._link_message, LinkStats: self._link_stats,
            VehicleState: self._vehicle_state, RcChannels: self._rc,
        }

    def _channel(self, topic: str, base: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            sid = self._schemas.get(base)
            if sid is None:  # one schema per kind, shared by the vehicles' channels
                name, schema = SCHEMAS[base]
                sid = self._schemas[base] = self._writer.register_schema(
                    name, SchemaEncoding.JSONSchema, orjson.dumps(schema))
            cid = self._writer.register_channel(topic, MessageEncoding.JSON, sid)
            self._channels[topic] = cid
        return cid

    def _write(self, base: str, ns: int, fields: dict[str, Any], vehicle: str = "") -> None:
        topic = vehicle_topic(base, vehicle)
        # orjson writes floats in their shortest round-trip form, and NaN/inf as null
        self._writer.add_message(self._channel(topic, base), log_time=ns,
                                 data=orjson.dumps(fields), publish_time=ns,
                                 sequence=self.counts[topic])
        self.counts[topic] += 1

    def add(self, t: float, msg: object, frame: bool = True) -> None:
        """Write ``msg``, received at ``t`` (s since the epoch).  ``frame``: it came in a
        valid wire frame from the source (which keeps the link up)."""
        if frame:
            self._frame_seen(t, getattr(msg, "origin", "") or self._source)
        ns = time_ns(t)
        route = self._routes.get(type(msg))
        if route is None:
            self.skipped[type(msg).__name__] += 1
        else:
            route(ns, msg)

    def _frame_seen(self, t: float, source: str) -> None:
        timeout = self._link_timeout_s
        silent = [(last, s) for s, last in self._up_last.items() if t - last >= timeout]
        for last, s in sorted(silent):  # each down when the gateway would have called it
            self._now = last + timeout
            self._links.check()
            del self._up_last[s]
        self._now = t
        self._up_last[source] = t
        self._links.frame_seen(source)

    def _link_event(self, ev: LinkEvent) -> None:
        self._link_message(time_ns(self._now), ev)

    def _sm_update(self, ns: int, m: SmUpdate) -> None:
        self._write(STATE, ns, state_fields(m), m.vehicle)
        self._write(ALTITUDE, ns, altitude_fields(m), m.vehicle)
        self._write(ATTITUDE, ns, attitude_fields(m, ns), m.vehicle)

    def _status(self, ns: int, m: Status) -> None:
        self._write(STATUS, ns, status_fields(m), m.vehicle)

    def _position(self, ns: int, m: Position) -> None:
        self._write(POSITION, ns, position_fields(m, ns), m.vehicle)

    def _battery(self, ns: int, m: Battery) -> None:
        self._write(BATTERY, ns, m.fields(), m.vehicle)

    def _vehicle_state(self, ns: int, m: VehicleState) -> None:
        self._write(VEHICLE, ns, m.fields(), m.vehicle)
        if m.roll_rad is not None and m.pitch_rad is not None and m.yaw_rad is not None:
            x, y, z, w = quaternion(m.roll_rad, m.pitch_rad, m.yaw_rad)
            self._write(ATTITUDE, ns, {
                "timestamp": _stamp(ns), "parent_frame_id": PARENT_FRAME,
                "child_frame_id": child_frame(m.vehicle),
                "translation": {"x": 0.0, "y": 0.0, "z": m.altitude_m or 0.0},
                "rotation": {"x": x, "y": y, "z": z, "w": w}}, m.vehicle)

    def _rc(self, ns: int, m: RcChannels) -> None:
        self._write(RC, ns, {"channels_us": list(m.channels_us), "seq": m.seq}, m.vehicle)

    def _link_message(self, ns: int, ev: LinkEvent) -> None:
        self._write(LINK_EVENTS, ns,
                    {"source": ev.source, "up": ev.up, "silence_s": ev.silence_s})

    def _link_stats(self, ns: int, m: LinkStats) -> None:
        self._write(LINK, ns, {**m.fields(), "origin": m.origin}, m.vehicle)

    def finish(self) -> None:
        """Write the summary (statistics, indexes) and the closing magic."""
        self._writer.finish()


def write(messages: Iterable[tuple[float, object]], stream: IO[bytes],
          source: str = "recording", link_timeout_s: float = DEFAULT_LINK_TIMEOUT_S,
          metadata: dict[str, str] | None = None, vehicles: Iterable[str] = ()) -> McapExport:
    """Write ``(receive time, message)`` pairs, each from a valid frame, as a whole MCAP
    file to ``stream`` (``vehicles``: whose core channels it has even if empty); returns the
    export (its ``counts`` per topic)."""
    export = McapExport(stream, source, link_timeout_s, metadata, vehicles)
    for t, msg in messages:
        export.add(t, msg)
    export.finish()
    return export
