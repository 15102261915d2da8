"""Payloads published on Zenoh: JSON documents, packed Aurora payloads, raw wire frames.

Sans-I/O: messages in, ``(payload, encoding)`` out, and back.  The JSON documents use the
model's field names, whose suffixes are the units (``altitude_m``, ``velocity_mps``,
``roll_rad``, ``silence_s``); a NaN or infinite float becomes ``null``.  See README.md for
every document.

Packed encoding (``encoding = "packed"``) applies to the two kinds the Aurora wire format
defines: ``sm_update`` and ``status`` carry the frame's payload exactly as it arrived
(36 bytes f32 or 64 bytes f64 for SM_UPDATE, 8 bytes for STATUS, little-endian, layout in
``shared/specs/aurora-wire.md``).  The other kinds have no wire layout and stay JSON.
"""

from __future__ import annotations

import json
import math
from typing import Any

from dialects.states import state_name
from gateway import wire
from gateway.model import (
    SM_UPDATE_F32_LEN,
    SM_UPDATE_F64_LEN,
    Battery,
    GatewayStats,
    LinkEvent,
    LinkStats,
    Position,
    RawFrame,
    RcChannels,
    SmUpdate,
    Status,
    VehicleState,
)
from gateway.signals import held

with held():  # a Ctrl-C inside orjson's module init crashes it (gateway/signals.py)
    import orjson

JSON = "application/json"
SM_UPDATE_PACKED = "application/octet-stream;aurora.sm_update"
STATUS_PACKED = "application/octet-stream;aurora.status"
WIRE = "application/octet-stream;aurora.wire"

ENCODINGS = ("json", "packed")

_dumps = json.JSONEncoder(allow_nan=False, separators=(",", ":")).encode
_names: dict[tuple[int, int], str] = {}


class PayloadError(ValueError):
    """A payload that does not decode to a message."""


def _state_name(sm_type: int, state: int) -> str:
    name = _names.get((sm_type, state))
    if name is None:
        name = state_name(sm_type, state)
        if len(_names) < 4096:
            _names[(sm_type, state)] = name
    return name


def _finite(v: Any) -> Any:
    return None if isinstance(v, float) and not math.isfinite(v) else v


def dumps_stdlib(doc: dict[str, Any]) -> bytes:
    """Compact JSON with the standard library; NaN and ±inf become null (checked only when
    the strict encoder refuses one)."""
    try:
        return _dumps(doc).encode()
    except ValueError:
        return _dumps({k: _finite(v) for k, v in doc.items()}).encode()


_orjson_dumps = orjson.dumps
_orjson_error = orjson.JSONEncodeError


def dumps(doc: dict[str, Any]) -> bytes:
    """Compact JSON; NaN and ±inf become null.  orjson (about 15× faster than the standard
    library on these documents); :func:`dumps_stdlib` for what orjson refuses."""
    try:
        return _orjson_dumps(doc)
    except _orjson_error:  # e.g. an integer beyond 64 bits
        return dumps_stdlib(doc)


# -- messages → documents ----------------------------------------------------------------------

def sm_update_doc(m: SmUpdate) -> dict[str, Any]:
    return {
        "timestamp_ms": m.timestamp_ms,
        "state": m.state,
        "state_name": _state_name(m.sm_type, m.state),
        "armed": m.armed,
        "sm_type": m.sm_type,
        "altitude_m": m.altitude_m,
        "acceleration_mps2": m.acceleration_mps2,
        "accel_vert_mps2": m.accel_vert_mps2,
        "velocity_mps": m.velocity_mps,
        "roll_rad": m.roll_rad,
        "pitch_rad": m.pitch_rad,
        "yaw_rad": m.yaw_rad,
        "payload_len": m.payload_len,
    }


def status_doc(m: Status) -> dict[str, Any]:
    f = m.flags
    return {
        "timestamp_ms": m.timestamp_ms,
        "state": m.state,
        "state_name": _state_name(m.sm_type, m.state),
        "sm_type": m.sm_type,
        "flags": f,
        "armed": bool(f & 0x01),
        "imu_ok": bool(f & 0x02),
        "baro_ok": bool(f & 0x04),
        "calibrated": bool(f & 0x08),
        "log_ready": bool(f & 0x10),
    }


def link_doc(m: LinkEvent) -> dict[str, Any]:
    return {"source": m.source, "up": m.up, "silence_s": m.silence_s}


def document(msg: Any) -> dict[str, Any]:
    """The JSON document of a message (the kinds in :data:`keys.JSON_KINDS`)."""
    if isinstance(msg, SmUpdate):
        return sm_update_doc(msg)
    if isinstance(msg, Status):
        return status_doc(msg)
    if isinstance(msg, LinkEvent):
        return link_doc(msg)
    return msg.fields()


def to_json(msg: Any) -> bytes:
    return dumps(document(msg))


def wire_frame(msg: SmUpdate | Status | RawFrame) -> bytes:
    """The wire frame a message came from (re-encoded if it was built in memory)."""
    return msg.raw or wire.encode(msg)


def packed(msg: SmUpdate | Status) -> bytes:
    """The Aurora payload of an SM_UPDATE or STATUS, as it arrived."""
    return wire_frame(msg)[wire.HEADER_LEN:-wire.CRC_LEN]


