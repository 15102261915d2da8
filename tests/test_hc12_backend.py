"""The HC-12 backend against the emulator over a real RFC 2217 port: byte-identical relay,
generate mode in both revisions, the air budget measured on the far side of the port, the
SET line left alone on open, readiness, configuration and `run` flags."""

from __future__ import annotations

import contextlib
import re
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import serial
from test_hc12_support import (
    DEADLINE_S,
    emu_mod,
    sm,
    status,
    write_settings,
)

from backends.hc12.backend import Hc12Backend
from backends.hc12.options import Hc12Options
from gateway import config
from gateway.commands import cli
from gateway.config import ConfigError
from gateway.flight import FlightModel, FlightProfile
from gateway.model import RawFrame, SmUpdate, Status
from gateway.outcome import Outcome
from gateway.pacing import paced
from gateway.sources.sim import flight_frames
from gateway.wire import Decoder, decode_all, encode, frame

FAST = {"mode": 3, "baud": 115200}

pytest_plugins = ["test_hc12_support"]  # the emulator and settings_file fixtures


@contextlib.contextmanager
def running(settings: Path, **kwargs: Any) -> Iterator[Any]:
    emu = emu_mod.Hc12Emulator(settings, **kwargs).start()
    try:
        yield emu
    finally:
        emu.stop()


@contextlib.contextmanager
def backend_on(url: str, **options: Any) -> Iterator[Hc12Backend]:
    b = Hc12Backend(Hc12Options(url=url, control="off", **options))
    b.init()
    try:
        assert b.engine.wait_connected(DEADLINE_S)
        yield b
    finally:
        b.close()


def send(b: Hc12Backend, msg: Any) -> Outcome:
    return dict(b.routes())[type(msg)](msg)


def wait_air(emu: Any, n: int) -> bytes:
    model = emu.model
    assert model.wait_for(lambda: len(model.air_out) >= n, DEADLINE_S), \
        f"air carried {len(model.air_out)} of {n} bytes"
    return bytes(model.air_out)


def test_relay_is_byte_identical(settings_file: Path, vectors: dict) -> None:
    """Every vector frame (both SM_UPDATE revisions, STATUS, unknown types) plus frames full of
    0xFF (the RFC 2217 escape byte) comes out of the air exactly as it went in."""
    write_settings(settings_file, **FAST)
    frames = [bytes.fromhex(v["hex"]) for v in vectors["frames"]]
    frames.append(frame(0x7F, b"\xff\xff\x00\xff\xfe"))
    frames.append(frame(0xFF, bytes(range(256))[-40:]))
    stream = b"".join(frames)
    msgs = Decoder(origin="uplink").feed(stream)
    assert [m.raw for m in msgs] == frames
    assert {type(m) for m in msgs} == {SmUpdate, Status, RawFrame}
    assert {m.payload_len for m in msgs if isinstance(m, SmUpdate)} == {36, 64}
    with running(settings_file) as emu, backend_on(emu.url, baudrate=115200, air_baud=115200,
                                                   queue_depth=64) as b:
        outcomes = [send(b, m) for m in msgs]
        assert outcomes == [Outcome.ACCEPTED] * len(msgs)
        assert wait_air(emu, len(stream)) == stream
        assert emu.model.garbled_bytes == 0
        assert b.stats()["encoded"] == 0


def test_relay_encodes_what_has_no_raw_and_never_echoes_its_own_port(settings_file: Path
                                                                     ) -> None:
    write_settings(settings_file, **FAST)
    with running(settings_file) as emu, backend_on(emu.url, baudrate=115200,
                                                   air_baud=115200) as b:
        own = decode_all(frame(0x42, b"echo"), origin=emu.url)[0]
        assert send(b, own) is Outcome.ACCEPTED
        made = sm(2, armed=True, revision=36)
        assert send(b, made) is Outcome.ACCEPTED
        out = decode_all(wait_air(emu, 42))
        stats = b.stats()
    assert len(out) == 1 and isinstance(out[0], SmUpdate)
    assert out[0].payload_len == 36 and out[0].state == 2 and out[0].armed
    assert stats["skipped_loop"] == 1 and stats["encoded"] == 1


