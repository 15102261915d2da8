"""The UAVTalk flight side plays one flight controller, so it serves one vehicle: the first
source's by default, or ``vehicle``'s.  A ground station (the spec's rules, over TCP) reads
only that vehicle's attitude."""

from __future__ import annotations

import math
import re
import threading
from typing import Any

import pytest
from helpers import wait_for
from test_crsf_vehicles import context_of
from test_uavtalk_backend import ATTITUDE, CONNECTED, SpecGcs, attitude

from backends.uavtalk.backend import UavtalkBackend
from backends.uavtalk.options import UavtalkOptions
from dialects.states import SimpleState
from gateway import config
from gateway.config import ConfigError
from gateway.dispatcher import Dispatcher
from gateway.model import SmUpdate

ROLL_DEG = {"alpha": 10.0, "beta": -40.0}


def sm(vehicle: str, t: int) -> SmUpdate:
    return SmUpdate(timestamp_ms=t, state=SimpleState.BOOST, armed=True, sm_type=0,
                    altitude_m=100.0, acceleration_mps2=30.0, accel_vert_mps2=29.0,
                    velocity_mps=150.0, roll_rad=math.radians(ROLL_DEG[vehicle]),
                    pitch_rad=0.0, yaw_rad=0.0, vehicle=vehicle)


@pytest.mark.parametrize(("options", "served"), [
    ({}, "alpha"),                               # the first source's, though beta came first
    ({"vehicle": "beta"}, "beta"),
])
def test_the_gcs_sees_one_vehicle(options: dict[str, Any], served: str) -> None:
    d = Dispatcher()
    b = UavtalkBackend(UavtalkOptions(endpoints=["tcpin:127.0.0.1:0"], **options))
    ctx = context_of("alpha", "beta")
    ctx.emit = d.dispatch
    b.attach(ctx)
    d.add(b)
    d.start()
    stop = threading.Event()

    def feed() -> None:  # both rockets, beta first, every 20 ms
        t = 0
        while not stop.wait(0.02):
            for v in ("beta", "alpha"):
                d.dispatch(sm(v, t))
            t += 20

    feeder = threading.Thread(target=feed, daemon=True)
    gcs: SpecGcs | None = None
    try:
        feeder.start()
        assert wait_for(lambda: b.stats()["messages"] > 1)
        gcs = SpecGcs(b.address())
        g = gcs
        assert g.run_until(lambda: g.state == CONNECTED, 3.0)
        assert g.run_until(lambda: len(g.received[ATTITUDE]) >= 10)
        rolls = {round(attitude(data)[4], 3) for _, data in g.received[ATTITUDE]}
    finally:
        stop.set()
        feeder.join(2)
        if gcs is not None:
            gcs.close()
        d.close()
    assert rolls == {ROLL_DEG[served]}, rolls
    st = b.stats()
    assert st["other_vehicles"] >= 1 and st["messages"] >= 1


def test_vehicle_key_is_checked_naming_it() -> None:
    table = {"endpoints": ["tcpin:127.0.0.1:9000"], "vehicle": "beta"}
    part = config.parse({"backends": {"uavtalk": table}}).backends[0]
    assert part.options["vehicle"] == "beta"
    for bad in ("_a", "a:b", ""):
        with pytest.raises(ConfigError, match=re.escape("backends.uavtalk.vehicle: ")):
            config.parse({"backends": {"uavtalk": {**table, "vehicle": bad}}})
