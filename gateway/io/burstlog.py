"""Log a kind of event once per burst, not once per event: :class:`BurstLog`.

What a peer can trigger is bounded, log lines too: a burst of refused or cut clients is one
line when it starts, then one line with the count per :data:`BURST_LOG_S` while it lasts.
"""

from __future__ import annotations

import logging

from gateway.io.ioloop import IoLoop, Timer

log = logging.getLogger(__name__)

#: A burst: one line, then one line with the count per this interval.
BURST_LOG_S = 10.0


class BurstLog:
    """Log a kind of event once per burst: the first as a line of its own, the rest as one
    line with their count per ``interval_s`` while they keep coming (on ``loop``'s thread)."""

    def __init__(self, loop: IoLoop, text: str, *, level: int = logging.WARNING,
                 interval_s: float = BURST_LOG_S, logger: logging.Logger = log) -> None:
        self.loop = loop
        self.text = text
        self.level = level
        self.interval_s = interval_s
        self.logger = logger
        self.lines = 0  # lines written (for tests)
        self.events = 0  # every event, logged or counted
        self._more = 0
        self._timer: Timer | None = None

    def event(self, detail: str = "") -> None:
        """One event: a line if it starts a burst, else counted (``detail`` names the first)."""
        self.events += 1
        if self._timer is None:
            self.logger.log(self.level, "%s%s (more are counted, one line per %.0f s)",
                            self.text, f": {detail}" if detail else "", self.interval_s)
            self.lines += 1  # (after: a line counted is a line written, for another thread)
            self._timer = self.loop.call_later(self.interval_s, self._summary)
        else:
            self._more += 1

    def _summary(self) -> None:
        if not self._more:
            self._timer = None  # the burst is over
            return
        self.logger.log(self.level, "%s: %d more in the last %.0f s", self.text, self._more,
                        self.interval_s)
        self.lines += 1
        self._more = 0
        self._timer = self.loop.call_later(self.interval_s, self._summary)

    @property
    def active(self) -> bool:
        """A burst is on (its count will be logged)."""
        return self._timer is not None

    def cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
