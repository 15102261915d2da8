"""The F´ JSON dictionary, checked by fprime-gds 4.4.1's own loaders and decoders.

fprime-gds is the independent implementation: its JSON loaders read the generated file, its
``Dictionaries.load_dictionaries_into_config`` puts our type definitions and constants into its
process-wide ``ConfigManager``, and its ``Distributor`` + ``ChDecoder`` (the path the ground
system runs for ``FW_PACKET_TELEM`` data) decode packets built with our channel codecs and
``TlmPacker``.  Expected values come from the messages themselves (and the spec's vector),
never from what the code under test produced.

fprime-gds keeps state across a process (``ConfigManager`` singleton, ``JsonLoader``'s
class-level type cache): the ``gds`` fixture saves both before each test and puts them back
after, so these tests (and everyone else's) pass in any order.
"""

from __future__ import annotations

import io
import json
import struct
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fprime_gds.common.decoders.ch_decoder import ChDecoder
from fprime_gds.common.distributor.distributor import Distributor
from fprime_gds.common.handlers import DataHandler
from fprime_gds.common.loaders.json_loader import JsonLoader
from fprime_gds.common.models.dictionaries import Dictionaries
from fprime_gds.common.models.serialize.numerical_types import U8Type
from fprime_gds.common.utils.config_manager import ConfigManager

from backends.fprime import channels as ch
from backends.fprime.channels import CHANNELS, DEFAULT_ID_BASE, STATE_ENUM, codecs
from backends.fprime.commands import COMMANDS, EVENTS
from backends.fprime.dictionary import build_dictionary, write_dictionary
from backends.fprime.packets import TB_PROC_TIME, TB_WORKSTATION_TIME, TlmPacker, UpdateClock
from dialects.states import SimpleState
from gateway.model import Battery, LinkStats, Position, SmUpdate, Status, VehicleState

GATEWAY = Path(sys.executable).with_name("aurora-gateway")
# shared/specs/fprime.md, "Vector": Altitude (id 256) = 123.5 and State (id 257) = 3 at
# t = 1700000000.250000, workstation time, context 0, U16 descriptor
SPEC_PACKET = bytes.fromhex(
    "0001 00000100 0002 00 6553f100 0003d090 42f70000"
    " 00000101 0002 00 6553f100 0003d090 03".replace(" ", ""))
T0 = 1700000000.25


def f32(x: float) -> float:
    """``x`` as an IEEE single would hold it (the spec's F32 channels)."""
    return float(struct.unpack(">f", struct.pack(">f", x))[0])


# -- fprime-gds's process-wide state, saved and restored ------------------------------------------

class Gds:
    """fprime-gds with one of our dictionaries loaded (the way its pipeline loads one)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.dicts: Dictionaries | None = None

    def load(self, dictionary: dict[str, Any], name: str = "dict.json") -> Dictionaries:
        path = self.tmp / name
        path.write_text(json.dumps(dictionary), encoding="utf-8")
        self.dicts = Dictionaries.load_dictionaries_into_config(str(path))
        return self.dicts

    def decode(self, packets: list[bytes]) -> list[Any]:
        """Every ChData fprime-gds's distributor and channel decoder make of ``packets``,
        each sent as the ground's comm layer hands it on: a U32 length, then the packet."""
        assert self.dicts is not None
        received: list[Any] = []

        class Sink(DataHandler):
            def data_callback(self, data: Any, sender: Any = None) -> None:
                received.append(data)

        distributor = Distributor()
        decoder = ChDecoder(self.dicts.channel_id)
        decoder.register(Sink())
        distributor.register("FW_PACKET_TELEM", decoder)
        for packet in packets:
            distributor.on_recv(struct.pack(">I", len(packet)) + packet)
        return received


@pytest.fixture
def gds(tmp_path: Path) -> Iterator[Gds]:
    cm = ConfigManager()
    prop: dict[str, dict[str, Any]] = cm._ConfigManager__prop
    saved = {k: dict(v) for k, v in prop.items()}
    saved_types = dict(JsonLoader.parsed_types)
    JsonLoader.parsed_types.clear()  # a type cached from someone else's dictionary must not count
    try:
        yield Gds(tmp_path)
    finally:
        for k, v in saved.items():
            prop[k].clear()
            prop[k].update(v)
        JsonLoader.parsed_types.clear()
        JsonLoader.parsed_types.update(saved_types)


# -- the document ---------------------------------------------------------------------------------

