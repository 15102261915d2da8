"""The Foxglove backend's options, declared once (see :mod:`gateway.options`): its
``[backends.foxglove]`` schema, its ``--foxglove [HOST:]PORT`` flag and its documentation.
A light module (the ``aurora_gateway.backend_options`` entry point): it imports neither the
backend nor ``foxglove-sdk``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.options import Flag, Options, option

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


def _listen(text: str) -> dict[str, Any]:
    host, port = parse_address(text)
    return {"host": host, "port": port}


@dataclass(frozen=True, kw_only=True)
class FoxgloveOptions(Options):
    """``[backends.foxglove]``: the flight live in the Foxglove app."""

    TITLE: ClassVar[str] = "Foxglove backend"
    host: str = option(DEFAULT_HOST, "address to listen on (loopback by default; 0.0.0.0 for "
                       "the field network)")
    port: int = option(DEFAULT_PORT, "TCP port of the WebSocket server (0: any free port)",
                       minimum=0, maximum=65535,
                       flag=Flag("--foxglove", "serve the flight live to the Foxglove app "
                                 "(Foxglove WebSocket protocol, foxglove-sdk) on HOST:PORT; a "
                                 f"bare PORT listens on {DEFAULT_HOST} only (give "
                                 "0.0.0.0:PORT for the field network); off by default",
                                 metavar="[HOST:]PORT", parse=_listen))
    queue_depth: int = option(1024, "updates waiting for the worker before new ones are "
                              "dropped", minimum=1)
    backlog: int = option(1024, "messages buffered per client by the server (its oldest are "
                          "dropped when a client is slow)", minimum=1)
