"""The dispatcher's contract (seed 000): synchronous fan-out in the caller's thread, the first
non-accepted outcome while every backend is still tried, isolation of a backend that raises,
per-kind hooks, start/close life cycle, and never blocking on a backend's I/O."""

from __future__ import annotations

import errno
import logging
import threading
from typing import Any, NamedTuple

import pytest
from helpers import BlockingTransport, run_within

from gateway.backend import Backend, Outcome, Routes
from gateway.dispatcher import Dispatcher
from gateway.io.port import DEFAULT_QUEUE_DEPTH, PortEngine
from gateway.model import LinkEvent, RawFrame, SmUpdate, Status

DEADLINE_S = 5.0


def sm(t: int = 0) -> SmUpdate:
    return SmUpdate(t, 1, False, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def status(t: int = 0) -> Status:
    return Status(t, 1, 0, 0)


class Recorder(Backend):
    """Records every hook call (kind, message, thread) into a shared log; returns ``result``."""

    def __init__(self, name: str, log: list | None = None, result: Any = None) -> None:
        super().__init__(name)
        self.log = log if log is not None else []
        self.result = result
        self.calls: list[tuple[str, Any, int]] = []

    def _record(self, kind: str, msg: Any) -> Any:
        self.calls.append((kind, msg, threading.get_ident()))
        self.log.append(self.name)
        return self.result

    def routes(self) -> Routes:
        return (Routes().on(SmUpdate, self.send_sm_update).on(Status, self.send_status)
                .on(RawFrame, self.send_raw).on(LinkEvent, self.on_link))

    def send_sm_update(self, msg: SmUpdate) -> Any:
        return self._record("sm", msg)

    def send_status(self, msg: Status) -> Any:
        return self._record("status", msg)

    def send_raw(self, msg: RawFrame) -> Any:
        return self._record("raw", msg)

    def on_link(self, ev: LinkEvent) -> Any:
        return self._record("link", ev)


class SmOnly:
    """A plain object (no base class) routing only SM updates."""

    def __init__(self, name: str, result: Any = None) -> None:
        self.name = name
        self.result = result
        self.seen: list[Any] = []

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.send_sm_update)

    def send_sm_update(self, msg: Any) -> Any:
        self.seen.append(msg)
        return self.result


def started(*backends: Any) -> Dispatcher:
    d = Dispatcher(backends)
    assert d.start() == []
    return d


# -- threading and order ---------------------------------------------------------------------


def test_hooks_run_synchronously_in_the_callers_thread() -> None:
    a, b = Recorder("a"), Recorder("b")
    d = started(a, b)
    d.dispatch(sm())
    other = run_within(lambda: (d.dispatch(sm(1)), threading.get_ident())[1])
    main = threading.get_ident()
    assert [c[2] for c in a.calls] == [main, other]
    assert [c[2] for c in b.calls] == [main, other]
    assert other != main


def test_every_backend_is_called_in_registration_order() -> None:
    log: list[str] = []
    d = started(*(Recorder(n, log) for n in ("first", "second", "third")))
    d.dispatch(sm())
    d.dispatch(status())
    assert log == ["first", "second", "third"] * 2


# -- outcomes --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "outcome", [Outcome.ACCEPTED, Outcome.THROTTLED, Outcome.QUEUE_FULL, Outcome.NOT_READY]
)
def test_a_single_backends_outcome_is_returned(outcome: Outcome) -> None:
    d = started(Recorder("only", result=outcome))
    assert d.dispatch(sm()) is outcome


@pytest.mark.parametrize(
    ("results", "expected"),
    [
        ([None, Outcome.ACCEPTED, 0], Outcome.ACCEPTED),
        ([Outcome.ACCEPTED, Outcome.THROTTLED, Outcome.QUEUE_FULL], Outcome.THROTTLED),
        ([Outcome.QUEUE_FULL, Outcome.NOT_READY, Outcome.THROTTLED], Outcome.QUEUE_FULL),
        ([None, None, Outcome.NOT_READY], Outcome.NOT_READY),
    ],
)
def test_first_non_accepted_outcome_is_returned_and_every_backend_still_called(
    results: list[Any], expected: Outcome
) -> None:
    log: list[str] = []
    backends = [Recorder(f"b{i}", log, r) for i, r in enumerate(results)]
    d = started(*backends)
    assert d.dispatch(sm()) is expected
    assert log == ["b0", "b1", "b2"]


