"""XBee link state machines (seed 004): an AirLink and a GroundLink joined by a simulated pair
of modules written here — a fake clock, per-power loss and RSSI, a delivery delay, ``AT DB``
answered from the last packet the ground module received, and blackout injection — plus unit
tests of each rule on its own.  Expectations come from the seed's rules and the simulation's
own tables (the settled power is computed from the RSSI table and the threshold), never from
a previous run's output."""

from __future__ import annotations

import heapq
import itertools
import math
import random
from dataclasses import dataclass, field
from typing import Any

import pytest

from backends.xbee.link import (
    POWER_DBM_XBEE3,
    POWER_DBM_XBEE3_PRO,
    AirLink,
    GroundLink,
    QueryRssi,
    RcCommand,
    Send,
    power_mw,
)
from backends.xbee.packets import (
    Ack,
    Command,
    Packet,
    Ping,
    SmTelemetry,
    Stats,
    StatusTelemetry,
    encode,
    iter_decode,
    next_seq,
)
from gateway.model import LinkStats, SmUpdate, Status

DT = 0.005  # the fake clock's step: both links are ticked every 5 ms
RSSI = (-95.0, -90.0, -84.0, -78.0, -72.0)  # dBm of a packet sent at PL 0..4
LOSS = (0.9, 0.6, 0.01, 0.0, 0.0)  # loss probability of a packet sent at PL 0..4
THRESHOLD = -85.0
#: The lowest PL whose RSSI clears the threshold: where the ground's power must settle.
EXPECTED_POWER = min(p for p, r in enumerate(RSSI) if r >= THRESHOLD)


def sm(i: int) -> SmUpdate:
    """The i-th SM update of a made-up climb (values not on the wire's grid)."""
    return SmUpdate(1000 + 50 * i, 3, True, 1, 12.34 * i + 0.017, 9.81 + 0.013 * i,
                    -0.023 * i, 30.07 + 0.011 * i, 0.123456, -0.654321, 1.5 + 0.0001 * i)


def status(i: int) -> Status:
    return Status(1000 + 1000 * i, 3, 1, Status.make_flags(armed=True, imu_ok=i % 2 == 0))


@dataclass
class Sim:
    """Two modules on a fake clock; records every send and event with its time."""

    seed: int = 1
    loss: tuple[float, ...] = LOSS
    rssi: tuple[float, ...] = RSSI
    delay: float = 0.004
    db_delay: float = 0.003
    blackout: tuple[float, float] = (math.inf, math.inf)
    max_payload: int = 100
    air: AirLink = field(init=False)
    ground: GroundLink = field(init=False)
    t: float = 0.0
    step: int = 0
    air_sends: list[tuple[float, Send]] = field(default_factory=list)
    ground_sends: list[tuple[float, Send]] = field(default_factory=list)
    air_events: list[tuple[float, Any]] = field(default_factory=list)
    ground_events: list[tuple[float, Any]] = field(default_factory=list)
    ground_log: list[Any] = field(default_factory=list)  # every ground output, in order
    readings: list[dict[int, float]] = field(default_factory=list)  # after each DB answer
    sm_sent: list[SmUpdate] = field(default_factory=list)
    status_sent: list[Status] = field(default_factory=list)
    db_rssi: float | None = None  # what the ground module's DB would answer

    def __post_init__(self) -> None:
        self.rng = random.Random(self.seed)
        self.air = AirLink(max_payload=self.max_payload)
        self.ground = GroundLink(rssi_threshold_dbm=THRESHOLD)
        self._heap: list[tuple[float, int, str, Any]] = []
        self._n = 0

    def _push(self, t: float, kind: str, arg: Any) -> None:
        self._n += 1
        heapq.heappush(self._heap, (t, self._n, kind, arg))

    def _radio(self, send: Send, kind: str) -> None:
        b0, b1 = self.blackout
        if b0 <= self.t < b1 or self.rng.random() < self.loss[send.power]:
            return
        rssi = self.rssi[send.power] + self.rng.uniform(-0.9, 0.9)
        self._push(self.t + self.delay, kind, (send.payload, rssi))

    def _air_out(self, outs: list[Any]) -> None:
        for o in outs:
            if isinstance(o, Send):
                self.air_sends.append((self.t, o))
                self._radio(o, "to_ground")
            else:
                self.air_events.append((self.t, o))

    def _ground_out(self, outs: list[Any]) -> None:
        self.ground_log.extend(outs)
        for o in outs:
            if isinstance(o, Send):
                self.ground_sends.append((self.t, o))
                self._radio(o, "to_air")
            elif isinstance(o, QueryRssi):
                self._push(self.t + self.db_delay, "db", o.token)
            else:
                self.ground_events.append((self.t, o))

    def run(self, until: float, servos: bool = True, servo_until: float = math.inf) -> None:
        while self.t < until - 1e-9:
            self.step += 1
            self.t = round(self.step * DT, 9)
            while self._heap and self._heap[0][0] <= self.t + 1e-12:
                _, _, kind, arg = heapq.heappop(self._heap)
                if kind == "to_ground":
                    self.db_rssi = arg[1]  # the module's DB now reports this packet
                    self._ground_out(self.ground.on_packet(arg[0], None, self.t))
                elif kind == "to_air":
                    self._air_out(self.air.on_packet(arg[0], arg[1], self.t))
                else:
                    assert self.db_rssi is not None
                    self.ground.ping_rssi(arg, self.db_rssi, self.t)
                    self.readings.append(self.ground.ping_readings(self.t))
            if self.step % 10 == 0:  # SM updates at 20 Hz, STATUS at 1 Hz
                msg = sm(len(self.sm_sent))
                self.sm_sent.append(msg)
                self._air_out(self.air.sm_update(msg, self.t))
            if self.step % 200 == 0:
                st = status(len(self.status_sent))
                self.status_sent.append(st)
                self._air_out(self.air.status(st, self.t))
            if servos and self.t < servo_until:  # sticks sampled every 5 ms, moving every 100
                k = self.step // 20
                self._ground_out(self.ground.set_servos(
                    {0: 500 + k % 7 * 40, 1: 512, 3: 1000 - k % 5 * 100}, self.t))
            self._air_out(self.air.tick(self.t))
            self._ground_out(self.ground.tick(self.t))


