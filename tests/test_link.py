"""The link engine over real pyserial ``loop://`` ports: order, queue depth, rate limit,
readiness, reconnect with backoff, the shared write lock, shutdown; and the backoff itself."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

import pytest
import serial
from helpers import BlockingTransport, run_within, wait_for

from gateway.backend import Outcome
from gateway.backoff import Backoff
from gateway.link import DEFAULT_QUEUE_DEPTH, LinkEngine

DEADLINE_S = 5.0


def fast_backoff() -> Backoff:
    return Backoff(0.001, 0.004)


class FakeClock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def loop_port() -> serial.SerialBase:
    return serial.serial_for_url("loop://", timeout=0.05, write_timeout=1.0)


def read_exactly(port: serial.SerialBase, n: int, timeout: float = DEADLINE_S) -> bytes:
    """Read ``n`` bytes back from a loop:// port, failing after ``timeout``."""
    deadline = time.monotonic() + timeout
    data = b""
    while len(data) < n and time.monotonic() < deadline:
        data += port.read(n - len(data))
    assert len(data) == n, f"read {len(data)} of {n} bytes: {data!r}"
    return data


@pytest.fixture
def engines() -> Any:
    """Make engines that are closed (and whose blocked transports are released) at teardown."""
    made: list[tuple[LinkEngine, list[BlockingTransport]]] = []

    def make(opener: Callable[[], Any], blocked: tuple[BlockingTransport, ...] = (),
             **kw: Any) -> LinkEngine:
        kw.setdefault("backoff", fast_backoff())
        eng = LinkEngine(opener, **kw)
        made.append((eng, list(blocked)))
        return eng

    yield make
    for eng, blocked in made:
        for t in blocked:
            t.release.set()
        eng.close(0.5)


def started(make: Any, opener: Callable[[], Any], **kw: Any) -> LinkEngine:
    eng = make(opener, **kw)
    eng.start()
    assert eng.wait_connected(DEADLINE_S)
    return eng


# -- order and the real port ----------------------------------------------------------------


def test_frames_come_out_of_a_loop_port_in_order(engines: Any) -> None:
    port = loop_port()
    eng = started(engines, lambda: port, queue_depth=64)
    frames = [bytes([0xA5, 0x5A, i, 3, i, i + 1, i + 2]) for i in range(50)]
    assert [eng.submit(f) for f in frames] == [Outcome.ACCEPTED] * 50
    assert read_exactly(port, sum(map(len, frames))) == b"".join(frames)
    assert eng.drain(DEADLINE_S)
    assert eng.stats.sent_frames == 50
    assert eng.stats.sent_bytes == sum(map(len, frames))
    assert eng.stats.dropped == 0


def test_several_engines_run_at_once_on_different_loop_ports(engines: Any) -> None:
    ports = [loop_port() for _ in range(3)]
    engs = [started(engines, (lambda p=p: p), name=f"link{i}") for i, p in enumerate(ports)]
    for k in range(10):
        for i, eng in enumerate(engs):
            assert eng.submit(bytes([i, k])) is Outcome.ACCEPTED
    for i, port in enumerate(ports):
        assert read_exactly(port, 20) == b"".join(bytes([i, k]) for k in range(10))
    assert [e.stats.sent_frames for e in engs] == [10, 10, 10]


# -- queue depth ----------------------------------------------------------------------------


def test_queue_holds_16_frames_by_default_then_reports_queue_full(engines: Any) -> None:
    port = BlockingTransport()
    eng = started(engines, lambda: port, blocked=(port,))
    assert eng.queue_depth == DEFAULT_QUEUE_DEPTH == 16
    assert eng.submit(b"in-flight") is Outcome.ACCEPTED
    assert port.entered.wait(DEADLINE_S)  # the worker holds it inside write()
    queued = [eng.submit(bytes([i])) for i in range(16)]
    assert queued == [Outcome.ACCEPTED] * 16
    assert eng.queued() == 16
    assert eng.submit(b"one too many") is Outcome.QUEUE_FULL
    assert eng.submit(b"and another") is Outcome.QUEUE_FULL
    assert eng.stats.dropped_queue_full == 2
    assert eng.stats.dropped == 2
    port.release.set()
    assert eng.drain(DEADLINE_S)
    assert port.written == [b"in-flight", *(bytes([i]) for i in range(16))]


# -- rate limit -----------------------------------------------------------------------------


