"""UAVTalk object definitions: the spec's ids and vectors computed from the 16.09 XMLs, the
parser's rules (wire order, cloneof, element names, defaults), metaobjects, pack/unpack
properties, and dRonin's independent parser as a cross-check."""

from __future__ import annotations

import math
import struct
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from backends.uavtalk.codec import Decoder, Packet, PacketType, encode
from backends.uavtalk.objects import (
    META_SIZE,
    AccessMode,
    FieldDef,
    MetaDef,
    ObjectDef,
    ObjectSet,
    Telemetry,
    TelemetrySpec,
    UpdateMode,
    object_id,
)

XML_DIR = Path(__file__).resolve().parent.parent / "dialects" / "uavtalk"
OBJECTS = ObjectSet.load()

# The spec's known 16.09 ids (../shared/specs/uavtalk.md), typed here, computed by the code.
SPEC_IDS = {
    "FlightTelemetryStats": 0x6737BB5A,
    "GCSTelemetryStats": 0xCAD1DC0A,
    "AttitudeState": 0xD7E0D964,
    "FlightStatus": 0x24D25E28,
    "SystemAlarms": 0x20E6CAAC,
    "GPSPositionSensor": 0x9DF1F67A,
    "FirmwareIAPObj": 0x8328F252,
}

# The spec's vectors (whole packets).
ATTITUDE_VECTOR = bytes.fromhex(
    "3c 20 26 00 64 d9 e0 d7 00 00 00 00 80 3f 00 00 00 00 00 00 00 00 00 00 00 00 00 00"
    " 20 41 00 00 a0 c0 00 00 b4 42 cb"
)
FLIGHT_STATS_VECTOR = bytes.fromhex("3c 20 2f 00 5a bb 37 67 00 00") + bytes(36) + b"\x02\x68"
GCS_STATS_VECTOR = bytes.fromhex("3c 20 2f 00 0a dc d1 ca 00 00") + bytes(36) + b"\x01\x96"


def _data(packet: bytes) -> bytes:
    return packet[10:-1]


# ------------------------------------------------------------------------------- ids and sizes


@pytest.mark.parametrize(("name", "expected"), sorted(SPEC_IDS.items()))
def test_spec_ids(name: str, expected: int) -> None:
    obj = OBJECTS.by_name(name)
    assert obj.id == expected
    assert obj.meta_id == expected + 1
    assert OBJECTS.by_id(expected) is obj


@pytest.mark.parametrize(
    ("name", "size"),
    [("FlightStatus", 9), ("AttitudeState", 28), ("FlightTelemetryStats", 37),
     ("GCSTelemetryStats", 37)],
)
def test_spec_sizes(name: str, size: int) -> None:
    obj = OBJECTS.by_name(name)
    assert obj.size == size
    assert OBJECTS.data_length(obj.id) == size


@pytest.mark.parametrize("vector", [ATTITUDE_VECTOR, FLIGHT_STATS_VECTOR, GCS_STATS_VECTOR])
def test_vector_length_is_the_object_size(vector: bytes) -> None:
    size, oid = struct.unpack_from("<HI", vector, 2)
    assert OBJECTS.data_length(oid) == size - 10 == len(_data(vector))


def test_the_gateway_objects_are_there() -> None:
    for name in ("FlightTelemetryStats", "GCSTelemetryStats", "AttitudeState", "FlightStatus",
                 "SystemAlarms", "BaroSensor", "GPSPositionSensor", "FirmwareIAPObj",
                 "FlightBatteryState", "ObjectPersistence"):
        assert name in OBJECTS
    assert len(OBJECTS) == len(list(XML_DIR.glob("*.xml"))) == 113


def test_unknown_ids_and_names() -> None:
    assert OBJECTS.by_id(0x12345678) is None
    assert OBJECTS.data_length(0x12345678) is None
    with pytest.raises(KeyError, match="NoSuchObject"):
        OBJECTS.by_name("NoSuchObject")


def test_all_ids_are_distinct_and_even() -> None:
    ids = [obj.id for obj in OBJECTS]
    assert len(set(ids)) == len(ids)
    assert all(i % 2 == 0 for i in ids)


def test_load_is_cached_and_an_explicit_directory_parses_again() -> None:
    assert ObjectSet.load() is OBJECTS
    again = ObjectSet.load(XML_DIR)
    assert again is not OBJECTS
    assert [(o.name, o.id, o.size) for o in again] == [(o.name, o.id, o.size) for o in OBJECTS]


# ------------------------------------------------------------------------- the spec's vectors


