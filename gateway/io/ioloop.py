"""The I/O loop under every port: one thread, one selector, timers, and hand-over from others.

File descriptors are registered with a callback; timers (``call_later``/``call_every``) run on
the loop thread; any other thread hands work over with :meth:`IoLoop.call_soon`, which wakes
the loop through an eventfd (a socket pair where there is none) and never blocks.  A callback
that raises is logged (the first few times) and counted; the loop carries on.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import logging
import os
import select
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

MAX_WAIT_S = 0.5
LOGGED_ERRORS = 5


class Timer:
    """A scheduled call; :meth:`cancel` keeps it from running (safe from any thread)."""

    __slots__ = ("cancelled", "due", "fn")

    def __init__(self, due: float, fn: Callable[[], Any]) -> None:
        self.due = due
        self.fn = fn
        self.cancelled = False

    def cancel(self) -> None:
        self.cancelled = True


def _fd(fileobj: Any) -> int:
    return fileobj if isinstance(fileobj, int) else int(fileobj.fileno())


class _EpollPoller:
    """Callbacks on ``select.epoll``: what :meth:`select` returns is (callback, mask) pairs,
    masks in :mod:`selectors` terms, as ``selectors.EpollSelector`` reports them — without
    its key object per event (the loop's per-wake-up cost, and a router wakes per datagram)."""

    def __init__(self) -> None:
        self._ep = select.epoll()
        self._entries: dict[int, tuple[Callable[[int], Any], int]] = {}

    @staticmethod
    def _flags(events: int) -> int:
        return ((select.EPOLLIN if events & selectors.EVENT_READ else 0)
                | (select.EPOLLOUT if events & selectors.EVENT_WRITE else 0))

    def register(self, fileobj: Any, events: int, callback: Callable[[int], Any]) -> None:
        fd = _fd(fileobj)
        if fd in self._entries:
            raise KeyError(f"{fileobj!r} (fd {fd}) is already registered")
        self._ep.register(fd, self._flags(events))
        self._entries[fd] = (callback, events)

    def modify(self, fileobj: Any, events: int, callback: Callable[[int], Any]) -> None:
        fd = _fd(fileobj)
        if fd not in self._entries:
            raise KeyError(f"{fileobj!r} (fd {fd}) is not registered")
        self._ep.modify(fd, self._flags(events))
        self._entries[fd] = (callback, events)

    def unregister(self, fileobj: Any) -> None:
        fd = _fd(fileobj)
        del self._entries[fd]
        with contextlib.suppress(OSError):  # already closed: the kernel dropped it
            self._ep.unregister(fd)

    def select(self, timeout: float) -> list[tuple[Callable[[int], Any], int]]:
        entries = self._entries
        out = []
        for fd, ev in self._ep.poll(timeout, max(1, len(entries))):
            entry = entries.get(fd)
            if entry is None:
                continue
            mask = ((selectors.EVENT_WRITE if ev & ~select.EPOLLIN else 0)
                    | (selectors.EVENT_READ if ev & ~select.EPOLLOUT else 0))
            out.append((entry[0], mask & entry[1]))
        return out

    def close(self) -> None:
        self._ep.close()


class _SelectorPoller:
    """The same over :class:`selectors.DefaultSelector`, where there is no epoll."""

    def __init__(self) -> None:
        self._selector = selectors.DefaultSelector()

    def register(self, fileobj: Any, events: int, callback: Callable[[int], Any]) -> None:
        self._selector.register(fileobj, events, callback)

    def modify(self, fileobj: Any, events: int, callback: Callable[[int], Any]) -> None:
        self._selector.modify(fileobj, events, callback)

    def unregister(self, fileobj: Any) -> None:
        self._selector.unregister(fileobj)

    def select(self, timeout: float) -> list[tuple[Callable[[int], Any], int]]:
        return [(key.data, mask) for key, mask in self._selector.select(timeout)]

    def close(self) -> None:
        self._selector.close()


class _Waker:
    """What another thread writes to wake the loop: an eventfd (one cheap syscall each way),
    or a socket pair where there is none."""

    def __init__(self) -> None:
        self._efd = -1
        self._pair: tuple[socket.socket, socket.socket] | None = None
        if hasattr(os, "eventfd"):
            self._efd = os.eventfd(0, os.EFD_NONBLOCK | os.EFD_CLOEXEC)
        else:
            r, w = socket.socketpair()
            r.setblocking(False)
            w.setblocking(False)
            self._pair = (r, w)

    def fileno(self) -> int:
        return self._efd if self._pair is None else self._pair[0].fileno()

    def wake(self) -> None:
        try:  # (no context manager: this is every cross-thread hand-over's cost)
            if self._pair is None:
                os.eventfd_write(self._efd, 1)
            else:
                self._pair[1].send(b"\0")
        except OSError:  # full (a wake-up is pending) or closed
            pass

    def clear(self) -> None:
        try:
            if self._pair is None:
                os.eventfd_read(self._efd)  # the whole count at once
            else:
                while self._pair[0].recv(4096):
                    pass
        except OSError:  # nothing (more) to read
            pass

    def close(self) -> None:
        if self._pair is None:
            if self._efd >= 0:
                os.close(self._efd)
                self._efd = -1
        else:
            for sock in self._pair:
                sock.close()


class IoLoop:
    """A selector loop on a thread of its own (see the module docstring)."""

    def __init__(self, name: str = "io") -> None:
        self.name = name
        self._sel: _EpollPoller | _SelectorPoller = (
            _EpollPoller() if hasattr(select, "epoll") else _SelectorPoller())
        self._waker = _Waker()
        self._sel.register(self._waker.fileno(), selectors.EVENT_READ, self._on_wake)
        self._calls: deque[Callable[[], Any]] = deque()
        self._timers: list[tuple[float, int, Timer]] = []
        self._counter = itertools.count()
        self._woken = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.errors = 0

    # -- from any thread ---------------------------------------------------------------------

    def call_soon(self, fn: Callable[[], Any]) -> None:
        """Run ``fn`` on the loop thread soon; never blocks."""
        self._calls.append(fn)
        self.wake()

    def wake(self) -> None:
        if self._woken:
            return
        self._woken = True
        self._waker.wake()

    @property
    def in_loop_thread(self) -> bool:
        return threading.current_thread() is self._thread

    @property
    def alive(self) -> bool:
        """True while the loop's thread exists (it may be stuck in a callback)."""
        t = self._thread
        return t is not None and t.is_alive()

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._stop.is_set()

    def call_later(self, delay: float, fn: Callable[[], Any]) -> Timer:
        """Run ``fn`` on the loop thread after ``delay`` seconds (from any thread)."""
        timer = Timer(time.monotonic() + max(0.0, delay), fn)
        if self.in_loop_thread or self._thread is None:
            self._push(timer)
        else:
            self.call_soon(lambda: self._push(timer))
        return timer

    def call_every(self, period: float, fn: Callable[[], Any], *, first: float = 0.0) -> Timer:
        """Run ``fn`` every ``period`` seconds, the first time after ``first``; the returned
        timer's :meth:`~Timer.cancel` ends the series."""
        if period <= 0:
            raise ValueError("period must be positive")
        handle = Timer(0.0, fn)

        def tick() -> None:
            if handle.cancelled or self._stop.is_set():
                return
            try:
                fn()
            finally:
                if not handle.cancelled and not self._stop.is_set():
                    self._push(Timer(time.monotonic() + period, tick))

        self.call_later(first, tick)
        return handle

    # -- from the loop thread (or before start) ----------------------------------------------

    def register(self, fileobj: Any, events: int, callback: Callable[[int], Any]) -> None:
        self._sel.register(fileobj, events, callback)

    def modify(self, fileobj: Any, events: int, callback: Callable[[int], Any]) -> None:
        self._sel.modify(fileobj, events, callback)

    def unregister(self, fileobj: Any) -> None:
        with contextlib.suppress(KeyError, ValueError, OSError):
            self._sel.unregister(fileobj)

    def _push(self, timer: Timer) -> None:
        heapq.heappush(self._timers, (timer.due, next(self._counter), timer))

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"io-{self.name}", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> bool:
        """Stop the thread (True once it has ended); safe twice.  Registered files stay open:
        their owners close them."""
        self._stop.set()
        self._woken = False
        self.wake()
        t = self._thread
        if t is None or t is threading.current_thread():
            return True
        t.join(timeout)
        if t.is_alive():
            log.warning("%s: loop did not stop within %.1f s; abandoning it", self.name, timeout)
            return False
        return True

    def close(self) -> None:
        """Release the selector and the wake-up pair; safe twice."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(OSError):
            self._sel.close()
        self._waker.close()

    def _on_wake(self, mask: int) -> None:
        self._waker.clear()

    def _run(self) -> None:
        sel = self._sel
        timers = self._timers
        calls = self._calls
        stop = self._stop
        while not stop.is_set():
            wait = MAX_WAIT_S
            if calls:
                wait = 0.0
            elif timers:
                wait = min(wait, max(0.0, timers[0][0] - time.monotonic()))
            try:
                events = sel.select(wait)
            except (OSError, ValueError):  # a file closed under us: its owner unregisters it
                events = []
            for callback, mask in events:
                self._guard(callback, mask)
            self._woken = False
            while calls:
                self._guard(calls.popleft())
            now = time.monotonic()
            while timers and timers[0][0] <= now:
                timer = heapq.heappop(timers)[2]
                if not timer.cancelled:
                    self._guard(timer.fn)

    def _guard(self, fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except Exception:
            self.errors += 1
            if self.errors <= LOGGED_ERRORS:
                log.exception("%s: error in the I/O loop (continuing)", self.name)