@pytest.mark.parametrize(
    ("returned", "expected"),
    [
        (-11, Outcome.THROTTLED),  # -EAGAIN as the firmware's C backends return it
        (-errno.ENOMEM, Outcome.QUEUE_FULL),
        (-errno.ENODEV, Outcome.NOT_READY),
        (0, Outcome.ACCEPTED),
        (None, Outcome.ACCEPTED),
    ],
)
def test_plain_errno_integers_map_to_outcomes(returned: Any, expected: Outcome) -> None:
    d = started(SmOnly("c-style", returned))
    assert d.dispatch(sm()) is expected
    assert d.stats()["c-style"] == ({expected.label: 1})


def test_outcomes_are_counted_per_backend_in_stats() -> None:
    ok, slow = Recorder("ok"), Recorder("slow", result=Outcome.THROTTLED)
    d = started(ok, slow)
    for i in range(3):
        d.dispatch(sm(i))
    stats = d.stats()
    assert stats["ok"] == {"accepted": 3}
    assert stats["slow"] == {"throttled": 3}


# -- isolation of a backend that raises ---------------------------------------------------------


class Exploding(Backend):
    def __init__(self, name: str, errors: list[Exception]) -> None:
        super().__init__(name)
        self.errors = list(errors)

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.send_sm_update)

    def send_sm_update(self, msg: SmUpdate) -> Outcome:
        raise self.errors.pop(0)


def test_raising_backend_is_isolated_counted_and_logged_once_per_exception_type(
    caplog: pytest.LogCaptureFixture,
) -> None:
    errors: list[Exception] = [ValueError("bad 1"), ValueError("bad 2"), KeyError("k"),
                               ValueError("bad 3"), KeyError("k2")]
    before, after = Recorder("before"), Recorder("after")
    d = started(before, Exploding("boom", errors), after)
    caplog.set_level(logging.DEBUG, logger="gateway.dispatcher")
    results = [d.dispatch(sm(i)) for i in range(5)]
    assert results == [Outcome.FAILED] * 5
    assert len(before.calls) == len(after.calls) == 5  # neighbours unaffected
    assert d.stats()["boom"]["failed"] == 5
    errors_logged = [r for r in caplog.records
                     if r.name == "gateway.dispatcher" and r.levelno >= logging.ERROR]
    assert len(errors_logged) == 2
    assert "ValueError" in errors_logged[0].getMessage()
    assert "KeyError" in errors_logged[1].getMessage()
    assert all("boom" in r.getMessage() for r in errors_logged)


def test_failed_outcome_does_not_hide_an_earlier_non_accepted_one() -> None:
    d = started(Recorder("busy", result=Outcome.QUEUE_FULL), Exploding("boom", [OSError()]))
    assert d.dispatch(sm()) is Outcome.QUEUE_FULL
    assert d.stats()["boom"] == {"failed": 1}


# -- routing by kind ----------------------------------------------------------------------------


def test_status_goes_only_to_send_status() -> None:
    sm_only = SmOnly("sm-only")
    both = Recorder("both")
    d = started(sm_only, both)
    assert d.dispatch(status(5)) is Outcome.ACCEPTED
    assert sm_only.seen == []
    assert [(k, m) for k, m, _ in both.calls] == [("status", status(5))]


def test_throttling_sm_update_hook_does_not_affect_status() -> None:
    class ThrottlesUpdates(Backend):
        def __init__(self) -> None:
            super().__init__("hc12ish")
            self.statuses: list[Status] = []

        def routes(self) -> Routes:
            return Routes().on(SmUpdate, self.send_sm_update).on(Status, self.send_status)

        def send_sm_update(self, msg: SmUpdate) -> Outcome:
            return Outcome.THROTTLED

        def send_status(self, msg: Status) -> Outcome:
            self.statuses.append(msg)
            return Outcome.ACCEPTED

    b = ThrottlesUpdates()
    d = started(b)
    assert d.dispatch(sm()) is Outcome.THROTTLED
    assert d.dispatch(status()) is Outcome.ACCEPTED
    assert b.statuses == [status()]


