"""Opening the HC-12's serial port without glitching SET.

pyserial asserts RTS and DTR as it opens a port; with SET wired to one of them that would drop
the module into AT mode and swallow the frames.  The port is therefore created closed, the SET
line deasserted, then opened.  Device paths are opened exclusively (TIOCEXCL/flock), so a
stand-alone ``aurora-gateway hc12`` cannot talk over a gateway that owns the port.
``rfc2217://`` ports get no write timeout (pyserial's RFC 2217 client refuses one).
"""

from __future__ import annotations

from typing import Any

import serial

from backends.hc12.setline import SetLineSpec, prepare_port
from gateway.io.transport import TransportError

READ_TIMEOUT_S = 0.05
WRITE_TIMEOUT_S = 2.0


def is_device_path(url: str) -> bool:
    return "://" not in url


def open_port(url: str, baudrate: int, spec: SetLineSpec, *,
              timeout: float = READ_TIMEOUT_S) -> Any:
    """Open ``url`` at ``baudrate`` with SET released; raises :class:`TransportError`."""
    write_timeout = None if url.lower().startswith("rfc2217://") else WRITE_TIMEOUT_S
    try:
        port = serial.serial_for_url(url, do_not_open=True, baudrate=baudrate, timeout=timeout,
                                     write_timeout=write_timeout)
        prepare_port(port, spec)
        if is_device_path(url):
            port.exclusive = True
        port.open()
    except (serial.SerialException, OSError, ValueError, NotImplementedError) as exc:
        raise TransportError(f"cannot open {url}: {exc}") from exc
    return port
