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


def test_parameter_table_marks_bound_and_held_values_as_the_latex_table_does():
    """A value in ``at_bound`` gets †, one in ``held`` ‡ (the marks of armfit.tables'
    LaTeX), each explained under the table; a table without marks has no footnote."""
    import pandas as pd

    from armfit.report import params_markdown
    row = {"axis": "x", "grip_N": 1.0, "Ma": 0.15256, "k1": 86.291, "k2": 645.9, "b1": 8.1664,
           "b2": 0.05, "delay.delay_s": 0.012002, "rms_db": 0.22, "rms_deg": 1.59,
           "rms_norm": 0.22, "effects": "delay"}
    marked = pd.DataFrame([{**row, "at_bound": "b2", "held": "delay.delay_s"}])
    lines = params_markdown(marked)
    assert lines[2] == ("| x | 1 | 0.1526 | 86.29 | 645.9 | 8.166 | 0.05000† | 0.01200‡ | "
                        "0.22 | 1.6 | 0.22 |")
    assert lines[-2].startswith("† at a physical bound of the fit (within 1 % of its range)")
    assert "‡ held at the value estimated jointly from every trial of the axis" in lines[-2]
    plain = params_markdown(pd.DataFrame([{**row, "at_bound": float("nan"), "held": ""}]))
    assert not any("†" in ln or "‡" in ln for ln in plain)


def test_wu_roots_a_double_real_root_is_not_written_as_a_conjugate_pair():
    """wu.csv stores a double real root as one row with imaginary part 0 (formats.md): Table
    III writes it as "(double)", a complex pair as re ± im j."""
    from armfit.report import _pairs_text
    assert _pairs_text([complex(-3.037678, 0.0), complex(-34.2376, -108.8959)]) == \
        "-3.038 (double); -34.24 ± 108.9j"


def test_the_report_command_is_the_command_as_run():
    """The output folder as given, quoted for a shell where it needs it; the options that
    shape the results written out (defaults of armfit.pipeline.RunOptions too)."""
    from armfit.pipeline import RunOptions
    from armfit.report import _command
    cmd = _command(("sample_data/hidden",), "out/my run", RunOptions(skip_bad=True))
    assert cmd == ("armfit run sample_data/hidden -o 'out/my run' --skip-bad --method h1 "
                   "--cost complex --wu-cost envelope")


def test_a_screened_out_candidate_says_so():
    """A candidate the screening left out has no error after it nor ΔBIC (NaN in
    armfit.diagnosis.Candidate): its row says "screened out" rather than dashes alone."""
    from armfit.diagnosis import Candidate
    from armfit.report import _candidate_row
    nan = math.nan
    out = Candidate("lowpass", {"cutoff_hz": 11.32}, {}, {}, 6.49, nan, 32.0, nan, 330.0, nan,
                    (), (), 0.0, 0.0, nan, nan, False)
    kept = Candidate("delay", {"delay_s": 0.012}, {}, {}, 6.49, 0.78, 32.0, 5.7, 330.0, 0.95,
                     (), (), 0.0, 0.0, 3700.0, 3655.4, True)
    assert _candidate_row(out) == ["lowpass", "cutoff_hz=11.32", "6.49 → –", "32.0 → –", "–",
                                   "no (screened out)"]
    assert _candidate_row(kept) == ["delay", "delay_s=0.012", "6.49 → 0.78", "32.0 → 5.7",
                                    "3655.4", "yes"]
