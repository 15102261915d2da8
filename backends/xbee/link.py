"""The XBee link's two roles (seed 004) as sans-I/O state machines: :class:`AirLink` (the
seed's "wing", the rocket's gateway, a backend) and :class:`GroundLink` (the seed's ground
station, a source).

No I/O, no threads, no clock: every call takes ``now`` (seconds, any monotonic origin, never
going back) and returns a list of *outputs* for the driver (the module code that speaks API
frames on a port engine):

* :class:`Send` ``(payload, power)``: set the module's PL to ``power`` (AT PL) if it is not
  there already, *then* transmit ``payload`` (a 0x10 frame).  The power bits of every packet in
  the payload equal ``power``, so the receiver knows what PL the packet left at.
* :class:`QueryRssi` ``(token)`` (ground only): a payload holding a PING arrived without an
  RSSI; ask the module for ``AT DB`` and hand the answer to :meth:`GroundLink.ping_rssi` with
  the token.  The link drops the reading if another payload was passed to ``on_packet`` in
  between (DB reports the *last* packet received, which is then no longer the ping) — so the
  driver must call ``on_packet`` for every 0x90 in the order the module reported them.  A
  driver that knows a payload's RSSI (an emulator, a 0x81 frame) passes it to ``on_packet``
  and no query is made.
* events for the gateway: :class:`RcCommand` (air: received servo values),
  :class:`gateway.model.SmUpdate` / :class:`gateway.model.Status` (ground: decoded telemetry),
  :class:`gateway.model.LinkStats` (ground: on every STATS packet).

Air rules (the seed's, and the issue's decisions):

* a command: its values become an :class:`RcCommand` (once per distinct ``(seq, values)``: a
  resend is not re-applied); an ACK of its sequence goes out, at the command's power, if the
  last ACK left more than ``ack_interval`` (200 ms) ago;
* every ``ping_interval`` (500 ms) a PING, its power cycling 0, 1, 2, 3, 4;
* every ``stats_interval`` (100 ms) a STATS at the PL of the last packet received (4 before
  anything was heard), holding the readings the driver last gave
  :meth:`AirLink.module_readings` (DB, ER, GD, TR, EA, DC) and the commands received;
* telemetry (SM update → 24-byte SmTelem, STATUS → 9-byte StatTelem) goes at the highest PL
  among the packets received in the last ``silence`` (500 ms) — the ground picks its PL as the
  lowest one whose pings (air → ground) arrive well, so its power bits say what reaches it;
  the highest, not the last, so one lucky packet at PL 0 while the ground alternates 0/4 does
  not send the downlink at PL 0 — and at 4 when nothing was heard for 500 ms: with no uplink
  the air has no idea what reaches the ground, and the rocket's telemetry is the one thing the
  link must not lose; maximum power carries it through a fade and lets the ground pick it up
  again first.

Grouping: every packet waits in one outbox with a deadline — ACK and PING now, telemetry
``telemetry_hold`` (20 ms) after it was queued, STATS ``stats_hold`` (50 ms, half its period)
after it fell due.  When any packet is due, every packet waiting *at the same power* leaves with
it, in queue order, packed by :func:`backends.xbee.packets.group` into payloads of at most
``max_payload`` bytes (set it from ``AT NP``; 100 by default).  So a STATS rides with the
next telemetry going out at its power, and an SM update and a STATUS produced together share
one RF packet; nothing waits more than its hold (plus the guard below).  A PING's payload goes
last and nothing follows it for ``ping_guard`` (50 ms): the ground's ``AT DB`` must be
answered before its module receives another packet, or the reading is discarded.

Ground rules:

* :meth:`GroundLink.set_servos` (sampled every 1–5 ms): on a change, store the values and bump
  the sequence — unless the current sequence has not gone out yet (the new values simply ride
  on it), or it is unacknowledged and the last ACK is older than ``ack_stale`` (500 ms): then
  the values change in place under the same sequence (the seed's "sauf si le dernier numéro
  d'acquittement reçu est trop ancien"; it keeps the 5-bit sequence from wrapping onto an old
  ACK while the link is down: at most one bump per send, ≤ 17 per 500 ms).  An ACK of a
  sequence that went out with different values over its resends cannot say which ones arrived:
  it refreshes the ACK time, and the values go again under a new sequence.
* a command goes out when the sequence is unacknowledged and the last send is ≥
  ``min_send_interval`` (30 ms) old; with nothing to deliver, a keep-alive (empty mask, new
  sequence, so it is acked) every ``keepalive_interval`` (150 ms).  A command carries every
  servo set so far (the whole state, at most 10 bytes): one packet that arrives makes the air's
  servos exact whatever was lost before it.
* TX power: alternately 0 and 4 (one packet each) while no ACK or PING was heard for
  ``silence`` (500 ms); otherwise the lowest level whose latest PING RSSI, no older than
  ``ping_expiry`` (5.5 s: two rotations of five pings plus one period of slack, so one lost
  ping — or one reading discarded because another packet beat the DB answer — does not move
  the power; two in a row do, until that level's next ping), is ≥ ``rssi_threshold_dbm``
  (−85 dBm); 4 if none is.  (A ping measures air → ground at that PL; the ground assumes the
  path is reciprocal.)

TX power in mW (:class:`gateway.model.LinkStats` carries whole mW): :data:`POWER_DBM_XBEE3`
is the Digi XBee 3 802.15.4 user guide's PL table (PL 0..4 = −5, −1, 2, 5, 8 dBm; the module
the spec's NP of 100 implies), :data:`POWER_DBM_XBEE3_PRO` the PRO's (−5, 3, 8, 15, 19 dBm);
:func:`power_mw` rounds to the nearest mW, at least 1 (0 would read as "off").

Lost packets are counted per type from the running sequence numbers (:func:`seq_gap`); a
silence longer than 32 packets of one type is counted modulo 32 (the 5-bit field cannot say
more).  The ground's :class:`~gateway.model.LinkStats` carries: ``rssi_dbm`` the air module's
DB (uplink), ``link_quality_pct`` commands the air counted received / commands sent over
``lq_window`` (1 s), ``tx_power_mw`` the ground's PL in use, ``downlink_rssi_dbm`` the STATS
payload's RSSI (or the fresh ping reading at its PL), ``downlink_link_quality_pct`` received /
(received + lost) STATS and telemetry over ``lq_window`` — pings are left out: most of those
sent at low PL are meant to be lost.

Malformed payloads are counted and the rest of the payload skipped (its packet lengths can no
longer be trusted); the packets before the bad one are kept.  Nothing here raises on received
bytes.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

from backends.xbee.packets import (
    MAX_PACKET,
    POWER_MAX,
    SERVO_MAX,
    SERVOS,
    Ack,
    Command,
    Packet,
    PacketError,
    Ping,
    SmTelemetry,
    Stats,
    StatusTelemetry,
    encode,
    group,
    iter_decode,
    next_seq,
    seq_gap,
)
from gateway.counters import Counters
from gateway.model import LinkStats, SmUpdate, Status

#: XBee 3 (802.15.4 / DigiMesh firmware) transmit power per PL 0..4, dBm (Digi user guide).
POWER_DBM_XBEE3: tuple[float, ...] = (-5.0, -1.0, 2.0, 5.0, 8.0)
#: XBee 3 PRO transmit power per PL 0..4, dBm (same table, PRO column).
POWER_DBM_XBEE3_PRO: tuple[float, ...] = (-5.0, 3.0, 8.0, 15.0, 19.0)

POWERS = tuple(range(POWER_MAX + 1))


def power_mw(level: int, table: Sequence[float] = POWER_DBM_XBEE3) -> int:
    """PL ``level``'s transmit power in whole mW (nearest, at least 1) from a dBm ``table``."""
    return max(1, round(10 ** (table[level] / 10)))


