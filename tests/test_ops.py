"""Running the gateway as a service: ``check-config``, ``--log-format json``, the systemd unit,
the documented exit codes and the generated configuration reference.

Expected values come from the schemas (each :class:`gateway.config.Key`'s default) and from
the files as ``tomllib`` — an independent TOML reader — loads them, never from the output
under test.
"""

from __future__ import annotations

import configparser
import io
import json
import logging
import os
import re
import shlex
import subprocess
import sys
import tomllib
import uuid
from datetime import datetime
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway import config, registry, vehicles
from gateway.commands import cli
from gateway.commands.check_config import resolved_dict, toml_string, toml_value
from gateway.logjson import JsonFormatter, LineHandler

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "gateway.toml"
UNIT = ROOT / "examples" / "aurora-gateway.service"
CONSOLE_SCRIPT = Path(sys.executable).parent / "aurora-gateway"
TIMEOUT_S = 30.0

sys.path.insert(0, str(ROOT / "tools"))
import gen_config_reference as gen  # noqa: E402


def _own_lines(stderr: str) -> list[str]:
    """stderr without the registry's warnings about plug-ins that fail to import."""
    return [ln for ln in stderr.splitlines() if ln.strip() and " failed to import: " not in ln]


def _check_config(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = cli.main(["check-config", *args])
    out, err = capsys.readouterr()
    return code, out, err


def _defaults(schema: config.Schema) -> dict[str, Any]:
    return {k: key.default for k, key in schema.keys.items()}


# -- check-config -----------------------------------------------------------------------------

def test_check_config_prints_every_key_with_the_schemas_defaults_filled_in(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "gw.toml"
    path.write_text('[gateway]\nlink_timeout_s = 7\n\n[[sources]]\ntype = "sim"\nspeed = 4\n\n'
                    '[backends.console]\nstream = "stderr"\n')
    code, out, err = _check_config(capsys, str(path))
    assert code == 0, err
    got = tomllib.loads(out)
    sim = registry.load(registry.SOURCE_GROUP, "sim").CONFIG
    console = registry.load(registry.BACKEND_GROUP, "console").CONFIG
    assert got["gateway"] == {**_defaults(config.GATEWAY_SCHEMA), "link_timeout_s": 7.0}
    assert len(got["sources"]) == 1
    source = got["sources"][0]
    assert source.pop("type") == "sim" and isinstance(source.pop("name"), str)
    assert vehicles.check_name(source.pop("vehicle"))
    assert source == {**_defaults(sim), "speed": 4.0}
    assert got["backends"] == {"console": {"type": "console", **_defaults(console),
                                           "stream": "stderr"}}


def test_check_config_output_loads_back_to_the_same_configuration(
        capsys: pytest.CaptureFixture[str]) -> None:
    """The example sets every key of every type (lists, strings, numbers, booleans)."""
    code, out, err = _check_config(capsys, str(EXAMPLE))
    assert code == 0, err
    assert resolved_dict(config.parse(tomllib.loads(out))) == \
        resolved_dict(config.load(EXAMPLE))
    # the backends the file disables were checked and are named, not run
    disabled = {n for n, t in tomllib.loads(EXAMPLE.read_text())["backends"].items()
                if t.get("enabled") is False}
    assert disabled, "the example disables some backends"
    assert set(tomllib.loads(out)["backends"]).isdisjoint(disabled)
    for name in disabled:
        assert f"# [backends.{name}] enabled = false: checked, not run" in out


def test_check_config_json_is_the_same_configuration(capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    code, out, err = _check_config(capsys, str(EXAMPLE), "--json")
    assert code == 0, err
    doc = json.loads(out)
    disabled = doc.pop("disabled_backends")
    assert doc == json.loads(json.dumps(resolved_dict(config.load(EXAMPLE))))
    assert "mavlink" in disabled


def test_check_config_without_a_file_resolves_the_embedded_default(
        capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _check_config(capsys)
    assert code == 0, err
    assert resolved_dict(config.parse(tomllib.loads(out))) == \
        resolved_dict(config.embedded_default())


def test_check_config_refuses_a_bad_file_in_one_line_naming_the_key_with_status_2(
        tmp_path: Path) -> None:
    """The installed console script, as an operator runs it."""
    path = tmp_path / "bad.toml"
    path.write_text('[[sources]]\ntype = "sim"\nspeed = "fast"\n')
    r = subprocess.run([str(CONSOLE_SCRIPT), "check-config", str(path)], capture_output=True,
                       text=True, timeout=TIMEOUT_S, cwd=tmp_path)
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = _own_lines(r.stderr)
    assert len(lines) == 1, lines
    assert "sources[0].speed" in lines[0] and str(path) in lines[0]
    assert r.stdout == ""


@pytest.mark.parametrize("kind", ["missing", "directory", "not-toml"])
def test_check_config_names_a_file_it_cannot_read_in_one_line_with_status_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str) -> None:
    path = tmp_path / "gw.toml"
    if kind == "directory":
        path.mkdir()
    elif kind == "not-toml":
        path.write_text("[gateway\n")
    code, out, err = _check_config(capsys, str(path))
    assert code == 2
    assert out == ""
    lines = _own_lines(err)
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"aurora-gateway check-config: {path}: ")
    assert lines[0].count(str(path)) == 1


@settings(max_examples=200, deadline=None)
@given(st.text())
def test_toml_strings_read_back_by_tomllib(text: str) -> None:
    assert tomllib.loads(f"k = {toml_string(text)}")["k"] == text


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.booleans(), st.integers(-2**63, 2**63 - 1),
                 st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=20),
                 st.lists(st.text(max_size=8), max_size=4),
                 st.dictionaries(st.text(max_size=6), st.integers(), max_size=3)))
