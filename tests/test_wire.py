"""The Aurora wire codec (``gateway.wire``) against the spec, the shared vectors and properties.

Frames in these tests are built by :func:`make_frame`, a deliberately naive reference
(bit-by-bit CRC-16/MCRF4XX) that shares no code with ``gateway.wire``; the CRC itself is
also checked against pymavlink's ``x25crc``, an independent real-world implementation.
"""

from __future__ import annotations

import binascii
import itertools
import math
import random
import struct
from collections.abc import Iterable, Sequence
from typing import Any

import pytest
from hypothesis import assume, event, example, given, settings
from hypothesis import strategies as st
from pymavlink.generator.mavcrc import x25crc

from gateway import wire
from gateway.model import LinkEvent, RawFrame, SmUpdate, Status

# -- reference helpers (independent of gateway.wire) ----------------------------------------

MAGIC = b"\xa5\x5a"
MAX_FRAME = 4 + 255 + 2

#: Spec (vector) field name → model attribute, for the SM_UPDATE floats.
SPEC_TO_MODEL = {
    "altitude": "altitude_m",
    "acceleration": "acceleration_mps2",
    "accel_vert": "accel_vert_mps2",
    "velocity": "velocity_mps",
    "roll": "roll_rad",
    "pitch": "pitch_rad",
    "yaw": "yaw_rad",
}
FLOAT_FIELDS = tuple(SPEC_TO_MODEL)
SM_UPDATE_FIELDS = {"timestamp_ms", "state", "armed", "sm_type", *FLOAT_FIELDS}
STATUS_FIELDS = {"timestamp_ms", "state", "sm_type", "flags"}
#: STATUS flag bits 0..4, in bit order.
STATUS_FLAG_NAMES = ("armed", "imu_ok", "baro_ok", "calibrated", "log_ready")

FAST = settings(deadline=None, max_examples=60)
MEDIUM = settings(deadline=None, max_examples=150)


def ref_crc(data: bytes) -> int:
    """CRC-16/MCRF4XX, bit by bit: reflected poly 0x1021 (0x8408), init 0xFFFF, no xorout."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc


def make_frame(ftype: int, payload: bytes, crc_func=ref_crc) -> bytes:
    """A wire frame built from the spec's table (CRC over type, len, payload; little-endian)."""
    body = bytes((ftype, len(payload))) + payload
    return MAGIC + body + crc_func(body).to_bytes(2, "little")


def is_valid_frame(raw: bytes) -> bool:
    """True when ``raw`` is exactly one well-formed frame with a correct CRC."""
    return (
        len(raw) >= 6
        and raw[:2] == MAGIC
        and raw[3] == len(raw) - 6
        and ref_crc(raw[2:-2]) == int.from_bytes(raw[-2:], "little")
    )


def expected_class(ftype: int, length: int) -> type:
    """Which message a frame of this type and payload length must decode to."""
    if ftype == 0x01 and length in (36, 64):
        return SmUpdate
    if ftype == 0x02 and length == 8:
        return Status
    return RawFrame


def f32_is_signalling_nan(bits: bytes) -> bool:
    """An IEEE-754 binary32 signalling NaN: exponent all ones, quiet bit clear, mantissa != 0."""
    (word,) = struct.unpack("<I", bits)
    return (word & 0x7F800000) == 0x7F800000 and not word & 0x00400000 and word & 0x003FFFFF != 0


def vector_bytes(v: dict[str, Any]) -> bytes:
    return bytes.fromhex(v["hex"])


def message_from_vector(v: dict[str, Any]) -> SmUpdate | Status | RawFrame:
    """Build the message a vector describes from its *fields* (never from a decode)."""
    if v["kind"] == "sm_update":
        f = v["fields"]
        assert set(f) == SM_UPDATE_FIELDS, "vector fields changed: update this test"
        assert f["armed"] in (0, 1)
        kw = {SPEC_TO_MODEL.get(k, k): val for k, val in f.items()}
        kw["armed"] = bool(f["armed"])
        return SmUpdate(**kw, payload_len=v["payload_len"])
    if v["kind"] == "status":
        assert set(v["fields"]) == STATUS_FIELDS, "vector fields changed: update this test"
        return Status(**v["fields"])
    assert v["kind"] == "unknown"
    return RawFrame(type=v["type"], payload=bytes.fromhex(v["payload_hex"]))


def assert_same_float(got: float, want: float, what: str = "") -> None:
    """Exact equality, with the sign of zero preserved."""
    assert got == want, what
    assert math.copysign(1.0, got) == math.copysign(1.0, want), f"{what}: sign of zero lost"


