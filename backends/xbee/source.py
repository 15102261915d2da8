"""The XBee ground side, as a source: the rocket's telemetry in, the pilot's commands up.

``run --source xbee:URL [--xbee-api 1|2]``: the telemetry downlink becomes the gateway's
messages (SM updates, STATUS — so QGroundControl, Zenoh, CRSF … see the rocket as from any
source — and :class:`~gateway.model.LinkStats` from the air's STATS), ``origin`` the source's
name, ``via`` ``"xbee"``.  The ground role (:class:`~.link.GroundLink`): command packets when
the sticks change (and a keep-alive every 150 ms), acked; TX power = the lowest level whose
ping RSSI clears ``rssi_threshold_dbm``, alternating 0/4 while nothing is heard.  The sticks
come from any :class:`~gateway.model.RcChannels` the gateway carries — a CRSF receiver's RC
channels, a ground station's MAVLink RC_CHANNELS_OVERRIDE or MANUAL_CONTROL — channel i
driving servo i (0..5; 1000..2000 µs ↔ 0..1023).  The ground answers the address the air's
packets come from (broadcast until the first one).

The source is one vehicle (the XBee link is point to point: one air side, one rocket): its
messages carry the source's :attr:`~gateway.sources.Source.vehicle` (the gateway stamps it by
``origin``), and it sends up only the commands addressed to that vehicle or to none
(``vehicle`` ""); others are counted as ``other_vehicles``.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from gateway.backend import Routes
from gateway.model import LinkStats, RcChannels, SmUpdate, Status
from gateway.sources import Source

from . import frames as f
from .link import GroundLink, QueryRssi, Send
from .options import XbeeSourceOptions
from .radio import SERVOS, Radio, servo_from_us

VIA_XBEE = "xbee"


class XbeeSource(Source):
    """The ground side of the XBee link (see the module docstring)."""

    NAME = "xbee"
    OPTIONS = XbeeSourceOptions
    NAME_FORMAT = "xbee:{url}"

    def __init__(self, options: XbeeSourceOptions, name: str | None = None) -> None:
        super().__init__(name or f"xbee:{options.url}")
        self.link = GroundLink(rssi_threshold_dbm=options.rssi_threshold_dbm, origin=self.name,
                               via=VIA_XBEE)
        self.radio = Radio(f"source {self.name}", options.url, options.baudrate, options.api_mode,
                           dest64=f.BROADCAST_64, perform=self._perform, tick=self.link.tick,
                           on_payload=self._on_payload, on_rssi=self._on_rssi,
                           tick_s=options.tick_s, poll_s=options.poll_s)
        self.messages = 0
        self.commands_in = 0
        self.other_vehicles = 0

    # -- the radio's thread -----------------------------------------------------------------

    def _perform(self, outputs: Iterable[Any]) -> None:
        sink = self._sink
        for out in outputs:
            if isinstance(out, Send):
                self.radio.send(out)
            elif isinstance(out, QueryRssi):
                self.radio.query(out)
            elif isinstance(out, SmUpdate | Status | LinkStats) and sink is not None:
                self.messages += 1
                sink(out)

    def _on_payload(self, data: bytes, src64: int, now: float) -> list[Any]:
        self.radio.module.dest64 = src64  # answer the air module
        return self.link.on_packet(data, None, now)

    def _on_rssi(self, token: int, dbm: float, now: float) -> None:
        self.link.ping_rssi(token, dbm, now)

    # -- the pilot's commands (handed over to the radio's thread) ----------------------------

    def routes(self) -> Routes:
        return Routes(handover=self.radio.handover).on(RcChannels, self.send_rc)

    def send_rc(self, msg: RcChannels) -> None:
        if msg.origin == self.name:
            return
        if msg.vehicle and msg.vehicle != self.vehicle:
            self.other_vehicles += 1  # another vehicle's sticks
            return
        values = {i: servo_from_us(us) for i, us in enumerate(msg.channels_us[:SERVOS])
                  if us is not None}
        self.commands_in += 1
        radio = self.radio
        radio.perform(self.link.set_servos(values, radio.clock()))

    def inbox_stats(self) -> dict[str, Any]:
        h = self.radio.handover
        return {"sent": self.commands_in, "dropped": h.dropped,
                "dropped_queue_full": h.dropped_queue_full, "errors": h.handler_errors,
                "other_vehicles": self.other_vehicles,
                "link": int(self.radio.engine.connected)}

    # -- life cycle --------------------------------------------------------------------------

    def begin(self) -> None:  # the radio's engine and timers run on the source's loop
        loop = self.io_loop
        assert loop is not None
        self.radio.engine.use_loop(loop)
        self.radio.start()

    def halt(self) -> None:
        self.radio.close(0.0)  # on the loop's thread: closes at once
        self.finish()

    def stats(self) -> dict[str, Any]:
        g = self.link
        return {**self.radio.stats(), "messages": self.messages, "seq": g.seq,
                "acked_seq": g.acked_seq, "power": g.power_in_use,
                "ack_latency_ms": None if g.ack_latency_median is None
                else round(g.ack_latency_median * 1000, 1),
                **{f"ground_{k}": v for k, v in g.counters.as_dict().items()}}
