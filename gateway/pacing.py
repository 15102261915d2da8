"""Release timestamped items at real time, or N times faster."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


def paced(
    items: Iterable[tuple[float, T]],
    speed: float,
    stop: threading.Event,
    clock: Callable[[], float] = time.monotonic,
) -> Iterator[tuple[float, T]]:
    """Yield ``(t, item)`` pairs when wall time reaches ``t / speed`` after the first item.

    ``speed`` 0 means as fast as possible.  Stops early when ``stop`` is set.  The schedule is
    anchored to the start, so late items catch up instead of drifting.
    """
    if speed < 0:
        raise ValueError("speed must be ≥ 0")
    start_wall: float | None = None
    start_t = 0.0
    for t, item in items:
        if stop.is_set():
            return
        if start_wall is None:
            start_wall, start_t = clock(), t
        elif speed > 0:
            delay = start_wall + (t - start_t) / speed - clock()
            if delay > 0 and stop.wait(delay):
                return
        yield t, item
