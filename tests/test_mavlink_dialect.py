"""The Aurora MAVLink dialect: reproducible from its XML, ids from an unused range, messages
that round-trip every SM_UPDATE/STATUS field through pymavlink."""

from __future__ import annotations

import importlib.util
import math
import re
import struct
import sys
from pathlib import Path

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


def test_checked_in_module_is_what_the_xml_generates(tmp_path: Path) -> None:
    """Byte for byte, against a fresh generation with the installed (pinned) pymavlink."""
    fresh = gen.generate(gen.XML, tmp_path / "aurora_mavlink.py")
    assert fresh.read_bytes() == gen.MODULE.read_bytes(), (
        f"dialects/aurora_mavlink.py differs from what pymavlink {gen.installed_pymavlink()} "
        f"generates from its XML (pyproject.toml pins {gen.pinned_pymavlink()}): run "
        "tools/gen_mavlink_dialect.py")


def test_the_regeneration_check_notices_a_changed_xml(tmp_path: Path) -> None:
    xml = tmp_path / "aurora_mavlink.xml"
    xml.write_text(gen.XML.read_text().replace('name="AURORA_STATUS"', 'name="AURORA_STATUS2"'))
    module = tmp_path / "aurora_mavlink.py"
    module.write_bytes(gen.MODULE.read_bytes())
    assert gen.main(["--xml", str(xml), "--output", str(module), "--check"]) == 1
    assert gen.main(["--output", str(gen.MODULE), "--check"]) == 0


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


def test_router_tables_agree_with_pymavlink() -> None:
    """The offsets the router reads targets from are where pymavlink packs them."""
    checked = 0
    for msgid, (so, co) in dialect.TARGETS.items():
        cls = mav.mavlink_map[msgid]
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
        buf = cls(*args).pack(mav.MAVLink(None, 1, 1))
        payload = buf[10:-2]
        assert payload[so] == 0xA7, cls.msgname
        if co >= 0:
            assert payload[co] == 0x5C, cls.msgname
        checked += 1
    assert checked > 50
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
