"""The XBee link carries one vehicle, over the emulated pair (``tests/xbee_pair.py``): the air
side sends down only the served vehicle's telemetry (what the real ground side decodes), and
names it on the commands it hands to its gateway; the ground side sends up only the commands
for its own vehicle (or for none)."""

from __future__ import annotations

import contextlib
import re
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import post, wait_for
from test_crsf_vehicles import context_of, sm_at
from xbee_pair import XBeePair

from backends.xbee.backend import XbeeBackend
from backends.xbee.options import XbeeOptions, XbeeSourceOptions
from backends.xbee.source import XbeeSource
from gateway import config
from gateway.config import ConfigError
from gateway.model import RcChannels, SmUpdate
from gateway.outcome import Outcome

DEADLINE_S = 15.0
ALPHA_M, BETA_M = 100.0, 500.0
LOSSLESS = (0.0,) * 5


class Inbox:
    """What a side hands to its gateway, with a condition to wait on."""

    def __init__(self) -> None:
        self.items: list[Any] = []
        self.cond = threading.Condition()

    def __call__(self, msg: Any) -> None:
        with self.cond:
            self.items.append(msg)
            self.cond.notify_all()

    def wait(self, pred: Any, timeout: float = DEADLINE_S) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: pred(self.items), timeout)


@contextlib.contextmanager
def xbee_link(**air_options: Any) -> Iterator[tuple[XbeeBackend, Inbox, XbeeSource, Inbox]]:
    """An emulated pair; the air side attached to a gateway whose sources are alpha and beta,
    the ground side a source of its own gateway (vehicle "rocket")."""
    with contextlib.ExitStack() as stack:
        pair = stack.enter_context(XBeePair(1, 1, loss=LOSSLESS, seed=3))
        air_in, ground_in = Inbox(), Inbox()
        air = XbeeBackend(XbeeOptions(url=pair.url_a, **air_options))
        ctx = context_of("alpha", "beta")
        ctx.emit = air_in
        air.attach(ctx)
        air.init()
        stack.callback(air.close)
        ground = XbeeSource(XbeeSourceOptions(url=pair.url_b), name="ground")
        ground.vehicle = "rocket"
        ground.start(ground_in)
        stack.callback(ground.stop)
        assert wait_for(lambda: air.radio.engine.connected and ground.radio.engine.connected,
                        DEADLINE_S)
        yield air, air_in, ground, ground_in


def altitudes(msgs: list[Any]) -> set[int]:
    return {round(m.altitude_m) for m in msgs if isinstance(m, SmUpdate)}


@pytest.mark.parametrize(("options", "served", "alt"), [
    ({}, "alpha", ALPHA_M),                      # the first source's, though beta came first
    ({"vehicle": "beta"}, "beta", BETA_M),
])
def test_one_vehicle_down_and_commands_naming_it_up(options: dict[str, Any], served: str,
                                                    alt: float) -> None:
    with xbee_link(**options) as (air, air_in, ground, ground_in):
        for i in range(10):
            for vehicle, a in (("beta", BETA_M), ("alpha", ALPHA_M)):
                assert post(air, sm_at(a, i, vehicle=vehicle)) is Outcome.ACCEPTED
        assert ground_in.wait(lambda items: len(altitudes(items)) >= 1)
        # the sticks the ground's pilot moves, for the ground's own vehicle
        post(ground, RcChannels((1100, 1900, 1500), vehicle="rocket"))
        assert air_in.wait(lambda items: any(m.channels_us[:3] == (1100, 1900, 1500)
                                             for m in items if isinstance(m, RcChannels)))
        air_stats = air.stats()
        down = list(ground_in.items)
    assert altitudes(down) == {round(alt)}, altitudes(down)
    assert air_stats["other_vehicles"] == 10
    commands = [m for m in air_in.items if isinstance(m, RcChannels)]
    assert commands and {m.vehicle for m in commands} == {served}
    assert {m.origin for m in commands} == {"xbee"}


def test_the_ground_sends_up_only_its_own_vehicles_commands() -> None:
    with xbee_link() as (air, air_in, ground, _ground_in):
        post(air, sm_at(ALPHA_M, vehicle="alpha"))
        post(ground, RcChannels((1200, 1200, 1200), vehicle="beta"))   # another vehicle's
        post(ground, RcChannels((1300, 1300, 1300), origin="ground"))  # its own, echoed
        post(ground, RcChannels((1400, 1400, 1400)))                   # for no vehicle
        assert air_in.wait(lambda items: any(m.channels_us[:3] == (1400, 1400, 1400)
                                             for m in items if isinstance(m, RcChannels)))
        post(ground, RcChannels((1500, 1600, 1700), vehicle="rocket"))
        assert air_in.wait(lambda items: any(m.channels_us[:3] == (1500, 1600, 1700)
                                             for m in items if isinstance(m, RcChannels))), \
            (air_in.items[-5:], ground.stats(), ground.inbox_stats(), air.stats())
        inbox = ground.inbox_stats()
        seen = {m.channels_us[:3] for m in air_in.items if isinstance(m, RcChannels)}
    assert inbox["other_vehicles"] == 1 and inbox["sent"] == 2
    assert (1200, 1200, 1200) not in seen and (1300, 1300, 1300) not in seen
    assert (1400, 1400, 1400) in seen


def test_vehicle_key_is_checked_naming_it() -> None:
    table = {"url": "/dev/ttyUSB0", "vehicle": "beta"}
    assert config.parse({"backends": {"xbee": table}}).backends[0].options["vehicle"] == "beta"
    for bad in ("-x", "x y", ""):
        with pytest.raises(ConfigError, match=re.escape("backends.xbee.vehicle: ")):
            config.parse({"backends": {"xbee": {**table, "vehicle": bad}}})
