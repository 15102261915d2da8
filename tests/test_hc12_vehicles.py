"""The HC-12 relay carries one vehicle: the first source's by default, or ``vehicle``'s; the
other's frames never reach the air (measured on the emulator's air side, over a real RFC 2217
port), nor the vehicle watch that provisioning judges."""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from test_crsf_vehicles import context_of
from test_hc12_support import DEADLINE_S, emu_mod, write_settings

from backends.hc12.backend import Hc12Backend
from backends.hc12.options import Hc12Options
from gateway import config
from gateway.config import ConfigError
from gateway.model import RawFrame, SmUpdate, Status
from gateway.outcome import Outcome
from gateway.wire import Decoder, decode_all, encode, frame

pytest_plugins = ["test_hc12_support"]  # the emulator and settings_file fixtures

ALPHA_M, BETA_M = 100.0, 500.0


def heard(vehicle: str, alt: float, i: int) -> list[Any]:
    """What a source hearing ``vehicle`` decodes: an SM update near ``alt``, a STATUS and a
    frame of an unknown type, each with its raw bytes."""
    sm = SmUpdate(1000 + i, 2, True, 0, alt + i * 0.1, 9.8, 9.7, 1.5, 0.1, -0.2, 0.3)
    st = Status(1000 + i, 2, 0, Status.make_flags(armed=True))
    stream = encode(sm) + encode(st) + frame(0x7E, vehicle.encode())
    return Decoder(origin=vehicle, vehicle=vehicle).feed(stream)


@contextlib.contextmanager
def relay(settings: Path, vehicles: tuple[str, ...], **options: Any) -> Iterator[Any]:
    """An emulator and a relay attached to a gateway whose sources are ``vehicles``."""
    write_settings(settings, mode=3, baud=115200)
    emu = emu_mod.Hc12Emulator(settings).start()
    b = Hc12Backend(Hc12Options(url=emu.url, control="off", baudrate=115200,
                                air_baud=115200, queue_depth=64, **options))
    b.attach(context_of(*vehicles))
    b.init()
    try:
        assert b.engine.wait_connected(DEADLINE_S)
        yield emu, b
    finally:
        b.close()
        emu.stop()


def send_both(b: Hc12Backend) -> tuple[bytes, bytes]:
    """beta's frames first, then alpha's, interleaved; the bytes of each vehicle's."""
    handlers = dict(b.routes())
    own = {"alpha": b"", "beta": b""}
    for i in range(5):
        for vehicle, alt in (("beta", BETA_M), ("alpha", ALPHA_M)):
            for msg in heard(vehicle, alt, i):
                assert handlers[type(msg)](msg) is Outcome.ACCEPTED
                own[vehicle] += msg.raw
    return own["alpha"], own["beta"]


def air(emu: Any, n: int) -> bytes:
    model = emu.model
    assert model.wait_for(lambda: len(model.air_out) >= n, DEADLINE_S), \
        f"air carried {len(model.air_out)} of {n} bytes"
    return bytes(model.air_out)


@pytest.mark.parametrize(("vehicles", "options", "served"), [
    (("alpha", "beta"), {}, "alpha"),            # the first source's, though beta came first
    (("alpha", "beta"), {"vehicle": "beta"}, "beta"),
])
def test_the_relay_carries_one_vehicle(settings_file: Path, vehicles: tuple[str, ...],
                                       options: dict[str, Any], served: str) -> None:
    with relay(settings_file, vehicles, **options) as (emu, b):
        alpha, beta = send_both(b)
        want = alpha if served == "alpha" else beta
        out = air(emu, len(want))
        stats = b.stats()
    assert out == want
    alts = {round(m.altitude_m) for m in decode_all(out) if isinstance(m, SmUpdate)}
    assert alts == ({100} if served == "alpha" else {500})
    assert [m.payload for m in decode_all(out) if isinstance(m, RawFrame)] == \
        [served.encode()] * 5
    assert stats["other_vehicles"] == 15 and stats["dropped"] == 0
    # provisioning judges the served vehicle's state only
    assert b.watch.last is not None and b.watch.last.origin == served


def test_vehicle_key_is_checked_naming_it() -> None:
    part = config.parse({"backends": {"hc12": {"url": "/dev/ttyUSB0", "vehicle": "beta"}}})
    assert part.backends[0].options["vehicle"] == "beta"
    for bad in ("9lives", "a.b", ""):
        with pytest.raises(ConfigError, match=re.escape("backends.hc12.vehicle: ")):
            config.parse({"backends": {"hc12": {"url": "/dev/ttyUSB0", "vehicle": bad}}})
