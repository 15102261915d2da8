"""The router's framer against pymavlink-packed frames: whole, split anywhere, corrupted,
unknown, MAVLink 1 and signed."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from backends.mavlink.frames import FramerStats, StreamFramer, split, split_datagram
from dialects import aurora_mavlink as mav


def _packer(sysid: int = 3, compid: int = 1, *, signed: bool = False) -> mav.MAVLink:
    m = mav.MAVLink(None, sysid, compid)
    if signed:
        m.signing.secret_key = bytes(range(32))
        m.signing.link_id = 2
        m.signing.timestamp = 1000
        m.signing.sign_outgoing = True
    return m


def _pack(m: mav.MAVLink, msg: object) -> bytes:
    buf = msg.pack(m)  # type: ignore[attr-defined]
    m.seq = (m.seq + 1) % 256
    return buf


def sample_messages(rng: random.Random) -> list[object]:
    """A varied mix: broadcast, targeted (with targets in different places), extensions,
    strings, the Aurora messages."""
    r = rng.random
    return [
        mav.MAVLink_heartbeat_message(9, 0, 129, rng.randrange(9), 4, 3),
        mav.MAVLink_attitude_message(rng.randrange(2**32), r(), r(), r(), r(), r(), r()),
        mav.MAVLink_command_long_message(rng.randrange(256), rng.randrange(256), 512, 0,
                                         148, 0, 0, 0, 0, 0, 0),
        mav.MAVLink_command_ack_message(512, 0, 0, 0, rng.randrange(256), rng.randrange(256)),
        mav.MAVLink_param_request_list_message(rng.randrange(256), rng.randrange(256)),
        mav.MAVLink_statustext_message(5, b"#APOGEE", 0, 0),
        mav.MAVLink_mission_count_message(rng.randrange(256), 0, rng.randrange(5), 0),
        mav.MAVLink_aurora_status_message(rng.randrange(2**32), 4, 0, 0x1F, 0),
        mav.MAVLink_aurora_sm_update_message(7, 2, 1, 0, 0, r(), r(), r(), r(), r(), r(), r(),
                                             64),
    ]


def stream(seed: int, n: int = 40, *, signed: bool = False) -> tuple[bytes, list[bytes], list]:
    rng = random.Random(seed)
    p = _packer(signed=signed)
    frames, msgs = [], []
    for _ in range(n):
        msg = rng.choice(sample_messages(rng))
        frames.append(_pack(p, msg))
        msgs.append(msg)
    return b"".join(frames), frames, msgs


def _targets(msg: object) -> tuple[int, int]:
    ts = getattr(msg, "target_system", -1)
    tc = getattr(msg, "target_component", -1)
    return ts, tc


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), cuts=st.lists(st.integers(0, 4000), max_size=30),
       signed=st.booleans())
def test_any_split_gives_the_same_frames_as_pymavlink_packed(seed, cuts, signed) -> None:
    data, frames, msgs = stream(seed, signed=signed)
    f = StreamFramer()
    got = []
    last = 0
    for c in [*sorted({c % (len(data) + 1) for c in cuts}), len(data)]:
        got += f.feed(data[last:c])
        last = c
    assert [g.raw for g in got] == frames
    assert f.pending() == 0
    assert f.stats.crc_errors == f.stats.bytes_skipped == 0
    for g, msg in zip(got, msgs, strict=True):
        assert g.msgid == msg.get_msgId()  # type: ignore[attr-defined]
        assert (g.sysid, g.compid) == (3, 1)
        assert g.signed == signed and g.version == 2
        assert (g.target_system, g.target_component) == _targets(msg)
    assert [g.seq for g in got] == list(range(len(frames)))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 10**6), signed=st.booleans(), flip=st.integers(-1, 300))
def test_one_frame_per_datagram_reads_as_the_stream_framer_reads_it(seed, signed, flip) -> None:
    """split_datagram's shortcut for a datagram that is one frame agrees with the general
    splitter, frame for frame and counter for counter, on good frames and corrupted ones."""
    _, frames, _ = stream(seed, n=10, signed=signed)
    for frame in frames:
        data = bytearray(frame)
        if 0 <= flip < len(data):
            data[flip] ^= 0x41
        quick, general = FramerStats(), FramerStats()
        got = split_datagram(bytes(data), quick)
        want: list = []
        split(bytes(data), general, want)  # a datagram starts in sync
        assert got == want
        assert (quick.frames, quick.crc_errors, quick.bad_headers, quick.unknown_ids) == (
            general.frames, general.crc_errors, general.bad_headers, general.unknown_ids)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600))
def test_arbitrary_bytes_never_raise_and_only_valid_known_frames_come_out(data) -> None:
    f = StreamFramer()
    out = f.feed(data)
    d = FramerStats()
    out2 = split_datagram(data, d)
    decoder = mav.MAVLink(None)
    for g in out + out2:
        if g.msgid in mav.mavlink_map:  # CRC checked: pymavlink must agree it is a frame
            decoder.decode(bytearray(g.raw))
    assert f.pending() <= 280


def test_a_corrupt_frame_costs_one_byte_not_its_claimed_length() -> None:
    p = _packer()
    good1 = _pack(p, mav.MAVLink_heartbeat_message(9, 0, 0, 0, 3, 3))
    good2 = _pack(p, mav.MAVLink_attitude_message(1, 0.1, 0.2, 0.3, 0, 0, 0))
    # A false start marker whose length (28, plausible for ATTITUDE) would swallow good2 if
    # the framer skipped what a frame with a bad CRC claims.
    false_start = bytes([0xFD, 0x1C, 0x00, 0x00, 0x01, 0x02, 0x03, 0x1E, 0x00, 0x00])
    corrupt = bytearray(good1)
    corrupt[12] ^= 0x40  # a payload bit flipped: the CRC no longer matches
    data = good1 + bytes(corrupt) + false_start + good2 + good1
    for chunks in ([data], [data[i:i + 1] for i in range(len(data))]):
        f = StreamFramer()
        got = [g for c in chunks for g in f.feed(c)]
        assert [g.raw for g in got] == [good1, good2, good1]
        assert f.stats.crc_errors >= 2
        assert f.stats.bytes_skipped == len(corrupt) + len(false_start)


def test_unknown_ids_are_passed_on_unvalidated_and_counted() -> None:
    # id 50500: in no dialect we know; the CRC cannot be checked, the frame is still a frame
    body = bytes([0xFD, 3, 0, 0, 9, 42, 1]) + (50500).to_bytes(3, "little") + b"abc"
    frame = body + b"\x12\x34"
    p = _packer()
    hb = _pack(p, mav.MAVLink_heartbeat_message(9, 0, 0, 0, 3, 3))
    stats = FramerStats()
    got = split_datagram(frame + hb, stats)
    assert [g.raw for g in got] == [frame, hb]
    assert (got[0].msgid, got[0].sysid, got[0].compid, got[0].target_system) == (50500, 42, 1, -1)
    assert stats.unknown_ids == 1


def test_mavlink1_frames_and_truncated_datagrams() -> None:
    p = _packer(5, 7)
    v1 = mav.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(
        p, force_mavlink1=True)
    stats = FramerStats()
    (g,) = split_datagram(v1, stats)
    assert (g.version, g.msgid, g.sysid, g.compid, g.target_system, g.target_component) == (
        1, 76, 5, 7, 1, 1)
    assert split_datagram(v1[:-3], stats) == []
    assert stats.truncated == 1


def test_trimmed_trailing_zero_targets_read_as_broadcast() -> None:
    # MAVLink 2 trims trailing zero bytes: a COMMAND_ACK to 0/0 ends before its targets
    p = _packer()
    buf = _pack(p, mav.MAVLink_command_ack_message(512, 0, 0, 0, 0, 0))
    assert buf[1] < mav.MAVLink_command_ack_message.unpacker.size
    (g,) = split_datagram(buf, FramerStats())
    assert (g.target_system, g.target_component) == (0, 0)


@pytest.mark.parametrize("flag", [0x02, 0x80])
def test_unknown_incompat_flags_are_not_a_frame(flag: int) -> None:
    p = _packer()
    buf = bytearray(_pack(p, mav.MAVLink_heartbeat_message(9, 0, 0, 0, 3, 3)))
    buf[2] |= flag
    stats = FramerStats()
    assert split_datagram(bytes(buf), stats) == []
    assert stats.bad_headers == 1


def test_in_a_stream_unknown_ids_pass_only_in_sync() -> None:
    """Joined mid-stream or after corruption, an unknown-id "frame" could be anything: the
    framer waits for a CRC-valid frame before it passes unvalidated ones on again."""
    unknown = bytes([0xFD, 3, 0, 0, 9, 42, 1]) + (50500).to_bytes(3, "little") + b"abc\x12\x34"
    p = _packer()
    hb = _pack(p, mav.MAVLink_heartbeat_message(9, 0, 0, 0, 3, 3))
    bad = bytearray(hb)
    bad[-1] ^= 1
    f = StreamFramer()
    got = f.feed(unknown + hb + unknown + bytes(bad) + unknown + hb + unknown)
    assert [g.raw for g in got] == [hb, unknown, hb, unknown]
    assert f.stats.unknown_ids == 2
    assert f.stats.bytes_skipped == 2 * len(unknown) + len(bad)
