"""The control socket: how ``aurora-gateway hc12 …`` reaches a running gateway's HC-12 backend.

A running gateway owns the port (opened exclusively) through its port engine.  An AT exchange
must take the port from that engine (:meth:`gateway.io.port.PortEngine.exclusive`) and know the
vehicle's state, so the command-line tool does not open the port itself: it sends its request
over a Unix socket that the backend serves, and the backend runs the exchange itself,
applying its own knowledge of the vehicle (the latest SM_UPDATE/STATUS it relayed).

* The socket lives in a per-user directory: ``$XDG_RUNTIME_DIR/aurora-gateway/`` or else
  ``/tmp/aurora-gateway-<uid>/`` (created 0700, refused if anyone else owns it or may write
  to it); the socket itself is 0600.  Its name is derived from the port URL, so the tool finds
  the gateway driving ``--port`` without being told; ``control = "PATH"`` /
  ``--gateway PATH`` name it explicitly.
* One request per connection: a JSON object on one line (``{"op": "channel", "arg": "5",
  "bench": false}``), answered by one JSON line (a :class:`~backends.hc12.provision.Result`).
  Both ends read with the one sans-I/O :class:`JsonLines` reader.
* The server is a :class:`~gateway.io.server.PortServer` on an
  :class:`~gateway.io.ioloop.IoLoop` — the backend passes its port engine's, so a request runs
  on the thread that owns the port and connections need no threads of their own; each is a
  :class:`~gateway.io.port.PortEngine` writing its answer through a bounded queue.  At most
  ``max_clients`` connections at once (more are refused, counted); a client that sends no
  whole request, or does not read its answer, within ``client_timeout_s`` is cut.
* If the client goes away mid-exchange (Ctrl-C), the backend still completes the exchange and
  restores the port itself.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
import socket
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gateway.io.ioloop import IoLoop
from gateway.io.port import PortEngine
from gateway.io.server import (
    BACKLOG,
    DEFAULT_CLIENT_TIMEOUT_S,
    ClientLimits,
    PortServer,
    server_stats,
)
from gateway.io.transport import SocketPort

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
MAX_REQUEST = 4096
MAX_REPLY = 1 << 20
#: How long a client may take to send its request (and to read the answer) when the server
#: is not given :class:`~gateway.io.server.ClientLimits`.
REQUEST_TIMEOUT_S = DEFAULT_CLIENT_TIMEOUT_S


def runtime_dir(create: bool = True) -> Path:
    """The per-user directory for control sockets (created if missing and ``create``, checked
    if present)."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    path = Path(base) / "aurora-gateway" if base else Path(f"/tmp/aurora-gateway-{os.getuid()}")
    if not create and not path.exists():
        return path  # nothing serves there; a lookup must not leave directories behind
    path.mkdir(mode=0o700, parents=False, exist_ok=True)
    st = path.lstat()
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o022:
        raise OSError(f"{path} is not a private directory of this user; refusing to use it")
    return path


def socket_path_for(url: str, directory: Path | None = None, create: bool = True) -> Path:
    """The control socket of the gateway driving the HC-12 at ``url``."""
    slug = re.sub(r"[^A-Za-z0-9]+", "_", url).strip("_")[-24:].strip("_") or "port"
    digest = hashlib.sha1(url.encode()).hexdigest()[:8]
    return (directory or runtime_dir(create)) / f"hc12-{slug}-{digest}.sock"


def resolve(control: str, url: str, create: bool = True) -> Path | None:
    """The socket path for a ``control`` setting: ``auto`` (derived from the URL), ``off``
    (None) or a path.  ``create`` False: only look (the command line), never make the
    directory."""
    if control == "off":
        return None
    if control == "auto":
        return socket_path_for(url, create=create)
    return Path(control)


class BadMessage(ValueError):
    """A control line that is not one JSON object (or is too long)."""


