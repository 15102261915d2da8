"""MAVLink routing between links, as mavlink-router does it, plus the gateway's own nodes.

Every frame arriving on a link is framed (not decoded, see :mod:`.frames`), its source
(system, component) is learned for that link, and it is forwarded as the exact bytes that
arrived:

* a message without a target, or with target system 0 (broadcast), goes to every other link;
* a targeted message goes only to the links on which its target system (and component, when
  not 0) has been seen; a target nobody has been seen as is not forwarded (counted);
* never back to the link it came from, nor to a link on which its own source was seen
  (that is where it came from by another path: forwarding it would loop);
* unknown message ids are forwarded too (unvalidated, like mavlink-router).

**Local nodes** are the gateway's own MAVLink components: the rocket as a vehicle (the
backend's :class:`~.translate.AuroraVehicle`) and the listener that turns a vehicle's
telemetry into gateway messages (the source's :class:`~.source.VehicleListener`).  One router
may serve both: that is how ``run --source mavlink:… --mavlink …`` routes a vehicle to ground
stations in the same process as the translation.  A node gets the frames it reads when they
are addressed to it or broadcast — and only those are decoded:

* ``consumed`` ids are decoded and handed to ``node.handle`` at once (requests, heartbeats);
* ``latest`` ids are kept in a mailbox, one frame per (source, id), replaced by each newer
  one, and decoded only when the node asks (:meth:`Router.collect`, at the rate it needs
  them): the latest ATTITUDE, not all 50 Hz of them.

With signing on, those frames are verified first (see :mod:`.signing`).  A node's own messages
go to the links of its *groups* (the rocket to the ground-station side, the listener to the
vehicle side), packed per link and per source component, so each has its own sequence numbers
(and signing stream).  A SYS_STATUS without a battery goes only to links whose ground
stations read it right (:mod:`.ground_stations`).

**System ids.**  A node's messages never use a system id anybody routed through it uses:
when a node first speaks (:meth:`Router.claim`) an id already seen on a link is skipped, and a
system that later appears with the node's id (a different component, a message the node never
sends, or a heartbeat of another vehicle type — not our own echo coming back round a loop)
moves the node to a free id, logged.  A node answers only what is addressed to its own id,
and nothing before it has claimed one (the rocket routing a vehicle stays off the air until it
has something to say).

The table of systems seen (:attr:`Router.seen_at`) is what those rules read.  It is bounded
(one entry per system id, ≤ 256) and forgets a system silent for :attr:`Router.system_timeout_s`
(30 s by default).  With signing on, only a correctly signed frame (verdict ``OK``) is
evidence: a system enters the table, or moves a node, only by a signed frame; a frame carrying
one of our ids that is not correctly signed is dropped and counted (``impostor_frames``), and
one from a system not in the table that is not correctly signed does not enter it (counted
``unverified_systems``).  Each frame is verified at most once (the same verdict serves its
delivery).  When no id is free, a node keeps its own and the conflict is counted
(``sysid_conflicts``): nothing raises.  New systems, moves and conflicts are logged once per
burst, with a count per interval (:class:`~gateway.io.burstlog.BurstLog`), once the router has
a loop (:meth:`Router.use_loop`).

**Batches.**  :meth:`Router.receive_many` routes what one read returned; the common datagram
(one good MAVLink 2 frame, broadcast, from a source already seen on the link, not using a
node's id, read by no node or only into a mailbox) is routed by a loop compiled from
``_route_speedups.c`` where the install built it (:data:`COMPILED`), else by the same loop in
Python (:meth:`Router._route_datagrams`); anything else takes the general path.  Both are
tested to route alike (``tests/test_route_speedups.py``).

All state is guarded by :attr:`Router.lock`; links call :meth:`Router.receive` from whatever
thread reads them, and every ``Link.send`` is non-blocking.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

from backends.mavlink import signing
from backends.mavlink.dialect import mav
from backends.mavlink.frames import (
    INFO,
    Frame,
    FramerStats,
    StreamFramer,
    frame_v2,
    split_datagram,
)
from backends.mavlink.ground_stations import NO_VOLTAGE, shows_no_battery
from backends.mavlink.signing import Verdict
from gateway.counters import Counters
from gateway.crc import mcrf4xx
from gateway.io.burstlog import BurstLog
from gateway.io.ioloop import IoLoop

try:  # the common case of routing compiled (optional: the wheel may be built without it)
    from backends.mavlink import _route_speedups as _speedups
except ImportError:
    _speedups = None  # type: ignore[assignment]
if os.environ.get("AURORA_NO_SPEEDUPS"):
    _speedups = None  # type: ignore[assignment]
#: Whether the compiled loop routes the common case (else the pure-Python one does).
COMPILED = _speedups is not None

log = logging.getLogger(__name__)

MSG_HEARTBEAT = 0
SYS_STATUS = 1  # sent only where it reads right (see ground_stations)
HEARTBEAT_TYPE_OFS = 4  # payload: custom_mode (u32), then type (u8)
_NO_IDS: frozenset[int] = frozenset()
#: A system silent for this long is forgotten (its id is free again); the backend's
#: ``system_timeout_s`` option sets it.
SYSTEM_TIMEOUT_S = 30.0
#: A node in conflict (its id in use, none free) looks for a free id again after this long.
CONFLICT_RETRY_S = 1.0
#: The system ids a node of ours may use (0 is broadcast, 255 the ground stations').
FIRST_ID, LAST_ID = 1, 254


class LocalNode(Protocol):
    """What the router needs of a node it serves (``latest``, ``heartbeat_type`` and
    ``component_of`` are optional)."""

    sysid: int
    compid: int
    consumed: frozenset[int]

    def handle(self, msg: Any, src_sysid: int, src_compid: int) -> list[Any]: ...


@dataclass
class LinkCounters(Counters):
    rx_frames: int = 0
    rx_bytes: int = 0
    tx_frames: int = 0
    tx_bytes: int = 0
    tx_dropped: int = 0  # could not be queued/sent (full queue or buffer)
    tx_not_up: int = 0  # our own messages not sent: no peer yet / port down (not a drop)
    tx_errors: int = 0  # the OS refused a send
    seq_lost: int = 0  # gaps in the senders' sequence numbers
    rejected_signing: int = 0  # consumed frames refused by signature checks
    decode_errors: int = 0


class Link:
    """One MAVLink channel: a UDP endpoint, a TCP connection or a serial port.

    Subclasses implement :meth:`send` (non-blocking; True when the bytes were sent or queued)
    and :attr:`up`.  ``group`` names the side it is on ("gcs", "vehicle"): a node's own
    messages go to the links of its groups."""

    datagram = False

    def __init__(self, name: str, group: str = "") -> None:
        self.name = name
        self.group = group
        self.counters = LinkCounters()
        self.framer: StreamFramer | None = None if self.datagram else StreamFramer()
        self.framer_stats: FramerStats = (self.framer.stats if self.framer is not None
                                          else FramerStats())
        self.seen: set[int] = set()  # (sysid << 8) | compid of every source seen here
        self.seen_sys: set[int] = set()
        self.last_seq: dict[int, int] = {}
        self.encoders: dict[int, Any] = {}  # (sysid << 8) | compid → pymavlink packer
        self.signing = False
        self.router: Router | None = None

    @property
    def up(self) -> bool:
        return True

    def send(self, data: bytes) -> bool:
        raise NotImplementedError

    def batch_sink(self) -> list[bytes] | None:
        """During a router batch, a list to append what is sent to instead of :meth:`send`
        (the link counts and writes it when the batch ends), or None."""
        return None

    def stats(self) -> dict[str, Any]:
        d: dict[str, Any] = self.counters.as_dict()
        fs = self.framer_stats
        d.update(crc_errors=fs.crc_errors, bad_headers=fs.bad_headers,
                 bytes_skipped=fs.bytes_skipped, unknown_ids=fs.unknown_ids,
                 systems=sorted(f"{k >> 8}/{k & 0xFF}" for k in self.seen))
        return d


@dataclass
class RouterStats(Counters):
    forwarded: int = 0  # frames written to other links
    unroutable: int = 0  # targeted at a system no link has seen
    delivered: int = 0  # frames decoded for a local node
    mailboxed: int = 0  # frames kept for a node (only the latest of each is decoded)
    own_id_seen: int = 0  # our own frames coming back (a loop in the network)
    id_changes: int = 0  # a node moved to another system id (someone else used its id)
    sysid_conflicts: int = 0  # a node's id was in use and no other was free: it kept it
    impostor_frames: int = 0  # signing on: frames with one of our ids, not signed right
    unverified_systems: int = 0  # signing on: frames of an unknown system, not signed right
    systems_forgotten: int = 0  # systems silent for system_timeout_s, dropped from the table
    node_errors: int = 0  # a local node raised on a request (a bug; logged)
    encode_errors: int = 0  # one of our messages could not be packed (a bug; logged)
    sent_own: int = 0  # local messages sent (counted once per link)
    links_added: int = 0
    links_removed: int = 0
    extra: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, int]:
        d = super().as_dict()
        d.update(self.extra)
        return d


class _Slot:
    """A node as the router keeps it."""

    def __init__(self, node: LocalNode, groups: frozenset[str] | None, step: int) -> None:
        self.node = node
        self.groups = groups
        self.step = step  # the way to look for a free id: +1 (up from 1) or -1 (down)
        self.consumed: frozenset[int] = node.consumed
        self.latest: frozenset[int] = getattr(node, "latest", _NO_IDS)
        self.heartbeat_type: int | None = getattr(node, "heartbeat_type", None)
        self.component_of = getattr(node, "component_of", None)
        self.compids: set[int] = {node.compid}
        self.sent_ids: set[int] = set()
        self.claimed = False
        #: (source << 24) | id → the latest frame (or, from the batch paths, its bytes: made
        #: a Frame when collected) and the link it came on; the same dict for the slot's life
        #: (the batch paths keep it in :attr:`Router._boxes`)
        self.mailbox: dict[int, tuple[Frame | bytes | bytearray, Link]] = {}
        #: in conflict (no free id): when to look for one again (not on every frame)
        self.retry_at = 0.0

    def wants(self, tsys: int, tcomp: int) -> bool:
        """Whether a frame with these targets is for the node (broadcast, or its id)."""
        node = self.node
        return tsys <= 0 or (tsys == node.sysid and tcomp in (-1, 0, node.compid))


class Router:
    """Routes frames between links and serves local nodes; see the module docstring."""

    def __init__(self, node: LocalNode | None = None, *, forward: bool = True,
                 signing_key: bytes | None = None) -> None:
        self.lock = threading.RLock()
        self.forward = forward
        self.links: list[Link] = []
        self._others: dict[Link, tuple[Link, ...]] = {}
        #: link → key → where a broadcast of that source read on the link goes (a batch's)
        self._dests_of: dict[Link, Callable[[int], Any]] = {}
        self._batching: tuple[Link, ...] = ()  # links that write what a batch routes at once
        self.stats = RouterStats()
        self.signing_key: bytes | None = None
        self.verifier: signing.SignatureVerifier | None = None
        self._decoder = mav.MAVLink(None)  # decodes consumed frames; verification is ours
        self._next_link_id = 0
        self._slots: list[_Slot] = []
        self._by_node: dict[int, _Slot] = {}
        self._wants: dict[int, tuple[_Slot, ...]] = {}  # msgid → nodes that read it
        #: msgid → the mailboxes a broadcast of it goes to, or None: decoded at once (the
        #: general path); filled by the batch paths, emptied when a node is added, removed
        #: or claims its id
        self._boxes: dict[int, tuple[dict[int, Any], ...] | None] = {}
        self._own: dict[int, _Slot] = {}  # system id → the claimed node using it
        #: systems seen (the identity evidence, see the module docstring): id → when last
        #: heard (monotonic), and → the link it was first heard on; ≤ 256 entries each
        self.seen_at: dict[int, float] = {}
        self.seen_systems: dict[int, str] = {}
        self.system_timeout_s = SYSTEM_TIMEOUT_S
        self._now = time.monotonic()
        self._logs: dict[str, BurstLog] = {}
        #: called with every frame that crosses the router, once (under the lock, so in the
        #: order they crossed): each frame read from a link and kept (not our own echo, not
        #: an impostor), each of our nodes' messages as first sent; a telemetry log's
        #: writer (:mod:`.tlog`), or None
        self.tap: Callable[[bytes], Any] | None = None
        if signing_key is not None:
            self.set_signing_key(signing_key)
        if node is not None:
            self.add_node(node)

    @property
    def node(self) -> LocalNode | None:
        """The first node (a router serving one)."""
        return self._slots[0].node if self._slots else None

    # -- configuration -----------------------------------------------------------------------

    def use_loop(self, loop: IoLoop) -> None:
        """Log new systems, id changes and conflicts once per burst on ``loop``'s timers."""
        with self.lock:
            self._logs = {
                "new": BurstLog(loop, "MAVLink: new system seen", level=logging.INFO,
                                logger=log),
                "move": BurstLog(loop, "MAVLink: a system uses the id of a gateway node",
                                 logger=log),
                "conflict": BurstLog(loop, "MAVLink: system id conflict, no free id",
                                     logger=log),
                "impostor": BurstLog(loop, "MAVLink: frames carrying a gateway node's id, not "
                                     "correctly signed, dropped", logger=log),
            }

    def log_lines(self) -> dict[str, int]:
        """Lines logged so far about new systems, moves and conflicts (by kind)."""
        return {kind: b.lines for kind, b in self._logs.items()}

    def _say(self, kind: str, detail: str) -> None:
        burst = self._logs.get(kind)
        if burst is not None:
            burst.event(detail)
        else:  # a router without a loop (a test, a tool): not rate-limited, so debug only
            log.debug("MAVLink: %s", detail)

    def set_signing_key(self, key: bytes) -> None:
        """Sign what we send and verify what our nodes read; one key per router."""
        with self.lock:
            if self.signing_key is not None and self.signing_key != key:
                raise ValueError("two different MAVLink signing keys for one router: the "
                                 "source and the backend must use the same key")
            if self.signing_key is None:
                self.signing_key = key
                self.verifier = signing.SignatureVerifier(key)

    def add_node(self, node: LocalNode, groups: Iterable[str] | None = None, *,
                 step: int = 1) -> None:
        """Serve ``node``; its own messages go to links of ``groups`` (None: every link).
        Its system id is its preferred one until :meth:`claim`."""
        with self.lock:
            slot = _Slot(node, frozenset(groups) if groups is not None else None, step)
            self._slots.append(slot)
            self._by_node[id(node)] = slot
            self._index()

    def remove_node(self, node: LocalNode) -> None:
        """Stop serving ``node`` (its id is free again)."""
        with self.lock:
            slot = self._by_node.pop(id(node), None)
            if slot is None:
                return
            self._slots.remove(slot)
            if self._own.get(node.sysid) is slot:
                del self._own[node.sysid]
            self._index()

    def node_groups(self) -> set[str]:
        """The groups the nodes' own messages go to."""
        with self.lock:
            return {g for s in self._slots for g in (s.groups or ())}

    def _index(self) -> None:
        self._boxes.clear()
        wants: dict[int, list[_Slot]] = {}
        for s in self._slots:
            for msgid in s.consumed | s.latest:
                wants.setdefault(msgid, []).append(s)
        self._wants = {k: tuple(v) for k, v in wants.items()}

    def add_link(self, link: Link) -> None:
        with self.lock:
            if self.signing_key is not None:
                link.signing = True
            link.router = self
            self.links.append(link)
            self.stats.links_added += 1
            self._rebuild()

    def remove_link(self, link: Link) -> None:
        with self.lock:
            if link in self.links:
                self.links.remove(link)
                self.stats.links_removed += 1
                self._rebuild()

    def _rebuild(self) -> None:
        self._others = {lk: tuple(o for o in self.links if o is not lk) for lk in self.links}
        self._dests_of = {lk: functools.partial(self._destinations, others)
                          for lk, others in self._others.items()}
        self._batching = tuple(lk for lk in self.links if hasattr(lk, "flush_batch"))

    # -- system ids ----------------------------------------------------------------------------

    def in_use(self, sysid: int, now: float | None = None) -> bool:
        """Whether a system other than our nodes was heard with ``sysid`` within
        :attr:`system_timeout_s`."""
        t = self.seen_at.get(sysid)
        if t is None:
            return False
        return (time.monotonic() if now is None else now) - t <= self.system_timeout_s

    def expire(self, now: float | None = None) -> int:
        """Forget the systems silent for :attr:`system_timeout_s`; returns how many."""
        with self.lock:
            now = time.monotonic() if now is None else now
            old = [k for k, t in self.seen_at.items() if now - t > self.system_timeout_s]
            for k in old:
                del self.seen_at[k]
                self.seen_systems.pop(k, None)
            self.stats.systems_forgotten += len(old)
            return len(old)

    def free_id(self, start: int, step: int = 1, avoid: Iterable[int] = ()) -> int | None:
        """The first id from ``start`` on (then ``start + step`` …, round 1..254) that no
        system seen and no node of ours uses (on the air or not yet: an unclaimed node's id
        is kept for it), and not in ``avoid``; None when there is none."""
        with self.lock:
            now = time.monotonic()
            taken = set(avoid) | set(self._own)
            taken.update(s.node.sysid for s in self._slots if not s.claimed)
            for i in range(LAST_ID):
                cand = (start - FIRST_ID + step * i) % LAST_ID + FIRST_ID
                if cand not in taken and not self.in_use(cand, now):
                    return cand
            return None

    def claim(self, node: LocalNode) -> int:
        """Settle ``node``'s system id before it first speaks: its own unless a system seen on
        a link (or another node) uses it; returns the id.  When no other id is free the node
        keeps its own (counted ``sysid_conflicts``)."""
        with self.lock:
            slot = self._by_node[id(node)]
            if not slot.claimed:
                old = node.sysid
                if self.in_use(old) or old in self._own:
                    new = self._free_id(slot)
                    if new is None:
                        self.stats.sysid_conflicts += 1
                        self._say("conflict", f"system {old} is in use: the gateway's "
                                  f"{type(node).__name__} keeps it (no free id)")
                    else:
                        node.sysid = new
                        log.info("MAVLink: system %d is in use (on %s): the gateway's %s "
                                 "takes system %d", old,
                                 self.seen_systems.get(old, "this gateway"),
                                 type(node).__name__, node.sysid)
                slot.claimed = True
                self._boxes.clear()
                self._own.setdefault(node.sysid, slot)
            return node.sysid

    def _free_id(self, slot: _Slot) -> int | None:
        start = slot.node.sysid
        return self.free_id(start + slot.step, slot.step, avoid=(start,))

    def _move(self, slot: _Slot, link: Link, f: Frame) -> None:
        """Another system uses a claimed node's id: the node moves to a free one (or, with
        none free, keeps it: counted)."""
        node = slot.node
        old = node.sysid
        self.seen_systems.setdefault(old, link.name)
        self.seen_at[old] = self._now
        if self._now < slot.retry_at:  # in conflict: counted, a new search once a second
            self.stats.sysid_conflicts += 1
            return
        new = self._free_id(slot)
        if new is None:
            slot.retry_at = self._now + CONFLICT_RETRY_S
            self.stats.sysid_conflicts += 1
            self._say("conflict", f"system {f.sysid} component {f.compid} on {link.name} uses "
                      f"the id of the gateway's {type(node).__name__}, which keeps it (no free "
                      "id)")
            return
        if self._own.get(old) is slot:
            del self._own[old]
        node.sysid = new
        self._own[new] = slot
        self.stats.id_changes += 1
        self._say("move", f"system {f.sysid} component {f.compid} on {link.name} uses the id "
                  f"of the gateway's {type(node).__name__}: it moves to system {new}")

    def _is_echo(self, slot: _Slot, f: Frame) -> bool:
        """A frame from a claimed node's system id: ours coming back, or an impostor?  (With
        signing on we sign everything: an unsigned frame is never ours.)"""
        if f.compid not in slot.compids or f.msgid not in slot.sent_ids:
            return False
        if self.verifier is not None and not f.signed:
            return False
        if f.msgid == MSG_HEARTBEAT and slot.heartbeat_type is not None:
            head = 10 if f.version == 2 else 6
            raw = f.raw
            return len(raw) > head + HEARTBEAT_TYPE_OFS and \
                raw[head + HEARTBEAT_TYPE_OFS] == slot.heartbeat_type
        return True

    # -- receiving ---------------------------------------------------------------------------

    def receive(self, link: Link, data: bytes) -> None:
        """Bytes read from ``link`` (one datagram, or any piece of a stream)."""
        with self.lock:
            self._now = time.monotonic()
            frames = (split_datagram(data, link.framer_stats) if link.datagram
                      else link.framer.feed(data))  # type: ignore[union-attr]
            for f in frames:
                self._route(link, f)

    def receive_many(self, link: Link, datagrams: list[bytes]) -> None:
        """Several datagrams read from ``link`` in one go (one lock round trip); what they
        route to links that write in batches (``start_batch``/``flush_batch``: UDP) is
        written once they are all routed, one write per link (in order)."""
        with self.lock:
            self._now = time.monotonic()
            stats = link.framer_stats
            route = self._route
            batching = self._batching if len(datagrams) > 1 else ()
            for lk in batching:
                lk.start_batch()  # type: ignore[attr-defined]
            try:
                if link.datagram and self.verifier is None and self.tap is None and self.forward:
                    if _speedups is not None and type(datagrams) is list:
                        self._route_datagrams_compiled(link, datagrams)
                    else:
                        self._route_datagrams(link, datagrams)
                else:
                    for data in datagrams:
                        for f in split_datagram(data, stats):
                            route(link, f)
            finally:
                for lk in batching:
                    lk.flush_batch()  # type: ignore[attr-defined]

    def _route_datagrams(self, link: Link, datagrams: list[bytes]) -> None:
        """:meth:`_route` of each datagram, with the common case inlined (the router's cost
        per datagram is mostly Python steps): a datagram that is one MAVLink 2 frame of a
        known id with a good CRC, broadcast (no target, or target system 0), from a source
        already seen on this link, not using a node's id, read by no node or only into a
        mailbox.  Its effects are :meth:`_route`'s, counted per batch; anything else (or any
        doubt) takes the general path.  Only without signing and a tap (the caller checks)."""
        stats = link.framer_stats
        info_of, crc = INFO, mcrf4xx
        own, seen_at, seen = self._own, self.seen_at, link.seen
        last_seq = link.last_seq
        dests_of = self._dests_for(link)
        now = self._now
        c = link.counters
        route = self._route
        # source → where it goes this batch: the lists of links that take a batch, the rest
        dests: dict[int, tuple[tuple[list[bytes], ...], tuple[Callable[[bytes], Any], ...]]] = {}
        boxes, boxes_of = self._boxes, self._mailboxes_of
        frames = nbytes = forwarded = mailboxed = 0
        for data in datagrams:
            n = len(data)
            if n > 12 and data[0] == 0xFD and not data[2] & 0xFE:
                plen = data[1]
                crc_at = 10 + plen
                msgid = data[7] | (data[8] << 8) | (data[9] << 16)
                info = info_of.get(msgid)
                sysid = data[5]
                key = (sysid << 8) | data[6]
                if (info is not None and crc_at + (15 if data[2] else 2) == n
                        and plen <= info[1] and key in seen and sysid in seen_at
                        and sysid not in own):
                    so = info[2]
                    tsys = -1 if so < 0 else (data[10 + so] if so < plen else 0)
                    if msgid in boxes:
                        box = boxes[msgid]
                    else:
                        box = boxes[msgid] = boxes_of(msgid)
                    if (tsys <= 0 and box is not None
                            and crc(data[1:crc_at] + info[0])
                            == data[crc_at] | (data[crc_at + 1] << 8)):
                        seq = data[4]
                        last = last_seq.get(key)
                        if last is not None and (seq - last - 1) & 0xFF:
                            c.seq_lost += (seq - last - 1) & 0xFF
                        last_seq[key] = seq
                        seen_at[sysid] = now
                        frames += 1
                        nbytes += n
                        if box:
                            kept = (data, link)  # a Frame once collected
                            for mailbox in box:
                                mailbox[(key << 24) | msgid] = kept
                            mailboxed += len(box)
                        entry = dests.get(key)
                        if entry is None:
                            entry = dests[key] = dests_of(key)
                        sinks, sends = entry
                        for sink in sinks:
                            sink.append(data)
                        forwarded += len(sinks)
                        for send in sends:
                            if send(data):
                                forwarded += 1
                        continue
            for f in split_datagram(data, stats):
                route(link, f)
        self._count_batch(link, frames, nbytes, forwarded, mailboxed)

    def _route_datagrams_compiled(self, link: Link, datagrams: list[bytes]) -> None:
        """:meth:`_route_datagrams` with its common case compiled (``_route_speedups``): the
        compiled loop routes datagrams until one needs the general path, which routes that
        one here, and goes on after it."""
        stats = link.framer_stats
        route, fast = self._route, _speedups.route
        seen, seen_at, own, last_seq = link.seen, self.seen_at, self._own, link.last_seq
        now = self._now
        boxes, boxes_of = self._boxes, self._mailboxes_of
        dests: dict[int, tuple[tuple[list[bytes], ...], tuple[Callable[[bytes], Any], ...]]]
        dests = {}
        dests_of = self._dests_for(link)
        total = len(datagrams)
        i = frames = nbytes = forwarded = mailboxed = lost = 0
        try:
            while i < total:
                stop, f_n, b_n, fw_n, mb_n, lost_n = fast(
                    datagrams, i, INFO, seen, seen_at, own, last_seq, now, boxes, boxes_of,
                    dests, dests_of, link)
                frames += f_n
                nbytes += b_n
                forwarded += fw_n
                mailboxed += mb_n
                lost += lost_n
                if stop < total:
                    for f in split_datagram(datagrams[stop], stats):
                        route(link, f)
                i = stop + 1
        finally:
            link.counters.seq_lost += lost
            self._count_batch(link, frames, nbytes, forwarded, mailboxed)

    def _count_batch(self, link: Link, frames: int, nbytes: int, forwarded: int,
                     mailboxed: int) -> None:
        """What the batch loops counted, added once per batch."""
        stats, c = link.framer_stats, link.counters
        stats.frames += frames
        stats.bytes_in += nbytes
        c.rx_frames += frames
        c.rx_bytes += nbytes
        self.stats.forwarded += forwarded
        self.stats.mailboxed += mailboxed

    def _dests_for(self, link: Link) -> Callable[[int], Any]:
        """:meth:`_destinations` of a broadcast read on ``link``, by source (none: a link
        no longer routed)."""
        return self._dests_of.get(link) or functools.partial(self._destinations, ())

    @staticmethod
    def _destinations(others: tuple[Link, ...], key: int
                      ) -> tuple[tuple[list[bytes], ...], tuple[Callable[[bytes], Any], ...]]:
        """Where a broadcast of source ``key`` goes: the batches of the links that take one
        (lists to append it to), and the ``send`` of the others."""
        sinks: list[list[bytes]] = []
        sends: list[Callable[[bytes], Any]] = []
        for o in others:
            if key in o.seen:
                continue  # that is where it came from, by another way round
            sink = o.batch_sink()
            if sink is not None:
                sinks.append(sink)
            else:
                sends.append(o.send)
        return tuple(sinks), tuple(sends)

    def _mailboxes_of(self, msgid: int) -> tuple[dict[int, Any], ...] | None:
        """The mailboxes of the nodes that keep a broadcast ``msgid`` (those on the air), or
        None when one decodes it at once (the general path)."""
        readers = self._wants.get(msgid, ())
        mine = tuple(s for s in readers if s.claimed)
        if any(msgid in s.consumed for s in mine):
            return None
        return tuple(s.mailbox for s in mine)

    def _route(self, link: Link, f: Frame) -> None:
        raw, msgid, sysid, compid, seq, tsys, tcomp, _, _ = f  # one unpack: the hot path
        c = link.counters
        c.rx_frames += 1
        c.rx_bytes += len(raw)
        key = (sysid << 8) | compid
        own = self._own
        verifier = self.verifier
        verdict: Verdict | None = None  # checked at most once per frame, when it matters
        if sysid in own:
            slot = own[sysid]
            if self._is_echo(slot, f):
                self.stats.own_id_seen += 1  # our own frame, back round a loop: drop
                return
            if verifier is not None:
                verdict = verifier.check(f)
                if verdict is not Verdict.OK:  # not evidence: dropped, never forwarded
                    self.stats.impostor_frames += 1
                    c.rejected_signing += 1
                    self._say("impostor", f"system {sysid} component {compid} on "
                              f"{link.name}, {verdict.value}")
                    return
            self._move(slot, link, f)
        tap = self.tap
        if tap is not None:
            tap(raw)
        last_seq = link.last_seq
        last = last_seq.get(key)
        if last is not None:
            gap = (seq - last - 1) & 0xFF
            if gap:
                c.seq_lost += gap
        last_seq[key] = seq
        seen_at = self.seen_at
        if sysid in seen_at:
            seen_at[sysid] = self._now
        elif verifier is None or (verdict := verifier.check(f)) is Verdict.OK:
            seen_at[sysid] = self._now
            self.seen_systems.setdefault(sysid, link.name)
        else:
            self.stats.unverified_systems += 1
        if key not in link.seen:
            link.seen.add(key)
            link.seen_sys.add(sysid)
            self._say("new", f"system {sysid} component {compid} on {link.name}")
        readers = self._wants.get(msgid)
        if readers is not None:
            mine = ([s for s in readers if s.claimed] if tsys <= 0  # broadcast: for all
                    else [s for s in readers if s.claimed and s.wants(tsys, tcomp)])
            if mine:  # (not yet on the air: not ours)
                if verifier is not None and verdict is None:
                    verdict = verifier.check(f)
                if verdict is not None and not verdict.accepted:
                    c.rejected_signing += 1
                else:
                    self._hand_over(mine, link, f, key)
        if not self.forward:
            return
        others = self._others.get(link, ())
        if tsys <= 0:
            targets: Iterable[Link] = others
        elif tcomp <= 0:
            targets = [o for o in others if tsys in o.seen_sys]
        else:
            tkey = (tsys << 8) | tcomp
            targets = [o for o in others if tkey in o.seen]
        if not targets:
            if tsys > 0 and tsys not in own:
                self.stats.unroutable += 1
            return
        n = 0
        for o in targets:
            if key in o.seen:
                continue  # that is where it came from, by another way round
            if o.send(raw):
                n += 1
        self.stats.forwarded += n

    def _hand_over(self, slots: list[_Slot], link: Link, f: Frame, key: int) -> None:
        """A verified frame for our nodes: decoded once for those that consume it at once,
        kept in the mailbox of those that read it later."""
        msg: Any = None
        for slot in slots:
            if f.msgid in slot.consumed:
                if msg is None:
                    msg = self._decode(link, f)
                    if msg is None:
                        return
                self._handle(slot, link, f, msg)
            else:
                slot.mailbox[(key << 24) | f.msgid] = (f, link)
                self.stats.mailboxed += 1

    def _decode(self, link: Link, f: Frame) -> Any:
        try:
            return self._decoder.decode(bytearray(f.raw))
        except Exception:  # MAVError, struct.error: counted, the frame was routed anyway
            link.counters.decode_errors += 1
            return None

    def _handle(self, slot: _Slot, link: Link, f: Frame, msg: Any) -> None:
        self.stats.delivered += 1
        try:
            replies = slot.node.handle(msg, f.sysid, f.compid)
        except Exception:
            self.stats.node_errors += 1
            if self.stats.node_errors <= 3:
                log.exception("%s: handling %s failed", link.name, msg.get_type())
            return
        for r in replies:
            self._send(slot, link, r)

    def collect(self, node: LocalNode) -> int:
        """Decode the frames kept for ``node`` (the latest of each source and id) and hand
        them to it, oldest first; returns how many."""
        with self.lock:
            slot = self._by_node[id(node)]
            mailbox = slot.mailbox
            if not mailbox:
                return 0
            box = list(mailbox.values())
            mailbox.clear()  # (the same dict: the batch paths hold it)
            for kept, link in box:  # verified when kept
                f = kept if isinstance(kept, Frame) else frame_v2(kept)
                msg = self._decode(link, f)
                if msg is not None:
                    self._handle(slot, link, f, msg)
            return len(box)

    # -- sending our own messages ------------------------------------------------------------

    def _encoder(self, link: Link, sysid: int, compid: int) -> Any:
        key = (sysid << 8) | compid
        m = link.encoders.get(key)
        if m is None:
            m = mav.MAVLink(None, sysid, compid)
            if self.signing_key is not None:
                signing.setup_outgoing(m, self.signing_key, self._next_link_id)
                self._next_link_id = (self._next_link_id + 1) & 0xFF
            link.encoders[key] = m
        return m

    def _pack(self, slot: _Slot, link: Link, msg: Any) -> bytes:
        node = slot.node
        compid = slot.component_of(msg) if slot.component_of is not None else node.compid
        if compid not in slot.compids:
            slot.compids.add(compid)
        m = self._encoder(link, node.sysid, compid)
        if link.signing:
            signing.refresh_timestamp(m)
        buf: bytes = msg.pack(m)
        m.seq = (m.seq + 1) & 0xFF
        return buf

    def _send(self, slot: _Slot, link: Link, msg: Any) -> bool:
        if not link.up:
            link.counters.tx_not_up += 1
            return False
        try:
            buf = self._pack(slot, link, msg)
        except Exception:
            self._encode_failed(msg)
            return False
        slot.sent_ids.add(msg.get_msgId())
        ok = link.send(buf)
        if ok:
            self.stats.sent_own += 1
            tap = self.tap
            if tap is not None:
                tap(buf)
        return ok

    def _slot(self, node: LocalNode | None) -> _Slot:
        if node is None:
            return self._slots[0]
        return self._by_node[id(node)]

    def send_on(self, link: Link, msg: Any, node: LocalNode | None = None) -> bool:
        """Send one of ``node``'s messages (default: the first node's) on ``link``."""
        with self.lock:
            slot = self._slot(node)
            if not slot.claimed:
                self.claim(slot.node)
            return self._send(slot, link, msg)

    def broadcast(self, msgs: Iterable[Any], node: LocalNode | None = None) -> None:
        """Send ``node``'s messages (default: the first node's) on every link of its groups
        that is up."""
        with self.lock:
            slot = self._slot(node)
            if not slot.claimed:
                self.claim(slot.node)
            groups = slot.groups
            links = [lk for lk in self.links if groups is None or lk.group in groups]
            tap = self.tap
            for msg in msgs:
                mid = msg.get_msgId()
                logged = tap is None  # each message once in a telemetry log: as first sent
                targets = links
                if mid == SYS_STATUS and msg.voltage_battery == NO_VOLTAGE:
                    targets = [lk for lk in links if shows_no_battery(lk)]
                for link in targets:
                    if not link.up:
                        link.counters.tx_not_up += 1
                        continue
                    try:
                        buf = self._pack(slot, link, msg)
                    except Exception:  # a value that does not fit its field: skip, counted
                        self._encode_failed(msg)
                        break
                    slot.sent_ids.add(mid)
                    if link.send(buf):
                        self.stats.sent_own += 1
                        if not logged:
                            logged = True
                            tap(buf)  # type: ignore[misc]

    def _encode_failed(self, msg: Any) -> None:
        self.stats.encode_errors += 1
        if self.stats.encode_errors <= 3:
            log.exception("cannot pack %s", msg.get_type())
