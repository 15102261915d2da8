"""Helpers shared by the tests: bounded waits and gateway subprocesses.

Importable as ``helpers`` (pytest puts ``tests/`` on ``sys.path``).  Nothing here sleeps as
synchronisation: waits poll a condition or block on one, always with a deadline.
"""

from __future__ import annotations

import contextlib
import io
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
GATEWAY = [sys.executable, "-m", "gateway"]
DEADLINE_S = 10.0


def run_within(fn: Callable[[], Any], timeout: float = DEADLINE_S) -> Any:
    """Run ``fn`` in a helper thread; fail (instead of hanging) if it takes over ``timeout``."""
    box: dict[str, Any] = {}
    done = threading.Event()

    def target() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:
            box["error"] = exc
        finally:
            done.set()

    threading.Thread(target=target, daemon=True).start()
    assert done.wait(timeout), f"did not return within {timeout} s (blocked)"
    if "error" in box:
        raise box["error"]
    return box.get("value")


def wait_for(cond: Callable[[], bool], timeout: float = DEADLINE_S,
             poll_s: float = 0.002) -> bool:
    """Poll ``cond`` until it holds (True) or ``timeout`` passes (False): for states that
    signal no event (a worker blocked on a lock, bytes in a kernel buffer)."""
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(poll_s)
    return True


class BlockingTransport:
    """A port whose write blocks until ``release`` is set (a stalled UART or a full pipe);
    records what got through.  Closing it releases a blocked writer."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()
        self.written: list[bytes] = []
        self.closed = False

    def write(self, data: bytes) -> int:
        self.entered.set()
        self.release.wait()
        self.written.append(bytes(data))
        return len(data)

    def read(self, size: int = 1) -> bytes:
        return b""

    def close(self) -> None:
        self.closed = True
        self.release.set()


class Running:
    """A gateway subprocess whose stdout and stderr lines are collected by reader threads;
    ``wait_line`` blocks until a line matches (or the deadline passes)."""

    def __init__(self, *args: str, cmd: Sequence[str] = GATEWAY,
                 timeout: float = 20.0, group: bool = False) -> None:
        """``group``: the process leads a process group of its own, and :meth:`stop` ends
        the whole group (for a launcher that starts children of its own: fprime-gds)."""
        self.timeout = timeout
        self.group = group
        self.proc = subprocess.Popen([*cmd, *args], cwd=ROOT, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, bufsize=1,
                                     start_new_session=group)
        self.lines: dict[str, list[str]] = {"stdout": [], "stderr": []}
        self.cond = threading.Condition()
        self.eof = 0
        self.threads = [threading.Thread(target=self._pump, args=(name, pipe), daemon=True)
                        for name, pipe in (("stdout", self.proc.stdout),
                                           ("stderr", self.proc.stderr))]
        for th in self.threads:
            th.start()

    def _pump(self, name: str, pipe: io.TextIOBase) -> None:
        for line in pipe:
            with self.cond:
                self.lines[name].append(line.rstrip("\n"))
                self.cond.notify_all()
        with self.cond:
            self.eof += 1
            self.cond.notify_all()

    def wait_line(self, name: str, pred: Callable[[str], bool],
                  timeout: float | None = None) -> bool:
        """Wait until a line of ``name`` matches ``pred``; False if none does by the deadline
        or by the end of the process's output."""
        with self.cond:
            self.cond.wait_for(lambda: any(pred(ln) for ln in self.lines[name])
                               or self.eof == 2, timeout or self.timeout)
            return any(pred(ln) for ln in self.lines[name])

    def finish(self, timeout: float | None = None) -> int:
        rc = self.proc.wait(timeout or self.timeout)
        for th in self.threads:
            th.join(5)
        return rc

    def stop(self, timeout: float = 10.0) -> int:
        """Terminate it (its whole group if ``group``), kill what is left after ``timeout``,
        and collect its output; returns its exit status."""
        def signal_all(sig: int) -> None:
            with contextlib.suppress(ProcessLookupError):
                if self.group:
                    os.killpg(self.proc.pid, sig)
                else:
                    self.proc.send_signal(sig)

        signal_all(signal.SIGTERM)
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            signal_all(signal.SIGKILL)
            self.proc.wait(5)
        if self.group:  # children that outlived their leader
            signal_all(signal.SIGKILL)
        for th in self.threads:
            th.join(5)
        return self.proc.returncode

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5)
        for th in self.threads:
            th.join(5)

    def text(self, name: str) -> str:
        with self.cond:
            return "\n".join(self.lines[name])


def post(backend: Any, msg: Any) -> Any:
    """Hand ``msg`` to ``backend`` as the dispatcher does: its routed handler, through the
    routes' hand-over when they name one (then the handler runs on the backend's loop); the
    outcome."""
    routes = backend.routes()
    handler = dict(routes)[type(msg)]
    handover = routes.handover
    return handler(msg) if handover is None else handover.post(handler, msg)


class HeldLoop:
    """Keeps an :class:`~gateway.io.ioloop.IoLoop` busy (in a callback) until the ``with``
    block ends: what is handed to it meanwhile waits."""

    def __init__(self, loop: Any) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        loop.call_soon(self._hold)
        assert self.entered.wait(DEADLINE_S), "the loop did not run the hold"

    def _hold(self) -> None:
        self.entered.set()
        self.release.wait(DEADLINE_S)

    def __enter__(self) -> HeldLoop:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release.set()
