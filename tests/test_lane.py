"""The router's compiled lane (backends/mavlink/lane.py) against the Python path it stands in
for: the same datagrams out, in the same order, and the same counters, for a stream with a
new source, a targeted message and a second sender in it; and the loop it runs on still
answers calls and timers from other threads while a stream keeps the lane busy."""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import wait_for
from mavlink_peer import upstream_dialect
from test_mmsg import udp, udp_route

from backends.mavlink import lane as lane_mod
from backends.mavlink import router as router_mod
from gateway.io.transport import UdpPort

dev = upstream_dialect()

needs_lane = pytest.mark.skipif(
    not lane_mod.ENABLED or router_mod._speedups is None,
    reason="the lane is not built here, or turned off (AURORA_NO_LANE, AURORA_NO_SPEEDUPS)")


@pytest.fixture
def stack() -> Iterator[contextlib.ExitStack]:
    with contextlib.ExitStack() as s:
        yield s


def _stream() -> list[tuple[int, bytes]]:
    """(sender, datagram): system 1's ATTITUDE; from 600 on, system 2 too (a new source);
    at 900 a COMMAND_LONG from system 2 to system 1 (targeted); from 1200 on, a second
    sender (index 1) for system 3."""
    m1, m2, m3 = (dev.MAVLink(None, s, 1) for s in (1, 2, 3))
    out = []
    for i in range(1500):
        out.append((0, m1.attitude_encode(i, 0.1, 0.2, 0.3, 0, 0, 0).pack(m1)))
        m1.seq = (m1.seq + 1) & 0xFF
        if i >= 600 and i % 3 == 0:
            out.append((0, m2.attitude_encode(i, 0, 0, 0, 0, 0, 0).pack(m2)))
            m2.seq = (m2.seq + 1) & 0xFF
        if i == 900:
            out.append((0, m2.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(m2)))
            m2.seq = (m2.seq + 1) & 0xFF
        if i >= 1200 and i % 4 == 0:
            out.append((1, m3.attitude_encode(i, 0, 0, 0, 0, 0, 0).pack(m3)))
            m3.seq = (m3.seq + 1) & 0xFF
    return out


def _command(data: bytes) -> bool:
    """COMMAND_LONG (to system 1, on the vehicle's side: not forwarded to the GCS)."""
    return data[7:10] == (76).to_bytes(3, "little")


def _run(enabled: bool, monkeypatch: pytest.MonkeyPatch) -> tuple[list[bytes], dict[str, Any],
                                                                     int]:
    """The stream through a router (lane on or off): what the ground station got, the
    counters, and how often the lane ran."""
    monkeypatch.setattr(lane_mod, "ENABLED", enabled)
    with contextlib.ExitStack() as stack:
        gcs = udp(stack)
        router, vin, vout = udp_route(stack, gcs)
        senders = [udp(stack), udp(stack)]
        stream = _stream()
        got: list[bytes] = []
        for i in range(0, len(stream), 10):  # bursts, each read out before the next
            burst = stream[i:i + 10]
            for who, data in burst:
                senders[who].sendto(data, vin.address)
            got += [gcs.recv(65536) for _, d in burst if not _command(d)]
        wait_for(lambda: vout.stats()["tx_frames"] == len(got), 5)
        counters = {"router": router.stats.as_dict(), "in": vin.stats(), "out": vout.stats(),
                    "peers": list(vin.port.peers), "in_engine": vin.engine.stats_dict(),
                    "out_engine": vout.engine.stats_dict()}
        return got, counters, vin.engine.lane_runs


