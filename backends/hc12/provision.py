"""Provisioning the HC-12: one AT exchange with every safety rule of the firmware's shell.

:class:`AtSession` runs one exchange on a port its caller owns for the whole exchange — the
port engine's :meth:`~gateway.io.port.PortEngine.exclusive` (the firmware's TX lock), so
transparent-mode frame bytes can never interleave with AT commands; frames queue meanwhile
and drain when the port is handed back.  The session:

1. drains what the engine already wrote (``flush``), remembers the host UART rate and
   switches it to 9600 baud, asserts SET and waits for the module (≥ 40 ms);
2. sends commands and checks each reply (a port with a zero read timeout, as the engine
   keeps it, is polled every few milliseconds);
3. on **every** exit path — success, bad reply, timeout, port failure, Ctrl-C — releases SET,
   waits for the module to return to transparent mode (≤ 80 ms) and restores the host UART
   rate, with SIGINT deferred while it does.

:func:`run_request` turns an operator request (``info``, ``channel N`` …) into commands
(validated before anything is touched), runs them and words the result.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from typing import Any

from backends.hc12 import at
from backends.hc12.at import AtReplyError, AtUsageError, Command
from backends.hc12.setline import NoSetLine, SetLine, SetLineError
from backends.hc12.vehicle import VehicleWatch

log = logging.getLogger(__name__)

OPERATIONS = ("info", "channel", "baud", "power", "mode", "reset", "at")
NEEDS_ARG = {"channel": "a channel 1–127", "baud": "a rate (" + "|".join(map(str, at.BAUD_RATES))
             + ")", "power": "a power level 1–8", "mode": "a mode 1–4",
             "at": "an AT command, e.g. AT+V"}
REPLY_LIMIT = 512  # bytes; a flood of noise is garbage, not a reply
POLL_S = 0.005  # between reads of a port that returns at once when nothing is waiting


class ProvisionError(Exception):
    """The exchange failed (no answer, garbage, port trouble)."""


class Refused(ProvisionError):
    """A safety rule forbids the exchange; nothing was sent."""


class AtTimeout(ProvisionError):
    """The module did not answer (in full) in time."""


@dataclass(frozen=True)
class Timing:
    """Delays of an exchange (HC-12 manual: ≥ 40 ms after SET low; changes apply within 80 ms
    of SET high; ≥ 200 ms before entering AT mode again)."""

    enter_s: float = 0.05
    exit_s: float = 0.1
    reenter_s: float = 0.2
    reply_timeout_s: float = 1.0
    quiet_s: float = 0.15  # a raw command's reply ends after this much silence


@contextlib.contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold off SIGINT (Ctrl-C) for the duration; deliver it afterwards.  Only the main thread
    receives signals, so elsewhere this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    try:
        old = signal.signal(signal.SIGINT, lambda signum, frame: pending.append(signum))
    except ValueError:  # not the main interpreter
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
        if pending:
            if callable(old):
                old(signal.SIGINT, None)
            elif old == signal.SIG_DFL:
                raise KeyboardInterrupt


_last_exit: dict[int, float] = {}  # id(port) → monotonic time AT mode was last left


class AtSession:
    """One AT exchange on an open port (see the module docstring)."""

    def __init__(self, port: Any, set_line: SetLine, *, at_baud: int = at.AT_BAUD,
                 timing: Timing = Timing(), sleep: Callable[[float], None] = time.sleep,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.port = port
        self.set_line = set_line
        self.at_baud = at_baud
        self.timing = timing
        self._sleep = sleep
        self._clock = clock
        self._saved_baud: int | None = None
        self._set_asserted = False
        self.restore_error: str | None = None

    # -- entry and exit --------------------------------------------------------------------------

    def __enter__(self) -> AtSession:
        try:
            port = self.port
            port.flush()  # frame bytes already written leave at the transparent-mode rate
            left = _last_exit.get(id(port))
            if left is not None:
                wait = self.timing.reenter_s - (self._clock() - left)
                if wait > 0:
                    self._sleep(wait)
            self._saved_baud = port.baudrate
            if port.baudrate != self.at_baud:
                port.baudrate = self.at_baud
            self._set_asserted = True
            self.set_line.assert_()
            self._sleep(self.timing.enter_s)
            port.reset_input_buffer()  # whatever the module said before is not our reply
        except BaseException as exc:
            self._exit()
            if isinstance(exc, SetLineError | OSError):  # SerialException is an OSError
                raise ProvisionError(f"cannot enter AT mode: {exc}") from exc
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._exit()

    def _exit(self) -> None:
        """Release SET and restore the host baud rate — each step attempted whatever
        happened before it, with Ctrl-C held off."""
        errors: list[str] = []
        with sigint_deferred():
            port = self.port
            if self._set_asserted:
                self._set_asserted = False
                try:
                    port.flush()
                except Exception as exc:
                    errors.append(f"flush: {exc}")
                try:
                    self.set_line.release()
                except Exception as exc:
                    errors.append(f"releasing SET: {exc}")
                self._sleep(self.timing.exit_s)
                _last_exit[id(port)] = self._clock()
            if self._saved_baud is not None:
                saved, self._saved_baud = self._saved_baud, None
                try:
                    if port.baudrate != saved:
                        port.baudrate = saved
                except Exception as exc:
                    errors.append(f"restoring {saved} baud: {exc}")
        if errors:
            self.restore_error = "; ".join(errors)
            log.error("HC-12 AT exit: %s", self.restore_error)

    # -- commands -------------------------------------------------------------------------------

    def send(self, cmd: Command) -> list[str]:
        """Send one command; return its reply lines (checked against what ``cmd`` expects)."""
        port = self.port
        port.write(cmd.wire)
        port.flush()
        t = self.timing
        start = self._clock()
        buf = b""
        last_rx: float | None = None
        while True:
            now = self._clock()
            if now - start >= t.reply_timeout_s:
                break
            if cmd.reply_lines is None and last_rx is not None and now - last_rx >= t.quiet_s:
                break
            waiting = port.in_waiting
            chunk = port.read(waiting if waiting > 0 else 1)
            if not chunk:
                if not getattr(port, "timeout", None):  # returned at once: do not spin
                    self._sleep(POLL_S)
                continue
            buf += chunk
            last_rx = self._clock()
            if len(buf) > REPLY_LIMIT:
                raise AtReplyError(f"the module sent more than {REPLY_LIMIT} bytes of garbage "
                                   f"in reply to {cmd.text}: {buf[:32]!r}…")
            lines, _ = at.split_lines(buf)
            if cmd.reply_lines is not None and (len(lines) >= cmd.reply_lines
                                                or "ERROR" in lines):
                break
        if not buf:
            raise AtTimeout(f"no answer to {cmd.text} within {t.reply_timeout_s:g} s: is the "
                            f"module powered, SET wired to {self.set_line.description} and the "
                            f"host UART at {self.at_baud} baud?")
        lines, rest = at.split_lines(buf + b"\n" if cmd.reply_lines is None else buf)
        if rest:
            at.split_lines(rest + b"\n")  # raises on garbage
            shown = " | ".join([*lines, rest.decode("ascii")])
            raise AtTimeout(f"incomplete reply to {cmd.text} after {t.reply_timeout_s:g} s: "
                            f"{shown}")
        cmd.check(lines)
        return lines


# -- requests -----------------------------------------------------------------------------------

def plan(op: str, arg: Any = None) -> list[Command]:
    """The commands for an operator request; :class:`AtUsageError` (one line) when invalid."""
    if op not in OPERATIONS:
        raise AtUsageError(f"unknown command {op!r}; one of {', '.join(OPERATIONS)}")
    if op in NEEDS_ARG and (arg is None or str(arg).strip() == ""):
        raise AtUsageError(f"{op}: needs {NEEDS_ARG[op]}")
    if op not in NEEDS_ARG and arg not in (None, ""):
        raise AtUsageError(f"{op}: takes no argument, got {arg!r}")
    if op == "info":
        return [at.info()]
    if op == "channel":
        return [at.channel(arg)]
    if op == "baud":
        return [at.baud(arg)]
    if op == "power":
        return [at.power(arg)]
    if op == "mode":
        return [at.mode(arg), at.info()]  # read back: FU2/FU4 change the UART rate too
    if op == "reset":
        return [at.reset(), at.info()]
    return [at.raw(arg)]


@dataclass
class Result:
    """What a request did, in a form the control socket can carry (JSON)."""

    ok: bool
    op: str
    message: str = ""
    warnings: list[str] = field(default_factory=list)
    settings: dict[str, Any] | None = None
    replies: list[list[str]] = field(default_factory=list)
    error: str = ""
    kind: str = ""  # on failure: "usage" | "refused" | "failed" | "interrupted"

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Result:
        keys = cls.__dataclass_fields__
        return cls(**{k: v for k, v in d.items() if k in keys})


def follow_warning(module_baud: int, host_baud: int) -> str:
    return (f"the module's UART now runs at {module_baud} baud but the host at {host_baud}: the "
            f"host side must follow — set baudrate = {module_baud} in [backends.hc12] (or "
            f"--hc12-baud {module_baud}) and restart the gateway; the ground module needs the "
            f"same rate, channel and mode")


def describe(settings: at.Settings) -> str:
    level = settings.power_level
    power = f"{level} ({settings.power_dbm:+d} dBm)" if level else f"{settings.power_dbm:+d} dBm"
    air = f", air ≈ {settings.air_bps} bps" if settings.air_bps else ""
    return (f"mode     FU{settings.mode}\n"
            f"baud     {settings.baud}{air}\n"
            f"channel  {settings.channel} ({settings.frequency_mhz:.1f} MHz)\n"
            f"power    {power}")


def interpret(op: str, arg: Any, replies: list[list[str]], host_baud: int) -> Result:
    """Word the replies of a successful exchange."""
    res = Result(True, op, replies=replies)
    settings = at.parse_rx(replies[-1]) if op in ("info", "mode", "reset") else None
    if settings is not None:  # info, mode, reset: the module's settings read back
        res.settings = settings.as_dict()
        if op == "info":
            res.message = describe(settings)
        else:
            head = (f"mode set to FU{int(str(arg))}" if op == "mode"
                    else "factory defaults restored")
            res.message = head + "; the module now reports:\n" + describe(settings)
            if settings.baud != host_baud:
                res.warnings.append(follow_warning(settings.baud, host_baud))
    elif op == "channel":
        n = int(str(arg))
        res.message = (f"channel set to {n} ({at.channel_mhz(n):.1f} MHz); the ground module "
                       f"must use the same channel")
    elif op == "baud":
        rate = int(str(arg))
        res.message = f"module UART rate set to {rate} baud (in effect now SET is released)"
        if rate != host_baud:
            res.warnings.append(follow_warning(rate, host_baud))
    elif op == "power":
        n = int(str(arg))
        res.message = f"power set to {n} ({at.POWER_DBM[n]:+d} dBm)"
    else:
        res.message = "\n".join(replies[0]) if replies[0] else "(no reply)"
        cmd = str(arg).strip().upper()
        if cmd.startswith(("AT+B", "AT+DEFAULT", "AT+FU")):
            res.warnings.append("this command may change the module's UART rate: check with "
                                "`hc12 info` and make the host side follow")
        elif cmd.startswith("AT+SLEEP"):
            res.warnings.append("the module sleeps once SET is released and transmits nothing "
                                "until it is woken by entering AT mode again")
    return res


def check_allowed(set_line: SetLine, watch: VehicleWatch, bench: bool) -> None:
    """The shell's rules before anything is sent: SET wired (else :class:`Refused`, with the
    bench hint) and usable (else :class:`ProvisionError`), vehicle known IDLE (else
    :class:`Refused`)."""
    try:
        set_line.check()
    except SetLineError as exc:
        if isinstance(set_line, NoSetLine):
            raise Refused(str(exc)) from None
        raise ProvisionError(str(exc)) from None  # e.g. the GPIO bindings are missing
    reason = watch.refusal(bench)
    if reason is not None:
        raise Refused(reason)



def check_request(op: str, set_line: SetLine, watch: VehicleWatch, bench: bool) -> Result | None:
    """:func:`check_allowed` for request ``op``: None when it may go ahead, else the
    :class:`Result` that refuses it (kind "refused") or fails it (kind "failed")."""
    try:
        check_allowed(set_line, watch, bench)
    except Refused as exc:
        return Result(False, op, kind="refused", error=str(exc))
    except ProvisionError as exc:
        return Result(False, op, kind="failed", error=str(exc))
    return None

def run_request(port: Any, set_line: SetLine, op: str, arg: Any, *, host_baud: int,
                at_baud: int = at.AT_BAUD, timing: Timing = Timing()) -> Result:
    """Validate, exchange and word one request on an open port the caller owns (from
    :meth:`~gateway.io.port.PortEngine.exclusive`; checks done by the caller).

    Failures come back as a :class:`Result` with ``ok`` False; KeyboardInterrupt propagates
    (after the session restored the port)."""
    try:
        commands = plan(op, arg)
    except AtUsageError as exc:
        return Result(False, op, error=str(exc), kind="usage")
    replies: list[list[str]] = []
    session = AtSession(port, set_line, at_baud=at_baud, timing=timing)
    try:
        with session:
            for cmd in commands:
                replies.append(session.send(cmd))
    except (ProvisionError, AtReplyError) as exc:
        res = Result(False, op, error=str(exc), kind="failed", replies=replies)
    except Exception as exc:  # the port failed under us (SerialException, OSError …)
        res = Result(False, op, error=f"port failed during the exchange: {exc}", kind="failed",
                     replies=replies)
    else:
        res = interpret(op, arg, replies, host_baud)
    if session.restore_error:
        res.ok = False
        res.kind = "failed"
        res.error = ((res.error + "; ") if res.error else "") + \
            f"could not restore the port: {session.restore_error}"
    return res
