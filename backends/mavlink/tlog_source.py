"""Telemetry logs in: a MAVLink ``.tlog`` replayed as the vehicles it recorded
(``--source tlog:FILE``, ``[[sources]] type = "tlog"``).

A ``.tlog`` (MAVProxy's, QGroundControl's, mavlink-router's, this gateway's ``run --tlog`` and
``export --format tlog``) is a sequence of records: the 8-byte big-endian UNIX time in
microseconds, then one MAVLink frame (v1 or v2) as it went on the wire.  Nothing gives a
record's length but its frame's header, so :func:`records` reads each frame's length from its
header and checks its CRC, like the router's framer (:mod:`.frames`); a corrupt stretch is
skipped byte by byte until a whole record with a good frame (and a time near the last good
one) puts it back in step, counted; a record cut short at the end (a log whose writer was
killed) is counted and dropped.

The replay is the live MAVLink source with the log as its vehicle link: every frame enters
the gateway's MAVLink router (:mod:`.hub`) at its recorded time (scaled by ``speed``) on a
link of the vehicle side, so it is routed as it arrived to the MAVLink backend's ground
stations (a ground station sees the recorded frames at the recorded rate, not a translation
of them), and the source's :class:`~.source.VehicleListener` turns it into gateway messages
(VehicleState, Position, Battery, SmUpdate/Status from AURORA_* …) exactly as it does live:
one gateway vehicle per system heard, ``<vehicle>-<system id>``.  The listener's rate limits
count in flight time, so a fast replay gives the same messages as a real-time one."""

from __future__ import annotations

import logging
import struct
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from backends.mavlink.dialect import MESSAGES
from backends.mavlink.frames import (
    HEADER_V1,
    HEADER_V2,
    IFLAG_SIGNED,
    SIGNATURE_LEN,
    STX_V1,
    STX_V2,
    FramerStats,
    split_datagram,
)
from backends.mavlink.hub import VEHICLE, MavlinkHub
from backends.mavlink.options import TlogSourceOptions
from backends.mavlink.router import Link, Router
from backends.mavlink.source import VehicleListener
from gateway import vehicles
from gateway.backend import GatewayContext
from gateway.counters import Counters
from gateway.io.ioloop import IoLoop
from gateway.pacing import Pacer
from gateway.sources import Sink, Source

log = logging.getLogger(__name__)

STAMP = struct.Struct(">Q")
#: A first record's time must fall in these years' microseconds (UNIX time) for the file to
#: be taken as a telemetry log: 2000 … 2200.
PLAUSIBLE_US = (946_684_800_000_000, 7_258_118_400_000_000)
#: While resynchronising, a record's time must be this close to the last good one's.
RESYNC_WINDOW_US = 86_400_000_000


class TlogError(ValueError):
    """A file that is not a telemetry log (the ``path`` key's one line)."""


@dataclass
class TlogReadStats(Counters):
    records: int = 0
    corrupt_skips: int = 0  # corrupt stretches skipped (each resynchronised once)
    bytes_skipped: int = 0
    torn_tail_bytes: int = 0  # a last record cut short
    unknown_ids: int = 0  # frames of ids the dialect does not know (passed unchecked)


def _frame_len(data: bytes, i: int) -> int | None:
    """The length of the frame starting at ``data[i]`` from its header; 0 when it cannot be
    a frame, None when the header itself runs past the end."""
    n = len(data)
    if i + 3 > n:
        return None
    stx = data[i]
    if stx == STX_V2:
        flags = data[i + 2]
        if flags & ~IFLAG_SIGNED:
            return 0
        return HEADER_V2 + data[i + 1] + 2 + (SIGNATURE_LEN if flags else 0)
    if stx == STX_V1:
        return HEADER_V1 + data[i + 1] + 2
    return 0


def _good_frame(frame: bytes, synced: bool, stats: TlogReadStats) -> bool:
    """One whole frame with a good CRC (an unknown id, whose CRC cannot be checked, only
    while in step: after a corrupt stretch it could be anything)."""
    if len(frame) < HEADER_V1 + 2:
        return False
    msgid = (frame[5] if frame[0] == STX_V1
             else frame[7] | (frame[8] << 8) | (frame[9] << 16))
    if msgid not in MESSAGES:
        if synced:
            stats.unknown_ids += 1
        return synced
    out = split_datagram(frame, FramerStats())
    return len(out) == 1 and len(out[0].raw) == len(frame)