def packets_of(sends: list[tuple[float, Send]]) -> list[tuple[float, int, Packet]]:
    return [(t, s.power, p) for t, s in sends for p in iter_decode(s.payload)]


@pytest.fixture(scope="module")
def nominal() -> Sim:
    sim = Sim(seed=7)
    sim.run(8.0, servo_until=6.0)
    return sim


@pytest.fixture(scope="module")
def blackout() -> Sim:
    sim = Sim(seed=11, blackout=(5.0, 7.0))
    sim.run(13.0)
    return sim


# -- the simulated pair -----------------------------------------------------------------------

def test_every_packet_carries_the_power_it_is_sent_at(nominal: Sim, blackout: Sim) -> None:
    for sim in (nominal, blackout):
        for sends in (sim.air_sends, sim.ground_sends):
            for _, power, p in packets_of(sends):
                assert p.power == power


def test_telemetry_arrives_in_order_within_the_packet_resolution(nominal: Sim) -> None:
    got = [e for _, e in nominal.ground_events if isinstance(e, SmUpdate)]
    stats = [e for _, e in nominal.ground_events if isinstance(e, Status)]
    assert len(got) >= 0.9 * len(nominal.sm_sent)  # 1 % loss at the settled PL
    by_ts = {m.timestamp_ms: m for m in nominal.sm_sent}
    stamps = [m.timestamp_ms for m in got]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    for m in got:
        want = by_ts[m.timestamp_ms]
        assert (m.state, m.armed, m.sm_type) == (want.state, want.armed, want.sm_type)
        assert m.origin == "xbee"
        assert abs(m.altitude_m - want.altitude_m) <= 0.05 + 1e-9
        for name in ("velocity_mps", "acceleration_mps2", "accel_vert_mps2"):
            assert abs(getattr(m, name) - getattr(want, name)) <= 0.05 + 1e-9
        for name in ("roll_rad", "pitch_rad", "yaw_rad"):
            assert abs(getattr(m, name) - getattr(want, name)) <= 0.00005 + 1e-12
    sent_status = {s.timestamp_ms: s for s in nominal.status_sent}
    assert len(stats) >= len(sent_status) // 2
    assert [s.timestamp_ms for s in stats] == sorted(s.timestamp_ms for s in stats)
    for s in stats:
        assert s.fields() == sent_status[s.timestamp_ms].fields()


