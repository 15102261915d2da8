"""``aurora-gateway hc12 info | channel N | baud RATE | power N | mode N | reset | at CMD``.

Against a running gateway (its HC-12 backend's control socket, found from the port URL or
named with ``--gateway``) the exchange runs inside the gateway, on the port its engine owns
and with its knowledge of the vehicle.  Otherwise the command opens the port itself
(exclusively) and runs it the gateway's way: a :class:`~gateway.io.port.PortEngine` reads it
into the wire decoder, whose SM_UPDATE/STATUS feed a :class:`VehicleWatch` for ``--listen``
seconds; then the exchange takes the port with :meth:`~gateway.io.port.PortEngine.exclusive`.

Exit status: 0 done, 1 failed (no answer, garbage, port trouble), 2 invalid arguments
(nothing sent), 3 refused by a safety rule (nothing sent), 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path
from typing import Any

from backends.hc12 import at, control
from backends.hc12.port import open_port
from backends.hc12.provision import OPERATIONS, Result, Timing, check_request, plan, run_request
from backends.hc12.setline import SetLine, SetLineSpec, make_set_line, parse_set_line
from backends.hc12.vehicle import DEFAULT_MAX_AGE_S, VehicleWatch
from gateway import exits
from gateway.io.port import PortEngine, PortNotReady
from gateway.io.transport import TransportError
from gateway.model import SmUpdate, Status
from gateway.wire import Decoder

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_REFUSED, EXIT_INTERRUPTED = (
    exits.OK, exits.FAILED, exits.USAGE, exits.REFUSED, exits.INTERRUPTED)
DEFAULT_LISTEN_S = 1.5
ENGINE_DEADLINE_S = 5.0  # to take the port into the engine, and to hand it back on close
PROG = "aurora-gateway hc12"

DESCRIPTION = """\
Provision the HC-12 radio: same commands, ranges and safety rules as the firmware's
`telemetry hc12` shell.

commands:
  info            read the module's settings (AT+RX)
  channel N       set the channel, 1–127 (433.4 MHz + 400 kHz steps)
  baud RATE       set the module's UART rate: 1200 2400 4800 9600 19200 38400 57600 115200
  power N         set the TX power level, 1–8 (8 = +20 dBm)
  mode N          set the transmission mode FU1–FU4
  reset           restore factory defaults (AT+DEFAULT)
  at CMD          send a raw AT command, e.g. `at AT+V`

