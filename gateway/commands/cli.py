"""``aurora-gateway``: run the gateway, and the tools around it (decode, simulate, record,
replay).

Every flag that sets a configuration key is checked by that key's :class:`config.Key` — the
one a file's value goes through — whether or not anything uses it, and a bad value is one
line naming the flag and what is allowed, exit 2.  So is a bad file.  Ctrl-C at any point,
start-up and imports included, ends quietly with status 130 (130 = 128 + SIGINT), after a
running gateway's clean stop and stop report; SIGTERM stops the same way with 0.  The table:
:mod:`gateway.exits`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import sys
import threading
import traceback
from collections.abc import Sequence
from typing import Any, NamedTuple, NoReturn

from gateway import __version__, config, exits, logjson, registry, signals, vehicles
from gateway.app import Gateway
from gateway.config import ConfigError, GatewayConfig, GatewayOptions, Key, Schema
from gateway.flight_summary import summary_lines
from gateway.io.backoff import Backoff
from gateway.io.server import SERVER_KEYS
from gateway.options import Options, add_flag, options_of
from gateway.signals import Stopper
from gateway.sources import check_serial_url, parse_source_url

log = logging.getLogger("aurora-gateway")

EXIT_USAGE = exits.USAGE
EXIT_INTERRUPTED = exits.INTERRUPTED
EXIT_CODES_HELP = exits.HELP  # every command's --help ends with it (_Parser)

# -- flags that set configuration keys -------------------------------------------------------
# Declared with the keys they set (gateway.options): the gateway's own in
# config.GatewayOptions, each source's and backend's in its options class.  Each is checked by
# the key's own Key, named in errors as the flag.

#: (argparse dest, flag, key) of the [gateway] table's flags
GATEWAY_FLAGS = tuple((flag.dest, flag.name, key) for key, flag, _ in GatewayOptions.flags())
# simulate: (argparse dest, flag, key of the sim source)
SIMULATE_FLAGS = (
    ("rate_hz", "--rate-hz", "rate_hz"),
    ("status_hz", "--status-hz", "status_hz"),
    ("speed", "--speed", "speed"),
    ("revision", "--revision", "revision"),
    ("cycles", "--cycles", "cycles"),
)
# Flags of the command line only.
CLI_KEYS = Schema(
    duration=Key(float, None, "stop after S seconds", minimum=0, nullable=True),
    log_format=Key(str, "text", "log lines as text, or one JSON object a line (journald)",
                   choices=logjson.FORMATS),
)


class FlagScope(NamedTuple):
    """Whose flags ``run`` is built with: the source types and backends named (None: every
    installed one).  Each source's and backend's options module costs start-up time: a run
    that names its sources (``--source``) and backends (``--only``) needs only theirs
    (:func:`_narrow_scope`)."""

    sources: frozenset[str] | None = None
    backends: frozenset[str] | None = None


class _OutOfScope(Exception):
    """A narrowed parser met something it does not have: parse again with every flag."""



#: The compiled fast paths (pyproject's ext-modules), by what they speed up.
SPEEDUPS = {"MAVLink routing": "backends.mavlink._route_speedups",
            "recvmmsg/sendmmsg": "gateway.io._mmsg_speedups"}


def speedups_built() -> dict[str, bool]:
    """Which compiled fast paths this install has (each missing one's pure-Python path runs
    instead: the same behaviour, more CPU)."""
    import importlib.util
    return {what: importlib.util.find_spec(mod) is not None for what, mod in SPEEDUPS.items()}


class _VersionAction(argparse.Action):
    """``--version``: the version, and which compiled fast paths the install has."""

    def __init__(self, option_strings: Sequence[str], dest: str = argparse.SUPPRESS,
                 default: str = argparse.SUPPRESS, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=default,
                         help=help or "show the version and the compiled paths, and exit")

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        built = speedups_built()
        have = [w for w, ok in built.items() if ok]
        lacking = [w for w, ok in built.items() if not ok]
        line = f"{parser.prog} {__version__}"
        line += f"; compiled: {', '.join(have)}" if have else "; compiled: none"
        if lacking:
            line += f" (pure Python: {', '.join(lacking)})"
        sys.stdout.write(line + "\n")
        parser.exit()

def _narrow_scope(argv: Sequence[str]) -> FlagScope | None:
    """The flag scope ``run ARGS`` needs, read from the arguments: the source types of its
    ``--source`` URLs (or the embedded default's ``sim``) unless ``--config`` names a file,
    the backends of its ``--only``.  None when nothing narrows, or with ``--help`` (whose
    text lists every flag)."""
    if any(a == "-h" or a.startswith("--h") for a in argv):
        return None
    pre = _ScopedParser(add_help=False)
    pre.add_argument("--config", "-c")
    pre.add_argument("--source", "-s", action="append")
    pre.add_argument("--only", action="append")
    try:
        known, _ = pre.parse_known_args(argv)
    except _OutOfScope:
        return None
    return _scope_of(known)


def _scope_of(args: argparse.Namespace) -> FlagScope | None:
    """:func:`_narrow_scope` of parsed ``run`` arguments."""
    sources: frozenset[str] | None = None
    if args.config is None:
        installed = registry.source_names()
        types = set()
        for text in args.source or ["sim"]:
            head, _, rest = split_vehicle(text)[1].strip().partition(":")
            types.add(head if head in installed and not rest.startswith("//") else "serial")
        sources = frozenset(types)
    backends = frozenset(args.only) if args.only else None
    if sources is None and backends is None:
        return None
    return FlagScope(sources, backends)


def _parse_run(argv: list[str], scope: FlagScope) -> argparse.Namespace | None:
    """``run ARGS`` parsed by a parser with only ``scope``'s flags; None when that parser
    cannot (a flag outside the scope, a usage error) or reads them otherwise than the scope
    did: then the whole parser parses them, as it always did."""
    parser = build_parser(plugin_command="", command="run", scope=scope)
    try:
        args = parser.parse_args(argv)
    except _OutOfScope:
        return None
    return args if _scope_of(args) == scope else None


def _left_out_flag(argv: Sequence[str], only: Sequence[str]) -> str | None:
    """The error for a flag of a backend that ``--only`` leaves out (it would be ignored):
    one line naming the flag and the backend; None when there is no such flag."""
    given = {a.partition("=")[0] for a in argv if a.startswith("--")}
    for name, flags in _backend_flags().items():
        if name in only:
            continue
        probe = argparse.ArgumentParser(add_help=False)
        _add_backend_flags(probe, flags, None)
        for flag in sorted(given & set(probe._option_string_actions)):
            return f"{flag}: backend {name} is left out by --only"
    return None


def _source_key(type_name: str, key: str) -> Key:
    opts = registry.load_source_options(type_name)
    schema = opts.schema() if opts is not None else config.schema_of(
        registry.load(registry.SOURCE_GROUP, type_name))
    return schema.keys[key]


def gateway_key(key: str) -> Key:
    return config.GATEWAY_SCHEMA.keys[key]


def gateway_flag(p: Any, key: str) -> None:
    """Add the flag that sets ``[gateway]``'s ``key`` (declared by config.GatewayOptions)."""
    for name, flag, spec in GatewayOptions.flags():
        if name == key:
            add_flag(p, flag, spec)
            return
    raise KeyError(key)


def _source_options(types: frozenset[str] | None = None) -> dict[str, type[Options]]:
    """Source type → its options class (light modules: no source is imported); a source
    without one, or a broken plug-in (reported once), is left out.  ``types``: only these
    (:class:`FlagScope`); None: every installed one."""
    out = {}
    for name in registry.source_names():
        if types is not None and name not in types:
            continue
        try:
            opts = registry.load_source_options(name)
        except registry.RegistryError as exc:
            if name not in _warned:
                _warned.add(name)
                log.warning("%s", exc)
            continue
        if opts is not None:
            out[name] = opts
    return out


def key_flag(p: argparse.ArgumentParser, flag: str, key: Key, help: str, *,
              dest: str | None = None, metavar: str | None = None,
              aliases: Sequence[str] = (), required: bool = False) -> None:
    """A flag whose text becomes the value a file would hold; :func:`checked_flag` validates it
    with ``key`` (argparse converts nothing, so every error reads like a file's)."""
    kinds = key.kind if isinstance(key.kind, tuple) else (key.kind,)
    numeric = int in kinds or float in kinds
    if numeric or key.choices is not None:
        help = f"{help} ({key.describe()})"
    kwargs: dict[str, Any] = {"type": config.flag_value if numeric else str,
                              "metavar": metavar, "help": help, "required": required}
    if dest is not None:
        kwargs["dest"] = dest
    p.add_argument(flag, *aliases, **kwargs)


def checked_flag(args: argparse.Namespace, dest: str, flag: str, key: Key,
             sets: str = "") -> Any:
    """The flag's value checked by ``key``; None when the flag was not given."""
    value = getattr(args, dest, None)
    if value is None:
        return None
    return config.check_flag(flag, key, value, sets)


_warned: set[str] = set()


def source_flags() -> tuple[tuple[str, str, str, str], ...]:
    """(argparse dest, flag, source type, key) of every flag that sets a source's key (on
    every source of that type): derived from the source options classes."""
    return tuple((flag.dest, flag.name, type_name, key)
                 for type_name, opts in _source_options().items()
                 for key, flag, _ in opts.flags() if flag.sources)


def _backend_flags(names: frozenset[str] | None = None) -> dict[str, Any]:
    """Backend name → what adds its flags and reads them back (:func:`registry.load_flags`:
    a light module, so no backend is imported; else the class).  A broken plug-in is
    reported once and left out.  ``names``: only these (:class:`FlagScope`); None: every
    installed one."""
    out = {}
    for name in registry.backend_names():
        if names is not None and name not in names:
            continue
        try:
            out[name] = registry.load_flags(name)
        except registry.RegistryError as exc:
            if name not in _warned:
                _warned.add(name)
                log.warning("%s", exc)
    return out


def _add_gateway_options(p: argparse.ArgumentParser, *, sources: bool = True,
                         backend_flags: bool = True, scope: FlagScope | None = None) -> None:
    scope = FlagScope() if scope is None else scope
    p.add_argument("--config", "-c", metavar="FILE",
                   help="TOML configuration (default: the embedded one — the simulated "
                        "flight through every backend on loopback)")
    seen: set[str] = set()  # flags added, of fields two options classes share
    if sources:
        add_source_options(p, seen, scope.sources)
    gateway_flag(p, "record")
    gateway_flag(p, "record_dir")
    p.add_argument("--disable", action="append", default=[], metavar="BACKEND",
                   help="leave this backend out (repeatable)")
    p.add_argument("--only", action="append", default=[], metavar="BACKEND",
                   help="run only this backend (repeatable; with the configured or flag-set "
                        "options); the others are not even imported")
    _add_common_options(p)
    gateway_flag(p, "link_timeout_s")
    if not backend_flags:
        return
    for flags in _backend_flags(scope.backends).values():
        _add_backend_flags(p, flags, seen)
    # config_from_args: this parser has the backends' flags (those of flag_scope's)
    p.set_defaults(backend_flags=True, flag_scope=scope)


def _add_backend_flags(p: Any, flags: Any, seen: set[str] | None) -> None:
    """Add one backend's flags (see :func:`_backend_flags`)."""
    opts = flags if isinstance(flags, type) and issubclass(flags, Options) else \
        options_of(flags)
    if opts is not None:
        opts.add_cli_arguments(p, seen)
        return
    add = getattr(flags, "add_cli_arguments", None)
    if add is not None:
        add(p)


def add_source_options(p: argparse.ArgumentParser, seen: set[str] | None = None,
                       types: frozenset[str] | None = None) -> None:
    p.add_argument("--source", "-s", action="append", metavar="[NAME=]URL",
                   help="a vehicle's source, named NAME (a letter, then letters, digits, "
                        "'_' or '-'; default: derived from the URL): 'sim', 'replay:FILE', "
                        "'mavlink:ENDPOINT' (a MAVLink vehicle, "
                        "e.g. mavlink:udpin:0.0.0.0:14551), 'uavtalk:tcp:HOST:PORT' or "
                        "'uavtalk:DEVICE[,BAUD]' (a LibrePilot flight controller, the "
                        "gateway as its ground station), 'zenoh:[VEHICLE@]ENDPOINT' "
                        "(another gateway's frames over Zenoh) or a pyserial URL "
                        "(/dev/ttyUSB0, loop://, socket://host:port, rfc2217://host:port); "
                        "repeatable; replaces the configured sources")
    # each source type's flags (--baud, --sim-speed, --xbee-api), set on every source of it
    seen = set() if seen is None else seen
    for opts in _source_options(types).values():
        opts.add_cli_arguments(p, seen, sources=True)


def _add_common_options(p: argparse.ArgumentParser) -> None:
    gateway_flag(p, "status_interval_s")
    key_flag(p, "--duration", CLI_KEYS.keys["duration"], "stop after S seconds", metavar="S")
    gateway_flag(p, "log_level")
    key_flag(p, "--log-format", CLI_KEYS.keys["log_format"],
              "log lines as text (default), or one JSON object a line (journald)",
              metavar="FORMAT")


class _Parser(argparse.ArgumentParser):
    """argparse, except that a usage error is one line naming the flag (exit 2), like a bad
    configuration key; ``--help`` still prints the whole usage.  Subcommand parsers inherit
    this class."""

    _checking = False  # in add_argument

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: {message} (see {self.prog} --help)\n")

    def add_argument(self, *args: Any, **kwargs: Any) -> argparse.Action:
        self._checking = True
        try:
            return super().add_argument(*args, **kwargs)
        finally:
            self._checking = False

    def add_subparsers(self, **kwargs: Any) -> Any:
        self._checking = True
        try:
            return super().add_subparsers(**kwargs)
        finally:
            self._checking = False

    def _get_formatter(self) -> argparse.HelpFormatter:
        """argparse's formatter; that of add_argument (which checks a metavar against its
        nargs) and add_subparsers (the subcommands' prog: one short line) is given a width:
        the terminal's would import shutil (~2 ms of a start).  Help text gets the terminal's."""
        if self._checking:
            make: Any = self.formatter_class
            formatter: argparse.HelpFormatter = make(prog=self.prog, width=80)
            return formatter
        return super()._get_formatter()

    def format_help(self) -> str:
        """The usage, then the exit-status table every command shares (:mod:`gateway.exits`)."""
        return super().format_help().rstrip("\n") + "\n\n" + exits.HELP


class _ScopedParser(_Parser):
    """A parser built with a :class:`FlagScope` (and its subcommands' parsers): any error,
    an unknown flag among them, raises :class:`_OutOfScope` instead of exiting, so that the
    whole parser decides."""

    def error(self, message: str) -> NoReturn:
        raise _OutOfScope(message)


#: the parser every command uses (a standalone ``python -m backends.….cli`` too)
CommandParser = _Parser


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
            if only is not None and isinstance(exc, registry.MissingExtra):
                raise  # the command asked for needs an extra: named, exit 2 (_main)
            log.warning("%s", exc)
            continue
        add(sub)


def build_parser(backend_flags: bool = True,
                 plugin_command: str | None = None,
                 command: str | None = None,
                 scope: FlagScope | None = None) -> argparse.ArgumentParser:
    """The whole command line.  ``backend_flags`` False leaves the backends' own flags out of
    ``run`` and ``replay`` (they come from light modules, :func:`registry.load_flags`: no
    backend is imported either way).  ``plugin_command``: see :func:`_add_plugin_commands`
    ("" adds none).  ``command``: the built-in command about to run: only its parser gets its
    arguments (the others' flags, every source's and backend's options among them, cost
    start-up time and are never read); None builds them all (``--help``).  ``scope``: the
    sources and backends whose flags ``run`` gets (default: all)."""

    def full(name: str) -> bool:
        return command is None or command == name

    parser = (_Parser if scope is None else _ScopedParser)(
        prog="aurora-gateway",
        description="Aurora telemetry gateway: takes the rocket's frames in and fans them out "
                    "to every configured backend.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    run = sub.add_parser("run", help="run the gateway (default: simulated flight, every "
                         "backend, loopback)")
    if full("run"):
        _add_gateway_options(run, backend_flags=backend_flags, scope=scope)

    dec = sub.add_parser("decode", help="print the frames of a capture or recording (and its "
                         "other messages: positions, batteries …) as JSON lines")
    dec.add_argument("file", nargs="?", default="-", help="raw capture or recording; - = stdin")
    dec.add_argument("--vehicle", metavar="NAME",
                     help="a recording's frames of this vehicle only (default: every vehicle)")

    sim = sub.add_parser("simulate", help="write the simulated flight as wire frames to a port")
    if full("simulate"):
        key_flag(sim, "--out", _source_key("serial", "url"), "pyserial port or URL",
                  metavar="URL", aliases=("-o",), required=True)
        key_flag(sim, "--baud", _source_key("serial", "baudrate"), "baud rate (default 115200)",
                  metavar="N")
        sim_help = {"rate_hz": ("SM_UPDATE rate (default 10)", "HZ"),
                    "status_hz": ("STATUS rate; 0 = none (default 1)", "HZ"),
                    "speed": ("compress time N-fold; 0 = flat out (default 1)", "N"),
                    "revision": ("SM_UPDATE payload length (default 64)", "N"),
                    "cycles": ("flights; 0 = for ever (default)", "N")}
        for dest, flag, key in SIMULATE_FLAGS:
            text, metavar = sim_help[key]
            key_flag(sim, flag, _source_key("sim", key), text, dest=dest, metavar=metavar)
        gateway_flag(sim, "log_level")

    rec = sub.add_parser("record", help="record what the sources receive, with no backends",
                         description="Record what the sources receive, with no backends, every "
                         "vehicle into FILE with its vehicle and source names. "
                         "An Aurora message is recorded as its wire frame: the one it arrived "
                         "in, else the frame it encodes to (SM_UPDATE, STATUS and relayed "
                         "frames from a MAVLink or Zenoh source); every other kind (a MAVLink "
                         "vehicle's state, position, battery, RC channels, link statistics) as "
                         "a record of its fields.")
    if full("record"):
        rec.add_argument("file", help="recording to append to")
        add_source_options(rec)
        _add_common_options(rec)

    rep = sub.add_parser("replay", help="run the gateway with a recording as its source",
                         description="Run the gateway with a recording as its source: each "
                         "recorded vehicle comes back under its name (the frames of a version "
                         "1 recording, which name none, as the replay source's own vehicle).")
    if full("replay"):
        rep.add_argument("file", help="recording")
        key_flag(rep, "--speed", _source_key("replay", "speed"),
                  "N times real time; 0 = flat out (default 1)", metavar="N")
        rep.add_argument("--loop", action="store_true", help="start again at the end")
        _add_gateway_options(rep, sources=False, backend_flags=backend_flags)
    if plugin_command != "":
        _add_plugin_commands(sub, plugin_command)
    return parser


# -- configuration from flags --------------------------------------------------------------------

def split_vehicle(text: str) -> tuple[str | None, str]:
    """``NAME=URL`` → (NAME, URL); a URL alone → (None, URL).  What precedes the first ``=``
    is a name only when it has no ``:``, ``/`` or ``?`` (a pyserial URL's query has ``=``)."""
    head, sep, rest = text.partition("=")
    if sep and head and not any(c in head for c in ":/?,"):
        return head, rest
    return None, text


def _sources_from_urls(urls: Sequence[str]) -> list[config.Part]:
    parts = []
    given = []
    for i, text in enumerate(urls):
        name, url = split_vehicle(text)
        given.append(name is not None)
        try:
            if name is not None:
                vehicles.check_name(name)
            kind, opts = parse_source_url(url)
            if kind == "serial":
                check_serial_url(url)  # the url key's own check, naming the flag's text
        except ValueError as exc:
            raise ConfigError(f"--source {text!r}: {exc}") from None
        if name is not None:
            opts = {**opts, "vehicle": name}
        parts.append(config.make_source(kind, opts, name, f"--source[{i}]"))
    config.unique_source_names(parts, given, lambda i: f"--source {urls[i]!r}: the name")
    config.name_vehicles(parts)
    return parts


def _backend_filter(args: argparse.Namespace, backends: bool) -> tuple[Any, set[str]]:
    """``keep(name)`` for :func:`config.parse` from ``--only``/``--disable`` (``backends``
    False: none, as ``record`` runs), and the set it fills with every name it was asked
    about (the file's backends, to check the flags' names against)."""
    only = set(getattr(args, "only", None) or ())
    disabled = set(getattr(args, "disable", None) or ())
    asked: set[str] = set()

    def keep(name: str) -> bool:
        asked.add(name)
        return backends and (not only or name in only) and name not in disabled

    return keep, asked


def config_from_args(args: argparse.Namespace, *, backends: bool = True) -> GatewayConfig:
    """The configuration ``run``/``replay``/``record`` use: file or embedded default, then
    flags on top.  Every flag is checked first, by the key it sets, used or not.  A backend
    that ``--only``/``--disable`` leave out (all of them when ``backends`` is False) is
    dropped before its table is validated: its class is never imported."""
    if getattr(args, "record", None) is not None and \
            getattr(args, "record_dir", None) is not None:
        raise ConfigError("--record, --record-dir: give one or the other")
    gateway_opts = {}
    for dest, flag, key in GATEWAY_FLAGS:
        value = checked_flag(args, dest, flag, gateway_key(key), f"gateway.{key}")
        if value is not None:
            gateway_opts[key] = value
    scope: FlagScope = getattr(args, "flag_scope", None) or FlagScope()
    source_opts = []
    for type_name, opts_cls in _source_options(scope.sources).items():
        def sets(key: str, of: str = type_name) -> str:
            return f"{key} of {of} sources"

        values, _ = opts_cls.flag_values(args, sets, sources=True)
        source_opts += [(type_name, key, value) for key, value in values.items()]
    if hasattr(args, "duration"):
        args.duration = checked_flag(args, "duration", "--duration", CLI_KEYS.keys["duration"])
    if hasattr(args, "log_format"):
        args.log_format = checked_flag(args, "log_format", "--log-format",
                                   CLI_KEYS.keys["log_format"])
    keep, asked = _backend_filter(args, backends)
    cfg = config.load(args.config, keep) if getattr(args, "config", None) else None
    if cfg is None:
        cfg = config.embedded_default(keep, sources=not getattr(args, "source", None))
    if getattr(args, "source", None):
        cfg.sources = _sources_from_urls(args.source)
    for type_name, key, value in source_opts:
        for i, p in enumerate(cfg.sources):
            if p.type == type_name:
                part = config.make_source(type_name, {**p.options, key: value}, p.name,
                                          f"sources[{i}]")
                part.vehicle, part.vehicle_given = p.vehicle, p.vehicle_given
                part.mavlink_sysid = p.mavlink_sysid
                cfg.sources[i] = part
    for one, other in (("record", "record_dir"), ("record_dir", "record")):
        if gateway_opts.get(one):
            gateway_opts[other] = ""  # a flag replaces the file's way of recording
    cfg.gateway.update(gateway_opts)
    # Backend flags: each backend turns its own flags into options (and is enabled by them).
    # Only commands built with _add_gateway_options have them (`record` has no backends).
    by_name = {p.name: p for p in cfg.backends}
    with_flags = _backend_flags(scope.backends) if getattr(args, "backend_flags", False) \
        else {}
    for name, flags in with_flags.items():
        opts_fn = getattr(flags, "cli_options", None)
        opts = None
        if opts_fn is not None and keep(name):
            typed = flags if isinstance(flags, type) and issubclass(flags, Options) else \
                options_of(flags)
            opts = typed.cli_options(args, f"backends.{name}") if typed else opts_fn(args)
        if opts is None:
            continue
        current = by_name.get(name)
        merged = {**(current.options if current else {}), **opts}
        try:  # the file's table passed already: what fails now is a flag's value
            part = config.make_backend(current.type if current else name, merged, name,
                                       f"backends.{name}")
        except config.MissingExtraError:
            raise
        except ConfigError as exc:
            raise ConfigError(f"{exc} (set by a --{name}… flag)") from None
        if current is None:
            cfg.backends.append(part)
        else:
            cfg.backends[cfg.backends.index(current)] = part
        by_name[name] = part
    known = set(registry.backend_names()) | asked | set(by_name)
    for flag in ("disable", "only"):
        for name in getattr(args, flag, None) or ():
            if name not in known:
                raise ConfigError(f"--{flag} {name}: no such backend; "
                                  f"available: {', '.join(sorted(known))}")
    for name in getattr(args, "only", None) or ():
        if name not in by_name and keep(name):
            raise ConfigError(f"--only {name}: not configured (no [backends.{name}] table, "
                              "no embedded default, none of its flags given)")
    return cfg


# -- commands ----------------------------------------------------------------------------------

def setup_logging(level: str | None, fmt: str | None = None) -> None:
    logjson.setup_logging(level, fmt or "text")  # json: gateway/logjson.py


def say(text: str, level: int = logging.INFO, fields: dict[str, Any] | None = None) -> None:
    """One of the run's own lines to stderr in one write (a log line another thread writes
    meanwhile cannot land inside it), as the log format says: plain or JSON (with
    ``fields`` as keys of their own)."""
    logjson.say(text, level=level, fields=fields)


#: a backend's counters of frames claiming one of its vehicles' identities (MAVLink)
IDENTITY_KEYS = ("impostor_frames", "rejected_signing", "unverified_systems", "sysid_conflicts",
                 "id_changes")


def _report(summary: dict[str, Any]) -> None:
    """The stop report: plain lines; in JSON mode one object, its first line as the message,
    the others as ``report`` and the whole summary as ``summary``."""
    lines: list[str] = []

    def line_out(text: str) -> None:
        lines.append(text)
        if not logjson.json_mode():
            say(text)

    drops = []
    rec = summary.get("recorder") or {}
    rec_drops = {k: rec.get(f"dropped_{k}", 0)
                 for k in ("queue_full", "at_close", "disk_full", "write_error", "vehicle_limit",
                           "open_failed")}
    if any(rec_drops.values()):
        drops.append("recorder " + " ".join(f"dropped_{k}={v}"
                                            for k, v in rec_drops.items() if v))
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
        line += f"; {summary['recorded']} messages recorded"
        unrecordable = rec.get("not_recordable") or {}
        if unrecordable:
            line += (f", {sum(unrecordable.values())} messages with no wire frame not recorded ("
                     + ", ".join(f"{k} {v}" for k, v in sorted(unrecordable.items())) + ")")
    line_out(line)
    flights = summary.get("flights") or {}
    for text in summary_lines(flights):
        line_out(text)
    crc = summary.get("crc_errors") or {}
    line_out(f"crc errors: {sum(crc.values())}"
             + (f" ({', '.join(f'{k} {v}' for k, v in sorted(crc.items()))})" if crc else ""))
    for path in summary.get("recordings") or ():
        line_out(f"recording: {path}")
    line_out("dropped: " + ("; ".join(drops) if drops else "nothing"))
    refusals = [f"{name} " + " ".join(f"{k}={st[k]}" for k in SERVER_KEYS if st.get(k))
                for name, st in summary["backends"].items()
                if any(isinstance(st.get(k), int) and st.get(k) for k in SERVER_KEYS)]
    if refusals:  # a listener refused or cut clients (gateway.io.server)
        line_out("clients: " + "; ".join(refusals))
    systems = [f"{name} " + ", ".join(f"{v} {s['sysid']}" for v, s in st["systems"].items())
               for name, st in summary["backends"].items()
               if isinstance(st.get("systems"), dict) and st["systems"]
               and all(isinstance(s, dict) and "sysid" in s for s in st["systems"].values())]
    if systems:  # each vehicle's MAVLink system id
        line_out("systems: " + "; ".join(systems))
    identity = [f"{name} " + " ".join(f"{k}={st[k]}" for k in IDENTITY_KEYS if st.get(k))
                for name, st in summary["backends"].items()
                if any(isinstance(st.get(k), int) and st.get(k) for k in IDENTITY_KEYS)]
    if identity:  # frames that claimed a vehicle's id and what came of it (MAVLink)
        line_out("identity: " + "; ".join(identity))
    if logjson.json_mode():
        say(lines[0], fields={"event": "stop", "report": lines[1:], "summary": summary})


def run_gateway(cfg: GatewayConfig, duration_s: float | None = None) -> int:
    """Start everything, run until a signal, the duration, or the sources' end; stop.  The
    exit status: 130 when SIGINT stopped it, else 0 (:class:`Stopper`)."""
    gw = Gateway(cfg)
    with Stopper(gw.stop_event) as stopper:
        failures = gw.start()
        for name, err in failures:
            say(f"aurora-gateway: backend {name} did not start: {err}", logging.ERROR,
                fields={"event": "backend_failed", "backend": name, "error": err})
        names = ", ".join(p.name for p in cfg.backends) or "none"
        srcs = ", ".join(s.name if s.vehicle == s.name else f"{s.name} (vehicle {s.vehicle})"
                         for s in gw.sources) or "none"
        say(f"aurora-gateway {__version__}: sources {srcs}; backends {names}",
            fields={"event": "start", "version": __version__,
                    "sources": [{"name": s.name, "vehicle": s.vehicle} for s in gw.sources],
                    "backends": [p.name for p in cfg.backends]})
        try:
            gw.run(duration_s)
        finally:
            summary = gw.stop()
    _report(summary)
    return stopper.status


def cmd_run(args: argparse.Namespace) -> int:
    cfg = config_from_args(args)
    config.check_runnable(cfg)
    setup_logging(cfg.gateway["log_level"], args.log_format)
    return run_gateway(cfg, args.duration)


def cmd_replay(args: argparse.Namespace) -> int:
    speed_key = _source_key("replay", "speed")
    speed = checked_flag(args, "speed", "--speed", speed_key)
    cfg = config_from_args(args)
    config.check_runnable(cfg, sources=False)
    opts = {"path": args.file, "speed": speed_key.default if speed is None else speed,
            "loop": args.loop}
    cfg.sources = [config.make_source("replay", opts, None, "replay")]
    setup_logging(cfg.gateway["log_level"], args.log_format)
    return run_gateway(cfg, args.duration)


def cmd_record(args: argparse.Namespace) -> int:
    args.config = None
    cfg = config_from_args(args, backends=False)
    cfg.gateway["record"] = args.file
    setup_logging(cfg.gateway["log_level"], args.log_format)
    return run_gateway(cfg, args.duration)


def _json_safe(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in d.items()}


def cmd_decode(args: argparse.Namespace) -> int:
    with signals.held():  # (an import's bookkeeping is where a KeyboardInterrupt is lost)
        from gateway import recording
        from gateway.model import kind
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
                recording.check_header(data, args.file)
                recs = recording.name_unnamed(
                    recording.records(data, stats, messages=True),
                    recording.file_vehicle(args.file) if args.file != "-" else "")
                recs = recording.only_vehicle(recs, args.vehicle, args.file)
            except ValueError as exc:  # RecordingError included
                print(f"aurora-gateway: decode: {exc}", file=sys.stderr)
                return EXIT_USAGE
            for t, item, vehicle, source in recs:
                head = {"rx_time": t, "vehicle": vehicle, "source": source}
                if not isinstance(item, bytes):  # a message record: its kind and fields
                    out.write(json.dumps({**head, "kind": kind(item),
                                          **_json_safe(item.fields())}) + "\n")
                    continue
                for msg in dec.feed(item):
                    out.write(json.dumps({**head, **_json_safe(to_wire_dict(msg))}) + "\n")
            if stats.messages:
                bad = stats.bad_messages
                print(f"recording: {stats.messages} message records (position, battery, "
                      f"vehicle state …)" + (f", {bad} malformed skipped" if bad else ""),
                      file=sys.stderr)
            if stats.torn_tail_bytes or stats.corrupt_skips:
                print(f"recording: {stats.records} records, torn tail {stats.torn_tail_bytes} "
                      f"bytes, {stats.corrupt_skips} corrupt stretches skipped", file=sys.stderr)
        elif args.vehicle is not None:
            print(f"aurora-gateway: decode: --vehicle: {args.file} is a raw capture, which "
                  "names no vehicle", file=sys.stderr)
            return EXIT_USAGE
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
    from gateway.io.transport import TransportError, open_serial
    from gateway.pacing import paced
    from gateway.sources.sim import flight_frames

    sim: dict[str, Any] = {}
    for dest, flag, key in SIMULATE_FLAGS:
        k = _source_key("sim", key)
        value = checked_flag(args, dest, flag, k, f"{key} of the sim source")
        sim[key] = k.default if value is None else value
    out = checked_flag(args, "out", "--out", _source_key("serial", "url"))
    if out is None:
        raise ConfigError("--out: required (a pyserial port or URL)")
    baud_key = _source_key("serial", "baudrate")
    baud = checked_flag(args, "baud", "--baud", baud_key, "baudrate of serial sources")
    baud = baud_key.default if baud is None else baud
    level = checked_flag(args, "log_level", "--log-level", gateway_key("log_level"))
    setup_logging(level)
    model = FlightModel(FlightProfile(revision=sim["revision"]))
    stop = threading.Event()
    sent = errors = 0
    port = None
    backoff = Backoff(0.05, 2.0)
    with Stopper(stop) as stopper:
        frames = paced(flight_frames(model, sim["rate_hz"], sim["status_hz"], sim["cycles"]),
                       sim["speed"], stop)
        for _, frame in frames:
            while port is None and not stop.is_set():
                try:
                    port = open_serial(out, baud, timeout=0.1)
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
                log.warning("write to %s failed (%s); reopening", out, exc)
                port.close()
                port = None
        if port is not None:
            try:
                port.flush()
            finally:
                port.close()
    print(f"simulate: {sent} frames written to {out}, {errors} write errors",
          file=sys.stderr)
    return stopper.status


COMMANDS = {"run": cmd_run, "decode": cmd_decode, "simulate": cmd_simulate,
            "record": cmd_record, "replay": cmd_replay}


def _recording_errors() -> tuple[type[Exception], ...]:
    """:class:`gateway.recording.RecordingError` once that module is imported (only a command
    that reads or writes a recording imports it, and only it can raise one)."""
    module = sys.modules.get("gateway.recording")
    return (module.RecordingError,) if module is not None else ()


#: Commands whose handler installs a :class:`Stopper` before it does anything long (through
#: run_gateway, the monitor, simulate's and listen's own): signals stay held until it does,
#: and a signal noted meanwhile is raised as it is installed (the command never starts).
#: The others (decode, the short ones) start with the hold released: a Ctrl-C is their
#: KeyboardInterrupt.
HELD_TO_STOPPER = frozenset({"run", "record", "replay", "monitor", "simulate", "listen"})


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; its exit status.  Ctrl-C anywhere (the backends' imports while the
    parser is built, start-up, a command without its own handler) is a quiet 130.  A signal
    held while the modules loaded (:mod:`gateway.signals`) is delivered as the command
    starts, or here if the command line ended before it (``--help``, a usage error)."""
    try:
        try:
            return _main(argv)
        finally:
            signals.release()
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


def _main(argv: Sequence[str] | None) -> int:
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
    scope = _narrow_scope(argv[1:]) if first == "run" else None
    args = _parse_run(argv, scope) if scope is not None else None
    if args is None:
        try:
            parser = build_parser(backend_flags=first in ("run", "replay"),
                                  plugin_command=plugin,
                                  command=first if first in COMMANDS else None)
        except registry.MissingExtra as exc:
            print(f"aurora-gateway: {exc}", file=sys.stderr)
            return EXIT_USAGE
        args = parser.parse_args(argv)
        left_out = _left_out_flag(argv[1:], args.only) if scope is not None and \
            scope.backends is not None and getattr(args, "only", None) else None
        if left_out is not None:
            print(f"aurora-gateway: {left_out}", file=sys.stderr)
            return EXIT_USAGE
    handler = getattr(args, "handler", None) or COMMANDS[args.command]
    if args.command not in HELD_TO_STOPPER:
        signals.release()  # a Ctrl-C from here on reaches the command (its KeyboardInterrupt)
    try:
        return handler(args)
    except ValueError as exc:  # a ConfigError, or a RecordingError (not every other)
        if not isinstance(exc, (ConfigError, *_recording_errors())):
            raise
        print(f"aurora-gateway: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ModuleNotFoundError as exc:  # a command's optional dependency (plot: matplotlib)
        extra = registry.missing_extra(exc)
        if extra is None:
            raise
        print(f"aurora-gateway: {registry.extra_line(args.command, extra)}", file=sys.stderr)
        return EXIT_USAGE


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
    except KeyboardInterrupt:  # between main's own handler and here: still quiet
        code = EXIT_INTERRUPTED
    except BaseException as exc:
        status = exits.signalled(exc)  # a signal's exception, wrapped on its way here
        if status is not None:
            code = status
        else:
            traceback.print_exc()  # os._exit below would otherwise swallow it
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):  # a closed pipe
                stream.flush()
        os._exit(code)


if __name__ == "__main__":
    console_main()


def __getattr__(name: str) -> Any:
    """``SOURCE_FLAGS``: :func:`source_flags`, computed when asked for (importing this module
    imports no source's options: Ctrl-C during start-up is handled by :func:`console_main`)."""
    if name == "SOURCE_FLAGS":
        return source_flags()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
