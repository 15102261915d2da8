"""The MAVLink backend as QGroundControl sees it.

A pymavlink ground station (sysid 255, compid 190, parsing with pymavlink's own upstream
``development`` module) on its own UDP socket receives what the backend streams to it
(``udpout:``, as to QGC's port 14550) and plays QGC's connect sequence.  The backend is driven
through a real :class:`~gateway.dispatcher.Dispatcher`, by the real simulated flight or by
hand-made messages.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import socket
import struct
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from mavlink_peer import MavPeer

from backends.mavlink.backend import MavlinkBackend
from backends.mavlink.options import MavlinkOptions
from backends.mavlink.translate import sm_update_from_mavlink, status_from_mavlink
from dialects import aurora_mavlink as aurora
from dialects.states import SimpleState as S
from dialects.states import state_names
from gateway import config, registry
from gateway.backend import Backend, GatewayContext, Routes
from gateway.commands import cli
from gateway.config import ConfigError
from gateway.dispatcher import Dispatcher
from gateway.model import Battery, RcChannels, SmUpdate, Status
from gateway.sources.options import SimOptions
from gateway.sources.sim import SimSource
from gateway.wire import decode_all, encode

WAIT = 10.0  # generous deadlines: the machine is shared
US = (1, 1)  # the rocket: sysid 1, compid 1


@pytest.fixture
def gcs() -> Iterator[MavPeer]:
    with MavPeer(255, 190, announce=True) as p:  # QGC says who it is
        yield p


@contextlib.contextmanager
def running(port: int, **opts: Any) -> Iterator[tuple[MavlinkBackend, Dispatcher]]:
    b = MavlinkBackend(MavlinkOptions(endpoints=[f"udpout:127.0.0.1:{port}"], **opts))
    d = Dispatcher([b])
    assert d.start() == []
    try:
        yield b, d
    finally:
        d.close()


def sm(state: int = 0, *, t: int = 1000, armed: bool = False, alt: float = 0.0,
       vel: float = 0.0, rev: int = 64, sm_type: int = 0) -> SmUpdate:
    return SmUpdate(t, state, armed, sm_type, alt, 9.81, 9.7, vel, 0.1, 1.4, 0.6,
                    payload_len=rev, origin="test")


# -- being seen -------------------------------------------------------------------------------

def test_heartbeat_within_a_second_then_1_hz_without_updates(gcs: MavPeer) -> None:
    t0 = time.monotonic()
    with running(gcs.port):
        first = gcs.wait_for("HEARTBEAT", timeout=1.0)
        assert first, "no HEARTBEAT within 1 s of start"
        hbs = gcs.wait_for("HEARTBEAT", count=3, timeout=WAIT)
    assert len(hbs) >= 3
    times = [t for t, _ in gcs.timed("HEARTBEAT")]
    assert times[0] - t0 < 1.0
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert all(0.5 < g < 2.0 for g in gaps[:2]), gaps
    hb = hbs[0]
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == US
    assert hb.type == aurora.MAV_TYPE_ROCKET
    assert hb.autopilot == aurora.MAV_AUTOPILOT_GENERIC
    assert hb.base_mode & aurora.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & aurora.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.system_status == aurora.MAV_STATE_UNINIT  # nothing heard from the rocket yet
    # MAVLink 2 from the very first packet
    assert all(raw[0] == 0xFD for raw in gcs.raw_received)


def test_sysid_is_configurable(gcs: MavPeer) -> None:
    with running(gcs.port, sysid=42):
        hb = gcs.wait_for("HEARTBEAT", timeout=WAIT)
    assert (hb[0].get_srcSystem(), hb[0].get_srcComponent()) == (42, 1)


# -- QGC's connect sequence ---------------------------------------------------------------------

def test_qgc_connect_sequence_gets_every_answer(gcs: MavPeer) -> None:
    dev = gcs.dialect
    with running(gcs.port) as (_, d):
        d.dispatch(sm(S.ARMED, armed=True))
        assert gcs.wait_for("HEARTBEAT", timeout=WAIT)
        gcs.send(dev.MAVLink_heartbeat_message(dev.MAV_TYPE_GCS, dev.MAV_AUTOPILOT_INVALID, 0, 0,
                                               dev.MAV_STATE_ACTIVE, 3))
        # 1. AUTOPILOT_VERSION
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        av = gcs.wait_for("AUTOPILOT_VERSION", timeout=WAIT)
        # 2. the mode table
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_AVAILABLE_MODES, 0)
        modes = gcs.wait_for("AVAILABLE_MODES", count=9, timeout=WAIT)
        # 3. parameters (QGC retries; a component without parameters stays silent)
        gcs.send(dev.MAVLink_param_request_list_message(*US))
        # 4. mission, then fence and rally if QGC wanted them
        for mtype in (dev.MAV_MISSION_TYPE_MISSION, dev.MAV_MISSION_TYPE_RALLY):
            gcs.send(dev.MAVLink_mission_request_list_message(*US, mtype))
        counts = gcs.wait_for("MISSION_COUNT", count=2, timeout=WAIT)
        gcs.send(dev.MAVLink_mission_ack_message(*US, dev.MAV_MISSION_ACCEPTED, 0))
        # 5. something we cannot do, then a marker: everything before it has been answered
        gcs.command(US, dev.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        gcs.command(US, dev.MAV_CMD_NAV_TAKEOFF)
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_EXTENDED_SYS_STATE)
        assert gcs.wait_for("EXTENDED_SYS_STATE", count=1, timeout=WAIT)
        assert gcs.wait_until(lambda: len(gcs.messages("COMMAND_ACK")) >= 5, WAIT)
        # the answers' order on the wire: each ACK before the message it announces
        order = [m.get_type() for m in gcs.messages()
                 if m.get_type() in ("COMMAND_ACK", "AUTOPILOT_VERSION")]

    acks = gcs.messages("COMMAND_ACK")
    by_cmd: dict[int, list[Any]] = {}
    for a in acks:
        by_cmd.setdefault(a.command, []).append(a)
        assert (a.target_system, a.target_component) == (255, 190)
        assert (a.get_srcSystem(), a.get_srcComponent()) == US
    # exactly one ACK per command sent
    assert [a.result for a in by_cmd[dev.MAV_CMD_REQUEST_MESSAGE]] == [dev.MAV_RESULT_ACCEPTED] * 3
    assert [a.result for a in by_cmd[dev.MAV_CMD_COMPONENT_ARM_DISARM]] == [
        dev.MAV_RESULT_UNSUPPORTED]
    assert [a.result for a in by_cmd[dev.MAV_CMD_NAV_TAKEOFF]] == [dev.MAV_RESULT_UNSUPPORTED]
    assert order[:2] == ["COMMAND_ACK", "AUTOPILOT_VERSION"]

    assert len(av) == 1
    assert av[0].capabilities & dev.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert not av[0].capabilities & (dev.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
                                     | dev.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY)

    expected = state_names(0)
    assert len(modes) == len(expected) == 9
    assert [(m.custom_mode, m.mode_name) for m in modes] == expected
    assert [m.mode_index for m in modes] == list(range(1, 10))
    assert all(m.number_modes == 9 for m in modes)
    assert all(m.properties & dev.MAV_MODE_PROPERTY_NOT_USER_SELECTABLE for m in modes)
    assert {"BOOST", "APOGEE"} <= {m.mode_name for m in modes}

    assert [(c.count, c.mission_type, c.target_system, c.target_component) for c in counts] == [
        (0, dev.MAV_MISSION_TYPE_MISSION, 255, 190), (0, dev.MAV_MISSION_TYPE_RALLY, 255, 190)]
    assert gcs.messages("PARAM_VALUE") == []  # no invented "count 0"
    # the heartbeat names the state through the table: ARMED's number, armed bit set
    hb = gcs.messages("HEARTBEAT")[-1]
    assert hb.custom_mode == S.ARMED
    assert hb.base_mode & aurora.MAV_MODE_FLAG_SAFETY_ARMED


def test_commands_for_others_are_not_answered_and_requests_can_be_partial(gcs: MavPeer) -> None:
    dev = gcs.dialect
    with running(gcs.port):
        assert gcs.wait_for("HEARTBEAT", timeout=WAIT)
        gcs.command((7, 1), dev.MAV_CMD_NAV_TAKEOFF)  # another system
        gcs.command((1, 50), dev.MAV_CMD_NAV_TAKEOFF)  # another component of ours
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_AVAILABLE_MODES, 3)
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_ATTITUDE)
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, 12345)
        assert gcs.wait_until(lambda: len(gcs.messages("COMMAND_ACK")) >= 3, WAIT)
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_HEARTBEAT)
        assert gcs.wait_until(lambda: len(gcs.messages("COMMAND_ACK")) >= 4, WAIT)
    acks = [(a.command, a.result) for a in gcs.messages("COMMAND_ACK")]
    assert (dev.MAV_CMD_NAV_TAKEOFF, dev.MAV_RESULT_UNSUPPORTED) not in acks
    assert acks == [(dev.MAV_CMD_REQUEST_MESSAGE, dev.MAV_RESULT_ACCEPTED),
                    (dev.MAV_CMD_REQUEST_MESSAGE, dev.MAV_RESULT_TEMPORARILY_REJECTED),
                    (dev.MAV_CMD_REQUEST_MESSAGE, dev.MAV_RESULT_UNSUPPORTED),
                    (dev.MAV_CMD_REQUEST_MESSAGE, dev.MAV_RESULT_ACCEPTED)]
    modes = gcs.messages("AVAILABLE_MODES")
    assert [(m.mode_index, m.mode_name) for m in modes] == [(3, "BOOST")]


def test_message_intervals_can_be_read_and_changed(gcs: MavPeer) -> None:
    dev = gcs.dialect
    with running(gcs.port) as (_, d):
        gcs.wait_for("HEARTBEAT", timeout=WAIT)
        gcs.command(US, dev.MAV_CMD_GET_MESSAGE_INTERVAL, dev.MAVLINK_MSG_ID_ATTITUDE)
        iv = gcs.wait_for("MESSAGE_INTERVAL", timeout=WAIT)
        gcs.command(US, dev.MAV_CMD_SET_MESSAGE_INTERVAL, dev.MAVLINK_MSG_ID_ATTITUDE, -1)
        assert gcs.wait_until(lambda: len(gcs.messages("COMMAND_ACK")) >= 2, WAIT)
        for i in range(5):
            d.dispatch(sm(S.IDLE, t=2000 + 100 * i))
        assert gcs.wait_for("ALTITUDE", timeout=WAIT)
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_VFR_HUD)
        assert gcs.wait_for("COMMAND_ACK", count=3, timeout=WAIT)
    assert (iv[0].message_id, iv[0].interval_us) == (dev.MAVLINK_MSG_ID_ATTITUDE, 40000)
    assert gcs.messages("COMMAND_ACK")[1].result == dev.MAV_RESULT_ACCEPTED
    assert gcs.messages("ATTITUDE") == []  # switched off before any update came


# -- streams ------------------------------------------------------------------------------------

class Tap:
    """Stands between a source and the dispatcher and keeps what passed."""

    def __init__(self, d: Dispatcher) -> None:
        self.d = d
        self.seen: list[Any] = []
        self.lock = threading.Lock()

    def __call__(self, msg: Any) -> None:
        with self.lock:
            self.seen.append(msg)
        self.d.dispatch(msg)

    def sm_updates(self) -> list[SmUpdate]:
        with self.lock:
            return [m for m in self.seen if isinstance(m, SmUpdate)]


def test_attitude_follows_a_10_hz_rocket_update_for_update(gcs: MavPeer) -> None:
    with running(gcs.port) as (_, d):
        tap = Tap(d)
        src = SimSource(SimOptions(rate_hz=10, speed=1, pad_idle_s=5))
        src.start(tap)
        try:
            assert gcs.wait_until(lambda: len(tap.sm_updates()) >= 13, WAIT)
        finally:
            src.stop()
        sent = tap.sm_updates()
        assert gcs.wait_for("ATTITUDE", count=len(sent), timeout=WAIT)
    atts = gcs.messages("ATTITUDE")
    # every 10 Hz update became an ATTITUDE: the stream runs at the rocket's 10 Hz
    assert [a.time_boot_ms for a in atts] == [m.timestamp_ms for m in sent]
    span_s = (atts[-1].time_boot_ms - atts[0].time_boot_ms) / 1000
    assert (len(atts) - 1) / span_s >= 10 - 1e-9
    f32 = struct.Struct("<f")

    def r32(x: float) -> float:
        return f32.unpack(f32.pack(x))[0]

    for a, m in zip(atts, sent, strict=True):
        assert (a.roll, a.pitch, a.yaw) == (r32(m.roll_rad), r32(m.pitch_rad), r32(m.yaw_rad))


def test_a_simulated_flight_streams_everything_qgc_shows(gcs: MavPeer) -> None:
    order = ["IDLE", "ARMED", "BOOST", "BURNOUT", "APOGEE", "MAIN", "REDUNDANT", "LANDED"]
    with running(gcs.port, heartbeat_hz=10, extended_sys_state_hz=10) as (_, d):
        tap = Tap(d)
        src = SimSource(SimOptions(rate_hz=20, status_hz=2, speed=4, pad_idle_s=0.4,
                                   pad_armed_s=0.8))
        src.start(tap)
        try:
            landed = gcs.wait_for("STATUSTEXT", lambda m: m.text == "#LANDED", timeout=WAIT * 2)
            # The EXTENDED_SYS_STATE of the landing is sent right after that text: wait for it
            # to be parsed (the peer's thread), not just sent.
            on_ground = gcs.dialect.MAV_LANDED_STATE_ON_GROUND
            assert gcs.wait_until(lambda: [m.landed_state for m in gcs.messages(
                "EXTENDED_SYS_STATE")][-1:] == [on_ground], WAIT)
        finally:
            src.stop()
        assert landed, [m.text for m in gcs.messages("STATUSTEXT")]
        sent = tap.sm_updates()

    texts = [m.text for m in gcs.messages("STATUSTEXT")]
    assert texts == ["#" + s for s in order]  # each state announced once, spoken by QGC
    assert all(m.severity <= gcs.dialect.MAV_SEVERITY_NOTICE for m in gcs.messages("STATUSTEXT"))

    hbs = gcs.messages("HEARTBEAT")
    names = dict(state_names(0))
    seen_modes = []
    for hb in hbs:
        name = names[hb.custom_mode]
        if not seen_modes or seen_modes[-1] != name:
            seen_modes.append(name)
        armed = bool(hb.base_mode & aurora.MAV_MODE_FLAG_SAFETY_ARMED)
        assert armed == (name != "IDLE"), (name, hb)
        if name in ("BOOST", "BURNOUT", "APOGEE", "MAIN", "REDUNDANT"):
            assert hb.system_status == aurora.MAV_STATE_ACTIVE
        else:
            assert hb.system_status in (aurora.MAV_STATE_STANDBY, aurora.MAV_STATE_UNINIT)
    assert seen_modes == order

    landed_states = [m.landed_state for m in gcs.messages("EXTENDED_SYS_STATE")]
    dev = gcs.dialect
    for want in (dev.MAV_LANDED_STATE_ON_GROUND, dev.MAV_LANDED_STATE_TAKEOFF,
                 dev.MAV_LANDED_STATE_IN_AIR, dev.MAV_LANDED_STATE_LANDING):
        assert want in landed_states
    assert landed_states[-1] == dev.MAV_LANDED_STATE_ON_GROUND

    by_t = {m.timestamp_ms: m for m in sent}
    alts = gcs.messages("ALTITUDE")
    huds = gcs.messages("VFR_HUD")
    assert alts and huds
    for a in alts:
        m = by_t[a.time_usec // 1000]
        assert a.altitude_relative == pytest.approx(m.altitude_m, abs=1e-3)
        assert a.altitude_local == pytest.approx(m.altitude_m, abs=1e-3)
    peak = max(m.altitude_m for m in sent)
    assert max(a.altitude_relative for a in alts) == pytest.approx(peak, rel=0.05)
    climbs = sorted(h.climb for h in huds)
    assert climbs[-1] > 10 and climbs[0] < -3  # up on the motor, down under the chutes
    nvf = {m.name for m in gcs.messages("NAMED_VALUE_FLOAT")}
    assert nvf == {"accel", "accel_vert"}
    sys_status = gcs.messages("SYS_STATUS")
    assert sys_status
    last = sys_status[-1]  # the simulated rocket's sensors are all healthy: none failed
    assert last.onboard_control_sensors_enabled != 0
    assert last.onboard_control_sensors_health & last.onboard_control_sensors_enabled == (
        last.onboard_control_sensors_enabled)


@pytest.mark.parametrize(("flags", "healthy"), [
    (Status.make_flags(imu_ok=True, baro_ok=True, calibrated=True, log_ready=True), "all"),
    (Status.make_flags(baro_ok=True, calibrated=True, log_ready=True), "no-imu"),
    (Status.make_flags(imu_ok=True, calibrated=True), "no-baro-no-log"),
])
def test_sys_status_reports_the_status_flags(gcs: MavPeer, flags: int, healthy: str) -> None:
    dev = gcs.dialect
    imu = dev.MAV_SYS_STATUS_SENSOR_3D_GYRO | dev.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    baro = dev.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    log_bit = dev.MAV_SYS_STATUS_LOGGING
    prearm = dev.MAV_SYS_STATUS_PREARM_CHECK
    every = imu | baro | log_bit | prearm
    with running(gcs.port, sys_status_hz=0.5) as (_, d):
        before = gcs.wait_for("SYS_STATUS", timeout=WAIT)[0]
        d.dispatch(Status(5000, S.IDLE, 0, flags, origin="test"))
        after = gcs.wait_for("SYS_STATUS", lambda m: m.onboard_control_sensors_enabled != 0,
                             timeout=WAIT)
    # before any STATUS: sensors present but not enabled (unknown), so QGC shows no failure
    assert before.onboard_control_sensors_present == every
    assert before.onboard_control_sensors_enabled == 0
    s = after[0]
    assert s.onboard_control_sensors_present == every
    assert s.onboard_control_sensors_enabled == every
    # health: every subsystem bit (as ArduPilot: the geofence's too) but those that failed
    not_failed = dev.MAV_SYS_STATUS_EXTENSION_USED - 1
    assert before.onboard_control_sensors_health == not_failed
    failed = {"all": 0, "no-imu": imu | prearm, "no-baro-no-log": baro | log_bit | prearm}[healthy]
    assert s.onboard_control_sensors_health == not_failed & ~failed


def test_sys_status_without_a_battery_goes_where_it_reads_right() -> None:
    """MAVSDK reads SYS_STATUS's "not sent" voltage (65535) as a 65.535 V battery: while the
    rocket has no battery, its SYS_STATUS goes only where a ground station other than MAVSDK
    (known by its default identity 245/190) was heard — QGC gets the sensors' health, MAVSDK
    and a peer that never spoke get none; once a battery is known, every link gets it."""
    from backends.mavlink.ground_stations import MAVSDK_DEFAULT

    with MavPeer(255, 190, announce=True) as qgc, MavPeer(245, 190, announce=True) as mavsdk, \
            MavPeer(255, 191) as silent:
        b = MavlinkBackend(MavlinkOptions(
            endpoints=[f"udpout:127.0.0.1:{p.port}" for p in (qgc, mavsdk, silent)],
            sys_status_hz=5))
        d = Dispatcher([b])
        assert d.start() == []
        try:
            d.dispatch(Status(5000, S.IDLE, 0, Status.make_flags(
                imu_ok=True, baro_ok=True, calibrated=True, log_ready=True), origin="test"))
            router = b.router
            assert router is not None
            assert qgc.wait_until(lambda: any(MAVSDK_DEFAULT in lk.seen for lk in router.links),
                                  timeout=WAIT)  # the gateway has heard MAVSDK say who it is
            n = len(qgc.messages("SYS_STATUS"))
            assert len(qgc.wait_for("SYS_STATUS", count=n + 3, timeout=WAIT)) == n + 3
            assert mavsdk.messages("HEARTBEAT") and silent.messages("HEARTBEAT")  # on the air
            assert mavsdk.messages("SYS_STATUS") == [] and silent.messages("SYS_STATUS") == []
            assert all(m.voltage_battery == 65535 for m in qgc.messages("SYS_STATUS"))

            d.dispatch(Battery(7.9, battery_id=0, origin="test"))
            for peer in (qgc, mavsdk, silent):
                got = peer.wait_for("SYS_STATUS", lambda m: m.voltage_battery == 7900,
                                    timeout=WAIT)
                assert got, peer.mav.srcSystem
            assert all(m.voltage_battery == 7900 for m in mavsdk.messages("SYS_STATUS"))
        finally:
            d.close()


def test_error_state_and_stale_updates_have_defined_statuses(gcs: MavPeer) -> None:
    with running(gcs.port, heartbeat_hz=10, stale_after_s=0.5) as (_, d):
        d.dispatch(sm(S.ERROR, t=1000, armed=True))
        err = gcs.wait_for("HEARTBEAT", lambda m: m.custom_mode == S.ERROR, timeout=WAIT)
        stale = gcs.wait_for("HEARTBEAT", lambda m: m.system_status == aurora.MAV_STATE_UNINIT
                             and m.custom_mode == S.ERROR, timeout=WAIT)
        d.dispatch(sm(S.IDLE, t=2000))
        back = gcs.wait_for("HEARTBEAT", lambda m: m.custom_mode == S.IDLE
                            and m.system_status == aurora.MAV_STATE_STANDBY, timeout=WAIT)
    assert err[0].system_status == aurora.MAV_STATE_EMERGENCY
    assert stale and back
    text = gcs.messages("STATUSTEXT")
    assert [(t.text, t.severity) for t in text] == [
        ("#ERROR", aurora.MAV_SEVERITY_CRITICAL), ("#IDLE", aurora.MAV_SEVERITY_NOTICE)]


def test_dialect_messages_carry_both_revisions_losslessly() -> None:
    """AURORA_SM_UPDATE / AURORA_STATUS, decoded by a ground station with the Aurora dialect,
    give back exactly what was dispatched: the 36-byte revision's f32 values and the 64-byte
    revision's f64 values, awkward ones included."""
    awkward = [1 / 3, -0.0, 5e-324, 1.7976931348623157e308, math.pi, -2.5e-10, 123456.789]
    f64 = SmUpdate(0xFFFFFFF0, S.APOGEE, True, 0, *awkward, payload_len=64, reserved=7)
    f32 = decode_all(encode(SmUpdate(1234, S.BOOST, True, 0, *[1 / 3, -1.1, 2.2, 3.3e5, 0.1,
                                                               -0.2, 3.14159],
                                     payload_len=36)))[0]
    unknown = SmUpdate(99, 17, False, 5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, payload_len=64)
    nan = SmUpdate(100, S.MAIN, True, 0, math.nan, math.inf, -math.inf, 1.0, 2.0, 3.0, 4.0)
    st = Status(0xDEADBEEF, S.LANDED, 0, 0x1F, reserved=0xAB)
    with MavPeer(255, 190, dialect=aurora, announce=True) as gcs, \
            running(gcs.port, aurora_sm_update_hz=1000) as (_, d):
        for m in (f64, f32, unknown, nan):
            d.dispatch(m._replace(origin="test"))
        d.dispatch(st)
        got = gcs.wait_for("AURORA_SM_UPDATE", count=4, timeout=WAIT)
        stats = gcs.wait_for("AURORA_STATUS", timeout=WAIT)
    back = [sm_update_from_mavlink(g) for g in got]
    for orig, b in zip((f64, f32, unknown, nan), back, strict=True):
        want = orig.fields()
        have = b.fields()
        for k in want:
            if isinstance(want[k], float):
                assert struct.pack("<d", have[k]) == struct.pack("<d", want[k]), k
            else:
                assert have[k] == want[k], k
    assert back[1].payload_len == 36 and back[0].payload_len == 64
    assert status_from_mavlink(stats[0]).fields() == st.fields()


