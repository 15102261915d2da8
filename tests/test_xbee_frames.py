"""XBee API frames: the vectors of ``shared/specs/xbee.md`` both ways (API 1 and 2), digi-xbee
as the independent peer (it parses the frames we build and builds the frames we parse), the
stream decoder's counters and resync rule, a fuzz invariant (any bytes, any split: never
raises, bounded buffer), and the AT value helpers."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
from digi.xbee.models.address import XBee16BitAddress, XBee64BitAddress  # type: ignore[import-untyped, unused-ignore]
from digi.xbee.models.mode import OperatingMode  # type: ignore[import-untyped, unused-ignore]
from digi.xbee.models.status import DiscoveryStatus as DigiDiscovery  # type: ignore[import-untyped, unused-ignore]
from digi.xbee.models.status import ModemStatus as DigiModemStatus  # type: ignore[import-untyped, unused-ignore]
from digi.xbee.models.status import TransmitStatus as DigiTransmitStatus  # type: ignore[import-untyped, unused-ignore]
from digi.xbee.packets.base import XBeePacket  # type: ignore[import-untyped, unused-ignore]
from digi.xbee.packets.common import (  # type: ignore[import-untyped, unused-ignore]
    ATCommPacket,
    ATCommResponsePacket,
    ModemStatusPacket,
    RemoteATCommandPacket,
    RemoteATCommandResponsePacket,
    TransmitPacket,
    TransmitStatusPacket,
)
from digi.xbee.packets.common import ReceivePacket as DigiReceivePacket  # type: ignore[import-untyped, unused-ignore]
from digi.xbee.packets.factory import build_frame  # type: ignore[import-untyped, unused-ignore]
from hypothesis import given, settings
from hypothesis import strategies as st

from backends.xbee.frames import (
    BROADCAST_64,
    ESCAPED_BYTES,
    MAX_FRAME_DATA,
    UNKNOWN_16,
    AtCommand,
    AtResponse,
    AtValueError,
    Frame,
    FrameDecoder,
    FrameError,
    ModemStatus,
    ReceivePacket,
    RemoteAtCommand,
    RemoteAtResponse,
    TransmitRequest,
    TransmitStatus,
    UnknownFrame,
    at_int,
    checksum,
    counter_delta,
    decode_all,
    decode_counter,
    decode_db,
    decode_frame_data,
    decode_np,
    decode_pl,
    encode,
    escape,
    int_param,
    pl_param,
    wrap,
)

SPEC = Path(__file__).resolve().parents[1].parent / "shared" / "specs" / "xbee.md"
DEST = 0x0013A20040A1B2C3
TX = TransmitRequest(1, DEST, bytes.fromhex("11091c68"))

#: The spec's frame vectors in the order it lists them: (record, API mode).
SPEC_RECORDS: list[tuple[Frame, int]] = [
    (TX, 1),  # TX request, id 1, to 0013A20040A1B2C3, data 11 09 1c 68
    (TX, 2),  # the same escaped
    (TransmitStatus(1, UNKNOWN_16, 0, 0, 0), 1),  # TX status OK
    (AtCommand(0x52, "PL", b"\x02"), 1),  # AT PL=2
    (AtCommand(1, "DB"), 1),  # AT DB query
    (AtResponse(1, "DB", 0, b"\x28"), 1),  # DB response −40 dBm
]


def spec_vectors() -> list[bytes]:
    """The frames of the spec's vector list, in order; a missing spec is an error."""
    text = SPEC.read_text(encoding="utf-8")
    section = text.split("Vectors", 1)[1].split("## The link protocol", 1)[0]
    frames = [bytes.fromhex(h) for h in re.findall(r"`(7e(?: [0-9a-f]{2})+)`", section)]
    assert len(frames) == len(SPEC_RECORDS), "the spec's frame vectors were not all found"
    return frames


VECTORS = list(zip(spec_vectors(), SPEC_RECORDS, strict=True))
IDS = [f"{type(rec).__name__}-api{mode}-{i}" for i, (_, (rec, mode)) in enumerate(VECTORS)]


# -- spec vectors -----------------------------------------------------------------------------

@pytest.mark.parametrize(("raw", "expected"), VECTORS, ids=IDS)
def test_spec_vector_decodes(raw: bytes, expected: tuple[Frame, int]) -> None:
    rec, mode = expected
    dec = FrameDecoder(mode)
    assert dec.feed(raw) == [rec]
    assert dec.stats.frames == 1 and dec.stats.garbage_bytes == 0 and dec.pending == 0


