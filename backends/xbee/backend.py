"""The XBee air side (the seed's "wing"), as a backend: the rocket's gateway on an XBee.

``run --xbee URL [--xbee-api 1|2] [--xbee-dest HEX]``: URL a serial port or pyserial URL
(``socket://host:port`` reaches a module's UART over TCP).  SM updates and STATUS go down as
the link's compact telemetry packets, grouped (:class:`~.link.AirLink`); the air role's ACKs,
PINGs (every 500 ms, PL cycling 0..4) and STATS (every 100 ms) go with them; command packets
from the ground become :class:`~gateway.model.RcChannels` for the other backends (MAVLink
RC_CHANNELS to a ground station, …).  Without ``dest`` the air side broadcasts.

The air side carries one vehicle: the one named by ``vehicle`` in ``[backends.xbee]``, or else
the first source's (:class:`gateway.vehicles.VehicleSelector`); another vehicle's messages are
not sent (counted as ``other_vehicles``), and the commands from the ground carry the vehicle's
name once known (they address it).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, ClassVar

from gateway.backend import Backend, GatewayContext, Routes
from gateway.model import SmUpdate, Status
from gateway.vehicles import VehicleSelector

from .link import AirLink, RcCommand, Send
from .options import MIN_PAYLOAD, XbeeOptions
from .radio import Radio, parse_dest, rc_message


class XbeeBackend(Backend):
    """The air side of the XBee link (see the module docstring)."""

    NAME = "xbee"
    OPTIONS = XbeeOptions
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None  # needs a module: opt in

    def __init__(self, options: XbeeOptions, name: str | None = None) -> None:
        super().__init__(name)
        self.link = AirLink(max_payload=options.max_payload)
        self.commands = 0
        #: the vehicle this air side carries
        self.selector = VehicleSelector(options.vehicle)
        self.other_vehicles = 0
        self.radio = Radio(f"{self.name} {options.url}", options.url, options.baudrate,
                           options.api_mode,
                           dest64=parse_dest(options.dest), perform=self._perform,
                           tick=self.link.tick, on_payload=self._on_payload,
                           on_readings=self._on_readings, on_np=self._on_np,
                           tick_s=options.tick_s, poll_s=options.poll_s)

    # -- the radio's thread -----------------------------------------------------------------

    def _perform(self, outputs: Iterable[Any]) -> None:
        for out in outputs:
            if isinstance(out, Send):
                self.radio.send(out)
            elif isinstance(out, RcCommand):
                self.commands += 1
                self.emit(rc_message(out, self.name, self.selector.chosen))

    def _on_payload(self, data: bytes, src64: int, now: float) -> list[Any]:
        return self.link.on_packet(data, None, now)

    def _on_readings(self, r: dict[str, int]) -> None:
        self.link.module_readings(
            rssi_dbm=r.get("DB"), rx_errors=r.get("ER"), good_packets=r.get("GD"),
            tx_errors=r.get("TR"), ack_failures=r.get("EA"), duty_cycle_pct=r.get("DC"))

    def _on_np(self, np_: int) -> None:
        if np_ >= MIN_PAYLOAD:
            self.link.max_payload = np_

    # -- life cycle and routes --------------------------------------------------------------

    def attach(self, context: GatewayContext) -> None:
        """Learn which vehicle is carried by default (the first source's)."""
        super().attach(context)
        self.selector.attach(context, f"backends.{self.name}")

    def init(self) -> None:
        self.radio.start()

    def close(self) -> None:
        self.radio.close()

    def routes(self) -> Routes:
        """Handled on the radio's thread (its hand-over: NOT_READY while the port is down)."""
        return (Routes(handover=self.radio.handover).on(SmUpdate, self.send_sm_update)
                .on(Status, self.send_status))

    def send_sm_update(self, msg: SmUpdate) -> None:
        if not self.selector.accepts(msg):
            self.other_vehicles += 1
            return
        radio = self.radio
        radio.perform(self.link.sm_update(msg, radio.clock()))

    def send_status(self, msg: Status) -> None:
        if not self.selector.accepts(msg):
            self.other_vehicles += 1
            return
        radio = self.radio
        radio.perform(self.link.status(msg, radio.clock()))

    def stats(self) -> dict[str, Any]:
        c = self.link.counters
        r = self.radio.stats()
        return {"sent": r["payloads_sent"],
                "dropped": r["payloads_refused"] + r["dropped_handover"],
                "errors": r["errors"] + r["at_errors"], "link": r["link"],
                "commands_applied": self.commands, "other_vehicles": self.other_vehicles, **r,
                **{f"air_{k}": v for k, v in c.as_dict().items()}}
