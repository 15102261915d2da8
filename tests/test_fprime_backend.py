"""The F´ backend on real TCP sockets, read with fprime-gds's own deframers: every peer gets
the packets of every message in both framings, the ground's uplink is read and counted, a
peer that does not read stalls nobody, bad options are refused with the key named."""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from fprime_gds.common.communication.ccsds.chain import SpacePacketSpaceDataLinkFramerDeframer
from fprime_gds.common.communication.framing import FpFramerDeframer
from helpers import wait_for

from backends.fprime.backend import FprimeBackend
from backends.fprime.channels import codecs
from backends.fprime.commands import NO_OP, NO_OP_RECEIVED, NOT_SUPPORTED
from backends.fprime.options import FprimeOptions
from backends.fprime.packets import FW_PACKET_LOG, TlmPacker
from dialects.states import SimpleState
from gateway import config
from gateway.backend import STATS_KEYS, GatewayContext, Outcome
from gateway.config import ConfigError
from gateway.dispatcher import Dispatcher
from gateway.model import Battery, LinkStats, Position, SmUpdate, Status

FRAMINGS = ("ccsds", "fprime")
KEEPALIVE = b"sitting well"  # what fprime-gds's ip adapter sends up, unframed


def sm(t: int, altitude: float = 100.0) -> SmUpdate:
    return SmUpdate(timestamp_ms=t, state=SimpleState.BOOST, armed=True, sm_type=0,
                    altitude_m=altitude, acceleration_mps2=30.0, accel_vert_mps2=29.0,
                    velocity_mps=150.0, roll_rad=0.1, pitch_rad=-0.2, yaw_rad=1.5)


STATUS = Status(timestamp_ms=5, state=SimpleState.BOOST, sm_type=0,
                flags=Status.make_flags(armed=True, imu_ok=True, baro_ok=True))


def ground_deframer(framing: str) -> Any:
    if framing == "ccsds":
        return SpacePacketSpaceDataLinkFramerDeframer(scid=None, vcid=1, frame_size=None)
    return FpFramerDeframer()


class Ground:
    """A ground system's socket: what arrives is deframed by fprime-gds's deframer."""

    def __init__(self, address: Any, framing: str, *, read: bool = True,
                 rcvbuf: int = 0) -> None:
        self.sock = socket.socket()
        if rcvbuf:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.connect(address)
        self.deframer = ground_deframer(framing)
        self.framing = framing
        self.packets: list[bytes] = []
        self.discarded = b""
        self.lock = threading.Lock()
        self.pending = b""
        self.thread = threading.Thread(target=self._read, daemon=True)
        if read:
            self.thread.start()

    def _read(self) -> None:
        while True:
            try:
                data = self.sock.recv(65536)
            except OSError:
                return
            if not data:
                return
            with self.lock:
                packets, self.pending, discarded = self.deframer.deframe_all(
                    self.pending + data, no_copy=False)
                self.packets.extend(packets)
                self.discarded += discarded

    def got(self) -> list[bytes]:
        with self.lock:
            return list(self.packets)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()


@pytest.fixture
def gateway(request: Any) -> Iterator[tuple[Dispatcher, FprimeBackend]]:
    d = Dispatcher()
    b = FprimeBackend(FprimeOptions(endpoints=["tcpin:127.0.0.1:0"], framing=request.param))
    b.attach(GatewayContext(emit=d.dispatch))
    d.add(b)
    d.start()
    try:
        yield d, b
    finally:
        d.close()


def dispatch_paced(d: Dispatcher, messages: list[Any], grounds: list[Ground]) -> None:
    """Dispatch ``messages``, letting the grounds catch up every 16 (a burst larger than a
    peer's queue, 64, would be dropped for it by design)."""
    for i, m in enumerate(messages):
        assert d.dispatch(m) is not Outcome.FAILED
        if i % 16 == 15:
            assert wait_for(lambda i=i: all(len(g.got()) > i - 16 for g in grounds))


def expected_packets(b: FprimeBackend, msg: Any, tag: tuple[int, int, int, int]) -> list[bytes]:
    entries = [e for codec, get in codecs(b.id_base)[type(msg)]
               if (e := codec.entry(get(msg), tag)) is not None]
    return TlmPacker(b.packer.buffer_size).pack(entries)


def time_tag(packet: bytes) -> tuple[int, int, int, int]:
    """The time tag of a packet's first entry (descriptor U16, id U32, then the tag)."""
    return struct.unpack_from(">HBII", packet, 6)


