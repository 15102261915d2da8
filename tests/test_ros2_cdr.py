"""The CDR encoders, checked with an independent implementation: ``rosbags`` decodes each
encoder's bytes to the values given, and re-encodes the decoded message to the very same
bytes (so every alignment pad is where ROS 2 puts it)."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from backends.ros2 import cdr, types

TS = get_typestore(Stores.ROS2_JAZZY)
STAMP = 1_764_100_000_123_456_789
names = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",),
                              exclude_characters="\x00"), max_size=12)
finite = st.floats(allow_nan=False, allow_infinity=False)


def decode(data: bytes, ros_type: types.RosType) -> Any:
    msg = TS.deserialize_cdr(data, ros_type.name)
    assert TS.serialize_cdr(msg, ros_type.name) == data  # same bytes, pads included
    return msg


def stamp_of(header: Any) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


def test_encapsulation_header_is_plain_cdr_little_endian() -> None:
    for data in (cdr.string("x"), cdr.boolean(True), cdr.float64(1.0)):
        assert data[:4] == b"\x00\x01\x00\x00"
    assert cdr.without_header(cdr.float64(1.0)) == cdr.float64(1.0)[4:]


@given(names)
def test_string(text: str) -> None:
    assert decode(cdr.string(text), types.STRING).data == text


@pytest.mark.parametrize("value", [True, False])
def test_bool(value: bool) -> None:
    assert decode(cdr.boolean(value), types.BOOL).data is value


@given(st.floats(allow_nan=False))
def test_float64(value: float) -> None:
    assert decode(cdr.float64(value), types.FLOAT64).data == value


@given(names, finite, finite)
def test_imu(frame: str, qz: float, az: float) -> None:
    m = decode(cdr.imu(STAMP, frame, (0.1, 0.2, qz, 0.9), (0.0, 0.0, az)), types.IMU)
    assert stamp_of(m.header) == STAMP
    assert m.header.frame_id == frame
    assert (m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w) == (
        0.1, 0.2, qz, 0.9)
    assert m.linear_acceleration.z == az
    assert list(m.orientation_covariance) == [0.0] * 9      # known, covariance unknown
    assert m.angular_velocity_covariance[0] == -1.0         # not provided


def test_imu_with_angular_velocity() -> None:
    m = decode(cdr.imu(STAMP, "r", (0, 0, 0, 1), (0, 0, 0), angular_velocity=(1.0, 2.0, 3.0)),
               types.IMU)
    assert (m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z) == (1, 2, 3)
    assert list(m.angular_velocity_covariance) == [0.0] * 9


@given(st.lists(st.tuples(names, names, finite), max_size=3))
def test_tf_message(frames: list[tuple[str, str, float]]) -> None:
    tfs = [cdr.Transform(STAMP + i, parent, child, (1.0, 2.0, z), (0.0, 0.0, 0.6, 0.8))
           for i, (parent, child, z) in enumerate(frames)]
    m = decode(cdr.tf_message(tfs), types.TF_MESSAGE)
    assert len(m.transforms) == len(tfs)
    for got, want in zip(m.transforms, tfs, strict=True):
        assert stamp_of(got.header) == want.stamp_ns
        assert (got.header.frame_id, got.child_frame_id) == (want.parent, want.child)
        t, r = got.transform.translation, got.transform.rotation
        assert (t.x, t.y, t.z) == want.translation
        assert (r.x, r.y, r.z, r.w) == want.rotation


@given(names, st.sampled_from([-1, 0, 1, 2]), finite)
def test_nav_sat_fix(frame: str, status: int, alt: float) -> None:
    m = decode(cdr.nav_sat_fix(STAMP, frame, 47.5, -8.25, alt, status=status),
               types.NAV_SAT_FIX)
    assert m.header.frame_id == frame
    assert (m.status.status, m.status.service) == (status, cdr.SERVICE_GPS)
    assert (m.latitude, m.longitude, m.altitude) == (47.5, -8.25, alt)
    assert m.position_covariance_type == m.COVARIANCE_TYPE_UNKNOWN


@given(names, names)
def test_battery_state(frame: str, location: str) -> None:
    m = decode(cdr.battery_state(STAMP, frame, 7.5, current=-1.25, percentage=0.5,
                                 location=location), types.BATTERY_STATE)
    assert m.header.frame_id == frame
    assert (m.voltage, m.current, m.percentage) == (7.5, -1.25, 0.5)
    assert math.isnan(m.charge) and math.isnan(m.temperature)
    assert m.present is True
    assert m.location == location
    assert len(m.cell_voltage) == 0


@given(st.lists(st.tuples(st.integers(0, 3), names, names,
                          st.lists(st.tuples(names, names), max_size=3)), max_size=3))
def test_diagnostic_array(entries: list[tuple[int, str, str, list[tuple[str, str]]]]) -> None:
    statuses = [cdr.DiagnosticStatus(level, name, msg, "hw", tuple(values))
                for level, name, msg, values in entries]
    m = decode(cdr.diagnostic_array(STAMP, statuses), types.DIAGNOSTIC_ARRAY)
    assert stamp_of(m.header) == STAMP
    assert [(s.level, s.name, s.message, s.hardware_id,
             tuple((kv.key, kv.value) for kv in s.values)) for s in m.status] == [
        tuple(s) for s in statuses]
