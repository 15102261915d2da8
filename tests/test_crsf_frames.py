"""CRSF encoder and payload decoder: every vector of ``shared/specs/crsf.md`` both ways,
frame bounds, the all-0xFF rule, angle wrapping, both barometric altitude encodings, and
encode → decode round trips of every frame type over the full value ranges."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from backends.crsf.decoder import decode_all
from backends.crsf.frames import (
    MAX_PAYLOAD,
    SYNC_FC,
    AccelGyro,
    Airspeed,
    Attitude,
    BaroAltitude,
    Battery,
    FlightMode,
    Gps,
    LinkStatistics,
    RcChannels,
    Rpm,
    Temperatures,
    UnknownFrame,
    Vario,
    Voltages,
    build_frame,
    crc,
    encode,
    encode_payload,
    flight_mode_text,
    pack_baro_altitude,
    wrap_angle,
)

GYRO_LSB = 2000 / 32767
ACCEL_LSB = 16 / 32767
SPEC = Path(__file__).resolve().parents[1].parent / "shared" / "specs" / "crsf.md"

#: The spec's vectors, by the label of their table row, as records.
SPEC_RECORDS: dict[str, Any] = {
    "Battery 3.3 V, 29.6 A, 1234 mAh, 67 %": Battery(3.3, 29.6, 1234, 67),
    "Attitude pitch/roll/yaw 11833/26092/−31398 (×1e-4 rad)": Attitude(1.1833, 2.6092, -3.1398),
    "GPS lat 56°, lon 163°, 58.7 km/h, 147.9°, 2345 m, 9 sats": Gps(56, 163, 58.7, 147.9, 2345,
                                                                    9),
    'Flight mode "ACRO*"': FlightMode("ACRO*"),
    "Vario +2.50 m/s": Vario(2.5),
    "Baro (ELRS form) 123.4 m, −1.50 m/s": BaroAltitude(123.4, -1.5),
    "Airspeed 90 km/h": Airspeed(90),
    "RPM source 0: 12000, −500": Rpm(0, (12000, -500)),
    "Temperature source 1: 25.0, −5.0 °C": Temperatures(1, (25.0, -5.0)),
    "ExpressLRS unit test: battery all zero": Battery(0, 0, 0, 0),
    "ExpressLRS unit test: attitude all zero": Attitude(0, 0, 0),
}


def spec_vectors() -> list[tuple[str, bytes]]:
    """(label, bytes) of every row of the spec's vector table; a missing spec is an error."""
    text = SPEC.read_text(encoding="utf-8")
    table = text.split("## Vectors", 1)[1]
    rows = re.findall(r"^\|\s*([^|]+?)\s*\|\s*`([0-9A-F ]+)`\s*\|\s*$", table, re.M)
    assert len(rows) >= 11, "the spec's vector table was not found"
    return [(label, bytes.fromhex(h)) for label, h in rows]


VECTORS = spec_vectors()


def close(a: Any, b: Any, tol: float = 1e-9) -> bool:
    if isinstance(a, tuple | list):
        return len(a) == len(b) and all(close(x, y, tol) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) or isinstance(b, float):
        return a is not None and b is not None and abs(a - b) <= tol
    return a == b


def records_close(a: Any, b: Any, tol: float = 1e-9) -> bool:
    return type(a) is type(b) and all(close(x, y, tol) for x, y in zip(a, b, strict=True))


# -- vectors -----------------------------------------------------------------------------------

@pytest.mark.parametrize(("label", "frame"), VECTORS, ids=[lbl for lbl, _ in VECTORS])
def test_spec_vector_decodes(label: str, frame: bytes) -> None:
    assert label in SPEC_RECORDS, f"a spec vector without an expected record: {label}"
    (rec,) = decode_all(frame)
    assert records_close(rec, SPEC_RECORDS[label]), rec


@pytest.mark.parametrize(("label", "frame"), VECTORS, ids=[lbl for lbl, _ in VECTORS])
def test_spec_vector_encodes(label: str, frame: bytes) -> None:
    assert encode(SPEC_RECORDS[label], sync=frame[0]) == frame


