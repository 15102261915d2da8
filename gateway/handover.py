"""The one hand-over from the dispatcher's thread to a backend's :class:`~gateway.io.ioloop.IoLoop`.

A backend that does its work on a loop declares it in its routes::

    self.handover = Handover(self.name, depth=256)
    ...
    def routes(self) -> Routes:
        return Routes(handover=self.handover).on(SmUpdate, self._on_sm_update)

and the dispatcher, instead of calling ``_on_sm_update`` in its own thread, calls
:meth:`Handover.post`, which never blocks:

* **bounded**: at most ``depth`` messages wait; past that a message is refused,
  ``Outcome.QUEUE_FULL``, counted (``dropped_queue_full``).  With ``span_s`` the bound is
  sized by time instead: ``span_s`` seconds of the rate messages are offered at (measured
  over windows of half a second or more; what came in a window's first half second counts
  as that many per half second), never less than ``depth`` nor more than ``max_depth`` — a
  loop held up for a moment at 25k messages/s loses nothing, and a flood is still bounded;
* **not ready**: before :meth:`Handover.open` (after :meth:`Handover.close`), or while the
  ``ready`` predicate says no, a message is refused, ``Outcome.NOT_READY``, counted
  (``dropped_not_ready``);
* **coalesced**: a drain is scheduled on the loop only when none is pending, so a burst of
  messages costs one wake-up of the loop; a batch the dispatcher posts
  (:meth:`~gateway.dispatcher.Dispatcher.dispatch_batch`, between :meth:`Handover.hold` and
  :meth:`Handover.release`) schedules one drain at its end;
* **typed**: the drain calls the handler the backend routed the message's type to, on the
  loop's thread, in the order the messages were posted — no second dispatch by type behind
  it, so mypy follows a message from :class:`~gateway.backend.Routes` into the handler;
* **isolated**: a handler that raises is logged (once per kind of error) and counted
  (``handler_errors``); the next message is handled as usual;
* ``after_batch`` (optional) runs on the loop after each drained batch: a backend that
  coalesces (one store update or one send per batch, not per message) flushes there;
* ``lock`` (optional) is held around each batch and its ``after_batch``: a backend whose
  state another thread also touches takes its lock once per batch, not once per message;
* ``skip`` (optional) is asked in the poster's thread, before anything is queued: a message
  it says yes to is not the backend's to handle (it came from where the backend would send
  it: loop prevention) and is accepted at once, without waking the loop.  It must be cheap,
  never block, and count what it skips itself.

:meth:`Handover.close` stops accepting, then runs what is queued within its time bound;
what it could not run is discarded and counted (``dropped_closed``).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from gateway.checks import at_least
from gateway.io.ioloop import IoLoop
from gateway.outcome import FailureLog, Outcome

log = logging.getLogger(__name__)

#: Messages that may wait for a backend's loop by default: 2.5 s of a 100 Hz flight's
#: updates and statuses, enough for a loop busy with a burst; a backend may set its own.
DEFAULT_DEPTH = 256
CLOSE_TIMEOUT_S = 1.0
#: The most messages a hand-over sized by time (``span_s``) lets wait: 1 s at 50k/s.
MAX_DEPTH = 50_000
#: The least time over which the post rate is measured (a burst at start is not a rate).
RATE_WINDOW_S = 0.5

_ACCEPTED = Outcome.ACCEPTED
_QUEUE_FULL = Outcome.QUEUE_FULL
_NOT_READY = Outcome.NOT_READY

AnyHandler = Callable[[Any], Any]


class Handover:
    """A bounded, coalesced queue of (handler, message) from any thread to one loop (see the
    module docstring)."""

    def __init__(self, name: str, depth: int = DEFAULT_DEPTH, *,
                 ready: Callable[[], bool] | None = None,
                 after_batch: Callable[[], Any] | None = None,
                 lock: contextlib.AbstractContextManager[Any] | None = None,
                 skip: Callable[[Any], bool] | None = None,
                 span_s: float = 0.0, max_depth: int = MAX_DEPTH,
                 clock: Callable[[], float] = time.monotonic) -> None:
        at_least("a hand-over's depth", depth, 1)
        self.name = name
        self.depth = depth
        #: seconds of the post rate that may wait (0: ``depth`` messages, fixed)
        self.span_s = span_s
        self.max_depth = max(depth, max_depth) if span_s > 0 else depth
        #: the bound now: ``depth``, or ``span_s`` of the measured rate
        self.limit = depth
        self._clock = clock
        self._window_start = clock()
        self._window_posted = 0  # messages offered (posted or refused as full) before it
        self._rate = 0.0  # offered per second in the last window
        self.ready = ready
        self.after_batch = after_batch
        self.lock = lock  # may be set until open()
        self.skip = skip
        self._loop: IoLoop | None = None
        self._queue: deque[tuple[AnyHandler, Any]] = deque()
        self._scheduled = False  # a drain is scheduled and has not started
        self._held = False  # a batch is being posted: one drain is scheduled at its end
        self._failures = FailureLog(log)
        self.posted = 0
        self.handled = 0
        self.batches = 0
        self.dropped_queue_full = 0
        self.dropped_not_ready = 0
        self.dropped_closed = 0
        self.handler_errors = 0

    # -- life cycle ----------------------------------------------------------------------------

    def open(self, loop: IoLoop) -> None:
        """Accept messages from now on, handled on ``loop`` (again after :meth:`close`)."""
        self._scheduled = False  # a drain left on a loop that stopped will never run
        self._loop = loop

    @property
    def loop(self) -> IoLoop | None:
        return self._loop

    @property
    def is_open(self) -> bool:
        return self._loop is not None

    def close(self, timeout: float = CLOSE_TIMEOUT_S) -> int:
        """Stop accepting; run what is queued (on the loop, within ``timeout``), discard the
        rest, counted.  Returns how many were discarded; safe twice."""
        loop, self._loop = self._loop, None
        if loop is not None and self._queue:
            deadline = time.monotonic() + timeout
            if loop.in_loop_thread or not loop.alive:
                if loop.in_loop_thread:
                    self._run_until(deadline)
            else:
                done = threading.Event()

                def finish() -> None:
                    try:
                        self._run_until(deadline)
                    finally:
                        done.set()

                loop.call_soon(finish)
                done.wait(max(0.0, deadline - time.monotonic()))
        discarded = 0
        while True:
            try:
                self._queue.popleft()
            except IndexError:
                break
            discarded += 1
        if discarded:
            self.dropped_closed += discarded
            log.warning("%s: %d message(s) not handled before closing (discarded)", self.name,
                        discarded)
        return discarded

    # -- any thread (the dispatcher's) ---------------------------------------------------------

    def hook(self, handler: AnyHandler) -> Callable[[Any], Outcome]:
        """What the dispatcher calls for messages routed to ``handler``: a post."""
        return functools.partial(self.post, handler)

    def post(self, handler: AnyHandler, msg: Any) -> Outcome:
        """Queue ``handler(msg)`` for the loop; never blocks."""
        skip = self.skip
        if skip is not None and skip(msg):
            return _ACCEPTED
        loop = self._loop
        if loop is None or (self.ready is not None and not self.ready()):
            self.dropped_not_ready += 1
            return _NOT_READY
        q = self._queue
        if len(q) >= self.limit and (not self.span_s or len(q) >= self._resize()):
            self.dropped_queue_full += 1
            return _QUEUE_FULL
        q.append((handler, msg))
        self.posted += 1
        if not self._scheduled and not self._held:
            self._scheduled = True
            loop.call_soon(self._drain)
        return _ACCEPTED

    def hold(self) -> None:
        """A batch of posts begins (the dispatcher's): they schedule no drain until
        :meth:`release`, so the loop wakes once for the batch."""
        self._held = True

    def release(self) -> None:
        """The batch is posted: schedule a drain for it unless one is pending."""
        self._held = False
        loop = self._loop
        if self._queue and not self._scheduled and loop is not None:
            self._scheduled = True
            loop.call_soon(self._drain)

    def queued(self) -> int:
        return len(self._queue)

    def _resize(self, window_done: bool = False) -> int:
        """The bound from the post rate: the last window's or the current one's (over at
        least ``RATE_WINDOW_S``), whichever is higher; ``window_done`` (a drain, once the
        window is that long): the window's own, and a new window starts."""
        now = self._clock()
        elapsed = now - self._window_start
        offered = self.posted + self.dropped_queue_full
        current = (offered - self._window_posted) / max(elapsed, RATE_WINDOW_S)
        rate = current if window_done else max(self._rate, current)
        if window_done:
            self._rate = current
            self._window_start = now
            self._window_posted = offered
        self.limit = min(self.max_depth, max(self.depth, int(rate * self.span_s)))
        return self.limit

    def barrier(self, timeout: float) -> bool:
        """Wait until everything posted so far has been handled (tools and tests); False on
        timeout or when not open."""
        loop = self._loop
        if loop is None:
            return not self._queue
        if loop.in_loop_thread:
            self._drain()
            return True
        done = threading.Event()
        loop.call_soon(done.set)  # after every drain scheduled so far (the loop is FIFO)
        return done.wait(timeout)

    def stats(self) -> dict[str, int]:
        """The hand-over's counters, for a backend's ``stats()``."""
        return {"queued": len(self._queue), "queue_limit": self.limit,
                "dropped_queue_full": self.dropped_queue_full,
                "dropped_not_ready": self.dropped_not_ready,
                "dropped_closed": self.dropped_closed, "handler_errors": self.handler_errors}

    @property
    def dropped(self) -> int:
        return self.dropped_queue_full + self.dropped_not_ready + self.dropped_closed

    # -- the loop's thread -----------------------------------------------------------------------

    def _drain(self, deadline: float | None = None) -> None:
        """Handle the batch queued when the drain starts (later posts schedule another);
        closing, stop at ``deadline``."""
        self._scheduled = False
        with self.lock or contextlib.nullcontext():
            self._batch(deadline)

    def _batch(self, deadline: float | None) -> None:
        q = self._queue
        pop = q.popleft
        n = 0
        for _ in range(len(q)):
            if deadline is not None and time.monotonic() >= deadline:
                break
            try:
                handler, msg = pop()
            except IndexError:  # close() discarded it
                break
            n += 1
            try:
                handler(msg)
            except Exception as exc:
                self._failed(exc)
        self.handled += n
        self.batches += 1
        if self.span_s and self._clock() - self._window_start >= RATE_WINDOW_S:
            self._resize(window_done=True)
        after = self.after_batch
        if after is not None:
            try:
                after()
            except Exception as exc:
                self._failed(exc)

    def _run_until(self, deadline: float) -> None:
        """Closing: handle what is queued until ``deadline``."""
        while self._queue and time.monotonic() < deadline:
            self._drain(deadline)

    def _failed(self, exc: Exception) -> None:
        self.handler_errors += 1
        self._failures.failed(f"{self.name}: a handler", exc)
