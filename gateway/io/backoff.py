"""Exponential backoff for reconnecting to ports, routers and peers."""

from __future__ import annotations


class Backoff:
    """Delays ``initial``, ``initial*factor``, … capped at ``maximum``; :meth:`reset` on success."""

    __slots__ = ("_next", "factor", "initial", "maximum")

    def __init__(self, initial: float = 0.1, maximum: float = 5.0, factor: float = 2.0) -> None:
        if initial <= 0 or maximum < initial or factor < 1:
            raise ValueError("backoff needs 0 < initial <= maximum and factor >= 1")
        self.initial = initial
        self.maximum = maximum
        self.factor = factor
        self._next = initial

    def next(self) -> float:
        delay = self._next
        self._next = min(self.maximum, self._next * self.factor)
        return delay

    def reset(self) -> None:
        self._next = self.initial
