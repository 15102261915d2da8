"""Vehicles: the unit every view of the gateway is kept by.

Every message carries the name of the vehicle it is about (``vehicle``, see
:mod:`gateway.model`).  A source is one vehicle, named on the command line
(``--source NAME=URL``) or in its table (``vehicle = "NAME"``); an unnamed source's vehicle
is derived from the source's name (:func:`derive_name`).  A source that hears several systems
names one vehicle per system (a MAVLink source ``<its vehicle>-<system id>``, a Zenoh source
the names the other gateway publishes).

A name matches ``[A-Za-z][A-Za-z0-9_-]*`` (:data:`NAME`): it is a Zenoh key chunk, a Foxglove
topic level, a ROS name part and a file-name part as it is.

Links that carry one vehicle (CRSF, the HC-12 relay, XBee's air side, UAVTalk's flight side,
F´) serve the vehicle named by ``vehicle = "NAME"`` in their table, or the first source's
(:class:`VehicleSelector`, declared by :class:`VehicleOptions`).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

from gateway.options import Options, option

log = logging.getLogger(__name__)

#: what a vehicle name matches
NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]*\Z")
MAX_NAME_LEN = 64
_UNSAFE = re.compile(r"[^A-Za-z0-9_-]+")

#: the service (``GatewayContext.services``) giving the configured sources' vehicles in
#: source order (``list[SourceVehicle]``): the first is what a single-vehicle link serves by
#: default; the MAVLink backend assigns system ids in this order
SERVICE = "gateway.vehicles"


class SourceVehicle(NamedTuple):
    """A configured source and its vehicle, with the MAVLink system id fixed for it (None:
    assigned).  ``systems``: the source yields one vehicle per system it hears, ``vehicle``
    being only the stem of their names (``<vehicle>-<id>``), never a vehicle itself."""

    source: str
    vehicle: str
    mavlink_sysid: int | None = None
    systems: bool = False


def check_name(name: object) -> str:
    """``name`` if it is a vehicle name, else :class:`ValueError` saying what one is."""
    if not isinstance(name, str) or not NAME.match(name) or len(name) > MAX_NAME_LEN:
        raise ValueError(f"{name!r} is not a vehicle name: a letter, then letters, digits, "
                         f"'_' or '-' (at most {MAX_NAME_LEN})")
    return name


def derive_name(text: str, fallback: str = "vehicle") -> str:
    """A vehicle name made of ``text`` (a source's name, a URL): runs of other characters
    become ``-``, leading non-letters go.  ``"socket://127.0.0.1:5000"`` →
    ``"socket-127-0-0-1-5000"``; ``"/dev/ttyUSB0"`` → ``"dev-ttyUSB0"``."""
    name = _UNSAFE.sub("-", text).strip("-")
    while name and not name[0].isalpha():
        name = name[1:].lstrip("-_")
    name = name[:MAX_NAME_LEN].rstrip("-_")
    return name if name and NAME.match(name) else fallback


def unique_names(wanted: Iterable[tuple[str, bool]]) -> list[str]:
    """One name per ``(name, given)`` in order: given names are kept (a clash is the caller's
    error), derived ones get ``-2``, ``-3`` … until unique among all."""
    items = list(wanted)
    taken = {n for n, given in items if given}
    out: list[str] = []
    for name, given in items:
        if not given:
            base, i = name, 2
            while name in taken:
                name = f"{base[:MAX_NAME_LEN - 1 - len(str(i))]}-{i}"
                i += 1
            taken.add(name)
        out.append(name)
    return out


def system_vehicle(source_vehicle: str, system: int | str) -> str:
    """The vehicle of one system heard by a source that hears several: ``<vehicle>-<id>``."""
    return f"{source_vehicle}-{system}"


@dataclass(frozen=True, kw_only=True)
class VehicleOptions(Options):
    """The key of a backend whose link carries one vehicle (CRSF, HC-12 relay, XBee air side,
    UAVTalk flight side, F´), declared once here and inherited."""

    vehicle: str | None = option(None, "the vehicle this link serves (a source's vehicle "
                                 "name); unset: the first source's", validator=check_name)


class VehicleSelector:
    """Which vehicle a single-vehicle link serves: the configured name, or else the first
    configured source's vehicle — for a source that yields one vehicle per system, the first
    vehicle that source yields.  :meth:`accepts` is one string comparison once chosen."""

    __slots__ = ("_first_source", "_first_vehicle", "chosen")

    def __init__(self, wanted: str | None = None) -> None:
        #: the vehicle served ("" until known)
        self.chosen = wanted or ""
        self._first_source = ""
        self._first_vehicle = ""

    def attach(self, context: Any, who: str = "") -> None:
        """Learn the configured sources (their names and vehicles, in order) from the
        gateway's context (:data:`SERVICE`): the first, when no vehicle was configured; a
        configured name no source can yield is logged (``who``: the link's name), once —
        the link would otherwise show nothing, silently."""
        if context is None:
            return
        sources: list[SourceVehicle] = context.services.get(SERVICE) or []
        if self.chosen:
            # (a source of several systems may yield any name: a Zenoh source relays another
            # gateway's)
            if sources and not any(self.chosen == sv.vehicle or sv.systems for sv in sources):
                log.warning("%s: vehicle %r is no source's (%s): nothing is served until a "
                            "vehicle of that name is heard", who or "a link", self.chosen,
                            ", ".join(sv.vehicle for sv in sources))
            return
        if sources:
            first = sources[0]
            self._first_source = first.source
            self._first_vehicle = "" if first.systems else first.vehicle

    def accepts(self, msg: Any) -> bool:
        """True for a message about the vehicle served."""
        vehicle = msg.vehicle
        chosen = self.chosen
        if chosen:
            return vehicle == chosen or not vehicle
        if not vehicle:
            return True
        # not chosen yet: the first source's vehicle, or the first one it yields (a link
        # event names its source in ``source``, with no origin)
        if (vehicle == self._first_vehicle or not self._first_source
                or (msg.origin or getattr(msg, "source", "")) == self._first_source):
            self.chosen = vehicle
            return True
        return False
