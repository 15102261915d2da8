"""The options of the core's sources (serial, sim, replay), declared once (see
:mod:`gateway.options`); found through the ``aurora_gateway.source_options`` entry points
without importing the sources (the standard library, :mod:`gateway.options` and the endpoint
grammar only)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from gateway.options import Flag, Options, lazy, option, serial_port_option

#: Longest wait between two reopen attempts of a port (``gateway.io.port.REOPEN_MAX_S``).
REOPEN_MAX_S = 2.0


@dataclass(frozen=True, kw_only=True)
class SerialOptions(Options):
    """``[[sources]] type = "serial"``: the rocket's frames on a serial port."""

    TITLE: ClassVar[str] = "serial sources"
    url: str = serial_port_option("pyserial port or URL: /dev/ttyUSB0, loop://, "
                                  "socket://host:port, rfc2217://host:port")
    baudrate: int = option(115200, "host UART speed", minimum=50,
                           flag=Flag("--baud", "baud rate of serial sources", metavar="N"))
    reconnect_max_s: float = option(REOPEN_MAX_S, "longest wait between reopen attempts",
                                    minimum=0.01)


@dataclass(frozen=True, kw_only=True)
class SimOptions(Options):
    """``[[sources]] type = "sim"``: a simulated flight."""

    TITLE: ClassVar[str] = "simulated source"
    rate_hz: float = option(10.0, "SM_UPDATE rate (simulated time)", minimum=0.1, maximum=1000)
    status_hz: float = option(1.0, "STATUS rate; 0 = none", minimum=0, maximum=100)
    speed: float = option(1.0, "time compression: N = N times faster, 0 = as fast as possible",
                          minimum=0,
                          flag=Flag("--sim-speed", "run the simulated flight N times faster "
                                    "(0 = flat out)", metavar="N"))
    revision: int = option(64, "SM_UPDATE payload length", choices=(36, 64))
    cycles: int = option(0, "flights to simulate; 0 = for ever", minimum=0)
    pad_idle_s: float = option(5.0, "seconds IDLE on the pad", minimum=0)
    pad_armed_s: float = option(10.0, "seconds ARMED on the pad before launch", minimum=0.1)


@dataclass(frozen=True, kw_only=True)
class ReplayOptions(Options):
    """``[[sources]] type = "replay"``: a recording played back."""

    path: str = option(help="recording file", validator=lazy("gateway.recording:check_file"))
    speed: float = option(1.0, "1 = real time, N = N times faster, 0 = as fast as possible",
                          minimum=0)
    loop: bool = option(False, "start again at the end")