Refused unless the vehicle is known to be IDLE (heard within a few seconds); with no vehicle
heard at all, pass --bench. Needs the SET line wired (--set-line rts|dtr|gpio:CHIP:LINE).
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("command", choices=OPERATIONS, metavar="COMMAND",
                   help="info | channel N | baud RATE | power N | mode N | reset | at CMD")
    p.add_argument("argument", nargs="?", metavar="ARG", help="the command's argument")
    p.add_argument("--port", "-p", metavar="URL",
                   help="the HC-12's port: /dev/ttyUSB0, rfc2217://host:port (default: the "
                        "url of [backends.hc12] in --config)")
    p.add_argument("--baud", type=int, metavar="N",
                   help="the host's transparent-mode UART rate, restored after AT "
                        "(default: config, else 9600)")
    p.add_argument("--set-line", metavar="SPEC",
                   help="how SET is wired: none, rts, dtr, gpio:CHIP:LINE (default: config, "
                        "else none)")
    p.add_argument("--set-invert", action="store_true", default=None,
                   help="SET is driven through an inverter")
    p.add_argument("--config", "-c", metavar="FILE",
                   help="read port, baud and SET wiring from this gateway configuration")
    p.add_argument("--backend", default="hc12", metavar="NAME",
                   help="which [backends.NAME] table of --config (default hc12)")
    p.add_argument("--gateway", metavar="SOCKET",
                   help="the running gateway's control socket (default: found from the port)")
    p.add_argument("--bench", action="store_true",
                   help="the module is on the bench with no vehicle around: allow provisioning "
                        "when no vehicle is heard at all")
    p.add_argument("--listen", type=float, default=None, metavar="S",
                   help=f"stand-alone: listen this long for the vehicle's frames first "
                        f"(default {DEFAULT_LISTEN_S:g}; 0 = not at all)")
    p.add_argument("--timeout", type=float, default=None, metavar="S",
                   help="seconds to wait for each AT reply (default: config, else 1)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def add_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add the ``hc12`` subcommand (entry point group ``aurora_gateway.commands``)."""
    p = subparsers.add_parser("hc12", help="provision the HC-12 radio (info, channel, baud, …)",
                              description=DESCRIPTION,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    p.set_defaults(handler=main_handler)
    return p


# -- settings ------------------------------------------------------------------------------------

class _Usage(Exception):
    pass


def _settings(args: argparse.Namespace) -> dict[str, Any]:
    """Port, rates, SET wiring, control path: flags over the config table over defaults."""
    table: dict[str, Any] = {}
    if args.config:
        from gateway import config as gconfig

        try:
            cfg = gconfig.load(args.config)
        except gconfig.ConfigError as exc:
            raise _Usage(str(exc)) from None
        parts = [p for p in cfg.backends if p.name == args.backend]
        if not parts:
            raise _Usage(f"{args.config}: no enabled [backends.{args.backend}] table")
        table = parts[0].options
    url = args.port or table.get("url")
    if args.port:  # a bad --port is a usage error (2), before any safety rule (3) is asked
        from gateway.io.endpoints import EndpointError
        from gateway.sources import check_serial_url

        try:
            check_serial_url(args.port)
        except EndpointError as exc:
            raise _Usage(f"--port: {exc}") from None
    if not url and not args.gateway:
        raise _Usage("no port: pass --port URL (or --config FILE with a [backends.hc12] url, "
                     "or --gateway SOCKET)")
    baud = args.baud if args.baud is not None else table.get("baudrate", 9600)
    if baud not in at.BAUD_RATES:
        raise _Usage(f"--baud: expected one of {'|'.join(map(str, at.BAUD_RATES))}, got {baud}")
    invert = args.set_invert if args.set_invert is not None else table.get("set_invert", False)
    try:
        spec = parse_set_line(args.set_line or table.get("set_line", "none"), invert)
    except ValueError as exc:
        raise _Usage(str(exc)) from None
    timeout = args.timeout if args.timeout is not None else table.get("reply_timeout_s", 1.0)
    if not 0.05 <= timeout <= 30:
        raise _Usage(f"--timeout: expected 0.05–30 s, got {timeout:g}")
    listen = DEFAULT_LISTEN_S if args.listen is None else args.listen
    if not 0 <= listen <= 60:
        raise _Usage(f"--listen: expected 0–60 s, got {listen:g}")
    return {"url": url, "baud": baud, "spec": spec, "timeout": timeout, "listen": listen,
            "at_baud": table.get("at_baud", at.AT_BAUD),
            "max_age": table.get("idle_max_age_s", DEFAULT_MAX_AGE_S),
            "control": table.get("control", "auto")}


# -- the two ways to run ---------------------------------------------------------------------------

def _via_gateway(path: Path, args: argparse.Namespace, timeout: float) -> Result:
    # The exchange inside the gateway may wait for the port and then for each reply.
    budget = 10.0 + 3 * timeout + 1.0
    try:
        reply = control.call(path, {"op": args.command, "arg": args.argument,
                                    "bench": bool(args.bench)}, budget)
    except (OSError, ValueError) as exc:
        return Result(False, args.command, kind="failed",
                      error=f"cannot reach the gateway at {path}: {exc}")
    return Result.from_dict(reply)


def _listening_engine(port: Any, name: str, watch: VehicleWatch,
                      down: threading.Event) -> PortEngine:
    """An engine around the open ``port``: what arrives is decoded and every SM_UPDATE/STATUS
    goes to ``watch``; ``down`` is set if the port fails (it is not reopened)."""
    def heard(msg: Any) -> None:
        if isinstance(msg, SmUpdate | Status):
            watch.observe(msg)

    def link(up: bool) -> None:
        if not up:
            down.set()

    return PortEngine(lambda: port, name=name, protocol=Decoder(origin="hc12-listen"),
                      on_event=heard, on_link=link, reopen=False)


def _standalone(s: dict[str, Any], args: argparse.Namespace) -> Result:
    op, arg = args.command, args.argument
    spec: SetLineSpec = s["spec"]
    url = s["url"]
    # before touching the port: SET wired at all, GPIO bindings present
    if stop := check_request(op, make_set_line(spec, None), VehicleWatch(), bench=True):
        return stop
    watch = VehicleWatch(s["max_age"])
    if s["listen"] == 0 and not args.bench:
        return Result(False, op, kind="refused", error=watch.refusal(False) or "")
    try:
        port = open_port(url, s["baud"], spec, timeout=0)
    except TransportError as exc:
        hint = (" (is a gateway driving it? its control socket was not found)"
                if "lock" in str(exc).lower() or "busy" in str(exc).lower() else "")
        return Result(False, op, kind="failed", error=f"{exc}{hint}")
    down = threading.Event()
    engine = _listening_engine(port, url, watch, down)
    set_line: SetLine | None = None
    try:
        engine.start()
        if not engine.wait_connected(ENGINE_DEADLINE_S) or (
                s["listen"] > 0 and down.wait(s["listen"])):
            return Result(False, op, kind="failed",
                          error=f"{url} failed while listening for the vehicle")
        with engine.exclusive(ENGINE_DEADLINE_S) as lent:
            set_line = make_set_line(spec, lent)
            if stop := check_request(op, set_line, watch, bool(args.bench)):
                return stop
            return run_request(lent, set_line, op, arg, host_baud=s["baud"],
                               at_baud=s["at_baud"],
                               timing=Timing(reply_timeout_s=s["timeout"]))
    except PortNotReady as exc:
        return Result(False, op, kind="failed", error=f"{url} failed: {exc}")
    finally:
        try:
            if set_line is not None and spec.kind == "gpio":
                set_line.release()
        finally:
            engine.close(ENGINE_DEADLINE_S)


# -- the handler ---------------------------------------------------------------------------------

def _print(result: Result, as_json: bool) -> int:
    import json

    if as_json:
        print(json.dumps(result.as_dict()))
    elif result.ok:
        print(result.message)
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if not result.ok:
        label = {"refused": "refused", "usage": "", "interrupted": "interrupted"}.get(result.kind,
                                                                                    "failed")
        print(f"{PROG}: {label + ': ' if label else ''}{result.error}", file=sys.stderr)
        return {"usage": EXIT_USAGE, "refused": EXIT_REFUSED,
                "interrupted": EXIT_INTERRUPTED}.get(result.kind, EXIT_FAILED)
    return EXIT_OK


def main_handler(args: argparse.Namespace) -> int:
    """Run one ``hc12`` command; returns the exit status."""
    op = args.command
    try:
        plan(op, args.argument)  # invalid arguments: one line, nothing opened or sent
        s = _settings(args)
    except (at.AtUsageError, _Usage) as exc:
        return _print(Result(False, op, kind="usage", error=str(exc)), args.json)
    path: Path | None = Path(args.gateway) if args.gateway else None
    if path is None:
        try:
            path = control.resolve(s["control"], s["url"], create=False)
        except OSError:
            path = None
        if path is not None and not control.reachable(path):
            path = None
    elif not control.reachable(path):
        return _print(Result(False, op, kind="failed",
                             error=f"no gateway answers at {path}"), args.json)
    try:
        if path is not None:
            if args.set_line:
                print(f"warning: --set-line ignored: the running gateway at {path} uses its "
                      f"configured SET line", file=sys.stderr)
            result = _via_gateway(path, args, s["timeout"])
        else:
            result = _standalone(s, args)
    except KeyboardInterrupt:
        what = ("the gateway finishes the exchange and restores the port itself"
                if path is not None else "SET released and the host UART rate restored")
        return _print(Result(False, op, kind="interrupted", error=f"interrupted; {what}"),
                      args.json)
    return _print(result, args.json)


def main(argv: list[str] | None = None) -> int:
    """``python -m backends.hc12.cli …`` — the same command without the gateway's CLI."""
    from gateway.commands.cli import CommandParser  # one-line errors, the exit-status table

    parser = CommandParser(prog=PROG, description=DESCRIPTION,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(parser)
    return main_handler(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())