def records(data: bytes, stats: TlogReadStats) -> Iterator[tuple[int, bytes]]:
    """``(UNIX time in µs, frame)`` for every good record of a telemetry log's bytes, corrupt
    stretches and a torn last record counted in ``stats`` and skipped."""
    n = len(data)
    pos = 0
    synced = True
    last_us: int | None = None
    while pos < n:
        start = pos + STAMP.size
        flen = _frame_len(data, start)
        if flen is None or (flen and start + flen > n):
            if synced:  # the log ends inside this record
                stats.torn_tail_bytes += n - pos
                return
            pos += 1  # (garbage near the end, while hunting)
            stats.bytes_skipped += 1
            continue
        if flen:
            (t_us,) = STAMP.unpack_from(data, pos)
            frame = data[start:start + flen]
            near = synced or last_us is None or abs(t_us - last_us) <= RESYNC_WINDOW_US
            if near and _good_frame(frame, synced, stats):
                synced = True
                last_us = t_us
                stats.records += 1
                pos = start + flen
                yield t_us, frame
                continue
        if synced:
            synced = False
            stats.corrupt_skips += 1
        pos += 1
        stats.bytes_skipped += 1


def check_file(path: str | Path) -> None:
    """TlogError unless ``path`` is a readable telemetry log (its first record a MAVLink
    frame with a plausible UNIX time); an empty log is one (it replays nothing).  The source's
    ``path`` key checks it before anything starts."""
    p = Path(path)
    if not p.is_file():
        raise TlogError(f"no telemetry log at {path}")
    try:
        with p.open("rb") as f:
            head = f.read(STAMP.size + HEADER_V2 + 255 + 2 + SIGNATURE_LEN)
    except OSError as exc:
        raise TlogError(f"cannot read {path}: {exc.strerror or exc}") from None
    if not head:
        return
    first = next(records(head, TlogReadStats()), None) if len(head) > STAMP.size else None
    if (first is None or not PLAUSIBLE_US[0] <= first[0] < PLAUSIBLE_US[1]
            or not head.startswith(STAMP.pack(first[0]))):
        raise TlogError(f"{path} is not a MAVLink telemetry log (.tlog: each frame after "
                        "its 8-byte big-endian UNIX time in microseconds)")


class TlogLink(Link):
    """The log as the vehicle's link on the router: frames come in from the file; what the
    gateway would say to the vehicle goes nowhere (a log does not listen)."""

    datagram = True  # one record, one frame

    def send(self, data: bytes) -> bool:
        self.counters.tx_dropped += 1
        return False


