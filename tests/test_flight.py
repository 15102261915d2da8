"""The simulated flight: state sequence, real-flight timing, physical plausibility, repetition."""

from __future__ import annotations

import dataclasses
import itertools
import math
import threading
from typing import Any

import pytest

from dialects.states import SimpleState as S
from gateway.flight import SPEC_FLIGHT_2026_04_26_2, FlightModel, FlightProfile, G
from gateway.model import SmUpdate, Status
from gateway.wire import decode_all, encode

SEQUENCE = [S.IDLE, S.ARMED, S.BOOST, S.BURNOUT, S.APOGEE, S.MAIN, S.REDUNDANT, S.LANDED, S.IDLE]
TOL_S = 0.05


@pytest.fixture(scope="module")
def model() -> FlightModel:
    return FlightModel()


def times(start: float, stop: float, step: float) -> list[float]:
    """start, start + step, ... up to and including ``stop`` (within rounding)."""
    n = int((stop - start) / step + 1e-9)
    return [start + i * step for i in range(n + 1)]


def event(model: FlightModel, state: S) -> float:
    """Cycle time of the first transition into ``state`` after launch."""
    return next(t for t, s in model.transitions() if s == state and t >= model.launch_time_s)


def angle_diff(a: float, b: float) -> float:
    return abs(math.remainder(a - b, 2.0 * math.pi))


# -- the state machine ---------------------------------------------------------------------


def test_transition_sequence(model: FlightModel) -> None:
    trans = model.transitions()
    assert [s for _, s in trans] == [int(s) for s in SEQUENCE]
    assert trans[0] == (0.0, S.IDLE)
    ts = [t for t, _ in trans]
    assert ts == sorted(ts) and len(set(ts)) == len(ts)
    assert ts[-1] == pytest.approx(model.cycle_s)
    assert trans[2] == (pytest.approx(model.launch_time_s), S.BOOST)


def test_default_profile_launch_time(model: FlightModel) -> None:
    p = FlightProfile()
    assert model.launch_time_s == pytest.approx(p.idle_s + p.armed_s)
    assert model.state_at(p.idle_s - 0.01) == S.IDLE
    assert model.state_at(p.idle_s + 0.01) == S.ARMED
    assert model.state_at(model.launch_time_s - 0.01) == S.ARMED
    assert model.state_at(model.launch_time_s + 0.01) == S.BOOST


@pytest.mark.parametrize("name", list(SPEC_FLIGHT_2026_04_26_2))
def test_transition_times_match_real_flight(model: FlightModel, name: str) -> None:
    after_launch = event(model, S[name]) - model.launch_time_s
    assert after_launch == pytest.approx(SPEC_FLIGHT_2026_04_26_2[name], abs=TOL_S)
    assert model.events[name] == pytest.approx(after_launch)


def test_cycle_ends_back_in_idle(model: FlightModel) -> None:
    assert model.cycle_s - model.launch_time_s == pytest.approx(
        SPEC_FLIGHT_2026_04_26_2["IDLE"], abs=TOL_S
    )
    assert model.state_at(model.cycle_s - 0.01) == S.LANDED
    assert model.state_at(model.cycle_s) == S.IDLE


def test_state_at_follows_transitions(model: FlightModel) -> None:
    trans = model.transitions()
    for (t0, s), (t1, _) in itertools.pairwise(trans):
        for t in (t0 + 1e-6, (t0 + t1) / 2, t1 - 1e-6):
            assert model.state_at(t) == s
            assert model.sm_update(t, 0).state == s


def test_never_error(model: FlightModel) -> None:
    states = {model.state_at(t) for t in times(0.0, model.cycle_s, 0.01)}
    assert S.ERROR not in states
    assert states == {int(s) for s in SEQUENCE}


def test_armed_flag(model: FlightModel) -> None:
    for t in times(0.0, model.cycle_s, 0.05):
        msg = model.sm_update(t, 0)
        expected = S.ARMED <= msg.state <= S.LANDED
        assert msg.armed is expected
        assert model.status(t, 0).armed is expected


# -- repetition and determinism ------------------------------------------------------------


def test_cycle_repeats(model: FlightModel) -> None:
    c = model.cycle_s
    for t in times(0.013, c, 0.37):
        s = model.state_at(t)
        assert model.state_at(t + c) == s
        assert model.state_at(t + 3 * c) == s
        assert model.state_at(t - c) == s
        a, b = model.sm_update(t, 0), model.sm_update(t + 2 * c, 0)
        assert a.state == b.state and a.armed == b.armed
        for x, y in zip(a.fields().values(), b.fields().values(), strict=True):
            assert x == pytest.approx(y, abs=1e-6)


