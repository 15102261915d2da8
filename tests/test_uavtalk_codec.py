"""The UAVTalk packet codec: the spec's vectors both ways, the resync rule, the counters, and
hypothesis properties (any split gives the same packets; garbage never raises)."""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from backends.uavtalk import objects
from backends.uavtalk.codec import (
    MAX_DATA_LENGTH,
    MAX_SIZE,
    Decoder,
    Packet,
    PacketType,
    crc8,
    encode,
)

FLIGHT_STATS = 0x6737BB5A
GCS_STATS = 0xCAD1DC0A
ATTITUDE = 0xD7E0D964
FIRMWARE_IAP = 0x8328F252

# The decoder checks lengths against the real 16.09 object set (objects.py), metaobjects included.
OBJECTS = objects.ObjectSet.load()
data_length = OBJECTS.data_length
LENGTHS = {o.id: o.size for o in OBJECTS} | {o.id + 1: objects.META_SIZE for o in OBJECTS}
# Ids the tests use as unknown objects.
UNKNOWN_IDS = (0x10, 0x999, 0x11111110, 0x55555554, 0x77777776, 0x12345678)


def test_the_ids_the_tests_use_are_what_they_claim() -> None:
    assert (LENGTHS[FLIGHT_STATS], LENGTHS[GCS_STATS], LENGTHS[ATTITUDE]) == (37, 37, 28)
    assert FIRMWARE_IAP in LENGTHS and LENGTHS[ATTITUDE + 1] == objects.META_SIZE
    assert not any(i in LENGTHS for i in UNKNOWN_IDS)


def ref_crc8(data: bytes) -> int:
    """Bitwise CRC-8 (poly 0x07, init 0), written from the definition, as an independent check."""
    c = 0
    for b in data:
        c ^= b
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
    return c


def with_crc(body: bytes) -> bytes:
    return body + bytes((ref_crc8(body),))


VECTORS = [
    pytest.param("3c202f005abb37670000" + "00" * 36 + "0268",
                 Packet(PacketType.OBJ, FLIGHT_STATS, 0, bytes(36) + b"\x02"),
                 id="FlightStats-Ack"),
    pytest.param("3c202f000adcd1ca0000" + "00" * 36 + "0196",
                 Packet(PacketType.OBJ, GCS_STATS, 0, bytes(36) + b"\x01"), id="GCSStats-Req"),
    pytest.param("3c202600" "64d9e0d7" "0000" "0000803f" "00000000" "00000000" "00000000"
                 "00002041" "0000a0c0" "0000b442" "cb",
                 Packet(PacketType.OBJ, ATTITUDE, 0, struct.pack("<7f", 1, 0, 0, 0, 10, -5, 90)),
                 id="AttitudeState"),
    pytest.param("3c230a000adcd1ca000050", Packet(PacketType.ACK, GCS_STATS), id="ACK"),
    pytest.param("3c240a0052f228830000b0", Packet(PacketType.NACK, FIRMWARE_IAP), id="NACK"),
    pytest.param("3c210a005abb3767000006", Packet(PacketType.OBJ_REQ, FLIGHT_STATS), id="OBJ_REQ"),
]


def test_crc8_check_value_and_matches_the_definition() -> None:
    assert crc8(b"123456789") == 0xF4
    assert ref_crc8(b"123456789") == 0xF4
    assert crc8(b"") == 0


@given(st.binary(max_size=300))
def test_crc8_equals_bitwise_reference(data: bytes) -> None:
    assert crc8(data) == ref_crc8(data)


@pytest.mark.parametrize(("wire", "packet"), VECTORS)
def test_spec_vector_encodes(wire: str, packet: Packet) -> None:
    assert encode(packet) == bytes.fromhex(wire)


@pytest.mark.parametrize(("wire", "packet"), VECTORS)
def test_spec_vector_decodes_whole_and_byte_by_byte(wire: str, packet: Packet) -> None:
    raw = bytes.fromhex(wire)
    dec = Decoder(data_length)
    assert dec.feed(raw) == [packet]
    assert dec.stats.packets == 1 and dec.stats.bytes_skipped == 0 and dec.pending == 0
    dec = Decoder(data_length)
    out = []
    for b in raw:
        out += dec.feed(bytes((b,)))
    assert out == [packet]
    assert dec.stats.as_dict() == {"packets": 1, "bad_crc": 0, "bad_size": 0,
                                   "unknown_object": 0,
                                   "bad_length": 0, "bytes_skipped": 0, "timestamped": 0}