def test_acks_converge_and_the_air_holds_the_last_values(nominal: Sim) -> None:
    g = nominal.ground
    acked = [(t, p.seq) for t, _, p in packets_of(nominal.air_sends) if isinstance(p, Ack)]
    commands = [(t, p) for t, _, p in packets_of(nominal.ground_sends)
                if isinstance(p, Command)]
    t_last, last = [(t, p) for t, p in commands if p.mask][-1]  # the sticks' final values
    assert any(seq == last.seq and t_last <= t < t_last + 0.5 for t, seq in acked)
    # every keep-alive sequence sent after the sticks stopped was acked within 0.5 s
    for t0, p in commands:
        if 6.5 < t0 < 7.5:
            assert any(seq == p.seq and t0 <= t < t0 + 0.5 for t, seq in acked)
    rc = [e for _, e in nominal.air_events if isinstance(e, RcCommand)]
    assert rc and rc[-1].values == g.values
    assert g.counters.acked > 20
    median = g.ack_latency_median
    assert median is not None and 0 < median < 0.25  # acks are rate-limited to one per 200 ms
    # keep-alives kept coming after the sticks stopped (t ≥ 6 s): 100–200 ms apart
    late = [t for t, s in nominal.ground_sends if t > 6.5]
    gaps = [b - a for a, b in itertools.pairwise(late)]
    assert gaps and all(0.03 - 1e-9 <= gap <= 0.2 + 1e-9 for gap in gaps)
    keepalives = [p for t, _, p in packets_of(nominal.ground_sends)
                  if t > 6.5 and isinstance(p, Command)]
    assert all(p.mask == 0 for p in keepalives)
    seqs = [k for k, _ in itertools.groupby(p.seq for p in keepalives)]  # resends merged
    assert len(seqs) >= 5 and all(b == (a + 1) % 32 for a, b in itertools.pairwise(seqs))


def test_pings_every_500_ms_at_rotating_power(nominal: Sim) -> None:
    pings = [(t, power, p) for t, power, p in packets_of(nominal.air_sends)
             if isinstance(p, Ping)]
    assert len(pings) == 16  # 0.005 .. 7.505 s would be 16 slots within 8 s
    for (t0, _, a), (t1, _, b) in itertools.pairwise(pings):
        assert t1 - t0 == pytest.approx(0.5, abs=1e-6)
        assert b.power == (a.power + 1) % 5
        assert b.seq == (a.seq + 1) % 32
    assert [p.power for _, _, p in pings[:5]] == [0, 1, 2, 3, 4]


def test_stats_every_100_ms_at_the_last_received_power(nominal: Sim) -> None:
    stats = [(t, p) for t, _, p in packets_of(nominal.air_sends) if isinstance(p, Stats)]
    assert 79 <= len(stats) <= 80
    times = [t for t, _ in stats]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert all(0.05 - 1e-9 <= g <= 0.15 + 1e-9 for g in gaps)
    assert sum(gaps) / len(gaps) == pytest.approx(0.1, abs=0.002)
    # once the ground has settled, the air hears it at EXPECTED_POWER and answers there
    late_powers = [p.power for t, p in stats if t > 4.0]
    assert set(late_powers) <= {EXPECTED_POWER, EXPECTED_POWER + 1}
    assert late_powers.count(EXPECTED_POWER) >= 0.6 * len(late_powers)
    # the stats carry the RSSI the air module measured of the ground's packets
    # (the DB of the ground's last packet, whose PL the stats go at), rounded to 1 dB
    assert all(p.rssi_dbm is not None and abs(p.rssi_dbm - RSSI[p.power]) <= 0.9 + 0.5
               for t, p in stats if t > 4.0)
    # and some rode with telemetry in one payload
    shared = [s for t, s in nominal.air_sends
              if {type(p) for p in iter_decode(s.payload)} >= {Stats, SmTelemetry}]
    assert shared