def test_continuous_across_the_cycle_wrap(model: FlightModel) -> None:
    c = model.cycle_s
    before, after = model.sm_update(c - 0.05, 0), model.sm_update(c + 0.05, 0)
    assert (before.state, after.state) == (S.LANDED, S.IDLE)
    assert after.pitch_rad == pytest.approx(before.pitch_rad, abs=0.01)
    assert angle_diff(after.roll_rad, before.roll_rad) < 0.01
    assert angle_diff(after.yaw_rad, before.yaw_rad) < 0.01


def test_deterministic() -> None:
    a, b = FlightModel(), FlightModel()
    assert a.transitions() == b.transitions()
    for t in times(14.0, 26.0, 0.1):
        assert a.sm_update(t, 7) == b.sm_update(t, 7)


# -- physics -------------------------------------------------------------------------------


def test_apogee_is_the_highest_point(model: FlightModel) -> None:
    t_apo = event(model, S.APOGEE)
    flight = times(model.launch_time_s, event(model, S.LANDED), 0.001)
    alts = [model.sm_update(t, 0).altitude_m for t in flight]
    peak = max(alts)
    t_peak = flight[alts.index(peak)]
    assert t_peak == pytest.approx(t_apo, abs=0.002)
    assert model.apogee_altitude_m == pytest.approx(peak, abs=1e-3)
    assert model.sm_update(t_apo - 0.01, 0).velocity_mps > 0
    assert model.sm_update(t_apo + 0.01, 0).velocity_mps < 0
    assert model.sm_update(t_apo, 0).velocity_mps == pytest.approx(0.0, abs=0.02)
    assert 15.0 < peak < 100.0  # a small rocket that peaks after 2.8 s


def test_velocity_sign_by_phase(model: FlightModel) -> None:
    for t in times(model.launch_time_s + 0.05, event(model, S.LANDED) - 0.01, 0.01):
        msg = model.sm_update(t, 0)
        if msg.state in (S.BOOST, S.BURNOUT):
            assert msg.velocity_mps > 0
        else:
            assert msg.velocity_mps < 0


def test_fields_finite_and_in_range(model: FlightModel) -> None:
    for t in times(0.0, model.cycle_s, 0.01):
        msg = model.sm_update(t, 0)
        values = list(msg.fields().values())[4:11]
        assert all(math.isfinite(v) for v in values)
        assert msg.altitude_m >= 0.0
        assert msg.acceleration_mps2 >= 0.0
        assert abs(msg.accel_vert_mps2) <= msg.acceleration_mps2 + 1e-9
        for angle in (msg.roll_rad, msg.yaw_rad):
            assert -math.pi < angle <= math.pi
        assert -math.pi / 2 <= msg.pitch_rad <= math.pi / 2


def test_at_rest_on_the_pad(model: FlightModel) -> None:
    for t in times(0.0, model.launch_time_s - 0.001, 0.1):
        msg = model.sm_update(t, 0)
        assert msg.on_pad
        assert msg.altitude_m == 0.0 and msg.velocity_mps == 0.0
        assert msg.acceleration_mps2 == pytest.approx(G, abs=0.1)
        assert msg.pitch_rad == pytest.approx(1.48, abs=0.01)
        assert msg.accel_vert_mps2 == pytest.approx(G * math.sin(1.48), abs=0.1)


def test_at_rest_after_landing(model: FlightModel) -> None:
    t_land = event(model, S.LANDED)
    recovery = model.cycle_s - model.profile.recovery_s
    for t in times(t_land + 0.001, model.cycle_s - 0.001, 0.1):
        msg = model.sm_update(t, 0)
        assert msg.state == S.LANDED
        assert msg.altitude_m == 0.0 and msg.velocity_mps == 0.0
        assert msg.acceleration_mps2 == pytest.approx(G, abs=0.1)
        if t_land + 2.0 < t < recovery:
            assert msg.pitch_rad == pytest.approx(0.0, abs=0.01)  # lying on the ground