class JsonLines:
    """Sans-I/O reader of the control protocol, both ends: bytes in, one event per line out —
    the JSON object, or a :class:`BadMessage`.  A line longer than ``limit`` is a
    :class:`BadMessage` and is dropped."""

    def __init__(self, limit: int = MAX_REQUEST) -> None:
        self.limit = limit
        self._buf = b""
        self._skipping = False  # inside an over-long line: drop up to its end

    def feed(self, data: bytes) -> list[dict[str, Any] | BadMessage]:
        self._buf += data
        out: list[dict[str, Any] | BadMessage] = []
        while True:
            line, sep, rest = self._buf.partition(b"\n")
            if not sep:
                if len(self._buf) > self.limit and not self._skipping:
                    out.append(BadMessage(f"a line longer than {self.limit} bytes"))
                    self._skipping = True
                if self._skipping:
                    self._buf = b""
                return out
            self._buf = rest
            if self._skipping:
                self._skipping = False
            elif len(line) > self.limit:
                out.append(BadMessage(f"a line longer than {self.limit} bytes"))
            else:
                out.append(_parse(line))

    def flush(self) -> list[dict[str, Any] | BadMessage]:
        """End of the stream: a last line without its newline still counts."""
        line, self._buf = self._buf, b""
        if not line.strip() or self._skipping:
            return []
        return [_parse(line)]


def _parse(line: bytes) -> dict[str, Any] | BadMessage:
    try:
        value = json.loads(line or b"null")
    except ValueError as exc:
        return BadMessage(str(exc))
    if not isinstance(value, dict):
        return BadMessage("expected a JSON object")
    return value


def encode_line(message: dict[str, Any]) -> bytes:
    return json.dumps(message).encode() + b"\n"


class ControlServer:
    """Serves one-line JSON requests on a Unix socket, on ``loop`` (see the module doc)."""

    def __init__(self, path: Path, handler: Callable[[dict[str, Any]], dict[str, Any]],
                 loop: IoLoop, name: str = "hc12", limits: ClientLimits | None = None) -> None:
        self.path = Path(path)
        self.limits = limits or ClientLimits(client_timeout_s=REQUEST_TIMEOUT_S, queue_depth=2)
        self.handler = handler
        self.loop = loop
        self.name = name
        self.requests = 0
        self._inode: int | None = None
        self._bound: socket.socket | None = None
        self._server: PortServer | None = None
        self._clients: set[_Client] = set()
        self.listener: PortServer | None = None  # kept after close() for stats

    def start(self) -> None:
        """Bind (now, so a clash is known at once) and serve on the loop; raises OSError if
        another live server already answers there."""
        self._bound = self._listen()
        server = PortServer(self._listener, self._accepted, loop=self.loop,
                            name=f"{self.name} control", limits=self.limits)
        self._server = server
        self.listener = server
        server.start()

    def _listen(self) -> socket.socket:
        if self.path.exists() or self.path.is_symlink():
            if _alive(self.path):
                raise OSError(f"{self.path} is served by another running gateway")
            self.path.unlink()  # left behind by a gateway that died
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o177)
        try:
            sock.bind(str(self.path))
            os.chmod(self.path, 0o600)
            self._inode = self.path.stat().st_ino
            sock.listen(BACKLOG)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        finally:
            os.umask(old_umask)
        return sock

    def _listener(self) -> socket.socket:
        """The PortServer's opener: the socket bound by start(), later a fresh one."""
        sock, self._bound = self._bound, None
        return sock if sock is not None else self._listen()

    def _accepted(self, conn: socket.socket, _addr: Any) -> PortEngine:
        client = _Client(self)
        self._clients.add(client)

        def on_link(up: bool) -> None:
            if not up:
                self._clients.discard(client)

        engine = PortEngine(_not_reopened, name=f"{self.name} control client",
                            protocol=client, loop=self.loop,
                            queue_depth=self.limits.queue_depth, reopen=False, on_link=on_link,
                            hangup_level=logging.DEBUG)
        client.engine = engine
        engine.partial_since = time.monotonic()  # until its request line is complete
        engine.start_with(SocketPort(conn))
        return engine

    def answer(self, request: dict[str, Any] | BadMessage) -> dict[str, Any]:
        """The reply to one request (on the loop's thread); never raises."""
        if isinstance(request, BadMessage):
            return {"ok": False, "op": "", "kind": "usage",
                    "error": f"bad control request: {request}"}
        self.requests += 1
        try:
            return self.handler(request)
        except Exception as exc:  # never let one request kill the server
            log.exception("%s: control request failed", self.name)
            return {"ok": False, "op": str(request.get("op", "")), "kind": "failed",
                    "error": f"{type(exc).__name__}: {exc}"}

    def close(self) -> None:
        """Stop serving, drop open connections and remove the socket file (if it is still
        ours); safe twice, from any thread."""
        server, self._server = self._server, None
        if server is not None:
            server.close()
        bound, self._bound = self._bound, None
        if bound is not None:
            bound.close()
        _on_loop(self.loop, self._drop_clients)
        if self._inode is not None:
            with contextlib.suppress(OSError):
                if self.path.stat().st_ino == self._inode:
                    self.path.unlink()
            self._inode = None

    def _drop_clients(self) -> None:
        for client in list(self._clients):
            if client.engine is not None:
                client.engine.close(0.2)
        self._clients.clear()

    def stats(self) -> dict[str, int]:
        """The listener's refusals and cuts (see :func:`gateway.io.server.server_stats`)."""
        server = self.listener
        return server_stats((server,) if server is not None else ())


