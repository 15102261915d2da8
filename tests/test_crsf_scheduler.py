"""The telemetry scheduler under a fake clock: per-type rates, the refresh bound, the hold
time, immediate flight-mode frames on a change, the total-rate cap, and no backlog."""

from __future__ import annotations

import itertools
import math
from collections import Counter, defaultdict

import pytest

from backends.crsf.backend import CrsfBackend
from backends.crsf.frames import (
    FRAME_ATTITUDE,
    FRAME_BARO_ALTITUDE,
    FRAME_FLIGHT_MODE,
    FRAME_GPS,
    FRAME_VARIO,
)
from backends.crsf.scheduler import Scheduler

DEFAULT_RATES = {FRAME_ATTITUDE: 10.0, FRAME_BARO_ALTITUDE: 5.0, FRAME_VARIO: 2.0,
                 FRAME_FLIGHT_MODE: 2.0}
TICK = 0.001


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def run(sched: Scheduler, clock: Clock, seconds: float, publish_every: float | None = 0.01,
        types: list[int] | None = None) -> list[tuple[float, int, object]]:
    """Advance the fake clock in 1 ms ticks, publishing a new value of every type each
    ``publish_every`` seconds and taking whatever the scheduler offers; returns the sends."""
    sent = []
    types = list(DEFAULT_RATES) if types is None else types
    start = clock.now
    steps = round(seconds / TICK)
    every = None if publish_every is None else round(publish_every / TICK)
    for i in range(steps):
        clock.now = start + i * TICK
        if every and i % every == 0:
            for t in types:
                sched.publish(t, (t, clock.now))
        while (item := sched.take()) is not None:
            sent.append((clock.now, *item))
    return sent


def gaps(sent: list[tuple[float, int, object]]) -> dict[int, float]:
    last: dict[int, float] = {}
    worst: dict[int, float] = defaultdict(float)
    for t, ftype, _ in sent:
        if ftype in last:
            worst[ftype] = max(worst[ftype], t - last[ftype])
        last[ftype] = t
    return worst


def max_in_window(times: list[float], window: float = 1.0) -> int:
    best, j = 0, 0
    for i, t in enumerate(times):
        while times[j] <= t - window + 1e-9:  # the window (t − 1 s, t]
            j += 1
        best = max(best, i - j + 1)
    return best


def test_per_type_rates_with_the_backend_defaults() -> None:
    clock = Clock()
    backend = CrsfBackend(clock=clock)  # the scheduler exactly as the backend configures it
    sent = run(backend.scheduler, clock, 30.0, types=list(DEFAULT_RATES))
    counts = Counter(ftype for _, ftype, _ in sent)
    for ftype, hz in DEFAULT_RATES.items():
        assert counts[ftype] == pytest.approx(hz * 30, rel=0.03), hex(ftype)
    assert backend.scheduler.stats()["sent_0x1E"] == counts[FRAME_ATTITUDE]


def test_latest_value_is_sent() -> None:
    clock = Clock()
    s = Scheduler(DEFAULT_RATES, clock=clock)
    for v in range(5):
        s.publish(FRAME_ATTITUDE, v)
    assert s.take() == (FRAME_ATTITUDE, 4)
    assert s.take() is None


def test_every_type_refreshed_within_2_s_even_when_nothing_changes() -> None:
    clock = Clock()
    s = Scheduler({**DEFAULT_RATES, FRAME_GPS: 0.1}, hold_s=0, clock=clock)  # GPS asks 0.1 Hz
    for t in (*DEFAULT_RATES, FRAME_GPS):
        s.publish(t, "once")
    sent = run(s, clock, 20.0, publish_every=None)
    assert set(Counter(f for _, f, _ in sent)) == {*DEFAULT_RATES, FRAME_GPS}
    assert max(gaps(sent).values()) <= 2.0


def test_refresh_bound_holds_under_overload() -> None:
    """Eleven types at 10 Hz want 110 frames/s; the cap allows 20: each still goes out at
    least every 2 s, evenly, and no second has more than 20 frames."""
    clock = Clock()
    s = Scheduler({t: 10.0 for t in range(11)}, clock=clock)
    sent = run(s, clock, 20.0, types=list(range(11)))
    assert max(gaps(sent).values()) <= 2.0
    counts = Counter(f for _, f, _ in sent)
    assert max(counts.values()) - min(counts.values()) <= 2
    assert max_in_window([t for t, _, _ in sent]) <= 20
    assert len(sent) == pytest.approx(20 * 20, abs=2)


