"""Sources: where messages come from.  Each runs its own thread and hands every message to a
sink (normally :meth:`gateway.app.Gateway.ingest`).

A source **must** implement ``start(sink)`` (return at once; work in its own thread) and
``stop(timeout)`` (end within ``timeout``; safe twice).  It **might** implement ``stats()``
and set ``done`` (a ``threading.Event``) when it has nothing more to send (a replay's end).
Every message it emits carries ``origin`` = the source's name.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, ClassVar

log = logging.getLogger(__name__)

Sink = Callable[[Any], Any]


class Source:
    """Base class: a named worker thread running :meth:`run` until :meth:`stop`."""

    NAME: ClassVar[str] = "source"
    CONFIG: ClassVar[Any] = None

    def __init__(self, name: str | None = None) -> None:
        self.name = name or self.NAME
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sink: Sink | None = None

    @classmethod
    def from_config(cls, options: dict[str, Any], name: str | None = None) -> Source:
        return cls(name=name, **options)

    def start(self, sink: Sink) -> None:
        if self._thread is not None:
            return
        self._sink = sink
        self._thread = threading.Thread(target=self._main, name=f"source-{self.name}",
                                        daemon=True)
        self._thread.start()

    def _main(self) -> None:
        try:
            self.run(self._stop)
        except Exception:
            log.exception("source %s failed", self.name)
        finally:
            self.done.set()

    def run(self, stop: threading.Event) -> None:
        """The source's loop; return when ``stop`` is set (or when there is nothing left)."""
        raise NotImplementedError

    def emit(self, msg: Any) -> None:
        sink = self._sink
        if sink is not None:
            sink(msg)

    def stop(self, timeout: float = 1.0) -> None:
        self._stop.set()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout)
            if t.is_alive():
                log.warning("source %s did not stop within %.1f s", self.name, timeout)

    def stats(self) -> dict[str, Any]:
        return {}


def parse_source_url(url: str) -> tuple[str, dict[str, Any]]:
    """``sim``, ``replay:FILE``, ``mavlink:ENDPOINT``, ``zenoh:[VEHICLE@][ENDPOINT,…]`` or a
    pyserial URL → (source type, options)."""
    if url in ("sim", "sim:"):
        return "sim", {}
    if url.startswith("replay:"):
        path = url[len("replay:"):]
        if not path:
            raise ValueError("replay: needs a file, e.g. replay:flight.agrec")
        return "replay", {"path": path}
    if url.startswith("mavlink:"):
        endpoint = url[len("mavlink:"):]
        if not endpoint:
            raise ValueError("mavlink: needs an endpoint, e.g. mavlink:udpin:0.0.0.0:14551")
        return "mavlink", {"url": endpoint}
    if url == "zenoh" or url.startswith("zenoh:"):
        return "zenoh", {"url": url}  # zenoh:[VEHICLE@][ENDPOINT,…], parsed by the source
    if not url:
        raise ValueError("empty source URL")
    return "serial", {"url": url}
