"""``aurora-gateway plot RECORDING -o flight.png``: a recorded flight as one picture.

Three stacked panels sharing the time axis (seconds since the recording's first record, as
in ``export``'s ``t_s``): altitude, vertical speed, and the two accelerations (the specific
force's magnitude and its component along the body axis).  Behind them, a band per flight
state, named in a legend; the apogee (the highest altitude sample) is marked with a dashed
line through every panel and annotated with its altitude and time.

By default the picture is cropped to the flight: from a little before the first in-flight
state (BOOST … REDUNDANT for the SIMPLE machine, per ``dialects.states``) to a little after
the last, so a recording with minutes on the pad does not squash the flight into a sliver.
``--all`` plots the whole recording; so does a recording with no in-flight state.

A recording of several vehicles draws one series per vehicle, in its own colour and named in
a legend, each with its apogee marked (the state bands, which would overlap, are left out),
over the union of their flights; ``--vehicle NAME`` draws that vehicle alone, as above (a
name the recording does not have: one line naming the ones it has, exit status 2).  A
missing, empty or foreign file, a recording with no SM update, or no matplotlib: one line,
exit status 2; a picture that cannot be written: exit status 1 (:mod:`gateway.exits`).
The picture draws SM updates: a recording's other messages (a MAVLink vehicle's positions,
batteries, states …, and frames of no known type) are left out, counted on stderr
(``not drawn: position 40, battery 4``); ``export`` shows them.

matplotlib (the ``plot`` extra: ``pip install 'aurora-gateway[plot]'``) is imported only
when the command runs, and draws with its Agg canvas: no display needed.  The picture is
``--size`` pixels (1200×900 by default) at 100 dpi, laid out by matplotlib's constrained
layout engine.  The format follows the file's extension (``.png``, ``.svg``, ``.pdf`` …).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dialects.states import is_in_flight
from gateway import exits
from gateway.commands.export import ExportError, Flight, load

if TYPE_CHECKING:
    from matplotlib.figure import Figure

EXIT_FAILURE = exits.FAILED  # a picture that could not be written
EXIT_USAGE = exits.USAGE  # a missing, empty or foreign recording; no SM update; no matplotlib
DPI = 100
DEFAULT_SIZE = (1200, 900)
BAND_ALPHA = 0.18
#: State band colours, indexed by state number (matplotlib's "tab10" cycle).
BAND_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple",
                "tab:brown", "tab:pink", "tab:gray", "tab:olive", "tab:cyan")
APOGEE_COLOUR = "crimson"
#: One colour per vehicle when several are drawn (matplotlib's "tab10" cycle).
VEHICLE_COLOURS = BAND_COLOURS


@dataclass(frozen=True)
class Apogee:
    """The highest altitude sample: when (``t_s``) and how high."""

    t_s: float
    altitude_m: float


@dataclass(frozen=True)
class StateRun:
    """A stretch of consecutive rows in one state, from its first row to the next run's."""

    t_start: float
    t_end: float
    sm_type: int
    state: int
    name: str


def find_apogee(rows: list[dict[str, Any]]) -> Apogee | None:
    """The first row of highest altitude (NaNs ignored); None when there is none."""
    best: dict[str, Any] | None = None
    for row in rows:
        alt = row["altitude_m"]
        if alt == alt and (best is None or alt > best["altitude_m"]):  # alt == alt: not NaN
            best = row
    return None if best is None else Apogee(best["t_s"], best["altitude_m"])


def flight_window(rows: list[dict[str, Any]]) -> tuple[float, float]:
    """(start, end) seconds of the flight with a margin either side (15 % of the flight, at
    least 2 s), clipped to the recording; the whole recording when nothing flew."""
    first, last = rows[0]["t_s"], rows[-1]["t_s"]
    flying = [r["t_s"] for r in rows if is_in_flight(r["sm_type"], r["state"])]
    if not flying:
        return first, last
    margin = max(2.0, 0.15 * (flying[-1] - flying[0]))
    return max(first, flying[0] - margin), min(last, flying[-1] + margin)


