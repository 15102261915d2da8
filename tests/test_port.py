"""The duplex port engine (:mod:`gateway.io.port`) against real ports.

One reopen test per transport kind, each through a :class:`PortEngine` with a small collecting
(or echoing) protocol: a serial device path (a symlink to a pty), pyserial's ``socket://``, a
TCP client, a TCP server (:class:`PortServer`), UDP in and out, ``loop://`` (polled, no file
descriptor) and a device that is plugged in after start.  Then the engine's write contract
(outcomes, order, drain, close, partial writes, timers, exclusive use, protocol errors) and
the backoff.

Synchronisation is on events with deadlines: every engine report (data, flush, link up/down)
lands in an :class:`Events` log that wakes waiters; openers are wrapped to report each
attempt.  Nothing sleeps as synchronisation.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import logging
import os
import random
import select
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import serial
from helpers import BlockingTransport, run_within, wait_for

from gateway.io import mmsg
from gateway.io.backoff import Backoff
from gateway.io.ioloop import IoLoop, Timer
from gateway.io.port import (
    DATAGRAM_BATCH,
    DEFAULT_QUEUE_DEPTH,
    PortEngine,
    PortNotReady,
)
from gateway.io.server import PortServer
from gateway.io.transport import (
    SocketPort,
    open_serial,
    open_tcp_client,
    open_tcp_listener,
    open_udp,
)
from gateway.outcome import Outcome

DEADLINE_S = 5.0
FLUSHED = "flushed"  # the event the collecting protocol's flush() yields


def fast_backoff() -> Backoff:
    return Backoff(0.01, 0.05)


# -- what the engine reports -------------------------------------------------------------------

class Collect:
    """A sans-I/O protocol: every chunk read is one event; ``flush()`` yields :data:`FLUSHED`.
    A chunk containing ``fail_on`` makes ``feed`` raise (a buggy protocol)."""

    def __init__(self, fail_on: bytes | None = None) -> None:
        self.fail_on = fail_on

    def feed(self, data: bytes) -> list[Any]:
        if self.fail_on is not None and self.fail_on in data:
            raise ValueError("the protocol choked")
        return [bytes(data)]

    def flush(self) -> list[Any]:
        return [FLUSHED]


class Events:
    """An ordered log of what an engine reports: ``("data", bytes)``, ``("flush", None)`` and
    ``("link", up)``.  With ``echo`` set to an engine, every chunk read is written back."""

    def __init__(self) -> None:
        self.items: list[tuple[str, Any]] = []
        self.cond = threading.Condition()
        self.echo: PortEngine | None = None
        self.threads: set[str] = set()

    def _add(self, kind: str, value: Any) -> None:
        with self.cond:
            self.items.append((kind, value))
            self.threads.add(threading.current_thread().name)
            self.cond.notify_all()

    def on_event(self, ev: Any) -> None:
        if ev == FLUSHED:
            self._add("flush", None)
            return
        self._add("data", ev)
        if self.echo is not None:
            self.echo.submit(ev, rate_limited=False)

    def on_link(self, up: bool) -> None:
        self._add("link", up)

    def data(self) -> bytes:
        with self.cond:
            return b"".join(v for k, v in self.items if k == "data")

    def datagrams(self) -> list[bytes]:
        with self.cond:
            return [v for k, v in self.items if k == "data"]

    def links(self) -> list[bool]:
        with self.cond:
            return [v for k, v in self.items if k == "link"]

    def kinds(self) -> list[Any]:
        """The log without the data: ``"data"`` (once for consecutive chunks), ``"flush"``,
        ``True``/``False`` (link up/down)."""
        out: list[Any] = []
        with self.cond:
            for k, v in self.items:
                if not (k == "data" and out and out[-1] == "data"):
                    out.append(v if k == "link" else k)
        return out

    def wait(self, pred: Callable[[], bool], timeout: float = DEADLINE_S) -> bool:
        with self.cond:
            return self.cond.wait_for(pred, timeout)

    def wait_links(self, *expected: bool, timeout: float = DEADLINE_S) -> bool:
        """Wait until the link has gone exactly through ``expected`` (True = up)."""
        return self.wait(lambda: self.links() == list(expected), timeout)

    def wait_data(self, data: bytes, timeout: float = DEADLINE_S) -> bool:
        return self.wait(lambda: data in self.data(), timeout)


class Opener:
    """Wraps an opener and reports every attempt (so a test can wait for a failed one)."""

    def __init__(self, fn: Callable[[], Any]) -> None:
        self.fn = fn
        self.opened = 0
        self.failed = 0
        self.cond = threading.Condition()

    def __call__(self) -> Any:
        try:
            port = self.fn()
        except Exception:
            with self.cond:
                self.failed += 1
                self.cond.notify_all()
            raise
        with self.cond:
            self.opened += 1
            self.cond.notify_all()
        return port

    def wait_failed(self, n: int, timeout: float = DEADLINE_S) -> bool:
        """Wait until at least ``n`` attempts in all have failed."""
        with self.cond:
            return self.cond.wait_for(lambda: self.failed >= n, timeout)


@pytest.fixture
def engines() -> Iterator[Callable[..., PortEngine]]:
    """Make engines (closed at teardown).  ``events=`` wires a :class:`Collect` protocol and
    the log's callbacks; ``echo=True`` also writes back every chunk read."""
    made: list[tuple[PortEngine, tuple[BlockingTransport, ...]]] = []

    def make(opener: Callable[[], Any], *, events: Events | None = None, echo: bool = False,
             blocked: tuple[BlockingTransport, ...] = (), **kw: Any) -> PortEngine:
        kw.setdefault("backoff", fast_backoff())
        if events is not None:
            kw.setdefault("protocol", Collect())
            kw.setdefault("on_event", events.on_event)
            kw.setdefault("on_link", events.on_link)
        eng = PortEngine(opener, **kw)
        if echo:
            assert events is not None
            events.echo = eng
        made.append((eng, blocked))
        return eng

    yield make
    for eng, blocked in made:
        for t in blocked:
            t.release.set()
        eng.close(0.5)


@pytest.fixture
def stack() -> Iterator[contextlib.ExitStack]:
    """Peers (ptys, servers, sockets) the test opens, closed at teardown."""
    with contextlib.ExitStack() as s:
        yield s


@pytest.fixture
def io_loop() -> Iterator[IoLoop]:
    """A started loop to share; a test asks for it before ``engines`` so that its engines
    are closed while it still runs."""
    loop = IoLoop("test")
    loop.start()
    yield loop
    loop.stop(1.0)
    loop.close()