def test_min_interval_throttles_with_a_fake_clock_and_status_is_exempt(engines: Any) -> None:
    port = loop_port()
    clock = FakeClock()
    # Binary-exact steps, so the test is about the rule rather than float rounding.
    eng = started(engines, lambda: port, min_interval_s=0.5, clock=clock)
    assert eng.submit(b"a") is Outcome.ACCEPTED
    clock.now += 0.25
    assert eng.submit(b"b") is Outcome.THROTTLED
    assert eng.submit(b"S", rate_limited=False) is Outcome.ACCEPTED  # STATUS: exempt
    clock.now += 0.25  # exactly min_interval_s after "a"
    assert eng.submit(b"c") is Outcome.ACCEPTED
    clock.now += 0.4375
    assert eng.submit(b"d") is Outcome.THROTTLED  # the exempt frame did not move the window
    assert eng.submit(b"T", rate_limited=False) is Outcome.ACCEPTED
    assert read_exactly(port, 4) == b"aScT"
    assert eng.stats.dropped_throttled == 2
    assert eng.stats.accepted == 4


def test_zero_min_interval_never_throttles(engines: Any) -> None:
    port = loop_port()
    eng = started(engines, lambda: port, clock=FakeClock())
    assert [eng.submit(b"x") for _ in range(5)] == [Outcome.ACCEPTED] * 5
    assert read_exactly(port, 5) == b"xxxxx"


# -- readiness and reconnect ------------------------------------------------------------------


def test_not_ready_before_start(engines: Any) -> None:
    eng = engines(loop_port)
    assert eng.submit(b"early") is Outcome.NOT_READY
    assert eng.stats.dropped_not_ready == 1
    assert not eng.connected


def test_not_ready_while_the_opener_fails(engines: Any) -> None:
    attempts = threading.Semaphore(0)

    def opener() -> Any:
        attempts.release()
        raise serial.SerialException("could not open port /dev/ttyUSB9")

    eng = engines(opener)
    eng.start()
    for _ in range(3):
        assert attempts.acquire(timeout=DEADLINE_S)
    assert eng.submit(b"x") is Outcome.NOT_READY
    assert eng.stats.dropped_not_ready == 1
    assert eng.stats.connect_failures >= 3
    assert eng.stats.connects == 0
    assert eng.queued() == 0  # nothing is kept for a port that is not there


def test_reconnects_with_backoff_after_failed_opens(engines: Any) -> None:
    port = loop_port()
    calls = 0

    def opener() -> Any:
        nonlocal calls
        calls += 1
        if calls <= 3:
            raise serial.SerialException("port busy")
        return port

    backoff = Backoff(0.001, 0.004)
    eng = started(engines, opener, backoff=backoff)
    assert eng.stats.connect_failures == 3
    assert eng.stats.connects == 1
    assert backoff.next() == 0.001  # reset on success
    assert eng.submit(b"hello") is Outcome.ACCEPTED
    assert read_exactly(port, 5) == b"hello"


class FailingWrite:
    """A port that dies on its first write."""

    def __init__(self) -> None:
        self.closed = threading.Event()

    def write(self, data: bytes) -> int:
        raise serial.SerialException("device reports readiness to read but returned no data")

    def read(self, size: int = 1) -> bytes:
        return b""

    def close(self) -> None:
        self.closed.set()


def test_write_error_is_counted_and_the_engine_reconnects(engines: Any) -> None:
    dead, good = FailingWrite(), loop_port()
    ports = [dead, good]
    reopened = threading.Event()

    def opener() -> Any:
        p = ports.pop(0)
        if p is good:
            reopened.set()
        return p

    eng = started(engines, opener)
    assert eng.submit(b"lost") is Outcome.ACCEPTED
    assert reopened.wait(DEADLINE_S)
    assert dead.closed.wait(DEADLINE_S)
    assert eng.wait_connected(DEADLINE_S)
    assert eng.stats.write_errors == 1
    assert eng.stats.connects == 2
    assert eng.submit(b"after") is Outcome.ACCEPTED
    assert eng.submit(b"-more") is Outcome.ACCEPTED
    assert read_exactly(good, 10) == b"after-more"


def test_reconnect_on_request_closes_the_port_and_reopens_it(engines: Any) -> None:
    """A reader that sees the port fail asks the engine to reopen it (no write need fail)."""
    first, second = loop_port(), loop_port()
    ports = [first, second]
    eng = started(engines, lambda: ports.pop(0))
    assert eng.submit(b"one") is Outcome.ACCEPTED
    assert read_exactly(first, 3) == b"one"
    eng.reconnect()
    assert not eng.connected  # refused as not ready until the port is back
    assert eng.submit(b"lost") is Outcome.NOT_READY
    assert wait_for(lambda: eng.stats.connects == 2, DEADLINE_S)
    assert not first.is_open
    assert eng.wait_connected(DEADLINE_S)
    assert eng.submit(b"two") is Outcome.ACCEPTED
    assert read_exactly(second, 3) == b"two"
    assert eng.stats.reconnects_requested == 1 and eng.stats.write_errors == 0


def test_reconnect_while_the_port_is_down_is_ignored(engines: Any) -> None:
    eng = engines(lambda: (_ for _ in ()).throw(OSError("no such port")))
    eng.reconnect()  # not started, no port: nothing to do
    assert eng.stats.reconnects_requested == 0


# -- the shared write lock --------------------------------------------------------------------


