"""Ctrl-C and SIGTERM held while modules load (gateway/signals.py): noted, not raised, and
delivered through their own handlers when the hold ends; and the crash the hold prevents —
a Ctrl-C inside orjson's module initialisation — does not happen in our modules."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from gateway import exits, signals

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def handlers() -> Iterator[list[int]]:
    """SIGINT raises KeyboardInterrupt (as in a plain interpreter); SIGTERM is noted in the
    yielded list.  The handlers the test found are put back afterwards."""
    seen: list[int] = []
    old = {s: signal.getsignal(s) for s in signals.SIGNALS}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, lambda signum, frame: seen.append(signum))
    try:
        yield seen
    finally:
        signals.release()
        for s, h in old.items():
            signal.signal(s, h)


def test_a_ctrl_c_while_held_is_raised_when_the_hold_ends(handlers: list[int]) -> None:
    with pytest.raises(KeyboardInterrupt), signals.held():
        signal.raise_signal(signal.SIGINT)
        reached = True  # not interrupted here
    assert reached
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_the_last_signal_held_is_the_one_delivered(handlers: list[int]) -> None:
    with signals.held():
        signal.raise_signal(signal.SIGINT)
        signal.raise_signal(signal.SIGTERM)
    assert handlers == [signal.SIGTERM]


def test_a_nested_hold_leaves_the_outer_one_to_decide(handlers: list[int]) -> None:
    assert signals.hold()
    with signals.held():
        signal.raise_signal(signal.SIGINT)
    assert signals.holding()  # the inner block ended without delivering it
    with pytest.raises(KeyboardInterrupt):
        signals.release()
    assert not signals.holding()
    signals.release()  # nothing held: nothing happens


def test_a_hold_without_signals_changes_nothing(handlers: list[int]) -> None:
    with signals.held():
        pass
    assert handlers == []
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_only_the_main_thread_holds(handlers: list[int]) -> None:
    results: list[bool] = []
    t = threading.Thread(target=lambda: results.append(signals.hold()))
    t.start()
    t.join()
    assert results == [False]
    assert not signals.holding()


#: imports ``module`` with a Ctrl-C arriving in the middle of orjson's initialisation: an
#: import hook raises SIGINT when that init imports the first module it needs that is not
#: loaded yet (``uuid``, when the module came from ``aurora-gateway listen``)
TRIP = textwrap.dedent("""
    import signal, sys
    class Trip:
        fired = False
        def find_spec(self, name, path=None, target=None):
            if "orjson" in sys.modules and not name.startswith("orjson") and not self.fired:
                self.fired = True
                print("tripped on", name)
                signal.raise_signal(signal.SIGINT)
            return None
    sys.meta_path.insert(0, Trip())
    try:
        import {module}
    except KeyboardInterrupt:
        print("interrupted", "orjson.orjson" in sys.modules)
        sys.exit(130)
""")


@pytest.mark.parametrize("module", ["backends.zenoh.encoding", "backends.foxglove.backend",
                                    "gateway.commands.export_mcap"])
def test_a_ctrl_c_inside_orjsons_init_is_an_interrupt_not_a_crash(module: str) -> None:
    proc = subprocess.run([sys.executable, "-c", TRIP.format(module=module)], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    # the interrupt came after orjson had finished loading: the trip fired in its init
    assert proc.stdout.startswith("tripped on "), proc.stdout  # inside orjson's init
    assert (proc.returncode, proc.stdout.splitlines()[1:]) == (
        exits.INTERRUPTED, ["interrupted True"]), (proc.returncode, proc.stderr[-2000:])


#: the ``aurora-gateway`` entry point with ``sig`` arriving while the command line loads the
#: plugin commands' modules (the parser's build), before any command code runs
ENTRY = textwrap.dedent("""
    import signal, sys
    class Trip:
        def find_spec(self, name, path=None, target=None):
            if name == "backends.zenoh.cli":
                signal.raise_signal(signal.{sig})
            return None
    sys.meta_path.insert(0, Trip())
    sys.argv = ["aurora-gateway", "listen", "--connect", "tcp/127.0.0.1:9", "--duration", "2"]
    from gateway.__main__ import main
    main()
