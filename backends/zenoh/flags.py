"""``aurora-gateway run``'s Zenoh flags, apart from the backend so that building the parser
imports neither the backend nor Zenoh (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports only :mod:`backends.zenoh.keys` and
:mod:`backends.zenoh.session` (no Zenoh: the locator check)."""

from __future__ import annotations

import argparse
from typing import Any

from backends.zenoh.keys import DEFAULT_PREFIX, DEFAULT_VEHICLE
from backends.zenoh.session import check_locator

#: Zenoh's session modes (``backends.zenoh.session.MODES``).
MODES = ("peer", "client", "router")


def _locator(text: str) -> str:
    """``--zenoh-connect``/``--zenoh-listen``: a Zenoh locator, checked as the flag is read."""
    try:
        check_locator(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("zenoh backend")
    g.add_argument("--zenoh-connect", action="append", type=_locator, metavar="ENDPOINT",
                   help="connect to this Zenoh router or peer, e.g. tcp/10.0.0.5:7447 "
                        "(repeatable; then nothing listens unless --zenoh-listen)")
    g.add_argument("--zenoh-listen", action="append", type=_locator, metavar="ENDPOINT",
                   help="listen on this endpoint (repeatable; default tcp/127.0.0.1:7450)")
    g.add_argument("--zenoh-mode", choices=MODES, help="Zenoh mode (default peer)")
    g.add_argument("--zenoh-vehicle", metavar="ID",
                   help=f"vehicle key chunk (default {DEFAULT_VEHICLE})")
    g.add_argument("--zenoh-prefix", metavar="PREFIX",
                   help=f"key prefix (default {DEFAULT_PREFIX})")
    g.add_argument("--zenoh-config", metavar="FILE",
                   help="a full Zenoh JSON5 configuration for the session")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.zenoh]`` options the flags set; None when none was given."""
    flags = {
        "connect": getattr(args, "zenoh_connect", None),
        "listen": getattr(args, "zenoh_listen", None),
        "mode": getattr(args, "zenoh_mode", None),
        "vehicle": getattr(args, "zenoh_vehicle", None),
        "prefix": getattr(args, "zenoh_prefix", None),
        "config_file": getattr(args, "zenoh_config", None),
    }
    opts = {k: v for k, v in flags.items() if v is not None}
    return opts or None
