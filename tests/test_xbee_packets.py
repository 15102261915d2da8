"""XBee link packets: the spec's servo vector both ways, the command bit stream against a
bit-by-bit reference written here, round trips of every packet type, telemetry resolution,
grouping several packets in one payload, and malformed packets rejected with the right error
(a fuzz invariant: any bytes decode to a packet that re-encodes to them, or raise
PacketError)."""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from backends.xbee.packets import (
    MAX_PACKET,
    Ack,
    BadPacketField,
    BadPacketLength,
    Command,
    Packet,
    PacketError,
    Ping,
    SmTelemetry,
    Stats,
    StatusTelemetry,
    UnknownPacketType,
    decode,
    encode,
    encode_many,
    group,
    iter_decode,
    next_seq,
    packet_length,
    seq_gap,
)
from gateway.model import SmUpdate, Status

SPEC = Path(__file__).resolve().parents[1].parent / "shared" / "specs" / "xbee.md"

# Sizes and resolutions as the module docstring's table states them (the README copies it).
SIZES = {Ack: 2, Ping: 2, Stats: 15, SmTelemetry: 24, StatusTelemetry: 9}
TYPES = {Ack: 0x40, Ping: 0x41, Stats: 0x42, SmTelemetry: 0x43, StatusTelemetry: 0x44}
ALT_STEP, VEL_STEP, ACC_STEP, ANG_STEP = 0.1, 0.1, 0.1, 0.0001


def spec_servo_vector() -> bytes:
    text = SPEC.read_text(encoding="utf-8")
    m = re.search(r"seq 0, power 2 →\s*`([0-9a-f ]+)`", text)
    assert m, "the spec's servo packet vector was not found"
    return bytes.fromhex(m[1])


def test_spec_servo_vector_both_ways() -> None:
    raw = spec_servo_vector()
    cmd = Command.from_servos({0: 0x123, 2: 0x234}, seq=0, power=2)
    assert cmd.mask == 0x05
    assert encode(cmd) == raw
    assert decode(raw) == cmd
    assert decode(raw).servos == {0: 0x123, 2: 0x234}  # type: ignore[union-attr]


def reference_command(mask: int, seq: int, power: int, values: list[int]) -> bytes:
    """The spec's definition, one bit at a time: type byte, then seq (5), power (3), each
    value (10) MSB first, zero padding to a whole byte."""
    bits = f"{seq:05b}{power:03b}" + "".join(f"{v:010b}" for v in values)
    bits += "0" * (-len(bits) % 8)
    return bytes([mask]) + bytes(int(bits[i:i + 8], 2) for i in range(0, len(bits), 8))


seqs = st.integers(0, 31)
powers = st.integers(0, 4)


@st.composite
def commands(draw: st.DrawFn) -> Command:
    mask = draw(st.integers(0, 0x3F))
    values = tuple(draw(st.lists(st.integers(0, 0x3FF), min_size=mask.bit_count(),
                                 max_size=mask.bit_count())))
    return Command(draw(seqs), draw(powers), mask, values)


@settings(max_examples=200, deadline=None)
@given(commands())
def test_command_matches_the_bitwise_reference(cmd: Command) -> None:
    raw = reference_command(cmd.mask, cmd.seq, cmd.power, list(cmd.values))
    assert encode(cmd) == raw
    assert decode(raw) == cmd
    assert packet_length(cmd.mask) == len(raw) <= 10


def test_keep_alive_is_two_bytes() -> None:
    assert encode(Command(seq=9, power=3)) == bytes([0x00, 9 << 3 | 3])


# -- round trips ------------------------------------------------------------------------------

def on_grid(step: float, bits: int) -> st.SearchStrategy[float]:
    scale = round(1 / step)
    top = (1 << (bits - 1)) - 1
    return st.one_of(st.integers(-top, top).map(lambda k: k / scale), st.just(math.nan))


u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)


