"""Sources over real byte streams: the serial source on a pty pair and on ``socket://`` against
a TCP server the test runs on 127.0.0.1; the simulated flight; the replay of a recording.

Synchronisation is on events with deadlines: a sink that notifies a condition for every
message, log records that set events, and the sources' own ``done`` events.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import logging
import os
import socket
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import run_within, wait_for

from dialects.states import SimpleState as S
from gateway import recording
from gateway.app import Gateway
from gateway.backend import Routes
from gateway.config import ConfigError, GatewayConfig, Part, parse
from gateway.flight import FlightModel, FlightProfile
from gateway.io.ioloop import BLOCKING_WORKERS, BlockingCalls, IoLoop
from gateway.model import RawFrame, RcChannels, SmUpdate, Status
from gateway.pacing import BATCH, Pacer
from gateway.recorder import Recorder
from gateway.sources import Source
from gateway.sources.options import ReplayOptions, SerialOptions, SimOptions
from gateway.sources.replay import ReplaySource
from gateway.sources.serial_source import SerialSource
from gateway.sources.sim import BOOT_UPTIME_MS, SimSource, flight_frames
from gateway.wire import Decoder, decode_all, encode, frame

DEADLINE_S = 10.0
SIMPLE_ORDER = [S.IDLE, S.ARMED, S.BOOST, S.BURNOUT, S.APOGEE, S.MAIN, S.REDUNDANT, S.LANDED,
                S.IDLE]
PROBE_TYPE = 0x7E


# -- helpers -------------------------------------------------------------------------------------

class Sink:
    """Collects what a source emits (with a monotonic stamp) and wakes waiters."""

    def __init__(self) -> None:
        self.items: list[tuple[float, Any]] = []
        self.cond = threading.Condition()

    def __call__(self, msg: Any) -> None:
        with self.cond:
            self.items.append((time.monotonic(), msg))
            self.cond.notify_all()

    @property
    def msgs(self) -> list[Any]:
        with self.cond:
            return [m for _, m in self.items]

    def wait_for(self, pred: Callable[[list[Any]], bool], timeout: float = DEADLINE_S) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: pred([m for _, m in self.items]), timeout)

    def wait_count(self, n: int, timeout: float = DEADLINE_S,
                   keep: Callable[[Any], bool] = lambda m: True) -> bool:
        return self.wait_for(lambda ms: sum(1 for m in ms if keep(m)) >= n, timeout)


def not_probe(m: Any) -> bool:
    return not (isinstance(m, RawFrame) and m.type == PROBE_TYPE)


class _LogEvent(logging.Handler):
    def __init__(self, text: str) -> None:
        super().__init__(logging.DEBUG)
        self.text = text
        self.event = threading.Event()

    def emit(self, record: logging.LogRecord) -> None:
        if self.text in record.getMessage():
            self.event.set()


@contextlib.contextmanager
def log_event(logger: str, text: str) -> Iterator[threading.Event]:
    """An event set when ``logger`` logs a message containing ``text``."""
    h = _LogEvent(text)
    lg = logging.getLogger(logger)
    old = lg.level
    lg.setLevel(logging.DEBUG)
    lg.addHandler(h)
    try:
        yield h.event
    finally:
        lg.removeHandler(h)
        lg.setLevel(old)


def stop_in_time(src: Any, budget: float = 1.0, shared: bool = False) -> float:
    """Stop ``src``; assert it wound down (``done``; a blocking ``run`` returned) and the loop
    of its own (unless ``shared``: its owner's) ended within ``budget``; return how long it
    took."""
    t0 = time.monotonic()
    src.stop(budget)
    took = time.monotonic() - t0
    assert src.done.is_set(), "source not done after stop"
    loop = src.io_loop  # started alone: a loop of its own, which stop() ends
    assert shared or loop is None or not loop.alive, "source thread still alive"
    return took


def write_all(fd: int, data: bytes, chunk: int = 97) -> None:
    """Write ``data`` to ``fd`` in odd-sized pieces (frames split across reads)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view[:chunk])
        view = view[n:]


def sample_frames() -> list[bytes]:
    """Both SM_UPDATE revisions, STATUS, and frames of types nobody decodes."""
    f64 = [f for _, f in flight_frames(FlightModel(FlightProfile()), 10, 1, cycles=1)][140:200]
    f36 = [f for _, f in flight_frames(FlightModel(FlightProfile(revision=36)), 10, 1,
                                       cycles=1)][140:170]
    return [*f64, frame(0x42, b"\x01\x02\x03"), *f36, frame(0x10, b""),
            frame(0x01, b"\x00" * 20)]


