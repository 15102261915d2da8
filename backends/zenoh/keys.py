"""The Zenoh key layout, the attachment that identifies a publication, and loop prevention.

Keys (``prefix`` default ``aurora``; ``<vehicle>`` is each message's vehicle, see
:mod:`gateway.vehicles`)::

    <prefix>/<vehicle>/sm_update        state-machine snapshot (JSON, or packed)
    <prefix>/<vehicle>/status           health heartbeat (JSON, or packed)
    <prefix>/<vehicle>/link             a source's link went up / down (JSON)
    <prefix>/<vehicle>/link_stats       radio link quality (JSON)
    <prefix>/<vehicle>/position         GNSS fix (JSON)
    <prefix>/<vehicle>/battery          battery (JSON)
    <prefix>/<vehicle>/vehicle_state    non-Aurora vehicle state (JSON)
    <prefix>/<vehicle>/rc_channels      pilot or servo commands (JSON)
    <prefix>/<vehicle>/raw/<type>       the untouched wire frame; <type> in decimal (1, 2, 171)
    <prefix>/<vehicle>/gateway/<id>     liveliness token of each gateway publishing it
    <prefix>/@gateways/<id>/stats       a gateway's own counters (JSON), for a monitor

``@gateways`` is a Zenoh *verbatim* chunk: no wildcard matches it (``aurora/**`` and
``aurora/*/*`` never see a gateway's counters) and no vehicle name can be it.

Every publication carries an attachment ``gw=<gateway id>;seq=<n>``: the gateway that
published it and a sequence number counted per key from 0, so a subscriber can tell
gateways apart, ignore its own publications, and count what it lost.
"""

from __future__ import annotations

import re

DEFAULT_PREFIX = "aurora"
#: Where the embedded default listens and where ``aurora-gateway listen`` looks first: a
#: loopback port of its own, so it never collides with a Zenoh router (zenohd, rmw_zenoh) on
#: the usual 7447.
DEFAULT_PORT = 7450
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"

RAW = "raw"
GATEWAY = "gateway"
#: Kinds published as JSON documents under ``<prefix>/<vehicle>/<kind>``.
JSON_KINDS = ("sm_update", "status", "link", "link_stats", "position", "battery",
              "vehicle_state", "rc_channels")

#: The kind of a gateway's own counters (every backend's and source's ``stats()``), published
#: every ``stats_interval_s`` on :func:`stats_key`: for a monitor that follows it.
STATS_KIND = "gateway_stats"
#: The verbatim chunk under which gateways publish what is theirs, not a vehicle's.
GATEWAYS = "@gateways"
STATS = "stats"
#: The gateway service (``GatewayContext.services``) naming this gateway's Zenoh sources (a
#: set of source names): their vehicles are another gateway's, never published here again.
SOURCES_SERVICE = "zenoh.sources"
#: Vehicles one backend publishes, or one source follows, at most; beyond, a vehicle's
#: messages are counted (``dropped_vehicle_limit``) and not published or emitted.
MAX_VEHICLES = 256

_FORBIDDEN = re.compile(r"[*$?#\s]")


def check_prefix(prefix: str) -> str:
    """A prefix is one or more key chunks without wildcards; raise ValueError otherwise."""
    if not isinstance(prefix, str) or not prefix:
        raise ValueError("must be a non-empty key expression such as 'aurora'")
    if prefix.startswith("/") or prefix.endswith("/") or "//" in prefix:
        raise ValueError(f"{prefix!r}: no leading, trailing or doubled '/'")
    if _FORBIDDEN.search(prefix) or any(c.startswith("@") for c in prefix.split("/")):
        raise ValueError(f"{prefix!r}: no wildcards ('*', '$'), '?', '#', spaces or '@' chunks")
    return prefix


def check_chunk(value: str, what: str = "vehicle", wildcard: bool = False) -> str:
    """One key chunk (no '/'); ``wildcard`` allows exactly ``*``."""
    if wildcard and value == "*":
        return value
    if not isinstance(value, str) or not value:
        raise ValueError(f"{what} must be a non-empty name")
    if "/" in value or _FORBIDDEN.search(value) or value.startswith("@"):
        raise ValueError(f"{what} {value!r}: one key chunk, without '/', wildcards, '?', '#', "
                         "spaces or a leading '@'" + (" (or exactly '*')" if wildcard else ""))
    return value


#: ``via`` of a message that came in over Zenoh: ``zenoh:<publishing gateway's id>``.
VIA_ZENOH = "zenoh:"


