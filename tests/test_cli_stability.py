"""`armfit fit-trials` and `armfit stability` on small files with known answers."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from armfit.cli.main import cli
from armfit.data import paper_table
from armfit.io.schema import SPECTRA_COLUMNS
from armfit.models.arm import PARAM_NAMES, h_cl
from armfit.spectra import Spectra

GRID = np.geomspace(0.1, 30, 61)
PAPER_COLS = ["Ma_kg", "k1_N_per_m", "k2_N_per_m", "b1_Ns_per_m", "b2_Ns_per_m"]
TABLE1 = {(r["axis"], float(r["grip_N"])): dict(zip(PARAM_NAMES, r[PAPER_COLS].astype(float),
                                                    strict=True))
          for _, r in paper_table("grip").iterrows()}


def _trial(subject, axis, grip, h):
    db = 20 * np.log10(np.abs(h))
    return pd.DataFrame({
        "level": "trial", "subject": subject, "axis": axis, "grip_N": grip,
        "run": pd.array([None] * GRID.size, dtype="Int64"), "kind": "measured",
        "out_axis": axis, "method": "h1", "freq_hz": GRID, "re": h.real, "im": h.imag,
        "mag_db": db, "phase_deg": np.degrees(np.unwrap(np.angle(h))), "coherence": 0.99,
        "se_db": 0.1, "se_deg": 1.0, "n": 1, "q25_db": db, "q75_db": db,
        "q25_deg": 0.0, "q75_deg": 0.0, "flags": ""})[list(SPECTRA_COLUMNS)]


@pytest.fixture(scope="module")
def trial_files(tmp_path_factory):
    """Spectra with three trials: S1 and S2 exactly Table I's H_CL (eq. 4, X axis, grips
    1 and 2 N, Mp = 0.09 kg), S3 at 1 N with no usable bin (zero response), whose fit must
    fail and be listed. Returns (spectra path, fit-trials output path, CliRunner result)."""
    from click.testing import CliRunner
    d = tmp_path_factory.mktemp("trials")
    blocks = [_trial("S1", "x", 1.0, h_cl(GRID, **TABLE1[("x", 1.0)], mp=0.09)),
              _trial("S2", "x", 2.0, h_cl(GRID, **TABLE1[("x", 2.0)], mp=0.09))]
    bad = _trial("S3", "x", 1.0, np.zeros(GRID.size, complex) + 1e-30)
    bad[["re", "im"]] = 0.0
    blocks.append(bad)
    spectra = d / "spectra.parquet"
    Spectra.from_frame(pd.concat(blocks, ignore_index=True), meta={}).write(spectra)
    out = d / "trials.csv"
    res = CliRunner().invoke(cli, ["fit-trials", str(spectra), "-o", str(out)])
    return spectra, out, res


def test_fit_trials_fits_each_trial_and_lists_the_failing_one(trial_files):
    spectra, out, res = trial_files
    assert res.exit_code == 0, res.output
    df = pd.read_csv(out, dtype={"subject": str})
    assert list(df["subject"]) == ["S1", "S2", "S3"]
    assert list(df.columns[:4]) == ["axis", "subject", "grip_N", "run"]
    assert df.columns[-1] == "reason"
    for i, grip in ((0, 1.0), (1, 2.0)):      # noise-free Table I responses: exact
        for n in PARAM_NAMES:
            assert df[n].iloc[i] == pytest.approx(TABLE1[("x", grip)][n], rel=1e-3)
        assert bool(df["converged"].iloc[i])
    failed = df.iloc[2]
    assert not bool(failed["converged"]) and np.isnan(failed["Ma"])
    assert "usable bins" in failed["reason"]
    assert "S3" in res.stderr and "no fit" in res.stderr


def test_stability_on_trials_skips_the_failed_row_and_keeps_order(trial_files, runner):
    _, out, _ = trial_files
    res = runner.invoke(cli, ["stability", str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert [m["subject"] for m in doc["models"]] == ["S1", "S2"]
    assert [m["row"] for m in doc["models"]] == [1, 2]
    assert doc["skipped"][0]["row"] == 3 and "usable bins" in doc["skipped"][0]["reason"]
    assert "row 3" in res.stderr and "left out" in res.stderr
    ax = doc["axes"]["x"]
    ks = [m["k_max_N_per_m"] for m in doc["models"]]
    assert ax["k_max_min_N_per_m"] == pytest.approx(min(ks))
    assert ax["limiting_row"] == 1 + int(np.argmin(ks))


def test_stability_json_schema(runner):
    """The document of the issue: settings, models (one per PARAMS row, in order: Table I
    has 9), axes with min/median/p05/n_models per axis; values from the library."""
    res = runner.invoke(cli, ["stability", "grip", "--json", "--delay-samples", "0"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert set(doc) >= {"settings", "models", "axes"}
    assert doc["settings"]["delay_samples"] == 0
    assert doc["settings"]["sample_time_s"] == 1e-3
    assert len(doc["models"]) == 9
    for m in doc["models"]:
        assert set(m) >= {"axis", "grip_N", "subject", "k_max_N_per_m", "f_unstable_hz"}
    assert [(m["axis"], m["grip_N"]) for m in doc["models"]] == \
        [(a, g) for a in "xyz" for g in (1.0, 2.0, 3.0)]
    for a in "xyz":
        s = doc["axes"][a]
        ks = np.array([m["k_max_N_per_m"] for m in doc["models"] if m["axis"] == a])
        assert s["n_models"] == 3
        assert s["k_max_min_N_per_m"] == pytest.approx(ks.min())
        assert s["k_max_median_N_per_m"] == pytest.approx(np.median(ks))
        assert s["k_max_p05_N_per_m"] == pytest.approx(np.percentile(ks, 5))


def test_stability_certificate_says_plainly_when_it_holds_for_no_k(runner):
    res = runner.invoke(cli, ["stability", "nominal", "--weights", "paper", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    # Table III evaluated up to the Nyquist frequency (500 Hz): peaks 1.22 (x, 500 Hz),
    # 1.15 (y, in band) and 1.78 (z, 500 Hz) at K = 0 (tests/test_stability.py checks the
    # in-band values 1.11/1.15/0.77 against the paper's weights)
    for row in doc["models"]:
        assert row["wu_t_peak_k0"] > 1.0 and row["k_robust_N_per_m"] is None
    assert "axis x: the robust certificate holds for no K at all" in res.stderr


def test_stability_csv_output_is_refused_if_it_exists(tmp_path, runner):
    out = tmp_path / "k.csv"
    res = runner.invoke(cli, ["stability", "nominal", "-o", str(out)])
    assert res.exit_code == 0, res.output
    df = pd.read_csv(out)
    assert list(df["axis"]) == ["x", "y", "z"]
    assert df["k_max_N_per_m"].iloc[0] == pytest.approx(3623, rel=2e-3)
    res = runner.invoke(cli, ["stability", "nominal", "-o", str(out)])
    assert res.exit_code == 73
    res = runner.invoke(cli, ["stability", "nominal", "-o", str(out), "--overwrite",
                              "--delay-samples", "0"])
    assert res.exit_code == 0
    assert pd.read_csv(out)["k_max_N_per_m"].iloc[0] > 1e4


@pytest.mark.parametrize("args,text", [(["--sample-time", "0"], "sample-time"),
                                       (["--sample-time", "-1e-3"], "sample-time"),
                                       (["--delay-samples", "-1"], "delay-samples"),
                                       (["--damping", "-2"], "damping")])
def test_stability_bad_settings_exit_2(args, text, runner):
    res = runner.invoke(cli, ["stability", "nominal", *args])
    assert res.exit_code == 2
    assert text in res.stderr and "Traceback" not in res.stderr


def test_stability_unstable_row_warns(runner):
    res = runner.invoke(cli, ["stability", "nominal", "--damping", "500", "--json"])
    assert res.exit_code == 0
    doc = json.loads(res.stdout)
    assert all(m["k_max_N_per_m"] == 0 and m["unstable_at_zero"] for m in doc["models"])
    assert "row 1 (axis x)" in res.stderr and "unstable already at K = 0" in res.stderr


def test_stability_missing_file_exit_66(tmp_path, runner):
    res = runner.invoke(cli, ["stability", str(tmp_path / "none.csv")])
    assert res.exit_code == 66


def test_plot_stability_is_deterministic_and_marks_the_minimum(tmp_path, runner):
    """The CLI's PNG and the library figure saved again are byte-identical (same input,
    same bytes); the figure's minimum line of each axis sits at the smallest K_max of
    `armfit stability` on the same rows (Table II, defaults)."""
    from armfit import figures
    from armfit.models.params import paper_params
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    res = runner.invoke(cli, ["plot", "stability", "nominal", "-o", str(a)])
    assert res.exit_code == 0, res.output
    fig = figures.stability_figure(paper_params("nominal"))
    figures.save_figure(fig, b)
    assert a.read_bytes() == b.read_bytes()
    doc = json.loads(runner.invoke(cli, ["stability", "nominal", "--json"]).stdout)
    seen = set()
    for ax in fig.axes:
        for line in ax.get_lines():
            gid = line.get_gid() or ""
            if gid.startswith("kmin:"):
                axis = gid.split(":")[1]
                seen.add(axis)
                assert line.get_ydata()[0] * 1e3 == pytest.approx(
                    doc["axes"][axis]["k_max_min_N_per_m"])
    assert seen == {"x", "y", "z"}
    sweeps = [ln for ax in fig.axes for ln in ax.get_lines()
              if (ln.get_gid() or "").startswith("sweep-min:x:d1")]
    assert len(sweeps) == 1
    # at 1 kHz (on the sweep grid: 250 Hz in half-octave steps) the d = 1 minimum equals
    # the population minimum of the top row
    x, y = sweeps[0].get_data()
    i = int(np.argmin(np.abs(np.asarray(x) - 1000.0)))
    assert x[i] == pytest.approx(1000.0) and y[i] * 1e3 == pytest.approx(
        doc["axes"]["x"]["k_max_min_N_per_m"], rel=1e-9)


def test_stability_figure_from_sweeps_computed_elsewhere(tmp_path):
    """The stability figure drawn from sweeps computed beforehand (one axis at a time, as
    a run's worker processes compute them) is byte-identical to the figure that computes
    them itself; each sweep's 1 kHz, d = 1 column is K_max of `armfit.loop.stability_table`
    at its defaults (T = 1 ms, d = 1) for the same rows, and a sweep of other rows is
    refused."""
    from armfit import figures
    from armfit.errors import UsageError
    from armfit.loop import WallSettings, stability_table
    from armfit.models.params import paper_params

    rows = paper_params("grip")
    sweeps = {a: figures.stability_sweep(rows[rows["axis"] == a], WallSettings())
              for a in ("x", "y", "z")}
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    figures.save_figure(figures.stability_figure(rows), a)
    figures.save_figure(figures.stability_figure(rows, sweeps=sweeps), b)
    assert a.read_bytes() == b.read_bytes()
    table = stability_table(rows, WallSettings())
    k = list(figures.SWEEP_RATES_HZ).index(1000.0)
    d = list(figures.SWEEP_DELAYS).index(1)
    for axis, sweep in sweeps.items():
        assert sweep.shape == (len(figures.SWEEP_DELAYS), len(figures.SWEEP_RATES_HZ),
                               int((rows["axis"] == axis).sum()))
        want = table.loc[table["axis"] == axis, "k_max_N_per_m"].to_numpy(float)
        np.testing.assert_allclose(sweep[d, k], want, rtol=1e-9)
    with pytest.raises(UsageError, match="sweep of axis x has the shape"):
        figures.stability_figure(rows, sweeps={"x": sweeps["x"][:, :, :1]})


def test_stability_figure_leaves_out_the_effects_outside_the_loop(tmp_path, runner):
    """Table II with a 12 ms delay on every axis: the figure drawn with the delay outside
    the loop marks, on each axis, the lowest K_max `armfit stability --outside-loop
    delay` gives, which is that of Table II without the delay (an independent
    computation), not that of the delayed loop; its sweep's 1 kHz, d = 1 point is the
    same number. `armfit plot stability --outside-loop` and the plot of the
    ``armfit.stability(..., outside_loop=)`` result draw the same bytes as the library."""
    from armfit import figures
    from armfit.loop import WallSettings, stability_table
    from armfit.models.params import paper_params

    plain = paper_params("nominal")
    delayed = plain.assign(effects="delay", **{"delay.delay_s": 0.012})
    params = tmp_path / "delayed.csv"
    delayed.to_csv(params, index=False)
    fig = figures.stability_figure(delayed, outside_loop=("delay",))
    without = stability_table(plain, WallSettings())
    inside = stability_table(delayed, WallSettings())
    doc = json.loads(runner.invoke(cli, ["stability", str(params), "--outside-loop", "delay",
                                         "--json"]).stdout)
    k = list(figures.SWEEP_RATES_HZ).index(1000.0)
    for axis in ("x", "y", "z"):
        want = float(without.loc[without["axis"] == axis, "k_max_N_per_m"].min())
        assert doc["axes"][axis]["k_max_min_N_per_m"] == pytest.approx(want, rel=1e-9)
        assert want > 2 * float(inside.loc[inside["axis"] == axis, "k_max_N_per_m"].min())
        kmin = [ln for ax in fig.axes for ln in ax.get_lines() if ln.get_gid() == f"kmin:{axis}"]
        assert kmin[0].get_ydata()[0] * 1e3 == pytest.approx(want, rel=1e-9)
        line = [ln for ax in fig.axes for ln in ax.get_lines()
                if ln.get_gid() == f"sweep-min:{axis}:d1"]
        assert line[0].get_ydata()[k] * 1e3 == pytest.approx(want, rel=1e-9)
    # a Stability result plots with the effects it left out of the loop
    import armfit
    result = armfit.stability(delayed, outside_loop=["delay"])
    assert result.outside_loop == ("delay",)
    again = tmp_path / "again.png"
    figures.save_figure(result.plot(), again)
    out = tmp_path / "cli.png"
    res = runner.invoke(cli, ["plot", "stability", str(params), "--outside-loop", "delay",
                              "-o", str(out)])
    assert res.exit_code == 0, res.output
    lib = tmp_path / "lib.png"
    figures.save_figure(fig, lib)
    assert out.read_bytes() == lib.read_bytes() == again.read_bytes()
