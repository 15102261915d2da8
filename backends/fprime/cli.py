"""``aurora-gateway fprime-dictionary [-o FILE] [--id-base N] [--scid N] [--frame-size N]``.

Writes the F´ JSON dictionary of the gateway's channels (stdout by default) for
``fprime-gds --dictionary FILE``.  Numbers take decimal or ``0x…``.  Exit status 0 written,
1 the file could not be written, 2 a bad value (one line on stderr, nothing written).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from backends.fprime.channels import DEFAULT_ID_BASE
from gateway import exits

EXIT_OK, EXIT_FAILED, EXIT_USAGE = exits.OK, exits.FAILED, exits.USAGE
PROG = "aurora-gateway fprime-dictionary"


def parse_number(option: str, text: str | None) -> int | None:
    """``text`` as an integer in decimal or ``0x`` hexadecimal (None stays None).

    Raises ValueError naming ``option`` (checked in the handler rather than by argparse, so a
    bad value is one line, not the usage text).
    """
    if text is None:
        return None
    try:
        return int(text.strip(), 0)
    except ValueError:
        raise ValueError(f"{option}: {text!r} is not a number (decimal or 0x…)") from None


def add_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``fprime-dictionary`` to the ``aurora-gateway`` subcommands."""
    p = subparsers.add_parser(
        "fprime-dictionary", help="write the F´ JSON dictionary of the gateway's channels",
        description="Write the F´ JSON dictionary of the gateway's telemetry channels, for "
                    "fprime-gds --dictionary FILE.")
    p.add_argument("-o", "--output", metavar="FILE", default="-",
                   help="where to write it (default: stdout)")
    p.add_argument("--id-base", default=None, metavar="N",
                   help=f"id of the first channel, as the backend's id_base "
                        f"(default {DEFAULT_ID_BASE:#x})")
    p.add_argument("--scid", default=None, metavar="N",
                   help="add ComCfg.SpacecraftId (the ccsds framing's spacecraft id, 0..1023)")
    p.add_argument("--frame-size", default=None, metavar="N",
                   help="add ComCfg.TmFrameFixedSize (the ccsds framing's TM frame size)")
    p.set_defaults(handler=run_dictionary)
    return p


def run_dictionary(args: argparse.Namespace) -> int:
    """The ``fprime-dictionary`` handler; returns the exit status."""
    from backends.fprime.dictionary import write_dictionary

    try:
        id_base = parse_number("--id-base", args.id_base)
        write_dictionary(args.output, DEFAULT_ID_BASE if id_base is None else id_base,
                         scid=parse_number("--scid", args.scid),
                         frame_size=parse_number("--frame-size", args.frame_size))
    except ValueError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:
        print(f"{PROG}: cannot write {args.output}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_FAILED
    if args.output != "-":
        print(f"{PROG}: wrote {args.output}", file=sys.stderr)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command alone (``python -m backends.fprime.cli fprime-dictionary …``)."""
    from gateway.commands.cli import CommandParser  # one-line errors, the exit-status table

    parser = CommandParser(prog="aurora-gateway")
    sub = parser.add_subparsers(dest="command", required=True)
    add_command(sub)
    args = parser.parse_args(argv)
    handler = args.handler
    status: int = handler(args)
    return status


if __name__ == "__main__":
    sys.exit(main())