def encode(msg: Any, encoding: str = "json") -> tuple[bytes, str]:
    """``(payload, encoding string)`` for the message's own key."""
    if encoding == "packed":
        if isinstance(msg, SmUpdate):
            return packed(msg), SM_UPDATE_PACKED
        if isinstance(msg, Status):
            return packed(msg), STATUS_PACKED
    return to_json(msg), JSON


# -- documents → messages ----------------------------------------------------------------------

def _num(d: dict[str, Any], key: str) -> float:
    v = d.get(key)
    if v is None:
        return math.nan
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise PayloadError(f"{key}: expected a number, got {v!r}")
    return float(v)


def _int(d: dict[str, Any], key: str, default: int | None = None) -> int:
    v = d.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int):
        raise PayloadError(f"{key}: expected an integer, got {v!r}")
    return v


def _opt(d: dict[str, Any], cls: Any, required: tuple[str, ...] = ()) -> Any:
    for key in required:
        if d.get(key) is None:
            raise PayloadError(f"{key}: required")
    known = {k: d[k] for k in cls._fields if k in d and k != "origin"}
    return cls(**known)


def from_document(kind: str, d: Any, origin: str = "") -> Any:
    """The message a JSON document describes; raises :class:`PayloadError`."""
    if not isinstance(d, dict):
        raise PayloadError("expected a JSON object")
    try:
        if kind == "sm_update":
            plen = _int(d, "payload_len", SM_UPDATE_F64_LEN)
            if plen not in (SM_UPDATE_F32_LEN, SM_UPDATE_F64_LEN):
                raise PayloadError(f"payload_len: expected 36 or 64, got {plen}")
            return SmUpdate(_int(d, "timestamp_ms"), _int(d, "state"), bool(d.get("armed")),
                            _int(d, "sm_type", 0), _num(d, "altitude_m"),
                            _num(d, "acceleration_mps2"), _num(d, "accel_vert_mps2"),
                            _num(d, "velocity_mps"), _num(d, "roll_rad"), _num(d, "pitch_rad"),
                            _num(d, "yaw_rad"), plen, 0, b"", origin)
        if kind == "status":
            return Status(_int(d, "timestamp_ms"), _int(d, "state"), _int(d, "sm_type", 0),
                          _int(d, "flags") & 0xFF, 0, b"", origin)
        if kind == "link_stats":
            return _opt(d, LinkStats)._replace(origin=origin)
        if kind == "position":
            return _opt(d, Position, ("lat_deg", "lon_deg"))._replace(origin=origin)
        if kind == "battery":
            return _opt(d, Battery, ("voltage_v",))._replace(origin=origin)
        if kind == "vehicle_state":
            return _opt(d, VehicleState, ("armed", "mode"))._replace(origin=origin)
        if kind == "rc_channels":
            channels = d.get("channels_us")
            if not isinstance(channels, list) or not all(
                    c is None or (isinstance(c, int) and not isinstance(c, bool))
                    for c in channels):
                raise PayloadError("channels_us: expected a list of integers or nulls")
            seq = d.get("seq")
            if seq is not None and (isinstance(seq, bool) or not isinstance(seq, int)):
                raise PayloadError(f"seq: expected an integer, got {seq!r}")
            return RcChannels(tuple(channels), seq, origin)
    except TypeError as exc:
        raise PayloadError(str(exc)) from None
    raise PayloadError(f"no message for kind {kind!r}")


def decode(kind: str, payload: bytes, encoding: str, origin: str = "") -> Any:
    """A published payload back to a message (JSON or packed); raises PayloadError."""
    if encoding in (SM_UPDATE_PACKED, STATUS_PACKED):
        ftype = wire.TYPE_SM_UPDATE if encoding == SM_UPDATE_PACKED else wire.TYPE_STATUS
        if len(payload) > wire.MAX_PAYLOAD:
            raise PayloadError(f"packed payload of {len(payload)} bytes is too long")
        msgs = wire.decode_all(wire.frame(ftype, bytes(payload)), origin)
        if len(msgs) != 1 or isinstance(msgs[0], RawFrame):
            raise PayloadError(f"packed {kind} of {len(payload)} bytes has no known layout")
        return msgs[0]
    try:
        doc = json.loads(payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise PayloadError(f"not JSON: {exc}") from None
    return from_document(kind, doc, origin)


def stats_document(stats: dict[str, Any]) -> bytes:
    """A gateway's counters as JSON (values JSON cannot hold are written as text)."""
    return orjson.dumps(stats, default=str, option=orjson.OPT_NON_STR_KEYS)


def gateway_stats(gateway: str, payload: bytes, origin: str = "") -> GatewayStats:
    """A published ``gateway_stats`` document back; raises :class:`PayloadError`."""
    try:
        doc = json.loads(payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise PayloadError(f"not JSON: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("backends", {}), dict) \
            or not isinstance(doc.get("sources", {}), dict):
        raise PayloadError("expected {\"backends\": {...}, \"sources\": {...}}")
    return GatewayStats(gateway, doc.get("backends", {}), doc.get("sources", {}), origin)