# -- outputs ----------------------------------------------------------------------------------

class Send(NamedTuple):
    """Transmit ``payload`` with the module's PL at ``power`` (set PL first if it differs)."""

    payload: bytes
    power: int


class QueryRssi(NamedTuple):
    """Ask the module for ``AT DB`` and pass the answer to :meth:`GroundLink.ping_rssi`."""

    token: int


class RcCommand(NamedTuple):
    """Servo values received by the air side (servo index 0..5 → 0..1023) and their sequence."""

    values: dict[int, int]
    seq: int


AirOutput = Send | RcCommand
GroundOutput = Send | QueryRssi | SmUpdate | Status | LinkStats


# -- shared pieces ----------------------------------------------------------------------------

def _decode_payload(data: bytes) -> tuple[list[Packet], bool]:
    """The packets of a payload and whether it was clean (False: the rest was skipped)."""
    out: list[Packet] = []
    try:
        for p in iter_decode(data):
            out.append(p)
    except PacketError:
        return out, False
    return out, bool(data)


class _Periodic:
    """A period on a fixed grid (no drift); a late caller skips missed slots, no burst."""

    def __init__(self, period: float) -> None:
        self.period = period
        self.next: float | None = None

    def due(self, now: float) -> bool:
        if self.next is None:
            self.next = now
        if now < self.next:
            return False
        self.next += self.period
        if self.next <= now:
            self.next += math.floor((now - self.next) / self.period + 1) * self.period
        return True


