"""The ROS 2 backend's options, declared once (see :mod:`gateway.options`): its
``[backends.ros2]`` schema (no key needed), the ``--ros2`` flag that enables it and its
documentation.  A light module (the ``aurora_gateway.backend_options`` entry point): it imports
neither the backend nor ``cyclonedds``."""

from __future__ import annotations

import argparse
import os
import re
from dataclasses import dataclass
from typing import Any, ClassVar

from gateway.options import ConfigError, Flag, Options, option

#: The DDS domain ids ROS 2 can use (the RTPS port mapping's limit with ROS's defaults).
MAX_DOMAIN_ID = 232
DOMAIN_ENV = "ROS_DOMAIN_ID"
FLAG = "--ros2"
DEFAULT_NODE = "aurora_gateway"
_NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")


def check_node_name(name: str) -> None:
    """A ROS 2 node name (letters, digits, '_'; not a digit first; at most 255), or "" """
    if name and (not _NODE_NAME.match(name) or len(name) > 255):
        raise ValueError(f"{name!r} is not a ROS 2 node name: letters, digits and '_', not "
                         "starting with a digit")


def domain_from_env(environ: Any = os.environ) -> int:
    """``ROS_DOMAIN_ID`` as ROS 2 reads it: unset or empty → 0; else an integer 0..232
    (:class:`ConfigError` naming the variable otherwise)."""
    text = (environ.get(DOMAIN_ENV) or "").strip()
    if not text:
        return 0
    try:
        value = int(text, 10)
    except ValueError:
        value = -1
    if not 0 <= value <= MAX_DOMAIN_ID:
        raise ConfigError(f"{DOMAIN_ENV}={text!r}: the ROS 2 domain must be an integer from 0 "
                          f"to {MAX_DOMAIN_ID}")
    return value


@dataclass(frozen=True, kw_only=True)
class Ros2Options(Options):
    """``[backends.ros2]``: the flight on ROS 2 topics over DDS (Cyclone DDS), no bridge."""

    TITLE: ClassVar[str] = "ROS 2 backend"
    domain_id: int | None = option(
        None, f"DDS domain of the ROS 2 graph; unset: the {DOMAIN_ENV} environment variable, "
        "else 0 (the DDS configuration itself, e.g. the network interface: CYCLONEDDS_URI)",
        minimum=0, maximum=MAX_DOMAIN_ID,
        flag=Flag("--ros2-domain", "ROS 2 backend: publish on this DDS domain instead of "
                  f"{DOMAIN_ENV}'s (enables the backend)", metavar="ID"))
    queue_depth: int = option(1024, "updates waiting for the backend's DDS writer thread "
                              "before new ones are dropped", minimum=1)
    node: str = option(DEFAULT_NODE, "the ROS 2 node its topics belong to (ros2 node list, "
                       "rqt_graph), announced on ros_discovery_info as Iron and later do; \"\": "
                       "none (a graph of Humble nodes, whose announcement differs)",
                       validator=check_node_name)

    def check(self) -> None:
        """With no ``domain_id``, ``ROS_DOMAIN_ID`` is read now: a bad one is the
        configuration's error (one line, exit 2), not the backend's at start."""
        if self.domain_id is None:
            domain_from_env()

    def domain(self) -> int:
        """The domain to join: ``domain_id``, else ``ROS_DOMAIN_ID``'s, else 0."""
        return self.domain_id if self.domain_id is not None else domain_from_env()

    # ``--ros2`` takes no value (the backend needs no key): added beside the key's flags.
    @classmethod
    def add_cli_arguments(cls, parser: Any, seen: set[str] | None = None,
                          sources: bool = False) -> None:
        if sources:
            return
        super().add_cli_arguments(parser, seen, sources)
        if seen is not None:
            if FLAG in seen:
                return
            seen.add(FLAG)
        parser.add_argument(FLAG, dest="ros2", action="store_true", default=None,
                            help="publish the flight on ROS 2 topics over DDS (Cyclone DDS): "
                                 "/aurora/<vehicle>/{state,armed,altitude,imu,fix,battery}, "
                                 f"/tf, /diagnostics, on {DOMAIN_ENV} (default 0); off by "
                                 "default; needs the 'ros2' extra")

    @classmethod
    def flag_values(cls, args: argparse.Namespace, sets: Any = str,
                    sources: bool = False) -> tuple[dict[str, Any], bool]:
        opts, enabled = super().flag_values(args, sets, sources)
        if getattr(args, "ros2", None) and not sources:
            enabled = True
        return opts, enabled