def opt(s: st.SearchStrategy[int]) -> st.SearchStrategy[int | None]:
    return st.one_of(st.none(), s)


packets: st.SearchStrategy[Packet] = st.one_of(
    commands(),
    st.builds(Ack, seqs, powers),
    st.builds(Ping, seqs, powers),
    st.builds(Stats, seqs, powers, opt(st.integers(-255, 0)), opt(u16), opt(u16), opt(u16),
              opt(u16), opt(st.integers(0, 100)), u16),
    st.builds(SmTelemetry, seqs, powers, u32, u8, u8, st.booleans(),
              on_grid(ALT_STEP, 24), on_grid(VEL_STEP, 16), on_grid(ACC_STEP, 16),
              on_grid(ACC_STEP, 16), on_grid(ANG_STEP, 16), on_grid(ANG_STEP, 16),
              on_grid(ANG_STEP, 16)),
    st.builds(StatusTelemetry, seqs, powers, u32, u8, u8, u8),
)


def same(a: Any, b: Any) -> bool:
    """Equal records, NaN equal to NaN."""
    return type(a) is type(b) and all(
        (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))
        or x == y for x, y in zip(a, b, strict=True))


@settings(max_examples=200, deadline=None)
@given(packets)
def test_every_packet_round_trips(p: Packet) -> None:
    raw = encode(p)
    assert same(decode(raw), p)
    assert raw[1] == p.seq << 3 | p.power  # the common header
    if not isinstance(p, Command):
        assert raw[0] == TYPES[type(p)] and len(raw) == SIZES[type(p)]
    assert len(raw) <= MAX_PACKET


@settings(max_examples=150, deadline=None)
@given(st.lists(packets, max_size=8))
def test_grouped_packets_split_back(ps: list[Packet]) -> None:
    out = list(iter_decode(encode_many(ps)))
    assert len(out) == len(ps) and all(same(a, b) for a, b in zip(out, ps, strict=True))


def _flip(p: Packet, index: int, mask: int) -> bytes:
    raw = bytearray(encode(p))
    raw[index % len(raw)] ^= mask
    return bytes(raw)


# random bytes, and valid packets with one byte damaged (most of those still parse)
damaged = st.builds(_flip, packets, st.integers(0, 30), st.integers(1, 0xFF))


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.binary(max_size=30), damaged))
def test_any_bytes_decode_canonically_or_raise_packet_error(data: bytes) -> None:
    try:
        p = decode(data)
    except PacketError:
        return
    assert encode(p) == data


# -- telemetry values -------------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(st.floats(-838_000, 838_000), st.floats(-3000, 3000), st.floats(-3000, 3000),
       st.floats(-3000, 3000), st.floats(-3.2, 3.2), st.floats(-3.2, 3.2), st.floats(-3.2, 3.2))
def test_telemetry_is_within_half_a_step(alt: float, vel: float, acc: float, acc_v: float,
                                         roll: float, pitch: float, yaw: float) -> None:
    p = SmTelemetry(1, 2, 1234, 3, 0, True, alt, vel, acc, acc_v, roll, pitch, yaw)
    q = decode(encode(p))
    assert isinstance(q, SmTelemetry)
    tol = 1e-9
    assert abs(q.altitude_m - alt) <= ALT_STEP / 2 + tol
    assert abs(q.velocity_mps - vel) <= VEL_STEP / 2 + tol
    assert abs(q.acceleration_mps2 - acc) <= ACC_STEP / 2 + tol
    assert abs(q.accel_vert_mps2 - acc_v) <= ACC_STEP / 2 + tol
    for got, want in ((q.roll_rad, roll), (q.pitch_rad, pitch), (q.yaw_rad, yaw)):
        assert abs(got - want) <= ANG_STEP / 2 + tol


