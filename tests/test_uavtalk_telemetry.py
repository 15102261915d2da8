"""UAVTalk telemetry sessions, driven by a fake clock (no sleeps, no sockets).

The GCS and flight-controller simulators here are written from ``../shared/specs/uavtalk.md``'s
rules, independently of ``backends/uavtalk/telemetry.py``; everything crosses as bytes through
the real codec.
"""

from __future__ import annotations

import itertools
from collections import deque
from typing import Any

import pytest

from backends.uavtalk.codec import Decoder, Packet, PacketType, encode
from backends.uavtalk.objects import ObjectSet
from backends.uavtalk.telemetry import (
    CONNECTION_TIMEOUT,
    MAX_RETRIES,
    PRIORITY_QUEUE_SIZE,
    REGULAR_QUEUE_SIZE,
    FlightSession,
    GcsSession,
    ObjectStore,
    Status,
)

OBJECTS = ObjectSet.load()
FTS = OBJECTS.by_name("FlightTelemetryStats")
GTS = OBJECTS.by_name("GCSTelemetryStats")
ATT = OBJECTS.by_name("AttitudeState")
FIRMWARE = OBJECTS.by_name("FirmwareIAPObj")
FLIGHT_STATUS = OBJECTS.by_name("FlightStatus")
UNKNOWN_ID = 0x12345678
STEP = 0.01


def _store() -> ObjectStore:
    return ObjectStore({
        "AttitudeState": {"q1": 1.0, "Roll": 10.0, "Pitch": -5.0, "Yaw": 90.0},
        "FlightStatus": {"Armed": "Armed"},
        "SystemAlarms": {},
    })


def _decode_all(chunks: list[bytes]) -> list[Packet]:
    dec = Decoder(OBJECTS.data_length)
    out = dec.feed(b"".join(chunks))
    assert dec.stats.bad_crc == dec.stats.bad_length == dec.stats.bytes_skipped == 0
    return out


def _stats(status: int) -> Packet:
    return Packet(PacketType.OBJ, GTS.id, 0, GTS.pack({"Status": status}))


class GcsSim:
    """A ground station from the spec: HandshakeReq every 2 s until FlightTelemetryStats says
    HandshakeAck, then Connected (re-sent every 5 s); requests on demand; never ACKs unless
    told to."""

    def __init__(self, ack: bool = True) -> None:
        self.status = Status.HANDSHAKE_REQ
        self.next_stats = 0.0
        self.ack = ack
        self.silent = False
        self.received: list[tuple[float, Packet]] = []
        self.out: list[Packet] = []

    def step(self, now: float, packets: list[Packet]) -> None:
        for p in packets:
            self.received.append((now, p))
            if p.type == PacketType.OBJ_ACK and self.ack:
                self.out.append(Packet(PacketType.ACK, p.object_id))
            if p.object_id == FTS.id and p.type == PacketType.OBJ:
                flight = FTS.unpack(p.data)["Status"]
                if self.status == Status.HANDSHAKE_REQ and flight == Status.HANDSHAKE_ACK:
                    self.status = Status.CONNECTED
                    self.next_stats = now
                elif self.status == Status.CONNECTED and flight == Status.DISCONNECTED:
                    self.status = Status.HANDSHAKE_REQ
                    self.next_stats = now
        if not self.silent and now >= self.next_stats:
            self.out.append(_stats(self.status))
            self.next_stats = now + (5.0 if self.status == Status.CONNECTED else 2.0)

    def take(self) -> list[Packet]:
        out, self.out = ([], self.out) if self.silent else (self.out, [])
        return out

    def got(self, ptype: PacketType, object_id: int, since: float = 0.0) -> list[Packet]:
        return [p for t, p in self.received if t >= since and p.type == ptype
                and p.object_id == object_id]


def run_flight(session: FlightSession, gcs: GcsSim, start: float, end: float) -> float:
    """Both sides every 10 ms of fake time, bytes through the real decoder; returns ``end``."""
    decoder_gcs = Decoder(OBJECTS.data_length)
    now = start
    while now < end:
        session.tick(now)
        packets = decoder_gcs.feed(b"".join(session.outgoing()))
        assert all(p.timestamp is None for p in packets)
        gcs.step(now, packets)
        for p in gcs.take():
            session.receive(p, now)
        now = round(now + STEP, 6)
    return now


