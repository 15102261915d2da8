"""Configuration: one TOML file (or the embedded default), validated before anything starts.

A bad key or value raises :class:`ConfigError` whose text is one line naming the key and what
is allowed, e.g. ``sources[0].baudrate: expected an integer ≥ 50, got 'fast'``.

Command-line flags that set a key go through the same :class:`Key` (:func:`check_flag`), so
``--link-timeout 0.01`` is refused exactly as ``link_timeout_s = 0.01`` in a file is, with
the flag named in the message — whether or not anything would use the value.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from gateway import registry

REQUIRED: Any = object()


class ConfigError(ValueError):
    """A configuration problem, described in one line that names the key."""


@dataclass(frozen=True)
class Key:
    """One allowed key: its type, default and bounds."""

    kind: type | tuple[type, ...]
    default: Any = REQUIRED
    help: str = ""
    choices: tuple[Any, ...] | None = None
    minimum: float | None = None
    maximum: float | None = None
    nullable: bool = False
    #: a further check of a well-typed value: raise ValueError saying what is wrong
    validator: Callable[[Any], object] | None = None

    def describe(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        kinds = self.kind if isinstance(self.kind, tuple) else (self.kind,)
        names = {int: "an integer", float: "a number", str: "a string", bool: "true or false",
                 list: "a list", dict: "a table"}
        text = " or ".join(names.get(k, k.__name__) for k in kinds)
        if self.minimum is not None and self.maximum is not None:
            text += f" from {self.minimum:g} to {self.maximum:g}"
        elif self.minimum is not None:
            text += f" ≥ {self.minimum:g}"
        elif self.maximum is not None:
            text += f" ≤ {self.maximum:g}"
        return text

    def check(self, where: str, value: Any) -> Any:
        if value is None and self.nullable:
            return None
        kinds = self.kind if isinstance(self.kind, tuple) else (self.kind,)
        ok = False
        for k in kinds:
            if k is bool:
                ok = isinstance(value, bool)
            elif k is int:
                ok = isinstance(value, int) and not isinstance(value, bool)
            elif k is float:
                ok = isinstance(value, int | float) and not isinstance(value, bool)
                if ok and not math.isfinite(value):
                    ok = False
            else:
                ok = isinstance(value, k)
            if ok:
                break
        if ok and self.choices is not None and value not in self.choices:
            ok = False
        if ok and self.minimum is not None and value < self.minimum:
            ok = False
        if ok and self.maximum is not None and value > self.maximum:
            ok = False
        if not ok:
            raise ConfigError(f"{where}: expected {self.describe()}, got {value!r}")
        if self.validator is not None:
            try:
                self.validator(value)
            except ValueError as exc:
                raise ConfigError(f"{where}: {exc}") from None
        if float in kinds and int not in kinds and isinstance(value, int):
            return float(value)
        return value


class Schema:
    """The keys a table may have."""

    def __init__(self, **keys: Key) -> None:
        self.keys = keys

    def validate(self, table: dict[str, Any], where: str,
                 ignore: Iterable[str] = ()) -> dict[str, Any]:
        """Check ``table``; return it with defaults filled in (``ignore``d keys left out)."""
        if not isinstance(table, dict):
            raise ConfigError(f"{where}: expected a table, got {table!r}")
        ignored = set(ignore)
        out: dict[str, Any] = {}
        for key, value in table.items():
            if key in ignored:
                continue
            spec = self.keys.get(key)
            if spec is None:
                allowed = ", ".join(sorted(self.keys)) or "none"
                raise ConfigError(f"{where}.{key}: unknown key; allowed: {allowed}")
            out[key] = spec.check(f"{where}.{key}", value)
        for key, spec in self.keys.items():
            if key not in out:
                if spec.default is REQUIRED:
                    raise ConfigError(f"{where}.{key}: required ({spec.describe()})")
                out[key] = spec.default
        return out

    def __or__(self, other: Schema) -> Schema:
        return Schema(**self.keys, **other.keys)


EMPTY = Schema()


def flag_value(text: str) -> Any:
    """A number flag's text as the value a TOML file would hold (int, else float, else the
    text itself), left for :meth:`Key.check` to accept or refuse with the allowed range."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def check_flag(flag: str, key: Key, value: Any, sets: str = "") -> Any:
    """Validate a flag's value with the :class:`Key` it sets (``sets`` names that key in the
    message, e.g. ``gateway.link_timeout_s``)."""
    return key.check(f"{flag} ({sets})" if sets else flag, value)

