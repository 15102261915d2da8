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
the event ``CommandNotSupported`` (and a log line, once per opcode): see :mod:`.commands`.

Framing runs on the dispatcher's thread (a few µs per message); the engines only queue and
write, and a peer that does not read fills its own queue and loses frames (``dropped``),
nobody else waits.
"""

from __future__ import annotations

import logging
import threading
from typing import Any, ClassVar

from gateway.backend import Backend, BackendError, Outcome, Routes
from gateway.config import Key, Schema
from gateway.io.ioloop import IoLoop
from gateway.io.links import (
    USAGE,
    LinkSet,
    StreamEndpoint,
    endpoints_validator,
    parse_stream_endpoint,
)
from gateway.io.port import PortEngine
from gateway.io.server import (
    DEFAULT_CLIENT_TIMEOUT_S,
    DEFAULT_MAX_CLIENTS,
    ClientLimits,
)
from gateway.model import Battery, LinkEvent, LinkStats, Position, SmUpdate, Status, VehicleState

from .channels import DEFAULT_ID_BASE, ChannelCodec, Getter, check_id_base, codecs
from .commands import NO_OP, CommandHandler
from .framing import (
    DEFAULT_FRAMING,
    FRAMINGS,
    TM_MAX_FRAME,
    TM_MIN_FRAME,
    make_deframer,
    make_framer,
)
from .packets import DEFAULT_BUFFER_SIZE, TIME_BASES, TlmPacker, UpdateClock

log = logging.getLogger(__name__)

DEFAULT_SERIAL_BAUD = 115200
_ACCEPTED = Outcome.ACCEPTED
_NOT_READY = Outcome.NOT_READY


def parse_endpoint(text: str) -> StreamEndpoint:
    """Parse one endpoint (see :mod:`gateway.io.links`); raises ValueError naming it."""
    return parse_stream_endpoint(text, default_baud=DEFAULT_SERIAL_BAUD)


def _check_id_base(value: Any) -> None:
    check_id_base(value)


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
        for packet in self.deframer.feed(data):
            answer = self.backend.command(packet)
            if answer is not None:
                self.commands += 1
                self.send([answer])
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
                "uplink_frames": d.frames, "uplink_bad_crc": d.bad_crc,
                "uplink_garbage_bytes": d.garbage_bytes, "uplink_keepalives": d.keepalives,
                "commands": self.commands}


class FprimeBackend(Backend):
    """Serves the rocket's channels to F´ ground systems (see the module docstring)."""

    NAME = "fprime"
    CONFIG = Schema(
        endpoints=Key(list, [], "tcpin:HOST:PORT (fprime-gds --ip-client connects), "
                      "tcp:HOST:PORT, serial:DEVICE[,BAUD] or a pyserial URL",
                      validator=endpoints_validator(DEFAULT_SERIAL_BAUD)),
        framing=Key(str, DEFAULT_FRAMING, "ccsds (F´ v4 / fprime-gds default) or fprime",
                    choices=tuple(FRAMINGS)),
        id_base=Key(int, DEFAULT_ID_BASE, "id of the first channel (the dictionary's "
                    "--id-base must be the same)", validator=_check_id_base),
        buffer_size=Key(int, DEFAULT_BUFFER_SIZE, "bytes per telemetry packet "
                        "(FW_COM_BUFFER_MAX_SIZE)", minimum=32, maximum=4000),
        time_base=Key(str, "workstation", "time base of the time tags",
                      choices=tuple(TIME_BASES)),
        time_context=Key(int, 0, "time context of the time tags", minimum=0, maximum=255),
        scid=Key(int, 0x44, "ccsds: spacecraft id (fprime-gds --scid or the dictionary's "
                 "ComCfg.SpacecraftId)", minimum=0, maximum=0x3FF),
        vcid=Key(int, 1, "ccsds: virtual channel id (fprime-gds --vcid)", minimum=0,
                 maximum=7),
        frame_size=Key(int, 1024, "ccsds: TM frame size (fprime-gds --frame-size or the "
                       "dictionary's ComCfg.TmFrameFixedSize)", minimum=TM_MIN_FRAME,
                       maximum=TM_MAX_FRAME),
        queue_depth=Key(int, 64, "writes waiting per peer before drops", minimum=1,
                        maximum=4096),
        max_clients=Key(int, DEFAULT_MAX_CLIENTS, "clients a tcpin listener serves at once; "
                        "more are refused (counted)", minimum=1, maximum=1024),
        client_timeout_s=Key(float, DEFAULT_CLIENT_TIMEOUT_S, "a client that stops reading "
                             "(or leaves a request incomplete) this long is cut", minimum=0.1,
                             maximum=600),
    )
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None  # it listens on a port: opt in

    def __init__(self, endpoints: list[str] | None = None, framing: str = DEFAULT_FRAMING,
                 id_base: int = DEFAULT_ID_BASE, buffer_size: int = DEFAULT_BUFFER_SIZE,
                 time_base: str = "workstation", time_context: int = 0, scid: int = 0x44,
                 vcid: int = 1, frame_size: int = 1024, queue_depth: int = 64,
                 max_clients: int = DEFAULT_MAX_CLIENTS,
                 client_timeout_s: float = DEFAULT_CLIENT_TIMEOUT_S,
                 name: str | None = None) -> None:
        super().__init__(name)
        self.specs = [parse_endpoint(e) for e in (endpoints or [])]
        if not self.specs:
            raise ValueError(f"at least one endpoint is needed; {USAGE}")
        if framing not in FRAMINGS:
            raise ValueError(f"framing {framing!r}: use one of {', '.join(FRAMINGS)}")
        check_id_base(id_base)
        self.framing = framing
        self.id_base = id_base
        self.scid = scid
        self.vcid = vcid
        self.frame_size = frame_size
        self.new_framer()  # refuse a bad frame size now, not at the first client
        self.codecs: dict[type, tuple[tuple[ChannelCodec, Getter], ...]] = codecs(id_base)
        self.packer = TlmPacker(buffer_size)
        self.clock = UpdateClock(TIME_BASES[time_base], time_context)
        self.loop = IoLoop(self.name)
        self.linkset: LinkSet[Link] = LinkSet(
            self.name, self.specs, loop=self.loop, new_link=lambda n, _spec: Link(n, self),
            queue_depth=queue_depth, on_closed=self._retire, label="ground system",
            limits=ClientLimits(max_clients, client_timeout_s, queue_depth))
        self._running = False
        self._closed = {"sent": 0, "sent_bytes": 0, "dropped": 0, "errors": 0, "commands": 0,
                        "clients_closed": 0}
        self.commands = CommandHandler(id_base)
        self._commands_seen: set[int] = set()
        self.messages = 0
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

    def init(self) -> None:
        try:
            self.linkset.bind()
        except OSError as exc:
            raise BackendError(f"{self.name}: {exc}") from exc
        self.loop.start()
        self._running = True
        self.linkset.start()
        for spec in self.specs:
            if spec.kind == "tcpin":
                host, port = self.address(spec.text)
                log.info("%s: serving F´ %s frames on %s:%s (fprime-gds --ip-client "
                         "--ip-address %s --ip-port %s)", self.name, self.framing, host, port,
                         host, port)

    def close(self) -> None:
        if not self._running:
            return
        self._running = False
        self.linkset.close()
        if self.loop.stop(1.0):
            self.loop.close()

    def _retire(self, link: Link) -> None:
        t = self._closed
        d = link.stats()
        for key in ("sent", "sent_bytes", "dropped", "errors", "commands"):
            t[key] += d[key]
        t["clients_closed"] += 1

    def command(self, packet: bytes) -> bytes | None:
        """The event packet answering a command packet from the ground (None: not a
        command); an opcode the gateway does not have is also logged, once per opcode."""
        answer = self.commands.handle(packet, self.clock.tag())
        if answer is not None:
            opcode = self.commands.opcode(packet)
            if opcode != self.id_base + NO_OP.offset and opcode not in self._commands_seen:
                self._commands_seen.add(opcode)
                log.warning("%s: F´ command opcode %#x is not supported (answered with the "
                            "event CommandNotSupported)", self.name, opcode)
        return answer

    # -- routes ----------------------------------------------------------------------------------

    def routes(self) -> Routes:
        return (Routes().on(SmUpdate, self.send_timed).on(Status, self.send_timed)
                .on(LinkEvent, self.send_message).on(LinkStats, self.send_message)
                .on(Position, self.send_message).on(Battery, self.send_message)
                .on(VehicleState, self.send_message))

    def send_timed(self, msg: SmUpdate | Status) -> Outcome:
        """A message stamped by the flight computer: its channels carry that time."""
        return self._send(msg, self.clock.tag(msg.timestamp_ms))

    def send_message(self, msg: Any) -> Outcome:
        return self._send(msg, self.clock.tag())

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
                "link": int(connected > 0), "messages": self.messages, "packets": self.packets,
                "channel_values": self.entries, "dropped_too_big": self.packer.too_big,
                "time_resyncs": self.clock.resyncs, "clients": len(links),
                "commands_not_supported": self.commands.not_supported,
                "connected": connected, "clients_closed": t["clients_closed"],
                **self.linkset.server_stats(), "links": per}
