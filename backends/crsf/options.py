"""The CRSF backend's options, declared once (see :mod:`gateway.options`): its
``[backends.crsf]`` schema, its ``run`` flags (``--crsf``, ``--crsf-baud``) and its
documentation come from here; a light module."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.io.endpoints import SERIAL, check_serial_port, text_of
from gateway.options import Flag, option
from gateway.vehicles import VehicleOptions

#: 'pty': create a pseudo-terminal and log its path
PTY_URL = "pty"
#: ExpressLRS's UART speed
DEFAULT_BAUD = 420000
#: the address bytes a frame may start with (``backends.crsf.frames``): flight controller,
#: radio transmitter, receiver
SYNC_FC, SYNC_RADIO, SYNC_RX = 0xC8, 0xEA, 0xEC


def _check_suffix(text: str) -> None:
    if len(text) > 4 or not text.isascii():
        raise ValueError("expected at most 4 ASCII characters")


def _check_url(url: str) -> None:
    if url != PTY_URL:
        check_serial_port(url)


_PORT = text_of((SERIAL,), baud_suffix=False)


def _url(text: str) -> str:
    """``--crsf``'s value: 'pty', a serial port or a pyserial URL (the rate is --crsf-baud),
    checked as the flag is read."""
    return text if text == PTY_URL else _PORT(text)


@dataclass(frozen=True, kw_only=True)
class CrsfOptions(VehicleOptions):
    """``[backends.crsf]``: CRSF telemetry to an ExpressLRS/TBS receiver, of one vehicle
    (``vehicle``; default: the first source's)."""

    TITLE: ClassVar[str] = "CRSF backend"
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = {"url": PTY_URL}
    url: str = option(PTY_URL, "receiver UART: serial port or pyserial URL (/dev/ttyUSB0, "
                      "socket://host:port, rfc2217://…); 'pty' = create a pseudo-terminal "
                      "and log "
                      "its path", validator=_check_url,
                      flag=Flag("--crsf", "CRSF backend: the ExpressLRS receiver's UART "
                                "(serial port or pyserial URL), or 'pty' for a "
                                "pseudo-terminal", metavar="URL", convert=_url))
    baudrate: int = option(DEFAULT_BAUD, "UART speed: 420000 for ExpressLRS, 416666 for TBS",
                           minimum=1200, flag=Flag("--crsf-baud", metavar="N"))
    sync: int = option(SYNC_FC, "address byte of the frames sent (0xC8 = flight controller)",
                       choices=(SYNC_FC, SYNC_RADIO, SYNC_RX))
    pitch: str = option("nose-up", "which pitch is positive (Betaflight/INAV: nose-down)",
                        choices=("nose-up", "nose-down"))
    disarmed_suffix: str = option("*", "appended to the flight mode while disarmed; '' = none",
                                  validator=_check_suffix)
    health_marker: bool = option(True, "append !IMU/!BARO/!CAL/!LOG to the flight mode when "
                                 "STATUS reports a failing check")
    max_frames_per_s: float = option(20.0, "total frame rate cap", minimum=1, maximum=1000)
    refresh_s: float = option(2.0, "longest gap between two frames of one type",
                              minimum=0.2, maximum=15)
    hold_s: float = option(10.0, "stop re-sending a value not updated for this long, so the "
                           "radio shows it stale; 0 = never", minimum=0)
    attitude_hz: float = option(10.0, "attitude (0x1E) rate; 0 = off", minimum=0, maximum=100)
    altitude_hz: float = option(5.0, "baro altitude + vario (0x09) rate; 0 = off", minimum=0,
                                maximum=100)
    vario_hz: float = option(2.0, "vario (0x07) rate; 0 = off", minimum=0, maximum=100)
    flight_mode_hz: float = option(2.0, "flight mode (0x21) rate, plus at once on a change; "
                                   "0 = off", minimum=0, maximum=100)
    gps_hz: float = option(2.0, "GPS (0x02) rate; 0 = off", minimum=0, maximum=100)
    battery_hz: float = option(1.0, "battery (0x08) rate; 0 = off", minimum=0, maximum=100)
    voltages_hz: float = option(1.0, "voltages (0x0E) rate; 0 = off", minimum=0, maximum=100)
    voltages_source_id: int = option(128, "source id of the voltages frame (EdgeTX shows ids "
                                     "≥ 128 as a voltage array, lower ones as cells)", minimum=0,
                                     maximum=255)
    link_stats_hz: float = option(5.0, "most link-statistics messages per second handed to the "
                                  "other backends; 0 = none", minimum=0)