def settled(sends: list[tuple[float, Send]], since: float) -> None:
    """From ``since`` on, the ground sends at EXPECTED_POWER, never below it, and above it only
    while a lost ping (1 % at that level) has let its reading expire (then for one rotation,
    2.5 s: a lost ping at the lowest adequate level is evidence it is marginal)."""
    powers = [s.power for t, s in sends if t >= since]
    assert powers and min(powers) == EXPECTED_POWER
    assert powers.count(EXPECTED_POWER) >= 0.6 * len(powers)


def test_ground_power_settles_on_the_lowest_adequate_level(nominal: Sim) -> None:
    settled(nominal.ground_sends, 4.0)
    readings = nominal.ground.ping_readings(nominal.t)
    for p, r in readings.items():
        assert abs(r - RSSI[p]) <= 0.9 + 1e-9
    assert nominal.ground.time_at_power[EXPECTED_POWER] > 0.6 * (nominal.t - 4.0)
    link = [e for t, e in nominal.ground_events if isinstance(e, LinkStats) and t > 4.0]
    in_use = None  # the PL of the ground's latest send
    for o in nominal.ground_log:
        if isinstance(o, Send):
            in_use = o.power
        elif isinstance(o, LinkStats):
            assert o.tx_power_mw == (None if in_use is None else power_mw(in_use))
    assert all(e.downlink_link_quality_pct is not None and e.downlink_link_quality_pct >= 80
               for e in link)


def test_blackout_alternates_0_and_4_then_recovers(blackout: Sim) -> None:
    g = blackout.ground
    during = [s.power for t, s in blackout.ground_sends if 5.6 <= t < 7.0]
    assert len(during) > 20
    assert set(during) == {0, 4}
    assert all(a != b for a, b in itertools.pairwise(during))
    # telemetry at full power while the air hears nothing
    assert {s.power for t, s in blackout.air_sends
            if 5.6 <= t < 7.0 and any(isinstance(p, SmTelemetry)
                                      for p in iter_decode(s.payload))} == {4}
    # after it: acks again, telemetry back within 3 s, power settled again
    acks = [t for t, _, p in packets_of(blackout.air_sends) if isinstance(p, Ack) and t >= 7.0]
    assert acks and acks[0] < 7.5
    tele = [t for t, e in blackout.ground_events if isinstance(e, SmUpdate) and t >= 7.0]
    assert tele and tele[0] < 10.0
    settled(blackout.ground_sends, 10.0)
    assert g.delivered or g.counters.acked > 0
    assert g.counters.lost.get("stats", 0) >= 15  # the 2 s blackout, counted by seq_gap


def test_a_late_db_answer_is_discarded_never_misattributed() -> None:
    sim = Sim(seed=5, db_delay=0.052)  # just past the air's 50 ms quiet time after a ping:
    # some answers come back after the next payload (discarded), some before (accepted)
    sim.run(6.0)
    c = sim.ground.counters
    assert c.rssi_discarded > 0 and c.rssi_accepted > 0
    assert len(sim.readings) == c.rssi_discarded + c.rssi_accepted
    for readings in sim.readings:  # every accepted reading is its own power's RSSI
        for p, r in readings.items():
            assert abs(r - RSSI[p]) <= 0.9 + 1e-9


def test_grouping_never_exceeds_max_payload() -> None:
    sim = Sim(seed=3, max_payload=30)
    sim.run(3.0)
    assert sim.air_sends
    assert all(len(s.payload) <= 30 for _, s in sim.air_sends)
    assert all(len(s.payload) <= 30 for _, s in sim.ground_sends)
    air = AirLink(max_payload=40)
    out = [o for i in range(10) for o in air.sm_update(sm(i), 0.0)] + air.tick(1.0)
    sends = [o for o in out if isinstance(o, Send)]
    assert all(len(s.payload) <= 40 for s in sends)
    got = [p.timestamp_ms for s in sends for p in iter_decode(s.payload)
           if isinstance(p, SmTelemetry)]
    assert got == [sm(i).timestamp_ms for i in range(10)]


# -- air rules --------------------------------------------------------------------------------

def cmd(seq: int, power: int, servos: dict[int, int] | None = None) -> bytes:
    return encode(Command.from_servos(servos or {}, seq, power))


