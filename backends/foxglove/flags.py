"""``aurora-gateway run``'s Foxglove flag, apart from the backend so that building the parser
imports neither it nor ``foxglove-sdk`` (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library and the endpoint
grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
from typing import Any

from gateway.io.endpoints import TCPIN, argument

#: Where the server listens when only a port (or nothing) is given: loopback, never the field
#: network unless asked.
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765


#: ``--foxglove [HOST:]PORT`` (or ``tcpin:[HOST:]PORT``), checked as the flag is read.
ADDRESS = argument((TCPIN,), bare=TCPIN, listen_host=DEFAULT_HOST)


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--foxglove", type=ADDRESS, metavar="[HOST:]PORT",
                        help="serve the flight live to the Foxglove app (Foxglove WebSocket "
                             "protocol, foxglove-sdk) on HOST:PORT; a bare PORT listens on "
                             f"{DEFAULT_HOST} only (give 0.0.0.0:PORT for the field network); "
                             "IPv6 as [::1]:PORT; off by default")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.foxglove]`` options the flag sets; None when it was not given."""
    endpoint = getattr(args, "foxglove", None)
    if endpoint is None:
        return None
    return {"host": endpoint.host, "port": endpoint.port}
