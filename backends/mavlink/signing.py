"""MAVLink 2 message signing: keys, outgoing signing set-up, and incoming verification.

Outgoing frames are signed by pymavlink (``MAVLink.signing``: ``secret_key``, ``link_id``,
``timestamp``, ``sign_outgoing``), one signing stream per link.

Incoming frames the gateway consumes are checked by :class:`SignatureVerifier`, shared by all
links of a router (so a packet captured on one link and replayed on another is still a
replay).  It follows the MAVLink signing rules, in the safe order: the signature is checked
**before** the timestamp is recorded, so a forged packet cannot push a stream's timestamp
forward and lock its real sender out (pymavlink's ``check_signature`` records first).

Keys: 32 bytes from a file (raw, or 64 hex digits), or SHA-256 of a passphrase — how MAVProxy
(``signing setup``) and QGroundControl derive the key from what the user types.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from backends.mavlink.frames import SIGNATURE_LEN, Frame
from gateway.counters import Counters

KEY_LEN = 32
#: 1 January 2015 00:00:00 UTC, the signing epoch.
EPOCH_2015 = 1420070400
#: A new stream's first timestamp may be at most this far behind ours (one minute in 10 µs).
NEW_STREAM_WINDOW = 60 * 100_000
#: Messages accepted unsigned even when signing is required (the radio injects them).
UNSIGNED_ALLOWED: frozenset[int] = frozenset({109})  # RADIO_STATUS


class SigningError(ValueError):
    """A key cannot be loaded."""


def key_from_passphrase(passphrase: str) -> bytes:
    """The 32-byte key MAVProxy and QGroundControl derive: SHA-256 of the UTF-8 passphrase."""
    if not passphrase:
        raise SigningError("the signing passphrase is empty")
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def key_from_file(path: str | Path) -> bytes:
    """A key file: exactly 32 raw bytes, or 64 hexadecimal digits (whitespace ignored)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise SigningError(f"cannot read signing key {path}: {exc.strerror or exc}") from None
    if len(data) == KEY_LEN:
        return data
    text = data.strip()
    if len(text) == 2 * KEY_LEN:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SigningError(f"signing key {path}: expected 32 raw bytes or 64 hex digits, "
                       f"got {len(data)} bytes")


def now_timestamp(clock: float | None = None) -> int:
    """Signing timestamp for now: 10 µs units since 2015-01-01 UTC."""
    t = time.time() if clock is None else clock
    return max(0, int((t - EPOCH_2015) * 100_000))


def setup_outgoing(mav_obj: Any, key: bytes, link_id: int) -> None:
    """Make a pymavlink ``MAVLink`` object sign everything it packs on stream ``link_id``."""
    s = mav_obj.signing
    s.secret_key = key
    s.link_id = link_id & 0xFF
    s.timestamp = now_timestamp()
    s.sign_outgoing = True


def refresh_timestamp(mav_obj: Any) -> None:
    """Keep a signing stream's timestamp no older than the clock (pymavlink only counts up
    by one per packet)."""
    s = mav_obj.signing
    ts = now_timestamp()
    if ts > s.timestamp:
        s.timestamp = ts


class Verdict(enum.Enum):
    OK = "ok"
    UNSIGNED_ALLOWED = "unsigned-allowed"
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad-signature"
    REPLAY = "replay"
    STALE = "stale"

    @property
    def accepted(self) -> bool:
        return self in (Verdict.OK, Verdict.UNSIGNED_ALLOWED)


@dataclass
class VerifierStats(Counters):
    good: int = 0
    unsigned_allowed: int = 0
    rejected_unsigned: int = 0
    rejected_bad_signature: int = 0
    rejected_replay: int = 0
    rejected_stale: int = 0



class SignatureVerifier:
    """Accepts a frame when its signature matches ``key`` and its timestamp is newer than the
    last one of its (link id, system, component) stream — or, for a stream not seen before,
    at most a minute behind the local clock."""

    def __init__(self, key: bytes, unsigned_allowed: frozenset[int] = UNSIGNED_ALLOWED,
                 clock: Any = time.time) -> None:
        if len(key) != KEY_LEN:
            raise SigningError(f"a signing key has {KEY_LEN} bytes, not {len(key)}")
        self.key = key
        self.unsigned_allowed = unsigned_allowed
        self.stats = VerifierStats()
        self._clock = clock
        self._streams: dict[tuple[int, int, int], int] = {}

    def check(self, frame: Frame) -> Verdict:
        st = self.stats
        raw = frame.raw
        if not frame.signed:
            if frame.msgid in self.unsigned_allowed:
                st.unsigned_allowed += 1
                return Verdict.UNSIGNED_ALLOWED
            st.rejected_unsigned += 1
            return Verdict.UNSIGNED
        if len(raw) < SIGNATURE_LEN + 12:
            st.rejected_bad_signature += 1
            return Verdict.BAD_SIGNATURE
        digest = hashlib.sha256(self.key + raw[:-6]).digest()[:6]
        if not hmac.compare_digest(digest, raw[-6:]):  # constant time: no timing oracle
            st.rejected_bad_signature += 1
            return Verdict.BAD_SIGNATURE
        link_id = raw[-SIGNATURE_LEN]
        ts = int.from_bytes(raw[-12:-6], "little")
        key = (link_id, frame.sysid, frame.compid)
        last = self._streams.get(key)
        if last is not None:
            if ts <= last:
                st.rejected_replay += 1
                return Verdict.REPLAY
        elif ts + NEW_STREAM_WINDOW < now_timestamp(self._clock()):
            st.rejected_stale += 1
            return Verdict.STALE
        self._streams[key] = ts
        st.good += 1
        return Verdict.OK