def test_the_document_has_every_section_and_the_metadata() -> None:
    d = build_dictionary()
    for key in ("metadata", "typeDefinitions", "constants", "commands", "parameters", "events",
                "telemetryChannels", "records", "containers", "telemetryPacketSets"):
        assert isinstance(d[key], list | dict), key
    meta = d["metadata"]
    assert meta["deploymentName"] == ch.DEPLOYMENT
    assert meta["dictionarySpecVersion"] == "1.0.0"
    assert meta["frameworkVersion"].startswith("4.")
    assert meta["libraryVersions"] == []
    from importlib.metadata import version
    assert meta["projectVersion"] == version("aurora-gateway")
    json.dumps(d)  # JSON all the way down


def test_channel_entries_follow_the_table() -> None:
    entries = build_dictionary(0x1000)["telemetryChannels"]
    assert len(entries) == len(CHANNELS)
    by_name = {e["name"]: e for e in entries}
    assert len(by_name) == len(CHANNELS)
    assert len({e["id"] for e in entries}) == len(CHANNELS)
    for c in CHANNELS:
        e = by_name[f"{ch.DEPLOYMENT}.{c.component}.{c.name}"]
        assert e["id"] == 0x1000 + c.offset
        assert e["telemetryUpdate"] == "always"
        assert e["annotation"] == c.annotation
        assert e.get("format") == c.fmt
    assert by_name["Aurora.flight.Altitude"]["type"] == {"name": "F32", "kind": "float",
                                                         "size": 32}
    assert by_name["Aurora.flight.State"]["type"] == {"name": STATE_ENUM,
                                                      "kind": "qualifiedIdentifier"}


def test_bad_values_are_refused() -> None:
    for bad in (-1, 0xFFFFFFFF):
        with pytest.raises(ValueError):
            build_dictionary(bad)
    with pytest.raises(ValueError):
        build_dictionary(scid=0x400)
    with pytest.raises(ValueError):
        build_dictionary(frame_size=0)


def test_write_dictionary_to_a_stream_and_a_path(tmp_path: Path) -> None:
    buf = io.StringIO()
    d = write_dictionary(buf, 0x300)
    assert json.loads(buf.getvalue()) == d
    path = tmp_path / "d.json"
    write_dictionary(path, scid=7)
    assert json.loads(path.read_text(encoding="utf-8")) == build_dictionary(scid=7)


# -- fprime-gds's loaders -------------------------------------------------------------------------

def test_fprime_gds_loads_it_without_fallbacks(gds: Gds) -> None:
    dicts = gds.load(build_dictionary())
    assert set(dicts.channel_id) == {DEFAULT_ID_BASE + c.offset for c in CHANNELS}
    assert set(dicts.channel_name) == {c.full_name() for c in CHANNELS}
    assert dicts.packet is None  # no packet sets: channels arrive as FW_PACKET_TELEM
    assert {c.get_full_name() for c in dicts.command_id.values()} == {
        c.full_name() for c in COMMANDS}
    assert set(dicts.command_id) == {DEFAULT_ID_BASE + c.offset for c in COMMANDS}
    assert {e.get_full_name() for e in dicts.event_id.values()} == {
        e.full_name() for e in EVENTS}
    assert dicts.metadata["deploymentName"] == ch.DEPLOYMENT
    # the enum: the state machine's names and numbers, U8 on the wire
    state = dicts.channel_name["Aurora.flight.State"].get_type_obj()
    assert dict(zip(state.keys(), state.values(), strict=True)) == {
        s.name: int(s) for s in SimpleState}
    assert state.REP_TYPE is U8Type
    # the framework types fprime-gds looks up come from this dictionary, not its fallbacks
    cm = ConfigManager()
    widths = {"FwPacketDescriptorType": 2, "FwChanIdType": 4, "FwSizeStoreType": 2,
              "FwTimeBaseStoreType": 2, "FwTimeContextStoreType": 1}
    for name, size in widths.items():
        assert name in dicts.typedefs_name, name
        assert cm.get_type(name)().getSize() == size, name
    time_base = cm.get_type("TimeBase")
    assert time_base is dicts.typedefs_name["TimeBase"]
    assert time_base.from_int(TB_WORKSTATION_TIME).val == "TB_WORKSTATION_TIME"
    assert time_base.from_int(4).val == "TB_FPGA_TIME"  # every base the gateway can send
    apid = cm.get_type("ComCfg.Apid")
    assert apid is dicts.typedefs_name["ComCfg.Apid"]
    assert apid.from_int(6).val == "FW_PACKET_IDLE"  # F´ v4's numbering (fallback: 5)
    assert cm.get_constant("FW_SERIALIZE_TRUE_VALUE") == 0xFF