# -- configuration, flags and the default run ------------------------------------------------

def test_bad_endpoints_and_keys_are_one_clear_line() -> None:

    with pytest.raises(ConfigError,
                       match=r"backends\.mavlink\.endpoints: .*udpot:127\.0\.0\.1:14550"):
        config.parse({"backends": {"mavlink": {"endpoints": ["udpot:127.0.0.1:14550"]}}})
    with pytest.raises(ConfigError, match=r"backends\.mavlink\.endpoints: .*at least one"):
        config.parse({"backends": {"mavlink": {"endpoints": []}}})
    with pytest.raises(ConfigError, match=r"backends\.mavlink\.sysid"):
        config.parse({"backends": {"mavlink": {"sysid": 255}}})
    with pytest.raises(ConfigError, match=r"backends\.mavlink\.attitude_hz"):
        config.parse({"backends": {"mavlink": {"attitude_hz": -1}}})
    for bad in ("udpout:127.0.0.1", "tcp:host:port", "udpout:[::1]:70000", "serial:,9600",
                "serial:/dev/ttyUSB0,fast", "nonsense"):
        with pytest.raises(ValueError, match=r"\S"):
            MavlinkBackend(MavlinkOptions(endpoints=[bad]))


def test_an_endpoint_that_cannot_open_fails_the_backend_not_the_gateway() -> None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    try:
        b = MavlinkBackend(MavlinkOptions(endpoints=[f"udpin:127.0.0.1:{s.getsockname()[1]}"]))
        d = Dispatcher([b])
        failures = d.start()
        d.close()
    finally:
        s.close()
    assert len(failures) == 1 and "udpin:127.0.0.1" in failures[0][1]


