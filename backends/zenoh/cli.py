"""``aurora-gateway listen [KEY]``: watch what gateways publish on Zenoh, without code.

Prints one JSON line per update (``--compact``: one live status line per vehicle instead),
after first asking the gateways for the latest value of every matching key, so something shows
at once.
Counts publications lost on the way from the gateways' sequence numbers and reports them at
the end (stderr).  Also runnable as ``python -m backends.zenoh.cli listen …``.
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any, TextIO

from backends.zenoh import encoding as enc
from backends.zenoh.keys import (
    DEFAULT_ENDPOINT,
    DEFAULT_PREFIX,
    MAX_VEHICLES,
    RAW,
    STATS_KIND,
    SeqTracker,
    parse_attachment,
    parse_key,
    parse_stats_key,
)
from backends.zenoh.session import SessionOptions, zerror_text
from gateway import exits
from gateway.config import ConfigError
from gateway.io.backoff import Backoff
from gateway.signals import Stopper
from gateway.wire import decode_all, to_wire_dict

EXIT_USAGE = exits.USAGE
QUERY_TIMEOUT_S = 2.0
COMPACT_INTERVAL_S = 0.1
MAX_GATEWAYS = 4096  # gateway ids counted at most (a peer chooses them)
MAX_TOKENS = 4096  # liveliness keys remembered (to print each change once; a peer chooses them)
MAX_PENDING = 10_000  # samples waiting to be printed; more are dropped, counted


def add_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``listen`` to the ``aurora-gateway`` subcommands."""
    p = subparsers.add_parser(
        "listen", help="print what gateways publish on Zenoh (JSON lines or a live line)",
        description="Subscribe to KEY on Zenoh and print every update as a JSON line.")
    p.add_argument("key", nargs="?", default=None,
                   help="key expression (default <prefix>/*/* : every vehicle's JSON "
                        "documents; <prefix>/** adds the raw frames, decoded; "
                        "<prefix>/@gateways/*/stats: the gateways' counters)")
    p.add_argument("--connect", "-e", action="append", metavar="ENDPOINT",
                   help=f"router or gateway to connect to (repeatable; default "
                        f"{DEFAULT_ENDPOINT}, the local gateway)")
    p.add_argument("--mode", choices=("peer", "client"), default=None,
                   help="Zenoh mode (default peer)")
    p.add_argument("--config", metavar="FILE", help="a full Zenoh JSON5 configuration")
    p.add_argument("--user", help="user name (user/password authentication)")
    p.add_argument("--password", help="password (visible to other users of this machine: "
                   "prefer --config)")
    p.add_argument("--prefix", default=DEFAULT_PREFIX,
                   help=f"key prefix the gateways use (default {DEFAULT_PREFIX})")
    p.add_argument("--compact", action="store_true",
                   help="one live status line per vehicle instead of JSON lines")
    p.add_argument("--gateways", action="store_true",
                   help="also print gateways appearing and vanishing (liveliness)")
    p.add_argument("--no-query", dest="query", action="store_false",
                   help="do not ask for the latest values first")
    p.add_argument("--count", type=int, default=0, metavar="N",
                   help="exit after N updates (0 = never)")
    p.add_argument("--duration", type=float, default=0.0, metavar="S",
                   help="exit after S seconds (0 = never)")
    p.set_defaults(handler=run_listen)
    return p


# -- formatting --------------------------------------------------------------------------------

def _json_safe(d: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in d.items()}


def describe(key: str, payload: bytes, encoding: str, prefix: str) -> dict[str, Any]:
    """The JSON line for one publication: where it is from and what it says."""
    parsed = parse_key(key, prefix)
    vehicle, kind = (parsed[0], parsed[1]) if parsed else (None, None)
    if parse_stats_key(key, prefix) is not None:  # a gateway's, not a vehicle's
        vehicle, kind = None, STATS_KIND
    line: dict[str, Any] = {"key": key, "vehicle": vehicle, "kind": kind}
    if kind == RAW:
        msgs = decode_all(payload)
        line["value"] = _json_safe(to_wire_dict(msgs[0])) if len(msgs) == 1 else None
        line["hex"] = payload.hex()
    elif encoding in (enc.SM_UPDATE_PACKED, enc.STATUS_PACKED):
        try:
            line["value"] = _json_safe(enc.document(enc.decode(kind or "", payload, encoding)))
        except enc.PayloadError:
            line["value"] = None
        line["hex"] = payload.hex()
    else:
        try:
            line["value"] = json.loads(payload)
        except (ValueError, UnicodeDecodeError):
            line["value"] = None
            line["hex"] = payload.hex()
    return line


