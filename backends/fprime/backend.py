"""The F´ backend: the rocket's telemetry as F´ channels, for NASA's F´ ground system.

Every gateway message the channel table knows (:mod:`.channels`) becomes channel entries —
``[id][time tag][value]`` — packed into ``Fw::TlmPacket`` buffers (:mod:`.packets`), framed
(:mod:`.framing`: ``ccsds``, F´ v4's default Space Packets in TM frames, or ``fprime``, the
``DEADBEEF`` frames) and written to every connected peer.  ``aurora-gateway
fprime-dictionary`` writes the JSON dictionary that lets ``fprime-gds`` decode them.

Endpoints (``endpoints``, ``--fprime``, repeatable) are those of :mod:`gateway.io.links`:
``tcpin:HOST:PORT`` is what ``fprime-gds --ip-client`` connects to (its default port 50000);
``tcp:HOST:PORT`` connects out to a ``fprime-gds`` acting as the server; a serial device or
pyserial URL is a radio or UART (``fprime-gds --communication-selection uart``).

Each link has its own framer, so its frame and sequence counts run on without gaps for its
peer.  The ground writes up the same connection (keep-alives, framed commands): it is read
and counted; the command ``Aurora.gateway.NO_OP`` is answered with an event, any other with
the event ``CommandNotSupported`` (and a log line, once per burst
with a count: :class:`~gateway.io.burstlog.BurstLog`): see :mod:`.commands`.

Framing runs on the dispatcher's thread (a few µs per message); the engines only queue and
write, and a peer that does not read fills its own queue and loses frames (``dropped``),
nobody else waits.

The F´ deployment is one spacecraft, so the backend serves one vehicle: the one named by
``vehicle`` in ``[backends.fprime]``, or else the first source's
(:class:`gateway.vehicles.VehicleSelector`); another vehicle's message is dropped first thing
(counted as ``other_vehicles``).  Messages about no vehicle (``vehicle`` "") are served, but
for a link event, which names its source: it is served when that source is the served
vehicle's (or yields it), or no source of this gateway.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, ClassVar

from gateway.backend import Backend, BackendError, GatewayContext, Outcome, Routes
from gateway.io.burstlog import BurstLog
from gateway.io.endpoints import Endpoint
from gateway.io.ioloop import IoLoop
from gateway.io.links import (
    LinkSet,
    parse_stream_endpoint,
)
from gateway.io.port import PortEngine
from gateway.io.server import ClientLimits
from gateway.model import Battery, LinkEvent, LinkStats, Position, SmUpdate, Status, VehicleState
from gateway.vehicles import SERVICE, VehicleSelector

from .channels import ChannelCodec, Getter, codecs
from .commands import NO_OP, CommandHandler
from .framing import make_deframer, make_framer
from .options import DEFAULT_SERIAL_BAUD, FprimeOptions
from .packets import TIME_BASES, TlmPacker, UpdateClock

log = logging.getLogger(__name__)

_ACCEPTED = Outcome.ACCEPTED
_NOT_READY = Outcome.NOT_READY


def parse_endpoint(text: str) -> Endpoint:
    """Parse one endpoint (:mod:`gateway.io.endpoints`); raises its EndpointError."""
    return parse_stream_endpoint(text, default_baud=DEFAULT_SERIAL_BAUD)


class Link:
    """One F´ ground peer: its framer (downlink) and its deframer (what the ground sends up)."""

    def __init__(self, name: str, backend: FprimeBackend) -> None:
        self.name = name
        self.backend = backend
        self.engine: PortEngine | None = None
        self.framer = backend.new_framer()
        self.deframer = backend.new_deframer()
        self.lock = threading.Lock()
        self.sent = 0
        self.sent_bytes = 0
        self.dropped = 0
        self.commands = 0

    def feed(self, data: bytes) -> tuple[()]:  # the loop's thread
        answers = []
        for packet in self.deframer.feed(data):
            answer = self.backend.command(packet)
            if answer is not None:
                answers.append(answer)
        if answers:  # framed together: a flood of commands costs frames, not one each
            self.commands += len(answers)
            self.send(answers)
        return ()

    def send(self, packets: list[bytes]) -> None:
        """Frame and queue ``packets`` (telemetry from the dispatcher's thread, answers to
        commands from the loop's: one lock keeps the framer's counts in order)."""
        engine = self.engine
        if engine is None or not engine.connected:
            return
        with self.lock:
            data = self.framer.frame(packets)
            outcome = engine.submit(data, rate_limited=False)
        if outcome is _ACCEPTED:
            self.sent += 1
            self.sent_bytes += len(data)
        else:
            self.dropped += 1

    def stats(self) -> dict[str, Any]:
        d = self.deframer
        engine = self.engine
        return {"sent": self.sent, "sent_bytes": self.sent_bytes, "dropped": self.dropped,
                "link": int(engine is not None and engine.connected),
                "errors": d.bad_crc + (engine.stats.errors if engine is not None else 0),
                # its CRC failures are the backend's crc_failures (one key with "crc" in the
                # whole table: the stop report's crc errors add every such counter)
                "uplink_frames": d.frames, "uplink_corrupt_frames": d.bad_crc,
                "uplink_garbage_bytes": d.garbage_bytes, "uplink_keepalives": d.keepalives,
                "commands": self.commands}


class FprimeBackend(Backend):
    """Serves the rocket's channels to F´ ground systems (see the module docstring)."""

    NAME = "fprime"
    OPTIONS = FprimeOptions
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None  # it listens on a port: opt in

    def __init__(self, options: FprimeOptions, name: str | None = None) -> None:
        super().__init__(name)
        self.specs = [parse_endpoint(e) for e in options.endpoints]
        self.framing = options.framing
        self.id_base = options.id_base
        self.scid = options.scid
        self.vcid = options.vcid
        self.frame_size = options.frame_size
        self.new_framer()  # refuse a bad frame size now, not at the first client
        self.codecs: dict[type, tuple[tuple[ChannelCodec, Getter], ...]] = codecs(options.id_base)
        self.packer = TlmPacker(options.buffer_size)
        self.clock = UpdateClock(TIME_BASES[options.time_base], options.time_context)
        self.loop = IoLoop(self.name)
        self.linkset: LinkSet[Link] = LinkSet(
            self.name, self.specs, loop=self.loop, new_link=lambda n, _spec: Link(n, self),
            queue_depth=options.queue_depth, on_closed=self._retire, label="ground system",
            limits=ClientLimits.of(options, options.queue_depth))
        self._closed = {"sent": 0, "sent_bytes": 0, "dropped": 0, "errors": 0, "commands": 0,
                        "crc_failures": 0, "clients_closed": 0}
        self.commands = CommandHandler(options.id_base)
        #: commands the gateway does not have: one line, then a count per interval
        self.unsupported_log = BurstLog(
            self.loop, f"{self.name}: F´ commands not supported (answered with the event "
            "CommandNotSupported)", logger=log)
        self.messages = 0
        #: the vehicle this deployment is
        self.selector = VehicleSelector(options.vehicle)
        self.other_vehicles = 0
        self._source_vehicles: dict[str, str] = {}  # source → its vehicle (or their stem)
        self._first_source = ""
        self.packets = 0
        self.entries = 0

    def new_framer(self) -> Any:
        return make_framer(self.framing, scid=self.scid, vcid=self.vcid,
                           frame_size=self.frame_size)

    def new_deframer(self) -> Any:
        return make_deframer(self.framing, scid=self.scid)

    # -- life cycle ------------------------------------------------------------------------------

    @property
    def links(self) -> list[Link]:
        return self.linkset.links

    def address(self, endpoint: str | None = None) -> Any:
        """The bound (host, port) of a tcpin endpoint (the first when None)."""
        return self.linkset.address(endpoint)

    def attach(self, context: GatewayContext) -> None:
        """Learn which vehicle is served by default (the first source's)."""
        super().attach(context)
        self.selector.attach(context, f"backends.{self.name}")
        sources = context.services.get(SERVICE) or []
        self._source_vehicles = {s[0]: s[1] for s in sources}
        self._first_source = sources[0][0] if sources else ""

    def init(self) -> None:
        self.linkset.open(BackendError)
        for spec in self.specs:
            if spec.kind == "tcpin":
                host, port = self.address(spec.text)
                log.info("%s: serving F´ %s frames on %s:%s (fprime-gds --ip-client "
                         "--ip-address %s --ip-port %s)", self.name, self.framing, host, port,
                         host, port)

    def close(self) -> None:
        self.linkset.shut()

    def _retire(self, link: Link) -> None:
        t = self._closed
        d = link.stats()
        for key in ("sent", "sent_bytes", "dropped", "errors", "commands"):
            t[key] += d[key]
        t["crc_failures"] += link.deframer.bad_crc
        t["clients_closed"] += 1

    def command(self, packet: bytes) -> bytes | None:
        """The event packet answering a command packet from the ground (None: not a
        command); an opcode the gateway does not have is also logged, once per burst (the
        opcodes are counted, not kept: a peer can send any number of them)."""
        answer = self.commands.handle(packet, self.clock.tag())
        if answer is not None:
            opcode = self.commands.opcode(packet)
            if opcode != self.id_base + NO_OP.offset:
                burst = self.unsupported_log  # (the opcode is named on the burst's first line)
                burst.event("" if burst.active else f"opcode {opcode:#x}")
        return answer

    # -- routes ----------------------------------------------------------------------------------

    def routes(self) -> Routes:
        return (Routes().on(SmUpdate, self.send_timed).on(Status, self.send_timed)
                .on(LinkEvent, self.send_link_event).on(LinkStats, self.send_message)
                .on(Position, self.send_message).on(Battery, self.send_message)
                .on(VehicleState, self.send_message))

    def send_timed(self, msg: SmUpdate | Status) -> Outcome:
        """A message stamped by the flight computer: its channels carry that time."""
        if not self.selector.accepts(msg):
            return self._other()
        return self._send(msg, self.clock.tag(msg.timestamp_ms))

    def send_link_event(self, msg: LinkEvent) -> Outcome:
        """A source's link went up or down: the served vehicle's, or one of no vehicle."""
        if not msg.vehicle and not self._serves_source(msg.source):
            return self._other()
        return self.send_message(msg)

    def _serves_source(self, source: str) -> bool:
        """Whether ``source`` is the served vehicle's: its vehicle is the one served, or (a
        source hearing several systems) their stem; a name that is no source's: yes."""
        vehicle = self._source_vehicles.get(source)
        if vehicle is None:
            return True
        chosen = self.selector.chosen
        if not chosen:  # not chosen yet (nothing heard): the first source's
            return source == self._first_source
        if chosen == vehicle:
            return True
        return (chosen.startswith(vehicle + "-")
                and chosen not in self._source_vehicles.values())

    def send_message(self, msg: Any) -> Outcome:
        if not self.selector.accepts(msg):
            return self._other()
        return self._send(msg, self.clock.tag())

    def _other(self) -> Outcome:
        """Another vehicle's message: not for this deployment (counted, not an error)."""
        self.other_vehicles += 1
        return _ACCEPTED

    def _send(self, msg: Any, tag: tuple[int, int, int, int]) -> Outcome:
        self.messages += 1
        links = [k for k in self.linkset.links if k.engine is not None and k.engine.connected]
        if not links:
            return _NOT_READY
        entries = []
        for codec, get in self.codecs[type(msg)]:
            entry = codec.entry(get(msg), tag)
            if entry is not None:
                entries.append(entry)
        if not entries:
            return _ACCEPTED
        packets = self.packer.pack(entries)
        self.entries += len(entries)
        self.packets += len(packets)
        for link in links:
            link.send(packets)
        return _ACCEPTED

    # -- stats -----------------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        t = self._closed
        links = list(self.linkset.links)
        per = {link.name: link.stats() for link in links}
        total = {key: t[key] + sum(d[key] for d in per.values())
                 for key in ("sent", "sent_bytes", "dropped", "errors", "commands")}
        connected = sum(d["link"] for d in per.values())
        return {**total, "dropped": total["dropped"] + self.packer.too_big,
                "link": int(connected > 0), "messages": self.messages,
                "other_vehicles": self.other_vehicles, "packets": self.packets,
                "channel_values": self.entries, "dropped_too_big": self.packer.too_big,
                "time_resyncs": self.clock.resyncs, "clients": len(links),
                "commands_not_supported": self.commands.not_supported,
                "crc_failures": t["crc_failures"] + sum(k.deframer.bad_crc for k in links),
                "connected": connected, "clients_closed": t["clients_closed"],
                **self.linkset.server_stats(), "links": per}
