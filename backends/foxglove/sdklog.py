"""What foxglove-sdk logs per client, bounded: :func:`install` and :data:`CLIENT_LINES`.

The SDK's server logs (through Python's :mod:`logging`, its Rust modules as logger names) a
line per client event — ``Dropping client …: handshake failed`` and ``Error receiving from
client …: Connection reset by peer`` at ERROR for a client that just left, ``Registered`` /
``Unregistered client`` at INFO — and a line per client *message* for some (``Invalid message
from …`` at ERROR, ``outbox for client … full`` at INFO for every message a slow client
loses): a client could fill the log.  Behind :class:`~backends.foxglove.relay.ProtocolRelay`
every client the SDK sees is the relay on loopback, so those lines name no one either.

:func:`install` puts a filter on those loggers that takes the per-client lines out (they pass,
as DEBUG, only when that logger is set to DEBUG) and counts them by kind
(:data:`CLIENT_LINES`); the backend logs the counts of what the relay cannot see itself (bad
client messages, messages dropped for slow clients) once per interval
(:func:`take_counts`).  Every other line of the SDK passes as it was.
"""

from __future__ import annotations

import logging
import threading

#: The SDK's loggers that write per-client lines (pyo3-log names them after the Rust modules).
LOGGERS = ("foxglove.websocket.server", "foxglove.websocket.connected_client",
           "foxglove.websocket.connected_client.poller",
           "foxglove.websocket.connected_client.send_lossy")

#: The start of each per-client line → its kind.  ``connection``: a client came or went
#: (the relay logs those, with the client's address); ``server``: the SDK's own server
#: started or stopped on its loopback port (the backend logs the public one).
CLIENT_LINES = {
    "Registered client": "connection",
    "Unregistered client": "connection",
    "Connection closed by client": "connection",
    "Error receiving from client": "connection",
    "Error sending message to client": "connection",
    "Dropping client": "connection",
    "Started server on": "server",
    "Shutting down": "server",
    "Shutdown complete": "server",
    "Invalid message from": "bad_messages",
    "Received message for unknown channel": "bad_messages",
    "Failed to parse advertised channel": "bad_messages",
    "Client ": "bad_messages",  # "Client … attempted to subscribe to unknown channel"
    "outbox for client": "dropped_slow",
}
#: The kinds the backend reports (the others are the relay's or nothing to report).
REPORTED = ("bad_messages", "dropped_slow")


def kind_of(line: str) -> str | None:
    """The kind of a per-client line of the SDK (None: not one)."""
    for start, kind in CLIENT_LINES.items():
        if line.startswith(start):
            return kind
    return None


class _ClientLines(logging.Filter):
    """Counts the per-client lines and keeps them out of the log (unless DEBUG)."""

    def __init__(self) -> None:
        super().__init__("foxglove-sdk per-client lines")
        self._lock = threading.Lock()
        self.counts: dict[str, int] = {}  # since the last take()
        self.totals: dict[str, int] = {}  # since the start

    def filter(self, record: logging.LogRecord) -> bool:
        kind = kind_of(record.msg if isinstance(record.msg, str) else str(record.msg))
        if kind is None:
            return True
        with self._lock:
            self.counts[kind] = self.counts.get(kind, 0) + 1
            self.totals[kind] = self.totals.get(kind, 0) + 1
        if not logging.getLogger(record.name).isEnabledFor(logging.DEBUG):
            return False
        record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return True

    def take(self) -> dict[str, int]:
        with self._lock:
            counts, self.counts = self.counts, {}
        return counts


_FILTER = _ClientLines()
_installed = threading.Lock()


def install() -> None:
    """Put the filter on the SDK's loggers (once per process; safe to call again)."""
    with _installed:
        for name in LOGGERS:
            logger = logging.getLogger(name)
            if _FILTER not in logger.filters:
                logger.addFilter(_FILTER)


def take_counts() -> dict[str, int]:
    """The per-client lines kept out since the last call, by kind (process-wide: the SDK's
    loggers are)."""
    return _FILTER.take()


def total(kind: str) -> int:
    """The per-client lines of ``kind`` kept out since the process started."""
    return _FILTER.totals.get(kind, 0)


def summary(counts: dict[str, int]) -> str:
    """The reported kinds of ``counts`` in words ('' when there are none)."""
    words = {"bad_messages": "client messages the SDK could not use",
             "dropped_slow": "messages dropped for slow clients"}
    return ", ".join(f"{counts[k]} {words[k]}" for k in REPORTED if counts.get(k))