def test_run_flags_set_the_endpoints_sysid_and_key() -> None:
    args = cli.build_parser().parse_args(
        ["run", "--mavlink", "udpin:0.0.0.0:14551", "--mavlink", "tcpin:0.0.0.0:5760",
         "--mavlink-sysid", "7"])
    cfg = cli.config_from_args(args)
    (part,) = [p for p in cfg.backends if p.name == "mavlink"]
    assert part.options["endpoints"] == ["udpin:0.0.0.0:14551", "tcpin:0.0.0.0:5760"]
    assert part.options["sysid"] == 7
    default = [p for p in config.embedded_default().backends if p.name == "mavlink"]
    assert default[0].options["endpoints"] == ["udpout:127.0.0.1:14550"]


def test_the_default_run_shows_the_rocket_to_a_qgc_on_this_machine() -> None:
    """``aurora-gateway run`` with no configuration streams to 127.0.0.1:14550."""
    try:
        qgc = MavPeer(255, 190, bind=("127.0.0.1", 14550), announce=True)
    except OSError as exc:  # pragma: no cover - another program holds QGC's port
        pytest.skip(f"UDP 127.0.0.1:14550 is in use here ({exc})")
    others = [n for n in registry.backend_names() if n != "mavlink"]
    argv = ["run", "--duration", "2.5", "--sim-speed", "10", "--status-interval", "0"]
    for n in others:
        argv += ["--disable", n]
    result: dict[str, int] = {}
    t0 = time.monotonic()
    runner = threading.Thread(target=lambda: result.setdefault("rc", cli.main(argv)))
    try:
        runner.start()
        first = qgc.wait_for("HEARTBEAT", timeout=WAIT)
        assert first, "no HEARTBEAT on 127.0.0.1:14550"
        assert qgc.wait_for("STATUSTEXT", lambda m: m.text == "#ARMED", timeout=WAIT)
        runner.join(WAIT)
    finally:
        qgc.close()
    assert result.get("rc") == 0
    assert qgc.timed("HEARTBEAT")[0][0] - t0 < WAIT


