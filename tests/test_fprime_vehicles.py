"""The F´ backend serves one vehicle: the first source's by default, or ``vehicle``'s; what a
ground system reads (deframed by fprime-gds's own deframer) is that vehicle's channels only."""

from __future__ import annotations

import re
from typing import Any

import pytest
from helpers import wait_for
from test_crsf_vehicles import context_of
from test_fprime_backend import Ground, expected_packets, sm, time_tag

from backends.fprime.backend import FprimeBackend
from backends.fprime.options import FprimeOptions
from gateway import config
from gateway.config import ConfigError
from gateway.dispatcher import Dispatcher
from gateway.model import Battery, LinkEvent, Position


def vehicle(msg: Any, name: str) -> Any:
    return msg._replace(vehicle=name)


def about(msg: Any) -> str:
    """The vehicle a message is about (a link event without one: its source's, the sources
    being named like their vehicles here)."""
    return msg.source if isinstance(msg, LinkEvent) and not msg.vehicle else msg.vehicle


@pytest.mark.parametrize(("options", "served"), [
    ({}, "alpha"),                               # the first source's, though beta came first
    ({"vehicle": "beta"}, "beta"),
])
def test_the_ground_system_reads_one_vehicle(options: dict[str, Any], served: str) -> None:
    d = Dispatcher()
    b = FprimeBackend(FprimeOptions(endpoints=["tcpin:127.0.0.1:0"], **options))
    ctx = context_of("alpha", "beta")
    ctx.emit = d.dispatch
    b.attach(ctx)
    d.add(b)
    d.start()
    ground = None
    try:
        ground = Ground(b.address(), b.framing)
        assert wait_for(lambda: b.stats()["connected"] == 1)
        # the link monitor's events name the source, not the vehicle; they come first
        messages: list[Any] = [LinkEvent("beta", True), LinkEvent("alpha", True)]
        for t in range(40):
            messages.append(vehicle(sm(t * 10, 500.0 + t), "beta"))
            messages.append(vehicle(sm(t * 10, 100.0 + t), "alpha"))
        messages[10:10] = [vehicle(Position(47.0, 8.0, 900.0), "beta"),
                           vehicle(Battery(7.9), "beta"), vehicle(Position(46.0, 7.0, 420.0),
                                                                  "alpha")]
        g = ground
        messages += [LinkEvent("beta", False, 3.0), LinkEvent("alpha", False, 3.0)]
        mine = [m for m in messages if about(m) == served]
        for i, m in enumerate(messages):  # a pause every 16 (a peer's queue holds 64)
            d.dispatch(m)
            if i % 16 == 15:
                sent = sum(1 for x in messages[:i + 1] if about(x) == served)
                assert wait_for(lambda n=sent: len(g.got()) >= n)
        assert wait_for(lambda: len(g.got()) >= len(mine))
        got = g.got()
        assert len(got) == len(mine)
        for m, packet in zip(mine, got, strict=True):
            assert [packet] == expected_packets(b, m, time_tag(packet))
        st = b.stats()
        assert st["other_vehicles"] == len(messages) - len(mine) and st["errors"] == 0
        assert st["messages"] == len(mine)
    finally:
        if ground is not None:
            ground.close()
        d.close()


def test_vehicle_key_is_checked_naming_it() -> None:
    table = {"endpoints": ["tcpin:127.0.0.1:50000"], "vehicle": "beta"}
    part = config.parse({"backends": {"fprime": table}}).backends[0]
    assert part.options["vehicle"] == "beta"
    for bad in ("1st", "a/b", ""):
        with pytest.raises(ConfigError, match=re.escape("backends.fprime.vehicle: ")):
            config.parse({"backends": {"fprime": {**table, "vehicle": bad}}})