@pytest.mark.parametrize("revision", [36, 64])
def test_generate_mode_encodes_in_the_configured_revision(settings_file: Path,
                                                          revision: int) -> None:
    write_settings(settings_file, **FAST)
    other = 64 if revision == 36 else 36
    received = decode_all(encode(sm(5, t_ms=7, revision=other)), origin="sim")[0]
    msgs = [sm(3, t_ms=5, revision=other), received, status(4, t_ms=9),
            decode_all(frame(0x33, b"xyz"), origin="sim")[0]]
    with running(settings_file) as emu, backend_on(emu.url, baudrate=115200, air_baud=115200,
                                                   mode="generate", revision=revision) as b:
        assert [send(b, m) for m in msgs] == [Outcome.ACCEPTED] * 4
        expected = 2 * (revision + 6) + 14 + 9
        out = decode_all(wait_air(emu, expected))
    assert [type(m) for m in out] == [SmUpdate, SmUpdate, Status, RawFrame]
    assert [m.payload_len for m in out[:2]] == [revision, revision]
    assert (out[0].state, out[0].timestamp_ms, out[1].state, out[1].timestamp_ms) == (3, 5, 5, 7)
    assert out[0].altitude_m == pytest.approx(12.5) and out[0].yaw_rad == pytest.approx(0.3)
    assert (out[2].state, out[2].timestamp_ms) == (4, 9)
    assert out[3].raw == frame(0x33, b"xyz")


def test_budget_measured_on_the_far_side_of_a_real_port(settings_file: Path) -> None:
    """A 100 Hz stream (64-byte revision, 1 Hz STATUS) for 3 s of real time into the default
    budget (9600 baud, 80 %), measured where the bytes arrive: at the emulated module."""
    write_settings(settings_file)  # factory: FU3, 9600
    model = FlightModel(FlightProfile(revision=64))
    stop = threading.Event()
    dec = Decoder(origin="sim")
    offered = accepted_n = statuses = 0
    admitted: list[float] = []
    with running(settings_file, tx_buffer=4096) as emu, backend_on(emu.url) as b:
        for t, fr in paced(flight_frames(model, 100.0, 1.0), 1.0, stop):
            if t >= 3.0:
                break
            for msg in dec.feed(fr):
                offered += 1
                statuses += isinstance(msg, Status)
                if send(b, msg) is Outcome.ACCEPTED:
                    accepted_n += 1
                    admitted.append(time.monotonic())
        assert b.engine.drain(DEADLINE_S)
        stats = b.stats()  # after the drain: a frame still queued is sent by then
        sent = stats["sent_bytes"]
        wait_air(emu, sent)
        m = emu.model
        arrivals = [(t, len(d)) for t, d in m.rx_log]
        air = decode_all(bytes(m.air_out))
        dropped_air = m.air_dropped
    total = sum(n for _, n in arrivals)
    span = arrivals[-1][0] - arrivals[0][0]
    peak = max(sum(n for t, n in arrivals if t0 <= t < t0 + 1.0) for t0, _ in arrivals)
    fig = b.budget.fig
    print(f"\nreal port: offered {offered} frames in 3 s, accepted {accepted_n}; far side got "
          f"{total} B in {span:.2f} s = {total / span:.0f} B/s "
          f"({100 * total / span / fig.capacity_bps:.1f} % of {fig.capacity_bps:.0f}; "
          f"{(total - fig.burst_bytes) / span:.0f} B/s after the initial burst), "
          f"peak 1-s window {peak} B; dropped by budget {stats['dropped_budget']}, queue full "
          f"{stats['dropped_queue_full']}; STATUS on air "
          f"{sum(isinstance(x, Status) for x in air)}/{statuses}; air overflow {dropped_air}")
    assert total == sent == sum(len(x.raw) for x in air)  # everything accepted arrived
    # The budget's own guarantee, on admission times (exact whatever the machine load):
    assert total <= fig.burst_bytes + fig.rate_bps * (admitted[-1] - admitted[0]) + 1e-6
    # Where the bytes land, delivery jitter can bunch them: generous bounds only.
    assert peak <= 2 * fig.capacity_bps
    assert dropped_air == 0  # the module never had more than it could put on the air
    assert stats["dropped_budget"] > 0 and stats["dropped"] == offered - accepted_n
    assert sum(isinstance(x, Status) for x in air) == statuses == 3


