"""F´ telemetry packets: the spec's vector, "no room left", time tags, the channel table."""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from backends.fprime.channels import (
    ALTITUDE,
    ARMED,
    CHANNELS,
    DEFAULT_ID_BASE,
    MODE_CH,
    STATE_CH,
    WRITERS,
    ChannelCodec,
    codecs,
)
from backends.fprime.packets import (
    DESCRIPTOR,
    ENTRY_HEADER_SIZE,
    FW_PACKET_TELEM,
    RESYNC_S,
    TB_PROC_TIME,
    TB_WORKSTATION_TIME,
    TlmPacker,
    UpdateClock,
)
from gateway.model import SmUpdate, VehicleState

# shared/specs/fprime.md, "Vector": two channels at t = 1700000000.250000, workstation time
SPEC_PACKET = bytes.fromhex(
    "0001 00000100 0002 00 6553f100 0003d090 42f70000"
    " 00000101 0002 00 6553f100 0003d090 03".replace(" ", ""))
SPEC_TAG = (TB_WORKSTATION_TIME, 0, 1700000000, 250000)


def test_the_spec_vector() -> None:
    altitude = ChannelCodec(ALTITUDE, 256).entry(123.5, SPEC_TAG)
    state = ChannelCodec(STATE_CH, 257).entry(3, SPEC_TAG)
    assert altitude is not None and state is not None
    assert TlmPacker().pack([altitude, state]) == [SPEC_PACKET]


def test_the_default_id_base_puts_altitude_and_state_where_the_spec_has_them() -> None:
    c = {codec.channel: codec.id for rows in codecs().values() for codec, _ in rows}
    assert c[ALTITUDE] == 256 and c[STATE_CH] == 257
    c2 = {codec.channel: codec.id for rows in codecs(0x2000).values() for codec, _ in rows}
    assert c2[ALTITUDE] == 0x2000 and c2[STATE_CH] == 0x2001


def entries(sizes: list[int]) -> list[bytes]:
    return [bytes([i % 251]) * n for i, n in enumerate(sizes)]


@settings(max_examples=150, deadline=None)
@given(sizes=st.lists(st.integers(ENTRY_HEADER_SIZE + 1, 120), max_size=40),
       buffer_size=st.integers(40, 600))
def test_no_room_left_starts_the_next_packet_with_the_rejected_entry(
        sizes: list[int], buffer_size: int) -> None:
    packer = TlmPacker(buffer_size)
    items = entries(sizes)
    packets = packer.pack(items)
    room = buffer_size - DESCRIPTOR.size
    fitting = [e for e in items if len(e) <= room]
    assert packer.too_big == len(items) - len(fitting)
    # every packet: the descriptor, whole entries, within the buffer; in order; nothing lost
    assert all(p[:2] == DESCRIPTOR.pack(FW_PACKET_TELEM) for p in packets)
    assert all(len(p) <= buffer_size for p in packets)
    assert b"".join(p[2:] for p in packets) == b"".join(fitting)
    # a packet ends only where the next entry would not have fitted ("no room left")
    i = 0
    for p in packets:
        used = 0
        while i < len(fitting) and used + len(fitting[i]) <= room:
            used += len(fitting[i])
            i += 1
        assert len(p) - 2 == used
    assert i == len(fitting)


def test_a_bool_is_0xff_or_0x00_and_missing_values_are_not_written() -> None:
    tag = SPEC_TAG
    codec = ChannelCodec(ARMED, 258)
    assert codec.entry(0xFF, tag)[-1:] == b"\xff"  # type: ignore[index]
    armed_getter = dict(WRITERS[SmUpdate])[ARMED]
    update = SmUpdate(0, 2, True, 0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert armed_getter(update) == 0xFF
    assert armed_getter(update._replace(armed=False)) == 0
    assert ChannelCodec(ALTITUDE, 256).entry(None, tag) is None
    assert ChannelCodec(ALTITUDE, 256).entry(math.nan, tag) is None
    assert ChannelCodec(ALTITUDE, 256).entry(math.inf, tag) is None


def test_a_string_channel_is_a_u16_length_then_its_bytes_cut_to_size() -> None:
    codec = ChannelCodec(MODE_CH, 0x150)
    e = codec.entry("LOITER", SPEC_TAG)
    assert e is not None and e[15:] == struct.pack(">H", 6) + b"LOITER"
    long = codec.entry("X" * 100, SPEC_TAG)
    assert long is not None and long[15:17] == struct.pack(">H", MODE_CH.type.size)
    vs = VehicleState(armed=True, mode="GUIDED")
    written = [ch for ch, get in WRITERS[VehicleState] if get(vs) is not None]
    assert MODE_CH in written and ALTITUDE not in written


def test_the_channel_table_has_unique_ids_and_names() -> None:
    assert len({c.offset for c in CHANNELS}) == len(CHANNELS)
    assert len({c.full_name() for c in CHANNELS}) == len(CHANNELS)
    for rows in WRITERS.values():
        for ch, _ in rows:
            assert ch in CHANNELS


class FakeClock:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def test_proc_time_is_the_flight_computers_uptime() -> None:
    clock = UpdateClock(TB_PROC_TIME, 3)
    assert clock.tag(123_456) == (TB_PROC_TIME, 3, 123, 456_000)


def test_workstation_time_keeps_the_flight_computers_spacing_and_resyncs_on_a_jump() -> None:
    wall = FakeClock(1_700_000_000.0)
    clock = UpdateClock(TB_WORKSTATION_TIME, 0, clock=wall)
    first = clock.tag(10_000)
    assert first == (TB_WORKSTATION_TIME, 0, 1_700_000_000, 0)
    wall.t += 0.137  # the update arrived late: its own 10 ms spacing is kept
    assert clock.tag(10_010) == (TB_WORKSTATION_TIME, 0, 1_700_000_000, 10_000)
    wall.t += 1.0  # a replay at 10x: the uptime runs ahead of the clock, spacing kept
    assert clock.tag(20_010) == (TB_WORKSTATION_TIME, 0, 1_700_000_010, 10_000)
    assert clock.resyncs == 0
    wall.t += 30 + RESYNC_S  # a gap: the updates stamped far behind the clock
    t = clock.tag(20_020)
    assert (t[2], t[3]) == (int(wall.t), round(wall.t % 1 * 1e6)) and clock.resyncs == 1
    wall.t += 1.0
    t = clock.tag(5)  # the board rebooted: its uptime went back
    assert (t[2], t[3]) == (int(wall.t), round(wall.t % 1 * 1e6)) and clock.resyncs == 2
    assert clock.tag() == (TB_WORKSTATION_TIME, 0, int(wall.t), round(wall.t % 1 * 1e6))


def test_the_readme_lists_every_channel_with_its_default_id() -> None:
    readme = (Path(__file__).resolve().parents[1] / "backends" / "fprime" / "README.md")
    section = readme.read_text().split("## Channels", 1)[1].split("\n## ", 1)[0]
    listed = {name: int(i) for i, name in re.findall(r"^\| (\d+) \| `([\w.]+)` \|", section,
                                                      re.M)}
    assert listed == {c.full_name(): DEFAULT_ID_BASE + c.offset for c in CHANNELS}
