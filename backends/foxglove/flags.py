"""``aurora-gateway run``'s Foxglove flag, apart from the backend so that building the parser
imports neither it nor ``foxglove-sdk`` (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library."""

from __future__ import annotations

import argparse
from typing import Any

#: Where the server listens when only a port (or nothing) is given: loopback, never the field
#: network unless asked.
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765


def parse_address(text: str) -> tuple[str, int]:
    """``PORT``, ``HOST:PORT`` or ``[IPv6]:PORT`` → (host, port); a bare port means loopback.

    Raises ValueError naming what is wrong."""
    text = text.strip()
    host, port_text = DEFAULT_HOST, text
    if text.startswith("["):
        end = text.find("]")
        if end < 0 or text[end + 1:end + 2] != ":":
            raise ValueError(f"expected [IPv6]:PORT, got {text!r}")
        host, port_text = text[1:end], text[end + 2:]
    elif ":" in text:
        host, _, port_text = text.rpartition(":")
    if not host:
        raise ValueError(f"empty host in {text!r}")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"expected PORT or HOST:PORT, got {text!r}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"port {port} out of range 0..65535")
    return host, port


def _address(text: str) -> tuple[str, int]:
    try:
        return parse_address(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--foxglove", type=_address, metavar="[HOST:]PORT",
                        help="serve the flight live to the Foxglove app (Foxglove WebSocket "
                             "protocol, foxglove-sdk) on HOST:PORT; a bare PORT listens on "
                             f"{DEFAULT_HOST} only (give 0.0.0.0:PORT for the field network); "
                             "off by default")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.foxglove]`` options the flag sets; None when it was not given."""
    address = getattr(args, "foxglove", None)
    if address is None:
        return None
    host, port = address
    return {"host": host, "port": port}