""")


@pytest.mark.parametrize(("sig", "status"), [("SIGINT", exits.INTERRUPTED), ("SIGTERM", exits.OK)])
def test_a_signal_while_the_command_line_loads_stops_the_command_before_it_starts(
        sig: str, status: int) -> None:
    proc = subprocess.run([sys.executable, "-c", ENTRY.format(sig=sig)], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == status, proc.stderr[-2000:]
    assert proc.stderr == ""  # quiet, and listen never started (it would say it is connecting)


#: a Stopper's signal arriving while the main thread holds its event's lock, as
#: ``Event.wait`` does around its bookkeeping (where ``record`` once ignored a Ctrl-C)
IN_THE_LOCK = textwrap.dedent("""
    import signal, threading
    from gateway.signals import Stopper
    stop = threading.Event()
    stopper = Stopper(stop).install()
    with stop._cond:  # the lock Event.wait holds; the handler runs in here
        signal.raise_signal(signal.{sig})
    print(stop.wait(10), stopper.status)
""")


@pytest.mark.parametrize(("sig", "status"), [("SIGINT", exits.INTERRUPTED), ("SIGTERM", exits.OK)])
def test_a_stop_signal_inside_the_events_own_lock_still_stops(sig: str, status: int) -> None:
    try:
        proc = subprocess.run([sys.executable, "-c", IN_THE_LOCK.format(sig=sig)], cwd=ROOT,
                              capture_output=True, text=True, timeout=20)
    except subprocess.TimeoutExpired:
        pytest.fail("the handler deadlocked on the event's lock")
    assert (proc.returncode, proc.stdout) == (0, f"True {status}\n"), proc.stderr[-2000:]


#: a Ctrl-C the instant the entry point has caught SIGTERM (its first act, and what
#: tests/test_exit_codes.py waits for before it signals): it surfaces from that very call
FIRST_ACT = textwrap.dedent("""
    import signal, sys
    real = signal.signal
    def catching(sig, handler):
        old = real(sig, handler)
        if sig == signal.SIGTERM and handler is not signal.SIG_DFL:
            signal.signal = real
            signal.raise_signal(signal.SIGINT)
        return old
    signal.signal = catching
    sys.argv = ["aurora-gateway", "run", "--only", "console", "--duration", "5"]
    from gateway.__main__ import main
    main()
""")


def test_a_ctrl_c_as_the_entry_point_catches_sigterm_is_a_quiet_130() -> None:
    proc = subprocess.run([sys.executable, "-c", FIRST_ACT], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert (proc.returncode, proc.stderr) == (exits.INTERRUPTED, "")


def test_handlers_are_all_put_back_even_when_one_raises(handlers: list[int]) -> None:
    """Putting back SIGINT's handler can raise (a Ctrl-C arriving right then, through the
    handler just put back); SIGTERM's is put back all the same."""
    mine = signal.getsignal(signal.SIGTERM)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    with pytest.raises(TypeError):  # (a bad handler: the simplest raise there is)
        signals._put_back([(signal.SIGINT, "not a handler"), (signal.SIGTERM, mine)])
    assert signal.getsignal(signal.SIGTERM) is mine


def test_a_stopper_installed_while_held_ends_the_hold_raising_what_it_noted(
        handlers: list[int]) -> None:
    """(run, record, replay, monitor, simulate and listen are held until their Stopper: no
    moment between where a Ctrl-C raises into whatever runs, and the one that came
    meanwhile ends them before they start.)"""
    assert signals.hold()
    signal.raise_signal(signal.SIGINT)  # noted, not raised
    stop = threading.Event()
    with pytest.raises(KeyboardInterrupt):
        signals.Stopper(stop).install()
    assert not signals.holding() and not stop.is_set()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    stopper = signals.Stopper(stop).install()  # not held: installs as usual
    signal.raise_signal(signal.SIGTERM)
    assert stop.wait(5) and stopper.status == exits.OK and handlers == []
    stopper.restore()
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