class _Item(NamedTuple):
    power: int
    chunk: bytes
    deadline: float
    kind: str


@dataclass
class LinkCounters(Counters):
    """What either end of the link counts of what it receives."""

    rx_payloads: int = 0
    rx_packets: int = 0
    malformed: int = 0
    unexpected: int = 0

    def decode(self, data: bytes) -> list[Packet]:
        """The packets of one received RF payload, counted: the payload, the packets, and
        the payload again as malformed when part of it was not a packet."""
        self.rx_payloads += 1
        packets, ok = _decode_payload(data)
        if not ok:
            self.malformed += 1
        self.rx_packets += len(packets)
        return packets


@dataclass
class AirCounters(LinkCounters):
    """What an :class:`AirLink` did; ``sent`` counts by packet kind (not in ``as_dict``)."""

    commands_rx: int = 0
    rc_commands: int = 0
    payloads_sent: int = 0
    bytes_sent: int = 0
    acks: int = 0
    pings: int = 0
    stats: int = 0
    telemetry: int = 0
    telemetry_dropped: int = 0
    sent: dict[str, int] = field(default_factory=dict)


_KIND_COUNTER = {"ack": "acks", "ping": "pings", "stats": "stats", "telemetry": "telemetry"}


class AirLink:
    """The air ("wing") side: acks, pings, stats and the telemetry downlink (module doc)."""

    def __init__(self, *, max_payload: int = 100, ack_interval: float = 0.2,
                 ping_interval: float = 0.5, stats_interval: float = 0.1,
                 silence: float = 0.5, stats_hold: float = 0.05,
                 telemetry_hold: float = 0.02, ping_guard: float = 0.05,
                 max_queued: int = 64) -> None:
        self.max_payload = max_payload
        self.ack_interval = ack_interval
        self.silence = silence
        self.stats_hold = stats_hold
        self.telemetry_hold = telemetry_hold
        self.max_queued = max_queued
        self.ping_guard = ping_guard
        self._quiet_until = -math.inf
        self.counters = AirCounters()
        self._ping = _Periodic(ping_interval)
        self._stats = _Periodic(stats_interval)
        self._ping_power = 0
        self._seqs = {"ping": 0, "stats": 0, "sm": 0, "status": 0}
        self._last_ack: float = -math.inf
        self._rx_power: int | None = None
        self._heard_at: dict[int, float] = {}  # PL → when a packet at it last arrived
        self._applied: tuple[int, int, tuple[int, ...]] | None = None
        self._outbox: list[_Item] = []
        self._rssi: int | None = None
        self._module: dict[str, int | None] = {
            "rx_errors": None, "good_packets": None, "tx_errors": None,
            "ack_failures": None, "duty_cycle_pct": None}

    @property
    def max_payload(self) -> int:
        """The largest RF payload sent (the module's NP)."""
        return self._max_payload

    @max_payload.setter
    def max_payload(self, value: int) -> None:
        if value < MAX_PACKET:
            raise ValueError(f"max_payload {value}: must be ≥ {MAX_PACKET} (the largest packet)")
        self._max_payload = value

    @property
    def stats_power(self) -> int:
        """The PL of the last packet received (4 before any): acks aside, what STATS use."""
        return POWER_MAX if self._rx_power is None else self._rx_power

    def telemetry_power(self, now: float) -> int:
        """The PL telemetry goes at: the highest PL heard within ``silence``, else 4."""
        heard = [p for p, t in self._heard_at.items() if now - t <= self.silence]
        return max(heard) if heard else POWER_MAX

    def module_readings(self, *, rssi_dbm: float | None = None,
                        rx_errors: int | None = None, good_packets: int | None = None,
                        tx_errors: int | None = None, ack_failures: int | None = None,
                        duty_cycle_pct: int | None = None) -> None:
        """Module readings (DB, ER, GD, TR, EA, DC) for the next STATS; None = unchanged."""
        if rssi_dbm is not None:
            self._rssi = max(-255, min(0, round(rssi_dbm)))
        given = {"rx_errors": rx_errors, "good_packets": good_packets, "tx_errors": tx_errors,
                 "ack_failures": ack_failures, "duty_cycle_pct": duty_cycle_pct}
        for name, value in given.items():
            if value is not None:
                hi = 100 if name == "duty_cycle_pct" else 0xFFFF
                self._module[name] = max(0, min(hi, value))

    def on_packet(self, data: bytes, rssi_dbm: float | None, now: float) -> list[AirOutput]:
        """One received RF payload (``rssi_dbm`` if the driver knows it)."""
        c = self.counters
        packets = c.decode(data)
        out: list[AirOutput] = []
        if packets and rssi_dbm is not None:
            self._rssi = max(-255, min(0, round(rssi_dbm)))
        for p in packets:
            self._rx_power = p.power
            self._heard_at[p.power] = now
            if isinstance(p, Command):
                self._on_command(p, now, out)
            else:
                c.unexpected += 1
        out.extend(self._flush(now))
        return out

    def _on_command(self, p: Command, now: float, out: list[AirOutput]) -> None:
        self.counters.commands_rx += 1
        key = (p.seq, p.mask, p.values)
        if p.mask and key != self._applied:
            self._applied = key
            self.counters.rc_commands += 1
            out.append(RcCommand(p.servos, p.seq))
        if now - self._last_ack > self.ack_interval:
            self._last_ack = now
            self._queue(Ack(p.seq, p.power), now, "ack")

    def sm_update(self, msg: SmUpdate, now: float) -> list[AirOutput]:
        """Queue an SM update for the downlink; returns what is due now."""
        power = self.telemetry_power(now)
        return self._telemetry(SmTelemetry.from_sm_update(msg, self._bump("sm"), power), now)

    def status(self, msg: Status, now: float) -> list[AirOutput]:
        """Queue a STATUS for the downlink; returns what is due now."""
        power = self.telemetry_power(now)
        return self._telemetry(StatusTelemetry.from_status(msg, self._bump("status"), power),
                               now)

    def _telemetry(self, packet: Packet, now: float) -> list[AirOutput]:
        queued = [i for i in self._outbox if i.kind == "telemetry"]
        if len(queued) >= self.max_queued:
            self._outbox.remove(queued[0])
            self.counters.telemetry_dropped += 1
        self._queue(packet, now + self.telemetry_hold, "telemetry")
        return self._flush(now)

    def tick(self, now: float) -> list[AirOutput]:
        """Call often (every ~10 ms): pings, stats, and whatever is due."""
        if self._ping.due(now):
            power = self._ping_power
            self._ping_power = (power + 1) % (POWER_MAX + 1)
            self._queue(Ping(self._bump("ping"), power), now, "ping")
        if self._stats.due(now):
            self._queue(Stats(self._bump("stats"), self.stats_power, self._rssi,
                              commands_rx=self.counters.commands_rx & 0xFFFF,
                              **self._module), now + self.stats_hold, "stats")
        return self._flush(now)

    def _bump(self, kind: str) -> int:
        seq = self._seqs[kind]
        self._seqs[kind] = next_seq(seq)
        return seq

    def _queue(self, packet: Packet, deadline: float, kind: str) -> None:
        self._outbox.append(_Item(packet.power, encode(packet), deadline, kind))

    def _flush(self, now: float) -> list[AirOutput]:
        if now < self._quiet_until:
            return []
        pinged = {i.power for i in self._outbox if i.kind == "ping"}
        due = sorted({i.power for i in self._outbox if i.deadline <= now},
                     key=lambda p: (p in pinged, p))  # the ping's payload goes last
        out: list[AirOutput] = []
        c = self.counters
        for power in due:
            items = sorted((i for i in self._outbox if i.power == power),
                           key=lambda i: i.kind == "ping")
            self._outbox = [i for i in self._outbox if i.power != power]
            if power in pinged:
                self._quiet_until = now + self.ping_guard
            for i in items:
                c.sent[i.kind] = c.sent.get(i.kind, 0) + 1
                attr = _KIND_COUNTER[i.kind]
                setattr(c, attr, getattr(c, attr) + 1)
            for payload in group((i.chunk for i in items), self.max_payload):
                c.payloads_sent += 1
                c.bytes_sent += len(payload)
                out.append(Send(payload, power))
        return out


