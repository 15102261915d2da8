"""What the XBee air backend and ground source share: the module on a port engine, the link
role's outputs carried out, the periodic tick and poll, servo values ↔ pulse widths.

One :class:`Radio` runs on its engine's thread: the role (:mod:`.link`) is only ever called
there, so it needs no lock; the gateway's messages reach it through :attr:`Radio.handover`
(the routes of the backend or source that owns the radio name it), bounded.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from typing import Any

from gateway.handover import Handover
from gateway.io.backoff import Backoff
from gateway.io.port import REOPEN_FIRST_S, REOPEN_MAX_S, PortEngine
from gateway.io.transport import open_serial_nonblocking
from gateway.model import RcChannels

from . import frames as f
from .link import QueryRssi, RcCommand, Send
from .module import XBeeModule

log = logging.getLogger(__name__)

DEFAULT_BAUD = 9600  # an XBee's factory rate (BD = 3)
TICK_S = 0.01
POLL_S = 1.0
#: Gateway messages that may wait for the radio's thread before they are refused (QUEUE_FULL).
INBOX_DEPTH = 256
SERVOS = 6
SERVO_MAX = 0x3FF
US_MIN, US_SPAN = 1000, 1000  # a 10-bit servo value spans 1000..2000 µs


def servo_from_us(us: int) -> int:
    """A pulse width (µs) as the link's 10-bit servo value (1000..2000 µs → 0..1023)."""
    return max(0, min(SERVO_MAX, round((us - US_MIN) * SERVO_MAX / US_SPAN)))


def us_from_servo(value: int) -> int:
    """The link's 10-bit servo value as a pulse width (0..1023 → 1000..2000 µs)."""
    return US_MIN + round(value * US_SPAN / SERVO_MAX)


def rc_message(cmd: RcCommand, origin: str, vehicle: str = "") -> RcChannels:
    """The servo values a command carried, as a gateway message (channel i = servo i) for
    ``vehicle`` ("": not known)."""
    top = max(cmd.values, default=-1) + 1
    return RcChannels(tuple(us_from_servo(cmd.values[i]) if i in cmd.values else None
                            for i in range(top)), cmd.seq, origin=origin, vehicle=vehicle)


def parse_dest(text: str) -> int:
    """A 64-bit destination in hex (``0013A20040A1B2C3``); "" = broadcast."""
    if not text:
        return f.BROADCAST_64
    try:
        value = int(text, 16)
    except ValueError:
        raise ValueError(f"{text!r} is not a 64-bit address in hex") from None
    if not 0 <= value <= 0xFFFFFFFFFFFFFFFF:
        raise ValueError(f"{text!r} is not a 64-bit address")
    return value


class Radio:
    """The engine, the module and the periodic work of one role."""

    def __init__(self, name: str, url: str, baudrate: int, api_mode: int, *,
                 dest64: int, perform: Callable[[Iterable[Any]], None],
                 tick: Callable[[float], Iterable[Any]],
                 on_payload: Callable[[bytes, int, float], Iterable[Any]],
                 on_rssi: Callable[[int, float, float], Any] | None = None,
                 on_readings: Callable[[dict[str, int]], Any] | None = None,
                 on_np: Callable[[int], Any] | None = None,
                 tick_s: float = TICK_S, poll_s: float = POLL_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self.url = url
        self.baudrate = baudrate
        self.clock = clock
        self.tick_s = tick_s
        self.poll_s = poll_s
        self._perform = perform
        self._tick = tick
        self._on_payload = on_payload
        self._on_rssi = on_rssi
        self.module = XBeeModule(
            api_mode, dest64=dest64, on_payload=self._payload,
            on_rssi=self._rssi if on_rssi is not None else None, on_readings=on_readings,
            on_np=on_np)
        self.engine = PortEngine(self._open, name=name, protocol=self.module,
                                 on_link=self._on_link, queue_depth=64,
                                 backoff=Backoff(REOPEN_FIRST_S, REOPEN_MAX_S))
        self.module.engine = self.engine
        self._timers: list[Any] = []
        #: The gateway's messages to this radio's handlers, on its thread; refused while the
        #: module's port is down (NOT_READY).
        self.handover = Handover(name, INBOX_DEPTH, ready=lambda: self.engine.connected)
        self.errors = 0

    def _open(self) -> Any:
        return open_serial_nonblocking(self.url, self.baudrate)

    def _on_link(self, up: bool) -> None:
        if up:
            self.module.connected()
            log.info("%s: XBee on %s (API %d)", self.name, self.url, self.module.api_mode)

    def start(self) -> None:
        self.handover.open(self.engine.loop)
        self.engine.start()
        self._timers = [self.engine.call_every(self.tick_s, self._run_tick, first=self.tick_s),
                        self.engine.call_every(self.poll_s, self.module.poll, first=self.poll_s)]

    def close(self, timeout: float = 1.0) -> None:
        for timer in self._timers:
            timer.cancel()
        self.handover.close(timeout / 2)
        self.engine.close(timeout / 2)

    # -- the engine's thread ---------------------------------------------------------------

    def _guarded(self, fn: Callable[[], Iterable[Any]]) -> None:
        try:
            self._perform(fn())
        except Exception:
            self.errors += 1
            if self.errors == 1:
                log.exception("%s: the XBee link failed (counted; carrying on)", self.name)

    def _run_tick(self) -> None:
        if self.engine.connected:
            self._guarded(lambda: self._tick(self.clock()))

    def _payload(self, data: bytes, src64: int) -> None:
        self._guarded(lambda: self._on_payload(data, src64, self.clock()))

    def _rssi(self, token: int, dbm: float) -> None:
        on_rssi = self._on_rssi
        if on_rssi is not None:
            def reading() -> tuple[()]:
                on_rssi(token, dbm, self.clock())
                return ()

            self._guarded(reading)

    def perform(self, outputs: Iterable[Any]) -> None:
        """Carry out what the role returned (a handler on the radio's thread)."""
        self._perform(outputs)

    def send(self, out: Send) -> None:
        self.module.send(out.payload, out.power)

    def query(self, out: QueryRssi) -> None:
        self.module.query_rssi(out.token)

    # -- any thread -------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        es = self.engine.stats
        h = self.handover
        return {**self.module.stats(), "link": int(self.engine.connected),
                "dropped_queue_full": h.dropped_queue_full,
                "dropped_not_ready": h.dropped_not_ready, "dropped_closed": h.dropped_closed,
                "dropped_handover": h.dropped,
                "errors": self.errors + es.errors + h.handler_errors,
                "opens": es.connects, "open_failures": es.connect_failures}