def started(make: Callable[..., PortEngine], opener: Callable[[], Any],
            **kw: Any) -> PortEngine:
    eng = make(opener, **kw)
    eng.start()
    assert eng.wait_connected(DEADLINE_S)
    return eng


# -- peers ---------------------------------------------------------------------------------------

class PtyDevice:
    """A serial device at a path the test controls: a symlink to a pty's slave.  ``plug()``
    puts a new pty behind the path; ``unplug()`` removes the link (opens fail) and closes the
    master (reads of the open slave fail)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.master = -1
        self.slave = -1

    def plug(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # nothing echoed or line-edited before the engine opens it
        os.symlink(os.ttyname(self.slave), self.path)

    def unplug(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        for fd in (self.master, self.slave):
            if fd >= 0:
                os.close(fd)
        self.master = self.slave = -1

    def send(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.master, view):]

    def recv_exactly(self, n: int, timeout: float = DEADLINE_S) -> bytes:
        deadline = time.monotonic() + timeout
        data = b""
        while len(data) < n:
            left = deadline - time.monotonic()
            assert left > 0, f"read {len(data)} of {n} bytes: {data!r}"
            ready, _, _ = select.select([self.master], [], [], left)
            if ready:
                data += os.read(self.master, n - len(data))
        return data


def recv_exactly(sock: socket.socket, n: int, timeout: float = DEADLINE_S) -> bytes:
    deadline = time.monotonic() + timeout
    data = b""
    while len(data) < n:
        left = deadline - time.monotonic()
        assert left > 0, f"read {len(data)} of {n} bytes: {data!r}"
        sock.settimeout(left)
        chunk = sock.recv(n - len(data))
        assert chunk, f"the connection closed after {len(data)} of {n} bytes"
        data += chunk
    return data


def ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def bind_quiet(kind: int) -> socket.socket:
    """A socket bound to a free 127.0.0.1 port *below* the ephemeral range.  A port a test
    takes away and brings back must not be one the kernel can hand out as the source port
    of our own reconnect attempts (a socket connected to itself would "succeed")."""
    low = ephemeral_low()
    rng = random.Random()
    for _ in range(500):
        sock = socket.socket(socket.AF_INET, kind)
        if kind == socket.SOCK_STREAM:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(("127.0.0.1", rng.randrange(max(1024, low - 16384), low)))
        except OSError:
            sock.close()
            continue
        return sock
    raise AssertionError("no free port below the ephemeral range")


class TcpServer:
    """A plain TCP server the test drives by hand; ``stop()`` closes the listener and every
    accepted connection (the server "goes away"); a new one may take the same port."""

    def __init__(self, port: int | None = None) -> None:
        if port is None:
            self.sock = bind_quiet(socket.SOCK_STREAM)
            self.sock.listen()
        else:
            self.sock = socket.create_server(("127.0.0.1", port))
        self.port: int = self.sock.getsockname()[1]
        self.conns: list[socket.socket] = []

    def accept(self, timeout: float = DEADLINE_S) -> socket.socket:
        self.sock.settimeout(timeout)
        conn, _ = self.sock.accept()
        self.conns.append(conn)
        return conn

    def stop(self) -> None:
        for c in self.conns:
            c.close()
        self.sock.close()


def free_udp_port() -> int:
    """A UDP port nobody listens on (bound for a moment by us, then released)."""
    with bind_quiet(socket.SOCK_DGRAM) as s:
        return int(s.getsockname()[1])


def loop_port() -> serial.SerialBase:
    return open_serial("loop://", timeout=0)


def read_exactly(port: serial.SerialBase, n: int, timeout: float = DEADLINE_S) -> bytes:
    """Read ``n`` bytes back from a loop:// port (non-blocking reads), within ``timeout``."""
    got = bytearray()

    def more() -> bool:
        got.extend(port.read(n - len(got)))
        return len(got) >= n

    assert wait_for(more, timeout), f"read {len(got)} of {n} bytes: {bytes(got)!r}"
    return bytes(got)


# == one reopen test per transport kind =========================================================

def test_serial_device_path_that_vanishes_and_returns_is_reopened(
        engines: Any, stack: contextlib.ExitStack, tmp_path: Path) -> None:
    dev = PtyDevice(tmp_path / "ttyROCKET")
    stack.callback(dev.unplug)
    dev.plug()
    ev = Events()
    opener = Opener(lambda: open_serial(str(dev.path), 57600, timeout=0))
    eng = started(engines, opener, events=ev, echo=True, name="pty")
    assert ev.wait_links(True)
    ping = b"\xa5\x5a\x00\x11\x13\r\n\xff"  # binary-clean: no flow control, no line editing
    dev.send(ping)
    assert dev.recv_exactly(len(ping)) == ping  # read by the engine, echoed back through it

    dev.unplug()  # the device vanishes: reads fail, and the path is gone
    assert ev.wait_links(True, False)
    assert eng.submit(b"lost") is Outcome.NOT_READY  # nothing kept for a port not there
    assert opener.wait_failed(2)  # retried with backoff while the path is missing
    assert eng.connected is False

    dev.plug()  # a new pty behind the same path
    assert ev.wait_links(True, False, True)
    pong = b"after the return"
    dev.send(pong)
    assert dev.recv_exactly(len(pong)) == pong
    assert ev.data() == ping + pong
    assert ev.kinds() == [True, "data", "flush", False, True, "data"]  # flushed as it broke
    st = eng.stats
    assert (st.connects, st.disconnects, st.read_errors) == (2, 1, 1)
    assert st.connect_failures >= 2
    assert eng.stats_dict()["link"] == 1


def test_socket_url_to_a_server_that_restarts_is_reopened(
        engines: Any, stack: contextlib.ExitStack) -> None:
    srv = TcpServer()
    stack.callback(lambda: srv.stop())
    port = srv.port
    ev = Events()
    opener = Opener(lambda: open_serial(f"socket://127.0.0.1:{port}", timeout=0))
    eng = engines(opener, events=ev, echo=True, name="socket-url")
    eng.start()
    conn = srv.accept()
    assert ev.wait_links(True)
    conn.sendall(b"one")
    assert recv_exactly(conn, 3) == b"one"

    srv.stop()  # the server goes away: the engine reads EOF, then connects are refused
    assert ev.wait_links(True, False)
    assert opener.wait_failed(1)
    srv = TcpServer(port)  # and comes back on the same port
    conn = srv.accept()
    assert ev.wait_links(True, False, True)
    conn.sendall(b"two")
    assert recv_exactly(conn, 3) == b"two"
    assert ev.data() == b"onetwo"
    st = eng.stats
    assert (st.connects, st.disconnects, st.read_errors) == (2, 1, 1)
    assert st.connect_failures >= 1


