"""The Aurora MAVLink dialect: reproducible from its XML, ids from an unused range, messages
that round-trip every SM_UPDATE/STATUS field through pymavlink."""

from __future__ import annotations

import importlib.util
import math
import re
import struct
import sys
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.generator import mavparse

from backends.mavlink import dialect
from backends.mavlink.translate import (
    aurora_sm_update,
    aurora_status,
    sm_update_from_mavlink,
    status_from_mavlink,
)
from dialects import aurora_mavlink as mav
from gateway.model import SmUpdate, Status
from gateway.wire import decode_all, encode

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
import gen_mavlink_dialect as gen  # noqa: E402


def test_the_installed_pymavlink_is_the_pinned_one_that_generated_the_module() -> None:
    pinned = gen.pinned_pymavlink()
    assert pinned is not None, "pyproject.toml must pin pymavlink exactly: pymavlink==X"
    installed = gen.installed_pymavlink()
    assert installed == pinned, (
        f"this checkout expects pymavlink=={pinned} (pinned in pyproject.toml; it generated "
        f"dialects/aurora_mavlink.py), but {installed} is installed: pip install -e '.[test]'")
    assert gen.generated_with(gen.MODULE) == pinned, (
        f"dialects/aurora_mavlink.py says it was generated with pymavlink "
        f"{gen.generated_with(gen.MODULE)}, pyproject.toml pins {pinned}: regenerate it with "
        f"tools/gen_mavlink_dialect.py")


def test_checked_in_modules_are_what_the_xml_generates(tmp_path: Path) -> None:
    """Byte for byte, against a fresh generation with the installed (pinned) pymavlink."""
    fresh = gen.generate(gen.XML, tmp_path / "aurora_mavlink.py")
    assert fresh.read_bytes() == gen.MODULE.read_bytes(), (
        f"dialects/aurora_mavlink.py differs from what pymavlink {gen.installed_pymavlink()} "
        f"generates from its XML and keep list (pyproject.toml pins {gen.pinned_pymavlink()}): "
        "run tools/gen_mavlink_dialect.py")
    routing = gen.generate_routing(gen.XML, tmp_path / "mavlink_routing.py")
    assert routing.read_bytes() == gen.ROUTING.read_bytes(), (
        "dialects/mavlink_routing.py is out of date: run tools/gen_mavlink_dialect.py")


def _copies(tmp_path: Path) -> list[str]:
    """Both checked-in modules copied into tmp_path, as --output/--routing-output flags."""
    module, routing = tmp_path / "aurora_mavlink.py", tmp_path / "mavlink_routing.py"
    module.write_bytes(gen.MODULE.read_bytes())
    routing.write_bytes(gen.ROUTING.read_bytes())
    return ["--output", str(module), "--routing-output", str(routing)]


def test_the_regeneration_check_notices_a_changed_xml(tmp_path: Path) -> None:
    xml = tmp_path / "aurora_mavlink.xml"
    xml.write_text(gen.XML.read_text().replace('name="AURORA_STATUS"', 'name="AURORA_STATUS2"'))
    assert gen.main(["--xml", str(xml), *_copies(tmp_path), "--check"]) == 1
    assert gen.main([*_copies(tmp_path), "--check"]) == 0
    assert gen.main(["--check"]) == 0  # the checked-in ones


def test_the_regeneration_check_notices_a_changed_keep_list_or_routing_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    keep = tmp_path / "keep.txt"
    keep.write_text(gen.KEEP.read_text() + "message PARAM_EXT_VALUE\n")
    assert gen.main(["--keep", str(keep), *_copies(tmp_path), "--check"]) == 1
    assert "aurora_mavlink.py: OUT OF DATE" in capsys.readouterr().out
    flags = _copies(tmp_path)
    stale = tmp_path / "mavlink_routing.py"
    stale.write_text(stale.read_text().replace("0: ('HEARTBEAT', 50,", "0: ('HEARTBEAT', 51,"))
    assert gen.main([*flags, "--check"]) == 1
    out = capsys.readouterr().out
    assert "mavlink_routing.py: OUT OF DATE" in out and "aurora_mavlink.py: up to date" in out


def test_a_keep_list_naming_an_unknown_message_or_a_bad_line_is_refused(tmp_path: Path) -> None:
    keep = tmp_path / "keep.txt"
    keep.write_text("message HEARTBEAT\nmessage NO_SUCH_MESSAGE\nenum NO_SUCH_ENUM\n")
    with pytest.raises(gen.GenerationError, match="enum NO_SUCH_ENUM, message NO_SUCH_MESSAGE"):
        gen.generate(gen.XML, tmp_path / "x.py", keep=keep)
    keep.write_text("messages HEARTBEAT\n")
    with pytest.raises(gen.GenerationError, match=r"keep.txt:1: expected 'message NAME'"):
        gen.read_keep(keep)


