"""UAVTalk in: a LibrePilot (16.09) flight controller as a gateway source.

The gateway plays the ground station: a :class:`~.telemetry.GcsSession` (handshake every 2 s,
the OBJ_REQ walk after connecting, 8 s silence timeout) runs on a
:class:`gateway.io.port.PortEngine` around a TCP connection (``tcp:HOST:PORT``) or a serial
port / pyserial URL (``DEVICE[,BAUD]``), reopened with backoff.  The source is the engine's
protocol object: received bytes go through the :class:`~.codec.Decoder` into the session, and a
timer on the engine ticks the session and writes its ``outgoing()``.

The objects received become gateway messages (``origin`` = the source's name, ``via`` =
``"uavtalk"``, ``vehicle`` = the source's vehicle):

* :class:`~gateway.model.VehicleState`: armed (FlightStatus.Armed = Armed), mode (the name of
  FlightStatus.FlightMode's option; ``custom_mode`` its index), attitude (AttitudeState's
  Roll/Pitch/Yaw, degrees → radians), altitude (BaroSensor.Altitude, else −PositionState.Down).
  Sent once FlightStatus is known, at most ``rate_hz`` per second, and at once when armed or
  the mode changes;
* :class:`~gateway.model.Position` from GPSPositionSensor (Latitude/Longitude deg×1e7,
  Altitude m above sea level, Groundspeed m/s, Heading deg, Satellites, Status → fix type
  0 no GPS, 1 no fix, 2 2D, 3 3D — MAVLink's numbering), at most ``rate_hz``; none without a fix;
* :class:`~gateway.model.Battery` from FlightBatteryState (Voltage V, Current A,
  ConsumedEnergy mAh).

One vehicle per source: UAVTalk has no sender address (a packet is a sync byte, type, length,
object id, instance id, data and CRC), and a telemetry link (a serial port, an OPLink radio
pair, a TCP connection) joins one flight controller to one ground station, so everything a
source hears is one flight controller, named by the source's ``vehicle`` (``--source
NAME=URL``, ``vehicle = "NAME"``).  Several flight controllers are several sources.

Link up/down is nothing special: the gateway's monitor sees the messages; the session's state
changes are counted.  An object that fails to convert is counted, never raised.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from gateway.io.backoff import Backoff
from gateway.io.burstlog import BurstLog
from gateway.io.endpoints import SERIAL, TCP, Endpoint, parse_endpoint
from gateway.io.port import REOPEN_FIRST_S, PortEngine
from gateway.io.transport import open_serial, open_tcp_client
from gateway.model import Battery, Position, VehicleState
from gateway.outcome import Outcome
from gateway.sources import Source

from .codec import Decoder
from .objects import ObjectSet
from .options import UavtalkSourceOptions
from .telemetry import GcsSession, Status, TelemetryStats

log = logging.getLogger(__name__)

VIA_UAVTALK = "uavtalk"
TICK_S = 0.05
"""How often the session is ticked (its timeouts are 250 ms and up)."""
ARMED = 2  # FlightStatus.Armed: Disarmed, Arming, Armed
MIN_FIX = 2  # GPSPositionSensor.Status: NoGPS, NoFix, Fix2D, Fix3D


#: What the flight controller may be reached by (the grammar: :mod:`gateway.io.endpoints`).
URL_KINDS = (TCP, SERIAL)


def parse_url(url: str) -> Endpoint:
    """``tcp:[HOST:]PORT`` or ``[serial:]DEVICE[,BAUD]`` (baudrate 0: none given); raises
    :class:`~gateway.io.endpoints.EndpointError` naming the mistake."""
    return parse_endpoint(url, URL_KINDS)


class _Gate:
    """At most ``hz`` events a second (a minimum interval; ``hz`` ≤ 0: every event)."""

    __slots__ = ("_last", "interval")

    def __init__(self, hz: float) -> None:
        self.interval = 1.0 / hz if hz > 0 else 0.0
        self._last: float | None = None

    def ready(self, now: float) -> bool:
        if self._last is not None and now - self._last < self.interval:
            return False
        self._last = now
        return True


class UavtalkSource(Source):
    """A LibrePilot flight controller as a gateway source (``[[sources]] type = "uavtalk"``)."""

    NAME = "uavtalk"
    OPTIONS = UavtalkSourceOptions
    NAME_FORMAT = "uavtalk:{url}"

    def __init__(self, options: UavtalkSourceOptions, name: str | None = None, *,
                 objects: ObjectSet | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(name or f"uavtalk:{options.url}")
        self.url = options.url
        spec = parse_url(options.url)
        self.kind = spec.kind
        self.host, self.port_number = spec.host, spec.port
        self.device = spec.device
        self.baudrate = spec.baudrate or options.baudrate
        self.rate_hz = options.rate_hz
        self.objects = objects or ObjectSet.load()
        self.clock = clock
        self.decoder = Decoder(self.objects.data_length)
        self.session = self._new_session()
        self._retired = TelemetryStats()  # the counters of sessions of earlier connections
        self._lock = threading.Lock()  # the session swap against stats()
        self._mode_options = self.objects.by_name("FlightStatus").field("FlightMode").options
        self._state_gate = _Gate(options.rate_hz)
        self._position_gate = _Gate(options.rate_hz)
        self._out: list[Any] = []
        self._timer: Any = None
        self._last_state = self.session.state
        self._logs: dict[str, BurstLog] = {}
        # what VehicleState is built from
        self.armed: bool | None = None
        self.flight_mode: int | None = None
        self.attitude: tuple[float, float, float] | None = None
        self.baro_alt_m: float | None = None
        self.position_alt_m: float | None = None
        self.counts = {"objects": 0, "bad_objects": 0, "vehicle_states": 0, "positions": 0,
                       "batteries": 0, "no_fix": 0, "link_changes": 0, "write_drops": 0}
        self.engine = PortEngine(self._open, name=f"source {self.name}", protocol=self,
                                 on_event=self.emit, on_link=self._on_link, queue_depth=64,
                                 backoff=Backoff(REOPEN_FIRST_S,
                                                 max(REOPEN_FIRST_S, options.reconnect_max_s)))

    def _new_session(self) -> GcsSession:
        return GcsSession(self.objects, on_object=self._on_object)

    def _open(self) -> Any:
        if self.kind == "tcp":
            return open_tcp_client(self.host, self.port_number)
        return open_serial(self.device, self.baudrate, timeout=0)

    # -- the engine's protocol (its thread) -----------------------------------------------------

    def feed(self, data: bytes) -> list[Any]:
        """Bytes from the flight controller: into the session; returns the messages made."""
        now = self.clock()
        session = self.session
        for packet in self.decoder.feed(data):
            session.receive(packet, now)
        self._note_state()
        self._write()
        out, self._out = self._out, []
        return out

    def flush(self) -> list[Any]:
        """The stream broke: a partial packet never completes."""
        self.decoder = Decoder(self.objects.data_length)
        return []

    def _on_link(self, up: bool) -> None:
        self.counts["link_changes"] += 1
        if up:
            self._log("open", f"{self.url} open, handshaking").event()
            self._tick()
            return
        # A new connection starts a new handshake: a fresh session (its counters kept).
        with self._lock:
            old = self.session
            for key, value in old.stats.as_dict().items():
                if key != "handshake_ms":
                    setattr(self._retired, key, getattr(self._retired, key) + value)
            self._retired.handshake_ms = old.stats.handshake_ms or self._retired.handshake_ms
            if old.state == Status.CONNECTED and not self._stop.is_set():
                self._log("lost", "link lost").event()
            self.session = self._new_session()
            self._last_state = self.session.state

    def _tick(self) -> None:
        if not self.engine.connected:
            return
        self.session.tick(self.clock())
        self._note_state()
        self._write()

    def _write(self) -> None:
        for data in self.session.outgoing():
            if self.engine.submit(data, rate_limited=False) is not Outcome.ACCEPTED:
                self.counts["write_drops"] += 1

    def _note_state(self) -> None:
        state = self.session.state
        if state != self._last_state:
            self._last_state = state
            if state == Status.CONNECTED:
                self._log("connected", "connected").event(
                    f"handshake {self.session.stats.handshake_ms} ms")
            elif state == Status.DISCONNECTED or (state == Status.HANDSHAKE_REQ
                                                  and self.session.stats.disconnects):
                self._log("disconnected", "disconnected").event()

    def _log(self, kind: str, text: str) -> BurstLog:
        """The log of a kind of link event (on the loop's thread): a flight controller that
        handshakes or hangs up in a loop costs a line per burst, with a count."""
        burst = self._logs.get(kind)
        if burst is None:
            loop = self.io_loop
            assert loop is not None
            burst = self._logs[kind] = BurstLog(loop, f"source {self.name}: {text}",
                                                level=logging.INFO, logger=log)
        return burst

    # -- objects → messages -----------------------------------------------------------------------

    def _on_object(self, name: str, values: dict[str, Any]) -> None:
        self.counts["objects"] += 1
        handler = _HANDLERS.get(name)
        if handler is None:
            return
        try:
            handler(self, values)
        except Exception:
            self.counts["bad_objects"] += 1
            log.debug("source %s: cannot convert %s %r", self.name, name, values, exc_info=True)

    def _flight_status(self, v: dict[str, Any]) -> None:
        armed = int(v["Armed"]) == ARMED
        mode = int(v["FlightMode"])
        changed = armed != self.armed or mode != self.flight_mode
        self.armed, self.flight_mode = armed, mode
        self._emit_state(force=changed)

    def _attitude(self, v: dict[str, Any]) -> None:
        r, p, y = (float(v[k]) for k in ("Roll", "Pitch", "Yaw"))
        if not all(math.isfinite(a) for a in (r, p, y)):
            raise ValueError("attitude not finite")
        self.attitude = (math.radians(r), math.radians(p), math.radians(y))
        self._emit_state()

    def _baro(self, v: dict[str, Any]) -> None:
        alt = float(v["Altitude"])
        if math.isfinite(alt):
            self.baro_alt_m = alt

    def _position_state(self, v: dict[str, Any]) -> None:
        down = float(v["Down"])
        if math.isfinite(down):
            self.position_alt_m = -down

    def _emit_state(self, force: bool = False) -> None:
        if self.armed is None or self.flight_mode is None:
            return  # no FlightStatus yet: armed and mode unknown
        if not self._state_gate.ready(self.clock()) and not force:
            return
        mode = self.flight_mode
        name = self._mode_options[mode] if 0 <= mode < len(self._mode_options) \
            else f"MODE_{mode}"
        r, p, y = self.attitude if self.attitude is not None else (None, None, None)
        alt = self.baro_alt_m if self.baro_alt_m is not None else self.position_alt_m
        self._out.append(VehicleState(self.armed, name, mode, r, p, y, alt, None,
                                      origin=self.name, via=VIA_UAVTALK,
                                      vehicle=self.vehicle))
        self.counts["vehicle_states"] += 1

    def _gps(self, v: dict[str, Any]) -> None:
        fix = int(v["Status"])
        if fix < MIN_FIX:
            self.counts["no_fix"] += 1
            return
        if not self._position_gate.ready(self.clock()):
            return
        sats = int(v["Satellites"])
        heading = float(v["Heading"])
        self._out.append(Position(
            int(v["Latitude"]) / 1e7, int(v["Longitude"]) / 1e7, _finite(v["Altitude"]), None,
            _finite(v["Groundspeed"]), heading % 360.0 if math.isfinite(heading) else None,
            sats if sats >= 0 else None, fix, origin=self.name, via=VIA_UAVTALK,
            vehicle=self.vehicle))
        self.counts["positions"] += 1

    def _battery(self, v: dict[str, Any]) -> None:
        volts = float(v["Voltage"])
        if not math.isfinite(volts):
            raise ValueError("voltage not finite")
        self._out.append(Battery(volts, _finite(v["Current"]), _finite(v["ConsumedEnergy"]),
                                 None, 0, origin=self.name, via=VIA_UAVTALK,
                                 vehicle=self.vehicle))
        self.counts["batteries"] += 1

    # -- life cycle -------------------------------------------------------------------------------

    def begin(self) -> None:  # the source's loop: the engine and its tick run on it
        loop = self.io_loop
        assert loop is not None
        self.engine.use_loop(loop)
        self.engine.start()
        self._timer = self.engine.call_every(TICK_S, self._tick, first=TICK_S)

    def halt(self) -> None:
        timer, self._timer = self._timer, None
        if timer is not None:
            timer.cancel()
        self.engine.close(0.0)  # on the loop's thread: closes at once
        self.finish()

    @property
    def state(self) -> Status:
        """The session's handshake state."""
        return self.session.state

    def stats(self) -> dict[str, Any]:
        with self._lock:
            session = self.session
            totals = self._retired.as_dict()
        for key, value in session.stats.as_dict().items():
            if key != "handshake_ms":
                totals[key] += value
            elif value:  # the latest handshake's
                totals[key] = value
        es = self.engine.stats
        return {**totals, **{f"decoder_{k}": v for k, v in self.decoder.stats.as_dict().items()},
                **self.counts, "state": session.state.name.lower(),
                "walk_done": int(session.walk_done), "opens": es.connects,
                "open_failures": es.connect_failures, "disconnects_port": es.disconnects,
                "link": int(self.engine.connected)}


def _finite(value: Any) -> float | None:
    f = float(value)
    return f if math.isfinite(f) else None


_HANDLERS: dict[str, Callable[[UavtalkSource, dict[str, Any]], None]] = {
    "FlightStatus": UavtalkSource._flight_status,
    "AttitudeState": UavtalkSource._attitude,
    "BaroSensor": UavtalkSource._baro,
    "PositionState": UavtalkSource._position_state,
    "GPSPositionSensor": UavtalkSource._gps,
    "FlightBatteryState": UavtalkSource._battery,
}