@settings(max_examples=100, deadline=None)
@given(st.floats(-1e4, 1e4).filter(lambda a: abs(a) > 3.2767))
def test_angle_beyond_the_field_is_wrapped(a: float) -> None:
    p = SmTelemetry(0, 0, 0, 0, 0, False, 0.0, 0.0, 0.0, 0.0, a, 0.0, 0.0)
    q = decode(encode(p))
    assert isinstance(q, SmTelemetry)
    assert -math.pi - ANG_STEP <= q.roll_rad <= math.pi + ANG_STEP
    # the same direction: the difference is a whole number of turns
    turns = (a - q.roll_rad) / (2 * math.pi)
    assert abs(turns - round(turns)) * 2 * math.pi <= ANG_STEP / 2 + 1e-9 * max(1.0, abs(a))


def test_out_of_range_clamps_and_nan_survives() -> None:
    p = SmTelemetry(0, 0, 0, 0, 0, False, 1e9, -1e9, math.inf, -math.inf, math.nan, 0.0, 0.0)
    q = decode(encode(p))
    assert isinstance(q, SmTelemetry)
    assert q.altitude_m == pytest.approx(((1 << 23) - 1) * ALT_STEP)
    assert q.velocity_mps == pytest.approx(-((1 << 15) - 1) * VEL_STEP)
    assert q.acceleration_mps2 == pytest.approx(((1 << 15) - 1) * ACC_STEP)
    assert q.accel_vert_mps2 == pytest.approx(-((1 << 15) - 1) * ACC_STEP)
    assert math.isnan(q.roll_rad)


def test_sm_update_and_status_conversions() -> None:
    msg = SmUpdate(123456, 2, True, 0, 1234.56, 98.07, 95.3, 210.04, 0.1, 1.48, 0.6)
    p = SmTelemetry.from_sm_update(msg, seq=7, power=3)
    back = decode(encode(p))
    assert isinstance(back, SmTelemetry) and (back.seq, back.power) == (7, 3)
    m2 = back.to_sm_update(origin="xbee")
    assert m2.origin == "xbee"
    assert (m2.timestamp_ms, m2.state, m2.armed, m2.sm_type) == (123456, 2, True, 0)
    for name, step in (("altitude_m", ALT_STEP), ("velocity_mps", VEL_STEP),
                       ("acceleration_mps2", ACC_STEP), ("accel_vert_mps2", ACC_STEP),
                       ("roll_rad", ANG_STEP), ("pitch_rad", ANG_STEP), ("yaw_rad", ANG_STEP)):
        assert abs(getattr(m2, name) - getattr(msg, name)) <= step / 2 + 1e-9, name
    status = Status(5000, 1, 0, Status.make_flags(armed=True, baro_ok=True))
    s = decode(encode(StatusTelemetry.from_status(status, seq=1, power=4)))
    assert isinstance(s, StatusTelemetry)
    assert s.to_status().fields() == status.fields()


# -- grouping and sequence numbers ------------------------------------------------------------

@settings(max_examples=150, deadline=None)
@given(st.lists(st.binary(min_size=1, max_size=24), max_size=20), st.integers(24, 100))
def test_group_fills_payloads_in_order(chunks: list[bytes], limit: int) -> None:
    out = group(chunks, limit)
    assert b"".join(out) == b"".join(chunks)
    assert all(0 < len(g) <= limit for g in out)
    # greedy: the first chunk of each next payload did not fit in the one before
    sizes = [len(c) for c in chunks]
    k = 0
    for i, g in enumerate(out):
        n = 0
        while k < len(sizes) and n + sizes[k] <= len(g):
            n += sizes[k]
            k += 1
        assert n == len(g)
        if i + 1 < len(out):
            assert len(g) + sizes[k] > limit


def test_group_rejects_an_oversized_packet() -> None:
    with pytest.raises(ValueError):
        group([bytes(30)], 24)


def test_sequence_helpers() -> None:
    assert next_seq(30) == 31 and next_seq(31) == 0
    assert seq_gap(5, 6) == 0 and seq_gap(30, 1) == 2 and seq_gap(3, 3) == 31


