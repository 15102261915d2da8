"""The XBee pair emulator (``tests/xbee_pair.py``) over real TCP sockets, spoken to with
:mod:`backends.xbee.frames` in API 1, API 2 and mixed: AT commands, transmit/receive, loss per
power level, blackout, oversize payloads, remote AT, garbage on the UART, pyserial URLs.

Expected values come from the emulator's specification (the issue and ``shared/specs/xbee.md``),
never from a run: loss is checked against the configured probability within a binomial
tolerance, and what arrives on one side is checked against what the other side was told.
"""

from __future__ import annotations

import itertools
import math
import random
import socket
import sys
import time
from collections.abc import Iterator

import pytest
import serial
from helpers import Running
from xbee_pair import ADDRESS_A, ADDRESS_B, XBeePair

from backends.xbee import frames as xf

DEADLINE_S = 5.0
RSSI = (-95, -90, -84, -78, -72)
FAST = 10_000_000  # bit/s: statistics tests need many packets, not a realistic air rate
MODES = [(1, 1), (2, 2), (1, 2)]


class Host:
    """A host on one module's UART: a TCP client speaking API frames in ``api_mode``."""

    def __init__(self, port: int, api_mode: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=DEADLINE_S)
        self.api_mode = api_mode
        self.decoder = xf.FrameDecoder(api_mode)
        self.frames: list[xf.Frame] = []
        self._ids = itertools.cycle(range(1, 256))
        self.eof = False

    def close(self) -> None:
        self.sock.close()

    def next_id(self) -> int:
        return next(self._ids)

    def send(self, frame: xf.Frame) -> None:
        self.sock.sendall(xf.encode(frame, self.api_mode))

    def send_raw(self, data: bytes) -> None:
        self.sock.sendall(data)

    def recv(self, timeout: float = DEADLINE_S) -> xf.Frame:
        """The next frame from the module (fails after ``timeout``)."""
        deadline = time.monotonic() + timeout
        while not self.frames:
            left = deadline - time.monotonic()
            assert left > 0, "no frame from the module in time"
            self.sock.settimeout(left)
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            if not data:
                self.eof = True
                raise AssertionError("the module closed the connection")
            self.frames.extend(self.decoder.feed(data))
        return self.frames.pop(0)

    def expect(self, kind: type[xf.Frame]) -> xf.Frame:
        frame = self.recv()
        assert isinstance(frame, kind), f"expected {kind.__name__}, got {frame!r}"
        return frame

    def at(self, command: str, parameter: bytes = b"") -> xf.AtResponse:
        fid = self.next_id()
        self.send(xf.AtCommand(fid, command, parameter))
        resp = self.expect(xf.AtResponse)
        assert isinstance(resp, xf.AtResponse)
        assert (resp.frame_id, resp.command) == (fid, command)
        return resp

    def tx(self, dest64: int, data: bytes, options: int = 0) -> int:
        fid = self.next_id()
        self.send(xf.TransmitRequest(fid, dest64, data, options=options))
        return fid

    def tx_status(self, fid: int) -> xf.TransmitStatus:
        st = self.expect(xf.TransmitStatus)
        assert isinstance(st, xf.TransmitStatus)
        assert st.frame_id == fid
        return st

    def rx(self) -> xf.ReceivePacket:
        pkt = self.expect(xf.ReceivePacket)
        assert isinstance(pkt, xf.ReceivePacket)
        return pkt


def connect(port: int, api_mode: int) -> Host:
    """Connect and prove the module attached us (it answers an AT command)."""
    host = Host(port, api_mode)
    assert xf.decode_np(host.at("NP").value) >= 1
    return host


@pytest.fixture
def hosts() -> Iterator[list[Host]]:
    made: list[Host] = []
    yield made
    for h in made:
        h.close()


def open_pair(api_a: int = 1, api_b: int = 1, **kw: object) -> XBeePair:
    kw.setdefault("rssi", RSSI)
    kw.setdefault("seed", 14)
    return XBeePair(api_a, api_b, **kw).start()  # type: ignore[arg-type]


