"""armfit.report: sections of report.md rendered from the typed results (the whole report
is checked byte for byte by tests/test_output_hashes.py)."""

from __future__ import annotations

import math

from armfit.api import Comparisons
from armfit.diagnosis import BandError, Comparison, Step
from armfit.report import _compare_section, _step_row


def _band(lo, hi, k):
    return BandError(lo, hi, rms_db=k, rms_deg=10 * k, rms_norm=100 * k, n_points=5)


def test_compare_section_rows_follow_compare_csv():
    """Axes in order, each axis's models in the order first compared (as compare.csv);
    a band a model was not compared in is "–"; the bands are those of
    armfit.diagnosis.BANDS (0.1-1, 1-3, 3-10, 10-30 Hz)."""
    rows = (
        Comparison("z", None, "median", "base+delay", _band(0.1, 30, 1.0),
                   (_band(0.1, 1, 2.0),), (), {"delay.delay_s": 0.01}, 9),
        Comparison("x", None, "median", "base", _band(0.1, 30, 4.0), (), (), {}, 9),
        Comparison("z", None, "median", "base", _band(0.1, 30, 6.0), (), (), {}, 9),
    )
    lines = _compare_section(Comparisons(rows, "median"))
    table = [line for line in lines if line.startswith("| ")]
    assert table == [
        "| axis | model | overall | 0.1-1 Hz | 1-3 Hz | 3-10 Hz | 10-30 Hz |",
        "| x | base | 4.00 / 40.0 / 400.00 | – | – | – | – |",
        "| z | base+delay | 1.00 / 10.0 / 100.00 | 2.00 / 20.0 / 200.00 | – | – | – |",
        "| z | base | 6.00 / 60.0 / 600.00 | – | – | – | – |"]


def test_step_row_marks_bounds_and_leaves_a_missing_delta_bic_empty():
    """The base model's step has no ΔBIC (NaN; null in diagnosis.json): an empty cell; a
    parameter at its bound is marked."""
    base = Step(None, {"m": 1.23456}, {}, {}, (), 3.14159, 12.345, 6.789, math.nan)
    delay = Step("delay", {"delay_s": 0.0120004}, {}, {}, ("delay_s",), 1.0, 2.0, 0.95,
                 -412.34)
    assert _step_row(0, base) == ["0", "base model", "m=1.235", "3.14", "12.3", "6.79", ""]
    assert _step_row(1, delay) == ["1", "delay", "delay_s=0.012 (at bound)", "1.00", "2.0",
                                   "0.95", "-412.3"]
