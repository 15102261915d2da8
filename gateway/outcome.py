"""What a backend (or a port) did with a message: the firmware's return codes.

A leaf module: the port engine and the backend contract both use it, and it imports nothing
of the gateway."""

from __future__ import annotations

import errno
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
