"""The control socket: how ``aurora-gateway hc12 …`` reaches a running gateway's HC-12 backend.

A running gateway owns the port (opened exclusively) and its TX worker holds the port lock for
every frame.  An AT exchange must hold the *same* lock and know the vehicle's state, so the
command-line tool does not open the port itself: it sends its request over a Unix socket that
the backend serves, and the backend runs the exchange under its own lock, applying its own
knowledge of the vehicle (the latest SM_UPDATE/STATUS it relayed).

* The socket lives in a per-user directory: ``$XDG_RUNTIME_DIR/aurora-gateway/`` or else
  ``/tmp/aurora-gateway-<uid>/`` (created 0700, refused if anyone else owns it or may write
  to it); the socket itself is 0600.  Its name is derived from the port URL, so the tool finds
  the gateway driving ``--port`` without being told; ``control = "PATH"`` /
  ``--gateway PATH`` name it explicitly.
* One request per connection: a JSON object on one line (``{"op": "channel", "arg": "5",
  "bench": false}``), answered by one JSON line (a :class:`~backends.hc12.provision.Result`).
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
from collections.abc import Callable
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
MAX_REQUEST = 4096


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


class ControlServer:
    """Serves requests on a Unix socket, one connection at a time per thread."""

    def __init__(self, path: Path, handler: Callable[[dict[str, Any]], dict[str, Any]],
                 name: str = "hc12") -> None:
        self.path = Path(path)
        self.handler = handler
        self.name = name
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._inode: int | None = None
        self.requests = 0

    def start(self) -> None:
        """Bind and serve; raises OSError if another live server already answers there."""
        if self.path.exists() or self.path.is_symlink():
            if _alive(self.path):
                raise OSError(f"{self.path} is served by another running gateway")
            self.path.unlink()  # left behind by a gateway that died
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        old_umask = os.umask(0o177)
        try:
            sock.bind(str(self.path))
        except OSError:
            sock.close()
            raise
        finally:
            os.umask(old_umask)
        os.chmod(self.path, 0o600)
        self._inode = self.path.stat().st_ino
        sock.listen(4)
        sock.settimeout(0.2)
        self._sock = sock
        self._thread = threading.Thread(target=self._serve, name=f"{self.name}-control",
                                        daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        sock = self._sock
        assert sock is not None
        while not self._stop.is_set():
            try:
                conn, _ = sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            threading.Thread(target=self._handle, args=(conn,), name=f"{self.name}-control-req",
                             daemon=True).start()

    def _handle(self, conn: socket.socket) -> None:
        with conn:
            conn.settimeout(2.0)
            try:
                data = b""
                while b"\n" not in data and len(data) < MAX_REQUEST:
                    chunk = conn.recv(MAX_REQUEST)
                    if not chunk:
                        break
                    data += chunk
                request = json.loads(data.split(b"\n", 1)[0] or b"null")
                if not isinstance(request, dict):
                    raise ValueError("expected a JSON object")
            except (OSError, ValueError) as exc:
                reply: dict[str, Any] = {"ok": False, "op": "", "kind": "usage",
                                         "error": f"bad control request: {exc}"}
            else:
                self.requests += 1
                try:
                    reply = self.handler(request)
                except Exception as exc:  # never let one request kill the server
                    log.exception("%s: control request failed", self.name)
                    reply = {"ok": False, "op": str(request.get("op", "")), "kind": "failed",
                             "error": f"{type(exc).__name__}: {exc}"}
            with contextlib.suppress(OSError):
                conn.sendall(json.dumps(reply).encode() + b"\n")

    def close(self) -> None:
        """Stop serving and remove the socket file (if it is still ours); safe twice."""
        self._stop.set()
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()
        if self._thread is not None:
            self._thread.join(1.0)
            self._thread = None
        if self._inode is not None:
            with contextlib.suppress(OSError):
                if self.path.stat().st_ino == self._inode:
                    self.path.unlink()
            self._inode = None


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
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(str(path))
        s.sendall(json.dumps({"version": PROTOCOL_VERSION, **request}).encode() + b"\n")
        data = b""
        while b"\n" not in data:
            chunk = s.recv(65536)
            if not chunk:
                break
            data += chunk
    reply = json.loads(data.split(b"\n", 1)[0] or b"null")
    if not isinstance(reply, dict):
        raise ValueError("the gateway sent no answer")
    return reply
