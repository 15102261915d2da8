"""The loop's one facility for blocking work (:class:`gateway.io.ioloop.BlockingCalls`,
:meth:`IoLoop.run_blocking`): bounded, counted, results handed back on the loop; and what runs
on it — a port's open that hangs does not stall the other engines of a shared loop.

Synchronisation is on events with deadlines; each test that counts threads uses a pool of its
own (with its own thread names), so the process-wide pool other tests use does not interfere.
"""

from __future__ import annotations

import itertools
import os
import threading
from collections.abc import Iterator
from typing import Any

import pytest
import serial
from helpers import DEADLINE_S, wait_for

from gateway.io.ioloop import BlockingCall, BlockingCalls, IoLoop
from gateway.io.port import PortEngine
from gateway.io.transport import open_serial

_names = itertools.count()


def pool_threads(pool: BlockingCalls) -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(f"{pool.name}-")]


@pytest.fixture
def pool() -> Iterator[BlockingCalls]:
    p = BlockingCalls(workers=2, idle_s=0.05, name=f"test-pool{next(_names)}")
    yield p
    assert wait_for(lambda: p.stats()["workers"] == 0 and not pool_threads(p))


@pytest.fixture
def loop(pool: BlockingCalls) -> Iterator[IoLoop]:
    lp = IoLoop("blocking-test", blocking=pool)
    lp.start()
    yield lp
    lp.stop(1.0)
    lp.close()


def test_calls_beyond_the_bound_wait_their_turn_and_are_counted(pool: BlockingCalls) -> None:
    release = threading.Event()
    started: list[int] = []
    lock = threading.Lock()

    def blocked(i: int) -> int:
        with lock:
            started.append(i)
        release.wait(DEADLINE_S)
        return i

    calls = [pool.submit(lambda i=i: blocked(i), name=f"c{i}") for i in range(6)]
    assert wait_for(lambda: len(started) == 2)  # both workers busy ...
    st = pool.stats()
    assert st["workers"] == st["workers_peak"] == 2 and len(pool_threads(pool)) == 2
    assert st["queued"] == st["queued_peak"] == 4  # ... the other four queued, not threads
    assert not any(c.done for c in calls)
    release.set()
    assert all(c.wait(DEADLINE_S) for c in calls)
    assert [c.result for c in calls] == list(range(6))
    assert sorted(started) == list(range(6)) and started[2:] == [2, 3, 4, 5]  # in order
    st = pool.stats()
    assert st["calls"] == 6 and st["failed"] == 0 and st["queued"] == 0
    assert st["workers_peak"] == 2


def test_a_failing_call_is_counted_and_its_error_kept(pool: BlockingCalls) -> None:
    def fail() -> None:
        raise OSError("no such port")

    call = pool.submit(fail)
    assert call.wait(DEADLINE_S)
    assert isinstance(call.error, OSError) and call.result is None
    assert pool.stats()["failed"] == 1
    ok = pool.submit(lambda: 42)  # the worker carries on
    assert ok.wait(DEADLINE_S) and ok.result == 42


def test_idle_workers_end_and_new_calls_start_them_again(pool: BlockingCalls) -> None:
    assert pool.submit(lambda: None).wait(DEADLINE_S)
    assert wait_for(lambda: pool.stats()["workers"] == 0 and not pool_threads(pool))
    assert pool.submit(lambda: 7).wait(DEADLINE_S)
    assert pool.stats()["calls"] == 2


def test_a_long_call_gets_a_thread_of_its_own_and_leaves_the_workers_free(
        pool: BlockingCalls) -> None:
    stop = threading.Event()
    longs = [pool.submit(lambda: stop.wait(DEADLINE_S), name=f"run{i}", long=True)
             for i in range(3)]
    assert wait_for(lambda: pool.stats()["long_running"] == 3)
    short = [pool.submit(lambda i=i: i) for i in range(4)]  # not queued behind the long ones
    assert all(c.wait(DEADLINE_S) for c in short)
    stop.set()
    assert all(c.wait(DEADLINE_S) for c in longs)
    st = pool.stats()
    assert st["long_calls"] == 3 and st["long_running"] == 0 and st["workers_peak"] <= 2