def test_toml_values_read_back_by_tomllib(value: Any) -> None:
    assert tomllib.loads(f"k = {toml_value(value)}")["k"] == value


# -- --log-format json ------------------------------------------------------------------------

def _record(msg: str, *args: Any, exc: bool = False) -> logging.LogRecord:
    exc_info = None
    if exc:
        try:
            1 / 0  # noqa: B018
        except ZeroDivisionError:
            exc_info = sys.exc_info()
    return logging.LogRecord("aurora.test", logging.WARNING, __file__, 1, msg, args, exc_info)


def test_a_json_log_line_has_time_level_logger_message_and_the_exception() -> None:
    rec = _record("altitude %s m/s² %r", 12.5, "ünïcode", exc=True)
    line = JsonFormatter().format(rec)
    assert "\n" not in line and line.isascii()
    doc = json.loads(line)
    assert doc["level"] == "WARNING" and doc["logger"] == "aurora.test"
    assert doc["message"] == "altitude 12.5 m/s² 'ünïcode'"
    t = datetime.fromisoformat(doc["time"])
    assert t.utcoffset() is not None and abs(t.timestamp() - rec.created) < 0.001
    assert "ZeroDivisionError" in doc["exc"] and "Traceback" in doc["exc"]
    assert "exc" not in json.loads(JsonFormatter().format(_record("plain")))


def test_a_record_never_lands_inside_a_line_printed_in_two_writes() -> None:
    """print() writes a line's text, then its newline; a record logged from another thread
    between the two must come out as a line of its own."""
    r, w = os.pipe()
    stream = open(w, "w", encoding="utf-8", buffering=1)  # noqa: SIM115 - closed below
    handler = LineHandler(stream)
    handler.setFormatter(JsonFormatter())
    try:
        stream.write("aurora-gateway: sources sim")  # print's first write
        handler.emit(_record("link down"))
        stream.write("\n")
        stream.flush()
    finally:
        stream.close()
    with open(r, encoding="utf-8") as f:
        lines = f.read().splitlines()
    assert len(lines) == 2, lines
    assert "aurora-gateway: sources sim" in lines
    assert json.loads(next(ln for ln in lines if ln.startswith("{")))["message"] == "link down"


def test_a_line_handler_without_a_file_descriptor_writes_to_the_stream() -> None:
    buf = io.StringIO()
    handler = LineHandler(buf)
    handler.setFormatter(JsonFormatter())
    handler.emit(_record("one"))
    handler.emit(_record("two"))
    assert [json.loads(ln)["message"] for ln in buf.getvalue().splitlines()] == ["one", "two"]


