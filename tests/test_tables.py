"""Tables of parameters: the paper's Table I / II layout as CSV and LaTeX."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pandas as pd
import pytest

from armfit.data import paper_table
from armfit.io.artifacts import params_rows
from armfit.models.arm import PARAM_NAMES
from armfit.tables import caption_for, csv_text, latex_table, paper_layout, sig4

PAPER_COLS = ["Ma_kg", "k1_N_per_m", "k2_N_per_m", "b1_Ns_per_m", "b2_Ns_per_m"]


def _params_from_paper(name: str, effects: str = "") -> pd.DataFrame:
    """A params DataFrame (docs/formats.md, "Params CSV") holding the paper's table values,
    with intervals
    +-10 % and placeholder statistics."""
    rows = []
    for _, r in paper_table(name).iterrows():
        row = {"axis": r["axis"], "effects": effects, "mp_kg": 0.09}
        if name == "grip":
            row["grip_N"] = float(r["grip_N"])
        for n, c in zip(PARAM_NAMES, PAPER_COLS, strict=True):
            row[n] = float(r[c])
            row[f"{n}_lo"], row[f"{n}_hi"] = 0.9 * r[c], 1.1 * r[c]
        if effects == "delay":
            row["delay.delay_s"] = 0.0125
            row["delay.delay_s_lo"], row["delay.delay_s_hi"] = 0.011, 0.014
        rows.append(row)
    names = list(PARAM_NAMES) + (["delay.delay_s"] if effects == "delay" else [])
    return params_rows(rows, names, grip=name == "grip").to_frame()


@pytest.mark.parametrize(("value", "text"), [
    # as printed in the paper's tables (4 significant figures, trailing zeros kept)
    (7.41, "7.410"), (704.2, "704.2"), (4877.0, "4877"), (0.1925, "0.1925"),
    (628.0, "628.0"), (2.25, "2.250"), (12345.6, "12346"), (float("nan"), "")])
def test_sig4(value, text):
    assert sig4(value) == text


@pytest.mark.parametrize(("name", "fname"), [("grip", "table1_grip_dependent.csv"),
                                             ("nominal", "table2_nominal.csv")])
def test_csv_text_reproduces_the_paper_table(name, fname):
    # The paper's own CSV (armfit/data, transcribed from Tables I and II) is exactly what
    # csv_text prints for the paper's values: same columns, same 4-figure numbers.
    expected = resources.files("armfit.data").joinpath(fname).read_text()
    assert csv_text(_params_from_paper(name)) == expected


def test_paper_layout_with_intervals():
    lay = paper_layout(_params_from_paper("nominal"), ci=True)
    assert list(lay.columns[:4]) == ["axis", "Ma_kg", "Ma_kg_lo", "Ma_kg_hi"]
    # Table II, X: Ma = 0.2277 kg; interval set to +-10 % above
    assert lay.loc[0, "Ma_kg"] == 0.2277
    assert lay.loc[0, "Ma_kg_hi"] == pytest.approx(1.1 * 0.2277)


def test_latex_table_one_layout():
    tex = latex_table(_params_from_paper("grip"), caption="Grip 95 % fits", label="tab:g")
    lines = tex.splitlines()
    assert lines[0] == r"\begin{table}[t]"
    assert r"\caption{Grip 95 \% fits}" in lines and r"\label{tab:g}" in lines
    assert r"\begin{tabular}{lcrrrrr}" in lines
    header = lines[lines.index(r"\toprule") + 1]
    assert header == (r"Axis & Grip (N) & $M_a$ (kg) & $k_1$ (N/m) & $k_2$ (N/m) & "
                      r"$b_1$ (N$\cdot$s/m) & $b_2$ (N$\cdot$s/m) \\")
    body = [ln for ln in lines if ln.endswith(r"\\")][1:]
    assert len(body) == 9
    # first row of each axis names it; Table I X 1 N values as printed in the paper
    assert body[0] == r"X & 1 & 0.1925 & 85.48 & 704.2 & 7.410 & 2.477 \\"
    assert body[1].startswith(" & 2 & 0.2037 &")
    assert body[6] == r"Z & 1 & 4.374 & 4877 & 200.4 & 55.85 & 32.96 \\"
    # axes separated by rules: header rule + 2 between axis groups
    assert lines.count(r"\midrule") == 3
    assert lines[-3:] == [r"\bottomrule", r"\end{tabular}", r"\end{table}"]


def test_latex_table_two_with_intervals_and_effect():
    tex = latex_table(_params_from_paper("nominal", effects="delay"), ci=True)
    assert r"\begin{tabular}{lrrrrrr}" in tex
    assert r"\texttt{delay.delay\_s} (s)" in tex
    # Table II, Y: Ma = 0.4142 kg with its (+-10 %) interval in small type
    assert r"Y & 0.4142 {\scriptsize[0.3728, 0.4556]}" in tex
    assert r"0.01250 {\scriptsize[0.01100, 0.01400]}" in tex


def test_nan_interval_prints_empty():
    df = _params_from_paper("nominal")
    df.loc[0, "k2_lo"] = np.nan
    assert r"628.0 {\scriptsize[, 690.8]}" in latex_table(df, ci=True)


def test_caption_names_the_fit_and_the_intervals():
    assert caption_for("grip", ["jacobian"]) == (
        "Grip-dependent arm parameters (fit to the mean per axis and grip force); "
        "95 % intervals from the Jacobian.")
    assert caption_for("nominal", ["bootstrap-200"]).endswith(
        "95 % intervals from a bootstrap over subjects, 200 resamples.")


# ---------------------------------------------------------------------------
# The params CSV written from rows, without pandas
# ---------------------------------------------------------------------------

_NAN = float("nan")


@pytest.mark.parametrize("rows", [
    # the shapes of the columns a fit writes: floats, whole numbers, text, bools, and a
    # key a row lacks (an effect's parameter only one row's model has)
    [{"axis": "x", "Ma": 0.2085168061234, "n_points": 100, "converged": True,
      "effects": "", "held": "delay.delay_s"},
     {"axis": "y", "Ma": 1e-12, "n_points": 7, "converged": np.bool_(False),
      "effects": "delay;lag", "delay.delay_s": 0.0125}],
    # missing values: NaN and None in numbers and text, a whole column empty
    [{"axis": "z", "Ma": _NAN, "n_points": None, "effects": None, "held": None},
     {"axis": "x", "Ma": -0.0, "n_points": 3.5, "effects": "a", "held": None}],
    # numbers that need quoting or many digits, infinities, numpy scalars
    [{"axis": 'x "1", y', "Ma": float("inf"), "n_points": np.int64(2 ** 40),
      "effects": "line\nbreak", "converged": True},
     {"axis": "", "Ma": np.float64(123456789012.5), "n_points": np.int32(-4),
      "effects": "é;ß", "converged": False}],
    [],
])
def test_params_rows_write_the_csv_pandas_writes(rows, tmp_path):
    # the reference: DataFrame(rows, columns).to_csv(index=False, float_format="%.10g")
    from armfit.io.artifacts import RowTable, write_params
    columns = ("axis", "Ma", "n_points", "converged", "effects", "delay.delay_s", "held")
    table = RowTable(tuple(rows), columns)
    expected = pd.DataFrame(rows, columns=list(columns)).to_csv(index=False,
                                                                float_format="%.10g")
    assert table.csv_text() == expected
    write_params(table, tmp_path / "p.csv")
    assert (tmp_path / "p.csv").read_text() == expected


def test_a_column_pandas_holds_as_objects_is_written_by_pandas(tmp_path):
    # bools with a missing value (pandas: object column): the rows go through pandas
    from armfit.io.artifacts import RowTable, write_params
    rows = ({"axis": "x", "converged": True}, {"axis": "y", "converged": None},
            {"axis": "z", "converged": 1.5})
    table = RowTable(rows, ("axis", "converged"))
    assert table.csv_text() is None
    write_params(table, tmp_path / "p.csv")
    assert (tmp_path / "p.csv").read_text() == table.to_frame().to_csv(index=False)


@pytest.mark.parametrize("name", ["grip", "nominal"])
@pytest.mark.parametrize("effects", ["", "delay"])
def test_params_rows_of_the_papers_tables_write_the_csv_pandas_writes(name, effects):
    from armfit.io.artifacts import RowTable
    frame = _params_from_paper(name, effects)
    table = RowTable(tuple(frame.to_dict("records")), tuple(frame.columns))
    assert table.csv_text() == frame.to_csv(index=False, float_format="%.10g")
