"""The hand-over from the dispatcher's thread to a backend's loop (gateway/handover.py), on a
real IoLoop and through the real Dispatcher."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import DEADLINE_S, HeldLoop

from gateway.backend import Backend, Routes
from gateway.dispatcher import Dispatcher
from gateway.handover import Handover
from gateway.io.ioloop import IoLoop
from gateway.model import SmUpdate, Status
from gateway.outcome import Outcome


def sm(t: int) -> SmUpdate:
    return SmUpdate(t, 1, False, 0, float(t), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def st(t: int) -> Status:
    return Status(t, 1, 0, 0)


@pytest.fixture
def loop() -> Iterator[IoLoop]:
    lp = IoLoop("test-handover")
    lp.start()
    yield lp
    lp.stop()
    lp.close()


class LoopBackend(Backend):
    """A backend whose handlers run on its loop: it keeps what it got, and on which thread."""

    NAME = "looped"

    def __init__(self, loop: IoLoop, depth: int = 8, fail_on: frozenset[int] = frozenset()
                 ) -> None:
        super().__init__()
        self.loop = loop
        self.handover = Handover(self.name, depth, after_batch=self._batch_done)
        self.got: list[tuple[str, int]] = []
        self.on_loop: set[bool] = set()
        self.batch_sizes: list[int] = []
        self._in_batch = 0
        self.fail_on = fail_on
        self.done = threading.Condition()

    def init(self) -> None:
        self.handover.open(self.loop)

    def close(self) -> None:
        self.handover.close()

    def routes(self) -> Routes:
        return (Routes(handover=self.handover).on(SmUpdate, self.send_sm_update)
                .on(Status, self.send_status))

    def send_sm_update(self, msg: SmUpdate) -> None:
        self.on_loop.add(self.loop.in_loop_thread)
        self._in_batch += 1
        if msg.timestamp_ms in self.fail_on:
            raise ValueError(f"cannot take {msg.timestamp_ms}")
        with self.done:
            self.got.append(("sm", msg.timestamp_ms))
            self.done.notify_all()

    def send_status(self, msg: Status) -> None:
        self._in_batch += 1
        with self.done:
            self.got.append(("status", msg.timestamp_ms))
            self.done.notify_all()

    def _batch_done(self) -> None:
        self.batch_sizes.append(self._in_batch)
        self._in_batch = 0

    def wait_got(self, n: int) -> bool:
        with self.done:
            return self.done.wait_for(lambda: len(self.got) >= n, DEADLINE_S)


def test_the_handler_runs_on_the_loop_in_order_through_the_dispatcher(loop: IoLoop) -> None:
    b = LoopBackend(loop, depth=64)
    d = Dispatcher([b])
    assert d.start() == []
    msgs: list[Any] = [sm(i) if i % 3 else st(i) for i in range(40)]
    assert [d.dispatch(m) for m in msgs] == [Outcome.ACCEPTED] * 40
    assert b.wait_got(40)
    assert b.got == [("sm" if i % 3 else "status", i) for i in range(40)]
    assert b.on_loop == {True}  # never the dispatcher's thread
    d.close()


def test_a_full_hand_over_refuses_with_queue_full_counted(loop: IoLoop) -> None:
    b = LoopBackend(loop, depth=8)
    d = Dispatcher([b])
    assert d.start() == []
    with HeldLoop(loop):
        outcomes = [d.dispatch(sm(i)) for i in range(13)]
        assert b.handover.queued() == 8
    assert outcomes == [Outcome.ACCEPTED] * 8 + [Outcome.QUEUE_FULL] * 5
    assert b.handover.dropped_queue_full == 5
    assert d.stats()["looped"]["queue-full"] == 5  # the dispatcher counts the outcome
    assert b.wait_got(8)
    assert b.got == [("sm", i) for i in range(8)]  # the first eight, in order
    assert d.dispatch(sm(99)) is Outcome.ACCEPTED  # room again once drained
    d.close()


def test_messages_queued_while_the_loop_is_busy_are_one_drain(loop: IoLoop) -> None:
    b = LoopBackend(loop, depth=256)
    h = b.handover
    b.init()
    routes = dict(b.routes())
    with HeldLoop(loop):
        for i in range(100):
            assert h.post(routes[SmUpdate], sm(i)) is Outcome.ACCEPTED
    assert b.wait_got(100)
    assert h.barrier(DEADLINE_S)
    # one drain ran, for all 100 (a drain per post would count 100 batches, 99 empty)
    assert (h.batches, h.handled, b.batch_sizes) == (1, 100, [100])
    b.close()


def test_a_raising_handler_is_isolated_counted_and_logged_once(
        loop: IoLoop, caplog: pytest.LogCaptureFixture) -> None:
    b = LoopBackend(loop, depth=64, fail_on=frozenset({2, 7}))
    d = Dispatcher([b])
    assert d.start() == []
    with caplog.at_level(logging.DEBUG, logger="gateway.handover"):
        for i in range(10):
            assert d.dispatch(sm(i)) is Outcome.ACCEPTED
        assert b.wait_got(8)
        assert b.handover.barrier(DEADLINE_S)
    assert [t for _, t in b.got] == [0, 1, 3, 4, 5, 6, 8, 9]  # the rest still handled
    assert b.handover.handler_errors == 2
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "ValueError" in errors[0].getMessage()  # once per kind
    d.close()


def test_not_ready_before_open_after_close_and_while_not_ready(loop: IoLoop) -> None:
    up = threading.Event()
    h = Handover("gated", 4, ready=up.is_set)
    got: list[SmUpdate] = []
    assert h.post(got.append, sm(0)) is Outcome.NOT_READY  # not open
    h.open(loop)
    assert h.post(got.append, sm(1)) is Outcome.NOT_READY  # open, the link is down
    up.set()
    assert h.post(got.append, sm(2)) is Outcome.ACCEPTED
    assert h.barrier(DEADLINE_S) and got == [sm(2)]
    h.close()
    assert h.post(got.append, sm(3)) is Outcome.NOT_READY
    assert h.dropped_not_ready == 3 and h.dropped == 3


def test_close_runs_what_is_queued(loop: IoLoop) -> None:
    b = LoopBackend(loop, depth=64)
    b.init()
    routes = dict(b.routes())
    with HeldLoop(loop):
        for i in range(20):
            b.handover.post(routes[SmUpdate], sm(i))
        closing = threading.Thread(target=b.close)
        closing.start()
    closing.join(DEADLINE_S)
    assert [t for _, t in b.got] == list(range(20))
    assert b.handover.dropped_closed == 0
    assert b.handover.post(routes[SmUpdate], sm(0)) is Outcome.NOT_READY


def test_close_discards_counted_within_its_bound_when_the_loop_is_stuck(loop: IoLoop) -> None:
    h = Handover("stuck", 64)
    h.open(loop)
    got: list[SmUpdate] = []
    with HeldLoop(loop):
        for i in range(10):
            h.post(got.append, sm(i))
        t0 = time.monotonic()
        assert h.close(timeout=0.2) == 10
        assert time.monotonic() - t0 < 0.2 + 2.0  # within its bound (and slack for the load)
    assert h.dropped_closed == 10 and h.dropped == 10
    assert h.barrier(DEADLINE_S) and got == []  # discarded, never handled later
    assert h.close() == 0  # safe twice


def test_a_depth_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="depth"):
        Handover("x", 0)


class CountingLock:
    """A context manager that says whether it is held and how often it was taken."""

    def __init__(self) -> None:
        self.held = False
        self.taken = 0

    def __enter__(self) -> None:
        self.held = True
        self.taken += 1

    def __exit__(self, *exc: object) -> None:
        self.held = False


def test_the_lock_is_held_once_per_batch_around_the_handlers(loop: IoLoop) -> None:
    lock = CountingLock()
    seen: list[bool] = []
    h = Handover("locked", 64, lock=lock, after_batch=lambda: seen.append(lock.held))
    h.open(loop)

    def handler(msg: SmUpdate) -> None:
        seen.append(lock.held)

    with HeldLoop(loop):
        for i in range(10):
            h.post(handler, sm(i))
    assert h.barrier(DEADLINE_S)
    assert seen == [True] * 11 and lock.taken == 1 and not lock.held
    h.close()


def test_skipped_messages_are_accepted_in_the_posters_thread_never_queued(loop: IoLoop) -> None:
    skipped: list[SmUpdate] = []

    def mine(msg: SmUpdate) -> bool:  # e.g. it came from where the backend would send it
        if msg.timestamp_ms % 2:
            skipped.append(msg)
            return True
        return False

    h = Handover("skipping", 4, skip=mine)
    h.open(loop)
    got: list[SmUpdate] = []
    with HeldLoop(loop):
        outcomes = [h.post(got.append, sm(i)) for i in range(10)]
        assert h.queued() == 4  # the odd ones take no room: four even fit, the fifth is refused
    assert outcomes == [Outcome.ACCEPTED] * 8 + [Outcome.QUEUE_FULL, Outcome.ACCEPTED]
    assert h.barrier(DEADLINE_S)
    assert [m.timestamp_ms for m in got] == [0, 2, 4, 6]
    assert [m.timestamp_ms for m in skipped] == [1, 3, 5, 7, 9]
    h.close()


def test_it_opens_again_on_a_new_loop_after_close(loop: IoLoop) -> None:
    h = Handover("reopened", 8)
    h.open(loop)
    got: list[SmUpdate] = []
    with HeldLoop(loop):
        h.post(got.append, sm(0))  # a drain is scheduled on this loop ...
        loop.stop(0.1)  # ... which stops before it runs (the hold ends it after the deadline)
        h.close(timeout=0.1)
    assert h.dropped_closed == 1
    second = IoLoop("second")
    second.start()
    try:
        h.open(second)
        assert h.post(got.append, sm(1)) is Outcome.ACCEPTED
        assert h.barrier(DEADLINE_S) and got == [sm(1)]
    finally:
        h.close()
        second.stop()
        second.close()


class FakeClock:
    """A clock the test moves (the hand-over's rate windows, without waiting)."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_a_hand_over_sized_by_time_holds_span_s_of_the_post_rate(loop: IoLoop) -> None:
    clock = FakeClock()
    h = Handover("timed", depth=8, span_s=1.0, max_depth=100_000, clock=clock)
    h.open(loop)
    got: list[int] = []
    with HeldLoop(loop):
        # a burst in a new window: its rate is at least 3000 per 0.5 s, so the bound grows
        # past the floor of 8 as they come and all 3000 wait
        burst = [h.post(got.append, i) for i in range(3000)]
        assert burst == [Outcome.ACCEPTED] * 3000
        # 2 s later, the loop still held: 8000 offered over 2 s is 4000/s; 1 s of that
        # may wait — more than that once the bound is next looked at (it was at most 6000)
        clock.now += 2.0
        more = [h.post(got.append, 3000 + i) for i in range(5000)]
        accepted = more.count(Outcome.ACCEPTED)
        assert 0 < accepted < 3000 and more[accepted:] == [Outcome.QUEUE_FULL] * (5000 - accepted)
        assert h.limit == 7999 // 2 and h.queued() == 3000 + accepted
        assert h.dropped_queue_full == 5000 - accepted
        assert h.stats()["queue_limit"] == h.limit
    assert h.barrier(DEADLINE_S)
    assert got == list(range(3000 + accepted))  # in order, none lost but those refused
    h.close()


def test_a_hand_over_sized_by_time_never_exceeds_max_depth(loop: IoLoop) -> None:
    h = Handover("timed", depth=8, span_s=1.0, max_depth=100)
    h.open(loop)
    with HeldLoop(loop):
        outcomes = [h.post(lambda m: None, i) for i in range(500)]
        assert h.queued() == 100
    assert outcomes == [Outcome.ACCEPTED] * 100 + [Outcome.QUEUE_FULL] * 400
    assert h.dropped_queue_full == 400
    h.close()


def test_a_hand_over_sized_by_time_shrinks_to_its_floor_when_the_rate_falls(
        loop: IoLoop) -> None:
    clock = FakeClock()
    h = Handover("timed", depth=8, span_s=1.0, max_depth=10_000, clock=clock)
    h.open(loop)
    with HeldLoop(loop):
        for i in range(2000):
            h.post(lambda m: None, i)
    assert h.barrier(DEADLINE_S)
    clock.now += 1.0  # a window of 2000/s ends at the next drain
    h.post(lambda m: None, 0)
    assert h.barrier(DEADLINE_S)
    assert h.limit == 2001
    clock.now += 10.0  # 10 s, one post: the next window's rate is 0.1/s
    h.post(lambda m: None, 0)
    assert h.barrier(DEADLINE_S)
    assert h.limit == 8
    clock.now += 1.0  # 20 offered in the window's first second: about 20 may wait
    with HeldLoop(loop):
        first = [h.post(lambda m: None, i) for i in range(20)]
        clock.now += 1.0  # the next second, still held: 40 offered over 2 s is 20/s
        second = [h.post(lambda m: None, i) for i in range(20)]
        assert h.queued() == 19
    assert first.count(Outcome.QUEUE_FULL) == 1  # at 8 of 8 offered; the rate grew after
    assert second == [Outcome.QUEUE_FULL] * 20
    h.close()


def test_a_batch_through_the_dispatcher_wakes_the_loop_once(loop: IoLoop) -> None:
    b = LoopBackend(loop, depth=256)
    d = Dispatcher([b])
    assert d.start() == []
    for k in range(3):
        d.dispatch_batch([sm(100 * k + i) if i % 10 else st(100 * k + i) for i in range(100)])
        assert b.handover.barrier(DEADLINE_S)
    assert b.wait_got(300)
    # one drain per batch, however fast the loop (no drain starts before a batch is posted)
    assert b.handover.batches == 3 and b.batch_sizes == [100, 100, 100]
    assert b.got == [("status" if i % 10 == 0 else "sm", i) for k in range(3)
                     for i in range(100 * k, 100 * k + 100)]
    assert d.stats()["looped"]["accepted"] == 300 and d.dispatched == 300
    d.close()


def test_a_batch_past_a_full_hand_over_counts_what_was_refused(loop: IoLoop) -> None:
    b = LoopBackend(loop, depth=8)
    d = Dispatcher([b])
    assert d.start() == []
    with HeldLoop(loop):
        d.dispatch_batch([sm(i) for i in range(13)])
        assert b.handover.queued() == 8
    assert b.wait_got(8)
    assert d.stats()["looped"]["queue-full"] == 5 and b.handover.dropped_queue_full == 5
    d.close()
