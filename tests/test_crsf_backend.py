"""The CRSF backend over real ports: its own pty, a serial URL on a pty pair, loop:// and a
TCP socket that goes away; receiver input (link statistics through a real dispatcher, RC
channels); configuration and ``run`` flags; and the simulated flight end to end, in process
and through ``aurora-gateway run --crsf``, read back by the EdgeTX-semantics radio."""

from __future__ import annotations

import contextlib
import math
import os
import select
import socket
import subprocess
import sys
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from helpers import run_within, wait_for
from test_crsf_edgetx import EdgeTxRadio

from backends.crsf.backend import CrsfBackend
from backends.crsf.frames import LinkStatistics, RcChannels, encode
from backends.crsf.options import CrsfOptions
from backends.crsf.ports import PtyPair
from dialects.states import SimpleState
from gateway import config, model
from gateway.backend import Backend, GatewayContext, Outcome, Routes
from gateway.config import ConfigError
from gateway.dispatcher import Dispatcher
from gateway.flight import FlightModel, FlightProfile
from gateway.model import LinkStats, SmUpdate, Status
from gateway.sources.options import SimOptions
from gateway.sources.sim import SimSource, flight_messages

DEADLINE_S = 15.0
REPO = Path(__file__).resolve().parents[1]
FLIGHT = ["IDLE*", "ARMED", "BOOST", "BURNOUT", "APOGEE", "MAIN", "REDUNDANT", "LANDED"]
LINK_STATS = LinkStatistics(-52, -61, 97, 9, 0, 7, 3, -48, 100, 11)


def read_until(fd: int, radio: EdgeTxRadio, pred: Callable[[], bool],
               timeout: float = DEADLINE_S) -> bool:
    """Feed what arrives on ``fd`` to ``radio`` until ``pred()`` holds or ``timeout``."""
    deadline = time.monotonic() + timeout
    while not pred():
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        ready, _, _ = select.select([fd], [], [], min(left, 0.05))
        if ready:
            radio.feed(os.read(fd, 4096))
    return True


class Recorder(Backend):
    """A backend that keeps what it is given (a real peer on the dispatcher)."""

    def __init__(self) -> None:
        super().__init__("recorder")
        self.sm: list[SmUpdate] = []
        self.link_stats: list[LinkStats] = []
        self.got_stats = threading.Event()
        self.rc: list[model.RcChannels] = []

    def routes(self) -> Routes:
        return (Routes().on(SmUpdate, self.send_sm_update).on(LinkStats, self.send_link_stats)
                .on(model.RcChannels, self.rc.append))

    def send_sm_update(self, m: SmUpdate) -> None:
        self.sm.append(m)

    def send_link_stats(self, m: LinkStats) -> None:
        self.link_stats.append(m)
        self.got_stats.set()


