"""``aurora-gateway check-config FILE``: validate a configuration file and print it resolved.

The file goes through :func:`gateway.config.load`, the code ``run --config`` uses, so it
passes here exactly when ``run`` would accept its keys and values.  What needs the outside
world (a port, a recording, a key file) is left to ``run``: nothing is opened or built here.
The checks between keys (MAVLink: a key file *or* a passphrase) are made, by the options
declaration (:mod:`gateway.options`).  An enabled backend whose extra is not installed (a
base install enabling Foxglove) is an error naming the extra, as ``run`` says; a disabled one
is checked by its options declaration alone, its class not imported (:func:`config.parse`).

The resolved configuration is every source and every enabled backend with all its options,
defaults filled in, as TOML that loads back to the same configuration (``--json``: one JSON
document).  An option whose default is "not set" has no TOML form and is printed as a
comment.  A backend with ``enabled = false`` was checked too; it is named in a comment.  A
secret (a passphrase, a password: an option declared ``secret``) is never printed: a comment
says it is set.

Exit status: 0 valid; 2 invalid, unreadable or missing (one line on stderr naming the key,
or the file and why it cannot be read) — the status ``run`` exits with for the same file.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from typing import Any

from gateway import config, exits
from gateway.config import ConfigError, GatewayConfig

PROG = "aurora-gateway check-config"
EXIT_OK, EXIT_INVALID = exits.OK, exits.USAGE

_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


class _Secret:
    """A secret option's value, in place of it: printed as "set, not shown"."""

    def __repr__(self) -> str:
        return "SECRET"


SECRET: Any = _Secret()
SECRET_TEXT = "set, not shown (a secret)"


def toml_string(text: str) -> str:
    """``text`` as a TOML basic string (quotes, backslashes and control characters
    escaped)."""
    out = []
    for ch in text:
        if ch in '"\\':
            out.append("\\" + ch)
        elif ch == "\t":
            out.append(ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def toml_key(key: str) -> str:
    """A table or key name: bare when TOML allows it, else quoted."""
    return key if _BARE_KEY.fullmatch(key) else toml_string(key)


def toml_value(value: Any) -> str:
    """A configuration value in TOML syntax (str, bool, int, finite float, list, table)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{value!r} has no TOML form a configuration key accepts")
        return repr(value)
    if isinstance(value, str):
        return toml_string(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{toml_key(k)} = {toml_value(v)}"
                               for k, v in value.items()) + "}"
    raise ValueError(f"{value!r} has no TOML form")


def _table_lines(options: dict[str, Any]) -> list[str]:
    lines = []
    for key, value in options.items():
        if value is SECRET:
            lines.append(f"# {toml_key(key)}: {SECRET_TEXT}")
        elif value is None:
            lines.append(f"# {toml_key(key)}: not set (the default)")
        else:
            lines.append(f"{toml_key(key)} = {toml_value(value)}")
    return lines


def resolved_dict(cfg: GatewayConfig) -> dict[str, Any]:
    """The resolved configuration as plain data, shaped like the file: ``gateway``,
    ``sources`` (a list, each with its ``type``, ``name`` and ``vehicle``) and ``backends``
    (by name, each with its ``type``)."""
    return {
        "gateway": dict(cfg.gateway),
        "sources": [{"type": p.type, "name": p.name, "vehicle": p.vehicle,
                     **({"mavlink_sysid": p.mavlink_sysid} if p.mavlink_sysid else {}),
                     **_shown(p)} for p in cfg.sources],
        "backends": {p.name: {"type": p.type, **_shown(p)} for p in cfg.backends},
    }


def _shown(part: config.Part) -> dict[str, Any]:
    """A part's options, each set secret replaced by :data:`SECRET`."""
    keys = config.schema_of(part.cls).keys if part.cls is not None else {}
    return {k: SECRET if v and k in keys and keys[k].secret else v
            for k, v in part.options.items()}


def resolved_toml(cfg: GatewayConfig, origin: str, disabled: list[str]) -> str:
    """The resolved configuration as TOML text that loads back to the same configuration;
    ``disabled`` backends are named in a comment."""
    data = resolved_dict(cfg)
    lines = [f"# {origin}: valid; every key resolved, defaults filled in", "",
             "[gateway]", *_table_lines(data["gateway"])]
    for source in data["sources"]:
        lines += ["", "[[sources]]", *_table_lines(source)]
    for name, table in data["backends"].items():
        lines += ["", f"[backends.{toml_key(name)}]", *_table_lines(table)]
    if not data["backends"]:
        lines += ["", "# no backend enabled"]
    for name in disabled:
        lines += ["", f"# [backends.{toml_key(name)}] enabled = false: checked, not run"]
    return "\n".join(lines) + "\n"


def check(path: str | None) -> tuple[GatewayConfig, list[str]]:
    """Load and validate ``path`` (None: the embedded default) as ``run`` does; the
    configuration and the names of the backends it checked but leaves disabled.  Raises
    :class:`ConfigError`."""
    asked: list[str] = []

    def keep(name: str) -> bool:
        asked.append(name)
        return True

    if path is None:
        return config.embedded_default(), []
    cfg = config.load(path, keep)
    config.check_runnable(cfg)
    running = {p.name for p in cfg.backends}
    return cfg, [n for n in dict.fromkeys(asked) if n not in running]


def add_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``check-config`` to the ``aurora-gateway`` subcommands (entry point group
    ``aurora_gateway.commands``)."""
    p = subparsers.add_parser(
        "check-config", help="validate a configuration file and print it resolved",
        description="Validate a configuration file as `run --config` does and print every "
                    "source and backend with all its options, defaults filled in (TOML that "
                    "loads back to the same configuration). A bad file: one line on stderr "
                    "naming the key, exit status 2; so is a file that cannot be read.")
    p.add_argument("file", nargs="?", default=None, metavar="FILE",
                   help="TOML configuration (none: the embedded default run uses with no file)")
    p.add_argument("--json", action="store_true", help="print one JSON document instead")
    p.set_defaults(handler=main_handler)
    return p


def main_handler(args: argparse.Namespace) -> int:
    """Run ``check-config``; the exit status."""
    path: str | None = args.file
    try:
        cfg, disabled = check(path)
    except ConfigError as exc:
        text = str(exc)
        # config.load names the file in read and TOML errors; a key's error names the key only
        where = "" if path is None or text.startswith(f"{path}:") else f"{path}: "
        print(f"{PROG}: {where}{text}", file=sys.stderr)
        return EXIT_INVALID
    if args.json:
        print(json.dumps({**resolved_dict(cfg), "disabled_backends": disabled}, indent=2,
                         ensure_ascii=False, default=lambda _: SECRET_TEXT))
    else:
        sys.stdout.write(resolved_toml(cfg, path or "embedded default", disabled))
    return EXIT_OK
