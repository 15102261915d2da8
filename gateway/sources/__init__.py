"""Sources: where messages come from.  Each hands every message to a sink (normally
:meth:`gateway.app.Gateway.ingest`).

The contract, all of it public (the app uses nothing else):

* ``name``; ``CONFIG`` (a :class:`gateway.config.Schema`), ``from_config(options, name)`` and
  optionally ``default_name(options)``, which the configuration uses (the options arrive
  validated: the constructor does not check them again);
* ``attach(context)``, called before ``start`` with the gateway's
  :class:`gateway.backend.GatewayContext` (kept as ``context``);
* optionally ``use_loop(loop)``, called before ``start`` with the
  :class:`~gateway.io.ioloop.IoLoop` the gateway's sources share (a source started without
  one runs a loop of its own);
* ``start(sink)`` returns at once; the work happens on that loop (timers, a
  :class:`~gateway.io.port.PortEngine`, callbacks handed over with ``call_soon``) — a source
  starts no thread itself;
* ``request_stop()`` asks it to stop and returns at once (so many sources wind down
  together); ``stop(timeout)`` stops it and returns within about ``timeout``; both safe twice;
* ``done``, a ``threading.Event`` set once the source has nothing more to send (a replay's
  end, a one-flight simulation, or after ``stop``);
* ``stats()``, a dict of counters.

A subclass of :class:`Source` implements (the "must / might" list for source authors):

* **must**, one of: :meth:`Source.begin` — on the loop's thread, once: schedule timers
  (:class:`gateway.pacing.Pacer`, ``io_loop.call_every``) or start an engine on
  :attr:`Source.io_loop`, hand messages to :meth:`Source.emit` from the loop's thread, and
  call :meth:`Source.finish` when there is nothing more to send; what blocks (an open, a
  file read, a library's close) goes to ``io_loop.run_blocking`` and its result comes back on
  the loop.  Or, for code that can only block (a third-party source written for a thread of
  its own), :meth:`Source.run` — loop until the ``stop`` event it is given is set.  Such a
  ``run`` is a *long* blocking call of the loop (:meth:`IoLoop.run_blocking`): the loop's
  pool gives it a thread of its own, counted in the pool's ``long_running``, and ``emit`` is
  called from that thread;
* **might**: :meth:`Source.halt` — on the loop's thread, once, after ``request_stop``: cancel
  timers, close engines, then :meth:`Source.finish` (the default finishes at once, or, for a
  ``run`` source, when ``run`` returns); ``stats``, ``routes`` (messages it takes, through a
  :class:`SourceInbox`), ``attach``; or ``start``/``stop`` themselves, for a source whose
  work lives on another owner's loop (the MAVLink source on the hub's).

Every message carries ``origin`` = the source's name.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import threading
from collections.abc import Callable
from typing import Any, ClassVar
from urllib.parse import urlsplit

from gateway.backend import Backend, GatewayContext, Routes
from gateway.io.ioloop import BlockingCall, IoLoop

log = logging.getLogger(__name__)

Sink = Callable[[Any], Any]


class Source:
    """Base class: a source whose work runs on an I/O loop (see the module docstring)."""

    NAME: ClassVar[str] = "source"
    CONFIG: ClassVar[Any] = None

    def __init__(self, name: str | None = None) -> None:
        self.name = name or self.NAME
        self.context = GatewayContext()
        self.done = threading.Event()
        self._stop = threading.Event()  # what run() is given; set by request_stop()
        self._sink: Sink | None = None
        self._loop: IoLoop | None = None
        self._own_loop = False
        self._halted = False
        self._run_call: BlockingCall | None = None

    @classmethod
    def from_config(cls, options: dict[str, Any], name: str | None = None) -> Source:
        """An instance from options the class's ``CONFIG`` has already validated."""
        return cls(name=name, **options)

    def routes(self) -> Routes:
        """Gateway messages this source takes (none by default): a source that also sends
        (an XBee ground link sends the pilot's commands up) routes them like a backend; the
        gateway hands them to it through a :class:`SourceInbox`."""
        return Routes()

    def attach(self, context: GatewayContext) -> None:
        """Remember the gateway's context (called before :meth:`start`); a source that must
        tell this gateway's own publications from others' reads ``context.own_ids``."""
        self.context = context

    def use_loop(self, loop: IoLoop) -> None:
        """Run on ``loop`` (shared with the gateway's other sources; its owner starts and
        stops it) instead of a loop of the source's own; before :meth:`start`."""
        if self._sink is not None:
            raise RuntimeError(f"source {self.name}: use_loop() after start()")
        self._loop = loop
        self._own_loop = False

    @property
    def io_loop(self) -> IoLoop | None:
        """The loop the source runs on (None before :meth:`start` unless one was given)."""
        return self._loop

    @property
    def running(self) -> bool:
        """Started and not done (a source retrying its port is running)."""
        return self._sink is not None and not self.done.is_set()

    def start(self, sink: Sink) -> None:
        """Begin delivering messages to ``sink``; returns at once; a second call does
        nothing."""
        if self._sink is not None:
            return
        self._sink = sink
        loop = self._loop
        if loop is None:
            loop = self._loop = IoLoop(f"source-{self.name}")
            self._own_loop = True
            loop.start()
        loop.call_soon(self._begin)

    def _begin(self) -> None:
        if self._stop.is_set():
            self._halt()
            return
        try:
            self.begin()
        except Exception:
            log.exception("source %s failed to start", self.name)
            self.finish()

    def begin(self) -> None:
        """Start the work, on the loop's thread (see the module docstring).  The default
        runs :meth:`run` as a long blocking call of the loop."""
        loop = self._loop
        assert loop is not None
        self._run_call = loop.run_blocking(self._main, name=f"source-{self.name}", long=True)

    def _main(self) -> None:
        try:
            self.run(self._stop)
        except Exception:
            log.exception("source %s failed", self.name)
        finally:
            self.finish()

    def run(self, stop: threading.Event) -> None:
        """A blocking source's loop; return when ``stop`` is set (or when there is nothing
        left).  Only for code that cannot work on the loop: see :meth:`begin`."""
        raise NotImplementedError(f"source {self.name}: implement begin() or run()")

    def halt(self) -> None:
        """Stop the work, on the loop's thread, once; :meth:`finish` when it has wound down
        (the default: at once, or when a blocking :meth:`run` returns)."""
        if self._run_call is None:
            self.finish()

    def _halt(self) -> None:
        if self._halted:
            return
        self._halted = True
        try:
            self.halt()
        except Exception:
            log.exception("source %s failed to stop", self.name)
            self.finish()

    def finish(self) -> None:
        """Say that the source has nothing more to send (sets :attr:`done`); safe twice."""
        self.done.set()

    def emit(self, msg: Any) -> None:
        """Hand one message to the sink (from the loop's thread, or ``run``'s)."""
        sink = self._sink
        if sink is not None:
            sink(msg)

    @property
    def stop_requested(self) -> bool:
        return self._stop.is_set()

    def request_stop(self) -> None:
        """Ask the source to stop, without waiting for it; safe twice."""
        if self._stop.is_set():
            return
        self._stop.set()
        loop = self._loop
        if self._sink is None or loop is None:
            return
        if loop.in_loop_thread or not loop.alive:
            self._halt()
        else:
            loop.call_soon(self._halt)

    def stop(self, timeout: float = 1.0) -> None:
        """Stop and wait up to ``timeout`` for the source to wind down; safe twice."""
        self.request_stop()
        loop = self._loop
        if self._sink is None:
            self.finish()  # never started: nothing more will come
        elif loop is not None and not loop.in_loop_thread and not self.done.wait(timeout):
            log.warning("source %s did not stop within %.1f s", self.name, timeout)
        if (self._own_loop and loop is not None and not loop.in_loop_thread
                and loop.stop(0.2)):
            loop.close()

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
