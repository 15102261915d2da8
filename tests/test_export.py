"""``aurora-gateway export``: a recording of the simulated flight comes back
as CSV and JSON lines with the values the wire decoder gives, one row per SM update, in the
documented columns; errors are one line; a closed pipe is quiet."""

from __future__ import annotations

import csv
import io
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from gateway import recording
from gateway.commands.cli import main
from gateway.flight import FlightModel, FlightProfile
from gateway.model import SmUpdate, Status
from gateway.sources.sim import flight_messages
from gateway.wire import decode_all, encode

T0 = 1_790_000_000.25  # the recording's first receive time (Unix seconds)
CONSOLE = Path(sys.executable).with_name("aurora-gateway")

# The documented columns, in order (the export's contract, written out here on purpose).
DOCUMENTED = ["t_s", "rx_time", "vehicle", "timestamp_ms", "state", "state_name", "armed",
              "sm_type", "altitude_m", "velocity_mps", "acceleration_mps2", "accel_vert_mps2",
              "roll_deg", "pitch_deg", "yaw_deg", "imu_ok", "baro_ok", "calibrated",
              "log_ready"]
# STATUS flag bits (shared/specs/aurora-wire.md): armed 0x01, IMU 0x02, baro 0x04,
# calibrated 0x08, log ready 0x10.
FLAG_BITS = {"imu_ok": 0x02, "baro_ok": 0x04, "calibrated": 0x08, "log_ready": 0x10}


def _messages(revision: int) -> list[tuple[float, SmUpdate | Status]]:
    """One simulated flight; no STATUS in the first 1.5 s, and the later ones carrying every
    combination of the health flags in turn (the simulator's are all healthy)."""
    out: list[tuple[float, SmUpdate | Status]] = []
    n = 0
    model = FlightModel(FlightProfile(revision=revision))
    for t, msg in flight_messages(model, rate_hz=10.0, status_hz=1.0, cycles=1):
        if isinstance(msg, Status):
            if t < 1.5:
                continue
            msg = msg._replace(flags=(msg.flags & 0x01) | ((n % 16) << 1))
            n += 1
        out.append((t, msg))
    return out


def _write(path: Path, msgs: list[tuple[float, Any]]) -> list[tuple[float, Any]]:
    """Write the messages' frames as a recording; (receive time, decoded message) back."""
    decoded = []
    with path.open("wb") as f:
        f.write(recording.HEADER)
        for t, msg in msgs:
            frame = encode(msg)
            f.write(recording.encode_record(T0 + t, frame))
            (back,) = decode_all(frame)
            decoded.append((T0 + t, back))
    return decoded


def _expected(decoded: list[tuple[float, Any]], vehicle: str) -> list[dict[str, Any]]:
    """The rows the export should give, computed here from the decoded messages of one
    ``vehicle``."""
    rows = []
    flags: int | None = None
    for t, msg in decoded:
        if isinstance(msg, Status):
            flags = msg.flags
            continue
        health = {k: (None if flags is None else bool(flags & bit))
                  for k, bit in FLAG_BITS.items()}
        rows.append({"t": t - T0, "rx": t, "vehicle": vehicle, "msg": msg, **health})
    return rows


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[dict[str, Any]]]:
    path = tmp_path_factory.mktemp("export") / "flight.aur"
    # frames with no vehicle (as a version 1 recording's): named after the file
    return path, _expected(_write(path, _messages(64)), "flight")


def _check_row(got: dict[str, Any], exp: dict[str, Any], parse: Any) -> None:
    """``parse(column, cell)`` turns a cell into a Python value (None for empty/null)."""
    m: SmUpdate = exp["msg"]
    assert parse("t_s", got["t_s"]) == pytest.approx(exp["t"], abs=1e-6)
    assert parse("rx_time", got["rx_time"]) == exp["rx"]
    assert got["vehicle"] == exp["vehicle"]
    for col in ("timestamp_ms", "state", "sm_type"):
        assert parse(col, got[col]) == getattr(m, col)
    assert got["state_name"] == m.state_name
    assert parse("armed", got["armed"]) is m.armed
    for col in ("altitude_m", "velocity_mps", "acceleration_mps2", "accel_vert_mps2"):
        assert parse(col, got[col]) == getattr(m, col)  # shortest round-trip form: exact
    for col, rad in (("roll_deg", m.roll_rad), ("pitch_deg", m.pitch_rad),
                     ("yaw_deg", m.yaw_rad)):
        assert math.radians(parse(col, got[col])) == pytest.approx(rad, rel=1e-12, abs=1e-12)
    for col in FLAG_BITS:
        assert parse(col, got[col]) is exp[col], col


def _csv_value(col: str, cell: str) -> Any:
    if col == "vehicle":
        return cell
    if cell == "":
        return None
    if col in ("armed", *FLAG_BITS):
        assert cell in ("0", "1")
        return cell == "1"
    if col in ("timestamp_ms", "state", "sm_type"):
        return int(cell)
    return float(cell)


def _json_value(col: str, value: Any) -> Any:
    return value


def _strict_json(line: str) -> dict[str, Any]:
    def refuse(name: str) -> None:
        raise AssertionError(f"non-standard JSON constant {name}")
    obj: dict[str, Any] = json.loads(line, parse_constant=refuse)
    return obj


