"""Byte-stream transports.  Serial goes through pyserial's ``serial_for_url``, so
``/dev/ttyUSB0``, ``loop://``, ``socket://host:port``, ``rfc2217://host:port`` and
``spy://…`` all work with the same code."""

from __future__ import annotations

from typing import Protocol

import serial

DEFAULT_READ_TIMEOUT_S = 0.05


class Transport(Protocol):
    """What the link engine and the sources need of a port."""

    def write(self, data: bytes, /) -> int | None: ...
    def read(self, size: int = 1, /) -> bytes: ...
    def close(self) -> None: ...


class TransportError(OSError):
    """A port could not be opened or used."""


def open_serial(
    url: str,
    baudrate: int = 115200,
    *,
    timeout: float | None = DEFAULT_READ_TIMEOUT_S,
    write_timeout: float | None = 1.0,
    exclusive: bool | None = None,
) -> serial.SerialBase:
    """Open a pyserial port or URL; raises :class:`TransportError` with the URL in the text."""
    if url.startswith("rfc2217://"):
        write_timeout = None  # pyserial's RFC 2217 client refuses any write timeout
    kwargs: dict = {"baudrate": baudrate, "timeout": timeout, "write_timeout": write_timeout}
    if exclusive is not None:
        kwargs["exclusive"] = exclusive
    try:
        return serial.serial_for_url(url, **kwargs)
    except (serial.SerialException, OSError, ValueError, NotImplementedError) as exc:
        raise TransportError(f"cannot open {url}: {exc}") from exc
