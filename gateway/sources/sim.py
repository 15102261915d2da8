"""Simulated flight source: the SIMPLE state machine's flight, repeated, as the rocket sends it.

The flight is paced on the source's I/O loop (:class:`gateway.pacing.Pacer`).  Messages are
encoded to wire frames and decoded again, so what the gateway handles is exactly
what a receiver of the real frames would see (f32 rounding of the 36-byte revision included).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from typing import Any

from gateway.config import Key, Schema
from gateway.flight import FlightModel, FlightProfile
from gateway.model import SmUpdate, Status
from gateway.pacing import Pacer
from gateway.sources import Source
from gateway.wire import Decoder, encode

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


class SimSource(Source):
    NAME = "sim"
    CONFIG = Schema(
        rate_hz=Key(float, 10.0, "SM_UPDATE rate (simulated time)", minimum=0.1, maximum=1000),
        status_hz=Key(float, 1.0, "STATUS rate; 0 = none", minimum=0, maximum=100),
        speed=Key(float, 1.0, "time compression: N = N times faster, 0 = as fast as possible",
                  minimum=0),
        revision=Key(int, 64, "SM_UPDATE payload length", choices=(36, 64)),
        cycles=Key(int, 0, "flights to simulate; 0 = for ever", minimum=0),
        pad_idle_s=Key(float, 5.0, "seconds IDLE on the pad", minimum=0),
        pad_armed_s=Key(float, 10.0, "seconds ARMED on the pad before launch", minimum=0.1),
    )

    @classmethod
    def url_options(cls, rest: str | None) -> dict[str, Any]:
        """``sim`` (or ``sim:``): the options come from the flags or a file."""
        if rest:
            raise ValueError(f"sim takes nothing after 'sim:', got {rest!r}")
        return {}

    def __init__(self, rate_hz: float = 10.0, status_hz: float = 1.0, speed: float = 1.0,
                 revision: int = 64, cycles: int = 0, pad_idle_s: float = 5.0,
                 pad_armed_s: float = 10.0, name: str | None = None) -> None:
        super().__init__(name)
        self.model = FlightModel(FlightProfile(idle_s=pad_idle_s, armed_s=pad_armed_s,
                                               revision=revision))
        self.rate_hz = rate_hz
        self.status_hz = status_hz
        self.speed = speed
        self.cycles = cycles
        self.decoder = Decoder(origin=self.name)
        self.sent = 0
        self._pacer: Pacer[bytes] | None = None

    def begin(self) -> None:
        loop = self.io_loop
        assert loop is not None
        self._pacer = Pacer(loop, flight_frames(self.model, self.rate_hz, self.status_hz,
                                                self.cycles),
                            self.speed, self._deliver, on_end=self.finish)
        self._pacer.start()

    def _deliver(self, t: float, frame: bytes) -> None:
        for msg in self.decoder.feed(frame):
            self.sent += 1
            self.emit(msg)

    def halt(self) -> None:
        if self._pacer is not None:
            self._pacer.cancel()
        self.finish()

    def stats(self) -> dict[str, Any]:
        return {"sent": self.sent}
