"""Tests of armfit.noise: the standard error per bin of a response and the "× noise" statistic,
and that every place armfit prints "× noise" gives the same number for the same model.

Expected values of the unit tests are computed by hand from the definition
(docs/methods.md, "The noise model"); the agreement tests run ``armfit run`` on the
sample studies and compare what each output reports against the params files.
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import armfit
from armfit import figures, noise
from armfit.models.params import read_params
from armfit.spectra import Spectra

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------
# The standard errors
# ---------------------------------------------------------------------------

def test_a_constant_standard_error_is_kept():
    # pooling the variance of a constant over neighbours gives the constant back
    sdb, sdeg = noise.standard_errors(np.full(30, 0.4), np.full(30, 2.0))
    np.testing.assert_allclose(sdb, 0.4, rtol=1e-12)
    np.testing.assert_allclose(sdeg, 2.0, rtol=1e-12)


def test_a_runaway_standard_error_is_capped_then_pooled():
    # one bin with a Bendat-Piersol error of 1400 dB (coherence near 0) among bins of
    # 0.1 dB: capped at pure noise (5.57 dB), then its variance shared by the 9-bin
    # windows that hold it: sqrt((8 * 0.1^2 + 5.57^2) / 9) at bins 6..14, 0.1 elsewhere
    se = np.full(21, 0.1)
    se[10] = 1400.0
    sdb, _ = noise.standard_errors(se, np.ones(21))
    inside = math.sqrt((8 * 0.01 + 5.57 ** 2) / 9)
    np.testing.assert_allclose(sdb[6:15], inside, rtol=1e-12)
    np.testing.assert_allclose(np.r_[sdb[:6], sdb[15:]], 0.1, rtol=1e-12)
    # without pooling the cap alone: 5.57 dB, 103.9 deg (180/sqrt(3))
    sdb1, sdeg1 = noise.standard_errors(se, np.r_[np.ones(20), np.inf], pool=1)
    assert sdb1[10] == pytest.approx(5.57) and sdeg1[-1] == pytest.approx(103.9)


def test_missing_standard_errors_take_the_median_and_tiny_ones_the_floor():
    se = np.array([0.2, np.nan, 0.4, -1.0, 0.3])         # median of the valid: 0.3
    sdb, _ = noise.standard_errors(se, np.ones(5), pool=1)
    np.testing.assert_allclose(sdb, [0.2, 0.3, 0.4, 0.3, 0.3])
    sdb, sdeg = noise.standard_errors(np.full(12, 1e-4), np.full(12, 1e-3))
    np.testing.assert_allclose(sdb, 0.01)                # floors: 0.01 dB, 0.06 deg
    np.testing.assert_allclose(sdeg, 0.06)


def test_rows_are_separate_responses():
    # (T, n): each row pooled along frequency on its own; a row with no valid se has none
    se = np.array([[0.1] * 10, [np.nan] * 10])
    sdb, _ = noise.standard_errors(se, np.ones((2, 10)))
    np.testing.assert_allclose(sdb[0], 0.1)
    assert np.isnan(sdb[1]).all()
    assert math.isnan(noise.rms_norm(np.ones(10), np.ones(10), sdb[1], sdb[1]))


def test_standard_errors_made_in_place_are_the_former_steps_to_the_bit():
    """The noise model's steps done in one array of the responses' size give the same
    bits as the steps each making a new array (the former code, written out here with
    scipy's moving mean, which armfit's own equals to the bit: test_fast_paths.py), on
    rows with infinite, missing, zero and negative errors and one row without any."""
    from scipy.ndimage import uniform_filter1d
    rng = np.random.default_rng(7)
    se = rng.gamma(2.0, 0.4, (40, 100)) * rng.choice([1, 10, 100], (40, 100))
    se[rng.random(se.shape) < 0.05] = np.inf
    se[rng.random(se.shape) < 0.05] = np.nan
    se[rng.random(se.shape) < 0.03] = 0.0
    se[rng.random(se.shape) < 0.03] = -1.0
    se[7] = np.nan

    def former(x, cap, floor, pool=noise.POOL_BINS):
        x = np.array(x, float, ndmin=1)
        with np.errstate(invalid="ignore"):
            x = np.minimum(x, cap)
            ok = np.isfinite(x) & (x > 0)
        fill = np.nanmedian(np.where(ok, x, np.nan), axis=-1)[..., None]
        x = np.where(ok, x, fill)
        x = np.sqrt(uniform_filter1d(x * x, pool, axis=-1, mode="nearest"))
        return np.maximum(x, floor)

    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)   # numpy's all-NaN row
        want = (former(se, noise.SE_CAP_DB, noise.SE_FLOOR_DB),
                former(se * 20, noise.SE_CAP_DEG, noise.SE_FLOOR_DEG))
    got = noise.standard_errors(se, se * 20)
    for g, w in zip(got, want, strict=True):
        assert np.array_equal(g, w, equal_nan=True)
        assert np.isnan(g[7]).all() and np.isfinite(g[:7]).all()
    # one response (1-D) as well
    one = noise.standard_errors(se[0], se[0] * 20)
    assert np.array_equal(one[0], want[0][0]) and np.array_equal(one[1], want[1][0])


def test_rms_norm_pools_magnitude_and_phase():
    # z_db = (1, 2), z_deg = (3/3, 0/3): sqrt((1 + 4 + 1 + 0) / 4)
    got = noise.rms_norm([1.0, 2.0], [3.0, 0.0], [1.0, 1.0], [3.0, 3.0])
    assert got == pytest.approx(math.sqrt(6 / 4))
    # a bin without a finite residual is left out, not counted as zero
    got = noise.rms_norm([1.0, np.nan], [1.0, 5.0], [1.0, 1.0], [1.0, 1.0])
    assert got == pytest.approx(math.sqrt((1 + 1 + 25) / 3))


def test_rms_of_normalised_is_the_pooled_rms_of_the_finite_values_to_the_bit():
    """The same number as the definition written out (join both, keep the finite values
    in row-major order, mean of the squares), bit for bit, also for arrays laid out
    column-major as a band's boolean selection makes them, with NaN and inf entries."""
    rng = np.random.default_rng(7)
    z_db = rng.normal(size=(40, 100))[:, rng.random(100) < 0.6]   # column-major copy
    z_deg = 3.0 * rng.normal(size=(40, 100))[:, rng.random(100) < 0.6]
    assert not z_db.flags["C_CONTIGUOUS"]
    z_db[3, 4], z_deg[0, 1], z_deg[5, 2] = np.nan, np.inf, -np.nan
    z = np.concatenate([z_db.ravel(), z_deg.ravel()])
    z = z[np.isfinite(z)]
    assert z.size == z_db.size + z_deg.size - 3
    assert noise.rms_of_normalised(z_db, z_deg) == float(np.sqrt(np.mean(z * z)))
    # rms_norm is it of the normalised residuals; nothing finite: NaN
    assert noise.rms_norm(z_db, z_deg, 1.0, 1.0) == noise.rms_of_normalised(z_db, z_deg)
    assert math.isnan(noise.rms_of_normalised([np.nan], [np.inf]))


