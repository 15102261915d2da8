"""Serial wire source: Aurora frames from any pyserial port or URL.

One thread owns the port (pyserial's ReaderThread idiom) and feeds the sans-I/O decoder.
When the port fails or vanishes the source logs it once, counts it, and reopens with backoff
until the port is back.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from gateway.backoff import Backoff
from gateway.config import Key, Schema
from gateway.sources import Source
from gateway.transport import TransportError, open_serial
from gateway.wire import Decoder

log = logging.getLogger(__name__)

SOCKET_DRAIN_BYTES = 65536


def _open_unless_stopped(url: str, baudrate: int, stop: threading.Event) -> Any | None:
    """Open the port in a helper thread and wait for it or for ``stop``, whichever is first.

    An open can take far longer than the one second ``stop()`` may take: pyserial's
    ``socket://`` connect waits up to 5 s for a host that does not answer (one that is off
    the network, or a listener whose backlog is full).  On ``stop`` the open is abandoned and
    the port closed as soon as it completes; returns None then.  Raises
    :class:`TransportError` when the open fails.
    """
    lock = threading.Lock()
    done = threading.Event()
    result: dict[str, Any] = {"port": None, "error": None, "abandoned": False}

    def opener() -> None:
        try:
            port = open_serial(url, baudrate, timeout=0.05)
        except TransportError as exc:
            result["error"] = exc
            done.set()
            return
        with lock:
            abandoned = result["abandoned"]
            if not abandoned:
                result["port"] = port
        if abandoned:
            try:
                port.close()
            except Exception:
                log.debug("closing abandoned port %s failed", url, exc_info=True)
        done.set()

    threading.Thread(target=opener, name=f"open-{url}", daemon=True).start()
    while not done.wait(0.02):
        if stop.is_set():
            with lock:
                if result["port"] is None:
                    result["abandoned"] = True
                    return None
            break
    if result["error"] is not None:
        raise result["error"]
    return result["port"]


class SerialSource(Source):
    NAME = "serial"
    CONFIG = Schema(
        url=Key(str, help="pyserial port or URL: /dev/ttyUSB0, loop://, socket://host:port, "
                "rfc2217://host:port"),
        baudrate=Key(int, 115200, "host UART speed", minimum=50),
        reconnect_max_s=Key(float, 5.0, "longest wait between reopen attempts", minimum=0.01),
    )

    @staticmethod
    def default_name(options: dict[str, Any]) -> str:
        return options["url"]

    def __init__(self, url: str, baudrate: int = 115200, reconnect_max_s: float = 5.0,
                 name: str | None = None) -> None:
        super().__init__(name or url)
        self.url = url
        self.baudrate = baudrate
        self.decoder = Decoder(origin=self.name)
        self._backoff = Backoff(0.05, max(0.05, reconnect_max_s))
        self.opens = 0
        self.open_failures = 0
        self.disconnects = 0
        self.port: Any = None

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                port = _open_unless_stopped(self.url, self.baudrate, stop)
            except TransportError as exc:
                self.open_failures += 1
                if self.open_failures == 1 or self.disconnects:
                    log.warning("source %s: %s; retrying", self.name, exc)
                stop.wait(self._backoff.next())
                continue
            if port is None:  # stopped while the open was still under way
                break
            self.opens += 1
            self._backoff.reset()
            if self.opens > 1:
                log.info("source %s: port is back", self.name)
            else:
                log.info("source %s: %s open", self.name, self.url)
            self.port = port
            try:
                self._read_until_failure(port, stop)
            finally:
                self.port = None
                try:
                    port.close()
                except Exception:
                    log.debug("source %s: error closing", self.name, exc_info=True)
        for msg in self.decoder.flush():
            self.emit(msg)

    def _read_until_failure(self, port: Any, stop: threading.Event) -> None:
        decoder, emit = self.decoder, self.emit
        # pyserial's socket:// reports at most 1 byte waiting (it only polls the socket), so
        # after the first byte take whatever else has arrived without waiting: with timeout 0
        # its read() returns what the socket holds at once (settings are no-ops there).
        drain = type(port).__module__.endswith("protocol_socket")
        timeout = port.timeout
        while not stop.is_set():
            try:
                waiting = port.in_waiting
                data = port.read(waiting if waiting > 0 else 1)
                if drain and data:
                    port.timeout = 0
                    try:
                        data += port.read(SOCKET_DRAIN_BYTES)
                    finally:
                        port.timeout = timeout
            except Exception as exc:  # pyserial raises SerialException / OSError / TypeError
                self.disconnects += 1
                log.warning("source %s: port failed (%s); reconnecting", self.name, exc)
                for msg in decoder.flush():  # the stream broke: nothing completes a pending frame
                    emit(msg)
                stop.wait(self._backoff.next())
                return
            if data:
                for msg in decoder.feed(data):
                    emit(msg)

    def stats(self) -> dict[str, Any]:
        return {**self.decoder.stats.as_dict(), "opens": self.opens,
                "open_failures": self.open_failures, "disconnects": self.disconnects}
