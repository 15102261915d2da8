"""The CRSF backend's own pseudo-terminal (``url = "pty"``, the no-hardware default run).

:class:`PtyPair` creates the pair: the backend's :class:`~gateway.io.port.PortEngine` owns the
master end (through :meth:`PtyPair.port`) and a user, or a test, attaches a reader to
:attr:`PtyPair.path`, as EdgeTX would read the receiver's UART.  What the reader writes back
(link statistics, RC channels) is read from the master by the engine like any other port.

**The backlog bound.**  Writes never block, and while nobody reads, at most
``backlog_bytes`` wait unread: a reader attaching late sees the newest bytes, then what comes
next, never a stale backlog.  The kernel cannot be asked how much waits: ``FIONREAD`` on the
slave counts only the line discipline's buffer, not the bytes a write to the master left in
the tty's flip buffer, which a kernel worker moves over asynchronously (in a burst it reports
100 B while 3000 B wait).  So the bound rests on our own accounting instead:

* every byte that waits unread was written by us since the moment we last knew how much was
  waiting, so ``_unsure`` (the bytes written since then, plus what was waiting then) is an
  upper bound on the backlog whatever the kernel's timing;
* while ``_unsure`` plus the next write fits in ``backlog_bytes``, the write goes straight to
  the master;
* otherwise we learn the exact backlog by reading everything that waits through the slave fd
  the pair holds (a non-blocking read on a tty waits for the flip buffer's worker before it
  reports "nothing more", so nothing in flight is missed), keep the newest
  ``backlog_bytes - len(data)`` of it, write those back to the master, and start counting
  again from that exact figure.

A reader that keeps up costs one such check per ``backlog_bytes`` written, which finds nothing
to discard: it loses nothing.  Bytes taken while a reader is reading at that very instant are
written back at once, so a frame may be split (CRSF's CRC catches it) but is not dropped
unless the backlog is over the bound.  The bound holds for backlogs up to the line
discipline's 4 KiB (the default is 1 KiB) while the slave stays in raw mode, as the pair sets
it (a reader that switches it to canonical mode gets its lines, unbounded).
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import struct
import termios
import threading
import tty

log = logging.getLogger(__name__)

PTY_BACKLOG_BYTES = 1024  # about five seconds of telemetry at 20 frames/s
MAX_BACKLOG_BYTES = 4095  # what the line discipline holds (N_TTY_BUF_SIZE − 1)
_READ_SIZE = 65536


class PtyPort:
    """The master end as a port for :class:`gateway.io.port.PortEngine`.

    Reads return what the reader wrote to the slave (``b""`` when nothing waits); writes go
    through the pair's backlog bound.  Closing it leaves the pty to its owner, so an engine
    that reopens gets the same pair and the reader keeps its path."""

    def __init__(self, pty: PtyPair) -> None:
        self._pty = pty

    def fileno(self) -> int:
        return self._pty.master

    def read(self, size: int = _READ_SIZE) -> bytes:
        return self._pty.read(size)

    def write(self, data: bytes) -> int:
        return self._pty.write(data)

    def close(self) -> None:
        pass


class PtyPair:
    """A pseudo-terminal pair: the backend owns the master, a reader attaches to ``path``.

    The slave end is held open (so the pair survives readers coming and going, and the
    backlog can be measured through it) and put in raw mode (no echo, no CR/LF translation,
    no XON/XOFF: CRSF is binary).  See the module docstring for the backlog bound.
    """

    def __init__(self, backlog_bytes: int = PTY_BACKLOG_BYTES) -> None:
        if not 0 < backlog_bytes <= MAX_BACKLOG_BYTES:
            raise ValueError(f"backlog_bytes must be 1..{MAX_BACKLOG_BYTES}")
        self.backlog_bytes = backlog_bytes
        self.flushes = 0  # times unread bytes were discarded
        self.discarded_bytes = 0  # unread bytes discarded (the oldest)
        self.dropped_bytes = 0  # bytes not written at all (the pty stayed full)
        self.checks = 0  # times the backlog was measured
        self._unsure = 0  # upper bound on the bytes waiting unread (module docstring)
        self._closed = False
        self._lock = threading.Lock()
        self.master, self._slave = os.openpty()
        try:
            tty.setraw(self._slave)
            os.set_blocking(self.master, False)
            os.set_blocking(self._slave, False)  # our own open file only, not a reader's
            self.path = os.ttyname(self._slave)
        except Exception:
            self.close()
            raise

    def port(self) -> PtyPort:
        """The master end, for the port engine (an opener: raises once the pair is closed)."""
        if self._closed:
            raise OSError("pty closed")
        return PtyPort(self)

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def backlog_bound(self) -> int:
        """The most bytes that can be waiting unread now (our accounting, not the kernel's)."""
        return self._unsure

    def _unread(self) -> int:
        """Bytes in the slave's line discipline (``FIONREAD``): a lower bound on the backlog
        (bytes the kernel has not moved out of its flip buffer yet are not counted)."""
        return struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0]

    def _take_unread(self) -> bytes:
        """Everything waiting unread, oldest first, read (and so removed) through our slave
        fd; ends when the kernel reports nothing more, flip buffer included."""
        parts = []
        while True:
            try:
                chunk = os.read(self._slave, _READ_SIZE)
            except (BlockingIOError, InterruptedError):
                break
            if not chunk:
                break
            parts.append(chunk)
        return b"".join(parts)

    def _write_all(self, data: bytes) -> None:
        view = memoryview(data)
        retried = False
        while view:
            try:
                n = os.write(self.master, view)
            except BlockingIOError:
                if retried:  # still full after emptying it: cannot happen with our bound
                    self.dropped_bytes += len(view)
                    return
                retried = True
                taken = self._take_unread()
                if taken:
                    self.flushes += 1
                    self.discarded_bytes += len(taken)
                self._unsure = 0
                continue
            self._unsure += n
            view = view[n:]

    def _make_room(self, size: int) -> None:
        """Measure the backlog and keep only its newest bytes, so that ``size`` more fit."""
        self.checks += 1
        waiting = self._take_unread()
        keep = max(0, self.backlog_bytes - size)
        if len(waiting) > keep:
            self.flushes += 1
            self.discarded_bytes += len(waiting) - keep
            waiting = waiting[len(waiting) - keep:] if keep else b""
        self._unsure = 0
        if waiting:
            self._write_all(waiting)

    def write(self, data: bytes) -> int:
        """Write all of ``data`` without blocking, discarding the oldest unread bytes when
        more than ``backlog_bytes`` would wait (see the module docstring)."""
        with self._lock:
            if self._closed:
                raise OSError("pty closed")
            if self._unsure + len(data) > self.backlog_bytes:
                self._make_room(len(data))
            self._write_all(data)
            return len(data)

    def read(self, size: int = _READ_SIZE) -> bytes:
        """What the reader wrote to the slave end; ``b""`` when nothing waits."""
        if self._closed:
            raise OSError("pty closed")
        try:
            return os.read(self.master, size)
        except (BlockingIOError, InterruptedError):
            return b""

    def close(self) -> None:
        """Close both ends; safe to call twice."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            for fd in (self.master, self._slave):
                with contextlib.suppress(OSError):
                    os.close(fd)
