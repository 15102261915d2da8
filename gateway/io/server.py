"""The one edge for every TCP (and Unix) server of the gateway: :class:`PortServer`.

MAVLink ``tcpin``, UAVTalk, F´, the HC-12 control socket and the HTTP status page all listen
through it, on an :class:`~gateway.io.ioloop.IoLoop`, with the same limits (:class:`ClientLimits`):

* **a client cap** (``max_clients``, default 32).  A connection past it is accepted and
  closed at once — with ``refusal`` written first (HTTP: a short ``503``) — so it never waits
  in the backlog; counted as ``clients_refused``.  A newcomer may take the slot of a client
  whose request is still incomplete (:attr:`~gateway.io.port.PortEngine.partial_since`) if
  that one has been at it for ``SHED_AFTER_S`` or the newcomer holds a whole request
  (``ready(sock)``; a newcomer that has sent nothing yet waits up to ``WAIT_S`` for its
  request, ``MAX_WAITING`` at most, and one that has sent part of one is refused at the next
  look): slow talkers cannot lock out a client that has something to say;
* **a listen backlog** of ``BACKLOG`` (1024; at least 128): a burst of connects is queued;
* **a bounded write queue per client**: each client is a
  :class:`~gateway.io.port.PortEngine` (``queue_depth``) that the backend builds in
  ``on_client(sock, address)`` and returns;
* **timeouts** (``client_timeout_s``, default 5 s): a client that stops reading (something
  has waited to be written that long) is cut (``clients_cut_stalled``); a client whose
  request stays incomplete that long is cut (``clients_cut_partial``) — where the protocol
  has requests and says so through ``partial_since`` (HTTP, the HC-12 control socket; a
  telemetry stream's codec resyncs on its own and has none).  A cut is a reset: what the
  peer did not read is dropped, the slot and the kernel's buffers are freed at once;
* **accept failing** for want of descriptors (EMFILE/ENFILE…) is counted (``accept_errors``)
  and backed off (the listener is left alone for a while), never a busy loop; a spare
  descriptor is given up for a moment so the connection that could not be accepted is
  refused, not left hanging;
* every refusal and cut is **logged once per burst**: one line when it starts, then one line
  with the count per :data:`~gateway.io.burstlog.BURST_LOG_S` while it lasts.

The counters are :class:`ServerStats`; :func:`server_stats` sums those of a backend's
servers into the keys its ``stats()`` reports (and the stop report prints).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import selectors
import socket
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from gateway.checks import at_least, positive
from gateway.counters import Counters
from gateway.io.backoff import Backoff
from gateway.io.burstlog import BurstLog
from gateway.io.ioloop import IoLoop, Timer
from gateway.io.port import DEFAULT_QUEUE_DEPTH, REOPEN_FIRST_S, REOPEN_MAX_S, PortEngine
from gateway.io.transport import LISTEN_BACKLOG
from gateway.options import DEFAULT_CLIENT_TIMEOUT_S, DEFAULT_MAX_CLIENTS, ListenerOptions

log = logging.getLogger(__name__)

BACKLOG = LISTEN_BACKLOG
#: A client whose request has been incomplete this long gives its slot to a newcomer when
#: the server is full.
SHED_AFTER_S = 0.5
#: At the cap, with incomplete clients to shed: how long a newcomer may take to show a whole
#: request (then it takes the slot of the oldest incomplete one; else it is refused), and
#: how many newcomers may wait so at once (past it: refused at once).
WAIT_S = 0.1
WAIT_CHECK_S = 0.01
MAX_WAITING = 64
#: Accepts handled per wake-up of the loop (a burst of connects is taken in a few passes).
ACCEPT_BATCH = 64
#: A refused connection is half-closed and read until the peer closes, at most this long, so
#: that what the peer sent does not turn our close into a reset that loses the refusal...
LINGER_S = 1.0
#: ...for at most this many at once (past it: closed at once).
MAX_LINGERING = 64
#: Accept failing for want of descriptors: the listener rests this long, doubling to the max.
ACCEPT_PAUSE_FIRST_S = 0.05
ACCEPT_PAUSE_MAX_S = 1.0
_NO_DESCRIPTORS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)


@dataclass(frozen=True)
class ClientLimits:
    """What one listener allows its clients (the ``max_clients`` / ``client_timeout_s`` keys)."""

    max_clients: int = DEFAULT_MAX_CLIENTS
    client_timeout_s: float = DEFAULT_CLIENT_TIMEOUT_S
    queue_depth: int = DEFAULT_QUEUE_DEPTH

    def __post_init__(self) -> None:
        at_least("max_clients", self.max_clients, 1)
        positive("client_timeout_s", self.client_timeout_s)

    @classmethod
    def of(cls, options: ListenerOptions, queue_depth: int = DEFAULT_QUEUE_DEPTH
           ) -> ClientLimits:
        """The limits a backend's declared listener options set."""
        return cls(options.max_clients, options.client_timeout_s, queue_depth)