@pytest.mark.parametrize(("raw", "expected"), VECTORS, ids=IDS)
def test_spec_vector_encodes(raw: bytes, expected: tuple[Frame, int]) -> None:
    rec, mode = expected
    assert encode(rec, mode) == raw


@pytest.mark.parametrize(("raw", "expected"), VECTORS, ids=IDS)
def test_spec_vector_in_the_other_mode(raw: bytes, expected: tuple[Frame, int]) -> None:
    """A frame with no byte to escape is the same in both modes; one with escapes is not."""
    rec, mode = expected
    other = 3 - mode
    needs_escape = any(b in ESCAPED_BYTES for b in encode(rec, 1)[1:])
    assert (encode(rec, other) == raw) is not needs_escape
    assert decode_all(encode(rec, other), other) == [rec]


def test_spec_db_response_is_minus_40_dbm() -> None:
    (resp,) = decode_all(VECTORS[5][0])
    assert isinstance(resp, AtResponse) and resp.ok
    assert decode_db(resp.value) == -40


def test_transmit_status_and_receive_flags() -> None:
    assert TransmitStatus(1, UNKNOWN_16, 0, 0, 0).ok
    assert not TransmitStatus(1, UNKNOWN_16, 3, 0x21, 0).ok
    rx = ReceivePacket(DEST, 0x1234, 0x03, b"x")
    assert rx.acked and rx.broadcast
    assert not ReceivePacket(DEST, 0x1234, 0, b"").acked


# -- strategies -------------------------------------------------------------------------------

byte = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u64 = st.one_of(st.sampled_from([BROADCAST_64, DEST, 0]), st.integers(0, 2**64 - 1))
# payloads rich in the four bytes API 2 escapes
payload = st.lists(st.one_of(st.sampled_from(sorted(ESCAPED_BYTES)), byte), max_size=40).map(bytes)
at_cmd = st.text(alphabet="ABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789%", min_size=2, max_size=2)


def _codes(enum: Any) -> list[int]:
    return sorted({s.code for s in enum if s.name != "UNKNOWN"})


frames = st.one_of(
    st.builds(AtCommand, byte, at_cmd, payload),
    st.builds(AtResponse, byte, at_cmd, st.integers(0, 4), payload),
    st.builds(TransmitRequest, byte, u64, payload, u16, byte, byte),
    st.builds(TransmitStatus, byte, u16, byte, st.sampled_from(_codes(DigiTransmitStatus)),
              st.sampled_from(_codes(DigiDiscovery))),
    st.builds(ReceivePacket, u64, u16, byte, payload),
    st.builds(RemoteAtCommand, byte, u64, at_cmd, payload, u16, byte),
    st.builds(RemoteAtResponse, byte, u64, u16, at_cmd, st.integers(0, 4), payload),
    st.builds(ModemStatus, st.sampled_from(_codes(DigiModemStatus))),
)
modes = st.sampled_from([1, 2])


# -- digi-xbee, the independent implementation ------------------------------------------------

def _a64(a: XBee64BitAddress) -> int:
    return int.from_bytes(bytes(a.address), "big")


def _a16(a: XBee16BitAddress) -> int:
    return int.from_bytes(bytes(a.address), "big")


def _b(v: Any) -> bytes:
    return bytes(v) if v else b""


def from_digi(p: XBeePacket) -> Frame:
    """Our record for a digi-xbee packet, read through digi's own accessors."""
    if isinstance(p, ATCommPacket):
        return AtCommand(p.frame_id, p.command, _b(p.parameter))
    if isinstance(p, ATCommResponsePacket):
        return AtResponse(p.frame_id, p.command, p.real_status, _b(p.command_value))
    if isinstance(p, TransmitPacket):
        return TransmitRequest(p.frame_id, _a64(p.x64bit_dest_addr), _b(p.rf_data),
                               _a16(p.x16bit_dest_addr), p.broadcast_radius,
                               p.transmit_options)
    if isinstance(p, TransmitStatusPacket):
        return TransmitStatus(p.frame_id, _a16(p.x16bit_dest_addr), p.transmit_retry_count,
                              p.transmit_status.code, p.discovery_status.code)
    if isinstance(p, DigiReceivePacket):
        return ReceivePacket(_a64(p.x64bit_source_addr), _a16(p.x16bit_source_addr),
                             p.receive_options, _b(p.rf_data))
    if isinstance(p, RemoteATCommandPacket):
        return RemoteAtCommand(p.frame_id, _a64(p.x64bit_dest_addr), p.command,
                               _b(p.parameter), _a16(p.x16bit_dest_addr), p.transmit_options)
    if isinstance(p, RemoteATCommandResponsePacket):
        return RemoteAtResponse(p.frame_id, _a64(p.x64bit_source_addr),
                                _a16(p.x16bit_source_addr), p.command, p.real_status,
                                _b(p.command_value))
    if isinstance(p, ModemStatusPacket):
        return ModemStatus(p.modem_status.code)
    raise AssertionError(f"unexpected digi packet {type(p).__name__}")


