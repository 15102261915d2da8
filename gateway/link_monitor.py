"""Link monitor (OpenPilot's TelemetryMonitor, seed 001): per source, is the link up?

A source's link comes *up* on its first valid frame and goes *down* after ``timeout_s``
without one (default 3 s).  Every change becomes a :class:`LinkEvent` handed to ``sink``
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
        self._via: dict[str, str] = {}
        self._lock = threading.Lock()
        self._pending: deque[LinkEvent] = deque()
        self._delivering = threading.Lock()
        self.changes = 0

    def frame_seen(self, source: str, via: str = "") -> None:
        """A valid frame arrived from ``source`` (call from the source's loop); ``via`` is
        the message's (see :mod:`gateway.model`), carried on the source's link events."""
        now = self._clock()
        self._last[source] = now
        if self._up.get(source):
            return
        with self._lock:
            if self._up.get(source):
                return
            self._up[source] = True
            self._via[source] = via
            self.changes += 1
            self._pending.append(LinkEvent(source, True, 0.0, via=via))
        self._deliver()

    def check(self) -> list[LinkEvent]:
        """Mark silent links down; call periodically.  Returns the events it emitted."""
        events = []
        with self._lock:
            now = self._clock()
            for source, up in self._up.items():
                silence = now - self._last[source]
                if up and silence >= self.timeout_s:
                    self._up[source] = False
                    self.changes += 1
                    events.append(LinkEvent(source, False, silence,
                                            via=self._via.get(source, "")))
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

    def is_up(self, source: str) -> bool | None:
        """True/False once the source has been heard from; None before its first frame."""
        return self._up.get(source)

    def silence_s(self, source: str) -> float | None:
        last = self._last.get(source)
        return None if last is None else self._clock() - last

    def states(self) -> dict[str, bool]:
        return dict(self._up)