def test_attitude_vector_decodes() -> None:
    values = OBJECTS.by_name("AttitudeState").unpack(_data(ATTITUDE_VECTOR))
    assert values == {"q1": 1.0, "q2": 0.0, "q3": 0.0, "q4": 0.0, "Roll": 10.0, "Pitch": -5.0,
                      "Yaw": 90.0}


def test_attitude_vector_packs() -> None:
    obj = OBJECTS.by_name("AttitudeState")
    data = obj.pack({"q1": 1, "Roll": 10.0, "Pitch": -5.0, "Yaw": 90.0})
    assert data == _data(ATTITUDE_VECTOR)


@pytest.mark.parametrize(
    ("name", "vector", "status"),
    [("FlightTelemetryStats", FLIGHT_STATS_VECTOR, "HandshakeAck"),
     ("GCSTelemetryStats", GCS_STATS_VECTOR, "HandshakeReq")],
)
def test_telemetry_stats_vectors(name: str, vector: bytes, status: str) -> None:
    obj = OBJECTS.by_name(name)
    assert obj.pack({"Status": status}) == _data(vector)
    values = obj.unpack(_data(vector))
    assert values["Status"] == obj.field("Status").options.index(status)
    assert obj.fields[-1].name == "Status"  # the enum is the last byte on the wire


def test_codec_and_objects_together() -> None:
    decoder = Decoder(OBJECTS.data_length)
    packets = decoder.feed(ATTITUDE_VECTOR + FLIGHT_STATS_VECTOR)
    assert [OBJECTS.by_id(p.object_id).name for p in packets] == [  # type: ignore[union-attr]
        "AttitudeState", "FlightTelemetryStats"]
    obj = OBJECTS.by_name("FlightStatus")
    data = obj.pack({"Armed": "Armed", "FlightMode": "PositionHold"})
    (packet,) = decoder.feed(encode(Packet(PacketType.OBJ, obj.id, 0, data)))
    assert obj.unpack(packet.data)["Armed"] == 2


# ------------------------------------------------------------------------------ parser's rules


def _declared(name: str) -> list[str]:
    for path in XML_DIR.glob("*.xml"):
        node = ET.parse(path).getroot().find("object")
        if node is not None and node.get("name") == name:
            return [f.get("name", "") for f in node.findall("field")]
    raise KeyError(name)


@pytest.mark.parametrize("name", ["FirmwareIAPObj", "FlightTelemetryStats", "SystemAlarms",
                                  "GPSPositionSensor", "FlightBatteryState", "MixerSettings"])
def test_wire_order_is_a_stable_sort_by_element_size(name: str) -> None:
    obj = OBJECTS.by_name(name)
    declared = _declared(name)
    sizes = [f.element_size for f in obj.fields]
    assert sizes == sorted(sizes, reverse=True)
    for size in set(sizes):
        same = [f.name for f in obj.fields if f.element_size == size]
        assert same == [n for n in declared if n in same]


def test_object_id_ignores_declaration_order_across_sizes_but_not_within() -> None:
    a = FieldDef("A", "uint8", 1, (), (0,))
    b = FieldDef("B", "float", 1, (), (0.0,))
    c = FieldDef("C", "uint8", 1, (), (0,))
    assert object_id("X", False, True, [a, b, c]) == object_id("X", False, True, [b, a, c])
    assert object_id("X", False, True, [a, b, c]) != object_id("X", False, True, [c, b, a])
    assert object_id("X", True, True, [a]) != object_id("X", False, True, [a])
    e1 = FieldDef("E", "enum", 1, ("Off", "On"), (0,))
    e2 = FieldDef("E", "enum", 1, ("Off", "Onn"), (0,))
    assert object_id("X", False, True, [e1]) != object_id("X", False, True, [e2])


def test_elementnames_win_over_elements() -> None:
    # groundpathfollowersettings.xml: elements="2" elementnames="Min,SlowForward, Max" — the
    # 16.09 parser reads elementnames first, so 3 elements (dRonin's parser says 2).
    field = OBJECTS.by_name("GroundPathFollowerSettings").field("ThrustLimit")
    assert field.count == 3
    assert field.element_names == ("Min", "SlowForward", "Max")
    assert field.defaults == pytest.approx((-0.3, 0.15, 0.3))


def test_defaults_from_the_xml() -> None:
    status = OBJECTS.by_name("FlightStatus").defaults()
    assert status["Armed"] == 0 and status["FlightMode"] == 0  # no defaultvalue: 0
    assert status["ControlChain"] == [0, 0, 0]
    mixer = OBJECTS.by_name("MixerSettings").defaults()
    assert mixer["MixerValueRoll"] == 50
    assert mixer["ThrottleCurve2"] == pytest.approx([0, 0.25, 0.5, 0.75, 1])
    obj = OBJECTS.by_name("MixerSettings")
    assert obj.unpack(obj.pack({})) == mixer  # float defaults are held as f32 values