def assert_same_message(got: Any, want: Any) -> None:
    """Field-by-field equality where floats compare by their wire bits (NaN == same NaN).

    Tuple equality is useless for NaN (``nan != nan``) and blind to the sign of zero.  An
    SmUpdate's floats are compared as the binary32 / binary64 they travel as.
    """
    assert type(got) is type(want)
    fmt = "<f" if isinstance(want, SmUpdate) and want.payload_len == 36 else "<d"
    for name in want._fields:
        g, w = getattr(got, name), getattr(want, name)
        if isinstance(w, float):
            assert struct.pack(fmt, g) == struct.pack(fmt, w), name
        else:
            assert type(g) is type(w) and g == w, name


def check_message(msg: Any) -> None:
    """A decoded message is one CRC-valid frame, of the class its type and length call for."""
    raw = msg.raw
    assert is_valid_frame(raw), raw.hex()
    assert type(msg) is expected_class(raw[2], raw[3])
    if isinstance(msg, RawFrame):
        assert msg.type == raw[2] and msg.payload == raw[4:-2]
    elif isinstance(msg, SmUpdate):
        assert msg.payload_len == raw[3]
        assert msg.timestamp_ms == int.from_bytes(raw[4:8], "little")
    else:
        assert msg.timestamp_ms == int.from_bytes(raw[4:8], "little")
        assert msg.flags == raw[10]


def cuts_to_chunks(data: bytes, cuts: Iterable[int]) -> list[bytes]:
    points = [0, *sorted(c for c in cuts if 0 <= c <= len(data)), len(data)]
    return [data[a:b] for a, b in itertools.pairwise(points)]


def run_decoder(chunks: Sequence[bytes]) -> tuple[list[Any], wire.DecoderStats]:
    """Feed ``chunks`` then flush, checking the byte-accounting invariant at every step.

    Invariant: every byte fed is either inside an emitted frame, counted as skipped, or
    still pending; the pending buffer never exceeds one maximal frame; ``frames`` counts
    what was emitted; nothing is pending after ``flush``.
    """
    dec = wire.Decoder()
    out: list[Any] = []

    def check() -> None:
        s = dec.stats
        assert s.bytes_in == s.bytes_skipped + sum(len(m.raw) for m in out) + dec.pending
        assert s.frames == len(out)
        assert 0 <= dec.pending <= MAX_FRAME

    for chunk in chunks:
        out += dec.feed(chunk)
        check()
    out += dec.flush()
    check()
    assert dec.pending == 0
    return out, dec.stats


def raws(msgs: Iterable[Any]) -> list[bytes]:
    return [m.raw for m in msgs]


def is_subsequence(needles: Sequence[bytes], haystack: Sequence[bytes]) -> bool:
    it = iter(haystack)
    return all(any(n == h for h in it) for n in needles)


# -- 1. CRC ---------------------------------------------------------------------------------


def test_crc_check_value_is_mcrf4xx(vectors):
    """The frame CRC has the vector file's (CRC-16/MCRF4XX) check value, not CCITT-FALSE's."""
    check = int(vectors["crc"]["check_123456789"], 16)
    assert check == 0x6F91
    assert wire.crc(b"123456789") == check
    assert binascii.crc_hqx(b"123456789", 0xFFFF) == 0x29B1  # CRC-16/CCITT-FALSE
    assert wire.crc(b"123456789") != binascii.crc_hqx(b"123456789", 0xFFFF)


@FAST
@given(st.binary(max_size=300))
def test_crc_matches_reference_and_pymavlink(data):
    """wire.crc agrees with the bitwise reference and with pymavlink's x25crc (MAVLink's CRC)."""
    assert wire.crc(data) == ref_crc(data) == x25crc(data).crc


def test_vector_crcs_are_little_endian_over_type_len_payload(vector_frame):
    """Each vector's last two bytes are the reference CRC of type..payload, little-endian."""
    raw = vector_bytes(vector_frame)
    assert raw[-2:] == ref_crc(raw[2:-2]).to_bytes(2, "little")


def test_ccitt_false_frame_is_rejected(vector_frame):
    """A frame carrying the CRC-16/CCITT-FALSE of its body is a CRC failure, not a message."""
    raw = vector_bytes(vector_frame)
    body = raw[2:-2]
    bad_crc = binascii.crc_hqx(body, 0xFFFF)
    assert bad_crc != ref_crc(body)  # else this case proves nothing
    forged = raw[:-2] + bad_crc.to_bytes(2, "little")
    dec = wire.Decoder()
    assert dec.feed(forged) + dec.flush() == []
    assert dec.stats.crc_failures >= 1
    assert dec.stats.frames == 0
    assert dec.stats.bytes_skipped == len(forged)


def test_byte_swapped_crc_is_rejected(vectors):
    """The CRC is little-endian on the wire: the big-endian form is a CRC failure."""
    for v in vectors["frames"]:
        raw = vector_bytes(v)
        if raw[-1] != raw[-2]:
            break
    else:  # pragma: no cover
        pytest.fail("no vector with distinct CRC bytes")
    dec = wire.Decoder()
    assert dec.feed(raw[:-2] + raw[-2:][::-1]) + dec.flush() == []
    assert dec.stats.crc_failures >= 1


