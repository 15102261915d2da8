"""CRSF / ExpressLRS backend: the rocket's state, altitude, vertical speed, attitude and
health as telemetry sensors on an EdgeTX radio (see README.md in this directory)."""

# The classes are imported on first use (PEP 562), not with the package, so that its light
# modules (``flags``: the run command's flags) cost nothing heavy to import.
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from backends.crsf.backend import CrsfBackend

_LAZY = {
    "CrsfBackend": "backends.crsf.backend",
}
__all__ = ["CrsfBackend"]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
