"""CRSF / ExpressLRS backend: the rocket as telemetry sensors on an EdgeTX radio.

Handlers turn each message into CRSF records and put them in per-frame-type mailboxes (never
blocking; an update's records are made when they are sent, not for each update).  One
:class:`~gateway.io.port.PortEngine` owns the receiver's UART (a serial port or pyserial URL,
or the pseudo-terminal this backend creates for ``url = "pty"``) and everything else runs on
its thread, so the backend starts no thread of its own:

* **sending**: the scheduler (:mod:`backends.crsf.scheduler`) runs on the engine's timers; it
  picks the next frame at the per-type rates and submits it, then sleeps until the next one is
  due.  A state change wakes it at once (``engine.call_soon``, from the handler's thread), and
  so does the first value published while it had nothing to send.  It runs only while the
  port is up: a state change published before the port opens (or while it is down) waits in
  the scheduler's change ring and goes out, in order, as soon as the port is up, so the first
  flight state is never lost to a port that is still opening;
* **receiving**: the engine reads what the receiver sends back into the sans-I/O
  :class:`~backends.crsf.decoder.Decoder`; link statistics become
  :class:`gateway.model.LinkStats` messages handed to the gateway (so other backends can
  publish them), RC channels are decoded and counted.

The link carries one vehicle: the one named by ``vehicle`` in ``[backends.crsf]``, or else the
first source's (:class:`gateway.vehicles.VehicleSelector`); every handler first drops another
vehicle's message (counted as ``other_vehicles``).  The RC channels and link statistics it hands
to the gateway carry that vehicle's name once known.

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

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

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
from backends.crsf.options import PTY_URL, CrsfOptions
from backends.crsf.ports import PtyPair
from backends.crsf.scheduler import CHANGE_RING_DEPTH, Scheduler
from gateway import model
from gateway.backend import Backend, BackendError, GatewayContext, Outcome, Routes
from gateway.io.ioloop import Timer
from gateway.io.port import PortEngine
from gateway.io.transport import open_serial
from gateway.vehicles import VehicleSelector

log = logging.getLogger(__name__)

#: The port engine's queue holds a burst of state changes; regular frames are only picked
#: while fewer than MAX_QUEUED are waiting, so a slow port delays the next (latest) value
#: instead of queueing stale ones.
ENGINE_QUEUE_DEPTH = CHANGE_RING_DEPTH + 4
MAX_QUEUED = 2
BUSY_RETRY_S = 0.005  # the port is still writing: look again this soon
MIN_WAIT_S = 0.001
WRITE_TIMEOUT_S = 0.5  # a serial write stuck longer fails (and the port is reopened)
CLOSE_TIMEOUT_S = 0.5
#: The receiver's RC frames come at its packet rate (up to 1 kHz): unchanged sticks are passed
#: on to the gateway at most this often.
RC_EMIT_INTERVAL_S = 0.02
_HEALTH_CHECKS = (("imu_ok", "IMU"), ("baro_ok", "BARO"), ("calibrated", "CAL"),
                  ("log_ready", "LOG"))

ACCEPTED = Outcome.ACCEPTED
#: flight-mode records kept by (state machine, state, armed, marker)
MODES_KEPT = 1024


def _baro_altitude(m: model.SmUpdate) -> BaroAltitude:
    return BaroAltitude(m.altitude_m, m.velocity_mps)


def _vario(m: model.SmUpdate) -> Vario:
    return Vario(m.velocity_mps)


def health_marker(status: model.Status) -> str:
    """``!IMU`` etc. for the first failing health check of ``status``; "" when all pass."""
    for attr, code in _HEALTH_CHECKS:
        if not getattr(status, attr):
            return "!" + code
    return ""


class CrsfBackend(Backend):
    """Sends the rocket's telemetry as CRSF frames; reads link statistics back."""

    NAME = "crsf"
    OPTIONS = CrsfOptions
    EMBEDDED_DEFAULT = CrsfOptions.EMBEDDED_DEFAULT

    def __init__(self, options: CrsfOptions | None = None, name: str | None = None,
                 sink: Callable[[Any], Any] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(name)
        options = options or CrsfOptions()
        self.url = options.url
        self.baudrate = options.baudrate
        self.sync = options.sync
        self.pitch_sign = 1.0 if options.pitch == "nose-up" else -1.0
        self.disarmed_suffix = options.disarmed_suffix
        self.use_health_marker = options.health_marker
        self.voltages_source_id = options.voltages_source_id
        self.link_stats_interval_s = (1.0 / options.link_stats_hz if options.link_stats_hz > 0
                                      else math.inf)
        self._clock = clock
        self._sink = sink
        #: the vehicle this link serves
        self.selector = VehicleSelector(options.vehicle)
        self.other_vehicles = 0
        self.scheduler = Scheduler(
            {FRAME_ATTITUDE: options.attitude_hz, FRAME_BARO_ALTITUDE: options.altitude_hz,
             FRAME_VARIO: options.vario_hz, FRAME_FLIGHT_MODE: options.flight_mode_hz,
             FRAME_GPS: options.gps_hz, FRAME_BATTERY: options.battery_hz,
             FRAME_VOLTAGES: options.voltages_hz},
            max_rate_hz=options.max_frames_per_s, refresh_s=options.refresh_s,
            hold_s=options.hold_s, clock=clock)
        self.decoder = Decoder()
        self.pty: PtyPair | None = None
        self.engine = PortEngine(self._open, name=self.name, protocol=self.decoder,
                                 on_event=self._on_record, on_link=self._on_link,
                                 queue_depth=ENGINE_QUEUE_DEPTH)
        # state kept between handlers (the dispatcher never calls them concurrently)
        self._health = ""
        self._mode_text: str | None = None
        self._modes: dict[tuple[int, int, bool, str], FlightMode] = {}
        self._volts: dict[int, float] = {}
        # the scheduler on the engine's thread: its next run, and whether it sleeps with
        # nothing to send (then the next value published wakes it)
        self._timer: Timer | None = None
        self._idle = True
        self._started = False
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
        self.rc_emitted = 0
        self._last_rc: tuple[int, ...] | None = None
        self._last_rc_emit = -math.inf
        self._last_stats_emit = -math.inf

    # -- configuration ---------------------------------------------------------------------

    def attach(self, context: GatewayContext) -> None:
        """Where decoded link statistics go (the gateway's ingest; or set ``sink=``), and
        which vehicle is served by default (the first source's)."""
        super().attach(context)
        self._sink = context.emit
        self.selector.attach(context, f"backends.{self.name}")

    # -- life cycle ------------------------------------------------------------------------

    def _open(self) -> Any:
        """The engine's opener (it runs off the engine's thread)."""
        if self.pty is not None:
            return self.pty.port()
        port = open_serial(self.url, self.baudrate, timeout=0, write_timeout=WRITE_TIMEOUT_S)
        if self.engine.stats.connects == 0:
            log.info("%s: %s open at %d baud", self.name, self.url, self.baudrate)
        return port

    def init(self) -> None:
        if self._started:
            return
        if self.url == PTY_URL and (self.pty is None or self.pty.closed):
            try:
                self.pty = PtyPair()
            except OSError as exc:
                raise BackendError(f"cannot create a pseudo-terminal: {exc}") from exc
            log.info("%s: CRSF telemetry on %s (attach a reader, e.g. python -m "
                     "backends.crsf.monitor %s)", self.name, self.pty.path, self.pty.path)
        self._idle = False  # the port coming up runs the scheduler
        self._started = True
        self.engine.start()

    @property
    def pty_path(self) -> str | None:
        """The pseudo-terminal a reader attaches to (``url = "pty"`` only)."""
        return self.pty.path if self.pty is not None else None

    def close(self) -> None:
        """Send the state changes not sent yet (the last one of a flight), then close the
        port (and the pty); safe twice."""
        if self._started:
            self._started = False
            done = threading.Event()

            def last_changes() -> None:
                try:
                    self._cancel_timer()
                    while self.engine.connected and (item := self.scheduler.take_change()):
                        self._send(item[1])
                finally:
                    done.set()

            if self.engine.loop.in_loop_thread:
                last_changes()
            elif self.engine.loop.running:
                self.engine.call_soon(last_changes)
                done.wait(CLOSE_TIMEOUT_S)
            self.engine.close(CLOSE_TIMEOUT_S)
        if self.pty is not None:
            self.pty.close()

    # -- handlers (never block: mailboxes, and at most a hand-over to the engine) ------------

    def _wake(self) -> None:
        """Run the scheduler on the engine's thread soon (from a handler's thread)."""
        if self._started:
            self._idle = False
            self.engine.call_soon(self._pump)

    def _published(self) -> Outcome:
        """A handler published values: wake the scheduler if it sleeps with nothing to send;
        the handler's outcome."""
        if self._idle:
            self._wake()
        return ACCEPTED if self.engine.connected else Outcome.NOT_READY

    def _flight_mode(self, name: str, armed: bool) -> None:
        marker = self._health if self.use_health_marker else ""
        text = flight_mode_text(name, armed, disarmed_suffix=self.disarmed_suffix, marker=marker)
        self._publish_mode(FlightMode(text))

    def _update_mode(self, m: model.SmUpdate) -> None:
        """An update's flight mode: the record made once per (state machine, state, armed,
        marker), not per update (at 25k updates/s the text is the same for seconds)."""
        key = (m.sm_type, m.state, m.armed, self._health if self.use_health_marker else "")
        rec = self._modes.get(key)
        if rec is None:
            if len(self._modes) >= MODES_KEPT:  # (bounded: a peer may send any byte)
                self._modes.clear()
            marker = key[3]
            rec = self._modes[key] = FlightMode(flight_mode_text(
                m.state_name, m.armed, disarmed_suffix=self.disarmed_suffix, marker=marker))
        self._publish_mode(rec)

    def _publish_mode(self, rec: FlightMode) -> None:
        text = rec.text
        if text != self._mode_text:
            self._mode_text = text
            if self.scheduler.publish_change(FRAME_FLIGHT_MODE, rec):
                self._wake()
        else:
            self.scheduler.publish(FRAME_FLIGHT_MODE, rec)

    def routes(self) -> Routes:
        return (Routes().on(model.SmUpdate, self.send_sm_update)
                .on(model.Status, self.send_status)
                .on(model.Position, self.send_position)
                .on(model.Battery, self.send_battery)
                .on(model.VehicleState, self.send_vehicle_state))

    def _other(self) -> Outcome:
        """Another vehicle's message: not for this link (counted, not an error)."""
        self.other_vehicles += 1
        return ACCEPTED

    def send_sm_update(self, m: model.SmUpdate) -> Outcome:
        if not self.selector.accepts(m):
            return self._other()
        # the records are made when the scheduler sends them (20 a second), not per update
        lazy = self.scheduler.publish_lazy
        lazy(FRAME_ATTITUDE, self._attitude, m)
        lazy(FRAME_BARO_ALTITUDE, _baro_altitude, m)
        lazy(FRAME_VARIO, _vario, m)
        self._update_mode(m)
        return self._published()

    def _attitude(self, m: model.SmUpdate) -> Attitude:
        return Attitude(m.pitch_rad * self.pitch_sign, m.roll_rad, m.yaw_rad)

    def send_status(self, s: model.Status) -> Outcome:
        if not self.selector.accepts(s):
            return self._other()
        self._health = health_marker(s)
        self._flight_mode(s.state_name, s.armed)
        return self._published()

    def send_position(self, p: model.Position) -> Outcome:
        if not self.selector.accepts(p):
            return self._other()
        kmh = None if p.ground_speed_mps is None else p.ground_speed_mps * 3.6
        self.scheduler.publish(FRAME_GPS, Gps(p.lat_deg, p.lon_deg, kmh, p.course_deg,
                                              p.alt_amsl_m, p.satellites))
        return self._published()

    def send_battery(self, b: model.Battery) -> Outcome:
        if not self.selector.accepts(b):
            return self._other()
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
        return self._published()

    def send_vehicle_state(self, v: model.VehicleState) -> Outcome:
        if not self.selector.accepts(v):
            return self._other()
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
        return self._published()

    # -- the engine's thread: scheduler and receiver input -----------------------------------

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _on_link(self, up: bool) -> None:
        """The port came up (send what waits, starting with pending state changes) or went
        down (the scheduler sleeps; values and changes wait in its mailboxes and ring)."""
        if up:
            self._pump()
        else:
            self._cancel_timer()
            self._idle = False  # nothing to wake while down: the port coming up runs it

    def _pump(self) -> None:
        """Send the pending state changes and the frame due now, if any; then sleep until the
        next one is due (a timer), or until a value is published (idle)."""
        self._cancel_timer()
        engine, sched = self.engine, self.scheduler
        if not self._started or not engine.connected:
            return
        self._idle = True  # before looking: a value published from here on wakes us again
        now = self._clock()
        while True:
            item = sched.take_change(now)
            if item is None:
                if engine.queued() >= MAX_QUEUED:  # the port is still writing
                    self._idle = False
                    self._timer = engine.call_later(BUSY_RETRY_S, self._pump)
                    return
                item = sched.take(now)
                if item is None:
                    break
            self._send(item[1])
            if not engine.connected:
                return  # the write failed: the port coming back runs the scheduler again
        due = sched.next_due(now)
        if due == math.inf:
            return  # nothing to send until a value is published
        self._idle = False
        self._timer = engine.call_later(max(due - now, MIN_WAIT_S), self._pump)

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

    def feed(self, data: bytes) -> None:
        """Handle bytes received from the receiver (the engine feeds its decoder directly)."""
        for rec in self.decoder.feed(data):
            self._on_record(rec)

    def _on_record(self, rec: Any) -> None:
        """One record the receiver sent."""
        if isinstance(rec, LinkStatistics):
            self.link_stats_rx += 1
            self.last_link_stats = rec
            self._emit_link_stats(rec)
        elif isinstance(rec, RcChannels):
            self.rc_frames += 1
            self.rc_channels = rec.channels
            self._emit_rc(rec)
        else:
            self.rx_other += 1

    def _emit_rc(self, rec: RcChannels) -> None:
        """The pilot's sticks as a gateway message (for an XBee ground link to send up, a
        MAVLink ground station to show), at most every ``RC_EMIT_INTERVAL_S`` unless they
        moved."""
        sink = self._sink
        if sink is None:
            return
        now = self._clock()
        if rec.channels == self._last_rc and now - self._last_rc_emit < RC_EMIT_INTERVAL_S:
            return
        self._last_rc, self._last_rc_emit = rec.channels, now
        us = tuple(round(v) for v in rec.microseconds())
        try:
            sink(model.RcChannels(us, origin=self.name, vehicle=self.selector.chosen))
        except Exception:
            self.emit_errors += 1
            if self.emit_errors == 1:
                log.exception("%s: handing RC channels to the gateway failed", self.name)
            return
        self.rc_emitted += 1

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
            vehicle=self.selector.chosen,
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
        up = int(self.engine.connected)
        out: dict[str, int | float] = {
            "sent": e.sent_frames,
            "sent_bytes": e.sent_bytes,
            "dropped": e.dropped + self.scheduler.changes_dropped,
            "dropped_not_ready": e.dropped_not_ready,
            "dropped_queue_full": e.dropped_queue_full,
            "dropped_changes": self.scheduler.changes_dropped,
            "errors": e.errors + self.encode_errors + self.emit_errors,
            "link": up,
            "connected": up,
            "disconnects": e.disconnects,
            "rx_frames": d.frames,
            "rx_crc_errors": d.crc_failures,
            "rx_bad_lengths": d.bad_lengths,
            "rx_bytes_skipped": d.bytes_skipped,
            "link_stats": self.link_stats_rx,
            "link_stats_emitted": self.link_stats_emitted,
            "rc_frames": self.rc_frames,
            "rc_emitted": self.rc_emitted,
            "rx_other": self.rx_other,
            "other_vehicles": self.other_vehicles,
        }
        if self.encode_errors:
            out["encode_errors"] = self.encode_errors
        if self.emit_errors:
            out["emit_errors"] = self.emit_errors
        if self.pty is not None:
            out["pty_flushes"] = self.pty.flushes
            out["pty_discarded_bytes"] = self.pty.discarded_bytes
            out["pty_dropped_bytes"] = self.pty.dropped_bytes
        out.update(self.scheduler.stats())
        return out