def connect(session: FlightSession, gcs: GcsSim) -> float:
    now = run_flight(session, gcs, 0.0, 1.0)
    assert session.state == Status.CONNECTED and gcs.status == Status.CONNECTED
    return now


# ------------------------------------------------------------------------------ flight side


def test_flight_handshake_from_disconnected() -> None:
    s = FlightSession(OBJECTS, _store())
    s.tick(0.0)
    first = _decode_all(s.outgoing())
    assert [FTS.unpack(p.data)["Status"] for p in first if p.object_id == FTS.id] == [0]
    s.receive(_stats(Status.HANDSHAKE_REQ), 0.1)
    assert s.state == Status.HANDSHAKE_ACK
    (ack,) = _decode_all(s.outgoing())
    assert ack.object_id == FTS.id and FTS.unpack(ack.data)["Status"] == Status.HANDSHAKE_ACK
    s.receive(_stats(Status.CONNECTED), 0.3)
    assert s.state == Status.CONNECTED
    assert s.stats.handshake_ms == 200 and s.stats.connects == 1
    (conn,) = _decode_all(s.outgoing())
    assert FTS.unpack(conn.data)["Status"] == Status.CONNECTED


def test_handshake_packets_are_the_spec_vectors() -> None:
    s = FlightSession(OBJECTS, _store())
    s.receive(Packet(PacketType.OBJ, GTS.id, 0, GTS.pack({"Status": 1})), 0.0)
    assert s.outgoing() == [bytes.fromhex("3c202f005abb37670000") + bytes(36)
                            + bytes.fromhex("0268")]
    g = GcsSession(OBJECTS)
    g.tick(0.0)
    assert g.outgoing() == [bytes.fromhex("3c202f000adcd1ca0000") + bytes(36)
                            + bytes.fromhex("0196")]
    s.receive(Packet(PacketType.OBJ_REQ, UNKNOWN_ID), 0.1)
    g.receive(Packet(PacketType.OBJ_ACK, GTS.id, 0, GTS.pack({})), 0.1)
    assert s.outgoing() == [encode(Packet(PacketType.NACK, UNKNOWN_ID))]
    assert g.outgoing() == [bytes.fromhex("3c230a000adcd1ca000050")]


def test_flight_handshake_ack_then_gcs_disconnected() -> None:
    s = FlightSession(OBJECTS, _store())
    s.receive(_stats(Status.CONNECTED), 0.0)  # only a HandshakeReq leaves Disconnected
    s.receive(_stats(Status.HANDSHAKE_ACK), 0.0)
    assert s.state == Status.DISCONNECTED and s.stats.state_changes == 0
    s.receive(_stats(Status.HANDSHAKE_REQ), 0.0)
    s.receive(_stats(Status.HANDSHAKE_REQ), 0.05)  # stays HandshakeAck
    assert s.state == Status.HANDSHAKE_ACK
    s.receive(_stats(Status.DISCONNECTED), 0.1)
    assert s.state == Status.DISCONNECTED and s.stats.state_changes == 2


def test_flight_connected_drops_when_gcs_not_connected() -> None:
    s = FlightSession(OBJECTS, _store())
    for status in (Status.HANDSHAKE_REQ, Status.CONNECTED, Status.HANDSHAKE_REQ):
        s.receive(_stats(status), 0.0)
    assert s.state == Status.DISCONNECTED and s.stats.disconnects == 1
    s.receive(_stats(Status.HANDSHAKE_REQ), 0.1)
    assert s.state == Status.HANDSHAKE_ACK


def test_flight_stats_every_5_s_and_on_change() -> None:
    s = FlightSession(OBJECTS, _store())
    gcs = GcsSim()
    gcs.silent = True  # never answers: stays Disconnected, stats still every 5 s
    run_flight(s, gcs, 0.0, 12.0)
    times = [t for t, p in gcs.received if p.object_id == FTS.id]
    assert times == [0.0, 5.0, 10.0]
    s2 = FlightSession(OBJECTS, _store())
    gcs2 = GcsSim()
    run_flight(s2, gcs2, 0.0, 1.0)
    statuses = [FTS.unpack(p.data)["Status"] for p in gcs2.got(PacketType.OBJ, FTS.id)]
    assert statuses == [Status.DISCONNECTED, Status.HANDSHAKE_ACK, Status.CONNECTED]