def test_crc_check_value_and_residue() -> None:
    assert crc(b"123456789") == 0xBC
    for _, frame in VECTORS:
        assert crc(frame[2:-1]) == frame[-1]
        assert crc(frame[2:]) == 0


# -- frame bounds ------------------------------------------------------------------------------

def test_frame_length_bounds() -> None:
    f = build_frame(0x7F, bytes(MAX_PAYLOAD))
    assert len(f) == 64 and f[1] == 62
    assert build_frame(0x7F, b"") == bytes((SYNC_FC, 2, 0x7F, crc(b"\x7f")))
    with pytest.raises(ValueError, match="exceeds"):
        build_frame(0x7F, bytes(MAX_PAYLOAD + 1))
    with pytest.raises(ValueError):
        build_frame(0x100, b"")
    with pytest.raises(ValueError, match="does not fit"):
        encode(FlightMode("x" * 60))
    assert len(encode(FlightMode("x" * 59))) == 64
    with pytest.raises(ValueError):
        encode(Temperatures(0, (1.0,) * 21))
    with pytest.raises(ValueError):
        encode(Voltages(0, (1.0,) * 30))
    with pytest.raises(ValueError):
        encode(Rpm(0, ()))
    with pytest.raises(ValueError):
        encode(RcChannels((0,) * 15))
    with pytest.raises(ValueError):
        encode(RcChannels((2048,) + (0,) * 15))
    with pytest.raises(TypeError):
        encode_payload("not a record")  # type: ignore[arg-type]


# -- the all-0xFF rule -------------------------------------------------------------------------

@pytest.mark.parametrize("rec", [
    Vario(-0.01), Vario(-0.005), Vario(-0.014), Attitude(-0.0001, -0.0001, -0.0001),
    Gps(-1e-7, -1e-7, 6553.5, 655.35, 64535, 255), Battery(6553.5, 6553.5, 2 ** 24 - 1, 255),
    Temperatures(0, (-0.1,)), Voltages(0, (65.535,)), Rpm(0, (-1,)), Airspeed(6553.5),
    BaroAltitude(50, -0.01), AccelGyro(2 ** 32 - 1, -GYRO_LSB, -GYRO_LSB, -GYRO_LSB,
                                       -ACCEL_LSB, -ACCEL_LSB, -ACCEL_LSB, -0.01),
], ids=lambda r: type(r).__name__)
def test_real_values_never_encode_as_all_ff(rec: Any) -> None:
    """EdgeTX ignores a field whose bytes are all 0xFF: real values are nudged off it, and
    decode back within one step."""
    (back,) = decode_all(encode(rec))
    assert type(back) is type(rec)
    assert None not in [v for v in back if not isinstance(v, tuple)]
    for v in back:
        if isinstance(v, tuple):
            assert None not in v


def test_nudge_goes_to_the_nearer_neighbour() -> None:
    (a,) = decode_all(encode(Vario(-0.0096)))  # −0.96 cm/s: nearer 0 than −2
    assert a.vspeed_mps == 0.0
    (b,) = decode_all(encode(Vario(-0.0104)))  # −1.04 cm/s: nearer −2
    assert b.vspeed_mps == -0.02


def test_unknown_values_encode_as_all_ff_and_decode_as_none() -> None:
    f = encode(Gps(None, None))
    assert f[3:18] == b"\xff" * 15
    (g,) = decode_all(f)
    assert g == Gps(None, None, None, None, None, None)
    (v,) = decode_all(encode(Vario(float("nan"))))
    assert v == Vario(None)
    (t,) = decode_all(encode(Temperatures(2, (None, 20.0))))
    assert t == Temperatures(2, (None, 20.0))


# -- angles and altitudes ----------------------------------------------------------------------