def test_csv_round_trips_every_update_to_stdout(flight: tuple[Path, list[dict[str, Any]]],
                                                capsys: pytest.CaptureFixture[str]) -> None:
    path, expected = flight
    assert main(["export", str(path)]) == 0
    out, err = capsys.readouterr()
    reader = csv.DictReader(io.StringIO(out))
    assert reader.fieldnames == DOCUMENTED
    rows = list(reader)
    assert len(rows) == len(expected) > 1000
    for got, exp in zip(rows, expected, strict=True):
        _check_row(got, exp, _csv_value)
    assert rows[0]["imu_ok"] == "" and rows[-1]["imu_ok"] in ("0", "1")  # before/after STATUS
    assert f"{len(expected)} SM updates" in err


def test_jsonl_round_trips_every_update_to_a_file(
        flight: tuple[Path, list[dict[str, Any]]], tmp_path: Path) -> None:
    path, expected = flight
    out = tmp_path / "out.txt"
    assert main(["export", str(path), "--format", "jsonl", "-o", str(out)]) == 0
    lines = out.read_text().splitlines()
    assert len(lines) == len(expected)
    for line, exp in zip(lines, expected, strict=True):
        got = _strict_json(line)
        assert list(got) == DOCUMENTED
        _check_row(got, exp, _json_value)


def test_the_format_follows_the_output_file_unless_given(
        flight: tuple[Path, list[dict[str, Any]]], tmp_path: Path) -> None:
    path = flight[0]
    assert main(["export", str(path), "-o", str(tmp_path / "a.jsonl")]) == 0
    assert _strict_json((tmp_path / "a.jsonl").read_text().splitlines()[0])["state"] == 0
    assert main(["export", str(path), "-o", str(tmp_path / "a.csv")]) == 0
    assert (tmp_path / "a.csv").read_text().splitlines()[0] == ",".join(DOCUMENTED)
    assert main(["export", str(path), "-f", "csv", "-o", str(tmp_path / "b.json")]) == 0
    assert (tmp_path / "b.json").read_text().startswith("t_s,")


def test_the_f32_revision_exports_its_own_values(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "f32.aur"
    expected = _expected(_write(path, _messages(36)), "f32")
    assert {r["msg"].payload_len for r in expected} == {36}
    assert main(["export", str(path), "-o", "-"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert len(rows) == len(expected)
    for got, exp in zip(rows, expected, strict=True):
        _check_row(got, exp, _csv_value)


def test_non_finite_values_are_null_in_jsonl_and_readable_in_csv(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    msg = SmUpdate(timestamp_ms=5, state=2, armed=True, sm_type=0, altitude_m=math.nan,
                   acceleration_mps2=math.inf, accel_vert_mps2=-math.inf, velocity_mps=1.5,
                   roll_rad=0.0, pitch_rad=math.nan, yaw_rad=0.25)
    path = tmp_path / "odd.aur"
    _write(path, [(0.0, msg)])
    assert main(["export", str(path), "-f", "jsonl"]) == 0
    (line,) = capsys.readouterr().out.splitlines()
    got = _strict_json(line)
    assert (got["altitude_m"], got["acceleration_mps2"], got["accel_vert_mps2"],
            got["pitch_deg"]) == (None, None, None, None)
    assert got["velocity_mps"] == 1.5 and got["yaw_deg"] == pytest.approx(math.degrees(0.25))
    assert main(["export", str(path), "-f", "csv"]) == 0
    (row,) = csv.DictReader(io.StringIO(capsys.readouterr().out))
    assert math.isnan(float(row["altitude_m"]))
    assert float(row["acceleration_mps2"]) == math.inf
    assert float(row["accel_vert_mps2"]) == -math.inf


def test_a_torn_tail_is_skipped_and_reported(flight: tuple[Path, list[dict[str, Any]]],
                                             tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    src, expected = flight
    path = tmp_path / "torn.aur"
    path.write_bytes(src.read_bytes() + b"\x01\x02\x03\x04\x05")
    assert main(["export", str(path)]) == 0
    out, err = capsys.readouterr()
    assert len(out.splitlines()) == len(expected) + 1
    assert "torn tail 5 bytes" in err


@pytest.mark.parametrize("content", [None, b"", b"not a recording at all\n",
                                     b"\x89AUR\r\n\x1a\n\x07\x00\x00\x00"])
def test_a_missing_or_invalid_recording_is_one_line_and_status_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes | None) -> None:
    path = tmp_path / "bad.aur"
    if content is not None:
        path.write_bytes(content)
    assert main(["export", str(path)]) == 2  # bad input, as for replay and decode (issue 23)
    out, err = capsys.readouterr()
    assert out == ""
    assert len(err.splitlines()) == 1
    assert err.startswith("aurora-gateway export: ") and str(path) in err


def test_an_unwritable_output_is_one_line_and_status_1(
        flight: tuple[Path, list[dict[str, Any]]], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "no" / "such" / "dir.csv"
    assert main(["export", str(flight[0]), "-o", str(target)]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "cannot write" in err and str(target) in err


def test_an_unknown_format_is_a_usage_error(flight: tuple[Path, list[dict[str, Any]]],
                                            capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["export", str(flight[0]), "--format", "xlsx"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "xlsx" in err


def test_the_console_script_stops_quietly_when_the_pipe_closes(
        flight: tuple[Path, list[dict[str, Any]]]) -> None:
    """`aurora-gateway export … | head -1`: the reader goes after one line; the export (far
    more than a pipe's buffer) must end with status 0 and no traceback."""
    path, expected = flight
    proc = subprocess.Popen([str(CONSOLE), "export", str(path), "--format", "jsonl"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout is not None and proc.stderr is not None
    try:
        first = proc.stdout.readline()
        proc.stdout.close()
        err = proc.stderr.read().decode()
        rc = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert json.loads(first)["timestamp_ms"] == expected[0]["msg"].timestamp_ms
    assert rc == 0, err
    assert "Traceback" not in err and "BrokenPipe" not in err
