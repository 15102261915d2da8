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
* **Inside** :meth:`threading.Event.wait` **on the very event the handler sets**: the wait
  holds the event's lock around its bookkeeping, the handler's ``set`` takes that lock, and
  the main thread waits for itself forever (``record`` ignoring a Ctrl-C 0.2 s after start,
  once in a few hundred tries).  :class:`Stopper` sets its event from a thread of its own.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from gateway import exits

#: the signals held: a user's Ctrl-C and a service manager's stop
SIGNALS = (signal.SIGINT, signal.SIGTERM)

_saved: dict[int, Any] | None = None  # the handlers the hold replaced, while it holds
_noted: list[int] = []  # signals that arrived while held, in order


def _note(signum: int, frame: object) -> None:
    _noted.append(signum)


def holding() -> bool:
    """True while signals are held."""
    return _saved is not None


def hold() -> bool:
    """Start holding SIGINT and SIGTERM; False (and nothing changed) if already holding or
    not on the main thread."""
    global _saved
    if _saved is not None or threading.current_thread() is not threading.main_thread():
        return False
    saved: dict[int, Any] = {}
    for sig in SIGNALS:
        old = signal.signal(sig, _note)
        saved[sig] = signal.SIG_DFL if old is None else old  # None: not set from Python
    _saved = saved
    return True


def release() -> None:
    """Stop holding: the previous handlers again, then the last signal that arrived while
    held, raised now through its own handler (a :class:`KeyboardInterrupt`, say)."""
    global _saved
    if _saved is None:
        return
    saved, _saved = _saved, None
    for sig, old in saved.items():
        signal.signal(sig, old)
    if _noted:
        last = _noted[-1]
        _noted.clear()
        signal.raise_signal(last)


@contextmanager
def held() -> Iterator[None]:
    """Signals held for the block (nested in a hold: the outer one decides)."""
    mine = hold()
    try:
        yield
    finally:
        if mine:
            release()


def set_from_handler(event: threading.Event) -> None:
    """Set ``event`` from a signal handler: on a short-lived thread, since the handler may
    have interrupted the main thread inside that event's own lock."""
    try:
        threading.Thread(target=event.set, name="signal-stop", daemon=True).start()
    except RuntimeError:  # the interpreter is finalizing: no new threads, and no one waits
        event.set()


class Stopper:
    """SIGINT/SIGTERM set an event instead of raising in the middle of something; the last
    one received is :attr:`signal`, and :attr:`status` the exit status it makes
    (:func:`gateway.exits.after_stop`: 130 for SIGINT, 0 for SIGTERM or none).  Installed
    on the main thread only (elsewhere it changes nothing)."""

    def __init__(self, event: threading.Event) -> None:
        self.event = event
        self.signal: int | None = None
        self._old: dict[int, Any] = {}

    def install(self) -> Stopper:
        if threading.current_thread() is threading.main_thread():
            for sig in SIGNALS:
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def restore(self) -> None:
        """The handlers from before :meth:`install`."""
        for sig, old in self._old.items():
            signal.signal(sig, signal.SIG_DFL if old is None else old)
        self._old.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        self.signal = signum
        set_from_handler(self.event)

    @property
    def status(self) -> int:
        return exits.after_stop(self.signal)

    def __enter__(self) -> Stopper:
        return self.install()

    def __exit__(self, *exc: object) -> None:
        self.restore()