# -- ground -----------------------------------------------------------------------------------

@dataclass
class GroundCounters(LinkCounters):
    """What a :class:`GroundLink` did; ``lost``/``received`` count by packet kind."""

    commands_sent: int = 0
    keepalives: int = 0
    acks_rx: int = 0
    acked: int = 0
    pings_rx: int = 0
    rssi_accepted: int = 0
    rssi_discarded: int = 0
    stats_rx: int = 0
    telemetry_rx: int = 0
    lost_total: int = 0
    received: dict[str, int] = field(default_factory=dict)
    lost: dict[str, int] = field(default_factory=dict)


class GroundLink:
    """The ground side: commands and keep-alives, power from ping RSSI, telemetry in."""

    def __init__(self, *, rssi_threshold_dbm: float = -85.0, min_send_interval: float = 0.03,
                 keepalive_interval: float = 0.15, silence: float = 0.5,
                 ack_stale: float = 0.5, ping_expiry: float = 5.5,
                 lq_window: float = 1.0,
                 power_dbm: Sequence[float] = POWER_DBM_XBEE3,
                 origin: str = "xbee", via: str = "") -> None:
        if len(power_dbm) != POWER_MAX + 1:
            raise ValueError(f"power_dbm: {POWER_MAX + 1} values (PL 0..{POWER_MAX}) needed")
        self.rssi_threshold_dbm = rssi_threshold_dbm
        self.min_send_interval = min_send_interval
        self.keepalive_interval = keepalive_interval
        self.silence = silence
        self.ack_stale = ack_stale
        self.ping_expiry = ping_expiry
        self.lq_window = lq_window
        self.power_dbm = tuple(power_dbm)
        self.origin = origin
        self.via = via
        self.counters = GroundCounters()
        self.values: dict[int, int] = {}
        self._seq = 0
        self._pending = False  # the current sequence is to be delivered
        self._keepalive = False  # the current sequence is a keep-alive (empty mask)
        # what went out under the current sequence: its first value set, and whether any send
        # carried another (two fields, not a set of every value set: in a blackout the
        # sticks can move for minutes under one unacknowledged sequence)
        self._sent_first: tuple[int, tuple[int, ...]] | None = None
        self._sent_mixed = False
        self._acked: int | None = None
        self._last_ack: float = -math.inf
        self._heard: float = -math.inf
        self._last_send: float = -math.inf
        self._first_send: dict[int, float] = {}
        self._latencies: deque[float] = deque(maxlen=64)
        self._alt = 0
        self._power_in_use: int | None = None
        self._time_at = [0.0] * (POWER_MAX + 1)
        self._clock: float | None = None
        self._readings: dict[int, tuple[float, float]] = {}  # power → (rssi, time)
        self._rx_token = 0
        self._ping_wait: dict[int, tuple[int, float]] = {}  # token → (power, time)
        self._last_seq: dict[str, int] = {}
        self._down: deque[tuple[float, int, int]] = deque()
        self._up: deque[tuple[float, int, int]] = deque()

    # -- state ------------------------------------------------------------------------------

    @property
    def seq(self) -> int:
        """The current command sequence."""
        return self._seq

    @property
    def acked_seq(self) -> int | None:
        """The sequence of the last ACK received (None before any)."""
        return self._acked

    @property
    def delivered(self) -> bool:
        """True when the current sequence is acknowledged."""
        return not self._pending

    @property
    def power_in_use(self) -> int | None:
        """The PL of the last packet sent (None before any)."""
        return self._power_in_use

    @property
    def time_at_power(self) -> tuple[float, ...]:
        """Seconds spent at each PL 0..4 (time between calls, charged to the PL in use)."""
        return tuple(self._time_at)

    @property
    def ack_latency_last(self) -> float | None:
        """Seconds from the first send of the last acked sequence to its ACK."""
        return self._latencies[-1] if self._latencies else None

    @property
    def ack_latency_median(self) -> float | None:
        """Median ACK latency over the last 64 acked sequences."""
        return statistics.median(self._latencies) if self._latencies else None

    def ping_readings(self, now: float) -> dict[int, float]:
        """PL → RSSI (dBm) of the latest ping at that PL, those not yet expired."""
        return {p: r for p, (r, t) in self._readings.items() if now - t <= self.ping_expiry}

    def heard(self, now: float) -> bool:
        """True when an ACK or PING arrived within ``silence``."""
        return now - self._heard <= self.silence

    def adequate_power(self, now: float) -> int:
        """The lowest PL whose fresh ping RSSI clears the threshold (4 if none does)."""
        readings = self.ping_readings(now)
        for p in POWERS:
            r = readings.get(p)
            if r is not None and r >= self.rssi_threshold_dbm:
                return p
        return POWER_MAX

    # -- inputs -----------------------------------------------------------------------------

    def set_servos(self, values: Mapping[int, int], now: float) -> list[GroundOutput]:
        """The sampled inputs (servo index 0..5 → 0..1023); a change becomes a command."""
        new = dict(self.values)
        for i, v in values.items():
            if not 0 <= i < SERVOS or not 0 <= v <= SERVO_MAX:
                raise ValueError(f"servo {i} = {v}: index 0..{SERVOS - 1}, value 0..{SERVO_MAX}")
            new[i] = v
        if new != self.values:
            self.values = new
            sent = self._sent_first is not None
            stale = now - self._last_ack > self.ack_stale
            if sent and not (self._pending and stale):
                self._bump(now)
            self._pending = True
            self._keepalive = False
        return self._step(now)

    def tick(self, now: float) -> list[GroundOutput]:
        """Call often (every ~10 ms): resends and keep-alives."""
        return self._step(now)

    def on_packet(self, data: bytes, rssi_dbm: float | None, now: float) -> list[GroundOutput]:
        """One received RF payload (``rssi_dbm`` if the driver knows it, else None)."""
        c = self.counters
        self._rx_token += 1
        self._ping_wait.clear()
        packets = c.decode(data)
        out: list[GroundOutput] = []
        for p in packets:
            if isinstance(p, Ack):
                self._on_ack(p, now)
            elif isinstance(p, Ping):
                self._count("ping", p.seq, now, quality=False)
                c.pings_rx += 1
                self._heard = now
                if rssi_dbm is not None:
                    self._reading(p.power, rssi_dbm, now)
                else:
                    self._ping_wait[self._rx_token] = (p.power, now)
                    out.append(QueryRssi(self._rx_token))
            elif isinstance(p, Stats):
                self._count("stats", p.seq, now)
                c.stats_rx += 1
                out.append(self._link_stats(p, rssi_dbm, now))
            elif isinstance(p, SmTelemetry):
                self._count("sm", p.seq, now)
                c.telemetry_rx += 1
                out.append(p.to_sm_update(self.origin, self.via))
            elif isinstance(p, StatusTelemetry):
                self._count("status", p.seq, now)
                c.telemetry_rx += 1
                out.append(p.to_status(self.origin, self.via))
            else:
                c.unexpected += 1
        out.extend(self._step(now))
        return out

    def ping_rssi(self, token: int, rssi_dbm: float, now: float) -> bool:
        """The ``AT DB`` answer for :class:`QueryRssi` ``token``; False (discarded) if another
        payload arrived since that ping."""
        wait = self._ping_wait.pop(token, None)
        if wait is None:
            self.counters.rssi_discarded += 1
            return False
        self._reading(wait[0], rssi_dbm, wait[1])
        return True

    # -- internals --------------------------------------------------------------------------

    def _reading(self, power: int, rssi: float, t: float) -> None:
        self.counters.rssi_accepted += 1
        self._readings[power] = (rssi, t)

    def _count(self, kind: str, seq: int, now: float, quality: bool = True) -> None:
        c = self.counters
        c.received[kind] = c.received.get(kind, 0) + 1
        prev = self._last_seq.get(kind)
        self._last_seq[kind] = seq
        lost = 0 if prev is None else seq_gap(prev, seq)
        c.lost[kind] = c.lost.get(kind, 0) + lost
        c.lost_total += lost
        if quality:
            self._down.append((now, 1, lost))
        while self._down and now - self._down[0][0] > self.lq_window:
            self._down.popleft()

    def _on_ack(self, p: Ack, now: float) -> None:
        c = self.counters
        c.acks_rx += 1
        self._heard = now
        self._last_ack = now
        self._acked = p.seq
        first = self._first_send.pop(p.seq, None)
        if first is not None:
            c.acked += 1
            self._latencies.append(now - first)
        if p.seq == self._seq and self._pending:
            servos = {} if self._keepalive else self.values
            now_sent = Command.from_servos(servos, self._seq, 0)
            if self._sent_mixed or self._sent_first != (now_sent.mask, now_sent.values):
                # the sequence went out with other values too (which arrived?), or only with
                # others (the sticks moved in place since): send these again
                self._bump(now)
            else:
                self._pending = False

    def _bump(self, now: float) -> None:
        self._seq = next_seq(self._seq)
        self._sent_first = None
        self._sent_mixed = False
        self._first_send.pop(self._seq, None)

    def _choose_power(self, now: float) -> int:
        if not self.heard(now):
            self._alt ^= 1
            return POWER_MAX if self._alt == 0 else 0
        return self.adequate_power(now)

    def _step(self, now: float) -> list[GroundOutput]:
        if self._clock is not None and self._power_in_use is not None and now > self._clock:
            self._time_at[self._power_in_use] += now - self._clock
        self._clock = now
        if now - self._last_send < self.min_send_interval:
            return []
        if not self._pending:
            if now - self._last_send < self.keepalive_interval:
                return []
            self._bump(now)
            self._pending = self._keepalive = True
        keepalive = self._keepalive
        if keepalive and self._sent_first is None:
            self.counters.keepalives += 1
        power = self._choose_power(now)
        servos = {} if keepalive else self.values
        cmd = Command.from_servos(servos, self._seq, power)
        if self._sent_first is None:
            self._sent_first = (cmd.mask, cmd.values)
        elif self._sent_first != (cmd.mask, cmd.values):
            self._sent_mixed = True
        self._first_send.setdefault(self._seq, now)
        for s in [s for s, t in self._first_send.items() if s != self._seq and now - t > 2.0]:
            del self._first_send[s]
        self._last_send = now
        self._power_in_use = power
        self.counters.commands_sent += 1
        return [Send(encode(cmd), power)]

    def _link_stats(self, p: Stats, rssi_dbm: float | None, now: float) -> LinkStats:
        w = self.lq_window
        while self._down and now - self._down[0][0] > w:
            self._down.popleft()
        rx = sum(n for _, n, _ in self._down)
        lost = sum(n for _, _, n in self._down)
        down_lq = round(100 * rx / (rx + lost)) if rx + lost else None
        self._up.append((now, p.commands_rx, self.counters.commands_sent))
        while len(self._up) > 2 and now - self._up[0][0] > w:
            self._up.popleft()
        up_lq: int | None = None
        if len(self._up) >= 2:
            _, rx0, sent0 = self._up[0]
            drx = (p.commands_rx - rx0) % 0x10000
            dsent = self.counters.commands_sent - sent0
            if dsent > 0:
                up_lq = min(100, round(100 * drx / dsent))
        if rssi_dbm is None:
            rssi_dbm = self.ping_readings(now).get(p.power)
        power = self._power_in_use
        return LinkStats(
            rssi_dbm=None if p.rssi_dbm is None else float(p.rssi_dbm),
            link_quality_pct=up_lq,
            tx_power_mw=None if power is None else power_mw(power, self.power_dbm),
            downlink_rssi_dbm=rssi_dbm,
            downlink_link_quality_pct=down_lq,
            origin=self.origin, via=self.via)


__all__ = [
    "POWER_DBM_XBEE3", "POWER_DBM_XBEE3_PRO", "AirCounters", "AirLink",
    "AirOutput", "GroundCounters", "GroundLink", "GroundOutput", "QueryRssi", "RcCommand",
    "Send", "power_mw",
]
