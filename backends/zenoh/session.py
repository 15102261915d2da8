"""Session options (the same keys for the backend, the source and ``listen``) → zenoh.Config.

Defaults keep everything on the machine: peer mode, listening on loopback only
(``tcp/127.0.0.1:7450``), multicast scouting off.  Given ``connect`` endpoints and no
``listen``, the session only connects (it joins a network rather than offering one); a client
never listens.  ``config_file`` loads a full Zenoh JSON5 configuration as the base, and only
the keys given explicitly here override it.

When the default loopback port is already taken (a second gateway on the same machine), the
session listens on a random loopback port instead and connects to the first: both are then
reachable through the default endpoint (Zenoh's gossip tells the others about the newcomer).
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Any

from backends.zenoh.keys import DEFAULT_ENDPOINT
from backends.zenoh.options import MODES, ZenohSessionOptions, check_locator, check_locators
from gateway.options import ConfigError

log = logging.getLogger(__name__)

RETRY_INIT_MS = 100
#: The locator checks live in the light options module (the keys and flags use them); the
#: session re-checks what it is given with them.
__all__ = ["SessionOptions", "check_endpoints", "check_locator", "check_locators", "zerror_text"]

_RS_LOCATION = re.compile(r"\s+at\s+/\S+\.rs:\d+\.?")


def zerror_text(exc: BaseException) -> str:
    """A Zenoh error without the Rust source locations it carries."""
    return _RS_LOCATION.sub("", str(exc)).strip()


def check_endpoints(value: Any, key: str) -> list[str]:
    """A list of ``<protocol>/<address>`` strings (one string is a list of one); ConfigError
    naming the item otherwise."""
    if isinstance(value, str):
        value = [value]
    if not isinstance(value, list):
        raise ConfigError(f"{key}: expected a list of endpoints, got {value!r}")
    out = []
    for i, ep in enumerate(value):
        if not isinstance(ep, str):
            raise ConfigError(f"{key}[{i}]: expected a string, got {ep!r}")
        try:
            check_locator(ep)
        except ValueError as exc:
            raise ConfigError(f"{key}[{i}]: {exc}") from None
        out.append(ep)
    return out


class SessionOptions:
    """Validated session options; :meth:`config` builds the zenoh.Config."""

    def __init__(self, options: ZenohSessionOptions | None = None,
                 default_listen: list[str] | None = None, **keys: Any) -> None:
        """``options`` (or the session keys as keywords: ``SessionOptions(mode="client",
        connect=[…])``, validated by :class:`ZenohSessionOptions`)."""
        if options is None:
            options = ZenohSessionOptions(**keys)
        elif keys:
            options = options.replace(**keys)
        mode, connect, listen = options.mode, options.connect, options.listen
        tls_certificate, tls_root_ca = options.tls_certificate, options.tls_root_ca
        user, password = options.user, options.password
        tls_mtls, config_file = options.tls_mtls, options.config_file
        if mode is not None and mode not in MODES:
            raise ConfigError(f"mode: expected one of {', '.join(MODES)}, got {mode!r}")
        self.mode = mode
        self.connect = check_endpoints(connect, "connect") if connect is not None else None
        self.listen = check_endpoints(listen, "listen") if listen is not None else None
        self.multicast_scouting = options.multicast_scouting
        self.tls_root_ca = tls_root_ca
        self.tls_certificate = tls_certificate
        self.tls_private_key = options.tls_private_key
        self.tls_mtls = tls_mtls
        self.user = user
        self.password = password
        self.config_file = config_file
        self.reconnect_max_s = options.reconnect_max_s
        self.default_listen = ([DEFAULT_ENDPOINT] if default_listen is None
                               else list(default_listen))
        if bool(user) != bool(password):
            raise ConfigError("user/password: give both or neither")
        if bool(tls_certificate) != bool(options.tls_private_key):
            raise ConfigError("tls_certificate/tls_private_key: give both or neither")
        if tls_mtls and not (tls_certificate and tls_root_ca):
            raise ConfigError("tls_mtls: needs tls_root_ca, tls_certificate and "
                              "tls_private_key")
        for key in ("tls_root_ca", "tls_certificate", "tls_private_key", "config_file"):
            path = getattr(self, key)
            if path and not Path(path).is_file():
                raise ConfigError(f"{key}: no such file: {path}")
        if self.effective_mode == "client" and not self.connect and not config_file:
            raise ConfigError("connect: client mode needs at least one endpoint (a router)")
        self.config()  # a bad config file or value is found now, before anything starts

    @classmethod
    def from_options(cls, options: ZenohSessionOptions, **extra: Any) -> SessionOptions:
        """The session of a backend's or source's options (their session keys)."""
        return cls(options, **extra)

    @property
    def effective_mode(self) -> str:
        return self.mode or "peer"

    @property
    def uses_default_listen(self) -> bool:
        """True when the session listens where it does only because nothing was configured."""
        return (self.listen is None and not self.connect and not self.config_file
                and self.effective_mode != "client")

    def listen_endpoints(self) -> list[str]:
        if self.listen is not None:
            return self.listen
        if self.effective_mode == "client" or self.connect:
            return []
        return list(self.default_listen)

    def describe(self) -> str:
        """One line for logs: mode, listen and connect endpoints."""
        parts = [self.effective_mode]
        if self.config_file:
            parts.append(f"config {self.config_file}")
        lst = self.listen_endpoints() if not self.config_file or self.listen is not None else []
        if lst:
            parts.append("listen " + ",".join(lst))
        if self.connect:
            parts.append("connect " + ",".join(self.connect))
        return " ".join(parts)

    def config(self, listen: list[str] | None = None,
               connect: list[str] | None = None) -> Any:
        """The zenoh.Config; ``listen``/``connect`` override the endpoints (the fallback)."""
        import zenoh

        def put(key: str, value: Any) -> None:
            try:
                cfg.insert_json5(key, json.dumps(value))
            except zenoh.ZError as exc:
                raise ConfigError(f"{key.replace('/', '.')}: {zerror_text(exc)}") from None

        if self.config_file:
            try:
                cfg = zenoh.Config.from_file(self.config_file)
            except zenoh.ZError as exc:
                raise ConfigError(f"config_file: {self.config_file}: "
                                  f"{zerror_text(exc)}") from None
        else:
            cfg = zenoh.Config()
        base = not self.config_file
        if self.mode is not None or base:
            put("mode", self.effective_mode)
        if self.multicast_scouting is not None or base:
            put("scouting/multicast/enabled", bool(self.multicast_scouting))
        if listen is None and (self.listen is not None or base):
            listen = self.listen_endpoints()
        if listen is not None and self.effective_mode != "client":
            put("listen/endpoints", listen)
        if connect is None and self.connect is not None:
            connect = self.connect
        if connect is not None:
            put("connect/endpoints", connect)
        default_s = ZenohSessionOptions.schema().keys["reconnect_max_s"].default
        if base or self.reconnect_max_s != default_s:
            retry = {"period_init_ms": RETRY_INIT_MS,
                     "period_max_ms": max(RETRY_INIT_MS, round(self.reconnect_max_s * 1000)),
                     "period_increase_factor": 2}
            put("connect/retry", retry)
            put("listen/retry", retry)
        if self.tls_root_ca:
            put("transport/link/tls/root_ca_certificate", self.tls_root_ca)
        if self.tls_certificate:
            put("transport/link/tls/listen_certificate", self.tls_certificate)
            put("transport/link/tls/listen_private_key", self.tls_private_key)
            put("transport/link/tls/connect_certificate", self.tls_certificate)
            put("transport/link/tls/connect_private_key", self.tls_private_key)
        if self.tls_mtls:
            put("transport/link/tls/enable_mtls", True)
        if self.user:
            put("transport/auth/usrpwd/user", self.user)
            put("transport/auth/usrpwd/password", self.password)
        return cfg

    def open(self) -> Any:
        """Open the session (blocking: call it from a worker).  Raises zenoh.ZError when it
        cannot (a client whose router is down); the caller retries with backoff."""
        import zenoh

        try:
            return zenoh.open(self.config())
        except zenoh.ZError as exc:
            if not (self.uses_default_listen and "in use" in str(exc)):
                raise
        # Somebody (normally another gateway) holds the default port: join it.
        listen = [_any_port(ep) for ep in self.default_listen]
        log.info("zenoh: %s is taken (another gateway on this machine?); listening on %s "
                 "and joining it", ", ".join(self.default_listen), ", ".join(listen))
        return zenoh.open(self.config(listen=listen, connect=list(self.default_listen)))


def _any_port(endpoint: str) -> str:
    """The same endpoint on port 0 (any free port)."""
    head, sep, _ = endpoint.rpartition(":")
    return f"{head}:0" if sep else endpoint
