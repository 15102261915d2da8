"""``aurora-gateway export RECORDING``: a recording's messages as a table, or the whole flight
as an MCAP file.

One row per SM_UPDATE in the recording, in recording order, for spreadsheets and pandas (and
one per position, battery, vehicle state … when the recording holds any: below)::

    aurora-gateway export flight.aur > flight.csv
    aurora-gateway export flight.aur --format jsonl -o flight.jsonl

Or the decoded flight on the Foxglove backend's channels, per vehicle
(``/aurora/<vehicle>/state``, ``…/altitude``, ``…/attitude`` as a
``foxglove.FrameTransform``, ``…/status``) and link up/down on ``/aurora/link_events``, JSON
with JSON schemas, stamped with the receive times, for Foxglove or any MCAP tool (see
:mod:`gateway.commands.export_mcap`)::

    aurora-gateway export flight.aur -o flight.mcap

A recording of several vehicles gives every vehicle's rows (the ``vehicle`` column says
whose); ``--vehicle NAME`` keeps one (a name the recording does not have: one line naming
the vehicles it has, exit status 2).  A version 1 recording's frames name no vehicle: their
vehicle is named after the file (:func:`gateway.recording.file_vehicle`).

Or the flight as a rosbag2 bag for ``ros2 bag play`` — a new directory with ``metadata.yaml``
and MCAP storage, the live ``ros2`` backend's topics and CDR (:mod:`backends.ros2.rosbag2`;
the ``ros2`` extra)::

    aurora-gateway export flight.aur --format rosbag2 -o flight_bag

The recording itself stays the lossless format (every frame as received); the MCAP is a view.

Columns (the same names, in this order, in both formats):

=====================  =============================================================
``t_s``                receive time, seconds since the recording's first record (to 1 µs)
``rx_time``            receive time, seconds since the Unix epoch (what was recorded)
``vehicle``            the vehicle the update is about
``timestamp_ms``       the flight computer's uptime in the update, ms
``state``              state number
``state_name``         its name under ``sm_type`` (``STATE_<n>`` when unknown)
``armed``              armed flag of the update
``sm_type``            state machine type
``altitude_m``         altitude above the pad, m
``velocity_mps``       vertical speed, up positive, m/s
``acceleration_mps2``  magnitude of the specific force (about g at rest), m/s²
``accel_vert_mps2``    its signed component along the body axis, m/s²
``roll_deg``           roll, degrees (converted from the update's radians)
``pitch_deg``          pitch, degrees
``yaw_deg``            yaw, degrees
``imu_ok``             the vehicle's latest STATUS at or before the row: IMU healthy
``baro_ok``            … barometer healthy
``calibrated``         … sensors calibrated
``log_ready``          … flight log ready
=====================  =============================================================

The four health flags are empty (CSV) or ``null`` (JSONL) until the vehicle's first
STATUS.

**Every other kind.**  A recording that holds positions, batteries, vehicle states, RC
channels, link statistics or link events (a MAVLink vehicle's, see
:mod:`gateway.recording`) gives one row per such message too, in recording order, in the same
table: its columns are then ``t_s``, ``rx_time``, ``vehicle``, ``kind`` (``sm_update``,
``position``, ``battery``, ``vehicle_state``, ``rc_channels``, ``link_stats``, ``link``),
``source`` (the gateway source it came from), the SM_UPDATE columns above when there are
SM updates, then the columns of each kind present, in this order (a row leaves the columns
of other kinds empty; ``armed``, the attitude and ``altitude_m`` are shared)::

    position       lat, lon (WGS-84 degrees), alt_amsl (m above mean sea level),
                   relative_alt (m above home), ground_speed (m/s), course (degrees),
                   satellites, fix_type
    battery        voltage (V), current (A), consumed (mAh), remaining (%), battery_id
    vehicle_state  armed, mode (the autopilot's mode name), custom_mode, roll_deg,
                   pitch_deg, yaw_deg, altitude_m, climb (m/s, up positive)
    rc_channels    channels (µs; CSV: space-separated, ``-`` for a channel not sent; JSONL:
                   a list with null), seq
    link_stats     rssi_dbm, link_quality_pct, snr_db, tx_power_mw, downlink_rssi_dbm,
                   downlink_link_quality_pct, downlink_snr_db, rf_mode, antenna
    link           link_source, up, silence_s

A recording of SM updates only (every recording of earlier versions) exports exactly the
columns of the table above, as before.  ``--kind KIND`` (repeatable) keeps the rows of those
kinds (one CSV per kind: ``--kind position -o positions.csv``); a kind no row has gives the
header alone.  A recorded frame of an unknown type (a RawFrame) has no row: it is counted on
stderr as skipped, never silently.

Floats are written in Python's shortest round-trip form, so reading a cell back gives
exactly the value the gateway decoded (degrees excepted: they are converted).

CSV: a header row, then one row per update, ``\\n`` line ends; booleans as ``1``/``0``;
non-finite floats as ``nan``/``inf``/``-inf`` (which ``float()`` and pandas read back).
JSONL: one JSON object per line; booleans as ``true``/``false``; non-finite floats as
``null`` (JSON has no NaN).  The format defaults to JSONL when ``-o`` names a ``.jsonl``,
``.ndjson`` or ``.json`` file, to MCAP when it names a ``.mcap`` file, else CSV.  An MCAP
export needs ``-o FILE``: to stdout it is refused with one line and exit status 2.

A missing, unreadable or empty file, or one that is not a recording, is one line on stderr
and exit status 2, as for ``replay`` and ``decode`` (bad input: :mod:`gateway.exits`); so is
an MCAP export without the ``mcap`` extra.  A file that cannot be written: exit status 1.
Records that fail their CRC are skipped (as ``decode`` and ``replay`` do) and
counted on stderr.  A closed pipe (``| head``) ends the export quietly.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from gateway import __version__, exits, recording
from gateway.model import (
    Battery,
    LinkEvent,
    LinkStats,
    Position,
    RcChannels,
    SmUpdate,
    Status,
    VehicleState,
    kind,
)
from gateway.wire import Decoder

EXIT_FAILURE = exits.FAILED
EXIT_USAGE = exits.USAGE

#: The export's columns, in order (see the module docstring for their meaning).
COLUMNS: tuple[str, ...] = (
    "t_s", "rx_time", "vehicle", "timestamp_ms", "state", "state_name", "armed", "sm_type",
    "altitude_m", "velocity_mps", "acceleration_mps2", "accel_vert_mps2",
    "roll_deg", "pitch_deg", "yaw_deg",
    "imu_ok", "baro_ok", "calibrated", "log_ready",
)
#: The columns taken from the latest STATUS (None before the first one).
HEALTH_COLUMNS: tuple[str, ...] = ("imu_ok", "baro_ok", "calibrated", "log_ready")
#: The columns every row has when the export holds other kinds than SM updates.
COMMON_COLUMNS: tuple[str, ...] = ("t_s", "rx_time", "vehicle", "kind", "source")
#: The columns of each kind besides SM_UPDATE (the module docstring says what they hold).
KIND_COLUMNS: dict[str, tuple[str, ...]] = {
    "position": ("lat", "lon", "alt_amsl", "relative_alt", "ground_speed", "course",
                 "satellites", "fix_type"),
    "battery": ("voltage", "current", "consumed", "remaining", "battery_id"),
    "vehicle_state": ("armed", "mode", "custom_mode", "roll_deg", "pitch_deg", "yaw_deg",
                      "altitude_m", "climb"),
    "rc_channels": ("channels", "seq"),
    "link_stats": ("rssi_dbm", "link_quality_pct", "snr_db", "tx_power_mw",
                   "downlink_rssi_dbm", "downlink_link_quality_pct", "downlink_snr_db",
                   "rf_mode", "antenna"),
    "link": ("link_source", "up", "silence_s"),
}
#: The kinds ``--kind`` takes: the ones with rows.
ROW_KINDS: tuple[str, ...] = ("sm_update", *KIND_COLUMNS)
FORMATS = ("csv", "jsonl", "mcap", "tlog", "rosbag2")
_JSONL_SUFFIXES = (".jsonl", ".ndjson", ".json")
_MCAP_SUFFIXES = (".mcap",)
_TLOG_SUFFIXES = (".tlog",)

_COLUMN_HELP = (
    "columns: t_s (s since the first record), rx_time (Unix s), vehicle, timestamp_ms, "
    "state, state_name, armed, sm_type, altitude_m, velocity_mps, acceleration_mps2, "
    "accel_vert_mps2, roll_deg, pitch_deg, yaw_deg, and the vehicle's latest STATUS's imu_ok, "
    "baro_ok, calibrated, log_ready (empty/null before its first STATUS). CSV: header row, "
    "booleans 1/0. JSONL: one object a line, NaN as null. MCAP (needs -o FILE): each "
    "vehicle's flight on the channels /aurora/VEHICLE/state, …/altitude, …/attitude "
    "(foxglove.FrameTransform), …/status, and /aurora/link_events, JSON with JSON schemas, "
    "log time = receive time.")


class ExportError(Exception):
    """A recording that cannot be exported; the text is the one-line message."""


@dataclass
class Flight:
    """What :func:`load` found in a recording: the rows and the counts behind them."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    #: every decoded message (RawFrame included) and every message record's message, with
    #: its receive time, in recording order
    messages: list[tuple[float, Any]] = field(default_factory=list)
    statuses: int = 0
    other_frames: int = 0
    #: the rows of each kind (``sm_update``, ``position`` …)
    kinds: Counter[str] = field(default_factory=Counter)
    #: the vehicles exported, in the order they first appear
    vehicles: list[str] = field(default_factory=list)
    read_stats: recording.ReadStats = field(default_factory=recording.ReadStats)

    def notes(self) -> str:
        """The recording's damage in words, or "" when it was intact."""
        s = self.read_stats
        if not (s.torn_tail_bytes or s.corrupt_skips):
            return ""
        return (f"torn tail {s.torn_tail_bytes} bytes, {s.corrupt_skips} corrupt stretches "
                f"({s.bytes_skipped} bytes) skipped")