def test_tcp_client_to_a_server_that_restarts_is_reopened(
        engines: Any, stack: contextlib.ExitStack) -> None:
    srv = TcpServer()
    stack.callback(lambda: srv.stop())
    port = srv.port
    ev = Events()
    opener = Opener(lambda: open_tcp_client("127.0.0.1", port, timeout=1.0))
    eng = engines(opener, events=ev, echo=True, name="tcp")
    eng.start()
    conn = srv.accept()
    assert ev.wait_links(True)
    conn.sendall(b"one")
    assert recv_exactly(conn, 3) == b"one"

    srv.stop()
    assert ev.wait_links(True, False)
    assert eng.submit(b"lost") is Outcome.NOT_READY
    assert opener.wait_failed(1)
    srv = TcpServer(port)
    conn = srv.accept()
    assert ev.wait_links(True, False, True)
    conn.sendall(b"two")
    assert recv_exactly(conn, 3) == b"two"
    assert ev.kinds() == [True, "data", "flush", False, True, "data"]
    st = eng.stats
    assert (st.connects, st.disconnects, st.read_errors) == (2, 1, 1)
    assert st.connect_failures >= 1


def test_a_peer_that_hangs_up_at_once_again_and_again_costs_a_line_per_burst(
        engines: Any, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="gateway.io.port")
    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]
        listener.settimeout(DEADLINE_S)
        eng = engines(lambda: open_tcp_client("127.0.0.1", port, timeout=1.0),
                      events=Events(), name="flappy")
        eng.start()
        for _ in range(30):  # accept, hang up: the engine reopens each time
            listener.accept()[0].close()
        assert wait_for(lambda: eng.stats.disconnects >= 30, DEADLINE_S)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("flappy")]
    # one line as each burst starts; the rest counted, in one line per 10 s
    assert sum("reopening" in ln for ln in lines) == 1, lines
    assert sum("port is up" in ln for ln in lines) == 1, lines
    assert eng.stats.connects >= 30  # all counted


class ClientEngines:
    """``PortServer``'s ``on_client``: every accepted connection becomes an echoing engine on
    the server's loop, with ``reopen=False`` (a client that leaves is gone)."""

    def __init__(self, loop: IoLoop, make: Callable[..., PortEngine]) -> None:
        self.loop = loop
        self.make = make
        self.clients: list[tuple[PortEngine, Events, Opener]] = []
        self.cond = threading.Condition()

    def __call__(self, sock: socket.socket, addr: Any) -> None:
        ev = Events()
        opener = Opener(lambda: SocketPort(sock, f"{addr}"))
        eng = self.make(opener, events=ev, echo=True, loop=self.loop, reopen=False,
                        name=f"client {addr}")
        eng.start()
        with self.cond:
            self.clients.append((eng, ev, opener))
            self.cond.notify_all()

    def wait(self, n: int) -> tuple[PortEngine, Events, Opener]:
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.clients) >= n, DEADLINE_S)
            return self.clients[n - 1]


def echo_through(addr: Any, data: bytes, stack: contextlib.ExitStack) -> socket.socket:
    """Connect to ``addr``, send ``data`` and expect it back; the connection stays open."""
    client = stack.enter_context(socket.create_connection(addr, timeout=DEADLINE_S))
    client.sendall(data)
    assert recv_exactly(client, len(data)) == data
    return client


def test_tcp_server_client_that_drops_and_reconnects_gets_a_fresh_engine(
        io_loop: IoLoop, engines: Any, stack: contextlib.ExitStack,
        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="gateway.io.port")
    clients = ClientEngines(io_loop, engines)
    srv = PortServer(lambda: open_tcp_listener("127.0.0.1", 0), clients, loop=io_loop,
                     name="tcpin", backoff=fast_backoff())
    stack.callback(srv.close)
    srv.start()
    assert srv.wait_bound(DEADLINE_S)
    addr = srv.address

    first = echo_through(addr, b"hello", stack)
    eng1, ev1, opener1 = clients.wait(1)
    first.close()  # the client drops
    assert ev1.wait_links(True, False)
    assert eng1.submit(b"gone") is Outcome.NOT_READY

    echo_through(addr, b"again", stack)  # and reconnects: a new engine serves it
    _, ev2, _ = clients.wait(2)
    assert ev2.links() == [True]
    assert not opener1.wait_failed(1, timeout=0.2)  # reopen=False: never tried again
    assert ev1.kinds() == [True, "data", "flush", False]
    assert opener1.opened == 1
    assert [r.getMessage() for r in caplog.records if "reopening" in r.getMessage()] == []
    # a client hanging up is the normal end of its connection: said, not warned about
    assert [r.levelno for r in caplog.records if "not reopened" in r.getMessage()] == [
        logging.INFO]
    assert (eng1.stats.connects, eng1.stats.disconnects) == (1, 1)
    assert srv.accepted == 2 and srv.bind_failures == 0
    assert ev1.threads == ev2.threads == {f"io-{io_loop.name}"}  # one shared loop thread


def test_tcp_server_whose_port_is_taken_binds_with_backoff_once_it_is_freed(
        io_loop: IoLoop, engines: Any, stack: contextlib.ExitStack) -> None:
    squatter = stack.enter_context(bind_quiet(socket.SOCK_STREAM))
    squatter.listen()
    port = squatter.getsockname()[1]
    clients = ClientEngines(io_loop, engines)
    opener = Opener(lambda: open_tcp_listener("127.0.0.1", port))
    srv = PortServer(opener, clients, loop=io_loop, name="tcpin", backoff=fast_backoff())
    stack.callback(srv.close)
    srv.start()
    assert opener.wait_failed(3)  # bind refused, retried, never fatal
    assert not srv.wait_bound(0)
    squatter.close()
    assert srv.wait_bound(DEADLINE_S)
    assert srv.address == ("127.0.0.1", port)
    echo_through(("127.0.0.1", port), b"bound at last", stack)
    assert srv.bind_failures >= 3 and srv.accepted == 1


def test_udpout_with_nobody_listening_counts_refusals_and_keeps_going(
        engines: Any, stack: contextlib.ExitStack) -> None:
    port = free_udp_port()
    ev = Events()
    eng = started(engines, lambda: open_udp("127.0.0.1", port, listen=False), events=ev,
                  name="udpout")
    udp = eng.port
    assert udp.connected
    for i in range(1, 4):  # each datagram comes back as "port unreachable"
        assert eng.submit(b"anyone?") is Outcome.ACCEPTED
        assert wait_for(functools.partial(lambda n: udp.send_refused >= n, i), DEADLINE_S)
    assert udp.send_errors == 0  # nobody there yet is not a failure
    assert eng.connected and ev.links() == [True]

    gcs = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    gcs.bind(("127.0.0.1", port))  # someone listens now
    gcs.settimeout(DEADLINE_S)
    assert eng.submit(b"hello") is Outcome.ACCEPTED
    data, source = gcs.recvfrom(100)
    assert data == b"hello"
    gcs.sendto(b"reply", source)  # replies to our socket are read
    assert ev.wait_data(b"reply")
    st = eng.stats
    assert (st.connects, st.disconnects, st.errors) == (1, 0, 0)
    assert ev.links() == [True]


