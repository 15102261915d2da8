"""``aurora-gateway``: run the gateway, and the tools around it (decode, simulate, record,
replay)."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import signal
import sys
import threading
import traceback
from collections.abc import Sequence
from typing import Any, NoReturn

from gateway import __version__, config, recording, registry
from gateway.app import Gateway
from gateway.backoff import Backoff
from gateway.config import ConfigError, GatewayConfig
from gateway.sources import parse_source_url

log = logging.getLogger("aurora-gateway")

EXIT_USAGE = 2


# -- option groups -------------------------------------------------------------------------------

def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"expected a number ≥ 0, got {text!r}")
    return v


_warned: set[str] = set()


def _backend_classes() -> dict[str, Any]:
    """Every backend class that imports; a broken plug-in is reported once and left out."""
    out = {}
    for name in registry.backend_names():
        try:
            out[name] = registry.load(registry.BACKEND_GROUP, name)
        except registry.RegistryError as exc:
            if name not in _warned:
                _warned.add(name)
                log.warning("%s", exc)
    return out


def _add_gateway_options(p: argparse.ArgumentParser, *, sources: bool = True,
                         backend_flags: bool = True) -> None:
    p.add_argument("--config", "-c", metavar="FILE",
                   help="TOML configuration (default: the embedded one — the simulated "
                        "flight through every backend on loopback)")
    if sources:
        p.add_argument("--source", "-s", action="append", metavar="URL",
                       help="'sim', 'replay:FILE', 'mavlink:ENDPOINT' (a MAVLink vehicle, "
                            "e.g. mavlink:udpin:0.0.0.0:14551), 'zenoh:[VEHICLE@]ENDPOINT' "
                            "(another gateway's frames over Zenoh) or a pyserial URL "
                            "(/dev/ttyUSB0, loop://, socket://host:port, rfc2217://host:port); "
                            "repeatable; replaces the configured sources")
        p.add_argument("--baud", type=int, metavar="N", help="baud rate of serial sources")
        p.add_argument("--sim-speed", type=_positive, metavar="N",
                       help="run the simulated flight N times faster (0 = flat out)")
    p.add_argument("--record", metavar="FILE", help="append every received frame to FILE")
    p.add_argument("--disable", action="append", default=[], metavar="BACKEND",
                   help="leave this backend out (repeatable)")
    p.add_argument("--status-interval", type=_positive, metavar="S",
                   help="seconds between status lines on stderr (0 = none)")
    p.add_argument("--link-timeout", type=_positive, metavar="S",
                   help="silence after which a source's link is reported down (default 3)")
    p.add_argument("--duration", type=_positive, metavar="S", help="stop after S seconds")
    p.add_argument("--log-level", choices=("debug", "info", "warning", "error"))
    if not backend_flags:
        return
    for cls in _backend_classes().values():
        add = getattr(cls, "add_cli_arguments", None)
        if add is not None:
            add(p)
    p.set_defaults(backend_flags=True)  # config_from_args: this parser has the backends' flags


class _Parser(argparse.ArgumentParser):
    """argparse, except that a usage error is one line naming the flag (exit 2), like a bad
    configuration key; ``--help`` still prints the whole usage.  Subcommand parsers inherit
    this class."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _add_plugin_commands(sub: Any, only: str | None) -> None:
    """Subcommands from the ``aurora_gateway.commands`` entry points (``listen``, ``hc12``).

    Each is a function ``add_command(subparsers)`` that adds its parser and sets
    ``handler``.  Only ``only`` is imported when given (a command of its own), so ``decode``
    does not pay for importing Zenoh; None imports them all (for ``--help``)."""
    for name in registry.names(registry.COMMAND_GROUP):
        if only is not None and name != only:
            continue
        try:
            add = registry.load(registry.COMMAND_GROUP, name)
        except registry.RegistryError as exc:
            log.warning("%s", exc)
            continue
        add(sub)


