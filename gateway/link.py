"""The link engine (the firmware's "uart-link"): queue, rate-limit and write frames.

One reusable piece for every byte-stream backend (HC-12, CRSF serial, XBee): a producer
calls :meth:`LinkEngine.submit` and never blocks; a worker thread owns the port, writes
queued frames in order, and reconnects with backoff when the port fails.  Several engines run
side by side on different ports.

Outcomes of ``submit`` (the firmware's return codes):

* ``THROTTLED``: a rate-limited frame came sooner than ``min_interval_s`` after the last
  accepted one (frames submitted with ``rate_limited=False``, e.g. STATUS, are exempt);
* ``QUEUE_FULL``: ``queue_depth`` frames are already waiting;
* ``NOT_READY``: the engine is not running or its port is down (frames are not queued for
  a port that is not there: they would be stale when it comes back).

``lock`` is held by the worker around every write; anything else that must own the port
for a while (an AT-command exchange) takes the same lock, and frames queue meanwhile.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from gateway.backend import Outcome
from gateway.backoff import Backoff
from gateway.transport import Transport

log = logging.getLogger(__name__)

DEFAULT_QUEUE_DEPTH = 16


@dataclass
class LinkStats:
    submitted: int = 0
    accepted: int = 0
    sent_frames: int = 0
    sent_bytes: int = 0
    dropped_throttled: int = 0
    dropped_queue_full: int = 0
    dropped_not_ready: int = 0
    write_errors: int = 0
    connects: int = 0
    connect_failures: int = 0
    reconnects_requested: int = 0

    @property
    def dropped(self) -> int:
        return self.dropped_throttled + self.dropped_queue_full + self.dropped_not_ready

    def as_dict(self) -> dict[str, int]:
        d = dict(self.__dict__)
        d["dropped"] = self.dropped
        return d


_STOP = object()


class LinkEngine:
    """Bounded queue + worker thread writing frames to a transport opened by ``opener``."""

    def __init__(
        self,
        opener: Callable[[], Transport],
        *,
        name: str = "link",
        queue_depth: int = DEFAULT_QUEUE_DEPTH,
        min_interval_s: float = 0.0,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if queue_depth < 1:
            raise ValueError("queue_depth must be at least 1")
        if min_interval_s < 0:
            raise ValueError("min_interval_s must not be negative")
        self.name = name
        self.queue_depth = queue_depth
        self.min_interval_s = min_interval_s
        self.stats = LinkStats()
        self.lock = threading.RLock()
        self._opener = opener
        self._backoff = backoff or Backoff()
        self._clock = clock
        self._queue: queue.Queue = queue.Queue(queue_depth)
        self._stop = threading.Event()
        self._connected = threading.Event()
        self._thread: threading.Thread | None = None
        self._transport: Transport | None = None
        self._last_accepted: float | None = None
        self._reconnect_requested = False
        self._count_lock = threading.Lock()

    # -- producer side ------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def submit(self, data: bytes, *, rate_limited: bool = True) -> Outcome:
        """Queue one frame for the worker; never blocks."""
        st = self.stats
        with self._count_lock:
            st.submitted += 1
            if self._thread is None or self._stop.is_set() or not self._connected.is_set():
                st.dropped_not_ready += 1
                return Outcome.NOT_READY
            if rate_limited and self.min_interval_s > 0:
                now = self._clock()
                last = self._last_accepted
                if last is not None and now - last < self.min_interval_s:
                    st.dropped_throttled += 1
                    return Outcome.THROTTLED
            try:
                self._queue.put_nowait(data)
            except queue.Full:
                st.dropped_queue_full += 1
                return Outcome.QUEUE_FULL
            if rate_limited and self.min_interval_s > 0:
                self._last_accepted = now
            st.accepted += 1
            return Outcome.ACCEPTED

    def queued(self) -> int:
        return self._queue.qsize()

    # -- life cycle -----------------------------------------------------------------------------

    def start(self) -> None:
        if self._thread is not None:
            return
        # A fresh stop event per run: a worker left behind by an earlier close() (stuck in a
        # write that never returns) keeps its own, set, event and can never serve this run.
        self._stop = stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(stop,), name=f"link-{self.name}",
                                        daemon=True)
        self._thread.start()

    def wait_connected(self, timeout: float) -> bool:
        """Block until the port is open (for start-up and tests)."""
        return self._connected.wait(timeout)

    def drain(self, timeout: float) -> bool:
        """Wait until every queued frame has been written (True) or ``timeout`` passes."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._queue.unfinished_tasks == 0:
                return True
            time.sleep(0.005)
        return self._queue.unfinished_tasks == 0

    def close(self, timeout: float = 1.0) -> None:
        """Stop the worker and close the port, returning within about ``timeout``; safe to call
        twice.  The worker first writes what is already queued (while the port is up); frames
        still pending after ``timeout`` are discarded and counted as not-ready drops.  A worker
        stuck in a write that never returns is abandoned (it is a daemon thread)."""
        thread = self._thread
        if thread is None:
            return
        self._stop.set()
        with contextlib.suppress(queue.Full):  # if full, the worker stops when it is empty
            self._queue.put_nowait(_STOP)
        thread.join(timeout)
        self._thread = None
        if thread.is_alive():
            log.warning("%s: worker did not stop within %.1f s; abandoning it", self.name,
                        timeout)
        leftover = 0
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            self._queue.task_done()
            if item is not _STOP:
                leftover += 1
        with self._count_lock:
            self.stats.dropped_not_ready += leftover
        self._close_transport(self._transport)

    # -- worker -------------------------------------------------------------------------------

    def _open(self) -> Transport | None:
        try:
            transport = self._opener()
        except Exception as exc:
            self.stats.connect_failures += 1
            if self.stats.connect_failures == 1 or self.stats.connects:
                log.warning("%s: %s; retrying", self.name, exc)
            return None
        self.stats.connects += 1
        self._backoff.reset()
        self._transport = transport
        self._connected.set()
        if self.stats.connects > 1:
            log.info("%s: port is back", self.name)
        return transport

    def _close_transport(self, transport: Transport | None) -> None:
        """Close ``transport`` once, whoever (worker or close()) gets here first."""
        with self._count_lock:
            if transport is None or self._transport is not transport:
                return
            self._transport = None
            self._connected.clear()
        try:
            transport.close()
        except Exception:
            log.debug("%s: error closing port", self.name, exc_info=True)

    def reconnect(self) -> None:
        """The port failed outside a write (its reader saw it): the worker closes it and
        reopens with backoff, within about 0.1 s.  Frames submitted meanwhile are refused as
        not ready, as when a write fails."""
        with self._count_lock:
            if self._transport is not None:
                self._connected.clear()
                self._reconnect_requested = True

    def _run(self, stop: threading.Event) -> None:
        transport: Transport | None = None
        try:
            while True:
                if self._reconnect_requested:
                    self._reconnect_requested = False
                    self.stats.reconnects_requested += 1
                    self._close_transport(transport)
                    transport = None
                    stop.wait(self._backoff.next())
                if transport is None:
                    if stop.is_set():
                        return
                    transport = self._open()
                    if transport is None:
                        stop.wait(self._backoff.next())
                        continue
                    if stop.is_set() and self._stop is not stop:
                        return  # close() gave up on this worker while it was opening
                try:
                    item = self._queue.get(timeout=0.1)
                except queue.Empty:
                    if stop.is_set():
                        return  # stopping and nothing left to write
                    continue
                try:
                    if item is _STOP:
                        return
                    if not self._write(transport, item):
                        self._close_transport(transport)
                        transport = None
                finally:
                    self._queue.task_done()
        finally:
            # Covers an open that completed after close() stopped waiting for this worker.
            self._close_transport(transport)

    def _write(self, transport: Transport, data: bytes) -> bool:
        try:
            with self.lock:
                transport.write(data)
        except Exception as exc:
            self.stats.write_errors += 1
            log.warning("%s: write failed (%r); reconnecting", self.name, exc)
            return False
        self.stats.sent_frames += 1
        self.stats.sent_bytes += len(data)
        return True