def row_of(t_s: float, rx_time: float, msg: SmUpdate,
           health: dict[str, bool] | None) -> dict[str, Any]:
    """The export row of one update received at ``rx_time`` (``t_s`` after the first
    record), with the health flags of its vehicle's latest STATUS (``health``; None before
    any)."""
    return {
        "t_s": t_s,
        "rx_time": rx_time,
        "vehicle": msg.vehicle,
        "timestamp_ms": msg.timestamp_ms,
        "state": msg.state,
        "state_name": msg.state_name,
        "armed": bool(msg.armed),
        "sm_type": msg.sm_type,
        "altitude_m": msg.altitude_m,
        "velocity_mps": msg.velocity_mps,
        "acceleration_mps2": msg.acceleration_mps2,
        "accel_vert_mps2": msg.accel_vert_mps2,
        "roll_deg": math.degrees(msg.roll_rad),
        "pitch_deg": math.degrees(msg.pitch_rad),
        "yaw_deg": math.degrees(msg.yaw_rad),
        **{k: (None if health is None else health[k]) for k in HEALTH_COLUMNS},
    }


def _deg(v: float | None) -> float | None:
    return None if v is None else math.degrees(v)


def message_row(t_s: float, rx_time: float, msg: Any, source: str) -> dict[str, Any] | None:
    """The export row of a message of a kind besides SM_UPDATE (see :data:`KIND_COLUMNS`),
    None for a kind with no row."""
    row: dict[str, Any] = {"t_s": t_s, "rx_time": rx_time, "vehicle": msg.vehicle,
                           "kind": kind(msg), "source": source}
    if isinstance(msg, Position):
        row.update(lat=msg.lat_deg, lon=msg.lon_deg, alt_amsl=msg.alt_amsl_m,
                   relative_alt=msg.relative_alt_m, ground_speed=msg.ground_speed_mps,
                   course=msg.course_deg, satellites=msg.satellites, fix_type=msg.fix_type)
    elif isinstance(msg, Battery):
        row.update(voltage=msg.voltage_v, current=msg.current_a, consumed=msg.consumed_mah,
                   remaining=msg.remaining_pct, battery_id=msg.battery_id)
    elif isinstance(msg, VehicleState):
        row.update(armed=bool(msg.armed), mode=msg.mode, custom_mode=msg.custom_mode,
                   roll_deg=_deg(msg.roll_rad), pitch_deg=_deg(msg.pitch_rad),
                   yaw_deg=_deg(msg.yaw_rad), altitude_m=msg.altitude_m, climb=msg.climb_mps)
    elif isinstance(msg, RcChannels):
        row.update(channels=list(msg.channels_us), seq=msg.seq)
    elif isinstance(msg, LinkStats):
        row.update(msg.fields())
    elif isinstance(msg, LinkEvent):
        row.update(link_source=msg.source, up=msg.up, silence_s=msg.silence_s)
    else:
        return None
    return row


