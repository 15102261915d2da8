"""A deterministic model of one Aurora flight through the SIMPLE state machine, repeated.

Everything is a function of simulated time ``t`` (seconds since the start of a cycle): no
threads, sockets or clocks, so the flight can be sampled at any rate and tested without
waiting.

The cycle is::

    IDLE (idle_s) → ARMED (armed_s) → BOOST → BURNOUT → APOGEE → MAIN → REDUNDANT → LANDED
    → IDLE (landed_to_idle_s after touchdown: the crew disarms; the next cycle begins)

The flight itself is a 1-D vertical flight integrated once, at construction, with a fixed
1 ms RK4 step: a trapezoidal thrust curve with a constant propellant burn rate, gravity,
quadratic drag of the body, a drogue that inflates at apogee and a main chute that inflates
``main_delay_s`` after it.  The state changes where the firmware's would:

* BOOST at ignition (the end of ARMED), BURNOUT when the thrust ends;
* APOGEE when the vertical velocity crosses zero;
* MAIN and REDUNDANT on timers started at apogee (``main_delay_s``, ``redundant_delay_s``);
* LANDED at touchdown, when the altitude returns to the ground;
* IDLE ``landed_to_idle_s`` after touchdown (the disarm).

The default physics parameters were solved (bisection on ``thrust_n`` for the apogee time, then
on ``main_cda_m2`` for the touchdown time) so that the default profile reproduces the timing of
the real flight "2026-04-26 #2" (:data:`SPEC_FLIGHT_2026_04_26_2`, ``shared/specs/aurora-wire.md``).

Sign conventions of the snapshot: altitude above the pad, velocity up positive;
``acceleration_mps2`` is the magnitude of the specific force (what an accelerometer reads:
about g at rest), ``accel_vert_mps2`` its signed component along the rocket's body axis (nose
direction).  The attitude is synthetic but continuous: pitch ≈ 1.48 rad on the rail (5° tilt),
a roll spin-up from canted fins during the ascent, an arc-over towards apogee, a rocket hanging
roughly horizontal and swinging under the chutes, lying flat after touchdown, and in the last
``recovery_s`` of LANDED put back on the rail for the next cycle.

``armed`` is True from ARMED to LANDED inclusive: the firmware leaves LANDED only when it is
disarmed, which is the LANDED → IDLE transition.
"""

from __future__ import annotations

import math
import threading
from bisect import bisect_right
from dataclasses import dataclass
from typing import Any

from dialects.states import SimpleState
from gateway.model import SM_UPDATE_F32_LEN, SM_UPDATE_F64_LEN, SmUpdate, Status

G = 9.80665  # standard gravity, m/s²

#: The real flight "2026-04-26 #2": seconds after ARMED → BOOST of each later transition.
SPEC_FLIGHT_2026_04_26_2: dict[str, float] = {
    "BURNOUT": 0.56,
    "APOGEE": 2.81,
    "MAIN": 4.77,
    "REDUNDANT": 6.78,
    "LANDED": 9.23,
    "IDLE": 100.2,
}

_MAX_FLIGHT_S = 3600.0  # give up integrating a profile that has not landed after this long

# Attitude shaping (synthetic; only continuity and plausibility matter).
_APOGEE_PITCH_RAD = 1.0  # arc-over reached at apogee
_CHUTE_SETTLE_S = 0.8  # time constant of the pitch settling towards horizontal under the chute
_SWING_PITCH_RAD = 0.15  # pendulum swing under the chute
_SWING_PITCH_PERIOD_S = 1.7
_SWING_YAW_RAD = 0.08
_SWING_YAW_PERIOD_S = 2.3
_TOPPLE_S = 0.2  # time constant of the swing dying out once on the ground