def test_accelerometer_by_phase(model: FlightModel) -> None:
    p = model.profile
    launch = model.launch_time_s
    # boost: the motor pushes several g along the body axis
    for t in times(launch + 0.05, launch + p.burn_s - p.thrust_tail_s, 0.05):
        msg = model.sm_update(t, 0)
        assert msg.acceleration_mps2 > 3 * G
        assert msg.accel_vert_mps2 > 3 * G
    # coast: only drag, pointing down the body axis (the accelerometer reads below 1 g)
    for t in times(launch + p.burn_s + 0.01, event(model, S.APOGEE) - 0.01, 0.05):
        msg = model.sm_update(t, 0)
        assert msg.acceleration_mps2 < G
        assert msg.accel_vert_mps2 < 0
    # under the main chute at terminal speed: drag balances gravity
    for t in times(event(model, S.REDUNDANT), event(model, S.LANDED) - 0.01, 0.1):
        msg = model.sm_update(t, 0)
        assert msg.acceleration_mps2 == pytest.approx(G, abs=0.3)
        assert abs(msg.pitch_rad) < 0.3  # hanging roughly horizontal, swinging


def test_descent_is_survivable(model: FlightModel) -> None:
    t_land = event(model, S.LANDED)
    touchdown = model.sm_update(t_land - 0.002, 0).velocity_mps
    assert -7.0 < touchdown < -2.0
    drogue = model.sm_update(event(model, S.MAIN) - 0.01, 0).velocity_mps
    assert drogue < touchdown  # faster under the drogue than under the main


def test_velocity_is_the_altitude_derivative(model: FlightModel) -> None:
    launch, t_land = model.launch_time_s, event(model, S.LANDED)
    h = 0.005
    for t in times(launch + 0.1, t_land - 0.1, 0.1):
        rate = (model.sm_update(t + h, 0).altitude_m - model.sm_update(t - h, 0).altitude_m) / (
            2 * h
        )
        assert model.sm_update(t, 0).velocity_mps == pytest.approx(rate, abs=0.1)


@pytest.mark.parametrize("phase", [0.0, 0.033, 0.071])
def test_plausible_at_10_hz(model: FlightModel, phase: float) -> None:
    """No step between 10 Hz samples bigger than the motion in between allows."""
    dt = 0.1
    sub = 20
    t_land = event(model, S.LANDED)
    for t in times(phase, model.cycle_s - dt, dt):
        a, b = model.sm_update(t, 0), model.sm_update(t + dt, 0)
        inner = [model.sm_update(t + dt * i / sub, 0) for i in range(sub + 1)]
        vmax = max(abs(m.velocity_mps) for m in inner)
        amax = max(m.acceleration_mps2 for m in inner) + G  # |dv/dt| <= |specific force| + g
        assert abs(b.altitude_m - a.altitude_m) <= dt * vmax + 1e-6, t
        if not t < t_land <= t + dt:  # the touchdown's impact is not in the samples
            assert abs(b.velocity_mps - a.velocity_mps) <= dt * amax + 1e-6, t
        assert angle_diff(b.roll_rad, a.roll_rad) < 0.5, t
        assert abs(b.pitch_rad - a.pitch_rad) < 0.3, t
        assert angle_diff(b.yaw_rad, a.yaw_rad) < 0.1, t
        if b.state not in (S.BOOST, S.BURNOUT, S.MAIN):  # ignition, burnout, main opening
            assert abs(b.acceleration_mps2 - a.acceleration_mps2) < 3.0, t


def test_roll_spins_up_and_wraps(model: FlightModel) -> None:
    launch, t_apo = model.launch_time_s, event(model, S.APOGEE)
    rolls = [model.sm_update(t, 0).roll_rad for t in times(launch, t_apo, 0.01)]
    total = sum(math.remainder(b - a, 2 * math.pi) for a, b in itertools.pairwise(rolls))
    assert total > math.pi  # more than half a turn, so the wrap to (-π, π] is exercised
    assert any(b - a < -math.pi for a, b in itertools.pairwise(rolls))
    early = angle_diff(rolls[10], rolls[0])
    late = angle_diff(rolls[60], rolls[50])
    assert early < late  # spinning up while the speed builds


# -- the physics drives the events ---------------------------------------------------------


def test_events_follow_the_physics() -> None:
    base = FlightModel()
    stronger = FlightModel(FlightProfile(thrust_n=base.profile.thrust_n * 1.2))
    assert stronger.events["APOGEE"] > base.events["APOGEE"]
    assert stronger.apogee_altitude_m > base.apogee_altitude_m
    bigger = FlightModel(FlightProfile(main_cda_m2=base.profile.main_cda_m2 * 1.5))
    assert bigger.events["APOGEE"] == pytest.approx(base.events["APOGEE"])
    assert bigger.events["LANDED"] > base.events["LANDED"]
    longer = FlightModel(FlightProfile(burn_s=0.8))
    assert longer.events["BURNOUT"] == pytest.approx(0.8)
    # the firmware's timers stay timers
    for m in (stronger, bigger, longer):
        assert m.events["MAIN"] - m.events["APOGEE"] == pytest.approx(m.profile.main_delay_s)
        assert m.events["REDUNDANT"] - m.events["APOGEE"] == pytest.approx(
            m.profile.redundant_delay_s
        )


