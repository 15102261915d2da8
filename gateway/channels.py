"""Channels (seed 003): per message kind a mailbox and a ring, never blocking a producer.

* :class:`Mailbox` holds the latest value; a new one overwrites it (FreeRTOS
  ``xQueueOverwrite`` on a depth-1 queue).  Consumers that poll at their own rate (CRSF,
  MAVLink streams) read it.
* :class:`Ring` is a short FIFO history (default depth 32); when full the *newest* value is
  dropped and counted, like ``xQueueSend`` with a zero timeout.  Recorders drain it.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any, Generic, TypeVar

from gateway.backend import Backend, Outcome

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


class Channel(Generic[T]):
    """A mailbox and a ring for one message kind."""

    __slots__ = ("kind", "mailbox", "ring")

    def __init__(self, kind: str, ring_depth: int = RING_DEPTH) -> None:
        self.kind = kind
        self.mailbox: Mailbox[T] = Mailbox()
        self.ring: Ring[T] = Ring(ring_depth)

    def publish(self, value: T) -> bool:
        """Overwrite the mailbox and append to the ring; False when the ring dropped it."""
        self.mailbox.put(value)
        return self.ring.put(value)


class Channels:
    """One channel per message kind (``msg.KIND``), created on first use."""

    def __init__(self, ring_depth: int = RING_DEPTH) -> None:
        self._ring_depth = ring_depth
        self._channels: dict[str, Channel[Any]] = {}
        self._lock = threading.Lock()

    def __getitem__(self, kind: str) -> Channel[Any]:
        ch = self._channels.get(kind)
        if ch is None:
            with self._lock:
                ch = self._channels.setdefault(kind, Channel(kind, self._ring_depth))
        return ch

    def publish(self, msg: Any) -> bool:
        return self[msg.KIND].publish(msg)

    def latest(self, kind: str) -> Any | None:
        return self[kind].mailbox.peek()

    def kinds(self) -> list[str]:
        return list(self._channels)


class ChannelBackend(Backend):
    """A backend that publishes every message into :class:`Channels` for polling consumers.

    Always ``ACCEPTED``: the mailbox holds the latest value whatever the ring does; a full
    ring's drops are the ring's to count (``stats()`` reports them per kind), since a consumer
    that only polls mailboxes never drains the rings.
    """

    NAME = "channels"

    def __init__(self, channels: Channels | None = None, name: str | None = None) -> None:
        super().__init__(name)
        self.channels = channels if channels is not None else Channels()

    def _publish(self, msg: Any) -> Outcome:
        self.channels.publish(msg)
        return Outcome.ACCEPTED

    send_sm_update = send_status = send_raw = on_link = _publish
    send_link_stats = send_position = send_battery = send_vehicle_state = _publish

    def stats(self) -> dict[str, int]:
        return {f"ring_dropped_{kind}": self.channels[kind].ring.dropped
                for kind in self.channels.kinds()}
