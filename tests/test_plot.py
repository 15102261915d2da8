"""``aurora-gateway plot``: a PNG of the requested size, with something drawn
in every panel, state bands, and the apogee of the simulated flight marked where it is."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.image import imread
from matplotlib.text import Annotation

from gateway import recording
from gateway.commands.cli import main
from gateway.commands.export import load
from gateway.commands.plot import build_figure, flight_window
from gateway.flight import FlightModel
from gateway.model import SmUpdate
from gateway.sources.sim import flight_messages
from gateway.wire import encode

T0 = 1_790_000_000.0
CONSOLE = Path(sys.executable).with_name("aurora-gateway")
IN_FLIGHT = {"BOOST", "BURNOUT", "APOGEE", "MAIN", "REDUNDANT"}  # the SIMPLE machine's


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[tuple[float, SmUpdate]]]:
    """A recording of one simulated flight, and its SM updates as (time, message)."""
    path = tmp_path_factory.mktemp("plot") / "flight.aur"
    updates = []
    with path.open("wb") as f:
        f.write(recording.HEADER)
        for t, msg in flight_messages(FlightModel(), rate_hz=10.0, status_hz=1.0, cycles=1):
            f.write(recording.encode_record(T0 + t, encode(msg)))
            if isinstance(msg, SmUpdate):
                updates.append((t, msg))
    return path, updates


def _apogee(updates: list[tuple[float, SmUpdate]]) -> tuple[float, float]:
    """(time, altitude) of the first highest sample, found here independently."""
    top = max(m.altitude_m for _, m in updates)
    return next((t, m.altitude_m) for t, m in updates if m.altitude_m == top)


def _png(path: Path) -> np.ndarray[Any, Any]:
    img = imread(path)  # float RGBA in 0..1
    return np.asarray(img[..., :3] * 255, dtype=np.uint8)


def test_the_png_has_the_size_and_a_drawing_in_every_panel(
        flight: tuple[Path, list[tuple[float, SmUpdate]]], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    path, updates = flight
    out = tmp_path / "flight.png"
    assert main(["plot", str(path), "-o", str(out), "--title", "test flight"]) == 0
    img = _png(out)
    assert img.shape == (900, 1200, 3)
    # Where the panels are: the same figure, laid out the same way (layout is deterministic).
    rows = load(path).rows
    start, end = flight_window(rows)
    fig, _ = build_figure([r for r in rows if start <= r["t_s"] <= end], "test flight")
    fig.canvas.draw()
    assert len(fig.axes) == 3
    for ax in fig.axes:
        box = ax.get_window_extent()
        x0, x1 = int(box.x0) + 4, int(box.x1) - 4
        y0, y1 = 900 - int(box.y1) + 4, 900 - int(box.y0) - 4  # PNG rows count from the top
        area = img[y0:y1, x0:x1].reshape(-1, 3).astype(int)
        assert len(area) > 50_000
        not_white = (area.min(axis=1) < 245).mean()
        dark = (area.max(axis=1) < 70).sum()  # the black curve
        assert not_white > 0.9, "state bands should cover the panel"
        assert dark > 200, "a curve should be drawn"
        assert len(np.unique(area, axis=0)) > 6, "several state colours"
    err = capsys.readouterr().err
    t_top, alt_top = _apogee(updates)
    assert f"apogee {alt_top:.1f} m at t = {t_top:.2f} s" in err


def test_the_apogee_is_annotated_and_marked_where_it_is(
        flight: tuple[Path, list[tuple[float, SmUpdate]]], tmp_path: Path) -> None:
    path, updates = flight
    t_top, alt_top = _apogee(updates)
    rows = load(path).rows
    fig, apogee = build_figure(rows, "whole recording")
    assert apogee is not None
    assert apogee.t_s == pytest.approx(t_top, abs=1e-6) and apogee.altitude_m == alt_top
    ax_alt = fig.axes[0]
    notes = [a for a in ax_alt.texts if isinstance(a, Annotation)]
    assert len(notes) == 1
    assert f"{alt_top:.1f} m" in notes[0].get_text() and f"{t_top:.2f} s" in notes[0].get_text()
    note_t, note_alt = notes[0].xy
    assert note_t == pytest.approx(t_top, abs=1e-6) and note_alt == alt_top
    # The marker in the picture: the pixel where the apogee lands is the marker's colour.
    out = tmp_path / "whole.png"
    fig.savefig(out)
    img = _png(out)
    x, y = ax_alt.transData.transform((t_top, alt_top))
    px, py = round(float(x)), img.shape[0] - round(float(y))
    # (Left and right of the dashed apogee line, which is crimson too.)
    patch = np.concatenate([img[py - 4:py + 2, px - 5:px - 1], img[py - 4:py + 2, px + 2:px + 6]])
    patch = patch.reshape(-1, 3).astype(int)
    crimson = (patch[:, 0] > 170) & (patch[:, 1] < 90) & (patch[:, 2] < 110)
    assert crimson.sum() >= 12, crimson.sum()


def test_the_default_window_is_the_flight_and_all_is_everything(
        flight: tuple[Path, list[tuple[float, SmUpdate]]]) -> None:
    path, updates = flight
    rows = load(path).rows
    flying = [t for t, m in updates if m.state_name in IN_FLIGHT]
    start, end = flight_window(rows)
    assert start < flying[0] and end > flying[-1]
    assert end - start < 0.5 * (updates[-1][0] - updates[0][0])  # the long pad/landed waits
    fig, _ = build_figure(rows, "all")
    left, right = fig.axes[2].get_xlim()
    assert left == pytest.approx(0.0) and right == pytest.approx(updates[-1][0])


def test_the_console_script_draws_the_size_asked(
        flight: tuple[Path, list[tuple[float, SmUpdate]]], tmp_path: Path) -> None:
    path, updates = flight
    out = tmp_path / "small.png"
    proc = subprocess.run([str(CONSOLE), "plot", str(path), "-o", str(out), "--size",
                           "640x480", "--all"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert _png(out).shape == (480, 640, 3)
    t_top, alt_top = _apogee(updates)
    assert f"apogee {alt_top:.1f} m at t = {t_top:.2f} s" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("content", [None, b"garbage", recording.HEADER])
def test_a_missing_invalid_or_empty_recording_is_one_line_and_status_2(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes | None) -> None:
    path = tmp_path / "bad.aur"
    if content is not None:
        path.write_bytes(content)
    out = tmp_path / "x.png"
    assert main(["plot", str(path), "-o", str(out)]) == 2  # bad input (issue 23)
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("aurora-gateway plot: ")
    assert not out.exists()


def test_an_unwritable_picture_is_one_line_and_status_1_or_2(
        flight: tuple[Path, list[tuple[float, SmUpdate]]], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    # a directory that is not there: failed (1); an extension matplotlib cannot write: a bad
    # -o, bad input (2)
    for target, status in ((tmp_path / "no" / "dir.png", 1), (tmp_path / "flight.notaformat", 2)):
        assert main(["plot", str(flight[0]), "-o", str(target)]) == status
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and "cannot write" in err, err


@pytest.mark.parametrize("argv", [["--size", "big"], ["--size", "10x10"], []])
def test_bad_arguments_are_usage_errors(flight: tuple[Path, list[tuple[float, SmUpdate]]],
                                        argv: list[str]) -> None:
    """A bad size, or no -o at all."""
    with pytest.raises(SystemExit) as info:
        main(["plot", str(flight[0]), *argv])
    assert info.value.code == 2


def test_the_command_line_does_not_import_matplotlib_until_plot_runs() -> None:
    """`aurora-gateway --help` lists `plot` without paying for matplotlib's import."""
    code = ("import sys, contextlib, io\n"
            "from gateway.commands.cli import main\n"
            "o = io.StringIO()\n"
            "with contextlib.suppress(SystemExit), contextlib.redirect_stdout(o):\n"
            "    main(['--help'])\n"
            "assert ' plot ' in o.getvalue() and ' export ' in o.getvalue(), o.getvalue()\n"
            "print('matplotlib' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"
