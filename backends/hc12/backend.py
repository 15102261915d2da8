"""The HC-12 backend: relay or re-transmit Aurora frames within the air link's budget.

Every frame goes through a :class:`gateway.io.port.PortEngine` (bounded queue, default 16; the
engine's thread owns the port and reopens it with backoff; full → dropped and counted; the
producer never blocks; optional minimum interval between accepted SM_UPDATEs, STATUS
exempt).  In front of the engine an
:class:`~backends.hc12.budget.AirBudget` admits a frame only if the air link can carry it
(STATUS may use a small reserve but is charged like everything else); a frame it refuses is
dropped as ``THROTTLED`` and counted as ``dropped_budget``.

Modes:

``relay``
    every frame a source received — SM_UPDATE of either revision, STATUS, unknown types —
    goes out byte-identical (``msg.raw``); messages built in memory (no ``raw``) are encoded;
``generate``
    the backend encodes SM_UPDATEs itself in the configured revision (36 or 64 bytes),
    STATUS and unknown frames as they are.

The radio carries one vehicle: the one named by ``vehicle`` in ``[backends.hc12]``, or else
the first source's (:class:`gateway.vehicles.VehicleSelector`); another vehicle's frames are
not sent (counted as ``other_vehicles``), nor judged by provisioning.

Messages whose ``origin`` is this backend's port are never sent back to it.  The backend also
serves provisioning (``aurora-gateway hc12 …``) through its control socket, on the engine's
own thread: the exchange takes the port with :meth:`~gateway.io.port.PortEngine.exclusive` (the
firmware's TX lock; frames queue meanwhile) and judges the vehicle's state from the frames
the backend relayed (see ``control.py``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any, ClassVar

from backends.hc12 import at, control
from backends.hc12.budget import DEFAULT_PRIORITY_RESERVE, AirBudget, figures
from backends.hc12.control import ControlServer
from backends.hc12.options import Hc12Options
from backends.hc12.port import open_port
from backends.hc12.provision import Result, Timing, check_request, plan, run_request
from backends.hc12.setline import SetLine, make_set_line, parse_set_line
from backends.hc12.vehicle import VehicleWatch
from gateway.backend import Backend, BackendError, GatewayContext, Outcome, Routes
from gateway.io.port import PortEngine, PortNotReady
from gateway.io.server import ClientLimits, server_stats
from gateway.model import RawFrame, SmUpdate, Status
from gateway.vehicles import VehicleSelector
from gateway.wire import encode

log = logging.getLogger(__name__)



class Hc12Backend(Backend):
    """Drives an HC-12 433 MHz UART radio (see the module docstring)."""

    NAME = "hc12"
    OPTIONS = Hc12Options
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None

    def __init__(self, options: Hc12Options, name: str | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(name)
        self.url = options.url
        self.baudrate = options.baudrate
        self.mode = options.mode
        self.revision = options.revision
        self.set_spec = parse_set_line(options.set_line, options.set_invert)
        self.at_baud = options.at_baud
        self.timing = Timing(reply_timeout_s=options.reply_timeout_s)
        self.control = options.control
        self.control_limits = ClientLimits.of(options, queue_depth=2)
        self._clock = clock
        #: the vehicle this radio relays
        self.selector = VehicleSelector(options.vehicle)
        self.other_vehicles = 0
        self.budget = AirBudget(figures(min(options.baudrate, options.air_baud),
                                        options.utilisation_pct, options.burst_bytes,
                                        DEFAULT_PRIORITY_RESERVE), clock=clock)
        self.watch = VehicleWatch(options.idle_max_age_s, clock=clock)
        self.engine = PortEngine(self._open, name=self.name, queue_depth=options.queue_depth,
                                 min_interval_s=options.min_interval_s, clock=clock)
        self._set_line: SetLine | None = None
        self._control: ControlServer | None = None
        self._served: ControlServer | None = None  # kept after close(): its counters
        self._provision_lock = threading.Lock()
        self.control_path: Any = None
        self.encoded = 0
        self.skipped_loop = 0
        self.at_exchanges = 0
        self.at_failures = 0
        self.at_refused = 0

    # -- life cycle ----------------------------------------------------------------------------

    def attach(self, context: GatewayContext) -> None:
        """Learn which vehicle is relayed by default (the first source's)."""
        super().attach(context)
        self.selector.attach(context, f"backends.{self.name}")

    def _open(self) -> Any:
        """The engine's opener: SET released while opening; reads return at once."""
        return open_port(self.url, self.baudrate, self.set_spec, timeout=0)

    def init(self) -> None:
        self.engine.start()
        path = None
        try:
            path = control.resolve(self.control, self.url)
            if path is not None:
                # Served on the engine's loop: an exchange runs on the port's own thread.
                server = ControlServer(path, self.handle_control, self.engine.loop,
                                       name=self.name, limits=self.control_limits)
                server.start()
                self._control = self._served = server
                self.control_path = path
        except OSError as exc:
            if "served by another running gateway" in str(exc):
                self.engine.close(0.2)
                raise BackendError(f"another gateway already drives {self.url} ({exc})") from exc
            log.warning("%s: no control socket (%s); `aurora-gateway hc12` cannot reach this "
                        "gateway", self.name, exc)

    def close(self) -> None:
        server, self._control = self._control, None
        if server is not None:
            server.close()
        self.engine.drain(0.2)
        self.engine.close(0.8)  # closing an rfc2217:// port alone takes pyserial 0.3 s
        line, self._set_line = self._set_line, None
        if line is not None:
            try:
                line.release()
            except Exception:
                log.debug("%s: releasing SET failed", self.name, exc_info=True)

    # -- hooks ---------------------------------------------------------------------------------

    def _loops_back(self, origin: str) -> bool:
        return bool(origin) and origin in (self.url, self.name)

    def _frame(self, msg: SmUpdate | Status | RawFrame) -> bytes:
        if self.mode == "relay" and msg.raw:
            return msg.raw
        self.encoded += 1
        if isinstance(msg, SmUpdate) and self.mode == "generate":
            return encode(msg._replace(payload_len=self.revision))
        return encode(msg)

    def _submit(self, data: bytes, *, rate_limited: bool, priority: bool) -> Outcome:
        now = self._clock()
        if not self.budget.admit(len(data), priority=priority, now=now):
            return Outcome.THROTTLED
        outcome = self.engine.submit(data, rate_limited=rate_limited)
        if outcome is Outcome.ACCEPTED:
            self.budget.commit(len(data), now=now)
        return outcome

    def routes(self) -> Routes:
        return (Routes().on(SmUpdate, self.send_sm_update).on(Status, self.send_status)
                .on(RawFrame, self.send_raw))

    def send_sm_update(self, msg: SmUpdate) -> Outcome:
        if not self.selector.accepts(msg):
            return self._other()
        self.watch.observe(msg)
        return self._forward(msg, rate_limited=True, priority=False)

    def send_status(self, msg: Status) -> Outcome:
        if not self.selector.accepts(msg):
            return self._other()
        self.watch.observe(msg)
        return self._forward(msg, rate_limited=False, priority=True)

    def send_raw(self, msg: RawFrame) -> Outcome:
        if not self.selector.accepts(msg):
            return self._other()
        return self._forward(msg, rate_limited=False, priority=False)

    def _other(self) -> Outcome:
        """Another vehicle's message: not for this radio (counted, not an error)."""
        self.other_vehicles += 1
        return Outcome.ACCEPTED

    def _forward(self, msg: SmUpdate | Status | RawFrame, *, rate_limited: bool,
                 priority: bool) -> Outcome:
        """Frame and submit ``msg``, unless it came from this radio (it would loop back)."""
        if self._loops_back(msg.origin):
            self.skipped_loop += 1
            return Outcome.ACCEPTED
        return self._submit(self._frame(msg), rate_limited=rate_limited, priority=priority)

    # -- provisioning ----------------------------------------------------------------------------

    def provision(self, op: str, arg: Any = None, bench: bool = False) -> Result:
        """Run one provisioning request with the port taken from the engine (see
        provision.py); from any thread, the engine's own included."""
        try:
            plan(op, arg)
        except at.AtUsageError as exc:
            return Result(False, op, error=str(exc), kind="usage")
        # On the engine's thread another caller's exchange could only be waiting for that very
        # thread to park: answer "busy" at once rather than stall both.
        lock = self._provision_lock
        if not (lock.acquire(blocking=False) if self.engine.loop.in_loop_thread
                else lock.acquire(timeout=10.0)):
            return Result(False, op, kind="failed",
                          error="another provisioning exchange is running; nothing was sent")
        try:
            try:
                with self.engine.exclusive(timeout=5.0) as port:
                    return self._exchange(port, op, arg, bench)
            except PortNotReady as exc:
                return Result(False, op, kind="failed",
                              error=f"the HC-12 port is not available ({exc}); nothing was "
                                    f"sent")
        finally:
            self._provision_lock.release()

    def _exchange(self, port: Any, op: str, arg: Any, bench: bool) -> Result:
        """The checks and the exchange, on the port lent by the engine."""
        if self._set_line is None or getattr(self._set_line, "port", port) is not port:
            self._set_line = make_set_line(self.set_spec, port)
        set_line = self._set_line
        if stop := check_request(op, set_line, self.watch, bench):
            if stop.kind == "refused":
                self.at_refused += 1
            else:
                self.at_failures += 1
            return stop
        result = run_request(port, set_line, op, arg, host_baud=self.baudrate,
                             at_baud=self.at_baud, timing=self.timing)
        self.at_exchanges += 1
        if not result.ok:
            self.at_failures += 1
        return result

    def handle_control(self, request: dict[str, Any]) -> dict[str, Any]:
        """A control-socket request → a JSON-able reply."""
        op = str(request.get("op", ""))
        arg = request.get("arg")
        bench = request.get("bench") is True
        return self.provision(op, arg, bench).as_dict()

    # -- reporting -----------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        s = self.engine.stats
        b = self.budget
        return {
            "link": int(self.engine.connected),
            "sent": s.sent_frames,
            "sent_bytes": s.sent_bytes,
            "dropped": s.dropped + b.refused_frames,
            "dropped_budget": b.refused_frames,
            "dropped_throttled": s.dropped_throttled,
            "dropped_queue_full": s.dropped_queue_full,
            "dropped_not_ready": s.dropped_not_ready,
            "utilisation_pct": round(b.utilisation_pct(), 1),
            "peak_1s_bytes": b.peak_1s_bytes,
            "budget_bytes_per_s": round(b.fig.rate_bps, 1),
            "capacity_bytes_per_s": round(b.fig.capacity_bps, 1),
            "write_errors": s.write_errors,
            "errors": s.errors,
            "disconnects": s.disconnects,
            "encoded": self.encoded,
            "skipped_loop": self.skipped_loop,
            "other_vehicles": self.other_vehicles,
            "at_exchanges": self.at_exchanges,
            "at_failures": self.at_failures,
            "at_refused": self.at_refused,
            **(self._served.stats() if self._served is not None else server_stats(())),
        }
