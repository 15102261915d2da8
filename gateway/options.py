"""Options declared once: a backend's (or source's, or the gateway's) options are one frozen
dataclass whose fields carry their metadata (help, range or choices, secret, validator, the
``run`` flag that sets them).  Everything else is derived from it:

* the configuration schema (:meth:`Options.schema`, a :class:`Schema` of :class:`Key`) that
  validates a ``[backends.<name>]`` / ``[[sources]]`` table — one line naming the key and what
  is allowed, e.g. ``sources[0].baudrate: expected an integer ≥ 50, got 'fast'``;
* the ``run`` flags and their help (:meth:`Options.add_cli_arguments`,
  :meth:`Options.cli_options`);
* ``docs/config-reference.md`` and ``examples/gateway.toml`` (tools/gen_config_reference.py)
  and ``check-config``'s output (secrets are never printed).

A class is declared like this, in a light module found by the
``aurora_gateway.backend_options`` / ``source_options`` entry points: the standard library, this
module and the endpoint grammar (:mod:`gateway.io.endpoints`) only, so building the ``run``
parser imports no backend::

    @dataclass(frozen=True, kw_only=True)
    class CrsfOptions(Options):
        TITLE: ClassVar[str] = "CRSF backend"
        url: str = option(PTY_URL, "receiver UART …", validator=_check_url,
                          flag=Flag("--crsf", metavar="URL"))
        baudrate: int = option(420000, "UART speed", minimum=1200, flag="--crsf-baud")

``CrsfOptions(baudrate=416666)`` is validated in ``__post_init__`` (a bad value raises
:class:`ConfigError`, a ValueError, naming the key); the backend's constructor takes the
object: ``CrsfBackend(CrsfOptions(...), name=...)``.

This module imports only the standard library and the endpoint grammar.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import math
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

from gateway.io.endpoints import SERIAL, check_serial_port, text_of

REQUIRED: Any = object()


class ConfigError(ValueError):
    """A configuration problem, described in one line that names the key."""


@dataclass(frozen=True)
class Key:
    """One allowed key: its type, default and bounds (derived from an :func:`option` field,
    or written by hand for a table that has no dataclass)."""

    kind: type | tuple[type, ...]
    default: Any = REQUIRED
    help: str = ""
    choices: tuple[Any, ...] | None = None
    minimum: float | None = None
    maximum: float | None = None
    nullable: bool = False
    #: a further check of a well-typed value: raise ValueError saying what is wrong
    validator: Callable[[Any], object] | None = None
    #: never printed (check-config, docs): a password or passphrase
    secret: bool = False

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
                out[key] = _copy(spec.default)
        return out

    def __or__(self, other: Schema) -> Schema:
        return Schema(**self.keys, **other.keys)


EMPTY = Schema()


def _copy(value: Any) -> Any:
    return list(value) if isinstance(value, list) else value


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


# -- declaring a field ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Flag:
    """The ``run`` flag that sets one option.

    ``help``: the flag's own text (default: the key's help, prefixed with the options class's
    ``TITLE``).  A list option's flag is repeatable.  ``enables`` False: the flag alone does
    not configure the backend, it only adds to what its other flags (or the file) configure.
    ``parse``: the flag's text → the keys it sets (``--http HOST:PORT`` sets host and port),
    run by argparse, a ValueError being the usage error.  ``convert``: the flag's text → its
    own key's value, run by argparse on each value as it is read (a repeatable flag stays
    repeatable), a ValueError being the usage error in its own words (``argument --X: …``):
    the address flags check their text with the endpoint grammar there.  A source's flag
    (``--baud``) sets its key on every source of that type."""

    name: str
    help: str = ""
    metavar: str | None = None
    enables: bool = True
    parse: Callable[[str], dict[str, Any]] | None = None
    convert: Callable[[str], Any] | None = None
    #: False: the flag sets the backend's key only, not the sources' whose options share the
    #: field (the Zenoh session's keys)
    sources: bool = True

    @property
    def dest(self) -> str:
        return self.name.lstrip("-").replace("-", "_")


@dataclass(frozen=True)
class Meta:
    """What :func:`option` records on a dataclass field."""

    help: str
    choices: tuple[Any, ...] | None = None
    minimum: float | None = None
    maximum: float | None = None
    secret: bool = False
    validator: Callable[[Any], object] | None = None
    flag: Flag | None = None
    kind: type | tuple[type, ...] | None = None


def option(default: Any = REQUIRED, help: str = "", *, choices: Sequence[Any] | None = None,
           minimum: float | None = None, maximum: float | None = None, secret: bool = False,
           validator: Callable[[Any], object] | None = None, flag: Flag | str | None = None,
           kind: type | tuple[type, ...] | None = None) -> Any:
    """A dataclass field that is a configuration key (see the module docstring).  The key's
    type comes from the field's annotation (``X | None``: the key may be left unset) unless
    ``kind`` is given; no ``default``: the key is required."""
    meta = Meta(help, tuple(choices) if choices is not None else None, minimum, maximum, secret,
                validator, Flag(flag) if isinstance(flag, str) else flag, kind)
    metadata = {"option": meta}
    if default is REQUIRED:
        return field(metadata=metadata)
    if isinstance(default, list | dict):
        return field(default_factory=lambda: _copy(default), metadata=metadata)
    return field(default=default, metadata=metadata)


def serial_port_option(help: str, flag: str | None = None, flag_help: str = "") -> Any:
    """A required key naming a serial device or pyserial URL (checked by
    :func:`gateway.io.endpoints.check_serial_port`), with, when ``flag`` is given, the
    ``run`` flag that sets it (``--flag URL``)."""
    return option(help=help, validator=check_serial_port,
                  flag=None if flag is None else Flag(
                      flag, flag_help, metavar="URL",
                      convert=text_of((SERIAL,), baud_suffix=False)))


def lazy(target: str) -> Callable[[Any], object]:
    """A validator that lives in a heavier module (``"package.module:function"``), imported
    on its first use, so an options module stays light."""
    module_name, _, attr = target.partition(":")

    def check(value: Any) -> object:
        return getattr(importlib.import_module(module_name), attr)(value)

    check.__qualname__ = f"lazy({target})"
    return check


_KINDS = {int: int, float: float, str: str, bool: bool, list: list, tuple: list, dict: dict}


def _kind_of(annotation: Any) -> tuple[tuple[type, ...], bool]:
    """A field's annotation → (the TOML kinds it takes, whether None is allowed)."""
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        kinds: list[type] = []
        nullable = False
        for arg in args:
            if arg is type(None):
                nullable = True
            else:
                kinds += _kind_of(arg)[0]
        return tuple(dict.fromkeys(kinds)), nullable
    base = typing.get_origin(annotation) or annotation
    if base not in _KINDS:
        raise TypeError(f"no configuration kind for the annotation {annotation!r}")
    return (_KINDS[base],), False


