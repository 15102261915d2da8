"""What a backend (or a port) did with a message: the firmware's return codes, and the log of
the failures (a handler that raised).

A leaf module: the port engine and the backend contract both use it, and it imports nothing
of the gateway."""

from __future__ import annotations

import errno
import logging
from enum import IntEnum


class Outcome(IntEnum):
    """What a backend did with a message (the firmware's return codes)."""

    ACCEPTED = 0
    THROTTLED = -errno.EAGAIN
    QUEUE_FULL = -errno.ENOMEM
    NOT_READY = -errno.ENODEV
    FAILED = -errno.EIO  # the handler raised; the dispatcher isolates it

    @property
    def label(self) -> str:
        return self.name.lower().replace("_", "-")


class FailureLog:
    """The log of :attr:`Outcome.FAILED`: the first exception of each type a handler raises
    is an error line with its traceback, the rest debug lines (a handler that keeps raising
    the same error writes one line, not one per message)."""

    def __init__(self, logger: logging.Logger) -> None:
        self.logger = logger
        self.types_logged: set[str] = set()

    def failed(self, who: str, exc: Exception) -> None:
        """Log that ``who`` (e.g. ``backend zenoh``) raised ``exc`` and was isolated."""
        key = type(exc).__name__
        if key in self.types_logged:
            self.logger.debug("%s raised again: %r", who, exc)
            return
        self.types_logged.add(key)
        self.logger.error("%s raised %s: %s (isolated; further %s not logged)", who, key, exc,
                          key, exc_info=exc)
