"""Counters: the base of every statistics dataclass (decoders, framers, ports, routers)."""

from __future__ import annotations

from dataclasses import dataclass, fields


@dataclass
class Counters:
    """A dataclass of integer counters; :meth:`as_dict` is what ``stats()`` reports."""

    def as_dict(self) -> dict[str, int]:
        """Every integer field by name (fields of other types, e.g. a breakdown by type, are
        left out)."""
        return {f.name: v for f in fields(self) if isinstance(v := getattr(self, f.name), int)}
