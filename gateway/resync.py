"""The project's one resync rule, for the sans-I/O stream decoders (CRSF, UAVTalk, XBee API).

Find a frame start; check what the protocol can check there (length bound, CRC …); a whole
valid frame is consumed, a frame that has not fully arrived is held back for the next
:meth:`~ResyncDecoder.feed`, and on any failure *one* byte is dropped and the scan resumes
(never the claimed length, so a frame hiding behind a corrupted length is still found).
Every byte outside a consumed frame is counted as skipped.  A protocol supplies three small
hooks: where the next start is, what stands at a start, and which of its counters the bytes go
to.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Generic, TypeVar

T = TypeVar("T")

#: :meth:`ResyncDecoder._frame_at`: the frame at the start has not fully arrived.
WAIT = -1
#: :meth:`ResyncDecoder._frame_at`: no valid frame at the start (the hook counted why).
BAD = -2


class BufferedDecoder(ABC, Generic[T]):
    """Bytes in, records of type ``T`` out: holds back an incomplete frame between feeds.

    A decoder implements :meth:`_decode`; :class:`ResyncDecoder` does it by the resync rule
    from three small hooks, a decoder tuned for speed (:mod:`gateway.wire`) with its own loop.
    """

    __slots__ = ("_buf",)

    def __init__(self) -> None:
        self._buf = b""

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._buf)

    def feed(self, data: bytes) -> list[T]:
        """Add bytes; return every record completed by them, in stream order (any split of a
        stream gives the same records)."""
        buf = self._buf + bytes(data) if self._buf else bytes(data)
        return self._decode(buf, len(data), eof=False)

    def flush(self) -> list[T]:
        """End of input: rescan what is held back; a tail that cannot complete is skipped."""
        return self._decode(self._buf, 0, eof=True) if self._buf else []

    @abstractmethod
    def _decode(self, buf: bytes, bytes_in: int, eof: bool) -> list[T]:
        """The records in ``buf`` (what was held back, then ``bytes_in`` new bytes); keeps in
        ``_buf`` what must wait for more (nothing at ``eof``) and counts what it skipped."""


class ResyncDecoder(BufferedDecoder[T]):
    """A decoder by the resync rule: a protocol gives where a frame may start, what stands
    there and which counters the bytes go to.

    The retained buffer never exceeds one frame: everything before a pending start is decided
    at once.
    """

    __slots__ = ()

    def _decode(self, buf: bytes, bytes_in: int, eof: bool) -> list[T]:
        out: list[T] = []
        n = len(buf)
        pos = skipped = 0
        find = self._find_start
        frame_at = self._frame_at
        while True:
            i = find(buf, pos)
            if i < 0:
                skipped += n - pos
                pos = n
                break
            end = frame_at(buf, i, out)
            if end > i:  # a whole frame: consumed
                skipped += i - pos
                pos = end
            elif end == WAIT and not eof:
                skipped += i - pos
                pos = i
                break
            else:  # no frame here (or one that can never complete): drop one byte, rescan
                skipped += i + 1 - pos
                pos = i + 1
        self._buf = buf[pos:]
        self._count(bytes_in, skipped)
        return out

    @abstractmethod
    def _find_start(self, buf: bytes, pos: int) -> int:
        """Index of the first possible frame start at or after ``pos``; -1 if there is none."""

    @abstractmethod
    def _frame_at(self, buf: bytes, i: int, out: list[T]) -> int:
        """Look at the start ``buf[i]``: a valid frame's end index (after appending what it
        decodes to, if anything, to ``out``), or :data:`WAIT` or :data:`BAD`."""

    @abstractmethod
    def _count(self, bytes_in: int, skipped: int) -> None:
        """Add the bytes fed and the bytes skipped to the protocol's counters."""