def columns_of(rows: list[dict[str, Any]], only: list[str] | None = None) -> tuple[str, ...]:
    """The columns of an export of ``rows`` (of the kinds ``only``, when given: ``--kind``):
    :data:`COLUMNS` when they are SM updates only (or none), else :data:`COMMON_COLUMNS`,
    the SM_UPDATE columns if any, and the columns of each kind present."""
    kinds = set(only) if only else {r.get("kind", "sm_update") for r in rows}
    if kinds <= {"sm_update"}:
        return COLUMNS
    cols = dict.fromkeys(COMMON_COLUMNS)
    if "sm_update" in kinds:
        cols.update(dict.fromkeys(COLUMNS))
    for k, kcols in KIND_COLUMNS.items():
        if k in kinds:
            cols.update(dict.fromkeys(kcols))
    return tuple(cols)


class UnknownVehicle(ExportError):
    """``--vehicle`` names a vehicle the recording does not have (a usage error)."""


def load(path: str | Path, vehicle: str | None = None) -> Flight:
    """Read the recording at ``path`` into export rows (every kind's), of ``vehicle`` only
    if given.
    :class:`ExportError` (one line) when it is missing, unreadable or not a recording of a
    version this gateway reads; :class:`UnknownVehicle` when it has no such vehicle."""
    try:
        recording.check_file(path)
        flight = Flight()
        records = recording.name_unnamed(
            recording.read_records(path, flight.read_stats, messages=True),
            recording.file_vehicle(path))
    except ValueError as exc:  # RecordingError included
        raise ExportError(str(exc)) from None
    except OSError as exc:
        raise ExportError(f"cannot read {path}: {exc.strerror or exc}") from None
    t0 = records[0].t if records else 0.0  # the first record of any vehicle
    try:
        records = recording.only_vehicle(records, vehicle, path)
    except ValueError as exc:
        raise UnknownVehicle(str(exc)) from None
    flight.vehicles = recording.vehicles_in(records)
    decoder = Decoder()
    health: dict[str, dict[str, bool]] = {}  # per vehicle: its latest STATUS's flags
    for rec in records:
        t, name, source = rec.t, rec.vehicle, rec.source
        if isinstance(rec, recording.MessageRecord):
            flight.messages.append((t, rec.message))
            row = message_row(round(t - t0, 6), t, rec.message, source)
            if row is not None:
                flight.rows.append(row)
                flight.kinds[row["kind"]] += 1
            continue
        decoder.vehicle = name
        for msg in decoder.feed(rec.frame):
            if source:
                msg = msg._replace(origin=source)
            flight.messages.append((t, msg))
            if isinstance(msg, SmUpdate):
                row = row_of(round(t - t0, 6), t, msg, health.get(name))
                row["kind"], row["source"] = "sm_update", source  # (for a mixed export)
                flight.rows.append(row)
                flight.kinds["sm_update"] += 1
            elif isinstance(msg, Status):
                flight.statuses += 1
                health[name] = msg.health()
            else:
                flight.other_frames += 1
    return flight


