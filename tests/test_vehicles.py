"""Vehicles as the unit: names, the configuration's sources, ``--source NAME=URL`` and the
gateway stamping every message with its vehicle (issue 22's core)."""

from __future__ import annotations

import subprocess
import threading
from typing import Any

import pytest
from helpers import GATEWAY, ROOT

from gateway import config, vehicles
from gateway.app import Gateway
from gateway.backend import Backend, GatewayContext, Routes
from gateway.commands.cli import split_vehicle
from gateway.config import ConfigError
from gateway.model import LinkEvent, RcChannels, SmUpdate, Status


@pytest.mark.parametrize("name", ["alpha", "b", "Rocket_2", "x-1", "a" * 64])
def test_vehicle_names_that_are_valid(name: str) -> None:
    assert vehicles.check_name(name) == name


@pytest.mark.parametrize("name", ["", "1a", "-a", "a b", "a/b", "a*", "é", "a" * 65, 3, None])
def test_vehicle_names_that_are_not(name: Any) -> None:
    with pytest.raises(ValueError, match="not a vehicle name"):
        vehicles.check_name(name)


@pytest.mark.parametrize(("text", "name"), [
    ("sim", "sim"),
    ("socket://127.0.0.1:5000", "socket-127-0-0-1-5000"),
    ("/dev/ttyUSB0", "dev-ttyUSB0"),
    ("loop://", "loop"),
    ("0123", "vehicle"),
    ("uavtalk:tcp:10.0.0.2:9000", "uavtalk-tcp-10-0-0-2-9000"),
])
def test_derived_names_are_vehicle_names(text: str, name: str) -> None:
    assert vehicles.derive_name(text) == name
    assert vehicles.check_name(vehicles.derive_name(text))


def test_derived_names_are_made_unique_and_given_ones_kept() -> None:
    got = vehicles.unique_names([("sim", False), ("sim", False), ("sim-2", True), ("a", True)])
    assert got == ["sim", "sim-3", "sim-2", "a"]
    assert len(set(got)) == len(got)


@pytest.mark.parametrize(("text", "want"), [
    ("alpha=socket://127.0.0.1:5000", ("alpha", "socket://127.0.0.1:5000")),
    ("beta=sim", ("beta", "sim")),
    ("sim", (None, "sim")),
    ("loop://?logging=debug", (None, "loop://?logging=debug")),
    ("socket://h:1?x=1", (None, "socket://h:1?x=1")),
    ("mavlink:udpin:0.0.0.0:14550", (None, "mavlink:udpin:0.0.0.0:14550")),
])
def test_source_flag_splits_a_name_from_its_url(text: str, want: tuple[Any, str]) -> None:
    assert split_vehicle(text) == want


def test_configured_vehicles_given_derived_and_unique() -> None:
    cfg = config.parse({"sources": [
        {"type": "sim"},
        {"type": "sim", "name": "second"},
        {"type": "serial", "url": "socket://127.0.0.1:5000", "vehicle": "alpha",
         "mavlink_sysid": 7},
    ]})
    assert [(p.name, p.vehicle, p.mavlink_sysid) for p in cfg.sources] == [
        ("sim", "sim", None), ("second", "second", None),
        ("socket://127.0.0.1:5000", "alpha", 7)]


@pytest.mark.parametrize(("sources", "error"), [
    ([{"type": "sim", "vehicle": "1x"}], "sources[0].vehicle: '1x' is not a vehicle name"),
    ([{"type": "sim", "vehicle": 5}], "sources[0].vehicle: 5 is not a vehicle name"),
    ([{"type": "sim", "vehicle": "a"}, {"type": "sim", "name": "b", "vehicle": "a"}],
     "sources[1].vehicle: 'a' is already the vehicle of sources[0]"),
    ([{"type": "sim", "mavlink_sysid": 0}], "sources[0].mavlink_sysid: expected an integer"),
    ([{"type": "sim", "mavlink_sysid": True}], "sources[0].mavlink_sysid: expected an integer"),
    ([{"type": "sim", "mavlink_sysid": 3}, {"type": "sim", "name": "b", "mavlink_sysid": 3}],
     "sources[1].mavlink_sysid: 3 is already the system id of sources[0]"),
])
def test_bad_vehicle_keys_name_the_key(sources: list[dict[str, Any]], error: str) -> None:
    with pytest.raises(ConfigError) as info:
        config.parse({"sources": sources})
    assert str(info.value).startswith(error)