def test_mission_uploads_and_clears_are_refused_honestly(gcs: MavPeer) -> None:
    dev = gcs.dialect
    with running(gcs.port):
        assert gcs.wait_for("HEARTBEAT", timeout=WAIT)
        gcs.send(dev.MAVLink_mission_count_message(*US, 3, dev.MAV_MISSION_TYPE_FENCE))
        gcs.send(dev.MAVLink_mission_clear_all_message(*US, dev.MAV_MISSION_TYPE_MISSION))
        gcs.send(dev.MAVLink_mission_count_message(9, 1, 3, 0))  # not for us: no answer
        gcs.command(US, dev.MAV_CMD_REQUEST_MESSAGE, dev.MAVLINK_MSG_ID_HEARTBEAT)  # marker
        assert gcs.wait_for("COMMAND_ACK", timeout=WAIT)
        acks = gcs.wait_for("MISSION_ACK", count=2, timeout=WAIT)
    assert [(a.type, a.mission_type, a.target_system) for a in acks] == [
        (dev.MAV_MISSION_UNSUPPORTED, dev.MAV_MISSION_TYPE_FENCE, 255),
        (dev.MAV_MISSION_UNSUPPORTED, dev.MAV_MISSION_TYPE_MISSION, 255)]
    assert len(gcs.messages("MISSION_ACK")) == 2


