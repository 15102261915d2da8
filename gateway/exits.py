"""The exit statuses of every ``aurora-gateway`` command, declared once.

Every command (``run``, ``record``, ``replay``, ``decode``, ``simulate``, ``export``,
``plot``, ``check-config``, ``monitor``, ``listen``, ``hc12``, ``fprime-dictionary``,
``mavlink-modes``) ends with one of these; :data:`HELP` is the table each command's
``--help`` ends with, and the README shows the same table.

SIGINT (Ctrl-C) is "interrupted", 130 (128 + SIGINT, what a shell reports for a process
Ctrl-C ended), even when the command then stops cleanly and prints its stop report.  SIGTERM
is a service manager's normal stop: the command stops the same way and exits 0, the status
systemd counts as success.
"""

from __future__ import annotations

import signal

#: done
OK = 0
#: failed at run time (a file that could not be written, a radio that did not answer, an
#: unexpected error: its traceback on stderr)
FAILED = 1
#: bad input or configuration: one line on stderr naming the flag, key or file
USAGE = 2
#: ``hc12`` only: refused by its safety rules, nothing sent
REFUSED = 3
#: interrupted by SIGINT (Ctrl-C)
INTERRUPTED = 130

HELP = """\
exit status (every command):
  0    done (the duration passed, the input or the sources ended), or stopped by
       SIGTERM (a service manager's stop)
  1    failed at run time: a file that could not be written, a radio that did
       not answer, an unexpected error (its traceback on stderr)
  2    bad input or configuration: a bad flag value, a missing, empty or foreign
       file, an invalid config (one line on stderr naming it)
  130  interrupted by Ctrl-C (SIGINT), quietly, at any moment; a running command
       still stops cleanly first (run, record, replay: with their stop report)
  hc12 adds 3: refused by its safety rules (nothing sent)
"""


def after_stop(signum: int | None) -> int:
    """The status of a command that ran until it was stopped: :data:`INTERRUPTED` when
    ``signum`` is SIGINT, else :data:`OK` (SIGTERM, or no signal: it ended by itself)."""
    return INTERRUPTED if signum == signal.SIGINT else OK


def signalled(exc: BaseException) -> int | None:
    """The status of a Ctrl-C or a SIGTERM that surfaced as ``exc``: a
    :class:`KeyboardInterrupt` (130) or a :class:`SystemExit` (its code) that is ``exc`` or
    in its chain of causes — a signal handler's exception raised inside a class's creation
    reaches the caller wrapped ("RuntimeError: Error calling __set_name__ …"); None when no
    signal is behind it."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, KeyboardInterrupt):
            return INTERRUPTED
        if isinstance(e, SystemExit):
            return e.code if isinstance(e.code, int) else OK
        e = e.__cause__ or e.__context__
    return None
