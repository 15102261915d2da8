"""``aurora-gateway run``'s UAVTalk flags, apart from the backend so that building the parser
imports nothing of it (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library and the endpoint
grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
from typing import Any

from gateway.io.endpoints import SERIAL, TCP, TCPIN, argument

#: ``--uavtalk ENDPOINT``, checked as the flag is read.
ENDPOINT = argument((TCPIN, TCP, SERIAL))


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--uavtalk", action="append", type=ENDPOINT, metavar="ENDPOINT",
                        help="serve the rocket to LibrePilot ground stations over UAVTalk "
                             "(repeatable): tcpin:HOST:PORT (the GCS connects; each client "
                             "its own session), tcp:HOST:PORT, serial:DEVICE[,BAUD] or a "
                             "serial device / pyserial URL")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.uavtalk]`` options the flags set; None when none was given."""
    if getattr(args, "uavtalk", None):
        return {"endpoints": [e.text for e in args.uavtalk]}
    return None
