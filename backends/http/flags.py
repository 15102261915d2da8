"""``aurora-gateway run``'s ``--http`` flag, apart from the backend so that building the
parser imports nothing of it (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library."""

from __future__ import annotations

import argparse
from typing import Any

#: The host ``--http PORT`` binds to: loopback, so the page is not on the field network
#: unless asked for (``--http 0.0.0.0:8080``).
DEFAULT_HOST = "127.0.0.1"


def split_host_port(text: str) -> tuple[str, Any]:
    """``PORT``, ``HOST:PORT`` or ``[V6ADDR]:PORT`` → (host, port); a port that is not a
    number is returned as given, for the schema's key to refuse naming the key."""
    text = text.strip()
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = DEFAULT_HOST, text
    elif host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    host = host or DEFAULT_HOST
    try:
        return host, int(port)
    except ValueError:
        return host, port


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--http", metavar="[HOST:]PORT",
                        help="serve a live status page (/), /status.json, /events (SSE) and "
                             "/metrics (Prometheus) over HTTP; HOST defaults to 127.0.0.1 "
                             "(0.0.0.0 to serve the field network)")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.http]`` options ``--http`` sets; None when it was not given."""
    value = getattr(args, "http", None)
    if not value:
        return None
    host, port = split_host_port(value)
    return {"host": host, "port": port}
