"""Zenoh payloads, keys, attachments and session options: no network here."""

from __future__ import annotations

import contextlib
import json
import math
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from helpers import ROOT as REPO
from hypothesis import given
from hypothesis import strategies as st

from backends.zenoh import encoding as enc
from backends.zenoh.backend import ZenohBackend
from backends.zenoh.keys import (
    DEFAULT_ENDPOINT,
    KeyLayout,
    SeqTracker,
    make_attachment,
    parse_attachment,
    parse_key,
    parse_stats_key,
    stats_key,
    stats_key_expr,
)
from backends.zenoh.options import ZenohOptions, ZenohSourceOptions
from backends.zenoh.session import SessionOptions
from backends.zenoh.source import ZenohSource, parse_url
from gateway import config, wire
from gateway.app import Gateway
from gateway.config import ConfigError
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    RawFrame,
    SmUpdate,
    Status,
    VehicleState,
    kind,
)

floats = st.floats(allow_nan=True, allow_infinity=True, width=64)


def sm(**kw) -> SmUpdate:
    base = dict(timestamp_ms=1000, state=2, armed=True, sm_type=0, altitude_m=120.5,
                acceleration_mps2=30.0, accel_vert_mps2=29.0, velocity_mps=55.25,
                roll_rad=0.1, pitch_rad=1.4, yaw_rad=-0.2)
    base.update(kw)
    return SmUpdate(**base)


# -- documents ---------------------------------------------------------------------------------

def test_sm_update_document_names_fields_with_units():
    doc = json.loads(enc.to_json(sm()))
    assert doc == {
        "timestamp_ms": 1000, "state": 2, "state_name": "BOOST", "armed": True, "sm_type": 0,
        "altitude_m": 120.5, "acceleration_mps2": 30.0, "accel_vert_mps2": 29.0,
        "velocity_mps": 55.25, "roll_rad": 0.1, "pitch_rad": 1.4, "yaw_rad": -0.2,
        "payload_len": 64,
    }


def test_status_document_spells_out_the_flags():
    flags = Status.make_flags(armed=True, baro_ok=True, log_ready=True)
    doc = json.loads(enc.to_json(Status(5000, 1, 0, flags)))
    assert doc == {"timestamp_ms": 5000, "state": 1, "state_name": "ARMED", "sm_type": 0,
                   "flags": flags, "armed": True, "imu_ok": False, "baro_ok": True,
                   "calibrated": False, "log_ready": True}


def test_unknown_state_is_named_by_number():
    assert json.loads(enc.to_json(sm(sm_type=9, state=17)))["state_name"] == "STATE_17"


def test_nan_and_infinity_become_null():
    text = enc.to_json(sm(altitude_m=math.nan, velocity_mps=math.inf, yaw_rad=-math.inf))
    doc = json.loads(text)  # strict JSON: no NaN / Infinity literals
    assert b"NaN" not in text and b"Infinity" not in text
    assert doc["altitude_m"] is None and doc["velocity_mps"] is None and doc["yaw_rad"] is None
    assert doc["roll_rad"] == 0.1


@given(st.dictionaries(st.text(max_size=5), st.one_of(
    floats, st.integers(-(2**63), 2**64 - 1), st.booleans(), st.none(), st.text(max_size=5))))
def test_fast_and_standard_json_agree(doc):
    """orjson (when installed) and the standard library write the same documents."""
    def norm(d):
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in d.items()}

    assert json.loads(enc.dumps(doc)) == json.loads(enc.dumps_stdlib(doc)) == norm(doc)