@pytest.fixture
def pty_pair() -> Iterator[tuple[int, str]]:
    """(master fd, slave path).  The test keeps the slave open too, in raw mode, so nothing is
    echoed or line-edited before the source configures the port itself."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        yield master, os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


def wait_until_reading(send: int | Callable[[bytes], Any], sink: Sink) -> None:
    """pyserial discards pending input when it opens a port (a tty's ``tcflush``; for
    ``socket://`` it reads and drops whatever arrived before ``open()`` returned), so bytes
    sent before the source's open completes are lost: send probe frames until one comes
    through.  ``send`` is a pty master fd or a function (a socket's ``sendall``)."""
    write = (lambda b: os.write(send, b)) if isinstance(send, int) else send
    probe = frame(PROBE_TYPE, b"probe")
    seen = sum(1 for m in sink.msgs if not not_probe(m))
    deadline = time.monotonic() + DEADLINE_S
    while not sink.wait_count(seen + 1, 0.05, keep=lambda m: not not_probe(m)):
        assert time.monotonic() < deadline, "the source never read what was sent"
        write(probe)


# -- serial source on a pty ----------------------------------------------------------------------

def test_pty_frames_are_decoded_and_delivered_with_the_source_name(
        pty_pair: tuple[int, str]) -> None:
    master, slave_path = pty_pair
    src = SerialSource(SerialOptions(url=slave_path, baudrate=9600), name="rocket")
    sink = Sink()
    src.start(sink)
    try:
        wait_until_reading(master, sink)
        expected = sample_frames()
        write_all(master, b"\x00garbage\xa5" + b"".join(expected))
        assert sink.wait_count(len(expected), keep=not_probe)
        got = [m for m in sink.msgs if not_probe(m)]
        assert [m.raw for m in got] == expected
        assert got == decode_all(b"".join(expected), origin="rocket", vehicle="rocket")
        assert {m.origin for m in sink.msgs} == {"rocket"}
        kinds = {type(m) for m in got}
        assert kinds == {SmUpdate, Status, RawFrame}
        assert {m.payload_len for m in got if isinstance(m, SmUpdate)} == {36, 64}
        st = src.stats()
        assert st["opens"] == 1 and st["disconnects"] == 0
        assert st["crc_failures"] == 0 and st["bytes_skipped"] >= len(b"\x00garbage\xa5")
    finally:
        took = stop_in_time(src)
    assert took < 1.0


def test_a_pty_whose_master_goes_away_is_a_counted_disconnect_not_a_crash() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    src = SerialSource(SerialOptions(url=os.ttyname(slave), reconnect_max_s=0.2), name="pty")
    sink = Sink()
    try:
        with log_event("gateway.io.port", "read failed") as failed:
            src.start(sink)
            wait_until_reading(master, sink)
            os.close(master)  # hang up: the source's reads fail from now on
            master = -1
            assert failed.wait(DEADLINE_S), "the hang-up was not noticed"
        assert src.running  # retrying, not dead
        assert src.stats()["disconnects"] == 1
        assert stop_in_time(src) < 1.0
    finally:
        src.stop(1.0)
        if master >= 0:
            os.close(master)
        os.close(slave)


# -- serial source on socket:// --------------------------------------------------------------------

@pytest.fixture
def server() -> Iterator[socket.socket]:
    srv = socket.create_server(("127.0.0.1", 0))
    srv.settimeout(DEADLINE_S)
    try:
        yield srv
    finally:
        srv.close()


def test_socket_source_counts_a_disconnect_reconnects_and_continues(
        server: socket.socket) -> None:
    port = server.getsockname()[1]
    src = SerialSource(SerialOptions(url=f"socket://127.0.0.1:{port}", reconnect_max_s=0.5),
                       name="tcp")
    sink = Sink()
    frames = sample_frames()
    first, second = frames[:40], frames[40:]
    src.start(sink)
    try:
        conn1, _ = server.accept()
        with conn1:
            wait_until_reading(conn1.sendall, sink)
            conn1.sendall(b"".join(first))
        # the server closed right after sending: everything sent still arrives
        assert sink.wait_count(len(first), keep=not_probe)
        conn2, _ = server.accept()  # the source reconnects on its own
        with conn2:
            wait_until_reading(conn2.sendall, sink)
            conn2.sendall(b"".join(second))
            assert sink.wait_count(len(frames), keep=not_probe)
            assert [m.raw for m in sink.msgs if not_probe(m)] == frames
            assert {m.origin for m in sink.msgs} == {"tcp"}
            st = src.stats()
            assert st["disconnects"] == 1
            assert st["opens"] == 2
            took = stop_in_time(src)  # connected and idle
    finally:
        src.stop(1.0)
    assert took < 1.0


def test_socket_source_reads_a_burst_in_chunks_not_byte_by_byte(
        server: socket.socket) -> None:
    """pyserial's socket:// says at most one byte is waiting; the source must still take a
    burst in a handful of reads (it once read 1 byte per call: 1.9k frames/s on loopback)."""
    port = server.getsockname()[1]
    src = SerialSource(SerialOptions(url=f"socket://127.0.0.1:{port}"), name="tcp")
    sink = Sink()
    feeds: list[int] = []

    class CountingDecoder(Decoder):
        def feed(self, data: bytes) -> list:
            feeds.append(len(data))
            return super().feed(data)

    src.decoder = CountingDecoder(origin="tcp")
    burst = b"".join(sample_frames()) * 20
    src.start(sink)
    try:
        conn, _ = server.accept()
        with conn:
            wait_until_reading(conn.sendall, sink)
            before = len(feeds)
            conn.sendall(burst)
            n = len(sample_frames()) * 20
            assert sink.wait_count(n, keep=not_probe)
            reads = len(feeds) - before
    finally:
        src.stop(1.0)
    assert reads < len(burst) / 100, f"{reads} reads for {len(burst)} bytes"


def test_socket_source_hands_each_read_to_a_batch_sink_as_one_list_in_order(
        server: socket.socket) -> None:
    """With a batch sink (the gateway's ingest_batch) what one read decoded comes as one
    list; every frame arrives, in order, and nothing goes through the per-message sink."""
    port = server.getsockname()[1]
    src = SerialSource(SerialOptions(url=f"socket://127.0.0.1:{port}"), name="tcp")
    per_message = Sink()
    batched = Sink()
    batches: list[int] = []

    def batch_sink(msgs: list[Any]) -> None:
        batches.append(len(msgs))
        for m in msgs:
            batched(m)

    src.batch_sink = batch_sink
    frames = sample_frames() * 20
    src.start(per_message)
    try:
        conn, _ = server.accept()
        with conn:
            wait_until_reading(conn.sendall, batched)
            conn.sendall(b"".join(frames))
            assert batched.wait_count(len(frames), keep=not_probe)
    finally:
        src.stop(1.0)
    got = [m.raw for m in batched.msgs if not_probe(m)]
    assert got == frames
    assert per_message.msgs == []
    assert max(batches) > 1 and len(batches) < len(frames)  # lists of many, not one each


def test_a_port_with_no_listener_yet_is_retried_not_fatal() -> None:
    # Bound but not listening: connects are refused until listen() is called.
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.settimeout(DEADLINE_S)
    port = srv.getsockname()[1]
    src = SerialSource(SerialOptions(url=f"socket://127.0.0.1:{port}", reconnect_max_s=0.2),
                       name="late")
    sink = Sink()
    try:
        with log_event("gateway.io.port", "retrying") as retrying:
            src.start(sink)
            assert retrying.wait(DEADLINE_S), "no failed open was reported"
        assert src.running
        assert src.stats()["open_failures"] >= 1 and src.stats()["opens"] == 0
        srv.listen(1)
        conn, _ = srv.accept()
        with conn:
            wait_until_reading(conn.sendall, sink)
            expected = sample_frames()[:10]
            conn.sendall(b"".join(expected))
            assert sink.wait_count(len(expected), keep=not_probe)
            assert [m.raw for m in sink.msgs if not_probe(m)] == expected
            assert src.stats()["opens"] == 1
        took = stop_in_time(src)
    finally:
        src.stop(1.0)
        srv.close()
    assert took < 1.0


def test_stop_while_retrying_a_refused_port_is_quick() -> None:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))  # never listens
    port = srv.getsockname()[1]
    src = SerialSource(SerialOptions(url=f"socket://127.0.0.1:{port}", reconnect_max_s=5.0))
    try:
        with log_event("gateway.io.port", "retrying") as retrying:
            src.start(Sink())
            assert retrying.wait(DEADLINE_S)
        assert stop_in_time(src) < 1.0
        assert src.done.is_set()
    finally:
        src.stop(1.0)
        srv.close()


