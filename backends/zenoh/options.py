"""The Zenoh backend's and source's options, declared once (see :mod:`gateway.options`):
their schemas, the ``--zenoh-…`` flags (the backend's) and their documentation.  The session
keys both share are declared once, in :class:`ZenohSessionOptions`.  A light module (the
``aurora_gateway.backend_options`` / ``source_options`` entry points): it imports neither the
backend nor Zenoh.  The locators of ``connect``/``listen`` (and of their flags) are checked
here, their HOST:PORT by the endpoint grammar (:mod:`gateway.io.endpoints`)."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar

from backends.zenoh.keys import (
    DEFAULT_ENDPOINT,
    DEFAULT_PREFIX,
    check_chunk,
    check_prefix,
)
from gateway.io.endpoints import EndpointError, parse_address
from gateway.options import ConfigError, Flag, Options, Schema, lazy, option
from gateway.vehicles import check_name

#: Zenoh's session modes
MODES = ("peer", "client", "router")
#: Zenoh's priorities, highest first
PRIORITIES = ("real_time", "interactive_high", "interactive_low", "data_high", "data",
              "data_low", "background")
#: The payloads of sm_update/status (``backends.zenoh.encoding.ENCODINGS``)
ENCODINGS = ("json", "packed")
#: What a source subscribes to: the raw wire frames or the JSON documents
KEY_SETS = ("raw", "json")
#: Zenoh's locator protocols, and those whose address is HOST:PORT (IPv6 as [::1]:PORT, as
#: Zenoh writes it)
PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial",
             "vsock")
HOST_PORT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


def check_locator(text: str) -> None:
    """A Zenoh locator, ``<protocol>/<address>`` (Zenoh's own grammar); for tcp, udp, tls,
    quic and ws the address is HOST:PORT as :mod:`gateway.io.endpoints` reads it (IPv6 as
    ``[::1]:7447``).  ValueError saying what is wrong."""
    proto, slash, addr = text.partition("/")
    if not slash or not addr:
        raise ValueError(f"{text!r} is not <protocol>/<address>, e.g. tcp/127.0.0.1:7447")
    if proto not in PROTOCOLS:
        raise ValueError(f"unknown protocol {proto!r}; one of {', '.join(PROTOCOLS)}")
    if proto in HOST_PORT_PROTOCOLS:
        try:  # what follows ? or # is Zenoh's metadata and configuration
            parse_address(re.split(r"[?#]", addr, maxsplit=1)[0], default_host=None)
        except EndpointError as exc:
            raise ValueError(f"{text!r}: {exc}") from None


def check_locators(value: Any) -> None:
    """A ``connect``/``listen`` key's value: every locator checked (:func:`check_locator`)."""
    for item in [value] if isinstance(value, str) else value:
        if not isinstance(item, str):
            raise ValueError(f"{item!r} is not a string")
        check_locator(item)


def _locator(text: str) -> str:
    """``--zenoh-connect``/``--zenoh-listen``: a Zenoh locator, checked as the flag is read."""
    check_locator(text)
    return text


#: Why the backend's ``vehicle`` key (``--zenoh-vehicle``) is refused: keys follow each
#: message's vehicle since issue 22.
VEHICLE_REMOVED = ("removed: keys are <prefix>/<each message's vehicle>/…; name a vehicle "
                   "with vehicle = \"NAME\" in its [[sources]] table or --source NAME=URL")
REMOVED_FLAG = "--zenoh-vehicle"


class _BackendSchema(Schema):
    """The backend's schema, which names what replaced a removed key."""

    def validate(self, table: dict[str, Any], where: str,
                 ignore: Iterable[str] = ()) -> dict[str, Any]:
        if isinstance(table, dict) and "vehicle" in table:
            raise ConfigError(f"{where}.vehicle: {VEHICLE_REMOVED}")
        return super().validate(table, where, ignore)


def _removed_flag(_text: str) -> str:
    raise argparse.ArgumentTypeError(VEHICLE_REMOVED)


def check_follow(value: str) -> str:
    """The vehicle a Zenoh source follows: a vehicle name, or ``*`` (every vehicle)."""
    if value == "*":
        return value
    try:
        return check_name(value)
    except ValueError as exc:
        raise ValueError(f"{exc}, or '*' (every vehicle)") from None


def _check_gateway_id(value: str) -> None:
    if value:
        check_chunk(value, "gateway_id")


@dataclass(frozen=True, kw_only=True)
class ZenohSessionOptions(Options):
    """The Zenoh session's keys, which the backend and the source share (their flags set the
    backend's only)."""

    mode: str | None = option(None, "Zenoh mode", choices=MODES,
                              flag=Flag("--zenoh-mode", "Zenoh mode (default peer)",
                                        metavar="MODE", sources=False))
    connect: list[str] | str | None = option(
        None, "endpoints to connect to, e.g. ['tcp/192.168.1.10:7447']",
        validator=check_locators,
        flag=Flag("--zenoh-connect", "connect to this Zenoh router or peer, e.g. "
                  "tcp/10.0.0.5:7447 (repeatable; then nothing listens unless --zenoh-listen)",
                  metavar="ENDPOINT", sources=False, convert=_locator))
    listen: list[str] | str | None = option(
        None, f"endpoints to listen on (default {DEFAULT_ENDPOINT}, or none when connect is "
        "given)", validator=check_locators,
        flag=Flag("--zenoh-listen", "listen on this endpoint (repeatable; default "
                  f"{DEFAULT_ENDPOINT})", metavar="ENDPOINT", sources=False,
                  convert=_locator))
    multicast_scouting: bool | None = option(None, "find peers and routers by UDP multicast "
                                             "(default off)")
    tls_root_ca: str = option("", "CA certificate (PEM) that signs the peers' certificates")
    tls_certificate: str = option("", "this node's certificate (PEM), to listen on tls/ "
                                  "endpoints or for mutual TLS")
    tls_private_key: str = option("", "this node's private key (PEM)")
    tls_mtls: bool = option(False, "mutual TLS: present tls_certificate when connecting and "
                            "require one from whoever connects")
    user: str = option("", "user name for user/password authentication")
    password: str = option("", "password for user/password authentication", secret=True)
    config_file: str = option("", "a full Zenoh JSON5 configuration file used as the base",
                              flag=Flag("--zenoh-config", "a full Zenoh JSON5 configuration "
                                        "for the session", metavar="FILE", sources=False))
    reconnect_max_s: float = option(1.0, "longest wait between attempts to (re)connect to an "
                                    "endpoint", minimum=0.1, maximum=3600)


@dataclass(frozen=True, kw_only=True)
class ZenohOptions(ZenohSessionOptions):
    """``[backends.zenoh]``: the rocket's frames and documents published over Zenoh."""

    TITLE: ClassVar[str] = "zenoh backend"
    EMBEDDED_DEFAULT: ClassVar[dict[str, Any] | None] = {}
    prefix: str = option(DEFAULT_PREFIX, "first chunk(s) of every key: "
                         "<prefix>/<each message's vehicle>/…",
                         validator=check_prefix,
                         flag=Flag("--zenoh-prefix", metavar="PREFIX"))
    gateway_id: str = option("", "this gateway's id in attachments and its liveliness token "
                             "(default: the gateway's own, <host>-<pid>-<n>)",
                             validator=_check_gateway_id)
    encoding: str = option("json", "payload of sm_update/status", choices=ENCODINGS)
    raw: bool = option(True, "also publish each untouched wire frame on raw/<type>")
    congestion_control: str = option("drop", "when the network cannot keep up: drop "
                                     "(latest data first) or block (never lose in Zenoh)",
                                     choices=("drop", "block"))
    priority: str = option("data", "Zenoh priority of the publications", choices=PRIORITIES)
    queue_depth: int = option(1024, "updates waiting for the worker before new ones are "
                              "dropped (the least, with queue_s)", minimum=1,
                              maximum=1_000_000)
    queue_s: float = option(1.0, "seconds of updates (at the rate they come in) that may wait "
                            "for the worker, at least queue_depth and at most 50000; 0 = "
                            "queue_depth, fixed", minimum=0, maximum=60)
    liveliness: bool = option(True, "declare a liveliness token <prefix>/<vehicle>/gateway/<id> "
                              "per vehicle published")
    queryable: bool = option(True, "answer get() with the latest value of each key, per "
                             "vehicle")
    stats_interval_s: float = option(1.0, "seconds between publications of this gateway's "
                                     "counters on <prefix>/@gateways/<id>/stats (for a "
                                     "monitor); 0 = none", minimum=0)

    @classmethod
    def schema(cls) -> Schema:
        """The declared keys; a removed key (``vehicle``) is refused saying what replaced
        it."""
        cached = cls.__dict__.get("_backend_schema")
        if cached is None:
            cached = _BackendSchema(**super().schema().keys)
            type.__setattr__(cls, "_backend_schema", cached)
        return cached

    @classmethod
    def add_cli_arguments(cls, parser: Any, seen: set[str] | None = None,
                          sources: bool = False) -> None:
        """The flags, and the removed ``--zenoh-vehicle`` (hidden), refused by argparse with
        what replaced it (exit 2)."""
        super().add_cli_arguments(parser, seen, sources)
        if not sources and (seen is None or REMOVED_FLAG not in seen):
            parser.add_argument(REMOVED_FLAG, dest="zenoh_vehicle_removed",
                                type=_removed_flag, help=argparse.SUPPRESS)
            if seen is not None:
                seen.add(REMOVED_FLAG)


@dataclass(frozen=True, kw_only=True)
class ZenohSourceOptions(ZenohSessionOptions):
    """``[[sources]] type = "zenoh"``: another gateway's frames over Zenoh."""

    url: str = option("", "zenoh:[FOLLOW@][ENDPOINT,...] (sets follow and connect)",
                      validator=lazy("backends.zenoh.source:check_url"))
    prefix: str = option(DEFAULT_PREFIX, "key prefix of the publishing gateways")
    follow: str = option("*", "the vehicle to follow (its name in the publishing gateway's "
                         "keys); '*' = every vehicle, each kept apart under its own name",
                         validator=check_follow)
    keys: str = option("raw", "subscribe to the raw wire frames or to the JSON documents",
                       choices=KEY_SETS)
    queue_depth: int = option(1024, "samples waiting for the sources' loop before new ones "
                              "are dropped", minimum=1, maximum=1_000_000)
