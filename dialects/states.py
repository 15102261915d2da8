"""State-machine enums of the Aurora firmware, selected by ``sm_type``.

The firmware sends ``sm_type`` with every update so a receiver can name ``state`` without
prior agreement.  Unknown machines and unknown states are never rejected: they keep their
number and display as ``STATE_<n>``.
"""

from __future__ import annotations

from enum import IntEnum


class SimpleState(IntEnum):
    """States of the SIMPLE state machine (``sm_type`` 0)."""

    IDLE = 0
    ARMED = 1
    BOOST = 2
    BURNOUT = 3
    APOGEE = 4
    MAIN = 5
    REDUNDANT = 6
    LANDED = 7
    ERROR = 8


SM_TYPE_SIMPLE = 0

#: ``sm_type`` → the enum naming its states.
STATE_MACHINES: dict[int, type[IntEnum]] = {SM_TYPE_SIMPLE: SimpleState}

#: States that count as "in flight" and "on the pad", per ``sm_type``.
IN_FLIGHT: dict[int, frozenset[int]] = {
    SM_TYPE_SIMPLE: frozenset(range(SimpleState.BOOST, SimpleState.REDUNDANT + 1)),
}
ON_PAD: dict[int, frozenset[int]] = {
    SM_TYPE_SIMPLE: frozenset({SimpleState.IDLE, SimpleState.ARMED}),
}
#: The state a machine returns to when it is safe to touch the vehicle (e.g. to provision it).
IDLE_STATE: dict[int, int] = {SM_TYPE_SIMPLE: SimpleState.IDLE}
#: The state that means the flight computer gave up.
ERROR_STATE: dict[int, int] = {SM_TYPE_SIMPLE: SimpleState.ERROR}


def state_enum(sm_type: int) -> type[IntEnum] | None:
    """The enum for ``sm_type``, or None when the machine is unknown."""
    return STATE_MACHINES.get(sm_type)


def state_name(sm_type: int, state: int) -> str:
    """Display name of ``state`` under ``sm_type``: the enum name, else ``STATE_<n>``."""
    enum = STATE_MACHINES.get(sm_type)
    if enum is not None:
        try:
            return enum(state).name
        except ValueError:
            pass
    return f"STATE_{state}"


def state_names(sm_type: int) -> list[tuple[int, str]]:
    """Every (number, name) of a known machine, in order; empty for an unknown one."""
    enum = STATE_MACHINES.get(sm_type)
    return [(int(s), s.name) for s in enum] if enum is not None else []


def is_in_flight(sm_type: int, state: int) -> bool:
    return state in IN_FLIGHT.get(sm_type, frozenset())


def is_on_pad(sm_type: int, state: int) -> bool:
    return state in ON_PAD.get(sm_type, frozenset())
