"""The backend contract: what a backend must implement, what it may, and what it reports.

A backend **must**:

* have a ``name`` (unique in one gateway; defaults to the class's ``NAME``);
* say which message types it takes in :meth:`Backend.routes` — a :class:`Routes` table,
  message type → handler, which the dispatcher reads once at start.  The table is typed:
  ``Routes().on(SmUpdate, self.send_sm_update)`` is checked by mypy, so a misspelled handler
  or one that takes another message type fails ``make lint``, not silently at run time;
* never block in a handler: a backend that does its work on an
  :class:`~gateway.io.ioloop.IoLoop` says so in its routes — ``Routes(handover=h)`` with a
  :class:`gateway.handover.Handover` — and its handlers then run on that loop, handed over
  (bounded, coalesced, drops counted as ``QUEUE_FULL``); a handler without a hand-over runs in
  the dispatcher's thread and at most submits to a :class:`gateway.io.port.PortEngine`.  A
  handler returns an :class:`Outcome` (``None`` counts as accepted; on a loop the outcome is
  the hand-over's).

A backend **may** implement:

``init()``
    open what it needs; raise :class:`BackendError` (or anything) to refuse to start;
``close()``
    release everything; must be safe to call twice;
``stats()``
    its counters.  Every built-in backend reports at least :data:`STATS_KEYS` — ``sent``
    (frames or messages out), ``dropped`` (refused or lost, any reason), ``errors``
    (failures: write errors, encode errors …) and ``link`` (1 while its port, session or
    endpoint is up, else 0) — plus its own, ``dropped_<reason>`` for each drop reason;
``attach(context)``
    called before ``init`` with the gateway's :class:`GatewayContext`: ``emit`` hands a
    message the backend decoded (link statistics from a radio, commands from a ground
    station) to every other backend, with ``origin`` set to the backend's own name;
``OPTIONS``
    its options, declared once: a :class:`gateway.options.Options` dataclass (in a light
    module, found without importing the backend through the ``aurora_gateway.backend_options``
    entry point) from which its ``[backends.<name>]`` schema (``CONFIG``, derived), its
    ``run`` flags and its documentation come.  The constructor takes the validated object:
    ``XBackend(XOptions(...), name=...)``;
``from_config(table)``
    build it from the validated table (default: ``cls(OPTIONS.from_table(table), name=…)``;
    a plug-in with a hand-written ``CONFIG`` schema and no ``OPTIONS``: the keys as keyword
    arguments);
``EMBEDDED_DEFAULT``
    its options in the embedded default run (loopback, no hardware); None leaves it out
    (a backend with an options entry point declares it on its ``OPTIONS`` class, which is what
    the default run reads);
``add_cli_arguments(parser)`` / ``cli_options(args)``
    its quick flags on ``aurora-gateway run`` and the options they set (default: those its
    ``OPTIONS`` fields declare).
"""

from __future__ import annotations

import itertools
import os
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

from gateway.options import Options, options_of
from gateway.outcome import Outcome

if TYPE_CHECKING:
    from gateway.handover import Handover

#: The stats keys every built-in backend reports (see the module docstring).
STATS_KEYS = ("sent", "dropped", "errors", "link")


class BackendError(Exception):
    """A backend cannot start or run as configured."""


M = TypeVar("M")
Handler = Callable[[Any], "Outcome | None"]


class Routes:
    """A backend's routing table: message type → handler (see the module docstring).

    Routing is by exact type: a message is handed to the handlers registered for
    ``type(msg)``.  A backend package may route message types it defines itself.

    With ``handover``, the handlers run on the hand-over's loop: the dispatcher posts each
    message to it (bounded; never blocking) and the loop calls the handler."""

    __slots__ = ("_table", "handover")

    def __init__(self, handover: Handover | None = None) -> None:
        self._table: dict[type, Handler] = {}
        self.handover = handover

    def on(self, cls: type[M], handler: Callable[[M], Outcome | None]) -> Routes:
        """Route messages of type ``cls`` to ``handler``; returns the table (chainable)."""
        if cls in self._table:
            raise ValueError(f"{cls.__name__} is routed twice")
        self._table[cls] = handler
        return self

    def __iter__(self) -> Iterator[tuple[type, Handler]]:
        return iter(self._table.items())

    def __len__(self) -> int:
        return len(self._table)

    def types(self) -> list[type]:
        return list(self._table)