def test_opening_the_port_leaves_set_released(settings_file: Path) -> None:
    """pyserial asserts RTS as it opens a port — with SET on RTS that is AT mode.  The backend
    deasserts it first; a plain open shows what would happen otherwise."""
    with running(settings_file) as emu:
        with backend_on(emu.url, set_line="rts") as b:
            assert send(b, status()) is Outcome.ACCEPTED
            wait_air(emu, 14)
        assert emu.model.event_values("set") == []
        assert emu.model.wait_for(lambda: emu._client is None, DEADLINE_S)
        plain = serial.serial_for_url(emu.url, timeout=0.05)
        try:
            assert emu.model.wait_for(lambda: emu.model.event_values("set") == [True],
                                      DEADLINE_S)
        finally:
            plain.close()


def test_a_port_that_is_not_there_means_not_ready_never_blocking() -> None:
    with socket.socket() as s:  # a free port with nobody listening
        s.bind(("127.0.0.1", 0))
        url = f"rfc2217://127.0.0.1:{s.getsockname()[1]}"
    b = Hc12Backend(Hc12Options(url=url, control="off"))
    b.init()
    try:
        start = time.monotonic()
        outcomes = {send(b, sm(t_ms=i)) for i in range(50)}
        assert time.monotonic() - start < 1.0  # never blocks (generous for a loaded machine)
        assert outcomes == {Outcome.NOT_READY}
        assert b.stats()["dropped_not_ready"] == 50
    finally:
        b.close()


# -- configuration and flags ---------------------------------------------------------------------


def test_config_table_is_validated_naming_the_key() -> None:
    part = config.parse({"backends": {"hc12": {"url": "/dev/ttyUSB0"}}}).backends[0]
    assert part.options["baudrate"] == 9600 and part.options["utilisation_pct"] == 80.0
    assert part.options["queue_depth"] == 16 and part.options["min_interval_s"] == 0.0
    for key, bad, words in [("baudrate", 9601, "backends.hc12.baudrate"),
                            ("mode", "both", "backends.hc12.mode"),
                            ("revision", 48, "backends.hc12.revision"),
                            ("utilisation_pct", 120, "backends.hc12.utilisation_pct"),
                            ("speed", 1, "backends.hc12.speed: unknown key")]:
        with pytest.raises(ConfigError, match=re.escape(words)):
            config.parse({"backends": {"hc12": {"url": "/dev/ttyUSB0", key: bad}}})
    with pytest.raises(ConfigError, match=re.escape("backends.hc12.url: required")):
        config.parse({"backends": {"hc12": {}}})


def test_bad_set_line_is_a_config_error_when_built() -> None:
    from gateway.app import Gateway

    cfg = config.parse({"sources": [{"type": "sim"}],
                        "backends": {"hc12": {"url": "loop://", "set_line": "cts"}}})
    with pytest.raises(ConfigError, match=re.escape("backends.hc12: set_line: expected none, rts")):
        Gateway(cfg)


def test_run_flags_enable_the_backend_and_the_default_run_leaves_it_out() -> None:
    assert Hc12Backend.EMBEDDED_DEFAULT is None
    assert "hc12" not in [p.name for p in config.embedded_default().backends]
    args = cli.build_parser().parse_args(["run", "--hc12", "rfc2217://127.0.0.1:4000",
                                          "--hc12-baud", "19200", "--hc12-mode", "generate"])
    cfg = cli.config_from_args(args)
    part = next(p for p in cfg.backends if p.name == "hc12")
    assert part.options["url"] == "rfc2217://127.0.0.1:4000"
    assert part.options["baudrate"] == 19200 and part.options["mode"] == "generate"
    args = cli.build_parser().parse_args(["run", "--hc12", "loop://", "--hc12-baud", "1000"])
    with pytest.raises(ConfigError, match=re.escape("backends.hc12.baudrate")):
        cli.config_from_args(args)