def only_kinds(rows: list[dict[str, Any]], kinds: list[str] | None) -> list[dict[str, Any]]:
    """The rows of ``kinds`` (None: all)."""
    if not kinds:
        return rows
    wanted = set(kinds)
    return [r for r in rows if r.get("kind", "sm_update") in wanted]


# -- writers -------------------------------------------------------------------------------------

def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, bool):
        return 1 if v else 0
    if isinstance(v, float):
        return repr(v)  # shortest round trip; nan, inf, -inf for the non-finite
    return v


def _csv_value(v: Any) -> Any:
    if isinstance(v, list):  # RC channels
        return " ".join("-" if c is None else str(c) for c in v)
    return _csv_cell(v)


def write_csv(rows: list[dict[str, Any]], out: TextIO,
              columns: tuple[str, ...] | None = None) -> None:
    """The rows as CSV with a header row (``columns``: default :func:`columns_of`)."""
    cols = columns_of(rows) if columns is None else columns
    w = csv.writer(out, lineterminator="\n")
    w.writerow(cols)
    for row in rows:
        w.writerow([_csv_value(row.get(c)) for c in cols])


def _json_value(v: Any) -> Any:
    if isinstance(v, list):
        return [_json_value(c) for c in v]
    return None if isinstance(v, float) and not math.isfinite(v) else v