def derive_config(cls: Any) -> None:
    """Set ``cls.CONFIG`` to the schema its ``OPTIONS`` declare (a class with no ``OPTIONS``
    keeps its own)."""
    opts = options_of(cls)
    if opts is not None:
        cls.CONFIG = opts.schema()


def build(cls: Any, table: dict[str, Any], name: str | None) -> Any:
    """A backend or source from its validated table: ``cls(OPTIONS.from_table(table),
    name=name)``, or for a class without ``OPTIONS`` the keys as keyword arguments."""
    opts = options_of(cls)
    if opts is not None:
        return cls(opts.from_table(table), name=name)
    return cls(name=name, **table)


_instances = itertools.count(1)


def new_gateway_id() -> str:
    """``<host>-<pid>-<n>``: unique per gateway, also between two gateways of one process."""
    host = "".join(c if c.isalnum() or c in "_.-" else "-" for c in socket.gethostname())
    return f"{host or 'host'}-{os.getpid()}-{next(_instances)}"


@dataclass
class GatewayContext:
    """What a gateway hands each backend and source as it starts (one per gateway: two
    gateways in one process share nothing).

    ``emit``
        ingest a message (it reaches every backend);
    ``gateway_id``
        this gateway's id (used in Zenoh attachments, liveliness tokens);
    ``own_ids``
        every id under which a backend of this gateway publishes; a source that hears one of
        them is hearing this gateway, not another;
    ``services``
        objects the plugins of one gateway share, by name (e.g. ``"mavlink.hub"``: the one
        MAVLink router that the MAVLink source and backend both use).
    """

    emit: Callable[[Any], Any] = lambda msg: None
    gateway_id: str = field(default_factory=new_gateway_id)
    own_ids: set[str] = field(default_factory=set)
    services: dict[str, Any] = field(default_factory=dict)


class Plugin:
    """What a backend and a source (:class:`gateway.sources.Source`) share: a ``NAME``,
    options declared once (``OPTIONS``, from which ``CONFIG`` is derived for every subclass),
    an instance's name and the gateway's :class:`GatewayContext`."""

    NAME: ClassVar[str] = "plugin"
    #: the options declaration (see the module docstring); None: a plug-in's own CONFIG
    OPTIONS: ClassVar[type[Options] | None] = None
    #: the schema of its table: derived from OPTIONS (a plug-in may write its own)
    CONFIG: ClassVar[Any] = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        derive_config(cls)

    def __init__(self, name: str | None = None) -> None:
        self.name = name or self.NAME
        self.context = GatewayContext()

    def attach(self, context: GatewayContext) -> None:
        """Remember the gateway's context (called before the plug-in starts); a plug-in that
        must tell this gateway's own publications from others' reads ``context.own_ids``."""
        self.context = context


class Backend(Plugin):
    """Base class for backends: sensible defaults for everything a backend may implement."""

    NAME: ClassVar[str] = "backend"
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None

    @classmethod
    def from_config(cls, table: dict[str, Any], name: str | None = None) -> Backend:
        return build(cls, table, name)

    @classmethod
    def add_cli_arguments(cls, parser: Any) -> None:
        """Add this backend's quick flags to ``aurora-gateway run`` (e.g. ``--mavlink``)."""
        opts = options_of(cls)
        if opts is not None:
            opts.add_cli_arguments(parser)

    @classmethod
    def cli_options(cls, args: Any, where: str = "") -> dict[str, Any] | None:
        """Options the parsed flags set for this backend, or None when none were given."""
        opts = options_of(cls)
        return opts.cli_options(args, where) if opts is not None else None

    def routes(self) -> Routes:
        """The message types this backend takes and their handlers (none by default)."""
        return Routes()

    def emit(self, msg: Any) -> None:
        """Hand a message this backend decoded to the gateway (a no-op until attached)."""
        self.context.emit(msg)

    def init(self) -> None:
        """Open resources; raise to refuse to start."""

    def close(self) -> None:
        """Release resources; safe to call twice."""

    def stats(self) -> dict[str, Any]:
        return {}

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"
