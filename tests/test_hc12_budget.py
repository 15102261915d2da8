"""HC-12 logic without hardware: the air budget (fake clock, property tests, the 100 Hz stream
through the real backend and a real loop:// port), the AT command set, the SET-line specs and
the IDLE rule."""

from __future__ import annotations

import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_hc12_support import FakeClock, sm, status

from backends.hc12 import at
from backends.hc12.backend import Hc12Backend
from backends.hc12.budget import AirBudget, figures
from backends.hc12.options import Hc12Options
from backends.hc12.setline import BENCH_HINT, NoSetLine, SetLineError, parse_set_line
from backends.hc12.vehicle import VehicleWatch
from gateway.flight import FlightModel, FlightProfile
from gateway.model import Status
from gateway.outcome import Outcome
from gateway.sources.sim import flight_messages
from gateway.wire import decode_all, encode

# -- the budget ----------------------------------------------------------------------------------


def test_default_figures_follow_the_spec() -> None:
    fig = figures()  # 9600 baud, 10 bits a byte, 80 %
    assert fig.capacity_bps == 960
    assert fig.rate_bps == pytest.approx(768)
    assert fig.burst_bytes == pytest.approx(192)  # the headroom of one second


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 0.2), st.integers(1, 192), st.booleans()),
                min_size=1, max_size=300),
       st.sampled_from([1200, 9600, 115200]), st.floats(10, 100))
def test_admitted_bytes_never_exceed_burst_plus_rate(
        arrivals: list[tuple[float, int, bool]], baud: int, pct: float) -> None:
    fig = figures(baud, pct, burst_bytes=192)
    clock = FakeClock()
    budget = AirBudget(fig, clock=clock)
    admitted: list[tuple[float, int]] = []
    for gap, n, prio in arrivals:
        clock.advance(gap)
        if budget.admit(n, priority=prio):
            budget.commit(n)
            admitted.append((clock.now, n))
    for i, (t0, _) in enumerate(admitted):
        total = 0
        for t1, n in admitted[i:]:
            total += n
            assert total <= fig.burst_bytes + fig.rate_bps * (t1 - t0) + 1e-6
    assert budget.committed_bytes == sum(n for _, n in admitted)


def test_a_frame_larger_than_the_burst_waits_for_a_full_bucket_and_pays_back() -> None:
    clock = FakeClock()
    budget = AirBudget(figures(9600, 80, burst_bytes=100, reserve_bytes=0), clock=clock)
    assert budget.admit(250)  # full bucket: admitted, 150 bytes of debt
    budget.commit(250)
    clock.advance(150 / 768 + 99 / 768)  # debt paid, 99 bytes back
    assert not budget.admit(100)
    clock.advance(2 / 768)
    assert budget.admit(100)


def test_status_reserve_gets_heartbeats_through_a_saturated_stream() -> None:
    clock = FakeClock()
    budget = AirBudget(figures(), clock=clock)
    sm_len, st_len = 70, 14
    for i in range(1000):  # 100 Hz SM_UPDATE, STATUS every 100th tick
        clock.advance(0.01)
        if i % 100 == 50:
            assert budget.admit(st_len, priority=True), f"STATUS starved at tick {i}"
            budget.commit(st_len)
        if budget.admit(sm_len):
            budget.commit(sm_len)
    assert budget.refused_frames > 800


# -- the 100 Hz stream through the backend ------------------------------------------------------


class FarSide:
    """Reads the far side of a loop:// port in a thread (its buffer holds only 4 KiB)."""

    def __init__(self, port: object) -> None:
        self.port = port
        self.data = bytearray()
        self.cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                chunk = self.port.read(4096)
            except Exception:
                return
            if chunk:
                with self.cond:
                    self.data += chunk
                    self.cond.notify_all()

    def wait_bytes(self, n: int, timeout: float = 10.0) -> bytes:
        with self.cond:
            self.cond.wait_for(lambda: len(self.data) >= n, timeout)
            return bytes(self.data)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(2.0)


def _stream(seconds: float, revision: int) -> list[tuple[float, object]]:
    model = FlightModel(FlightProfile(revision=revision))
    out = []
    for t, msg in flight_messages(model, 100.0, 1.0):
        if t >= seconds:
            break
        # as a source hands them over: decoded from the wire, raw attached
        out.append((t, decode_all(encode(msg), origin="sim")[0]))
    return out