def to_digi(f: Frame, mode: int) -> XBeePacket:
    """A digi-xbee packet with the fields of ``f``, built by digi's own constructors."""
    op = OperatingMode.ESCAPED_API_MODE if mode == 2 else OperatingMode.API_MODE

    def a64(v: int) -> XBee64BitAddress:
        return XBee64BitAddress(bytearray(v.to_bytes(8, "big")))

    def a16(v: int) -> XBee16BitAddress:
        return XBee16BitAddress(bytearray(v.to_bytes(2, "big")))

    def opt(v: bytes) -> bytearray | None:
        return bytearray(v) if v else None

    if isinstance(f, AtCommand):
        return ATCommPacket(f.frame_id, f.command, opt(f.parameter), op_mode=op)
    if isinstance(f, AtResponse):
        return ATCommResponsePacket(f.frame_id, f.command, f.status, opt(f.value), op_mode=op)
    if isinstance(f, TransmitRequest):
        return TransmitPacket(f.frame_id, a64(f.dest64), a16(f.dest16), f.radius, f.options,
                              opt(f.data), op_mode=op)
    if isinstance(f, TransmitStatus):
        return TransmitStatusPacket(f.frame_id, a16(f.dest16), f.retries,
                                    DigiTransmitStatus.get(f.delivery),
                                    DigiDiscovery.get(f.discovery), op_mode=op)
    if isinstance(f, ReceivePacket):
        return DigiReceivePacket(a64(f.src64), a16(f.src16), f.options, opt(f.data), op_mode=op)
    if isinstance(f, RemoteAtCommand):
        return RemoteATCommandPacket(f.frame_id, a64(f.dest64), a16(f.dest16), f.options,
                                     f.command, opt(f.parameter), op_mode=op)
    if isinstance(f, RemoteAtResponse):
        return RemoteATCommandResponsePacket(f.frame_id, a64(f.src64), a16(f.src16), f.command,
                                             f.status, opt(f.value), op_mode=op)
    if isinstance(f, ModemStatus):
        return ModemStatusPacket(DigiModemStatus.get(f.status), op_mode=op)
    raise AssertionError(f"unexpected record {type(f).__name__}")


def digi_parse(raw: bytes, mode: int) -> XBeePacket:
    """digi-xbee's reading of a whole frame (its build_frame takes unescaped bytes)."""
    if mode == 2:
        unescaped = XBeePacket.unescape_data(bytearray(raw))
        return build_frame(unescaped, OperatingMode.ESCAPED_API_MODE)
    return build_frame(bytearray(raw), OperatingMode.API_MODE)


@pytest.mark.parametrize(("raw", "expected"), VECTORS, ids=IDS)
def test_digi_reads_the_spec_vectors(raw: bytes, expected: tuple[Frame, int]) -> None:
    rec, mode = expected
    assert from_digi(digi_parse(raw, mode)) == rec


@settings(max_examples=150, deadline=None)
@given(frames, modes)
def test_digi_parses_what_we_build(frame: Frame, mode: int) -> None:
    raw = encode(frame, mode)
    pkt = digi_parse(raw, mode)
    assert from_digi(pkt) == frame
    assert bytes(pkt.output(escaped=mode == 2)) == raw


@settings(max_examples=150, deadline=None)
@given(frames, modes)
def test_we_parse_what_digi_builds(frame: Frame, mode: int) -> None:
    raw = bytes(to_digi(frame, mode).output(escaped=mode == 2))
    dec = FrameDecoder(mode)
    assert dec.feed(raw) == [frame]
    assert dec.stats.frames == 1 and dec.stats.garbage_bytes == 0


# -- the stream decoder -----------------------------------------------------------------------