# -- 2. every vector frame ------------------------------------------------------------------


def test_vector_file_covers_every_kind(vectors):
    """Guard: the vectors exercise both SM_UPDATE revisions, STATUS, unknown types, a stream."""
    frames = vectors["frames"]
    kinds = {(v["kind"], v.get("payload_len")) for v in frames}
    assert {("sm_update", 36), ("sm_update", 64), ("status", None), ("unknown", None)} <= kinds
    assert vectors["streams"], "no stream vectors"


def test_vector_frame_decodes_to_its_fields(vector_frame):
    """The hex decodes, from feed() alone, to exactly one message with the vector's fields."""
    raw = vector_bytes(vector_frame)
    dec = wire.Decoder()
    msgs = dec.feed(raw)
    assert dec.pending == 0
    assert dec.flush() == []
    assert len(msgs) == 1
    (msg,) = msgs
    assert msg.raw == raw
    s = dec.stats
    assert (s.frames, s.bytes_skipped, s.crc_failures, s.bad_lengths) == (1, 0, 0, 0)
    assert s.unknown_types == (1 if vector_frame["kind"] == "unknown" else 0)
    wd = wire.to_wire_dict(msg)

    if vector_frame["kind"] == "sm_update":
        f = vector_frame["fields"]
        assert isinstance(msg, SmUpdate)
        assert msg.payload_len == vector_frame["payload_len"] == len(raw) - 6 == raw[3]
        assert wd["payload_len"] == vector_frame["payload_len"]
        assert wd["type"] == 0x01
        for name in ("timestamp_ms", "state", "sm_type"):
            assert getattr(msg, name) == f[name] == wd[name], name
        assert msg.armed is bool(f["armed"])
        assert wd["armed"] == f["armed"]
        for spec_name, model_name in SPEC_TO_MODEL.items():
            assert_same_float(getattr(msg, model_name), f[spec_name], model_name)
            assert_same_float(wd[spec_name], f[spec_name], spec_name)
    elif vector_frame["kind"] == "status":
        f = vector_frame["fields"]
        assert isinstance(msg, Status)
        assert len(raw) - 6 == raw[3] == 8
        assert wd["type"] == 0x02 and wd["payload_len"] == 8
        for name in STATUS_FIELDS:
            assert getattr(msg, name) == f[name] == wd[name], name
        for bit, name in enumerate(STATUS_FLAG_NAMES):
            want = bool(f["flags"] >> bit & 1)
            assert getattr(msg, name) is want, name
            assert wd[name] is want, name
        assert msg.health() == {
            n: bool(f["flags"] >> b & 1) for b, n in enumerate(STATUS_FLAG_NAMES)
        }
    else:
        assert isinstance(msg, RawFrame)
        assert msg.type == vector_frame["type"]
        assert msg.payload.hex() == vector_frame["payload_hex"]
        assert wd == {
            "type": vector_frame["type"],
            "payload_len": len(msg.payload),
            "payload_hex": vector_frame["payload_hex"],
        }


def test_vector_fields_encode_to_the_hex(vector_frame):
    """A message built from the vector's fields (not from a decode) encodes to its hex."""
    msg = message_from_vector(vector_frame)
    assert wire.encode(msg).hex() == vector_frame["hex"]


def test_vector_decode_equals_message_built_from_fields(vector_frame):
    """Decoding equals the field-built message (plus raw), compared bit-exactly."""
    raw = vector_bytes(vector_frame)
    (msg,) = wire.decode_all(raw)
    assert_same_message(msg, message_from_vector(vector_frame)._replace(raw=raw))


def test_unknown_machine_and_state_are_kept_as_numbers(vectors):
    """sm_type 3 / state 17: decoded, not rejected; named STATE_17; -0.0 keeps its sign."""
    matches = [
        v
        for v in vectors["frames"]
        if v["kind"] == "sm_update" and v["fields"]["state"] == 17 and v["fields"]["sm_type"] == 3
    ]
    assert matches, "vector with sm_type 3 / state 17 missing"
    for v in matches:
        (msg,) = wire.decode_all(vector_bytes(v))
        assert (msg.sm_type, msg.state) == (3, 17)
        assert msg.state_name == "STATE_17"
        assert wire.to_wire_dict(msg)["state_name"] == "STATE_17"
        assert not msg.in_flight and not msg.on_pad
        assert msg.timestamp_ms == 0xFFFFFFFF
        assert math.copysign(1.0, msg.altitude_m) == -1.0
        assert math.copysign(1.0, msg.acceleration_mps2) == 1.0


def test_origin_is_stamped_on_every_message(vectors):
    """Decoder(origin) labels each message with its source (loop prevention)."""
    data = b"".join(vector_bytes(v) for v in vectors["frames"])
    msgs = wire.decode_all(data, origin="radio0")
    assert len(msgs) == len(vectors["frames"])
    assert all(m.origin == "radio0" for m in msgs)


