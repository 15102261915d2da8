"""Channels (seed 003): a mailbox and a ring, never blocking a producer.

* :class:`Mailbox` holds the latest value; a new one overwrites it (FreeRTOS
  ``xQueueOverwrite`` on a depth-1 queue).  A consumer that polls at its own rate (the CRSF
  scheduler, one per frame type) reads it.
* :class:`Ring` is a short FIFO history (default depth 32); when full the *newest* value is
  dropped and counted, like ``xQueueSend`` with a zero timeout (the CRSF scheduler keeps its
  state changes in one).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")

RING_DEPTH = 32


class Mailbox(Generic[T]):
    """The latest value, overwritten by every publish.  ``version`` counts publishes.

    One producer at a time (a backend's handlers: the dispatcher never runs them
    concurrently); any thread may read.  The version and the value are one tuple, swapped in a
    single store, so a reader never sees one without the other and a publish takes no lock.
    :meth:`put_lazy` publishes a value to be made only when it is read: a producer at 25k
    updates/s feeding a consumer that reads 20 values a second makes 20, not 25 000."""

    __slots__ = ("_cell",)

    def __init__(self) -> None:
        # (version, value or the argument of make, make or None)
        self._cell: tuple[int, Any, Callable[[Any], T] | None] = (0, None, None)

    @property
    def version(self) -> int:
        return self._cell[0]

    def put(self, value: T) -> None:
        self._cell = (self._cell[0] + 1, value, None)

    def put_lazy(self, make: Callable[[Any], T], arg: Any) -> None:
        """Publish ``make(arg)``, made when it is read (by every read: ``make`` must be
        cheap and pure)."""
        self._cell = (self._cell[0] + 1, arg, make)

    def peek(self) -> T | None:
        """The latest value (None before the first publish); does not consume it."""
        _, value, make = self._cell
        return value if make is None else make(value)

    def poll(self, seen_version: int) -> tuple[int, T | None]:
        """(version, value) if something newer than ``seen_version`` arrived, else
        (seen_version, None)."""
        version, value, make = self._cell
        if version == seen_version:
            return seen_version, None
        return version, (value if make is None else make(value))


class Ring(Generic[T]):
    """Bounded FIFO; a put into a full ring drops the new value and counts it."""

    __slots__ = ("_items", "_lock", "depth", "dropped")

    def __init__(self, depth: int = RING_DEPTH) -> None:
        if depth < 1:
            raise ValueError("ring depth must be at least 1")
        self.depth = depth
        self._items: deque[T] = deque()
        self._lock = threading.Lock()
        self.dropped = 0

    def put(self, value: T) -> bool:
        """Append; False (and counted) when full."""
        with self._lock:
            if len(self._items) >= self.depth:
                self.dropped += 1
                return False
            self._items.append(value)
            return True

    def drain(self, max_items: int | None = None) -> list[T]:
        """Remove and return up to ``max_items`` of the oldest values (all by default)."""
        with self._lock:
            n = len(self._items) if max_items is None else min(max_items, len(self._items))
            return [self._items.popleft() for _ in range(n)]

    def __len__(self) -> int:
        return len(self._items)
