"""The I/O loop under every port: one thread, one selector, timers, and hand-over from others.

File descriptors are registered with a callback; timers (``call_later``/``call_every``) run on
the loop thread; any other thread hands work over with :meth:`IoLoop.call_soon`, which wakes
the loop through an eventfd (a socket pair where there is none) and never blocks.  A callback
that raises is logged (the first few times) and counted; the loop carries on.

Work that blocks and cannot be made non-blocking (an open that may wait seconds for a host,
a recording's close and fsync, a third-party source's blocking loop) goes to
:meth:`IoLoop.run_blocking`: a call on :class:`BlockingCalls`, a small pool of worker threads
shared by every loop of the process (at most ``BLOCKING_WORKERS``, started on demand, ended
after ``BLOCKING_IDLE_S`` without work), counted, its result handed back on the loop.  This
module is where the runtime creates threads: the loops' and the pool's.
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
import weakref
from collections import deque
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

MAX_WAIT_S = 0.5
#: Waits shorter than this are timed with select's microseconds, not epoll's milliseconds.
FINE_WAIT_S = 0.002
LOGGED_ERRORS = 5
#: Worker threads for blocking calls, for the whole process: opens that wait on a host that
#: does not answer (pyserial's ``socket://``: up to 5 s) are the longest; more of them than
#: this wait their turn in a queue (counted) instead of adding threads.
BLOCKING_WORKERS = 4
#: A worker with nothing to do for this long ends: the burst of opens at start-up shares
#: one or two workers, and a gateway at rest keeps none.
BLOCKING_IDLE_S = 1.0


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
        self._fine = (self._ep.fileno(),)
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
        out: list[tuple[Callable[[int], Any], int]] = []
        ep = self._ep
        if 0 < timeout < FINE_WAIT_S:
            # epoll waits whole milliseconds (Python rounds up): a shorter wait (a router's
            # coalescing window) waits on the epoll descriptor with select's microseconds
            if not select.select(self._fine, (), (), timeout)[0]:
                return out  # the time is up, nothing is ready: no epoll call needed
            timeout = 0
        for fd, ev in ep.poll(timeout, max(1, len(entries))):
            entry = entries.get(fd)
            if entry is None:
                continue
            mask = ((selectors.EVENT_WRITE if ev & ~select.EPOLLIN else 0)
                    | (selectors.EVENT_READ if ev & ~select.EPOLLOUT else 0))
            out.append((entry[0], mask & entry[1]))
        return out

    def fileno(self) -> int:
        return self._ep.fileno()

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


class BlockingCall:
    """One call handed to :class:`BlockingCalls`: :meth:`wait` for it from any thread."""

    __slots__ = ("_done", "error", "fn", "name", "result")

    def __init__(self, fn: Callable[[], Any], name: str) -> None:
        self.fn = fn
        self.name = name
        self.result: Any = None
        self.error: BaseException | None = None
        self._done = threading.Event()

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """True once the call has returned or raised."""
        return self._done.wait(timeout)


class BlockingCalls:
    """A bounded pool of worker threads for calls that block (see the module docstring).

    At most ``workers`` threads run short calls; calls beyond that queue in order.  A
    *long* call (a third-party source's blocking ``run`` loop, which returns only when it is
    stopped) would hold a worker for the whole run, so it gets a thread of its own instead,
    counted apart (``long_running``).  Every call, its failures and the queue's peak are
    counted in :meth:`stats`."""

    def __init__(self, workers: int = BLOCKING_WORKERS, idle_s: float = BLOCKING_IDLE_S,
                 name: str = "blocking") -> None:
        if workers < 1:
            raise ValueError("workers must be at least 1")
        self.workers = workers
        self.idle_s = idle_s
        self.name = name
        self._lock = threading.Lock()
        self._ready = threading.Condition(self._lock)
        self._queue: deque[BlockingCall] = deque()
        self._threads = 0  # worker threads alive
        self._idle = 0  # of which waiting for work
        self._ids = itertools.count(1)
        self.calls = 0
        self.failed = 0
        self.queued_peak = 0
        self.workers_peak = 0
        self.long_running = 0  # long calls running now
        self.long_calls = 0
        if hasattr(os, "register_at_fork"):  # a forked child has none of these threads
            after = weakref.WeakMethod(self._after_fork)
            os.register_at_fork(after_in_child=lambda: (m := after()) and m())

    def _after_fork(self) -> None:
        self._lock = threading.Lock()
        self._ready = threading.Condition(self._lock)
        self._threads = self._idle = 0
        self.long_running = 0

    def submit(self, fn: Callable[[], Any], *, name: str = "call",
               long: bool = False) -> BlockingCall:
        """Run ``fn`` on a worker thread (``long``: on a thread of its own); never blocks."""
        call = BlockingCall(fn, name)
        if long:
            with self._lock:
                self.long_calls += 1
                self.long_running += 1
            threading.Thread(target=self._run_long, args=(call,), name=f"{self.name}-{name}",
                             daemon=True).start()
            return call
        with self._lock:
            self.calls += 1
            self._queue.append(call)
            waiting = len(self._queue)
            self.queued_peak = max(self.queued_peak, waiting)
            if self._idle >= waiting:
                self._ready.notify()
                return call
            if self._threads >= self.workers:
                return call  # every worker busy: it waits its turn
            self._threads += 1
            self.workers_peak = max(self.workers_peak, self._threads)
        threading.Thread(target=self._work, name=f"{self.name}-{next(self._ids)}",
                         daemon=True).start()
        return call

    def _execute(self, call: BlockingCall) -> None:
        try:
            call.result = call.fn()
        except BaseException as exc:
            call.error = exc
            with self._lock:
                self.failed += 1
            log.debug("blocking call %s failed", call.name, exc_info=True)
        finally:
            call._done.set()

    def _run_long(self, call: BlockingCall) -> None:
        try:
            self._execute(call)
        finally:
            with self._lock:
                self.long_running -= 1

    def _work(self) -> None:
        while True:
            with self._lock:
                if not self._queue:
                    self._idle += 1
                    self._ready.wait_for(lambda: bool(self._queue), self.idle_s)
                    self._idle -= 1
                    if not self._queue:  # idle for idle_s: this worker ends
                        self._threads -= 1
                        return
                call = self._queue.popleft()
            self._execute(call)

    def stats(self) -> dict[str, int]:
        with self._lock:
            return {"calls": self.calls, "failed": self.failed, "queued": len(self._queue),
                    "queued_peak": self.queued_peak, "workers": self._threads,
                    "workers_peak": self.workers_peak, "workers_max": self.workers,
                    "long_running": self.long_running, "long_calls": self.long_calls}


#: The pool every loop of the process uses unless it is given another.
BLOCKING = BlockingCalls()


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
        except (OSError, ValueError):  # full (a wake-up is pending) or closed (fd -1)
            pass

    def clear(self) -> None:
        try:
            if self._pair is None:
                os.eventfd_read(self._efd)  # the whole count at once
            else:
                while self._pair[0].recv(4096):
                    pass
        except (OSError, ValueError):  # nothing (more) to read, or closed (fd -1)
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

    def __init__(self, name: str = "io", *, blocking: BlockingCalls | None = None) -> None:
        self.name = name
        self.blocking = blocking if blocking is not None else BLOCKING
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

    def run_blocking(self, fn: Callable[[], Any],
                     then: Callable[[Any, BaseException | None], Any] | None = None, *,
                     name: str = "call", long: bool = False) -> BlockingCall:
        """Run ``fn`` (which may block) on :attr:`blocking`'s workers, never on this loop's
        thread; then, if given, ``then(result, error)`` runs on the loop's thread (not at
        all if the loop has stopped by then: a caller that must release what ``fn`` made
        does it in ``fn``).  ``long``: ``fn`` runs until it is told to stop (a source's
        blocking loop) and gets a thread of its own.  Never blocks."""
        if then is None:
            return self.blocking.submit(fn, name=name, long=long)

        def call() -> Any:
            result: Any = None
            error: BaseException | None = None
            try:
                result = fn()
            except Exception as exc:
                error = exc
            self.call_soon(lambda: then(result, error))
            if error is not None:
                raise error
            return result

        return self.blocking.submit(call, name=name, long=long)

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

    def call_at_here(self, due: float, fn: Callable[[], Any]) -> Timer:
        """Run ``fn`` on the loop thread at ``due`` (``time.monotonic()`` time); from the
        loop's own thread only (unchecked: a hot path's timer)."""
        timer = Timer(due, fn)
        heapq.heappush(self._timers, (due, next(self._counter), timer))
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

    def lane_wait(self) -> tuple[int, float] | None:
        """For a callback that waits in compiled code on the loop's behalf (a router's
        lane), from the loop's thread: the descriptor to watch beside its own — ready when
        the loop has anything to do — and until when (``time.monotonic()``: the next timer);
        None when calls are waiting or the loop cannot be watched this way.  Another
        thread's :meth:`call_soon` from now on makes the descriptor ready."""
        sel = self._sel
        if not isinstance(sel, _EpollPoller):
            return None
        self._woken = False  # (a wake-up from now on writes the waker)
        if self._calls:
            return None
        due = self._timers[0][0] if self._timers else time.monotonic() + MAX_WAIT_S
        return sel.fileno(), due

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
            for callback, mask in events:  # (_guard inlined: a router's cost per wake-up)
                try:
                    callback(mask)
                except Exception:
                    self._failed()
            self._woken = False
            while calls:
                self._guard(calls.popleft())
            now = time.monotonic()
            while timers and timers[0][0] <= now:
                timer = heapq.heappop(timers)[2]
                if not timer.cancelled:
                    try:
                        timer.fn()
                    except Exception:
                        self._failed()

    def _guard(self, fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except Exception:
            self._failed()

    def _failed(self) -> None:
        """A callback raised (call it in the handler): counted, the first few logged."""
        self.errors += 1
        if self.errors <= LOGGED_ERRORS:
            log.exception("%s: error in the I/O loop (continuing)", self.name)