def test_armed_byte_other_than_one_reads_as_armed():
    """Out-of-spec armed byte (2) is decoded as armed (C truthiness), not rejected.

    The model keeps ``armed`` as a bool, so re-encoding writes 1: the byte-exact round trip
    below therefore only draws armed bytes 0 and 1.
    """
    payload = struct.pack("<IBBBB7f", 1, 2, 2, 0, 0, *([0.0] * 7))
    (msg,) = wire.decode_all(make_frame(0x01, payload))
    assert msg.armed is True


# -- 3. the stream vector -------------------------------------------------------------------


def test_stream_vector_yields_exactly_its_intact_frames(vector_stream):
    """Garbage, false sync, corrupted copy, truncated tail: exactly the intact frames survive."""
    data = vector_bytes(vector_stream)
    intact = [bytes.fromhex(h) for h in vector_stream["intact_frames"]]
    assert intact
    msgs, stats = run_decoder([data])
    assert raws(msgs) == intact
    for m in msgs:
        check_message(m)
    assert stats.bytes_in == len(data)
    assert stats.frames == len(intact)
    assert stats.crc_failures >= 1
    assert stats.bytes_skipped == len(data) - sum(len(f) for f in intact)


# -- 4. splitting never changes the result --------------------------------------------------


def _split_sources(vectors) -> dict[str, bytes]:
    return {
        "stream": vector_bytes(vectors["streams"][0]),
        "all_frames": b"".join(vector_bytes(v) for v in vectors["frames"]),
    }


@pytest.mark.parametrize("source", ["stream", "all_frames"])
def test_whole_bytewise_and_seeded_random_splits_agree(vectors, source):
    """Whole, one byte at a time and 50 seeded random splits give identical messages and stats."""
    data = _split_sources(vectors)[source]
    whole, whole_stats = run_decoder([data])
    assert whole
    bytewise, bytewise_stats = run_decoder([data[i : i + 1] for i in range(len(data))])
    assert bytewise == whole
    assert bytewise_stats.as_dict() == whole_stats.as_dict()
    rng = random.Random(20260426)
    for _ in range(50):
        cuts = rng.sample(range(len(data) + 1), rng.randint(1, 40))
        msgs, stats = run_decoder(cuts_to_chunks(data, cuts))
        assert msgs == whole, cuts
        assert stats.as_dict() == whole_stats.as_dict(), cuts


@FAST
@given(data=st.data())
def test_hypothesis_splits_agree(vectors, data):
    """Hypothesis-drawn split points (incl. empty chunks) give the same messages and stats."""
    source = data.draw(st.sampled_from(["stream", "all_frames"]))
    stream = _split_sources(vectors)[source]
    cuts = data.draw(st.lists(st.integers(0, len(stream)), max_size=60))
    whole, whole_stats = run_decoder([stream])
    msgs, stats = run_decoder(cuts_to_chunks(stream, cuts))
    assert msgs == whole
    assert stats.as_dict() == whole_stats.as_dict()


def test_concatenated_vector_frames_all_decode_in_order(vectors):
    """Back-to-back frames of every kind decode one-for-one, equal to their single decodes."""
    frames = [vector_bytes(v) for v in vectors["frames"]]
    msgs, stats = run_decoder([b"".join(frames)])
    assert raws(msgs) == frames
    assert msgs == [wire.decode_all(f)[0] for f in frames]
    assert stats.bytes_skipped == 0 and stats.crc_failures == 0


def test_trailing_partial_frame_is_held_then_completed(vectors):
    """A frame cut anywhere is held (pending == bytes so far) and completes with the rest."""
    frames = [vector_bytes(v) for v in vectors["frames"]]
    for idx, tail in enumerate(frames):
        head = frames[idx - 1]  # some other complete frame before it
        for k in range(1, len(tail)):
            dec = wire.Decoder()
            assert raws(dec.feed(head + tail[:k])) == [head], (idx, k)
            assert dec.pending == k, (idx, k)
            assert raws(dec.feed(tail[k:])) == [tail], (idx, k)
            assert dec.pending == 0
            assert dec.stats.bytes_skipped == 0


def test_truncated_tail_is_skipped_on_flush(vectors):
    """At end of input a partial frame is dropped and counted as skipped, never emitted."""
    raw = vector_bytes(vectors["frames"][0])
    for k in (1, 2, 3, 4, len(raw) - 1):
        dec = wire.Decoder()
        assert dec.feed(raw[:k]) == []
        assert dec.pending == k
        assert dec.flush() == []
        assert dec.pending == 0
        assert dec.stats.bytes_skipped == k
        assert dec.stats.crc_failures == 0


# -- 5. wrong lengths and unknown types -----------------------------------------------------


