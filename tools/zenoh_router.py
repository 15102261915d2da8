"""A small Zenoh router for tests and fleets (zenohd is not installable everywhere).

    python tools/zenoh_router.py                               # tcp/127.0.0.1:7447
    python tools/zenoh_router.py --listen tcp/0.0.0.0:7447     # reachable from the network
    python tools/zenoh_router.py --config examples/zenoh-router-acl.json5

The same as ``python -m backends.zenoh.router``; see that module.
"""

from __future__ import annotations

import sys
from pathlib import Path

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout
    from backends.zenoh.router import main

    sys.exit(main())