@pytest.mark.parametrize("msg", [
    LinkEvent("serial0", False, 3.5),
    LinkStats(rssi_dbm=-70.0, link_quality_pct=98),
    Position(48.1, 11.5, alt_amsl_m=520.0, satellites=9),
    Battery(11.7, current_a=3.2, remaining_pct=80),
    VehicleState(True, "AUTO", roll_rad=0.1),
])
def test_other_kinds_publish_their_fields(msg):
    doc = json.loads(enc.to_json(msg))
    assert doc == msg.fields()
    if not isinstance(msg, LinkEvent):  # link events are a gateway's own; never decoded
        assert enc.decode(kind(msg), enc.to_json(msg), enc.JSON, origin="z") == msg._replace(
            origin="z")


@given(ts=st.integers(0, 2**32 - 1), state=st.integers(0, 255), armed=st.booleans(),
       sm_type=st.integers(0, 255), f=st.lists(floats, min_size=7, max_size=7),
       plen=st.sampled_from([36, 64]))
def test_json_round_trip(ts, state, armed, sm_type, f, plen):
    m = SmUpdate(ts, state, armed, sm_type, *f, payload_len=plen)
    back = enc.decode("sm_update", enc.to_json(m), enc.JSON)
    for a, b in zip(m.fields().values(), back.fields().values(), strict=True):
        if isinstance(a, float) and not math.isfinite(a):
            assert math.isnan(b)  # null comes back as NaN: "not known"
        else:
            assert a == b


@given(f=st.lists(st.floats(width=32, allow_nan=False), min_size=7, max_size=7),
       plen=st.sampled_from([36, 64]), flags=st.integers(0, 0x1F))
def test_packed_is_the_wire_payload_and_decodes_back(f, plen, flags):
    frame = wire.encode(SmUpdate(77, 3, False, 0, *f, payload_len=plen))
    m = wire.decode_all(frame)[0]
    payload, encoding = enc.encode(m, "packed")
    assert payload == frame[4:-2] and len(payload) == plen
    assert encoding == enc.SM_UPDATE_PACKED
    assert enc.decode("sm_update", payload, encoding) == m  # raw included: the same frame
    st_frame = wire.encode(Status(5, 1, 0, flags))
    payload, encoding = enc.encode(wire.decode_all(st_frame)[0], "packed")
    assert payload == st_frame[4:-2] and encoding == enc.STATUS_PACKED
    assert enc.decode("status", payload, encoding).flags == flags


def test_packed_mode_keeps_json_for_kinds_without_a_wire_layout():
    payload, encoding = enc.encode(Battery(12.0), "packed")
    assert encoding == enc.JSON and json.loads(payload)["voltage_v"] == 12.0


def test_in_memory_message_gets_a_real_frame():
    m = sm()  # built in memory: no raw
    frame = enc.wire_frame(m)
    assert wire.decode_all(frame)[0].fields() == m.fields()
    raw = RawFrame(0x42, b"\x01\x02", wire.frame(0x42, b"\x01\x02"))
    assert enc.wire_frame(raw) == raw.raw


@given(st.binary(max_size=300), st.sampled_from(["sm_update", "status", "battery", "x"]),
       st.sampled_from([enc.JSON, enc.SM_UPDATE_PACKED, enc.STATUS_PACKED, "text/plain"]))
def test_decoding_arbitrary_payloads_raises_only_payload_error(data, kind, encoding):
    with contextlib.suppress(enc.PayloadError):
        enc.decode(kind, data, encoding)


@pytest.mark.parametrize("doc", [[], {"timestamp_ms": "x", "state": 1},
                                 {"timestamp_ms": 1}, {"timestamp_ms": 1, "state": 1,
                                                       "altitude_m": "high"},
                                 {"timestamp_ms": 1, "state": 1, "payload_len": 40}])
def test_bad_documents_are_refused_clearly(doc):
    with pytest.raises(enc.PayloadError):
        enc.decode("sm_update", json.dumps(doc).encode(), enc.JSON)


# -- keys and attachments ----------------------------------------------------------------------

