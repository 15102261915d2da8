"""Is the vehicle known to be IDLE?  The provisioning shell's first rule, as pure logic.

Reprovisioning the radio silences the downlink and stalls the UART worker for a fraction of a
second: never the right thing to do unless the vehicle is on the ground and disarmed.  The
rule (seed 000, "Provisioning shell"), with an injectable clock:

* the latest SM_UPDATE or STATUS says IDLE (under its ``sm_type``) and not armed, and is no
  older than ``max_age_s`` → allowed;
* a vehicle was heard but its latest word is older than that, or says anything but IDLE, or
  comes from an unknown state machine → refused (``--bench`` does not override this: a vehicle
  that went quiet may be in flight, out of range);
* no vehicle heard at all → refused unless the operator says ``--bench`` (the module is on a
  bench with no vehicle around).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from dialects.states import IDLE_STATE, state_name
from gateway.model import SmUpdate, Status, kind

DEFAULT_MAX_AGE_S = 3.0


@dataclass(frozen=True)
class Heard:
    """The latest word from the vehicle."""

    kind: str  # "sm_update" | "status"
    sm_type: int
    state: int
    armed: bool
    at: float  # clock time it arrived
    origin: str = ""

    @property
    def state_name(self) -> str:
        return state_name(self.sm_type, self.state)

    @property
    def idle(self) -> bool:
        return IDLE_STATE.get(self.sm_type) == self.state and not self.armed


class VehicleWatch:
    """Remembers the latest SM_UPDATE/STATUS and judges whether provisioning is safe."""

    def __init__(self, max_age_s: float = DEFAULT_MAX_AGE_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.max_age_s = max_age_s
        self._clock = clock
        self._lock = threading.Lock()
        self.last: Heard | None = None

    def observe(self, msg: SmUpdate | Status) -> None:
        heard = Heard(kind(msg), msg.sm_type, msg.state, bool(msg.armed), self._clock(),
                      msg.origin)
        with self._lock:
            self.last = heard

    def refusal(self, bench: bool = False) -> str | None:
        """None when provisioning is allowed now, else the reason (one line)."""
        with self._lock:
            last = self.last
        if last is None:
            if bench:
                return None
            return ("no vehicle heard: cannot confirm it is IDLE; if the module is on the bench "
                    "with no vehicle around, pass --bench")
        age = self._clock() - last.at
        if age > self.max_age_s:
            return (f"vehicle last heard {age:.1f} s ago ({last.state_name}): cannot confirm it "
                    f"is IDLE now (must be heard within {self.max_age_s:g} s)")
        if not last.idle:
            armed = ", armed" if last.armed and last.state_name != "ARMED" else ""
            return (f"vehicle is {last.state_name}{armed} (heard {age:.1f} s ago): "
                    f"provisioning is only allowed while it is IDLE")
        return None

    def describe(self) -> str:
        with self._lock:
            last = self.last
        if last is None:
            return "no vehicle heard"
        return f"vehicle {last.state_name}, heard {self._clock() - last.at:.1f} s ago"
