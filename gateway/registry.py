"""Backends, sources and commands found by name, imported lazily (python-can's ``BACKENDS``
idiom).

The entry-point groups below are the one list: the built-ins are declared in this project's
``pyproject.toml`` exactly as a third-party package declares its own, so the package must be
installed (``pip install -e .`` for a checkout; ``make`` does it) for its metadata to exist.
Adding a backend touches neither the dispatcher nor the CLI.

A backend's (or source's) options are found apart from its class, in
``BACKEND_OPTIONS_GROUP`` (``SOURCE_OPTIONS_GROUP``): same name, its
:class:`gateway.options.Options` dataclass in a light module, which has
``add_cli_arguments(parser)`` and ``cli_options(args)``.  So building ``run``'s parser imports
no backend: the class (and pymavlink, Zenoh…) is imported only for a backend the configuration
runs.  A backend with no entry there has its class used instead (:func:`load_flags`).

An optional dependency that is not installed (a base install running ``--foxglove``) is named
by the extra that provides it (:data:`EXTRA_OF_MODULE`, :func:`missing_extra`):
:func:`load` raises :class:`MissingExtra`, whose text is the one line the user sees, and the
command line maps a command's own ``ModuleNotFoundError`` the same way.
"""

from __future__ import annotations

import functools
import importlib
import os
import re
import sys
from typing import Any

from gateway.exits import signalled

BACKEND_GROUP = "aurora_gateway.backends"
SOURCE_GROUP = "aurora_gateway.sources"
COMMAND_GROUP = "aurora_gateway.commands"
BACKEND_OPTIONS_GROUP = "aurora_gateway.backend_options"
SOURCE_OPTIONS_GROUP = "aurora_gateway.source_options"

DISTRIBUTION = "aurora-gateway"

#: Top-level module → the extra of this distribution that installs it: the one table from which
#: every "needs the 'x' extra" line comes.  pyproject.toml's ``[project.optional-dependencies]``
#: says which distributions each extra installs; tests/test_packaging.py proves the two agree.
EXTRA_OF_MODULE = {
    "foxglove": "foxglove",              # foxglove-sdk: backends/foxglove
    "h11": "http",                       # backends/http's HTTP/1.1 parser
    "prometheus_client": "http",         # backends/http's /metrics
    "mcap": "mcap",                      # export --format mcap
    "matplotlib": "plot",                # plot
    "gpiod": "gpio",                     # the HC-12 SET line on a Linux GPIO
    "cyclonedds": "ros2",                # backends/ros2's DDS writers (Cyclone DDS)
    "rosbags": "ros2",                   # export --format rosbag2
    "xxhash": "ros2",                    # the rmw_zenoh topics' publisher GIDs
}

_cache: dict[tuple[str, str], Any] = {}


class RegistryError(LookupError):
    """No backend or source by that name, or it failed to import."""


class MissingExtra(RegistryError):
    """A backend, source or command needs an optional dependency that is not installed; the
    text is one line naming the extra that installs it."""

    def __init__(self, what: str, extra: str) -> None:
        super().__init__(extra_line(what, extra))
        self.what = what
        self.extra = extra


def extra_line(what: str, extra: str) -> str:
    """``what`` needs ``extra``, and the command that installs it."""
    return f"{what} needs the {extra!r} extra: pip install '{DISTRIBUTION}[{extra}]'"


def missing_extra(exc: BaseException) -> str | None:
    """The extra that provides the module whose absence caused ``exc`` (a
    ``ModuleNotFoundError``, or an error raised from or while handling one: the chain a
    traceback would show is followed); None when that module belongs to no extra (a bug or a
    broken install, not a choice)."""
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        if isinstance(cur, ModuleNotFoundError) and cur.name:
            extra = EXTRA_OF_MODULE.get(cur.name.partition(".")[0])
            if extra is not None:
                return extra
        # as a traceback shows the chain: the cause, else the context unless "from None"
        cur = cur.__cause__ if cur.__cause__ is not None else (
            None if cur.__suppress_context__ else cur.__context__)
    return None


_KINDS = {BACKEND_GROUP: "backend", SOURCE_GROUP: "source", COMMAND_GROUP: "command",
          BACKEND_OPTIONS_GROUP: "backend's options", SOURCE_OPTIONS_GROUP: "source's options"}


def names(group: str) -> dict[str, str]:
    """Every name installed in ``group`` → its ``module:attr`` target, sorted by name."""
    return dict(_installed().get(group, ()))