def test_key_layout():
    k = KeyLayout("aurora", "rocket1")
    assert k.kind("sm_update") == "aurora/rocket1/sm_update"
    assert k.raw(1) == "aurora/rocket1/raw/1" and k.raw(0xAB) == "aurora/rocket1/raw/171"
    assert k.token("gw-1") == "aurora/rocket1/gateway/gw-1"
    assert k.everything == "aurora/rocket1/**"
    assert KeyLayout("org/aurora", "r2").kind("status") == "org/aurora/r2/status"
    assert parse_key("aurora/rocket1/raw/1", "aurora") == ("rocket1", "raw", "1")
    assert parse_key("aurora/rocket1/status", "aurora") == ("rocket1", "status", "")
    assert parse_key("other/rocket1/status", "aurora") is None


@pytest.mark.parametrize("prefix", ["", "a/*", "/a", "a//b", "a b", "a/$*", "a/@x"])
def test_a_bad_prefix_is_a_config_error_naming_the_key(prefix):
    with pytest.raises(ConfigError) as info:
        config.parse({"backends": {"zenoh": {"prefix": prefix}}})
    assert str(info.value).startswith("backends.zenoh.prefix:")


def test_the_removed_vehicle_key_says_what_replaced_it():
    """Keys follow each message's vehicle (issue 22): the backend's old ``vehicle`` key and
    ``--zenoh-vehicle`` are refused with one line naming them and what names a vehicle now."""
    with pytest.raises(ConfigError) as info:
        config.parse({"backends": {"zenoh": {"vehicle": "rocket1"}}})
    text = str(info.value)
    assert text.startswith("backends.zenoh.vehicle: removed")
    assert "[[sources]]" in text and "--source NAME=URL" in text
    done = subprocess.run([sys.executable, "-m", "gateway", "run", "--zenoh-vehicle", "r1",
                           "--duration", "0"], cwd=REPO, capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode == 2
    assert "--zenoh-vehicle: removed" in done.stderr and "--source NAME=URL" in done.stderr
    assert "Traceback" not in done.stderr
    help_text = subprocess.run([sys.executable, "-m", "gateway", "run", "--help"], cwd=REPO,
                               capture_output=True, text=True, timeout=60, check=True).stdout
    assert "--zenoh-vehicle" not in help_text and "--zenoh-prefix" in help_text


def test_stats_keys_are_a_gateways_not_a_vehicles():
    zenoh = pytest.importorskip("zenoh")
    assert stats_key("aurora", "gw-1") == "aurora/@gateways/gw-1/stats"
    assert parse_stats_key("aurora/@gateways/gw-1/stats", "aurora") == "gw-1"
    assert parse_stats_key("aurora/gw-1/stats", "aurora") is None
    assert parse_stats_key("aurora/@gateways/a/b/stats", "aurora") is None
    # a verbatim chunk: no vehicle wildcard reaches it
    for expr in ("aurora/**", "aurora/*/*", "aurora/*/**"):
        assert not zenoh.KeyExpr(expr).intersects(zenoh.KeyExpr(stats_key("aurora", "g")))
    assert zenoh.KeyExpr(stats_key_expr("aurora")).intersects(
        zenoh.KeyExpr(stats_key("aurora", "g")))


def test_seq_tracker_is_bounded():
    t = SeqTracker(max_keys=3)
    for i in range(10):
        t.see("gw", f"k{i}", 0)
    assert len(t._last) == 3 and t.forgotten == 7
    t.see("gw", "k9", 5)
    assert t.lost == 4


def test_a_bad_gateway_id_is_a_config_error_naming_the_key():
    with pytest.raises(ConfigError) as info:
        config.parse({"backends": {"zenoh": {"gateway_id": "a/b"}}})
    assert str(info.value).startswith("backends.zenoh.gateway_id:")


@given(st.text(alphabet=st.characters(blacklist_characters=";=", blacklist_categories=["Cs"]),
               min_size=1), st.integers(0, 2**63))
def test_attachment_round_trip(gw, seq):
    assert parse_attachment(make_attachment(gw, seq)) == (gw, seq)


@given(st.binary(max_size=100))
def test_arbitrary_attachments_never_raise(data):
    gw, seq = parse_attachment(data)
    assert gw is None or isinstance(gw, str)
    assert seq is None or isinstance(seq, int)


def test_seq_tracker_counts_gaps_and_restarts():
    t = SeqTracker()
    for seq in (0, 1, 2, 5, 6, 0, 1, 3):
        t.see("gw", "k", seq)
    t.see("gw", "other", 7)  # first sample of another key: no loss
    t.see(None, "k", None)  # a foreign publisher: nothing to count
    assert t.lost == 2 + 1 and t.restarts == 1


# -- source URL --------------------------------------------------------------------------------

def test_source_url_forms():
    assert parse_url("zenoh") == {} and parse_url("zenoh:") == {}
    assert parse_url("zenoh:tcp/10.0.0.5:7447") == {"connect": ["tcp/10.0.0.5:7447"]}
    assert parse_url("zenoh:rocket1@tcp/h:1,tls/h:2") == {
        "follow": "rocket1", "connect": ["tcp/h:1", "tls/h:2"]}
    assert parse_url("zenoh:*@tcp/h:1")["follow"] == "*"
    for bad in ("zenoh:nonsense", "zenoh:r/1@tcp/h:1x", "mqtt:tcp/h:1", "zenoh:foo/h:1"):
        with pytest.raises(ValueError):
            parse_url(bad)
    src = ZenohSource(ZenohSourceOptions(url="zenoh:rocket2@tcp/127.0.0.1:9"))
    assert src.name == "zenoh:rocket2@tcp/127.0.0.1:9"
    assert src.key_expr == "aurora/rocket2/raw/**"
    assert src.session_options.connect == ["tcp/127.0.0.1:9"]
    assert ZenohSource(ZenohSourceOptions(keys="json", follow="r3")).key_expr == "aurora/r3/*"


# -- session options ---------------------------------------------------------------------------

def _cfg(**kw):
    return json.loads(str(SessionOptions(**kw).config()))


def test_embedded_default_keeps_everything_on_loopback():
    assert ZenohBackend.EMBEDDED_DEFAULT is not None
    part = config.make_backend("zenoh", dict(ZenohBackend.EMBEDDED_DEFAULT), "zenoh",
                               "backends.zenoh")
    b = part.cls.from_config(dict(part.options), name="zenoh")
    c = json.loads(str(b.session_options.config()))
    assert c["mode"] == "peer"
    assert c["listen"]["endpoints"] == [DEFAULT_ENDPOINT] == ["tcp/127.0.0.1:7450"]
    assert c["connect"]["endpoints"] == []
    assert c["scouting"]["multicast"]["enabled"] is False


def test_connect_alone_means_do_not_listen():
    c = _cfg(connect=["tcp/10.1.2.3:7447"])
    assert c["connect"]["endpoints"] == ["tcp/10.1.2.3:7447"]
    assert c["listen"]["endpoints"] == []
    c = _cfg(connect="tcp/10.1.2.3:7447", listen=["tcp/127.0.0.1:9000"])
    assert c["listen"]["endpoints"] == ["tcp/127.0.0.1:9000"]


def test_reconnection_is_bounded():
    c = _cfg(mode="client", connect=["tcp/127.0.0.1:7447"], reconnect_max_s=2.0)
    assert c["mode"] == "client"
    assert c["connect"]["retry"]["period_max_ms"] == 2000


def test_security_options_reach_the_zenoh_config(tmp_path):
    for name in ("ca.pem", "me.pem", "me.key"):
        (tmp_path / name).write_text("-----BEGIN CERTIFICATE-----\n")
    c = _cfg(connect=["tls/router.example:7447"], tls_root_ca=str(tmp_path / "ca.pem"),
             tls_certificate=str(tmp_path / "me.pem"), tls_private_key=str(tmp_path / "me.key"),
             tls_mtls=True, user="gateway", password="s3cret")
    tls = c["transport"]["link"]["tls"]
    assert tls["root_ca_certificate"] == str(tmp_path / "ca.pem")
    assert tls["connect_certificate"] == str(tmp_path / "me.pem")
    assert tls["connect_private_key"] == str(tmp_path / "me.key")
    assert tls["enable_mtls"] is True
    assert c["transport"]["auth"]["usrpwd"]["user"] == "gateway"


def test_config_file_is_the_base_and_explicit_keys_override(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "client", connect: { endpoints: ["tcp/10.0.0.1:7447"] },\n'
                 '  // a comment: JSON5\n  queries_default_timeout: 1234 }')
    c = _cfg(config_file=str(f))
    assert c["mode"] == "client" and c["connect"]["endpoints"] == ["tcp/10.0.0.1:7447"]
    assert c["queries_default_timeout"] == 1234
    c = _cfg(config_file=str(f), connect=["tcp/10.0.0.2:7447"])
    assert c["connect"]["endpoints"] == ["tcp/10.0.0.2:7447"]


@pytest.mark.parametrize("opts,key", [
    # the locators are checked by their key's validator, in the words a file gets (the item
    # named by its text: "connect: 'localhost:7447' is not <protocol>/<address>, …")
    ({"connect": ["localhost:7447"]}, "connect: 'localhost:7447'"),
    ({"listen": ["carrier-pigeon/coop:1"]}, "listen: unknown protocol 'carrier-pigeon'"),
    ({"connect": [7447]}, "connect: 7447 is not a string"),
    ({"mode": "client"}, "connect"),
    ({"user": "u"}, "user/password"),
    ({"tls_root_ca": "/nonexistent/ca.pem"}, "tls_root_ca"),
    ({"config_file": "/nonexistent/z.json5"}, "config_file"),
])
def test_bad_session_options_name_the_key(opts, key):
    with pytest.raises(ConfigError) as info:
        ZenohBackend(ZenohOptions(**opts))
    assert str(info.value).startswith(key if ": " in key else key + ":")


def test_bad_values_in_a_gateway_config_name_the_table_and_key():
    with pytest.raises(ConfigError) as info:
        config.parse({"backends": {"zenoh": {"congestion_control": "maybe"}}})
    assert str(info.value).startswith("backends.zenoh.congestion_control:")
    with pytest.raises(ConfigError) as info:
        config.parse({"backends": {"zenoh": {"mode": "server"}}})
    assert str(info.value).startswith("backends.zenoh.mode:")
    with pytest.raises(ConfigError) as info:
        config.parse({"sources": [{"type": "zenoh", "keys": "xml"}]})
    assert str(info.value).startswith("sources[0].keys:")


def test_malformed_config_file_is_a_config_error(tmp_path):
    f = tmp_path / "bad.json5"
    f.write_text("{ mode: ")
    with pytest.raises(ConfigError) as info:
        ZenohBackend(ZenohOptions(config_file=str(f)))
    assert str(info.value).startswith("config_file:")
    cfg = config.parse({"sources": [{"type": "zenoh", "config_file": str(f)}]})
    with pytest.raises(ConfigError) as info:
        Gateway(cfg)  # before anything starts
    assert str(info.value).startswith("sources.zenoh: config_file:")


# -- the user docs -----------------------------------------------------------------------------

README = Path(__file__).resolve().parents[1] / "backends" / "zenoh" / "README.md"


def test_readme_toml_examples_are_valid_and_list_every_key():
    text = README.read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, flags=re.S)
    assert blocks
    for block in blocks:
        config.parse(tomllib.loads(block))
    for key in (*ZenohBackend.CONFIG.keys, *ZenohSource.CONFIG.keys):
        assert re.search(rf"^#? ?{key} = |; {key} = |`{key}`", text, re.M), key