def _syn_sent_to(port: int) -> int:
    """Sockets of this host in SYN_SENT towards 127.0.0.1:port (Linux /proc/net/tcp)."""
    want = f"0100007F:{port:04X}"
    n = 0
    with open("/proc/net/tcp") as f:
        next(f)
        for line in f:
            cols = line.split()
            if cols[2] == want and cols[3] == "02":
                n += 1
    return n


@pytest.mark.skipif(not os.path.exists("/proc/net/tcp"), reason="needs Linux /proc/net/tcp")
def test_stop_ends_the_thread_within_1s_even_while_a_connect_hangs() -> None:
    """pyserial's socket:// connect waits up to 5 s when SYNs go unanswered (a host gone from
    the network).  On loopback the same happens with a listener whose backlog is full."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(0)
    port = srv.getsockname()[1]
    fillers = []
    for _ in range(3):  # fill the accept queue; later SYNs are dropped
        c = socket.socket()
        c.setblocking(False)
        with contextlib.suppress(BlockingIOError):
            c.connect(("127.0.0.1", port))
        fillers.append(c)
    src = SerialSource(SerialOptions(url=f"socket://127.0.0.1:{port}"))
    try:
        baseline = _syn_sent_to(port)
        src.start(Sink())
        deadline = time.monotonic() + DEADLINE_S
        stalled = threading.Event()
        while _syn_sent_to(port) <= baseline:  # wait for the source's connect to hang
            assert time.monotonic() < deadline, "the source never tried to connect"
            stalled.wait(0.01)
        assert stop_in_time(src) < 1.0
    finally:
        src.stop(1.0)
        for c in fillers:
            c.close()
        srv.close()


# -- sim source --------------------------------------------------------------------------------

@pytest.mark.parametrize("revision", [64, 36])
def test_sim_with_speed_0_and_one_cycle_emits_exactly_one_flight(revision: int) -> None:
    src = SimSource(SimOptions(speed=0, cycles=1, revision=revision))
    model = FlightModel(FlightProfile(revision=revision))
    sink = Sink()
    src.start(sink)
    try:
        assert src.done.wait(30), "the one-cycle simulation did not finish"
    finally:
        stop_in_time(src)
    msgs = sink.msgs
    sm = [m for m in msgs if isinstance(m, SmUpdate)]
    st = [m for m in msgs if isinstance(m, Status)]
    assert len(sm) + len(st) == len(msgs) == src.stats()["sent"]
    # SM_UPDATE at 10 Hz over one cycle, up to the first sample after the return to IDLE
    assert [m.timestamp_ms for m in sm] == [BOOT_UPTIME_MS + 100 * k for k in range(len(sm))]
    assert (len(sm) - 2) * 0.1 < model.cycle_s <= (len(sm) - 1) * 0.1 + 1e-9
    # STATUS at 1 Hz over the same span
    assert [m.timestamp_ms for m in st] == [BOOT_UPTIME_MS + 1000 * k for k in range(len(st))]
    assert len(st) == int((len(sm) - 1) * 0.1) + 1
    # merged in time order
    stamps = [m.timestamp_ms for m in msgs]
    assert stamps == sorted(stamps)
    # the SIMPLE state order, once, ending back in IDLE (disarmed)
    states = [m.state for m in sm]
    runs = [s for i, s in enumerate(states) if i == 0 or s != states[i - 1]]
    assert runs == SIMPLE_ORDER
    assert not sm[-1].armed and sm[-2].state == S.LANDED and sm[-2].armed
    for k, m in enumerate(sm):
        assert m.state == model.state_at(k * 0.1)
        assert m.payload_len == revision
    for m in st:
        assert m.state == model.state_at((m.timestamp_ms - BOOT_UPTIME_MS) / 1000)
        assert m.armed == (S.ARMED <= m.state <= S.LANDED)
    # messages carry their raw frames, which decode to themselves
    assert {m.origin for m in msgs} == {"sim"}
    for m in msgs:
        assert decode_all(m.raw, origin="sim", vehicle="sim") == [m]
        assert encode(m) == m.raw


def test_sim_source_stops_within_1s_while_pacing() -> None:
    src = SimSource(SimOptions(speed=1.0), name="slow-sim")
    sink = Sink()
    src.start(sink)
    try:
        assert sink.wait_count(2)  # running, waiting for the next 100 ms slot
        assert {m.origin for m in sink.msgs} == {"slow-sim"}
    finally:
        took = stop_in_time(src)
    assert took < 1.0
    assert src.done.is_set()


# -- replay ------------------------------------------------------------------------------------

def make_recording(path: Path, frames: list[bytes], span_s: float,
                   t0: float = 1_700_000_000.0) -> list[tuple[float, bytes]]:
    items = [(t0 + span_s * i / (len(frames) - 1), f) for i, f in enumerate(frames)]
    rec = Recorder(path)
    for t, f in items:
        rec.write(f, t=t)
    rec.close()
    return items


def run_replay(src: ReplaySource, timeout: float = DEADLINE_S) -> Sink:
    sink = Sink()
    src.start(sink)
    try:
        assert src.done.wait(timeout), "the replay did not finish"
    finally:
        stop_in_time(src)
    return sink


def test_replay_at_speed_0_emits_every_frame_in_order(tmp_path: Path) -> None:
    frames = sample_frames()
    make_recording(tmp_path / "f.agrec", frames, span_s=3600.0)  # an hour, replayed at once
    src = ReplaySource(ReplayOptions(path=str(tmp_path / "f.agrec"), speed=0))
    sink = run_replay(src, timeout=5.0)
    assert [m.raw for m in sink.msgs] == frames
    assert {m.origin for m in sink.msgs} == {"replay:f.agrec"}
    assert src.stats()["frames"] == len(frames) == src.stats()["records"]
    assert src.stats()["torn_tail_bytes"] == 0


@pytest.mark.parametrize("speed", [4.0, 10.0])
def test_replay_at_speed_n_compresses_the_recorded_span_n_fold(tmp_path: Path,
                                                               speed: float) -> None:
    frames = sample_frames()[:41]
    items = make_recording(tmp_path / "p.agrec", frames, span_s=2.0)
    sink = run_replay(ReplaySource(ReplayOptions(path=str(tmp_path / "p.agrec"), speed=speed)))
    stamps = [s for s, _ in sink.items]
    assert [m.raw for m in sink.msgs] == frames
    want = 2.0 / speed
    span = stamps[-1] - stamps[0]
    # a behaviour check, loose on purpose (scheduling noise of a loaded machine)
    assert want - 0.05 <= span <= 3 * want + 0.1, (span, want)
    for (s, _), (t, _) in zip(sink.items, items, strict=True):  # never early
        assert s - stamps[0] >= (t - items[0][0]) / speed - 0.05


def test_replay_skips_a_torn_tail(tmp_path: Path) -> None:
    frames = sample_frames()[:20]
    path = tmp_path / "torn.agrec"
    make_recording(path, frames, span_s=1.0)
    data = path.read_bytes()
    path.write_bytes(data[:-7])  # the last record loses its CRC and part of its frame
    src = ReplaySource(ReplayOptions(path=str(path), speed=0))
    sink = run_replay(src)
    assert [m.raw for m in sink.msgs] == frames[:-1]
    assert src.stats()["torn_tail_bytes"] > 0
    assert src.stats()["crc_failures"] == 0


def test_replay_passes_a_corrupt_record_in_the_middle(tmp_path: Path) -> None:
    frames = sample_frames()[:10]
    path = tmp_path / "c.agrec"
    make_recording(path, frames, span_s=1.0)
    data = bytearray(path.read_bytes())
    off = len(recording.HEADER) + sum(len(f) + recording.REC_OVERHEAD for f in frames[:3])
    data[off + 12] ^= 0x55  # inside the fourth record's frame
    path.write_bytes(bytes(data))
    src = ReplaySource(ReplayOptions(path=str(path), speed=0))
    sink = run_replay(src)
    assert [m.raw for m in sink.msgs] == frames[:3] + frames[4:]
    assert src.stats()["corrupt_skips"] == 1


def test_replay_loop_repeats_until_stopped(tmp_path: Path) -> None:
    frames = sample_frames()[:5]
    make_recording(tmp_path / "l.agrec", frames, span_s=0.01)
    src = ReplaySource(ReplayOptions(path=str(tmp_path / "l.agrec"), speed=1.0, loop=True))
    sink = Sink()
    src.start(sink)
    try:
        assert sink.wait_count(3 * len(frames))
        assert not src.done.is_set()
    finally:
        took = stop_in_time(src)
    assert took < 1.0
    assert [m.raw for m in sink.msgs[:15]] == frames * 3


def test_replay_loop_paces_every_pass_on_one_clock(tmp_path: Path) -> None:
    """Each pass's times carry on from the last one's end, one record interval later: the
    pacer's clock never goes back (every pass after the first used to play flat out)."""
    frames = sample_frames()[:5]
    make_recording(tmp_path / "l.agrec", frames, span_s=0.4)
    src = ReplaySource(ReplayOptions(path=str(tmp_path / "l.agrec"), speed=1.0, loop=True))
    data = (tmp_path / "l.agrec").read_bytes()
    times = [t for t, _ in itertools.islice(src._passes(data), 15)]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert all(g > 0 for g in gaps), gaps
    assert times[-1] - times[0] == pytest.approx(3 * 0.4 + 2 * 0.1)  # 3 passes, 2 joins


