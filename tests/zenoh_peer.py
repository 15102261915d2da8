"""Zenoh helpers for tests and benchmarks: free loopback endpoints, a router subprocess, and a
subscriber that records what it receives and lets callers wait for it.

Importable as ``zenoh_peer`` (pytest puts ``tests/`` on ``sys.path``; ``tools/bench`` adds it).
Nothing here sleeps to synchronise: every wait is on a condition, with a deadline.
"""

from __future__ import annotations

import contextlib
import json
import os
import selectors
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from helpers import ROOT, wait_for

from backends.zenoh.keys import parse_attachment


def free_port() -> int:
    """A TCP port on 127.0.0.1 nobody listened on a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


def peer_config(listen: Sequence[str] = (), connect: Sequence[str] = (),
                mode: str = "peer", **extra: Any) -> Any:
    """A zenoh.Config with explicit endpoints and multicast scouting off."""
    import zenoh

    doc: dict[str, Any] = {"mode": mode, "connect": {"endpoints": list(connect)},
                           "scouting": {"multicast": {"enabled": False}}}
    if mode != "client":
        doc["listen"] = {"endpoints": list(listen)}
    doc.update(extra)
    return zenoh.Config.from_json5(json.dumps(doc))


def read_line(proc: subprocess.Popen, timeout: float) -> str:
    """The next line of a subprocess's stdout, or "" at EOF or after ``timeout``."""
    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            return ""
    return proc.stdout.readline()


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGTERM,
                 timeout: float = 5.0) -> int:
    """Signal a subprocess, wait for it, kill it if it will not go; its exit status."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(sig)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout)
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()
    return proc.returncode


class RouterProcess:
    """``python -m backends.zenoh.router`` on ``endpoint``, started and stopped by the caller.

    :meth:`start` returns once the router listens; :meth:`kill` ends it abruptly (a crash);
    use it as a context manager so it is always stopped."""

    def __init__(self, endpoint: str | None = None, config: str | Path | None = None,
                 cwd: str | Path | None = None) -> None:
        self.endpoint = endpoint or free_endpoint()
        self.config = config
        self.cwd = cwd or ROOT
        self.proc: subprocess.Popen | None = None
        self.started_at: float | None = None

    def start(self, timeout: float = 30.0) -> RouterProcess:
        cmd = [sys.executable, "-m", "backends.zenoh.router", "--listen", self.endpoint]
        if self.config:
            cmd += ["--config", str(self.config)]
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        self.proc = subprocess.Popen(cmd, cwd=self.cwd, env=env, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        line = read_line(self.proc, timeout)
        if not line.startswith("ready"):
            err = ""
            if self.proc.poll() is not None and self.proc.stderr is not None:
                err = self.proc.stderr.read()
            stop_process(self.proc)
            raise RuntimeError(f"router on {self.endpoint} did not start: {line!r} {err}")
        self.started_at = time.monotonic()
        return self

    def kill(self) -> None:
        if self.proc is not None:
            stop_process(self.proc, signal.SIGKILL)
            self.proc = None

    def stop(self) -> None:
        if self.proc is not None:
            stop_process(self.proc)
            self.proc = None

    def __enter__(self) -> RouterProcess:
        return self.start() if self.proc is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class Received:
    """One sample as a subscriber saw it."""

    __slots__ = ("attachment", "encoding", "gateway", "key", "payload", "rx", "seq")

    def __init__(self, key: str, payload: bytes, encoding: str, attachment: bytes | None,
                 rx: float) -> None:
        self.key = key
        self.payload = payload
        self.encoding = encoding
        self.attachment = attachment
        self.gateway, self.seq = parse_attachment(attachment)
        self.rx = rx

    def json(self) -> Any:
        return json.loads(self.payload)

    def __repr__(self) -> str:
        return f"<{self.key} gw={self.gateway} seq={self.seq} {self.payload[:60]!r}>"


class Recorder:
    """A subscriber callback that keeps every sample and wakes waiters."""

    def __init__(self) -> None:
        self.samples: list[Received] = []
        self._cond = threading.Condition()

    def __call__(self, sample: Any) -> None:
        att = sample.attachment
        item = Received(str(sample.key_expr), sample.payload.to_bytes(), str(sample.encoding),
                        att.to_bytes() if att is not None else None, time.monotonic())
        with self._cond:
            self.samples.append(item)
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[list[Received]], bool],
                 timeout: float = 20.0) -> bool:
        """Wait until ``predicate(samples)`` holds; False after ``timeout``."""
        with self._cond:
            return self._cond.wait_for(lambda: predicate(self.samples), timeout)

    def matching(self, key: str) -> list[Received]:
        with self._cond:
            return [s for s in self.samples if s.key == key]

    def snapshot(self) -> list[Received]:
        with self._cond:
            return list(self.samples)


def serving(backend: Any, *vehicles_: str, source: str = "serial") -> Any:
    """``backend`` attached to a gateway context whose configured sources are one per vehicle
    (the ``gateway.vehicles`` service the app provides; the first named ``source``): its
    Zenoh backend then declares their presence as its session opens.  Returns it."""
    from gateway import vehicles
    from gateway.backend import GatewayContext

    context = GatewayContext()
    context.services[vehicles.SERVICE] = [
        vehicles.SourceVehicle(source if i == 0 else f"{source}-{i + 1}", v)
        for i, v in enumerate(vehicles_)]
    backend.attach(context)
    return backend


def wait_until(predicate: Callable[[], bool], timeout: float = 20.0,
               interval: float = 0.01) -> bool:
    """Poll ``predicate`` until it holds (True) or ``timeout`` passes (False)."""
    return wait_for(predicate, timeout, interval)


def wait_for_gateway(session: Any, prefix: str, vehicle: str, timeout: float = 20.0) -> list:
    """Wait until a gateway publishing ``<prefix>/<vehicle>`` is reachable from ``session``,
    then query it: when the replies are in, the gateway has also seen every declaration
    ``session`` made before (one ordered link), so its publications reach them.  Returns the
    query's samples (the latest value of each key)."""
    deadline = time.monotonic() + timeout
    pause = threading.Event()
    token = f"{prefix}/{vehicle}/gateway/*"
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError(f"no gateway for {prefix}/{vehicle} within {timeout} s")
        replies = list(session.liveliness().get(token, timeout=min(1.0, remaining)))
        if any(r.ok is not None for r in replies):
            break
        pause.wait(0.05)
    replies = list(session.get(f"{prefix}/{vehicle}/**", timeout=max(1.0, remaining)))
    return [r.ok for r in replies if r.ok is not None]
