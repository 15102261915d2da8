"""One endpoint grammar for every backend and source: text → :class:`Endpoint`, or one
:class:`EndpointError` whose text names the mistake and the forms the caller accepts.

==============================  ============================================================
``[HOST:]PORT``                 a bare address, where the caller gives it a kind (the HTTP
                                page and the Foxglove server listen on one)
``tcpin:[HOST:]PORT``           a TCP server; HOST defaults to ``0.0.0.0`` (the caller may
                                say otherwise); port 0: the system picks one
``tcp:[HOST:]PORT``             a TCP client; HOST defaults to ``127.0.0.1``
``udpin:[HOST:]PORT``           a UDP socket bound there (``udp:`` is the same, as in MAVProxy)
``udpout:[HOST:]PORT``          a UDP socket sending there
``serial:DEVICE[,BAUD]``        a serial port (any path) or a pyserial URL, optional baud rate
``/dev/…``, ``COMn``, ``/…``    a serial device without ``serial:`` (optional ``,BAUD``)
``SCHEME://…``                  a pyserial URL, for the schemes pyserial has a handler for
                                (``loop://``, ``socket://HOST:PORT``, ``rfc2217://HOST:PORT``,
                                ``spy://…``, ``hwgrep://…`` …)
==============================  ============================================================

IPv6 is written one way everywhere: in brackets, ``tcpin:[::1]:5760`` (a zone is allowed:
``[fe80::1%eth0]:5760``).  An IPv6 address without brackets is refused, because
``tcpin:::1:5760`` cannot be read one way only.  A HOST made of digits and dots must be an
IPv4 address (``300.1.1.1`` is refused here, not at start); anything else must be a host
name (letters, digits, ``-``, ``_``, dots).  An empty HOST (``tcpin::5760``) is the default.

A key that holds a host alone (``[backends.http] host``, :func:`check_host`) takes an IPv6
address without brackets (no port follows it, so there is nothing to confuse).

Every caller states which kinds it accepts; the same mistake gives the same words whoever
calls, followed by the forms that caller accepts: ``empty endpoint``, ``unclosed '['``,
``expected :PORT after ']'``, ``an IPv6 address needs brackets``, ``invalid IPv6 address``,
``invalid IP address``, ``invalid host name``, ``no host``, ``no port``, ``port 'x' is not a
number``, ``port N is out of range (L to 65535)``, ``unknown kind``, ``K is not allowed
here``, ``no kind given``, ``not an endpoint``, ``no serial device``, ``baud rate 'x' is not a
whole number ≥ 50``, ``no ,BAUD here``, ``unknown URL scheme``, ``S:// needs HOST:PORT``.  Standard
library only (pyserial is imported to list its URL schemes when a URL is checked), so the
``run`` flags can use it without importing a backend.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import ipaddress
import pkgutil
import re
from collections.abc import Callable, Collection, Iterable
from typing import Any, NamedTuple

TCPIN = "tcpin"
TCP = "tcp"
UDPIN = "udpin"
UDPOUT = "udpout"
SERIAL = "serial"
#: Every kind, in the order the accepted forms are listed.
KINDS = (TCPIN, TCP, UDPIN, UDPOUT, SERIAL)
#: What a byte-stream link set serves (UAVTalk's and F´'s endpoints: gateway.io.links).
STREAM_KINDS = (TCPIN, TCP, SERIAL)
NETWORK = frozenset((TCPIN, TCP, UDPIN, UDPOUT))
LISTEN = frozenset((TCPIN, UDPIN))
ALIASES = {"udp": UDPIN}  # MAVProxy's udp: listens

DEFAULT_LISTEN_HOST = "0.0.0.0"
DEFAULT_CONNECT_HOST = "127.0.0.1"
MIN_BAUD = 50

_DIGITS = re.compile(r"[0-9]+")
_DOTTED = re.compile(r"[0-9.]+")
_LABEL = r"[A-Za-z0-9_](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9_])?"
_HOSTNAME = re.compile(rf"{_LABEL}(?:\.{_LABEL})*\.?")
_WORD = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*")
_COM = re.compile(r"COM[0-9]+", re.IGNORECASE)
_HOST_PORT_SCHEMES = ("socket", "rfc2217")


class EndpointError(ValueError):
    """An endpoint that cannot be used: one line, naming the text, the mistake and the
    accepted forms."""


class Endpoint(NamedTuple):
    """A parsed endpoint: ``kind`` is one of :data:`KINDS`; ``host``/``port`` for the network
    kinds, ``device``/``baudrate`` for serial (``baudrate`` 0: none given and no default);
    ``text`` is the endpoint as written (stripped), the name logs and stats use."""

    kind: str
    host: str = ""
    port: int = 0
    device: str = ""
    baudrate: int = 0
    text: str = ""

    @property
    def address(self) -> tuple[str, int]:
        return self.host, self.port


class _Mistake(Exception):
    """Internal: the problem part of an :class:`EndpointError`."""


# -- the forms a caller accepts ------------------------------------------------------------------

def usage(kinds: Collection[str], bare: str | None = None, *, serial_baud: bool = True) -> str:
    """The accepted forms, for messages and help: e.g. ``tcpin:[HOST:]PORT, serial:DEVICE…``."""
    forms = ["[HOST:]PORT"] if bare is not None else []
    forms += [f"{k}:[HOST:]PORT" for k in KINDS if k in NETWORK and k in kinds]
    if SERIAL in kinds:
        baud = "[,BAUD]" if serial_baud else ""
        forms.append(f"[serial:]DEVICE{baud} (/dev/…, COMn or a pyserial URL: loop://, "
                     "socket://HOST:PORT …)")
    if not forms:
        return "nothing (no kind is accepted here)"
    text = ", ".join(forms[:-1]) + (" or " if len(forms) > 1 else "") + forms[-1]
    if bare is not None or NETWORK & set(kinds):
        text += "; IPv6 as [::1]:PORT"
    return text


# -- the pieces ------------------------------------------------------------------------------------

def _port(text: str, lowest: int) -> int:
    if not text:
        raise _Mistake("no port")
    if not _DIGITS.fullmatch(text):
        raise _Mistake(f"port {text!r} is not a number")
    port = int(text) if len(text) <= 6 else 1 << 20
    if not lowest <= port <= 65535:
        raise _Mistake(f"port {text} is out of range ({lowest} to 65535)")
    return port


def _host(text: str) -> str:
    """A host name or an IPv4 address (IPv6 comes bracketed, through :func:`_v6`)."""
    if _DOTTED.fullmatch(text):
        try:
            ipaddress.IPv4Address(text)
        except ValueError:
            raise _Mistake(f"invalid IP address {text!r}") from None
        return text
    if len(text) > 253 or not _HOSTNAME.fullmatch(text):
        raise _Mistake(f"invalid host name {text!r}")
    return text


def _is_v6(text: str) -> bool:
    try:
        ipaddress.IPv6Address(text)
    except ValueError:
        return False
    return True


def _v6(text: str) -> str:
    if not _is_v6(text):
        raise _Mistake(f"invalid IPv6 address {text!r}")
    return text


def _address(text: str, default_host: str | None, lowest: int) -> tuple[str, int]:
    """``[HOST:]PORT`` or ``[V6]:PORT`` → (host, port); ``default_host`` None: HOST needed."""
    if text.startswith("["):
        end = text.find("]")
        if end < 0:
            raise _Mistake("unclosed '['")
        host, rest = _v6(text[1:end]), text[end + 1:]
        if not rest.startswith(":"):
            raise _Mistake("expected :PORT after ']'")
        return host, _port(rest[1:], lowest)
    host, sep, port_text = text.rpartition(":")
    if not sep and default_host is None:
        raise _Mistake("no port")  # HOST alone
    if ":" in host:
        if _is_v6(host) or _is_v6(text):
            raise _Mistake("an IPv6 address needs brackets: [::1]:PORT")
        word = host.partition(":")[0]
        if _WORD.fullmatch(word):
            raise _Mistake(f"unknown kind {word!r}")
        raise _Mistake(f"invalid host name {host!r}")
    if "]" in host:
        raise _Mistake(f"invalid host name {host!r}")
    if not host:
        if default_host is None:
            raise _Mistake("no host")
        host = default_host
    else:
        host = _host(host)
    return host, _port(port_text, lowest)


@functools.cache
def serial_url_schemes() -> tuple[str, ...]:
    """The URL schemes ``serial.serial_for_url`` has a handler module for (sorted)."""
    import serial

    found: set[str] = set()
    for package in serial.protocol_handler_packages:
        try:
            path = importlib.import_module(package).__path__
        except (ImportError, AttributeError):
            continue
        found.update(m.name[len("protocol_"):] for m in pkgutil.iter_modules(path)
                     if m.name.startswith("protocol_"))
    return tuple(sorted(found))


def _serial_url(url: str) -> None:
    scheme, _, rest = url.partition("://")
    scheme = scheme.lower()
    known = serial_url_schemes()
    if scheme not in known:
        raise _Mistake(f"unknown URL scheme {scheme!r} (pyserial knows "
                       f"{', '.join(s + '://' for s in known)})")
    if scheme in _HOST_PORT_SCHEMES:
        netloc = re.split(r"[/?#]", rest, maxsplit=1)[0]
        if not netloc:
            raise _Mistake(f"{scheme}:// needs HOST:PORT")
        _address(netloc, None, 1)


def _serial(text: str, default_baud: int, baud_suffix: bool, *, any_path: bool) -> Endpoint:
    device, sep, baud_text = text.rpartition(",")
    if not sep:
        device, baud_text = text, ""
    device = device.strip()
    if sep and not baud_suffix:
        raise _Mistake("no ,BAUD here: the baud rate has its own key")
    if not device:
        raise _Mistake("no serial device")
    baud = default_baud
    if sep:
        baud_text = baud_text.strip()
        if not _DIGITS.fullmatch(baud_text) or len(baud_text) > 9 or int(baud_text) < MIN_BAUD:
            raise _Mistake(f"baud rate {baud_text!r} is not a whole number ≥ {MIN_BAUD}")
        baud = int(baud_text)
    if "://" in device:
        _serial_url(device)
    elif not any_path and not is_device(device):
        raise _Mistake("not an endpoint")
    return Endpoint(SERIAL, device=device, baudrate=baud, text=text)


def is_device(text: str) -> bool:
    """A serial device path written without ``serial:``: ``/…`` or ``COMn``."""
    return text.startswith("/") or bool(_COM.fullmatch(text))


# -- the parser ------------------------------------------------------------------------------------

def parse_endpoint(text: str, kinds: Collection[str] = KINDS, *, bare: str | None = None,
                   listen_host: str = DEFAULT_LISTEN_HOST,
                   connect_host: str = DEFAULT_CONNECT_HOST, default_baud: int = 0,
                   baud_suffix: bool = True) -> Endpoint:
    """Parse ``text`` as one of ``kinds``; raises :class:`EndpointError`.

    ``bare``: the kind a bare ``[HOST:]PORT`` is (None: a kind must be written);
    ``listen_host``/``connect_host``: the HOST when none is written; ``default_baud``: the
    serial baud rate when none is written; ``baud_suffix`` False refuses ``,BAUD`` (the
    caller has a key for it)."""
    if not isinstance(text, str):
        raise EndpointError(f"{text!r} is not a string; expected "
                            f"{usage(kinds, bare, serial_baud=baud_suffix)}")
    t = text.strip()
    try:
        return _parse(t, kinds, bare, listen_host, connect_host, default_baud, baud_suffix)
    except _Mistake as exc:
        what = repr(t) if t else "empty endpoint"
        problem = "" if not t else f": {exc}"
        raise EndpointError(f"{what}{problem}; expected "
                            f"{usage(kinds, bare, serial_baud=baud_suffix)}") from None


def _parse(t: str, kinds: Collection[str], bare: str | None, listen_host: str,
           connect_host: str, default_baud: int, baud_suffix: bool) -> Endpoint:
    if not t:
        raise _Mistake("empty")
    head, sep, rest = t.partition(":")
    kind = head.lower()
    kind = ALIASES.get(kind, kind)
    if sep and rest.startswith("//"):  # a pyserial URL
        if SERIAL not in kinds:
            raise _Mistake(f"{SERIAL} is not allowed here")
        return _serial(t, default_baud, baud_suffix, any_path=False)
    if sep and kind in KINDS:
        if kind not in kinds:
            raise _Mistake(f"{kind} is not allowed here")
        if kind == SERIAL:
            return _serial(rest, default_baud, baud_suffix, any_path=True)._replace(text=t)
        return _network(kind, rest, t, listen_host, connect_host)
    if is_device(t.partition(",")[0].strip()):
        if SERIAL not in kinds:
            raise _Mistake(f"{SERIAL} is not allowed here")
        return _serial(t, default_baud, baud_suffix, any_path=False)
    if bare is not None:
        return _network(bare, t, t, listen_host, connect_host)
    try:
        _address(t, "", 0)
    except _Mistake:
        if t.startswith("["):
            raise
        if sep and _WORD.fullmatch(head):
            raise _Mistake(f"unknown kind {head!r}") from None
        raise _Mistake("not an endpoint") from None
    if not NETWORK & set(kinds):
        raise _Mistake("not an endpoint")  # an address where only a serial port will do
    raise _Mistake("no kind given")


def _network(kind: str, address: str, text: str, listen_host: str,
             connect_host: str) -> Endpoint:
    listen = kind in LISTEN
    host, port = _address(address, listen_host if listen else connect_host, 0 if listen else 1)
    return Endpoint(kind, host, port, text=text)


def parse_address(text: str, *, default_host: str | None = DEFAULT_CONNECT_HOST,
                  lowest_port: int = 0) -> tuple[str, int]:
    """``[HOST:]PORT`` or ``[V6]:PORT`` alone → (host, port) (Zenoh locators' address part);
    ``default_host`` None: HOST is needed.  Raises :class:`EndpointError`."""
    t = text.strip()
    try:
        if not t:
            raise _Mistake("empty")
        return _address(t, default_host, lowest_port)
    except _Mistake as exc:
        form = "HOST:PORT" if default_host is None else "[HOST:]PORT"
        what = repr(t) if t else "empty address"
        problem = "" if not t else f": {exc}"
        raise EndpointError(f"{what}{problem}; expected {form} "
                            "(IPv6 as [::1]:PORT)") from None


def check_port(value: Any) -> None:
    """A port key's value (0 to 65535; 0: the system picks), refused in the words an endpoint's
    port is.  Raises :class:`EndpointError`."""
    if not isinstance(value, int) or isinstance(value, bool):
        raise EndpointError(f"port {value!r} is not a number")
    try:
        _port(str(value), 0)
    except _Mistake as exc:
        raise EndpointError(str(exc)) from None


def check_host(value: Any) -> None:
    """A host key's value (no port): a host name, an IPv4 address or an IPv6 address, written
    without brackets since no port follows.  Raises :class:`EndpointError`."""
    if not isinstance(value, str):
        raise EndpointError(f"{value!r} is not a string; expected a host name or an IP address")
    t = value.strip()
    try:
        if not t:
            raise _Mistake("empty")
        if t.startswith("["):
            raise _Mistake("an IPv6 address goes without brackets in a host key")
        if ":" in t:
            _v6(t)
        else:
            _host(t)
    except _Mistake as exc:
        what = repr(t) if t else "empty host"
        problem = "" if not t else f": {exc}"
        raise EndpointError(f"{what}{problem}; expected a host name or an IP address") from None


# -- for the configuration and the command line ---------------------------------------------------

def check_serial_port(value: Any) -> None:
    """A serial port key's value (the baud rate has a key of its own): ``[serial:]DEVICE``
    (``/dev/…``, ``COMn``; not checked for existence: it may appear later) or a pyserial URL.
    Raises :class:`EndpointError`."""
    parse_endpoint(value, (SERIAL,), baud_suffix=False)


def validator(kinds: Collection[str] = KINDS, **options: Any) -> Callable[[Any], None]:
    """A config key's validator for one endpoint (``options`` as :func:`parse_endpoint`'s)."""

    def check(value: Any) -> None:
        parse_endpoint(value, kinds, **options)

    return check


def list_validator(kinds: Collection[str] = KINDS, *, minimum: int = 1,
                   **options: Any) -> Callable[[Any], None]:
    """A config key's validator for a list of endpoints, at least ``minimum`` of them."""

    def check(value: Any) -> None:
        if not isinstance(value, list | tuple) or len(value) < minimum:
            count = "one endpoint is" if minimum == 1 else f"{minimum} endpoints are"
            raise EndpointError(f"at least {count} needed; expected "
                                f"{usage(kinds, options.get('bare'))}")
        for item in value:
            parse_endpoint(item, kinds, **options)

    return check


def parse_all(values: Iterable[str], kinds: Collection[str] = KINDS,
              **options: Any) -> list[Endpoint]:
    """Every endpoint of ``values`` parsed (the first bad one raises)."""
    return [parse_endpoint(v, kinds, **options) for v in values]


def text_of(kinds: Collection[str] = KINDS, **options: Any) -> Callable[[str], str]:
    """The endpoint's text (stripped) once the grammar accepts it, else its EndpointError: an
    option's flag ``convert`` (:class:`gateway.options.Flag`), where the key holds the text."""

    def check(text: str) -> str:
        return parse_endpoint(text, kinds, **options).text

    return check


def argument(kinds: Collection[str] = KINDS, **options: Any) -> Callable[[str], Endpoint]:
    """An argparse ``type=`` for one endpoint flag: the flag's error is the endpoint's."""

    def convert(text: str) -> Endpoint:
        try:
            return parse_endpoint(text, kinds, **options)
        except EndpointError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    convert.__name__ = "endpoint"
    return convert
