"""Configuration: one TOML file (or the embedded default), validated before anything starts.

A bad key or value raises :class:`ConfigError` whose text is one line naming the key and what
is allowed, e.g. ``sources[0].baudrate: expected an integer ≥ 50, got 'fast'``.

Command-line flags that set a key go through the same :class:`Key` (:func:`check_flag`), so
``--link-timeout 0.01`` is refused exactly as ``link_timeout_s = 0.01`` in a file is, with
the flag named in the message — whether or not anything would use the value.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gateway import registry, vehicles
from gateway.options import (
    EMPTY,
    REQUIRED,
    ConfigError,
    Flag,
    Key,
    Options,
    Schema,
    check_flag,
    flag_value,
    option,
    options_of,
)

__all__ = ["REQUIRED", "ConfigError", "GatewayConfig", "GatewayOptions", "Key", "Part",
           "Schema", "check_flag", "flag_value", "load", "parse"]


@dataclass(frozen=True, kw_only=True)
class GatewayOptions(Options):
    """The ``[gateway]`` table."""

    status_interval_s: float = option(
        1.0, "seconds between status lines; 0 = none", minimum=0,
        flag=Flag("--status-interval", "seconds between status lines on stderr (0 = none)",
                  metavar="S"))
    link_timeout_s: float = option(
        3.0, "silence after which a source's link is down", minimum=0.05,
        flag=Flag("--link-timeout", "silence after which a source's link is reported down "
                  "(default 3)", metavar="S"))
    record: str = option("", "append every message received (wire frames as they came), "
                         "every vehicle's, to this recording file",
                         flag=Flag("--record", "append every message received (every "
                                   "vehicle's) to FILE", metavar="FILE"))
    record_dir: str = option(
        "", "record into a new file in this directory per vehicle and flight, named "
        "<UTC start>-<vehicle>.aur (not with record)",
        flag=Flag("--record-dir", "record into a new file in DIR (created) per vehicle and "
                  "flight, named <UTC start>-<vehicle>.aur; not with --record", metavar="DIR"))
    log_level: str = option("info", "logging level",
                            choices=("debug", "info", "warning", "error"),
                            flag=Flag("--log-level", "logging level", metavar="LEVEL"))

    def check(self) -> None:
        if self.record and self.record_dir:
            raise ConfigError("gateway.record, gateway.record_dir: give one or the other")


GATEWAY_SCHEMA = GatewayOptions.schema()


@dataclass
class Part:
    """One configured source or backend instance."""

    type: str
    name: str
    options: dict[str, Any]
    cls: Any = None
    #: (sources) the vehicle's name, given (``vehicle = "NAME"``, ``--source NAME=URL``) or
    #: derived from ``name`` (:func:`gateway.vehicles.derive_name`, made unique by
    #: :func:`parse`)
    vehicle: str = ""
    #: (sources) the MAVLink system id fixed for this vehicle (``mavlink_sysid``); None: assigned
    mavlink_sysid: int | None = None
    #: (sources) True when ``vehicle`` was given, not derived
    vehicle_given: bool = False


@dataclass
class GatewayConfig:
    """A validated configuration."""

    gateway: dict[str, Any] = field(default_factory=lambda: GATEWAY_SCHEMA.validate({}, "gateway"))
    sources: list[Part] = field(default_factory=list)
    backends: list[Part] = field(default_factory=list)


class MissingExtraError(ConfigError):
    """A configured backend or source needs an extra that is not installed (the text says
    which, and the pip command)."""


def _resolve(group: str, type_name: str, where: str) -> Any:
    try:
        return registry.load(group, type_name)
    except registry.MissingExtra as exc:  # one line naming the backend and the extra
        raise MissingExtraError(str(exc)) from None
    except registry.RegistryError as exc:
        raise ConfigError(f"{where}.type: {exc}") from None


def schema_of(cls: Any) -> Schema:
    """A backend's or source's schema: derived from its ``OPTIONS`` declaration (a
    :class:`gateway.options.Options`), else a plug-in's own ``CONFIG``."""
    opts = options_of(cls)
    if opts is not None:
        return opts.schema()
    return getattr(cls, "CONFIG", None) or EMPTY


def _check_together(cls: Any, table: dict[str, Any], where: str) -> None:
    """The checks between keys (:meth:`Options.check`), as the options object is built."""
    opts = options_of(cls)
    if opts is not None:
        try:
            opts.from_table(table)
        except ConfigError as exc:
            raise ConfigError(f"{where}: {exc}") from None


#: the keys every ``[[sources]]`` table may have besides its type's own
SOURCE_COMMON_KEYS = ("type", "name", "vehicle", "mavlink_sysid")