MINI = """<xml>
  <object name="Mini" singleinstance="false" settings="false" priority="true">
    <description>test</description>
    <field name="Mode" units="" type="enum" defaultvalue="B, C">
      <elementnames><elementname>First</elementname><elementname>Second</elementname></elementnames>
      <options><option>A</option><option>B</option><option>C</option></options>
    </field>
    <field name="Gain" units="" type="float" elements="3" defaultvalue="1.5"/>
    <field name="ModeCopy" units="" cloneof="Mode"/>
    <field name="Count" units="" type="int16" elements="1" defaultvalue="-7"/>
    <access gcs="readonly" flight="readwrite"/>
    <telemetrygcs acked="true" updatemode="onchange" period="0"/>
    <telemetryflight acked="false" updatemode="throttled" period="250"/>
    <logging updatemode="periodic" period="1000"/>
  </object>
</xml>
"""


@pytest.fixture
def mini(tmp_path: Path) -> ObjectDef:
    (tmp_path / "mini.xml").write_text(MINI)
    return ObjectSet.load(tmp_path).by_name("Mini")


def test_child_lists_clones_and_legacy_defaults(mini: ObjectDef) -> None:
    assert [f.name for f in mini.fields] == ["Gain", "Count", "Mode", "ModeCopy"]
    assert mini.field("ModeCopy") == mini.field("Mode")._replace(name="ModeCopy")
    assert mini.field("Mode").options == ("A", "B", "C")
    assert mini.defaults() == {"Gain": [1.5, 1.5, 1.5], "Count": -7, "Mode": [1, 2],
                               "ModeCopy": [1, 2]}
    assert mini.size == 3 * 4 + 2 + 2 + 2
    assert not mini.single_instance and mini.priority
    assert mini.id == object_id("Mini", False, False, list(mini.fields))


def test_bad_definitions_name_the_file_and_field(tmp_path: Path) -> None:
    (tmp_path / "bad.xml").write_text(MINI.replace('defaultvalue="B, C"', 'defaultvalue="B, Z"'))
    with pytest.raises(ValueError, match=r"bad\.xml.*Mode.*'Z'"):
        ObjectSet.load(tmp_path)
    (tmp_path / "bad.xml").write_text(MINI.replace('cloneof="Mode"', 'cloneof="Nope"'))
    with pytest.raises(ValueError, match=r"ModeCopy.*Nope"):
        ObjectSet.load(tmp_path)


# ------------------------------------------------------------------------------------ metadata


def test_metaobject_layout_and_defaults(mini: ObjectDef) -> None:
    assert META_SIZE == 8
    flags = (0 << 0 | 1 << 1 | 0 << 2 | 1 << 3 | UpdateMode.THROTTLED << 4
             | UpdateMode.ONCHANGE << 6 | UpdateMode.PERIODIC << 8)
    assert mini.telemetry.flags == flags
    meta = MetaDef(mini)
    assert meta.id == mini.id + 1 and meta.size == META_SIZE and meta.parent is mini
    assert meta.pack({}) == struct.pack("<4H", flags, 250, 0, 1000)
    assert Telemetry.from_metadata(meta.unpack(meta.pack({}))) == mini.telemetry


def test_metaobjects_resolve_by_id_and_name() -> None:
    attitude = OBJECTS.by_name("AttitudeState")
    meta = OBJECTS.by_id(attitude.meta_id)
    assert isinstance(meta, MetaDef) and meta.parent is attitude
    assert OBJECTS.by_name("AttitudeStateMeta") is meta
    assert OBJECTS.data_length(attitude.meta_id) == META_SIZE
    # telemetryflight: periodic, 130 ms, not acked; everything else manual, read-write
    assert attitude.telemetry == Telemetry(TelemetrySpec(False, UpdateMode.PERIODIC, 130),
                                           TelemetrySpec(False, UpdateMode.MANUAL, 0),
                                           TelemetrySpec(False, UpdateMode.MANUAL, 0),
                                           AccessMode.READWRITE, AccessMode.READWRITE)
    assert meta.unpack(meta.pack({})) == {"Modes": 0x10, "FlightTelemetryUpdatePeriod": 130,
                                          "GCSTelemetryUpdatePeriod": 0, "LoggingUpdatePeriod": 0}


