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
"""

from __future__ import annotations

import functools
import importlib
from importlib.metadata import entry_points
from typing import Any

BACKEND_GROUP = "aurora_gateway.backends"
SOURCE_GROUP = "aurora_gateway.sources"
COMMAND_GROUP = "aurora_gateway.commands"
BACKEND_OPTIONS_GROUP = "aurora_gateway.backend_options"
SOURCE_OPTIONS_GROUP = "aurora_gateway.source_options"

_cache: dict[tuple[str, str], Any] = {}


class RegistryError(LookupError):
    """No backend or source by that name, or it failed to import."""


def names(group: str) -> dict[str, str]:
    """Every name installed in ``group`` → its ``module:attr`` target, sorted by name."""
    return dict(_installed(group))


@functools.cache
def _installed(group: str) -> tuple[tuple[str, str], ...]:
    """``group``'s entry points, read once: scanning the installed distributions is slow
    (every ``names`` call was a scan), and they do not change while the gateway runs.  A test
    that installs a plug-in mid-run calls ``_installed.cache_clear()``."""
    return tuple(sorted((ep.name, ep.value) for ep in entry_points(group=group)))


def load(group: str, name: str) -> Any:
    """Import and return the class registered as ``name`` in ``group``."""
    key = (group, name)
    if key in _cache:
        return _cache[key]
    targets = names(group)
    target = targets.get(name)
    if target is None:
        kind = {BACKEND_GROUP: "backend", SOURCE_GROUP: "source", COMMAND_GROUP: "command",
                BACKEND_OPTIONS_GROUP: "backend's options",
                SOURCE_OPTIONS_GROUP: "source's options"}.get(group, group)
        available = ", ".join(targets) or (
            "none (no aurora_gateway entry points: install the package, pip install -e .)")
        raise RegistryError(f"unknown {kind} {name!r}; available: {available}")
    module_name, _, attr = target.partition(":")
    try:
        obj = importlib.import_module(module_name)
        for part in attr.split(".") if attr else ():  # "module" alone names the module
            obj = getattr(obj, part)
    except Exception as exc:  # ImportError, AttributeError, or whatever a plug-in raises
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
