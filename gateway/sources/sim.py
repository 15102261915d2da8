"""Simulated flight source: the SIMPLE state machine's flight, repeated, as the rocket sends it.

The flight is paced on the source's I/O loop (:class:`gateway.pacing.Pacer`).  Messages are
encoded to wire frames and decoded again, so what the gateway handles is exactly
what a receiver of the real frames would see (f32 rounding of the 36-byte revision included).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import Any

from gateway.flight import FlightModel, FlightProfile
from gateway.model import SmUpdate, Status
from gateway.sources.options import SimOptions
from gateway.sources.paced import PacedFrameSource
from gateway.wire import encode

BOOT_UPTIME_MS = 12_000  # the flight computer's uptime when the simulation starts


def flight_messages(
    model: FlightModel,
    rate_hz: float = 10.0,
    status_hz: float = 1.0,
    cycles: int = 0,
) -> Iterator[tuple[float, SmUpdate | Status]]:
    """(simulated time, message) for the flight, SM_UPDATE at ``rate_hz`` and STATUS at
    ``status_hz``, merged in time order; ``cycles`` 0 repeats for ever.

    With ``cycles`` N the stream ends with the first SM_UPDATE at or after N × ``cycle_s``:
    the return to IDLE (the disarm) that closes the last flight, so a one-flight run shows
    the whole flight, not a rocket left LANDED and armed."""
    if rate_hz <= 0:
        raise ValueError("rate_hz must be positive")
    sm_dt = 1.0 / rate_hz
    st_dt = 1.0 / status_hz if status_hz > 0 else None
    end = model.cycle_s * cycles if cycles else None
    next_st = 0.0
    for k in itertools.count():
        t = k * sm_dt
        while st_dt is not None and next_st <= t:
            yield next_st, model.status(next_st, BOOT_UPTIME_MS + round(next_st * 1000))
            next_st += st_dt
        yield t, model.sm_update(t, BOOT_UPTIME_MS + round(t * 1000))
        if end is not None and t >= end:
            return


def flight_frames(model: FlightModel, rate_hz: float = 10.0, status_hz: float = 1.0,
                  cycles: int = 0) -> Iterator[tuple[float, bytes]]:
    """The same as :func:`flight_messages`, encoded as wire frames."""
    for t, msg in flight_messages(model, rate_hz, status_hz, cycles):
        yield t, encode(msg)


class SimSource(PacedFrameSource):
    NAME = "sim"
    OPTIONS = SimOptions

    @classmethod
    def url_options(cls, rest: str | None) -> dict[str, Any]:
        """``sim`` (or ``sim:``): the options come from the flags or a file."""
        if rest:
            raise ValueError(f"sim takes nothing after 'sim:', got {rest!r}")
        return {}

    def __init__(self, options: SimOptions | None = None, name: str | None = None) -> None:
        super().__init__(name)
        options = options or SimOptions()
        # lazy: the physics are the default profile's (valid); the flight is integrated by
        # the first sample, after the backends have started, not at start-up
        self.model = FlightModel(FlightProfile(idle_s=options.pad_idle_s,
                                               armed_s=options.pad_armed_s,
                                               revision=options.revision), lazy=True)
        self.rate_hz = options.rate_hz
        self.status_hz = options.status_hz
        self.speed = options.speed
        self.cycles = options.cycles

    def begin(self) -> None:
        self.pace(flight_frames(self.model, self.rate_hz, self.status_hz, self.cycles),
                  self.speed)

    def stats(self) -> dict[str, Any]:
        return {"sent": self.sent}
