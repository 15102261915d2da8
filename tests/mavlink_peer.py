"""A MAVLink peer on its own UDP socket, built on pymavlink alone: a stand-in ground station
(or vehicle) for tests and tools.

It parses what it receives with a pymavlink generated dialect module — by default pymavlink's
own ``development`` module (upstream definitions, what QGroundControl's MAVLink library is
generated from), not this package's dialect — and packs what it sends with it too.  Never
``mavutil``.  Importable as ``mavlink_peer`` (pytest puts ``tests/`` on ``sys.path``).
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterator
from types import ModuleType
from typing import Any


def upstream_dialect() -> ModuleType:
    from pymavlink.dialects.v20 import development

    return development


class MavPeer:
    """One MAVLink system/component speaking through a UDP socket bound to ``bind``.

    Replies go to ``dest`` (set it, or it becomes the address of the first datagram
    received).  With ``announce`` it says who it is as a ground station does: one GCS
    HEARTBEAT as soon as it has a destination (QGroundControl sends one every second; the
    gateway sends some messages only where a ground station was heard).  Every received
    message is kept with its arrival time; :meth:`wait_for` waits on a condition with a
    deadline."""

    def __init__(self, sysid: int = 255, compid: int = 190, *, dialect: ModuleType | None = None,
                 bind: tuple[str, int] = ("127.0.0.1", 0), dest: Any = None,
                 signing_key: bytes | None = None, link_id: int = 0,
                 announce: bool = False) -> None:
        self.dialect = dialect or upstream_dialect()
        self.mav = self.dialect.MAVLink(None, sysid, compid)
        self.mav.robust_parsing = True
        if signing_key is not None:
            s = self.mav.signing
            s.secret_key = signing_key
            s.link_id = link_id
            s.timestamp = int((time.time() - 1420070400) * 100_000)
            s.sign_outgoing = True
            s.allow_unsigned_callback = lambda _mav, _msgid: True
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(bind)
        self.sock.settimeout(0.05)
        self.dest = dest
        self.received: list[tuple[float, Any]] = []
        self.raw_received: list[bytes] = []
        self.bad = 0
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._announce = announce
        self._thread = threading.Thread(target=self._rx, name="mavpeer", daemon=True)
        self._thread.start()
        if announce and dest is not None:
            self.announce()

    def announce(self) -> None:
        """Send one HEARTBEAT as a ground station (QGroundControl's fields)."""
        d = self.dialect
        self.send(d.MAVLink_heartbeat_message(
            d.MAV_TYPE_GCS, d.MAV_AUTOPILOT_INVALID, d.MAV_MODE_FLAG_SAFETY_ARMED
            | d.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED, 0, d.MAV_STATE_ACTIVE, 3))

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def _rx(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(65536)
            except (TimeoutError, BlockingIOError):
                continue
            except OSError:
                if self._stop.is_set():
                    return
                continue
            if self.dest is None:
                self.dest = addr
                if self._announce:
                    self.announce()
            try:
                msgs = self.mav.parse_buffer(data) or []
            except Exception:
                msgs = []
                self.bad += 1
            now = time.monotonic()
            with self._cond:
                self.raw_received.append(data)
                for m in msgs:
                    if m.get_type() == "BAD_DATA":
                        self.bad += 1
                    else:
                        self.received.append((now, m))
                self._cond.notify_all()

    # -- sending -------------------------------------------------------------------------------

    def pack(self, msg: Any) -> bytes:
        """Pack with this peer's sequence number (and signature), advancing it."""
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf

    def send(self, msg: Any, dest: Any = None) -> bytes:
        buf = self.pack(msg)
        self.send_raw(buf, dest)
        return buf

    def send_raw(self, data: bytes, dest: Any = None) -> None:
        d = dest if dest is not None else self.dest
        if d is None:
            raise RuntimeError("no destination yet: nothing received and none given")
        self.sock.sendto(data, d)

    def command(self, target: tuple[int, int], command: int, *params: float,
                dest: Any = None) -> bytes:
        p = [*params, *([0.0] * (7 - len(params)))]
        return self.send(self.dialect.MAVLink_command_long_message(
            target[0], target[1], command, 0, *p), dest)

    # -- receiving -----------------------------------------------------------------------------

    def messages(self, mtype: str | None = None,
                 where: Callable[[Any], bool] | None = None) -> list[Any]:
        with self._cond:
            return [m for _, m in self.received
                    if (mtype is None or m.get_type() == mtype) and (where is None or where(m))]

    def timed(self, mtype: str) -> list[tuple[float, Any]]:
        with self._cond:
            return [(t, m) for t, m in self.received if m.get_type() == mtype]

    def wait_for(self, mtype: str, where: Callable[[Any], bool] | None = None, *,
                 count: int = 1, timeout: float = 5.0) -> list[Any]:
        """Wait until ``count`` messages of ``mtype`` (matching ``where``) have arrived in all;
        returns them (fewer if the deadline passed)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                found = [m for _, m in self.received
                         if m.get_type() == mtype and (where is None or where(m))]
                left = deadline - time.monotonic()
                if len(found) >= count or left <= 0:
                    return found
                self._cond.wait(left)

    def wait_until(self, predicate: Callable[[], bool], timeout: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.1))
            return True

    def clear(self) -> None:
        with self._cond:
            self.received.clear()
            self.raw_received.clear()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        with contextlib.suppress(OSError):
            self.sock.close()

    def __enter__(self) -> MavPeer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def running_backend(*endpoints: str, **opts: Any) -> Iterator[Any]:
    """A started MavlinkBackend on ``endpoints`` behind a real Dispatcher; closed on exit."""
    from backends.mavlink.backend import MavlinkBackend
    from backends.mavlink.options import MavlinkOptions
    from gateway.dispatcher import Dispatcher

    b = MavlinkBackend(MavlinkOptions(endpoints=list(endpoints), **opts))
    d = Dispatcher([b])
    assert d.start() == [], d.records[0].init_error
    try:
        yield b
    finally:
        d.close()
