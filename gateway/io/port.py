"""The duplex port engine (the firmware's "uart-link", made two-way): one thread owns a port.

Every byte-stream user — the serial source, MAVLink serial/TCP/UDP endpoints, CRSF, HC-12 —
is a :class:`PortEngine` around a port and a sans-I/O protocol object:

* **reading**: what the port yields is fed to ``protocol.feed(data)``, and every event it
  returns is handed to ``on_event`` (in the engine's thread).  A port with a file descriptor
  is watched by the loop's selector; one without (``loop://``, ``rfc2217://``) is polled
  every ``poll_s``.  A datagram port (``port.datagram = True``) is fed one datagram at a time;
* **writing**: :meth:`PortEngine.submit` never blocks — it queues the bytes (at most
  ``queue_depth`` frames) and returns an :class:`~gateway.backend.Outcome`; the engine's
  thread writes them in order.  ``THROTTLED``: a rate-limited frame came sooner than
  ``min_interval_s`` after the last accepted one; ``QUEUE_FULL``: the queue is full;
  ``NOT_READY``: the engine is not running or its port is down (frames are not kept for a port
  that is not there: they would be stale when it comes back);
* **reopening**: when the opener fails, or a read or write fails, the port is closed and
  reopened with backoff by the same code for every kind of port; ``on_link(True/False)``
  reports each change, and the counters say how often;
* **timers**: :meth:`call_later` / :meth:`call_every` / :meth:`call_soon` run protocol work
  (retries, pings, periodic sends) on the engine's thread — no ad-hoc threads;
* **exclusive use**: :meth:`exclusive` parks the engine and hands the raw port to the caller
  (an AT-command exchange, as the firmware's TX lock does); frames queue meanwhile.

By default an engine runs a loop thread of its own.  Engines of non-blocking ports may share
one :class:`~gateway.io.ioloop.IoLoop` (``loop=``, or :meth:`PortEngine.use_loop` before
start), as a MAVLink router's UDP and TCP links and a gateway's sources do.  Opens run on the
loop's bounded pool of blocking calls, never on its thread.

What a port must offer: ``write(data) -> int | None`` (bytes written; None means all),
``read(size) -> bytes`` (returns ``b""`` when nothing is waiting once the engine has set a
zero ``timeout``; raises when the port has failed), ``close()``; optionally ``fileno()``,
``timeout`` and ``datagram``.  pyserial ports (:func:`gateway.io.transport.open_serial`) and the
sockets of :mod:`gateway.io.transport` are such ports.
"""

from __future__ import annotations

import contextlib
import logging
import selectors
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any, Protocol

from gateway.checks import at_least, not_negative
from gateway.counters import Counters
from gateway.io.backoff import Backoff
from gateway.io.burstlog import BurstLog
from gateway.io.ioloop import IoLoop, Timer
from gateway.outcome import Outcome

log = logging.getLogger(__name__)

DEFAULT_QUEUE_DEPTH = 16
#: Reopening a port that failed or vanished: the first retry after 50 ms, then twice as long
#: each time up to 2 s — so a port that comes back is in use again within 2 s, whoever uses it.
REOPEN_FIRST_S = 0.05
REOPEN_MAX_S = 2.0
# Bound once: an enum attribute lookup per frame is measurable on the router's path.
_ACCEPTED = Outcome.ACCEPTED
_THROTTLED = Outcome.THROTTLED
_QUEUE_FULL = Outcome.QUEUE_FULL
_NOT_READY = Outcome.NOT_READY
_get_ident = threading.get_ident
DEFAULT_POLL_S = 0.01
READ_SIZE = 65536
DATAGRAM_BATCH = 64
#: A feed_many protocol (a router) on a port with ``read_many`` (a UDP socket: every datagram
#: waiting in one ``recvmmsg``) is read in batches, and while datagrams keep coming (the
#: last batch within COALESCE_GAP_S), the port is left unwatched for COALESCE_S after each
#: batch: what arrives meanwhile waits in the socket and is read, routed and written in one
#: go (one wake-up, one read, one write per destination for the lot, instead of one each
#: per datagram).  A datagram after a quiet spell is read at once; one in a stream waits at
#: most about COALESCE_S (the loop's timers have a 1 ms grain).  The socket's receive
#: buffer holds far more than arrives in that time (see transport.UDP_RCVBUF).
COALESCE_S = 0.001
COALESCE_GAP_S = 0.004
#: A wake-up that reads at least this many datagrams at once, after a hold that found none,
#: is a burst: the port is not held after it (nothing more is coming for a while).
BURST_MIN = 4
#: Batches read back to back at most per wake-up, when each one fills DATAGRAM_BATCH.
COALESCE_MAX_READS = 16
#: Without ``read_many``: one datagram per wake-up, as mavlink-router does, unless the loop
#: came back to the port within this long of the last batch (a backlog: the poller,
#: level-triggered, did not wait): then up to DATAGRAM_BATCH.  Datagrams mostly arrive one
#: at a time, and a read that finds nothing (a system call and an exception) would cost
#: ~10 % of the router's work per frame; under a backlog, batches are cheaper.
BACKLOG_GAP_S = 20e-6