def test_gcs_simulator_connects_reads_firmware_and_gets_attitude_at_period() -> None:
    s = FlightSession(OBJECTS, _store(), board_type=0x09)
    gcs = GcsSim()
    now = connect(s, gcs)
    assert s.stats.handshake_ms <= 50
    gcs.out.append(Packet(PacketType.OBJ_REQ, FIRMWARE.id))
    gcs.out.append(Packet(PacketType.OBJ_REQ, FIRMWARE.meta_id))
    now = run_flight(s, gcs, now, now + 3.0)
    (fw,) = gcs.got(PacketType.OBJ, FIRMWARE.id)
    assert FIRMWARE.unpack(fw.data)["BoardType"] == 0x09
    assert len(gcs.got(PacketType.OBJ, FIRMWARE.meta_id)) == 1
    # AttitudeState's telemetryflight period is 130 ms: 3 s → 23 sends (≥ 5 Hz)
    att = gcs.got(PacketType.OBJ, ATT.id, since=1.0)
    assert 21 <= len(att) <= 24
    assert ATT.unpack(att[-1].data)["Yaw"] == 90.0


def test_nothing_periodic_before_connected() -> None:
    s = FlightSession(OBJECTS, _store())
    gcs = GcsSim()
    gcs.silent = True
    run_flight(s, gcs, 0.0, 3.0)
    assert not gcs.got(PacketType.OBJ, ATT.id)


def test_unknown_id_and_unserved_object_are_nacked() -> None:
    s = FlightSession(OBJECTS, _store())
    gcs = GcsSim()
    now = connect(s, gcs)
    baro = OBJECTS.by_name("BaroSensor")  # known, not in the store
    gcs.out += [Packet(PacketType.OBJ_REQ, UNKNOWN_ID), Packet(PacketType.OBJ_REQ, baro.id),
                Packet(PacketType.OBJ_REQ, baro.meta_id),
                Packet(PacketType.OBJ_REQ, ATT.meta_id)]
    run_flight(s, gcs, now, now + 0.1)
    assert len(gcs.got(PacketType.NACK, UNKNOWN_ID)) == 1
    assert len(gcs.got(PacketType.NACK, baro.id)) == 1
    assert len(gcs.got(PacketType.NACK, baro.meta_id)) == 1
    (meta,) = gcs.got(PacketType.OBJ, ATT.meta_id)
    meta_values = OBJECTS.by_name("AttitudeStateMeta").unpack(meta.data)
    assert meta_values["FlightTelemetryUpdatePeriod"] == 130


def test_obj_ack_acked_or_nacked() -> None:
    store = _store()
    s = FlightSession(OBJECTS, store)
    s.receive(Packet(PacketType.OBJ_ACK, UNKNOWN_ID, 0, b"\x00" * 4), 0.0)
    s.receive(Packet(PacketType.OBJ_ACK, ATT.id, 0, b"\x00" * 5), 0.0)
    s.receive(Packet(PacketType.OBJ_ACK, ATT.id, 0, ATT.pack({"Yaw": 45.0})), 0.0)
    out = _decode_all(s.outgoing())
    replies = [(p.type, p.object_id) for p in out if p.object_id != FTS.id]
    assert replies == [(PacketType.NACK, UNKNOWN_ID), (PacketType.NACK, ATT.id),
                       (PacketType.ACK, ATT.id)]
    assert store.get("AttitudeState")["Yaw"] == 45.0  # type: ignore[index]
    assert s.stats.rx_unknown == 1 and s.stats.rx_bad_length == 1


def test_obj_req_flood_is_bounded() -> None:
    s = FlightSession(OBJECTS, _store())
    s.tick(0.0)
    s.outgoing()  # the first FlightTelemetryStats; the next is due at 5 s
    for i in range(10_000):
        s.receive(Packet(PacketType.OBJ_REQ, ATT.id if i % 2 else UNKNOWN_ID), i * 1e-5)
        s.tick(i * 1e-5)
    assert s.queued <= PRIORITY_QUEUE_SIZE + REGULAR_QUEUE_SIZE
    assert s.stats.priority_drops == 10_000 - PRIORITY_QUEUE_SIZE
    assert len(_decode_all(s.outgoing())) == PRIORITY_QUEUE_SIZE
    assert s.queued == 0
    # served again once drained
    s.receive(Packet(PacketType.OBJ_REQ, UNKNOWN_ID), 1.0)
    assert [p.type for p in _decode_all(s.outgoing())] == [PacketType.NACK]


