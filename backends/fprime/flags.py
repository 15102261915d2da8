"""``aurora-gateway run``'s F´ flags, apart from the backend so that building the parser
imports nothing of it (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library and the endpoint
grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
from typing import Any

from gateway.io.endpoints import SERIAL, TCP, TCPIN, argument

#: The framings (``backends.fprime.framing.FRAMINGS``); the first is the default.
FRAMINGS = ("ccsds", "fprime")
#: ``--fprime ENDPOINT``, checked as the flag is read.
ENDPOINT = argument((TCPIN, TCP, SERIAL))


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--fprime", action="append", type=ENDPOINT, metavar="ENDPOINT",
                        help="serve the rocket's channels to the F´ ground system, fprime-gds "
                             "(repeatable): tcpin:HOST:PORT (fprime-gds --ip-client connects), "
                             "tcp:HOST:PORT, serial:DEVICE[,BAUD] or a serial device / "
                             "pyserial URL")
    parser.add_argument("--fprime-framing", choices=FRAMINGS,
                        help="F´ backend: ccsds (Space Packets in TM frames, fprime-gds's "
                             "default) or fprime (DEADBEEF frames: fprime-gds "
                             "--framing-selection fprime); default ccsds")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.fprime]`` options the flags set; None when none was given."""
    opts: dict[str, Any] = {}
    if getattr(args, "fprime", None):
        opts["endpoints"] = [e.text for e in args.fprime]
    if getattr(args, "fprime_framing", None):
        opts["framing"] = args.fprime_framing
    return opts or None