def test_udpout_that_cannot_be_connected_still_opens_and_counts_its_errors(
        engines: Any) -> None:
    """A broadcast address without SO_BROADCAST refuses connect() (as a destination with no
    route yet does): the port is opened unconnected and every refused datagram counted."""
    ev = Events()
    eng = started(engines, lambda: open_udp("255.255.255.255", 9, listen=False), events=ev,
                  name="udpout")
    udp = eng.port
    assert not udp.connected
    assert [eng.submit(b"x") for _ in range(3)] == [Outcome.ACCEPTED] * 3
    assert eng.drain(DEADLINE_S)
    assert udp.send_errors == 3 and eng.stats.sent_frames == 3
    assert eng.connected and ev.links() == [True] and eng.stats.errors == 0


def test_udpin_learns_its_peers_and_answers_each(
        engines: Any, stack: contextlib.ExitStack) -> None:
    ev = Events()
    eng = started(engines, lambda: open_udp("127.0.0.1", 0, listen=True), events=ev,
                  echo=True, name="udpin")
    udp = eng.port
    assert eng.submit(b"nobody yet") is Outcome.ACCEPTED  # no peer: nowhere to send, no error
    assert eng.drain(DEADLINE_S) and udp.not_sent == 1
    addr = udp.address()
    a, b = (stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
            for _ in range(2))
    for s in (a, b):
        s.bind(("127.0.0.1", 0))
        s.settimeout(DEADLINE_S)
    a.sendto(b"from a", addr)
    assert a.recvfrom(100) == (b"from a", addr)
    b.sendto(b"from b", addr)  # the echo goes to every peer learned so far
    assert b.recvfrom(100) == (b"from b", addr)
    assert a.recvfrom(100) == (b"from b", addr)
    assert list(udp.peers) == [a.getsockname(), b.getsockname()]
    assert udp.new_peers == 2 and udp.last_peer == b.getsockname()
    assert ev.datagrams() == [b"from a", b"from b"]  # fed one datagram at a time
    assert (eng.stats.connects, eng.stats.disconnects, eng.stats.errors) == (1, 0, 0)


class Batches(Collect):
    """A datagram protocol taking what is waiting in one call (a router's per-frame path);
    a batch holding ``b"boom"`` makes it raise."""

    def __init__(self) -> None:
        super().__init__()
        self.batches: list[list[bytes]] = []

    def feed(self, data: bytes) -> list[Any]:
        raise AssertionError("feed() called although feed_many() exists")

    def feed_many(self, datagrams: list[bytes]) -> list[Any]:
        self.batches.append(list(datagrams))
        if b"boom" in datagrams:
            raise ValueError("the protocol choked")
        return list(datagrams)


def test_udp_datagrams_go_to_feed_many_in_batches_and_its_errors_are_counted(
        engines: Any, stack: contextlib.ExitStack) -> None:
    proto = Batches()
    ev = Events()
    eng = started(engines, lambda: open_udp("127.0.0.1", 0, listen=True), events=ev,
                  protocol=proto, name="udpin")
    peer = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    sent = [b"d%d" % i for i in range(100)]
    for d in sent:
        peer.sendto(d, eng.port.address())
    assert ev.wait(lambda: len(ev.datagrams()) == len(sent))
    assert ev.datagrams() == sent  # in order, none lost or merged
    assert all(1 <= len(b) <= DATAGRAM_BATCH for b in proto.batches)
    peer.sendto(b"boom", eng.port.address())
    assert wait_for(lambda: eng.stats.protocol_errors == 1)
    peer.sendto(b"after", eng.port.address())
    assert ev.wait_data(b"after")
    assert (eng.stats.connects, eng.stats.disconnects, eng.stats.read_errors) == (1, 0, 0)


@pytest.mark.skipif(not mmsg.AVAILABLE, reason="needs recvmmsg/sendmmsg")
def test_a_bursty_sender_gets_one_read_per_burst_not_a_hold_each(
        engines: Any, stack: contextlib.ExitStack) -> None:
    proto = Batches()
    ev = Events()
    reads = [0]

    def opener() -> Any:
        port = open_udp("127.0.0.1", 0, listen=True)
        read_many = port.read_many

        def counted() -> list[bytes]:
            reads[0] += 1
            return read_many()

        port.read_many = counted  # type: ignore[method-assign]
        return port

    eng = started(engines, opener, events=ev, protocol=proto, name="udpin")
    peer = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    peer.connect(eng.port.address())
    sender = mmsg.MmsgSocket(peer)
    burst = [b"d%d" % i for i in range(20)]
    before = 0

    def fed(count: int) -> bool:
        return len(ev.datagrams()) == count

    def sent_while_the_loop_is_busy() -> None:
        """One burst, whole in the socket before the loop looks: the scheduler cannot
        split it across wake-ups (on a loaded machine it did, and each piece is a read)."""
        parked, go = threading.Event(), threading.Event()

        def park() -> None:
            parked.set()
            go.wait(DEADLINE_S)

        eng.loop.call_soon(park)
        assert parked.wait(DEADLINE_S)
        try:
            assert sender.send(burst) == (0, 0, 0)  # 20 datagrams in one system call
        finally:
            go.set()

    for n in range(1, 13):
        if n == 8:
            before = reads[0]
        sent_while_the_loop_is_busy()
        assert ev.wait(functools.partial(fed, 20 * n))
        time.sleep(0.002)  # the sender's pace (a burst every ~2 ms), not a synchronisation
    assert ev.datagrams() == burst * 12  # in order, none lost
    # a hold after each burst would read once more, finding nothing: 2 reads a burst
    assert reads[0] - before <= 5 + 2


def test_loop_url_without_a_descriptor_is_polled_and_reopened(engines: Any) -> None:
    ports: list[serial.SerialBase] = []

    def opener() -> serial.SerialBase:
        ports.append(loop_port())
        return ports[-1]

    ev = Events()
    eng = started(engines, opener, events=ev, name="loop", poll_s=0.005)
    with pytest.raises(OSError):
        ports[0].fileno()  # nothing for a selector: the engine polls it
    assert eng.submit(b"one") is Outcome.ACCEPTED
    assert ev.wait_data(b"one")  # written, looped back, polled, fed to the protocol
    ports[0].close()  # closed under the engine: its next read fails
    assert ev.wait_links(True, False, True)
    assert eng.submit(b"two") is Outcome.ACCEPTED
    assert ev.wait_data(b"onetwo")
    assert ev.kinds() == [True, "data", "flush", False, True, "data"]
    assert len(ports) == 2 and ports[1].is_open
    st = eng.stats
    assert (st.connects, st.disconnects, st.read_errors, st.connect_failures) == (2, 1, 1, 0)


