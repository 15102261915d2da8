"""What a backend is, and what it must and might implement.

A backend **must**:

* have a ``name`` (unique in one gateway; defaults to the class's ``NAME``);
* never block in a hook: a backend that does I/O hands the work to its own bounded queue and
  worker thread (see :class:`gateway.link.LinkEngine`) and drops, counted, when full.

A backend **might** implement any of these hooks; the dispatcher skips backends without one:

``send_sm_update(msg: SmUpdate)``, ``send_status(msg: Status)``, ``send_raw(msg: RawFrame)``,
``on_link(event: LinkEvent)``
    return an :class:`Outcome` (``None`` counts as accepted);
``init()``
    open what the backend needs; raise :class:`BackendError` (or anything) to refuse to start;
``close()``
    release everything; must be safe to call twice;
``stats()``
    counters for the status line, at least ``sent`` and ``dropped`` where meaningful;
``from_config(table)``
    classmethod building the backend from its ``[backends.<name>]`` config table
    (the default passes the table's keys as keyword arguments);
``CONFIG``
    a :class:`gateway.config.Schema` describing the table, so a bad key or value is one clear
    line before anything starts;
``EMBEDDED_DEFAULT``
    the options it runs with in the embedded default (no config file), on loopback and with
    no hardware; None keeps it out of the default run;
``add_cli_arguments(parser)`` / ``cli_options(args)``
    classmethods adding its quick flags to ``run`` and turning them into options;
``attach(emit)``
    receive the gateway's ingest function before ``init``: a backend that also *reads*
    (link statistics from a radio, commands from a ground station) hands what it decodes to
    ``emit`` with ``origin`` set to its own name, and the message reaches every other backend.
"""

from __future__ import annotations

import errno
from collections.abc import Callable
from enum import IntEnum
from typing import Any, ClassVar


class Outcome(IntEnum):
    """What a backend did with a message (the firmware's return codes)."""

    ACCEPTED = 0
    THROTTLED = -errno.EAGAIN
    QUEUE_FULL = -errno.ENOMEM
    NOT_READY = -errno.ENODEV
    FAILED = -errno.EIO  # the hook raised; the dispatcher isolates it

    @property
    def label(self) -> str:
        return self.name.lower().replace("_", "-")


class BackendError(Exception):
    """A backend cannot start or run as configured."""


class Backend:
    """Optional base class for backends: sensible defaults for everything but the hooks."""

    NAME: ClassVar[str] = "backend"
    CONFIG: ClassVar[Any] = None  # a gateway.config.Schema
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None

    def __init__(self, name: str | None = None) -> None:
        self.name = name or self.NAME

    @classmethod
    def from_config(cls, table: dict[str, Any], name: str | None = None) -> Backend:
        return cls(name=name, **table)

    @classmethod
    def add_cli_arguments(cls, parser: Any) -> None:
        """Add this backend's quick flags to ``aurora-gateway run`` (e.g. ``--mavlink``)."""

    @classmethod
    def cli_options(cls, args: Any) -> dict[str, Any] | None:
        """Options the parsed flags set for this backend, or None when none were given."""
        return None

    def attach(self, emit: Callable[[Any], Any]) -> None:
        """Remember the gateway's ingest function (called before :meth:`init`)."""
        self.emit = emit

    def emit(self, msg: Any) -> None:
        """Hand a message this backend decoded to the gateway (a no-op until attached)."""

    def init(self) -> None:
        """Open resources; raise to refuse to start."""

    def close(self) -> None:
        """Release resources; safe to call twice."""

    def stats(self) -> dict[str, int | float]:
        return {}

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"