def test_replay_of_a_missing_or_foreign_file_is_a_config_error_naming_the_key(
        tmp_path: Path) -> None:
    """Checked by the path key, before anything is built (the constructor does not check)."""
    with pytest.raises(ConfigError, match=r"^sources\[0\]\.path: no recording"):
        parse({"sources": [{"type": "replay", "path": str(tmp_path / "nope.agrec")}]})
    (tmp_path / "x.txt").write_text("hello, not a recording\n")
    with pytest.raises(ConfigError, match=r"^sources\[0\]\.path: .*magic"):
        parse({"sources": [{"type": "replay", "path": str(tmp_path / "x.txt")}]})
    (tmp_path / "v9.agrec").write_bytes(recording.MAGIC + b"\x09\x00\x00\x00")
    with pytest.raises(ConfigError, match="version 9"):
        parse({"sources": [{"type": "replay", "path": str(tmp_path / "v9.agrec")}]})


# -- the contract --------------------------------------------------------------------------------

class _Counting(Source):
    """A thread source that emits until asked to stop, then winds down only once
    ``release`` is set (a source with something slow to close)."""

    NAME = "counting"

    def __init__(self, name: str | None = None) -> None:
        super().__init__(name)
        self.n = 0
        self.release = threading.Event()

    def run(self, stop: threading.Event) -> None:
        while not stop.wait(0.001):
            self.n += 1
            self.emit(RawFrame(0x42, self.n.to_bytes(4, "little"), origin=self.name))
        self.release.wait(DEADLINE_S)

    def stats(self) -> dict[str, Any]:
        return {"sent": self.n}