def test_a_device_missing_at_start_is_opened_when_it_is_plugged_in(
        engines: Any, stack: contextlib.ExitStack, tmp_path: Path) -> None:
    dev = PtyDevice(tmp_path / "ttyUSB0")
    stack.callback(dev.unplug)
    ev = Events()
    opener = Opener(lambda: open_serial(str(dev.path), timeout=0))
    eng = engines(opener, events=ev, echo=True, name="hotplug")
    eng.start()
    assert opener.wait_failed(3)  # not there: retried, not fatal
    assert eng.submit(b"early") is Outcome.NOT_READY
    assert ev.links() == []  # never up, so never reported down
    dev.plug()
    assert ev.wait_links(True)
    dev.send(b"plugged")
    assert dev.recv_exactly(7) == b"plugged"
    assert eng.stats.connects == 1 and eng.stats.connect_failures >= 3
    assert eng.stats.disconnects == 0


# == the write contract ============================================================================

def test_frames_come_out_in_order_and_drain_waits_for_them(engines: Any) -> None:
    port = loop_port()
    eng = started(engines, lambda: port, queue_depth=64)
    frames = [bytes([0xA5, 0x5A, i, 3, i, i + 1, i + 2]) for i in range(50)]
    assert [eng.submit(f) for f in frames] == [Outcome.ACCEPTED] * 50
    assert eng.drain(DEADLINE_S)
    assert eng.queued() == 0
    assert read_exactly(port, sum(map(len, frames))) == b"".join(frames)
    st = eng.stats
    assert (st.submitted, st.accepted, st.sent_frames) == (50, 50, 50)
    assert st.sent_bytes == sum(map(len, frames)) and st.dropped == 0


def test_several_engines_run_at_once_on_different_ports(engines: Any) -> None:
    ports = [loop_port() for _ in range(3)]
    engs = [started(engines, functools.partial(lambda p: p, p), name=f"port{i}")
            for i, p in enumerate(ports)]
    for k in range(10):
        for i, eng in enumerate(engs):
            assert eng.submit(bytes([i, k])) is Outcome.ACCEPTED
    for i, port in enumerate(ports):
        assert read_exactly(port, 20) == b"".join(bytes([i, k]) for k in range(10))
    assert [e.stats.sent_frames for e in engs] == [10, 10, 10]


def test_queue_holds_16_frames_by_default_then_reports_queue_full(engines: Any) -> None:
    port = BlockingTransport()
    eng = started(engines, lambda: port, blocked=(port,))
    assert eng.queue_depth == DEFAULT_QUEUE_DEPTH == 16
    assert eng.submit(b"in-flight") is Outcome.ACCEPTED
    assert port.entered.wait(DEADLINE_S)  # the engine's thread is inside write()
    assert [eng.submit(bytes([i])) for i in range(16)] == [Outcome.ACCEPTED] * 16
    assert eng.queued() == 16
    assert not eng.drain(0.01)  # a write in flight: not drained, and drain() did not hang
    assert eng.submit(b"one too many") is Outcome.QUEUE_FULL
    assert eng.submit(b"and another") is Outcome.QUEUE_FULL
    assert eng.stats.dropped_queue_full == eng.stats.dropped == 2
    port.release.set()
    assert eng.drain(DEADLINE_S)
    assert port.written == [b"in-flight", *(bytes([i]) for i in range(16))]