def state_runs(rows: list[dict[str, Any]]) -> list[StateRun]:
    """The rows' states as runs; each run lasts until the next one starts (the last one
    until the last row)."""
    runs: list[StateRun] = []
    start: dict[str, Any] | None = None
    for row in rows:
        if start is not None and (row["sm_type"], row["state"]) == (start["sm_type"],
                                                                    start["state"]):
            continue
        if start is not None:
            runs.append(StateRun(start["t_s"], row["t_s"], start["sm_type"], start["state"],
                                 start["state_name"]))
        start = row
    if start is not None:
        runs.append(StateRun(start["t_s"], rows[-1]["t_s"], start["sm_type"], start["state"],
                             start["state_name"]))
    return runs


def _colour(state: int) -> str:
    return BAND_COLOURS[state % len(BAND_COLOURS)]


def build_figure(rows: list[dict[str, Any]], title: str,
                 size_px: tuple[int, int] = DEFAULT_SIZE) -> tuple[Figure, Apogee | None]:
    """The flight's figure (on an Agg canvas) and the apogee it marks.  ``rows`` are
    :func:`gateway.commands.export.load` rows, already cropped; at least one."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    fig = Figure(figsize=(size_px[0] / DPI, size_px[1] / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax_alt, ax_vel, ax_acc = fig.subplots(3, 1, sharex=True,
                                          gridspec_kw={"height_ratios": (2, 1.3, 1.3)})
    t = [r["t_s"] for r in rows]
    ax_alt.plot(t, [r["altitude_m"] for r in rows], color="black", lw=1.4, label="altitude")
    ax_vel.plot(t, [r["velocity_mps"] for r in rows], color="black", lw=1.2,
                label="vertical speed")
    ax_vel.axhline(0.0, color="0.5", lw=0.8)
    ax_acc.plot(t, [r["acceleration_mps2"] for r in rows], color="black", lw=1.1,
                label="specific force (magnitude)")
    ax_acc.plot(t, [r["accel_vert_mps2"] for r in rows], color="tab:blue", lw=1.1,
                label="along the body axis")
    ax_alt.set_ylabel("altitude (m)")
    ax_vel.set_ylabel("vertical speed (m/s)")
    ax_acc.set_ylabel("acceleration (m/s²)")
    ax_acc.set_xlabel("time since the recording's first record (s)")
    ax_acc.legend(loc="upper right", fontsize="small")
    ax_acc.set_xlim(t[0], t[-1] if t[-1] > t[0] else t[0] + 1.0)

    legend: dict[tuple[int, int], Patch] = {}
    for run in state_runs(rows):
        colour = _colour(run.state)
        for ax in (ax_alt, ax_vel, ax_acc):
            ax.axvspan(run.t_start, run.t_end, color=colour, alpha=BAND_ALPHA, lw=0)
        legend.setdefault((run.sm_type, run.state),
                          Patch(color=colour, alpha=BAND_ALPHA * 2, label=run.name))
    patches = [legend[k] for k in sorted(legend)]
    fig.legend(handles=patches, loc="outside lower center", ncols=min(len(patches), 9),
               fontsize="small", frameon=False)

    apogee = find_apogee(rows)
    if apogee is not None:
        for ax in (ax_alt, ax_vel, ax_acc):
            ax.axvline(apogee.t_s, color=APOGEE_COLOUR, lw=1.0, ls="--")
        ax_alt.plot([apogee.t_s], [apogee.altitude_m], marker="v", ms=9, color=APOGEE_COLOUR,
                    ls="none")
        lo, hi = ax_alt.get_ylim()
        ax_alt.set_ylim(lo, hi + 0.15 * (hi - lo))  # headroom for the marker and its label
        left, right = ax_acc.get_xlim()
        on_right = apogee.t_s > left + 0.6 * (right - left)
        ax_alt.annotate(f"apogee {apogee.altitude_m:.1f} m\nat t = {apogee.t_s:.2f} s",
                        xy=(apogee.t_s, apogee.altitude_m),
                        xytext=(-14 if on_right else 14, -4), textcoords="offset points",
                        ha="right" if on_right else "left", va="top", color=APOGEE_COLOUR,
                        fontweight="bold")
    for ax in (ax_alt, ax_vel, ax_acc):
        ax.grid(True, color="0.85", lw=0.6)
    fig.suptitle(title)
    return fig, apogee


def by_vehicle(rows: list[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    """The rows of each vehicle, vehicles in the order they first appear."""
    out: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        out.setdefault(row["vehicle"], []).append(row)
    return out


def build_vehicles_figure(series: dict[str, list[dict[str, Any]]], title: str,
                          size_px: tuple[int, int] = DEFAULT_SIZE,
                          ) -> tuple[Figure, dict[str, Apogee | None]]:
    """The figure of several vehicles (each a non-empty list of rows, already cropped): one
    colour per vehicle, named in a legend, each vehicle's apogee marked; and the apogees."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size_px[0] / DPI, size_px[1] / DPI), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax_alt, ax_vel, ax_acc = fig.subplots(3, 1, sharex=True,
                                          gridspec_kw={"height_ratios": (2, 1.3, 1.3)})
    apogees: dict[str, Apogee | None] = {}
    t_lo, t_hi = min(r[0]["t_s"] for r in series.values()), max(
        r[-1]["t_s"] for r in series.values())
    for i, (vehicle, rows) in enumerate(series.items()):
        colour = VEHICLE_COLOURS[i % len(VEHICLE_COLOURS)]
        t = [r["t_s"] for r in rows]
        ax_alt.plot(t, [r["altitude_m"] for r in rows], color=colour, lw=1.4, label=vehicle)
        ax_vel.plot(t, [r["velocity_mps"] for r in rows], color=colour, lw=1.2,
                    label=vehicle)
        ax_acc.plot(t, [r["acceleration_mps2"] for r in rows], color=colour, lw=1.1,
                    label=f"{vehicle}: specific force (magnitude)")
        ax_acc.plot(t, [r["accel_vert_mps2"] for r in rows], color=colour, lw=1.0, ls="--",
                    label=f"{vehicle}: along the body axis")
        apogee = apogees[vehicle] = find_apogee(rows)
        if apogee is not None:
            ax_alt.plot([apogee.t_s], [apogee.altitude_m], marker="v", ms=9, color=colour,
                        ls="none")
            ax_alt.annotate(f"{vehicle}: {apogee.altitude_m:.1f} m at t = {apogee.t_s:.2f} s",
                            xy=(apogee.t_s, apogee.altitude_m), xytext=(8, 6 + 13 * i),
                            textcoords="offset points", color=colour, fontweight="bold",
                            fontsize="small")
    ax_vel.axhline(0.0, color="0.5", lw=0.8)
    lo, hi = ax_alt.get_ylim()
    ax_alt.set_ylim(lo, hi + 0.15 * (hi - lo))  # headroom for the labels
    ax_alt.set_ylabel("altitude (m)")
    ax_vel.set_ylabel("vertical speed (m/s)")
    ax_acc.set_ylabel("acceleration (m/s²)")
    ax_acc.set_xlabel("time since the recording's first record (s)")
    ax_alt.legend(loc="upper right", fontsize="small", title="vehicle")
    ax_acc.legend(loc="upper right", fontsize="x-small", ncols=len(series))
    ax_acc.set_xlim(t_lo, t_hi if t_hi > t_lo else t_lo + 1.0)
    for ax in (ax_alt, ax_vel, ax_acc):
        ax.grid(True, color="0.85", lw=0.6)
    fig.suptitle(title)
    return fig, apogees