def test_request_stop_returns_at_once_and_the_source_winds_down_on_its_own() -> None:
    src = _Counting()
    sink = Sink()
    src.start(sink)
    try:
        assert sink.wait_count(3)
        assert not src.stop_requested and not src.done.is_set()
        run_within(src.request_stop)  # returns though the source is still winding down
        assert src.stop_requested and not src.done.is_set()
        src.request_stop()  # safe twice
        src.release.set()
        assert src.done.wait(DEADLINE_S), "the source did not end after request_stop"
    finally:
        src.release.set()
        stop_in_time(src)
    src.stop(0.1)  # and stop after that
    assert src.stats()["sent"] == len(sink.msgs)


class _PublicOnly:
    """A source written against the documented contract alone: no base class, no private
    attributes for the gateway to reach into."""

    CONFIG = None

    def __init__(self, name: str) -> None:
        self.name = name
        self.done = threading.Event()
        self.calls: list[str] = []
        self._go = threading.Event()

    def attach(self, context: Any) -> None:
        self.calls.append("attach")

    def start(self, sink: Callable[[Any], Any]) -> None:
        self.calls.append("start")
        sink(RawFrame(0x42, b"hello", origin=self.name))

    def request_stop(self) -> None:
        self.calls.append("request_stop")

    def stop(self, timeout: float = 1.0) -> None:
        self.calls.append("stop")
        self.done.set()

    def stats(self) -> dict[str, Any]:
        return {"calls": len(self.calls)}