garbage = st.binary(max_size=12).map(lambda b: b.replace(b"\x7e", b""))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(garbage, frames), max_size=6), garbage, modes, st.data())
def test_frames_split_anywhere_between_garbage(
    items: list[tuple[bytes, Frame]], tail: bytes, mode: int, data: st.DataObject
) -> None:
    """Valid frames with garbage (no 0x7E) between them, cut at random points, all come out
    in order, and every garbage byte is counted."""
    stream = b"".join(g + encode(f, mode) for g, f in items) + tail
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=8)))
    dec = FrameDecoder(mode)
    out: list[Frame] = []
    prev = 0
    for c in [*cuts, len(stream)]:
        out += dec.feed(stream[prev:c])
        prev = c
    out += dec.flush()
    assert out == [f for _, f in items]
    assert dec.stats.frames == len(items)
    assert dec.stats.garbage_bytes == sum(len(g) for g, _ in items) + len(tail)
    assert dec.stats.crc_failures == dec.stats.bad_length == dec.stats.bad_escape == 0
    assert dec.pending == 0


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=600), modes, st.integers(1, 64))
def test_any_bytes_never_raise_and_the_buffer_stays_bounded(
    data: bytes, mode: int, chunk: int
) -> None:
    dec = FrameDecoder(mode, max_length=40)
    bound = 4 + 40 if mode == 1 else 1 + 2 * (40 + 3)
    for i in range(0, len(data), chunk):
        for f in dec.feed(data[i:i + chunk]):
            assert isinstance(f, Frame)
        assert dec.pending <= bound
    dec.flush()
    assert dec.pending == 0
    assert dec.stats.bytes_in == len(data)


@pytest.mark.parametrize("mode", [1, 2])
def test_byte_at_a_time_equals_whole(mode: int) -> None:
    stream = b"\x00\x7d" + encode(TX, mode) + b"\x13" + encode(AtResponse(1, "DB", 0, b"\x28"),
                                                            mode)
    whole = decode_all(stream, mode)
    dec = FrameDecoder(mode)
    single = [f for b in stream for f in dec.feed(bytes((b,)))] + dec.flush()
    assert whole == single == [TX, AtResponse(1, "DB", 0, b"\x28")]


def _frame1(data: bytes) -> bytes:
    """An API 1 frame built here from the spec's rule, independently of the module."""
    return b"\x7e" + len(data).to_bytes(2, "big") + data + bytes(((0xFF - sum(data)) & 0xFF,))


@pytest.mark.parametrize("mode", [1, 2])
def test_bad_checksum_is_counted_and_the_next_frame_found(mode: int) -> None:
    good = encode(TX, mode)
    bad = good[:-1] + bytes(((good[-1] + 1) & 0xFF,))
    dec = FrameDecoder(mode)
    assert dec.feed(bad + good) == [TX]
    assert dec.stats.crc_failures == 1 and dec.stats.frames == 1
    assert dec.stats.garbage_bytes == len(bad)


@pytest.mark.parametrize("mode", [1, 2])
@pytest.mark.parametrize("length", [0, MAX_FRAME_DATA + 1])
def test_length_out_of_bounds_is_counted(mode: int, length: int) -> None:
    dec = FrameDecoder(mode)
    head = b"\x7e" + length.to_bytes(2, "big") + b"\x08\x01"
    assert dec.feed(head + encode(TX, mode)) == [TX]
    assert dec.stats.bad_length == 1


def test_a_corrupted_length_never_skips_the_frames_it_claims() -> None:
    """API 1: a start whose length claims 0x30 bytes, then two good frames inside that span —
    the false start is refuted (one byte dropped) and both frames are found."""
    stream = b"\x7e\x00\x30\x10" + encode(TX) + encode(AtCommand(2, "DB")) + bytes(60)
    dec = FrameDecoder(1)
    assert dec.feed(stream) == [TX, AtCommand(2, "DB")]
    assert dec.stats.crc_failures == 1


def test_api2_frame_cut_short_by_a_new_start() -> None:
    good = encode(TX, 2)
    dec = FrameDecoder(2)
    assert dec.feed(good[:9] + good) == [TX]
    assert dec.stats.bad_length == 1 and dec.stats.garbage_bytes == 9


@pytest.mark.parametrize("bad", [b"\x7d\x00", b"\x11", b"\x13", b"\x7d\x7e"],
                         ids=["escape-of-plain-byte", "raw-xon", "raw-xoff", "escape-then-start"])
