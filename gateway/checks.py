"""Argument checks of the core's constructors, with one wording for each kind of mistake
(``queue_depth must be at least 1``, ``hold_s must not be negative`` …).  Configuration values
are checked by their option declarations (:mod:`gateway.options`); these guard the Python API."""

from __future__ import annotations


def at_least(name: str, value: float, low: float) -> None:
    """ValueError unless ``value >= low``."""
    if not value >= low:
        raise ValueError(f"{name} must be at least {low:g}")


def positive(name: str, value: float) -> None:
    """ValueError unless ``value > 0``."""
    if not value > 0:
        raise ValueError(f"{name} must be positive")


def not_negative(name: str, value: float) -> None:
    """ValueError unless ``value >= 0``."""
    if not value >= 0:
        raise ValueError(f"{name} must not be negative")