class PtyPeer:
    """A pty pair owned by the test: the backend opens ``path``, the test uses ``master``."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)

    def close(self) -> None:
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.fixture
def peer() -> Any:
    p = PtyPeer()
    yield p
    p.close()


def sm(state: int, armed: bool, alt: float = 12.5) -> SmUpdate:
    return SmUpdate(timestamp_ms=1, state=state, armed=armed, sm_type=0, altitude_m=alt,
                    acceleration_mps2=9.8, accel_vert_mps2=9.8, velocity_mps=-1.25,
                    roll_rad=0.1, pitch_rad=1.2, yaw_rad=-0.3)


def check_link_stats(ls: LinkStats, name: str = "crsf") -> None:
    assert ls.fields() == {
        "rssi_dbm": -52.0, "link_quality_pct": 97, "snr_db": 9.0, "tx_power_mw": 100,
        "downlink_rssi_dbm": -48.0, "downlink_link_quality_pct": 100, "downlink_snr_db": 11.0,
        "rf_mode": 7, "antenna": 0}
    assert ls.origin == name


# -- configuration ---------------------------------------------------------------------------

def test_config_table_is_validated_naming_the_key() -> None:
    cfg = config.parse({"backends": {"crsf": {"url": "/dev/ttyUSB0", "baudrate": 416666,
                                              "pitch": "nose-down", "gps_hz": 0}}})
    (part,) = cfg.backends
    b = part.cls.from_config(dict(part.options), name=part.name)
    assert (b.url, b.baudrate, b.pitch_sign) == ("/dev/ttyUSB0", 416666, -1.0)
    assert not b.scheduler.scheduled(0x02)
    for key, value in (("pitch", "up"), ("baudrate", "fast"), ("sync", 0x11),
                       ("max_frames_per_s", 0), ("speed", 3)):
        with pytest.raises(ConfigError, match=rf"backends\.crsf\.{key}"):
            config.parse({"backends": {"crsf": {key: value}}})
    for key, value in (("disarmed_suffix", "DISARMED"), ("url", "")):
        with pytest.raises(ConfigError, match=rf"backends\.crsf\.{key}"):
            config.parse({"backends": {"crsf": {key: value}}})


def test_embedded_default_runs_on_a_pty() -> None:
    parts = {p.name: p for p in config.embedded_default().backends}
    assert parts["crsf"].options["url"] == "pty"


def test_run_flags() -> None:
    from gateway.commands.cli import build_parser, config_from_args

    args = build_parser().parse_args(["run", "--crsf", "socket://127.0.0.1:9", "--crsf-baud",
                                      "416666"])
    parts = {p.name: p for p in config_from_args(args).backends}
    assert parts["crsf"].options["url"] == "socket://127.0.0.1:9"
    assert parts["crsf"].options["baudrate"] == 416666
    args = build_parser().parse_args(["run"])
    assert CrsfOptions.cli_options(args) is None


# -- ports -----------------------------------------------------------------------------------

def test_own_pty_sends_telemetry_and_reads_the_receiver() -> None:
    d = Dispatcher()
    rec = Recorder()
    b = CrsfBackend()
    b.attach(GatewayContext(emit=d.dispatch))
    d.add(b)
    d.add(rec)
    assert b.send_sm_update(sm(1, True)) is Outcome.NOT_READY  # not started yet
    d.start()
    path = b.pty_path
    assert path is not None and os.path.exists(path)
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY)
    try:
        assert wait_for(lambda: b.engine.connected)
        assert d.dispatch(sm(SimpleState.ARMED, True)) is Outcome.ACCEPTED
        radio = EdgeTxRadio()
        assert read_until(fd, radio, lambda: {"FM", "Alt", "Ptch", "VSpd"} <= set(radio.sensors))
        assert radio.sensors["FM"] == "ARMED" and radio.sensors["Alt"] == 1250
        channels = tuple(range(172, 172 + 16 * 100, 100))
        os.write(fd, b"\x00garbage" + encode(LINK_STATS) + encode(RcChannels(channels)))
        assert rec.got_stats.wait(DEADLINE_S)
        check_link_stats(rec.link_stats[0])
        assert wait_for(lambda: b.rc_frames == 1)
        assert b.rc_channels == channels
        # the sticks reach the gateway as pulse widths (EdgeTX: 172 → 988 µs, 992 → 1500 µs)
        assert wait_for(lambda: len(rec.rc) == 1)
        assert rec.rc[0].channels_us == tuple(round(1500 + (v - 992) * 5 / 8) for v in channels)
        assert rec.rc[0].channels_us[0] == 988 and rec.rc[0].origin == b.name
        st = b.stats()
        assert st["link_stats"] == 1 and st["rx_bytes_skipped"] == 8 and st["sent"] >= 3
    finally:
        d.close()
        os.close(fd)
    d.close()  # twice is fine
    assert not os.path.exists(path)


def test_serial_url_shares_the_port_between_writer_and_reader(peer: PtyPeer) -> None:
    d = Dispatcher()
    rec = Recorder()
    b = CrsfBackend(CrsfOptions(url=peer.path), sink=d.dispatch)
    d.add(b)
    d.add(rec)
    d.start()
    try:
        d.dispatch(Status(timestamp_ms=1, state=SimpleState.IDLE, sm_type=0,
                          flags=Status.make_flags(imu_ok=True, baro_ok=True, calibrated=True,
                                                  log_ready=True)))
        radio = EdgeTxRadio()
        assert read_until(peer.master, radio, lambda: radio.sensors.get("FM") == "IDLE*")
        os.write(peer.master, encode(LINK_STATS))
        assert rec.got_stats.wait(DEADLINE_S)
        check_link_stats(rec.link_stats[0])
        assert b.engine.stats.connects == 1 and b.stats()["link"] == 1
    finally:
        d.close()


def test_loop_url_reads_back_what_it_writes() -> None:
    b = CrsfBackend(CrsfOptions(url="loop://"))
    b.init()
    try:
        assert wait_for(lambda: b.engine.connected)
        b.send_sm_update(sm(SimpleState.BOOST, True))
        assert wait_for(lambda: b.stats()["rx_other"] >= 4)  # its own frames, decoded
        assert b.stats()["rx_crc_errors"] == 0 and b.link_stats_rx == 0
    finally:
        b.close()


def test_dead_port_is_retried_and_a_lost_connection_reconnects() -> None:
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
    port = srv.getsockname()[1]
    b = CrsfBackend(CrsfOptions(url=f"socket://127.0.0.1:{port}"))
    b.init()
    conns: list[socket.socket] = []
    try:
        assert wait_for(lambda: b.engine.stats.connect_failures >= 1)
        assert b.send_sm_update(sm(SimpleState.IDLE, False)) is Outcome.NOT_READY
        srv.listen()
        srv.settimeout(DEADLINE_S)
        for expected in ("MAIN", "LANDED"):
            conn, _ = srv.accept()
            conns.append(conn)
            state = SimpleState[expected]
            radio = EdgeTxRadio()
            conn.settimeout(0.05)

            def got(radio: EdgeTxRadio = radio, expected: str = expected) -> bool:
                return radio.sensors.get("FM") == expected

            deadline = time.monotonic() + DEADLINE_S
            while not got() and time.monotonic() < deadline:
                b.send_sm_update(sm(state, True))
                with contextlib.suppress(TimeoutError):
                    radio.feed(conn.recv(4096))
            assert got()
            conn.close()  # the receiver goes away: the next writes fail, the backend reopens
        assert b.engine.stats.connects == 2
    finally:
        b.close()
        for c in conns:
            c.close()
        srv.close()


def test_state_changes_published_before_the_port_opens_go_out_first() -> None:
    """The flight starts before the receiver's port is open (it opens in the background;
    here it is refused until the test listens): the states published meanwhile wait and go
    out first, in order, once the port is up (``run --crsf`` used to lose the first one)."""
    srv = socket.socket()
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
    b = CrsfBackend(CrsfOptions(url=f"socket://127.0.0.1:{srv.getsockname()[1]}"))
    b.init()
    conn: socket.socket | None = None
    try:
        assert wait_for(lambda: b.engine.stats.connect_failures >= 1)
        assert b.send_sm_update(sm(SimpleState.IDLE, False)) is Outcome.NOT_READY
        assert b.send_sm_update(sm(SimpleState.ARMED, True)) is Outcome.NOT_READY
        srv.listen()
        srv.settimeout(DEADLINE_S)
        conn, _ = srv.accept()
        radio = EdgeTxRadio()
        assert read_until(conn.fileno(), radio, lambda: len(radio.texts()) >= 2)
        assert radio.texts()[:2] == ["IDLE*", "ARMED"]
        assert b.submit_failures == 0 and b.stats()["dropped_changes"] == 0
    finally:
        b.close()
        if conn is not None:
            conn.close()
        srv.close()


def test_backend_starts_no_thread_of_its_own(peer: PtyPeer) -> None:
    """Sending, receiving and the scheduler all run on the port engine's thread; and the
    last state change still goes out when the backend closes right after it."""
    before = set(threading.enumerate())
    b = CrsfBackend(CrsfOptions(url=peer.path), name="crsf-solo")
    b.init()
    radio = EdgeTxRadio()
    try:
        b.send_sm_update(sm(SimpleState.BOOST, True))
        assert read_until(peer.master, radio, lambda: radio.sensors.get("FM") == "BOOST")
        os.write(peer.master, encode(LINK_STATS))
        assert wait_for(lambda: b.link_stats_rx == 1)
        new = {t.name for t in threading.enumerate() if t not in before}
        # the engine's loop, and the shared pool of blocking calls its opener ran on
        assert {n for n in new if not n.startswith("blocking-")} <= {"io-crsf-solo"}, new
        b.send_sm_update(sm(SimpleState.LANDED, False))
    finally:
        b.close()
    assert read_until(peer.master, radio, lambda: "LANDED*" in radio.texts())
    st = b.stats()
    assert st["link"] == 0 and st["errors"] == 0 and st["dropped"] == 0


def read_exactly(fd: int, n: int, timeout: float = DEADLINE_S) -> bytes:
    """``n`` bytes from ``fd`` (fewer only if they do not come within ``timeout``)."""
    got = b""
    deadline = time.monotonic() + timeout
    while len(got) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            break
        if select.select([fd], [], [], min(left, 0.05))[0]:
            got += os.read(fd, n - len(got))
    return got


def nothing_more(fd: int) -> bool:
    """True when nothing waits on ``fd`` (a non-blocking read on a tty also waits for the
    bytes the kernel has not moved to the line discipline yet)."""
    os.set_blocking(fd, False)
    try:
        os.read(fd, 1)
    except BlockingIOError:
        return True
    finally:
        os.set_blocking(fd, True)
    return False


def pattern(i: int, size: int = 100) -> bytes:
    return bytes((i * 7 + k) % 251 for k in range(size))


def test_own_pty_never_blocks_and_keeps_no_stale_backlog() -> None:
    """With nobody reading, writes go on without blocking (100 kB in one burst, far faster
    than the kernel moves bytes to the slave) and a reader attaching late finds exactly the
    newest ``backlog_bytes``, then what comes next."""
    p = PtyPair(backlog_bytes=1024)
    try:
        sent = b""

        def burst() -> None:
            nonlocal sent
            for i in range(1000):
                chunk = pattern(i)
                assert p.write(chunk) == 100
                sent += chunk
                assert p.backlog_bound <= 1024

        run_within(burst)
        assert p.flushes >= 1 and p.dropped_bytes == 0
        assert p.discarded_bytes == len(sent) - p.backlog_bound
        fd = os.open(p.path, os.O_RDWR | os.O_NOCTTY)
        try:
            stale = read_exactly(fd, p.backlog_bound)
            assert len(stale) == 1024 and stale == sent[-1024:]  # the newest, not the oldest
            assert nothing_more(fd)
            p.write(b"fresh")
            assert read_exactly(fd, 5) == b"fresh"
        finally:
            os.close(fd)
    finally:
        p.close()
        p.close()
    with pytest.raises(OSError):
        p.write(b"late")


def test_own_pty_backlog_seen_by_a_late_reader() -> None:
    """The issue's case: 30 writes of 100 B in a burst (FIONREAD then reports about 100 B
    while 3000 B wait): a late reader gets at most the bound, ending with the newest byte."""
    p = PtyPair(backlog_bytes=1024)
    try:
        for i in range(30):
            p.write(bytes([i]) * 100)
        fd = os.open(p.path, os.O_RDWR | os.O_NOCTTY)
        try:
            stale = read_exactly(fd, 1024)
            assert nothing_more(fd)
            assert stale == b"".join(bytes([i]) * 100 for i in range(30))[-1024:]
            assert stale[-1] == 29
        finally:
            os.close(fd)
    finally:
        p.close()


def test_own_pty_reader_that_keeps_up_loses_nothing() -> None:
    """A reader that reads what comes never loses a byte: the backlog is measured every
    ``backlog_bytes`` written and found empty, so nothing is discarded."""
    p = PtyPair(backlog_bytes=256)
    fd = os.open(p.path, os.O_RDWR | os.O_NOCTTY)
    try:
        for i in range(100):  # 10 kB, 40 times the bound
            chunk = pattern(i)
            p.write(chunk)
            assert read_exactly(fd, 100) == chunk
        assert p.checks >= 30 and p.flushes == 0 and p.discarded_bytes == 0
        assert nothing_more(fd)
    finally:
        os.close(fd)
        p.close()


def test_own_pty_is_a_port_the_engine_reads() -> None:
    """The master end as a port: what the reader writes to the slave is read back, nothing
    waiting reads as b"", and closing the port view leaves the pty open."""
    p = PtyPair()
    port = p.port()
    fd = os.open(p.path, os.O_RDWR | os.O_NOCTTY)
    try:
        assert port.fileno() == p.master and port.read(64) == b""
        os.write(fd, b"\xc8\x02up")
        assert select.select([port.fileno()], [], [], DEADLINE_S)[0]
        got = b""
        deadline = time.monotonic() + DEADLINE_S
        while len(got) < 4 and time.monotonic() < deadline:
            if select.select([port.fileno()], [], [], 0.05)[0]:
                got += port.read(64)
        assert got == b"\xc8\x02up"
        port.close()
        assert port.write(b"still") == 5 and read_exactly(fd, 5) == b"still"
    finally:
        os.close(fd)
        p.close()
    with pytest.raises(OSError):
        port.read(64)


# -- link statistics to the gateway ----------------------------------------------------------

class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_link_stats_are_rate_limited_and_a_failing_sink_is_isolated() -> None:
    clock = Clock()
    got: list[LinkStats] = []
    b = CrsfBackend(CrsfOptions(link_stats_hz=5.0), sink=got.append, clock=clock, name="elrs")
    frame = encode(LINK_STATS)
    b.feed(frame * 10)
    assert len(got) == 1 and b.link_stats_rx == 10
    check_link_stats(got[0], "elrs")
    clock.now += 0.2
    b.feed(frame[:5])
    b.feed(frame[5:])
    assert len(got) == 2

    def broken(msg: Any) -> None:
        raise RuntimeError("gateway gone")

    b.attach(GatewayContext(emit=broken))
    clock.now += 1
    b.feed(frame)
    assert b.emit_errors == 1 and b.stats()["emit_errors"] == 1
    quiet = CrsfBackend(CrsfOptions(link_stats_hz=0), sink=got.append)
    quiet.feed(frame)
    assert len(got) == 2 and quiet.link_stats_rx == 1


# -- the simulated flight end to end ---------------------------------------------------------

def angle_close(a: float, b: float, tol: float) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) <= tol


def match_in_order(values: list[Any], sources: list[SmUpdate],
                   same: Callable[[Any, SmUpdate], bool]) -> None:
    """Every decoded value matches a source message, in the source's order."""
    j = 0
    for v in values:
        while j < len(sources) and not same(v, sources[j]):
            j += 1
        assert j < len(sources), f"decoded {v} matches no later source message"