@pytest.mark.parametrize(
    ("ftype", "length"),
    [
        (0x01, 20),
        (0x01, 0),
        (0x01, 35),
        (0x01, 37),
        (0x01, 63),
        (0x01, 65),
        (0x01, 8),
        (0x01, 255),
        (0x02, 0),
        (0x02, 7),
        (0x02, 9),
        (0x02, 36),
        (0x02, 64),
        (0x02, 255),
    ],
)
def test_known_type_with_wrong_length_is_raw_and_counted(ftype, length):
    """SM_UPDATE not 36/64 or STATUS not 8 bytes: relayed as RawFrame, counted in bad_lengths."""
    payload = bytes(range(length))
    raw = make_frame(ftype, payload)
    dec = wire.Decoder()
    msgs = dec.feed(raw) + dec.flush()
    assert msgs == [RawFrame(type=ftype, payload=payload, raw=raw)]
    s = dec.stats
    assert (s.frames, s.bad_lengths, s.unknown_types, s.crc_failures) == (1, 1, 0, 0)


@pytest.mark.parametrize(
    ("ftype", "length"), [(0x00, 0), (0x03, 8), (0x7F, 36), (0xA5, 64), (0x5A, 1), (0xFF, 255)]
)
def test_unknown_type_is_raw_and_counted(ftype, length):
    """A CRC-valid frame of an unknown type is passed on as RawFrame and counted."""
    payload = bytes((i * 7) & 0xFF for i in range(length))
    raw = make_frame(ftype, payload)
    dec = wire.Decoder()
    msgs = dec.feed(raw) + dec.flush()
    assert msgs == [RawFrame(type=ftype, payload=payload, raw=raw)]
    s = dec.stats
    assert (s.frames, s.unknown_types, s.bad_lengths, s.crc_failures) == (1, 1, 0, 0)


def test_counters_accumulate_over_a_mixed_stream():
    """Counters add up across frames: 2 unknown, 3 bad lengths, 1 CRC failure."""
    good = make_frame(0x02, bytes(8))
    corrupt = bytearray(make_frame(0x01, bytes(36)))
    corrupt[10] ^= 0x40
    parts = [
        make_frame(0x09, b"x"),
        make_frame(0x01, bytes(20)),
        bytes(corrupt),
        good,
        make_frame(0x02, b""),
        make_frame(0x01, bytes(1)),
        make_frame(0xEE, b""),
    ]
    msgs, s = run_decoder([b"".join(parts)])
    assert raws(msgs) == [p for p in parts if p != bytes(corrupt)]
    assert (s.unknown_types, s.bad_lengths, s.crc_failures) == (2, 3, 1)
    assert s.bytes_skipped == len(corrupt)


# -- 6. false sync with a long claimed length -----------------------------------------------

FALSE_SYNC = bytes.fromhex("a55a01f0")  # claims 240 payload bytes: 246 bytes from the sync
FALSE_SYNC_SPAN = 4 + 0xF0 + 2


def _short_burst(vectors) -> list[bytes]:
    """One frame of each kind, well under 240 bytes in total."""
    picked: dict[tuple, bytes] = {}
    for v in vectors["frames"]:
        picked.setdefault((v["kind"], v.get("payload_len")), vector_bytes(v))
    burst = list(picked.values())
    assert sum(map(len, burst)) < FALSE_SYNC_SPAN - 4
    return burst


def test_false_sync_holds_frames_until_flush(vectors):
    """Good frames behind an unrefuted long false sync wait in pending; flush() releases them."""
    burst = _short_burst(vectors)
    data = FALSE_SYNC + b"".join(burst)
    dec = wire.Decoder()
    assert dec.feed(data) == []
    assert dec.pending == len(data)
    assert raws(dec.flush()) == burst
    assert dec.pending == 0
    assert dec.stats.bytes_skipped == len(FALSE_SYNC)


def test_false_sync_refuted_at_exactly_its_claimed_length(vectors):
    """Held while the false frame could still complete; released by feed() once it is whole."""
    burst = _short_burst(vectors)
    data = FALSE_SYNC + b"".join(burst)
    filler = bytes(FALSE_SYNC_SPAN - 1 - len(data))
    dec = wire.Decoder()
    assert dec.feed(data) == []
    assert dec.feed(filler) == []
    assert dec.pending == FALSE_SYNC_SPAN - 1
    assert raws(dec.feed(b"\x00")) == burst  # byte 246 from the sync: CRC checked, fails
    assert dec.stats.crc_failures == 1
    assert dec.pending == 0
    assert dec.flush() == []


