"""One HTTP connection of the status page: h11 (sans-I/O HTTP/1.1) as a port engine's protocol.

The engine (a :class:`~gateway.io.port.PortEngine` on the backend's loop, accepted by its
:class:`~gateway.io.server.PortServer`) feeds the bytes in; h11 turns them into a request; the
:class:`Site` answers it on the loop's thread.  One request per connection (every answer says
``Connection: close``), so a connection is either reading its request (``partial_since`` set:
the server cuts it if the request is not complete within ``client_timeout_s``), writing its
answer, or an event stream.  An event stream gets its events through the engine's bounded
queue: a viewer that stops reading fills it, events are dropped (counted) and the server cuts
it after ``client_timeout_s``.  What a client sends after its request is read and discarded.
"""

from __future__ import annotations

import logging
import socket
import time
from http import HTTPStatus
from typing import Any, Protocol

try:
    import h11
except ImportError as exc:  # an install without the extra: say which
    raise ImportError("the http backend needs h11 and prometheus-client: "
                      "pip install 'aurora-gateway[http]'") from exc

from gateway.io.port import PortEngine
from gateway.outcome import Outcome

log = logging.getLogger(__name__)

SERVER = "aurora-gateway"
#: The longest request head accepted (a longer one is answered 431 and closed).
MAX_HEAD = 16 * 1024
#: The longest request body read (only to answer 405: nothing here takes a body).
MAX_BODY = 64 * 1024
TEXT = "text/plain; charset=utf-8"


def refusal() -> bytes:
    """What a client past the cap gets before the connection is closed."""
    body = b"too many clients\n"
    return (b"HTTP/1.1 503 Service Unavailable\r\n"
            b"Content-Type: " + TEXT.encode() + b"\r\n"
            b"Content-Length: " + str(len(body)).encode() + b"\r\n"
            b"Retry-After: 5\r\nCache-Control: no-store\r\nConnection: close\r\n"
            b"Server: " + SERVER.encode() + b"\r\n\r\n" + body)


def has_request(sock: socket.socket) -> bool:
    """Does ``sock`` already hold a whole request head (looked at, not read)?"""
    try:
        data = sock.recv(MAX_HEAD, socket.MSG_PEEK | socket.MSG_DONTWAIT)
    except OSError:
        return False
    return b"\r\n\r\n" in data or b"\n\n" in data


class Site(Protocol):
    """What answers the requests (the backend)."""

    def answer(self, client: HttpClient, method: str, path: str) -> None: ...
    def bad_request(self) -> None: ...
    def stream_closed(self, client: HttpClient) -> None: ...


class HttpClient:
    """The protocol object of one connection (see the module doc)."""

    def __init__(self, site: Site, name: str) -> None:
        self.site = site
        self.name = name
        self.h11 = h11.Connection(h11.SERVER, max_incomplete_event_size=MAX_HEAD)
        self.engine: PortEngine | None = None
        self.streaming = False
        self.stream_started = 0.0
        self.events_dropped = 0
        self._request: h11.Request | None = None
        self._body = 0
        self._done = False  # the request is complete (or refused): further bytes are discarded

    def attach(self, engine: PortEngine) -> None:
        self.engine = engine
        engine.partial_since = time.monotonic()  # until its request is complete

    # -- the engine's protocol ----------------------------------------------------------------

    def feed(self, data: bytes) -> list[Any]:
        if self._done:
            return []
        conn = self.h11
        conn.receive_data(data)
        while not self._done:
            try:
                event = conn.next_event()
            except h11.RemoteProtocolError as exc:
                self._refuse_request(exc)
                break
            if event is h11.NEED_DATA or event is h11.PAUSED:
                break
            if isinstance(event, h11.Request):
                self._request = event
            elif isinstance(event, h11.Data):
                self._body += len(event.data)
                if self._body > MAX_BODY:
                    self._refuse_request(None, HTTPStatus.REQUEST_ENTITY_TOO_LARGE)
            elif isinstance(event, h11.EndOfMessage):
                self._done = True
                self._answer()
            elif isinstance(event, h11.ConnectionClosed):
                break
        return []

    def flush(self) -> list[Any]:
        """The connection ended."""
        if self.streaming:
            self.streaming = False
            self.site.stream_closed(self)
        return []

    # -- answering ------------------------------------------------------------------------------

    def _answer(self) -> None:
        request = self._request
        if request is None:
            return
        if self.engine is not None:
            self.engine.partial_since = None
        method = request.method.decode("ascii", "replace")
        path = request.target.decode("latin-1").split("?", 1)[0]
        self.site.answer(self, method, path)

    def _refuse_request(self, exc: h11.RemoteProtocolError | None,
                        status: int | None = None) -> None:
        self._done = True
        self.site.bad_request()
        code = status or (exc.error_status_hint if exc is not None else 400)
        if self.engine is not None:
            self.engine.partial_since = None
        if self.h11.our_state in (h11.IDLE, h11.SEND_RESPONSE):
            self.respond(code, f"{HTTPStatus(code).phrase}\n".encode(), TEXT)
        elif self.engine is not None:
            self.engine.finish()

    def respond(self, status: int, body: bytes, ctype: str, *, head: bool = False,
                extra: tuple[tuple[str, str], ...] = ()) -> None:
        """A whole answer, then the end of the connection."""
        headers = [("Content-Type", ctype), ("Content-Length", str(len(body))),
                   ("Cache-Control", "no-store"), *extra]
        data = self._head(status, headers)
        if not head and body:
            data += self.h11.send(h11.Data(data=body)) or b""
        data += self.h11.send(h11.EndOfMessage()) or b""
        self._write(data)
        if self.engine is not None:
            self.engine.finish()

    def start_stream(self, first: bytes, *, head: bool = False) -> None:
        """Answer with an event stream; ``first``: what it starts with."""
        data = self._head(200, [("Content-Type", "text/event-stream"),
                                ("Cache-Control", "no-store")])
        if head:
            data += self.h11.send(h11.EndOfMessage()) or b""
            self._write(data)
            if self.engine is not None:
                self.engine.finish()
            return
        self.streaming = True
        self.stream_started = time.monotonic()
        self._write(data + (self.h11.send(h11.Data(data=first)) or b""))

    def end_stream(self) -> None:
        """End the event stream (the viewer's EventSource reconnects by itself); the
        connection closes once the end is written."""
        if not self.streaming or self.engine is None:
            return
        self.streaming = False
        self.site.stream_closed(self)
        self._write(self.h11.send(h11.EndOfMessage()) or b"")
        self.engine.finish()

    def send_event(self, event: bytes) -> Outcome:
        """One more event of the stream, through the bounded queue (QUEUE_FULL: dropped)."""
        if not self.streaming or self.engine is None:
            return Outcome.NOT_READY
        outcome = self.engine.submit(self.h11.send(h11.Data(data=event)) or b"",
                                     rate_limited=False)
        if outcome is Outcome.QUEUE_FULL:
            self.events_dropped += 1
        return outcome

    def _head(self, status: int, headers: list[tuple[str, str]]) -> bytes:
        headers = [*headers, ("Connection", "close"), ("Server", SERVER)]
        reason = HTTPStatus(status).phrase.encode()
        return self.h11.send(h11.Response(status_code=status, headers=headers,
                                          reason=reason)) or b""

    def _write(self, data: bytes) -> None:
        if self.engine is not None:
            self.engine.submit(data, rate_limited=False)