def test_a_given_name_wins_over_a_derived_one() -> None:
    cfg = config.parse({"sources": [{"type": "sim"}, {"type": "sim", "name": "b",
                                                      "vehicle": "sim"}]})
    assert [p.vehicle for p in cfg.sources] == ["sim-2", "sim"]


def test_check_config_prints_each_source_vehicle_and_reads_it_back(tmp_path: Any) -> None:
    first = tmp_path / "a.toml"
    first.write_text('[[sources]]\ntype = "sim"\nvehicle = "alpha"\nmavlink_sysid = 4\n'
                     '[[sources]]\ntype = "sim"\nname = "b"\n[backends.console]\n')
    printed = subprocess.run([*GATEWAY, "check-config", str(first)], cwd=ROOT,
                             capture_output=True, text=True, timeout=30)
    assert printed.returncode == 0, printed.stderr
    again = tmp_path / "b.toml"
    again.write_text(printed.stdout)
    cfg = config.load(again)
    assert [(p.name, p.vehicle, p.mavlink_sysid) for p in cfg.sources] == [
        ("sim", "alpha", 4), ("b", "b", None)]


def test_the_command_line_names_vehicles() -> None:
    cfg = config.embedded_default()
    assert [p.vehicle for p in cfg.sources] == ["sim"]
    res = subprocess.run([*GATEWAY, "run", "--only", "console", "--source", "alpha=sim",
                          "--source", "sim", "--source", "sim", "--duration", "0.3",
                          "--sim-speed", "0"], cwd=ROOT, capture_output=True, text=True,
                         timeout=30)
    assert res.returncode == 0, res.stderr
    assert "sources alpha, sim, sim-2;" in res.stderr
    for vehicle in ("alpha", "sim", "sim-2"):
        assert f"flight {vehicle}:" in res.stderr


