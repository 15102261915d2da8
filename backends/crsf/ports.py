"""The CRSF backend's two kinds of port, each written by the link engine and read by the
backend's reader thread.

* :class:`SharedSerial` opens a pyserial port or URL for the link engine and keeps a reference,
  so the reader reads the very port the engine writes (one file descriptor, full duplex, as
  a receiver's UART is); when the engine reopens after a failure the reader follows.
* :class:`PtyPair` is a pseudo-terminal the backend creates for the no-hardware default run:
  frames go to the master end and a user (or a test) attaches a reader to :attr:`PtyPair.path`.
  Writes never block: when more than ``backlog_bytes`` are waiting unread (nobody is reading)
  they are discarded first, so a reader that attaches late sees current telemetry, not a
  stale backlog.  (The kernel reports unread bytes only once its line discipline has them, so
  in a burst a little more than ``backlog_bytes`` may wait.)
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import select
import struct
import termios
import threading
import tty
from typing import Any

from gateway.transport import open_serial

log = logging.getLogger(__name__)

PTY_BACKLOG_BYTES = 1024  # about five seconds of telemetry at 20 frames/s
READ_TIMEOUT_S = 0.05


class SharedSerial:
    """Opener for :class:`gateway.link.LinkEngine` that remembers the port it opened."""

    def __init__(self, url: str, baudrate: int, name: str = "crsf") -> None:
        self.url = url
        self.baudrate = baudrate
        self.name = name
        self.port: Any = None
        self.opens = 0

    def open(self) -> Any:
        port = open_serial(self.url, self.baudrate, timeout=READ_TIMEOUT_S, write_timeout=0.5)
        self.port = port
        self.opens += 1
        if self.opens == 1:
            log.info("%s: %s open at %d baud", self.name, self.url, self.baudrate)
        return port

    def read(self, stop: threading.Event) -> bytes:
        """Bytes from the current port (waits up to about 50 ms); b"" when there is none or
        it failed (the engine reopens it when a write fails)."""
        port = self.port
        if port is None or not getattr(port, "is_open", True):
            stop.wait(READ_TIMEOUT_S)
            return b""
        try:
            waiting = port.in_waiting
            return port.read(waiting if waiting > 0 else 1)
        except Exception as exc:  # pyserial: SerialException, OSError, TypeError on close
            if self.port is port:
                log.debug("%s: read failed (%s); waiting for the port to be reopened",
                          self.name, exc)
                self.port = None
            stop.wait(READ_TIMEOUT_S)
            return b""


class _PtyTransport:
    """What the link engine writes through; closing it leaves the pty to its owner."""

    def __init__(self, pty: PtyPair) -> None:
        self._pty = pty

    def write(self, data: bytes) -> int:
        return self._pty.write(data)

    def read(self, size: int = 1) -> bytes:
        return b""

    def close(self) -> None:
        pass


class PtyPair:
    """A pseudo-terminal pair: the backend owns the master, a reader attaches to ``path``.

    The slave end is held open (so the pair survives readers coming and going) and put in raw
    mode (no echo, no CR/LF translation, no XON/XOFF: CRSF is binary).
    """

    def __init__(self, backlog_bytes: int = PTY_BACKLOG_BYTES) -> None:
        self.backlog_bytes = backlog_bytes
        self.flushes = 0  # times unread bytes were discarded
        self.dropped_bytes = 0  # bytes not written at all (the pty stayed full)
        self._closed = False
        self._lock = threading.Lock()
        self.master, self._slave = os.openpty()
        try:
            tty.setraw(self._slave)
            os.set_blocking(self.master, False)
            self.path = os.ttyname(self._slave)
        except Exception:
            self.close()
            raise

    def transport(self) -> _PtyTransport:
        return _PtyTransport(self)

    def _unread(self) -> int:
        return struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0]

    def _discard_unread(self) -> None:
        termios.tcflush(self._slave, termios.TCIFLUSH)
        self.flushes += 1

    def write(self, data: bytes) -> int:
        """Write all of ``data`` without blocking, discarding unread old bytes if needed."""
        with self._lock:
            if self._closed:
                raise OSError("pty closed")
            if self._unread() + len(data) > self.backlog_bytes:
                self._discard_unread()
            view = memoryview(data)
            retried = False
            while view:
                try:
                    n = os.write(self.master, view)
                except BlockingIOError:
                    if retried:
                        self.dropped_bytes += len(view)
                        break
                    self._discard_unread()
                    retried = True
                    continue
                view = view[n:]
            return len(data)

    def read(self, stop: threading.Event, timeout: float = READ_TIMEOUT_S) -> bytes:
        """What a peer wrote to the slave end (waits up to ``timeout``)."""
        if self._closed:
            stop.wait(timeout)
            return b""
        try:
            ready, _, _ = select.select([self.master], [], [], timeout)
            if not ready:
                return b""
            return os.read(self.master, 4096)
        except (BlockingIOError, InterruptedError):
            return b""
        except (OSError, ValueError):  # closed under us
            stop.wait(timeout)
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
