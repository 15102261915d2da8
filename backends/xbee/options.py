"""The XBee backend's (air side) and source's (ground side) options, declared once (see
:mod:`gateway.options`): their schemas, the ``--xbee``, ``--xbee-dest`` and ``--xbee-api``
flags (the last, declared once by the field both share, sets the API mode of the backend
and of every XBee source) and their documentation; a light module."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from gateway.options import Flag, Options, lazy, option, serial_port_option
from gateway.vehicles import VehicleOptions

#: an XBee's factory UART rate (BD = 3), ``backends.xbee.radio.DEFAULT_BAUD``
DEFAULT_BAUD = 9600
#: seconds between link ticks, and between reads of the module's counters
TICK_S = 0.01
POLL_S = 1.0
#: the largest packet (SmTelem) must fit
MIN_PAYLOAD = 24


@dataclass(frozen=True, kw_only=True)
class XbeeModuleOptions(Options):
    """What both sides of the XBee link set on their module."""

    baudrate: int = option(DEFAULT_BAUD, "the module's UART rate (its BD)", minimum=50)
    api_mode: int = option(1, "the module's API mode (AP): 1, or 2 (escaped)", choices=(1, 2),
                           flag=Flag("--xbee-api", "XBee: the modules' API mode (AP) for "
                                     "--source xbee:URL and --xbee (1, or 2: escaped; "
                                     "default 1)", metavar="1|2", enables=False))
    tick_s: float = option(TICK_S, "seconds between link ticks", minimum=0.001, maximum=0.1)


@dataclass(frozen=True, kw_only=True)
class XbeeOptions(XbeeModuleOptions, VehicleOptions):
    """``[backends.xbee]``: the air side, one vehicle's telemetry down (``vehicle``; default:
    the first source's) and commands up."""

    TITLE: ClassVar[str] = "XBee backend"
    url: str = serial_port_option("the XBee module: a serial device or pyserial URL "
                                  "(socket://HOST:PORT)", "--xbee", "XBee air side: the "
                                  "rocket's telemetry down and commands up through the XBee "
                                  "module on this serial port or pyserial URL "
                                  "(socket://HOST:PORT)")
    dest: str = option("", "64-bit destination in hex; empty: broadcast",
                       validator=lazy("backends.xbee.radio:parse_dest"),
                       flag=Flag("--xbee-dest", "XBee air side: the ground module's 64-bit "
                                 "address (default: broadcast)", metavar="HEX"))
    max_payload: int = option(100, "largest RF payload until the module's NP is known",
                              minimum=MIN_PAYLOAD, maximum=256)
    poll_s: float = option(POLL_S, "seconds between reads of the module's counters (DB, ER, "
                           "GD, TR, EA, DC)", minimum=0.1)


@dataclass(frozen=True, kw_only=True)
class XbeeSourceOptions(XbeeModuleOptions):
    """``[[sources]] type = "xbee"``: the ground side."""

    url: str = serial_port_option("the XBee module: a serial device or pyserial URL "
                                  "(socket://HOST:PORT)")
    rssi_threshold_dbm: float = option(-85.0, "a power level whose pings arrive at least this "
                                       "strong is adequate; the lowest adequate one is used",
                                       minimum=-120, maximum=0)
    poll_s: float = option(POLL_S, "seconds between reads of the module's counters",
                           minimum=0.1)
