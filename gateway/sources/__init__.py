"""Sources: where messages come from.  Each hands every message to a sink (normally
:meth:`gateway.app.Gateway.ingest`).

The contract, all of it public (the app uses nothing else):

* ``name``; ``OPTIONS`` (a :class:`gateway.options.Options` dataclass, its options declared
  once; the schema ``CONFIG`` is derived from it), ``from_config(options, name)`` (default:
  ``cls(OPTIONS.from_table(options), name=name)``) and optionally ``default_name(options)``,
  which the configuration uses;
* ``attach(context)``, called before ``start`` with the gateway's
  :class:`gateway.backend.GatewayContext` (kept as ``context``);
* ``start(sink)`` returns at once; the work happens on the source's own thread (or a port
  engine's);
* ``request_stop()`` asks it to stop and returns at once (so many sources wind down
  together); ``stop(timeout)`` stops it and returns within about ``timeout``; both safe twice;
* ``done``, a ``threading.Event`` set once the source has nothing more to send (a replay's
  end, a one-flight simulation, or after ``stop``);
* ``stats()``, a dict of counters.

A subclass that needs a thread implements :meth:`Source.run` (loop until the ``stop`` event
it is given is set) and hands messages to :meth:`Source.emit`; a source on a
:class:`gateway.io.port.PortEngine` overrides ``start``/``stop`` instead.  Every message carries
``origin`` = the source's name.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, ClassVar

from gateway import registry
from gateway.backend import Backend, GatewayContext, Routes, build, derive_config
from gateway.io.endpoints import check_serial_port, is_device
from gateway.options import Options

log = logging.getLogger(__name__)

Sink = Callable[[Any], Any]


class Source:
    """Base class: a named worker thread running :meth:`run` until :meth:`stop`."""

    NAME: ClassVar[str] = "source"
    #: the options declaration; CONFIG, its schema, is derived from it
    OPTIONS: ClassVar[type[Options] | None] = None
    CONFIG: ClassVar[Any] = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        derive_config(cls)

    def __init__(self, name: str | None = None) -> None:
        self.name = name or self.NAME
        self.context = GatewayContext()
        self.done = threading.Event()
        self._stop = threading.Event()  # what run() is given; set by request_stop()
        self._thread: threading.Thread | None = None
        self._sink: Sink | None = None

    @classmethod
    def from_config(cls, options: dict[str, Any], name: str | None = None) -> Source:
        """An instance from options the class's ``CONFIG`` has already validated."""
        source: Source = build(cls, options, name)
        return source

    @classmethod
    def url_options(cls, rest: str | None) -> dict[str, Any]:
        """The options of ``--source NAME:REST`` (``rest`` None: the name alone), for the
        ``CONFIG`` to check: by default REST is the ``url`` key."""
        return {} if rest is None else {"url": rest}

    def routes(self) -> Routes:
        """Gateway messages this source takes (none by default): a source that also sends
        (an XBee ground link sends the pilot's commands up) routes them like a backend; the
        gateway hands them to it through a :class:`SourceInbox`."""
        return Routes()

    def attach(self, context: GatewayContext) -> None:
        """Remember the gateway's context (called before :meth:`start`); a source that must
        tell this gateway's own publications from others' reads ``context.own_ids``."""
        self.context = context

    @property
    def running(self) -> bool:
        """Started and not done (a source retrying its port is running)."""
        return self._sink is not None and not self.done.is_set()

    def start(self, sink: Sink) -> None:
        """Begin delivering messages to ``sink``; returns at once; a second call does
        nothing."""
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
        """Hand one message to the sink (from the source's thread)."""
        sink = self._sink
        if sink is not None:
            sink(msg)

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    def request_stop(self) -> None:
        """Ask the source to stop, without waiting for it; safe twice."""
        self._stop.set()

    def stop(self, timeout: float = 1.0) -> None:
        """Stop and wait up to ``timeout`` for the thread to end; safe twice."""
        self.request_stop()
        t = self._thread
        if t is not None and t is not threading.current_thread():
            t.join(timeout)
            if t.is_alive():
                log.warning("source %s did not stop within %.1f s", self.name, timeout)

    def stats(self) -> dict[str, Any]:
        return {}


def check_serial_url(url: Any) -> None:
    """A serial port key's value: a device path (``/dev/…``, ``COMn``, any absolute path; not
    checked for existence: it may appear later, and the source retries it) or a pyserial URL
    of a scheme pyserial has a handler for (``socket://`` and ``rfc2217://`` with HOST:PORT).
    The baud rate has its own key.  Raises :class:`~gateway.io.endpoints.EndpointError`."""
    check_serial_port(url)


def _url_forms(names: list[str]) -> str:
    return (f"NAME[:…] for a source ({', '.join(names)}), a serial device (/dev/…, COMn) or "
            "a pyserial URL (loop://, socket://HOST:PORT …)")


def parse_source_url(url: str) -> tuple[str, dict[str, Any]]:
    """``NAME[:REST]`` → (source type, options), NAME one of the installed sources' entry-point
    names (``sim``, ``replay:FILE``, ``mavlink:ENDPOINT`` …; each source's
    :meth:`Source.url_options` turns REST into options); a device path or a pyserial URL →
    the serial source.  ValueError for an empty or unknown one.  The options go through the
    source's ``CONFIG`` like a file's, which checks them."""
    text = url.strip()
    names = registry.source_names()
    if not text:
        raise ValueError(f"empty source URL; expected {_url_forms(names)}")
    head, sep, rest = text.partition(":")
    if head in names and not rest.startswith("//"):
        try:
            cls = registry.load(registry.SOURCE_GROUP, head)
        except registry.RegistryError as exc:
            raise ValueError(str(exc)) from None
        url_options = getattr(cls, "url_options", None) or Source.url_options
        return head, url_options(rest if sep else None)
    if "://" in text or is_device(text.partition(",")[0]):
        return "serial", {"url": text}  # checked by the url key (check_serial_url)
    raise ValueError(f"no source {head!r}; expected {_url_forms(names)}")


class SourceInbox(Backend):
    """The backend side of a source that takes gateway messages (:meth:`Source.routes`): the
    dispatcher hands them to the source's handlers like to any backend's."""

    def __init__(self, source: Source) -> None:
        super().__init__(f"{source.name} (in)")
        self.source = source

    def routes(self) -> Routes:
        return self.source.routes()

    def stats(self) -> dict[str, Any]:
        inbox = getattr(self.source, "inbox_stats", None)
        return dict(inbox()) if inbox is not None else {}