def test_the_slim_module_holds_the_keep_list_and_our_xml_and_nothing_else() -> None:
    keep = gen.read_keep()
    ours = mavparse.MAVXML(str(gen.XML), mavparse.PROTOCOL_2_0)
    names = {cls.msgname for cls in mav.mavlink_map.values()}
    assert names == keep.messages | {m.name for m in ours.message}
    assert set(mav.enums) == keep.enums | {e.name for e in ours.enum}
    assert len(names) < 80  # not the 230-odd of common + development


# Names the product takes from the dialect module: mav.X, and message classes and ids however
# they are reached (not `self.mav.…`, a MAVLink link object).
_MAV_ATTR = re.compile(r"(?<![\w.])mav\.([A-Za-z_]\w*)")
_MSG_NAMES = re.compile(r"\b(MAVLink_\w+_message|MAVLINK_MSG_ID_\w+)\b")


def test_every_dialect_name_the_code_uses_is_in_the_slim_module() -> None:
    used: dict[str, str] = {}
    for path in sorted([*(ROOT / "gateway").rglob("*.py"), *(ROOT / "backends").rglob("*.py")]):
        text = path.read_text(encoding="utf-8")
        for name in [*_MAV_ATTR.findall(text), *_MSG_NAMES.findall(text)]:
            used.setdefault(name, str(path.relative_to(ROOT)))
    assert len(used) > 60  # really scanned the code
    missing = {name: where for name, where in used.items() if not hasattr(mav, name)}
    assert not missing, (f"not in the slim dialect: {missing}; add them to "
                         "dialects/aurora_mavlink_keep.txt and run tools/gen_mavlink_dialect.py")