@pytest.mark.parametrize("cap", [5.0, 20.0, 50.0])
def test_total_rate_cap(cap: float) -> None:
    clock = Clock()
    s = Scheduler({t: 100.0 for t in range(6)}, max_rate_hz=cap, clock=clock)
    sent = run(s, clock, 10.0, types=list(range(6)))
    times = [t for t, _, _ in sent]
    assert min(b - a for a, b in itertools.pairwise(times)) >= 1 / cap - 1e-9
    assert max_in_window(times) <= cap


def test_hold_stops_refreshing_a_value_that_stopped_updating() -> None:
    clock = Clock()
    s = Scheduler({FRAME_ATTITUDE: 10.0, FRAME_GPS: 1.0}, hold_s=5.0, clock=clock)
    s.publish(FRAME_GPS, "fix")
    sent = run(s, clock, 12.0, types=[FRAME_ATTITUDE])  # attitude keeps coming, GPS does not
    gps_times = [t for t, f, _ in sent if f == FRAME_GPS]
    assert gps_times and max(gps_times) <= 5.0 + 0.1
    assert max(t for t, f, _ in sent if f == FRAME_ATTITUDE) >= 11.8
    s.publish(FRAME_GPS, "new fix")  # a new value makes it live again
    later = run(s, clock, 1.0, types=[FRAME_ATTITUDE])
    assert (FRAME_GPS, "new fix") in [(f, v) for _, f, v in later]


def test_flight_mode_change_goes_out_at_once_ahead_of_the_cap() -> None:
    clock = Clock()
    s = Scheduler(DEFAULT_RATES, clock=clock)
    s.publish(FRAME_ATTITUDE, "att")
    assert s.take() == (FRAME_ATTITUDE, "att")  # the cap now holds everything for 50 ms
    clock.now += 0.001
    s.publish_change(FRAME_FLIGHT_MODE, "BOOST")
    assert s.next_due() == clock.now
    assert s.take() == (FRAME_FLIGHT_MODE, "BOOST")
    assert s.take() is None


def test_a_burst_of_state_changes_keeps_every_state_in_order() -> None:
    clock = Clock()
    s = Scheduler(DEFAULT_RATES, clock=clock)
    states = ["BOOST", "BURNOUT", "APOGEE", "MAIN", "REDUNDANT", "LANDED"]
    for name in states:  # faster than any frame rate
        s.publish_change(FRAME_FLIGHT_MODE, name)
    got = []
    while (item := s.take()) is not None:
        got.append(item[1])
    assert got == states
    assert s.mailbox(FRAME_FLIGHT_MODE).peek() == "LANDED"
    assert s.changes_sent == len(states)


def test_change_ring_overflow_is_counted() -> None:
    s = Scheduler(DEFAULT_RATES, change_depth=4, clock=Clock())
    results = [s.publish_change(FRAME_FLIGHT_MODE, i) for i in range(6)]
    assert results == [True] * 4 + [False] * 2
    assert s.changes_dropped == 2
    assert s.mailbox(FRAME_FLIGHT_MODE).peek() == 5  # the mailbox still has the latest


def test_no_backlog_after_a_stalled_consumer() -> None:
    """Ten seconds of updates while nobody takes: afterwards one frame per type, the latest."""
    clock = Clock()
    s = Scheduler(DEFAULT_RATES, clock=clock)
    for i in range(1000):
        clock.now = i * 0.01
        for t in DEFAULT_RATES:
            s.publish(t, i)
    got = []
    for _ in range(len(DEFAULT_RATES)):
        clock.now += 0.05
        item = s.take()
        assert item is not None
        got.append(item)
    assert sorted(got) == sorted((t, 999) for t in DEFAULT_RATES)
    clock.now += 0.05
    assert s.take() is None  # nothing new: nothing due until its period or refresh


def test_disabled_types_and_next_due() -> None:
    clock = Clock()
    s = Scheduler({FRAME_ATTITUDE: 10.0, FRAME_GPS: 0.0}, clock=clock)
    assert not s.scheduled(FRAME_GPS)
    assert s.publish(FRAME_GPS, 1) is False and s.publish_change(FRAME_GPS, 1) is False
    assert s.next_due() == math.inf
    s.publish(FRAME_ATTITUDE, 1)
    assert s.next_due() == clock.now
    assert s.take() == (FRAME_ATTITUDE, 1)
    s.publish(FRAME_ATTITUDE, 2)
    assert s.next_due() == pytest.approx(0.1)


@pytest.mark.parametrize("kwargs", [{"max_rate_hz": 0}, {"refresh_s": 0}, {"hold_s": -1}])
def test_bad_parameters(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        Scheduler(DEFAULT_RATES, **kwargs)
    with pytest.raises(ValueError):
        Scheduler({FRAME_ATTITUDE: -1.0})