def test_air_acks_at_the_commands_power_at_most_every_200_ms() -> None:
    air = AirLink()
    out = air.on_packet(cmd(5, 3, {2: 700}), -60.0, 10.0)
    assert RcCommand({2: 700}, 5) in out
    assert [list(iter_decode(s.payload)) for s in out if isinstance(s, Send)] == [[Ack(5, 3)]]
    assert [s.power for s in out if isinstance(s, Send)] == [3]
    again = air.on_packet(cmd(5, 3, {2: 700}), -60.0, 10.1)  # a resend: not re-applied
    assert again == []
    later = air.on_packet(cmd(6, 1, {2: 701}), -60.0, 10.201)
    assert RcCommand({2: 701}, 6) in later
    assert [(list(iter_decode(s.payload)), s.power) for s in later
            if isinstance(s, Send)] == [([Ack(6, 1)], 1)]
    assert air.counters.commands_rx == 3 and air.counters.acks == 2


def test_air_power_rules() -> None:
    air = AirLink()
    assert air.telemetry_power(0.0) == 4 and air.stats_power == 4  # nothing heard yet
    air.on_packet(cmd(0, 1), None, 1.0)
    assert air.telemetry_power(1.4) == 1 and air.stats_power == 1
    assert air.telemetry_power(1.6) == 4  # silent for 500 ms: full power
    assert air.stats_power == 1  # stats keep the last received packet's PL (the seed)
    air.on_packet(cmd(1, 4), None, 2.0)
    air.on_packet(cmd(1, 0), None, 2.1)  # the ground alternating 0/4
    assert air.stats_power == 0
    assert air.telemetry_power(2.2) == 4  # the highest heard in the last 500 ms
    assert air.telemetry_power(2.55) == 0


def test_stats_carry_module_values_and_commands_received() -> None:
    air = AirLink()
    air.module_readings(rx_errors=3, good_packets=70000, tx_errors=1, duty_cycle_pct=7)
    air.on_packet(cmd(0, 2) + cmd(1, 2), -71.4, 0.0)
    out = air.tick(0.0) + air.tick(0.06)
    stats = [p for o in out if isinstance(o, Send) for p in iter_decode(o.payload)
             if isinstance(p, Stats)]
    assert stats == [Stats(0, 2, -71, 3, 0xFFFF, 1, None, 7, 2)]


def test_malformed_payloads_are_counted_and_skipped() -> None:
    air = AirLink()
    ground = GroundLink()
    assert air.on_packet(b"\x45\x00", None, 0.0) == []
    out = air.on_packet(cmd(3, 2, {0: 9}) + b"\x41\x07", None, 0.0)  # power 7: bad
    assert RcCommand({0: 9}, 3) in out
    air.on_packet(b"", None, 0.0)
    assert air.counters.malformed == 3 and air.counters.rx_packets == 1
    ev = ground.on_packet(encode(Ping(0, 2)) + b"\x43\x00", -70.0, 0.0)
    assert ground.ping_readings(0.0) == {2: -70.0}
    assert not [e for e in ev if isinstance(e, SmUpdate)]
    ground.on_packet(b"\xff" * 5, None, 0.1)
    assert ground.counters.malformed == 2
    # both keep working: the air pings, the ground sends its keep-alive
    assert any(isinstance(p, Ping) for o in air.tick(1.0) if isinstance(o, Send)
               for p in iter_decode(o.payload))
    assert sent_commands(ground.tick(1.0))


# -- ground rules -----------------------------------------------------------------------------

def sent_commands(out: list[Any]) -> list[tuple[Command, int]]:
    return [(p, s.power) for s in out if isinstance(s, Send) for p in iter_decode(s.payload)
            if isinstance(p, Command)]