def stats_key(prefix: str, gateway_id: str) -> str:
    """Where gateway ``gateway_id`` publishes its counters: ``<prefix>/@gateways/<id>/stats``."""
    return f"{prefix}/{GATEWAYS}/{gateway_id}/{STATS}"


def stats_key_expr(prefix: str) -> str:
    """Every gateway's counters under ``prefix``."""
    return f"{prefix}/{GATEWAYS}/*/{STATS}"


def parse_stats_key(key: str, prefix: str) -> str | None:
    """The gateway id of a :func:`stats_key`; None if ``key`` is not one."""
    head = f"{prefix}/{GATEWAYS}/"
    if not key.startswith(head) or not key.endswith("/" + STATS):
        return None
    gateway = key[len(head):-len(STATS) - 1]
    return gateway if gateway and "/" not in gateway else None


class KeyLayout:
    """The keys of one vehicle under one prefix, built once (a dict lookup per message)."""

    __slots__ = ("_kinds", "_raw", "base", "prefix", "vehicle")

    def __init__(self, prefix: str, vehicle: str) -> None:
        self.prefix = check_prefix(prefix)
        self.vehicle = check_chunk(vehicle, "vehicle")
        self.base = f"{prefix}/{vehicle}"
        self._raw: dict[int, str] = {}
        self._kinds: dict[str, str] = {}

    def kind(self, kind: str) -> str:
        key = self._kinds.get(kind)
        if key is None:
            key = self._kinds[kind] = f"{self.base}/{kind}"
        return key

    def raw(self, frame_type: int) -> str:
        key = self._raw.get(frame_type)
        if key is None:
            key = self._raw[frame_type] = f"{self.base}/{RAW}/{frame_type}"
        return key

    def token(self, gateway_id: str) -> str:
        return f"{self.base}/{GATEWAY}/{gateway_id}"

    @property
    def everything(self) -> str:
        """Every key of this vehicle: ``<prefix>/<vehicle>/**``."""
        return f"{self.base}/**"


def parse_key(key: str, prefix: str) -> tuple[str, str, str] | None:
    """``(vehicle, kind, rest)`` of a key under ``prefix``; None if it is not one of ours.

    ``kind`` is e.g. ``sm_update`` or ``raw`` (then ``rest`` is the frame type)."""
    head = prefix + "/"
    if not key.startswith(head):
        return None
    parts = key[len(head):].split("/", 2)
    if len(parts) < 2:
        return None
    return parts[0], parts[1], parts[2] if len(parts) > 2 else ""


# -- attachments -------------------------------------------------------------------------------

def make_attachment(gateway_id: str, seq: int) -> bytes:
    return f"gw={gateway_id};seq={seq}".encode()


def parse_attachment(data: bytes | None) -> tuple[str | None, int | None]:
    """``(gateway id, seq)`` from an attachment; (None, None) for a foreign or missing one."""
    if not data:
        return None, None
    try:
        text = bytes(data).decode()
    except UnicodeDecodeError:
        return None, None
    gw: str | None = None
    seq: int | None = None
    for part in text.split(";"):
        name, _, value = part.partition("=")
        if name == "gw":
            gw = value or None
        elif name == "seq":
            try:
                seq = int(value)
            except ValueError:
                seq = None
    return gw, seq


class SeqTracker:
    """Counts publications lost on the way, from the per-key sequence numbers.

    ``lost`` grows by the size of every forward gap; a sequence number that goes backwards
    means the publisher restarted (``restarts``), never a loss.  At most ``max_keys``
    (gateway, key) pairs are remembered: a new one beyond makes the oldest forgotten
    (``forgotten``; a forgotten key's next gap goes uncounted)."""

    __slots__ = ("_last", "forgotten", "lost", "max_keys", "restarts")

    def __init__(self, max_keys: int = 65536) -> None:
        self._last: dict[tuple[str, str], int] = {}
        self.max_keys = max_keys
        self.lost = 0
        self.restarts = 0
        self.forgotten = 0

    def see(self, gateway: str | None, key: str, seq: int | None) -> int:
        """Record one sample; return how many were lost just before it."""
        if gateway is None or seq is None:
            return 0
        k = (gateway, key)
        table = self._last
        last = table.get(k)
        if last is None:
            if len(table) >= self.max_keys:
                try:  # (another of Zenoh's threads may be at it too)
                    del table[next(iter(table))]
                    self.forgotten += 1
                except (RuntimeError, KeyError, StopIteration):
                    pass
            table[k] = seq
            return 0
        table[k] = seq
        if seq > last + 1:
            gap = seq - last - 1
            self.lost += gap
            return gap
        if seq <= last:
            self.restarts += 1
        return 0