def _not_reopened() -> Any:
    raise OSError("a control connection is not reopened")


class _Client:
    """One control connection (its engine's protocol): the request line, then the answer."""

    def __init__(self, server: ControlServer) -> None:
        self.server = server
        self.reader = JsonLines(MAX_REQUEST)
        self.engine: PortEngine | None = None
        self.answered = False

    def feed(self, data: bytes) -> list[Any]:
        events = self.reader.feed(data)
        if events and not self.answered:
            self.respond(events[0])
        return []

    def respond(self, request: dict[str, Any] | BadMessage) -> None:
        engine = self.engine
        assert engine is not None
        self.answered = True
        engine.partial_since = None
        reply = self.server.answer(request)  # may run an AT exchange: seconds
        engine.submit(encode_line(reply), rate_limited=False)
        engine.finish()


def _on_loop(loop: IoLoop, fn: Callable[[], Any], timeout: float = 1.0) -> None:
    """Run ``fn`` on ``loop``'s thread and wait for it (at once if that is not running)."""
    if loop.in_loop_thread or not loop.running:
        fn()
        return
    done = threading.Event()

    def run() -> None:
        try:
            fn()
        finally:
            done.set()

    loop.call_soon(run)
    if not done.wait(timeout):
        log.debug("loop %s busy; closing control connections from here", loop.name)
        fn()


def _alive(path: Path) -> bool:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(0.5)
    try:
        s.connect(str(path))
    except OSError:
        return False
    finally:
        s.close()
    return True


def reachable(path: Path) -> bool:
    """Does a gateway answer at ``path``?"""
    return path.exists() and _alive(path)


def call(path: Path, request: dict[str, Any], timeout: float) -> dict[str, Any]:
    """Send one request and wait up to ``timeout`` for its answer; OSError/ValueError on
    failure."""
    reader = JsonLines(MAX_REPLY)
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(str(path))
        s.sendall(encode_line({"version": PROTOCOL_VERSION, **request}))
        events: list[dict[str, Any] | BadMessage] = []
        while not events:
            chunk = s.recv(65536)
            events = reader.feed(chunk) if chunk else reader.flush()
            if not chunk:
                break
    if not events:
        raise ValueError("the gateway sent no answer")
    if isinstance(events[0], BadMessage):
        raise events[0]
    return events[0]