class Port(Protocol):
    """What the engine needs of a port (pyserial's ``Serial`` is one)."""

    def write(self, data: bytes, /) -> int | None: ...
    def read(self, size: int = 1, /) -> bytes: ...
    def close(self) -> None: ...


class StreamProtocol(Protocol):
    """A sans-I/O protocol: bytes in, events out (h11's shape)."""

    def feed(self, data: bytes, /) -> Iterable[Any]: ...


class PortNotReady(OSError):
    """The port is down, the engine is not running, or it could not be had in time."""


@dataclass
class PortStats(Counters):
    """Counters of one port engine; :meth:`as_dict` adds the totals every backend reports."""

    submitted: int = 0
    accepted: int = 0
    sent_frames: int = 0
    sent_bytes: int = 0
    received_bytes: int = 0
    dropped_throttled: int = 0
    dropped_queue_full: int = 0
    dropped_not_ready: int = 0
    write_errors: int = 0
    read_errors: int = 0
    protocol_errors: int = 0
    connects: int = 0
    connect_failures: int = 0
    disconnects: int = 0
    reconnects_requested: int = 0

    @property
    def dropped(self) -> int:
        return self.dropped_throttled + self.dropped_queue_full + self.dropped_not_ready

    @property
    def errors(self) -> int:
        return self.write_errors + self.read_errors + self.protocol_errors

    def as_dict(self) -> dict[str, int]:
        d = super().as_dict()
        d["dropped"] = self.dropped
        d["errors"] = self.errors
        return d


