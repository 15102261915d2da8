"""The MAVLink backend: the rocket as a MAVLink vehicle on any number of endpoints, with
mavlink-router-style routing between them and optional MAVLink 2 signing."""

from __future__ import annotations

import contextlib
import logging
import time
from typing import Any, ClassVar

from backends.mavlink import signing
from backends.mavlink.endpoints import (
    Endpoint,
    EndpointSpec,
    TcpServerEndpoint,
    parse_endpoint,
)
from backends.mavlink.hub import GCS, VEHICLE, MavlinkHub
from backends.mavlink.options import QGC_UDP, MavlinkOptions
from backends.mavlink.router import Router
from backends.mavlink.translate import VIA_MAVLINK, AuroraVehicle
from gateway import __version__
from gateway.backend import Backend, BackendError, Outcome, Routes
from gateway.handover import Handover
from gateway.io.endpoints import KINDS, list_validator
from gateway.io.ioloop import IoLoop, Timer
from gateway.io.server import ClientLimits, server_stats
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    RcChannels,
    SmUpdate,
    Status,
    VehicleState,
)

log = logging.getLogger(__name__)

#: Gateway messages waiting for the loop before drops (QUEUE_FULL, counted).
INBOX_DEPTH = 256
POLL_S = 0.02
#: Routing a vehicle, the rocket takes its system id once the vehicle has been heard, or
#: after this long (a vehicle heartbeats at 1 Hz): never the vehicle's id, even briefly.
CLAIM_GRACE_S = 1.5


_CHECK_ENDPOINTS = list_validator(KINDS)


def check_endpoints(endpoints: Any) -> list[EndpointSpec]:
    """The parsed endpoints (at least one); EndpointError naming the first bad one."""
    _CHECK_ENDPOINTS(endpoints)
    return [parse_endpoint(e) for e in endpoints]