@pytest.mark.parametrize("revision", [64, 36])
def test_100hz_stream_into_9600_baud_budget(revision: int) -> None:
    """100 Hz SM_UPDATE + 1 Hz STATUS for 20 s (fake clock) into a 9600-baud link at 80 %:
    what reaches the far side of the port never exceeds the budget, drops are counted, every
    STATUS is delivered."""
    clock = FakeClock(0.0)
    backend = Hc12Backend(Hc12Options(url="loop://", queue_depth=4096, control="off"), clock=clock)
    backend.init()
    reader = None
    try:
        assert backend.engine.wait_connected(5.0)
        reader = FarSide(backend.engine.port)  # loop://: what the engine writes comes back here
        accepted: list[tuple[float, bytes]] = []
        outcomes: dict[Outcome, int] = {}
        statuses = 0
        duration = 20.0
        for t, msg in _stream(duration, revision):
            clock.now = t
            hook = backend.send_status if isinstance(msg, Status) else backend.send_sm_update
            outcome = hook(msg)
            outcomes[outcome] = outcomes.get(outcome, 0) + 1
            statuses += isinstance(msg, Status)
            if outcome is Outcome.ACCEPTED:
                accepted.append((t, msg.raw))
        assert backend.engine.drain(10.0)
        expected = b"".join(raw for _, raw in accepted)
        got = reader.wait_bytes(len(expected))
        stats = backend.stats()
    finally:
        if reader is not None:
            reader.stop()
        backend.close()
    assert got == expected  # exactly the accepted frames, in order, byte-identical

    fig = backend.budget.fig
    total = sum(len(raw) for _, raw in accepted)
    peak = 0
    for i, (t0, _) in enumerate(accepted):
        window = sum(len(raw) for t, raw in accepted[i:] if t < t0 + 1.0)
        peak = max(peak, window)
    sustained = total / duration
    after_burst = (total - fig.burst_bytes) / duration
    print(f"\nrevision {revision}: offered {len(_stream(duration, revision))} frames, "
          f"accepted {len(accepted)} ({total} B, {sustained:.0f} B/s = "
          f"{100 * sustained / fig.capacity_bps:.1f} % of {fig.capacity_bps:.0f} B/s; "
          f"{after_burst:.0f} B/s = {100 * after_burst / fig.capacity_bps:.1f} % after the "
          f"initial {fig.burst_bytes:.0f}-byte burst), "
          f"peak 1-s window {peak} B, dropped by budget {stats['dropped_budget']}, "
          f"STATUS {sum(1 for _, r in accepted if r[2] == 2)}/{statuses}")
    assert peak <= fig.capacity_bps  # no one-second window above what the air carries
    assert total <= fig.rate_bps * duration + fig.burst_bytes  # sustained ≤ 80 %
    assert sustained >= 0.9 * fig.rate_bps  # and the budget is used, not wasted
    assert stats["dropped_budget"] == outcomes[Outcome.THROTTLED] > 0
    assert stats["dropped"] == stats["dropped_budget"]
    assert sum(1 for _, raw in accepted if raw[2] == 2) == statuses == 20
    assert stats["sent_bytes"] == total


def test_min_interval_limits_sm_updates_but_not_status() -> None:
    clock = FakeClock(0.0)
    backend = Hc12Backend(Hc12Options(url="loop://", min_interval_s=0.2, utilisation_pct=100,
                                      burst_bytes=10_000, queue_depth=4096, control="off"),
                          clock=clock)
    backend.init()
    try:
        assert backend.engine.wait_connected(5.0)
        ok_sm = ok_st = 0
        for i in range(500):  # 5 s at 100 Hz
            clock.now = i * 0.01
            ok_sm += backend.send_sm_update(sm(t_ms=i * 10)) is Outcome.ACCEPTED
            if i % 20 == 0:
                ok_st += backend.send_status(status(t_ms=i * 10)) is Outcome.ACCEPTED
        stats = backend.stats()
    finally:
        backend.close()
    assert ok_sm == 25  # one per 0.2 s
    assert ok_st == 25  # STATUS exempt from the interval
    assert stats["dropped_throttled"] == 475
    assert stats["dropped_budget"] == 0


def test_utilisation_is_reported() -> None:
    clock = FakeClock(0.0)
    budget = AirBudget(figures(), clock=clock)
    for i in range(1000):
        clock.now = i * 0.01
        if budget.admit(42):
            budget.commit(42)
    assert 78 <= budget.utilisation_pct() <= 82
    assert budget.peak_1s_bytes <= 960


