"""What the ground stations on a link read wrongly, and how the rocket's messages avoid it.

One case today: **SYS_STATUS without a battery.**  MAVLink's "not sent" value for
``voltage_battery`` is 65535, and QGroundControl and MAVProxy show it as no battery.  MAVSDK
(checked up to 4.1.0) reads every SYS_STATUS's battery fields as values, so a rocket that has
no battery would show a 65.535 V one there (0 would read as 0 V everywhere); only a vehicle
that sends no SYS_STATUS has no battery in MAVSDK.  So while a vehicle has no battery, its
SYS_STATUS (the sensors' health, which QGroundControl and MAVProxy show) goes only to a link
on which a ground station was heard and MAVSDK was not; once it has a battery, to every link.

MAVSDK is known by its default ground-station identity, system 245, component 190
(``MAV_COMP_ID_MISSIONPLANNER``); a MAVSDK application that chose another system id is not
told apart (it then shows the 65.535 V battery, as before).
"""

from __future__ import annotations

import logging
from typing import Any

log = logging.getLogger(__name__)

#: MAVSDK's default identity as a ground station: (system 245 << 8) | component 190.
MAVSDK_DEFAULT = (245 << 8) | 190

#: SYS_STATUS ``voltage_battery`` when no battery voltage is sent.
NO_VOLTAGE = 0xFFFF


def shows_no_battery(link: Any) -> bool:
    """Whether a SYS_STATUS without a battery reads as no battery to every ground station
    heard on ``link``: one was heard (``link.seen``), and none of them is MAVSDK."""
    seen: set[int] = link.seen
    if MAVSDK_DEFAULT in seen:
        if not getattr(link, "mavsdk_noted", False):
            link.mavsdk_noted = True
            log.info("MAVSDK (system 245) on %s: the rocket's SYS_STATUS is not sent there "
                     "until it has a battery (MAVSDK would show 'no battery' as 65.535 V)",
                     link.name)
        return False
    return bool(seen)