# -- malformed packets ------------------------------------------------------------------------

SM = encode(SmTelemetry(1, 1, 1, 1, 0, True, 1.0, 1.0, 1.0, 1.0, 0.1, 0.2, 0.3))
STATS = encode(Stats(1, 1, -60, 1, 2, 3, 4, 5, 6))


def _case(raw: bytes, error: type[PacketError], name: str) -> Any:
    return pytest.param(raw, error, id=name)


@pytest.mark.parametrize(("raw", "error"), [
    _case(b"", BadPacketLength, "empty"),
    _case(b"\x45\x00", UnknownPacketType, "type-0x45"),
    _case(b"\xff", UnknownPacketType, "type-0xff"),
    _case(b"\x40", BadPacketLength, "ack-short"),
    _case(b"\x40\x00\x00", BadPacketLength, "ack-long"),
    _case(b"\x41", BadPacketLength, "ping-short"),
    _case(STATS[:-1], BadPacketLength, "stats-short"),
    _case(STATS + b"\x00", BadPacketLength, "stats-long"),
    _case(SM[:-1], BadPacketLength, "sm-short"),
    _case(SM + b"\x00", BadPacketLength, "sm-long"),
    _case(b"\x44" + bytes(7), BadPacketLength, "status-short"),
    _case(bytes.fromhex("05 02 48 e3"), BadPacketLength, "command-short"),
    _case(bytes.fromhex("05 02 48 e3 40 00"), BadPacketLength, "command-long"),
    _case(bytes.fromhex("05 02 48 e3 41"), BadPacketField, "command-padding-set"),
    _case(bytes([0x40, 0 << 3 | 5]), BadPacketField, "ack-power-5"),
    _case(bytes([0x00, 3 << 3 | 7]), BadPacketField, "keepalive-power-7"),
    _case(bytes([0x42, 0x08, 0x40]) + bytes(12), BadPacketField, "stats-undefined-bit"),
    _case(bytes([0x42, 0x08, 0x00, 0x3C]) + bytes(11), BadPacketField, "stats-rssi-no-bit"),
    _case(bytes([0x42, 0x08, 0x20, 0x00]) + bytes(8) + b"\x65\x00\x00", BadPacketField,
          "stats-duty-101"),
    _case(SM[:8] + b"\x03" + SM[9:], BadPacketField, "sm-undefined-flag"),
])
def test_malformed_packets_raise_the_right_error(raw: bytes, error: type[PacketError]) -> None:
    with pytest.raises(error) as info:
        decode(raw)
    assert isinstance(info.value, ValueError) and str(info.value)


def test_grouped_payload_stops_at_the_first_bad_packet() -> None:
    good = encode(Ack(3, 1))
    it = iter_decode(good + b"\x45\x00" + good)
    assert next(it) == Ack(3, 1)
    with pytest.raises(UnknownPacketType):
        next(it)
    it = iter_decode(good + SM[:10])
    assert next(it) == Ack(3, 1)
    with pytest.raises(BadPacketLength):
        next(it)


@pytest.mark.parametrize("bad", [
    Ack(32, 0), Ack(0, 5), Ping(-1, 0), Command(0, 0, 0x40, ()), Command(0, 0, 0x01, ()),
    Command(0, 0, 0x01, (1024,)), Stats(0, 0, rssi_dbm=1), Stats(0, 0, duty_cycle_pct=101),
    Stats(0, 0, commands_rx=0x10000), StatusTelemetry(0, 0, 2**32, 0, 0, 0),
    SmTelemetry(0, 0, 0, 256, 0, False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
])
def test_encode_rejects_fields_out_of_range(bad: Packet) -> None:
    with pytest.raises(BadPacketField):
        encode(bad)


def test_from_servos_rejects_an_index_beyond_five() -> None:
    with pytest.raises(BadPacketField):
        Command.from_servos({6: 1}, 0, 0)
