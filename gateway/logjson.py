"""Log records as JSON lines, for ``--log-format json`` (journald, log shippers, ``jq``).

One JSON object a line: ``time`` (ISO-8601, UTC, milliseconds), ``level`` (``INFO``…),
``logger``, ``message`` (the formatted text), and, when the record carries them, ``exc``
(the exception's traceback text) and ``stack``.  Output is ASCII: anything else is escaped,
so the lines survive any locale.  The lines a command writes itself (``run``'s start line,
status lines and stop report) go through :func:`say`: plain text, or in JSON mode an object of
the same form (logger ``aurora-gateway.report``), so a JSON log holds nothing but JSON;
``fields`` give a line's figures as keys of their own (:func:`jsonable` makes them plain
JSON).

Each record reaches the file descriptor in one ``os.write`` of the whole line (when the stream
has one), past the stream's buffer: ``print`` writes a line's text and its newline
separately, and a record logged by another thread in between would otherwise land in the
middle of that line.  Lines are at most a few KiB, below a pipe's atomic-write size.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
from typing import Any, TextIO

FORMATS = ("text", "json")
TEXT_FORMAT = "%(asctime)s %(levelname)-7s %(name)s: %(message)s"
#: The logger named on a command's own lines in JSON mode (:func:`say`).
REPORT_LOGGER = "aurora-gateway.report"
_json_mode = False  # set by setup_logging


class JsonFormatter(logging.Formatter):
    """Formats a record as one JSON object on one line."""

    def format(self, record: logging.LogRecord) -> str:
        from datetime import UTC, datetime  # here: a text-logging start needs none of it

        doc: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, tz=UTC).isoformat(
                timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info and not record.exc_text:
            record.exc_text = self.formatException(record.exc_info)
        if record.exc_text:
            doc["exc"] = record.exc_text
        if record.stack_info:
            doc["stack"] = self.formatStack(record.stack_info)
        fields = getattr(record, "fields", None)  # a report line's figures (say's fields)
        if fields:
            doc.update({k: jsonable(v) for k, v in fields.items() if k not in doc})
        return json.dumps(doc, ensure_ascii=True)


def json_mode() -> bool:
    """True once :func:`setup_logging` chose JSON lines."""
    return _json_mode


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values: tuples and sets as lists, keys as strings, a float that
    is not finite as None (JSON has no NaN), anything else as its ``str``."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set | frozenset):
        return [jsonable(v) for v in obj]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, str | int | bool):
        return obj
    return str(obj)


def write_line(stream: TextIO, line: str) -> None:
    """``line`` (ending in a newline) to ``stream`` in one write of its descriptor, when it has
    one, so that no other thread's line lands inside it."""
    try:
        fd: int | None = stream.fileno()
    except (AttributeError, OSError, ValueError):
        fd = None
    if fd is None:
        stream.write(line)
        stream.flush()
        return
    encoding = getattr(stream, "encoding", None) or "utf-8"
    data = memoryview(line.encode(encoding, "backslashreplace"))
    while data:
        data = data[os.write(fd, data):]


def say(text: str, stream: TextIO | None = None, level: int = logging.INFO,
        fields: dict[str, Any] | None = None) -> None:
    """One of a command's own lines (a start line, a status line, the stop report) to
    ``stream`` (default stderr): plain, or one JSON object at ``level`` in JSON mode, with
    ``fields`` (JSON values) as keys of their own besides the standard ones."""
    if _json_mode:
        record = logging.LogRecord(REPORT_LOGGER, level, "", 0, text, None, None)
        record.fields = fields
        text = JsonFormatter().format(record)
    write_line(sys.stderr if stream is None else stream, text + "\n")


class LineHandler(logging.StreamHandler[TextIO]):
    """A stream handler that writes each record as one whole line in one write."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            write_line(self.stream, self.format(record) + self.terminator)
        except RecursionError:
            raise
        except Exception:
            self.handleError(record)


def setup_logging(level: str | None, fmt: str | None = "text",
                  stream: TextIO | None = None) -> None:
    """Configure the root logger once (as :func:`logging.basicConfig` does): ``level`` by
    name (default info), ``fmt`` ``"text"`` or ``"json"``, to ``stream`` (default stderr)."""
    global _json_mode
    if fmt not in (None, *FORMATS):
        raise ValueError(f"log format: expected one of {', '.join(FORMATS)}, got {fmt!r}")
    _json_mode = fmt == "json"
    handler = LineHandler(sys.stderr if stream is None else stream)
    handler.setFormatter(JsonFormatter() if fmt == "json" else logging.Formatter(TEXT_FORMAT))
    logging.basicConfig(level=getattr(logging, (level or "info").upper()), handlers=[handler])