@dataclass(frozen=True, slots=True)
class FlightProfile:
    """Parameters of the simulated flight; defaults reproduce the 2026-04-26 #2 flight's timing.

    Changing a physics parameter changes the flight (and so the transition times) accordingly;
    the pad and timer durations only shift or stretch the states they name.
    """

    idle_s: float = 5.0  # on the pad, IDLE, before arming
    armed_s: float = 10.0  # ARMED on the pad before ignition (real rockets sit minutes)
    # motor: trapezoidal thrust curve, propellant burnt at a constant rate
    burn_s: float = 0.56  # ignition to the end of thrust (BURNOUT)
    thrust_n: float = 34.32  # plateau thrust, N
    thrust_rise_s: float = 0.03  # linear ramp 0 → thrust_n after ignition
    thrust_tail_s: float = 0.08  # linear tail-off thrust_n → 0 before burn_s
    dry_mass_kg: float = 0.60
    propellant_kg: float = 0.025
    # aerodynamics: drag = ½ ρ (Cd·A) v², opposing the velocity
    air_density_kgpm3: float = 1.225
    body_cda_m2: float = 0.0015  # Cd·A of the body (Cd 0.53, 60 mm diameter)
    drogue_cda_m2: float = 0.12  # added when the drogue opens, at apogee
    main_cda_m2: float = 0.4395  # added when the main opens, main_delay_s after apogee
    chute_inflation_s: float = 0.3  # a chute's Cd·A grows linearly over this time
    # the firmware's timers, started at apogee
    main_delay_s: float = 1.96  # APOGEE → MAIN (main chute deployment)
    redundant_delay_s: float = 3.97  # APOGEE → REDUNDANT (backup charges)
    # after the flight
    landed_to_idle_s: float = 90.97  # touchdown → disarm (LANDED → IDLE)
    recovery_s: float = 5.0  # last part of LANDED in which the rocket is set back on the rail
    # attitude on the pad and spin
    rail_tilt_rad: float = 0.0908  # from vertical: pitch on the rail = π/2 − tilt ≈ 1.48
    heading_rad: float = 0.6  # yaw of the rail
    pad_roll_rad: float = 0.1
    spin_rad_per_m: float = 0.12  # roll gained per metre climbed (canted fins)
    # integration and wire
    step_s: float = 0.001
    revision: int = SM_UPDATE_F64_LEN  # SM_UPDATE payload_len to emit (36 or 64)
    sm_type: int = 0

    def __post_init__(self) -> None:
        if self.revision not in (SM_UPDATE_F32_LEN, SM_UPDATE_F64_LEN):
            raise ValueError(f"revision must be 36 or 64, not {self.revision}")
        if self.idle_s < 0 or self.armed_s < 0 or self.landed_to_idle_s < 0:
            raise ValueError("idle_s, armed_s and landed_to_idle_s must not be negative")
        if self.recovery_s < 0:
            raise ValueError("recovery_s must not be negative")
        if not 0 < self.step_s <= 0.01:
            raise ValueError("step_s must be in (0, 0.01]")
        if self.burn_s <= 0 or self.thrust_rise_s < 0 or self.thrust_tail_s < 0:
            raise ValueError("burn_s must be positive and the thrust ramps not negative")
        if self.thrust_rise_s + self.thrust_tail_s > self.burn_s:
            raise ValueError("thrust_rise_s + thrust_tail_s must not exceed burn_s")
        if self.dry_mass_kg <= 0 or self.propellant_kg < 0:
            raise ValueError("dry_mass_kg must be positive and propellant_kg not negative")
        if min(self.body_cda_m2, self.drogue_cda_m2, self.main_cda_m2) < 0:
            raise ValueError("drag areas must not be negative")
        if self.drogue_cda_m2 + self.main_cda_m2 <= 0 or self.air_density_kgpm3 <= 0:
            raise ValueError("a parachute and air are needed to come down gently")
        if self.chute_inflation_s < 0:
            raise ValueError("chute_inflation_s must not be negative")
        if not 0 <= self.main_delay_s <= self.redundant_delay_s:
            raise ValueError("need 0 <= main_delay_s <= redundant_delay_s")


def _ramp(x: float, length: float) -> float:
    """0 → 1 linearly over [0, length] (a step at 0 when length is 0)."""
    if x <= 0.0:
        return 0.0
    if x >= length:
        return 1.0
    return x / length


def _wrap(a: float) -> float:
    """``a`` wrapped to (−π, π]."""
    return math.pi - (math.pi - a) % (2.0 * math.pi)


