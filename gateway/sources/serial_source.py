"""Serial wire source: Aurora frames from any pyserial port or URL.

The port belongs to a :class:`gateway.io.port.PortEngine` on the source's I/O loop (the
gateway's, shared by its sources): the loop's thread reads whatever arrives
into the sans-I/O :class:`gateway.wire.Decoder` and hands what each read decoded on, as one
batch.  When the
port fails or vanishes the engine logs it once, counts it and reopens it with backoff until
it is back (a device path that is not there yet is simply retried: hot-plug).
"""

from __future__ import annotations

import logging
from typing import Any

from gateway.io.backoff import Backoff
from gateway.io.port import REOPEN_FIRST_S, PortEngine
from gateway.io.transport import open_serial
from gateway.sources import Source
from gateway.sources.options import SerialOptions
from gateway.wire import Decoder

log = logging.getLogger(__name__)


class SerialSource(Source):
    NAME = "serial"
    OPTIONS = SerialOptions

    NAME_FORMAT = "{url}"

    def __init__(self, options: SerialOptions, name: str | None = None) -> None:
        super().__init__(name or options.url)
        self.url = options.url
        self.baudrate = options.baudrate
        reconnect_max_s = options.reconnect_max_s
        self.decoder = Decoder(origin=self.name, vehicle=self.vehicle)
        self.engine = PortEngine(self._open, name=f"source {self.name}", protocol=self,
                                 on_event=self.emit,
                                 backoff=Backoff(REOPEN_FIRST_S,
                                                 max(REOPEN_FIRST_S, reconnect_max_s)))

    def _open(self) -> Any:
        port = open_serial(self.url, self.baudrate, timeout=0)
        if self.engine.stats.connects == 0:
            log.info("source %s: %s open", self.name, self.url)
        return port

    # The engine's protocol: the decoder, looked up at each call so it can be swapped.
    def feed(self, data: bytes) -> list[Any]:
        """What one read decoded goes to the gateway as one batch (nothing is left for the
        engine to hand over message by message)."""
        self.emit_batch(self.decoder.feed(data))
        return []

    def flush(self) -> list[Any]:
        """The stream broke (or stopped): nothing completes a pending frame."""
        return self.decoder.flush()

    def begin(self) -> None:
        loop = self.io_loop
        assert loop is not None
        self.engine.use_loop(loop)
        self.engine.start()

    def halt(self) -> None:
        self.engine.close(0.0)  # on the loop's thread: closes at once
        self.finish()

    def stats(self) -> dict[str, Any]:
        es = self.engine.stats
        return {**self.decoder.stats.as_dict(), "opens": es.connects,
                "open_failures": es.connect_failures, "disconnects": es.disconnects,
                "bytes_in": es.received_bytes, "link": int(self.engine.connected)}
