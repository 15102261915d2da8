"""gateway.resync: the one resync rule, on a toy protocol (0xAA, length, payload, xor check)."""

from __future__ import annotations

from functools import reduce

from hypothesis import given
from hypothesis import strategies as st

from gateway.resync import BAD, WAIT, ResyncDecoder

SYNC = 0xAA


def frame(payload: bytes) -> bytes:
    return bytes((SYNC, len(payload))) + payload + bytes((reduce(int.__xor__, payload, 0),))


class Toy(ResyncDecoder[bytes]):
    __slots__ = ("bad", "bytes_in", "skipped")

    def __init__(self) -> None:
        super().__init__()
        self.bad = self.bytes_in = self.skipped = 0

    def _find_start(self, buf: bytes, pos: int) -> int:
        return buf.find(SYNC, pos)

    def _frame_at(self, buf: bytes, i: int, out: list[bytes]) -> int:
        if i + 2 > len(buf):
            return WAIT
        length = buf[i + 1]
        if not 1 <= length <= 8:
            self.bad += 1
            return BAD
        end = i + 3 + length
        if end > len(buf):
            return WAIT
        payload = buf[i + 2:end - 1]
        if reduce(int.__xor__, payload, 0) != buf[end - 1]:
            self.bad += 1
            return BAD
        out.append(payload)
        return end

    def _count(self, bytes_in: int, skipped: int) -> None:
        self.bytes_in += bytes_in
        self.skipped += skipped


def test_frames_between_garbage_and_the_skip_count() -> None:
    d = Toy()
    data = b"\x01\x02" + frame(b"ab") + b"\x03" + frame(b"c")
    assert d.feed(data) == [b"ab", b"c"]
    assert (d.bytes_in, d.skipped, d.bad, d.pending) == (len(data), 3, 0, 0)


def test_a_partial_frame_is_held_back_until_it_completes() -> None:
    d = Toy()
    f = frame(b"xyz")
    assert d.feed(b"\x00" + f[:4]) == []
    assert d.pending == 4 and d.skipped == 1
    assert d.feed(f[4:]) == [b"xyz"]
    assert d.pending == 0


def test_a_bad_frame_drops_one_byte_so_a_frame_behind_it_is_found() -> None:
    d = Toy()
    inner = frame(b"ok")
    # a false start claiming 3 payload bytes swallows the real frame's first bytes; its check
    # fails, and rescanning from the next byte finds the real frame
    data = bytes((SYNC, 3)) + inner
    assert d.feed(data) == [b"ok"]
    assert d.bad == 1 and d.skipped == 2


def test_flush_skips_a_tail_that_cannot_complete_and_rescans_it() -> None:
    d = Toy()
    data = bytes((SYNC, 8)) + frame(b"k")  # the long false start waits for bytes never sent
    assert d.feed(data) == []
    assert d.flush() == [b"k"]
    assert d.skipped == 2 and d.pending == 0
    assert d.flush() == []


@given(st.lists(st.one_of(st.binary(min_size=1, max_size=8).map(frame),
                          st.binary(max_size=5)), max_size=20),
       st.lists(st.integers(min_value=1, max_value=9), min_size=1, max_size=10))
def test_any_split_gives_the_same_records_and_counts(parts: list[bytes],
                                                     cuts: list[int]) -> None:
    data = b"".join(parts)
    whole = Toy()
    expected = whole.feed(data) + whole.flush()
    split = Toy()
    got: list[bytes] = []
    pos = k = 0
    while pos < len(data):
        step = cuts[k % len(cuts)]
        got += split.feed(data[pos:pos + step])
        pos += step
        k += 1
    got += split.flush()
    assert got == expected
    assert (split.skipped, split.bad, split.bytes_in) == (whole.skipped, whole.bad, len(data))
    assert split.skipped + sum(len(r) + 3 for r in got) == len(data)
