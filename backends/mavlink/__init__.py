"""MAVLink: the rocket as a vehicle QGroundControl, MAVProxy and MAVSDK understand, a
mavlink-router-style router between endpoints, MAVLink 2 signing, and MAVLink vehicles as a
source.  See ``backends/mavlink/README.md``."""

# The classes are imported on first use (PEP 562), not with the package, so that its light
# modules (``flags``: the run command's flags) cost nothing heavy to import.
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from backends.mavlink.backend import MavlinkBackend
    from backends.mavlink.source import MavlinkSource

_LAZY = {
    "MavlinkBackend": "backends.mavlink.backend",
    "MavlinkSource": "backends.mavlink.source",
}
__all__ = ["MavlinkBackend", "MavlinkSource"]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