def test_the_comcfg_constants_reach_fprime_gds(gds: Gds) -> None:
    gds.load(build_dictionary(scid=0x123, frame_size=2048))
    cm = ConfigManager()
    assert cm.get_constant("ComCfg.SpacecraftId") == 0x123
    assert cm.get_constant("ComCfg.TmFrameFixedSize") == 2048
    from fprime_gds.common.communication.ccsds.space_data_link import (
        SpaceDataLinkFramerDeframer,
    )
    link = SpaceDataLinkFramerDeframer(None, 1, None)  # no CLI overrides: the dictionary's
    assert (link.scid, link.frame_size) == (0x123, 2048)
    names = {c["qualifiedName"] for c in build_dictionary()["constants"]}
    assert "ComCfg.SpacecraftId" not in names and "ComCfg.TmFrameFixedSize" not in names


# -- fprime-gds's decoders ------------------------------------------------------------------------

def test_the_spec_vector_decodes(gds: Gds) -> None:
    gds.load(build_dictionary())
    got = gds.decode([SPEC_PACKET])
    assert [(c.template.get_full_name(), c.get_val()) for c in got] == [
        ("Aurora.flight.Altitude", 123.5), ("Aurora.flight.State", SimpleState(3).name)]
    for c in got:
        assert c.time.get_float() == T0
        assert c.time.timeBase.val == "TB_WORKSTATION_TIME"
        assert c.time.timeContext == 0


Expected = list[tuple[str, Any, float]]  # channel, value, time


def pack_all(msgs: list[Any], id_base: int, clock: UpdateClock, when: Callable[[Any], float],
             buffer_size: int = 512) -> tuple[list[bytes], Expected]:
    """Our packets for ``msgs`` and, beside them, what each entry should decode to: the value
    read from the message through the table's getters, the time ``when(message)``."""
    table = codecs(id_base)
    entries: list[bytes] = []
    expected: Expected = []
    for m in msgs:
        tag = clock.tag(getattr(m, "timestamp_ms", None))
        for codec, get in table[type(m)]:
            value = get(m)
            e = codec.entry(value, tag)
            if e is None:
                continue
            entries.append(e)
            expected.append((codec.channel.full_name(), value, when(m)))
    return TlmPacker(buffer_size).pack(entries), expected


def check(got: list[Any], expected: Expected) -> None:
    """Each decoded channel against the value the message held, as its type carries it."""
    assert [c.template.get_full_name() for c in got] == [n for n, _, _ in expected]
    by_name = {c.full_name(): c for c in CHANNELS}
    for c, (name, value, t_s) in zip(got, expected, strict=True):
        assert c.time.get_float() == pytest.approx(t_s, abs=1e-6), name
        t = by_name[name].type
        v = c.get_val()
        if t.name == "F32":
            assert v == pytest.approx(f32(value), rel=1e-7, abs=1e-30), name
        elif t.name == "F64":
            assert v == value, name
        elif t.kind == "bool":
            assert v is (value == ch.FW_TRUE), name
        elif t is ch.STATE:
            assert v == SimpleState(value).name, name
        elif t.kind == "string":
            assert v == value, name
        else:
            assert v == value, name


MESSAGES: list[Any] = [
    SmUpdate(timestamp_ms=61_500, state=SimpleState.BOOST, armed=True, sm_type=0,
             altitude_m=1234.56789, acceleration_mps2=52.25, accel_vert_mps2=-3.5,
             velocity_mps=211.125, roll_rad=0.5, pitch_rad=-1.25, yaw_rad=3.0),
    Status(timestamp_ms=61_600, state=SimpleState.APOGEE, sm_type=0,
           flags=Status.make_flags(armed=False, imu_ok=True, baro_ok=False, calibrated=True,
                                   log_ready=True)),
    LinkStats(rssi_dbm=-71.5, link_quality_pct=97, snr_db=9.0, tx_power_mw=250,
              downlink_rssi_dbm=-80.0, downlink_link_quality_pct=88, downlink_snr_db=-2.5,
              rf_mode=5, antenna=1),
    Position(lat_deg=47.397742123456, lon_deg=8.545594987654, alt_amsl_m=488.25,
             relative_alt_m=12.5, ground_speed_mps=3.75, course_deg=271.0, satellites=14,
             fix_type=3),
    Battery(voltage_v=11.85, current_a=4.5, consumed_mah=1234.0, remaining_pct=76),
    VehicleState(armed=False, mode="STABILIZE", custom_mode=0x1_0000_0002, roll_rad=-0.1,
                 altitude_m=55.5, climb_mps=-1.5),
]