# -- the command ---------------------------------------------------------------------------------

def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not WIDTHxHEIGHT (e.g. 1200x900)") from None
    if not (200 <= w <= 10000 and 200 <= h <= 10000):
        raise argparse.ArgumentTypeError(f"{text}: each side must be 200..10000 pixels")
    return w, h


def add_command(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``plot`` to the ``aurora-gateway`` subcommands."""
    p = subparsers.add_parser(
        "plot", help="draw a recorded flight (altitude, speed, accelerations, states) to a "
                     "PNG",
        description="Draw a recording's altitude, vertical speed and accelerations over time, "
                    "with a band per flight state and the apogee marked. Needs matplotlib "
                    "(pip install 'aurora-gateway[plot]').")
    p.add_argument("recording", metavar="RECORDING", help="the recording (.aur)")
    p.add_argument("-o", "--output", metavar="FILE", required=True,
                   help="picture to write; the extension picks the format (.png, .svg, .pdf)")
    p.add_argument("--title", help="figure title (default: the file's name and the first "
                   "record's UTC time)")
    p.add_argument("--size", type=_size, default=DEFAULT_SIZE, metavar="WxH",
                   help="picture size in pixels (default 1200x900)")
    p.add_argument("--all", action="store_true",
                   help="plot the whole recording, not just the flight and a margin around it")
    p.add_argument("--vehicle", metavar="NAME",
                   help="draw this vehicle only (default: one series per vehicle)")
    p.set_defaults(handler=run_plot)
    return p


def _default_title(path: str, rx_time: float) -> str:
    when = datetime.fromtimestamp(rx_time, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    return f"{Path(path).name} — {when}"


def run_plot(args: argparse.Namespace) -> int:
    """The ``plot`` handler; returns the exit status."""
    err = sys.stderr
    try:
        flight = load(args.recording, args.vehicle)
    except ExportError as exc:
        print(f"aurora-gateway plot: {exc}", file=err)
        return EXIT_USAGE  # a missing, empty or foreign file, or a vehicle it does not have
    rows = [r for r in flight.rows if r.get("kind", "sm_update") == "sm_update"]
    not_drawn = _not_drawn(flight)
    if not rows:
        print(f"aurora-gateway plot: {args.recording}: no SM updates to plot"
              + (f" ({not_drawn})" if not_drawn else ""), file=err)
        return EXIT_USAGE
    # without matplotlib: the command line names the extra, exit 2 (gateway.registry)
    import matplotlib  # noqa: F401
    title = args.title if args.title is not None else _default_title(args.recording,
                                                                      rows[0]["rx_time"])
    series = by_vehicle(rows)
    notes = "; ".join(n for n in (not_drawn, flight.notes()) if n)
    if len(series) > 1:
        return _plot_vehicles(args, series, title, notes)
    if not args.all:
        start, end = flight_window(rows)
        rows = [r for r in rows if start <= r["t_s"] <= end]
    fig, apogee = build_figure(rows, title, args.size)
    if failed := _save(fig, args):
        return failed
    where = (f"apogee {apogee.altitude_m:.1f} m at t = {apogee.t_s:.2f} s"
             if apogee is not None else "no altitude")
    print(f"aurora-gateway plot: {args.output} ({args.size[0]}×{args.size[1]} px): "
          f"{len(rows)} SM updates of {rows[0]['vehicle']}, t = {rows[0]['t_s']:.2f} … "
          f"{rows[-1]['t_s']:.2f} s; {where}" + (f"; {notes}" if notes else ""), file=err)
    return 0


def _not_drawn(flight: Flight) -> str:
    """What the picture leaves out, counted: the recording's messages of other kinds than
    SM_UPDATE (STATUS aside: its flags are no curve either way)."""
    other = [f"{k} {n}" for k, n in flight.kinds.items() if k != "sm_update"]
    if flight.other_frames:
        other.append(f"raw {flight.other_frames}")
    return f"not drawn: {', '.join(other)}" if other else ""


def _save(fig: Figure, args: argparse.Namespace) -> int:
    """Write the picture; 0, else the exit status (one line said why): 2 for an extension
    matplotlib cannot write (a bad ``-o``), 1 for a file that could not be written."""
    try:
        fig.savefig(args.output, dpi=DPI)
    except (OSError, ValueError) as exc:  # ValueError: an extension matplotlib cannot write
        text = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        print(f"aurora-gateway plot: cannot write {args.output}: {text}", file=sys.stderr)
        return EXIT_FAILURE if isinstance(exc, OSError) else EXIT_USAGE
    return 0


def _plot_vehicles(args: argparse.Namespace, series: dict[str, list[dict[str, Any]]],
                   title: str, notes: str) -> int:
    """Several vehicles in one picture, over the union of their flights' windows."""
    if not args.all:
        windows = [flight_window(rows) for rows in series.values()]
        start, end = min(w[0] for w in windows), max(w[1] for w in windows)
        series = {v: kept for v, rows in series.items()
                  if (kept := [r for r in rows if start <= r["t_s"] <= end])}
    fig, apogees = build_vehicles_figure(series, title, args.size)
    if failed := _save(fig, args):
        return failed
    n = sum(len(rows) for rows in series.values())
    where = "; ".join(f"{v} apogee {a.altitude_m:.1f} m at t = {a.t_s:.2f} s"
                      if a is not None else f"{v} no altitude" for v, a in apogees.items())
    print(f"aurora-gateway plot: {args.output} ({args.size[0]}×{args.size[1]} px): "
          f"{n} SM updates of {len(series)} vehicles ({', '.join(series)}); {where}"
          + (f"; {notes}" if notes else ""), file=sys.stderr)
    return 0