def test_the_gateway_drives_sources_through_the_public_contract_only() -> None:
    gw = Gateway(parse({"gateway": {"status_interval_s": 0}}), status_out=io.StringIO())
    a, b = _PublicOnly("a"), _PublicOnly("b")
    gw.sources = [a, b]  # type: ignore[list-item]
    gw.start()
    summary = gw.stop()
    # every source is asked to stop before any is waited for
    assert a.calls == b.calls == ["attach", "start", "request_stop", "stop"]
    assert summary["messages_in"] == {"raw": 2}
    assert summary["sources"] == {"a": {"calls": 4}, "b": {"calls": 4}}


class _Uplink(Source):
    """A source that also sends (as an XBee ground link sends the pilot's commands up)."""

    NAME = "uplink"

    def __init__(self, name: str | None = None) -> None:
        super().__init__(name)
        self.taken: list[RcChannels] = []
        self.got = threading.Event()

    def routes(self) -> Routes:
        return Routes().on(RcChannels, self.take)

    def take(self, msg: RcChannels) -> None:
        self.taken.append(msg)
        self.got.set()

    def inbox_stats(self) -> dict[str, int]:
        return {"taken": len(self.taken)}

    def run(self, stop: threading.Event) -> None:
        stop.wait()


def test_a_source_with_routes_gets_the_gateways_messages() -> None:
    cfg = GatewayConfig(sources=[Part("uplink", "up", {}, _Uplink)])
    gw = Gateway(cfg)
    gw.start()
    try:
        (src,) = gw.sources
        sticks = RcChannels((1500, 1000, None), origin="crsf")
        gw.ingest(sticks)  # e.g. a CRSF receiver's channels, handed on by its backend
        assert src.got.wait(5) and src.taken == [sticks]
        assert gw.dispatcher.stats()["up (in)"]["taken"] == 1
    finally:
        gw.stop()


