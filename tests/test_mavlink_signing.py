"""MAVLink 2 signing: outgoing traffic signed, incoming commands accepted only when correctly
signed and fresh; keys from a file or a passphrase as MAVProxy/QGC derive them."""

from __future__ import annotations

import contextlib
import hashlib
import struct
import time
from pathlib import Path
from typing import Any

import pytest
from mavlink_peer import MavPeer, running_backend, upstream_dialect

from backends.mavlink.backend import MavlinkBackend
from backends.mavlink.frames import FramerStats, split_datagram
from backends.mavlink.options import MavlinkOptions
from backends.mavlink.signing import (
    NEW_STREAM_WINDOW,
    SignatureVerifier,
    SigningError,
    Verdict,
    key_from_file,
    key_from_passphrase,
    now_timestamp,
)
from gateway import config
from gateway.app import Gateway
from gateway.config import ConfigError
from gateway.dispatcher import Dispatcher

WAIT = 10.0
PASS = "correct horse battery staple"
KEY = hashlib.sha256(PASS.encode()).digest()
dev = upstream_dialect()
REQ = dev.MAV_CMD_REQUEST_MESSAGE
HB_ID = dev.MAVLINK_MSG_ID_HEARTBEAT


def signed_backend(port: int, **opts: Any) -> contextlib.AbstractContextManager[MavlinkBackend]:
    return running_backend(f"udpout:127.0.0.1:{port}", **opts)


def valid_signature(raw: bytes, key: bytes) -> bool:
    return hashlib.sha256(key + raw[:-6]).digest()[:6] == raw[-6:]


def acks(peer: MavPeer) -> list[Any]:
    return peer.messages("COMMAND_ACK")


def test_signed_commands_are_answered_and_everything_we_send_is_signed() -> None:
    with MavPeer(255, 190, signing_key=KEY, link_id=3) as gcs, \
            signed_backend(gcs.port, signing_passphrase=PASS) as b:
        assert gcs.wait_for("HEARTBEAT", timeout=WAIT)
        gcs.command((1, 1), REQ, HB_ID)
        assert gcs.wait_until(lambda: len(acks(gcs)) == 1, WAIT)
        assert acks(gcs)[0].result == dev.MAV_RESULT_ACCEPTED
        raws = list(gcs.raw_received)
        sig = b.stats()["signing"]
    assert raws
    for raw in raws:
        assert raw[2] & 0x01, "unsigned frame sent"
        assert valid_signature(raw, KEY)
    assert sig["good"] == 1
    # timestamps increase per stream
    stamps = [int.from_bytes(r[-12:-6], "little") for r in raws]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    assert abs(stamps[-1] - now_timestamp()) < 60 * 100_000


def test_unsigned_replayed_and_wrongly_signed_commands_are_rejected_and_counted() -> None:
    with MavPeer(255, 190, signing_key=KEY, link_id=1) as gcs, \
            MavPeer(255, 191) as plain, \
            MavPeer(255, 192, signing_key=hashlib.sha256(b"wrong").digest()) as wrong, \
            signed_backend(gcs.port, signing_passphrase=PASS) as b:
        assert gcs.wait_for("HEARTBEAT", timeout=WAIT)
        # Sent through the ground station's socket (udpout takes datagrams from its
        # destination only): packed by a peer without a key, and by one with another key.
        cmd = dev.MAVLink_command_long_message(1, 1, REQ, 0, HB_ID, 0, 0, 0, 0, 0, 0)
        gcs.send_raw(plain.pack(cmd))  # unsigned
        gcs.send_raw(wrong.pack(cmd))  # signed with another key
        good = gcs.command((1, 1), REQ, HB_ID)  # valid: answered
        gcs.send_raw(good)  # the same bytes again: a replay
        # a forged packet far in the future must not lock the real sender out
        forged = bytearray(gcs.pack(dev.MAVLink_command_long_message(
            1, 1, REQ, 0, HB_ID, 0, 0, 0, 0, 0, 0)))
        forged[-12:-6] = (now_timestamp() + 10**9).to_bytes(6, "little")
        gcs.send_raw(bytes(forged))
        gcs.command((1, 1), REQ, dev.MAVLINK_MSG_ID_AUTOPILOT_VERSION)  # valid again
        assert gcs.wait_for("AUTOPILOT_VERSION", timeout=WAIT)
        sig = b.stats()["signing"]
        rejected = b.stats()["endpoints"][f"udpout:127.0.0.1:{gcs.port}"]["rejected_signing"]
    got = [(a.command, a.result) for a in acks(gcs)]
    assert got == [(REQ, dev.MAV_RESULT_ACCEPTED), (REQ, dev.MAV_RESULT_ACCEPTED)]
    assert plain.messages("COMMAND_ACK") == [] and wrong.messages("COMMAND_ACK") == []
    assert sig["rejected_unsigned"] == 1
    assert sig["rejected_bad_signature"] == 2  # the wrong key, and the forgery
    assert sig["rejected_replay"] == 1
    assert sig["good"] == 2
    assert rejected == 4


