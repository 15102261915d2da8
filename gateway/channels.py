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
from typing import Generic, TypeVar

T = TypeVar("T")

RING_DEPTH = 32


class Mailbox(Generic[T]):
    """The latest value, overwritten by every publish.  ``version`` counts publishes."""

    __slots__ = ("_lock", "_value", "version")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._value: T | None = None
        self.version = 0

    def put(self, value: T) -> None:
        with self._lock:
            self._value = value
            self.version += 1

    def peek(self) -> T | None:
        """The latest value (None before the first publish); does not consume it."""
        return self._value

    def poll(self, seen_version: int) -> tuple[int, T | None]:
        """(version, value) if something newer than ``seen_version`` arrived, else
        (seen_version, None)."""
        with self._lock:
            if self.version == seen_version:
                return seen_version, None
            return self.version, self._value


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