def test_api2_bad_escape_is_counted(bad: bytes) -> None:
    good = encode(TX, 2)
    broken = good[:6] + bad + good[6:]
    dec = FrameDecoder(2)
    assert dec.feed(broken + good) == [TX]
    assert dec.stats.bad_escape == 1


def test_unknown_type_comes_out_as_a_generic_record() -> None:
    raw = _frame1(bytes.fromhex("a1 02 03"))
    dec = FrameDecoder(1)
    assert dec.feed(raw) == [UnknownFrame(0xA1, b"\x02\x03")]
    assert dec.stats.unknown_type == 1 and dec.stats.frames == 1
    assert encode(UnknownFrame(0xA1, b"\x02\x03")) == raw


@pytest.mark.parametrize("data", ["90 00 01 02", "8b 01 ff fe 00 00", "8b 01 ff fe 00 00 00 00",
                                  "88 01 44", "8a"])
def test_known_type_of_impossible_length_is_dropped(data: str) -> None:
    raw = _frame1(bytes.fromhex(data))
    dec = FrameDecoder(1)
    assert dec.feed(raw + encode(TX)) == [TX]
    assert dec.stats.bad_length == 1 and dec.stats.frames == 1
    with pytest.raises(FrameError):
        decode_frame_data(bytes.fromhex(data))


@pytest.mark.parametrize("ftype", sorted(ESCAPED_BYTES))
def test_an_escaped_type_byte_round_trips(ftype: int) -> None:
    """Even the type byte is escaped in API 2 (digi-xbee's unescaping agrees)."""
    rec = UnknownFrame(ftype, bytes([0x7E, 0x00, 0x7D]))
    raw = encode(rec, 2)
    assert raw[3] == 0x7D
    assert bytes(XBeePacket.unescape_data(bytearray(raw))) == encode(rec, 1)
    assert decode_all(raw, 2) == [rec]


def test_checksum_and_escape_follow_the_spec_rule() -> None:
    assert checksum(bytes.fromhex("08 52 50 4c 02")) == 0x07
    assert escape(bytes([0x7E, 0x7D, 0x11, 0x13, 0x12])) == bytes.fromhex("7d5e 7d5d 7d31 7d33 12")
    assert wrap(bytes.fromhex("08 01 44 42"), 1) == bytes.fromhex("7e 00 04 08 01 44 42 70")


@pytest.mark.parametrize("bad", [
    AtCommand(256, "PL"), AtCommand(1, "P"), AtCommand(1, "PLX"), AtCommand(1, "é1"),
    TransmitRequest(1, 2**64, b""), TransmitRequest(1, 0, b"", dest16=0x10000),
    TransmitStatus(1, 0, 0, -1, 0), ModemStatus(300),
    TransmitRequest(1, 0, bytes(0x10000)),
])
def test_encode_rejects_bad_fields(bad: Frame) -> None:
    with pytest.raises(FrameError):
        encode(bad)


def test_bad_api_mode_is_rejected() -> None:
    with pytest.raises(ValueError):
        encode(TX, 3)
    with pytest.raises(ValueError):
        FrameDecoder(0)


# -- AT values --------------------------------------------------------------------------------

def test_at_value_helpers() -> None:
    assert pl_param(0) == b"\x00" and pl_param(4) == b"\x04"
    assert decode_pl(b"\x03") == 3 and decode_pl(b"\x00\x02") == 2
    assert decode_db(b"\x28") == -40 and decode_db(b"\x00\x5a") == -90
    assert decode_counter(b"\xff\xff") == 0xFFFF and decode_counter(b"\x12") == 0x12
    assert decode_np(b"\x00\x64") == 100
    assert int_param(0) == b"\x00" and int_param(0x1234) == b"\x12\x34"
    assert at_int(b"\x00\x00\x01\x00") == 256
    assert counter_delta(10, 15) == 5 and counter_delta(0xFFFF, 0xFFFF) == 0
    assert counter_delta(500, 3) == 3  # reset in between


@pytest.mark.parametrize(("fn", "arg"), [
    (pl_param, 5), (pl_param, -1), (decode_pl, b"\x05"), (decode_pl, b""),
    (decode_db, b"\x01\x00"), (decode_counter, b"\x01\x00\x00"), (decode_np, b"\x00"),
    (int_param, -1),
])
def test_at_values_out_of_range_raise(fn: Any, arg: Any) -> None:
    with pytest.raises(AtValueError):
        fn(arg)
