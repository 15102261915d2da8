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

import importlib
import logging
import pkgutil
import threading
from collections.abc import Callable
from typing import Any, ClassVar
from urllib.parse import urlsplit

from gateway.backend import Backend, GatewayContext, Routes, build, derive_config
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


def serial_url_schemes() -> list[str]:
    """The URL schemes pyserial's ``serial_for_url`` has a handler module for."""
    import serial

    found: set[str] = set()
    for package in serial.protocol_handler_packages:
        try:
            path = importlib.import_module(package).__path__
        except (ImportError, AttributeError):
            continue
        found.update(m.name[len("protocol_"):] for m in pkgutil.iter_modules(path)
                     if m.name.startswith("protocol_"))
    return sorted(found)


_HOST_PORT_SCHEMES = ("socket", "rfc2217")


def _check_host_port(url: str, scheme: str) -> None:
    """``socket://`` and ``rfc2217://`` need HOST:PORT, or every reopen fails the same way."""
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        port = None
    if not parts.hostname or port is None:
        raise ValueError(f"expected {scheme}://HOST:PORT, got {url!r}")


def check_serial_url(url: str) -> None:
    """ValueError unless ``url`` is a device path or has a scheme pyserial handles, looked up
    the way ``serial.serial_for_url`` does (and, for ``socket://`` and ``rfc2217://``, unless
    it names HOST:PORT).  A device path is not checked: it may appear later (hot-plug), and
    the source retries it."""
    if "://" not in url:
        return
    scheme = url.split("://", 1)[0].lower()
    import serial

    for package in serial.protocol_handler_packages:
        try:
            importlib.import_module(package)
            importlib.import_module(f".protocol_{scheme}", package)
        except ImportError:
            continue
        if scheme in _HOST_PORT_SCHEMES:
            _check_host_port(url, scheme)
        return
    raise ValueError(f"unknown URL scheme {scheme!r}; known: "
                     f"{', '.join(s + '://' for s in serial_url_schemes())} or a device path")


def parse_source_url(url: str) -> tuple[str, dict[str, Any]]:
    """``sim``, ``replay:FILE``, ``mavlink:ENDPOINT``, ``uavtalk:TARGET``, ``xbee:URL``,
    ``zenoh:[VEHICLE@][ENDPOINT,…]`` or a
    pyserial URL → (source type, options); ValueError for a malformed one.  The options go
    through the source's ``CONFIG`` like a file's (a serial URL's scheme is checked there)."""
    if url in ("sim", "sim:"):
        return "sim", {}
    if url.startswith("replay:"):
        path = url[len("replay:"):]
        if not path:
            raise ValueError("replay: needs a file, e.g. replay:flight.aur")
        return "replay", {"path": path}
    if url.startswith("mavlink:"):
        endpoint = url[len("mavlink:"):]
        if not endpoint:
            raise ValueError("mavlink: needs an endpoint, e.g. mavlink:udpin:0.0.0.0:14551")
        return "mavlink", {"url": endpoint}
    if url.startswith("uavtalk:"):
        target = url[len("uavtalk:"):]
        if not target:
            raise ValueError("uavtalk: needs a flight controller, e.g. uavtalk:tcp:HOST:PORT "
                             "or uavtalk:/dev/ttyACM0,57600")
        return "uavtalk", {"url": target}
    if url.startswith("xbee:"):
        target = url[len("xbee:"):]
        if not target:
            raise ValueError("xbee: needs the ground module's port, e.g. xbee:/dev/ttyUSB0 "
                             "or xbee:socket://HOST:PORT")
        return "xbee", {"url": target}
    if url == "zenoh" or url.startswith("zenoh:"):
        return "zenoh", {"url": url}  # zenoh:[VEHICLE@][ENDPOINT,…], parsed by the source
    if not url:
        raise ValueError("empty source URL")
    return "serial", {"url": url}  # its scheme is checked with the url key (check_serial_url)


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