class CompactView:
    """One status line for every vehicle seen (sorted by name; at most MAX_VEHICLES, any
    further one counted in the last line), then a line of totals: the block is rewritten in
    place at most 10 times a second."""

    def __init__(self, out: TextIO) -> None:
        self.out = out
        self.vehicles: dict[str, str] = {}
        self.untracked = 0
        self._last = 0.0
        self._drawn = 0

    def update(self, line: dict[str, Any], stats: str) -> None:
        v, kind, value = line.get("vehicle"), line.get("kind"), line.get("value")
        if v is None or not isinstance(value, dict):
            return
        if v not in self.vehicles and len(self.vehicles) >= MAX_VEHICLES:
            self.untracked += 1
            return
        if kind == "sm_update":
            self.vehicles[v] = (
                f"{value.get('state_name', '?'):<9} "
                f"{'ARMED' if value.get('armed') else 'safe '} "
                f"alt {_num(value.get('altitude_m')):8.1f} m "
                f"vel {_num(value.get('velocity_mps')):7.1f} m/s")
        elif kind == "link" and not value.get("up"):
            self.vehicles[v] = f"LINK DOWN ({value.get('source')})"
        else:
            return
        now = time.monotonic()
        if now - self._last >= COMPACT_INTERVAL_S:
            self._last = now
            self.render(stats)

    def lines(self, stats: str) -> list[str]:
        """What :meth:`render` shows: a line per vehicle, then the totals."""
        width = max(map(len, self.vehicles), default=0)
        rows = [f"{v:<{width}} {self.vehicles[v]}" for v in sorted(self.vehicles)] or ["waiting"]
        more = f", {self.untracked} updates of further vehicles" if self.untracked else ""
        return [*rows, f"{len(self.vehicles)} vehicle(s), {stats}{more}"]

    def render(self, stats: str) -> None:
        lines = self.lines(stats)
        # back to the first line of the block drawn last, then every line cleared and written
        up = f"\x1b[{self._drawn - 1}F" if self._drawn > 1 else "\r"
        self.out.write(up + "\n".join(f"{ln}\x1b[K" for ln in lines))
        self.out.flush()
        self._drawn = len(lines)


def _num(v: Any) -> float:
    return float(v) if isinstance(v, int | float) else math.nan


# -- the command -------------------------------------------------------------------------------

