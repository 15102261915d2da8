"""Two gateways over an emulated XBee pair (``tests/xbee_pair.py``), as the issue runs them:

    air:    aurora-gateway run --source sim --xbee socket://… --xbee-api N
    ground: aurora-gateway run --source xbee:socket://… --xbee-api N --mavlink udpout:…

A pymavlink listener sees the flight (heartbeat, altitude rising, RADIO_STATUS), and its RC
override reaches the rocket (the air gateway's own MAVLink listener sees RC_CHANNELS with the
same values); the emulator's log of the
air shows the air's pings every ~500 ms cycling PL 0..4 and its stats every ~100 ms, the
ground's power settling on the lowest level whose RSSI clears the threshold, a 2 s blackout
bringing the ground's 0/4 alternation, and telemetry back within 3 s after it.  In API 1 and 2.
"""

from __future__ import annotations

import contextlib
import itertools
import statistics
import time
from collections.abc import Iterator
from typing import Any

import pytest
from helpers import Running
from mavlink_peer import MavPeer
from xbee_pair import AirEvent, XBeePair

from backends.xbee import packets as p

LOSS = (0.6, 0.3, 0.05, 0.0, 0.0)  # per power level 0..4
RSSI = (-95.0, -90.0, -84.0, -78.0, -72.0)
THRESHOLD = -85.0  # the ground's default
ADEQUATE = min(i for i, r in enumerate(RSSI) if r >= THRESHOLD)  # the level it must settle on


def types_in(payload: bytes) -> list[int]:
    """The packet types an RF payload holds (the link groups several)."""
    return [payload_type(pk) for pk in p.iter_decode(payload)]


def payload_type(packet: Any) -> int:
    return {p.Ack: p.TYPE_ACK, p.Ping: p.TYPE_PING, p.Stats: p.TYPE_STATS,
            p.SmTelemetry: p.TYPE_SM_TELEMETRY,
            p.StatusTelemetry: p.TYPE_STATUS_TELEMETRY}.get(type(packet), 0)


def pings(events: list[AirEvent]) -> list[tuple[float, int]]:
    """(time, power) of every PING the air sent (each carries the PL it left at)."""
    out = []
    for e in events:
        if e.src == "a" and e.kind == "data":
            for pk in p.iter_decode(e.payload):
                if isinstance(pk, p.Ping):
                    assert pk.power == e.power  # the power bits say what PL it left at
                    out.append((e.t_sent, pk.power))
    return out


@pytest.fixture
def gcs() -> Iterator[MavPeer]:
    with MavPeer(255, 190) as peer:
        yield peer


@pytest.mark.parametrize("api", [1, 2])
def test_two_gateways_over_an_xbee_pair(api: int, gcs: MavPeer) -> None:
    with contextlib.ExitStack() as stack:
        pair = stack.enter_context(XBeePair(api, api, loss=LOSS, rssi=RSSI, seed=7))
        on_board = stack.enter_context(MavPeer(255, 191))  # sees what the rocket was told
        air = Running("run", "--only", "xbee", "--only", "mavlink", "--source", "sim",
                      "--sim-speed", "4", "--xbee", pair.url_a, "--xbee-api", str(api),
                      "--mavlink", f"udpout:127.0.0.1:{on_board.port}",
                      "--status-interval", "0", timeout=60)
        stack.callback(air.stop)
        ground = Running("run", "--only", "mavlink", "--source", f"xbee:{pair.url_b}",
                         "--xbee-api", str(api), "--mavlink", f"udpout:127.0.0.1:{gcs.port}",
                         "--status-interval", "0", timeout=60)
        stack.callback(ground.stop)
        assert gcs.wait_for("HEARTBEAT", timeout=20), ground.text("stderr")[-2000:]

        # the flight reaches the ground station: altitude rising (sim at 4x: BOOST after ~4 s)
        def climbing() -> bool:
            alts = [m.altitude_relative for m in gcs.messages("ALTITUDE")]
            # the simulated rocket peaks near 33 m; rising = a climb of 10 m over the pad
            return len(alts) > 5 and alts[0] < 1.0 and max(alts) > 10.0

        assert gcs.wait_until(climbing, 30), (
            [m.altitude_relative for m in gcs.messages("ALTITUDE")][-5:],
            pair.summary(), ground.text("stderr")[-2000:])
        # the ground settles on the lowest adequate power within 10 s of its start
        events = pair.event_list()
        t0 = min(e.t_sent for e in events)

        def ground_powers(after: float) -> list[int]:
            return [e.power for e in pair.event_list() if e.src == "b" and e.kind == "data"
                    and e.t_sent >= after]

        assert pair.wait(lambda: len(ground_powers(t0 + 10.0)) > 20, 20)
        settled = ground_powers(t0 + 10.0)
        assert statistics.mode(settled) == ADEQUATE, settled
        assert sum(1 for x in settled if x == ADEQUATE) >= 0.8 * len(settled), settled

        # pings every ~500 ms cycling 0..4; stats every ~100 ms
        ping_log = pings(pair.event_list())
        assert len(ping_log) >= 10
        gaps = [b[0] - a[0] for a, b in itertools.pairwise(ping_log)]
        assert 0.45 <= statistics.median(gaps) <= 0.6, gaps
        powers = [pw for _, pw in ping_log]
        assert all(b == (a + 1) % 5 for a, b in itertools.pairwise(powers)), powers
        stats_t = [e.t_sent for e in pair.event_list() if e.src == "a" and e.kind == "data"
                   and p.TYPE_STATS in types_in(e.payload)]
        stat_gaps = [b - a for a, b in itertools.pairwise(stats_t)]
        assert 0.08 <= statistics.median(stat_gaps) <= 0.13, stat_gaps

        # the air's STATS reach the ground station as RADIO_STATUS
        assert gcs.wait_for("RADIO_STATUS", timeout=5)
        # the pilot's sticks go up: an RC override to the ground's gateway becomes command
        # packets, acked; the air applies them and its ground station sees RC_CHANNELS
        dev = gcs.dialect
        gcs.send(dev.MAVLink_rc_channels_override_message(
            1, 1, 1100, 1900, 1500, 0, 0, 0, 0, 0, *([0] * 10)))

        def applied() -> bool:
            return any((m.chan1_raw, m.chan2_raw, m.chan3_raw) == (1100, 1900, 1500)
                       for m in on_board.messages("RC_CHANNELS"))

        assert on_board.wait_until(applied, 5), on_board.messages("RC_CHANNELS")[-3:]

        # a 2 s blackout: the ground alternates 0/4; telemetry is back within 3 s after it
        black_start = time.monotonic()
        pair.blackout(2.0)
        assert pair.wait(lambda: not pair.in_blackout, 5)
        black_end = time.monotonic()
        during = [e.power for e in pair.event_list() if e.src == "b" and e.kind == "data"
                  and black_start + 0.6 <= e.t_sent <= black_end]
        assert len(during) >= 4 and set(during) == {0, 4}, during
        assert all(a != b for a, b in itertools.pairwise(during)), during
        count = len(gcs.messages("ALTITUDE"))
        assert gcs.wait_until(lambda: len(gcs.messages("ALTITUDE")) > count + 2, 3.0)
        assert time.monotonic() - black_end < 3.0
