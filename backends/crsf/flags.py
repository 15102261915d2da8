"""``aurora-gateway run``'s CRSF flags, apart from the backend so that building the parser
imports no backend (the ``aurora_gateway.backend_flags`` entry point; see
:mod:`gateway.registry`).  Imports nothing but the standard library and the endpoint
grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
from typing import Any

from gateway.io.endpoints import SERIAL, argument

#: The backend's default UART speed (``backends.crsf.backend.DEFAULT_BAUD``, ExpressLRS).
DEFAULT_BAUD = 420000
#: The backend's ``PTY_URL``: a pseudo-terminal of its own.
PTY = "pty"
_PORT = argument((SERIAL,), baud_suffix=False)


def _url(text: str) -> str:
    """``--crsf``'s value: 'pty', a serial port or a pyserial URL (the rate is --crsf-baud)."""
    return text if text == PTY else _PORT(text).text


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--crsf", type=_url, metavar="URL",
                        help="CRSF backend: the ExpressLRS receiver's UART (serial port "
                             "or pyserial URL), or 'pty' for a pseudo-terminal")
    parser.add_argument("--crsf-baud", type=int, metavar="N",
                        help=f"CRSF backend: UART speed (default {DEFAULT_BAUD})")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.crsf]`` options the flags set; None when none was given."""
    url = getattr(args, "crsf", None)
    baud = getattr(args, "crsf_baud", None)
    if url is None and baud is None:
        return None
    opts: dict[str, Any] = {}
    if url is not None:
        opts["url"] = url
    if baud is not None:
        opts["baudrate"] = baud
    return opts