def test_backends_without_a_hook_for_the_kind_are_skipped() -> None:
    class LinkOnly:
        name = "link-only"

        def __init__(self) -> None:
            self.events: list[LinkEvent] = []

        def routes(self) -> Routes:
            return Routes().on(LinkEvent, self.on_link)

        def on_link(self, ev: LinkEvent) -> None:
            self.events.append(ev)

    lo, rec = LinkOnly(), Recorder("rec")
    d = started(lo, rec)
    assert d.dispatch(sm()) is Outcome.ACCEPTED
    assert d.dispatch(RawFrame(0x7F, b"\x01")) is Outcome.ACCEPTED
    assert lo.events == []
    assert d.stats()["link-only"] == {}
    assert [k for k, _, _ in rec.calls] == ["sm", "raw"]


def test_raw_frames_go_to_send_raw_and_link_events_to_on_link() -> None:
    rec = Recorder("rec")
    d = started(rec)
    frame = RawFrame(0x42, b"\xde\xad", origin="src")
    ev = LinkEvent("src", True)
    d.dispatch(frame)
    d.dispatch(ev)
    assert [(k, m) for k, m, _ in rec.calls] == [("raw", frame), ("link", ev)]


def test_a_message_class_outside_the_model_is_routed_by_its_type() -> None:
    class Custom(NamedTuple):
        value: int

    class NotRouted(NamedTuple):
        value: int

    class WantsCustom(Backend):
        def __init__(self) -> None:
            super().__init__("custom")
            self.seen: list[Custom] = []

        def routes(self) -> Routes:
            return Routes().on(Custom, self.send_custom)

        def send_custom(self, msg: Custom) -> Outcome:
            self.seen.append(msg)
            return Outcome.THROTTLED

    b = WantsCustom()
    d = started(b, Recorder("rec"))
    assert d.dispatch(Custom(1)) is Outcome.THROTTLED
    assert b.seen == [Custom(1)]
    assert d.dispatch(NotRouted(2)) is Outcome.ACCEPTED
    assert d.unrouted == 1


def test_a_hook_may_dispatch_through_the_same_dispatcher_without_deadlock() -> None:
    d = Dispatcher()

    class Relay(Backend):
        def routes(self) -> Routes:
            return Routes().on(SmUpdate, self.send_sm_update)

        def send_sm_update(self, msg: SmUpdate) -> Outcome:
            return d.dispatch(LinkEvent("relay", True))

    rec = Recorder("rec")
    d.add(Relay("relay"))
    d.add(rec)
    assert d.start() == []
    assert run_within(lambda: d.dispatch(sm())) is Outcome.ACCEPTED
    assert [k for k, _, _ in rec.calls] == ["link", "sm"]


# -- life cycle ---------------------------------------------------------------------------------


def test_no_backend_is_called_before_start() -> None:
    rec = Recorder("rec")
    d = Dispatcher([rec])
    assert d.dispatch(sm()) is Outcome.ACCEPTED
    assert rec.calls == []
    assert d.unrouted == 1


class Lifecycle(Backend):
    def __init__(self, name: str, init_error: Exception | None = None,
                 close_error: Exception | None = None) -> None:
        super().__init__(name)
        self.init_error = init_error
        self.close_error = close_error
        self.inits = 0
        self.closes = 0
        self.seen: list[Any] = []

    def init(self) -> None:
        self.inits += 1
        if self.init_error is not None:
            raise self.init_error

    def close(self) -> None:
        self.closes += 1
        if self.close_error is not None:
            raise self.close_error

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.send_sm_update)

    def send_sm_update(self, msg: SmUpdate) -> None:
        self.seen.append(msg)


def test_start_initialises_every_backend_and_reports_failures_by_name() -> None:
    a = Lifecycle("a")
    bad = Lifecycle("bad", init_error=RuntimeError("no port /dev/ttyUSB9"))
    worse = Lifecycle("worse", init_error=OSError())
    c = Lifecycle("c")
    d = Dispatcher([a, bad, worse, c])
    failures = d.start()
    assert failures == [("bad", "RuntimeError: no port /dev/ttyUSB9"), ("worse", "OSError")]
    assert (a.inits, bad.inits, worse.inits, c.inits) == (1, 1, 1, 1)
    assert d.dispatch(sm()) is Outcome.ACCEPTED
    assert len(a.seen) == len(c.seen) == 1
    assert bad.seen == worse.seen == []  # excluded from the fan-out
    assert d.stats()["bad"]["init_error"] == "RuntimeError: no port /dev/ttyUSB9"