@given(st.floats(-1e6, 1e6))
def test_attitude_wraps_to_pi_and_never_overflows(a: float) -> None:
    (back,) = decode_all(encode(Attitude(a, -a, a * 3)))
    for sent, got in zip((a, -a, a * 3), back, strict=True):
        assert -math.pi - 1e-4 <= got <= math.pi + 1e-4
        assert abs(math.remainder(got - sent, 2 * math.pi)) <= 1.5e-4  # 1e6 rad loses digits


def test_wrap_angle() -> None:
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert wrap_angle(-3 * math.pi / 2) == pytest.approx(math.pi / 2)
    assert wrap_angle(0.3) == pytest.approx(0.3)
    assert math.isnan(wrap_angle(math.nan))


@pytest.mark.parametrize(("alt", "packed"), [
    (-2000.0, 0x0000), (-1000.0, 0x0000), (0.0, 10000), (123.4, 11234), (2276.7, 0x7FFF),
    (2276.8, 0x8000 | 2277), (2277.4, 0x8000 | 2277), (10000.0, 0x8000 | 10000),
    (32766.0, 0xFFFE), (40000.0, 0xFFFE), (None, 0xFFFF),
])
def test_baro_altitude_both_encodings_by_range(alt: float | None, packed: int) -> None:
    assert pack_baro_altitude(alt) == packed


def test_baro_without_vario_is_the_two_byte_form() -> None:
    f = encode(BaroAltitude(10.0))
    assert f[1] == 4 and f[3:5] == (10100).to_bytes(2, "big")
    assert decode_all(f) == [BaroAltitude(10.0, None)]


def test_gps_altitude_is_offset_and_not_clamped_at_5_km() -> None:
    f = encode(Gps(0.0, 0.0, altitude_m=12000))
    assert f[15:17] == (13000).to_bytes(2, "big")
    (g,) = decode_all(f)
    assert g.altitude_m == 12000.0


def test_flight_mode_text() -> None:
    assert flight_mode_text("IDLE", armed=False) == "IDLE*"
    assert flight_mode_text("BOOST", armed=True) == "BOOST"
    assert flight_mode_text("REDUNDANT", armed=False, marker="!BARO") == "REDUNDA!BARO*"
    assert flight_mode_text("ABCDEFGHIJKLMNOP", armed=True) == "ABCDEFGHIJKLM"
    assert flight_mode_text("IDLE", armed=False, disarmed_suffix="") == "IDLE"
    assert encode(FlightMode("ACRO*"))[-2] == 0  # the NUL EdgeTX needs to show the last char


# -- round trips over full ranges ------------------------------------------------------------

def opt(strategy: st.SearchStrategy[Any]) -> st.SearchStrategy[Any]:
    return st.one_of(st.none(), strategy)


def fl(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_nan=False)


RECORDS = st.one_of(
    st.builds(Gps, opt(fl(-214.7, 214.7)), opt(fl(-214.7, 214.7)), opt(fl(0, 6553.4)),
              opt(fl(0, 359.99)), opt(fl(-1000, 64534)), opt(st.integers(0, 254))),
    st.builds(Vario, opt(fl(-327.68, 327.67))),
    st.builds(Battery, opt(fl(0, 6553.4)), opt(fl(0, 6553.4)), opt(fl(0, 2 ** 24 - 2)),
              opt(st.integers(0, 100))),
    st.builds(BaroAltitude, opt(fl(-1000, 32766)), opt(fl(-327.68, 327.67))),
    st.builds(Airspeed, opt(fl(0, 6553.4))),
    st.builds(Rpm, st.integers(0, 255),
              st.lists(opt(st.integers(-(2 ** 23), 2 ** 23 - 1)), min_size=1, max_size=19)
              .map(tuple)),
    st.builds(Temperatures, st.integers(0, 255),
              st.lists(opt(fl(-3276.8, 3276.7)), max_size=20).map(tuple)),
    st.builds(Voltages, st.integers(0, 255), st.lists(opt(fl(0, 65.534)), max_size=29).map(tuple)),
    st.builds(AccelGyro, opt(st.integers(0, 2 ** 32 - 2)),
              *[opt(fl(-2000, 2000))] * 3, *[opt(fl(-16, 16))] * 3, opt(fl(-327.68, 327.67))),
    st.builds(Attitude, opt(fl(-3.1415, 3.1415)), opt(fl(-3.1415, 3.1415)),
              opt(fl(-3.1415, 3.1415))),
    st.builds(FlightMode, st.text(st.characters(min_codepoint=1, max_codepoint=127),
                                  max_size=59)),
    st.builds(LinkStatistics, st.integers(-255, 0), st.integers(-255, 0), st.integers(0, 255),
              st.integers(-128, 127), st.integers(0, 255), st.integers(0, 255),
              st.integers(0, 255), st.integers(-255, 0), st.integers(0, 255),
              st.integers(-128, 127)),
    st.builds(RcChannels, st.lists(st.integers(0, 2047), min_size=16, max_size=16).map(tuple)),
)