@needs_lane
def test_the_lane_routes_a_stream_as_the_python_path_does(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Byte for byte, in order, with the same counters: the general path's cases (a new
    source, a targeted message, a second sender) handed back and the stream going on."""
    got_py, counters_py, runs_py = _run(False, monkeypatch)
    got_lane, counters_lane, runs_lane = _run(True, monkeypatch)
    assert runs_py == 0 and runs_lane > 0
    sent = [d for _, d in _stream() if not _command(d)]
    assert got_py == sent and got_lane == sent
    for c in (counters_py, counters_lane):  # (the peers' ports differ between the runs)
        assert len(c.pop("peers")) == 2
    assert counters_lane == counters_py
    assert counters_lane["out"]["tx_frames"] == len(sent)
    assert counters_lane["router"]["forwarded"] >= len(sent)


@needs_lane
def test_the_loop_answers_calls_and_timers_while_a_stream_keeps_the_lane_busy(
        stack: contextlib.ExitStack) -> None:
    """The lane waits on the loop's own descriptor and until its next timer: a call from
    another thread and a timer set meanwhile run at once, not when the stream pauses (which
    here is never: a lane deaf to them fails the waits; one that only met them at its 0.5 s
    cap fails the bounds, which leave room for a loaded machine)."""
    gcs = udp(stack)
    gcs.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
    _router, vin, _vout = udp_route(stack, gcs)
    vehicle = udp(stack)
    frames = [d for who, d in _stream()[:600]]
    stop = threading.Event()

    def stream() -> None:  # bursts of 5 every millisecond, until the test ends
        i = 0
        while not stop.is_set():
            for _ in range(5):
                vehicle.sendto(frames[i % len(frames)], vin.address)
                i += 1
            time.sleep(0.001)

    def drain() -> None:
        gcs.settimeout(0.2)
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                gcs.recv(65536)

    threads = [threading.Thread(target=stream), threading.Thread(target=drain)]
    stack.callback(lambda: [t.join(5) for t in threads])
    stack.callback(stop.set)
    for t in threads:
        t.start()
    loop = vin.engine.loop
    wait_for(lambda: vin.engine.lane_runs > 0, 5)
    for _ in range(5):
        ran = threading.Event()
        t0 = time.monotonic()
        loop.call_soon(ran.set)
        assert ran.wait(5)
        assert time.monotonic() - t0 < 0.25  # (the lane's own wait ends at 0.5 s at most)
        timer = threading.Event()
        t0 = time.monotonic()
        loop.call_later(0.02, timer.set)
        assert timer.wait(5)
        assert 0.02 <= time.monotonic() - t0 < 0.27
    assert vin.engine.lane_runs > 0


@needs_lane
def test_after_the_loops_timers_the_lane_goes_on_without_the_ports_own_path(
        stack: contextlib.ExitStack, monkeypatch: pytest.MonkeyPatch) -> None:
    """A timer due ends the lane's wait (a router ticks 50 times a second); after it the lane
    starts again with the port still unwatched — not through a wake-up on the port and a
    read by its own path, which is what each tick cost before (one read of the port's path
    per tick: a Python path fails the bound)."""
    reads = [0]
    real = UdpPort.read_many

    def counted(self: UdpPort) -> list[bytes]:  # the port's own path, counted
        reads[0] += 1
        return real(self)

    monkeypatch.setattr(UdpPort, "read_many", counted)
    gcs = udp(stack)
    _router, vin, _vout = udp_route(stack, gcs)
    ticks = [0]
    timer = vin.engine.loop.call_every(0.005, lambda: ticks.__setitem__(0, ticks[0] + 1))
    stack.callback(timer.cancel)
    vehicle = udp(stack)
    frames = [d for who, d in _stream()[:600] if who == 0]  # system 1 only: the lane's path
    sent = 0
    end = time.monotonic() + 0.5
    while time.monotonic() < end or ticks[0] < 40:
        for _ in range(5):
            vehicle.sendto(frames[sent % len(frames)], vin.address)
            sent += 1
        for _ in range(5):
            gcs.recv(65536)  # (every datagram through: a lost one fails on the timeout)
        time.sleep(0.001)
    runs, n = vin.engine.lane_runs, reads[0]
    assert ticks[0] >= 40 and runs >= ticks[0] // 2  # the lane anew after each tick
    assert n < ticks[0] // 4, (n, ticks[0], runs)


def _refused_run(enabled: bool, monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """System 1's stream in bursts to a ground station that has gone (its port closed):
    the out link's counters once every burst is through."""
    monkeypatch.setattr(lane_mod, "ENABLED", enabled)
    with contextlib.ExitStack() as stack:
        gcs = udp(stack)
        _router, vin, vout = udp_route(stack, gcs)
        vehicle = udp(stack)
        frames = [d for who, d in _stream()[:400] if who == 0]
        vehicle.sendto(frames[0], vin.address)  # (system 1 seen: the compiled path)
        gcs.recv(65536)
        gcs.close()
        for i in range(1, len(frames), 10):
            for d in frames[i:i + 10]:
                vehicle.sendto(d, vin.address)
            n = min(i + 10, len(frames))
            wait_for(lambda n=n: vout.stats()["tx_frames"] == n, 5)
        out = vout.stats()
        return {k: out[k] for k in ("tx_frames", "tx_bytes", "tx_refused", "tx_dropped",
                                    "tx_errors")}


@needs_lane
def test_a_ground_station_that_has_gone_is_counted_as_the_python_path_counts_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Each burst to a closed port is refused: the lane hands the short write back to the
    port (MmsgSocket.send goes on from it).  Every datagram is counted sent, as flush_batch
    counts it, and most as refused, as on the Python path (where the kernel's refusals
    land in a batch varies from run to run: the counts are compared as such)."""
    python = _refused_run(False, monkeypatch)
    reasons: list[int] = []
    real = lane_mod._lane

    def watched(*args: Any) -> Any:  # the real lane, its hand-backs noted
        got = real(*args)
        reasons.append(got[0])
        return got

    monkeypatch.setattr(lane_mod, "_lane", watched)
    lane = _refused_run(True, monkeypatch)
    assert 4 in reasons  # a short sendmmsg handed back
    for c in (python, lane):
        assert c["tx_frames"] == 399 + 1 and c["tx_bytes"] == 28 * c["tx_frames"]
        assert c["tx_dropped"] == c["tx_errors"] == 0
        assert c["tx_frames"] // 2 < c["tx_refused"] <= c["tx_frames"]


@needs_lane
def test_a_lane_that_cannot_watch_its_descriptors_fails_as_the_lane_not_the_port(
        tmp_path: Any) -> None:
    """epoll refuses a regular file: the lane raises RuntimeError (the port engine then turns
    the lane off and the port's own path goes on), not OSError (which the engine takes for a
    failed read, and reopens the port)."""
    import types

    from backends.mavlink import _route_speedups

    f = (tmp_path / "not-a-socket").open("wb")
    try:
        counters = types.SimpleNamespace()
        router = types.SimpleNamespace(stats=counters)
        with pytest.raises(RuntimeError, match=r"lane\(\): epoll_ctl: "):
            _route_speedups.lane(f.fileno(), 0, 1, f.fileno(), time.monotonic() + 1, None,
                                 (None,) * 10, (), counters, counters, counters, router,
                                 threading.RLock(), (), 0.001, 0.004, 4)
    finally:
        f.close()
