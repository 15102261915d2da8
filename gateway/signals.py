"""Ctrl-C and SIGTERM, handled where they cannot break what they interrupt.

Python runs a signal's handler in the main thread at the next bytecode, wherever that is.
Two places there are unsafe, and this module keeps the handlers out of both:

* **Inside a C extension's module initialisation** that imports Python modules of its own.
  A :class:`KeyboardInterrupt` there makes the import fail, and an extension that does not
  check crashes: orjson's init (3.x) then dies with SIGSEGV instead of the quiet status 130
  (a Ctrl-C 0.1 s after ``aurora-gateway listen`` started, once in a few hundred tries).
  While :func:`hold` holds, SIGINT and SIGTERM are only noted; :func:`release` puts the
  previous handlers back and raises the last noted signal again, at a point of our choosing.
  Only the main thread can hold (only it runs signal handlers).
* **Inside a lock the handler needs.** :meth:`threading.Event.wait` holds the event's lock
  around its bookkeeping; a handler that sets that event takes the lock, and the main thread
  waits for itself forever (``record`` ignoring a Ctrl-C 0.2 s after start, once in a few
  hundred tries).  Starting a thread from the handler is no way out: ``Thread.start`` takes
  threading's own lock, which the main thread holds while it starts the gateway's threads.
  :class:`Stopper`'s handler takes no lock: it puts the signal on a
  :class:`queue.SimpleQueue` (whose ``put`` is reentrant) for a relay thread, started with
  the handlers, that sets the event.
"""

from __future__ import annotations

import queue
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from gateway import exits

#: the signals held: a user's Ctrl-C and a service manager's stop
SIGNALS = (signal.SIGINT, signal.SIGTERM)

_saved: dict[int, Any] | None = None  # the handlers the hold replaced, while it holds
_noted: int | None = None  # the last signal that arrived while held (a flood keeps one)


def _note(signum: int, frame: object) -> None:
    global _noted
    _noted = signum


def holding() -> bool:
    """True while signals are held."""
    return _saved is not None


def hold(after: dict[int, Any] | None = None) -> bool:
    """Start holding SIGINT and SIGTERM; False (and nothing changed) if already holding or
    not on the main thread.  ``after``: the handler a signal gets when the hold ends, if
    not the one it had before."""
    global _saved
    if _saved is not None or threading.current_thread() is not threading.main_thread():
        return False
    saved: dict[int, Any] = {sig: signal.signal(sig, _note) for sig in SIGNALS}
    _saved = {**saved, **(after or {})}
    return True


def release() -> None:
    """Stop holding: the previous handlers again, then the last signal that arrived while
    held, raised now through its own handler (a :class:`KeyboardInterrupt`, say)."""
    global _saved, _noted
    if _saved is None:
        return
    saved, _saved = _saved, None
    _put_back(list(saved.items()))
    if _noted is not None:
        last, _noted = _noted, None
        signal.raise_signal(last)


def _put_back(handlers: list[tuple[int, Any]]) -> None:
    """Install each (signal, handler) (None, a handler not set from Python: the default),
    all of them even if a signal arriving meanwhile raises through one just put back (its
    exception then goes on once all are in)."""
    if handlers:
        (sig, handler), rest = handlers[0], handlers[1:]
        try:
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
        finally:
            _put_back(rest)


@contextmanager
def held() -> Iterator[None]:
    """Signals held for the block (nested in a hold: the outer one decides)."""
    mine = hold()
    try:
        yield
    finally:
        if mine:
            release()


class Stopper:
    """SIGINT/SIGTERM set an event instead of raising in the middle of something; the last
    one received is :attr:`signal`, and :attr:`status` the exit status it makes
    (:func:`gateway.exits.after_stop`: 130 for SIGINT, 0 for SIGTERM or none).  Installed
    on the main thread only (elsewhere it changes nothing).  Installed while signals are
    held, it ends the hold first (:func:`release`): a signal noted meanwhile is raised
    there, so the command ends before it starts anything.  A command that installs one is
    held from the entry point to here (gateway.commands.cli.main), with no moment between
    where a Ctrl-C raises into whatever runs — a KeyboardInterrupt raised inside a
    finalizer (an import's lock bookkeeping, a generator freed) is printed and dropped by
    Python, and the command would run on."""

    def __init__(self, event: threading.Event) -> None:
        self.event = event
        self.signal: int | None = None
        self._old: dict[int, Any] = {}
        self._relay: queue.SimpleQueue[int | None] = queue.SimpleQueue()
        self._relay_thread: threading.Thread | None = None

    def install(self) -> Stopper:
        if threading.current_thread() is threading.main_thread() and not self._old:
            release()  # a hold ends here: what it noted is raised now, before any stop
            self._relay_thread = threading.Thread(target=self._run_relay, name="signal-stop",
                                                  daemon=True)
            self._relay_thread.start()
            for sig in SIGNALS:
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def restore(self) -> None:
        """The handlers from before :meth:`install`; the relay thread ends."""
        old, self._old = list(self._old.items()), {}
        try:
            _put_back(old)
        finally:
            if self._relay_thread is not None:
                self._relay.put(None)
                self._relay_thread = None

    def _handle(self, signum: int, frame: Any) -> None:
        self.signal = signum
        if not self.event.is_set():  # (a flood of signals queues nothing more)
            self._relay.put(signum)  # no lock taken here (see the module's docstring)

    def _run_relay(self) -> None:
        while self._relay.get() is not None:
            self.event.set()

    @property
    def status(self) -> int:
        return exits.after_stop(self.signal)

    def __enter__(self) -> Stopper:
        return self.install()

    def __exit__(self, *exc: object) -> None:
        self.restore()