def write_jsonl(rows: list[dict[str, Any]], out: TextIO,
                columns: tuple[str, ...] | None = None) -> None:
    """The rows as JSON lines (non-finite floats as null: strict JSON; ``columns``: default
    :func:`columns_of`)."""
    cols = columns_of(rows) if columns is None else columns
    for row in rows:
        out.write(json.dumps({c: _json_value(row.get(c)) for c in cols}, allow_nan=False))
        out.write("\n")


WRITERS: dict[str, Callable[[list[dict[str, Any]], TextIO, tuple[str, ...] | None], None]] = {
    "csv": write_csv, "jsonl": write_jsonl}


# -- the command ---------------------------------------------------------------------------------

def add_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``export`` to the ``aurora-gateway`` subcommands."""
    p = subparsers.add_parser(
        "export", help="write a recording's SM updates as CSV or JSON lines, or as MCAP",
        description="Write one row per SM_UPDATE of a recording, for spreadsheets and "
                    "pandas, or the flight as an MCAP file for Foxglove. " + _COLUMN_HELP)
    p.add_argument("recording", metavar="RECORDING", help="the recording (.aur)")
    p.add_argument("--format", "-f", choices=FORMATS, default=None,
                   help="csv, jsonl, mcap, tlog (a MAVLink telemetry log) or rosbag2 (a new "
                        "directory -o DIR for ros2 bag play; the ros2 extra); default: jsonl "
                        "for a .jsonl/.ndjson/.json -o file, mcap for .mcap, tlog for .tlog, "
                        "else csv")
    p.add_argument("-o", "--output", metavar="FILE", default="-",
                   help="file to write; - = stdout (default)")
    p.add_argument("--vehicle", metavar="NAME",
                   help="this vehicle's rows only (default: every vehicle's)")
    p.add_argument("--kind", action="append", choices=ROW_KINDS, metavar="KIND",
                   help="csv/jsonl: this kind's rows only (repeatable; "
                        f"{', '.join(ROW_KINDS)}; default: every kind's)")
    p.set_defaults(handler=run_export)
    return p


def _format_of(args: argparse.Namespace) -> str:
    if args.format:
        return str(args.format)
    suffix = Path(args.output).suffix.lower() if args.output != "-" else ""
    if suffix in _JSONL_SUFFIXES:
        return "jsonl"
    if suffix in _MCAP_SUFFIXES:
        return "mcap"
    if suffix in _TLOG_SUFFIXES:
        return "tlog"
    return "csv"


def _quiet_stdout() -> None:
    """After a closed pipe: point stdout at /dev/null, so the interpreter's last flush of
    what is still buffered does not fail (and print) again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # no real stdout (a test's capture): nothing to flush
        pass