def test_ground_sequence_send_spacing_and_keepalive() -> None:
    g = GroundLink()
    first = sent_commands(g.set_servos({0: 0x123, 2: 0x234}, 0.0))
    assert [(c.seq, c.servos) for c, _ in first] == [(0, {0: 0x123, 2: 0x234})]
    assert g.set_servos({0: 0x124}, 0.01) == []  # < 30 ms since the last send
    assert g.seq == 0  # no ACK ever (stale): the values change in place
    resend = sent_commands(g.tick(0.03))
    assert [(c.seq, c.servos) for c, _ in resend] == [(0, {0: 0x124, 2: 0x234})]
    g.on_packet(encode(Ack(0, 0)), None, 0.04)  # seq 0 went out with two value sets:
    assert g.seq == 1 and not g.delivered  # they go again under a new sequence
    assert g.ack_latency_last == pytest.approx(0.04)
    again = sent_commands(g.tick(0.06))
    assert [(c.seq, c.servos) for c, _ in again] == [(1, {0: 0x124, 2: 0x234})]
    assert g.set_servos({0: 0x125}, 0.07) == []  # fresh ACK, seq 1 out: bump
    assert g.seq == 2
    g.set_servos({0: 0x126}, 0.08)  # seq 2 not out yet: the values ride on it
    assert g.seq == 2
    out = sent_commands(g.tick(0.09))
    assert [(c.seq, c.servos) for c, _ in out] == [(2, {0: 0x126, 2: 0x234})]
    g.on_packet(encode(Ack(2, 0)), None, 0.1)
    assert g.delivered and g.acked_seq == 2
    assert g.ack_latency_last == pytest.approx(0.01)
    assert g.tick(0.2) == []  # nothing to deliver, keep-alive not due
    ka = sent_commands(g.tick(0.09 + 0.15))
    assert [(c.seq, c.mask) for c, _ in ka] == [(3, 0)]
    assert not g.delivered


def test_ground_does_not_bump_while_acks_are_stale() -> None:
    g = GroundLink()
    g.set_servos({0: 1}, 0.0)
    g.on_packet(encode(Ack(0, 0)), None, 0.01)
    g.set_servos({0: 2}, 0.05)  # seq 1 out
    g.tick(0.1)
    assert g.seq == 1
    g.set_servos({0: 3}, 0.2)  # ack 190 ms old: bump
    assert g.seq == 2
    g.tick(0.3)
    g.set_servos({0: 4}, 0.6)  # ack 590 ms old and seq 2 unacked: in place
    assert g.seq == 2
    out = sent_commands(g.tick(0.7))
    assert [(c.seq, c.servos) for c, _ in out] == [(2, {0: 4})]
    # seq 2 went out with two different values: its ACK cannot say which; send them again
    g.on_packet(encode(Ack(2, 0)), None, 0.72)
    assert g.seq == 3 and not g.delivered
    assert [(c.seq, c.servos) for c, _ in sent_commands(g.tick(0.75))] == [(3, {0: 4})]
    g.on_packet(encode(Ack(3, 0)), None, 0.76)
    assert g.delivered


def test_an_ack_of_what_went_out_before_the_sticks_moved_does_not_deliver_them() -> None:
    """The sticks move in place (no ACK yet: stale) while a keep-alive is out and before the
    new values could go (< 30 ms): the keep-alive's ACK says nothing about them."""
    g = GroundLink()
    ka = sent_commands(g.tick(0.0))
    assert [c.mask for c, _ in ka] == [0]
    seq = g.seq
    assert g.set_servos({0: 5}, 0.01) == [] and g.seq == seq  # in place, not sent yet
    g.on_packet(encode(Ack(seq, 0)), None, 0.02)
    assert not g.delivered
    out = sent_commands(g.tick(0.05))
    assert [(c.seq, c.servos) for c, _ in out] == [(next_seq(seq), {0: 5})]
    g.on_packet(encode(Ack(next_seq(seq), 0)), None, 0.06)
    assert g.delivered


def test_sticks_moving_through_a_long_blackout_keep_the_ground_state_bounded() -> None:
    """No ACK for minutes while the pilot (or a ground station's RC override) moves the sticks:
    every new value set goes out in place under the one unacknowledged sequence, and what the
    ground keeps about them does not grow."""
    g = GroundLink()
    g.set_servos({0: 0}, 0.0)
    seq = g.seq
    t = 1.0  # the ACK is stale from here on
    for i in range(1, 3000):
        t += 0.04  # a new value set per send (30 ms apart at least)
        g.set_servos({0: i % 1024, 1: (i * 7) % 1024}, t)
    assert g.seq == seq  # in place: still the same sequence
    sizes = {k: len(v) for k, v in vars(g).items() if hasattr(v, "__len__")
             and not isinstance(v, (str, bytes, tuple))}
    assert max(sizes.values()) <= 64, sizes  # the latencies' deque is the largest
    # that sequence went out with many value sets: its ACK delivers none, the last goes again
    g.on_packet(encode(Ack(seq, 0)), None, t + 0.01)
    assert g.seq == next_seq(seq) and not g.delivered
    assert [c.servos for c, _ in sent_commands(g.tick(t + 0.05))] == [{0: 2999 % 1024,
                                                                      1: (2999 * 7) % 1024}]