def make_source(type_name: str, options: dict[str, Any], name: str | None,
                where: str) -> Part:
    """Validate one source table into a :class:`Part` (its vehicle derived from its name when
    the table names none; :func:`parse` makes derived names unique)."""
    cls = _resolve(registry.SOURCE_GROUP, type_name, where)
    opts = schema_of(cls).validate(options, where, ignore=SOURCE_COMMON_KEYS)
    _check_together(cls, opts, where)
    default_name = getattr(cls, "default_name", lambda o: None)(opts)
    part = Part(type_name, name or default_name or type_name, opts, cls)
    vehicle = options.get("vehicle")
    if vehicle is not None:
        try:
            part.vehicle = vehicles.check_name(vehicle)
        except ValueError as exc:
            raise ConfigError(f"{where}.vehicle: {exc}") from None
        part.vehicle_given = True
    else:  # the type's own default (a replay's: its file's), else derived from the name
        default_vehicle = getattr(cls, "default_vehicle", None)
        derived = default_vehicle(opts) if default_vehicle is not None and name is None \
            else None
        part.vehicle = derived or vehicles.derive_name(part.name, fallback=type_name)
    sysid = options.get("mavlink_sysid")
    if sysid is not None:
        if isinstance(sysid, bool) or not isinstance(sysid, int) or not 1 <= sysid <= 255:
            raise ConfigError(f"{where}.mavlink_sysid: expected an integer 1 to 255, "
                              f"got {sysid!r}")
        part.mavlink_sysid = sysid
    return part


def unique_source_names(parts: list[Part], given: list[bool],
                        where: Callable[[int], str]) -> None:
    """Source names as given (one given twice: an error led by ``where(i)``); unnamed sources
    of one type or URL told apart as ``sim``, ``sim-2`` … (and their derived vehicles with
    them)."""
    seen: set[str] = set()
    for i, p in enumerate(parts):
        if given[i] and p.name in seen:
            raise ConfigError(f"{where(i)} {p.name!r} is used twice")
        seen.add(p.name)
    unique = vehicles.unique_names(zip((p.name for p in parts), given, strict=True))
    for p, name in zip(parts, unique, strict=True):
        if name != p.name:
            old, p.name = p.name, name
            if not p.vehicle_given and p.vehicle == vehicles.derive_name(old, fallback=p.type):
                p.vehicle = vehicles.derive_name(name, fallback=p.type)


def name_vehicles(sources: list[Part]) -> None:
    """Check the sources' vehicles: a given name or MAVLink system id used twice is an error
    naming the key; derived names get ``-2``, ``-3`` … until unique."""
    seen: dict[str, int] = {}
    ids: dict[int, int] = {}
    for i, p in enumerate(sources):
        if p.vehicle_given:
            if p.vehicle in seen:
                raise ConfigError(f"sources[{i}].vehicle: {p.vehicle!r} is already the "
                                  f"vehicle of sources[{seen[p.vehicle]}]")
            seen[p.vehicle] = i
        if p.mavlink_sysid is not None:
            if p.mavlink_sysid in ids:
                raise ConfigError(f"sources[{i}].mavlink_sysid: {p.mavlink_sysid} is already "
                                  f"the system id of sources[{ids[p.mavlink_sysid]}]")
            ids[p.mavlink_sysid] = i
    names = vehicles.unique_names((p.vehicle, p.vehicle_given) for p in sources)
    for p, vehicle in zip(sources, names, strict=True):
        p.vehicle = vehicle


def make_backend(type_name: str, options: dict[str, Any], name: str, where: str) -> Part:
    """Validate one backend table into a :class:`Part`."""
    cls = _resolve(registry.BACKEND_GROUP, type_name, where)
    opts = schema_of(cls).validate(options, where, ignore=("type", "enabled"))
    _check_together(cls, opts, where)
    return Part(type_name, name, opts, cls)


def _check_options_only(type_name: str, table: dict[str, Any], where: str) -> None:
    """Validate a backend's table by its options declaration alone (a light module,
    :data:`registry.BACKEND_OPTIONS_GROUP`): a disabled backend whose class needs an extra that
    is not installed."""
    holder = type("_Declared", (), {"OPTIONS": _resolve(registry.BACKEND_OPTIONS_GROUP,
                                                        type_name, where)})
    opts = schema_of(holder).validate(table, where, ignore=("type", "enabled"))
    _check_together(holder, opts, where)


