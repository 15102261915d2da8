"""Many datagrams per system call (gateway.io.mmsg) and the router's batched path over it.

Every test that goes through a UDP port runs twice: with ``recvmmsg``/``sendmmsg`` (where the
platform has them) and with the plain one-datagram-per-call fallback, which must behave the
same: the same datagrams, in the same order, to the same peers."""

from __future__ import annotations

import contextlib
import functools
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import wait_for
from mavlink_peer import upstream_dialect

from backends.mavlink.endpoints import make_endpoint, parse_endpoint
from backends.mavlink.router import Router
from gateway.io import mmsg, port
from gateway.io.ioloop import IoLoop
from gateway.io.transport import open_udp

dev = upstream_dialect()
needs_mmsg = pytest.mark.skipif(not mmsg.AVAILABLE, reason="no recvmmsg/sendmmsg here")


@pytest.fixture(autouse=True, params=["compiled", "ctypes"])
def per_datagram(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Each test twice: the per-datagram work of recvmmsg/sendmmsg compiled
    (``_mmsg_speedups``) and in Python (ctypes only)."""
    if request.param == "compiled":
        if not mmsg.COMPILED:
            pytest.skip("the compiled helpers were not built")
    else:
        monkeypatch.setattr(mmsg, "_speedups", None)
    return str(request.param)


@pytest.fixture(params=["mmsg", "fallback"])
def mode(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    if request.param == "mmsg":
        if not mmsg.AVAILABLE:
            pytest.skip("no recvmmsg/sendmmsg here")
    else:
        monkeypatch.setattr(mmsg, "AVAILABLE", False)
    return str(request.param)


@pytest.fixture
def stack() -> Iterator[contextlib.ExitStack]:
    with contextlib.ExitStack() as s:
        yield s


def udp(stack: contextlib.ExitStack, family: int = socket.AF_INET,
        host: str = "127.0.0.1") -> socket.socket:
    s = stack.enter_context(socket.socket(family, socket.SOCK_DGRAM))
    s.bind((host, 0))
    s.settimeout(5.0)
    return s


def recv_all(sock: socket.socket, n: int) -> list[bytes]:
    return [sock.recv(65536) for _ in range(n)]


@needs_mmsg
def test_recvmmsg_reads_every_waiting_datagram_in_order_with_its_sender(
        stack: contextlib.ExitStack) -> None:
    rx = udp(stack)
    rx.setblocking(False)
    a, b = udp(stack), udp(stack)
    mm = mmsg.MmsgSocket(rx)
    assert mm.recv(True) == ([], None)  # nothing waiting: no error, nothing
    sent = []
    for i in range(mmsg.BATCH + 10):
        peer = a if i % 3 else b
        d = b"d%d" % i * (i % 7 + 1)
        peer.sendto(d, rx.getsockname())
        sent.append((d, peer.getsockname()))
    got: list[tuple[bytes, Any]] = []

    def read() -> bool:
        data, addrs = mm.recv(True)
        got.extend(zip(data, addrs or [], strict=True))
        return len(got) == len(sent)

    assert wait_for(read)
    assert got == sent
    big = bytes(range(256)) * 200  # far more than a MAVLink frame: read whole
    a.sendto(big, rx.getsockname())
    assert wait_for(lambda: (r := mm.recv(False))[0] and r[0] == [big])


@needs_mmsg
def test_recv_senders_gives_one_sender_per_run_of_datagrams(stack: contextlib.ExitStack
                                                             ) -> None:
    rx = udp(stack)
    rx.setblocking(False)
    a, b = udp(stack), udp(stack)
    mm = mmsg.MmsgSocket(rx)
    assert mm.recv_senders() == ([], [])
    order = [a, a, a, b, a, b, b]
    for i, peer in enumerate(order):
        peer.sendto(b"s%d" % i, rx.getsockname())
    data: list[bytes] = []
    senders: list[Any] = []

    def read() -> bool:
        d, s = mm.recv_senders()
        if d:
            data.extend(d)
            if senders and s and s[0] == senders[-1]:  # a run split across two reads
                s = s[1:]
            senders.extend(s)
        return len(data) == len(order)

    assert wait_for(read)
    assert data == [b"s%d" % i for i in range(len(order))]
    runs = [a, b, a, b]
    assert senders == [p.getsockname() for p in runs]


@needs_mmsg
def test_sendmmsg_writes_a_batch_in_order_to_a_connected_socket_or_a_destination(
        stack: contextlib.ExitStack) -> None:
    rx = udp(stack)
    tx = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    tx.connect(rx.getsockname())
    tx.setblocking(False)
    batch = [b"x%d" % i for i in range(150)]  # more than one sendmmsg's worth
    assert mmsg.MmsgSocket(tx).send(batch) == (0, 0, 0)
    assert recv_all(rx, len(batch)) == batch
    free = udp(stack)
    free.setblocking(False)
    assert mmsg.MmsgSocket(free).send([b"a", bytearray(b"b")], rx.getsockname()) == (0, 0, 0)
    assert recv_all(rx, 2) == [b"a", b"b"]


@needs_mmsg
def test_ipv6_senders_are_read_and_answered(stack: contextlib.ExitStack) -> None:
    try:
        rx = udp(stack, socket.AF_INET6, "::1")
    except OSError:
        pytest.skip("no IPv6 loopback")
    rx.setblocking(False)
    peer = udp(stack, socket.AF_INET6, "::1")
    mm = mmsg.MmsgSocket(rx)
    peer.sendto(b"v6", rx.getsockname())
    box: list[Any] = []
    assert wait_for(lambda: (r := mm.recv(True))[0] and box.append(r) is None)
    data, addrs = box[0]
    assert data == [b"v6"] and addrs == [peer.getsockname()]
    assert mm.send([b"back"], addrs[0]) == (0, 0, 0)
    assert peer.recvfrom(100) == (b"back", rx.getsockname())


@needs_mmsg
def test_a_refusal_reported_to_a_connected_socket_is_counted_and_the_rest_still_goes(
        stack: contextlib.ExitStack) -> None:
    gone = udp(stack)
    addr = gone.getsockname()
    gone.close()  # nobody listens there: the kernel answers "port unreachable"
    tx = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    tx.connect(addr)
    tx.setblocking(False)
    mm = mmsg.MmsgSocket(tx)
    refused = 0
    deadline = time.monotonic() + 5.0
    while refused == 0 and time.monotonic() < deadline:
        r, dropped, failed = mm.send([b"1", b"2", b"3"])
        refused += r
        assert (dropped, failed) == (0, 0)
    assert refused >= 1


@needs_mmsg
def test_a_batch_to_a_peer_that_is_not_listening_costs_two_calls_not_one_per_datagram(
        stack: contextlib.ExitStack) -> None:
    """Each datagram to a closed port comes back as "port unreachable", and sendmmsg stops
    after one datagram each call: the rest of the batch is counted refused after two such
    calls, and once the peer listens, a batch goes whole again."""
    gone = udp(stack)
    addr = gone.getsockname()
    gone.close()
    tx = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    tx.connect(addr)
    tx.setblocking(False)
    mm = mmsg.MmsgSocket(tx)
    compiled = mm._fast_send is not None
    real: Any = mm._fast_send if compiled else mm._send
    calls = [0]

    def counted(*args: Any) -> int:
        calls[0] += 1
        return int(real(*args))

    if compiled:
        mm._fast_send = counted
    else:
        mm._send = counted
    batch = [bytes([i]) * 20 for i in range(20)]
    for _ in range(3):
        calls[0] = 0
        refused, dropped, failed = mm.send(batch)
        assert (refused, dropped, failed) == (refused, 0, 0)
        assert refused >= 18, refused  # at most the first two calls' datagrams left
        assert calls[0] <= 3, calls[0]  # (one more when a refusal is reported as an error)
    rx = stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    rx.bind(addr)
    rx.settimeout(5.0)
    refused, dropped, failed = mm.send(batch)
    assert refused <= 1 and (dropped, failed) == (0, 0)  # one error may still be pending
    got = recv_all(rx, 20 - refused)
    assert got == batch[refused:]


def test_udp_port_reads_and_writes_batches_the_same_way_either_path(
        mode: str, stack: contextlib.ExitStack) -> None:
    listener = stack.enter_context(contextlib.closing(open_udp("127.0.0.1", 0, listen=True)))
    assert (listener.mmsg is not None) == (mode == "mmsg")
    assert listener.read_many() == []
    a, b = udp(stack), udp(stack)
    for i in range(20):
        (a if i < 10 else b).sendto(b"n%d" % i, listener.address())
    got: list[bytes] = []

    def read() -> bool:
        got.extend(listener.read_many())
        return len(got) == 20

    assert wait_for(read)
    assert got == [b"n%d" % i for i in range(20)]
    assert list(listener.peers) == [a.getsockname(), b.getsockname()]
    assert listener.new_peers == 2 and listener.last_peer == b.getsockname()
    listener.write_many([b"r1", b"r2"])  # to every peer, in order
    assert recv_all(a, 2) == [b"r1", b"r2"] and recv_all(b, 2) == [b"r1", b"r2"]
    out = stack.enter_context(contextlib.closing(
        open_udp("127.0.0.1", a.getsockname()[1], listen=False)))
    out.write_many([b"o%d" % i for i in range(100)])
    assert recv_all(a, 100) == [b"o%d" % i for i in range(100)]


def test_a_datagram_after_a_quiet_spell_is_not_held_back(mode: str) -> None:
    """The coalescing window only applies inside a stream: a lone datagram is read at once,
    and so is one in a stream (within about the window)."""
    loop = IoLoop("t")
    loop.start()
    arrived: list[float] = []
    done = threading.Event()

    class Proto:
        def feed_many(self, datagrams: list[bytes]) -> tuple[()]:
            arrived.extend(time.monotonic() for _ in datagrams)
            done.set()
            return ()

    eng = port.PortEngine(lambda: open_udp("127.0.0.1", 0, listen=True), name="udpin",
                          protocol=Proto(), loop=loop)  # type: ignore[arg-type]
    try:
        eng.start()
        assert eng.wait_connected(5.0)
        addr = eng._port.address()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            for _ in range(5):
                done.clear()
                t0 = time.monotonic()
                s.sendto(b"lone", addr)
                assert done.wait(5.0)
                # read on the wake-up, not after a window (a generous bound: a loaded CI)
                assert arrived[-1] - t0 < 0.25
                assert wait_for(lambda: not eng._holding)
                time.sleep(port.COALESCE_GAP_S * 2)  # a quiet spell (not synchronisation)
    finally:
        eng.close(1.0)
        loop.stop()
        loop.close()


def _frames(n: int) -> list[bytes]:
    m = dev.MAVLink(None, 1, 1)
    out = []
    for i in range(n):
        out.append(m.attitude_encode(i, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0).pack(m))
        m.seq = (m.seq + 1) & 0xFF
    return out


def udp_route(stack: contextlib.ExitStack, gcs: socket.socket) -> tuple[Router, Any, Any]:
    """A router on a loop of its own between ``udpin`` on an ephemeral port (the vehicle's
    side) and ``udpout`` to ``gcs``; all closed with ``stack``."""
    loop = IoLoop("router")
    loop.start()
    stack.callback(loop.close)
    stack.callback(loop.stop)
    router = Router()
    router.use_loop(loop)
    vin = make_endpoint(parse_endpoint("udpin:127.0.0.1:0"))
    vout = make_endpoint(parse_endpoint(f"udpout:127.0.0.1:{gcs.getsockname()[1]}"))
    for ep in (vin, vout):
        ep.start(loop, router)
        stack.callback(ep.close)
    return router, vin, vout


def test_the_router_forwards_a_stream_in_order_through_batches(
        mode: str, stack: contextlib.ExitStack) -> None:
    """A vehicle's stream into ``udpin`` comes out of ``udpout`` complete, in order, byte
    for byte, decoded by pymavlink (datagrams read and written in batches)."""
    gcs = udp(stack)
    router, vin, vout = udp_route(stack, gcs)
    vehicle = udp(stack)
    frames = _frames(2000)
    got: list[bytes] = []
    for i in range(0, len(frames), 100):  # bursts well within the socket's receive buffer
        for f in frames[i:i + 100]:
            vehicle.sendto(f, vin.address)  # type: ignore[attr-defined]
        got += recv_all(gcs, 100)
    assert got == frames
    parser = dev.MAVLink(None)
    msgs = [parser.decode(bytearray(g)) for g in got]
    assert [m.time_boot_ms for m in msgs] == list(range(len(frames)))
    st = vout.stats()
    assert st["tx_frames"] == len(frames) and st["tx_dropped"] == 0
    assert router.stats.forwarded == len(frames)
    # the reply path: the GCS answers; the vehicle (the udpin peer) gets it
    gcs_mav = dev.MAVLink(None, 255, 190)
    reply = gcs_mav.heartbeat_encode(6, 8, 0, 0, 0).pack(gcs_mav)
    gcs.sendto(reply, ("127.0.0.1", vout.port.sock.getsockname()[1]))  # type: ignore[attr-defined]
    assert vehicle.recv(65536) == reply


def test_a_udp_port_keeps_its_peers_in_order_of_their_latest_datagram(
        mode: str, stack: contextlib.ExitStack) -> None:
    """The peer table of ``udpin`` (whom it answers) follows each read's senders, also when a
    read's one sender is the one of the read before."""
    p = open_udp("127.0.0.1", 0, listen=True)
    stack.callback(p.close)
    a, b = udp(stack), udp(stack)
    got: list[bytes] = []

    def read(n: int) -> bool:
        got.extend(p.read_many())
        return len(got) == n

    for i, peer in enumerate([a, a, b, b, a]):
        peer.sendto(b"p%d" % i, p.address())
        assert wait_for(functools.partial(read, i + 1))
        assert p.last_peer == peer.getsockname()
    assert got == [b"p%d" % i for i in range(5)]
    assert list(p.peers) == [b.getsockname(), a.getsockname()]
    b.sendto(b"again", p.address())
    assert wait_for(lambda: p.read_many() == [b"again"])
    assert list(p.peers) == [a.getsockname(), b.getsockname()]


def test_a_router_failing_on_a_batch_is_counted_and_the_port_routes_on(
        mode: str, stack: contextlib.ExitStack, monkeypatch: pytest.MonkeyPatch) -> None:
    """What the router raises on is the protocol's fault, not the socket's: counted, that
    batch skipped, the port kept (not reopened) and the next datagrams forwarded."""
    gcs = udp(stack)
    router, vin, _ = udp_route(stack, gcs)
    routed = router.receive_many
    failures = [RuntimeError("a fault in the router")]

    def receive_many(link: Any, datagrams: list[bytes]) -> None:
        if failures:
            raise failures.pop()
        routed(link, datagrams)

    monkeypatch.setattr(router, "receive_many", receive_many)
    vehicle = udp(stack)
    frames = _frames(3)
    vehicle.sendto(frames[0], vin.address)  # type: ignore[attr-defined]
    engine = vin.engine  # type: ignore[attr-defined]
    assert wait_for(lambda: engine.stats.protocol_errors == 1)
    for f in frames[1:]:
        vehicle.sendto(f, vin.address)  # type: ignore[attr-defined]
    assert recv_all(gcs, 2) == frames[1:]
    st = engine.stats
    assert (st.connects, st.read_errors, st.protocol_errors) == (1, 0, 1)
