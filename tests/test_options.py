"""Options declared once (gateway/options.py): every backend's and source's options are one
dataclass, from which the schema, the ``run`` flags, the reference and check-config come."""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from backends.crsf.options import CrsfOptions
from backends.mavlink.options import MavlinkOptions
from gateway import config, registry
from gateway.commands import cli
from gateway.io.endpoints import KINDS, usage
from gateway.options import ConfigError, Options, option_fields, options_of

ROOT = Path(__file__).resolve().parents[1]
PART_GROUPS = (registry.BACKEND_GROUP, registry.SOURCE_GROUP)


def _classes() -> list[tuple[str, str, Any]]:
    return [(group, name, registry.load(group, name))
            for group in PART_GROUPS for name in registry.names(group)]


def _options_classes() -> list[type[Options]]:
    found = [config.GatewayOptions] + [cls.OPTIONS for _, _, cls in _classes()]
    return list(dict.fromkeys(found))


@pytest.mark.parametrize(("group", "name", "cls"), _classes(),
                         ids=[f"{g.rsplit('.', 1)[1]}-{n}" for g, n, _ in _classes()])
def test_a_backends_or_sources_options_are_declared_once(group: str, name: str,
                                                         cls: Any) -> None:
    opts = options_of(cls)
    assert opts is not None, f"{name}: no OPTIONS dataclass"
    # the schema is derived from the dataclass, not written beside it
    assert cls.CONFIG is opts.schema()
    assert list(opts.schema().keys) == [f.name for f in option_fields(opts)]
    # every key is annotated by exactly one class of the options' MRO: no field redeclared
    for key in opts.schema().keys:
        owners = [c for c in opts.__mro__ if key in inspect.get_annotations(c)]
        assert len(owners) == 1, (name, key, owners)
    # the constructor takes the options object: no option as a keyword of its own
    params = inspect.signature(cls.__init__).parameters
    assert "options" in params
    assert not set(params) & set(opts.schema().keys), (name, set(params) & set(opts.schema().keys))
    # the light entry point names the same class the backend or source uses
    options_group = {registry.BACKEND_GROUP: registry.BACKEND_OPTIONS_GROUP,
                     registry.SOURCE_GROUP: registry.SOURCE_OPTIONS_GROUP}[group]
    if name in registry.names(options_group):
        assert registry.load(options_group, name) is opts


def test_no_module_writes_a_schema_or_a_flags_module_by_hand() -> None:
    for path in [*ROOT.glob("backends/**/*.py"), *ROOT.glob("gateway/**/*.py")]:
        text = path.read_text(encoding="utf-8")
        assert "CONFIG = Schema(" not in text, path
        assert "def cli_options(" not in text or path.name in ("options.py", "backend.py"), path
    assert not list(ROOT.glob("backends/*/flags.py"))


def test_every_flag_maps_to_one_field() -> None:
    owners: dict[str, set[tuple[type, str]]] = {}
    for opts in _options_classes():
        for key, flag, _ in opts.flags():
            declaring = next(c for c in opts.__mro__
                             if key in inspect.get_annotations(c))
            owners.setdefault(flag.name, set()).add((declaring, key))
    assert owners, "no flags at all"
    for flag_name, fields in owners.items():
        assert len(fields) == 1, (flag_name, fields)
    parser = cli.build_parser()
    run = next(a for a in parser._subparsers._group_actions[0].choices.items()  # type: ignore[union-attr]
               if a[0] == "run")[1]
    given = {s for action in run._actions for s in action.option_strings}
    assert set(owners) <= given  # every declared flag is on `run`, added once (argparse
    # refuses a flag added twice)