# -- AT command set ------------------------------------------------------------------------------


@pytest.mark.parametrize(("build", "arg", "text"), [
    (at.channel, "1", "AT+C001"), (at.channel, 127, "AT+C127"), (at.channel, " 42 ", "AT+C042"),
    (at.baud, "1200", "AT+B1200"), (at.baud, 115200, "AT+B115200"),
    (at.power, "1", "AT+P1"), (at.power, "8", "AT+P8"),
    (at.mode, "1", "AT+FU1"), (at.mode, "4", "AT+FU4"),
    (at.raw, "AT+V", "AT+V"),
])
def test_commands_are_built(build, arg, text) -> None:
    assert build(arg).text == text


@pytest.mark.parametrize(("build", "arg", "words"), [
    (at.channel, "0", "1–127"), (at.channel, "128", "1–127"), (at.channel, "x", "integer"),
    (at.baud, "9601", "1200|2400"), (at.baud, "fast", "1200|2400"),
    (at.power, "0", "1–8"), (at.power, "9", "1–8"),
    (at.mode, "0", "1–4"), (at.mode, "5", "1–4"),
    (at.raw, "HELLO", "starts with AT"), (at.raw, "AT+C001\r\nAT+P8", "printable"),
    (at.raw, "AT" + "X" * 40, "printable"),
])
def test_invalid_arguments_are_one_clear_line(build, arg, words) -> None:
    with pytest.raises(at.AtUsageError) as err:
        build(arg)
    assert words in str(err.value) and "\n" not in str(err.value)


def test_rx_reply_parses_into_fields() -> None:
    s = at.parse_rx(["OK+FU4", "OK+B1200", "OK+C021", "OK+RP:-1dBm"])
    assert (s.mode, s.baud, s.channel, s.power_dbm, s.power_level) == (4, 1200, 21, -1, 1)
    assert s.frequency_mhz == 441.4
    assert s.air_bps == 500
    with pytest.raises(at.AtReplyError):
        at.parse_rx(["OK+FU3", "OK+B9600", "OK+C001"])


def test_replies_are_checked() -> None:
    at.channel(5).check(["OK+C005"])
    at.reset().check(["OK_DEFAULT"])
    at.mode(4).check(["OK+FU4,B1200"])
    with pytest.raises(at.AtReplyError):
        at.channel(5).check(["OK+C006"])
    with pytest.raises(at.AtReplyError):
        at.power(8).check(["ERROR"])
    with pytest.raises(at.AtReplyError, match="garbled"):
        at.split_lines(b"\xfe\x81OK\r\n")
    assert at.split_lines(b"OK+B9600\r\nOK+C0") == (["OK+B9600"], b"OK+C0")


# -- SET line and IDLE rule ----------------------------------------------------------------------


def test_set_line_specs() -> None:
    assert parse_set_line("RTS").kind == "rts"
    spec = parse_set_line("gpio:/dev/gpiochip1:17")
    assert (spec.kind, spec.chip, spec.line) == ("gpio", "/dev/gpiochip1", 17)
    for bad in ("cts", "gpio:17", "gpio:chip:x", ""):
        with pytest.raises(ValueError, match="set_line"):
            parse_set_line(bad)
    with pytest.raises(SetLineError) as err:
        NoSetLine().check()
    assert str(err.value) == BENCH_HINT and "bench" in BENCH_HINT


def test_idle_rule() -> None:
    clock = FakeClock()
    watch = VehicleWatch(3.0, clock=clock)
    assert "no vehicle heard" in watch.refusal(bench=False)
    assert watch.refusal(bench=True) is None
    watch.observe(sm(0))
    assert watch.refusal() is None
    watch.observe(status(1, armed=True))  # the latest word counts, whichever kind
    assert "ARMED" in watch.refusal()
    watch.observe(sm(0, armed=True))  # IDLE but armed: not safe
    assert "armed" in watch.refusal()
    watch.observe(status(0))
    clock.advance(3.5)
    assert "3.5 s ago" in watch.refusal(bench=True)  # --bench does not cover a quiet vehicle
    watch.observe(sm(4))
    assert "APOGEE" in watch.refusal()
    watch.observe(sm(0)._replace(sm_type=9))  # unknown state machine: cannot know IDLE
    assert "STATE_0" in watch.refusal()
