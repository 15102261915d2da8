"""MAVLink routing between links, as mavlink-router does it, plus one local node.

Every frame arriving on a link is framed (not decoded, see :mod:`.frames`), its source
(system, component) is learned for that link, and it is forwarded as the exact bytes that
arrived:

* a message without a target, or with target system 0 (broadcast), goes to every other link;
* a targeted message goes only to the links on which its target system (and component, when
  not 0) has been seen; a target nobody has been seen as is not forwarded (counted);
* never back to the link it came from, nor to a link on which its own source was seen
  (that is where it came from by another path: forwarding it would loop);
* unknown message ids are forwarded too (unvalidated, like mavlink-router).

The local node (the rocket as a vehicle, or the gateway as a ground station for the MAVLink
source) gets the frames it consumes — only those are decoded — when they are addressed to it
or broadcast; with signing on, those frames are verified first (see :mod:`.signing`).  Its own
messages are packed per link, so each link has its own sequence numbers (and signing
stream).

All state is guarded by :attr:`Router.lock`; links call :meth:`Router.receive` from whatever
thread reads them, and every ``Link.send`` is non-blocking.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

from backends.mavlink import signing
from backends.mavlink.dialect import mav
from backends.mavlink.frames import Frame, FramerStats, StreamFramer, split_datagram
from gateway.counters import Counters

log = logging.getLogger(__name__)


class LocalNode(Protocol):
    """What the router needs of the node it serves."""

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
    and :attr:`up`."""

    datagram = False

    def __init__(self, name: str) -> None:
        self.name = name
        self.counters = LinkCounters()
        self.framer: StreamFramer | None = None if self.datagram else StreamFramer()
        self.framer_stats: FramerStats = (self.framer.stats if self.framer is not None
                                          else FramerStats())
        self.seen: set[int] = set()  # (sysid << 8) | compid of every source seen here
        self.seen_sys: set[int] = set()
        self.last_seq: dict[int, int] = {}
        self.mav: Any = None  # per-link pymavlink encoder, set by Router.add_link
        self.signing = False
        self.router: Router | None = None

    @property
    def up(self) -> bool:
        return True

    def send(self, data: bytes) -> bool:
        raise NotImplementedError

    def encode(self, msg: Any) -> bytes:
        """Pack one of our own messages with this link's sequence number (and signature)."""
        m = self.mav
        if self.signing:
            signing.refresh_timestamp(m)
        buf = msg.pack(m)
        m.seq = (m.seq + 1) & 0xFF
        return buf

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
    delivered: int = 0  # frames handed to the local node
    own_id_seen: int = 0  # frames claiming the local node's own (sysid, compid)
    node_errors: int = 0  # the local node raised on a request (a bug; logged)
    encode_errors: int = 0  # one of our messages could not be packed (a bug; logged)
    sent_own: int = 0  # local messages sent (counted once per link)
    links_added: int = 0
    links_removed: int = 0
    extra: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, int]:
        d = super().as_dict()
        d.update(self.extra)
        return d


