"""The HTTP backend's options, declared once (see :mod:`gateway.options`): its
``[backends.http]`` schema, its ``--http [HOST:]PORT`` flag and its documentation.  A light
module (the ``aurora_gateway.backend_options`` entry point)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.options import Flag, Options, option

#: The host ``--http PORT`` binds to: loopback, so the page is not on the field network
#: unless asked for (``--http 0.0.0.0:8080``).
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080


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


def _listen(text: str) -> dict[str, Any]:
    host, port = split_host_port(text)
    return {"host": host, "port": port}


@dataclass(frozen=True, kw_only=True)
class HttpOptions(Options):
    """``[backends.http]``: the status page, /status.json, /events and /metrics."""

    TITLE: ClassVar[str] = "HTTP backend"
    host: str = option(DEFAULT_HOST, "address to listen on (0.0.0.0: every interface)")
    port: int = option(DEFAULT_PORT, "TCP port (0: any free port)", minimum=0, maximum=65535,
                       flag=Flag("--http", "serve a live status page (/), /status.json, "
                                 "/events (SSE) and /metrics (Prometheus) over HTTP; HOST "
                                 "defaults to 127.0.0.1 (0.0.0.0 to serve the field network)",
                                 metavar="[HOST:]PORT", parse=_listen))
    max_clients: int = option(16, "event streams (/events) served at once; more get 503",
                              minimum=1, maximum=256)
    event_interval_s: float = option(0.25, "seconds between two events of a stream",
                                     minimum=0.05, maximum=10)
    client_timeout_s: float = option(5.0, "a client that does not read for this long is cut",
                                     minimum=0.1, maximum=60)