def test_ground_power_choice_from_pings() -> None:
    g = GroundLink(rssi_threshold_dbm=-85.0)
    powers = [p for _, p in sent_commands(g.tick(0.0) + g.tick(0.2) + g.tick(0.4))]
    assert powers == [0, 4, 0]  # nothing heard: alternate
    for power, rssi in enumerate((-95.0, -88.0, -85.0, -70.0, -60.0)):
        g.on_packet(encode(Ping(power, power)), rssi, 0.5 + power * 0.01)
    assert g.adequate_power(0.6) == 2  # −85 clears a −85 threshold
    assert [p for _, p in sent_commands(g.tick(0.6))] == [2]
    # one lost ping does not move the power: readings live 5.5 s (two rotations + slack)
    assert g.adequate_power(5.9) == 2
    # then they expire; a later ping at 3 only
    g.on_packet(encode(Ping(5, 3)), -70.0, 5.9)
    assert g.adequate_power(6.03) == 3
    assert g.adequate_power(6.1) == 3
    assert g.heard(6.1) and not g.heard(6.5)


def test_ping_rssi_is_discarded_when_another_packet_came_between() -> None:
    g = GroundLink()
    out = g.on_packet(encode(Ping(0, 1)), None, 1.0)
    q = [o for o in out if isinstance(o, QueryRssi)]
    assert len(q) == 1
    g.on_packet(encode(Stats(0, 1)), None, 1.001)
    assert g.ping_rssi(q[0].token, -50.0, 1.002) is False
    assert g.ping_readings(1.002) == {}
    out = g.on_packet(encode(Ping(1, 3)), None, 2.0)
    (q2,) = [o for o in out if isinstance(o, QueryRssi)]
    assert g.ping_rssi(q2.token, -77.0, 2.003) is True
    assert g.ping_readings(2.003) == {3: -77.0}
    assert g.counters.rssi_discarded == 1 and g.counters.rssi_accepted == 1


def test_ground_counts_losses_and_reports_link_stats() -> None:
    g = GroundLink()
    g.tick(0.0)
    g.on_packet(encode(Stats(3, 2, -60, commands_rx=10)), -70.0, 0.1)  # sends after it
    sends = [o for t in (0.13, 0.16, 0.19) for o in g.tick(t) if isinstance(o, Send)]
    assert len(sends) == 3  # pending keep-alive resent every 30 ms
    ev = g.on_packet(encode(Stats(6, 2, -61, commands_rx=12)), -71.0, 0.2)  # 4, 5 lost
    (ls,) = [e for e in ev if isinstance(e, LinkStats)]
    assert g.counters.lost == {"stats": 2} and g.counters.lost_total == 2
    assert ls.rssi_dbm == -61.0 and ls.downlink_rssi_dbm == -71.0
    assert ls.downlink_link_quality_pct == round(100 * 2 / 4)
    # 2 commands received of 4 sent between the stats (at 0.1 after the stats, 0.13 … 0.19)
    assert ls.link_quality_pct == round(100 * 2 / 4)
    assert g.power_in_use is not None
    assert ls.tx_power_mw == power_mw(g.power_in_use)
    tele = g.on_packet(encode(SmTelemetry.from_sm_update(sm(1), 0, 2))
                       + encode(StatusTelemetry.from_status(status(1), 0, 2)), None, 0.3)
    assert [type(e) for e in tele if not isinstance(e, Send)] == [SmUpdate, Status]


def test_power_in_mw_follows_the_digi_tables() -> None:
    # Digi XBee 3 802.15.4 user guide, PL table: XBee 3 −5/−1/2/5/8 dBm, PRO −5/3/8/15/19
    assert [power_mw(p) for p in range(5)] == [
        max(1, round(10 ** (d / 10))) for d in (-5, -1, 2, 5, 8)]
    assert power_mw(4, POWER_DBM_XBEE3_PRO) == 79 and power_mw(3, POWER_DBM_XBEE3_PRO) == 32
    assert len(POWER_DBM_XBEE3) == 5