def test_false_sync_refuted_by_following_frames(vectors):
    """≥ 246 bytes of good frames after the sync come out of feed() alone, byte-wise too."""
    frames = [vector_bytes(v) for v in vectors["frames"]]
    data = FALSE_SYNC + b"".join(frames)
    assert len(data) - len(FALSE_SYNC) >= 246  # far more than the false frame claims
    dec = wire.Decoder()
    assert raws(dec.feed(data)) == frames
    assert dec.pending == 0
    dec = wire.Decoder()
    out = []
    for i in range(len(data)):
        out += dec.feed(data[i : i + 1])
    assert raws(out) == frames


# -- 7a. arbitrary bytes --------------------------------------------------------------------

#: Bytes biased towards sync bytes and the interesting lengths, so false syncs are common.
frame_ish_bytes = st.lists(
    st.one_of(
        st.sampled_from([0xA5, 0x5A, 0x01, 0x02, 0x08, 0x24, 0x40, 0x00, 0xFF]), st.integers(0, 255)
    ),
    max_size=1200,
).map(bytes)


@MEDIUM
@given(blob=st.one_of(st.binary(max_size=1200), frame_ish_bytes), data=st.data())
def test_arbitrary_bytes_never_raise_and_account_for_every_byte(blob, data):
    """Any bytes, any split: no exception, invariant holds after each step, splits agree."""
    cuts = data.draw(st.lists(st.integers(0, len(blob)), max_size=40))
    whole, whole_stats = run_decoder([blob])
    split, split_stats = run_decoder(cuts_to_chunks(blob, cuts))
    assert raws(split) == raws(whole)
    assert split_stats.as_dict() == whole_stats.as_dict()
    for m in whole:
        check_message(m)


# -- 7b. recovery from corruption -----------------------------------------------------------


@st.composite
def valid_frames(draw) -> bytes:
    """A valid frame: SM_UPDATE 36/64, STATUS 8, or any type with any length 0..255."""
    kind = draw(st.sampled_from(["sm36", "sm64", "status", "any"]))
    if kind == "any":
        ftype, length = draw(st.integers(0, 255)), draw(st.integers(0, 255))
    else:
        ftype, length = {"sm36": (1, 36), "sm64": (1, 64), "status": (2, 8)}[kind]
    return make_frame(ftype, draw(st.binary(min_size=length, max_size=length)))


@st.composite
def corrupted_copies(draw) -> bytes:
    """A valid frame, possibly truncated, with 1..3 byte flips (at least one change)."""
    raw = draw(valid_frames())
    copy = bytearray(raw[: draw(st.integers(1, len(raw)))])
    min_flips = 1 if len(copy) == len(raw) else 0
    for _ in range(draw(st.integers(min_flips, 3))):
        copy[draw(st.integers(0, len(copy) - 1))] ^= draw(st.integers(1, 255))
    return bytes(copy)


garbage = st.one_of(st.binary(max_size=80), frame_ish_bytes.map(lambda b: b[:80]))
pieces = st.lists(
    st.one_of(
        valid_frames().map(lambda f: ("frame", f)),
        corrupted_copies().map(lambda f: ("corrupt", f)),
        garbage.map(lambda g: ("garbage", g)),
    ),
    max_size=14,
)


def swallowing_candidates(stream: bytes, starts: set[int]) -> list[tuple[int, int]]:
    """Spans of CRC-valid frames in ``stream`` that do not start at a planted frame.

    Only such a span can make the decoder jump over a planted frame's start: the one-byte
    resync visits every position it has not consumed as part of a CRC-valid frame.
    """
    spans = []
    i = stream.find(MAGIC)
    while i >= 0:
        if i not in starts and i + 4 <= len(stream):
            end = i + 6 + stream[i + 3]
            if end <= len(stream) and is_valid_frame(stream[i:end]):
                spans.append((i, end))
        i = stream.find(MAGIC, i + 1)
    return spans


@MEDIUM
@given(parts=pieces, cuts=st.lists(st.integers(0, 1 << 16), max_size=30))
@example(parts=[("corrupt", FALSE_SYNC), ("frame", make_frame(2, bytes(8)))], cuts=[])
@example(
    parts=[
        ("garbage", b"\xa5"),
        ("frame", make_frame(1, bytes(36))),
        ("garbage", b"\xa5\x5a"),
        ("frame", make_frame(0x10, b"")),
    ],
    cuts=[1, 2, 3, 45],
)
def test_every_untouched_frame_is_recovered(parts, cuts):
    """Valid frames amid garbage and corrupted copies all come out, in order (any split)."""
    stream = b""
    planted: list[tuple[int, bytes]] = []
    for kind, chunk in parts:
        if kind == "frame":
            planted.append((len(stream), chunk))
        stream += chunk
    starts = {o for o, _ in planted}
    spans = swallowing_candidates(stream, starts)
    # A planted frame is guaranteed only if no CRC-valid accidental frame straddles its start
    # (a ~2**-16 chance per false sync; such an accident legitimately consumes it).
    expected = [f for o, f in planted if not any(a < o < b for a, b in spans)]
    if len(expected) != len(planted):
        event("a planted frame was straddled by an accidental valid frame")

    msgs, stats = run_decoder(cuts_to_chunks(stream, [c % (len(stream) + 1) for c in cuts]))
    got = raws(msgs)
    assert is_subsequence(expected, got)
    for m in msgs:
        check_message(m)
    assert stats.bytes_in == len(stream)


