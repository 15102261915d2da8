"""Release timestamped items at real time, or N times faster: :func:`paced` for a thread that
may sleep, :class:`Pacer` on an I/O loop's timers (the sources' way)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Generic, TypeVar

from gateway.io.ioloop import IoLoop, Timer

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


#: Items released in one go at speed 0 (or when late) before the loop serves others again.
BATCH = 256


class Pacer(Generic[T]):
    """The same schedule as :func:`paced`, on an :class:`~gateway.io.ioloop.IoLoop`'s timers
    instead of a thread that sleeps: ``deliver(t, item)`` runs on the loop's thread when wall
    time reaches ``t / speed`` after the first item (``speed`` 0: as fast as possible, in
    batches of :data:`BATCH` so the loop's other work is not held up), ``on_end()`` once the
    items run out.  :meth:`cancel` stops it (from the loop's thread)."""

    def __init__(
        self,
        loop: IoLoop,
        items: Iterable[tuple[float, T]],
        speed: float,
        deliver: Callable[[float, T], object],
        on_end: Callable[[], object] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if speed < 0:
            raise ValueError("speed must be ≥ 0")
        self.loop = loop
        self.speed = speed
        self._items: Iterator[tuple[float, T]] = iter(items)
        self._deliver = deliver
        self._on_end = on_end
        self._clock = clock
        self._next: tuple[float, T] | None = None
        self._start_wall: float | None = None
        self._start_t = 0.0
        self._timer: Timer | None = None
        self.cancelled = False
        self.ended = False

    def start(self) -> None:
        """Release the first item now (on the loop's thread) and schedule the rest."""
        self.loop.call_soon(self._step)

    def cancel(self) -> None:
        self.cancelled = True
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _step(self) -> None:
        self._timer = None
        if self.cancelled or self.ended:
            return
        now = self._clock()
        for _ in range(BATCH):
            if self._next is None:
                try:
                    self._next = next(self._items)
                except StopIteration:
                    self.ended = True
                    if self._on_end is not None:
                        self._on_end()
                    return
            t, item = self._next
            if self._start_wall is None:
                self._start_wall, self._start_t = now, t
            elif self.speed > 0:
                delay = self._start_wall + (t - self._start_t) / self.speed - now
                if delay > 0:
                    self._timer = self.loop.call_later(delay, self._step)
                    return
            self._next = None
            self._deliver(t, item)
            if self.cancelled:
                return
        self.loop.call_soon(self._step)  # a batch out: let the loop serve the others