class _RcRecorder(Backend):
    """Keeps the RcChannels the gateway hands on (a real peer on the dispatcher)."""

    def __init__(self) -> None:
        super().__init__("rc")
        self.rc: list[RcChannels] = []

    def routes(self) -> Routes:
        return Routes().on(RcChannels, self.rc.append)


def test_rc_overrides_reach_the_gateway_and_commands_go_out_as_rc_channels(gcs: MavPeer) -> None:
    dev = gcs.dialect
    rec = _RcRecorder()
    b = MavlinkBackend(MavlinkOptions(endpoints=[f"udpout:127.0.0.1:{gcs.port}"]))
    d = Dispatcher([b, rec])
    b.attach(GatewayContext(emit=d.dispatch))
    assert d.start() == []
    try:
        assert gcs.wait_for("HEARTBEAT", timeout=WAIT)
        # a ground station's sticks for the rocket: 0 releases a channel, UINT16_MAX ignores it
        gcs.send(dev.MAVLink_rc_channels_override_message(
            *US, 1100, 1900, 0, 65535, 1500, 0, 0, 0, *([0] * 10)))
        gcs.send(dev.MAVLink_manual_control_message(US[0], 1000, -1000, 500, 0, 0))
        gcs.send(dev.MAVLink_rc_channels_override_message(7, 1, *([1234] * 8), *([0] * 10)))
        assert gcs.wait_until(lambda: len(rec.rc) >= 2, WAIT)
        assert [m.channels_us for m in rec.rc] == [(1100, 1900, None, None, 1500),
                                                    (1000, 2000, 1500, 1500)]
        assert rec.rc[0].origin == b.name
        # commands the rocket's link received (an XBee air link's servos) go to the GCS
        d.dispatch(RcChannels((1000, None, 2000), origin="xbee"))
        assert gcs.wait_for("RC_CHANNELS", timeout=WAIT)
        out = gcs.messages("RC_CHANNELS")[-1]
        assert out.chancount == 3
        assert (out.chan1_raw, out.chan2_raw, out.chan3_raw, out.chan4_raw) == \
            (1000, 65535, 2000, 65535)
    finally:
        d.close()