@pytest.mark.parametrize("gateway", FRAMINGS, indirect=True)
def test_every_peer_gets_every_message_as_fprime_gds_reads_it(gateway: Any) -> None:
    d, b = gateway
    grounds = [Ground(b.address(), b.framing) for _ in range(2)]
    try:
        assert wait_for(lambda: b.stats()["connected"] == 2)
        messages: list[Any] = [sm(t * 10, 100.0 + t) for t in range(300)]
        messages[50:50] = [STATUS, LinkStats(rssi_dbm=-70.0, link_quality_pct=98),
                           Position(47.1, 8.5, 420.0, satellites=9),
                           Battery(7.9, current_a=1.2, remaining_pct=80)]
        dispatch_paced(d, messages, grounds)
        # one packet per message (each fits a 512-byte buffer): wait for all of them
        assert wait_for(lambda: all(len(g.got()) == len(messages) for g in grounds))
        for g in grounds:
            got = g.got()
            for m, packet in zip(messages, got, strict=True):
                assert [packet] == expected_packets(b, m, time_tag(packet))
            assert g.discarded == b""
        st = b.stats()
        assert st["packets"] == len(messages) and st["dropped"] == 0 and st["errors"] == 0
        assert set(STATS_KEYS) <= set(st)
    finally:
        for g in grounds:
            g.close()


def command_packet(opcode: int) -> bytes:
    return struct.pack(">HI", 0, opcode) + b"\x01\x02"


def uplink_frame(framing: str, packet: bytes) -> bytes:
    if framing == "ccsds":  # fprime-gds's own TC framer (Space Packet in a TC frame)
        return bytes(SpacePacketSpaceDataLinkFramerDeframer(
            scid=None, vcid=1, frame_size=None).frame(packet))
    return bytes(FpFramerDeframer().frame(packet))


@pytest.mark.parametrize("gateway", FRAMINGS, indirect=True)
def test_commands_are_answered_with_events_and_telemetry_carries_on(
        gateway: Any, caplog: pytest.LogCaptureFixture) -> None:
    d, b = gateway
    g = Ground(b.address(), b.framing)
    try:
        assert wait_for(lambda: b.stats()["connected"] == 1)
        caplog.set_level(logging.WARNING, logger="backends.fprime.backend")
        no_op = b.id_base + NO_OP.offset
        up = (KEEPALIVE + b"\x00garbage" + uplink_frame(b.framing, command_packet(0x1234))
              + KEEPALIVE + uplink_frame(b.framing, command_packet(no_op))
              + uplink_frame(b.framing, command_packet(0x1234)))
        g.sock.sendall(up)
        assert wait_for(lambda: len(g.got()) == 3)
        # event packets: descriptor FW_PACKET_LOG, event id, time tag, the U32 arguments
        answers = [(*struct.unpack_from(">HI", p), p[17:]) for p in g.got()]
        not_supported = (FW_PACKET_LOG, b.id_base + NOT_SUPPORTED.offset,
                         struct.pack(">I", 0x1234))
        assert answers == [not_supported, (FW_PACKET_LOG, b.id_base + NO_OP_RECEIVED.offset,
                                           b""), not_supported]
        st = b.stats()
        assert st["commands"] == 3 and st["commands_not_supported"] == 2
        link = next(iter(st["links"].values()))
        assert link["uplink_frames"] == 3 and link["uplink_keepalives"] == 2
        assert link["uplink_garbage_bytes"] > 0 and link["uplink_corrupt_frames"] == 0
        assert st["crc_failures"] == 0
        # one warning for the burst, naming the first opcode (the second is counted)
        assert sum("0x1234" in r.getMessage() for r in caplog.records) == 1
        dispatch_paced(d, [sm(t) for t in range(20)], [g])
        assert wait_for(lambda: len(g.got()) == 23)
    finally:
        g.close()


