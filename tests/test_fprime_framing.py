"""F´ framings checked against fprime-gds 4.4.1's own framers and deframers.

Downlink: what our framers write, fprime-gds's deframers (``FpFramerDeframer``, the default
``space-packet-space-data-link`` chain) read back exactly, in order, with garbage before and a
partial frame after, printing no warning (so frame and sequence counts run on and the First
Header Pointers agree with the packets).  A small TM parser written here from the CCSDS layout
checks every header field besides.  Uplink: what fprime-gds's framers (and its ip adapter's
keep-alive) write, our deframers read, with garbage in between, in any split.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import logging
import random
import struct
import zlib
from collections.abc import Iterator, Sequence
from typing import Any

import pytest
from fprime_gds.common.communication.ccsds.chain import SpacePacketSpaceDataLinkFramerDeframer
from fprime_gds.common.communication.ccsds.space_data_link import SpaceDataLinkFramerDeframer
from fprime_gds.common.communication.framing import FpFramerDeframer
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from backends.fprime.framing import (
    DEFAULT_FRAMING,
    FRAMINGS,
    KEEPALIVE,
    CcsdsFramer,
    FprimeDeframer,
    FprimeFramer,
    TcDeframer,
    crc16_ccitt,
    make_deframer,
    make_framer,
)

# shared/specs/fprime.md, "Vector"
SPEC_PACKET = bytes.fromhex(
    "0001 00000100 0002 00 6553f100 0003d090 42f70000"
    " 00000101 0002 00 6553f100 0003d090 03".replace(" ", ""))
SPEC_FRAME = bytes.fromhex("deadbeef 00000025".replace(" ", "")) + SPEC_PACKET \
    + bytes.fromhex("412c14df")

# Bytes no fprime-gds deframer can take for a frame start (no 0xDE, no SCID 0x44 / VCID 1 pair
# in any window, including the one joining them to a frame), so it warns about nothing.
GARBAGE = b"\xffnoise\x01\x02 before the stream\xfe"

CCITT = SpaceDataLinkFramerDeframer.CCITT_CRC_FUNCTION  # fprime-gds's crcmod CRC-16
SCID, VCID = 0x44, 1
SP_HEADER = 6


@contextlib.contextmanager
def gds_warnings() -> Iterator[list[str]]:
    """Collect what fprime-gds warns about: ``[WARNING]`` lines on stderr and the ``framing``
    logger's records."""
    found: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            found.append(record.getMessage())

    logger = logging.getLogger("framing")
    handler = Collect(logging.WARNING)
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING)
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            yield found
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        found.extend(line for line in err.getvalue().splitlines() if line.strip())


def their_tm(frame_size: int = 1024) -> Any:
    return SpacePacketSpaceDataLinkFramerDeframer(scid=SCID, vcid=VCID, frame_size=frame_size)


def deframe(deframer: Any, chunks: Sequence[bytes]) -> tuple[list[bytes], bytes, bytes]:
    """Feed ``chunks`` to a fprime-gds deframer as its downlinker does (pool kept between)."""
    packets: list[bytes] = []
    pool = b""
    discarded = b""
    for chunk in chunks:
        found, pool, dropped = deframer.deframe_all(pool + chunk, False)
        packets += [bytes(p) for p in found]
        discarded += bytes(dropped)
    return packets, bytes(pool), discarded


def split(data: bytes, sizes: Sequence[int]) -> list[bytes]:
    chunks, i, k = [], 0, 0
    while i < len(data):
        n = sizes[k % len(sizes)]
        chunks.append(data[i:i + n])
        i += n
        k += 1
    return chunks


def packet(descriptor: int, size: int, seed: int = 0) -> bytes:
    """An F´ packet of ``size`` bytes: U16 descriptor then filler."""
    rng = random.Random(seed * 7919 + size)
    return descriptor.to_bytes(2, "big") + rng.randbytes(size - 2)


