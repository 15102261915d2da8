"""``python -m gateway`` and the ``aurora-gateway`` command.

The command's entry point is :func:`main` here, not in :mod:`gateway.commands.cli`, so that a
Ctrl-C while that module and its imports load (the first ~0.1 s) ends quietly with status 130
like a Ctrl-C later on, instead of a traceback."""

from __future__ import annotations

import os
import sys

EXIT_INTERRUPTED = 130  # 128 + SIGINT, as gateway.commands.cli.EXIT_INTERRUPTED


def main() -> None:
    """Import the command line, then run it (:func:`gateway.commands.cli.console_main`)."""
    try:
        from gateway.commands.cli import console_main
    except KeyboardInterrupt:
        sys.stderr.flush()
        os._exit(EXIT_INTERRUPTED)
    console_main()


if __name__ == "__main__":
    main()
