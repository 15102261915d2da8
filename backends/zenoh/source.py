"""Zenoh source: another gateway's publications, fed into this gateway's dispatcher.

A rocket-side gateway publishes; a ground-side one subscribes to
``<prefix>/<follow>/raw/**`` (the untouched wire frames, decoded here with the same codec
as a serial port) — or, with ``keys = "json"``, to the JSON documents and to the gateways'
counters (``<prefix>/@gateways/*/stats``, for a monitor) — and drives its local tools
(QGroundControl, a radio) as if the rocket were plugged in.

One vehicle per remote vehicle: the vehicle chunk of the key a sample arrived on becomes the
message's ``vehicle`` (gateway A's ``alpha`` is ``alpha`` here too); ``follow`` (``*``, the
default: every vehicle) chooses which.  Each remote vehicle has its own wire decoder; at most
:data:`~backends.zenoh.keys.MAX_VEHICLES` are followed (samples of any further one are
counted, ``dropped_vehicle_limit``), and a chunk that is not a vehicle name
(:func:`gateway.vehicles.check_name`) is ignored (``bad_vehicle_names``).

Loop prevention, both ways:

* every message emitted carries ``via = "zenoh:<publishing gateway>"``, so a Zenoh backend
  of this gateway never publishes it again;
* publications whose attachment names a Zenoh backend of this gateway (the ids in its
  :class:`~gateway.backend.GatewayContext`: its own publications coming back) are ignored
  (``ignored_own``).  Nothing is shared between two gateways of one process.

The URL form (``--source``) is ``zenoh:[VEHICLE@][ENDPOINT[,ENDPOINT...]]``::

    zenoh:                                  every vehicle, via tcp/127.0.0.1:7450
    zenoh:tcp/10.0.0.5:7447                 every vehicle, via that router or gateway
    zenoh:alpha@tcp/10.0.0.5:7447           only alpha

The session is opened (and retried with backoff, and closed) on the source's I/O loop's
blocking calls; samples are handed from Zenoh's callback thread to the loop through a bounded
queue (``queue_depth``; overflow counted as ``dropped_queue_full``); gaps in the publishers'
sequence numbers are counted as ``lost``.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Any

from backends.zenoh import encoding as enc
from backends.zenoh.keys import (
    DEFAULT_ENDPOINT,
    JSON_KINDS,
    MAX_VEHICLES,
    RAW,
    SOURCES_SERVICE,
    VIA_ZENOH,
    SeqTracker,
    check_prefix,
    parse_attachment,
    parse_key,
    parse_stats_key,
    stats_key_expr,
)
from backends.zenoh.options import KEY_SETS, ZenohSourceOptions, check_follow
from backends.zenoh.session import SessionOptions, check_endpoints, zerror_text
from gateway.backend import GatewayContext
from gateway.config import ConfigError
from gateway.io.backoff import Backoff
from gateway.io.ioloop import Timer
from gateway.sources import Source
from gateway.vehicles import check_name
from gateway.wire import Decoder, DecoderStats

log = logging.getLogger(__name__)

URL_SCHEME = "zenoh"
DRAIN_BATCH = 256  # samples handled per turn of the loop
LOGGED_VEHICLES = 8  # new remote vehicles logged one by one; beyond, one line


def parse_url(url: str) -> dict[str, Any]:
    """Options from ``zenoh:[VEHICLE@][ENDPOINT[,ENDPOINT...]]``; ValueError if malformed."""
    scheme, colon, rest = url.partition(":")
    if scheme != URL_SCHEME:
        raise ValueError(f"{url!r}: expected zenoh:[VEHICLE@][ENDPOINT,...]")
    opts: dict[str, Any] = {}
    if not colon or not rest:
        return opts
    head, at, tail = rest.partition("@")
    if at and "/" not in head:
        opts["follow"] = check_follow(head)
        rest = tail
    if rest:
        try:
            opts["connect"] = check_endpoints(rest.split(","), "endpoint")
        except ConfigError as exc:
            raise ValueError(f"{url!r}: {exc}") from None
    return opts


def check_url(url: str) -> None:
    """The ``url`` key: empty, or a :func:`parse_url` form (its endpoints checked as Zenoh
    locators); ValueError naming the mistake."""
    if url:
        parse_url(url)


class ZenohSource(Source):
    """Subscribes to another gateway's publications and emits them as messages."""

    NAME = "zenoh"
    OPTIONS = ZenohSourceOptions
    YIELDS_SYSTEMS = True  # the publishing gateway's vehicles, under their names

    @staticmethod
    def default_name(options: dict[str, Any]) -> str:
        return options.get("url") or URL_SCHEME

    @classmethod
    def url_options(cls, rest: str | None) -> dict[str, Any]:
        """``--source zenoh[:VEHICLE@ENDPOINT,…]``: the url key keeps the whole text."""
        return {} if rest is None else {"url": f"{URL_SCHEME}:{rest}"}

    def __init__(self, options: ZenohSourceOptions | None = None,
                 name: str | None = None) -> None:
        options = options or ZenohSourceOptions()
        super().__init__(name or options.url or URL_SCHEME)
        prefix, follow, keys = options.prefix, options.follow, options.keys
        session: dict[str, Any] = {}
        if options.url:
            try:
                from_url = parse_url(options.url)
            except ValueError as exc:
                raise ConfigError(f"url: {exc}") from None
            follow = from_url.get("follow", follow)
            if "connect" in from_url:
                session["connect"] = from_url["connect"]
        try:
            self.prefix = check_prefix(prefix)
        except ValueError as exc:
            raise ConfigError(f"prefix: {exc}") from None
        try:
            self.follow = check_follow(follow)
        except ValueError as exc:
            raise ConfigError(f"follow: {exc}") from None
        if keys not in KEY_SETS:
            raise ConfigError(f"keys: expected 'raw' or 'json', got {keys!r}")
        connect = session.get("connect", options.connect)
        if connect is None and not options.config_file:
            session["connect"] = [DEFAULT_ENDPOINT]
        self.session_options = SessionOptions(options, default_listen=[], **session)
        self.keys = keys
        self.queue_depth = options.queue_depth
        self.key_expr = (f"{self.prefix}/{self.follow}/{RAW}/**" if keys == "raw"
                         else f"{self.prefix}/{self.follow}/*")
        #: what else it subscribes to: with the documents, the gateways' counters
        self.stats_key_expr = stats_key_expr(self.prefix) if keys == "json" else None
        #: one wire decoder per remote vehicle (the loop's thread), their counters summed in
        #: one :class:`DecoderStats`
        self.decoders: dict[str, Decoder] = {}
        self.decoder_stats = DecoderStats()
        self._bad_names: set[str] = set()
        self.tracker = SeqTracker()
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._backoff = Backoff(0.1, max(0.1, self.session_options.reconnect_max_s))
        self.ready = threading.Event()
        self._session: Any = None
        self._opening = False
        self._retry: Timer | None = None
        self._drain_scheduled = False
        self.received = 0
        self.emitted = 0
        self.ignored_own = 0
        self.ignored_other = 0
        self.bad_payloads = 0
        self.bad_vehicle_names = 0
        self.dropped_vehicle_limit = 0
        self.dropped_queue_full = 0
        self.session_opens = 0
        self.open_failures = 0

    def attach(self, context: GatewayContext) -> None:
        """Say in the gateway's context that this source's vehicles are another gateway's
        (:data:`~backends.zenoh.keys.SOURCES_SERVICE`): a Zenoh backend declares no presence
        for this source's own vehicle name."""
        super().attach(context)
        context.services.setdefault(SOURCES_SERVICE, set()).add(self.name)

    # -- zenoh's callback thread ------------------------------------------------------------------

    def _on_sample(self, sample: Any) -> None:
        att = sample.attachment
        gw, seq = parse_attachment(att.to_bytes() if att is not None else None)
        if gw is not None and gw in self.context.own_ids:  # this gateway's own publication
            self.ignored_own += 1
            return
        self.received += 1
        key = str(sample.key_expr)
        self.tracker.see(gw, key, seq)
        q = self._queue
        if q.qsize() >= self.queue_depth:
            self.dropped_queue_full += 1
            return
        q.put((key, sample.payload.to_bytes(), str(sample.encoding), gw or "?"))
        self._schedule_drain()

    # -- the source's loop ------------------------------------------------------------------------

    def begin(self) -> None:
        self._try_open()

    def _try_open(self) -> None:
        """One attempt to open the session, on the loop's blocking calls (an open waits for
        its endpoints); retried with backoff."""
        self._retry = None
        loop = self.io_loop
        if self.stop_requested or loop is None:
            return
        self._opening = True
        loop.run_blocking(self._open, self._opened, name=f"open {self.name}")

    def _opened(self, session: Any, error: BaseException | None) -> None:
        self._opening = False
        if error is not None:  # (the expected failures are counted and logged by _open)
            self.open_failures += 1
            log.warning("source %s: opening the Zenoh session failed: %s; retrying",
                        self.name, error)
        if self.stop_requested:  # halted meanwhile: it waited for this attempt
            self._close(session)
            return
        if session is None:
            loop = self.io_loop
            if loop is not None:
                self._retry = loop.call_later(self._backoff.next(), self._try_open)
            return
        self._session = session

    def _arrived(self) -> None:  # the loop's thread, handed over from Zenoh's
        self._drain_scheduled = False
        q = self._queue
        for _ in range(DRAIN_BATCH):
            try:
                item = q.get_nowait()
            except queue.Empty:
                return
            self._handle(*item)
        self._schedule_drain()  # more waiting: after the loop's other work

    def _schedule_drain(self) -> None:
        loop = self.io_loop
        if not self._drain_scheduled and loop is not None:
            self._drain_scheduled = True
            loop.call_soon(self._arrived)

    def halt(self) -> None:
        if self._retry is not None:
            self._retry.cancel()
            self._retry = None
        self.ready.clear()
        session, self._session = self._session, None
        if session is not None:
            self._close(session)
        elif not self._opening:  # (an open in flight: _opened closes what it brings)
            self.finish()

    def _close(self, session: Any) -> None:
        """Close ``session`` on the loop's blocking calls, then finish."""
        def close() -> None:
            try:
                if session is not None:
                    session.close()
            except Exception:
                log.debug("source %s: session close failed", self.name, exc_info=True)
            finally:
                self.finish()

        loop = self.io_loop
        if loop is None:
            close()
        else:
            loop.run_blocking(close, name=f"close {self.name}")

    def _open(self) -> Any:
        import zenoh

        try:
            session = self.session_options.open()
        except (zenoh.ZError, ConfigError) as exc:
            self.open_failures += 1
            if self.open_failures == 1:
                log.warning("source %s: cannot open the Zenoh session (%s): %s; retrying",
                            self.name, self.session_options.describe(), zerror_text(exc))
            return None
        if self._stop.is_set():
            session.close()
            return None
        try:
            session.declare_subscriber(self.key_expr, self._on_sample)
            if self.stats_key_expr is not None:
                session.declare_subscriber(self.stats_key_expr, self._on_sample)
        except zenoh.ZError as exc:
            self.open_failures += 1
            log.warning("source %s: cannot subscribe to %s: %s", self.name, self.key_expr,
                        zerror_text(exc))
            session.close()
            return None
        self.session_opens += 1
        log.info("source %s: subscribed to %s (%s)", self.name, self.key_expr,
                 self.session_options.describe())
        self.ready.set()
        return session

    def _decoder(self, vehicle: str) -> Decoder | None:
        """``vehicle``'s wire decoder, made on its first sample; None (counted) for a chunk
        that is not a vehicle name, or a vehicle beyond MAX_VEHICLES."""
        dec = self.decoders.get(vehicle)
        if dec is not None:
            return dec
        try:
            check_name(vehicle)
        except ValueError as exc:
            self.bad_vehicle_names += 1
            if vehicle not in self._bad_names and len(self._bad_names) < 16:
                self._bad_names.add(vehicle)
                log.warning("source %s: ignoring vehicle %s", self.name, exc)
            return None
        if len(self.decoders) >= MAX_VEHICLES:
            self.dropped_vehicle_limit += 1
            if self.dropped_vehicle_limit == 1:
                log.warning("source %s: more than %d vehicles; %r and any further one "
                            "ignored (dropped_vehicle_limit)", self.name, MAX_VEHICLES,
                            vehicle)
            return None
        dec = self.decoders[vehicle] = Decoder(origin=self.name, vehicle=vehicle)
        dec.stats = self.decoder_stats
        n = len(self.decoders)
        if n <= LOGGED_VEHICLES:
            log.info("source %s: following vehicle %s", self.name, vehicle)
        elif n == LOGGED_VEHICLES + 1:
            log.info("source %s: following more vehicles (%s, …; not logged: counted in its "
                     "stats' vehicles)", self.name, vehicle)
        return dec

    def _handle(self, key: str, payload: bytes, encoding: str, gateway: str = "?") -> None:
        """One sample, from the gateway whose id its attachment names ("?" = none)."""
        via = VIA_ZENOH + gateway
        parsed = parse_key(key, self.prefix)
        if parsed is None:
            self.ignored_other += 1
            return
        vehicle, kind, _ = parsed
        if self.stats_key_expr is not None:
            publisher = parse_stats_key(key, self.prefix)
            if publisher is not None:  # a gateway's counters, for a monitor
                self._handle_stats(publisher, payload, via)
                return
        dec = self._decoder(vehicle)
        if dec is None:
            return
        if kind == RAW:
            stats = self.decoder_stats
            dec.via = via
            before = stats.frames
            msgs = dec.feed(payload) + dec.flush()
            if stats.frames == before:
                self.bad_payloads += 1
            for msg in msgs:
                self.emitted += 1
                self.emit(msg)
            return
        if kind not in JSON_KINDS or kind == "link":  # link events are this gateway's own
            self.ignored_other += 1
            return
        try:
            msg = enc.decode(kind, payload, encoding, origin=self.name)._replace(
                via=via, vehicle=vehicle)
        except enc.PayloadError as exc:
            self.bad_payloads += 1
            if self.bad_payloads == 1:
                log.warning("source %s: %s: %s", self.name, key, exc)
            return
        self.emitted += 1
        self.emit(msg)

    def _handle_stats(self, publisher: str, payload: bytes, via: str) -> None:
        try:
            stats = enc.gateway_stats(publisher, payload, origin=self.name)._replace(via=via)
        except enc.PayloadError:
            self.bad_payloads += 1
            return
        self.emitted += 1
        self.emit(stats)

    def stats(self) -> dict[str, Any]:
        return {
            "received": self.received,
            "emitted": self.emitted,
            "lost": self.tracker.lost,
            "dropped_queue_full": self.dropped_queue_full,
            "ignored_own": self.ignored_own,
            "bad_payloads": self.bad_payloads,
            "crc_failures": self.decoder_stats.crc_failures,
            "vehicles": len(self.decoders),
            "bad_vehicle_names": self.bad_vehicle_names,
            "dropped_vehicle_limit": self.dropped_vehicle_limit,
            "session_opens": self.session_opens,
            "open_failures": self.open_failures,
        }
