"""``python -m gateway`` and the ``aurora-gateway`` command.

The command's entry point is :func:`main` here, not in :mod:`gateway.commands.cli`, so that
its first act can be to hold SIGINT and SIGTERM (:mod:`gateway.signals`): from then on
until the command installs its own stop (or starts, for a command without one), a signal
is noted, never raised into whatever runs — an import's bookkeeping, where Python prints a
KeyboardInterrupt and drops it, or a C extension's initialisation, which can crash.  A
Ctrl-C then ends the command quietly with status 130, and a SIGTERM with 0, whenever it
comes (the exit-status table: :mod:`gateway.exits`)."""

from __future__ import annotations

import os
import signal
import sys

from gateway import signals


def _terminated(signum: int, frame: object) -> None:
    """SIGTERM before a command installs its own stop (gateway.commands.cli.Stopper): leave
    with status 0, quietly (a service manager's stop)."""
    raise SystemExit(0)


def main() -> None:
    """Hold the signals, import the command line, run it
    (:func:`gateway.commands.cli.console_main`)."""
    signals.hold(after={signal.SIGTERM: _terminated})  # released or taken over by the command
    try:
        from gateway.commands.cli import console_main
    except BaseException as exc:
        # (a signal's exception cannot arise while held; kept for one that escaped a hold,
        # maybe wrapped by a class being created)
        from gateway.exits import signalled

        status = signalled(exc)
        if status is None:
            raise
        sys.stderr.flush()
        os._exit(status)
    console_main()


if __name__ == "__main__":
    main()
