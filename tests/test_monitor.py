"""LinkMonitor (seed 001's TelemetryMonitor) on a fake clock: up on the first frame, down after
the silence timeout, per source, in order, and through a real dispatcher."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from gateway import link_monitor
from gateway.backend import Backend, Outcome, Routes
from gateway.dispatcher import Dispatcher
from gateway.link_monitor import DEFAULT_LINK_TIMEOUT_S, LinkMonitor
from gateway.model import LinkEvent

DEADLINE_S = 5.0


class FakeClock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> FakeClock:
    return FakeClock()


@pytest.fixture
def events() -> list[LinkEvent]:
    return []


@pytest.fixture
def monitor(clock: FakeClock, events: list[LinkEvent]) -> LinkMonitor:
    return LinkMonitor(events.append, timeout_s=2.0, clock=clock)


def test_default_timeout_is_three_seconds(clock: FakeClock, events: list[LinkEvent]) -> None:
    mon = LinkMonitor(events.append, clock=clock)
    assert mon.timeout_s == DEFAULT_LINK_TIMEOUT_S == 3.0
    mon.frame_seen("sim")
    clock.now += 2.5
    assert mon.check() == []
    clock.now += 0.5
    assert [(e.source, e.up) for e in mon.check()] == [("sim", False)]


def test_no_event_before_the_first_frame(monitor: LinkMonitor, clock: FakeClock,
                                         events: list[LinkEvent]) -> None:
    clock.now += 100.0
    assert monitor.check() == []
    assert events == []
    assert monitor.is_up("sim") is None
    assert monitor.silence_s("sim") is None
    assert monitor.states() == {}


def test_first_frame_brings_the_link_up_once(monitor: LinkMonitor, clock: FakeClock,
                                             events: list[LinkEvent]) -> None:
    monitor.frame_seen("sim")
    for _ in range(5):
        clock.now += 0.1
        monitor.frame_seen("sim")
        assert monitor.check() == []
    assert events == [LinkEvent("sim", True, 0.0)]
    assert monitor.is_up("sim") is True
    assert monitor.changes == 1


def test_silence_reaching_the_timeout_gives_one_down_event(
    monitor: LinkMonitor, clock: FakeClock, events: list[LinkEvent]
) -> None:
    monitor.frame_seen("sim")
    clock.now += 1.5
    assert monitor.silence_s("sim") == pytest.approx(1.5)
    assert monitor.check() == []
    clock.now += 0.5  # exactly the timeout
    down = monitor.check()
    assert down == [LinkEvent("sim", False, pytest.approx(2.0))]
    clock.now += 10.0
    assert monitor.check() == []  # still down: no repeat
    assert events == [LinkEvent("sim", True, 0.0), *down]
    assert monitor.is_up("sim") is False


def test_next_frame_after_down_brings_the_link_up_again(
    monitor: LinkMonitor, clock: FakeClock, events: list[LinkEvent]
) -> None:
    monitor.frame_seen("sim")
    clock.now += 5.0
    monitor.check()
    monitor.frame_seen("sim")
    monitor.frame_seen("sim")
    assert [e.up for e in events] == [True, False, True]
    assert monitor.states() == {"sim": True}
    assert monitor.changes == 3


def test_sources_are_tracked_independently(monitor: LinkMonitor, clock: FakeClock,
                                           events: list[LinkEvent]) -> None:
    monitor.frame_seen("radio")
    clock.now += 1.0
    monitor.frame_seen("usb")
    clock.now += 1.0  # radio silent 2.0 s, usb 1.0 s
    assert [(e.source, e.up) for e in monitor.check()] == [("radio", False)]
    monitor.frame_seen("usb")
    clock.now += 1.875
    assert monitor.check() == []
    clock.now += 0.125
    assert [(e.source, e.up) for e in monitor.check()] == [("usb", False)]
    assert [(e.source, e.up) for e in events] == [
        ("radio", True), ("usb", True), ("radio", False), ("usb", False)
    ]


def test_refuses_a_non_positive_timeout(events: list[LinkEvent]) -> None:
    with pytest.raises(ValueError):
        LinkMonitor(events.append, timeout_s=0)


def test_events_reach_backends_on_link_through_a_real_dispatcher(clock: FakeClock) -> None:
    class Watcher(Backend):
        def __init__(self) -> None:
            super().__init__("watcher")
            self.seen: list[tuple[LinkEvent, int]] = []

        def routes(self) -> Routes:
            return Routes().on(LinkEvent, self.on_link)

        def on_link(self, ev: LinkEvent) -> Outcome:
            self.seen.append((ev, threading.get_ident()))
            return Outcome.ACCEPTED

    w = Watcher()
    d = Dispatcher([w])
    assert d.start() == []
    mon = LinkMonitor(d.dispatch, timeout_s=3.0, clock=clock)
    mon.frame_seen("sim")
    clock.now += 3.0
    mon.check()
    mon.frame_seen("sim")
    assert [(e.source, e.up) for e, _ in w.seen] == [("sim", True), ("sim", False),
                                                      ("sim", True)]
    assert {tid for _, tid in w.seen} == {threading.get_ident()}
    assert d.stats()["watcher"] == {"accepted": 3}


def test_a_late_down_cannot_overtake_the_up_that_followed_it(clock: FakeClock) -> None:
    """check() decides "down" and is still delivering it when a frame arrives on another
    thread: the sink must receive down, then up (not up, then a stale down)."""
    delivered: list[tuple[str, bool]] = []
    down_entered, release_down = threading.Event(), threading.Event()

    def sink(ev: LinkEvent) -> None:
        if not ev.up:
            down_entered.set()
            release_down.wait(DEADLINE_S)
        delivered.append((ev.source, ev.up))

    mon = LinkMonitor(sink, timeout_s=1.0, clock=clock)
    mon.frame_seen("sim")
    clock.now += 1.0
    checker = threading.Thread(target=mon.check, daemon=True)
    checker.start()
    assert down_entered.wait(DEADLINE_S)
    source = threading.Thread(target=mon.frame_seen, args=("sim",), daemon=True)
    source.start()
    source.join(DEADLINE_S)
    assert not source.is_alive()  # the source's thread never waits for another's delivery
    release_down.set()
    checker.join(DEADLINE_S)
    assert not checker.is_alive()
    assert delivered == [("sim", True), ("sim", False), ("sim", True)]
    assert mon.is_up("sim") is True


def test_a_sink_may_call_back_into_the_monitor(clock: FakeClock) -> None:
    seen: list[Any] = []
    mon: LinkMonitor

    def sink(ev: LinkEvent) -> None:
        seen.append((ev.up, mon.is_up(ev.source)))
        mon.frame_seen("other")  # e.g. a backend that also reads, feeding the gateway

    mon = LinkMonitor(sink, timeout_s=1.0, clock=clock)
    done = threading.Event()

    def run() -> None:
        mon.frame_seen("sim")
        done.set()

    threading.Thread(target=run, daemon=True).start()
    assert done.wait(DEADLINE_S)
    assert seen[0] == (True, True)
    assert mon.states() == {"sim": True, "other": True}


def test_link_events_carry_the_via_of_the_sources_messages(events: list[LinkEvent],
                                                           clock: FakeClock) -> None:
    mon = LinkMonitor(events.append, timeout_s=1.0, clock=clock)
    mon.frame_seen("zenoh:", "zenoh:gw-far")
    clock.now += 1.0
    mon.check()
    assert [(e.up, e.via) for e in events] == [(True, "zenoh:gw-far"), (False, "zenoh:gw-far")]


def test_links_are_kept_per_vehicle_and_name_source_and_vehicle(
        monitor: LinkMonitor, clock: FakeClock, events: list[LinkEvent]) -> None:
    """One source hearing two systems has two links; each event names both."""
    monitor.frame_seen("mav", "mavlink:1", "drone-1")
    monitor.frame_seen("mav", "mavlink:2", "drone-2")
    clock.now += 1.5
    monitor.frame_seen("mav", "mavlink:1", "drone-1")
    clock.now += 1.0
    monitor.check()
    assert [(e.source, e.vehicle, e.via, e.up) for e in events] == [
        ("mav", "drone-1", "mavlink:1", True),
        ("mav", "drone-2", "mavlink:2", True),
        ("mav", "drone-2", "mavlink:2", False)]
    assert monitor.states() == {"drone-1": True, "drone-2": False}


def test_the_table_of_links_is_bounded(monitor: LinkMonitor, events: list[LinkEvent]) -> None:
    for i in range(link_monitor.MAX_LINKS + 10):
        monitor.frame_seen("zenoh", "", f"v{i}")
    assert len(monitor.states()) == link_monitor.MAX_LINKS
    assert monitor.untracked == 10
    assert len(events) == link_monitor.MAX_LINKS
