"""The HTTP backend's options, declared once (see :mod:`gateway.options`): its
``[backends.http]`` schema, its ``--http [HOST:]PORT`` flag and its documentation.  A light
module (the ``aurora_gateway.backend_options`` entry point): the standard library,
:mod:`gateway.options` and the endpoint grammar (:mod:`gateway.io.endpoints`), which reads
``--http`` and checks the host and port keys in its words."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.io.endpoints import TCPIN, check_host, check_port, parse_endpoint
from gateway.options import Flag, ListenerOptions, option

#: The host ``--http PORT`` binds to: loopback, so the page is not on the field network
#: unless asked for (``--http 0.0.0.0:8080``).
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080


def _listen(text: str) -> dict[str, Any]:
    """``--http [HOST:]PORT`` (or ``tcpin:[HOST:]PORT``; IPv6 as ``[::1]:PORT``) → the host
    and port keys, read by the endpoint grammar: a mistake is its one line, exit 2."""
    endpoint = parse_endpoint(text, (TCPIN,), bare=TCPIN, listen_host=DEFAULT_HOST)
    return {"host": endpoint.host, "port": endpoint.port}


@dataclass(frozen=True, kw_only=True)
class HttpOptions(ListenerOptions):
    """``[backends.http]``: the status page, /status.json, /events and /metrics."""

    TITLE: ClassVar[str] = "HTTP backend"
    host: str = option(DEFAULT_HOST, "address to listen on (0.0.0.0: every interface)",
                       validator=check_host)
    port: int = option(DEFAULT_PORT, "TCP port, 0 to 65535 (0: any free port)",
                       validator=check_port,
                       flag=Flag("--http", "serve a live status page (/), /status.json, "
                                 "/events (SSE) and /metrics (Prometheus) over HTTP; HOST "
                                 "defaults to 127.0.0.1 (0.0.0.0 to serve the field network; "
                                 "IPv6 as [::1]:PORT)", metavar="[HOST:]PORT", parse=_listen))
    event_interval_s: float = option(0.25, "seconds between two events of a stream",
                                     minimum=0.05, maximum=10)
