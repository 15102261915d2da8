"""Shared fixtures: the independent test vectors in ``../shared/vectors/``.

The shared directory sits beside the repository (locally and in CI).  A missing or unreadable
vector file is an error, never a skip: tests that silently skip their vectors prove nothing.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

# Hypothesis's per-example deadline is a wall-clock assertion: on a shared 2-core machine
# running the suite on four workers an example can take 300 ms that takes 5 ms alone.  So is
# its "too slow" health check (data generation timed against a fixed budget), which fails a
# property whose examples were drawn while the machine was busy.  The properties are about
# results, not speed (benchmarks live in tools/bench/).
settings.register_profile("aurora", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("aurora")

SHARED_DIR = Path(__file__).resolve().parents[1].parent / "shared"
WIRE_VECTORS_PATH = SHARED_DIR / "vectors" / "aurora-wire.json"


@cache
def _load_wire_vectors() -> dict[str, Any]:
    try:
        text = WIRE_VECTORS_PATH.read_text(encoding="utf-8")
    except OSError as exc:  # pragma: no cover - only when the checkout is incomplete
        raise RuntimeError(f"wire test vectors not found at {WIRE_VECTORS_PATH}: {exc}") from exc
    return json.loads(text)


def _vector_id(index: int, vector: dict[str, Any]) -> str:
    kind = vector["kind"]
    if kind == "sm_update":
        return f"{index:02d}-sm_update{vector['payload_len']}"
    if kind == "unknown":
        return f"{index:02d}-unknown-type{vector['type']}"
    return f"{index:02d}-{kind}"


@pytest.fixture(scope="session")
def vectors() -> dict[str, Any]:
    """The whole ``aurora-wire.json`` (keys ``crc``, ``frames``, ``streams``)."""
    return _load_wire_vectors()


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Parametrise ``vector_frame`` / ``vector_stream`` with every entry of the vector file."""
    if "vector_frame" in metafunc.fixturenames:
        frames = _load_wire_vectors()["frames"]
        metafunc.parametrize(
            "vector_frame", frames, ids=[_vector_id(i, v) for i, v in enumerate(frames)]
        )
    if "vector_stream" in metafunc.fixturenames:
        streams = _load_wire_vectors()["streams"]
        metafunc.parametrize(
            "vector_stream", streams, ids=[f"stream{i}" for i in range(len(streams))]
        )


# -- leaving the test process ------------------------------------------------------------------
# Zenoh's Rust runtime keeps native threads after every session is closed.  If one needs the
# GIL while CPython finalizes, CPython ends it with pthread_exit and the unwind through Rust
# frames aborts the process ("FATAL: exception not rethrown") -- after every test has passed,
# turning a green run red.  The CLI avoids it the same way (gateway.commands.cli.console_main): once
# pytest has reported, leave with its exit status without interpreter teardown.

_exit_status: list[int] = []


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    _exit_status.append(int(exitstatus))


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config: pytest.Config) -> None:
    import os
    import sys

    if "zenoh" not in sys.modules or not _exit_status or hasattr(config, "workerinput"):
        return
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(_exit_status[-1])


# -- order -------------------------------------------------------------------------------------
# pytest-randomly shuffles every run (its seed is printed: `--randomly-seed=N`
# replays one); `--reverse` (with `-p no:randomly`) runs the suite back to front.  A test that
# passes in one order and fails in another leans on another test's leftovers.

def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--reverse", action="store_true", help="run the tests in reverse order")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--reverse"):
        items.reverse()