# -- sources on the gateway's loop ---------------------------------------------------------------

def test_sources_sharing_one_loop_deliver_on_its_thread_and_each_stops_within_1s(
        pty_pair: tuple[int, str], tmp_path: Path) -> None:
    """A simulation, a replay and a serial port on one loop: no thread of their own, every
    message handed on from the loop's thread, each stopped within a second."""
    master, slave_path = pty_pair
    frames = sample_frames()
    make_recording(tmp_path / "f.agrec", frames, span_s=3600.0)
    loop = IoLoop("shared-sources")
    loop.start()
    before = set(threading.enumerate())
    sink = Sink()
    threads: set[str] = set()

    def on_loop(msg: Any) -> None:
        threads.add(threading.current_thread().name)
        sink(msg)

    sim = SimSource(SimOptions(speed=1.0), name="sim-a")
    replay = ReplaySource(ReplayOptions(path=str(tmp_path / "f.agrec"), speed=0), name="again")
    port = SerialSource(SerialOptions(url=slave_path, baudrate=9600), name="rocket")
    sources: list[Source] = [sim, replay, port]
    try:
        for s in sources:
            s.use_loop(loop)
            s.start(on_loop)
        wait_until_reading(master, sink)
        write_all(master, b"".join(frames))
        assert sink.wait_count(len(frames), keep=lambda m: m.origin == "again")
        assert replay.done.wait(DEADLINE_S)  # a replay that ends ends on the loop too
        assert sink.wait_count(2, keep=lambda m: m.origin == "sim-a")
        assert sink.wait_count(len(frames), keep=lambda m: m.origin == "rocket" and not_probe(m))
        assert threads == {"io-shared-sources"}
        new = {t.name for t in threading.enumerate() if t not in before}
        assert {n for n in new if not n.startswith("blocking-")} == set(), new  # the open's
        for s in sources:
            assert stop_in_time(s, shared=True) < 1.0
        assert loop.alive  # the loop is its owner's to stop
        n = len(sink.msgs)
        ran = threading.Event()
        loop.call_later(0.2, ran.set)  # nothing more comes once they have stopped
        assert ran.wait(DEADLINE_S) and len(sink.msgs) == n
    finally:
        for s in sources:
            s.stop(1.0)
        loop.stop(1.0)
        loop.close()


