"""One XBee module in API mode, driven from a :class:`gateway.io.port.PortEngine` (its protocol
object): API frames in and out (:mod:`.frames`), and what the link roles (:mod:`.link`) ask of
the module.

* :meth:`XBeeModule.send` ``(payload, power)``: when the module's PL is not ``power``, an AT PL
  frame goes first, in the same write as the 0x10 Transmit Request — the module handles its
  UART's frames in order, so the payload leaves at ``power``, as its power bits say.
* :meth:`XBeeModule.query_rssi` ``(token)``: AT DB; the answer comes back through
  ``on_rssi(token, dbm)``.
* At each (re)connection: AT NP (the largest payload: the roles never build a larger one) and
  AT PL (what the module is set to); every ``poll_s`` the counters ER, GD, TR, EA and DC, and
  DB, handed to ``on_readings``.
* A 0x90 Receive Packet → ``on_payload(data, src64)``; 0x8B counted (delivered, failed);
  0x8A modem status after a reset: the PL is set again before the next payload.

Frame ids 1..255 cycle; an AT answer is matched to its request by id.  Nothing here blocks or
raises on what the module sends: bad frames are the decoder's counters.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from gateway.counters import Counters
from gateway.io.port import PortEngine
from gateway.outcome import Outcome

from . import frames as f

log = logging.getLogger(__name__)

POLL_COMMANDS = (f.AT_RSSI, f.AT_RX_ERRORS, f.AT_GOOD_PACKETS, f.AT_TX_ERRORS,
                 f.AT_ACK_FAILURES, "DC")


@dataclass
class ModuleCounters(Counters):
    payloads_sent: int = 0
    payloads_refused: int = 0  # the engine's queue was full or the port down
    pl_sets: int = 0
    tx_delivered: int = 0
    tx_failed: int = 0
    payloads_received: int = 0
    at_errors: int = 0
    resets: int = 0


class XBeeModule:
    """The engine's protocol for one module (see the module docstring)."""

    def __init__(self, api_mode: int = 1, *, dest64: int = f.BROADCAST_64,
                 on_payload: Callable[[bytes, int], Any],
                 on_rssi: Callable[[int, float], Any] | None = None,
                 on_readings: Callable[[dict[str, int]], Any] | None = None,
                 on_np: Callable[[int], Any] | None = None) -> None:
        if api_mode not in f.API_MODES:
            raise ValueError(f"API mode {api_mode!r}: use 1 or 2")
        self.api_mode = api_mode
        self.dest64 = dest64
        self.on_payload = on_payload
        self.on_rssi = on_rssi
        self.on_readings = on_readings
        self.on_np = on_np
        self.engine: PortEngine | None = None
        self.decoder = f.FrameDecoder(api_mode)
        self.counters = ModuleCounters()
        self.pl: int | None = None  # None: not known (PL is set before the next payload)
        self.np: int | None = None
        self.readings: dict[str, int] = {}
        self._frame_id = 0
        self._pending: dict[int, tuple[str, int | None]] = {}  # frame id → (AT, rssi token)

    # -- writing ---------------------------------------------------------------------------------

    def _next_id(self) -> int:
        self._frame_id = self._frame_id % 255 + 1
        self._pending.pop(self._frame_id, None)
        return self._frame_id

    def _at(self, command: str, parameter: bytes = b"", token: int | None = None) -> bytes:
        fid = self._next_id()
        self._pending[fid] = (command, token)
        return f.encode(f.AtCommand(fid, command, parameter), self.api_mode)

    def _write(self, data: bytes) -> bool:
        engine = self.engine
        return engine is not None and engine.submit(data, rate_limited=False) is \
            Outcome.ACCEPTED

    def send(self, payload: bytes, power: int) -> bool:
        """Transmit ``payload`` at PL ``power`` (PL set first when it differs)."""
        data = b""
        if self.pl != power:
            data = self._at(f.AT_POWER_LEVEL, f.pl_param(power))
        frame = f.TransmitRequest(self._next_id(), self.dest64, payload)
        if not self._write(data + f.encode(frame, self.api_mode)):
            self.counters.payloads_refused += 1
            return False
        if data:
            self.pl = power
            self.counters.pl_sets += 1
        self.counters.payloads_sent += 1
        return True

    def query_rssi(self, token: int) -> None:
        self._write(self._at(f.AT_RSSI, token=token))

    def poll(self) -> None:
        """Ask for the counters and the last RSSI (answers go to ``on_readings``)."""
        self._write(b"".join(self._at(c) for c in POLL_COMMANDS))

    def connected(self) -> None:
        """The port came up: learn NP and PL again (a module may have been swapped)."""
        self.pl = None
        self.decoder = f.FrameDecoder(self.api_mode)
        self._pending.clear()
        self._write(self._at(f.AT_MAX_PAYLOAD) + self._at(f.AT_POWER_LEVEL))

    # -- reading (the engine's thread) ------------------------------------------------------

    def feed(self, data: bytes) -> tuple[()]:
        for frame in self.decoder.feed(data):
            self._handle(frame)
        return ()

    def _handle(self, frame: Any) -> None:
        c = self.counters
        if isinstance(frame, f.ReceivePacket):
            c.payloads_received += 1
            self.on_payload(frame.data, frame.src64)
        elif isinstance(frame, f.TransmitStatus):
            if frame.delivery == f.DELIVERY_SUCCESS:
                c.tx_delivered += 1
            else:
                c.tx_failed += 1
        elif isinstance(frame, f.AtResponse):
            self._at_response(frame)
        elif isinstance(frame, f.ModemStatus) and frame.status in (f.MODEM_HARDWARE_RESET,
                                                                     f.MODEM_WATCHDOG_RESET):
            c.resets += 1
            self.pl = None

    def _at_response(self, r: f.AtResponse) -> None:
        pending = self._pending.pop(r.frame_id, None)
        if pending is None or pending[0] != r.command:
            return
        command, token = pending
        if not r.ok:
            self.counters.at_errors += 1
            if command == f.AT_POWER_LEVEL:
                self.pl = None  # not applied: set it again before the next payload
            return
        try:
            if command == f.AT_POWER_LEVEL:
                if r.value:  # a query's answer (a set's answer carries no value)
                    self.pl = f.decode_pl(r.value)
            elif command == f.AT_MAX_PAYLOAD:
                self.np = f.decode_np(r.value)
                if self.on_np is not None:
                    self.on_np(self.np)
            elif command == f.AT_RSSI:
                dbm = f.decode_db(r.value)
                self.readings[command] = dbm
                if token is not None and self.on_rssi is not None:
                    self.on_rssi(token, float(dbm))
                elif self.on_readings is not None:
                    self.on_readings({command: dbm})
            else:
                self.readings[command] = f.at_int(r.value, 16)
                if self.on_readings is not None:
                    self.on_readings({command: self.readings[command]})
        except f.AtValueError:
            self.counters.at_errors += 1

    def stats(self) -> dict[str, Any]:
        return {**self.counters.as_dict(), "pl": self.pl, "np": self.np,
                **{f"module_{k.lower()}": v for k, v in self.readings.items()},
                **{f"decoder_{k}": v for k, v in self.decoder.stats.as_dict().items()}}