def run_export(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """The ``export`` handler; returns the exit status.  ``out`` replaces stdout (tests)."""
    err = sys.stderr
    fmt = _format_of(args)
    if fmt in ("mcap", "tlog", "rosbag2") and args.output == "-":
        what = {"mcap": "an MCAP file", "tlog": "a telemetry log",
                "rosbag2": "a rosbag2 bag"}[fmt]
        target = "-o DIR (a new directory)" if fmt == "rosbag2" else "-o FILE"
        print(f"aurora-gateway export: {what} is written with {target}, not to stdout",
              file=err)
        return EXIT_USAGE
    if fmt == "rosbag2":
        from backends.ros2 import rosbag2  # (rosbags itself only when it writes)
        try:
            rosbag2.check_target(args.output)
        except rosbag2.BagError as exc:
            print(f"aurora-gateway export: -o: {exc}", file=err)
            return EXIT_USAGE
    try:
        flight = load(args.recording, args.vehicle)
    except ExportError as exc:
        print(f"aurora-gateway export: {exc}", file=err)
        return EXIT_USAGE  # a missing, empty or foreign file, or a vehicle it does not have
    if fmt == "mcap":
        return _run_mcap(args, flight)
    if fmt == "tlog":
        return _run_tlog(args, flight)
    if fmt == "rosbag2":
        return _run_rosbag2(args, flight)
    to_stdout = args.output == "-"
    stream = out if out is not None else sys.stdout
    kinds = getattr(args, "kind", None)
    rows = only_kinds(flight.rows, kinds)
    columns = columns_of(rows, kinds)
    try:
        if to_stdout:
            WRITERS[fmt](rows, stream, columns)
            stream.flush()
        else:
            with open(args.output, "w", encoding="utf-8", newline="") as f:
                WRITERS[fmt](rows, f, columns)
    except BrokenPipeError:
        if to_stdout and out is None:
            _quiet_stdout()
        return 0
    except OSError as exc:
        print(f"aurora-gateway export: cannot write {args.output}: {exc.strerror or exc}",
              file=err)
        return EXIT_FAILURE
    where = "stdout" if to_stdout else args.output
    notes = flight.notes()
    print(f"aurora-gateway export: {flight.kinds['sm_update']} SM updates ({flight.statuses} "
          f"STATUS){_other_kinds(flight, rows)} of {_vehicles(flight)} as {fmt} to {where}"
          + _skipped(flight) + (f"; {notes}" if notes else ""), file=err)
    return 0


def _other_kinds(flight: Flight, rows: list[dict[str, Any]]) -> str:
    """``, position 40, battery 4`` (the rows of other kinds), and the rows a ``--kind``
    left out."""
    text = "".join(f", {k} {n}" for k, n in flight.kinds.items() if k != "sm_update")
    if len(rows) != len(flight.rows):
        text += f" ({len(flight.rows) - len(rows)} rows of other kinds left out: --kind)"
    return text


def _skipped(flight: Flight) -> str:
    """What the table cannot show, counted: frames of no known type."""
    return (f"; skipped {flight.other_frames} frames of no known type (raw)"
            if flight.other_frames else "")



def _vehicles(flight: Flight) -> str:
    n = len(flight.vehicles)
    return (f"vehicle {flight.vehicles[0]}" if n == 1 else
            f"{n} vehicles ({', '.join(flight.vehicles)})" if n else "no vehicle")


def _run_mcap(args: argparse.Namespace, flight: Flight) -> int:
    """Write ``flight`` as MCAP to ``args.output``; the exit status."""
    # the mcap library only when asked for; without it the command line names the extra,
    # exit 2 (gateway.registry)
    from gateway.commands import export_mcap
    name = Path(args.recording).name
    try:
        with open(args.output, "wb") as f:
            written = export_mcap.write(
                flight.messages, f, source=f"replay:{name}",
                metadata={"recording": name, "records": str(flight.read_stats.records),
                          "vehicles": ",".join(flight.vehicles)},
                vehicles=flight.vehicles)
    except OSError as exc:
        print(f"aurora-gateway export: cannot write {args.output}: {exc.strerror or exc}",
              file=sys.stderr)
        return EXIT_FAILURE
    topics = ", ".join(f"{t} {n}" for t, n in written.counts.items())
    notes = flight.notes()
    skipped = ", ".join(f"{k} {n}" for k, n in written.skipped.items())
    print(f"aurora-gateway export: {flight.kinds['sm_update']} SM updates ({flight.statuses} "
          f"STATUS) of {_vehicles(flight)} as mcap to {args.output}: "
          f"{topics or 'no messages'}" + (f"; skipped (no channel): {skipped}" if skipped else "")
          + (f"; {notes}" if notes else ""), file=sys.stderr)
    return 0


def _run_tlog(args: argparse.Namespace, flight: Flight) -> int:
    """Write ``flight`` as a MAVLink telemetry log to ``args.output`` (what the MAVLink
    backend would have sent live: :mod:`backends.mavlink.tlog_export`); the exit status."""
    from backends.mavlink import tlog_export
    try:
        with open(args.output, "wb") as f:
            written = tlog_export.write(flight.messages, f, flight.vehicles)
    except OSError as exc:
        print(f"aurora-gateway export: cannot write {args.output}: {exc.strerror or exc}",
              file=sys.stderr)
        return EXIT_FAILURE
    kinds = ", ".join(f"{k} {n}" for k, n in sorted(written.counts.items()))
    notes = flight.notes()
    fast = tlog_export.time_compression(flight.messages)
    if fast is not None:
        print(f"aurora-gateway export: note: this recording was made faster than real time "
              f"({fast[1]:.1f} s of flight received in {fast[0]:.1f} s): translated at the "
              "flight's own pace (its rate-limited streams, ATTITUDE, ALTITUDE …, as the "
              "backend sends a flight received in real time), frames stamped with their "
              "receive times", file=sys.stderr)
    print(f"aurora-gateway export: {written.frames} MAVLink frames of {_vehicles(flight)} "
          f"as tlog to {args.output}: {kinds or 'none'}" + (f"; {notes}" if notes else ""),
          file=sys.stderr)
    return 0


def _run_rosbag2(args: argparse.Namespace, flight: Flight) -> int:
    """Write ``flight`` as a rosbag2 directory ``args.output`` (the live ``ros2`` backend's
    topics: :mod:`backends.ros2.rosbag2`); the exit status."""
    from backends.ros2 import rosbag2
    try:
        written = rosbag2.write(
            flight.messages, args.output, flight.vehicles,
            custom_data={"aurora_gateway.recording": Path(args.recording).name,
                         "aurora_gateway.version": __version__})
    except rosbag2.BagError as exc:
        print(f"aurora-gateway export: -o: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:
        print(f"aurora-gateway export: cannot write {args.output}: {exc.strerror or exc}",
              file=sys.stderr)
        return EXIT_FAILURE
    topics = ", ".join(f"{t} {n}" for t, n in written.counts.items())
    notes = flight.notes()
    print(f"aurora-gateway export: {flight.kinds['sm_update']} SM updates ({flight.statuses} "
          f"STATUS) of {_vehicles(flight)} as rosbag2 to {args.output}: "
          f"{topics or 'no messages'}" + (f"; {notes}" if notes else ""), file=sys.stderr)
    return 0