def build_parser(backend_flags: bool = True,
                 plugin_command: str | None = None) -> argparse.ArgumentParser:
    """The whole command line.  ``backend_flags`` False leaves the backends' own flags out of
    ``run`` and ``replay``, which spares importing every backend (pymavlink's dialect alone
    takes a third of a second) for commands that have no backends.  ``plugin_command``: see
    :func:`_add_plugin_commands` ("" adds none)."""
    parser = _Parser(
        prog="aurora-gateway",
        description="Aurora telemetry gateway: takes the rocket's frames in and fans them out "
                    "to every configured backend.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    run = sub.add_parser("run", help="run the gateway (default: simulated flight, every "
                         "backend, loopback)")
    _add_gateway_options(run, backend_flags=backend_flags)

    dec = sub.add_parser("decode", help="print the frames of a capture or recording as JSON "
                         "lines")
    dec.add_argument("file", nargs="?", default="-", help="raw capture or recording; - = stdin")

    sim = sub.add_parser("simulate", help="write the simulated flight as wire frames to a port")
    sim.add_argument("--out", "-o", required=True, metavar="URL", help="pyserial port or URL")
    sim.add_argument("--baud", type=int, default=115200, metavar="N")
    sim.add_argument("--speed", type=_positive, default=1.0, metavar="N",
                     help="compress time N-fold (0 = flat out)")
    sim.add_argument("--rate-hz", type=float, default=10.0, metavar="HZ")
    sim.add_argument("--status-hz", type=float, default=1.0, metavar="HZ")
    sim.add_argument("--revision", type=int, choices=(36, 64), default=64)
    sim.add_argument("--cycles", type=int, default=0, metavar="N", help="flights; 0 = for ever")
    sim.add_argument("--log-level", choices=("debug", "info", "warning", "error"))

    rec = sub.add_parser("record", help="record what the sources receive, with no backends")
    rec.add_argument("file", help="recording to append to")
    rec.add_argument("--source", "-s", action="append", metavar="URL", default=None)
    rec.add_argument("--baud", type=int, metavar="N")
    rec.add_argument("--sim-speed", type=_positive, metavar="N")
    rec.add_argument("--duration", type=_positive, metavar="S")
    rec.add_argument("--status-interval", type=_positive, metavar="S")
    rec.add_argument("--log-level", choices=("debug", "info", "warning", "error"))

    rep = sub.add_parser("replay", help="run the gateway with a recording as its source")
    rep.add_argument("file", help="recording")
    rep.add_argument("--speed", type=_positive, default=1.0, metavar="N",
                     help="N times real time (0 = flat out)")
    rep.add_argument("--loop", action="store_true", help="start again at the end")
    _add_gateway_options(rep, sources=False, backend_flags=backend_flags)
    if plugin_command != "":
        _add_plugin_commands(sub, plugin_command)
    return parser


# -- configuration from flags --------------------------------------------------------------------

def _sources_from_urls(urls: Sequence[str], baud: int | None) -> list[config.Part]:
    parts = []
    for i, url in enumerate(urls):
        try:
            kind, opts = parse_source_url(url)
        except ValueError as exc:
            raise ConfigError(f"--source {url!r}: {exc}") from None
        if kind == "serial" and baud is not None:
            opts["baudrate"] = baud
        parts.append(config.make_source(kind, opts, None, f"--source[{i}]"))
    return parts


def config_from_args(args: argparse.Namespace) -> GatewayConfig:
    """The configuration ``run``/``replay``/``record`` use: file or embedded default, then
    flags on top."""
    cfg = config.load(args.config) if getattr(args, "config", None) else None
    if cfg is None:
        cfg = config.embedded_default()
    if getattr(args, "source", None):
        cfg.sources = _sources_from_urls(args.source, getattr(args, "baud", None))
    elif getattr(args, "baud", None) is not None:
        for i, p in enumerate(cfg.sources):
            if p.type == "serial":
                cfg.sources[i] = config.make_source("serial", {**p.options, "baudrate": args.baud},
                                                    p.name, f"sources[{i}]")
    if getattr(args, "sim_speed", None) is not None:
        for i, p in enumerate(cfg.sources):
            if p.type == "sim":
                cfg.sources[i] = config.make_source("sim", {**p.options, "speed": args.sim_speed},
                                                    p.name, f"sources[{i}]")
    g = cfg.gateway
    if getattr(args, "record", None):
        g["record"] = args.record
    if getattr(args, "status_interval", None) is not None:
        g["status_interval_s"] = args.status_interval
    if getattr(args, "link_timeout", None) is not None:
        if args.link_timeout <= 0:
            raise ConfigError("--link-timeout: expected a number > 0")
        g["link_timeout_s"] = args.link_timeout
    if getattr(args, "log_level", None):
        g["log_level"] = args.log_level
    # Backend flags: each backend turns its own flags into options (and is enabled by them).
    # Only commands built with _add_gateway_options have them (`record` has no backends).
    by_name = {p.name: p for p in cfg.backends}
    with_flags = _backend_classes() if getattr(args, "backend_flags", False) else {}
    for name, cls in with_flags.items():
        opts_fn = getattr(cls, "cli_options", None)
        opts = opts_fn(args) if opts_fn is not None else None
        if opts is None:
            continue
        current = by_name.get(name)
        merged = {**(current.options if current else {}), **opts}
        part = config.make_backend(current.type if current else name, merged, name,
                                   f"backends.{name}")
        if current is None:
            cfg.backends.append(part)
        else:
            cfg.backends[cfg.backends.index(current)] = part
        by_name[name] = part
    known = set(registry.backend_names()) | set(by_name)
    for name in getattr(args, "disable", []) or []:
        if name not in known:
            raise ConfigError(f"--disable {name}: no such backend; "
                              f"available: {', '.join(sorted(known))}")
        cfg.backends = [p for p in cfg.backends if p.name != name]
    return cfg


# -- commands ----------------------------------------------------------------------------------

class _Stopper:
    """SIGINT/SIGTERM set an event instead of raising in the middle of something."""

    def __init__(self, event: threading.Event) -> None:
        self.event = event
        self.signal: int | None = None
        self._old: dict[int, Any] = {}

    def __enter__(self) -> _Stopper:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum: int, frame: Any) -> None:
        self.signal = signum
        self.event.set()

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)


