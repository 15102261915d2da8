"""``aurora-gateway monitor``: a live terminal view of the vehicles, their links and counters.

With ``--source`` (the forms ``run`` takes) the sources run in this process, in a gateway
with no backends, and the wire decoders' counters (frames, CRC errors) are shown.  Without
one it follows the gateway running on this machine over Zenoh (``make run``: a peer on
``tcp/127.0.0.1:7450``), subscribed to its JSON documents, which carry every kind it
publishes (state, status, position, battery, link quality).  A gateway publishes no counters
of its backends on Zenoh, so the table then shows the Zenoh source's own (received, lost,
dropped).

On a terminal: a full-screen view (``rich``), refreshed every ``--refresh`` seconds (default
0.25): a row per vehicle, the detail of the selected one (↑/↓, k/j or tab/shift-tab select
another), q or Ctrl-C quits.  Otherwise (a pipe, a file): one ``key=value`` line per vehicle
every ``--refresh`` seconds (default 1), each starting ``vehicle=NAME``, no escape codes.
``--speak`` says state changes and the apogee altitude through ``espeak-ng`` (see
:class:`gateway.commands.live.Speaker`; with several vehicles, prefixed by the vehicle's
name).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import select
import shutil
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any, TextIO

from gateway import config, vehicles
from gateway.app import Gateway
from gateway.backend import Backend, Routes
from gateway.commands import cli
from gateway.commands.live import (
    EndpointRow,
    LiveState,
    Speaker,
    endpoint_row,
    plain_lines,
    render,
)
from gateway.config import ConfigError
from gateway.model import MESSAGE_TYPES, GatewayStats
from gateway.signals import Stopper

SPEECH_PROGRAM = "espeak-ng"
TTY_REFRESH_S = 0.25
PLAIN_REFRESH_S = 1.0
CHECK_S = 0.05  # how often links are checked and keys read


class LiveFeed(Backend):
    """A backend that hands every message to a :class:`LiveState` (never blocks)."""

    NAME = "monitor"

    def __init__(self, state: LiveState, clock: Any = time.monotonic) -> None:
        super().__init__()
        self.state = state
        self._clock = clock

    def routes(self) -> Routes:
        r = Routes()
        for cls in MESSAGE_TYPES:
            r.on(cls, self._take)
        return r.on(GatewayStats, self._remote)

    def _remote(self, msg: GatewayStats) -> None:
        self.state.set_remote(msg.gateway, msg.backends, msg.sources)

    def _take(self, msg: Any) -> None:
        self.state.feed(msg, self._clock())


class _NoteHandler(logging.Handler):
    """Log records into the view's notes (stderr would tear a full-screen view)."""

    def __init__(self, state: LiveState) -> None:
        super().__init__(logging.INFO)
        self.state = state

    def emit(self, record: logging.LogRecord) -> None:
        self.state.note(f"{record.levelname.lower()}: {record.getMessage()}")