def test_every_metaobject_round_trips() -> None:
    for obj in OBJECTS:
        meta = OBJECTS.by_id(obj.meta_id)
        assert isinstance(meta, MetaDef)
        decoded = Telemetry.from_metadata(meta.unpack(meta.pack({})))
        assert decoded == obj.telemetry


# ------------------------------------------------------------------------------- pack / unpack


def _element(f: FieldDef) -> st.SearchStrategy[Any]:
    if f.type == "float":
        return st.floats(width=32, allow_nan=False)
    bounds = {"int8": (-128, 127), "int16": (-(1 << 15), (1 << 15) - 1),
              "int32": (-(1 << 31), (1 << 31) - 1), "uint8": (0, 255), "uint16": (0, 0xFFFF),
              "uint32": (0, 0xFFFFFFFF), "enum": (0, 255)}[f.type]
    return st.integers(*bounds)


@st.composite
def _object_and_values(draw: st.DrawFn) -> tuple[ObjectDef, dict[str, Any]]:
    obj = draw(st.sampled_from(list(OBJECTS)))
    values: dict[str, Any] = {}
    for f in obj.fields:
        if draw(st.booleans()):  # some fields missing: they take their defaults
            if f.count == 1:
                values[f.name] = draw(_element(f))
            else:
                values[f.name] = draw(st.lists(_element(f), min_size=f.count, max_size=f.count))
    return obj, values


@settings(max_examples=300, deadline=None)
@given(_object_and_values())
def test_pack_unpack_round_trip(case: tuple[ObjectDef, dict[str, Any]]) -> None:
    obj, values = case
    data = obj.pack(values)
    assert len(data) == obj.size
    expected = {**obj.defaults(), **values}
    assert obj.unpack(data) == expected
    assert obj.pack(obj.unpack(data)) == data


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(list(OBJECTS)), st.data())
def test_any_data_of_the_right_length_unpacks_and_repacks(
    obj: ObjectDef, data: st.DataObject
) -> None:
    raw = data.draw(st.binary(min_size=obj.size, max_size=obj.size))
    values = obj.unpack(raw)
    if not any(isinstance(v, float) and math.isnan(v) for v in _flat(values)):
        assert obj.pack(values) == raw


def _flat(values: dict[str, Any]) -> list[Any]:
    out: list[Any] = []
    for v in values.values():
        out.extend(v if isinstance(v, list) else [v])
    return out


def test_enums_by_name_and_bad_values() -> None:
    obj = OBJECTS.by_name("FlightStatus")
    assert obj.unpack(obj.pack({"Armed": "Arming"}))["Armed"] == 1
    assert obj.unpack(obj.pack({"ControlChain": ["True", 0, 1]}))["ControlChain"] == [1, 0, 1]
    for bad in ({"Armed": "Flying"}, {"Armed": 256}, {"Armed": -1}, {"ControlChain": [0, 1]},
                {"Nope": 1}, {"Armed": 1.5}):
        with pytest.raises(ValueError):
            obj.pack(bad)
    with pytest.raises(ValueError, match="8 bytes, 9"):
        obj.unpack(bytes(8))
    with pytest.raises(ValueError):
        OBJECTS.by_name("AttitudeState").pack({"Roll": "ten"})


def test_definitions_are_immutable() -> None:
    obj = OBJECTS.by_name("AttitudeState")
    with pytest.raises(AttributeError):
        obj.id = 1  # type: ignore[misc]


# ------------------------------------------------------------------- dRonin, an independent parser


def test_dronin_agrees_on_ids_sizes_and_decoding() -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        uavo = pytest.importorskip("dronin.uavo")
        collection = pytest.importorskip("dronin.uavo_collection").UAVOCollection()
    checked = 0
    for path in sorted(XML_DIR.glob("*.xml")):
        cls = uavo.make_class(collection, path.read_text(), update_globals=False)
        ours = OBJECTS.by_name(cls._name.removeprefix("UAVO_"))
        if ours.name == "GroundPathFollowerSettings":
            # dRonin takes elements="2" before elementnames: see test_elementnames_win_over_elements
            assert (cls._id, cls.get_size_of_data()) != (ours.id, ours.size)
            continue
        assert (cls._id, cls.get_size_of_data()) == (ours.id, ours.size), ours.name
        checked += 1
    assert checked == 112
    cls = uavo.make_class(collection, (XML_DIR / "attitudestate.xml").read_text(),
                          update_globals=False)
    theirs = cls.from_bytes(_data(ATTITUDE_VECTOR), 0, None)
    ours_values = OBJECTS.by_name("AttitudeState").unpack(_data(ATTITUDE_VECTOR))
    assert {k: getattr(theirs, k) for k in ours_values} == ours_values
