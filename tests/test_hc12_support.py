"""Shared pieces of the HC-12 tests: the emulator (tools/hc12_emulator.py, loaded by path),
a fake clock, and frame helpers.  No tests here."""

from __future__ import annotations

import importlib.util
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from gateway.model import SmUpdate, Status

ROOT = Path(__file__).resolve().parents[1]
EMULATOR_PATH = ROOT / "tools" / "hc12_emulator.py"
DEADLINE_S = 10.0


def load_emulator() -> Any:
    name = "hc12_emulator"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, EMULATOR_PATH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


emu_mod = load_emulator()


class FakeClock:
    def __init__(self, now: float = 1000.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now

    def advance(self, dt: float) -> None:
        self.now += dt


def write_settings(path: Path, **settings: int) -> Path:
    base = {"mode": 3, "baud": 9600, "channel": 1, "power": 8}
    path.write_text(json.dumps({**base, **settings}), encoding="utf-8")
    return path


@pytest.fixture
def settings_file(tmp_path: Path) -> Path:
    return tmp_path / "hc12-settings.json"


@pytest.fixture
def emulator(settings_file: Path) -> Iterator[Any]:
    """A running HC-12 emulator (SET on RTS), stopped after the test."""
    emu = emu_mod.Hc12Emulator(settings_file).start()
    try:
        yield emu
    finally:
        emu.stop()


def sm(state: int = 0, *, armed: bool = False, t_ms: int = 1000, revision: int = 64,
       origin: str = "sim", alt: float = 12.5) -> SmUpdate:
    """An SM_UPDATE built in memory (no ``raw``)."""
    return SmUpdate(t_ms, state, armed, 0, alt, 9.81, 9.7, 1.5, 0.1, -0.2, 0.3, revision, 0, b"",
                    origin)


def status(state: int = 0, *, armed: bool = False, t_ms: int = 1000,
           origin: str = "sim") -> Status:
    return Status(t_ms, state, 0, Status.make_flags(armed=armed, imu_ok=True, baro_ok=True),
                  0, b"", origin)


def last_value(model: Any, kind: str) -> Any:
    values = model.event_values(kind)
    return values[-1] if values else None
