"""A small Zenoh router: a Python session in ``router`` mode, for tests and for fleets.

zenohd is not installable everywhere; a Python session in router mode runs the same Rust
routing code (without zenohd's plugins: no REST API, no storages).  Gateways and dashboards
connect to it in client (or peer) mode and it routes between them.

    python -m backends.zenoh.router                           # tcp/127.0.0.1:7447
    python -m backends.zenoh.router --listen tcp/0.0.0.0:7447 # reachable from the network
    python -m backends.zenoh.router --config examples/zenoh-router-acl.json5

``--config`` loads a full Zenoh JSON5 configuration (ACL, TLS, authentication …); ``--listen``
then replaces its listen endpoints.  The process prints ``ready <endpoints>`` on stdout once it
listens (tests wait for that line), then runs until SIGINT/SIGTERM and closes the session.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from collections.abc import Sequence
from typing import Any

from gateway.signals import Stopper

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def build_config(listen: Sequence[str], config_file: str | None, multicast: bool) -> Any:
    import zenoh

    if config_file:
        cfg = zenoh.Config.from_file(config_file)
    else:
        cfg = zenoh.Config()
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    cfg.insert_json5("mode", json.dumps("router"))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    elif not config_file:
        cfg.insert_json5("listen/endpoints", json.dumps([DEFAULT_LISTEN]))
    return cfg


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="zenoh_router", description="A small Zenoh router: a "
                                "Python session in router mode.")
    p.add_argument("--listen", "-l", action="append", default=[], metavar="ENDPOINT",
                   help=f"endpoint to listen on (repeatable; default {DEFAULT_LISTEN}, or the "
                        "config file's)")
    p.add_argument("--config", "-c", metavar="FILE", help="a full Zenoh JSON5 configuration")
    p.add_argument("--multicast-scouting", action="store_true",
                   help="answer multicast scouting (off by default; ignored with --config)")
    args = p.parse_args(argv)

    import zenoh

    try:
        cfg = build_config(args.listen, args.config, args.multicast_scouting)
        session = zenoh.open(cfg)
    except (zenoh.ZError, OSError, ValueError) as exc:
        print(f"zenoh_router: cannot start: {exc}", file=sys.stderr)
        return 1
    stop = threading.Event()
    Stopper(stop).install()
    endpoints = json.loads(cfg.get_json("listen/endpoints"))
    print(f"ready {' '.join(endpoints) if isinstance(endpoints, list) else endpoints} "
          f"zid {session.zid()}", flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