def test_writes_wait_for_an_external_holder_of_the_lock(engines: Any) -> None:
    port = loop_port()
    eng = started(engines, lambda: port)
    with eng.lock:  # e.g. an AT-command exchange owns the port
        assert [eng.submit(f) for f in (b"1", b"2", b"3")] == [Outcome.ACCEPTED] * 3
        assert wait_for(lambda: eng.queued() == 2)  # the worker took "1" and waits for the lock
        assert eng.stats.sent_frames == 0
        assert port.in_waiting == 0
    assert read_exactly(port, 3) == b"123"


# -- shutdown -------------------------------------------------------------------------------


def test_close_writes_what_is_queued_before_stopping(
    engines: Any, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.link")
    port = BlockingTransport()
    eng = started(engines, lambda: port, blocked=(port,), queue_depth=3)
    assert eng.submit(b"0") is Outcome.ACCEPTED
    assert port.entered.wait(DEADLINE_S)
    assert [eng.submit(f) for f in (b"1", b"2", b"3")] == [Outcome.ACCEPTED] * 3
    closer = threading.Thread(target=eng.close, args=(DEADLINE_S,), daemon=True)
    closer.start()
    # The queue is full, so submit says QUEUE_FULL (queueing nothing) until close() begins.
    assert wait_for(lambda: eng.submit(b"probe") is Outcome.NOT_READY)
    port.release.set()
    closer.join(DEADLINE_S)
    assert not closer.is_alive()
    assert port.written == [b"0", b"1", b"2", b"3"]
    assert eng.stats.sent_frames == 4
    assert port.closed
    assert not [r for r in caplog.records if "did not stop" in r.getMessage()]  # it stopped


def test_close_returns_within_its_timeout_with_a_writer_blocked_forever(
    engines: Any, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.link")
    port = BlockingTransport()
    eng = started(engines, lambda: port, blocked=(port,))
    assert eng.submit(b"stuck") is Outcome.ACCEPTED
    assert port.entered.wait(DEADLINE_S)
    assert [eng.submit(bytes([i])) for i in range(5)] == [Outcome.ACCEPTED] * 5
    run_within(lambda: eng.close(timeout=0.1), timeout=DEADLINE_S)
    assert eng.stats.dropped_not_ready == 5  # the leftovers, counted
    assert any("did not stop" in r.getMessage() for r in caplog.records)
    assert eng.queued() == 0
    assert port.closed
    assert not eng.connected
    assert eng.submit(b"late") is Outcome.NOT_READY
    run_within(lambda: eng.close(timeout=0.1))  # twice is safe


def test_close_is_safe_twice_and_before_start(engines: Any) -> None:
    port = loop_port()
    never_started = engines(loop_port)
    never_started.close()
    eng = started(engines, lambda: port)
    eng.close()
    eng.close()
    assert not port.is_open
    assert eng.submit(b"x") is Outcome.NOT_READY


def test_close_while_the_opener_keeps_failing_returns_promptly(engines: Any) -> None:
    tried = threading.Event()

    def opener() -> Any:
        tried.set()
        raise serial.SerialException("gone")

    eng = engines(opener, backoff=Backoff(30.0, 30.0))  # a long wait between attempts
    eng.start()
    assert tried.wait(DEADLINE_S)
    run_within(lambda: eng.close(timeout=DEADLINE_S), timeout=DEADLINE_S / 2)


# -- arguments and stats --------------------------------------------------------------------


@pytest.mark.parametrize("kw", [{"queue_depth": 0}, {"min_interval_s": -0.1}])
def test_bad_arguments_are_refused(kw: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        LinkEngine(loop_port, **kw)


def test_stats_dict_reports_total_drops(engines: Any) -> None:
    eng = engines(loop_port)
    eng.submit(b"x")
    d = eng.stats.as_dict()
    assert d["dropped"] == d["dropped_not_ready"] == 1
    assert d["submitted"] == 1


# -- backoff ----------------------------------------------------------------------------------


def test_backoff_doubles_up_to_its_cap_and_resets() -> None:
    b = Backoff(0.1, 1.0)
    assert [b.next() for _ in range(6)] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.0, 1.0])
    b.reset()
    assert b.next() == pytest.approx(0.1)


def test_backoff_factor_is_configurable() -> None:
    b = Backoff(1.0, 100.0, factor=3.0)
    assert [b.next() for _ in range(5)] == pytest.approx([1, 3, 9, 27, 81])
    assert Backoff(0.5, 0.5, factor=1.0).next() == 0.5


@pytest.mark.parametrize(
    ("initial", "maximum", "factor"), [(0, 1, 2), (-1, 1, 2), (2, 1, 2), (0.1, 1, 0.5)]
)
def test_backoff_refuses_bad_parameters(initial: float, maximum: float, factor: float) -> None:
    with pytest.raises(ValueError):
        Backoff(initial, maximum, factor)