@pytest.fixture(params=MODES, ids=[f"api{a}-api{b}" for a, b in MODES])
def pair_hosts(request: pytest.FixtureRequest,
               hosts: list[Host]) -> Iterator[tuple[XBeePair, Host, Host]]:
    api_a, api_b = request.param
    with open_pair(api_a, api_b) as pair:
        a = connect(pair.module_a.port, api_a)
        b = connect(pair.module_b.port, api_b)
        hosts += [a, b]
        yield pair, a, b
        assert pair.internal_errors == 0, pair.last_internal_error


def test_addresses_urls_and_identity(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    pair, a, b = pair_hosts
    assert pair.module_a.address64 != pair.module_b.address64
    assert pair.url_a == f"socket://127.0.0.1:{pair.module_a.port}"
    for host, mod in ((a, pair.module_a), (b, pair.module_b)):
        sh, sl = host.at("SH"), host.at("SL")
        assert sh.ok and sl.ok
        assert (xf.at_int(sh.value) << 32) | xf.at_int(sl.value) == mod.address64
        ap = host.at("AP")
        assert ap.ok and xf.at_int(ap.value) == host.api_mode == mod.api_mode
        np_ = host.at("NP")
        assert np_.ok and xf.decode_np(np_.value) == 100
        dc = host.at("DC")
        assert dc.ok and 0 <= xf.at_int(dc.value) <= 100
        assert host.at("ZZ").status == xf.AT_INVALID_COMMAND
        assert host.at("NP", b"\x20").status == xf.AT_INVALID_PARAMETER  # read only


def test_at_power_level(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    pair, a, _ = pair_hosts
    assert xf.decode_pl(a.at("PL").value) == 4  # default
    assert a.at("PL", xf.pl_param(2)).ok
    assert xf.decode_pl(a.at("PL").value) == 2
    assert pair.module_a.pl == 2
    assert a.at("PL", b"\x05").status == xf.AT_INVALID_PARAMETER
    assert pair.module_a.pl == 2
    # frame id 0: applied, no response (the next response is the query's)
    a.send(xf.AtCommand(xf.NO_RESPONSE, "PL", xf.pl_param(0)))
    assert xf.decode_pl(a.at("PL").value) == 0
    assert pair.module_b.pl == 4  # the other module is untouched


def test_db_before_any_packet_is_an_error(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    _, a, _ = pair_hosts
    assert a.at("DB").status == xf.AT_ERROR


def test_unicast_and_broadcast_delivery(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    pair, a, b = pair_hosts
    data = b"\x7e\x7d\x11\x13 escapable bytes"
    fid = a.tx(ADDRESS_B, data)
    pkt = b.rx()
    assert pkt == xf.ReceivePacket(ADDRESS_A, xf.UNKNOWN_16, xf.RX_ACKED, data)
    st = a.tx_status(fid)
    assert st.delivery == xf.DELIVERY_SUCCESS
    # broadcast, the other way
    fid = b.tx(xf.BROADCAST_64, b"ping")
    assert a.rx() == xf.ReceivePacket(ADDRESS_B, xf.UNKNOWN_16, xf.RX_BROADCAST, b"ping")
    assert b.tx_status(fid).delivery == xf.DELIVERY_SUCCESS
    # unicast without MAC ack: not flagged acked
    fid = a.tx(ADDRESS_B, b"x", options=xf.TX_DISABLE_ACK)
    assert b.rx().options == 0
    assert a.tx_status(fid).ok
    assert pair.module_a.tx_sent[4] == pair.module_a.tx_delivered[4] == 2
    assert pair.module_b.tx_sent[4] == pair.module_b.tx_delivered[4] == 1
    assert xf.decode_counter(b.at("GD").value) == 2
    assert xf.decode_counter(a.at("GD").value) == 1


def test_db_is_the_rssi_of_the_last_packet_at_the_senders_power(
        pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    pair, a, b = pair_hosts
    for level in (4, 1, 0, 3):
        assert a.at("PL", xf.pl_param(level)).ok
        fid = a.tx(ADDRESS_B, b"d")
        b.rx()
        a.tx_status(fid)
        assert xf.decode_db(b.at("DB").value) == RSSI[level]
    assert a.at("DB").status == xf.AT_ERROR  # A has still received nothing
    pair.set_rssi((-60, -59, -58, -57, -56))
    fid = b.tx(ADDRESS_A, b"e")  # B at its default PL 4
    a.rx()
    b.tx_status(fid)
    assert xf.decode_db(a.at("DB").value) == -56


def test_frame_id_zero_gets_no_transmit_status(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    _, a, b = pair_hosts
    a.send(xf.TransmitRequest(xf.NO_RESPONSE, ADDRESS_B, b"silent"))
    assert b.rx().data == b"silent"  # resolved: a status would now be on its way to A
    assert a.at("PL").ok  # the next frame A gets is this answer, no 0x8B before it
    assert not a.frames


def test_oversize_payload_refused(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    pair, a, b = pair_hosts
    fid = a.tx(ADDRESS_B, bytes(101))
    assert a.tx_status(fid).delivery == 0x74
    assert sum(pair.module_a.tx_sent) == 0
    fid = a.tx(ADDRESS_B, bytes(range(100)))  # exactly NP: fine
    assert b.rx().data == bytes(range(100))  # the first thing B got
    assert a.tx_status(fid).ok


def test_unknown_and_own_address(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    pair, a, _ = pair_hosts
    fid = a.tx(0x0013A200DEADBEEF, b"?")
    assert a.tx_status(fid).delivery == 0x24
    fid = a.tx(ADDRESS_A, b"?")
    assert a.tx_status(fid).delivery == 0x23
    assert sum(pair.module_a.tx_sent) == 0
    assert xf.decode_counter(a.at("TR").value) == 2


def test_remote_at_power_level(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    pair, a, b = pair_hosts
    fid = a.next_id()
    a.send(xf.RemoteAtCommand(fid, ADDRESS_B, "PL", xf.pl_param(1)))
    resp = a.expect(xf.RemoteAtResponse)
    assert isinstance(resp, xf.RemoteAtResponse)
    assert (resp.frame_id, resp.src64, resp.command, resp.status) == (fid, ADDRESS_B, "PL", 0)
    assert pair.module_b.pl == 1
    assert xf.decode_pl(b.at("PL").value) == 1
    assert pair.module_a.pl == 4
    # query it remotely; the answer went out at B's new level
    fid = a.next_id()
    a.send(xf.RemoteAtCommand(fid, ADDRESS_B, "PL"))
    resp = a.expect(xf.RemoteAtResponse)
    assert isinstance(resp, xf.RemoteAtResponse)
    assert resp.ok and xf.decode_pl(resp.value) == 1
    answers = [e for e in pair.event_list() if e.kind == "remote_at_response"]
    assert [e.power for e in answers] == [1, 1]
    assert xf.decode_db(a.at("DB").value) == RSSI[1]
    # an address that is not the other module, and a request during a blackout
    fid = a.next_id()
    a.send(xf.RemoteAtCommand(fid, 0x0013A200DEADBEEF, "PL", xf.pl_param(0)))
    resp = a.expect(xf.RemoteAtResponse)
    assert isinstance(resp, xf.RemoteAtResponse) and resp.status == xf.AT_TX_FAILURE
    pair.set_blackout(True)
    fid = a.next_id()
    a.send(xf.RemoteAtCommand(fid, ADDRESS_B, "PL", xf.pl_param(3)))
    resp = a.expect(xf.RemoteAtResponse)
    assert isinstance(resp, xf.RemoteAtResponse) and resp.status == xf.AT_TX_FAILURE
    assert pair.module_b.pl == 1  # never arrived


def test_blackout_drops_both_ways_then_recovers(pair_hosts: tuple[XBeePair, Host, Host]) -> None:
    pair, a, b = pair_hosts
    pair.set_blackout(True)
    assert pair.in_blackout
    for src, dst_addr in ((a, ADDRESS_B), (b, ADDRESS_A)):
        fid = src.tx(dst_addr, b"lost")
        assert src.tx_status(fid).delivery == 0x01  # MAC ACK failure
        fid = src.tx(xf.BROADCAST_64, b"lost too")
        assert src.tx_status(fid).ok  # broadcasts are never acked
    pair.set_blackout(False)
    for src, dst, dst_addr in ((a, b, ADDRESS_B), (b, a, ADDRESS_A)):
        fid = src.tx(dst_addr, b"back")
        assert dst.rx().data == b"back"  # nothing from the blackout arrived before it
        assert src.tx_status(fid).ok
    for mod in pair.modules:
        assert mod.tx_blackout[4] == 2 and mod.tx_delivered[4] == 1 and mod.tx_lost[4] == 0
        assert (mod.tr, mod.ea, mod.er) == (1, 1, 0)  # a blackout is silence, not errors
    reasons = [(e.src, e.reason) for e in pair.event_list()]
    assert reasons.count(("a", "blackout")) == reasons.count(("b", "blackout")) == 2


def test_timed_blackout_ends_by_itself(hosts: list[Host]) -> None:
    with open_pair(2, 2) as pair:
        a, b = connect(pair.module_a.port, 2), connect(pair.module_b.port, 2)
        hosts += [a, b]
        pair.blackout(0.5)
        fid = a.tx(ADDRESS_B, b"during")
        assert a.tx_status(fid).delivery == 0x01
        assert pair.wait(lambda: not pair.in_blackout, DEADLINE_S)
        fid = b.tx(ADDRESS_A, b"after")
        assert a.rx().data == b"after"
        assert b.tx_status(fid).ok
        fid = a.tx(ADDRESS_B, b"after")
        assert b.rx().data == b"after"
        assert a.tx_status(fid).ok


def _tolerance(p: float, n: int) -> float:
    return 4.5 * math.sqrt(p * (1 - p) / n) + 0.01


def test_loss_per_power_level(hosts: list[Host]) -> None:
    loss = (0.6, 0.3, 0.05, 0.0, 0.0)
    n = 400
    with open_pair(2, 1, loss=loss, bitrate=FAST, latency_s=0.0) as pair:
        a, b = connect(pair.module_a.port, 2), connect(pair.module_b.port, 1)
        hosts += [a, b]
        for level in (0, 1, 2, 3):
            assert a.at("PL", xf.pl_param(level)).ok
            payloads = [f"{level}:{i}".encode() for i in range(n)]
            fids = [a.tx(ADDRESS_B, p) for p in payloads]
            ok = {p for p, fid in zip(payloads, fids, strict=True)
                  if a.tx_status(fid).delivery == xf.DELIVERY_SUCCESS}
            got = set()
            for _ in range(len(ok)):
                got.add(b.rx().data)
            assert got == ok  # B received exactly what A was told was delivered
            observed = 1 - len(ok) / n
            assert abs(observed - loss[level]) <= _tolerance(loss[level], n), (level, observed)
            mod = pair.module_a
            assert mod.tx_sent[level] == n
            assert mod.tx_delivered[level] == len(ok)
            assert mod.tx_lost[level] == n - len(ok)
        lost = sum(pair.module_a.tx_lost)
        assert xf.decode_counter(a.at("TR").value) == lost
        assert xf.decode_counter(a.at("EA").value) == lost
        assert xf.decode_counter(b.at("ER").value) == lost
        events = [e for e in pair.event_list() if e.src == "a" and e.kind == "data"]
        assert len(events) == 4 * n
        assert sum(not e.delivered for e in events) == lost


def test_broadcast_loss_is_not_reported(hosts: list[Host]) -> None:
    n = 300
    with open_pair(1, 2, loss=(0.5, 0, 0, 0, 0), bitrate=FAST, latency_s=0.0) as pair:
        a, b = connect(pair.module_a.port, 1), connect(pair.module_b.port, 2)
        hosts += [a, b]
        assert a.at("PL", xf.pl_param(0)).ok
        fids = [a.tx(xf.BROADCAST_64, i.to_bytes(2, "big")) for i in range(n)]
        assert all(a.tx_status(fid).ok for fid in fids)
        delivered = pair.module_a.tx_delivered[0]
        assert abs((1 - delivered / n) - 0.5) <= _tolerance(0.5, n)
        marker = a.tx(ADDRESS_B, b"end")
        seen = [b.rx() for _ in range(delivered + 1)]
        assert seen[-1].data == b"end" and a.tx_status(marker).ok
        assert all(p.broadcast and p.src64 == ADDRESS_A for p in seen[:-1])
        assert [e.power for e in pair.event_list()][:n] == [0] * n


def test_rssi_noise_spreads_db(hosts: list[Host]) -> None:
    with open_pair(1, 1, bitrate=FAST, rssi_noise_db=3.0) as pair:
        a, b = connect(pair.module_a.port, 1), connect(pair.module_b.port, 1)
        hosts += [a, b]
        readings = []
        for _ in range(60):
            fid = a.tx(ADDRESS_B, b"n")
            b.rx()
            a.tx_status(fid)
            readings.append(xf.decode_db(b.at("DB").value))
        mean = sum(readings) / len(readings)
        assert abs(mean - RSSI[4]) < 2.0  # σ/√60 ≈ 0.4 dB
        assert len(set(readings)) > 3


@pytest.mark.parametrize("api_mode", [1, 2])
def test_garbage_counted_and_skipped(api_mode: int, hosts: list[Host]) -> None:
    with open_pair(api_mode, api_mode) as pair:
        a = connect(pair.module_a.port, api_mode)
        hosts.append(a)
        good = xf.encode(xf.AtCommand(9, "NP"), api_mode)
        a.send_raw(b"hello, no start byte here\x00\xff")
        a.send_raw(good[:-1] + bytes(((good[-1] + 1) & 0xFF,)))  # bad checksum
        a.send_raw(b"\x7e\x00\x00")  # length 0
        if api_mode == 2:
            a.send_raw(b"\x7e\x00\x04\x7d\x01")  # 0x7D then a byte that is no escape
        a.send_raw(xf.wrap(b"\x08\x05\xff\xfe", api_mode))  # an AT "command" of no letters
        a.send_raw(xf.encode(xf.ReceivePacket(1, 2, 0, b"?"), api_mode))  # not a host's frame
        assert xf.decode_np(a.at("NP").value) == 100
        st = pair.module_a.decoder_stats()
        assert st["crc_failures"] == 1 and st["bad_length"] == 1
        assert st.get("bad_escape", 0) == (1 if api_mode == 2 else 0)
        assert pair.module_a.uart_errors() == 2 + (api_mode == 2)
        assert pair.module_a.er == 0  # UART errors are not RF errors
        assert pair.module_a.ignored_frames == 2
        # random bytes (start bytes included), then enough zeros to end any frame they began
        rng = random.Random(api_mode)
        a.send_raw(bytes(rng.randrange(256) for _ in range(3000)) + bytes(600))
        fid = a.next_id()
        a.send(xf.AtCommand(fid, "PL"))
        while True:  # a random frame may have passed its checksum and been answered
            frame = a.recv()
            if isinstance(frame, xf.AtResponse) and frame.frame_id == fid:
                break
        assert frame.ok and xf.decode_pl(frame.value) in range(5)
        assert pair.module_a.uart_errors() > 2 + (api_mode == 2)
        assert pair.internal_errors == 0, pair.last_internal_error


def test_new_client_replaces_old_and_nothing_is_kept_for_a_late_one(hosts: list[Host]) -> None:
    with open_pair(1, 2) as pair:
        a1 = connect(pair.module_a.port, 1)
        hosts.append(a1)
        fid = a1.tx(ADDRESS_B, b"nobody listens")
        assert a1.tx_status(fid).ok  # B's radio got it; its UART has no host
        assert pair.wait(lambda: pair.module_b.dropped_no_client == 1, DEADLINE_S)
        a2 = connect(pair.module_a.port, 1)
        b = connect(pair.module_b.port, 2)
        hosts += [a2, b]
        with pytest.raises(AssertionError, match="closed"):
            a1.recv()
        assert pair.module_a.clients == 2
        fid = a2.tx(ADDRESS_B, b"now")
        assert b.rx().data == b"now"
        assert a2.tx_status(fid).ok


def test_pyserial_socket_url() -> None:
    with open_pair(2, 1) as pair:
        port = serial.serial_for_url(pair.url_a, timeout=DEADLINE_S)
        try:
            port.write(xf.encode(xf.AtCommand(3, "SL"), 2))
            dec = xf.FrameDecoder(2)
            got: list[xf.Frame] = []
            deadline = time.monotonic() + DEADLINE_S
            while not got and time.monotonic() < deadline:
                got += dec.feed(port.read(1) + port.read(port.in_waiting))
        finally:
            port.close()
        assert got == [xf.AtResponse(3, "SL", 0, (ADDRESS_A & 0xFFFFFFFF).to_bytes(4, "big"))]


def test_main_prints_urls_and_serves() -> None:
    proc = Running("tests/xbee_pair.py", "--api-a", "2", "--api-b", "2",
                   "--loss", "0.6,0.3,0.05,0,0", "--rssi=-95,-90,-84,-78,-72",
                   cmd=[sys.executable])
    try:
        assert proc.wait_line("stdout", lambda ln: ln.startswith("B socket://")), \
            proc.text("stderr")
        lines = proc.text("stdout").splitlines()
        url_a = next(ln.split()[1] for ln in lines if ln.startswith("A socket://"))
        host = Host(int(url_a.rsplit(":", 1)[1]), 2)
        try:
            assert xf.decode_pl(host.at("PL").value) == 4
        finally:
            host.close()
    finally:
        assert proc.stop() == 0


def test_a_packet_in_flight_keeps_its_power_and_dies_in_a_blackout(hosts: list[Host]) -> None:
    latency = 0.4
    with open_pair(1, 2, latency_s=latency) as pair:
        a, b = connect(pair.module_a.port, 1), connect(pair.module_b.port, 2)
        hosts += [a, b]
        assert a.at("PL", xf.pl_param(1)).ok
        fid = a.tx(ADDRESS_B, b"at PL 1")
        assert a.at("PL", xf.pl_param(4)).ok  # answered at once, long before the packet lands
        assert b.rx().data == b"at PL 1"
        assert a.tx_status(fid).ok
        assert xf.decode_db(b.at("DB").value) == RSSI[1]  # the power it went out at
        (event,) = pair.event_list()
        assert event.power == 1 and event.t_done - event.t_sent >= latency
        t0 = time.monotonic()
        fid = a.tx(ADDRESS_B, b"in flight")
        pair.set_blackout(True)
        assert time.monotonic() - t0 < latency  # the blackout began before it could land
        assert a.tx_status(fid).delivery == 0x01
        assert pair.module_a.tx_blackout[4] == 1


def test_duty_cycle_is_the_airtime_of_the_last_second(hosts: list[Host]) -> None:
    bitrate, size, count = 80_000, 100, 10
    with open_pair(1, 1, bitrate=bitrate, latency_s=0.0) as pair:
        a, b = connect(pair.module_a.port, 1), connect(pair.module_b.port, 1)
        hosts += [a, b]
        fids = [a.tx(ADDRESS_B, bytes(size)) for _ in range(count)]
        for fid in fids:
            assert a.tx_status(fid).ok
        # 802.15.4 frame: 6 B PHY header + 21 B MAC header (64-bit addresses) + 2 B FCS
        airtime = count * (size + 6 + 21 + 2) * 8 / bitrate
        assert xf.at_int(a.at("DC").value) == round(100 * airtime)
        assert [b.rx().data for _ in range(count)] == [bytes(size)] * count
        assert xf.at_int(b.at("DC").value) == 0  # B sent nothing