def _setup_logging(level: str | None) -> None:
    logging.basicConfig(level=getattr(logging, (level or "info").upper()), stream=sys.stderr,
                        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s")


def _report(summary: dict[str, Any]) -> None:
    drops = []
    for name, st in summary["backends"].items():
        # A backend's own per-reason counters say most; else its total; else what the
        # dispatcher saw it return.  Hooks that raised ("failed") are reported on top.
        counts = {k: v for k, v in st.items() if isinstance(v, int) and v}
        dropped = {k: v for k, v in counts.items() if k.startswith("dropped_")}
        if not dropped:
            dropped = ({"dropped": counts["dropped"]} if "dropped" in counts else
                       {k: v for k, v in counts.items() if k in ("queue-full", "not-ready")})
        if "failed" in counts:
            dropped["failed"] = counts["failed"]
        if dropped:
            drops.append(f"{name} " + " ".join(f"{k}={v}" for k, v in sorted(dropped.items())))
    ins = summary["messages_in"]
    line = (f"stopped after {summary['uptime_s']:.1f} s: {sum(ins.values())} messages in "
            f"({', '.join(f'{k} {v}' for k, v in sorted(ins.items())) or 'none'})")
    if summary.get("recorded") is not None:
        line += f"; {summary['recorded']} frames recorded"
    print(line, file=sys.stderr)
    print("dropped: " + ("; ".join(drops) if drops else "nothing"), file=sys.stderr)


def run_gateway(cfg: GatewayConfig, duration_s: float | None = None) -> int:
    """Start everything, run until a signal, the duration, or the sources' end; stop."""
    gw = Gateway(cfg)
    with _Stopper(gw.stop_event):
        failures = gw.start()
        for name, err in failures:
            print(f"aurora-gateway: backend {name} did not start: {err}", file=sys.stderr)
        names = ", ".join(p.name for p in cfg.backends) or "none"
        srcs = ", ".join(s.name for s in gw.sources) or "none"
        print(f"aurora-gateway {__version__}: sources {srcs}; backends {names}", file=sys.stderr)
        try:
            gw.run(duration_s)
        finally:
            summary = gw.stop()
    _report(summary)
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    _setup_logging(cfg.gateway["log_level"])
    return run_gateway(cfg, args.duration)


def cmd_replay(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    opts = {"path": args.file, "speed": args.speed, "loop": args.loop}
    cfg.sources = [config.make_source("replay", opts, None, "replay")]
    _setup_logging(cfg.gateway["log_level"])
    return run_gateway(cfg, args.duration)


def cmd_record(args: argparse.Namespace) -> int:
    args.config = None
    cfg = config_from_args(args)
    cfg.backends = []
    cfg.gateway["record"] = args.file
    _setup_logging(cfg.gateway["log_level"])
    return run_gateway(cfg, args.duration)


def _json_safe(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in d.items()}


def cmd_decode(args: argparse.Namespace) -> int:
    from gateway.wire import Decoder, to_wire_dict

    dec = Decoder()
    out = sys.stdout
    if args.file == "-":
        stream = sys.stdin.buffer
        close = False
    else:
        try:
            stream = open(args.file, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            print(f"aurora-gateway: decode: cannot open {args.file}: {exc.strerror}",
                  file=sys.stderr)
            return EXIT_USAGE
        close = True
    try:
        head = stream.read(len(recording.MAGIC))
        if head == recording.MAGIC:
            data = head + stream.read()
            stats = recording.ReadStats()
            try:
                recording._check_header(data, args.file)
            except recording.RecordingError as exc:
                print(f"aurora-gateway: decode: {exc}", file=sys.stderr)
                return EXIT_USAGE
            for _, t, frame in recording.scan(data, stats):
                for msg in dec.feed(frame):
                    out.write(json.dumps({"rx_time": t, **_json_safe(to_wire_dict(msg))}) + "\n")
            if stats.torn_tail_bytes or stats.corrupt_skips:
                print(f"recording: {stats.records} records, torn tail {stats.torn_tail_bytes} "
                      f"bytes, {stats.corrupt_skips} corrupt stretches skipped", file=sys.stderr)
        else:
            chunk = head
            while chunk:
                for msg in dec.feed(chunk):
                    out.write(json.dumps(_json_safe(to_wire_dict(msg))) + "\n")
                chunk = stream.read1(65536) if hasattr(stream, "read1") else stream.read(65536)
            for msg in dec.flush():
                out.write(json.dumps(_json_safe(to_wire_dict(msg))) + "\n")
        out.flush()
    except BrokenPipeError:
        return 0
    finally:
        if close:
            stream.close()
    s = dec.stats
    print(f"decoded {s.frames} frames from {s.bytes_in} bytes; crc failures {s.crc_failures}, "
          f"bytes skipped {s.bytes_skipped}, unknown types {s.unknown_types}, "
          f"bad lengths {s.bad_lengths}", file=sys.stderr)
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from gateway.flight import FlightModel, FlightProfile
    from gateway.pacing import paced
    from gateway.sources.sim import flight_frames
    from gateway.transport import TransportError, open_serial

    _setup_logging(args.log_level)
    if args.rate_hz <= 0:
        raise ConfigError(f"--rate-hz: expected a number > 0, got {args.rate_hz}")
    if args.cycles < 0:
        raise ConfigError(f"--cycles: expected an integer ≥ 0, got {args.cycles}")
    model = FlightModel(FlightProfile(revision=args.revision))
    stop = threading.Event()
    sent = errors = 0
    port = None
    backoff = Backoff(0.05, 2.0)
    with _Stopper(stop):
        frames = paced(flight_frames(model, args.rate_hz, args.status_hz, args.cycles),
                       args.speed, stop)
        for _, frame in frames:
            while port is None and not stop.is_set():
                try:
                    port = open_serial(args.out, args.baud, timeout=0.1)
                except TransportError as exc:
                    log.warning("%s; retrying", exc)
                    stop.wait(backoff.next())
            if port is None:
                break
            try:
                port.write(frame)
                sent += 1
            except Exception as exc:
                errors += 1
                log.warning("write to %s failed (%s); reopening", args.out, exc)
                port.close()
                port = None
        if port is not None:
            try:
                port.flush()
            finally:
                port.close()
    print(f"simulate: {sent} frames written to {args.out}, {errors} write errors",
          file=sys.stderr)
    return 0


COMMANDS = {"run": cmd_run, "decode": cmd_decode, "simulate": cmd_simulate,
            "record": cmd_record, "replay": cmd_replay}


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or (argv[0].startswith("-") and argv[0] not in ("-h", "--help", "--version")):
        argv = ["run", *argv]  # the default command: `aurora-gateway --duration 5` runs
    first = argv[0]
    if first in COMMANDS:
        plugin: str | None = ""
    elif first in registry.names(registry.COMMAND_GROUP):
        plugin = first
    else:
        plugin = None  # --help, --version or a typo: list every command
    parser = build_parser(backend_flags=first in ("run", "replay"), plugin_command=plugin)
    args = parser.parse_args(argv)
    handler = getattr(args, "handler", None) or COMMANDS[args.command]
    try:
        return handler(args)
    except (ConfigError, recording.RecordingError) as exc:
        print(f"aurora-gateway: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130


def console_main() -> NoReturn:
    """The ``aurora-gateway`` command: :func:`main`, then leave without interpreter teardown.

    Zenoh's Rust runtime keeps native threads after its sessions close; if one of them needs
    the GIL while the interpreter finalizes (dropping a Python callback a peer's query kept
    alive, say), CPython ends it with ``pthread_exit`` and the unwind through Rust frames
    aborts the process ("FATAL: exception not rethrown", exit -6) after a clean stop.  Every
    command has closed its sessions, ports and recordings by the time ``main`` returns, so the
    process flushes its standard streams and exits with ``main``'s status directly.
    """
    code = 1
    try:
        code = main()
    except SystemExit as exc:  # argparse's --help/--version and usage errors
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
    except BaseException:
        traceback.print_exc()  # os._exit below would otherwise swallow it
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):  # a closed pipe
                stream.flush()
        os._exit(code)


if __name__ == "__main__":
    console_main()