def test_close_is_safe_twice_and_isolates_errors(caplog: pytest.LogCaptureFixture) -> None:
    a = Lifecycle("a", close_error=RuntimeError("stuck"))
    b = Lifecycle("b")
    d = started(a, b)
    with caplog.at_level(logging.ERROR, logger="gateway.dispatcher"):
        d.close()
        d.close()
    assert b.closes == 2  # reached despite a's error, both times
    assert a.closes == 2
    assert any("stuck" in r.getMessage() or "stuck" in (r.exc_text or "")
               for r in caplog.records)
    assert d.dispatch(sm()) is Outcome.ACCEPTED
    assert a.seen == b.seen == []  # nothing reaches a closed backend


def test_duplicate_backend_names_are_refused() -> None:
    d = Dispatcher([Recorder("same")])
    with pytest.raises(ValueError, match="same"):
        d.add(Recorder("same"))
    with pytest.raises(ValueError, match="dup"):
        Dispatcher([SmOnly("dup"), SmOnly("dup")])


# -- never blocks ---------------------------------------------------------------------------------


class LinkBackend(Backend):
    """A byte-stream backend built on the real port engine."""

    def __init__(self, name: str, transport: BlockingTransport) -> None:
        super().__init__(name)
        self.engine = PortEngine(lambda: transport, name=name)

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.send_sm_update)

    def init(self) -> None:
        self.engine.start()
        if not self.engine.wait_connected(DEADLINE_S):
            raise RuntimeError("not connected")

    def close(self) -> None:
        self.engine.close(0.2)

    def send_sm_update(self, msg: SmUpdate) -> Outcome:
        return self.engine.submit(msg.timestamp_ms.to_bytes(4, "little"))

    def stats(self) -> dict[str, int]:
        s = self.engine.stats
        return {"sent": s.sent_frames, "dropped": s.dropped}


def test_dispatch_never_blocks_on_a_stalled_link_backend() -> None:
    port = BlockingTransport()
    link, rec = LinkBackend("stalled", port), Recorder("rec")
    d = started(link, rec)
    try:
        assert d.dispatch(sm(0)) is Outcome.ACCEPTED
        assert port.entered.wait(DEADLINE_S)  # the worker is now stuck inside write()
        extra = 10
        results = run_within(
            lambda: [d.dispatch(sm(i)) for i in range(1, DEFAULT_QUEUE_DEPTH + 1 + extra)]
        )
        assert results[:DEFAULT_QUEUE_DEPTH] == [Outcome.ACCEPTED] * DEFAULT_QUEUE_DEPTH
        assert results[DEFAULT_QUEUE_DEPTH:] == [Outcome.QUEUE_FULL] * extra
        assert len(rec.calls) == 1 + DEFAULT_QUEUE_DEPTH + extra  # the neighbour saw them all
        stats = d.stats()["stalled"]
        assert stats["queue-full"] == extra
        assert stats["dropped"] == extra
        assert link.engine.stats.dropped_queue_full == extra
        port.release.set()
        assert link.engine.drain(DEADLINE_S)
        assert port.written == [i.to_bytes(4, "little") for i in range(DEFAULT_QUEUE_DEPTH + 1)]
    finally:
        port.release.set()
        d.close()


# -- the routing table -----------------------------------------------------------------------------


def test_an_object_without_routes_is_refused_when_added() -> None:
    class Hooky:  # the old, string-routed shape: a hook by name and nothing else
        name = "hooky"

        def send_sm_update(self, msg: SmUpdate) -> None:
            pass

    with pytest.raises(TypeError, match="routes"):
        Dispatcher([Hooky()])


def test_a_type_routed_twice_by_one_backend_is_an_error() -> None:
    with pytest.raises(ValueError, match="SmUpdate"):
        Routes().on(SmUpdate, lambda m: None).on(SmUpdate, lambda m: None)


def test_the_table_is_read_once_at_start() -> None:
    calls = []

    class Counting(Recorder):
        def routes(self) -> Routes:
            calls.append(1)
            return super().routes()

    d = started(Counting("c"))
    for i in range(5):
        d.dispatch(sm(i))
    assert len(calls) == 1
