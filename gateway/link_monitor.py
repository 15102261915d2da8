"""Link monitor (OpenPilot's TelemetryMonitor, seed 001): per vehicle, is its link up?

A vehicle's link comes *up* on its first valid frame and goes *down* after ``timeout_s``
without one (default 3 s).  Links are kept per vehicle (a source is one vehicle; a MAVLink
source hearing two systems has two links), named by the vehicle (or the source, for a message
with none); each :class:`LinkEvent` names its source, vehicle and ``via``.  At most
:data:`MAX_LINKS` are kept (a source naming vehicles at will cannot grow the table).
Every change becomes a :class:`LinkEvent` handed to ``sink``
(normally the dispatcher, so every backend hears it).  The clock is injectable so the
behaviour is testable without waiting.

Events reach the sink in the order the state changed, even when a source's loop
(:meth:`LinkMonitor.frame_seen`) and the checking thread (:meth:`LinkMonitor.check`) race:
changes are queued under a lock and delivered by one thread at a time, so a late "down"
can never overtake the "up" that followed it.  No lock is held while the sink runs and no
caller ever waits for another's delivery, so a sink may call back into the monitor.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from gateway.model import LinkEvent

DEFAULT_LINK_TIMEOUT_S = 3.0
#: links kept; frames of more vehicles are not tracked (counted in ``untracked``)
MAX_LINKS = 1024


class LinkMonitor:
    def __init__(
        self,
        sink: Callable[[LinkEvent], Any],
        timeout_s: float = DEFAULT_LINK_TIMEOUT_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if timeout_s <= 0:
            raise ValueError("link timeout must be positive")
        self.timeout_s = timeout_s
        self._sink = sink
        self._clock = clock
        self._last: dict[str, float] = {}
        self._up: dict[str, bool] = {}
        self._meta: dict[str, tuple[str, str, str]] = {}  # link → (source, via, vehicle)
        self.untracked = 0
        self._lock = threading.Lock()
        self._pending: deque[LinkEvent] = deque()
        self._delivering = threading.Lock()
        self.changes = 0

    def frame_seen(self, source: str, via: str = "", vehicle: str = "") -> None:
        """A valid frame arrived from ``source`` about ``vehicle`` (call from the source's
        loop); ``via`` is the message's (see :mod:`gateway.model`), carried on the link's
        events.  The link is the vehicle's (the source's when ``vehicle`` is "")."""
        now = self._clock()
        link = vehicle or source
        if self._up.get(link):
            self._last[link] = now
            return
        with self._lock:
            if self._up.get(link):
                self._last[link] = now
                return
            if link not in self._up and len(self._up) >= MAX_LINKS:
                self.untracked += 1
                return
            self._last[link] = now
            self._up[link] = True
            self._meta[link] = (source, via, vehicle)
            self.changes += 1
            self._pending.append(LinkEvent(source, True, 0.0, via=via,
                                           vehicle=vehicle))
        self._deliver()

    def check(self) -> list[LinkEvent]:
        """Mark silent links down; call periodically.  Returns the events it emitted."""
        events = []
        with self._lock:
            now = self._clock()
            for link, up in self._up.items():
                silence = now - self._last[link]
                if up and silence >= self.timeout_s:
                    self._up[link] = False
                    self.changes += 1
                    source, via, vehicle = self._meta[link]
                    events.append(LinkEvent(source, False, silence, via=via,
                                            vehicle=vehicle))
            self._pending.extend(events)
        self._deliver()
        return events

    def _deliver(self) -> None:
        """Hand queued events to the sink in order; whoever holds ``_delivering`` does it for
        everyone, the others return at once (their events are already queued)."""
        while self._pending:
            if not self._delivering.acquire(blocking=False):
                return
            try:
                while True:
                    with self._lock:
                        if not self._pending:
                            break
                        ev = self._pending.popleft()
                    self._sink(ev)
            finally:
                self._delivering.release()

    def is_up(self, link: str) -> bool | None:
        """True/False once the link (a vehicle's, or a source's for messages with no vehicle)
        has been heard from; None before its first frame."""
        return self._up.get(link)

    def silence_s(self, link: str) -> float | None:
        last = self._last.get(link)
        return None if last is None else self._clock() - last

    def states(self) -> dict[str, bool]:
        """Every link (by vehicle) and whether it is up."""
        return dict(self._up)