@pytest.mark.parametrize("bad", [
    Packet(PacketType.OBJ, GCS_STATS, 0, bytes(37), timestamp=5),
    Packet(PacketType.OBJ_REQ, GCS_STATS, 0, b"\x00"),
    Packet(PacketType.ACK, GCS_STATS, 0, b"\x00"),
    Packet(PacketType.NACK, GCS_STATS, 0, b"\x00"),
    Packet(PacketType.OBJ, GCS_STATS, 0, bytes(MAX_DATA_LENGTH + 1)),
    Packet(PacketType.OBJ, 1 << 32),
    Packet(PacketType.OBJ, -1),
    Packet(PacketType.OBJ, GCS_STATS, 0x10000),
    Packet(0xA0, GCS_STATS),  # type: ignore[arg-type]
])
def test_encode_refuses_what_a_gcs_would_not_take(bad: Packet) -> None:
    with pytest.raises(ValueError):
        encode(bad)


def test_encode_largest_packet_and_all_instances() -> None:
    p = Packet(PacketType.OBJ_ACK, 0x12345678, 0xFFFF, bytes(range(256)))
    raw = encode(p)
    assert len(raw) == MAX_SIZE + 1 and raw[2:4] == MAX_SIZE.to_bytes(2, "little")
    assert Decoder().feed(raw) == [p]


def timestamped(ptype: int, object_id: int, instance: int, stamp: int, data: bytes) -> bytes:
    """A timestamped variant as 16.09's flight/uavtalk/uavtalk.c builds it: the stamp follows the
    instance id and is counted in the size."""
    return with_crc(struct.pack("<BBHIHH", 0x3C, ptype | 0x80, 12 + len(data), object_id, instance,
                                stamp) + data)


def test_timestamped_variants_decode_and_count() -> None:
    att = struct.pack("<7f", 1, 0, 0, 0, 1, 2, 3)
    raw = (timestamped(PacketType.OBJ, ATTITUDE, 0, 0xBEEF, att)
           + timestamped(PacketType.OBJ_ACK, 0x11111110, 3, 7, b"xyz"))
    dec = Decoder(data_length)
    assert dec.feed(raw) == [Packet(PacketType.OBJ, ATTITUDE, 0, att, 0xBEEF),
                             Packet(PacketType.OBJ_ACK, 0x11111110, 3, b"xyz", 7)]
    assert dec.stats.timestamped == 2 and dec.stats.packets == 2
    assert dec.stats.unknown_object == 1 and dec.stats.bytes_skipped == 0


def test_timestamped_length_is_checked_without_the_stamp() -> None:
    # 30 bytes after the instance id is the stamp plus 28 data bytes: right for AttitudeState
    # timestamped, wrong (bad_length) if read as a plain OBJ.
    body = bytes(30)
    plain = with_crc(struct.pack("<BBHIH", 0x3C, 0x20, 10 + len(body), ATTITUDE, 0) + body)
    dec = Decoder(data_length)
    assert dec.feed(plain) == []
    assert dec.stats.bad_length == 1 and dec.stats.bytes_skipped == len(plain)


@pytest.mark.parametrize("ptype", [0xA1, 0xA3, 0xA4, 0x25, 0x00, 0x3C])
def test_no_other_type_byte_is_a_packet(ptype: int) -> None:
    bad = with_crc(struct.pack("<BBHIH", 0x3C, ptype, 10, GCS_STATS, 0))
    good = encode(Packet(PacketType.ACK, GCS_STATS))
    dec = Decoder(data_length)
    assert dec.feed(bad + good) == [Packet(PacketType.ACK, GCS_STATS)]
    assert dec.stats.bytes_skipped == len(bad) and dec.stats.packets == 1


# --- counters ------------------------------------------------------------------------------

GOOD = [Packet(PacketType.OBJ, ATTITUDE, 0, struct.pack("<7f", 1, 0, 0, 0, 10, -5, 90)),
        Packet(PacketType.ACK, GCS_STATS),
        Packet(PacketType.OBJ, FLIGHT_STATS, 0, bytes(36) + b"\x03")]
GOOD_WIRE = b"".join(encode(p) for p in GOOD)


