"""The rocket node's rate gates skipped while shut (backends/mavlink/translate.py): an SM
update arriving before any of its gates can open is not put through them, and what goes
out is the same, message for message, as with every gate asked at every update."""

from __future__ import annotations

import itertools
import math
import random

from backends.mavlink.translate import AuroraVehicle
from gateway.flight import FlightModel, FlightProfile
from gateway.model import SmUpdate
from gateway.sources.sim import flight_messages


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _signature(out: list) -> list[tuple[str, tuple]]:
    """Each message's type and fields (pymavlink messages: their field values)."""
    return [(type(m).__name__, tuple(getattr(m, f) for f in m.get_fieldnames()))
            for m in out]


def test_skipping_shut_gates_sends_exactly_what_asking_every_gate_sends() -> None:
    rng = random.Random(26)
    clock_a, clock_b = Clock(), Clock()
    fast = AuroraVehicle(clock=clock_a)  # skips the gates while they are shut
    every = AuroraVehicle(clock=clock_b)  # made to ask every gate at every update
    updates = [m for _, m in itertools.islice(
        flight_messages(FlightModel(FlightProfile()), 2000.0, 0.0), 60_000)
        if isinstance(m, SmUpdate)]
    skipped = 0
    for k, m in enumerate(updates):
        step = rng.choice((0.0, 1e-5, 4e-5, 4e-5, 1e-3, 0.02))  # bursts and gaps
        clock_a.now += step
        clock_b.now += step
        if k == 30_000:  # a ground station changes ATTITUDE's rate mid-flight
            for v in (fast, every):
                v._set_interval(30, 5_000)  # ATTITUDE at 200 Hz
        every._sm_gates_shut_until = -math.inf
        skipped += clock_a.now < fast._sm_gates_shut_until
        assert _signature(fast.on_sm_update(m)) == _signature(every.on_sm_update(m)), k
    assert skipped > len(updates) // 2  # the shortcut was taken, most of the time
    assert fast.stats.updates == every.stats.updates == len(updates)
