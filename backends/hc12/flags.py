"""``aurora-gateway run``'s HC-12 flags, apart from the backend so that building the parser
imports no backend (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library and the endpoint
grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
from typing import Any

from gateway.io.endpoints import SERIAL, argument

#: The backend's modes (``backends.hc12.backend.MODES``).
MODES = ("relay", "generate")
#: ``--hc12 URL``: a serial port or pyserial URL (the rate is --hc12-baud).
PORT = argument((SERIAL,), baud_suffix=False)


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--hc12", type=PORT, metavar="URL",
                        help="HC-12 backend: relay frames to the HC-12 on this port or URL")
    parser.add_argument("--hc12-baud", type=int, metavar="N",
                        help="HC-12 backend: host UART rate (the module's AT+B rate)")
    parser.add_argument("--hc12-mode", choices=MODES,
                        help="HC-12 backend: relay frames byte-identical or generate them")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.hc12]`` options the flags set; None when none was given."""
    opts: dict[str, Any] = {}
    if getattr(args, "hc12", None):
        opts["url"] = args.hc12.text
    if getattr(args, "hc12_baud", None) is not None:
        opts["baudrate"] = args.hc12_baud
    if getattr(args, "hc12_mode", None):
        opts["mode"] = args.hc12_mode
    return opts or None