class FakeClock:
    def __init__(self, now: float = 100.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def test_min_interval_throttles_and_unlimited_frames_are_exempt(engines: Any) -> None:
    port = loop_port()
    clock = FakeClock()
    # Binary-exact steps, so the test is about the rule rather than float rounding.
    eng = started(engines, lambda: port, min_interval_s=0.5, clock=clock)
    assert eng.submit(b"a") is Outcome.ACCEPTED
    clock.now += 0.25
    assert eng.submit(b"b") is Outcome.THROTTLED
    assert eng.submit(b"S", rate_limited=False) is Outcome.ACCEPTED  # e.g. STATUS: exempt
    clock.now += 0.25  # exactly min_interval_s after "a"
    assert eng.submit(b"c") is Outcome.ACCEPTED
    clock.now += 0.4375
    assert eng.submit(b"d") is Outcome.THROTTLED  # the exempt frame did not move the window
    assert eng.submit(b"T", rate_limited=False) is Outcome.ACCEPTED
    assert read_exactly(port, 4) == b"aScT"
    assert eng.stats.dropped_throttled == 2 and eng.stats.accepted == 4


def test_zero_min_interval_never_throttles(engines: Any) -> None:
    port = loop_port()
    eng = started(engines, lambda: port, clock=FakeClock())
    assert [eng.submit(b"x") for _ in range(5)] == [Outcome.ACCEPTED] * 5
    assert read_exactly(port, 5) == b"xxxxx"


def test_not_ready_before_start(engines: Any) -> None:
    eng = engines(loop_port)
    assert eng.submit(b"early") is Outcome.NOT_READY
    assert eng.stats.dropped_not_ready == eng.stats.dropped == 1
    assert not eng.connected and eng.stats_dict()["link"] == 0


def test_not_ready_while_the_opener_fails(engines: Any) -> None:
    opener = Opener(lambda: open_serial("/dev/nonexistent-aurora-port"))
    eng = engines(opener)
    eng.start()
    assert opener.wait_failed(3)
    assert eng.submit(b"x") is Outcome.NOT_READY
    assert eng.stats.dropped_not_ready == 1
    assert eng.stats.connects == 0
    assert eng.queued() == 0  # nothing is kept for a port that is not there


def test_reopens_with_backoff_after_failed_opens_and_resets_it(engines: Any) -> None:
    port = loop_port()
    calls = 0

    def opener() -> Any:
        nonlocal calls
        calls += 1
        if calls <= 3:
            raise serial.SerialException("port busy")
        return port

    backoff = fast_backoff()
    eng = started(engines, opener, backoff=backoff)
    assert (eng.stats.connect_failures, eng.stats.connects) == (3, 1)
    assert backoff.next() == 0.01  # reset on success
    assert eng.submit(b"hello") is Outcome.ACCEPTED
    assert read_exactly(port, 5) == b"hello"


class FailingWrite:
    """A port that dies on its first write."""

    def __init__(self) -> None:
        self.closed = threading.Event()

    def write(self, data: bytes) -> int:
        raise serial.SerialException("write failed: [Errno 5] Input/output error")

    def read(self, size: int = 1) -> bytes:
        return b""

    def close(self) -> None:
        self.closed.set()


def test_write_error_is_counted_and_the_engine_reopens(engines: Any) -> None:
    dead, good = FailingWrite(), loop_port()
    ports: list[Any] = [dead, good]
    ev = Events()
    eng = started(engines, lambda: ports.pop(0), on_link=ev.on_link)
    assert eng.submit(b"lost") is Outcome.ACCEPTED
    assert ev.wait_links(True, False, True)
    assert dead.closed.is_set()
    assert eng.stats.write_errors == 1 and eng.stats.connects == 2
    assert eng.submit(b"after") is Outcome.ACCEPTED
    assert eng.submit(b"-more") is Outcome.ACCEPTED
    assert read_exactly(good, 10) == b"after-more"


def test_reconnect_on_request_closes_the_port_and_reopens_it(engines: Any) -> None:
    first, second = loop_port(), loop_port()
    ports = [first, second]
    ev = Events()
    eng = started(engines, lambda: ports.pop(0), on_link=ev.on_link)
    assert eng.submit(b"one") is Outcome.ACCEPTED
    assert read_exactly(first, 3) == b"one"
    eng.reconnect()
    assert ev.wait_links(True, False, True)
    assert not first.is_open
    assert eng.submit(b"two") is Outcome.ACCEPTED
    assert read_exactly(second, 3) == b"two"
    assert eng.stats.reconnects_requested == 1 and eng.stats.errors == 0


def test_reconnect_while_the_port_is_down_is_ignored(engines: Any) -> None:
    opener = Opener(lambda: open_serial("/dev/nonexistent-aurora-port"))
    eng = engines(opener)
    eng.reconnect()  # not started: nothing to do (and no error)
    eng.start()
    assert opener.wait_failed(1)
    eng.reconnect()
    done = threading.Event()
    eng.call_soon(done.set)  # runs after the request on the engine's thread
    assert done.wait(DEADLINE_S)
    assert eng.stats.reconnects_requested == 0 and eng.stats.disconnects == 0


def test_close_writes_what_is_queued_before_stopping(
        engines: Any, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.io.port")
    port = BlockingTransport()
    eng = started(engines, lambda: port, blocked=(port,), queue_depth=3)
    assert eng.submit(b"0") is Outcome.ACCEPTED
    assert port.entered.wait(DEADLINE_S)
    assert [eng.submit(f) for f in (b"1", b"2", b"3")] == [Outcome.ACCEPTED] * 3
    closer = threading.Thread(target=eng.close, args=(DEADLINE_S,), daemon=True)
    closer.start()
    # The queue is full, so submit says QUEUE_FULL (queueing nothing) until close() begins.
    assert wait_for(lambda: eng.submit(b"probe") is Outcome.NOT_READY)
    port.release.set()
    closer.join(DEADLINE_S)
    assert not closer.is_alive()
    assert port.written == [b"0", b"1", b"2", b"3"]
    assert eng.stats.sent_frames == 4 and port.closed
    assert not [r for r in caplog.records if "did not" in r.getMessage()]  # it stopped


def test_close_returns_within_its_bound_with_a_write_that_never_returns(
        engines: Any, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="gateway.io.port")
    port = BlockingTransport()
    eng = started(engines, lambda: port, blocked=(port,))
    assert eng.submit(b"stuck") is Outcome.ACCEPTED
    assert port.entered.wait(DEADLINE_S)
    assert [eng.submit(bytes([i])) for i in range(5)] == [Outcome.ACCEPTED] * 5
    run_within(lambda: eng.close(timeout=0.1), timeout=2.0)  # not the stuck write's time
    assert eng.stats.dropped_not_ready == 5  # the leftovers, counted
    assert any("did not close" in r.getMessage() for r in caplog.records)
    assert eng.queued() == 0 and port.closed and not eng.connected
    assert eng.submit(b"late") is Outcome.NOT_READY
    run_within(lambda: eng.close(timeout=0.1))  # twice is safe


def test_close_is_safe_twice_and_before_start(engines: Any) -> None:
    engines(loop_port).close()  # never started
    port = loop_port()
    ev = Events()
    eng = started(engines, lambda: port, events=ev)
    eng.close()
    eng.close()
    assert not port.is_open
    assert eng.submit(b"x") is Outcome.NOT_READY
    assert not eng.loop.alive
    assert ev.kinds() == [True, "flush", False]  # closing flushes and reports the link down


def test_an_engine_can_be_started_again_after_close(engines: Any) -> None:
    first, second = loop_port(), loop_port()
    ports = [first, second]
    eng = started(engines, lambda: ports.pop(0))
    eng.close()
    assert not first.is_open
    eng.start()
    assert eng.wait_connected(DEADLINE_S)
    assert eng.submit(b"again") is Outcome.ACCEPTED
    assert read_exactly(second, 5) == b"again"
    assert eng.stats.connects == 2


def test_close_while_the_opener_keeps_failing_returns_promptly(engines: Any) -> None:
    opener = Opener(lambda: open_serial("/dev/nonexistent-aurora-port"))
    eng = engines(opener, backoff=Backoff(30.0, 30.0))  # a long wait between attempts
    eng.start()
    assert opener.wait_failed(1)
    run_within(lambda: eng.close(timeout=DEADLINE_S), timeout=2.0)


def test_close_while_an_open_hangs_returns_promptly_and_the_late_port_is_closed(
        engines: Any) -> None:
    entered, release = threading.Event(), threading.Event()
    port = loop_port()

    def opener() -> Any:
        entered.set()
        release.wait(DEADLINE_S)  # e.g. a connect to a host that does not answer
        return port

    eng = engines(opener)
    eng.start()
    assert entered.wait(DEADLINE_S)
    run_within(lambda: eng.close(timeout=DEADLINE_S), timeout=2.0)
    release.set()
    assert wait_for(lambda: not port.is_open, DEADLINE_S)  # nobody is left to use it
    assert eng.stats.connects == 0


def test_an_engine_on_a_shared_loop_that_has_stopped_still_closes_at_once(
        io_loop: IoLoop, engines: Any) -> None:
    port = loop_port()
    ev = Events()
    eng = started(engines, lambda: port, events=ev, loop=io_loop)
    assert io_loop.stop(DEADLINE_S)  # its owner stopped the loop first
    run_within(lambda: eng.close(timeout=DEADLINE_S), timeout=2.0)
    assert not port.is_open and not eng.connected
    assert ev.kinds() == [True, "flush", False]


@pytest.mark.parametrize("kw", [{"queue_depth": 0}, {"min_interval_s": -0.1}])
def test_bad_arguments_are_refused(kw: dict[str, Any]) -> None:
    with pytest.raises(ValueError):
        PortEngine(loop_port, **kw)


def test_stats_dict_reports_totals_and_the_link(engines: Any) -> None:
    eng = engines(loop_port)
    eng.submit(b"x")
    d = eng.stats_dict()
    assert d["dropped"] == d["dropped_not_ready"] == 1
    assert d["submitted"] == 1 and d["errors"] == 0 and d["link"] == 0


# -- partial writes on a non-blocking socket ------------------------------------------------------

@pytest.fixture
def slow_reader(stack: contextlib.ExitStack) -> tuple[socket.socket, socket.socket]:
    """(our end, the peer's end) of a TCP connection with small buffers; the peer reads only
    when the test says so."""
    srv = stack.enter_context(socket.socket())
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # inherited by the accepted end
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    ours = socket.socket()
    ours.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    ours.connect(srv.getsockname())
    peer, _ = srv.accept()
    stack.enter_context(peer)
    stack.callback(ours.close)
    return ours, peer


FRAME = 64 * 1024


def test_partial_writes_to_a_peer_that_does_not_read_are_bounded_and_never_block(
        engines: Any, slow_reader: tuple[socket.socket, socket.socket]) -> None:
    ours, peer = slow_reader
    eng = started(engines, lambda: SocketPort(ours, "slow"), queue_depth=4)
    frames = [bytes([i]) * FRAME for i in range(8)]
    assert eng.submit(frames[0]) is Outcome.ACCEPTED
    assert wait_for(lambda: eng.stats.sent_frames == 1)  # begun, and the socket took part
    assert not eng.drain(0)  # the rest of it waits for room
    outcomes = run_within(lambda: [eng.submit(f) for f in frames[1:]], timeout=2.0)
    assert outcomes == [Outcome.ACCEPTED] * 4 + [Outcome.QUEUE_FULL] * 3
    alive = threading.Event()
    eng.call_soon(alive.set)
    assert alive.wait(DEADLINE_S)  # the engine's thread is free while the peer does not read

    expected = b"".join(frames[:5])
    assert recv_exactly(peer, len(expected)) == expected  # the peer reads: the rest follows
    assert eng.drain(DEADLINE_S)
    st = eng.stats
    assert (st.sent_frames, st.sent_bytes, st.dropped_queue_full) == (5, len(expected), 3)
    assert st.errors == 0 and eng.connected


def test_close_with_a_peer_that_does_not_read_returns_promptly(
        engines: Any, slow_reader: tuple[socket.socket, socket.socket]) -> None:
    ours, _ = slow_reader
    eng = started(engines, lambda: SocketPort(ours, "slow"), queue_depth=4)
    assert eng.submit(b"\x01" * FRAME) is Outcome.ACCEPTED
    assert wait_for(lambda: eng.stats.sent_frames == 1)
    assert [eng.submit(b"\x02" * FRAME) for _ in range(3)] == [Outcome.ACCEPTED] * 3
    run_within(lambda: eng.close(timeout=DEADLINE_S), timeout=2.0)
    assert eng.stats.dropped_not_ready == 3  # what never got a turn, counted
    assert ours.fileno() == -1  # closed


# -- timers ---------------------------------------------------------------------------------------

def test_timers_run_on_the_engines_thread_and_cancel_works(engines: Any) -> None:
    eng = started(engines, loop_port)
    ran: list[tuple[str, bool]] = []
    done = threading.Event()

    def note(what: str) -> Callable[[], None]:
        return lambda: ran.append((what, eng.loop.in_loop_thread))

    eng.call_soon(note("soon"))
    eng.call_later(0.01, note("later"))
    eng.call_later(0.02, note("cancelled")).cancel()
    ticks: list[bool] = []
    handle: list[Timer] = []
    assigned = threading.Event()

    def tick() -> None:
        ticks.append(eng.loop.in_loop_thread)
        if len(ticks) == 3 and assigned.wait(DEADLINE_S):
            handle[0].cancel()  # no fourth tick, though one would be due in 5 ms
            eng.call_later(0.05, done.set)

    handle.append(eng.call_every(0.005, tick))
    assigned.set()
    assert done.wait(DEADLINE_S)
    assert ticks == [True] * 3
    assert ran == [("soon", True), ("later", True)]


# -- exclusive use ---------------------------------------------------------------------------------

def test_exclusive_parks_the_engine_and_frames_queue_until_it_is_released(
        engines: Any) -> None:
    port = loop_port()
    ev = Events()
    eng = started(engines, lambda: port, events=ev, poll_s=0.001)  # reads the port too
    with eng.exclusive(timeout=DEADLINE_S) as raw:
        assert raw is port
        assert [eng.submit(f) for f in (b"1", b"2", b"3")] == [Outcome.ACCEPTED] * 3
        woke = threading.Event()
        eng.call_soon(woke.set)
        assert not woke.wait(0.1)  # parked: a running engine would have run it at once
        raw.write(b"AT+RX\r")  # an AT-command exchange of our own
        assert read_exactly(raw, 6) == b"AT+RX\r"  # the engine did not take the answer
        assert eng.queued() == 3 and eng.stats.sent_frames == 0
    assert woke.wait(DEADLINE_S)
    assert ev.wait_data(b"123")
    assert eng.drain(DEADLINE_S) and eng.stats.sent_frames == 3
    assert ev.data() == b"123"


def test_exclusive_puts_back_the_settings_the_borrower_changed(engines: Any) -> None:
    port = open_serial("loop://", 19200, timeout=0)
    ev = Events()
    eng = started(engines, lambda: port, events=ev)
    with eng.exclusive(DEADLINE_S) as raw:
        raw.baudrate = 9600  # e.g. a radio's command mode runs at another rate
        raw.timeout = 0.5  # and the exchange waits for its answers
    assert (port.baudrate, port.timeout) == (19200, 0)
    assert eng.submit(b"resumed") is Outcome.ACCEPTED
    assert ev.wait_data(b"resumed")
    assert eng.stats.reconnects_requested == 0


def test_exclusive_is_refused_when_the_port_is_down_or_the_engine_is_not_running(
        engines: Any) -> None:
    opener = Opener(lambda: open_serial("/dev/nonexistent-aurora-port"))
    eng = engines(opener)
    with pytest.raises(PortNotReady), eng.exclusive(1.0):
        pass  # not started
    eng.start()
    assert opener.wait_failed(1)
    with pytest.raises(PortNotReady, match="down"), eng.exclusive(DEADLINE_S):
        pass
    eng.close()
    with pytest.raises(PortNotReady), eng.exclusive(1.0):
        pass


def test_exclusive_gives_up_on_an_engine_stuck_in_a_write(engines: Any) -> None:
    port = BlockingTransport()
    eng = started(engines, lambda: port, blocked=(port,))
    assert eng.submit(b"stuck") is Outcome.ACCEPTED
    assert port.entered.wait(DEADLINE_S)
    with pytest.raises(PortNotReady, match="busy"), eng.exclusive(0.05):
        pass
    port.release.set()
    assert eng.drain(DEADLINE_S)
    with eng.exclusive(DEADLINE_S) as raw:  # free again
        assert raw is port


# -- the protocol ---------------------------------------------------------------------------------

def test_a_protocol_that_raises_is_counted_and_the_engine_carries_on(engines: Any) -> None:
    port = loop_port()
    ev = Events()
    eng = started(engines, lambda: port, events=ev, protocol=Collect(fail_on=b"!"))
    assert eng.submit(b"bad!") is Outcome.ACCEPTED
    assert wait_for(lambda: eng.stats.protocol_errors == 1)
    assert eng.submit(b"good") is Outcome.ACCEPTED
    assert ev.wait_data(b"good")
    assert ev.data() == b"good"
    st = eng.stats
    assert (st.connects, st.disconnects, st.read_errors) == (1, 0, 0)
    assert eng.connected


def test_a_protocol_whose_flush_raises_is_counted_and_the_port_still_reopens(
        engines: Any) -> None:
    class BadFlush(Collect):
        def flush(self) -> list[Any]:
            raise RuntimeError("cannot flush")

    ports = [loop_port(), loop_port()]
    ev = Events()
    eng = started(engines, lambda: ports.pop(0), events=ev, protocol=BadFlush())
    eng.reconnect()
    assert ev.wait_links(True, False, True)
    assert eng.stats.protocol_errors == 1


# -- backoff ---------------------------------------------------------------------------------------

def test_backoff_doubles_up_to_its_cap_and_resets() -> None:
    b = Backoff(0.1, 1.0)
    assert [b.next() for _ in range(6)] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.0, 1.0])
    b.reset()
    assert b.next() == pytest.approx(0.1)