GATEWAY_SCHEMA = Schema(
    status_interval_s=Key(float, 1.0, "seconds between status lines; 0 = none", minimum=0),
    link_timeout_s=Key(float, 3.0, "silence after which a source's link is down", minimum=0.05),
    record=Key(str, "", "append every received frame to this recording file"),
    record_dir=Key(str, "", "record into a new file in this directory for each run and "
                   "flight, named <UTC start>-<source>.aur (not with record)"),
    log_level=Key(str, "info", "logging level",
                  choices=("debug", "info", "warning", "error")),
)


@dataclass
class Part:
    """One configured source or backend instance."""

    type: str
    name: str
    options: dict[str, Any]
    cls: Any = None


@dataclass
class GatewayConfig:
    """A validated configuration."""

    gateway: dict[str, Any] = field(default_factory=lambda: GATEWAY_SCHEMA.validate({}, "gateway"))
    sources: list[Part] = field(default_factory=list)
    backends: list[Part] = field(default_factory=list)


def _resolve(group: str, type_name: str, where: str) -> Any:
    try:
        return registry.load(group, type_name)
    except registry.RegistryError as exc:
        raise ConfigError(f"{where}.type: {exc}") from None


def _schema_of(cls: Any) -> Schema:
    return getattr(cls, "CONFIG", None) or EMPTY


def make_source(type_name: str, options: dict[str, Any], name: str | None,
                where: str) -> Part:
    """Validate one source table into a :class:`Part`."""
    cls = _resolve(registry.SOURCE_GROUP, type_name, where)
    opts = _schema_of(cls).validate(options, where, ignore=("type", "name"))
    return Part(type_name, name or getattr(cls, "default_name", lambda o: type_name)(opts),
                opts, cls)


def make_backend(type_name: str, options: dict[str, Any], name: str, where: str) -> Part:
    """Validate one backend table into a :class:`Part`."""
    cls = _resolve(registry.BACKEND_GROUP, type_name, where)
    opts = _schema_of(cls).validate(options, where, ignore=("type", "enabled"))
    return Part(type_name, name, opts, cls)


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
    names: set[str] = set()
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
        if part.name in names:
            raise ConfigError(f"{where}.name: {part.name!r} is used twice; give each a name")
        names.add(part.name)
        cfg.sources.append(part)
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
        part = make_backend(type_name, table, name, where)
        if enabled:
            cfg.backends.append(part)
    return cfg


def load(path: str | Path, keep: Callable[[str], bool] | None = None) -> GatewayConfig:
    """Read and validate a TOML configuration file (``keep``: see :func:`parse`)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return parse(data, keep)


def embedded_default(keep: Callable[[str], bool] | None = None) -> GatewayConfig:
    """The configuration used with no file: the simulated flight through every backend
    that can run on loopback with its defaults (``keep``: see :func:`parse`)."""
    backends: dict[str, Any] = {}
    for name in registry.backend_names():
        if keep is not None and not keep(name):
            continue
        try:
            cls = registry.load(registry.BACKEND_GROUP, name)
        except registry.RegistryError:
            continue  # a broken third-party plug-in must not stop the default run
        default = getattr(cls, "EMBEDDED_DEFAULT", {})
        if default is not None:
            backends[name] = dict(default)
    return parse({"sources": [{"type": "sim"}], "backends": backends})
