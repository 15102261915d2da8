"""The Foxglove backend's options, declared once (see :mod:`gateway.options`): its
``[backends.foxglove]`` schema, its ``--foxglove [HOST:]PORT`` flag and its documentation.
A light module (the ``aurora_gateway.backend_options`` entry point): it imports neither the
backend nor ``foxglove-sdk``, only the endpoint grammar (:mod:`gateway.io.endpoints`), which
reads ``--foxglove`` and checks the host and port keys in its words."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.io.endpoints import TCPIN, check_host, check_port, parse_endpoint
from gateway.options import Flag, ListenerOptions, option

#: Where the server listens when only a port (or nothing) is given: loopback, never the field
#: network unless asked.
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765


def _listen(text: str) -> dict[str, Any]:
    """``--foxglove [HOST:]PORT`` (or ``tcpin:[HOST:]PORT``; IPv6 as ``[::1]:PORT``) → the
    host and port keys, read by the endpoint grammar: a mistake is its one line, exit 2."""
    endpoint = parse_endpoint(text, (TCPIN,), bare=TCPIN, listen_host=DEFAULT_HOST)
    return {"host": endpoint.host, "port": endpoint.port}


@dataclass(frozen=True, kw_only=True)
class FoxgloveOptions(ListenerOptions):
    """``[backends.foxglove]``: the flight live in the Foxglove app (``max_clients`` and
    ``client_timeout_s``: the listener's limits, as every TCP server of the gateway has)."""

    TITLE: ClassVar[str] = "Foxglove backend"
    host: str = option(DEFAULT_HOST, "address to listen on (loopback by default; 0.0.0.0 for "
                       "the field network)", validator=check_host)
    port: int = option(DEFAULT_PORT, "TCP port of the WebSocket server, 0 to 65535 (0: any "
                       "free port)", validator=check_port,
                       flag=Flag("--foxglove", "serve the flight live to the Foxglove app "
                                 "or Lichtblick (Foxglove WebSocket protocol, foxglove-sdk; "
                                 "clients offering foxglove.sdk.v1 or foxglove.websocket.v1) "
                                 "on HOST:PORT; a "
                                 f"bare PORT listens on {DEFAULT_HOST} only (give "
                                 "0.0.0.0:PORT for the field network; IPv6 as [::1]:PORT); "
                                 "off by default",
                                 metavar="[HOST:]PORT", parse=_listen))
    queue_depth: int = option(1024, "updates waiting for the worker before new ones are "
                              "dropped", minimum=1)
    backlog: int = option(1024, "messages buffered per client by the server (its oldest are "
                          "dropped when a client is slow)", minimum=1)
