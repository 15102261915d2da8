"""The rocket's flight states as the mode map pymavlink tools read (``custom_mode_map.json``).

pymavlink's ``mavutil`` names a HEARTBEAT's ``custom_mode`` from a table keyed by the
HEARTBEAT's ``type`` (MAV_TYPE), extended at import by ``~/.pymavlink/custom_mode_map.json``:
``{"<MAV_TYPE>": {"<custom_mode>": "<name>", …}, …}``.  MAVProxy 1.8.75 (which does not read
AVAILABLE_MODES) and every other ``mavutil`` user show ``Mode(2)`` without an entry, and the
name with one.  The gateway's HEARTBEAT is ``MAV_TYPE_ROCKET`` with ``custom_mode`` = the state
number, so the map is built here from the project's own state tables (``dialects.states``).

A HEARTBEAT does not carry ``sm_type``, so one map serves every state machine: a number that
two known machines name differently is named ``A/B`` (both candidates, never a guess), unless
``sm_type`` selects one machine.  The map is keyed by MAV_TYPE only, so any rocket a tool sees
gets these names.  ``aurora-gateway mavlink-modes`` prints the map, ``--install`` merges it
into the file without touching other vehicle types' entries.  Light: imports no dialect.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from dialects.states import STATE_MACHINES, state_names
from gateway import exits

#: MAV_TYPE_ROCKET (common.xml), the type of the gateway's HEARTBEAT (a test checks it against
#: the dialect; the dialect module is not imported here: it is 1.85 MB).
MAV_TYPE_ROCKET = 9

#: Where pymavlink's mavutil looks for the map (``~`` expanded at use).
MAP_PATH = Path("~") / ".pymavlink" / "custom_mode_map.json"


def rocket_modes(sm_type: int | None = None) -> dict[int, str]:
    """custom_mode (state number) → name: of machine ``sm_type``, or (None) of every known
    machine, a number named differently by two machines getting ``A/B``."""
    machines = sorted(STATE_MACHINES) if sm_type is None else [sm_type]
    names: dict[int, list[str]] = {}
    for machine in machines:
        for number, name in state_names(machine):
            seen = names.setdefault(number, [])
            if name not in seen:
                seen.append(name)
    return {number: "/".join(names[number]) for number in sorted(names)}


def custom_mode_map(sm_type: int | None = None) -> dict[str, dict[str, str]]:
    """The map in ``custom_mode_map.json``'s form (JSON object keys are strings)."""
    return {str(MAV_TYPE_ROCKET): {str(n): name for n, name in rocket_modes(sm_type).items()}}


def merge(existing: dict[str, Any], ours: dict[str, dict[str, str]]) -> dict[str, Any]:
    """``existing`` with our vehicle types' entries replaced and every other entry kept."""
    merged = {key: value for key, value in existing.items()
              if not (key.strip().lstrip("+-").isdigit() and str(int(key)) in ours)}
    merged.update(ours)
    return merged


def install(path: Path | None = None, sm_type: int | None = None) -> Path:
    """Merge the map into ``path`` (default ``~/.pymavlink/custom_mode_map.json``), creating
    it; other entries stay.  Written to a temporary file then renamed, so a reader never sees
    half a file.  Raises ValueError when the existing file is not a JSON object."""
    target = (path or MAP_PATH).expanduser()
    existing: dict[str, Any] = {}
    if target.exists():
        try:
            loaded = json.loads(target.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{target}: not valid JSON ({exc}); fix or remove it") from None
        if not isinstance(loaded, dict):
            raise ValueError(f"{target}: not a JSON object (MAV_TYPE → modes); fix or remove it")
        existing = loaded
    text = json.dumps(merge(existing, custom_mode_map(sm_type)), indent=2)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    tmp.write_text(text + "\n", encoding="utf-8")
    tmp.replace(target)
    return target


# -- the `aurora-gateway mavlink-modes` command ----------------------------------------------

def add_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``mavlink-modes`` to the ``aurora-gateway`` subcommands (entry point group
    ``aurora_gateway.commands``)."""
    p = subparsers.add_parser(
        "mavlink-modes", help="print or install the rocket's mode names for MAVProxy and "
        "other pymavlink tools (custom_mode_map.json)",
        description="Print the mode map pymavlink tools read (MAV_TYPE_ROCKET: state number → "
                    "state name), or merge it into ~/.pymavlink/custom_mode_map.json so "
                    "MAVProxy shows BOOST instead of Mode(2). Other vehicle types' entries in "
                    "the file are kept.")
    p.add_argument("--install", action="store_true",
                   help="merge the map into the file instead of printing it")
    p.add_argument("--file", type=Path, default=None, metavar="PATH",
                   help=f"the file --install writes (default {MAP_PATH})")
    p.add_argument("--sm-type", type=int, default=None, metavar="N",
                   choices=sorted(STATE_MACHINES),
                   help="name the states of this state machine only (default: every known "
                        "machine; a number two machines name differently shows as A/B)")
    p.set_defaults(handler=main_handler)
    return p


def main_handler(args: argparse.Namespace) -> int:
    if not args.install:
        print(json.dumps(custom_mode_map(args.sm_type), indent=2))
        return 0
    if args.file is not None and args.file.expanduser().is_dir():
        print(f"aurora-gateway mavlink-modes: --file: {args.file} is a directory",
              file=sys.stderr)
        return exits.USAGE
    try:
        path = install(args.file, args.sm_type)
    except ValueError as exc:  # the file is there but is not a JSON object: bad input
        print(f"aurora-gateway mavlink-modes: {exc}", file=sys.stderr)
        return exits.USAGE
    except OSError as exc:  # could not be read or written
        print(f"aurora-gateway mavlink-modes: {exc.filename or args.file}: "
              f"{exc.strerror or exc}", file=sys.stderr)
        return exits.FAILED
    print(f"mode names of MAV_TYPE_ROCKET ({MAV_TYPE_ROCKET}) written to {path}; pymavlink "
          "tools started from now on show them")
    return 0
