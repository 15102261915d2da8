"""``aurora-gateway run``'s MAVLink flags, apart from the backend so that building the parser
imports neither pymavlink nor the dialect (found through the ``aurora_gateway.backend_flags``
entry point; see :mod:`gateway.registry`).  Imports nothing but the standard library and the
endpoint grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
from typing import Any

from gateway.io.endpoints import KINDS, argument

#: The default endpoint: QGroundControl on this machine (the backend's ``QGC_UDP``).
QGC_UDP = "udpout:127.0.0.1:14550"
#: ``--mavlink ENDPOINT``, checked as the flag is read (every kind; a serial port's default
#: baud rate is the backend's, 57600).
ENDPOINT = argument(KINDS)


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mavlink", action="append", type=ENDPOINT, metavar="ENDPOINT",
                        help="MAVLink endpoint (repeatable; replaces the configured ones): "
                             "udpout:HOST:PORT, udpin:HOST:PORT, tcpin:HOST:PORT, "
                             "tcp:HOST:PORT (IPv6 as [::1]:PORT), serial:DEVICE[,BAUD] "
                             f"(default {QGC_UDP}, QGroundControl on this machine); "
                             "with --source mavlink:ENDPOINT, the vehicle is routed to and "
                             "from them, as by mavlink-router")
    parser.add_argument("--mavlink-sysid", type=int, metavar="N",
                        help="MAVLink system id of the rocket (default 1; if a system on the "
                             "links uses it, the next free one is taken, and logged)")
    parser.add_argument("--mavlink-signing-key", metavar="FILE",
                        help="sign MAVLink 2 traffic with this key file and require "
                             "signed commands")


def cli_options(args: argparse.Namespace) -> dict[str, Any] | None:
    """The ``[backends.mavlink]`` options the flags set; None when none was given."""
    opts: dict[str, Any] = {}
    if getattr(args, "mavlink", None):
        opts["endpoints"] = [e.text for e in args.mavlink]
    if getattr(args, "mavlink_sysid", None) is not None:
        opts["sysid"] = args.mavlink_sysid
    if getattr(args, "mavlink_signing_key", None):
        opts["signing_key_file"] = args.mavlink_signing_key
    return opts or None