# -- 7c. round trips ------------------------------------------------------------------------

u32 = st.integers(0, 0xFFFFFFFF)
u8 = st.integers(0, 0xFF)
#: Messages built in memory: no raw frame, no provenance (st.builds would otherwise fill it).
IN_MEMORY = {"raw": st.just(b""), "origin": st.just(""), "via": st.just(""),
             "vehicle": st.just("")}


def sm_updates(payload_len: int) -> st.SearchStrategy[SmUpdate]:
    # f32 revision: only f32-representable values can survive the wire unchanged.
    fl = st.floats(width=32) if payload_len == 36 else st.floats()
    return st.builds(
        SmUpdate,
        timestamp_ms=u32,
        state=u8,
        armed=st.booleans(),
        sm_type=u8,
        altitude_m=fl,
        acceleration_mps2=fl,
        accel_vert_mps2=fl,
        velocity_mps=fl,
        roll_rad=fl,
        pitch_rad=fl,
        yaw_rad=fl,
        payload_len=st.just(payload_len),
        reserved=u8,
        **IN_MEMORY,
    )


statuses = st.builds(
    Status, timestamp_ms=u32, state=u8, sm_type=u8, flags=u8, reserved=u8, **IN_MEMORY
)
raw_frames = st.builds(RawFrame, type=u8, payload=st.binary(max_size=255), **IN_MEMORY).filter(
    lambda m: expected_class(m.type, len(m.payload)) is RawFrame
)
messages = st.one_of(sm_updates(36), sm_updates(64), statuses, raw_frames)


@MEDIUM
@given(messages)
@example(
    SmUpdate(0, 0, False, 0, -0.0, math.inf, -math.inf, math.nan, 0.0, -0.0, 1.5, payload_len=36)
)
@example(
    SmUpdate(
        0xFFFFFFFF,
        255,
        True,
        255,
        -0.0,
        math.inf,
        -math.inf,
        math.nan,
        5e-324,
        -1.7976931348623157e308,
        1.5,
        payload_len=64,
        reserved=255,
    )
)
def test_decode_of_encode_is_identity(msg):
    """decode(encode(m)) == m (with raw = the frame), bit-exact floats incl. NaN/inf/-0.0."""
    raw = wire.encode(msg)
    assert is_valid_frame(raw)
    msgs, stats = run_decoder([raw])
    assert len(msgs) == 1
    assert_same_message(msgs[0], msg._replace(raw=raw))
    assert stats.bytes_skipped == 0


F32_SPECIALS = [struct.pack("<f", x) for x in (math.inf, -math.inf, -0.0, 0.0, math.nan)] + [
    bytes.fromhex("0100c07f"),  # quiet NaN with a payload
    bytes.fromhex("ffffffff"),  # negative quiet NaN, all payload bits set
    bytes.fromhex("01000000"),  # smallest subnormal
]
F64_SPECIALS = [struct.pack("<d", x) for x in (math.inf, -math.inf, -0.0, 0.0, math.nan)] + [
    bytes.fromhex("010000000000f87f"),  # quiet NaN with a payload
    bytes.fromhex("010000000000f07f"),  # signalling NaN: a C double keeps it bit-exact
    bytes.fromhex("ffffffffffffffff"),
]


@st.composite
def decodable_frames(draw) -> bytes:
    """A valid frame of a decodable (type, length) with random payload bytes.

    Floats are random bits or special patterns (NaN with payloads, ±inf, ±0, subnormal).
    The armed byte is 0 or 1 (the model keeps a bool; see the armed test above).
    """
    kind = draw(st.sampled_from(["sm36", "sm64", "status"]))
    if kind == "status":
        return make_frame(0x02, draw(st.binary(min_size=8, max_size=8)))
    width, specials = (4, F32_SPECIALS) if kind == "sm36" else (8, F64_SPECIALS)
    head = bytearray(draw(st.binary(min_size=8, max_size=8)))
    head[5] = draw(st.integers(0, 1))
    floats = [
        draw(st.one_of(st.binary(min_size=width, max_size=width), st.sampled_from(specials)))
        for _ in range(7)
    ]
    if width == 4:
        # A binary32 signalling NaN cannot survive a Python float: unpacking widens it to a
        # C double, and the float->double conversion (cvtss2sd on x86, fcvt on ARM) sets the
        # quiet bit; packing it back then yields the quiet NaN.  Its NaN-ness survives (see
        # test_f32_signalling_nan_stays_nan), its bits do not.  A binary64 sNaN is copied
        # bit for bit, so the f64 revision has no such exception.
        assume(not any(f32_is_signalling_nan(f) for f in floats))
    return make_frame(0x01, bytes(head) + b"".join(floats))