def _smoothstep(x: float) -> float:
    x = min(max(x, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


#: The slots :meth:`FlightModel._complete` fills (see ``FlightModel.__getattr__``).
_INTEGRATED = frozenset({"_alt", "_vel", "_f", "_t_apogee", "_t_land", "apogee_altitude_m",
                         "max_velocity_mps", "_apogee_roll", "_land_pitch", "_land_yaw",
                         "_trans_times", "_trans_states"})


_INTEGRATING = threading.RLock()


class FlightModel:
    """One flight cycle of ``profile``, integrated once; sampled at any time ``t``.

    ``t`` is seconds since the start of a cycle and wraps modulo :attr:`cycle_s`.
    """

    __slots__ = (
        "_alt",
        "_apogee_roll",
        "_busy",
        "_f",
        "_land_pitch",
        "_land_yaw",
        "_t_apogee",
        "_t_land",
        "_trans_states",
        "_trans_times",
        "_vel",
        "apogee_altitude_m",
        "launch_time_s",
        "max_velocity_mps",
        "profile",
    )

    def __init__(self, profile: FlightProfile = FlightProfile(), *, lazy: bool = False) -> None:
        """``lazy``: integrate when first sampled (see :meth:`__getattr__`), for a profile
        known to be valid (a bad one raises ValueError there instead of here)."""
        self.profile = p = profile
        #: cycle time of ARMED → BOOST (ignition)
        self.launch_time_s: float = p.idle_s + p.armed_s
        if not lazy:
            self._busy = True
            self._complete()

    def __getattr__(self, name: str) -> Any:
        """A lazy model is integrated when first needed, not when it is made: tens of
        milliseconds of a gateway's start-up (its backends start first, the simulated
        source's first sample waits for it).  Only the slots it fills come here."""
        if name not in _INTEGRATED:
            raise AttributeError(name)
        with _INTEGRATING:  # another thread integrating: wait for it
            try:  # complete? (the state table is its last step)
                object.__getattribute__(self, "_trans_states")
            except AttributeError:
                try:
                    object.__getattribute__(self, "_busy")
                except AttributeError:
                    self._busy = True
                    self._complete()
                else:  # under way on this very thread: the slot is not set yet
                    raise AttributeError(name) from None
        return object.__getattribute__(self, name)

    def _complete(self) -> None:
        p = self.profile
        self._integrate()
        self._apogee_roll = p.pad_roll_rad + p.spin_rad_per_m * self.apogee_altitude_m
        self._land_pitch = self._descent_pitch(self._t_land)
        self._land_yaw = self._descent_yaw(self._t_land)
        S = SimpleState
        after_launch = [
            (0.0, S.BOOST),
            (p.burn_s, S.BURNOUT),
            (self._t_apogee, S.APOGEE),
            (self._t_apogee + p.main_delay_s, S.MAIN),
            (self._t_apogee + p.redundant_delay_s, S.REDUNDANT),
            (self._t_land, S.LANDED),
            (self._t_land + p.landed_to_idle_s, S.IDLE),
        ]
        trans = [(0.0, int(S.IDLE)), (p.idle_s, int(S.ARMED))]
        trans += [(self.launch_time_s + t, int(s)) for t, s in after_launch]
        self._trans_times = [t for t, _ in trans]
        self._trans_states = [s for _, s in trans]

    # -- the physics, once ------------------------------------------------------------------

    def _thrust(self, t: float) -> float:
        p = self.profile
        if t < 0.0 or t >= p.burn_s:
            return 0.0
        return p.thrust_n * min(_ramp(t, p.thrust_rise_s), _ramp(p.burn_s - t, p.thrust_tail_s))

    def _integrate(self) -> None:
        """Integrate the flight from ignition to touchdown; fill the sample table and events."""
        p = self.profile
        h = p.step_s
        q = 0.5 * p.air_density_kgpm3
        burn_s, dry, prop = p.burn_s, p.dry_mass_kg, p.propellant_kg
        body, drogue, main = p.body_cda_m2, p.drogue_cda_m2, p.main_cda_m2
        infl = p.chute_inflation_s
        thrust = self._thrust
        t_apo = math.inf  # unknown until the velocity crosses zero

        def force(t: float, v: float) -> float:
            """Specific force (non-gravitational acceleration) in flight, up positive."""
            m = dry + prop * (1.0 - t / burn_s) if t < burn_s else dry
            cda = body
            if t > t_apo:
                cda += drogue * _ramp(t - t_apo, infl)
                cda += main * _ramp(t - t_apo - p.main_delay_s, infl)
            return (thrust(t) - q * cda * v * abs(v)) / m

        alt, vel, spf = [0.0], [0.0], [G]
        x = v = 0.0
        airborne = False
        t_land = math.nan
        vmax = 0.0
        k = 0
        while True:
            t = k * h
            if t > _MAX_FLIGHT_S:
                raise ValueError("the profile does not land (check drag and chutes)")
            if not airborne:
                if force(t, 0.0) > G:
                    airborne = True
                elif t > burn_s:
                    raise ValueError("thrust_n is too low to lift the rocket off the pad")
            if airborne:
                h2 = 0.5 * h
                a1 = force(t, v) - G
                v2 = v + h2 * a1
                a2 = force(t + h2, v2) - G
                v3 = v + h2 * a2
                a3 = force(t + h2, v3) - G
                v4 = v + h * a3
                a4 = force(t + h, v4) - G
                x_new = x + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
                v_new = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
                if t_apo == math.inf and v > 0.0 >= v_new and t > 0.0:
                    t_apo = t + h * v / (v - v_new)
                    self._t_apogee = t_apo
                if t_apo != math.inf and x_new <= 0.0:
                    t_land = t + h * x / (x - x_new)
                    x, v = 0.0, v_new
                else:
                    x, v = x_new, v_new
                vmax = max(vmax, v)
                alt.append(x)
                vel.append(v)
                spf.append(force(t + h, v))
            else:
                alt.append(0.0)
                vel.append(0.0)
                spf.append(G)
            k += 1
            if not math.isnan(t_land):
                break
        self._alt, self._vel, self._f = alt, vel, spf
        self._t_land = t_land
        if t_land < t_apo + p.redundant_delay_s:
            raise ValueError("the profile lands before REDUNDANT; the state sequence would break")
        self.apogee_altitude_m = max(alt)
        self.max_velocity_mps = vmax

    # -- attitude ----------------------------------------------------------------------------

    def _pad_pitch(self) -> float:
        return 0.5 * math.pi - self.profile.rail_tilt_rad

    def _descent_pitch(self, tr: float) -> float:
        """Pitch after apogee (``tr`` seconds after launch): settling to a swing about 0."""
        dt = tr - self._t_apogee
        settle = math.exp(-dt / _CHUTE_SETTLE_S)
        swing = _SWING_PITCH_RAD * math.sin(2.0 * math.pi * dt / _SWING_PITCH_PERIOD_S)
        return _APOGEE_PITCH_RAD * settle + (1.0 - settle) * swing

    def _descent_yaw(self, tr: float) -> float:
        dt = tr - self._t_apogee
        settle = math.exp(-dt / _CHUTE_SETTLE_S)
        swing = _SWING_YAW_RAD * math.sin(2.0 * math.pi * dt / _SWING_YAW_PERIOD_S)
        return self.profile.heading_rad + (1.0 - settle) * swing

    def _attitude(self, tc: float, tr: float, alt: float) -> tuple[float, float, float]:
        """(roll, pitch, yaw) at cycle time ``tc`` (``tr`` after launch, altitude ``alt``)."""
        p = self.profile
        pad_pitch = self._pad_pitch()
        if tr < 0.0:
            return _wrap(p.pad_roll_rad), pad_pitch, _wrap(p.heading_rad)
        if tr < self._t_apogee:
            s = tr / self._t_apogee
            pitch = pad_pitch - (pad_pitch - _APOGEE_PITCH_RAD) * s * s * s
            roll = p.pad_roll_rad + p.spin_rad_per_m * alt
            return _wrap(roll), pitch, _wrap(p.heading_rad)
        if tr < self._t_land:
            return _wrap(self._apogee_roll), self._descent_pitch(tr), _wrap(self._descent_yaw(tr))
        # on the ground: the swing dies out, then the crew sets the rocket back on the rail
        lie = math.exp(-(tr - self._t_land) / _TOPPLE_S)
        pitch = self._land_pitch * lie
        yaw = self._land_yaw
        roll = self._apogee_roll
        rec = min(p.recovery_s, p.landed_to_idle_s)
        if rec > 0.0:
            u = _smoothstep(1.0 - (self.cycle_s - tc) / rec)
            if u > 0.0:
                pitch += (pad_pitch - pitch) * u
                yaw += _wrap(p.heading_rad - yaw) * u
                roll += _wrap(p.pad_roll_rad - roll) * u
        return _wrap(roll), pitch, _wrap(yaw)

    # -- public API --------------------------------------------------------------------------

    @property
    def cycle_s(self) -> float:
        """Length of one full cycle (IDLE ... back to IDLE, where the next cycle starts)."""
        return self._trans_times[-1]

    @property
    def events(self) -> dict[str, float]:
        """Seconds after launch of each in-flight transition and of the return to IDLE."""
        launch = self.launch_time_s
        return {
            SimpleState(s).name: t - launch
            for t, s in zip(self._trans_times[3:], self._trans_states[3:], strict=True)
        }

    def transitions(self) -> list[tuple[float, int]]:
        """(time since cycle start, new state) for one cycle, in order, from (0.0, IDLE).

        The last entry is the return to IDLE at :attr:`cycle_s`, i.e. the next cycle's start.
        """
        return list(zip(self._trans_times, self._trans_states, strict=True))

    def _cycle_time(self, t: float) -> float:
        tc = t % self.cycle_s
        return 0.0 if tc >= self.cycle_s else tc  # guard the rounding of a negative t

    def _state_in_cycle(self, tc: float) -> int:
        i = bisect_right(self._trans_times, tc) - 1
        return self._trans_states[max(i, 0)]

    def state_at(self, t: float) -> int:
        """The SimpleState value at time ``t`` (``t`` wraps modulo :attr:`cycle_s`)."""
        return self._state_in_cycle(self._cycle_time(t))

    def _armed(self, state: int) -> bool:
        return SimpleState.ARMED <= state <= SimpleState.LANDED

    def sm_update(self, t: float, timestamp_ms: int) -> SmUpdate:
        """The state-machine snapshot at ``t``, as the flight computer would send it."""
        p = self.profile
        tc = self._cycle_time(t)
        state = self._state_in_cycle(tc)
        tr = tc - self.launch_time_s
        if 0.0 <= tr < self._t_land:
            x = tr / p.step_s
            k = min(int(x), len(self._alt) - 2)
            w = x - k
            alt = max(0.0, self._alt[k] + w * (self._alt[k + 1] - self._alt[k]))
            vel = self._vel[k] + w * (self._vel[k + 1] - self._vel[k])
            f = self._f[k] + w * (self._f[k + 1] - self._f[k])
        else:
            alt, vel, f = 0.0, 0.0, G
        roll, pitch, yaw = self._attitude(tc, tr, alt)
        return SmUpdate(
            timestamp_ms=timestamp_ms,
            state=state,
            armed=self._armed(state),
            sm_type=p.sm_type,
            altitude_m=alt,
            acceleration_mps2=abs(f),
            accel_vert_mps2=f * math.sin(pitch),
            velocity_mps=vel,
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=yaw,
            payload_len=p.revision,
        )

    def status(self, t: float, timestamp_ms: int) -> Status:
        """The STATUS heartbeat at ``t``: ARMED as the state machine is, every sensor healthy."""
        state = self.state_at(t)
        flags = Status.make_flags(
            armed=self._armed(state), imu_ok=True, baro_ok=True, calibrated=True, log_ready=True
        )
        return Status(
            timestamp_ms=timestamp_ms, state=state, sm_type=self.profile.sm_type, flags=flags
        )