OptionsT = TypeVar("OptionsT", bound="Options")
T = TypeVar("T")


@dataclass(frozen=True, kw_only=True)
class Options:
    """Base class of an options declaration (see the module docstring).  Subclasses are
    ``@dataclass(frozen=True, kw_only=True)`` and declare every field with :func:`option`."""

    #: names the flags' group in ``run --help`` (e.g. "CRSF backend")
    TITLE: ClassVar[str] = ""
    #: (a backend's options) its table in the embedded default run (loopback, no hardware);
    #: None leaves it out.  Declared here, on the light options module, so the default run
    #: need not import the backends it leaves out (their SDKs: Cyclone DDS, Foxglove …)
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = None

    def __post_init__(self) -> None:
        for name, key in self.schema().keys.items():
            value = getattr(self, name)
            if isinstance(value, tuple) and list in _kinds(key):
                value = list(value)
            checked = key.check(name, value)
            if checked is not getattr(self, name):
                object.__setattr__(self, name, checked)
        self.check()

    def check(self) -> None:
        """Checks between fields (raise :class:`ConfigError` naming the keys); none by
        default."""

    # -- derived: the schema ----------------------------------------------------------------

    @classmethod
    def schema(cls) -> Schema:
        """The configuration schema, one :class:`Key` per field (cached per class)."""
        cached = cls.__dict__.get("_schema")
        if cached is None:
            hints = typing.get_type_hints(cls)
            keys = {f.name: key_of(f, hints[f.name]) for f in option_fields(cls)}
            cached = Schema(**keys)
            type.__setattr__(cls, "_schema", cached)
        return cached

    @classmethod
    def from_table(cls: type[OptionsT], table: dict[str, Any]) -> OptionsT:
        """An instance from a table :meth:`schema` validated (the file's or the flags')."""
        return cls(**table)

    def table(self) -> dict[str, Any]:
        """The options as a configuration table (key → value)."""
        return {f.name: getattr(self, f.name) for f in option_fields(type(self))}

    def replace(self: OptionsT, **changes: Any) -> OptionsT:
        """A copy with ``changes`` (validated again)."""
        return dataclasses.replace(self, **changes)

    # -- derived: the run flags -------------------------------------------------------------

    @classmethod
    def flags(cls) -> list[tuple[str, Flag, Key]]:
        """(field name, its flag, its key) for every field that has a ``run`` flag."""
        keys = cls.schema().keys
        out = []
        for f in option_fields(cls):
            flag = meta(f).flag
            if flag is not None:
                out.append((f.name, flag, keys[f.name]))
        return out

    @classmethod
    def add_cli_arguments(cls, parser: Any, seen: set[str] | None = None,
                          sources: bool = False) -> None:
        """Add the ``run`` flags (a flag already in ``seen``, declared once by a field that
        two options classes share, is not added twice; ``sources``: only those that set a
        source's keys, ``Flag.sources``)."""
        flags = [(n, f, k) for n, f, k in cls.flags()
                 if (seen is None or f.name not in seen) and (f.sources or not sources)]
        if not flags:
            return
        group = parser.add_argument_group(cls.TITLE) if cls.TITLE else parser
        for _, flag, key in flags:
            add_flag(group, flag, key, cls.TITLE)
            if seen is not None:
                seen.add(flag.name)

    @classmethod
    def flag_values(cls, args: argparse.Namespace, sets: Callable[[str], str] = str,
                    sources: bool = False) -> tuple[dict[str, Any], bool]:
        """The keys the given flags set, each checked by its key (one line naming the flag,
        and the key as ``sets(key)``), and whether a flag that ``enables`` was among them.
        ``sources``: only the flags that set a source's keys (``Flag.sources``)."""
        opts: dict[str, Any] = {}
        enabled = False
        keys = cls.schema().keys
        for name, flag, _ in cls.flags():
            value = getattr(args, flag.dest, None)
            if value is None or (sources and not flag.sources):
                continue
            enabled = enabled or flag.enables
            values = value if flag.parse is not None else {name: value}
            for k, v in values.items():
                opts[k] = check_flag(flag.name, keys[k], v, sets(k))
        return opts, enabled

    @classmethod
    def cli_options(cls, args: argparse.Namespace, where: str = "") -> dict[str, Any] | None:
        """The options the given flags set (see :meth:`flag_values`; ``where`` names the
        table, e.g. ``backends.crsf``); None when no flag that ``enables`` was given."""
        opts, enabled = cls.flag_values(args, (lambda k: f"{where}.{k}") if where else str)
        return opts if enabled else None