def test_the_count_tool_finds_no_key_declared_twice() -> None:
    out = subprocess.run([sys.executable, "tools/count_option_declarations.py"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120, check=True).stdout
    assert out.splitlines()[-1].startswith("0 of "), out


# -- building an options object ------------------------------------------------------------------

def test_defaults_come_from_the_declaration_and_values_are_checked() -> None:
    o = CrsfOptions(baudrate=416666)
    assert (o.url, o.baudrate, o.attitude_hz) == ("pty", 416666, 10.0)
    assert CrsfOptions.schema().keys["baudrate"].default == CrsfOptions().baudrate
    with pytest.raises(ConfigError, match=r"^baudrate: expected an integer ≥ 1200, got 10$"):
        CrsfOptions(baudrate=10)
    with pytest.raises(ConfigError, match=r"^disarmed_suffix: expected at most 4 ASCII"):
        CrsfOptions(disarmed_suffix="toolong")
    with pytest.raises(TypeError):
        CrsfOptions(colour="red")  # type: ignore[call-arg]
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.baudrate = 1  # type: ignore[misc]


def test_an_integer_for_a_number_is_a_float_and_a_tuple_for_a_list_a_list() -> None:
    o = MavlinkOptions(endpoints=("udpout:127.0.0.1:9",), stale_after_s=2)
    assert o.endpoints == ["udpout:127.0.0.1:9"]
    assert type(o.stale_after_s) is float
    assert o.replace(sysid=7).sysid == 7 and o.sysid == 1


def test_checks_between_keys_run_for_a_file_as_for_python() -> None:
    with pytest.raises(ConfigError, match="give one, not both"):
        MavlinkOptions(signing_key_file="k", signing_passphrase="p")
    with pytest.raises(ConfigError, match=r"^backends\.mavlink: signing_key_file and "):
        config.parse({"backends": {"mavlink": {"signing_key_file": "k",
                                               "signing_passphrase": "p"}}})


def test_a_required_key_has_no_default() -> None:
    from backends.hc12.options import Hc12Options

    with pytest.raises(TypeError, match="url"):
        Hc12Options()  # type: ignore[call-arg]
    with pytest.raises(ConfigError, match=r"^backends\.hc12\.url: required"):
        config.parse({"backends": {"hc12": {}}})


# -- flags ---------------------------------------------------------------------------------------

def _opts(cls: type[Options], *argv: str) -> dict[str, Any] | None:
    p = argparse.ArgumentParser()
    cls.add_cli_arguments(p)
    return cls.cli_options(p.parse_args(list(argv)), "backends.x")


def test_a_flag_is_checked_by_its_key_and_named() -> None:
    assert _opts(CrsfOptions) is None
    assert _opts(CrsfOptions, "--crsf-baud", "416666") == {"baudrate": 416666}
    with pytest.raises(ConfigError, match=r"^--crsf-baud \(backends\.x\.baudrate\): expected "
                                          r"an integer ≥ 1200, got 'fast'$"):
        _opts(CrsfOptions, "--crsf-baud", "fast")
    assert _opts(MavlinkOptions, "--mavlink", "udpin:0.0.0.0:1", "--mavlink", "tcpin::2") == \
        {"endpoints": ["udpin:0.0.0.0:1", "tcpin::2"]}


def test_a_convert_flag_is_read_by_argparse_in_its_own_words(
        capsys: pytest.CaptureFixture[str]) -> None:
    """Flag(convert=...) runs as argparse reads each value (a repeatable flag stays so): the
    address flags' mistakes are the endpoint grammar's one usage line, not a key's."""
    assert _opts(MavlinkOptions, "--mavlink", " udp:[::1]:0 ") == {"endpoints": ["udp:[::1]:0"]}
    with pytest.raises(SystemExit) as info:
        _opts(MavlinkOptions, "--mavlink", "udpout:127.0.0.1:9", "--mavlink", "tcpin:h:x")
    assert info.value.code == 2
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.endswith("argument --mavlink: 'tcpin:h:x': port 'x' is not a number; expected "
                        + usage(KINDS)), err
    assert _opts(CrsfOptions, "--crsf", "pty") == {"url": "pty"}
    with pytest.raises(SystemExit):
        _opts(CrsfOptions, "--crsf", "")


def test_a_shared_flag_sets_the_backend_and_every_source_of_its_type() -> None:
    """--xbee-api is declared once, by the field the XBee backend and source share: alone it
    configures no backend, but sets the sources' API mode; with --xbee, the backend's too."""
    args = cli.build_parser().parse_args(["run", "--source", "xbee:loop://", "--xbee-api", "2",
                                          "--only", "console"])
    cfg = cli.config_from_args(args)
    assert [p.options["api_mode"] for p in cfg.sources] == [2]
    assert "xbee" not in {p.name for p in cfg.backends}
    args = cli.build_parser().parse_args(["run", "--xbee", "loop://", "--xbee-api", "2"])
    cfg = cli.config_from_args(args)
    assert {p.name: p for p in cfg.backends}["xbee"].options["api_mode"] == 2


def test_the_zenoh_session_flags_set_the_backend_only() -> None:
    args = cli.build_parser().parse_args(["run", "--source", "zenoh:", "--zenoh-mode", "client",
                                          "--zenoh-connect", "tcp/127.0.0.1:9"])
    cfg = cli.config_from_args(args)
    assert cfg.sources[0].options["mode"] is None
    assert {p.name: p for p in cfg.backends}["zenoh"].options["mode"] == "client"


# -- secrets -------------------------------------------------------------------------------------

def test_check_config_never_prints_a_secret(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text('[backends.mavlink]\nsigning_passphrase = "hunter2-pass"\n'
                    '[backends.zenoh]\nuser = "u"\npassword = "pw-secret-9"\n'
                    '[[sources]]\ntype = "mavlink"\nurl = "udpin:127.0.0.1:0"\n'
                    'signing_passphrase = "src-pass-7"\n')
    for extra in ([], ["--json"]):
        r = subprocess.run([sys.executable, "-m", "gateway", "check-config", str(path), *extra],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        for secret in ("hunter2-pass", "pw-secret-9", "src-pass-7"):
            assert secret not in r.stdout
        assert r.stdout.count("set, not shown") == 3
        if extra:
            json.loads(r.stdout)
    secrets = sorted(f"{o.__name__}.{k}" for o in _options_classes()
                     for k, key in o.schema().keys.items() if key.secret)
    assert secrets == ["MavlinkOptions.signing_passphrase",
                       "MavlinkSourceOptions.signing_passphrase",
                       "ZenohOptions.password", "ZenohSourceOptions.password"]


# -- the light modules' constants are the protocol modules' ----------------------------------------

def test_the_options_modules_constants_are_the_protocol_modules() -> None:
    from backends.crsf import frames as crsf_frames
    from backends.crsf import options as crsf
    from backends.fprime import channels, framing, packets
    from backends.fprime import options as fprime
    from backends.hc12 import at, vehicle
    from backends.hc12 import options as hc12
    from backends.uavtalk import options as uavtalk
    from backends.uavtalk import telemetry
    from backends.xbee import options as xbee
    from backends.xbee import radio
    from backends.zenoh import encoding
    from backends.zenoh import options as zenoh
    from gateway import model
    from gateway.io import port
    from gateway.sources import options as sources

    assert (crsf.SYNC_FC, crsf.SYNC_RADIO, crsf.SYNC_RX) == (
        crsf_frames.SYNC_FC, crsf_frames.SYNC_RADIO, crsf_frames.SYNC_RX)
    assert tuple(framing.FRAMINGS) == fprime.FRAMINGS
    assert fprime.DEFAULT_FRAMING == framing.DEFAULT_FRAMING
    assert tuple(packets.TIME_BASES) == fprime.TIME_BASES
    assert fprime.DEFAULT_ID_BASE == channels.DEFAULT_ID_BASE
    assert fprime.DEFAULT_BUFFER_SIZE == packets.DEFAULT_BUFFER_SIZE
    assert (fprime.TM_MIN_FRAME, fprime.TM_MAX_FRAME) == (framing.TM_MIN_FRAME,
                                                          framing.TM_MAX_FRAME)
    assert (hc12.BAUD_RATES, hc12.AT_BAUD) == (at.BAUD_RATES, at.AT_BAUD)
    assert (hc12.SM_UPDATE_F32_LEN, hc12.SM_UPDATE_F64_LEN) == (model.SM_UPDATE_F32_LEN,
                                                                model.SM_UPDATE_F64_LEN)
    assert hc12.DEFAULT_MAX_AGE_S == vehicle.DEFAULT_MAX_AGE_S
    assert uavtalk.DEFAULT_BOARD_TYPE == telemetry.DEFAULT_BOARD_TYPE
    assert (xbee.DEFAULT_BAUD, xbee.TICK_S, xbee.POLL_S) == (radio.DEFAULT_BAUD, radio.TICK_S,
                                                             radio.POLL_S)
    assert zenoh.ENCODINGS == encoding.ENCODINGS
    assert sources.REOPEN_MAX_S == uavtalk.REOPEN_MAX_S == port.REOPEN_MAX_S


def test_the_example_file_shows_the_declared_defaults() -> None:
    """examples/gateway.toml is checked against the declarations: each value it shows, set or
    commented out, is the declared default, except where the default is "not set" or empty
    (then it shows what a value looks like)."""
    import re
    import tomllib

    from test_config import EXAMPLE, _sections

    shown = 0
    for group, type_name, block in _sections(EXAMPLE.read_text(encoding="utf-8")):
        keys = config.schema_of(registry.load(group, type_name)).keys
        for line in block.splitlines():
            m = re.match(r"^(?:# )?(\w+) = (.*?)(?:\s+#.*)?$", line)
            if not m or m.group(1) in ("type", "name", "enabled") or (
                    group == registry.SOURCE_GROUP and m.group(1) in config.SOURCE_COMMON_KEYS):
                continue
            key = keys[m.group(1)]
            if key.default in (config.REQUIRED, None, []):
                continue
            value = tomllib.loads(f"v = {m.group(2)}")["v"]
            assert value == key.default, (type_name, m.group(1), value, key.default)
            shown += 1
    assert shown > 150
