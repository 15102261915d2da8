"""The MAVLink backend: the rocket as a MAVLink vehicle on any number of endpoints, with
mavlink-router-style routing between them and optional MAVLink 2 signing."""

from __future__ import annotations

import contextlib
import logging
import time
from typing import TYPE_CHECKING, Any

from backends.mavlink import signing
from backends.mavlink.endpoints import (
    Endpoint,
    EndpointSpec,
    TcpServerEndpoint,
    parse_endpoint,
)
from backends.mavlink.hub import GCS, VEHICLE, MavlinkHub
from backends.mavlink.options import MavlinkOptions
from backends.mavlink.router import LAST_ID, Router
from backends.mavlink.translate import VIA_MAVLINK, AuroraVehicle
from gateway import __version__, vehicles
from gateway.backend import Backend, BackendError, Outcome, Routes
from gateway.flight_summary import FlightSummary
from gateway.handover import Handover
from gateway.io.burstlog import BurstLog
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

if TYPE_CHECKING:
    from backends.mavlink.tlog import TlogWriter

log = logging.getLogger(__name__)

#: Gateway messages waiting for the loop before drops (QUEUE_FULL, counted).
INBOX_DEPTH = 256
#: seconds of the gateway's messages (at the rate they come in) that may wait for the loop,
#: at least INBOX_DEPTH of them (see gateway.handover: sized by time)
INBOX_SPAN_S = 1.0
POLL_S = 0.02
#: Routing a vehicle, the rocket takes its system id once the vehicle has been heard, or
#: after this long (a vehicle heartbeats at 1 Hz): never the vehicle's id, even briefly.
CLAIM_GRACE_S = 1.5
#: How often the router forgets the systems silent for ``system_timeout_s``.
EXPIRE_EVERY_S = 1.0
#: A vehicle no id was free for is looked for one again after this long (its messages in
#: between are dropped, counted).
NO_ID_RETRY_S = 5.0


_CHECK_ENDPOINTS = list_validator(KINDS)


def check_endpoints(endpoints: Any) -> list[EndpointSpec]:
    """The parsed endpoints (at least one); EndpointError naming the first bad one."""
    _CHECK_ENDPOINTS(endpoints)
    return [parse_endpoint(e) for e in endpoints]