def check_flight(radio: EdgeTxRadio, sources: list[SmUpdate]) -> None:
    alts = [v for name, v in radio.history if name == "Alt"]
    match_in_order(alts, sources, lambda cm, m: abs(cm / 100 - m.altitude_m) <= 0.1)
    att = radio.raw_attitude

    def same_attitude(raw: tuple[int | None, ...], m: SmUpdate) -> bool:
        p, r, y = (k / 10000 for k in raw if k is not None)
        return (angle_close(p, m.pitch_rad, 1e-4 + 1e-9) and angle_close(r, m.roll_rad, 1e-4 + 1e-9)
                and angle_close(y, m.yaw_rad, 1e-4 + 1e-9))

    match_in_order(att, sources, same_attitude)
    assert len(alts) >= 5 and len(att) >= 5


def test_simulated_flight_in_process(peer: PtyPeer) -> None:
    """The flight at 4× speed through a real dispatcher into a pty; every state in order,
    altitude within 0.1 m and attitude within 1e-4 rad of what the source sent."""
    rec = Recorder()
    d = Dispatcher([CrsfBackend(CrsfOptions(url=peer.path)), rec])
    d.start()
    src = SimSource(SimOptions(speed=4, cycles=1, pad_idle_s=0.5, pad_armed_s=0.5))
    radio = EdgeTxRadio()
    try:
        src.start(d.dispatch)
        assert read_until(peer.master, radio, lambda: "LANDED" in radio.texts(), 30.0), \
            radio.texts()
        read_until(peer.master, radio, lambda: False, 0.3)  # a little of LANDED too
    finally:
        src.stop()
        d.close()
    assert radio.texts() == FLIGHT
    check_flight(radio, rec.sm)
    model = FlightModel(FlightProfile(idle_s=0.5, armed_s=0.5))
    in_flight = [v / 100 for name, v in radio.history if name == "Alt" and v > 100]
    assert len(in_flight) >= 3 and max(in_flight) >= 0.5 * model.apogee_altitude_m
    assert min(v for name, v in radio.history if name == "VSpd") < -100  # under the chutes


