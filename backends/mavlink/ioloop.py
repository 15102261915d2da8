"""A small selector loop: one thread owning the non-blocking sockets of a MAVLink router.

Sockets are registered with a callback; timers run on the loop; other threads hand work over
with :meth:`IoLoop.call_soon` (which wakes the loop through a socket pair and never blocks).
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import logging
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

MAX_WAIT_S = 0.5


class IoLoop:
    def __init__(self, name: str = "mavlink") -> None:
        self.name = name
        self._sel = selectors.DefaultSelector()
        self._rsock, self._wsock = socket.socketpair()
        self._rsock.setblocking(False)
        self._wsock.setblocking(False)
        self._sel.register(self._rsock, selectors.EVENT_READ, self._on_wake)
        self._calls: deque[Callable[[], Any]] = deque()
        self._timers: list[tuple[float, int, Callable[[], Any]]] = []
        self._counter = itertools.count()
        self._woken = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
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
        with contextlib.suppress(BlockingIOError, OSError):
            self._wsock.send(b"\0")  # a full pair already holds a pending wake-up

    @property
    def in_loop_thread(self) -> bool:
        return threading.current_thread() is self._thread

    # -- from the loop thread (or before start) ----------------------------------------------

    def register(self, sock: Any, events: int, callback: Callable[[int], Any]) -> None:
        self._sel.register(sock, events, callback)

    def modify(self, sock: Any, events: int, callback: Callable[[int], Any]) -> None:
        self._sel.modify(sock, events, callback)

    def unregister(self, sock: Any) -> None:
        with contextlib.suppress(KeyError, ValueError, OSError):
            self._sel.unregister(sock)

    def call_later(self, delay: float, fn: Callable[[], Any]) -> None:
        heapq.heappush(self._timers, (time.monotonic() + delay, next(self._counter), fn))

    def call_every(self, period: float, fn: Callable[[], Any]) -> None:
        """Run ``fn`` every ``period`` seconds, first now."""
        def tick() -> None:
            try:
                fn()
            finally:
                if not self._stop.is_set():
                    self.call_later(period, tick)
        self.call_later(0.0, tick)

    # -- life cycle ----------------------------------------------------------------------------

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name=f"mavlink-{self.name}",
                                        daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        """Stop the thread; safe twice.  Sockets stay open (their owners close them)."""
        self._stop.set()
        self._woken = False
        self.wake()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout)
            if t.is_alive():
                log.warning("%s: loop did not stop within %.1f s", self.name, timeout)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sel.close()
        self._rsock.close()
        self._wsock.close()

    def _on_wake(self, mask: int) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            while self._rsock.recv(4096):
                pass

    def _run(self) -> None:
        sel = self._sel
        timers = self._timers
        calls = self._calls
        while not self._stop.is_set():
            wait = MAX_WAIT_S
            if calls:
                wait = 0.0
            elif timers:
                wait = min(wait, max(0.0, timers[0][0] - time.monotonic()))
            try:
                events = sel.select(wait)
            except OSError:  # a socket closed under us: its owner unregisters it
                events = []
            for key, mask in events:
                self._guard(key.data, mask)
            self._woken = False
            while calls:
                fn = calls.popleft()
                self._guard(fn)
            now = time.monotonic()
            while timers and timers[0][0] <= now:
                _, _, fn = heapq.heappop(timers)
                self._guard(fn)

    def _guard(self, fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except Exception:
            self.errors += 1
            if self.errors <= 5:
                log.exception("%s: error in the I/O loop (continuing)", self.name)