@pytest.mark.parametrize("gateway", FRAMINGS, indirect=True)
def test_a_flood_of_distinct_opcodes_costs_a_few_lines_and_counts_everything(
        gateway: Any, caplog: pytest.LogCaptureFixture) -> None:
    _, b = gateway
    caplog.set_level(logging.WARNING, logger="backends.fprime.backend")
    n = 3000
    g = Ground(b.address(), b.framing)
    try:
        assert wait_for(lambda: b.stats()["connected"] == 1)
        bad = bytearray(uplink_frame(b.framing, command_packet(7)))
        bad[-1] ^= 0xFF  # a CRC failure, counted
        frames = [uplink_frame(b.framing, command_packet(0x20000000 + i)) for i in range(n)]
        g.sock.sendall(bytes(bad) + b"".join(frames))
        assert wait_for(lambda: b.stats()["commands_not_supported"] == n)
        st = b.stats()
        assert st["commands"] == n and st["crc_failures"] == 1
        # answered: every event names its opcode, all framed in a few frames
        assert wait_for(lambda: len(g.got()) == n)
        assert {struct.unpack_from(">I", p, 17)[0] for p in g.got()} == \
            {0x20000000 + i for i in range(n)}
    finally:
        g.close()
    lines = [r.getMessage() for r in caplog.records if "not supported" in r.getMessage()]
    assert len(lines) == 1 and "0x20000000" in lines[0]  # the rest: one count per 10 s
    assert b.unsupported_log.events == n
    assert wait_for(lambda: b.stats()["clients"] == 0)
    assert b.stats()["crc_failures"] == 1  # a peer gone: its counts stay


@pytest.mark.parametrize("gateway", FRAMINGS, indirect=True)
def test_a_peer_that_never_reads_stalls_nobody(gateway: Any) -> None:
    d, b = gateway
    good = Ground(b.address(), b.framing)
    sink = Ground(b.address(), b.framing, read=False, rcvbuf=4096)
    try:
        assert wait_for(lambda: b.stats()["connected"] == 2)
        port = sink.sock.getsockname()[1]
        (link,) = [k for k in b.links if k.name.endswith(f":{port}>")]
        # the kernel would otherwise take megabytes for a peer that does not read
        link.engine.port.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        n = 2000  # far more than the sink's socket buffers and queue hold
        dispatch_paced(d, [sm(t) for t in range(n)], [good])  # it keeps up: loses nothing
        assert wait_for(lambda: len(good.got()) == n)
        stalled = next(v for k, v in b.stats()["links"].items() if k.endswith(f":{port}>"))
        assert stalled["dropped"] > 0 and b.stats()["dropped"] == stalled["dropped"]
    finally:
        good.close()
        sink.close()


@pytest.mark.parametrize("gateway", ["ccsds"], indirect=True)
def test_a_ground_system_that_leaves_and_comes_back_gets_a_fresh_stream(gateway: Any) -> None:
    d, b = gateway
    first = Ground(b.address(), b.framing)
    assert wait_for(lambda: b.stats()["connected"] == 1)
    for t in range(10):
        d.dispatch(sm(t))
    assert wait_for(lambda: len(first.got()) == 10)
    first.close()
    assert wait_for(lambda: b.stats()["clients"] == 0 and b.stats()["clients_closed"] == 1)
    assert d.dispatch(sm(99)) is not Outcome.FAILED  # nobody there: not ready, not an error
    again = Ground(b.address(), b.framing)  # a new deframer: counts start again for it
    try:
        assert wait_for(lambda: b.stats()["connected"] == 1)
        for t in range(10):
            d.dispatch(sm(t))
        assert wait_for(lambda: len(again.got()) == 10)
        assert b.stats()["sent"] == 20
    finally:
        again.close()


def test_options_are_checked_with_the_key_named() -> None:
    for table, key in (({"endpoints": ["udp:1.2.3.4:5"]}, "endpoints"),
                       ({"endpoints": ["tcpin::50000"], "framing": "ax25"}, "framing"),
                       ({"endpoints": ["tcpin::50000"], "id_base": -1}, "id_base"),
                       ({"endpoints": ["tcpin::50000"], "time_base": "tai"}, "time_base"),
                       ({"endpoints": ["tcpin::50000"], "scid": 0x400}, "scid")):
        with pytest.raises(ConfigError, match=f"backends.fprime.{key}"):
            config.parse({"backends": {"fprime": table}})


def test_run_flags_and_off_by_default() -> None:
    from gateway.commands.cli import build_parser, config_from_args

    assert FprimeBackend.EMBEDDED_DEFAULT is None
    assert "fprime" not in {p.name for p in config.embedded_default().backends}
    args = build_parser().parse_args(["run", "--fprime", "tcpin:127.0.0.1:50000",
                                      "--fprime-framing", "fprime"])
    parts = {p.name: p for p in config_from_args(args).backends}
    options = parts["fprime"].options
    assert options["endpoints"] == ["tcpin:127.0.0.1:50000"] and options["framing"] == "fprime"


def test_a_busy_port_refuses_the_start() -> None:
    from gateway.backend import BackendError

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        b = FprimeBackend(FprimeOptions(endpoints=[f"tcpin:127.0.0.1:{port}"]))
        with pytest.raises(BackendError, match=str(port)):
            b.init()
        b.close()