class TlogSource(Source):
    """A telemetry log replayed as MAVLink vehicles (see the module docstring); ``done`` at
    the end of the file (or, with ``loop``, when stopped)."""

    NAME = "tlog"
    OPTIONS = TlogSourceOptions
    YIELDS_SYSTEMS = True  # one vehicle per system heard, <vehicle>-<system id>

    @staticmethod
    def default_name(options: dict[str, Any]) -> str:
        return f"tlog:{Path(options['path']).name}"

    @staticmethod
    def default_vehicle(options: dict[str, Any]) -> str:
        """The stem of the replayed vehicles' names: the file's (``flight.tlog`` → vehicles
        ``flight-1`` …)."""
        stem = Path(options["path"]).name.partition(".")[0]
        return vehicles.derive_name(stem, fallback="tlog")

    @classmethod
    def url_options(cls, rest: str | None) -> dict[str, Any]:
        """``tlog:FILE``."""
        if not rest:
            raise ValueError("tlog: needs a file, e.g. tlog:flight.tlog")
        return {"path": rest}

    def __init__(self, options: TlogSourceOptions, name: str | None = None) -> None:
        super().__init__(name or f"tlog:{Path(options.path).name}")
        self.path = Path(options.path)  # checked by its option (check_file)
        self.speed = options.speed
        self.loop = options.loop
        self.rate_hz = options.rate_hz
        self.read_stats = TlogReadStats()
        self._flight_s = 0.0  # the replayed frame's time: the listener's clock
        self._next_collect = 0.0
        self._pending: deque[Any] = deque()
        self.listener = VehicleListener(self._pending.append, self.name, rate_hz=self.rate_hz,
                                        request_streams=False, clock=lambda: self._flight_s)
        self.link = TlogLink(self.name, VEHICLE)
        self.hub: MavlinkHub | None = None
        self.router: Router | None = None
        self.hub_loop: IoLoop | None = None
        self._pacer: Pacer[bytes] | None = None
        self.emitted = 0
        self.frames = 0

    def attach(self, context: GatewayContext) -> None:
        super().attach(context)
        hub = MavlinkHub.of(context)
        hub.expect(VEHICLE)  # before the backend's first tick: it shares the router
        hub.stems.add(self.vehicle)  # one vehicle per system heard: none of its own

    # -- life cycle: the replay runs on the hub's loop, where the router's links live ---------

    def start(self, sink: Sink) -> None:
        if self._sink is not None:
            return
        self._sink = sink
        hub = MavlinkHub.of(self.context)
        self.listener.stem = self.vehicle  # (named by the gateway after construction)
        hub.join(self.listener, VEHICLE, step=-1)
        self.hub, self.router, self.hub_loop = hub, hub.router, hub.loop
        hub.router.add_link(self.link)
        hub.router.claim(self.listener)
        hub.loop.run_blocking(self.path.read_bytes, self._loaded, name=f"read {self.path.name}")

    def _loaded(self, data: bytes | None, error: BaseException | None) -> None:
        if self.stop_requested or self.hub_loop is None:
            return
        if error is not None or data is None:
            log.error("source %s: cannot read %s: %s", self.name, self.path, error)
            self.finish()
            return
        log.info("source %s: replaying %s (%d bytes) at %s", self.name, self.path, len(data),
                 f"{self.speed:g}x" if self.speed else "full speed")
        self._pacer = Pacer(self.hub_loop, self._passes(data), self.speed, self._deliver,
                            on_end=self._ended)
        self._pacer.start()

    def _passes(self, data: bytes) -> Iterator[tuple[float, bytes]]:
        """The log's frames with their times in seconds, once or (``loop``) again and again,
        each pass's times carried on from the last one's (the pacing and the listener's rate
        limits see one flight time running forwards)."""
        shift = 0.0
        while not self.stop_requested:
            self.read_stats = stats = TlogReadStats()
            first: float | None = None
            t = 0.0
            for t_us, frame in records(data, stats):
                t = t_us / 1e6
                if first is None:
                    first = t
                    if self.frames:
                        shift = self._flight_s - t  # this pass follows on at once
                yield t + shift, frame
            if stats.corrupt_skips or stats.torn_tail_bytes:
                log.warning("source %s: %s: skipped %d corrupt stretch(es) (%d bytes) and a "
                            "torn last record of %d bytes", self.name, self.path,
                            stats.corrupt_skips, stats.bytes_skipped, stats.torn_tail_bytes)
            if not self.loop or first is None:
                return
            self._collect()  # the last of each, before the next pass replaces it

    def _deliver(self, t: float, frame: bytes) -> None:  # the hub's loop
        router = self.router
        if router is None:
            return
        self._flight_s = t
        self.frames += 1
        router.receive(self.link, frame)  # routed to the ground stations; the listener reads
        if t >= self._next_collect:  # the latest telemetry, at rate_hz of flight time
            self._next_collect = t + 1.0 / self.rate_hz
            router.collect(self.listener)
        self._emit_pending()

    def _emit_pending(self) -> None:  # outside the router's lock
        pending = self._pending
        while pending:
            self.emit(pending.popleft())
            self.emitted += 1

    def _collect(self) -> None:  # the hub's loop
        router = self.router
        if router is not None:
            router.collect(self.listener)
            self._emit_pending()

    def _ended(self) -> None:
        self._collect()  # the last of each
        log.info("source %s: end of %s: %d frames", self.name, self.path, self.frames)
        self.finish()

    def halt(self) -> None:
        """(request_stop) Cancel the pacing on the hub's loop; :meth:`stop` leaves the hub."""
        loop = self.hub_loop
        pacer = self._pacer
        if pacer is not None and loop is not None and loop.alive:
            loop.call_soon(pacer.cancel)
        self.finish()

    def stop(self, timeout: float = 1.0) -> None:
        self.request_stop()
        if self._loop is None:  # started without the sources' loop: halt here
            self._halt()
        hub, self.hub = self.hub, None
        if hub is not None:
            pacer = self._pacer
            if pacer is not None:
                pacer.cancelled = True  # (its next step on the loop does nothing)
            hub.router.remove_link(self.link)
            hub.leave(self.listener, (), timeout)
            self.router = None
        self.finish()

    def stats(self) -> dict[str, Any]:
        st = self.read_stats
        systems = {str(s.sysid): s.vehicle for s in list(self.listener.systems.values())}
        return {"frames": self.frames, "emitted": self.emitted, "records": st.records,
                "corrupt_skips": st.corrupt_skips, "bytes_skipped": st.bytes_skipped,
                "torn_tail_bytes": st.torn_tail_bytes, "unknown_ids": st.unknown_ids,
                # each corrupt stretch starts at a record failing its frame check: the stop
                # report's "crc errors" count them
                "crc_failures": st.corrupt_skips,
                "systems": systems, "systems_ignored": self.listener.systems_ignored}
