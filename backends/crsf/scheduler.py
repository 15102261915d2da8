"""Which telemetry frame to send next: the seed's mailbox semantics, as pure logic.

Producers :meth:`Scheduler.publish` the latest value per frame type into a
:class:`~gateway.channels.Mailbox` (overwritten, never queued: an ELRS receiver keeps only
the latest frame per type anyway).  A consumer calls :meth:`Scheduler.take` at its own pace
and gets at most one (frame type, value) per call, chosen so that

* each type goes out at its own rate while new values arrive (``rates``, Hz);
* every type that has a value is re-sent at least every ``refresh_s`` even when nothing new
  arrives, as long as its value is younger than ``hold_s`` (then it is left to go stale on
  the radio, which is the honest thing to show when the source has gone quiet);
* frames are at least ``1 / max_rate_hz`` apart (the total rate cap);
* among due types the most overdue goes first, ties round-robin, so an overloaded
  configuration degrades every type evenly and each still meets the refresh bound;
* a *change* (:meth:`Scheduler.publish_change`, e.g. a new flight state) goes out at once,
  ahead of the cap, and every change is kept in order in a short ring (the seed's ring), so
  a burst of state changes faster than the frame rate still shows each state.

No threads, no I/O: the clock is injectable and every method takes ``now``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from gateway.channels import Mailbox, Ring
from gateway.checks import not_negative, positive

DEFAULT_MAX_RATE_HZ = 20.0
DEFAULT_REFRESH_S = 2.0
DEFAULT_HOLD_S = 10.0
CHANGE_RING_DEPTH = 16
_EPS = 1e-9


@dataclass
class Slot:
    """One frame type's mailbox and schedule."""

    frame_type: int
    period_s: float
    order: int
    mailbox: Mailbox[Any] = field(default_factory=Mailbox)
    version_seen: int = 0
    updated_at: float = -math.inf
    sent_version: int = 0
    anchor: float | None = None  # reference time of the last send; None = never sent
    sent: int = 0


