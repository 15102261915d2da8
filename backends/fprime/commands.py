"""F´ commands from the ground, and the events that answer them (sans-I/O).

The gateway serves telemetry; it has one command, so an operator can check the uplink from
fprime-gds: ``Aurora.gateway.NO_OP`` is answered with the event ``Aurora.gateway.NoOpReceived``.
Any other opcode (a dictionary of another deployment, a command the gateway does not have) is
answered with ``Aurora.gateway.CommandNotSupported`` naming the opcode, so the operator sees at
once why nothing happened.  Opcodes and event ids are ``id_base`` + offset, like the channels.

A command packet is ``[descriptor U16 = 0][opcode U32][arguments]``; an event packet is
``[descriptor U16 = FW_PACKET_LOG][event id U32][time tag][arguments, back to back]``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

from .channels import DEPLOYMENT
from .packets import DESCRIPTOR, FW_PACKET_LOG, TimeTag

FW_PACKET_COMMAND = 0
_HEAD = struct.Struct(">HIHBII")  # descriptor, event id, time tag
_U32 = struct.Struct(">I")


@dataclass(frozen=True)
class Command:
    name: str
    offset: int
    annotation: str

    def full_name(self) -> str:
        return f"{DEPLOYMENT}.gateway.{self.name}"


@dataclass(frozen=True)
class Event:
    name: str
    offset: int
    severity: str  # the dictionary's: ACTIVITY_HI, WARNING_LO …
    format: str
    args: tuple[tuple[str, str], ...] = ()  # (name, U32) — the only argument type used
    annotation: str = ""

    def full_name(self) -> str:
        return f"{DEPLOYMENT}.gateway.{self.name}"


NO_OP = Command("NO_OP", 0x00, "Check the uplink: the gateway answers with NoOpReceived")
COMMANDS: tuple[Command, ...] = (NO_OP,)

NO_OP_RECEIVED = Event("NoOpReceived", 0x00, "ACTIVITY_HI", "The gateway received NO_OP",
                       annotation="Answer to NO_OP: commands reach the gateway")
NOT_SUPPORTED = Event(
    "CommandNotSupported", 0x01, "WARNING_LO",
    "Command opcode {} is not supported: the gateway serves telemetry and has only NO_OP",
    args=(("opcode", "U32"),), annotation="A command the gateway does not have")
EVENTS: tuple[Event, ...] = (NO_OP_RECEIVED, NOT_SUPPORTED)


def event_packet(event: Event, event_id: int, tag: TimeTag, *args: int) -> bytes:
    """An F´ event (log) packet of ``event`` with its U32 arguments."""
    if len(args) != len(event.args):
        raise ValueError(f"{event.name} takes {len(event.args)} argument(s)")
    return _HEAD.pack(FW_PACKET_LOG, event_id, *tag) + b"".join(_U32.pack(a) for a in args)


class CommandHandler:
    """Answers the ground's command packets with event packets, for one id base."""

    def __init__(self, id_base: int) -> None:
        self.id_base = id_base
        self.received = 0
        self.not_supported = 0
        self.malformed = 0

    def handle(self, packet: bytes, tag: TimeTag) -> bytes | None:
        """The event packet answering ``packet`` (a command), or None (not a command)."""
        if len(packet) < DESCRIPTOR.size or DESCRIPTOR.unpack_from(packet)[0] != \
                FW_PACKET_COMMAND:
            return None
        if len(packet) < DESCRIPTOR.size + _U32.size:
            self.malformed += 1
            return None
        self.received += 1
        (opcode,) = _U32.unpack_from(packet, DESCRIPTOR.size)
        if opcode == self.id_base + NO_OP.offset:
            return event_packet(NO_OP_RECEIVED, self.id_base + NO_OP_RECEIVED.offset, tag)
        self.not_supported += 1
        return event_packet(NOT_SUPPORTED, self.id_base + NOT_SUPPORTED.offset, tag, opcode)

    @staticmethod
    def opcode(packet: bytes) -> int:
        return int(_U32.unpack_from(packet, DESCRIPTOR.size)[0])

    def stats(self) -> dict[str, Any]:
        return {"commands": self.received, "commands_not_supported": self.not_supported,
                "commands_malformed": self.malformed}