def test_backoff_factor_is_configurable() -> None:
    b = Backoff(1.0, 100.0, factor=3.0)
    assert [b.next() for _ in range(5)] == pytest.approx([1, 3, 9, 27, 81])
    assert Backoff(0.5, 0.5, factor=1.0).next() == 0.5


@pytest.mark.parametrize(
    ("initial", "maximum", "factor"), [(0, 1, 2), (-1, 1, 2), (2, 1, 2), (0.1, 1, 0.5)]
)
def test_backoff_refuses_bad_parameters(initial: float, maximum: float, factor: float) -> None:
    with pytest.raises(ValueError):
        Backoff(initial, maximum, factor)


def test_a_stopped_loop_can_be_woken_and_stopped_again() -> None:
    """stop() after close() (a source stopped twice, a late call_soon) is a no-op, never an
    exception from the closed wake-up descriptor."""
    loop = IoLoop("twice")
    loop.start()
    assert loop.stop(1.0)
    loop.close()
    loop.wake()
    loop.call_soon(lambda: None)
    assert loop.stop(1.0)


def test_a_socket_url_port_closes_without_pyserials_sleep(monkeypatch: Any) -> None:
    """``socket://`` ports are pyserial's with a close() that does not sleep 0.3 s on the
    closing thread (a shared loop's): the peer sees the end of the stream, the port reads as
    closed, and closing twice is harmless.  (That close() never reaches time.sleep is what
    this checks: a clock-free check of the cost.)"""
    from types import SimpleNamespace

    from serial.urlhandler import protocol_socket

    from gateway.io.transport import SocketSerial, open_serial

    slept: list[float] = []
    monkeypatch.setattr(protocol_socket, "time", SimpleNamespace(sleep=slept.append,
                                                                 time=time.time))
    with socket.create_server(("127.0.0.1", 0)) as srv:
        port = open_serial(f"socket://127.0.0.1:{srv.getsockname()[1]}", timeout=0)
        conn, _ = srv.accept()
        with conn:
            assert isinstance(port, SocketSerial)
            port.write(b"x")
            assert conn.recv(1) == b"x"
            port.close()
            port.close()
            assert slept == []
            assert not port.is_open
            conn.settimeout(5)
            assert conn.recv(1) == b""