@pytest.mark.parametrize(("args", "error"), [
    (["--source", "9x=sim"], "--source '9x=sim': '9x' is not a vehicle name"),
    (["--source", "a=sim", "--source", "a=sim"], "the name 'a' is used twice"),
])
def test_bad_source_names_on_the_command_line(args: list[str], error: str) -> None:
    res = subprocess.run([*GATEWAY, "run", "--only", "console", *args, "--duration", "0.1"],
                         cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert res.returncode == 2
    assert error in res.stderr
    assert "Traceback" not in res.stderr


class Collect(Backend):
    """Every SmUpdate and Status the dispatcher hands it, per vehicle."""

    def __init__(self) -> None:
        super().__init__("collect")
        self.got: dict[str, list[Any]] = {}
        self.lock = threading.Lock()

    def routes(self) -> Routes:
        return Routes().on(SmUpdate, self.take).on(Status, self.take)

    def take(self, msg: Any) -> None:
        with self.lock:
            self.got.setdefault(msg.vehicle, []).append(msg)


def test_two_simulated_rockets_are_two_vehicles_end_to_end() -> None:
    """Each source's messages carry its own vehicle and origin, and the flight summary keeps
    a figure per vehicle: nothing of one rocket is filed under the other."""
    sim = {"type": "sim", "speed": 0, "cycles": 1, "pad_idle_s": 0.5, "pad_armed_s": 0.5}
    cfg = config.parse({"sources": [{**sim, "name": "a", "vehicle": "alpha"},
                                    {**sim, "name": "b", "vehicle": "beta",
                                     "revision": 36}]})
    gw = Gateway(cfg)
    sink = Collect()
    gw.dispatcher.add(sink)
    gw.start()
    try:
        gw.run(duration_s=20)
    finally:
        summary = gw.stop()
    assert set(sink.got) == {"alpha", "beta"}
    for vehicle, origin, length in (("alpha", "a", 64), ("beta", "b", 36)):
        msgs = sink.got[vehicle]
        assert {m.origin for m in msgs} == {origin}
        assert {m.payload_len for m in msgs if type(m) is SmUpdate} == {length}
    assert set(summary["flights"]) == {"alpha", "beta"}
    assert all(f["launches"] == 1 for f in summary["flights"].values())


def test_ingest_stamps_the_source_vehicle_on_what_comes_without_one() -> None:
    cfg = config.parse({"sources": [{"type": "sim", "name": "radio", "vehicle": "alpha"}]})
    gw = Gateway(cfg)
    sink = Collect()
    gw.dispatcher.add(sink)
    gw.dispatcher.start()
    gw.ingest(Status(1, 0, 0, 0, origin="radio"))
    gw.ingest(Status(2, 0, 0, 0, origin="radio", vehicle="other"))
    gw.ingest(Status(3, 0, 0, 0, origin="a-backend"))
    gw.dispatcher.close()
    assert {v: [m.timestamp_ms for m in ms] for v, ms in sink.got.items()} == {
        "alpha": [1], "other": [2], "": [3]}


def context_with(*pairs: tuple[str, str], systems: str = "") -> GatewayContext:
    ctx = GatewayContext()
    ctx.services[vehicles.SERVICE] = [vehicles.SourceVehicle(s, v, None, s == systems)
                                      for s, v in pairs]
    return ctx


def test_a_single_vehicle_link_serves_the_first_source_by_default() -> None:
    sel = vehicles.VehicleSelector()
    sel.attach(context_with(("a", "alpha"), ("b", "beta")))
    assert not sel.accepts(Status(0, 0, 0, 0, origin="b", vehicle="beta"))
    assert sel.accepts(Status(0, 0, 0, 0, origin="a", vehicle="alpha"))
    assert sel.accepts(RcChannels((1500,)))  # what a ground link sends carries no vehicle
    assert sel.chosen == "alpha"


def test_a_single_vehicle_link_of_a_many_system_source_takes_its_first_system() -> None:
    sel = vehicles.VehicleSelector()
    sel.attach(context_with(("mav", "mav"), ("b", "beta"), systems="mav"))
    assert not sel.accepts(Status(0, 0, 0, 0, origin="b", vehicle="beta"))
    assert not sel.accepts(Status(0, 0, 0, 0, origin="b", vehicle="mav"))  # the stem is none
    assert sel.accepts(Status(0, 0, 0, 0, origin="mav", vehicle="mav-3"))
    assert not sel.accepts(Status(0, 0, 0, 0, origin="mav", vehicle="mav-4"))


def test_a_link_event_of_the_first_source_chooses_its_vehicle() -> None:
    """A link comes up before its first message is dispatched: its event (which names its
    source in ``source``, with no origin) is the first thing a link sees of a vehicle."""
    sel = vehicles.VehicleSelector()
    sel.attach(context_with(("mav", "mav"), ("b", "beta"), systems="mav"))
    assert not sel.accepts(LinkEvent("b", True, vehicle="beta"))
    assert sel.accepts(LinkEvent("mav", True, vehicle="mav-1"))
    assert sel.chosen == "mav-1"


def test_a_configured_vehicle_no_source_has_is_logged(caplog: Any) -> None:
    sel = vehicles.VehicleSelector("alhpa")
    with caplog.at_level("WARNING"):
        sel.attach(context_with(("a", "alpha"), ("b", "beta")), "backends.crsf")
    assert "backends.crsf: vehicle 'alhpa' is no source's (alpha, beta)" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING"):
        vehicles.VehicleSelector("beta").attach(context_with(("a", "alpha"), ("b", "beta")))
        vehicles.VehicleSelector("x-1").attach(context_with(("z", "z"), systems="z"))
    assert caplog.text == ""


def test_a_configured_vehicle_is_served_whatever_comes_first() -> None:
    sel = vehicles.VehicleSelector("beta")
    sel.attach(context_with(("a", "alpha"), ("b", "beta")))
    assert not sel.accepts(Status(0, 0, 0, 0, origin="a", vehicle="alpha"))
    assert sel.accepts(Status(0, 0, 0, 0, origin="b", vehicle="beta"))


def test_an_unnamed_replay_is_named_after_its_file_as_decode_names_it(tmp_path: Any) -> None:
    from gateway import recording

    path = tmp_path / "2026-11-23T14-02-11-rocket7.aur"
    path.write_bytes(recording.HEADER)  # an empty recording
    cfg = config.parse({"sources": [{"type": "replay", "path": str(path)},
                                    {"type": "replay", "path": str(path), "name": "again"}]})
    assert [p.vehicle for p in cfg.sources] == ["rocket7", "again"]
    assert recording.file_vehicle(path) == "rocket7"


def test_unnamed_sources_of_one_type_in_a_file_are_told_apart_as_on_the_command_line() -> None:
    cfg = config.parse({"sources": [{"type": "sim"}, {"type": "sim"},
                                    {"type": "sim", "vehicle": "x"}]})
    assert [(p.name, p.vehicle) for p in cfg.sources] == [
        ("sim", "sim"), ("sim-2", "sim-2"), ("sim-3", "x")]
    with pytest.raises(ConfigError, match=r"^sources\[1\]\.name: 'a' is used twice"):
        config.parse({"sources": [{"type": "sim", "name": "a"}, {"type": "sim", "name": "a"}]})