@functools.cache
def _installed() -> dict[str, tuple[tuple[str, str], ...]]:
    """Every group's entry points (sorted), read once: scanning the installed distributions
    is slow, and they do not change while the gateway runs.  A test that installs a plug-in
    mid-run calls ``_installed.cache_clear()``."""
    found = _read_entry_points()
    if found is None:  # a path this scan does not read (a zip): the standard library's way
        from importlib.metadata import entry_points

        found = {group: [(ep.name, ep.value) for ep in entry_points(group=group)]
                 for group in entry_points().groups}
    return {group: tuple(sorted(eps)) for group, eps in found.items()}


_DIST_DIR = re.compile(r"^([^-]+)(?:-[^/]*)?\.(?:dist|egg)-info$")


def _read_entry_points() -> dict[str, list[tuple[str, str]]] | None:
    """Every group's entry points of the distributions on ``sys.path``, as
    :func:`importlib.metadata.entry_points` finds them (the first distribution of a name on
    the path wins; ``entry_points.txt`` in each ``*.dist-info``/``*.egg-info`` directory),
    without importing :mod:`importlib.metadata` (email, zipfile, csv …: a fifth of the
    start-up).  None when a path entry is not a directory (a zip): then use the library."""
    groups: dict[str, list[tuple[str, str]]] = {}
    seen: set[str] = set()
    for entry in sys.path:
        path = entry or "."
        if not os.path.isdir(path):
            if os.path.exists(path):
                return None
            continue
        try:
            names = os.listdir(path)
        except OSError:
            continue
        for name in names:
            m = _DIST_DIR.match(name)
            if m is None:
                continue
            dist = re.sub(r"[-_.]+", "_", m.group(1)).lower()
            if dist in seen:
                continue
            try:
                with open(os.path.join(path, name, "entry_points.txt"), encoding="utf-8") as f:
                    text = f.read()
            except OSError:  # no entry points, or an egg-info file, not a directory
                if os.path.isdir(os.path.join(path, name)):
                    seen.add(dist)
                continue
            seen.add(dist)
            _parse_entry_points(text, groups)
    return groups


def _parse_entry_points(text: str, groups: dict[str, list[tuple[str, str]]]) -> None:
    """``entry_points.txt`` (INI: ``[group]`` then ``name = value`` lines) into ``groups``."""
    current: list[tuple[str, str]] | None = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = groups.setdefault(line[1:-1].strip(), [])
            continue
        name, sep, value = line.partition("=")
        if sep and current is not None:
            current.append((name.strip(), value.strip()))


def load(group: str, name: str) -> Any:
    """Import and return the class registered as ``name`` in ``group``."""
    key = (group, name)
    if key in _cache:
        return _cache[key]
    targets = names(group)
    target = targets.get(name)
    if target is None:
        kind = _KINDS.get(group, group)
        available = ", ".join(targets) or (
            "none (no aurora_gateway entry points: install the package, pip install -e .)")
        raise RegistryError(f"unknown {kind} {name!r}; available: {available}")
    module_name, _, attr = target.partition(":")
    try:
        obj = importlib.import_module(module_name)
        for part in attr.split(".") if attr else ():  # "module" alone names the module
            obj = getattr(obj, part)
    except Exception as exc:  # ImportError, AttributeError, or whatever a plug-in raises
        if signalled(exc) is not None:  # a Ctrl-C or SIGTERM while the module was executing
            raise                       # (wrapped by a class's creation): not an import error
        extra = missing_extra(exc)
        if extra is not None:
            raise MissingExtra(f"{_KINDS.get(group, group)} {name}", extra) from exc
        raise RegistryError(f"{name!r} ({target}) failed to import: "
                            f"{type(exc).__name__}: {exc}") from exc
    _cache[key] = obj
    return obj


def backend_names() -> list[str]:
    return list(names(BACKEND_GROUP))


def source_names() -> list[str]:
    return list(names(SOURCE_GROUP))


def load_flags(name: str) -> Any:
    """What adds backend ``name``'s flags and reads them back: its options class from
    ``BACKEND_OPTIONS_GROUP`` (imports nothing heavy), else its class (which has the two
    classmethods, as every :class:`gateway.backend.Backend` does).  RegistryError if neither
    imports."""
    if name in names(BACKEND_OPTIONS_GROUP):
        return load(BACKEND_OPTIONS_GROUP, name)
    return load(BACKEND_GROUP, name)


def load_source_options(name: str) -> Any:
    """Source type ``name``'s options class: its ``SOURCE_OPTIONS_GROUP`` entry (imports
    nothing heavy), else its class's ``OPTIONS``; None for a source with neither (a plug-in
    with its own ``CONFIG``).  RegistryError if it fails to import."""
    if name in names(SOURCE_OPTIONS_GROUP):
        return load(SOURCE_OPTIONS_GROUP, name)
    return getattr(load(SOURCE_GROUP, name), "OPTIONS", None)