def test_gcs_that_never_acks_two_retries_then_failure() -> None:
    s = FlightSession(OBJECTS, _store())
    gcs = GcsSim(ack=False)
    now = connect(s, gcs)
    s.updated("FirmwareIAPObj", now)  # on change, acked on the flight side
    s.updated("FlightStatus", now)  # on change, not acked: flows past the open transaction
    end = run_flight(s, gcs, now, now + 2.0)
    sends = [t for t, p in gcs.received if p.type == PacketType.OBJ_ACK]
    assert len(sends) == 1 + MAX_RETRIES
    assert [round(b - a, 2) for a, b in itertools.pairwise(sends)] == [0.25, 0.25]
    assert s.stats.retries == MAX_RETRIES and s.stats.failures == 1
    assert not s.transaction_pending
    assert len(gcs.got(PacketType.OBJ, FLIGHT_STATUS.id)) == 1
    assert len(gcs.got(PacketType.OBJ, ATT.id, since=end - 1.0)) >= 7
    # an ACK ends the next one at once
    gcs.ack = True
    s.updated("FirmwareIAPObj", end)
    run_flight(s, gcs, end, end + 1.0)
    assert s.stats.failures == 1 and s.stats.retries == MAX_RETRIES
    assert s.stats.rx_ack == 1 and not s.transaction_pending


def test_one_outstanding_transaction() -> None:
    s = FlightSession(OBJECTS, ObjectStore())
    for status in (Status.HANDSHAKE_REQ, Status.CONNECTED):
        s.receive(_stats(status), 0.0)
    s.outgoing()
    s.updated("FirmwareIAPObj", 0.0)
    s.store.set("FirmwareIAPObj", {"BoardType": 3})
    s.updated("FirmwareIAPObj", 0.0)  # same object: refreshed in the queue, not duplicated
    assert [p.type for p in _decode_all(s.outgoing())] == [PacketType.OBJ_ACK]
    assert s.transaction_pending
    s.receive(Packet(PacketType.ACK, FIRMWARE.id), 0.1)
    assert not s.transaction_pending and s.stats.transactions == 1
    # two acked objects: the second waits for the first's ACK, plain packets pass it
    s.store.set("ActuatorSettings", {})
    s.updated("FirmwareIAPObj", 0.2)
    s.updated("ActuatorSettings", 0.2)
    s.updated("FlightStatus", 0.2)  # not in the store: nothing sent
    s.store.set("FlightStatus", {})
    s.updated("FlightStatus", 0.2)
    first = [(p.type, p.object_id) for p in _decode_all(s.outgoing())]
    assert first == [(PacketType.OBJ_ACK, FIRMWARE.id), (PacketType.OBJ, FLIGHT_STATUS.id)]
    assert s.outgoing() == []
    s.receive(Packet(PacketType.ACK, FIRMWARE.id), 0.3)
    (second,) = _decode_all(s.outgoing())
    assert second.type == PacketType.OBJ_ACK
    assert second.object_id == OBJECTS.by_name("ActuatorSettings").id


def test_nine_seconds_of_gcs_silence_then_reconnect() -> None:
    s = FlightSession(OBJECTS, _store())
    gcs = GcsSim()
    now = connect(s, gcs)
    gcs.silent = True
    quiet_from = now
    last_heard = s._last_rx
    assert last_heard is not None and last_heard < 0.1
    now = run_flight(s, gcs, now, now + 9.0)
    assert s.state == Status.DISCONNECTED and s.stats.disconnects == 1
    drops = [t for t, p in gcs.received if p.object_id == FTS.id
             and FTS.unpack(p.data)["Status"] == Status.DISCONNECTED and t > quiet_from]
    # 8 s after the GCS's last packet (its Connected, before the quiet second)
    assert drops and 0 <= drops[0] - last_heard - CONNECTION_TIMEOUT <= STEP
    gcs.silent = False
    gcs.status = Status.HANDSHAKE_REQ
    gcs.next_stats = now
    run_flight(s, gcs, now, now + 1.0)
    assert s.state == Status.CONNECTED and s.stats.connects == 2


# -------------------------------------------------------------------------------- GCS side


