"""Replay a recording (see :mod:`gateway.recording`) at real time or N× speed: the file is
read once on the loop's blocking calls, then paced on the source's I/O loop
(:class:`gateway.pacing.Pacer`).

Each frame replays as the vehicle it was recorded from (a version 2 recording of several
vehicles gives several vehicles again, each under its recorded name); a frame recorded
without a vehicle (every frame of a version 1 recording), or with a name that is not a
vehicle name, replays as the source's own vehicle.

A message record (a kind with no wire frame: position, battery, vehicle state, RC
channels, link statistics) replays as that message of its vehicle, from this source.
Recorded link events are not replayed (counted, ``link_events_skipped``): the replaying
gateway's own link monitor makes them again from the replayed traffic, for the replay
source; re-emitting the recorded ones would report links this gateway does not have."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from gateway import recording, vehicles
from gateway.model import LinkEvent
from gateway.sources.options import ReplayOptions
from gateway.sources.paced import PacedFrameSource

log = logging.getLogger(__name__)


class ReplaySource(PacedFrameSource):
    NAME = "replay"
    OPTIONS = ReplayOptions
    #: a version 2 recording replays each recorded vehicle under its name
    YIELDS_SYSTEMS = True

    @staticmethod
    def default_name(options: dict[str, Any]) -> str:
        return f"replay:{Path(options['path']).name}"

    @staticmethod
    def default_vehicle(options: dict[str, Any]) -> str:
        """A version 1 recording's vehicle, unnamed in the file: named after the file, as
        ``decode`` and ``export`` name it (``…-rocket1.aur`` → ``rocket1``)."""
        return recording.file_vehicle(options["path"])

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
        self.read_stats = recording.ReadStats()
        self._names: dict[str, str] = {}  # a recorded vehicle name -> the one replayed
        self.link_events_skipped = 0

    def begin(self) -> None:
        loop = self.io_loop
        assert loop is not None
        # the file is read once, off the loop (a long recording takes a while), then paced
        loop.run_blocking(self._read, self._loaded, name=f"read {self.path.name}")

    def _read(self) -> bytes:
        data = self.path.read_bytes()
        recording.check_header(data, self.path)
        return data

    def _loaded(self, data: bytes | None, error: BaseException | None) -> None:
        loop = self.io_loop
        if self.stop_requested or loop is None:  # halted meanwhile (and finished)
            return
        if error is not None or data is None:
            log.error("replay %s: cannot read it: %s", self.path, error)
            self.finish()
            return
        self.pace(self._passes(data), self.speed)

    def _passes(self, data: bytes) -> Iterator[tuple[float, recording.AnyRecord]]:
        """The recording's records, once or (``loop``) again and again; each pass is paced
        from its own first record: its times carry on from the last pass's end (one mean
        record interval later), so the pacer's clock never goes back (it played every pass
        after the first flat out)."""
        base: float | None = None  # where this pass's first record goes on the pacer's clock
        while not self.stop_requested:
            self.read_stats = recording.ReadStats()
            first = last = None
            n = 0
            for rec in recording.records(data, self.read_stats, messages=True):
                if first is None:
                    first = rec.t
                last, n = rec.t, n + 1
                yield (rec.t if base is None else base + (rec.t - first)), rec
            if first is not None and last is not None:
                span = last - first
                start = first if base is None else base
                base = start + span + (span / (n - 1) if n > 1 else 0.0)
            if self.read_stats.torn_tail_bytes:
                log.info("replay %s: skipped a torn last record (%d bytes)", self.path,
                         self.read_stats.torn_tail_bytes)
            if not self.loop:
                return

    def _replayed_vehicle(self, recorded: str) -> str:
        name = self._names.get(recorded)
        if name is None:
            ok = bool(recorded) and vehicles.NAME.match(recorded) is not None \
                and len(recorded) <= vehicles.MAX_NAME_LEN
            name = recorded if ok else self.vehicle
            if len(self._names) < 4096:  # bounded: a crafted file names at most 65535
                self._names[recorded] = name
        return name

    def _deliver(self, t: float, item: Any) -> None:
        if isinstance(item, bytes):
            super()._deliver(t, item)
            return
        if isinstance(item, recording.MessageRecord):
            msg = item.message
            if isinstance(msg, LinkEvent):
                self.link_events_skipped += 1
                return
            self.sent += 1
            self.emit(msg._replace(origin=self.name,
                                   vehicle=self._replayed_vehicle(item.vehicle)))
            return
        self.decoder.vehicle = self._replayed_vehicle(item.vehicle)
        super()._deliver(t, item.frame)

    def stats(self) -> dict[str, Any]:
        st = self.read_stats
        return {"frames": self.sent, "records": st.records, "messages": st.messages,
                "link_events_skipped": self.link_events_skipped,
                "torn_tail_bytes": st.torn_tail_bytes, "corrupt_skips": st.corrupt_skips,
                "vehicles": len(set(self._names.values())),
                "crc_failures": self.decoder.stats.crc_failures}