def run_listen(args: argparse.Namespace, out: TextIO | None = None,
               stop: threading.Event | None = None) -> int:
    """The ``listen`` handler; returns the exit status."""
    import zenoh

    out = out if out is not None else sys.stdout
    err = sys.stderr
    prefix = args.prefix
    key = args.key or f"{prefix}/*/*"
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        print(f"aurora-gateway listen: KEY: {zerror_text(exc)}", file=err)
        return EXIT_USAGE
    if args.count < 0 or args.duration < 0 or not math.isfinite(args.duration):
        print("aurora-gateway listen: --count and --duration must be ≥ 0", file=err)
        return EXIT_USAGE
    try:
        opts = SessionOptions(
            mode=args.mode,
            connect=args.connect if args.connect else (None if args.config
                                                       else [DEFAULT_ENDPOINT]),
            config_file=args.config or "", user=args.user or "",
            password=args.password or "", default_listen=[])
        opts.config()
    except ConfigError as exc:
        print(f"aurora-gateway listen: {exc}", file=err)
        return EXIT_USAGE

    stop = stop if stop is not None else threading.Event()
    samples: queue.SimpleQueue[Any] = queue.SimpleQueue()
    stopper = Stopper(stop).install()  # its signal: SIGINT exits 130 (gateway.exits)
    session = None
    tracker = SeqTracker()
    gateways: set[str] = set()
    alive_tokens: dict[str, bool] = {}  # liveliness key → alive, as last printed
    count = 0
    compact = CompactView(out) if args.compact else None
    deadline = time.monotonic() + args.duration if args.duration else None

    dropped = [0]  # samples that arrived while MAX_PENDING waited to be printed

    def on_sample(sample: Any) -> None:
        if samples.qsize() >= MAX_PENDING:  # the output is slower than the publishers
            dropped[0] += 1
            return
        att = sample.attachment
        samples.put((False, str(sample.key_expr), sample.payload.to_bytes(),
                     str(sample.encoding), att.to_bytes() if att is not None else None))

    def on_token(sample: Any) -> None:
        samples.put((None, str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, "", None))

    def stats_text() -> str:
        return f"{count} rx, {tracker.lost} lost, {len(gateways)} gateway(s)"

    try:
        backoff = Backoff(0.2, 2.0)
        failures = 0
        while session is None and not stop.is_set():
            try:
                session = opts.open()
            except zenoh.ZError as exc:
                failures += 1
                if failures == 1:
                    print(f"aurora-gateway listen: cannot connect ({opts.describe()}): "
                          f"{zerror_text(exc)}; retrying", file=err)
                stop.wait(backoff.next())
        if session is None:
            return stopper.status
        if args.gateways:
            # The gateways alive now are asked for (and queued) before any update can be:
            # so they print first, whatever --count says.  A token that appears between the
            # subscriber and the query is printed once, by whichever sees it first.
            tokens = f"{prefix}/*/gateway/*"
            session.liveliness().declare_subscriber(tokens, on_token)
            try:
                for reply in session.liveliness().get(tokens, timeout=QUERY_TIMEOUT_S):
                    if reply.ok is not None:
                        samples.put((None, str(reply.ok.key_expr), True, "", None))
            except zenoh.ZError as exc:
                print(f"aurora-gateway listen: liveliness query failed: {zerror_text(exc)}",
                      file=err)
        session.declare_subscriber(key, on_sample)
        print(f"aurora-gateway listen: {key} ({opts.describe()})", file=err)
        if args.query:
            try:
                for reply in session.get(key, timeout=QUERY_TIMEOUT_S):
                    s = reply.ok
                    if s is not None:
                        att = s.attachment
                        samples.put((True, str(s.key_expr), s.payload.to_bytes(),
                                     str(s.encoding), att.to_bytes() if att is not None else None))
            except zenoh.ZError as exc:
                print(f"aurora-gateway listen: query failed: {zerror_text(exc)}", file=err)
        while not stop.is_set():
            if deadline is not None and time.monotonic() >= deadline:
                break
            try:
                item = samples.get(timeout=0.1)
            except queue.Empty:
                continue
            from_query, k, payload, encoding, att = item
            if from_query is None:  # liveliness
                if alive_tokens.get(k) == payload:
                    continue  # the subscriber and the query both saw it
                if k not in alive_tokens and len(alive_tokens) >= MAX_TOKENS:
                    del alive_tokens[next(iter(alive_tokens))]  # the oldest is forgotten
                alive_tokens[k] = payload
                line = {"gateway_token": k, "alive": payload}
                if compact is None:
                    out.write(json.dumps(line) + "\n")
                    out.flush()
                continue
            gw, seq = parse_attachment(att)
            if gw is not None and len(gateways) < MAX_GATEWAYS:
                gateways.add(gw)
            if not from_query:
                tracker.see(gw, k, seq)
            line = describe(k, payload, encoding, prefix)
            line["gateway"] = gw
            line["seq"] = seq
            if from_query:
                line["latest"] = True
            line["rx_time"] = round(time.time(), 6)
            count += 1
            if compact is not None:
                compact.update(line, stats_text())
            else:
                out.write(json.dumps(line) + "\n")
                out.flush()
            if args.count and count >= args.count:
                break
    except BrokenPipeError:
        return 0
    finally:
        stopper.restore()
        if session is not None:
            session.close()
        if compact is not None:
            compact.render(stats_text())
            out.write("\n")
    print(f"aurora-gateway listen: {count} updates from {len(gateways)} gateway(s); "
          f"{tracker.lost} lost (sequence gaps), {tracker.restarts} publisher restarts"
          + (f", {dropped[0]} dropped (printing fell behind)" if dropped[0] else ""),
          file=err)
    return stopper.status


def main(argv: Sequence[str] | None = None) -> int:
    from gateway.commands.cli import CommandParser  # one-line errors, the exit-status table

    parser = CommandParser(prog="aurora-gateway")
    sub = parser.add_subparsers(dest="command", required=True)
    add_command(sub)
    args = parser.parse_args(argv)
    return args.handler(args)


if __name__ == "__main__":
    sys.exit(main())