class FlightSim:
    """A flight controller from the spec's flight-side rules; serves ``serve``, NACKs the rest,
    ignores requests for ``mute``."""

    def __init__(self, serve: dict[str, dict[str, Any]], mute: frozenset[str] = frozenset()):
        self.status = Status.DISCONNECTED
        self.serve = serve
        self.mute = {OBJECTS.by_name(n).id for n in mute}
        self.requests: list[tuple[float, int]] = []
        self.out: list[Packet] = []
        self.silent = False

    def step(self, now: float, packets: list[Packet]) -> None:
        for p in packets:
            if p.type == PacketType.OBJ and p.object_id == GTS.id:
                gcs = GTS.unpack(p.data)["Status"]
                old = self.status
                if old == Status.DISCONNECTED and gcs == Status.HANDSHAKE_REQ:
                    self.status = Status.HANDSHAKE_ACK
                elif old == Status.HANDSHAKE_ACK and gcs == Status.CONNECTED:
                    self.status = Status.CONNECTED
                elif old == Status.CONNECTED and gcs != Status.CONNECTED:
                    self.status = Status.DISCONNECTED
                if self.status != old:
                    self.out.append(Packet(PacketType.OBJ, FTS.id, 0,
                                           FTS.pack({"Status": self.status})))
            elif p.type == PacketType.OBJ_REQ:
                self.requests.append((now, p.object_id))
                obj = OBJECTS.by_id(p.object_id)
                if p.object_id in self.mute:
                    continue
                if obj is not None and obj.name in self.serve:
                    self.out.append(Packet(PacketType.OBJ, obj.id, 0,
                                           obj.pack(self.serve[obj.name])))
                else:
                    self.out.append(Packet(PacketType.NACK, p.object_id))

    def take(self) -> list[Packet]:
        out, self.out = ([], self.out) if self.silent else (self.out, [])
        return out


def run_gcs(session: GcsSession, fc: FlightSim, start: float, end: float) -> float:
    decoder = Decoder(OBJECTS.data_length)
    now = start
    while now < end:
        session.tick(now)
        fc.step(now, decoder.feed(b"".join(session.outgoing())))
        for p in fc.take():
            session.receive(p, now)
        now = round(now + STEP, 6)
    return now


SERVED: dict[str, dict[str, Any]] = {
    "FirmwareIAPObj": {"BoardType": 9}, "FlightStatus": {"Armed": 2},
    "AttitudeState": {"q1": 1.0, "Yaw": 90.0}, "SystemAlarms": {}}


def test_gcs_session_handshake_and_walk_against_flight_simulator() -> None:
    seen: list[str] = []
    g = GcsSession(OBJECTS, on_object=lambda name, values: seen.append(name))
    fc = FlightSim(SERVED)
    run_gcs(g, fc, 0.0, 2.0)
    assert g.state == Status.CONNECTED and fc.status == Status.CONNECTED
    assert g.walk_done
    walked = [OBJECTS.by_id(i).name for _, i in fc.requests]  # type: ignore[union-attr]
    assert walked == ["FirmwareIAPObj", "FlightStatus", "AttitudeState", "SystemAlarms",
                      "GPSPositionSensor", "FlightBatteryState", "BaroSensor"]
    assert g.walk_nacked == ["GPSPositionSensor", "FlightBatteryState", "BaroSensor"]
    assert g.values["FirmwareIAPObj"]["BoardType"] == 9
    assert g.values["FlightStatus"]["Armed"] == 2
    assert {"FlightTelemetryStats", "FirmwareIAPObj", "AttitudeState"} <= set(seen)
    assert g.stats.failures == 0 and g.stats.retries == 0


def test_gcs_handshake_req_every_2_s_until_answered() -> None:
    g = GcsSession(OBJECTS)
    fc = FlightSim(SERVED)
    fc.silent = True
    sent: list[float] = []
    decoder = Decoder(OBJECTS.data_length)
    now = 0.0
    while now < 7.0:
        g.tick(now)
        for p in decoder.feed(b"".join(g.outgoing())):
            assert p.object_id == GTS.id
            assert GTS.unpack(p.data)["Status"] == Status.HANDSHAKE_REQ
            sent.append(now)
        now = round(now + STEP, 6)
    assert sent == [0.0, 2.0, 4.0, 6.0]
    assert g.state == Status.HANDSHAKE_REQ


def test_gcs_walk_retries_a_silent_request_then_moves_on() -> None:
    g = GcsSession(OBJECTS)
    fc = FlightSim(SERVED, mute=frozenset({"FlightStatus"}))
    run_gcs(g, fc, 0.0, 3.0)
    times = [t for t, i in fc.requests if i == FLIGHT_STATUS.id]
    assert len(times) == 1 + MAX_RETRIES
    assert [round(b - a, 2) for a, b in itertools.pairwise(times)] == [0.25, 0.25]
    assert g.stats.failures == 1 and g.walk_done
    assert "FlightStatus" in g.walk_nacked and "AttitudeState" in g.values


