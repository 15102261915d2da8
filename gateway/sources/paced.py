"""A source that paces wire frames on its I/O loop (:class:`gateway.pacing.Pacer`) and emits
what they decode to: what the simulated flight and a recording's replay have in common."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from gateway.pacing import Pacer
from gateway.sources import Source
from gateway.wire import Decoder


class PacedFrameSource(Source):
    """Base class: :meth:`pace` hands ``(time, frame)`` pairs (or ``(time, item)`` pairs
    that a subclass's ``_deliver`` takes apart) to a :class:`Pacer` at ``speed``; each frame
    is decoded (as a receiver of the real frames would) and its messages emitted, counted in
    ``sent``; :meth:`halt` cancels the pacing."""

    def __init__(self, name: str | None = None) -> None:
        super().__init__(name)
        self.decoder = Decoder(origin=self.name, vehicle=self.vehicle)
        self.sent = 0
        self._pacer: Pacer[Any] | None = None

    def pace(self, frames: Iterator[tuple[float, Any]], speed: float) -> None:
        """Start pacing ``frames`` on the source's loop; the source finishes at their end."""
        loop = self.io_loop
        assert loop is not None
        self._pacer = Pacer(loop, frames, speed, self._deliver, on_end=self.finish)
        self._pacer.start()

    def _deliver(self, t: float, frame: Any) -> None:
        for msg in self.decoder.feed(frame):
            self.sent += 1
            self.emit(msg)

    def halt(self) -> None:
        if self._pacer is not None:
            self._pacer.cancel()
        self.finish()