@pytest.mark.parametrize(("bad", "counter"), [
    (with_crc(struct.pack("<BBHIH", 0x3C, 0x23, 9, GCS_STATS, 0)), "bad_size"),
    (with_crc(struct.pack("<BBHIH", 0x3C, 0x20, MAX_SIZE + 1, 0x10, 0) + bytes(257)), "bad_size"),
    (with_crc(struct.pack("<BBHIH", 0x3C, 0x23, 11, GCS_STATS, 0) + b"\x00"), "bad_length"),
    (with_crc(struct.pack("<BBHIH", 0x3C, 0x21, 12, 0x10, 0) + b"\x00\x00"), "bad_length"),
    (with_crc(struct.pack("<BBHIH", 0x3C, 0x20, 46, GCS_STATS, 0) + bytes(36)), "bad_length"),
    (with_crc(struct.pack("<BBHIH", 0x3C, 0x22, 48, GCS_STATS, 0) + bytes(38)), "bad_length"),
    (encode(Packet(PacketType.OBJ, GCS_STATS, 0, bytes(37)))[:-1] + b"\x00", "bad_crc"),
])
def test_each_error_is_counted_and_costs_only_the_bad_packet(bad: bytes, counter: str) -> None:
    dec = Decoder(data_length)
    assert dec.feed(bad + GOOD_WIRE) == GOOD
    stats = dec.stats.as_dict()
    assert stats[counter] == 1
    assert stats["bytes_skipped"] == len(bad)
    assert stats["packets"] == len(GOOD)
    assert sum(stats[k] for k in ("bad_crc", "bad_size", "bad_length")) == 1


def test_unknown_object_with_valid_crc_is_passed_up_and_counted() -> None:
    pkts = [Packet(PacketType.OBJ_ACK, 0x55555554, 0, b"abc"), Packet(PacketType.OBJ_REQ, 0x999)]
    dec = Decoder(data_length)
    assert dec.feed(b"".join(encode(p) for p in pkts)) == pkts
    assert dec.stats.unknown_object == 2 and dec.stats.packets == 2


def test_without_data_length_nothing_is_checked_or_unknown() -> None:
    wrong = Packet(PacketType.OBJ, GCS_STATS, 0, bytes(5))
    dec = Decoder()
    assert dec.feed(encode(wrong)) == [wrong]
    assert dec.stats.unknown_object == 0 and dec.stats.bad_length == 0


# --- resync ----------------------------------------------------------------------------------

def test_corrupted_packet_costs_one_byte_not_its_claimed_size() -> None:
    """A good packet carried inside a corrupted one is found: the decoder drops one byte on the
    CRC failure and rescans, it does not skip the claimed size."""
    inner = encode(GOOD[1])
    outer = bytearray(encode(Packet(PacketType.OBJ, 0x77777776, 0, b"ab" + inner + b"cd")))
    outer[-1] ^= 0xFF
    dec = Decoder(data_length)
    assert dec.feed(bytes(outer) + GOOD_WIRE) == [GOOD[1], *GOOD]
    assert dec.stats.bad_crc == 1
    assert dec.stats.bytes_skipped == len(outer) - len(inner)


def test_corrupted_size_of_a_known_object_does_not_hold_back_what_follows() -> None:
    """The size byte of a known object is corrupted upwards: the length check rejects it at the
    header, so the packets behind it come out at once instead of waiting for 266 bytes."""
    bad = bytearray(encode(GOOD[0]))
    bad[2] = 250
    dec = Decoder(data_length)
    assert dec.feed(bytes(bad) + GOOD_WIRE) == GOOD
    assert dec.stats.bad_length == 1 and dec.pending == 0


def test_corrupted_size_of_an_unknown_object_recovers_when_the_bytes_arrive() -> None:
    bad = bytearray(encode(Packet(PacketType.OBJ, 0x77777776, 0, b"abcd")))
    bad[2] = 250  # claims 250 bytes: wait for them, fail the CRC, drop one byte, rescan
    dec = Decoder(data_length)
    assert dec.feed(bytes(bad) + GOOD_WIRE) == []
    assert 0 < dec.pending <= MAX_SIZE
    assert dec.feed(bytes(300)) == GOOD
    assert dec.stats.bad_crc == 1 and dec.pending == 0


@pytest.mark.parametrize("cut", range(1, len(encode(GOOD[0]))))
def test_truncated_packet_followed_by_good_ones(cut: int) -> None:
    """Every cut of a packet followed by good ones: the truncated packet costs its own bytes.
    CRC-8 lets one bad candidate in 256 through; with this packet cut 30 is such a case (the
    truncated header, claiming 28 bytes, ends on a byte that happens to be its CRC): then a
    CRC-valid false packet swallows the start of the next one, as in LibrePilot's own parser,
    and every packet behind it still comes out."""
    dec = Decoder(data_length)
    head = encode(GOOD[0])[:cut]
    raw = head + GOOD_WIRE
    out = dec.feed(raw)
    if cut == 30:
        assert len(out) == 3 and out[0] != GOOD[0] and out[1:] == GOOD[1:]
        assert encode(out[0]) == raw[:len(encode(out[0]))]
        return
    assert out == GOOD
    assert dec.stats.bytes_skipped == cut