@pytest.mark.parametrize(("idle_s", "armed_s"), [(5.0, 120.0), (0.0, 0.1), (30.0, 10.0)])
def test_pad_time_shifts_launch_only(model: FlightModel, idle_s: float, armed_s: float) -> None:
    other = FlightModel(FlightProfile(idle_s=idle_s, armed_s=armed_s))
    assert other.launch_time_s == pytest.approx(idle_s + armed_s)
    assert other.cycle_s == pytest.approx(model.cycle_s - model.launch_time_s + idle_s + armed_s)
    assert other.events == pytest.approx(model.events)
    assert [s for _, s in other.transitions()] == [int(s) for s in SEQUENCE]
    for tr in times(-min(0.5, idle_s + armed_s), 10.0, 0.1):
        a = model.sm_update(model.launch_time_s + tr, 0)
        b = other.sm_update(other.launch_time_s + tr, 0)
        assert b.state == a.state
        assert b.altitude_m == pytest.approx(a.altitude_m, abs=1e-9)
        assert b.velocity_mps == pytest.approx(a.velocity_mps, abs=1e-9)


# -- messages and wire ---------------------------------------------------------------------


@pytest.mark.parametrize(("revision", "frame_len"), [(36, 42), (64, 70)])
def test_revision(revision: int, frame_len: int) -> None:
    m = FlightModel(FlightProfile(revision=revision))
    msg = m.sm_update(m.launch_time_s + 1.0, 123_456)
    assert isinstance(msg, SmUpdate)
    assert msg.payload_len == revision
    assert msg.raw == b"" and msg.origin == ""
    assert msg.timestamp_ms == 123_456 and msg.sm_type == 0
    frame = encode(msg)
    assert len(frame) == frame_len
    (back,) = decode_all(frame)
    assert back.payload_len == revision and back.state == msg.state
    for x, y in zip(
        list(back.fields().values())[4:11], list(msg.fields().values())[4:11], strict=True
    ):
        assert x == pytest.approx(y, rel=1e-6, abs=1e-6)


def test_status(model: FlightModel) -> None:
    t = model.launch_time_s + 3.0
    st = model.status(t, 99)
    assert isinstance(st, Status)
    assert (st.timestamp_ms, st.state, st.sm_type) == (99, model.state_at(t), 0)
    assert st.health() == {
        "armed": True,
        "imu_ok": True,
        "baro_ok": True,
        "calibrated": True,
        "log_ready": True,
    }
    idle = model.status(1.0, 0)
    assert idle.state == S.IDLE and not idle.armed and idle.imu_ok
    assert len(encode(st)) == 14


def test_sm_type_passes_through() -> None:
    m = FlightModel(FlightProfile(sm_type=0))
    assert m.sm_update(0.0, 0).sm_type == 0 and m.sm_update(0.0, 0).state_name == "IDLE"


@pytest.mark.parametrize(
    "kwargs",
    [
        {"revision": 48},
        {"thrust_n": 1.0},  # cannot lift off
        {"main_cda_m2": 0.0, "drogue_cda_m2": 0.0},
        {"main_delay_s": 5.0, "redundant_delay_s": 4.0},
        {"armed_s": -1.0},
        {"drogue_cda_m2": 5.0, "main_cda_m2": 0.0, "thrust_n": 20.0, "redundant_delay_s": 60.0},
    ],
)
def test_invalid_profiles(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        FlightModel(dataclasses.replace(FlightProfile(), **kwargs))


def test_a_lazy_model_is_the_same_flight_integrated_at_first_use() -> None:
    """The simulated source's model integrates when first sampled (start-up time), from any
    thread, and flies exactly the eager model's flight."""
    eager = FlightModel()
    lazy = FlightModel(lazy=True)
    results: list[Any] = []

    def sample() -> None:
        results.append(lazy.sm_update(30.0, 0))

    threads = [threading.Thread(target=sample) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(10.0)
    assert len(results) == 4 and all(r == eager.sm_update(30.0, 0) for r in results)
    assert lazy.apogee_altitude_m == eager.apogee_altitude_m
    assert lazy.transitions() == eager.transitions()
    for t in (0.0, 12.5, 47.0, eager.cycle_s - 0.1):
        assert lazy.sm_update(t, 7) == eager.sm_update(t, 7)
    with pytest.raises(AttributeError):
        _ = lazy.no_such_attribute  # type: ignore[attr-defined]