def test_a_blocking_run_source_runs_on_a_counted_long_call_of_the_loop() -> None:
    """A third-party source that still implements a blocking ``run(stop)``: it works, on a
    thread of the loop's blocking calls counted as ``long_running``, and stops within 1 s."""
    pool = BlockingCalls(workers=1, idle_s=0.05, name="legacy-pool")
    loop = IoLoop("legacy", blocking=pool)
    loop.start()
    src = _Counting()
    sink = Sink()
    try:
        src.use_loop(loop)
        src.start(sink)
        assert sink.wait_count(3)
        assert pool.stats()["long_running"] == 1 and pool.stats()["long_calls"] == 1
        src.release.set()
        assert stop_in_time(src, shared=True) < 1.0
        assert pool.stats()["long_running"] == 0  # run() returned: done is set after it
    finally:
        src.release.set()
        src.stop(1.0)
        loop.stop(1.0)
        loop.close()


def _gateway_threads(args: list[str]) -> tuple[set[str], int, int]:
    """Run an in-process gateway from ``run`` flags until 5 messages are in; return the names
    of the threads it added (pool workers apart), how many were pool workers, and how many
    backends it has."""
    from gateway.commands import cli

    cfg = cli.config_from_args(cli.build_parser().parse_args(["run", *args]))
    g = Gateway(cfg, status_out=io.StringIO())
    before = set(threading.enumerate())
    g.start()
    try:
        assert wait_for(lambda: sum(g.counts.values()) >= 5)
        new = [t.name for t in threading.enumerate() if t not in before]
    finally:
        g.stop()
    pool = [n for n in new if n.startswith("blocking-")]
    ours = {n for n in new if not n.startswith("blocking-")}
    return ours, len(pool), len(g.dispatcher.backends())


def test_the_default_runs_threads_are_bounded_and_do_not_grow_with_its_sources() -> None:
    """The embedded default (the simulation through every default backend): one loop for
    the sources, at most one thread of ours per backend (its loop or worker), what the
    libraries start themselves (Zenoh's and foxglove-sdk's callback threads), and at most
    BLOCKING_WORKERS pool workers for the opens.  Four sources instead of one add none."""
    one, pool_one, backends = _gateway_threads(["--sim-speed", "10"])
    four, pool_four, _ = _gateway_threads(["--sim-speed", "10", *["--source", "sim"] * 4])
    for names, pool in ((one, pool_one), (four, pool_four)):
        ours = {n for n in names if "pyo3" not in n}  # (named by the Rust bindings)
        assert "io-sources" in ours and not any(n.startswith("source") for n in ours), ours
        assert len(ours) <= 1 + backends, ours
        assert len(names) - len(ours) <= 2, names
        assert pool <= BLOCKING_WORKERS
    assert len(four) == len(one), (one, four)


def test_a_pacer_at_speed_0_lets_the_loop_serve_others_between_batches() -> None:
    loop = IoLoop("pacer")
    loop.start()
    got: list[int] = []
    seen_at: list[int] = []
    ended = threading.Event()
    n = 10 * BATCH

    def deliver(t: float, i: int) -> None:
        got.append(i)
        if i == 0:  # other work handed to the loop while the pacer has thousands to go
            loop.call_soon(lambda: seen_at.append(len(got)))

    try:
        Pacer(loop, ((float(i), i) for i in range(n)), 0.0, deliver, on_end=ended.set).start()
        assert ended.wait(DEADLINE_S)
        assert got == list(range(n))
        assert seen_at and seen_at[0] <= BATCH  # served after the first batch, not the last
    finally:
        loop.stop(1.0)
        loop.close()


def test_a_cancelled_pacer_delivers_nothing_more() -> None:
    loop = IoLoop("pacer")
    loop.start()
    got: list[int] = []
    first = threading.Event()
    try:
        pacer = Pacer(loop, ((i * 0.05, i) for i in range(1000)), 1.0,
                      lambda t, i: (got.append(i), first.set()))
        pacer.start()
        assert first.wait(DEADLINE_S)
        stopped = threading.Event()
        loop.call_soon(lambda: (pacer.cancel(), stopped.set()))
        assert stopped.wait(DEADLINE_S)
        n = len(got)
        later = threading.Event()
        loop.call_later(0.2, later.set)  # four items' worth of schedule
        assert later.wait(DEADLINE_S) and len(got) == n and n < 1000
    finally:
        loop.stop(1.0)
        loop.close()
