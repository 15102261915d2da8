"""The HC-12 backend's options, declared once (see :mod:`gateway.options`): its
``[backends.hc12]`` schema, its ``run`` flags (``--hc12``, ``--hc12-baud``, ``--hc12-mode``)
and its documentation.  A light module (the ``aurora_gateway.backend_options`` entry point);
the constants the protocol modules also hold are checked equal by tests/test_options.py."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from gateway.options import Flag, ListenerOptions, option, serial_port_option
from gateway.vehicles import VehicleOptions

#: relay frames byte-identical, or generate them
MODES = ("relay", "generate")
#: the module's UART rates (``backends.hc12.BAUD_RATES``) and its AT-mode rate
BAUD_RATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
AT_BAUD = 9600
#: SM_UPDATE payload lengths (``gateway.model.SM_UPDATE_F32_LEN`` / ``_F64_LEN``)
SM_UPDATE_F32_LEN, SM_UPDATE_F64_LEN = 36, 64
#: how fresh the vehicle's IDLE must be for provisioning (``backends.hc12.vehicle``)
DEFAULT_MAX_AGE_S = 3.0


@dataclass(frozen=True, kw_only=True)
class Hc12Options(ListenerOptions, VehicleOptions):
    """``[backends.hc12]``: an HC-12 433 MHz UART radio, relaying one vehicle (``vehicle``;
    default: the first source's)."""

    TITLE: ClassVar[str] = "HC-12 backend"
    url: str = serial_port_option("the HC-12's serial port or pyserial URL: /dev/ttyUSB0, "
                                  "rfc2217://host:port", "--hc12", "HC-12 backend: relay "
                                  "frames to the HC-12 on this port or URL")
    baudrate: int = option(9600, "host UART rate; must equal the module's (AT+B)",
                           choices=BAUD_RATES, flag=Flag("--hc12-baud", metavar="N"))
    mode: str = option("relay", "relay: pass frames on byte-identical; generate: encode "
                       "updates in `revision`", choices=MODES,
                       flag=Flag("--hc12-mode", "HC-12 backend: relay frames byte-identical "
                                 "or generate them", metavar="MODE"))
    revision: int = option(SM_UPDATE_F64_LEN, "SM_UPDATE payload length in generate mode",
                           choices=(SM_UPDATE_F32_LEN, SM_UPDATE_F64_LEN))
    air_baud: int = option(9600, "the link rate the byte budget is computed from (10 bits a "
                           "byte); the lower of this and baudrate counts", minimum=300,
                           maximum=1_000_000)
    utilisation_pct: float = option(80.0, "share of the air link frames may use", minimum=1,
                                    maximum=100)
    burst_bytes: int | None = option(None, "bytes that may go out back to back; default: the "
                                     "headroom of one second", minimum=0, maximum=65536)
    queue_depth: int = option(16, "frames waiting for the port before drops", minimum=1,
                              maximum=4096)
    min_interval_s: float = option(0.0, "least time between accepted SM_UPDATEs; 0 = off "
                                   "(STATUS exempt)", minimum=0)
    set_line: str = option("none", "the module's SET line: none, rts, dtr or gpio:CHIP:LINE")
    set_invert: bool = option(False, "SET is driven through an inverter")
    at_baud: int = option(AT_BAUD, "host UART rate while in AT mode", choices=BAUD_RATES)
    reply_timeout_s: float = option(1.0, "how long to wait for an AT reply", minimum=0.05,
                                    maximum=30)
    idle_max_age_s: float = option(DEFAULT_MAX_AGE_S, "how fresh the vehicle's IDLE must be "
                                   "for provisioning", minimum=0.1, maximum=600)
    control: str = option("auto", "control socket for `aurora-gateway hc12`: auto, off or a "
                          "path")
