"""The Zenoh backend's and source's options, declared once (see :mod:`gateway.options`):
their schemas, the ``--zenoh-…`` flags (the backend's) and their documentation.  The session
keys both share are declared once, in :class:`ZenohSessionOptions`.  A light module (the
``aurora_gateway.backend_options`` / ``source_options`` entry points): it imports neither the
backend nor Zenoh."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from backends.zenoh.keys import (
    DEFAULT_ENDPOINT,
    DEFAULT_PREFIX,
    DEFAULT_VEHICLE,
    check_chunk,
    check_prefix,
)
from gateway.options import Flag, Options, option

#: Zenoh's session modes
MODES = ("peer", "client", "router")
#: Zenoh's priorities, highest first
PRIORITIES = ("real_time", "interactive_high", "interactive_low", "data_high", "data",
              "data_low", "background")
#: The payloads of sm_update/status (``backends.zenoh.encoding.ENCODINGS``)
ENCODINGS = ("json", "packed")
#: What a source subscribes to: the raw wire frames or the JSON documents
KEY_SETS = ("raw", "json")


def _check_vehicle(value: str) -> None:
    check_chunk(value, "vehicle")


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
        flag=Flag("--zenoh-connect", "connect to this Zenoh router or peer, e.g. "
                  "tcp/10.0.0.5:7447 (repeatable; then nothing listens unless --zenoh-listen)",
                  metavar="ENDPOINT", sources=False))
    listen: list[str] | str | None = option(
        None, f"endpoints to listen on (default {DEFAULT_ENDPOINT}, or none when connect is "
        "given)",
        flag=Flag("--zenoh-listen", "listen on this endpoint (repeatable; default "
                  f"{DEFAULT_ENDPOINT})", metavar="ENDPOINT", sources=False))
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
    prefix: str = option(DEFAULT_PREFIX, "first chunk(s) of every key",
                         validator=check_prefix,
                         flag=Flag("--zenoh-prefix", metavar="PREFIX"))
    vehicle: str = option(DEFAULT_VEHICLE, "this vehicle's key chunk", validator=_check_vehicle,
                          flag=Flag("--zenoh-vehicle", "vehicle key chunk (default "
                                    f"{DEFAULT_VEHICLE})", metavar="ID"))
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
                              "dropped", minimum=1, maximum=1_000_000)
    liveliness: bool = option(True, "declare a liveliness token for this gateway")
    queryable: bool = option(True, "answer get() with the latest value of each key")
    stats_interval_s: float = option(1.0, "seconds between publications of this gateway's "
                                     "counters on gateway_stats (for a monitor); 0 = none",
                                     minimum=0)


@dataclass(frozen=True, kw_only=True)
class ZenohSourceOptions(ZenohSessionOptions):
    """``[[sources]] type = "zenoh"``: another gateway's frames over Zenoh."""

    url: str = option("", "zenoh:[VEHICLE@][ENDPOINT,...] (sets vehicle and connect)")
    prefix: str = option(DEFAULT_PREFIX, "key prefix of the publishing gateways")
    vehicle: str = option("*", "vehicle to follow; '*' = every vehicle (their messages are "
                          "merged: use one source per vehicle to keep them apart)")
    keys: str = option("raw", "subscribe to the raw wire frames or to the JSON documents",
                       choices=KEY_SETS)
    queue_depth: int = option(1024, "samples waiting for the source's thread before new ones "
                              "are dropped", minimum=1, maximum=1_000_000)