def option_fields(cls: type) -> list[dataclasses.Field[Any]]:
    """The fields of an options class that are configuration keys."""
    return [f for f in dataclasses.fields(cls) if "option" in f.metadata]


def meta(f: dataclasses.Field[Any]) -> Meta:
    m: Meta = f.metadata["option"]
    return m


def key_of(f: dataclasses.Field[Any], annotation: Any) -> Key:
    """The :class:`Key` a field declares."""
    m = meta(f)
    kinds, nullable = _kind_of(annotation)
    if m.kind is not None:
        kinds = m.kind if isinstance(m.kind, tuple) else (m.kind,)
    if f.default is not dataclasses.MISSING:
        default = f.default
    elif f.default_factory is not dataclasses.MISSING:
        default = f.default_factory()
    else:
        default = REQUIRED
    return Key(kinds[0] if len(kinds) == 1 else kinds, default, m.help, m.choices, m.minimum,
               m.maximum, nullable, m.validator, m.secret)


def _kinds(key: Key) -> tuple[type, ...]:
    return key.kind if isinstance(key.kind, tuple) else (key.kind,)


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return repr(value)
    return str(value)


def flag_help(flag: Flag, key: Key, title: str = "") -> str:
    """A flag's help: its own text or the key's, what it allows, and the default."""
    text = flag.help or (f"{title}: {key.help}" if title else key.help)
    kinds = _kinds(key)
    notes = []
    if flag.parse is None and (int in kinds or float in kinds or key.choices is not None):
        notes.append(key.describe())
    if key.default not in (REQUIRED, None, "", []) and not key.secret and not flag.help:
        notes.append(f"default {_toml(key.default)}")
    if list in kinds and flag.parse is None and "repeatable" not in text:
        notes.append("repeatable")
    return f"{text} ({'; '.join(notes)})" if notes else text


def add_flag(parser: Any, flag: Flag, key: Key, title: str = "") -> None:
    """Add one flag: argparse converts nothing but a ``parse`` flag's text, so a bad value
    is refused by the key, in the words a file's would be."""
    kinds = _kinds(key)
    kwargs: dict[str, Any] = {"dest": flag.dest, "metavar": flag.metavar,
                              "help": flag_help(flag, key, title).replace("%", "%%")}
    if flag.parse is not None:
        kwargs["type"] = _argparse_type(flag.parse)
    elif flag.convert is not None:
        kwargs["type"] = _argparse_type(flag.convert)
    elif int in kinds or float in kinds:
        kwargs["type"] = flag_value
    if list in kinds and flag.parse is None:
        kwargs["action"] = "append"
    parser.add_argument(flag.name, **kwargs)


def _argparse_type(parse: Callable[[str], T]) -> Callable[[str], T]:
    def convert(text: str) -> T:
        try:
            return parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    return convert


def options_of(cls: Any) -> type[Options] | None:
    """The :class:`Options` class a backend or source class declares (``OPTIONS``), if any."""
    opts = getattr(cls, "OPTIONS", None)
    return opts if isinstance(opts, type) and issubclass(opts, Options) else None


#: The defaults of every listener's ``max_clients`` / ``client_timeout_s`` (gateway.io.server).
DEFAULT_MAX_CLIENTS = 32
DEFAULT_CLIENT_TIMEOUT_S = 5.0


@dataclass(frozen=True, kw_only=True)
class ListenerOptions(Options):
    """The options every backend with a TCP listener shares (MAVLink ``tcpin``, UAVTalk, F´,
    the HC-12 control socket, HTTP), declared once here and inherited."""

    max_clients: int = option(DEFAULT_MAX_CLIENTS, "clients a listener serves at once; more "
                              "are refused (counted)", minimum=1, maximum=1024)
    client_timeout_s: float = option(DEFAULT_CLIENT_TIMEOUT_S, "a client that stops reading "
                                     "(or leaves a request incomplete) this long is cut",
                                     minimum=0.1, maximum=600)
