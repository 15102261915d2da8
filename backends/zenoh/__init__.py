"""Zenoh backend and source: every update published on Zenoh, and gateways fed from Zenoh.

See README.md in this directory for the key layout, the payloads, the configuration keys and
the fleet set-up.
"""

from __future__ import annotations

from backends.zenoh.backend import ZenohBackend
from backends.zenoh.source import ZenohSource

__all__ = ["ZenohBackend", "ZenohSource"]