def test_run_with_log_format_json_logs_one_json_object_a_line(tmp_path: Path) -> None:
    """A serial source whose device does not exist: the port engine logs a warning."""
    device = f"/nonexistent/ttyAURORA-{uuid.uuid4().hex[:8]}"
    r = subprocess.run([sys.executable, "-m", "gateway", "run", "--duration", "0.3",
                        "--log-format", "json", "--only", "console", "--status-interval", "0",
                        "--source", device], capture_output=True, text=True,
                       timeout=TIMEOUT_S, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    docs = [json.loads(line) for line in _own_lines(r.stderr)]  # every line: JSON
    assert docs, r.stderr
    # the command's own lines (the start line, the stop report) are objects too
    report = [d["message"] for d in docs if d["logger"] == "aurora-gateway.report"]
    assert report and re.match(r"aurora-gateway \S+: sources ", report[0]), report
    assert any(m.startswith("stopped after ") for m in report), report
    assert all(re.match(r"aurora-gateway \S+: sources |stopped after |dropped: |flight |"
                        r"crc errors: |recording: ", m) for m in report), report
    for doc in docs:
        assert {"time", "level", "logger", "message"} <= set(doc)
        assert datetime.fromisoformat(doc["time"]).utcoffset() is not None
        assert doc["level"] in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
    assert any(doc["level"] == "WARNING" and device in doc["message"] for doc in docs), docs


def test_a_bad_log_format_is_one_line_naming_the_flag(capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    assert cli.main(["run", "--log-format", "yaml", "--duration", "0"]) == cli.EXIT_USAGE
    lines = _own_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("aurora-gateway: --log-format"), lines
    assert "'json'" in lines[0]


# -- the systemd unit and the exit codes ------------------------------------------------------

def _unit() -> configparser.ConfigParser:
    unit = configparser.ConfigParser(interpolation=None, strict=False)
    unit.optionxform = str  # type: ignore[assignment,method-assign]
    unit.read_string(UNIT.read_text())
    return unit


def test_the_units_command_line_is_one_the_gateway_accepts() -> None:
    service = _unit()["Service"]
    argv = shlex.split(service["ExecStart"])
    assert argv[0] == "/opt/aurora-gateway/.venv/bin/aurora-gateway"
    args = cli.build_parser(backend_flags=False, plugin_command="").parse_args(argv[1:])
    assert args.command == "run"
    assert args.config == "/etc/aurora-gateway/gateway.toml"
    assert args.log_format == "json"


def test_the_unit_restarts_on_failure_but_not_on_a_bad_configuration() -> None:
    unit = _unit()
    service = unit["Service"]
    assert service["Type"] == "simple"
    assert service["Restart"] == "on-failure"
    assert service["RestartPreventExitStatus"].split() == [str(cli.EXIT_USAGE)]
    assert service["User"] and service["User"] != "root"
    assert "dialout" in service["SupplementaryGroups"].split()
    assert "PrivateDevices" not in service  # it would hide the serial ports
    assert "PYTHONUNBUFFERED" not in service.get("Environment", "")
    assert unit["Install"]["WantedBy"] == "multi-user.target"


def test_the_exit_codes_are_documented_in_the_readme_and_the_help() -> None:
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Service on a companion computer", 1)[1].split("\n## ", 1)[0]
    table = dict(re.findall(r"^\| (\d+) \| (.+) \|$", section, re.M))
    codes = {0, 1, cli.EXIT_USAGE, cli.EXIT_INTERRUPTED}
    assert {int(c) for c in table} == codes
    epilog = cli.build_parser(backend_flags=False, plugin_command="").format_help()
    for code in codes:
        assert re.search(rf"^  {code} +\S", epilog, re.M), code


# -- the configuration reference --------------------------------------------------------------

def test_the_configuration_reference_is_up_to_date() -> None:
    assert gen.main(["--check"]) == 0, "run .venv/bin/python tools/gen_config_reference.py"


def test_the_reference_check_notices_a_stale_file(tmp_path: Path) -> None:
    stale = tmp_path / "ref.md"
    stale.write_text(gen.OUTPUT.read_text().replace("| `link_timeout_s` |", "| `timeout` |"))
    assert gen.main(["--output", str(stale), "--check"]) == 1
    assert gen.main(["--output", str(stale)]) == 0
    assert gen.main(["--output", str(stale), "--check"]) == 0


def _ours(group: str) -> list[str]:
    return sorted({ep.name for ep in entry_points(group=group)
                   if ep.dist is not None and ep.dist.name == "aurora-gateway"})


def test_the_reference_has_every_key_of_every_registered_source_and_backend() -> None:
    text = gen.OUTPUT.read_text()
    sections = {"[gateway]": config.GATEWAY_SCHEMA}
    for name in _ours(registry.SOURCE_GROUP):
        sections[f'type = "{name}"'] = registry.load(registry.SOURCE_GROUP, name).CONFIG
    for name in _ours(registry.BACKEND_GROUP):
        sections[f"[backends.{name}]"] = registry.load(registry.BACKEND_GROUP, name).CONFIG
    parts = re.split(r"^##+ `(.+?)`.*$", text, flags=re.M)
    found = dict(zip(parts[1::2], parts[2::2], strict=True))
    assert set(found) >= set(sections), set(sections) - set(found)
    for title, schema in sections.items():
        for key, spec in schema.keys.items():
            row = re.search(rf"^\| `{key}` \| (.*) \|$", found[title], re.M)
            assert row, f"{title} misses {key}"
            if spec.default not in (config.REQUIRED, None):
                default = row.group(1).split(" | ")[1].strip("`").replace("\\|", "|")
                assert tomllib.loads(f"k = {default}")["k"] == spec.default, (title, key)


def test_json_logs_carry_the_status_lines_as_objects_too() -> None:
    """journald / Loki get nothing but JSON: the per-second status lines included."""
    r = subprocess.run([sys.executable, "-m", "gateway", "run", "--duration", "1.3",
                        "--log-format", "json", "--only", "console", "--status-interval", "0.5"],
                       capture_output=True, text=True, timeout=TIMEOUT_S, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    docs = [json.loads(line) for line in _own_lines(r.stderr)]
    status = [d for d in docs if d["message"].startswith("[")]
    assert status and all(d["logger"] == "aurora-gateway.report" and d["level"] == "INFO"
                          for d in status), docs


def test_a_json_log_has_its_figures_as_fields_and_one_stop_object() -> None:
    """The start line names sources and vehicles, each status line carries its counters, a
    link change is a line of its own, and the stop report is ONE object holding the summary
    (the plain report's lines under ``report``)."""
    r = subprocess.run([sys.executable, "-m", "gateway", "run", "--duration", "1.6",
                        "--log-format", "json", "--only", "console", "--status-interval", "0.5",
                        "--source", "alpha=sim", "--source", "beta=sim", "--sim-speed", "5"],
                       capture_output=True, text=True, timeout=TIMEOUT_S, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    docs = [json.loads(line) for line in _own_lines(r.stderr)]
    events = [d.get("event") for d in docs if d["logger"] == "aurora-gateway.report"]
    # (a link may come up before the start line is written: the sources start first)
    assert events.count("start") == 1 and events.index("start") < events.index("status")
    assert events[-1] == "stop" and events.count("stop") == 1, events
    start = docs[[d.get("event") for d in docs].index("start")]
    assert start["sources"] == [{"name": "alpha", "vehicle": "alpha"},
                                {"name": "beta", "vehicle": "beta"}]
    links = [d for d in docs if d.get("event") == "link"]
    assert {(d["vehicle"], d["up"]) for d in links} == {("alpha", True), ("beta", True)}
    status = [d for d in docs if d.get("event") == "status"]
    assert status and all(d["links"] == {"alpha": True, "beta": True} for d in status[1:])
    last = status[-1]
    assert sum(last["messages_in"].values()) > 0 and last["backends"]["console"]["sent"] > 0
    stop = docs[-1]
    assert stop["event"] == "stop" and stop["message"].startswith("stopped after ")
    assert set(stop["summary"]["flights"]) == {"alpha", "beta"}
    assert any(line.startswith("flight alpha: ") for line in stop["report"]), stop["report"]
    assert "dropped: nothing" in stop["report"]