def test_buffer_stays_bounded() -> None:
    dec = Decoder()
    start = struct.pack("<BBHIH", 0x3C, 0x20, MAX_SIZE, 0x10, 0)
    assert dec.feed(start) == []
    for _ in range(MAX_SIZE - 10):
        dec.feed(b"\x3c")
        assert dec.pending <= MAX_SIZE
    dec.feed(bytes(10_000))
    assert dec.pending == 0
    assert dec.feed(GOOD_WIRE) == GOOD


# --- properties ------------------------------------------------------------------------------

KNOWN_IDS = sorted(LENGTHS)
assert all(n <= MAX_DATA_LENGTH for n in LENGTHS.values())


@st.composite
def packets(draw: st.DrawFn) -> Packet:
    ptype = draw(st.sampled_from(PacketType))
    object_id = draw(st.one_of(st.sampled_from(KNOWN_IDS), st.integers(0, 0xFFFFFFFF)))
    instance = draw(st.integers(0, 0xFFFF))
    if ptype in (PacketType.OBJ_REQ, PacketType.ACK, PacketType.NACK):
        data = b""
    elif object_id in LENGTHS:
        data = draw(st.binary(min_size=LENGTHS[object_id], max_size=LENGTHS[object_id]))
    else:
        data = draw(st.binary(max_size=MAX_DATA_LENGTH))
    return Packet(ptype, object_id, instance, data)


def feed_split(dec: Decoder, raw: bytes, cuts: list[int]) -> list[Packet]:
    out: list[Packet] = []
    prev = 0
    for c in [*sorted({min(c, len(raw)) for c in cuts}), len(raw)]:
        out += dec.feed(raw[prev:c])
        prev = c
    return out


@settings(max_examples=150)
@given(st.lists(packets(), max_size=12), st.lists(st.integers(0, 4000), max_size=20))
def test_any_split_of_valid_packets_gives_them_all(pkts: list[Packet], cuts: list[int]) -> None:
    raw = b"".join(encode(p) for p in pkts)
    dec = Decoder(data_length)
    assert feed_split(dec, raw, cuts) == pkts
    assert dec.stats.packets == len(pkts) and dec.stats.bytes_skipped == 0 and dec.pending == 0
    assert dec.stats.bad_crc == dec.stats.bad_size == dec.stats.bad_length == 0


@settings(max_examples=150)
@given(st.lists(st.tuples(st.binary(max_size=40).map(lambda b: b.replace(b"\x3c", b"")),
                          packets()), max_size=8))
def test_garbage_between_packets_costs_only_the_garbage(items: list[tuple[bytes, Packet]]) -> None:
    raw = b"".join(g + encode(p) for g, p in items)
    dec = Decoder(data_length)
    assert dec.feed(raw) == [p for _, p in items]
    assert dec.stats.bytes_skipped == sum(len(g) for g, _ in items)


@settings(max_examples=300)
@given(st.binary(max_size=2000), st.lists(st.integers(0, 2000), max_size=30),
       st.booleans())
def test_garbage_never_raises_and_only_crc_valid_packets_come_out(
        raw: bytes, cuts: list[int], sync_rich: bool) -> None:
    if sync_rich:  # make sync bytes and plausible headers common
        raw = raw.replace(b"\x00", b"\x3c").replace(b"\x01", b"\x20")
    dec = Decoder(data_length)
    out = feed_split(dec, raw, cuts)
    assert dec.pending <= MAX_SIZE
    for p in out:
        assert p.timestamp is None or 0 <= p.timestamp <= 0xFFFF
        wire = (encode(p) if p.timestamp is None
                else timestamped(p.type, p.object_id, p.instance_id, p.timestamp, p.data))
        assert wire in raw and crc8(wire) == 0
    # the same bytes in one piece give the same packets and the same counters
    whole = Decoder(data_length)
    assert whole.feed(raw) == out
    assert whole.stats == dec.stats


# --- with the real 16.09 object set ------------------------------------------------------------

def test_vectors_decode_against_the_16_09_object_set() -> None:
    """The decoder fed by objects.py: every object of the spec's vectors is known, with the sizes
    the vectors carry; a metaobject's id checks against META_SIZE."""
    dec = Decoder(OBJECTS.data_length)
    raw = b"".join(bytes.fromhex(str(v.values[0])) for v in VECTORS)
    assert dec.feed(raw) == [v.values[1] for v in VECTORS]
    assert dec.stats.unknown_object == 0 and dec.stats.bad_length == 0
    meta = Packet(PacketType.OBJ, ATTITUDE + 1, 0, bytes(objects.META_SIZE))
    short = Packet(PacketType.OBJ, ATTITUDE + 1, 0, bytes(objects.META_SIZE - 1))
    assert dec.feed(encode(short) + encode(meta)) == [meta]
    assert dec.stats.bad_length == 1 and dec.stats.unknown_object == 0
