"""Count the configuration keys declared more than once.

A key is *declared* where its default, type or flag is written down: the schema (a
``CONFIG = Schema(key=Key(...))`` entry, or a field of an options dataclass), a backend's or
source's constructor keyword with a default, and a flag that sets it written out by hand (a
``flags.py`` module's or a class's ``cli_options``, or ``gateway/commands/cli.py``'s flag
tables).  Derived declarations (a schema, a flag or a document computed from the one
declaration) do not count.

Runs against whichever checkout's ``gateway`` it imports, so the same script gives the before
and after figures::

    .venv/bin/python tools/count_option_declarations.py                 # this checkout
    cd ../wt-before && .venv/bin/python ../wt-options/tools/count_option_declarations.py

Prints one line per key declared more than once (``-v``: every key), then the totals.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import re
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path.cwd()))

from gateway import config, registry

FLAGS_GROUPS = ("aurora_gateway.backend_flags", "aurora_gateway.backend_options")


def _source(obj: Any) -> str:
    try:
        return inspect.getsource(obj)
    except (OSError, TypeError):
        return ""


def _fields_declaring(cls: Any, key: str) -> int:
    """How many classes of an options dataclass's MRO annotate ``key`` (1 = declared once)."""
    opts = getattr(cls, "OPTIONS", None)
    if opts is None or not dataclasses.is_dataclass(opts):
        return 1  # a hand-written CONFIG schema: one declaration
    return sum(1 for c in opts.__mro__ if key in inspect.get_annotations(c))


def _init_defaults(cls: Any) -> set[str]:
    """The constructor's keyword parameters that have a default."""
    try:
        sig = inspect.signature(cls.__init__)
    except (TypeError, ValueError):
        return set()
    return {p.name for p in sig.parameters.values()
            if p.default is not inspect.Parameter.empty and p.name not in ("name", "options")}


def _flags_text(name: str) -> str:
    """The hand-written source that turns backend ``name``'s flags into options."""
    for group in FLAGS_GROUPS:
        if name in registry.names(group):
            obj = registry.load(group, name)
            if inspect.ismodule(obj):
                return _source(obj)
            return _source(getattr(obj, "cli_options", None)) if "cli_options" in vars(obj) \
                else ""
    cls = registry.load(registry.BACKEND_GROUP, name)
    return _source(cls.cli_options) if "cli_options" in vars(cls) else ""


def _sets_key(text: str, key: str) -> bool:
    return bool(re.search(rf"""["']{re.escape(key)}["']\s*[\]:]""", text))


def count() -> list[tuple[str, str, int]]:
    """(table, key, declarations) for every key of every registered source and backend and
    of the gateway's own table."""
    try:
        from gateway.commands import cli
    except ImportError:  # before the floor plan: gateway/cli.py
        from gateway import cli  # type: ignore[no-redef]

    cli_text = _source(cli)
    rows: list[tuple[str, str, int]] = []
    for key in config.GATEWAY_SCHEMA.keys:
        by_hand = re.search(rf"""\(\s*"\w+",\s*"--[\w-]+",\s*"{key}"\s*\)""", cli_text)
        rows.append(("[gateway]", key, 1 + bool(by_hand)))
    for group, label in ((registry.SOURCE_GROUP, "sources"), (registry.BACKEND_GROUP, "backends")):
        for name in registry.names(group):
            cls = registry.load(group, name)
            schema = config.schema_of(cls) if hasattr(config, "schema_of") else cls.CONFIG
            defaults = _init_defaults(cls)
            flags = _flags_text(name) if group == registry.BACKEND_GROUP else ""
            for key in schema.keys:
                n = _fields_declaring(cls, key) + (key in defaults) + _sets_key(flags, key)
                if group == registry.SOURCE_GROUP and re.search(
                        rf"""\(\s*"\w+",\s*"--[\w-]+",\s*"{name}",\s*"{key}"\s*\)""", cli_text):
                    n += 1
                rows.append((f"{label}.{name}", key, n))
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    p.add_argument("-v", "--verbose", action="store_true", help="print every key")
    args = p.parse_args(argv)
    rows = count()
    twice = [r for r in rows if r[2] > 1]
    for table, key, n in rows if args.verbose else twice:
        print(f"{table}.{key}: declared {n} times")
    print(f"{len(twice)} of {len(rows)} configuration keys declared more than once "
          f"({sum(1 for r in rows if r[2] > 2)} three times or more)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