def test_gcs_disconnects_when_flight_says_so_or_on_silence() -> None:
    g = GcsSession(OBJECTS)
    fc = FlightSim(SERVED)
    now = run_gcs(g, fc, 0.0, 1.0)
    assert g.state == Status.CONNECTED
    g.receive(Packet(PacketType.OBJ, FTS.id, 0, FTS.pack({"Status": 0})), now)
    assert g.stats.disconnects == 1
    fc.status = Status.DISCONNECTED
    now = run_gcs(g, fc, now, now + 1.0)
    assert g.state == Status.CONNECTED and g.stats.connects == 2
    fc.silent = True
    now = run_gcs(g, fc, now, now + CONNECTION_TIMEOUT + 0.5)
    assert g.state == Status.HANDSHAKE_REQ and g.stats.disconnects == 2
    # a request open when the flight side drops the link does not outlive it
    fc.silent = False
    fc.status = Status.DISCONNECTED
    now = run_gcs(g, fc, now, now + 2.5)
    assert g.state == Status.CONNECTED
    g._walk = deque(["SystemAlarms"])
    g._walk_next()
    g.outgoing()
    assert g.transaction_pending
    g.receive(Packet(PacketType.OBJ, FTS.id, 0, FTS.pack({"Status": 0})), now)
    assert not g.transaction_pending and g.stats.failures == 0


def test_gcs_acks_obj_ack_and_nacks_requests() -> None:
    g = GcsSession(OBJECTS)
    g.receive(Packet(PacketType.OBJ_ACK, ATT.id, 0, ATT.pack({})), 0.0)
    g.receive(Packet(PacketType.OBJ_ACK, UNKNOWN_ID, 0, b"\x01"), 0.0)
    g.receive(Packet(PacketType.OBJ_REQ, ATT.id), 0.0)
    g.receive(Packet(PacketType.OBJ_REQ, GTS.id), 0.0)
    out = [(p.type, p.object_id) for p in _decode_all(g.outgoing())]
    assert out == [(PacketType.ACK, ATT.id), (PacketType.NACK, UNKNOWN_ID),
                   (PacketType.NACK, ATT.id), (PacketType.OBJ, GTS.id)]


# ------------------------------------------------------------------------------ end to end


def test_flight_and_gcs_sessions_against_each_other() -> None:
    received: list[tuple[float, str]] = []
    clock = [0.0]
    flight = FlightSession(OBJECTS, _store())
    gcs = GcsSession(OBJECTS, on_object=lambda n, v: received.append((clock[0], n)))
    to_gcs = Decoder(OBJECTS.data_length)
    to_flight = Decoder(OBJECTS.data_length)

    def run(end: float, gcs_silent: bool = False) -> None:
        now = clock[0]
        while now < end:
            clock[0] = now
            flight.tick(now)
            gcs.tick(now)
            for p in to_gcs.feed(b"".join(flight.outgoing())):
                gcs.receive(p, now)
            data = b"".join(gcs.outgoing())
            if not gcs_silent:
                for p in to_flight.feed(data):
                    flight.receive(p, now)
            now = round(now + STEP, 6)
        clock[0] = now

    run(1.0)
    assert flight.state == gcs.state == Status.CONNECTED
    assert gcs.walk_done and gcs.values["FirmwareIAPObj"]["BoardType"] != 0
    assert gcs.values["FlightStatus"]["Armed"] == 2
    run(4.0)
    att = [t for t, n in received if n == "AttitudeState" and t >= 2.0]
    assert len(att) / 2.0 >= 5.0
    run(13.0, gcs_silent=True)
    assert flight.state == Status.DISCONNECTED
    assert gcs.state != Status.CONNECTED  # it heard FlightTelemetryStats(Disconnected)
    run(15.0)
    assert flight.state == gcs.state == Status.CONNECTED
    assert flight.stats.connects == gcs.stats.connects == 2
    assert to_gcs.stats.bad_crc == to_flight.stats.bad_crc == 0


def test_board_type_must_be_nonzero() -> None:
    with pytest.raises(ValueError):
        FlightSession(OBJECTS, ObjectStore(), board_type=0)


def test_never_sends_timestamped() -> None:
    with pytest.raises(ValueError):
        encode(Packet(PacketType.OBJ, ATT.id, 0, ATT.pack({}), timestamp=5))