class Scheduler:
    """Round-robin, rate-limited choice of the next telemetry frame (see module docstring)."""

    def __init__(
        self,
        rates: Mapping[int, float],
        *,
        max_rate_hz: float = DEFAULT_MAX_RATE_HZ,
        refresh_s: float = DEFAULT_REFRESH_S,
        hold_s: float = DEFAULT_HOLD_S,
        change_depth: int = CHANGE_RING_DEPTH,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        positive("max_rate_hz", max_rate_hz)
        positive("refresh_s", refresh_s)
        not_negative("hold_s", hold_s)
        self.max_rate_hz = max_rate_hz
        self.refresh_s = refresh_s
        self.hold_s = hold_s
        self.spacing_s = 1.0 / max_rate_hz
        self._clock = clock
        self._slots: dict[int, Slot] = {}
        for ftype, hz in rates.items():
            if hz < 0 or not math.isfinite(hz):
                raise ValueError(f"rate of frame type 0x{ftype:02X} must be ≥ 0, got {hz}")
            if hz > 0:
                self._slots[ftype] = Slot(ftype, 1.0 / hz, len(self._slots))
        self._order = list(self._slots.values())
        self._changes: Ring[tuple[int, Any]] = Ring(change_depth)
        self._last_emit: float | None = None
        self._rr_next = 0
        self.sent = 0
        self.changes_sent = 0

    # -- producer side (never blocks) -----------------------------------------------------------

    def scheduled(self, frame_type: int) -> bool:
        return frame_type in self._slots

    def mailbox(self, frame_type: int) -> Mailbox[Any]:
        return self._slots[frame_type].mailbox

    def publish(self, frame_type: int, value: Any) -> bool:
        """Make ``value`` the latest of its type; False when the type is not scheduled."""
        slot = self._slots.get(frame_type)
        if slot is None:
            return False
        slot.mailbox.put(value)
        return True

    def publish_lazy(self, frame_type: int, make: Callable[[Any], Any], arg: Any) -> bool:
        """Make ``make(arg)`` the latest of its type, made only if it is read (sent or
        peeked); False when the type is not scheduled."""
        slot = self._slots.get(frame_type)
        if slot is None:
            return False
        slot.mailbox.put_lazy(make, arg)
        return True

    def publish_change(self, frame_type: int, value: Any) -> bool:
        """Publish ``value`` and send it at once, ahead of the rate cap (a state change).
        False when the type is not scheduled or the change ring is full (counted)."""
        if not self.publish(frame_type, value):
            return False
        return self._changes.put((frame_type, value))

    @property
    def changes_dropped(self) -> int:
        return self._changes.dropped

    # -- consumer side ----------------------------------------------------------------------

    def _observe(self, slot: Slot, now: float) -> bool:
        """Note a new value; True when the slot has a value young enough to send."""
        v = slot.mailbox.version
        if v != slot.version_seen:
            slot.version_seen = v
            slot.updated_at = now
        if v == 0:
            return False
        return not (self.hold_s > 0 and now - slot.updated_at > self.hold_s)

    def _due(self, slot: Slot, refresh: float) -> float:
        if slot.anchor is None:
            return -math.inf
        fresh = slot.version_seen != slot.sent_version
        return slot.anchor + (min(slot.period_s, refresh) if fresh else refresh)

    def _effective_refresh(self, active: int) -> float:
        """The refresh interval leaving room for every other active type to go first once
        (the worst wait of a due type), so the gap between two sends stays ≤ ``refresh_s``."""
        return max(self.spacing_s, self.refresh_s - (active + 1) * self.spacing_s)

    @property
    def changes_pending(self) -> int:
        return len(self._changes)

    def take_change(self, now: float | None = None) -> tuple[int, Any] | None:
        """The oldest pending change (what :meth:`take` would return first), or None."""
        change = self._changes.drain(1)
        if not change:
            return None
        if now is None:
            now = self._clock()
        ftype, value = change[0]
        slot = self._slots[ftype]
        slot.anchor = now
        slot.sent += 1
        self._last_emit = now
        self.sent += 1
        self.changes_sent += 1
        return ftype, value

    def take(self, now: float | None = None) -> tuple[int, Any] | None:
        """The next (frame type, value) to send now, or None; what it returns counts as sent."""
        if now is None:
            now = self._clock()
        change = self.take_change(now)
        if change is not None:
            return change
        if self._last_emit is not None and now - self._last_emit < self.spacing_s - _EPS:
            return None
        active = [s for s in self._order if self._observe(s, now)]
        if not active:
            return None
        refresh = self._effective_refresh(len(active))
        n = len(self._order)
        best: Slot | None = None
        best_key: tuple[float, int] | None = None
        for slot in active:
            due = self._due(slot, refresh)
            if due > now + _EPS:
                continue
            key = (due, (slot.order - self._rr_next) % n)
            if best_key is None or key < best_key:
                best, best_key = slot, key
        if best is None or best_key is None:
            return None
        version, value = best.mailbox.poll(-1)
        due = best_key[0]
        fresh = best.version_seen != best.sent_version
        interval = min(best.period_s, refresh) if fresh else refresh
        # Anchor to the due time so a slightly late send does not lower the rate, but never
        # further back than one interval (no bursts to catch up).
        best.anchor = now if due == -math.inf else max(due, now - interval)
        best.sent_version = version
        best.version_seen = max(best.version_seen, version)
        best.sent += 1
        self._rr_next = (best.order + 1) % n
        self._last_emit = now
        self.sent += 1
        return best.frame_type, value

    def next_due(self, now: float | None = None) -> float:
        """The earliest time :meth:`take` may return something (``inf``: nothing to send
        until a value is published)."""
        if now is None:
            now = self._clock()
        if len(self._changes):
            return now
        active = [s for s in self._order if self._observe(s, now)]
        if not active:
            return math.inf
        refresh = self._effective_refresh(len(active))
        earliest = min(self._due(s, refresh) for s in active)
        if self._last_emit is not None:
            earliest = max(earliest, self._last_emit + self.spacing_s)
        return max(earliest, now)

    def stats(self) -> dict[str, int]:
        """Frames chosen per type (``sent_0x1E`` …) and change counters."""
        d = {f"sent_0x{s.frame_type:02X}": s.sent for s in self._order}
        d["changes_sent"] = self.changes_sent
        d["changes_dropped"] = self.changes_dropped
        return d