def add_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``monitor`` to the ``aurora-gateway`` subcommands."""
    p = subparsers.add_parser(
        "monitor", help="live view of the vehicles, links and counters (full screen on a "
                        "terminal, status lines otherwise)",
        description="A live view of the vehicles (a row each: state, altitude, max altitude, "
                    "vertical speed, link, age; the selected one in detail: attitude, "
                    "position, battery, health), the links and counters. With --source the "
                    "sources run here (one vehicle each: --source NAME=URL); without, it "
                    "follows the gateway running on this machine over Zenoh "
                    "(tcp/127.0.0.1:7450). On a terminal: full screen; up/down (or k/j, "
                    "tab/shift-tab) select the vehicle shown in detail, q or Ctrl-C quits. "
                    "Else one key=value line per vehicle per --refresh seconds, starting "
                    "vehicle=NAME.")
    cli.add_source_options(p)
    p.add_argument("--speak", action="store_true",
                   help=f"say state changes and the apogee altitude ({SPEECH_PROGRAM})")
    cli.key_flag(p, "--refresh", cli.CLI_KEYS.keys["duration"],
                  f"seconds between redraws (default {TTY_REFRESH_S} on a terminal, "
                  f"{PLAIN_REFRESH_S} for status lines)", metavar="S")
    cli.key_flag(p, "--duration", cli.CLI_KEYS.keys["duration"], "stop after S seconds",
                  metavar="S")
    cli.key_flag(p, "--link-timeout", cli.gateway_key("link_timeout_s"),
                  "silence after which a source's link is reported down (default 3)",
                  metavar="S")
    cli.key_flag(p, "--log-level", cli.gateway_key("log_level"), "logging level",
                  metavar="LEVEL")
    p.set_defaults(handler=run_monitor)
    return p


def _config(args: argparse.Namespace) -> config.GatewayConfig:
    args.config = None
    cfg = cli.config_from_args(args, backends=False)
    if not args.source:
        cfg.sources = [config.make_source("zenoh", {"keys": "json"}, "zenoh", "monitor")]
    return cfg


def _sample(gw: Gateway, state: LiveState, now: float) -> None:
    """Counters of the sources (their wire decoders') and backends into the state."""
    frames = crc = 0
    rows: list[EndpointRow] = []
    for src in gw.sources:
        st = src.stats()
        dec = getattr(src, "decoder", None)
        ds = getattr(dec, "stats", None)
        if ds is not None and ds.frames:
            frames += ds.frames
            crc += ds.crc_failures
        else:
            n = st.get("received", st.get("messages", st.get("emitted", st.get("sent", 0))))
            frames += n if isinstance(n, int) else 0
            c = st.get("crc_failures", 0)
            crc += c if isinstance(c, int) else 0
        row = endpoint_row(src.name, st)
        if ds is not None and ds.frames:
            row = EndpointRow(row.name, ds.frames, row.sent, row.dropped, ds.crc_failures,
                              row.clients, row.link)
        if row.link is None:
            up = gw.monitor.is_up(getattr(src, "vehicle", "") or src.name)
            row = EndpointRow(row.name, row.received, row.sent, row.dropped, row.errors,
                              row.clients, up)
        rows.append(row)
        for ep_name, ep in (st.get("endpoints") or {}).items():  # MAVLink source endpoints
            if isinstance(ep, dict):
                rows.append(endpoint_row(f"  {ep_name}", ep))
    for name, st in gw.dispatcher.stats().items():
        if name != LiveFeed.NAME and isinstance(st, dict):
            rows.append(endpoint_row(name, st))
    state.set_counters(now, frames, crc)
    state.set_endpoints(rows)


@contextlib.contextmanager
def _keys(stream: TextIO) -> Iterator[int | None]:
    """The terminal in cbreak mode (keys arrive one at a time, Ctrl-C still signals); yields
    its descriptor, or None when ``stream`` is not a terminal."""
    try:
        fd = stream.fileno()
    except (AttributeError, OSError, ValueError):
        fd = -1
    if fd < 0 or not os.isatty(fd):
        yield None
        return
    import termios
    import tty

    old = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)
        yield fd
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, old)


#: Keys read on a terminal (cbreak mode) → what they do: q quits (None), the others move the
#: selection by that many rows.  Arrow keys arrive as escape sequences.
KEYS: dict[bytes, int | None] = {
    b"q": None, b"Q": None,
    b"\x1b[A": -1, b"\x1bOA": -1, b"k": -1, b"\x1b[Z": -1,  # up, shift-tab
    b"\x1b[B": 1, b"\x1bOB": 1, b"j": 1, b"\t": 1,  # down, tab
}


def read_keys(data: bytes) -> list[int | None]:
    """The actions of the keys in ``data`` (see :data:`KEYS`; others are ignored)."""
    out: list[int | None] = []
    i = 0
    while i < len(data):
        for size in (3, 1):
            key = data[i:i + size]
            if key in KEYS:
                out.append(KEYS[key])
                i += size
                break
        else:
            i += 1
    return out


def _handle_keys(fd: int, state: LiveState, timeout: float) -> str:
    """Wait up to ``timeout`` for keys and act on them: ``"quit"`` when q was pressed (or
    the terminal closed), ``"moved"`` when the selection moved, else ``""``."""
    ready, _, _ = select.select([fd], [], [], timeout)
    if not ready:
        return ""
    data = os.read(fd, 64)
    if not data:
        return "quit"
    moved = ""
    for action in read_keys(data):
        if action is None:
            return "quit"
        state.select(action)
        moved = "moved"
    return moved


