"""The backend contract (gateway/backend.py): typed routing that mypy checks, and the same
stats keys from every built-in backend."""

from __future__ import annotations

import contextlib
import textwrap
from pathlib import Path
from typing import Any

import pytest
from helpers import DEADLINE_S, HeldLoop, wait_for
from mypy import api as mypy_api  # a test dependency: make lint runs it too
from zenoh_peer import free_endpoint

from gateway.backend import STATS_KEYS

ROOT = Path(__file__).resolve().parent.parent

BACKEND = textwrap.dedent("""
    from gateway.backend import Backend, Outcome, Routes
    from gateway.handover import Handover
    from gateway.model import SmUpdate, Status


    class Radio(Backend):
        handover = Handover("radio")

        def routes(self) -> Routes:
            return Routes({via}).on(SmUpdate, {handler})

        def send_sm_update(self, msg: SmUpdate) -> Outcome:
            return Outcome.ACCEPTED

        def send_status(self, msg: Status) -> Outcome:
            return Outcome.ACCEPTED
""")


def _mypy(tmp_path: Path, handler: str, via: str = "") -> tuple[str, int]:
    src = tmp_path / "radio.py"
    src.write_text(BACKEND.format(handler=handler, via=via))
    out, err, status = mypy_api.run([
        "--config-file", str(ROOT / "pyproject.toml"), "--cache-dir", str(tmp_path / "cache"),
        "--follow-imports", "silent", str(src)])
    return out + err, status


@pytest.fixture(scope="module")
def checked(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[str, int]]:
    """mypy's verdict on one backend routing SmUpdate to three handlers, in the dispatcher's
    thread and on its loop through a hand-over (one run each)."""
    results = {}
    for label, handler, via in (("right", "self.send_sm_update", ""),
                                ("misspelled", "self.send_sm_updat", ""),
                                ("wrong type", "self.send_status", ""),
                                ("right on a loop", "self.send_sm_update",
                                 "handover=self.handover"),
                                ("wrong type on a loop", "self.send_status",
                                 "handover=self.handover")):
        results[label] = _mypy(tmp_path_factory.mktemp(label.replace(" ", "-")), handler, via)
    return results


def test_a_correctly_routed_backend_passes_mypy(checked: dict[str, tuple[str, int]]) -> None:
    out, status = checked["right"]
    assert status == 0, out


def test_a_misspelled_handler_fails_mypy(checked: dict[str, tuple[str, int]]) -> None:
    out, status = checked["misspelled"]
    assert status == 1
    assert "send_sm_updat" in out and "attr-defined" in out, out


def test_a_handler_of_another_message_type_fails_mypy(
        checked: dict[str, tuple[str, int]]) -> None:
    out, status = checked["wrong type"]
    assert status == 1
    assert "arg-type" in out and "Status" in out, out


def test_mypy_follows_a_message_through_the_hand_over_into_the_handler(
        checked: dict[str, tuple[str, int]]) -> None:
    out, status = checked["right on a loop"]
    assert status == 0, out
    out, status = checked["wrong type on a loop"]
    assert status == 1
    assert "arg-type" in out and "Status" in out, out


# -- the stats keys ---------------------------------------------------------------------------


def _built_in(name: str, tmp_path: Path) -> Any:
    """A running built-in backend on loopback, with no hardware."""
    from gateway import config

    options: dict[str, Any] = {
        "console": {"stream": "stderr"},
        "crsf": {"url": "pty"},
        "mavlink": {"endpoints": ["udpin:127.0.0.1:0"]},
        "zenoh": {"listen": [free_endpoint()]},
        "hc12": {"url": "loop://", "control": "off"},
        "uavtalk": {"endpoints": ["tcpin:127.0.0.1:0"]},
        "foxglove": {"host": "127.0.0.1", "port": 0},
    }[name]
    (part,) = config.parse({"backends": {name: options}}).backends
    return part.cls.from_config(dict(part.options), name=part.name)


@pytest.mark.parametrize("name", ["console", "crsf", "mavlink", "zenoh", "hc12"])
def test_every_built_in_backend_reports_the_common_stats_keys(name: str, tmp_path: Path) -> None:
    backend = _built_in(name, tmp_path)
    try:
        missing = [k for k in STATS_KEYS if k not in backend.stats()]
        assert missing == [], f"{name} before init lacks {missing}"
        backend.init()
        stats = backend.stats()
        assert [k for k in STATS_KEYS if k not in stats] == [], stats
        assert all(isinstance(stats[k], int) for k in STATS_KEYS), stats
        assert stats["link"] in (0, 1)
    finally:
        backend.close()


#: The built-in backends whose handlers run on their loop, behind a hand-over.
HANDED_OVER = ["mavlink", "uavtalk", "xbee", "zenoh", "foxglove"]


@pytest.mark.parametrize("name", HANDED_OVER)
def test_a_backend_on_a_loop_counts_a_full_hand_over(name: str, tmp_path: Path) -> None:
    with contextlib.ExitStack() as stack:
        if name == "xbee":  # a module that answers: an emulated pair
            from xbee_pair import XBeePair

            from backends.xbee.backend import XbeeBackend
            from backends.xbee.options import XbeeOptions
            pair = stack.enter_context(XBeePair(1, 1))
            backend = XbeeBackend(XbeeOptions(url=pair.url_a))
        else:
            backend = _built_in(name, tmp_path)
        _fill_the_hand_over(backend)


def _fill_the_hand_over(backend: Any) -> None:
    from gateway.dispatcher import Dispatcher
    from gateway.model import Status
    from gateway.outcome import Outcome

    d = Dispatcher([backend])
    assert d.start() == []
    try:
        handover = backend.routes().handover
        assert handover is not None and handover.loop is not None
        status = Status(1000, 1, 0, 0)
        # ready (XBee: its port is up; Zenoh: its session is open)
        assert wait_for(lambda: d.dispatch(status) is Outcome.ACCEPTED)
        assert handover.barrier(DEADLINE_S)
        # (a hand-over sized by time, span_s: its bound is max_depth at most)
        with HeldLoop(handover.loop):
            outcomes = [d.dispatch(status) for _ in range(handover.max_depth + 3)]
            assert handover.queued() == len(outcomes) - outcomes.count(Outcome.QUEUE_FULL)
        full = outcomes.count(Outcome.QUEUE_FULL)
        if handover.span_s:
            assert full >= 3
        else:
            assert full == 3, outcomes
        stats = backend.stats()
        assert stats["dropped_queue_full"] == full
        assert stats["dropped"] >= full
    finally:
        d.close()
