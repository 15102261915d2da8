"""The HTTP status page and Prometheus metrics backend (``run --http HOST:PORT``)."""

from __future__ import annotations

from .backend import HttpBackend

__all__ = ["HttpBackend"]