class PortEngine:
    """One port, read into a protocol and written from a bounded queue; see the module doc."""

    def __init__(
        self,
        opener: Callable[[], Any],
        *,
        name: str = "port",
        protocol: StreamProtocol | None = None,
        on_event: Callable[[Any], Any] | None = None,
        on_link: Callable[[bool], Any] | None = None,
        queue_depth: int = DEFAULT_QUEUE_DEPTH,
        min_interval_s: float = 0.0,
        backoff: Backoff | None = None,
        clock: Callable[[], float] = time.monotonic,
        loop: IoLoop | None = None,
        reopen: bool = True,
        poll_s: float = DEFAULT_POLL_S,
        hangup_level: int = logging.INFO,
    ) -> None:
        at_least("queue_depth", queue_depth, 1)
        not_negative("min_interval_s", min_interval_s)
        self.name = name
        self.queue_depth = queue_depth
        self.min_interval_s = min_interval_s
        self.protocol = protocol
        self._datagrams_done = 0.0  # when _read_datagrams last finished (monotonic)
        self._holding = False  # reads paused for COALESCE_S (see there)
        self._bursty = False  # the sender writes bursts: no hold after a burst (see there)
        self._held: tuple[Any, Any, Any] = (None, None, None)  # what _resume reads
        #: a batch-read datagram port's read_many and its protocol's feed_many (see _reader)
        self._batches: tuple[Callable[[], list[bytes]], Callable[[list[bytes]], Any]] | None = None
        self._lane: Callable[[Callable[[], None]], bool] | None = None  # see _run_lane
        self._lane_next: Any = None  # the timer that starts the lane again (_lane_again)
        self.lane_runs = 0  # times the lane ran (a compiled router's wake-ups: see _run_lane)
        self._want_write = False
        #: the coalescing window of a batch-read datagram port (0: read on every wake-up)
        self.coalesce_s = COALESCE_S
        self.on_event = on_event
        self.on_link = on_link
        self.stats = PortStats()
        self.reopen = reopen
        self.poll_s = poll_s
        #: How a peer hanging up on an engine that is not reopened is logged (a served
        #: client's end; DEBUG for a server whose clients come and go by the hundred).
        self.hangup_level = hangup_level
        self._opener = opener
        self._backoff = backoff or Backoff(REOPEN_FIRST_S, REOPEN_MAX_S)
        self._clock = clock
        self._own_loop = loop is None
        self._loop = loop if loop is not None else IoLoop(name)
        self._queue: deque[bytes] = deque()
        self._lock = threading.Lock()  # guards the queue, the counters submit() touches
        self._idle = threading.Condition(self._lock)
        self._writing = False
        self._flush_scheduled = False
        self._drainers = 0  # threads waiting in drain()
        self._loop_ident = 0  # the loop thread's id, set when the port is attached
        self._port: Any = None
        self._fd: Any = None
        self._interest = 0
        self._pending = b""  # the unwritten tail of a frame a non-blocking port took in part
        self._poll: Timer | None = None
        self._retry: Timer | None = None
        self._connected = threading.Event()
        self._started = False
        self._closing = False
        self._up = False  # started, not closing and the port attached: submit() reads only this
        self._opening = False
        self._shut = threading.Event()
        self._last_accepted: float | None = None
        self._outage_logged = False
        self._bursts: dict[str, BurstLog] = {}  # made on the loop's thread, when first needed
        self._blocked_since: float | None = None  # a write has waited for room since then
        self._finish = False  # close once everything queued is written (finish())
        self._abort_next = False  # cut(): close the port with a reset where it can
        #: Since when the peer's request has been incomplete (None: not waiting for one): set
        #: by the protocol of a served client; a :class:`~gateway.io.server.PortServer` cuts
        #: a client whose request stays incomplete too long.
        self.partial_since: float | None = None

    # -- any thread --------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    @property
    def port(self) -> Any:
        """The open port, or None while it is down (for reading settings, not for I/O)."""
        return self._port

    def use_loop(self, loop: IoLoop) -> None:
        """Serve the port on ``loop`` (shared with others, started and stopped by its owner)
        instead of a loop of the engine's own; only before :meth:`start`."""
        if self._started:
            raise RuntimeError(f"{self.name}: use_loop() after start()")
        if loop is self._loop:
            return
        if self._own_loop:
            self._loop.close()
        self._loop = loop
        self._own_loop = False

    @property
    def loop(self) -> IoLoop:
        return self._loop

    def submit(self, data: bytes, *, rate_limited: bool = True) -> Outcome:
        """Queue ``data`` for the port; never blocks.  See the module doc for the outcomes."""
        st = self.stats
        with self._lock:
            st.submitted += 1
            if not self._up:  # (started, not closing, port attached: see _set_up)
                st.dropped_not_ready += 1
                return _NOT_READY
            now = 0.0
            limited = rate_limited and self.min_interval_s > 0
            if limited:
                now = self._clock()
                last = self._last_accepted
                if last is not None and now - last < self.min_interval_s:
                    st.dropped_throttled += 1
                    return _THROTTLED
            if len(self._queue) >= self.queue_depth:
                st.dropped_queue_full += 1
                return _QUEUE_FULL
            if limited:
                self._last_accepted = now
            st.accepted += 1
            schedule = not self._flush_scheduled
            # nothing queued, nothing pending, and on the port's thread (the attaching one):
            direct = schedule and _get_ident() == self._loop_ident
            if direct:
                self._writing = True
            else:
                self._queue.append(data)
                self._flush_scheduled = True
        if direct:
            self._write_now(data)  # on the port's thread: write it, no queue, no hand-over
        elif schedule:
            self._loop.call_soon(self._flush)
        return _ACCEPTED

    def send_datagram(self, data: bytes) -> bool:
        """Write one datagram at once, on the engine's thread: a router's per-frame path
        (what :meth:`submit` does there when nothing is queued, without its bookkeeping).
        False when it cannot be written directly now (not up, another thread, something
        queued): then use :meth:`submit`."""
        if not self._up or self._writing or self._flush_scheduled or \
                _get_ident() != self._loop_ident:
            return False
        st = self.stats
        st.submitted += 1
        st.accepted += 1
        try:
            self._port.write(data)
        except Exception as exc:
            st.write_errors += 1
            self._fail(exc, "write failed")
            return True  # taken (and lost with the port, counted)
        st.sent_frames += 1
        st.sent_bytes += len(data)
        return True

    def send_datagrams(self, datagrams: list[bytes], first: int | None = None) -> bool:
        """:meth:`send_datagram` for several at once, in order, through the port's
        ``write_many`` (one system call where the platform allows); False, with nothing
        written, when they cannot be written directly now (then :meth:`submit` each).
        ``first``: a compiled lane already made the first call (it checked that the port
        could be written), see ``MmsgSocket.send``."""
        if first is None and (not self._up or self._writing or self._flush_scheduled or
                              _get_ident() != self._loop_ident):
            return False
        st = self.stats
        n = len(datagrams)
        st.submitted += n
        st.accepted += n
        try:
            if first is None:
                self._port.write_many(datagrams)
            else:
                self._port.write_many(datagrams, first)
        except Exception as exc:
            st.write_errors += 1
            self._fail(exc, "write failed")
            return True  # taken (and lost with the port, counted)
        st.sent_frames += n
        st.sent_bytes += sum(map(len, datagrams))
        return True

    def queued(self) -> int:
        return len(self._queue)

    @property
    def alive(self) -> bool:
        """Started, not closed and its port attached (or being opened): a server's client
        that still holds its slot."""
        return self._started and not self._closing and (self._port is not None
                                                       or self.reopen)

    def stalled_for(self, now: float) -> float:
        """How long something has waited for the port to take it (0: nothing waits): a
        client that stopped reading."""
        since = self._blocked_since
        return 0.0 if since is None else now - since

    def cut(self, why: str) -> None:
        """Close the port now, dropping what is queued (a server cutting a client); on the
        engine's thread.  ``on_link(False)`` follows; nothing is logged (the server logs its
        cuts once per burst)."""
        if self._port is not None:
            log.debug("%s: cut (%s)", self.name, why)
            self._abort_next = True  # a reset: what is unsent is dropped (SocketPort.abort)
            self._fail(None, why)

    def finish(self) -> None:
        """Close the port once everything queued has been written (an answer, then the end
        of the connection); on the engine's thread."""
        if self._port is None:
            return
        if self._queue or self._pending or self._writing or self._flush_scheduled:
            self._finish = True
        else:
            self._fail(None, "finished")

    def stats_dict(self) -> dict[str, int]:
        """The counters with the totals (``dropped``, ``errors``) and ``link`` (1 up, 0 down)."""
        d = self.stats.as_dict()
        d["link"] = int(self._connected.is_set())
        return d

    def call_soon(self, fn: Callable[[], Any]) -> None:
        """Run ``fn`` on the engine's thread soon."""
        self._loop.call_soon(fn)

    def call_later(self, delay: float, fn: Callable[[], Any]) -> Timer:
        """Run ``fn`` on the engine's thread after ``delay`` seconds."""
        return self._loop.call_later(delay, fn)

    def call_every(self, period: float, fn: Callable[[], Any], *, first: float = 0.0) -> Timer:
        """Run ``fn`` on the engine's thread every ``period`` seconds."""
        return self._loop.call_every(period, fn, first=first)

    def start(self) -> None:
        """Open the port (in the engine's thread) and start serving it; safe twice."""
        if self._begin():
            self._loop.call_soon(self._open)

    def start_with(self, port: Any) -> None:
        """Start serving ``port``, already open (a client a :class:`PortServer` accepted):
        no open attempt; on the loop's thread it is attached at once, so what is submitted
        right after is not refused.  Reopening (if ``reopen``) goes through the opener."""
        if not self._begin():
            return
        if self._loop.in_loop_thread:
            self._opened(port, None)
        else:
            self._loop.call_soon(lambda: self._opened(port, None))

    def _begin(self) -> bool:
        """Mark the engine started and run its loop; False when it already was."""
        if self._started:
            return False
        self._started = True
        self._closing = False
        self._shut.clear()
        if self._own_loop:
            if self._loop.closed:
                self._loop = IoLoop(self.name)  # started again after close()
            self._loop.start()
        return True

    def wait_connected(self, timeout: float) -> bool:
        """Block until the port is open (for start-up and tests)."""
        return self._connected.wait(timeout)

    def drain(self, timeout: float) -> bool:
        """Wait until every queued frame has been written (True) or ``timeout`` passes."""
        deadline = time.monotonic() + timeout
        with self._idle:
            self._drainers += 1
            try:
                while self._queue or self._writing or self._pending:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return False
                    self._idle.wait(left)
            finally:
                self._drainers -= 1
        return True

    def reconnect(self) -> None:
        """Close the port and reopen it with backoff (a caller saw it misbehave)."""
        def request() -> None:
            if self._port is not None:
                self.stats.reconnects_requested += 1
                self._fail(None, "reconnect requested")
        self._loop.call_soon(request)

    @contextlib.contextmanager
    def exclusive(self, timeout: float = 5.0) -> Iterator[Any]:
        """Park the engine and lend its open port to the caller for the ``with`` block.

        Nothing is read or written by the engine meanwhile; submitted frames queue (up to
        ``queue_depth``).  Raises :class:`PortNotReady` when the port is down, the engine is
        not running, or it cannot be parked within ``timeout`` (a write stuck that long).
        Settings the block changed (``baudrate``, ``timeout``: an exchange at another rate)
        are put back before the engine resumes; if that fails the port is reopened."""
        if self._loop.in_loop_thread:
            port = self._require_port()
            saved = _lent_settings(port)
            try:
                yield port
            finally:
                self._restore_lent(port, saved)
            return
        if not self._started or self._closing or not self._loop.running:
            raise PortNotReady(f"{self.name}: the port engine is not running")
        parked = threading.Event()
        release = threading.Event()
        lent: list[Any] = []

        def park() -> None:
            lent.append(self._port)
            parked.set()
            release.wait()  # the engine's thread waits here while the caller has the port

        self._loop.call_soon(park)
        if not parked.wait(timeout):
            release.set()
            raise PortNotReady(f"{self.name}: the port is busy (not free within {timeout} s)")
        try:
            port = lent[0]
            if port is None:
                raise PortNotReady(f"{self.name}: the port is down")
            saved = _lent_settings(port)
            try:
                yield port
            finally:
                self._restore_lent(port, saved)  # still ours: the engine is parked
        finally:
            release.set()

    def _restore_lent(self, port: Any, saved: dict[str, Any]) -> None:
        """Put back the settings an exclusive block changed; reopen the port if that fails."""
        for name, value in saved.items():
            try:
                if getattr(port, name) != value:
                    setattr(port, name, value)
            except Exception as exc:
                log.warning("%s: cannot restore the port's %s after exclusive use (%s); "
                            "reopening it", self.name, name, exc)
                self.reconnect()
                return

    def close(self, timeout: float = 1.0) -> None:
        """Write what is queued (while the port is up), close the port and stop, returning
        within about ``timeout``; safe twice and before :meth:`start`.  Frames still queued
        then are counted as not-ready drops; a thread stuck in a write that never returns is
        abandoned (it is a daemon thread)."""
        with self._lock:
            if not self._started:
                return
            self._closing = True
            self._up = False
        if self._loop.in_loop_thread or not self._loop.alive:
            self._shutdown()  # (a shared loop already stopped would never run it)
        else:
            self._loop.call_soon(self._shutdown)
            if not self._shut.wait(timeout):
                log.warning("%s: port did not close within %.1f s; abandoning it", self.name,
                            timeout)
                self._abandon()
        if self._own_loop and self._loop.stop(0.2):
            self._loop.close()
        with self._lock:
            self._started = False

    # -- the engine's thread -----------------------------------------------------------------

    def _require_port(self) -> Any:
        if self._port is None:
            raise PortNotReady(f"{self.name}: the port is down")
        return self._port

    def _open(self) -> None:
        """Start one open attempt.  The opener runs on the loop's pool of blocking calls
        (:meth:`IoLoop.run_blocking`): an open can block for seconds (pyserial's
        ``socket://`` waits up to 5 s for a host that does not answer) and the engine's
        thread must stay free to stop or to serve the other engines of a shared loop."""
        self._retry = None
        if self._closing or self._port is not None or self._opening:
            return
        self._opening = True
        self._loop.run_blocking(self._open_in_background, name=f"open {self.name}")

    def _open_in_background(self) -> None:
        """(A pool worker.)  The result goes back to the loop unless close() came first;
        then the late port is closed here, as the loop may be gone."""
        port: Any = None
        error: Exception | None = None
        try:
            port = self._opener()
        except Exception as exc:
            error = exc
        with self._lock:
            closing = self._closing
            if not closing:
                self._loop.call_soon(lambda: self._opened(port, error))
        if closing:  # close() came first: nobody will use this port
            self._opening = False
            if port is not None:
                self._close_port(port)

    def _opened(self, port: Any, error: Exception | None) -> None:
        self._opening = False
        if error is not None:
            self.stats.connect_failures += 1
            if not self._outage_logged:
                self._outage_logged = True
                log.warning("%s: %s; retrying", self.name, error)
            else:
                log.debug("%s: %s; retrying", self.name, error)
            self._schedule_open()
            return
        if self._closing:
            self._close_port(port)
            return
        self._attach(port)

    def _schedule_open(self) -> None:
        if self._closing or not self.reopen:
            return
        self._retry = self._loop.call_later(self._backoff.next(), self._open)

    def _attach(self, port: Any) -> None:
        if hasattr(port, "timeout") and not getattr(port, "datagram", False):
            with contextlib.suppress(Exception):
                if port.timeout != 0:  # (a needless set costs an RFC 2217 round trip)
                    port.timeout = 0  # reads return what is waiting, at once
        fd = None
        with contextlib.suppress(Exception):
            fd = port.fileno()
        self._port = port
        self._fd = fd
        self._batches = self._reader(port)
        self._lane = self._lane_of(port) if self._batches is not None else None
        self._loop_ident = threading.get_ident()
        if fd is not None:
            self._set_interest(write=False)
        elif self.protocol is not None:
            self._poll = self._loop.call_every(self.poll_s, self._read_available,
                                               first=self.poll_s)
        self.stats.connects += 1
        self._backoff.reset()
        if self._outage_logged or self.stats.connects > 1:
            self._burst("up", "port is up", logging.INFO).event()
        self._outage_logged = False
        with self._lock:
            self._connected.set()
            self._up = self._started and not self._closing
        if self.on_link is not None:
            self.on_link(True)
        self._flush()

    def _set_interest(self, *, write: bool) -> None:
        """Watch the port's descriptor for reading (with a protocol) and, while a partial
        write is pending, for writing."""
        self._want_write = write
        fd = self._fd
        if fd is None:
            return
        mask = (selectors.EVENT_READ if self.protocol is not None and not self._holding
                else 0) | (selectors.EVENT_WRITE if write else 0)
        if mask == self._interest:
            return
        if self._interest and mask:
            self._loop.modify(fd, mask, self._on_ready)
        elif mask:
            self._loop.register(fd, mask, self._on_ready)
        else:
            self._loop.unregister(fd)
        self._interest = mask

    def _on_ready(self, mask: int) -> None:
        if mask & selectors.EVENT_READ:
            self._read_available()
        if mask & selectors.EVENT_WRITE and self._port is not None:
            self._flush()

    def _read_available(self) -> None:
        port = self._port
        if port is None:
            return
        batches = self._batches
        if batches is not None:
            self._read_batches(port, *batches)
            return
        datagram = getattr(port, "datagram", False)
        many = getattr(self.protocol, "feed_many", None) if datagram else None
        if many is not None:
            self._read_datagrams(port, many)
            return
        # A polled stream is drained at each poll: some ports hand over a single byte a read
        # when they must not wait (pyserial's rfc2217:// at timeout 0).
        drain = self._fd is None and not datagram
        for _ in range(DATAGRAM_BATCH if datagram else 1):
            try:
                data = port.read(READ_SIZE)
                if drain and data:
                    data = _read_more(port, data)
            except Exception as exc:  # pyserial: SerialException / OSError / TypeError
                self.stats.read_errors += 1
                self._fail(exc, "read failed")
                return
            if not data:
                return
            self.stats.received_bytes += len(data)
            self._deliver(data)
            if self._port is not port:
                return  # a handler closed or reopened the port

    def _read_datagrams(self, port: Any, feed_many: Callable[[list[bytes]], Any]) -> None:
        """A datagram port whose protocol has ``feed_many(datagrams)``: what is waiting, in
        batches (see COALESCE_S and BACKLOG_GAP_S), each handed over in one call (a
        router's per-frame path); a port with ``read_many`` is read by :meth:`_read_batches`."""
        batch: list[bytes] = []
        read, keep = port.read, batch.append
        error: Exception | None = None
        backlog = time.monotonic() - self._datagrams_done < BACKLOG_GAP_S
        for _ in range(DATAGRAM_BATCH if backlog else 1):
            try:
                data = read(READ_SIZE)
            except Exception as exc:
                error = exc
                break
            if not data:
                break
            keep(data)
        if batch:
            self._feed_batch(batch, feed_many)
        self._datagrams_done = time.monotonic()
        if error is not None and self._port is port:
            self.stats.read_errors += 1
            self._fail(error, "read failed")

    def _reader(self, port: Any) -> tuple[Callable[[], list[bytes]],
                                          Callable[[list[bytes]], Any]] | None:
        """How :meth:`_read_batches` reads ``port`` (found once per open, not per wake-up):
        a datagram port's ``read_many`` and its protocol's ``feed_many``; None otherwise."""
        if not getattr(port, "datagram", False):
            return None
        read_many = getattr(port, "read_many", None)
        feed_many = getattr(self.protocol, "feed_many", None)
        if read_many is None or feed_many is None:
            return None
        return read_many, feed_many

    def _read_batches(self, port: Any, read_many: Callable[[], list[bytes]],
                      feed_many: Callable[[list[bytes]], Any]) -> None:
        """What is waiting on a batch-read datagram port, each batch handed over in one call,
        again while batches come full; then, inside a stream, the port is held (see
        COALESCE_S)."""
        got = 0
        for _ in range(COALESCE_MAX_READS):
            try:
                batch = read_many()
            except Exception as exc:
                if self._port is port:
                    self.stats.read_errors += 1
                    self._fail(exc, "read failed")
                return
            if batch:
                got += len(batch)
                self._feed_batch(batch, feed_many)
                if self._port is not port:
                    return  # the protocol closed or reopened the port
            if len(batch) < DATAGRAM_BATCH:
                break
        lane = self._lane
        if got and lane is not None and self._run_lane(port, lane):
            return
        now = time.monotonic()
        dense = now - self._datagrams_done < COALESCE_GAP_S
        self._datagrams_done = now
        # A hold that found nothing means the datagrams come in bursts, each read whole at
        # once: holding after one only costs a wake-up.  Until a wake-up reads a few
        # datagrams only (a paced stream again), batches are read as they come.
        holding = self._holding
        if holding:
            if not got:
                self._bursty = True
        elif got < BURST_MIN:
            self._bursty = False
        if got and dense and self.coalesce_s > 0 and (holding or not self._bursty):
            if not holding:  # leave the port unwatched for coalesce_s, then read it again
                self._holding = True
                self._set_interest(write=self._want_write)
            self._held = (port, read_many, feed_many)
            self._loop.call_at_here(now + self.coalesce_s, self._resume)
        elif holding:
            self._watch_port()

    def _lane_of(self, port: Any) -> Callable[[Callable[[], None]], bool] | None:
        """The protocol's compiled lane for ``port`` (``lane_for(engine, port, feed)``), if it
        has one; ``feed(datagrams, senders)`` is the port's own path for what it hands back."""
        lane_for = getattr(self.protocol, "lane_for", None)
        if lane_for is None or self._batches is None:
            return None
        feed_many = self._batches[1]

        def feed(datagrams: list[bytes], senders: list[Any]) -> None:
            port.took(senders)
            self._feed_batch(datagrams, feed_many)

        lane: Callable[[Callable[[], None]], bool] | None = lane_for(self, port, feed)
        return lane

    def _run_lane(self, port: Any, lane: Callable[[Callable[[], None]], bool], *,
                  again_: bool = False) -> bool:
        """Run the lane (the loop's thread waits and routes in compiled code until the loop
        has work); the port's descriptor is not watched meanwhile.  False: it did not apply
        now (then the port is read and held as before).

        When the lane ends for the loop's work (a timer due, an event), the port stays
        unwatched and the lane starts again right after that work (:meth:`_lane_again`), not
        through a wake-up and a read of the port's own path: a router's ticks (50 a second)
        cost that much each otherwise."""
        started = again_  # (again: the port is unwatched already)
        if self._lane_next is not None:
            self._lane_next.cancel()
            self._lane_next = None

        def begin() -> None:
            nonlocal started
            if not started:
                started = True
                self._holding = True
                self._set_interest(write=self._want_write)

        ran = again = False
        try:
            ran = lane(begin)
            self.lane_runs += ran
            again = ran and self._port is port and self._lane is lane and not self._closing
        except OSError as exc:  # a read failed
            if self._port is port:
                self.stats.read_errors += 1
                self._fail(exc, "read failed")
        except Exception:
            self.stats.protocol_errors += 1
            log.exception("%s: the router's lane failed (the Python path goes on)", self.name)
            self._lane = None
        finally:
            if again:  # after the loop's work (timers due before now run first)
                self._lane_next = self._loop.call_at_here(time.monotonic(), self._lane_again)
            elif started and self._port is port:
                self._watch_port()
        return ran

    def _lane_again(self) -> None:
        """The lane, again, after the loop's work (see :meth:`_run_lane`); where it does not
        apply now, the port is watched again and read by its own path."""
        port, lane = self._port, self._lane
        self._lane_next = None
        if port is None or lane is None or self._closing:
            if self._port is port and port is not None:
                self._watch_port()
            return
        self._run_lane(port, lane, again_=True)

    def _watch_port(self) -> None:
        """The end of a hold or of the lane: the port's descriptor is watched again."""
        self._holding = False
        self._set_interest(write=self._want_write)

    def _resume(self) -> None:
        """The end of a hold: read what came meanwhile (unless the port changed)."""
        port, read_many, feed_many = self._held
        if self._port is port and self._holding:
            self._read_batches(port, read_many, feed_many)

    def _feed_batch(self, batch: list[bytes], feed_many: Callable[[list[bytes]], Any]) -> None:
        self.stats.received_bytes += sum(map(len, batch))
        try:
            events = feed_many(batch)
        except Exception:
            self.stats.protocol_errors += 1
            log.exception("%s: the protocol failed on %d datagrams (skipped)", self.name,
                          len(batch))
            events = ()
        handler = self.on_event
        if handler is not None:
            for ev in events:
                handler(ev)

    def _deliver(self, data: bytes) -> None:
        protocol = self.protocol
        if protocol is None:
            return
        try:
            events = protocol.feed(data)
        except Exception:
            self.stats.protocol_errors += 1
            log.exception("%s: the protocol failed on %d bytes (skipped)", self.name, len(data))
            return
        handler = self.on_event
        if handler is not None:
            for ev in events:
                handler(ev)

    def _flush(self) -> None:
        """Write everything queued, in order (on the engine's thread)."""
        queue, lock, st = self._queue, self._lock, self.stats
        while True:
            with lock:
                port = self._port
                if port is None:
                    self._flush_scheduled = False
                    return  # the port went down meanwhile: _fail counted what was queued
                if self._pending:
                    data, whole = self._pending, False
                elif queue:
                    data, whole = queue.popleft(), True
                else:
                    self._flush_scheduled = False
                    self._idle.notify_all()
                    finish = self._finish
                    break
                self._writing = True
            try:
                n = port.write(data)
            except Exception as exc:
                with lock:
                    self._writing = False
                st.write_errors += 1
                self._fail(exc, "write failed")
                return
            with lock:
                self._writing = False
                if whole:
                    st.sent_frames += 1
                    st.sent_bytes += len(data)
                if n is not None and n < len(data):
                    self._pending = data[n:]  # a non-blocking socket took part: wait for room
                    if self._blocked_since is None:
                        self._blocked_since = time.monotonic()
                    self._set_interest(write=True)
                    return
                if self._pending:
                    self._pending = b""
                    self._set_interest(write=False)
                self._blocked_since = None
        if finish:
            self._fail(None, "finished")

    def _write_now(self, data: bytes) -> None:
        """Write one frame submitted on the engine's thread while nothing was queued or
        pending (the router's per-frame path): one write, no queue round trip."""
        st = self.stats
        try:
            n = self._port.write(data)
        except Exception as exc:
            with self._lock:
                self._writing = False
                self._idle.notify_all()
            st.write_errors += 1
            self._fail(exc, "write failed")
            return
        st.sent_frames += 1  # (only this thread writes these counters)
        st.sent_bytes += len(data)
        if n is not None and n < len(data):
            with self._lock:
                self._pending = data[n:]  # the rest when the port has room, before the queue
                if self._blocked_since is None:
                    self._blocked_since = time.monotonic()
                self._flush_scheduled = True
                self._writing = False
                self._set_interest(write=True)
            return
        self._writing = False  # no lock: a drain() that starts waiting counts itself first
        if self._drainers:
            with self._lock:
                self._idle.notify_all()

    def _fail(self, exc: BaseException | None, what: str) -> None:
        """Close the failed port, report the link down and reopen with backoff."""
        port = self._port
        if port is None:
            return
        self.stats.disconnects += 1  # counted before it is logged: a reader of the log
        self._outage_logged = True     # sees the count
        self._detach(port)
        if exc is not None:
            # A peer hanging up on a connection we do not reopen (an accepted client) is the
            # normal end of it, not a fault.
            if self.reopen:  # a peer can hang up at once, again and again: once per burst
                self._burst(what, f"{what}; reopening", logging.WARNING).event(str(exc))
            else:
                level = (self.hangup_level if isinstance(exc, ConnectionError)
                         else logging.WARNING)
                log.log(level, "%s: %s (%s); closed (not reopened)", self.name, what, exc)
        self._flush_protocol()
        if self.on_link is not None:
            self.on_link(False)
        self._schedule_open()

    def _burst(self, kind: str, text: str, level: int) -> BurstLog:
        """The log of a kind of event a peer can repeat (a port that comes up and fails at
        once, in a loop): a line when a burst starts, then one with the count per 10 s."""
        burst = self._bursts.get(kind)
        if burst is None:
            burst = self._bursts[kind] = BurstLog(self._loop, f"{self.name}: {text}",
                                                  level=level, logger=log)
        return burst

    def _detach(self, port: Any) -> None:
        with self._lock:
            self._port = None
            self._connected.clear()
            self._up = False
            self.stats.dropped_not_ready += len(self._queue)
            self._queue.clear()
            self._pending = b""
            self._blocked_since = None
            self._finish = False
            self._flush_scheduled = False
            self._idle.notify_all()
        if self._fd is not None:
            if self._interest:
                self._loop.unregister(self._fd)
            self._interest = 0
            self._fd = None
        self._holding = False
        self._batches = None
        self._lane = None
        if self._lane_next is not None:
            self._lane_next.cancel()
            self._lane_next = None
        self._held = (None, None, None)
        if self._poll is not None:
            self._poll.cancel()
            self._poll = None
        self._close_port(port)

    def _flush_protocol(self) -> None:
        """The stream broke: nothing completes a pending frame; let the protocol say so."""
        flush = getattr(self.protocol, "flush", None)
        if flush is None:
            return
        try:
            events = flush()
        except Exception:
            self.stats.protocol_errors += 1
            log.exception("%s: the protocol failed to flush", self.name)
            return
        handler = self.on_event
        if handler is not None:
            for ev in events:
                handler(ev)

    def _close_port(self, port: Any) -> None:
        abort, self._abort_next = self._abort_next, False
        try:
            getattr(port, "abort", port.close)() if abort else port.close()
        except Exception:
            log.debug("%s: error closing the port", self.name, exc_info=True)

    def _shutdown(self) -> None:
        if self._retry is not None:
            self._retry.cancel()
            self._retry = None
        port = self._port
        if port is not None:
            self._flush()
            port = self._port
        if port is not None:
            self._detach(port)
            self._flush_protocol()
            if self.on_link is not None:
                self.on_link(False)
        self._shut.set()

    def _abandon(self) -> None:
        """close() timed out (a write that never returns): drop what is queued, close the port
        from here so a blocked writer is released, and leave the thread behind."""
        with self._lock:
            self.stats.dropped_not_ready += len(self._queue)
            self._queue.clear()
            port, self._port = self._port, None
            self._connected.clear()
            self._up = False
            self._idle.notify_all()
        if self._poll is not None:
            self._poll.cancel()
        if port is not None:
            self._close_port(port)


def _read_more(port: Any, data: bytes) -> bytes:
    """``data`` and whatever else ``port`` has waiting, up to ``READ_SIZE`` bytes."""
    parts = [data]
    total = len(data)
    while total < READ_SIZE:
        more = port.read(READ_SIZE - total)
        if not more:
            break
        parts.append(more)
        total += len(more)
    return b"".join(parts) if len(parts) > 1 else data


LENT_SETTINGS = ("baudrate", "timeout")


def _lent_settings(port: Any) -> dict[str, Any]:
    """The settings of ``port`` an exclusive block may change and the engine puts back."""
    saved: dict[str, Any] = {}
    for name in LENT_SETTINGS:
        with contextlib.suppress(Exception):
            if hasattr(port, name):
                saved[name] = getattr(port, name)
    return saved

