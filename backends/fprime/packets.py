"""F´ telemetry packets (sans-I/O): time tags and ``Fw::TlmPacket`` buffers.

A packet is ``[descriptor U16 = FW_PACKET_TELEM]`` then ``[channel id U32][time tag][value]``
repeated, big-endian, no lengths (the ground knows each channel's size from the dictionary).
Entries fill a packet until the next would overflow the buffer (``Fw::ComBuffer``,
``FW_COM_BUFFER_MAX_SIZE`` = 512 bytes by default): as ``TlmPacket::addValue`` answers
"no room left", that entry starts the next packet.
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable, Iterable

FW_PACKET_TELEM = 1
FW_PACKET_LOG = 2
DESCRIPTOR = struct.Struct(">H")  # FwPacketDescriptorType: U16 in F´ v4
#: ``FW_COM_BUFFER_MAX_SIZE`` of F´ v4's default configuration.
DEFAULT_BUFFER_SIZE = 512
ENTRY_HEADER_SIZE = 4 + 11  # channel id U32, time tag (base U16, context U8, s U32, µs U32)

# Fw::TimeBase
TB_NONE = 0
TB_PROC_TIME = 1
TB_WORKSTATION_TIME = 2
TB_SC_TIME = 3
TB_FPGA_TIME = 4
TB_DONT_CARE = 0xFFFF
TIME_BASES = {"none": TB_NONE, "proc": TB_PROC_TIME, "workstation": TB_WORKSTATION_TIME,
              "spacecraft": TB_SC_TIME, "fpga": TB_FPGA_TIME, "dont-care": TB_DONT_CARE}
#: An update stamped this far behind the gateway's clock (after a gap: the link was down, a
#: replay paused) is anchored again.
RESYNC_S = 2.0

TimeTag = tuple[int, int, int, int]  # base, context, seconds, microseconds


class UpdateClock:
    """Time tags from the updates' own timestamps (the flight computer's ms since boot).

    With time base ``proc`` the tag is that uptime itself.  With any other base (default
    ``workstation``) the uptime is anchored once to the gateway's clock, so the ground sees
    wall-clock times spaced exactly as the flight computer stamped them, free of radio and
    scheduling jitter.  It is anchored again when the uptime goes back (a reboot, the 32-bit
    ms counter's wrap, a replay starting over) or falls more than :data:`RESYNC_S` behind the
    clock (a gap); an uptime running ahead (a simulation or replay faster than real time)
    keeps its spacing, so the ground's times never go back while the uptime does not.
    A message without a timestamp is tagged with the gateway's clock.
    """

    def __init__(self, base: int = TB_WORKSTATION_TIME, context: int = 0,
                 clock: Callable[[], float] = time.time) -> None:
        if not 0 <= base <= 0xFFFF:
            raise ValueError(f"time base {base} is not a U16")
        if not 0 <= context <= 0xFF:
            raise ValueError(f"time context {context} is not a U8")
        self.base = base
        self.context = context
        self.clock = clock
        self.anchor: float | None = None
        self.last = 0.0  # the last update's uptime, s
        self.resyncs = 0

    def tag(self, timestamp_ms: int | None = None) -> TimeTag:
        if timestamp_ms is None:
            return self._split(self.clock())
        if self.base == TB_PROC_TIME:
            return (self.base, self.context, timestamp_ms // 1000, timestamp_ms % 1000 * 1000)
        now = self.clock()
        t = timestamp_ms / 1000.0
        anchor = self.anchor
        if anchor is None or t < self.last or anchor + t < now - RESYNC_S:
            if anchor is not None:
                self.resyncs += 1
            self.anchor = anchor = now - t
        self.last = t
        return self._split(anchor + t)

    def _split(self, t: float) -> TimeTag:
        us = round(t * 1e6)
        return (self.base, self.context, us // 1_000_000, us % 1_000_000)


class TlmPacker:
    """Packs serialized channel entries into telemetry packets of at most ``buffer_size``."""

    def __init__(self, buffer_size: int = DEFAULT_BUFFER_SIZE) -> None:
        if buffer_size < DESCRIPTOR.size + ENTRY_HEADER_SIZE + 1:
            raise ValueError(f"buffer size {buffer_size} holds no channel entry")
        self.buffer_size = buffer_size
        self._head = DESCRIPTOR.pack(FW_PACKET_TELEM)
        self.too_big = 0  # entries larger than a whole packet (dropped, counted)

    def pack(self, entries: Iterable[bytes]) -> list[bytes]:
        """The packets holding ``entries``, in order."""
        packets: list[bytes] = []
        room = self.buffer_size - len(self._head)
        parts: list[bytes] = []
        used = 0
        for entry in entries:
            n = len(entry)
            if n > room:
                self.too_big += 1
                continue
            if used + n > room:  # "no room left": this entry starts the next packet
                packets.append(self._head + b"".join(parts))
                parts, used = [], 0
            parts.append(entry)
            used += n
        if parts:
            packets.append(self._head + b"".join(parts))
        return packets
