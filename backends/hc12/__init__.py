"""HC-12 433 MHz radio backend: relay or re-transmit Aurora frames within the air link's
budget, and provision the module safely (``aurora-gateway hc12 …``).  See README.md."""

# The classes are imported on first use (PEP 562), not with the package, so that its light
# modules (``flags``: the run command's flags) cost nothing heavy to import.
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from backends.hc12.backend import Hc12Backend

_LAZY = {
    "Hc12Backend": "backends.hc12.backend",
}
__all__ = ["Hc12Backend"]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