@dataclass
class ServerStats(Counters):
    """The counters of one listener."""

    accepted: int = 0
    clients_refused: int = 0
    clients_cut_stalled: int = 0
    clients_cut_partial: int = 0
    accept_errors: int = 0
    bind_failures: int = 0


#: The keys :func:`server_stats` reports (a backend's ``stats()``, the stop report).
SERVER_KEYS = ("clients_refused", "clients_cut_stalled", "clients_cut_partial",
               "accept_errors")


def server_stats(servers: Iterable[PortServer]) -> dict[str, int]:
    """The refusal and cut counters of ``servers``, summed, for a backend's ``stats()``."""
    out = dict.fromkeys(SERVER_KEYS, 0)
    for server in servers:
        st = server.stats
        for key in SERVER_KEYS:
            out[key] += getattr(st, key)
    return out


class PortServer:
    """A listener on ``loop`` with the limits of the module doc.

    ``opener()`` returns a bound, listening, non-blocking socket (bound again with backoff
    after a failure); ``on_client(sock, address)`` serves an accepted connection — typically
    a :class:`~gateway.io.port.PortEngine` on the same loop with ``reopen=False``, which it
    returns so the server can hold it to the limits (None: the caller keeps it to itself and
    it does not count against the cap).  ``ready(sock)``: does a newcomer at the cap already
    hold a whole request (then it may take an incomplete client's slot)?"""

    def __init__(
        self,
        opener: Callable[[], Any],
        on_client: Callable[[Any, Any], PortEngine | None],
        *,
        loop: IoLoop,
        name: str = "server",
        limits: ClientLimits | None = None,
        refusal: bytes = b"",
        ready: Callable[[socket.socket], bool] | None = None,
        backoff: Backoff | None = None,
    ) -> None:
        self.name = name
        self.loop = loop
        self.limits = limits or ClientLimits()
        self.refusal = refusal
        self.stats = ServerStats()
        self.sock: Any = None
        self.clients: list[PortEngine] = []  # loop thread only
        self._opener = opener
        self._on_client = on_client
        self._ready = ready
        self._backoff = backoff or Backoff(REOPEN_FIRST_S, REOPEN_MAX_S)
        self._pause = Backoff(ACCEPT_PAUSE_FIRST_S, ACCEPT_PAUSE_MAX_S)
        self._bound = threading.Event()
        self._retry: Timer | None = None
        self._resume: Timer | None = None
        self._sweep: Timer | None = None
        self._lingering: dict[socket.socket, Timer] = {}
        self._waiting: dict[socket.socket, tuple[Any, float]] = {}  # newcomers at the cap
        self._spare: int | None = None
        self._closing = False
        self._logged = False
        self._refused_log = BurstLog(loop, f"{name}: refusing clients "
                                     f"(at most {self.limits.max_clients})", logger=log)
        self._cut_log = BurstLog(loop, f"{name}: cutting clients", level=logging.INFO,
                                 logger=log)
        self._accept_log = BurstLog(loop, f"{name}: cannot accept", logger=log)

    # -- any thread --------------------------------------------------------------------------

    @property
    def address(self) -> Any:
        sock = self.sock
        return sock.getsockname() if sock is not None else None

    @property
    def accepted(self) -> int:
        return self.stats.accepted

    @property
    def bind_failures(self) -> int:
        return self.stats.bind_failures

    @property
    def client_count(self) -> int:
        return len(self.clients)

    def stats_dict(self) -> dict[str, int]:
        d = self.stats.as_dict()
        d["clients"] = len(self.clients)
        return d

    def start(self) -> None:
        self._closing = False
        self.loop.call_soon(self._bind)

    def wait_bound(self, timeout: float) -> bool:
        return self._bound.wait(timeout)

    def close(self) -> None:
        """Stop listening (clients are their owners' to close); safe twice, any thread."""
        self._closing = True
        if self.loop.in_loop_thread or not self.loop.running:
            self._close_now()
        else:
            done = threading.Event()

            def close_now() -> None:
                self._close_now()
                done.set()

            self.loop.call_soon(close_now)
            if not done.wait(1.0):
                self._close_now()

    # -- the loop's thread -------------------------------------------------------------------

    def _bind(self) -> None:
        self._retry = None
        if self._closing or self.sock is not None:
            return
        try:
            sock = self._opener()
        except Exception as exc:
            self.stats.bind_failures += 1
            if not self._logged:
                self._logged = True
                log.warning("%s: %s; retrying", self.name, exc)
            self._retry = self.loop.call_later(self._backoff.next(), self._bind)
            return
        if self._logged:
            log.info("%s: listening", self.name)
        self._logged = False
        self._backoff.reset()
        self.sock = sock
        if self._spare is None:
            self._spare = _spare_descriptor()
        self.loop.register(sock, selectors.EVENT_READ, self._on_accept)
        if self._sweep is None:
            period = min(1.0, max(0.02, self.limits.client_timeout_s / 5))
            self._sweep = self.loop.call_every(period, self._check_clients, first=period)
        self._bound.set()

    def _on_accept(self, mask: int) -> None:
        for _ in range(ACCEPT_BATCH):
            sock = self.sock
            if sock is None or self._resume is not None:
                return
            try:
                conn, addr = sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                if exc.errno in _NO_DESCRIPTORS:
                    self._out_of_descriptors(exc)
                    return
                log.warning("%s: accept failed (%s); listening again", self.name, exc)
                self._drop_listener()
                self._retry = self.loop.call_later(self._backoff.next(), self._bind)
                return
            self._pause.reset()
            self._admit(conn, addr)

    def _admit(self, conn: socket.socket, addr: Any) -> None:
        self._prune()
        if len(self.clients) >= self.limits.max_clients and not self._shed_for(conn):
            if (self._ready is not None and len(self._waiting) < MAX_WAITING
                    and any(e.partial_since is not None for e in self.clients)):
                self._waiting[conn] = (addr, time.monotonic() + WAIT_S)
                self.loop.call_later(WAIT_CHECK_S, lambda: self._wait_check(conn))
            else:
                self._refuse(conn, addr)
            return
        self._serve(conn, addr)

    def _wait_check(self, conn: socket.socket) -> None:
        """A newcomer at the cap: admitted once its request is whole (if a slot can be shed
        for it), refused when WAIT_S has passed, dropped if it left."""
        entry = self._waiting.get(conn)
        if entry is None:
            return
        addr, deadline = entry
        try:
            sent = conn.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT)
            gone = not sent
        except (BlockingIOError, InterruptedError):
            sent, gone = b"", False  # nothing sent yet
        except OSError:
            sent, gone = b"", True
        if gone:
            del self._waiting[conn]
            conn.close()
            return
        self._prune()
        if len(self.clients) < self.limits.max_clients or self._shed_for(conn):
            del self._waiting[conn]
            self._serve(conn, addr)
        elif sent or time.monotonic() >= deadline or self._closing:
            # (it sent part of a request and no more: a slow talker, its place goes to the
            # next newcomer at once)
            del self._waiting[conn]
            self._refuse(conn, addr)
        else:
            self.loop.call_later(WAIT_CHECK_S, lambda: self._wait_check(conn))

    def _serve(self, conn: socket.socket, addr: Any) -> None:
        self.stats.accepted += 1
        engine = self._on_client(conn, addr)
        if engine is not None:
            self.clients.append(engine)

    def _shed_for(self, conn: socket.socket) -> bool:
        """At the cap: cut the client whose request has been incomplete longest, if it has
        been so for SHED_AFTER_S or the newcomer has a whole request; True if one was cut."""
        ready = self._ready
        oldest: PortEngine | None = None
        for engine in self.clients:
            since = engine.partial_since
            if since is None or (oldest is not None and since >= (oldest.partial_since or 0)):
                continue
            sock = getattr(engine.port, "sock", None)
            if ready is not None and sock is not None and ready(sock):
                continue  # its request is here, not read yet (a burst): not a slow one
            oldest = engine
        if oldest is None or oldest.partial_since is None:
            return False
        if time.monotonic() - oldest.partial_since < SHED_AFTER_S and not (
                ready is not None and ready(conn)):
            return False
        self.stats.clients_cut_partial += 1  # (counted before the peer can see it)
        self._cut(oldest, "incomplete request, its slot taken by a newcomer")
        return True

    def _refuse(self, conn: socket.socket, addr: Any) -> None:
        self.stats.clients_refused += 1
        self._refused_log.event(_peer(addr))
        try:
            conn.setblocking(False)
            _discard_input(conn)
            if self.refusal:
                conn.send(self.refusal)
            conn.shutdown(socket.SHUT_WR)
        except OSError:
            conn.close()
            return
        if len(self._lingering) >= MAX_LINGERING:
            conn.close()
            return
        self._lingering[conn] = self.loop.call_later(LINGER_S, lambda: self._unlinger(conn))
        try:
            self.loop.register(conn, selectors.EVENT_READ,
                               lambda mask: self._on_lingering(conn))
        except (OSError, ValueError, KeyError):
            self._unlinger(conn)

    def _on_lingering(self, conn: socket.socket) -> None:
        try:
            data = conn.recv(4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._unlinger(conn)

    def _unlinger(self, conn: socket.socket) -> None:
        timer = self._lingering.pop(conn, None)
        if timer is None:
            return
        timer.cancel()
        self.loop.unregister(conn)
        conn.close()

    def _out_of_descriptors(self, exc: OSError) -> None:
        """No descriptor for the next connection: refuse it with the spare one, then let the
        listener rest (a level-triggered poller would otherwise call us at once, forever)."""
        self.stats.accept_errors += 1
        self._accept_log.event(f"{exc.strerror or exc}")
        sock = self.sock
        if self._spare is not None and sock is not None:
            os.close(self._spare)
            self._spare = None
            with contextlib.suppress(OSError):
                conn, _ = sock.accept()
                self.stats.clients_refused += 1
                conn.close()
            self._spare = _spare_descriptor()
        if sock is not None:
            self.loop.unregister(sock)
            self._resume = self.loop.call_later(self._pause.next(), self._resume_accepting)

    def _resume_accepting(self) -> None:
        self._resume = None
        if self.sock is not None and not self._closing:
            self.loop.register(self.sock, selectors.EVENT_READ, self._on_accept)

    def _prune(self) -> None:
        self.clients = [e for e in self.clients if e.alive]

    def _check_clients(self) -> None:
        """Cut the clients that stopped reading or left a request incomplete too long."""
        self._prune()
        now = time.monotonic()
        timeout = self.limits.client_timeout_s
        for engine in list(self.clients):
            if engine.stalled_for(now) >= timeout:
                self.stats.clients_cut_stalled += 1
                self._cut(engine, f"not reading for {timeout:g} s")
            elif engine.partial_since is not None and now - engine.partial_since >= timeout:
                self.stats.clients_cut_partial += 1
                self._cut(engine, f"request incomplete after {timeout:g} s")

    def _cut(self, engine: PortEngine, why: str) -> None:
        self._cut_log.event(f"{engine.name} {why}")
        engine.cut(why)
        with contextlib.suppress(ValueError):
            self.clients.remove(engine)

    def _drop_listener(self) -> None:
        sock, self.sock = self.sock, None
        self._bound.clear()
        if self._resume is not None:
            self._resume.cancel()
            self._resume = None
        if sock is not None:
            self.loop.unregister(sock)
            with contextlib.suppress(OSError):
                sock.close()

    def _close_now(self) -> None:
        if self._retry is not None:
            self._retry.cancel()
            self._retry = None
        if self._sweep is not None:
            self._sweep.cancel()
            self._sweep = None
        self._drop_listener()
        for conn in list(self._lingering):
            self._unlinger(conn)
        for conn in list(self._waiting):
            conn.close()
        self._waiting.clear()
        for burst in (self._refused_log, self._cut_log, self._accept_log):
            burst.cancel()
        if self._spare is not None:
            with contextlib.suppress(OSError):
                os.close(self._spare)
            self._spare = None


def _spare_descriptor() -> int | None:
    try:
        return os.open(os.devnull, os.O_RDONLY)
    except OSError:
        return None


def _discard_input(conn: socket.socket) -> None:
    """Read what the peer has sent already (a close with unread input resets the connection,
    and the peer may lose what we wrote)."""
    with contextlib.suppress(OSError):
        for _ in range(16):
            if not conn.recv(65536):
                return


def _peer(addr: Any) -> str:
    if isinstance(addr, tuple) and len(addr) >= 2:
        return f"{addr[0]}:{addr[1]}"
    return str(addr) or "a client"

