"""The air link's byte budget: never schedule more bytes than the HC-12 can carry.

A token bucket counted in bytes (pure logic, injectable clock, no threads).  It fills at the
budget rate — ``air_baud / bits_per_byte × utilisation`` (9600 baud, 10 bits a byte on the
UART, 80 %: 768 B/s) — up to ``burst_bytes``.  A frame is admitted when the bucket holds
enough for it and is then charged in full.  So, for frames no larger than the burst:

    in any interval of T seconds, admitted bytes ≤ burst_bytes + rate × T.

The default burst is the headroom the utilisation leaves in one second (960 − 768 = 192 B at
the defaults): then no one-second window ever carries more than the air link does (960 B),
and the sustained rate never exceeds the budget (768 B/s).  A frame larger than the burst is
admitted only from a full bucket and leaves it in debt, paid back before the next frame.

``priority`` frames (STATUS, the heartbeat that must get through a saturated SM_UPDATE
stream) may use a small reserve the others must leave in the bucket; they are still charged,
so they count against the budget like everything else.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

BITS_PER_BYTE = 10  # 8N1 on the UART: start bit, 8 data bits, stop bit
DEFAULT_AIR_BAUD = 9600
DEFAULT_UTILISATION_PCT = 80.0
#: What priority frames may dip into: two STATUS frames (8-byte payload + 6 bytes framing).
DEFAULT_PRIORITY_RESERVE = 2 * 14
UTILISATION_WINDOW_S = 5.0


@dataclass(frozen=True)
class BudgetFigures:
    """How a budget is set up, in bytes and bytes per second."""

    capacity_bps: float  # what the air link carries
    rate_bps: float  # what the budget allows, sustained
    burst_bytes: float
    reserve_bytes: float


def figures(air_baud: int = DEFAULT_AIR_BAUD, utilisation_pct: float = DEFAULT_UTILISATION_PCT,
            burst_bytes: int | None = None,
            reserve_bytes: int = DEFAULT_PRIORITY_RESERVE) -> BudgetFigures:
    """The budget for an air link of ``air_baud`` used at ``utilisation_pct`` percent.

    ``burst_bytes`` None: the headroom of one second, ``capacity − rate`` bytes.  The bucket
    is never smaller than the priority reserve."""
    if air_baud <= 0:
        raise ValueError("air_baud must be positive")
    if not 0 < utilisation_pct <= 100:
        raise ValueError("utilisation_pct must be in (0, 100]")
    capacity = air_baud / BITS_PER_BYTE
    rate = capacity * utilisation_pct / 100.0
    burst = capacity - rate if burst_bytes is None else float(burst_bytes)
    if burst < 0:
        raise ValueError("burst_bytes must not be negative")
    return BudgetFigures(capacity, rate, max(burst, float(reserve_bytes)), float(reserve_bytes))


class AirBudget:
    """Admission control in bytes per second (see the module docstring).

    :meth:`admit` only looks; :meth:`commit` charges an admitted frame.  The split lets a
    caller charge only frames the queue really took.  Thread-safe."""

    def __init__(self, fig: BudgetFigures, clock: Callable[[], float] = time.monotonic,
                 window_s: float = UTILISATION_WINDOW_S) -> None:
        self.fig = fig
        self._clock = clock
        self._lock = threading.Lock()
        self._tokens = fig.burst_bytes  # an idle link starts with a full bucket
        self._stamp: float | None = None
        self._window_s = window_s
        self._recent: deque[tuple[float, int]] = deque()  # (time, bytes) within window_s
        self._recent_bytes = 0
        self._second: deque[tuple[float, int]] = deque()  # (time, bytes) within 1 s
        self._second_bytes = 0
        self.first_commit: float | None = None
        self.committed_bytes = 0
        self.committed_frames = 0
        self.refused_frames = 0
        self.refused_bytes = 0
        self.peak_1s_bytes = 0

    def now(self) -> float:
        return self._clock()

    def _refill(self, now: float) -> None:
        if self._stamp is not None and now > self._stamp:
            self._tokens = min(self.fig.burst_bytes,
                               self._tokens + (now - self._stamp) * self.fig.rate_bps)
        if self._stamp is None or now > self._stamp:
            self._stamp = now

    def _threshold(self, n: int, priority: bool) -> float:
        cap = self.fig.burst_bytes
        if priority:
            return min(n, cap)
        reserve = self.fig.reserve_bytes
        return min(n, cap - reserve) + reserve

    def admit(self, n: int, *, priority: bool = False, now: float | None = None) -> bool:
        """Would a frame of ``n`` bytes fit now?  Counts a refusal when it would not."""
        t = self._clock() if now is None else now
        with self._lock:
            self._refill(t)
            if self._tokens >= self._threshold(n, priority):
                return True
            self.refused_frames += 1
            self.refused_bytes += n
            return False

    def commit(self, n: int, *, now: float | None = None) -> None:
        """Charge an admitted frame of ``n`` bytes."""
        t = self._clock() if now is None else now
        with self._lock:
            self._refill(t)
            self._tokens -= n
            self.committed_bytes += n
            self.committed_frames += 1
            if self.first_commit is None:
                self.first_commit = t
            self._recent.append((t, n))
            self._recent_bytes += n
            self._second.append((t, n))
            self._second_bytes += n
            self._prune(t)
            self.peak_1s_bytes = max(self.peak_1s_bytes, self._second_bytes)

    def _prune(self, t: float) -> None:
        while self._recent and self._recent[0][0] <= t - self._window_s:
            self._recent_bytes -= self._recent.popleft()[1]
        while self._second and self._second[0][0] <= t - 1.0:
            self._second_bytes -= self._second.popleft()[1]

    def utilisation_pct(self, now: float | None = None) -> float:
        """Admitted bytes over the last window as a percentage of the air link's capacity."""
        t = self._clock() if now is None else now
        with self._lock:
            self._prune(t)
            if self.first_commit is None:
                return 0.0
            span = min(self._window_s, max(t - self.first_commit, 1.0))
            return 100.0 * self._recent_bytes / (self.fig.capacity_bps * span)

    def average_pct(self, now: float | None = None) -> float:
        """Admitted bytes since the first one as a percentage of the capacity (≥ 1 s span)."""
        t = self._clock() if now is None else now
        with self._lock:
            if self.first_commit is None:
                return 0.0
            span = max(t - self.first_commit, 1.0)
            return 100.0 * self.committed_bytes / (self.fig.capacity_bps * span)
