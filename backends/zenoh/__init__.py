"""Zenoh backend and source: every update published on Zenoh, and gateways fed from Zenoh.

See README.md in this directory for the key layout, the payloads, the configuration keys and
the fleet set-up.
"""

# The classes are imported on first use (PEP 562), not with the package, so that its light
# modules (``flags``: the run command's flags) cost nothing heavy to import.
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from backends.zenoh.backend import ZenohBackend
    from backends.zenoh.source import ZenohSource

_LAZY = {
    "ZenohBackend": "backends.zenoh.backend",
    "ZenohSource": "backends.zenoh.source",
}
__all__ = ["ZenohBackend", "ZenohSource"]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