def test_run_blocking_hands_the_result_back_on_the_loops_thread(loop: IoLoop) -> None:
    got: list[tuple[Any, BaseException | None, str]] = []
    done = threading.Event()

    def then(result: Any, error: BaseException | None) -> None:
        got.append((result, error, threading.current_thread().name))
        if len(got) == 2:
            done.set()

    ran_on: list[str] = []

    def work() -> str:
        ran_on.append(threading.current_thread().name)
        return "opened"

    def fail() -> None:
        raise ValueError("bad")

    call = loop.run_blocking(work, then)
    failing = loop.run_blocking(fail, then)
    assert done.wait(DEADLINE_S)
    assert isinstance(call, BlockingCall) and call.wait(DEADLINE_S) and call.result == "opened"
    assert ran_on[0].startswith(loop.blocking.name)  # not the loop's thread
    results = {r if e is None else type(e).__name__: name for r, e, name in got}
    assert results == {"opened": "io-blocking-test", "ValueError": "io-blocking-test"}
    # ``then`` is handed to the loop before the pool counts the failure: wait for the call
    assert failing.wait(DEADLINE_S)
    assert loop.blocking.stats()["failed"] == 1


def test_bad_pool_size_is_refused() -> None:
    with pytest.raises(ValueError):
        BlockingCalls(workers=0)


# -- what runs on it: a port's open -------------------------------------------------------------

def test_an_open_that_hangs_does_not_stall_the_other_engines_or_timers_of_the_loop(
        loop: IoLoop) -> None:
    entered, release = threading.Event(), threading.Event()
    late = open_serial("loop://", timeout=0)

    def hanging() -> serial.SerialBase:
        entered.set()
        release.wait(DEADLINE_S)  # e.g. socket:// to a host that does not answer: up to 5 s
        return late

    got = threading.Event()
    data: list[bytes] = []

    class Proto:
        def feed(self, chunk: bytes) -> list[bytes]:
            data.append(chunk)
            got.set()
            return []

    stuck = PortEngine(hanging, name="stuck", loop=loop)
    fine = PortEngine(lambda: open_serial("loop://", timeout=0), name="fine", protocol=Proto(),
                      loop=loop)
    ticks = threading.Event()
    try:
        stuck.start()
        assert entered.wait(DEADLINE_S)  # its open hangs on a worker ...
        fine.start()  # ... while the loop opens, reads and writes another port
        assert fine.wait_connected(DEADLINE_S)
        fine.submit(b"ping", rate_limited=False)
        assert got.wait(DEADLINE_S) and b"".join(data) == b"ping"
        loop.call_later(0.01, ticks.set)  # and runs its timers
        assert ticks.wait(DEADLINE_S)
        assert not stuck.connected
        release.set()
        assert stuck.wait_connected(DEADLINE_S)  # the late open is taken once it returns
        assert loop.blocking.stats()["calls"] == 2
    finally:
        release.set()
        stuck.close(1.0)
        fine.close(1.0)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_starts_workers_of_its_own(pool: BlockingCalls) -> None:
    """A child forked while the parent's workers are busy has none of them: its calls must
    not wait for threads that do not exist there."""
    release = threading.Event()
    busy = [pool.submit(lambda: release.wait(DEADLINE_S)) for _ in range(pool.workers)]
    assert wait_for(lambda: pool.stats()["workers"] == pool.workers)
    pid = os.fork()
    if pid == 0:  # the child: exit 0 only if its call ran
        code = 1
        try:
            code = 0 if pool.submit(lambda: 5).wait(5.0) else 3
        finally:
            os._exit(code)
    try:
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
    finally:
        release.set()
        assert all(c.wait(DEADLINE_S) for c in busy)
