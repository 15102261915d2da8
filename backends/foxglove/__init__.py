"""Foxglove live backend: the flight on the Foxglove WebSocket protocol (``foxglove-sdk``).

The class lives in :mod:`backends.foxglove.backend` (imported only when the backend runs);
its ``run`` flags in :mod:`backends.foxglove.flags` (standard library only)."""
