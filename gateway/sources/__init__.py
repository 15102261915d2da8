"""Sources: where messages come from.  Each hands every message to a sink (normally
:meth:`gateway.app.Gateway.ingest`).

The contract, all of it public (the app uses nothing else):

* ``name``; ``OPTIONS`` (a :class:`gateway.options.Options` dataclass, its options declared
  once; the schema ``CONFIG`` is derived from it), ``from_config(options, name)`` (default:
  ``cls(OPTIONS.from_table(options), name=name)``) and ``default_name(options)`` (default:
  ``NAME_FORMAT`` over the options), which the configuration uses;
* optionally ``default_vehicle(options)``: its vehicle's name when neither its table nor
  ``--source NAME=URL`` gives one and the source is unnamed (default: derived from its name);
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
  call :meth:`Source.finish` when there is nothing more to send (what one read decoded may go
  as one list to :meth:`Source.emit_batch`); what blocks (an open, a
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

Every message carries ``origin`` = the source's name and ``vehicle`` = the source's
:attr:`Source.vehicle` (set by the gateway from its configuration before ``start``; derived
from the name until then) — or, for a source that hears several systems, one vehicle name per
system (:func:`gateway.vehicles.system_vehicle`).  A message a source leaves without a vehicle
gets the source's at :meth:`gateway.app.Gateway.ingest`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from typing import Any, ClassVar

from gateway import registry, vehicles
from gateway.backend import Backend, Plugin, Routes, build
from gateway.io.endpoints import check_serial_port, is_device
from gateway.io.ioloop import BlockingCall, IoLoop

log = logging.getLogger(__name__)

Sink = Callable[[Any], Any]


class Source(Plugin):
    """Base class: a source whose work runs on an I/O loop (see the module docstring)."""

    NAME: ClassVar[str] = "source"
    #: its name when its table gives none: ``str.format`` over its validated options, e.g.
    #: ``"uavtalk:{url}"`` (empty: the type's name); a source may override :meth:`default_name`
    NAME_FORMAT: ClassVar[str] = ""
    #: True for a source that yields one vehicle per system it hears (its :attr:`vehicle` is
    #: then only the stem of their names, ``<vehicle>-<id>``, or unused)
    YIELDS_SYSTEMS: ClassVar[bool] = False

    @classmethod
    def default_name(cls, options: dict[str, Any]) -> str | None:
        """An instance's name from its validated options (None: the type's name)."""
        return cls.NAME_FORMAT.format(**options) if cls.NAME_FORMAT else None

    @classmethod
    def works_alone(cls, options: dict[str, Any]) -> bool:
        """Whether a run of this source with these validated options has a job with no
        backend and no recording (a MAVLink source routing its vehicle to more endpoints)."""
        return False

    def __init__(self, name: str | None = None) -> None:
        super().__init__(name)
        self.done = threading.Event()
        self._stop = threading.Event()  # what run() is given; set by request_stop()
        self._sink: Sink | None = None
        #: takes a list of messages at once (the gateway's :meth:`~gateway.app.Gateway.
        #: ingest_batch`, set before :meth:`start`); None: :meth:`emit_batch` emits each
        self.batch_sink: Callable[[list[Any]], Any] | None = None
        self._loop: IoLoop | None = None
        self._own_loop = False
        self._halted = False
        self._run_call: BlockingCall | None = None
        self._vehicle = ""
        #: the MAVLink system id configured for this source's vehicle (None: assigned)
        self.mavlink_sysid: int | None = None

    @property
    def vehicle(self) -> str:
        """The name of the vehicle this source hears (for a source of several systems: the
        stem of their names)."""
        return self._vehicle or vehicles.derive_name(self.name, fallback=self.NAME)

    @vehicle.setter
    def vehicle(self, name: str) -> None:
        self._vehicle = vehicles.check_name(name)
        decoder = getattr(self, "decoder", None)
        if hasattr(decoder, "vehicle"):  # a wire decoder stamps it on every message
            decoder.vehicle = self._vehicle  # type: ignore[union-attr]

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

    def emit_batch(self, msgs: list[Any]) -> None:
        """Hand what one read decoded to the sink at once (in order): the gateway dispatches
        it as one batch, each backend's loop woken once for it."""
        if self._sink is None or not msgs:
            return
        batch = self.batch_sink
        if batch is not None:
            batch(msgs)
        else:
            for msg in msgs:
                self.emit(msg)

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
