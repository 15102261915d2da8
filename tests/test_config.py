"""Configuration: the embedded default, a full valid file, and one clear line naming the key for
every kind of mistake."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest

from backends.console import ConsoleBackend
from gateway import registry
from gateway.config import (
    GATEWAY_SCHEMA,
    ConfigError,
    GatewayConfig,
    check_flag,
    embedded_default,
    flag_value,
    load,
    parse,
)
from gateway.recorder import Recorder
from gateway.sources.serial_source import SerialSource
from gateway.sources.sim import SimSource

FULL = """
[gateway]
status_interval_s = 0.5
link_timeout_s = 2
record = "flight.aurora"
log_level = "debug"

[[sources]]
type = "sim"
rate_hz = 20
speed = 0

[[sources]]
type = "serial"
name = "radio"
url = "loop://"
baudrate = 9600

[backends.console]
interval_s = 0.25
status = true

[backends.quiet]
type = "console"
enabled = false
"""


def parse_toml(text: str) -> GatewayConfig:
    return parse(tomllib.loads(text))


def config_error(text: str) -> str:
    with pytest.raises(ConfigError) as info:
        parse_toml(text)
    message = str(info.value)
    assert "\n" not in message, f"not one line: {message!r}"
    return message


# -- what works -----------------------------------------------------------------------------


def test_embedded_default_runs_the_sim_through_the_console() -> None:
    cfg = embedded_default()
    assert [(p.type, p.cls) for p in cfg.sources] == [("sim", SimSource)]
    consoles = [p for p in cfg.backends if p.type == "console"]
    assert len(consoles) == 1
    assert consoles[0].cls is ConsoleBackend
    assert consoles[0].options == {"interval_s": 1.0, "stream": "stdout", "status": False}
    assert cfg.gateway["link_timeout_s"] == 3.0


def test_a_full_valid_file_parses_with_defaults_filled_in() -> None:
    cfg = parse_toml(FULL)
    assert cfg.gateway == {"status_interval_s": 0.5, "link_timeout_s": 2.0,
                           "record": "flight.aurora", "record_dir": "", "log_level": "debug"}
    sim, radio = cfg.sources
    assert (sim.type, sim.name, sim.cls) == ("sim", "sim", SimSource)
    assert sim.options["rate_hz"] == 20.0
    assert sim.options["speed"] == 0.0
    assert sim.options["revision"] == 64  # default
    assert (radio.type, radio.name, radio.cls) == ("serial", "radio", SerialSource)
    assert radio.options == {"url": "loop://", "baudrate": 9600, "reconnect_max_s": 2.0}
    assert [(b.type, b.name) for b in cfg.backends] == [("console", "console")]  # quiet is off
    assert cfg.backends[0].options == {"interval_s": 0.25, "stream": "stdout", "status": True}


def test_an_empty_file_gives_the_gateway_defaults_and_nothing_else() -> None:
    cfg = parse_toml("")
    assert cfg.sources == [] and cfg.backends == []
    assert cfg.gateway == {"status_interval_s": 1.0, "link_timeout_s": 3.0, "record": "",
                           "record_dir": "", "log_level": "info"}


def test_a_serial_source_is_named_after_its_url_by_default() -> None:
    cfg = parse_toml('[[sources]]\ntype = "serial"\nurl = "socket://localhost:7777"\n')
    assert cfg.sources[0].name == "socket://localhost:7777"


@pytest.mark.parametrize(("table", "name"), [
    ('type = "uavtalk"\nurl = "tcp:127.0.0.1:9000"', "uavtalk:tcp:127.0.0.1:9000"),
    ('type = "xbee"\nurl = "socket://127.0.0.1:9750"', "xbee:socket://127.0.0.1:9750"),
    ('type = "mavlink"\nurl = "udpin:127.0.0.1:14550"', "mavlink:udpin:127.0.0.1:14550"),
    ('type = "sim"', "sim"),
])
def test_a_source_without_a_name_is_named_by_its_name_format(table: str, name: str) -> None:
    assert parse_toml(f"[[sources]]\n{table}\n").sources[0].name == name


def test_float_keys_accept_integers_as_floats() -> None:
    cfg = parse_toml("[gateway]\nstatus_interval_s = 2\nlink_timeout_s = 1\n")
    assert cfg.gateway["status_interval_s"] == 2.0
    assert type(cfg.gateway["status_interval_s"]) is float
    assert type(cfg.gateway["link_timeout_s"]) is float


# -- what is refused, in one line naming the key ----------------------------------------------


@pytest.mark.parametrize(
    ("text", "starts", "mentions"),
    [
        pytest.param("[telemetry]\nx = 1\n", "telemetry: unknown section",
                     ["backends, gateway, sources"], id="unknown-section"),
        pytest.param("[gateway]\nverbose = true\n", "gateway.verbose: unknown key",
                     ["link_timeout_s", "status_interval_s"], id="unknown-gateway-key"),
        pytest.param('[gateway]\nstatus_interval_s = "fast"\n', "gateway.status_interval_s:",
                     ["a number", "'fast'"], id="wrong-type"),
        pytest.param("[gateway]\nstatus_interval_s = -1\n", "gateway.status_interval_s:",
                     ["≥ 0", "-1"], id="below-minimum"),
        pytest.param("[gateway]\nlink_timeout_s = 0.01\n", "gateway.link_timeout_s:",
                     ["≥ 0.05", "0.01"], id="timeout-too-small"),
        pytest.param('[gateway]\nlog_level = "loud"\n', "gateway.log_level:",
                     ["'debug'", "'error'", "'loud'"], id="not-a-choice"),
        pytest.param("[gateway]\nstatus_interval_s = true\n", "gateway.status_interval_s:",
                     ["True"], id="bool-for-float"),
        pytest.param("gateway = 3\n", "gateway:", ["a table"], id="gateway-not-a-table"),
        pytest.param('[[sources]]\ntype = "carrier-pigeon"\n', "sources[0].type:",
                     ["'carrier-pigeon'", "replay", "serial", "sim"], id="unknown-source"),
        pytest.param('[[sources]]\nname = "x"\n', "sources[0].type: required",
                     ["sim"], id="source-without-type"),
        pytest.param('[[sources]]\ntype = "sim"\n\n[[sources]]\ntype = "serial"\n',
                     "sources[1].url: required", ["a string"], id="required-key-missing"),
        pytest.param('[[sources]]\ntype = "sim"\nname = "a"\n\n[[sources]]\ntype = "sim"\n'
                     'name = "a"\n', "sources[1].name:", ["'a'", "twice"],
                     id="duplicate-source-names"),
        pytest.param('[[sources]]\ntype = "sim"\nname = 7\n', "sources[0].name:",
                     ["a string"], id="source-name-not-a-string"),
        pytest.param('[[sources]]\ntype = "sim"\nwarp = 9\n', "sources[0].warp: unknown key",
                     ["rate_hz"], id="unknown-source-key"),
        pytest.param('[[sources]]\ntype = "sim"\nrate_hz = 5000\n', "sources[0].rate_hz:",
                     ["from 0.1 to 1000", "5000"], id="above-maximum"),
        pytest.param('[[sources]]\ntype = "sim"\ncycles = true\n', "sources[0].cycles:",
                     ["an integer", "True"], id="bool-for-int"),
        pytest.param('[[sources]]\ntype = "sim"\nrevision = 48\n', "sources[0].revision:",
                     ["36", "64"], id="int-not-a-choice"),
        pytest.param('[[sources]]\ntype = "serial"\nurl = "loop://"\nbaudrate = 9600.0\n',
                     "sources[0].baudrate:", ["an integer", "9600.0"], id="float-for-int"),
        pytest.param('sources = { type = "sim" }\n', "sources:", ["[[sources]]"],
                     id="sources-not-an-array"),
        pytest.param("[backends.teleporter]\n", "backends.teleporter.type:",
                     ["'teleporter'", "console"], id="unknown-backend"),
        pytest.param('[backends.console]\nenabled = "yes"\n', "backends.console.enabled:",
                     ["true or false", "'yes'"], id="enabled-not-bool"),
        pytest.param('[backends.console]\ninterval_s = "1s"\n', "backends.console.interval_s:",
                     ["a number", "'1s'"], id="backend-option-wrong-type"),
        pytest.param('[backends.console]\nstream = "printer"\n', "backends.console.stream:",
                     ["'stdout'", "'stderr'"], id="backend-option-not-a-choice"),
        pytest.param("[backends.console]\nenabled = false\nbogus = 1\n",
                     "backends.console.bogus: unknown key", ["interval_s"],
                     id="disabled-backend-still-validated"),
        pytest.param("backends = [1]\n", "backends:", ["[backends.<name>]"],
                     id="backends-not-a-table"),
    ],
)
def test_bad_configuration_is_one_line_naming_the_key(text: str, starts: str,
                                                      mentions: list[str]) -> None:
    message = config_error(text)
    assert message.startswith(starts), message
    for word in mentions:
        assert word in message, f"{word!r} not in {message!r}"


# -- files ----------------------------------------------------------------------------------


def test_load_reads_and_validates_a_file(tmp_path: Path) -> None:
    path = tmp_path / "gateway.toml"
    path.write_text(FULL, encoding="utf-8")
    assert load(path) == parse_toml(FULL)
    assert load(str(path)).sources[1].name == "radio"


def one_line_load_error(path: Path) -> str:
    with pytest.raises(ConfigError) as info:
        load(path)
    message = str(info.value)
    assert "\n" not in message, f"not one line: {message!r}"
    assert message.startswith(str(path)), message
    return message


def test_load_of_a_missing_file_is_one_line_naming_it(tmp_path: Path) -> None:
    message = one_line_load_error(tmp_path / "nope.toml")
    assert "cannot read" in message


def test_load_of_invalid_toml_is_one_line_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "broken.toml"
    path.write_text("[gateway\nstatus_interval_s = 1\n", encoding="utf-8")
    message = one_line_load_error(path)
    assert "not valid TOML" in message
    assert "line 1" in message


def test_load_of_a_file_that_is_not_utf8_is_one_line_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes('[gateway]\nrecord = "vol_à_été"\n'.encode("latin-1"))
    message = one_line_load_error(path)
    assert "UTF-8" in message


def test_load_of_a_valid_file_with_a_bad_value_names_the_key(tmp_path: Path) -> None:
    path = tmp_path / "bad.toml"
    path.write_text('[gateway]\nlog_level = "chatty"\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"^gateway\.log_level: expected one of"):
        load(path)


# -- a source URL's scheme, checked by the url key ---------------------------------------------


@pytest.mark.parametrize("url", ["nosuch://x", "serial2://dev", "http://example.com"])
def test_a_serial_url_with_a_scheme_pyserial_does_not_know_is_refused(url: str) -> None:
    message = config_error(f'[[sources]]\ntype = "serial"\nurl = "{url}"\n')
    scheme = url.split("://")[0]
    assert message.startswith(f"sources[0].url: '{url}': unknown URL scheme '{scheme}'"), message
    for known in ("loop://", "socket://", "rfc2217://", "/dev/…"):
        assert known in message


@pytest.mark.parametrize("url", ["socket://nohost", "socket://host:99999", "socket://host:x",
                                 "rfc2217://:2217"])
def test_a_socket_or_rfc2217_url_without_host_and_port_is_refused(url: str) -> None:
    """pyserial would fail every reopen of these the same way: retrying cannot help."""
    message = config_error(f'[[sources]]\ntype = "serial"\nurl = "{url}"\n')
    assert message.startswith(f"sources[0].url: {url!r}: "), message
    assert "://HOST:PORT" in message and repr(url) in message


@pytest.mark.parametrize("url", ["/dev/ttyNOTTHEREYET0", "COM7", "loop://", "LOOP://",
                                 "socket://127.0.0.1:7777", "socket://[::1]:7777",
                                 "rfc2217://host:2217?ign_set_control",
                                 "spy://loop://?file=/dev/null", "hwgrep://0403:6001"])
def test_device_paths_and_known_schemes_are_accepted(url: str) -> None:
    """A device path that does not exist yet is accepted: the source retries it (hot-plug)."""
    cfg = parse_toml(f'[[sources]]\ntype = "serial"\nurl = "{url}"\n')
    assert cfg.sources[0].options["url"] == url


# -- flags: the same keys ----------------------------------------------------------------------


@pytest.mark.parametrize(("text", "value"), [("5", 5), ("-5", -5), ("0.01", 0.01),
                                             ("1e3", 1000.0), ("fast", "fast"), ("", "")])
def test_a_number_flag_reads_as_a_file_value_would(text: str, value: object) -> None:
    got = flag_value(text)
    assert got == value and type(got) is type(value)


def test_a_flag_is_judged_by_its_key_and_named_in_the_message() -> None:
    key = GATEWAY_SCHEMA.keys["link_timeout_s"]
    assert check_flag("--link-timeout", key, 2) == 2.0
    for bad, shown in ((0.01, "0.01"), (flag_value("nan"), "nan"), ("x", "'x'")):
        with pytest.raises(ConfigError) as info:
            check_flag("--link-timeout", key, bad, "gateway.link_timeout_s")
        assert str(info.value) == ("--link-timeout (gateway.link_timeout_s): expected a number "
                                   f"≥ 0.05, got {shown}")


# -- the example file shows every key -------------------------------------------------------------

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "gateway.toml"
_COMMENTED = re.compile(r"^# (\[\[?[\w.]+\]\]?|\w+ = .*)$")
_TABLE = re.compile(r"^(?:# )?(\[\[sources\]\]|\[backends\.(\w+)\])")


def _sections(text: str) -> list[tuple[str, str, str]]:
    """(group, type, block) for every table of the example, commented out or not."""
    out: list[tuple[str, str, str]] = []
    lines = text.splitlines()
    starts = [i for i, ln in enumerate(lines) if _TABLE.match(ln)]
    for i, j in zip(starts, [*starts[1:], len(lines)], strict=True):
        block = "\n".join(lines[i:j])
        m = _TABLE.match(lines[i])
        assert m is not None
        if m.group(2) is not None:
            typed = re.search(r'^(?:# )?type = "(\w+)"', block, re.M)
            out.append((registry.BACKEND_GROUP, typed.group(1) if typed else m.group(2),
                        block))
        else:
            typed = re.search(r'^(?:# )?type = "(\w+)"', block, re.M)
            assert typed, f"a [[sources]] table without a type:\n{block}"
            out.append((registry.SOURCE_GROUP, typed.group(1), block))
    return out


@pytest.mark.parametrize("group", [registry.SOURCE_GROUP, registry.BACKEND_GROUP])
def test_the_example_file_shows_every_key_of_every_source_and_backend(group: str) -> None:
    """What the README promises: examples/gateway.toml lists every key with its default."""
    sections = _sections(EXAMPLE.read_text(encoding="utf-8"))
    for name in registry.names(group):
        cls = registry.load(group, name)
        blocks = [b for g, t, b in sections if g == group and t == name]
        assert blocks, f"examples/gateway.toml has no table for {name}"
        block = "\n".join(blocks)
        for key in (cls.CONFIG.keys if cls.CONFIG else {}):
            assert re.search(rf"^(# )?{key} = ", block, re.M), \
                f"examples/gateway.toml: {name} does not show {key}"


def test_the_example_file_is_valid_with_every_commented_key_switched_on(
        tmp_path: Path) -> None:
    """Every value shown, commented out or not, is one the schema accepts."""
    text = EXAMPLE.read_text(encoding="utf-8")
    on = "\n".join(m.group(1) if (m := _COMMENTED.match(ln)) else ln
                   for ln in text.splitlines())
    data = tomllib.loads(on)
    replay = tmp_path / "flight.agrec"
    rec = Recorder(replay)  # the example's path names a recording the user has
    rec.write(b"\xa5\x5a\x7f\x00\xb4\x83")  # (a file exists from its first record on)
    rec.close()
    tlog = tmp_path / "flight.tlog"
    tlog.write_bytes(b"")  # (an empty telemetry log is one: it replays nothing)
    for table in data["sources"]:
        if table["type"] == "replay":
            table["path"] = str(replay)
        if table["type"] == "tlog":
            table["path"] = str(tlog)
    cfg = parse(data)
    assert {p.type for p in cfg.sources} == set(registry.source_names())
    assert {p.type for p in cfg.backends} == {"console"}  # the others are shown disabled
    commented = sum(1 for ln in text.splitlines() if _COMMENTED.match(ln))
    assert commented > 40  # the switch above did switch something on