@MEDIUM
@given(decodable_frames())
def test_encode_of_decode_is_identity(raw):
    """encode(decode(frame)) == frame for SM_UPDATE 36/64 and STATUS with random payloads."""
    (msg,) = wire.decode_all(raw)
    assert type(msg) is expected_class(raw[2], raw[3])
    assert wire.encode(msg) == raw


@FAST
@given(st.integers(0, 255), st.binary(max_size=255))
def test_encode_of_decode_is_identity_for_raw_frames(ftype, payload):
    """Any type/length, decodable or not, re-encodes to the same bytes (f32 sNaN aside)."""
    raw = make_frame(ftype, payload)
    if ftype == 1 and len(payload) == 36:
        assume(not any(f32_is_signalling_nan(payload[o : o + 4]) for o in range(8, 36, 4)))
    if ftype == 1 and len(payload) in (36, 64):
        assume(payload[5] in (0, 1))
    (msg,) = wire.decode_all(raw)
    assert wire.encode(msg) == raw


@pytest.mark.parametrize("kind", ["sm36", "sm64", "status"])
def test_encode_keeps_the_low_32_bits_of_the_timestamp(kind):
    """timestamp_ms is the uptime's low 32 bits on the wire: a longer uptime wraps, no error."""
    ts = (1 << 32) * 3 + 12345
    if kind == "status":
        msg: Any = Status(ts, 1, 0, 0)
    else:
        msg = SmUpdate(ts, 1, False, 0, *([0.0] * 7), payload_len=36 if kind == "sm36" else 64)
    (back,) = wire.decode_all(wire.encode(msg))
    assert back.timestamp_ms == 12345


def test_f32_signalling_nan_stays_nan():
    """The documented exception: an f32 sNaN decodes to NaN and re-encodes as a NaN."""
    snan = bytes.fromhex("0100807f")
    assert f32_is_signalling_nan(snan)
    payload = struct.pack("<IBBBB", 7, 2, 1, 0, 0) + snan + bytes(24)
    (msg,) = wire.decode_all(make_frame(0x01, payload))
    assert math.isnan(msg.altitude_m)
    again = wire.encode(msg)
    assert is_valid_frame(again)
    assert again[:12] == make_frame(0x01, payload)[:12]
    assert again[16:-2] == payload[12:]
    (msg2,) = wire.decode_all(again)
    assert math.isnan(msg2.altitude_m)


@FAST
@given(st.integers(0, 255), st.binary(max_size=255))
def test_frame_helper_matches_reference(ftype, payload):
    """wire.frame() builds the spec's layout, identical to the independent reference."""
    assert wire.frame(ftype, payload) == make_frame(ftype, payload)


# -- 8. encode() errors ---------------------------------------------------------------------


@pytest.mark.parametrize("payload_len", [0, 8, 35, 37, 63, 65, 255])
def test_encode_rejects_unknown_sm_update_revision(payload_len):
    """Only the 36-byte (f32) and 64-byte (f64) SM_UPDATE revisions exist."""
    msg = SmUpdate(1, 2, True, 0, *([0.0] * 7), payload_len=payload_len)
    with pytest.raises(ValueError, match="payload_len"):
        wire.encode(msg)


@pytest.mark.parametrize("size", [256, 1000])
def test_encode_rejects_oversized_payload(size):
    """Payload > 255 bytes: the codec's own ValueError (naming the limit), not an accident."""
    with pytest.raises(ValueError, match="255"):
        wire.encode(RawFrame(type=0x42, payload=bytes(size)))
    with pytest.raises(ValueError, match="255"):
        wire.frame(0x42, bytes(size))


def test_encode_accepts_largest_payload():
    """255 bytes is the limit, not past it: a 261-byte frame encodes and is valid."""
    raw = wire.encode(RawFrame(type=0x42, payload=bytes(255)))
    assert len(raw) == MAX_FRAME and is_valid_frame(raw)


@pytest.mark.parametrize("ftype", [-1, 256])
def test_encode_rejects_type_that_is_not_a_byte(ftype):
    """The type field is one byte."""
    with pytest.raises(ValueError):
        wire.encode(RawFrame(type=ftype, payload=b""))


@pytest.mark.parametrize(
    "obj",
    [
        None,
        b"\xa5\x5a\x10\x00",
        "status",
        (1, 2, 0, 0, 0, b"", ""),
        LinkEvent(source="radio0", up=True),
    ],
    ids=["None", "bytes", "str", "plain-tuple", "LinkEvent"],
)
def test_encode_rejects_non_wire_messages(obj):
    """Anything but SmUpdate/Status/RawFrame (even a same-shaped tuple) is a TypeError."""
    with pytest.raises(TypeError):
        wire.encode(obj)
