"""Replay a recording (see :mod:`gateway.recording`) at real time or N× speed."""

from __future__ import annotations

import logging
import threading
from pathlib import Path
from typing import Any

from gateway import recording
from gateway.pacing import paced
from gateway.sources import Source
from gateway.sources.options import ReplayOptions
from gateway.wire import Decoder

log = logging.getLogger(__name__)


class ReplaySource(Source):
    NAME = "replay"
    OPTIONS = ReplayOptions

    @staticmethod
    def default_name(options: dict[str, Any]) -> str:
        return f"replay:{Path(options['path']).name}"

    @classmethod
    def url_options(cls, rest: str | None) -> dict[str, Any]:
        """``replay:FILE``."""
        if not rest:
            raise ValueError("replay: needs a file, e.g. replay:flight.aur")
        return {"path": rest}

    def __init__(self, options: ReplayOptions, name: str | None = None) -> None:
        super().__init__(name or f"replay:{Path(options.path).name}")
        self.path = Path(options.path)  # checked by its option (recording.check_file)
        self.speed = options.speed
        self.loop = options.loop
        self.decoder = Decoder(origin=self.name)
        self.read_stats = recording.ReadStats()
        self.frames_sent = 0

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            self.read_stats = recording.ReadStats()
            records = recording.read(self.path, self.read_stats)
            for _, frame in paced(records, self.speed, stop):
                for msg in self.decoder.feed(frame):
                    self.frames_sent += 1
                    self.emit(msg)
            if self.read_stats.torn_tail_bytes:
                log.info("replay %s: skipped a torn last record (%d bytes)", self.path,
                         self.read_stats.torn_tail_bytes)
            if not self.loop:
                return

    def stats(self) -> dict[str, Any]:
        st = self.read_stats
        return {"frames": self.frames_sent, "records": st.records,
                "torn_tail_bytes": st.torn_tail_bytes, "corrupt_skips": st.corrupt_skips,
                "crc_failures": self.decoder.stats.crc_failures}