def test_routed_traffic_passes_unverified_and_unchanged() -> None:
    """Like mavlink-router, the router forwards signed (and unsigned) frames as they are;
    signing applies to what the gateway itself consumes and sends."""
    other_key = hashlib.sha256(b"the vehicle's own key").digest()
    with MavPeer(255, 190) as gcs:
        b = MavlinkBackend(MavlinkOptions(
            endpoints=["udpin:127.0.0.1:0", f"udpout:127.0.0.1:{gcs.port}"],
                                          signing_passphrase=PASS))
        d = Dispatcher([b])
        assert d.start() == []
        try:
            with MavPeer(7, 1, signing_key=other_key, dest=b.endpoints[0].address) as veh:
                hb = veh.send(dev.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3))
                assert gcs.wait_until(lambda: hb in gcs.raw_received, WAIT)
        finally:
            d.close()
    assert hb[2] & 0x01 and valid_signature(hb, other_key)


# -- the verifier on its own ---------------------------------------------------------------------

def _signed_frame(key: bytes, ts: int, link_id: int = 0, msg: Any = None) -> Any:
    m = dev.MAVLink(None, 255, 190)
    m.signing.secret_key = key
    m.signing.link_id = link_id
    m.signing.timestamp = ts
    m.signing.sign_outgoing = True
    raw = (msg or dev.MAVLink_command_long_message(1, 1, REQ, 0, 0, 0, 0, 0, 0, 0, 0)).pack(m)
    (f,) = split_datagram(raw, FramerStats())
    return f


def test_verifier_rules() -> None:
    clock = time.time()
    v = SignatureVerifier(KEY, clock=lambda: clock)
    now = now_timestamp(clock)
    assert v.check(_signed_frame(KEY, now)) is Verdict.OK
    assert v.check(_signed_frame(KEY, now)) is Verdict.REPLAY  # not newer
    assert v.check(_signed_frame(KEY, now + 1)) is Verdict.OK
    assert v.check(_signed_frame(KEY, now - 5, link_id=1)) is Verdict.OK  # another stream
    # a new stream more than a minute behind our clock is stale
    assert v.check(_signed_frame(KEY, now - NEW_STREAM_WINDOW - 1, link_id=2)) is Verdict.STALE
    assert v.check(_signed_frame(b"\x01" * 32, now + 9)) is Verdict.BAD_SIGNATURE
    unsigned = split_datagram(dev.MAVLink_command_long_message(
        1, 1, REQ, 0, 0, 0, 0, 0, 0, 0, 0).pack(dev.MAVLink(None, 255, 190)), FramerStats())[0]
    assert v.check(unsigned) is Verdict.UNSIGNED
    radio = split_datagram(dev.MAVLink_radio_status_message(200, 190, 90, 10, 12, 0, 0).pack(
        dev.MAVLink(None, 1, 68)), FramerStats())[0]
    assert v.check(radio) is Verdict.UNSIGNED_ALLOWED  # the radio injects it unsigned
    assert v.stats.as_dict() == {"good": 3, "unsigned_allowed": 1, "rejected_unsigned": 1,
                                 "rejected_bad_signature": 1, "rejected_replay": 1,
                                 "rejected_stale": 1}


def test_a_signature_wrong_in_any_one_of_its_six_bytes_is_rejected() -> None:
    clock = time.time()
    raw = _signed_frame(KEY, now_timestamp(clock)).raw
    for i in range(1, 7):
        bad = bytearray(raw)
        bad[-i] ^= 0x01
        (frame,) = split_datagram(bytes(bad), FramerStats())
        assert SignatureVerifier(KEY, clock=lambda: clock).check(frame) is \
            Verdict.BAD_SIGNATURE, f"signature byte {6 - i} not checked"
    (frame,) = split_datagram(raw, FramerStats())
    assert SignatureVerifier(KEY, clock=lambda: clock).check(frame) is Verdict.OK


def test_keys_from_passphrase_and_files(tmp_path: Path) -> None:
    assert key_from_passphrase(PASS) == KEY  # MAVProxy's `signing setup` / QGC derivation
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    hexf = tmp_path / "hex.key"
    hexf.write_text(KEY.hex().upper() + "\n")
    assert key_from_file(raw) == KEY == key_from_file(hexf)
    bad = tmp_path / "bad.key"
    bad.write_text("too short")
    for path in (bad, tmp_path / "missing.key"):
        with pytest.raises(SigningError, match=str(path.name)):
            key_from_file(path)
    with pytest.raises(SigningError):
        key_from_passphrase("")
    with pytest.raises(SigningError, match=r"bad\.key"):  # at construction: a config error
        MavlinkBackend(MavlinkOptions(endpoints=["udpout:127.0.0.1:9"], signing_key_file=str(bad)))
    cfg = config.parse({"backends": {"mavlink": {"signing_key_file": str(bad)}}})
    with pytest.raises(ConfigError, match=r"^backends\.mavlink: signing key .*bad\.key"):
        Gateway(cfg)
    with pytest.raises(ValueError, match="one, not both"):
        MavlinkBackend(MavlinkOptions(signing_key_file=str(raw), signing_passphrase=PASS))
    assert struct.calcsize("<IH") == 6  # the 48-bit timestamp layout the tests read