#: The resolution of each record's fields (half a step of rounding, one step when nudged).
STEP: dict[type, tuple[float, ...]] = {
    Gps: (1e-7, 1e-7, 0.1, 0.01, 1, 1), Vario: (0.01,), Battery: (0.1, 0.1, 1, 1),
    BaroAltitude: (0.1, 0.01), Airspeed: (0.1,), Attitude: (1e-4, 1e-4, 1e-4),
    AccelGyro: (1, 2000 / 32767, 2000 / 32767, 2000 / 32767, 16 / 32767, 16 / 32767,
                16 / 32767, 0.01),
}


def within(sent: Any, got: Any, step: float) -> bool:
    if sent is None:
        return got is None
    return got is not None and abs(got - sent) <= step * (1 + 1e-9) + 1e-9 * abs(sent)


@given(RECORDS)
def test_round_trip_every_frame_type(rec: Any) -> None:
    (back,) = decode_all(encode(rec))
    assert type(back) is type(rec)
    if isinstance(rec, Rpm):
        assert back.source_id == rec.source_id
        assert all(within(s, g, 1) for s, g in zip(rec.rpm, back.rpm, strict=True))
    elif isinstance(rec, Temperatures | Voltages):
        step = 0.1 if isinstance(rec, Temperatures) else 0.001
        values = rec[1]
        assert back.source_id == rec.source_id
        assert all(within(s, g, step) for s, g in zip(values, back[1], strict=True))
    elif isinstance(rec, BaroAltitude):
        alt_step = 0.1 if rec.altitude_m is None or rec.altitude_m < 2276.75 else 1.0
        assert within(rec.altitude_m, back.altitude_m, alt_step)
        assert within(rec.vspeed_mps, back.vspeed_mps, 0.01)
    elif isinstance(rec, FlightMode | LinkStatistics | RcChannels):
        assert back == rec
    else:
        for s, g, step in zip(rec, back, STEP[type(rec)], strict=True):
            assert within(s, g, step), (rec, back)
    # and the bytes round-trip exactly: decode → encode reproduces the frame
    assert encode(back) == encode(rec)


@given(st.integers(0x28, 0xFF), st.integers(0, 255), st.integers(0, 255),
       st.binary(max_size=58))
def test_extended_frames_keep_their_header(ftype: int, dest: int, origin: int,
                                           payload: bytes) -> None:
    rec = UnknownFrame(ftype, payload, dest, origin)
    assert decode_all(encode(rec)) == [rec]


def test_link_statistics_and_rc_channels_fields() -> None:
    ls = LinkStatistics(-52, -61, 100, 9, 1, 7, 3, -48, 99, -3)
    raw = encode(ls)
    assert raw[3:13] == bytes([52, 61, 100, 9, 1, 7, 3, 48, 99, 0xFD])
    assert ls.uplink_rssi_dbm == -61 and ls.uplink_tx_power_mw == 100
    assert LinkStatistics(0, 0, 0, 0, 0, 0, 9, 0, 0, 0).uplink_tx_power_mw is None
    rc = RcChannels((172, 992, 1811) + (992,) * 13)
    assert rc.microseconds()[:3] == (987.5, 1500.0, 2011.875)