def parse(data: dict[str, Any], keep: Callable[[str], bool] | None = None) -> GatewayConfig:
    """Validate a configuration mapping (what a TOML file loads to).  ``keep(name)`` False
    leaves backend ``name`` out before its options are validated, so its class is never
    imported (the command line's ``--disable``/``--only``)."""
    allowed = {"gateway", "sources", "backends"}
    for key in data:
        if key not in allowed:
            raise ConfigError(f"{key}: unknown section; allowed: {', '.join(sorted(allowed))}")
    cfg = GatewayConfig(gateway=GATEWAY_SCHEMA.validate(data.get("gateway", {}), "gateway"))
    if cfg.gateway["record"] and cfg.gateway["record_dir"]:
        raise ConfigError("gateway.record, gateway.record_dir: give one or the other")
    sources = data.get("sources", [])
    if not isinstance(sources, list):
        raise ConfigError("sources: expected an array of tables ([[sources]])")
    given: list[bool] = []
    for i, table in enumerate(sources):
        where = f"sources[{i}]"
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: expected a table, got {table!r}")
        type_name = table.get("type")
        if not isinstance(type_name, str):
            raise ConfigError(f"{where}.type: required; one of "
                              f"{', '.join(registry.source_names())}")
        name = table.get("name")
        if name is not None and not isinstance(name, str):
            raise ConfigError(f"{where}.name: expected a string, got {name!r}")
        part = make_source(type_name, table, name, where)
        given.append(name is not None)
        cfg.sources.append(part)
    unique_source_names(cfg.sources, given, lambda i: f"sources[{i}].name:")
    name_vehicles(cfg.sources)
    backends = data.get("backends", {})
    if not isinstance(backends, dict):
        raise ConfigError("backends: expected a table of [backends.<name>] tables")
    for name, table in backends.items():
        where = f"backends.{name}"
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: expected a table, got {table!r}")
        enabled = table.get("enabled", True)
        if not isinstance(enabled, bool):
            raise ConfigError(f"{where}.enabled: expected true or false, got {enabled!r}")
        type_name = table.get("type", name)
        if not isinstance(type_name, str):
            raise ConfigError(f"{where}.type: expected a string, got {type_name!r}")
        if keep is not None and not keep(name):
            continue
        try:
            part = make_backend(type_name, table, name, where)
        except MissingExtraError:  # checked all the same when disabled: its extra runs it
            if enabled or type_name not in registry.names(registry.BACKEND_OPTIONS_GROUP):
                raise
            _check_options_only(type_name, table, where)
            continue
        if enabled:
            cfg.backends.append(part)
    return cfg


def check_runnable(cfg: GatewayConfig, *, sources: bool = True) -> None:
    """A configuration ``run`` can do something with: a source (unless ``sources`` is False:
    a command that brings its own) and a backend, a recording or a source with a job of its
    own (:meth:`Source.works_alone`); else :class:`ConfigError` saying what to add (a run
    with none idled for ever)."""
    if sources and not cfg.sources:
        raise ConfigError("sources: none configured; add a [[sources]] table "
                          "(or run --source URL)")
    if cfg.backends or cfg.gateway.get("record") or cfg.gateway.get("record_dir"):
        return
    if any(getattr(p.cls, "works_alone", lambda _o: False)(p.options) for p in cfg.sources):
        return  # e.g. a MAVLink source routing its vehicle to its endpoints
    raise ConfigError("backends: none enabled; add a [backends.NAME] table "
                      "(or a backend's flag, see run --help)")


def load(path: str | Path, keep: Callable[[str], bool] | None = None) -> GatewayConfig:
    """Read and validate a TOML configuration file (``keep``: see :func:`parse`)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    import tomllib  # here: a run from flags alone never reads TOML (~5 ms of start-up)

    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return parse(data, keep)


def embedded_default(keep: Callable[[str], bool] | None = None, *,
                     sources: bool = True) -> GatewayConfig:
    """The configuration used with no file: the simulated flight through every backend
    that can run on loopback with its defaults (``keep``: see :func:`parse`).  ``sources``
    False leaves the simulated source out (``--source`` replaces it: it is not imported)."""
    backends: dict[str, Any] = {}
    light = registry.names(registry.BACKEND_OPTIONS_GROUP)  # EMBEDDED_DEFAULT without the SDK
    for name in registry.backend_names():
        if keep is not None and not keep(name):
            continue
        try:
            cls = registry.load(registry.BACKEND_OPTIONS_GROUP if name in light
                                else registry.BACKEND_GROUP, name)
        except registry.RegistryError:
            continue  # a broken third-party plug-in must not stop the default run
        default = getattr(cls, "EMBEDDED_DEFAULT", {})
        if default is not None:
            backends[name] = dict(default)
    return parse({"sources": [{"type": "sim"}] if sources else [], "backends": backends})