def test_run_crsf_flag_full_flight(peer: PtyPeer, tmp_path: Path) -> None:
    """``aurora-gateway run --crsf <pty>``: one whole simulated flight, IDLE to IDLE, at 50×."""
    cfg = tmp_path / "gw.toml"
    cfg.write_text('[gateway]\nstatus_interval_s = 0\n\n'
                   '[[sources]]\ntype = "sim"\nspeed = 50\ncycles = 1\n'
                   'pad_idle_s = 1\npad_armed_s = 1\n\n'
                   '[backends.crsf]\nurl = "pty"\n', encoding="utf-8")
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway", "run", "--config", str(cfg), "--crsf", peer.path,
         "--log-level", "warning"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    radio = EdgeTxRadio()
    try:
        read_until(peer.master, radio, lambda: proc.poll() is not None, 60.0)
        read_until(peer.master, radio, lambda: False, 0.2)  # what is left in the pty
        _out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err.decode()
    assert radio.texts() == [*FLIGHT, "IDLE*"], (radio.texts(), err.decode())
    model = FlightModel(FlightProfile(idle_s=1, armed_s=1))
    sources = [m for _, m in flight_messages(model, cycles=1) if isinstance(m, SmUpdate)]
    check_flight(radio, sources)
    assert radio.crc_errors == 0


def test_monitor_tool_shows_the_radio_view(capsys: pytest.CaptureFixture[str]) -> None:
    from backends.crsf import monitor

    b = CrsfBackend()
    b.init()
    try:
        path = b.pty_path
        assert path is not None
        for state in (SimpleState.IDLE, SimpleState.BOOST):
            b.send_sm_update(sm(state, state != SimpleState.IDLE, alt=12.5 * state))
            b.send_status(Status(timestamp_ms=1, state=state, sm_type=0,
                                 flags=Status.make_flags(armed=state != SimpleState.IDLE)))
        assert monitor.main([path, "--summary", "--quiet", "--duration", "1.5"]) == 0
    finally:
        b.close()
    out = capsys.readouterr().out
    # a status without the IMU check passing: the marker shows; the latest values are shown
    assert "FM BOOST!IMU" in out and "Alt 25.00 m" in out and "Ptch 1.200 rad" in out, out
