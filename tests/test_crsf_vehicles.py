"""The CRSF link carries one vehicle: two rockets into one gateway, the radio shows one.

Two TCP feeds of Aurora wire frames (``socket://`` sources), one rocket near 100 m and one near
500 m, into ``aurora-gateway run --source alpha=… --source beta=… --crsf <pty>``; an EdgeTX
radio (:class:`test_crsf_edgetx.EdgeTxRadio`, written from the spec) reads the pty.  By default
the link serves the first source's vehicle even when the other is heard first; ``vehicle =
"beta"`` in ``[backends.crsf]`` serves beta.  :class:`WireFeed` is shared with the other
single-vehicle links' tests.
"""

from __future__ import annotations

import contextlib
import re
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import Running
from test_crsf_backend import PtyPeer, read_until
from test_crsf_edgetx import EdgeTxRadio

from backends.crsf.backend import CrsfBackend
from backends.crsf.frames import (
    FRAME_BARO_ALTITUDE,
    FRAME_BATTERY,
    FRAME_GPS,
    FlightMode,
    LinkStatistics,
)
from backends.crsf.frames import RcChannels as CrsfRc
from backends.crsf.frames import encode as crsf_encode
from backends.crsf.options import CrsfOptions
from gateway import config
from gateway.backend import GatewayContext
from gateway.config import ConfigError
from gateway.model import Battery, Position, RcChannels, SmUpdate, Status, VehicleState
from gateway.vehicles import SERVICE, SourceVehicle
from gateway.wire import encode

DEADLINE_S = 20.0
ALPHA_M, BETA_M = 100.0, 500.0
#: what each run is waiting for on the radio: this many altitudes
ALTITUDES = 12


def sm_at(alt: float, i: int = 0, state: int = 2, vehicle: str = "") -> SmUpdate:
    """An armed SM update near ``alt`` (±0.5 m as ``i`` goes on)."""
    return SmUpdate(timestamp_ms=1000 + 20 * i, state=state, armed=True, sm_type=0,
                    altitude_m=alt + (i % 10) * 0.1 - 0.5, acceleration_mps2=9.8,
                    accel_vert_mps2=0.0, velocity_mps=1.0, roll_rad=0.0, pitch_rad=0.1,
                    yaw_rad=0.0, vehicle=vehicle)


def context_of(*vehicles: str) -> GatewayContext:
    """A gateway context whose configured sources are ``vehicles`` in order (each source
    named like its vehicle), as the app fills it."""
    ctx = GatewayContext()
    ctx.services[SERVICE] = [SourceVehicle(v, v) for v in vehicles]
    return ctx


class WireFeed:
    """A TCP server streaming one rocket's Aurora wire frames (SM updates near ``alt``, a STATUS
    every tenth) to whoever connects (a ``socket://`` source), every ``period_s``.  With
    ``after``, it waits until that feed has sent ``after_frames`` frames before sending: which
    rocket is heard first is then known."""

    def __init__(self, alt: float, period_s: float = 0.02, after: WireFeed | None = None,
                 after_frames: int = 20) -> None:
        self.alt = alt
        self.period_s = period_s
        self.after = after
        self.after_frames = after_frames
        self.server = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        self.sent = 0
        self.progress = threading.Condition()
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def wait_sent(self, n: int, timeout: float = DEADLINE_S) -> bool:
        with self.progress:
            return self.progress.wait_for(lambda: self.sent >= n or self.stop.is_set(),
                                          timeout) and self.sent >= n

    def _serve(self) -> None:
        self.server.settimeout(0.2)
        while not self.stop.is_set():
            try:
                conn, _ = self.server.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                self._stream(conn)

    def _stream(self, conn: socket.socket) -> None:
        if self.after is not None:
            while not self.after.wait_sent(self.after_frames, 0.2):
                if self.stop.is_set():
                    return
        i = 0
        while not self.stop.is_set():
            frame = encode(sm_at(self.alt, i))
            if i % 10 == 0:
                frame += encode(Status(timestamp_ms=1000 + 20 * i, state=2, sm_type=0,
                                       flags=Status.make_flags(armed=True)))
            try:
                conn.sendall(frame)
            except OSError:
                return
            i += 1
            with self.progress:
                self.sent += 1
                self.progress.notify_all()
            self.stop.wait(self.period_s)

    def close(self) -> None:
        self.stop.set()
        with self.progress:
            self.progress.notify_all()
        self.server.close()
        self.thread.join(5)


@contextlib.contextmanager
def two_rockets() -> Iterator[tuple[WireFeed, WireFeed]]:
    """alpha near 100 m and beta near 500 m; beta is heard first (alpha waits for it)."""
    beta = WireFeed(BETA_M)
    alpha = WireFeed(ALPHA_M, after=beta)
    try:
        yield alpha, beta
    finally:
        alpha.close()
        beta.close()


