"""CRSF / ExpressLRS backend: the rocket as telemetry sensors on an EdgeTX radio.

Hooks turn each message into CRSF records and put them in per-frame-type mailboxes (never
blocking).  A scheduler thread picks the next frame at the per-type rates
(:mod:`backends.crsf.scheduler`) and submits it to a :class:`~gateway.link.LinkEngine` that
writes the receiver's UART (or a pty this backend creates).  A reader thread decodes what the
receiver sends back on the same port: link statistics become :class:`gateway.model.LinkStats`
messages handed to the gateway (so other backends can publish them), RC channels are decoded
and counted.

Mapping (what each gateway message feeds):

========================  =====================================================================
``SmUpdate``              attitude 0x1E (pitch, roll, yaw), baro altitude 0x09 (altitude +
                          velocity as vario), vario 0x07 (velocity), flight mode 0x21 (state
                          name, ``*`` when disarmed)
``Status``                flight mode 0x21 (state, armed flag, health marker ``!IMU`` /
                          ``!BARO`` / ``!CAL`` / ``!LOG`` for the first failing check)
``Position``              GPS 0x02 (altitude AMSL, ground speed, course, satellites)
``Battery``               battery 0x08 (battery 0); every battery's voltage in voltages 0x0E
                          once a second battery id appears
``VehicleState``          attitude, baro altitude + vario, vario, flight mode (mode text)
========================  =====================================================================
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from backends.crsf.decoder import Decoder
from backends.crsf.frames import (
    FRAME_ATTITUDE,
    FRAME_BARO_ALTITUDE,
    FRAME_BATTERY,
    FRAME_FLIGHT_MODE,
    FRAME_GPS,
    FRAME_VARIO,
    FRAME_VOLTAGES,
    MAX_VOLTAGES,
    SYNC_FC,
    SYNC_RADIO,
    SYNC_RX,
    Attitude,
    BaroAltitude,
    Battery,
    FlightMode,
    Gps,
    LinkStatistics,
    RcChannels,
    Vario,
    Voltages,
    encode,
    flight_mode_text,
)
from backends.crsf.ports import PtyPair, SharedSerial
from backends.crsf.scheduler import CHANGE_RING_DEPTH, Scheduler
from gateway import model
from gateway.backend import Backend, BackendError, Outcome
from gateway.config import Key, Schema
from gateway.link import LinkEngine

log = logging.getLogger(__name__)

PTY_URL = "pty"
DEFAULT_BAUD = 420000
#: The link engine's queue holds a burst of state changes; regular frames are only picked
#: while fewer than MAX_QUEUED are waiting, so a slow port delays the next (latest) value
#: instead of queueing stale ones.
ENGINE_QUEUE_DEPTH = CHANGE_RING_DEPTH + 4
MAX_QUEUED = 2
_HEALTH_CHECKS = (("imu_ok", "IMU"), ("baro_ok", "BARO"), ("calibrated", "CAL"),
                  ("log_ready", "LOG"))

ACCEPTED = Outcome.ACCEPTED


def health_marker(status: model.Status) -> str:
    """``!IMU`` etc. for the first failing health check of ``status``; "" when all pass."""
    for attr, code in _HEALTH_CHECKS:
        if not getattr(status, attr):
            return "!" + code
    return ""


class CrsfBackend(Backend):
    """Sends the rocket's telemetry as CRSF frames; reads link statistics back."""

    NAME = "crsf"
    CONFIG = Schema(
        url=Key(str, PTY_URL, "receiver UART: serial port or pyserial URL (/dev/ttyUSB0, "
                "socket://host:port, rfc2217://…); 'pty' = create a pseudo-terminal and log "
                "its path"),
        baudrate=Key(int, DEFAULT_BAUD, "UART speed: 420000 for ExpressLRS, 416666 for TBS",
                     minimum=1200),
        sync=Key(int, SYNC_FC, "address byte of the frames sent (0xC8 = flight controller)",
                 choices=(SYNC_FC, SYNC_RADIO, SYNC_RX)),
        pitch=Key(str, "nose-up", "which pitch is positive (Betaflight/INAV: nose-down)",
                  choices=("nose-up", "nose-down")),
        disarmed_suffix=Key(str, "*", "appended to the flight mode while disarmed; '' = none"),
        health_marker=Key(bool, True, "append !IMU/!BARO/!CAL/!LOG to the flight mode when "
                          "STATUS reports a failing check"),
        max_frames_per_s=Key(float, 20.0, "total frame rate cap", minimum=1, maximum=1000),
        refresh_s=Key(float, 2.0, "longest gap between two frames of one type",
                      minimum=0.2, maximum=15),
        hold_s=Key(float, 10.0, "stop re-sending a value not updated for this long, so the "
                   "radio shows it stale; 0 = never", minimum=0),
        attitude_hz=Key(float, 10.0, "attitude (0x1E) rate; 0 = off", minimum=0, maximum=100),
        altitude_hz=Key(float, 5.0, "baro altitude + vario (0x09) rate; 0 = off", minimum=0,
                        maximum=100),
        vario_hz=Key(float, 2.0, "vario (0x07) rate; 0 = off", minimum=0, maximum=100),
        flight_mode_hz=Key(float, 2.0, "flight mode (0x21) rate, plus at once on a change; "
                           "0 = off", minimum=0, maximum=100),
        gps_hz=Key(float, 2.0, "GPS (0x02) rate; 0 = off", minimum=0, maximum=100),
        battery_hz=Key(float, 1.0, "battery (0x08) rate; 0 = off", minimum=0, maximum=100),
        voltages_hz=Key(float, 1.0, "voltages (0x0E) rate; 0 = off", minimum=0, maximum=100),
        voltages_source_id=Key(int, 128, "source id of the voltages frame (EdgeTX shows ids "
                               "≥ 128 as a voltage array, lower ones as cells)", minimum=0,
                               maximum=255),
        link_stats_hz=Key(float, 5.0, "most link-statistics messages per second handed to the "
                          "other backends; 0 = none", minimum=0),
    )
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = {"url": PTY_URL}

    def __init__(
        self,
        url: str = PTY_URL,
        baudrate: int = DEFAULT_BAUD,
        sync: int = SYNC_FC,
        pitch: str = "nose-up",
        disarmed_suffix: str = "*",
        health_marker: bool = True,
        max_frames_per_s: float = 20.0,
        refresh_s: float = 2.0,
        hold_s: float = 10.0,
        attitude_hz: float = 10.0,
        altitude_hz: float = 5.0,
        vario_hz: float = 2.0,
        flight_mode_hz: float = 2.0,
        gps_hz: float = 2.0,
        battery_hz: float = 1.0,
        voltages_hz: float = 1.0,
        voltages_source_id: int = 128,
        link_stats_hz: float = 5.0,
        name: str | None = None,
        sink: Callable[[Any], Any] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(name)
        if not url:
            raise ValueError("url: expected a serial port, a pyserial URL or 'pty'")
        if pitch not in ("nose-up", "nose-down"):
            raise ValueError(f"pitch: expected 'nose-up' or 'nose-down', got {pitch!r}")
        if len(disarmed_suffix) > 4 or not disarmed_suffix.isascii():
            raise ValueError(f"disarmed_suffix: expected at most 4 ASCII characters, got "
                             f"{disarmed_suffix!r}")
        self.url = url
        self.baudrate = baudrate
        self.sync = sync
        self.pitch_sign = 1.0 if pitch == "nose-up" else -1.0
        self.disarmed_suffix = disarmed_suffix
        self.use_health_marker = health_marker
        self.voltages_source_id = voltages_source_id
        self.link_stats_interval_s = 1.0 / link_stats_hz if link_stats_hz > 0 else math.inf
        self._clock = clock
        self._sink = sink
        self.scheduler = Scheduler(
            {FRAME_ATTITUDE: attitude_hz, FRAME_BARO_ALTITUDE: altitude_hz,
             FRAME_VARIO: vario_hz, FRAME_FLIGHT_MODE: flight_mode_hz, FRAME_GPS: gps_hz,
             FRAME_BATTERY: battery_hz, FRAME_VOLTAGES: voltages_hz},
            max_rate_hz=max_frames_per_s, refresh_s=refresh_s, hold_s=hold_s, clock=clock)
        self.decoder = Decoder()
        self.pty: PtyPair | None = None
        self._serial: SharedSerial | None = None
        self.engine = LinkEngine(self._open, name=self.name, queue_depth=ENGINE_QUEUE_DEPTH)
        # state kept between hooks (the dispatcher never calls hooks concurrently)
        self._health = ""
        self._mode_text: str | None = None
        self._volts: dict[int, float] = {}
        # scheduler / reader threads
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._threads: list[threading.Thread] = []
        # counters
        self.encode_errors = 0
        self.submit_failures = 0
        self.link_stats_rx = 0
        self.link_stats_emitted = 0
        self.emit_errors = 0
        self.rc_frames = 0
        self.rx_other = 0
        self.voltages_ignored = 0
        self.last_link_stats: LinkStatistics | None = None
        self.rc_channels: tuple[int, ...] | None = None
        self._last_stats_emit = -math.inf

    # -- configuration ---------------------------------------------------------------------

    @classmethod
    def add_cli_arguments(cls, parser: argparse.ArgumentParser) -> None:
        parser.add_argument("--crsf", metavar="URL",
                            help="CRSF backend: the ExpressLRS receiver's UART (serial port "
                                 "or pyserial URL), or 'pty' for a pseudo-terminal")
        parser.add_argument("--crsf-baud", type=int, metavar="N",
                            help=f"CRSF backend: UART speed (default {DEFAULT_BAUD})")

    @classmethod
    def cli_options(cls, args: argparse.Namespace) -> dict[str, Any] | None:
        url = getattr(args, "crsf", None)
        baud = getattr(args, "crsf_baud", None)
        if url is None and baud is None:
            return None
        opts: dict[str, Any] = {}
        if url is not None:
            opts["url"] = url
        if baud is not None:
            opts["baudrate"] = baud
        return opts

    def attach(self, emit: Callable[[Any], Any]) -> None:
        """Where decoded link statistics go (the gateway's ingest; or set ``sink=``)."""
        self._sink = emit

    # -- life cycle ------------------------------------------------------------------------

    def _open(self) -> Any:
        if self.pty is not None:
            return self.pty.transport()
        assert self._serial is not None
        return self._serial.open()

    def init(self) -> None:
        if self._threads:
            return
        if self.url == PTY_URL:
            try:
                self.pty = PtyPair()
            except OSError as exc:
                raise BackendError(f"cannot create a pseudo-terminal: {exc}") from exc
            log.info("%s: CRSF telemetry on %s (attach a reader, e.g. python -m "
                     "backends.crsf.monitor %s)", self.name, self.pty.path, self.pty.path)
        else:
            self._serial = SharedSerial(self.url, self.baudrate, self.name)
        self._stop = threading.Event()
        self.engine.start()
        for target, what in ((self._schedule_loop, "tx"), (self._read_loop, "rx")):
            t = threading.Thread(target=target, args=(self._stop,), name=f"{self.name}-{what}",
                                 daemon=True)
            t.start()
            self._threads.append(t)

    @property
    def pty_path(self) -> str | None:
        """The pseudo-terminal a reader attaches to (``url = "pty"`` only)."""
        return self.pty.path if self.pty is not None else None

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        for t in self._threads:
            t.join(0.5)
        self._threads = []
        # state changes not sent yet (the last one of a flight) still go out
        while (item := self.scheduler.take_change()) is not None:
            self._send(item[1])
        self.engine.close(0.3)
        if self.pty is not None:
            self.pty.close()

    # -- hooks (never block: mailboxes only) -----------------------------------------------

    def _outcome(self) -> Outcome:
        return ACCEPTED if self.engine.connected else Outcome.NOT_READY

    def _flight_mode(self, name: str, armed: bool) -> None:
        marker = self._health if self.use_health_marker else ""
        text = flight_mode_text(name, armed, disarmed_suffix=self.disarmed_suffix, marker=marker)
        rec = FlightMode(text)
        if text != self._mode_text:
            self._mode_text = text
            if self.scheduler.publish_change(FRAME_FLIGHT_MODE, rec):
                self._wake.set()
        else:
            self.scheduler.publish(FRAME_FLIGHT_MODE, rec)

    def send_sm_update(self, m: model.SmUpdate) -> Outcome:
        pub = self.scheduler.publish
        pub(FRAME_ATTITUDE, Attitude(m.pitch_rad * self.pitch_sign, m.roll_rad, m.yaw_rad))
        pub(FRAME_BARO_ALTITUDE, BaroAltitude(m.altitude_m, m.velocity_mps))
        pub(FRAME_VARIO, Vario(m.velocity_mps))
        self._flight_mode(m.state_name, m.armed)
        return self._outcome()

    def send_status(self, s: model.Status) -> Outcome:
        self._health = health_marker(s)
        self._flight_mode(s.state_name, s.armed)
        return self._outcome()

    def send_position(self, p: model.Position) -> Outcome:
        kmh = None if p.ground_speed_mps is None else p.ground_speed_mps * 3.6
        self.scheduler.publish(FRAME_GPS, Gps(p.lat_deg, p.lon_deg, kmh, p.course_deg,
                                              p.alt_amsl_m, p.satellites))
        return self._outcome()

    def send_battery(self, b: model.Battery) -> Outcome:
        if b.battery_id == 0:
            self.scheduler.publish(FRAME_BATTERY, Battery(b.voltage_v, b.current_a,
                                                          b.consumed_mah, b.remaining_pct))
        if 0 <= b.battery_id < MAX_VOLTAGES:
            self._volts[b.battery_id] = b.voltage_v
        else:
            self.voltages_ignored += 1
        if any(i != 0 for i in self._volts):
            n = max(self._volts) + 1
            self.scheduler.publish(FRAME_VOLTAGES, Voltages(
                self.voltages_source_id, tuple(self._volts.get(i) for i in range(n))))
        return self._outcome()

    def send_vehicle_state(self, v: model.VehicleState) -> Outcome:
        pub = self.scheduler.publish
        if not (v.roll_rad is None and v.pitch_rad is None and v.yaw_rad is None):
            pitch = None if v.pitch_rad is None else v.pitch_rad * self.pitch_sign
            pub(FRAME_ATTITUDE, Attitude(pitch, v.roll_rad, v.yaw_rad))
        if v.altitude_m is not None:
            pub(FRAME_BARO_ALTITUDE, BaroAltitude(v.altitude_m, v.climb_mps))
        if v.climb_mps is not None:
            pub(FRAME_VARIO, Vario(v.climb_mps))
        if v.mode:
            self._flight_mode(v.mode, v.armed)
        return self._outcome()

    # -- scheduler thread ------------------------------------------------------------------

    def _schedule_loop(self, stop: threading.Event) -> None:
        sched, clock = self.scheduler, self._clock
        engine = self.engine
        while not stop.is_set():
            self._wake.clear()
            now = clock()
            item = sched.take_change(now)
            if item is None and engine.queued() < MAX_QUEUED:
                item = sched.take(now)
            if item is not None:
                self._send(item[1])
                continue
            delay = sched.next_due(now) - now if engine.queued() < MAX_QUEUED else 0.005
            self._wake.wait(min(max(delay, 0.001), 0.05))

    def _send(self, record: Any) -> None:
        try:
            frame = encode(record, self.sync)
        except (ValueError, TypeError, OverflowError) as exc:
            self.encode_errors += 1
            if self.encode_errors == 1:
                log.warning("%s: cannot encode %r: %s", self.name, record, exc)
            return
        if self.engine.submit(frame, rate_limited=False) is not ACCEPTED:
            self.submit_failures += 1

    # -- reader thread ---------------------------------------------------------------------

    def _read_loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            if self.pty is not None:
                data = self.pty.read(stop)
            elif self._serial is not None:
                data = self._serial.read(stop)
            else:
                return
            if data:
                self.feed(data)

    def feed(self, data: bytes) -> None:
        """Handle bytes received from the receiver (the reader thread calls this)."""
        for rec in self.decoder.feed(data):
            if isinstance(rec, LinkStatistics):
                self.link_stats_rx += 1
                self.last_link_stats = rec
                self._emit_link_stats(rec)
            elif isinstance(rec, RcChannels):
                self.rc_frames += 1
                self.rc_channels = rec.channels
            else:
                self.rx_other += 1

    def _emit_link_stats(self, rec: LinkStatistics) -> None:
        sink = self._sink
        if sink is None or self.link_stats_interval_s == math.inf:
            return
        now = self._clock()
        if now - self._last_stats_emit < self.link_stats_interval_s:
            return
        self._last_stats_emit = now
        msg = model.LinkStats(
            rssi_dbm=float(rec.uplink_rssi_dbm),
            link_quality_pct=rec.uplink_link_quality_pct,
            snr_db=float(rec.uplink_snr_db),
            tx_power_mw=rec.uplink_tx_power_mw,
            downlink_rssi_dbm=float(rec.downlink_rssi_dbm),
            downlink_link_quality_pct=rec.downlink_link_quality_pct,
            downlink_snr_db=float(rec.downlink_snr_db),
            rf_mode=rec.rf_mode,
            antenna=rec.active_antenna,
            origin=self.name,
        )
        try:
            sink(msg)
        except Exception:
            self.emit_errors += 1
            if self.emit_errors == 1:
                log.exception("%s: handing link statistics to the gateway failed", self.name)
            return
        self.link_stats_emitted += 1

    # -- reporting -------------------------------------------------------------------------

    def stats(self) -> dict[str, int | float]:
        e = self.engine.stats
        d = self.decoder.stats
        out: dict[str, int | float] = {
            "sent": e.sent_frames,
            "sent_bytes": e.sent_bytes,
            "dropped": e.dropped + self.scheduler.changes_dropped,
            "connected": int(self.engine.connected),
            "rx_frames": d.frames,
            "rx_crc_errors": d.crc_failures,
            "rx_bad_lengths": d.bad_lengths,
            "rx_bytes_skipped": d.bytes_skipped,
            "link_stats": self.link_stats_rx,
            "link_stats_emitted": self.link_stats_emitted,
            "rc_frames": self.rc_frames,
            "rx_other": self.rx_other,
        }
        if self.encode_errors:
            out["encode_errors"] = self.encode_errors
        if self.emit_errors:
            out["emit_errors"] = self.emit_errors
        if self.pty is not None:
            out["pty_flushes"] = self.pty.flushes
            out["pty_dropped_bytes"] = self.pty.dropped_bytes
        out.update(self.scheduler.stats())
        return out