def test_every_kind_of_message_decodes_to_its_channels(gds: Gds) -> None:
    gds.load(build_dictionary())
    clock = UpdateClock(TB_WORKSTATION_TIME, 0, clock=lambda: T0)
    # the first timestamp is anchored at the gateway's clock (T0), later ones keep their
    # spacing; messages without a timestamp are stamped with the gateway's clock
    first_ms = MESSAGES[0].timestamp_ms
    packets, expected = pack_all(
        MESSAGES, DEFAULT_ID_BASE, clock,
        lambda m: T0 + (m.timestamp_ms - first_ms) / 1000 if hasattr(m, "timestamp_ms") else T0)
    assert len(packets) > 1  # several packets: "no room left" split at 512 bytes
    got = gds.decode(packets)
    check(got, expected)
    names = {n for n, _, _ in expected}
    for must in ("Aurora.flight.State", "Aurora.flight.Armed", "Aurora.status.ImuOk",
                 "Aurora.status.BaroOk", "Aurora.vehicle.Mode", "Aurora.gps.Latitude",
                 "Aurora.link.TxPower", "Aurora.flight.Uptime", "Aurora.vehicle.CustomMode"):
        assert must in names, must
    # booleans both ways, the string, the enum, the time
    vals = {c.template.get_full_name(): c.get_val() for c in got}
    assert vals["Aurora.status.ImuOk"] is True and vals["Aurora.status.BaroOk"] is False
    assert vals["Aurora.vehicle.Mode"] == "STABILIZE"
    assert vals["Aurora.vehicle.CustomMode"] == 0x0000_0002
    assert vals["Aurora.gps.Latitude"] == 47.397742123456
    assert {c.time.timeBase.val for c in got} == {"TB_WORKSTATION_TIME"}
    assert {c.time.get_float() for c in got} == {T0, T0 + 0.1}  # SM_UPDATE, then STATUS


def test_processor_time_and_a_small_buffer(gds: Gds) -> None:
    gds.load(build_dictionary())
    clock = UpdateClock(TB_PROC_TIME, 7)  # the flight computer's uptime itself
    packets, expected = pack_all(MESSAGES[:2], DEFAULT_ID_BASE, clock,
                                 lambda m: m.timestamp_ms / 1000, buffer_size=21)
    # descriptor + one F32 entry: every entry (U8 16 B, F32/U32 19 B) travels alone
    assert len(packets) == len(expected)
    got = gds.decode(packets)
    check(got, expected)
    first = got[0]
    assert (first.time.seconds, first.time.useconds) == (61, 500_000)  # uptime 61.5 s
    assert first.time.timeBase.val == "TB_PROC_TIME" and first.time.timeContext == 7


def test_a_non_default_id_base_round_trips(gds: Gds) -> None:
    base = 0x0ABC_0000
    dicts = gds.load(build_dictionary(base))
    assert dicts.channel_name["Aurora.flight.Altitude"].get_id() == base
    clock = UpdateClock(TB_WORKSTATION_TIME, 0, clock=lambda: T0)
    packets, expected = pack_all(MESSAGES[:1], base, clock, lambda m: T0)
    check(gds.decode(packets), expected)
    # the same packets against a default-base dictionary: rejected, nothing decodes
    default_packets, _ = pack_all(MESSAGES[:1], DEFAULT_ID_BASE, clock, lambda m: T0)
    assert gds.decode(default_packets) == []


# -- the command ----------------------------------------------------------------------------------

def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(GATEWAY), "fprime-dictionary", *args], capture_output=True,
                          text=True, timeout=60, check=False)


def test_the_command_writes_the_file(tmp_path: Path) -> None:
    out = tmp_path / "dict.json"
    p = run("-o", str(out), "--id-base", "0x400", "--scid", "0x45", "--frame-size", "2048")
    assert p.returncode == 0, p.stderr
    assert json.loads(out.read_text(encoding="utf-8")) == build_dictionary(
        0x400, scid=0x45, frame_size=2048)


@pytest.mark.parametrize("args", [("--id-base", "nope"), ("--id-base", "-5"),
                                  ("--scid", "0x400")])
def test_the_command_rejects_a_bad_value_in_one_line(tmp_path: Path,
                                                     args: tuple[str, str]) -> None:
    out = tmp_path / "dict.json"
    p = run("-o", str(out), *args)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "fprime-dictionary" in lines[0], p.stderr
    assert not out.exists()
    assert p.stdout == ""


def test_the_handler_writes_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    from backends.fprime.cli import main
    assert main(["fprime-dictionary", "--id-base", "512"]) == 0
    assert json.loads(capsys.readouterr().out) == build_dictionary(512)