# ---------------------------------------------------------------------------
# One number everywhere: params files, compare (API and compare.csv), the residual
# figure's legend and the report, on the sample studies
# ---------------------------------------------------------------------------

def _report_tables(text: str) -> dict[str, list[list[str]]]:
    """{"<heading> / <line before the table>": table rows (cells)} of a report's markdown
    tables, without their header rows."""
    out: dict[str, list[list[str]]] = {}
    heading = line_before = ""
    for line in text.splitlines():
        if line.startswith("|"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            if not set(line) <= set("|-"):
                out.setdefault(f"{heading} / {line_before}", []).append(cells)
        elif line.startswith("#"):
            heading = line.strip()
        elif line.strip():
            line_before = line.strip()
    return {k: rows[1:] for k, rows in out.items()}


def _report_norms(tables, title: str, grip: bool) -> dict[tuple, str]:
    """{(axis, grip): the "rms × noise" cell} of the report's table under ``title``."""
    (rows,) = [r for t, r in tables.items() if title in t]
    return {(r[0], float(r[1]) if grip else None): r[-1] for r in rows}


@pytest.fixture(scope="module", params=["study", "hidden"])
def run(request, sample_runs):
    return request.param, sample_runs(request.param)


def _files(out: Path, which: str) -> list[tuple[str, Path]]:
    """(report caption, params file) of the tables the run wrote: the adopted (or only)
    model, and the base model's when something was adopted."""
    first = {"nominal": "## Nominal parameters", "grip": "## Grip-dependent parameters"}
    base = {"nominal": "Table II, base model", "grip": "Table I, base model"}
    files = [(first[which], out / f"{which}_params.csv")]
    if (out / f"{which}_params_base.csv").exists():
        files.append((base[which], out / f"{which}_params_base.csv"))
    return files


def test_every_output_gives_the_params_files_noise_ratio(run):
    name, out = run
    spectra = Spectra.read(out / "spectra.parquet")
    tables = _report_tables((out / "report.md").read_text(encoding="utf-8"))
    compare_csv = pd.read_csv(out / "compare.csv", keep_default_na=False)
    (report_compare,) = [r for t, r in tables.items() if "RMS magnitude error" in t]
    checked = 0
    for which in ("nominal", "grip"):
        for caption, path in _files(out, which):
            params = read_params(path)
            grip = which == "grip"
            in_report = _report_norms(tables, caption, grip)
            api_rows = armfit.compare(spectra, path).rows
            for _, row in params.iterrows():
                key = (row["axis"], float(row["grip_N"]) if grip else None)
                want = float(row["rms_norm"])
                # the report's Table I / II
                assert in_report[key] == f"{want:.2f}", (name, path.name, key)
                # compare through the API: the overall row of the same model
                (cmp,) = [r for r in api_rows
                          if (r.axis, r.grip_N) == key and r.model == _label(row)]
                assert cmp.overall.rms_norm == pytest.approx(want, rel=1e-8), (name, key)
                # the residual figure's legend
                label = figures.residual_labels(spectra, params, row["axis"])[key[1]]
                shown = float(re.search(r"\((\d+\.\d+)× noise", label).group(1))
                assert shown == pytest.approx(want, abs=0.005 + 1e-12), (name, key, label)
                assert f"({want:.2f}× noise" in label
                checked += 1
                if grip:
                    continue
                # compare.csv and the report's copy of it (nominal models)
                csv = compare_csv[(compare_csv["axis"] == row["axis"])
                                  & (compare_csv["model"] == _label(row))
                                  & (compare_csv["band"] == "overall")]
                assert len(csv) == 1
                assert float(csv["rms_norm"].iloc[0]) == pytest.approx(want, rel=1e-8)
                cells = [r for r in report_compare
                         if r[0] == row["axis"] and r[1] == _label(row)]
                assert cells and cells[0][2].split(" / ")[-1] == f"{want:.2f}"
    # every table of the run was checked: 3 nominal and 9 grip rows per model
    assert checked == 12 * len(_files(out, "nominal"))


def _label(row) -> str:
    effects = row["effects"] if isinstance(row["effects"], str) else ""
    return "+".join(["base", *[e for e in effects.split(";") if e]])


def test_the_residual_figure_prints_the_labels(run):
    # the legend of the drawn figure holds the labels of figures.residual_labels
    _, out = run
    spectra = Spectra.read(out / "spectra.parquet")
    params = read_params(out / "nominal_params.csv")
    fig = figures.residual_figure(spectra, params, axis="x")
    texts = [t.get_text() for ax in fig.axes if ax.get_legend() for t in
             ax.get_legend().get_texts()]
    assert figures.residual_labels(spectra, params, "x")[None] in texts


def test_the_diagnosis_prints_its_own_noise_ratio(run):
    # the verdict's "error/noise" and the report's base error repeat diagnosis.json's
    # base_error.rms_norm (the joint fit to every trial, the same noise model)
    import json

    _, out = run
    doc = json.loads((out / "diagnosis.json").read_text(encoding="utf-8"))
    report = (out / "report.md").read_text(encoding="utf-8")
    for axis, d in doc["axes"].items():
        base = d["base_error"]["rms_norm"]
        assert f"/ {base:.2f} × noise (RMS)" in report, axis
        assert d["steps"][0]["rms_norm"] == pytest.approx(base, rel=1e-12)
        assert d["error_steps"][0] == pytest.approx(base, rel=1e-12)
