"""The dispatcher: synchronous fan-out of every message to every backend that wants it.

The seed's contract, in Python:

* it runs in the caller's thread and never blocks (a backend that does I/O has its handlers
  run on its loop: its routes name a :class:`~gateway.handover.Handover`, and what the
  dispatcher calls is that hand-over's bounded, non-blocking post);
* every backend whose :class:`~gateway.backend.Routes` take the message's type is called, in
  registration order (the table is built once, at :meth:`Dispatcher.start`);
* it returns the first outcome that is not ``ACCEPTED`` and still tries every backend;
* a backend that raises is isolated: logged (once per kind of error), counted as ``FAILED``;
* ``Status`` goes through its own handler, never subject to SM-update rate limits;
* handlers of one dispatcher are never called concurrently (one short lock around a fan-out).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from gateway.backend import Backend, Handler
from gateway.handover import Handover
from gateway.outcome import FailureLog, Outcome

log = logging.getLogger(__name__)

ACCEPTED = Outcome.ACCEPTED


@dataclass
class BackendRecord:
    """A registered backend and what the dispatcher has seen it do."""

    backend: Backend
    started: bool = False
    init_error: str | None = None
    outcomes: dict[Outcome, int] = field(default_factory=lambda: dict.fromkeys(Outcome, 0))
    failures: FailureLog = field(default_factory=lambda: FailureLog(log))

    @property
    def name(self) -> str:
        return getattr(self.backend, "name", type(self.backend).__name__)


class Dispatcher:
    """Fans messages out to backends; see the module docstring for the contract."""

    def __init__(self, backends: Iterable[Backend] = ()) -> None:
        self._records: list[BackendRecord] = []
        self._routes: dict[type, list[tuple[BackendRecord, Handler]]] = {}
        self._handovers: list[Handover] = []  # the routes' hand-overs (held for a batch)
        self._lock = threading.RLock()  # re-entrant: a hook may dispatch (no self-deadlock)
        self.dispatched = 0
        self.unrouted = 0
        for b in backends:
            self.add(b)

    # -- registration and life cycle ----------------------------------------------------------

    def add(self, backend: Backend) -> None:
        """Register a backend.  It receives messages once :meth:`start` has initialised it."""
        if not callable(getattr(backend, "routes", None)):
            raise TypeError(f"{backend!r} has no routes(): derive it from gateway.backend.Backend")
        names = {r.name for r in self._records}
        rec = BackendRecord(backend)
        if rec.name in names:
            raise ValueError(f"a backend named {rec.name!r} is already registered")
        self._records.append(rec)

    @property
    def records(self) -> list[BackendRecord]:
        return list(self._records)

    def backends(self) -> list[Backend]:
        return [r.backend for r in self._records]

    def start(self) -> list[tuple[str, str]]:
        """Initialise every registered backend (the seed's ``telemetry_init()``).

        A backend whose ``init`` raises is reported and left out of the fan-out; the others
        still start.  Returns the failures as (name, first error), empty when all started.
        """
        failures: list[tuple[str, str]] = []
        for rec in self._records:
            if rec.started:
                continue
            init = getattr(rec.backend, "init", None)
            try:
                if init is not None:
                    init()
            except Exception as exc:  # a failing backend must not stop the others
                rec.init_error = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                failures.append((rec.name, rec.init_error))
                log.error("backend %s failed to start: %s", rec.name, rec.init_error)
                continue
            rec.started = True
        self._rebuild_routes()
        return failures

    def close(self) -> None:
        """Close every backend (errors logged, never raised); safe to call twice."""
        with self._lock:
            self._routes = {}
            self._handovers = []
        for rec in self._records:
            close = getattr(rec.backend, "close", None)
            if close is None:
                continue
            try:
                close()
            except Exception:
                log.exception("backend %s failed to close", rec.name)
            rec.started = False

    def _rebuild_routes(self) -> None:
        """The type → handlers table, from the started backends' routes (in their order)."""
        routes: dict[type, list[tuple[BackendRecord, Handler]]] = {}
        handovers: list[Handover] = []
        for rec in self._records:
            if not rec.started:
                continue
            try:
                table = rec.backend.routes()
            except Exception:
                log.exception("backend %s: routes() failed; it receives nothing", rec.name)
                continue
            handover = table.handover
            if handover is not None and handover not in handovers:
                handovers.append(handover)
            for cls, handler in table:
                hook = handler if handover is None else handover.hook(handler)
                routes.setdefault(cls, []).append((rec, hook))
        with self._lock:
            self._routes = routes
            self._handovers = handovers

    # -- fan-out ----------------------------------------------------------------------------

    def dispatch(self, msg: Any) -> Outcome:
        """Hand ``msg`` to every backend that routes its type; the first non-accepted
        outcome, or ``ACCEPTED``.  Never raises because of a backend."""
        hooks = self._routes.get(type(msg))
        if not hooks:
            self.unrouted += 1
            return ACCEPTED
        first = ACCEPTED
        with self._lock:
            self.dispatched += 1
            for rec, fn in hooks:
                try:
                    res = fn(msg)
                    outcome = (ACCEPTED if res is None or res == 0 else
                               res if type(res) is Outcome else Outcome(res))
                except Exception as exc:
                    outcome = Outcome.FAILED
                    self._log_failure(rec, exc)
                rec.outcomes[outcome] += 1
                if outcome is not ACCEPTED and first is ACCEPTED:
                    first = outcome
        return first

    __call__ = dispatch

    def dispatch_batch(self, msgs: Iterable[Any]) -> None:
        """:meth:`dispatch` each of ``msgs`` in order (what one read of a source decoded), with
        the backends' hand-overs held: each backend's loop wakes once for the batch, not once
        per message.  Outcomes are counted as for :meth:`dispatch`."""
        dispatch = self.dispatch
        with self._lock:  # (re-entrant: each dispatch takes it again)
            handovers = self._handovers
            for h in handovers:
                h.hold()
            try:
                for msg in msgs:
                    dispatch(msg)
            finally:
                for h in handovers:
                    h.release()

    def _log_failure(self, rec: BackendRecord, exc: Exception) -> None:
        rec.failures.failed(f"backend {rec.name}", exc)

    # -- reporting ----------------------------------------------------------------------------

    def stats(self) -> dict[str, dict[str, Any]]:
        """Per backend: outcome counts plus the backend's own ``stats()``."""
        out: dict[str, dict[str, Any]] = {}
        for rec in self._records:
            d: dict[str, Any] = {o.label: n for o, n in rec.outcomes.items() if n}
            if rec.init_error:
                d["init_error"] = rec.init_error
            own = getattr(rec.backend, "stats", None)
            if callable(own):
                try:
                    d.update(own())
                except Exception:
                    log.exception("backend %s failed to report stats", rec.name)
            out[rec.name] = d
        return out
