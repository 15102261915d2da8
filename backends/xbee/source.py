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
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from gateway.backend import Routes
from gateway.config import Key, Schema
from gateway.model import LinkStats, RcChannels, SmUpdate, Status
from gateway.sources import Sink, Source, check_serial_url

from . import frames as f
from .link import GroundLink, QueryRssi, Send
from .radio import DEFAULT_BAUD, POLL_S, SERVOS, TICK_S, Radio, servo_from_us

VIA_XBEE = "xbee"


class XbeeSource(Source):
    """The ground side of the XBee link (see the module docstring)."""

    NAME = "xbee"
    CONFIG = Schema(
        url=Key(str, help="the XBee module: a serial device or pyserial URL "
                "(socket://HOST:PORT)", validator=check_serial_url),
        baudrate=Key(int, DEFAULT_BAUD, "the module's UART rate (its BD)", minimum=50),
        api_mode=Key(int, 1, "the module's API mode (AP): 1, or 2 (escaped)", choices=(1, 2)),
        rssi_threshold_dbm=Key(float, -85.0, "a power level whose pings arrive at least this "
                               "strong is adequate; the lowest adequate one is used",
                               minimum=-120, maximum=0),
        tick_s=Key(float, TICK_S, "seconds between link ticks", minimum=0.001, maximum=0.1),
        poll_s=Key(float, POLL_S, "seconds between reads of the module's counters",
                   minimum=0.1),
    )

    @staticmethod
    def default_name(options: dict[str, Any]) -> str:
        return f"xbee:{options['url']}"

    def __init__(self, url: str, baudrate: int = DEFAULT_BAUD, api_mode: int = 1,
                 rssi_threshold_dbm: float = -85.0, tick_s: float = TICK_S,
                 poll_s: float = POLL_S, name: str | None = None) -> None:
        super().__init__(name or f"xbee:{url}")
        self.link = GroundLink(rssi_threshold_dbm=rssi_threshold_dbm, origin=self.name,
                               via=VIA_XBEE)
        self.radio = Radio(f"source {self.name}", url, baudrate, api_mode,
                           dest64=f.BROADCAST_64, perform=self._perform, tick=self.link.tick,
                           on_payload=self._on_payload, on_rssi=self._on_rssi,
                           tick_s=tick_s, poll_s=poll_s)
        self.messages = 0
        self.commands_in = 0

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
        values = {i: servo_from_us(us) for i, us in enumerate(msg.channels_us[:SERVOS])
                  if us is not None}
        self.commands_in += 1
        radio = self.radio
        radio.perform(self.link.set_servos(values, radio.clock()))

    def inbox_stats(self) -> dict[str, Any]:
        h = self.radio.handover
        return {"sent": self.commands_in, "dropped": h.dropped,
                "dropped_queue_full": h.dropped_queue_full, "errors": h.handler_errors,
                "link": int(self.radio.engine.connected)}

    # -- life cycle --------------------------------------------------------------------------

    def start(self, sink: Sink) -> None:
        if self._sink is not None:
            return
        self._sink = sink
        self.radio.start()

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        self.radio.close(timeout)
        self.done.set()

    def stats(self) -> dict[str, Any]:
        g = self.link
        return {**self.radio.stats(), "messages": self.messages, "seq": g.seq,
                "acked_seq": g.acked_seq, "power": g.power_in_use,
                "ack_latency_ms": None if g.ack_latency_median is None
                else round(g.ack_latency_median * 1000, 1),
                **{f"ground_{k}": v for k, v in g.counters.as_dict().items()}}
