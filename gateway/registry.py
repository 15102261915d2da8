"""Backends and sources found by name, imported lazily (python-can's ``BACKENDS`` idiom).

Names come from the entry-point groups below (declared in ``pyproject.toml``; any installed
package can add its own) plus the built-ins, so a source checkout works before it is
installed.  Adding a backend touches neither the dispatcher nor the CLI.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

BACKEND_GROUP = "aurora_gateway.backends"
SOURCE_GROUP = "aurora_gateway.sources"
COMMAND_GROUP = "aurora_gateway.commands"

_BUILTIN: dict[str, dict[str, str]] = {
    BACKEND_GROUP: {
        "console": "backends.console:ConsoleBackend",
        "mavlink": "backends.mavlink:MavlinkBackend",
        "crsf": "backends.crsf:CrsfBackend",
        "zenoh": "backends.zenoh:ZenohBackend",
        "hc12": "backends.hc12:Hc12Backend",
    },
    SOURCE_GROUP: {
        "serial": "gateway.sources.serial_source:SerialSource",
        "sim": "gateway.sources.sim:SimSource",
        "replay": "gateway.sources.replay:ReplaySource",
        "mavlink": "backends.mavlink:MavlinkSource",
        "zenoh": "backends.zenoh:ZenohSource",
    },
    COMMAND_GROUP: {
        "listen": "backends.zenoh.cli:add_command",
        "hc12": "backends.hc12.cli:add_command",
    },
}

_cache: dict[tuple[str, str], Any] = {}


class RegistryError(LookupError):
    """No backend or source by that name, or it failed to import."""


def names(group: str) -> dict[str, str]:
    """Every registered name in ``group`` → its ``module:attr`` target."""
    found = dict(_BUILTIN.get(group, {}))
    for ep in entry_points(group=group):
        found[ep.name] = ep.value
    return dict(sorted(found.items()))


def load(group: str, name: str) -> Any:
    """Import and return the class registered as ``name`` in ``group``."""
    key = (group, name)
    if key in _cache:
        return _cache[key]
    targets = names(group)
    target = targets.get(name)
    if target is None:
        kind = {BACKEND_GROUP: "backend", SOURCE_GROUP: "source",
                COMMAND_GROUP: "command"}.get(group, group)
        raise RegistryError(
            f"unknown {kind} {name!r}; available: {', '.join(targets) or 'none'}"
        )
    module_name, _, attr = target.partition(":")
    try:
        obj = importlib.import_module(module_name)
        for part in attr.split("."):
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
