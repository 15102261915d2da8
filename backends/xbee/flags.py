"""``aurora-gateway run``'s XBee flags, apart from the backend so that building the parser
imports nothing of it (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  ``--xbee-api`` sets the API mode here and of ``--source xbee:URL``
(``gateway.commands.cli.SOURCE_FLAGS``, which declares it: the source reads it too).  Imports
nothing but the standard library and the endpoint grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
from typing import Any

from gateway.io.endpoints import SERIAL, argument

#: ``--xbee URL``: a serial port or pyserial URL (the module's rate is the baudrate key).
PORT = argument((SERIAL,), baud_suffix=False)


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--xbee", type=PORT, metavar="URL",
                        help="XBee air side: the rocket's telemetry down and commands up "
                             "through the XBee module on this serial port or pyserial URL "
                             "(socket://HOST:PORT)")
    parser.add_argument("--xbee-dest", metavar="HEX",
                        help="XBee air side: the ground module's 64-bit address "
                             "(default: broadcast)")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.xbee]`` options the flags set; None when none was given."""
    opts: dict[str, Any] = {}
    if getattr(args, "xbee", None):
        opts["url"] = args.xbee.text
    if getattr(args, "xbee_api", None) is not None and opts:
        opts["api_mode"] = args.xbee_api
    if getattr(args, "xbee_dest", None):
        opts["dest"] = args.xbee_dest
    return opts or None