class Router:
    """Routes frames between links and serves one local node; see the module docstring."""

    def __init__(self, node: LocalNode | None = None, *, forward: bool = True,
                 signing_key: bytes | None = None) -> None:
        self.lock = threading.RLock()
        self.node = node
        self.forward = forward
        self.links: list[Link] = []
        self._others: dict[Link, tuple[Link, ...]] = {}
        self.stats = RouterStats()
        self.signing_key = signing_key
        self.verifier = signing.SignatureVerifier(signing_key) if signing_key else None
        self._decoder = mav.MAVLink(None)  # decodes consumed frames; verification is ours
        self._next_link_id = 0
        self._own_key = ((node.sysid << 8) | node.compid) if node is not None else -1

    # -- links -------------------------------------------------------------------------------

    def add_link(self, link: Link) -> None:
        with self.lock:
            node = self.node
            link.mav = mav.MAVLink(None, node.sysid if node else 255, node.compid if node else 0)
            if self.signing_key is not None:
                signing.setup_outgoing(link.mav, self.signing_key, self._next_link_id)
                link.signing = True
            self._next_link_id = (self._next_link_id + 1) & 0xFF
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

    # -- receiving ---------------------------------------------------------------------------

    def receive(self, link: Link, data: bytes) -> None:
        """Bytes read from ``link`` (one datagram, or any piece of a stream)."""
        with self.lock:
            frames = (split_datagram(data, link.framer_stats) if link.datagram
                      else link.framer.feed(data))  # type: ignore[union-attr]
            for f in frames:
                self._route(link, f)

    def receive_many(self, link: Link, datagrams: Iterable[bytes]) -> None:
        """Several datagrams read from ``link`` in one go (one lock round trip)."""
        with self.lock:
            stats = link.framer_stats
            route = self._route
            for data in datagrams:
                for f in split_datagram(data, stats):
                    route(link, f)

    def _route(self, link: Link, f: Frame) -> None:
        raw, msgid, sysid, compid, seq, tsys, tcomp, _, _ = f  # one unpack: the hot path
        c = link.counters
        c.rx_frames += 1
        c.rx_bytes += len(raw)
        key = (sysid << 8) | compid
        if key == self._own_key:
            self.stats.own_id_seen += 1  # our own echo, or a system using our id: drop
            return
        last_seq = link.last_seq
        last = last_seq.get(key)
        if last is not None:
            gap = (seq - last - 1) & 0xFF
            if gap:
                c.seq_lost += gap
        last_seq[key] = seq
        if key not in link.seen:
            link.seen.add(key)
            link.seen_sys.add(sysid)
            log.info("%s: system %d component %d seen", link.name, sysid, compid)
        node = self.node
        if node is not None and msgid in node.consumed and (
                tsys <= 0 or (tsys == node.sysid and tcomp in (-1, 0, node.compid))):
            self._deliver(link, f)
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
            if tsys > 0 and tsys != (node.sysid if node is not None else -1):
                self.stats.unroutable += 1
            return
        n = 0
        for o in targets:
            if key in o.seen:
                continue  # that is where it came from, by another way round
            if o.send(raw):
                n += 1
        self.stats.forwarded += n

    def _deliver(self, link: Link, f: Frame) -> None:
        if self.verifier is not None and not self.verifier.check(f).accepted:
            link.counters.rejected_signing += 1
            return
        try:
            msg = self._decoder.decode(bytearray(f.raw))
        except Exception:  # MAVError, struct.error: counted, the frame was routed anyway
            link.counters.decode_errors += 1
            return
        self.stats.delivered += 1
        try:
            replies = self.node.handle(msg, f.sysid, f.compid)  # type: ignore[union-attr]
        except Exception:
            self.stats.node_errors += 1
            if self.stats.node_errors <= 3:
                log.exception("%s: handling %s failed", link.name, msg.get_type())
            return
        for r in replies:
            self.send_on(link, r)

    # -- sending our own messages ------------------------------------------------------------

    def send_on(self, link: Link, msg: Any) -> bool:
        with self.lock:
            if not link.up:
                link.counters.tx_not_up += 1
                return False
            try:
                buf = link.encode(msg)
            except Exception:
                self._encode_failed(msg)
                return False
            ok = link.send(buf)
            if ok:
                self.stats.sent_own += 1
            return ok

    def broadcast(self, msgs: Iterable[Any]) -> None:
        """Send our own messages on every link that is up."""
        with self.lock:
            for msg in msgs:
                for link in self.links:
                    if not link.up:
                        link.counters.tx_not_up += 1
                        continue
                    try:
                        buf = link.encode(msg)
                    except Exception:  # a value that does not fit its field: skip, counted
                        self._encode_failed(msg)
                        break
                    if link.send(buf):
                        self.stats.sent_own += 1

    def _encode_failed(self, msg: Any) -> None:
        self.stats.encode_errors += 1
        if self.stats.encode_errors <= 3:
            log.exception("cannot pack %s", msg.get_type())
