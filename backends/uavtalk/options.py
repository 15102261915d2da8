"""The UAVTalk backend's and source's options, declared once (see :mod:`gateway.options`):
their schemas, the ``--uavtalk`` flag and their documentation; a light module."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from gateway.io.endpoints import SERIAL, STREAM_KINDS, TCP, list_validator, text_of, validator
from gateway.options import Flag, ListenerOptions, Options, option
from gateway.vehicles import VehicleOptions

#: A serial endpoint's baud rate when it names none (LibrePilot's telemetry port).
DEFAULT_SERIAL_BAUD = 57600
DEFAULT_BAUD = 57600
#: FirmwareIAPObj.BoardType (``backends.uavtalk.telemetry.DEFAULT_BOARD_TYPE``): Revolution
DEFAULT_BOARD_TYPE = 0x09
#: Longest wait between two reopen attempts (``gateway.io.port.REOPEN_MAX_S``).
REOPEN_MAX_S = 2.0
#: The source's url (the backend's endpoints are ``STREAM_KINDS``).
URL_KINDS = (TCP, SERIAL)


@dataclass(frozen=True, kw_only=True)
class UavtalkOptions(ListenerOptions, VehicleOptions):
    """``[backends.uavtalk]``: one vehicle (``vehicle``; default: the first source's) to
    LibrePilot ground stations."""

    TITLE: ClassVar[str] = "UAVTalk backend"
    endpoints: list[str] = option([], "tcpin:HOST:PORT (the GCS connects), tcp:HOST:PORT, "
                                  "serial:DEVICE[,BAUD] or a pyserial URL",
                                  validator=list_validator(STREAM_KINDS,
                                                           default_baud=DEFAULT_SERIAL_BAUD),
                                  flag=Flag("--uavtalk", "serve the rocket to LibrePilot "
                                            "ground stations over UAVTalk (repeatable): "
                                            "tcpin:HOST:PORT (the GCS connects; each client "
                                            "its own session), tcp:HOST:PORT, "
                                            "serial:DEVICE[,BAUD] or a serial device / "
                                            "pyserial URL", metavar="ENDPOINT",
                                            convert=text_of(STREAM_KINDS)))
    board_type: int = option(DEFAULT_BOARD_TYPE, "FirmwareIAPObj.BoardType shown to the GCS "
                             "(9: Revolution); must be nonzero", minimum=1, maximum=255)
    tick_s: float = option(0.02, "seconds between telemetry ticks (periodic sends, retries)",
                           minimum=0.001, maximum=1.0)
    queue_depth: int = option(64, "packets waiting per link before drops", minimum=1,
                              maximum=4096)
    inbox_depth: int = option(256, "gateway messages waiting for the loop before drops",
                              minimum=1, maximum=65536)


@dataclass(frozen=True, kw_only=True)
class UavtalkSourceOptions(Options):
    """``[[sources]] type = "uavtalk"``: a LibrePilot flight controller, the gateway as its
    ground station."""

    url: str = option(help="the flight controller: tcp:HOST:PORT, or a serial device / "
                      "pyserial URL with an optional ,BAUD (/dev/ttyACM0,57600)",
                      validator=validator(URL_KINDS))
    baudrate: int = option(DEFAULT_BAUD, "serial speed when the url gives none", minimum=50)
    rate_hz: float = option(10.0, "most vehicle-state and position messages per second",
                            minimum=0.1, maximum=1000)
    reconnect_max_s: float = option(REOPEN_MAX_S, "longest wait between reopen attempts",
                                    minimum=0.01)