def radio_altitudes(tmp_path: Path, crsf_table: str) -> tuple[list[float], str]:
    """Run the gateway on two rockets with the CRSF table given; the altitudes (m) the radio
    shows, and the gateway's stderr."""
    peer = PtyPeer()
    cfg = tmp_path / "gw.toml"
    cfg.write_text(f'[gateway]\nstatus_interval_s = 0\n\n[backends.crsf]\nurl = "{peer.path}"\n'
                   f'{crsf_table}', encoding="utf-8")
    radio = EdgeTxRadio()
    try:
        with two_rockets() as (alpha, beta):
            gw = Running("run", "--config", str(cfg), "--source", f"alpha={alpha.url}",
                         "--source", f"beta={beta.url}", "--log-level", "warning")
            try:
                assert beta.wait_sent(5) and alpha.wait_sent(5), gw.text("stderr")
                alts = lambda: [v for name, v in radio.history if name == "Alt"]  # noqa: E731
                assert read_until(peer.master, radio, lambda: len(alts()) >= ALTITUDES,
                                  DEADLINE_S), (radio.history, gw.text("stderr"))
            finally:
                rc = gw.stop()
            assert rc == 0, gw.text("stderr")
    finally:
        peer.close()
    return [v / 100 for name, v in radio.history if name == "Alt"], gw.text("stderr")


def test_two_rockets_the_radio_shows_the_first_sources_only(tmp_path: Path) -> None:
    """beta (500 m) is heard first, yet the link serves alpha, the first source: every
    altitude the radio shows is alpha's."""
    alts, err = radio_altitudes(tmp_path, "")
    assert len(alts) >= ALTITUDES
    assert all(abs(a - ALPHA_M) <= 1.0 for a in alts), (alts, err)


def test_two_rockets_vehicle_beta_shows_beta_only(tmp_path: Path) -> None:
    alts, err = radio_altitudes(tmp_path, 'vehicle = "beta"\n')
    assert len(alts) >= ALTITUDES
    assert all(abs(a - BETA_M) <= 1.0 for a in alts), (alts, err)


# -- in process: the handlers, the counters, what the link hands to the gateway ---------------

def test_another_vehicles_messages_are_skipped_first_and_counted() -> None:
    """Before any state update: beta's STATUS does not change the flight mode alpha shows,
    beta's updates publish nothing."""
    b = CrsfBackend()
    b.attach(context_of("alpha", "beta"))
    b.send_sm_update(sm_at(ALPHA_M, vehicle="alpha"))
    b.send_status(Status(timestamp_ms=1, state=3, sm_type=0, flags=0, vehicle="beta"))
    b.send_sm_update(sm_at(BETA_M, state=5, vehicle="beta"))
    b.send_position(Position(45.0, 7.0, 900.0, vehicle="beta"))
    b.send_battery(Battery(11.1, vehicle="beta"))
    b.send_vehicle_state(VehicleState(True, "AUTO", altitude_m=BETA_M, vehicle="beta"))
    assert b.stats()["other_vehicles"] == 5
    changes = []
    while (item := b.scheduler.take_change()) is not None:
        changes.append(item[1])
    assert changes == [FlightMode("BOOST")]  # beta's BURNOUT!IMU never replaced it
    alt = b.scheduler.mailbox(FRAME_BARO_ALTITUDE).peek()
    assert alt is not None and abs(alt.altitude_m - ALPHA_M) <= 1.0
    for ftype in (FRAME_GPS, FRAME_BATTERY):
        assert b.scheduler.mailbox(ftype).peek() is None
    assert b.stats()["errors"] == 0


def test_rc_channels_and_link_stats_carry_the_served_vehicle() -> None:
    got: list[Any] = []
    b = CrsfBackend(CrsfOptions(vehicle="beta"), sink=got.append)
    b.feed(crsf_encode(CrsfRc((992,) * 16), 0xC8))
    b.feed(crsf_encode(LinkStatistics(-52, -61, 97, 9, 0, 7, 3, -48, 100, 11), 0xC8))
    assert [type(m).__name__ for m in got] == ["RcChannels", "LinkStats"]
    assert {m.vehicle for m in got} == {"beta"}
    assert isinstance(got[0], RcChannels) and got[0].origin == "crsf"


def test_vehicle_key_is_checked_naming_it() -> None:
    part = config.parse({"backends": {"crsf": {"vehicle": "beta"}}}).backends[0]
    assert part.options["vehicle"] == "beta"
    assert config.parse({"backends": {"crsf": {}}}).backends[0].options["vehicle"] is None
    for bad in ("2fast", "al pha", "", 7):
        with pytest.raises(ConfigError, match=re.escape("backends.crsf.vehicle: ")):
            config.parse({"backends": {"crsf": {"vehicle": bad}}})
