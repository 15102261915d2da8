"""The CRSF monitor's radio view: what each sensor showed per flight phase, in bounded memory
however long it runs and whatever the stream's flight-mode texts do."""

from __future__ import annotations

from backends.crsf.frames import BaroAltitude, FlightMode
from backends.crsf.monitor import MAX_PHASES, RadioView


def test_a_phase_keeps_each_sensors_range_and_the_summary_shows_it() -> None:
    view = RadioView()
    view.update(FlightMode("BOOST"))
    for alt in (10.0, 250.0, 120.0):
        view.update(BaroAltitude(alt))
    view.update(FlightMode("IDLE*"))
    view.update(BaroAltitude(3.0))
    rows = view.summary().splitlines()
    assert rows[0].startswith("FM BOOST") and "Alt 10" in rows[0] and "… 250" in rows[0]
    assert rows[1].startswith("FM IDLE*") and "Alt 3" in rows[1] and "…" not in rows[1]


def test_a_long_run_and_endless_mode_changes_stay_bounded() -> None:
    view = RadioView()
    for i in range(3 * MAX_PHASES):
        view.update(FlightMode(f"M{i % 7}{i}"))
        for k in range(20):
            view.update(BaroAltitude(float(k)))
    assert len(view.phases) == MAX_PHASES
    assert view.phases_merged == 2 * MAX_PHASES + 1  # (the first phase has no mode)
    assert all(len(p.values) == 1 for p in view.phases[1:])  # one range per sensor, no list
    assert view.summary().endswith(f"beyond {MAX_PHASES} phases, ran on in the last one)")