class MavlinkBackend(Backend):
    """Streams the rocket to ground stations (QGroundControl, MAVProxy, MAVSDK) and routes
    MAVLink between its endpoints.  Options: see :attr:`CONFIG` and the README."""

    NAME = "mavlink"
    OPTIONS = MavlinkOptions
    #: The default run shows the rocket in a QGroundControl on this machine.
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = {"endpoints": [QGC_UDP]}

    def __init__(self, options: MavlinkOptions | None = None, name: str | None = None) -> None:
        super().__init__(name)
        options = options or MavlinkOptions()
        self.specs = check_endpoints(options.endpoints)  # validated: the parsed endpoints
        self.sysid = options.sysid
        self.compid = options.compid
        self.route = options.route
        self.signing_key_file = options.signing_key_file
        self.signing_passphrase = options.signing_passphrase
        self.serial_queue_depth = options.serial_queue_depth
        self.limits = ClientLimits.of(options, options.serial_queue_depth)
        # A key that cannot be read is a configuration error, reported before anything starts.
        self.signing_key = self._signing_key()
        self.vehicle = AuroraVehicle(options.sysid, options.compid, rates=options.rates(),
                                     stale_after_s=options.stale_after_s,
                                     pad_altitude_amsl_m=options.pad_altitude_amsl_m,
                                     version=__version__)
        self.vehicle.on_rc = self._on_rc
        self.hub: MavlinkHub | None = None
        self.router: Router | None = None
        self.loop: IoLoop | None = None
        self.endpoints: list[Endpoint] = []
        # the messages a batch of the gateway's makes, sent once after the batch
        # (what came from a MAVLink system on our router is skipped in the dispatcher's thread)
        self.handover = Handover(self.name, INBOX_DEPTH, after_batch=self._send_out,
                                 skip=self._repeats)
        self._out: list[Any] = []
        self._ticker: Timer | None = None
        self._spoken = False
        self._started_at = 0.0
        self.not_repeated = 0

    # -- life cycle ----------------------------------------------------------------------------

    def _signing_key(self) -> bytes | None:
        """The signing key, or None; raises SigningError (a ValueError) naming the file."""
        if self.signing_key_file:
            return signing.key_from_file(self.signing_key_file)
        if self.signing_passphrase:
            return signing.key_from_passphrase(self.signing_passphrase)
        return None

    def init(self) -> None:
        hub = MavlinkHub.of(self.context)  # shared with a MAVLink source of this gateway
        try:
            hub.join(self.vehicle, GCS, forward=self.route, signing_key=self.signing_key)
        except ValueError as exc:
            raise BackendError(str(exc)) from None
        try:
            endpoints = hub.open(self.specs, GCS, self.serial_queue_depth, self.limits)
        except OSError as exc:
            hub.leave(self.vehicle)
            raise BackendError(str(exc)) from None
        self.hub, self.loop, self.router, self.endpoints = hub, hub.loop, hub.router, endpoints
        self._started_at = time.monotonic()
        self.handover.lock = hub.router.lock  # the vehicle's state is the router's too
        self.handover.open(hub.loop)
        self._ticker = hub.loop.call_every(POLL_S, self._tick)  # first HEARTBEAT at once
        log.info("%s: MAVLink system %d on %s%s", self.name, self.sysid,
                 ", ".join(s.text for s in self.specs), " (signed)" if self.signing_key else "")

    def close(self) -> None:
        hub, self.hub = self.hub, None
        if hub is None:
            return
        self.handover.close()  # what is queued goes out first (within its bound)
        self.loop = None
        if self._ticker is not None:
            self._ticker.cancel()
        hub.leave(self.vehicle, self.endpoints)  # queued frames are written first

    # -- the loop thread -----------------------------------------------------------------------

    def _may_speak(self) -> bool:
        """Routing a vehicle, the rocket shows itself only once it has something to say (its
        first update) and its id is known not to be the vehicle's; otherwise at once."""
        if self._spoken:
            return True
        hub = self.hub
        if hub is not None:
            routed, heard = hub.side(VEHICLE)
            if routed and (self.vehicle.stats.updates == 0 or (
                    not heard and time.monotonic() - self._started_at < CLAIM_GRACE_S)):
                return False
        self._spoken = True
        if self.router is not None:
            sysid = self.router.claim(self.vehicle)
            if sysid != self.sysid:
                self.sysid = sysid
        return True

    def _tick(self) -> None:
        router = self.router
        if router is None:
            return
        with router.lock:
            out = self.vehicle.poll()
            if out and self._may_speak():
                router.broadcast(out, self.vehicle)

    def _send_out(self) -> None:
        """After a batch of the gateway's messages (under the router's lock): what they made,
        to the ground stations."""
        out, self._out = self._out, []
        router = self.router
        if out and router is not None and self._may_speak():
            router.broadcast(out, self.vehicle)

    def _repeats(self, msg: Any) -> bool:
        """``msg`` came from a MAVLink system on our router: its own frames are routed to the
        ground stations already; repeating them as the rocket's would show it twice (the
        hand-over's ``skip``: the dispatcher's thread)."""
        if self.route and msg.via.startswith(VIA_MAVLINK):
            self.not_repeated += 1
            return True
        return False

    # -- handlers (on the loop, handed over by the dispatcher, under the router's lock) ---------

    def routes(self) -> Routes:
        return (Routes(handover=self.handover).on(SmUpdate, self.send_sm_update)
                .on(Status, self.send_status).on(Position, self.send_position)
                .on(Battery, self.send_battery).on(LinkStats, self.send_link_stats)
                .on(VehicleState, self.send_vehicle_state)
                .on(RcChannels, self.send_rc_channels))

    def send_rc_channels(self, msg: RcChannels) -> None:
        if msg.origin == self.name:
            return  # a ground station's override: not the rocket's to repeat
        self._out += self.vehicle.on_rc_channels(msg)

    def _on_rc(self, channels: tuple[int | None, ...]) -> None:
        """A ground station's RC override or manual control for the rocket (the loop's
        thread): to the gateway, e.g. for an XBee ground link to send up."""
        self.emit(RcChannels(channels, origin=self.name))

    def send_sm_update(self, msg: SmUpdate) -> None:
        self._out += self.vehicle.on_sm_update(msg)

    def send_status(self, msg: Status) -> None:
        self._out += self.vehicle.on_status(msg)

    def send_position(self, msg: Position) -> None:
        if msg.via.startswith(VIA_MAVLINK):
            return  # it came from a MAVLink vehicle: it speaks for itself
        self._out += self.vehicle.on_position(msg)

    def send_battery(self, msg: Battery) -> None:
        if msg.via.startswith(VIA_MAVLINK):
            return
        self._out += self.vehicle.on_battery(msg)

    def send_vehicle_state(self, msg: VehicleState) -> None:
        # a non-Aurora vehicle (UAVTalk): shown as this system
        self._out += self.vehicle.on_vehicle_state(msg)

    def send_link_stats(self, msg: LinkStats) -> None:
        self._out += self.vehicle.on_link_stats(msg)  # → RADIO_STATUS

    def on_link(self, ev: LinkEvent) -> Outcome:
        return Outcome.ACCEPTED  # staleness is judged from the updates themselves

    # -- reporting -------------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        router = self.router
        with router.lock if router is not None else contextlib.nullcontext():
            eps = {ep.name: ep.stats() for ep in self.endpoints}  # sets change under routing
            up = any(link.up for ep in self.endpoints for link in ep.links())
        sent = sum(s.get("tx_frames", 0) for s in eps.values())
        h = self.handover
        dropped = sum(s.get("tx_dropped", 0) for s in eps.values()) + h.dropped
        errors = sum(s.get(k, 0) for s in eps.values()
                     for k in ("tx_errors", "crc_errors", "decode_errors"))
        d: dict[str, Any] = {"sent": sent, "dropped": dropped,
                             "errors": errors + h.handler_errors, "link": int(up),
                             "dropped_queue_full": h.dropped_queue_full,
                             "dropped_not_ready": h.dropped_not_ready,
                             "dropped_closed": h.dropped_closed,
                             "sysid": self.vehicle.sysid, "not_repeated": self.not_repeated,
                             **server_stats(ep.server for ep in self.endpoints
                                            if isinstance(ep, TcpServerEndpoint)
                                            and ep.server is not None),
                             "endpoints": eps}
        if self.router is not None:
            rs = self.router.stats
            d["errors"] += rs.node_errors + rs.encode_errors
            d["router"] = rs.as_dict()
            if self.router.verifier is not None:
                d["signing"] = self.router.verifier.stats.as_dict()
        d["vehicle"] = dict(self.vehicle.stats.__dict__)
        return d