class MavlinkBackend(Backend):
    """Streams each vehicle of the gateway to ground stations (QGroundControl, MAVProxy,
    MAVSDK) as a MAVLink system of its own, and routes MAVLink between its endpoints.
    Options: see :attr:`CONFIG` and the README.

    One node (:class:`~.translate.AuroraVehicle`) per vehicle, found by ``msg.vehicle`` (one
    dict lookup per message): its own system id (component 1), HEARTBEAT schedule, sequence
    numbers, rate limits and state.  The configured sources' vehicles (the
    ``gateway.vehicles`` service) have theirs from the start, ids in source order from
    ``sysid`` (or their ``mavlink_sysid``); any other vehicle (one a source names per system
    it hears) gets the next free id when first heard.  At most one node per id: ≤ 254."""

    NAME = "mavlink"
    OPTIONS = MavlinkOptions
    #: The default run shows the rocket in a QGroundControl on this machine.
    EMBEDDED_DEFAULT = MavlinkOptions.EMBEDDED_DEFAULT

    def __init__(self, options: MavlinkOptions | None = None, name: str | None = None) -> None:
        super().__init__(name)
        options = options or MavlinkOptions()
        self.options = options
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
        #: vehicle name → its node ("" → the first vehicle's: what comes without a name)
        self.nodes: dict[str, AuroraVehicle] = {}
        self._node_list: list[AuroraVehicle] = []  # each node once, in creation order
        #: vehicles no id was free for → when to look again (bounded)
        self._refused: dict[str, float] = {}
        self._no_id_log: BurstLog | None = None
        #: a configured source's node, until that source's first message: if it names
        #: another vehicle (a source that names those it hears, e.g. a Zenoh source following
        #: another gateway), that vehicle takes the node over, so no system stands for the
        #: source itself; "*": a backend on its own, whose one node the first name takes
        self._vacant: dict[str, AuroraVehicle] = {}
        self.vehicles_without_id = 0  # their messages, dropped (counted)
        self.hub: MavlinkHub | None = None
        self.router: Router | None = None
        self.loop: IoLoop | None = None
        self.endpoints: list[Endpoint] = []
        # the messages a batch of the gateway's makes, sent once after the batch
        # (what came from a MAVLink system on our router is skipped in the dispatcher's thread)
        self.handover = Handover(self.name, INBOX_DEPTH, after_batch=self._send_out,
                                 skip=self._repeats, span_s=INBOX_SPAN_S)
        #: (None, []): a vehicle starts a new flight there (``tlog``)
        self._out: list[tuple[AuroraVehicle | None, list[Any]]] = []
        self._ticker: Timer | None = None
        self._tick_s = POLL_S
        self._started_at = 0.0
        self._next_expiry = 0.0
        self.not_repeated = 0
        #: ``tlog``: the telemetry log's writer (the router's tap), and the flights that
        #: start its next file (a vehicle arming on the pad after a flight)
        self.tlog: TlogWriter | None = None
        self._flights = FlightSummary()

    @property
    def vehicle(self) -> AuroraVehicle | None:
        """The first vehicle's node (the only one of a single-source gateway)."""
        return self._node_list[0] if self._node_list else None

    def _new_node(self, name: str, sysid: int) -> AuroraVehicle:
        o = self.options
        node = AuroraVehicle(sysid, o.compid, rates=o.rates(), stale_after_s=o.stale_after_s,
                             pad_altitude_amsl_m=o.pad_altitude_amsl_m, version=__version__,
                             vehicle=name)
        node.on_rc = lambda channels: self._on_rc(channels, name)
        self.nodes[name] = node
        self._node_list.append(node)
        if self._ticker is not None and self.hub is not None and self._tick_s != POLL_S:
            self._start_ticker()
        return node

    def _start_ticker(self) -> None:
        """The vehicles' periodic messages are polled every POLL_S (the first at once); with
        no vehicle yet (a router of other systems' messages) only the router's expiry runs,
        every EXPIRE_EVERY_S: each tick is a wake-up of the loop (and of a compiled lane)."""
        if self._ticker is not None:
            self._ticker.cancel()
        self._tick_s = POLL_S if self._node_list else EXPIRE_EVERY_S
        assert self.hub is not None
        self._ticker = self.hub.loop.call_every(self._tick_s, self._tick)

    def _configured(self, hub: MavlinkHub) -> list[tuple[str, str, int]]:
        """The configured vehicles with their ids: fixed ones kept, the others from ``sysid``
        on in source order, skipping the fixed ones.  A source that names one vehicle per
        system it hears (the MAVLink source) has none of its own."""
        service = self.context.services.get(vehicles.SERVICE) if self.context else None
        if service is None:  # a backend on its own (a test, a tool): one vehicle, as before
            return [("*", "", self.sysid)]  # (named by the first message that names one)
        wanted = [sv for sv in service if not sv.systems and sv.vehicle not in hub.stems]
        fixed = {sv.mavlink_sysid for sv in wanted if sv.mavlink_sysid}
        taken = set(fixed)
        out: list[tuple[str, str, int]] = []
        nxt = self.sysid
        for sv in wanted:
            sysid = sv.mavlink_sysid
            if not sysid:
                for _ in range(LAST_ID):
                    if nxt not in taken:
                        break
                    nxt = nxt % LAST_ID + 1
                else:
                    log.warning("%s: no MAVLink system id left for vehicle %s", self.name,
                                sv.vehicle)
                    continue
                sysid = nxt
            taken.add(sysid)
            out.append((sv.source, sv.vehicle, sysid))
        return out

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
            hub.join(None, GCS, forward=self.route, signing_key=self.signing_key)
        except ValueError as exc:
            raise BackendError(str(exc)) from None
        router = hub.router
        with router.lock:
            self.nodes, self._node_list, self._vacant = {}, [], {}  # (a second init: anew)
            router.system_timeout_s = self.options.system_timeout_s
            planned = self._configured(hub)
            for source, name, sysid in planned:  # (an unclaimed node's id is no other's)
                node = self._new_node(name, sysid)
                hub.add(node, GCS)
                self._vacant[source] = node
            if planned and "" not in self.nodes:
                self.nodes[""] = self._node_list[0]  # what comes without a vehicle name
        if self.options.tlog:
            from backends.mavlink.tlog import TlogWriter  # with the recording format: ~2 ms

            try:
                self.tlog = TlogWriter(self.options.tlog, self.name)
            except OSError as exc:
                self._leave(hub)
                raise BackendError(f"tlog: cannot write telemetry logs into "
                                   f"{self.options.tlog}: {exc.strerror or exc}") from None
            with router.lock:
                router.tap = self.tlog.frame
        try:
            endpoints = hub.open(self.specs, GCS, self.serial_queue_depth, self.limits)
        except OSError as exc:
            self._leave(hub)
            raise BackendError(str(exc)) from None
        self.hub, self.loop, self.router, self.endpoints = hub, hub.loop, hub.router, endpoints
        self._started_at = time.monotonic()
        self.handover.lock = hub.router.lock  # the vehicles' state is the router's too
        self.handover.open(hub.loop)
        self._no_id_log = BurstLog(hub.loop, f"{self.name}: no free MAVLink system id for a "
                                   "vehicle: not shown", logger=log)
        self._start_ticker()  # (a vehicle's first HEARTBEAT at once)
        ids = ", ".join(f"{n.vehicle or 'rocket'} {n.sysid}" for n in self._node_list)
        log.info("%s: MAVLink system%s %s on %s%s", self.name,
                 "s" if len(self._node_list) > 1 else "", ids or "(none yet)",
                 ", ".join(s.text for s in self.specs), " (signed)" if self.signing_key else "")

    def _leave(self, hub: MavlinkHub, endpoints: list[Endpoint] | None = None) -> None:
        with hub.router.lock:
            for node in self._node_list:
                hub.remove(node)
        hub.leave(None, endpoints or [])
        tlog = self.tlog  # (kept: its figures are the stop report's)
        if tlog is not None and not tlog.closed:
            with hub.router.lock:
                if hub.router.tap == tlog.frame:
                    hub.router.tap = None
            tlog.close()
            for path in tlog.paths:
                log.info("%s: telemetry log %s", self.name, path)

    def close(self) -> None:
        hub, self.hub = self.hub, None
        if hub is None:
            return
        self.handover.close()  # what is queued goes out first (within its bound)
        self.loop = None
        if self._ticker is not None:
            self._ticker.cancel()
            self._ticker = None
        if self._no_id_log is not None:
            self._no_id_log.cancel()
        self._leave(hub, self.endpoints)  # queued frames are written first

    # -- the vehicles ----------------------------------------------------------------------------

    def _node(self, msg: Any) -> AuroraVehicle | None:
        """The node of a vehicle not seen before (the loop's thread, under the router's
        lock): its source's vacant node (see ``_vacant``), else one with the next free id
        from ``sysid``; None (its messages dropped, counted) when no id is free."""
        name = msg.vehicle
        node = self.nodes.get(name)
        if node is not None:
            return node
        vacant = self._vacant
        if vacant:
            node = vacant.pop("*", None)
            if node is None:
                node = vacant.pop(msg.origin, None)
                if node is not None and node.stats.updates:
                    node = None  # it speaks for its own vehicle: taken
            if node is not None:
                log.info("%s: vehicle %s is MAVLink system %d (its source's)", self.name,
                         name, node.sysid)
                node.vehicle = name
                node.on_rc = lambda channels: self._on_rc(channels, name)
                self.nodes[name] = node
                return node
        router, hub = self.router, self.hub
        if router is None or hub is None:
            return None
        retry = self._refused.get(name)
        if retry is not None and time.monotonic() < retry:
            self.vehicles_without_id += 1
            return None
        sysid = router.free_id(self.sysid)
        if sysid is None:
            self.vehicles_without_id += 1
            if len(self._refused) >= LAST_ID:
                self._refused.clear()
            self._refused[name] = time.monotonic() + NO_ID_RETRY_S
            if self._no_id_log is not None:
                self._no_id_log.event(name)
            return None
        self._refused.pop(name, None)
        node = self._new_node(name, sysid)
        hub.add(node, GCS)
        log.info("%s: vehicle %s is MAVLink system %d", self.name, name or "(unnamed)", sysid)
        return node

    def _may_speak(self, node: AuroraVehicle) -> bool:
        """Routing a vehicle, a rocket shows itself only once it has something to say (its
        first update) and its id is known not to be the vehicle's; otherwise at once."""
        if node.spoken:
            return True
        hub = self.hub
        if hub is not None:
            routed, heard = hub.side(VEHICLE)
            if routed and (node.stats.updates == 0 or (
                    not heard and time.monotonic() - self._started_at < CLAIM_GRACE_S)):
                return False
        node.spoken = True
        if self.router is not None:
            self.router.claim(node)
        return True

    # -- the loop thread -----------------------------------------------------------------------

    def _tick(self) -> None:
        router = self.router
        if router is None:
            return
        with router.lock:
            for node in self._node_list:
                out = node.poll()
                if out and self._may_speak(node):
                    router.broadcast(out, node)
        now = time.monotonic()
        if now >= self._next_expiry:
            self._next_expiry = now + EXPIRE_EVERY_S
            router.expire(now)

    def _send_out(self) -> None:
        """After a batch of the gateway's messages (under the router's lock): what they made,
        to the ground stations, each vehicle's from its own system."""
        out, self._out = self._out, []
        router = self.router
        if router is None:
            return
        for node, msgs in out:
            if node is None:  # a vehicle's new flight: the telemetry log's next file
                if self.tlog is not None:
                    self.tlog.new_flight()
            elif self._may_speak(node):
                router.broadcast(msgs, node)

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

    def _add(self, node: AuroraVehicle, msgs: list[Any]) -> None:
        if msgs:
            out = self._out
            if out and out[-1][0] is node:  # one broadcast per run of one vehicle's messages
                out[-1][1].extend(msgs)
            else:
                out.append((node, msgs))

    def send_rc_channels(self, msg: RcChannels) -> None:
        if msg.origin == self.name:
            return  # a ground station's override: not the rocket's to repeat
        node = self.nodes.get(msg.vehicle) or self._node(msg)
        if node is not None:
            self._add(node, node.on_rc_channels(msg))

    def _on_rc(self, channels: tuple[int | None, ...], vehicle: str) -> None:
        """A ground station's RC override or manual control for a vehicle (the loop's
        thread): to the gateway, e.g. for an XBee ground link to send up."""
        self.emit(RcChannels(channels, origin=self.name, vehicle=vehicle))

    def send_sm_update(self, msg: SmUpdate) -> None:
        if self.tlog is not None and self._flights.feed(msg):
            # the telemetry log's next file, from this update's frames on (in the order
            # the frames go out: after the batch's earlier messages')
            self._out.append((None, []))
        node = self.nodes.get(msg.vehicle) or self._node(msg)
        if node is not None:
            self._add(node, node.on_sm_update(msg))

    def send_status(self, msg: Status) -> None:
        node = self.nodes.get(msg.vehicle) or self._node(msg)
        if node is not None:
            self._add(node, node.on_status(msg))

    def send_position(self, msg: Position) -> None:
        if msg.via.startswith(VIA_MAVLINK):
            return  # it came from a MAVLink vehicle: it speaks for itself
        node = self.nodes.get(msg.vehicle) or self._node(msg)
        if node is not None:
            self._add(node, node.on_position(msg))

    def send_battery(self, msg: Battery) -> None:
        if msg.via.startswith(VIA_MAVLINK):
            return
        node = self.nodes.get(msg.vehicle) or self._node(msg)
        if node is not None:
            self._add(node, node.on_battery(msg))

    def send_vehicle_state(self, msg: VehicleState) -> None:
        # a non-Aurora vehicle (UAVTalk): shown as a system of its own
        node = self.nodes.get(msg.vehicle) or self._node(msg)
        if node is not None:
            self._add(node, node.on_vehicle_state(msg))

    def send_link_stats(self, msg: LinkStats) -> None:
        node = self.nodes.get(msg.vehicle) or self._node(msg)
        if node is not None:
            self._add(node, node.on_link_stats(msg))  # → RADIO_STATUS

    def on_link(self, ev: LinkEvent) -> Outcome:
        return Outcome.ACCEPTED  # staleness is judged from the updates themselves

    # -- reporting -------------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        router = self.router
        with router.lock if router is not None else contextlib.nullcontext():
            eps = {ep.name: ep.stats() for ep in self.endpoints}  # sets change under routing
            up = any(link.up for ep in self.endpoints for link in ep.links())
            nodes = list(self._node_list)
            systems = {n.vehicle: {"sysid": n.sysid, **n.stats.__dict__} for n in nodes}
        sent = sum(s.get("tx_frames", 0) for s in eps.values())
        h = self.handover
        dropped = sum(s.get("tx_dropped", 0) for s in eps.values()) + h.dropped
        errors = sum(s.get(k, 0) for s in eps.values()
                     for k in ("tx_errors", "crc_errors", "decode_errors"))
        first = nodes[0] if nodes else None
        d: dict[str, Any] = {"sent": sent, "dropped": dropped,
                             "errors": errors + h.handler_errors, "link": int(up),
                             "dropped_queue_full": h.dropped_queue_full,
                             "dropped_not_ready": h.dropped_not_ready,
                             "dropped_closed": h.dropped_closed,
                             "sysid": first.sysid if first is not None else self.sysid,
                             "not_repeated": self.not_repeated,
                             "vehicles_without_id": self.vehicles_without_id,
                             **server_stats(ep.server for ep in self.endpoints
                                            if isinstance(ep, TcpServerEndpoint)
                                            and ep.server is not None),
                             "endpoints": eps}
        d["rejected_signing"] = sum(s.get("rejected_signing", 0) for s in eps.values())
        if self.router is not None:
            rs = self.router.stats
            d["errors"] += rs.node_errors + rs.encode_errors
            # who tried to take a vehicle's id, and what came of it (also under "router")
            d["impostor_frames"], d["sysid_conflicts"] = rs.impostor_frames, rs.sysid_conflicts
            d["id_changes"] = rs.id_changes
            d["unverified_systems"] = rs.unverified_systems  # signing on: unsigned newcomers
            d["router"] = rs.as_dict()
            if self.router.verifier is not None:
                d["signing"] = self.router.verifier.stats.as_dict()
        d["vehicle"] = dict(first.stats.__dict__) if first is not None else {}
        d["systems"] = systems
        tlog = self.tlog
        if tlog is not None:
            # what the telemetry log lost, by reason (disk_full as dropped_disk_full: the
            # stop report's dropped line), also in the backend's total
            for reason, n in tlog.dropped.items():
                d["dropped_disk_full" if reason == "disk_full" else f"dropped_tlog_{reason}"] = n
            d["dropped"] += sum(tlog.dropped.values())
            d["tlog"] = {**tlog.stats(), "files": [str(p) for p in tlog.paths]}
        return d
