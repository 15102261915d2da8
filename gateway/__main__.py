"""``python -m gateway`` and the ``aurora-gateway`` command.

The command's entry point is :func:`main` here, not in :mod:`gateway.commands.cli`, so that a
Ctrl-C while that module and its imports load (the first ~0.1 s) ends quietly with status 130
like a Ctrl-C later on, instead of a traceback or a crash; and a SIGTERM then ends it with 0,
as it does a running command (the exit-status table: :mod:`gateway.exits`).  From the first
import on, both signals are held (:mod:`gateway.signals`) until the command line is
parsed and the command's own code starts (:func:`gateway.commands.cli.main`)."""

from __future__ import annotations

import os
import signal
import sys


def _terminated(signum: int, frame: object) -> None:
    """SIGTERM before a command installs its own stop (gateway.commands.cli.Stopper): leave
    with status 0, quietly (a service manager's stop)."""
    raise SystemExit(0)


def main() -> None:
    """Import the command line, then run it (:func:`gateway.commands.cli.console_main`)."""
    signal.signal(signal.SIGTERM, _terminated)
    try:
        from gateway import signals

        signals.hold()  # released when the command starts, or as main returns
        from gateway.commands.cli import console_main
    except BaseException as exc:
        # a Ctrl-C or SIGTERM before the hold, maybe wrapped by the class being created
        from gateway.exits import signalled

        status = signalled(exc)
        if status is None:
            raise
        sys.stderr.flush()
        os._exit(status)
    console_main()


if __name__ == "__main__":
    main()