# -- datagram ports read in batches ---------------------------------------------------------------

class DatagramPair:
    """A datagram port with ``read_many`` over a real socket pair (``peer`` is the far end):
    a datagram ``FAIL`` makes the read fail, as a socket's error would."""

    datagram = True

    def __init__(self) -> None:
        self.sock, self.peer = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        self.peer.settimeout(DEADLINE_S)

    def fileno(self) -> int:
        return self.sock.fileno()

    def read(self, size: int = 1) -> bytes:
        try:
            return self.sock.recv(size)
        except BlockingIOError:
            return b""

    def read_many(self) -> list[bytes]:
        out = []
        while data := self.read(65536):
            if data == b"FAIL":
                raise OSError(errno.EIO, "the socket failed")
            out.append(data)
        return out

    def write(self, data: bytes) -> int:
        return self.sock.send(data)

    def close(self) -> None:
        self.sock.close()
        self.peer.close()


def test_a_batch_read_port_counts_a_failed_read_as_the_ports_and_a_bad_batch_as_the_protocols(
        engines: Any) -> None:
    """A failed ``read_many`` fails the port (reopened); a batch the protocol raises on is
    counted and skipped, and the port reads on."""
    ports = [DatagramPair(), DatagramPair()]
    opened = list(ports)
    ev = Events()
    eng = started(engines, lambda: opened.pop(0), events=ev, protocol=Batches())
    first = ports[0]
    first.peer.send(b"one")
    assert ev.wait_data(b"one")
    first.peer.send(b"boom")
    assert wait_for(lambda: eng.stats.protocol_errors == 1)
    first.peer.send(b"two")
    assert ev.wait(lambda: ev.datagrams() == [b"one", b"two"])
    st = eng.stats
    assert (st.connects, st.read_errors) == (1, 0)  # the protocol's fault: the port reads on
    first.peer.send(b"FAIL")
    assert ev.wait_links(True, False, True)  # the port's fault: reopened
    assert (eng.stats.read_errors, eng.stats.disconnects) == (1, 1)
    ports[1].peer.send(b"three")
    assert ev.wait(lambda: ev.datagrams() == [b"one", b"two", b"three"])
    assert eng.stats.protocol_errors == 1