def run_monitor(args: argparse.Namespace) -> int:
    """The command: see the module docstring."""
    refresh = cli.checked_flag(args, "refresh", "--refresh", cli.CLI_KEYS.keys["duration"])
    if refresh is not None and refresh <= 0:
        raise ConfigError("--refresh: must be more than 0 seconds")
    cfg = _config(args)
    duration = args.duration
    tty = sys.stdout.isatty()
    state = LiveState(cfg.gateway["link_timeout_s"])
    speaker = None
    warning = None
    if args.speak:
        program = shutil.which(SPEECH_PROGRAM)
        if program is None:
            warning = (f"aurora-gateway monitor: --speak: {SPEECH_PROGRAM} not found on PATH; "
                       "running without speech")
            print(warning, file=sys.stderr, flush=True)
            state.note(f"{SPEECH_PROGRAM} not found: no speech")
        else:
            speaker = Speaker(program)
            state.on_announce = speaker.say
    level = cfg.gateway["log_level"]
    if tty:
        logging.basicConfig(level=getattr(logging, str(level).upper(), logging.WARNING),
                            handlers=[_NoteHandler(state)], force=True)
    else:
        cli.setup_logging(level)
    gw = Gateway(cfg, status_out=sys.stderr)
    state.set_order(sv.vehicle for sv in gw.context.services.get(vehicles.SERVICE, ()))
    gw.dispatcher.add(LiveFeed(state))
    srcs = ", ".join(s.name for s in gw.sources)
    state.title = f"aurora-gateway monitor · {srcs}"
    stop = gw.stop_event
    with Stopper(stop) as stopper:
        failures = gw.start()
        for name, err in failures:
            state.note(f"backend {name} did not start: {err}")
        try:
            if tty:
                _run_tty(gw, state, stop, refresh or TTY_REFRESH_S, duration)
            else:
                _run_plain(gw, state, stop, refresh or PLAIN_REFRESH_S, duration, sys.stdout)
        finally:
            gw.stop()
            if speaker is not None:
                speaker.close()
    return stopper.status  # q, the duration, the sources' end: 0; Ctrl-C: 130


def _run_plain(gw: Gateway, state: LiveState, stop: threading.Event, refresh: float,
               duration: float | None, out: TextIO) -> None:
    start = time.monotonic()
    next_line = start + refresh
    while not stop.is_set():
        now = time.monotonic()
        if duration is not None and now - start >= duration:
            break
        gw.monitor.check()
        _sample(gw, state, now)
        if now >= next_line:
            try:
                out.write("".join(line + "\n" for line in plain_lines(state, now)))
                out.flush()
            except BrokenPipeError:
                return
            next_line = max(next_line + refresh, now)
        if gw.sources and all(s.done.is_set() for s in gw.sources):
            break
        stop.wait(CHECK_S)


def _run_tty(gw: Gateway, state: LiveState, stop: threading.Event, refresh: float,
             duration: float | None) -> None:
    from rich.console import Console
    from rich.live import Live

    console = Console()
    start = time.monotonic()
    now = start
    _sample(gw, state, now)
    with _keys(sys.stdin) as fd, Live(render(state, now), console=console, screen=True,
                                      auto_refresh=False, redirect_stdout=False,
                                      redirect_stderr=False) as live:
        next_draw = start
        while not stop.is_set():
            now = time.monotonic()
            if duration is not None and now - start >= duration:
                break
            gw.monitor.check()
            if gw.sources and all(s.done.is_set() for s in gw.sources):
                state.sources_done = True
            if now >= next_draw:
                _sample(gw, state, now)
                live.update(render(state, now), refresh=True)
                next_draw = max(next_draw + refresh, now)
            if fd is not None:
                keys = _handle_keys(fd, state, CHECK_S)
                if keys == "quit":
                    break
                if keys == "moved":  # show the newly selected vehicle at once
                    next_draw = time.monotonic()
            else:
                stop.wait(CHECK_S)