def parse_tm(data: bytes, frame_size: int, first_count: int = 0) -> list[tuple[int, int, bytes]]:
    """Independent TM parser: check every frame's fields, return (APID, count, data) per
    Space Packet (idle ones included), reassembled across frames."""
    assert len(data) % frame_size == 0
    field_size = frame_size - 8
    stream = b""
    pointers = []
    for k in range(len(data) // frame_size):
        frame = data[k * frame_size:(k + 1) * frame_size]
        frame_id, mc, vc, status = struct.unpack_from(">HBBH", frame)
        assert frame_id >> 14 == 0 and (frame_id >> 4) & 0x3FF == SCID
        assert (frame_id >> 1) & 7 == VCID and frame_id & 1 == 0  # no OCF
        assert mc == vc == (first_count + k) % 256
        assert status >> 11 == 0b00011
        assert int.from_bytes(frame[-2:], "big") == CCITT(frame[:-2])
        pointers.append(status & 0x7FF)
        stream += frame[6:-2]
    starts = []
    out = []
    offset = 0
    while offset < len(stream):
        pid, seq, length = struct.unpack_from(">HHH", stream, offset)
        assert pid >> 11 == 0  # version 0, type TM, no secondary header
        assert seq >> 14 == 0b11
        starts.append(offset)
        end = offset + SP_HEADER + length + 1
        assert end <= len(stream)
        out.append((pid & 0x7FF, seq & 0x3FFF, stream[offset + SP_HEADER:end]))
        offset = end
    for k, fhp in enumerate(pointers):
        inside = [s - k * field_size for s in starts if k * field_size <= s < (k + 1) * field_size]
        assert fhp == (inside[0] if inside else 0x7FF)
    return out


def frames_needed(sizes: Sequence[int], field_size: int) -> int:
    """The fill rule for one call's packets of ``sizes`` bytes: whole frames, idle fill of 0 or
    at least 7 bytes (header + 1), and the last frame starts a packet (fprime-gds completes a
    spanning packet only at the next packet header)."""
    sp = [n + SP_HEADER for n in sizes]
    total = sum(sp)
    k = -(-total // field_size)
    room = k * field_size - total
    if 0 < room < SP_HEADER + 1:
        return k + 1
    if room == 0 and total - sp[-1] < (k - 1) * field_size:
        return k + 1
    return k


# ---------------------------------------------------------------------------------- fprime


def test_fprime_spec_vector_both_ways() -> None:
    ours = FprimeFramer()
    frame = ours.frame([SPEC_PACKET])
    assert frame == SPEC_FRAME
    assert frame == bytes(FpFramerDeframer().frame(SPEC_PACKET))
    assert (ours.frames, ours.packets) == (1, 1)
    with gds_warnings() as warnings:
        packets, rest, discarded = deframe(FpFramerDeframer(), [GARBAGE + frame + frame[:9]])
    assert packets == [SPEC_PACKET]
    assert rest == frame[:9] and discarded == GARBAGE
    assert warnings == []


def test_fprime_several_packets_in_chunks() -> None:
    sent = [packet(1, n, n) for n in (2, 3, 50, 512, 4000)]
    data = FprimeFramer().frame(sent)
    assert len(data) == sum(len(p) + 12 for p in sent)
    with gds_warnings() as warnings:
        packets, rest, _ = deframe(FpFramerDeframer(), split(GARBAGE + data, [1, 7, 100, 3]))
    assert packets == sent and rest == b"" and warnings == []
    assert FprimeFramer().frame([]) == b""


# ----------------------------------------------------------------------------------- ccsds


def check_ccsds(calls: Sequence[Sequence[bytes]], frame_size: int = 1024,
                chunks: Sequence[int] = (100_000,)) -> bytes:
    """Frame ``calls`` with one framer; fprime-gds must recover every packet in order, warning
    about nothing, from the stream with garbage before and a partial frame after."""
    framer = CcsdsFramer(SCID, VCID, frame_size)
    field_size = frame_size - 8
    data = b""
    for call in calls:
        out = framer.frame(call)
        sizes = [len(p) for p in call]
        assert len(out) == frame_size * (frames_needed(sizes, field_size) if call else 0)
        data += out
    sent = [p for call in calls for p in call]
    assert framer.frames * frame_size == len(data) and framer.packets == len(sent)
    assert framer.frames * field_size == sum(len(p) + SP_HEADER for p in sent) + framer.idle_bytes
    # independent parse: APIDs, per-APID counts, pointers, frame counts, CRCs
    parsed = parse_tm(data, frame_size)
    assert [d for apid, _, d in parsed if apid != 0x7FF] == sent
    expected_count: dict[int, int] = {}
    for apid, count, body in parsed:
        assert count == expected_count.get(apid, 0)
        expected_count[apid] = (count + 1) % 16384
        if apid != 0x7FF:
            assert apid == int.from_bytes(body[:2], "big")
    partial = data[:frame_size // 2] if data else b""
    with gds_warnings() as warnings:
        packets, rest, discarded = deframe(their_tm(frame_size),
                                           split(GARBAGE + data + partial, chunks))
    assert packets == sent
    assert rest == partial and discarded == GARBAGE
    assert warnings == []
    return data


def test_ccsds_several_packets_per_frame() -> None:
    calls = [[packet(1, 40, i) for i in range(5)], [packet(2, 30), packet(1, 100)], []]
    data = check_ccsds(calls)
    assert len(data) == 2 * 1024


def test_ccsds_packets_span_two_and_three_frames() -> None:
    field = 1016
    two = packet(1, field + 300)
    three = packet(1, 2 * field + 100)
    check_ccsds([[two], [three], [packet(1, 20), three, two, packet(4, 5)]])
    # exactly filling frames: no idle packet when the last frame starts a packet...
    framer = CcsdsFramer()
    fits = [packet(1, field - SP_HEADER), packet(1, 500), packet(1, field - 500 - 2 * SP_HEADER)]
    assert len(framer.frame(fits)) == 2 * 1024 and framer.idle_bytes == 0
    # ...but a spanning packet ending a frame gets a frame of idle after it, or fprime-gds
    # would hold it until the next call's frames: it must come out of these frames alone
    exact = packet(1, 2 * field - SP_HEADER)
    for sent in ([exact], [fits[1], packet(1, 2 * field - 500 - 2 * SP_HEADER)]):
        data = CcsdsFramer().frame(sent)
        assert len(data) == 3 * 1024
        with gds_warnings() as warnings:
            assert deframe(their_tm(), [data])[0] == sent
        assert warnings == []


@pytest.mark.parametrize("room", range(0, 9))
def test_ccsds_room_left_for_idle(room: int) -> None:
    """Room of 1..6 bytes: the idle packet starts there and runs through the next frame."""
    field = 1016
    head = [packet(1, 100, 1), packet(2, 200, 2)]
    used = sum(len(p) + SP_HEADER for p in head)
    last = packet(1, field - used - room - SP_HEADER, 3)
    data = check_ccsds([[*head, last], [packet(1, 10)], head])
    first_call = frames_needed([len(p) for p in [*head, last]], field)
    assert first_call == (2 if 1 <= room <= 6 else 1)
    if 1 <= room <= 6:
        second = data[1024:2048]
        assert struct.unpack_from(">H", second, 4)[0] & 0x7FF == 0x7FF
        # the next call starts a fresh frame with a packet header at offset 0
        assert struct.unpack_from(">H", data, 2048 + 4)[0] & 0x7FF == 0


def test_ccsds_counts_wrap() -> None:
    """256+ frames (frame counts wrap) and 16384+ packets of one APID (sequence count wraps)."""
    small = [packet(1, 3, i) for i in range(3)]
    calls = [small[i % 3:i % 3 + 1] for i in range(300)]
    check_ccsds(calls, frame_size=32)
    many = [packet(1, 2)] * 16400
    check_ccsds([many], frame_size=2048)


def test_ccsds_small_frames_and_largest_packet() -> None:
    check_ccsds([[packet(1, 65536)], [packet(3, 2)]], frame_size=2048)
    check_ccsds([[packet(1, 2), packet(1, 30)], [packet(1, 9)]] * 3, frame_size=15)


@settings(max_examples=60, deadline=None)
@given(calls=st.lists(st.lists(st.integers(2, 2500), max_size=6), min_size=1, max_size=4),
       descriptors=st.lists(st.integers(0, 6), min_size=1, max_size=5),
       frame_size=st.sampled_from([64, 100, 1024]),
       chunks=st.lists(st.integers(1, 3000), min_size=1, max_size=6))
def test_ccsds_property(calls: list[list[int]], descriptors: list[int], frame_size: int,
                        chunks: list[int]) -> None:
    assume(any(calls))  # garbage alone, shorter than a frame, is not discarded yet
    k = 0
    framed: list[list[bytes]] = []
    for call in calls:
        framed.append([])
        for size in call:
            framed[-1].append(packet(descriptors[k % len(descriptors)], size, k))
            k += 1
    check_ccsds(framed, frame_size=frame_size, chunks=[max(c, 16) for c in chunks])


def test_ccsds_refuses_bad_packets_without_counting() -> None:
    framer = CcsdsFramer()
    framer.frame([packet(1, 10)])
    before = (framer.frames, framer.packets, framer.idle_bytes)
    for bad in ([packet(1, 65537)], [b"\x00"], [b""], [b"\x07\xff\x00"], [b"\xff\xff\x00"],
                [packet(1, 10), packet(1, 65537)]):
        with pytest.raises(ValueError):
            framer.frame(bad)
    assert (framer.frames, framer.packets, framer.idle_bytes) == before
    # counts ran on untouched: the next frames still deframe without a warning
    data = CcsdsFramer().frame([packet(1, 10)]) + framer.frame([packet(1, 11)])
    with gds_warnings() as warnings:
        packets, _, _ = deframe(their_tm(), [data])
    assert packets == [packet(1, 10), packet(1, 11)] and warnings == []


@pytest.mark.parametrize("kwargs", [{"scid": 0x400}, {"scid": -1}, {"vcid": 8},
                                    {"frame_size": 14}, {"frame_size": 2049}])
def test_ccsds_refuses_bad_parameters(kwargs: dict[str, int]) -> None:
    with pytest.raises(ValueError):
        CcsdsFramer(**kwargs)


def test_crc16_is_ccitt_false() -> None:
    assert crc16_ccitt(b"123456789") == 0x29B1  # the catalogue's check value
    blob = random.Random(5).randbytes(1000)
    assert crc16_ccitt(blob) == CCITT(blob)


# ---------------------------------------------------------------------------------- uplink

COMMANDS = [b"\x00\x00" + struct.pack(">I", 0x501 + i) + bytes(range(i)) for i in range(6)]
FILE_PACKET = b"\x00\x03" + b"\x00\x01" + bytes(40)
UP_GARBAGE = [b"", b"\xde\xad\xbe", b"sitt", b"\x00\x45\x20\x45\x03", b"zz\xde", b"\x20"]


def uplink(frame: Any, packets: Sequence[bytes]) -> tuple[bytes, int, int]:
    """fprime-gds's frames of ``packets`` with keep-alives and garbage in between; the number of
    garbage bytes and keep-alives put in."""
    data = b""
    garbage = keepalives = 0
    for i, p in enumerate(packets):
        junk = UP_GARBAGE[i % len(UP_GARBAGE)]
        data += junk + bytes(frame(p))
        garbage += len(junk)
        if i % 2:
            data += KEEPALIVE
            keepalives += 1
    return data, garbage, keepalives


def gds_tc_framer() -> Any:
    return SpacePacketSpaceDataLinkFramerDeframer(scid=SCID, vcid=VCID, frame_size=1024)


@pytest.mark.parametrize("framing", ["fprime", "ccsds"])
@pytest.mark.parametrize("chunk", [1, 3, 17, 10_000])
def test_uplink_from_fprime_gds(framing: str, chunk: int) -> None:
    sent = [*COMMANDS, FILE_PACKET, SPEC_PACKET]
    frame = FpFramerDeframer().frame if framing == "fprime" else gds_tc_framer().frame
    data, garbage, keepalives = uplink(frame, sent)
    d = make_deframer(framing)
    got = [p for c in split(data, [chunk]) for p in d.feed(c)]
    assert got == sent
    assert (d.frames, d.bad_crc, d.garbage_bytes, d.keepalives) == \
        (len(sent), 0, garbage, keepalives)


@pytest.mark.parametrize("framing", ["fprime", "ccsds"])
def test_uplink_corrupt_frames_counted_and_skipped(framing: str) -> None:
    frame = FpFramerDeframer().frame if framing == "fprime" else gds_tc_framer().frame
    frames = [bytes(frame(p)) for p in COMMANDS[:4]]
    bad = bytearray(frames[1])
    bad[12] ^= 0x10  # inside the packet: only the CRC can tell
    data = frames[0] + bytes(bad) + frames[2] + KEEPALIVE + frames[3]
    d = make_deframer(framing)
    assert [p for c in split(data, [5]) for p in d.feed(c)] == [COMMANDS[i] for i in (0, 2, 3)]
    assert (d.frames, d.bad_crc, d.keepalives) == (3, 1, 1)
    assert d.garbage_bytes == len(bad)  # the corrupt frame, one byte at a time


def test_tc_deframer_other_spacecraft_is_garbage() -> None:
    other = SpacePacketSpaceDataLinkFramerDeframer(scid=0x45, vcid=VCID, frame_size=1024)
    data = bytes(other.frame(COMMANDS[0]))
    d = TcDeframer(scid=SCID)
    assert d.feed(data) == [] and d.frames == 0 and d.garbage_bytes == len(data)
    mine = TcDeframer(scid=0x45)
    assert mine.feed(data) == [COMMANDS[0]]


def test_fprime_deframer_empty_and_oversize_lengths() -> None:
    empty = FpFramerDeframer().frame(b"")
    d = FprimeDeframer()
    assert d.feed(empty) == [] and d.frames == 1 and d.garbage_bytes == 0
    huge = b"\xde\xad\xbe\xef" + struct.pack(">I", 5000)
    assert d.feed(huge + bytes(FpFramerDeframer().frame(COMMANDS[1]))) == [COMMANDS[1]]
    assert d.garbage_bytes == len(huge)


@settings(max_examples=150, deadline=None)
@given(data=st.binary(max_size=600), cuts=st.lists(st.integers(0, 600), max_size=8))
def test_uplink_arbitrary_bytes_never_raise_and_any_split_agrees(data: bytes,
                                                                 cuts: list[int]) -> None:
    good = bytes(FpFramerDeframer().frame(COMMANDS[2]))
    tc = bytes(gds_tc_framer().frame(COMMANDS[3]))
    for make, frame in ((FprimeDeframer, good), (TcDeframer, tc)):
        stream = data + frame + data
        whole = make()
        expected = whole.feed(stream)
        pieces = make()
        bounds = sorted({0, len(stream), *(c % (len(stream) + 1) for c in cuts)})
        got = [p for a, b in itertools.pairwise(bounds) for p in pieces.feed(stream[a:b])]
        assert got == expected
        assert (pieces.frames, pieces.bad_crc, pieces.garbage_bytes, pieces.keepalives) == \
            (whole.frames, whole.bad_crc, whole.garbage_bytes, whole.keepalives)


# ------------------------------------------------------------------------------- selection


def test_framings_and_factories() -> None:
    from fprime_gds.executables.cli import PluginArgumentParser

    gds_default = PluginArgumentParser.FPRIME_CHOICES["framing"]
    assert gds_default == SpacePacketSpaceDataLinkFramerDeframer.get_name()
    assert FRAMINGS[DEFAULT_FRAMING].framer is CcsdsFramer
    assert set(FRAMINGS) == {"fprime", "ccsds"}
    framer = make_framer("ccsds", scid=0x12, vcid=2, frame_size=128)
    assert isinstance(framer, CcsdsFramer)
    assert (framer.scid, framer.vcid, framer.frame_size) == (0x12, 2, 128)
    assert isinstance(make_framer("fprime", scid=1, vcid=1, frame_size=64), FprimeFramer)
    assert isinstance(make_deframer("ccsds", scid=0x12), TcDeframer)
    assert isinstance(make_deframer("fprime"), FprimeDeframer)
    for make in (make_framer, make_deframer):
        with pytest.raises(ValueError, match="ccsds, fprime"):
            make("deadbeef")


def test_spec_crc32_is_zlibs() -> None:
    """The spec's CRC-32 is zlib's over start word, length and packet."""
    assert zlib.crc32(SPEC_FRAME[:-4]) == int.from_bytes(SPEC_FRAME[-4:], "big")
