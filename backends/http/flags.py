"""``aurora-gateway run``'s ``--http`` flag, apart from the backend so that building the
parser imports nothing of it (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library and the endpoint
grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
from typing import Any

from gateway.io.endpoints import TCPIN, argument

#: The host ``--http PORT`` binds to: loopback, so the page is not on the field network
#: unless asked for (``--http 0.0.0.0:8080``).
DEFAULT_HOST = "127.0.0.1"


#: ``--http [HOST:]PORT`` (or ``tcpin:[HOST:]PORT``), checked as the flag is read.
ADDRESS = argument((TCPIN,), bare=TCPIN, listen_host=DEFAULT_HOST)


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--http", type=ADDRESS, metavar="[HOST:]PORT",
                        help="serve a live status page (/), /status.json, /events (SSE) and "
                             "/metrics (Prometheus) over HTTP; HOST defaults to 127.0.0.1 "
                             "(0.0.0.0 to serve the field network; IPv6 as [::1]:PORT)")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.http]`` options ``--http`` sets; None when it was not given."""
    endpoint = getattr(args, "http", None)
    if endpoint is None:
        return None
    return {"host": endpoint.host, "port": endpoint.port}
