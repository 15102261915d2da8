"""``aurora-gateway run``'s UAVTalk flags, apart from the backend so that building the parser
imports nothing of it (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library."""

from __future__ import annotations

import argparse
from typing import Any


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--uavtalk", action="append", metavar="ENDPOINT",
                        help="serve the rocket to LibrePilot ground stations over UAVTalk "
                             "(repeatable): tcpin:HOST:PORT (the GCS connects; each client "
                             "its own session), tcp:HOST:PORT, serial:DEVICE[,BAUD] or a "
                             "serial device / pyserial URL")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.uavtalk]`` options the flags set; None when none was given."""
    if getattr(args, "uavtalk", None):
        return {"endpoints": list(args.uavtalk)}
    return None