def test_the_generator_refuses_a_pymavlink_other_than_the_pinned_one(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    pyproject = tmp_path / "pyproject.toml"
    pyproject.write_text(re.sub(r'"pymavlink==[^"]*"', '"pymavlink==0.0.1"',
                                gen.PYPROJECT.read_text()))
    monkeypatch.setattr(gen, "PYPROJECT", pyproject)
    assert gen.pinned_pymavlink(pyproject) == "0.0.1"
    module = tmp_path / "aurora_mavlink.py"
    assert gen.main(["--output", str(module)]) == 2
    assert not module.exists()
    err = capsys.readouterr().err
    assert "pins pymavlink==0.0.1" in err and f"installed: {gen.installed_pymavlink()}" in err


def test_the_generated_module_imports_on_its_own(tmp_path: Path) -> None:
    out = gen.generate(gen.XML, tmp_path / "x_dialect.py")
    spec = importlib.util.spec_from_file_location("x_dialect", out)
    mod = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    spec.loader.exec_module(mod)  # type: ignore[union-attr]
    assert mod.MAVLINK_MSG_ID_AURORA_SM_UPDATE == 45000
    assert mod.WIRE_PROTOCOL_VERSION == "2.0"
    assert mod.MAVLINK_MSG_ID_AVAILABLE_MODES == 435  # from development.xml


def test_aurora_ids_are_in_a_range_no_published_dialect_uses() -> None:
    all_xml = Path(gen.upstream_definitions_dir()) / "all.xml"
    used: set[int] = set()
    pending = [all_xml]
    seen: set[Path] = set()
    while pending:
        p = pending.pop()
        if p in seen or not p.exists():
            continue
        seen.add(p)
        x = mavparse.MAVXML(str(p), mavparse.PROTOCOL_2_0)
        used |= {m.id for m in x.message}
        pending += [p.parent / inc for inc in x.include]
    assert len(seen) > 10 and len(used) > 300  # really read the published dialects
    ours = {i for i in mav.mavlink_map if i in dialect.AURORA_ID_RANGE}
    assert ours == {45000, 45001}
    assert not used & set(dialect.AURORA_ID_RANGE)
    assert max(dialect.AURORA_ID_RANGE) < 65536  # MESSAGE_INTERVAL's message_id is uint16


def _upstream_all() -> Any:
    from pymavlink.dialects.v20 import all as upstream

    return upstream


def _class_of(msgid: int) -> Any:
    """pymavlink's own generated class for an id of all.xml; ours for the Aurora ids."""
    return _upstream_all().mavlink_map.get(msgid) or mav.mavlink_map[msgid]


def test_the_routing_table_has_every_message_of_all_xml_and_ours() -> None:
    assert set(dialect.MESSAGES) == set(_upstream_all().mavlink_map) | {45000, 45001}
    assert set(mav.mavlink_map) <= set(dialect.MESSAGES)
    assert len(dialect.MESSAGES) > 300


def test_the_routing_table_agrees_with_pymavlinks_generated_modules() -> None:
    """crc_extra, largest payload and name of every id are what pymavlink's all.py (and our
    slim module, for the ids it decodes) say."""
    for msgid, info in dialect.MESSAGES.items():
        cls = _class_of(msgid)
        assert (dialect.NAMES[msgid], info.crc_extra, info.max_len) == (
            cls.msgname, cls.crc_extra, cls.unpacker.size), msgid
        ours = mav.mavlink_map.get(msgid)
        if ours is not None:
            assert (ours.crc_extra, ours.unpacker.size) == (info.crc_extra, info.max_len)


def test_router_tables_agree_with_pymavlink() -> None:
    """The offsets the router reads targets from are where pymavlink packs them, for every
    targeted id of the table; and no other id has such a field."""
    checked = 0
    for msgid, (so, co) in dialect.TARGETS.items():
        cls = _class_of(msgid)
        args = []
        for name, ftype, n in zip(cls.fieldnames, cls.fieldtypes,
                                  [cls.array_lengths[cls.ordered_fieldnames.index(f)]
                                   for f in cls.fieldnames], strict=True):
            if ftype == "char":
                args.append(b"x" * max(n, 1))
            elif name == "target_system":
                args.append(0xA7)
            elif name == "target_component":
                args.append(0x5C)
            elif n:
                args.append([0] * n)
            elif ftype in ("float", "double"):
                args.append(0.0)
            else:
                args.append(0)
        buf = cls(*args).pack(_upstream_all().MAVLink(None, 1, 1))
        payload = buf[10:-2]
        assert payload[so] == 0xA7, cls.msgname
        if co >= 0:
            assert payload[co] == 0x5C, cls.msgname
        checked += 1
    assert checked > 100
    untargeted = [i for i in dialect.MESSAGES if i not in dialect.TARGETS]
    assert all("target_system" not in _class_of(i).fieldnames for i in untargeted)
    assert dialect.CRC_EXTRA[0] == 50 and dialect.CRC_EXTRA[30] == 39  # HEARTBEAT, ATTITUDE


floats = st.floats(allow_nan=False, width=64)


@settings(max_examples=150, deadline=None)
@given(t=st.integers(0, 2**32 - 1), state=st.integers(0, 255), armed=st.booleans(),
       sm_type=st.integers(0, 255), reserved=st.integers(0, 255),
       values=st.lists(floats, min_size=7, max_size=7), rev=st.sampled_from([36, 64]))
def test_aurora_sm_update_round_trips_both_revisions(t, state, armed, sm_type, reserved, values,
                                                      rev) -> None:
    m = SmUpdate(t, state, armed, sm_type, *values, payload_len=rev, reserved=reserved)
    if rev == 36:  # what a 36-byte frame can carry: the f32 values
        m = decode_all(encode(m._replace(
            **{k: _f32(v) for k, v in m._asdict().items()
               if isinstance(v, float)})))[0]
    sender = mav.MAVLink(None, 1, 1)
    buf = aurora_sm_update(m).pack(sender)
    got = mav.MAVLink(None).decode(bytearray(buf))
    back = sm_update_from_mavlink(got)
    assert _bits(back.fields()) == _bits(m.fields())


@given(t=st.integers(0, 2**32 - 1), state=st.integers(0, 255), sm_type=st.integers(0, 255),
       flags=st.integers(0, 255), reserved=st.integers(0, 255))
def test_aurora_status_round_trips(t, state, sm_type, flags, reserved) -> None:
    m = Status(t, state, sm_type, flags, reserved=reserved)
    buf = aurora_status(m).pack(mav.MAVLink(None, 1, 1))
    back = status_from_mavlink(mav.MAVLink(None).decode(bytearray(buf)))
    assert back.fields() == m.fields()


def _f32(x: float) -> float:
    if math.isfinite(x) and abs(x) > 3.4028234663852886e38:
        return math.copysign(math.inf, x)
    return struct.unpack("<f", struct.pack("<f", x))[0]


def _bits(d: dict) -> dict:
    return {k: struct.pack("<d", v) if isinstance(v, float) else v for k, v in d.items()}
