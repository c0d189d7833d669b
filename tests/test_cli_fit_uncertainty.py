"""Tests of ``armfit fit-uncertainty`` on a small simulated study (simulate → estimate →
fit-nominal → fit-uncertainty), and its error paths.

Reference values: W_max recomputed here from the spectra file and the nominal
parameters with plain numpy (eq. 6, H_ARM of eq. 3), Wu evaluated with
scipy.signal.freqs_zpk (scipy's definition of a zero-pole-gain response), the layout of
the paper's Table III CSV, and the exit codes documented in armfit/errors.py.
"""

import json
from importlib import resources

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from scipy import signal

from armfit.cli.main import cli
from armfit.data import paper_table
from armfit.io.schema import WU_SUMMARY_COLUMNS
from armfit.models.arm import h_arm
from armfit.uncertainty import read_wu

BAND = (0.2, 30.0)  # the spectra below start at 0.2 Hz: the default band is limited to it


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """2 subjects × 3 axes × 3 grips, 20–25 s trials; derived spectra from 0.2 Hz."""
    d = tmp_path_factory.mktemp("study")
    steps = [
        ("simulate", "-o", d / "raw", "--subjects", 2, "--duration", "20,25", "--seed", 5),
        ("estimate", d / "raw", "-o", d / "spectra.parquet", "--fmin", 0.2),
        ("fit-nominal", d / "spectra.parquet", "-o", d / "nominal.csv"),
    ]
    for step in steps:
        res = invoke(*step)
        assert res.exit_code == 0, res.output
    return d


@pytest.fixture(scope="module")
def default_run(study):
    out = study / "fit" / "wu.csv"
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal",
                 study / "nominal.csv", "-o", out, "--check-weights", "paper",
                 "--latex", study / "fit" / "wu.tex", "--json")
    assert res.exit_code == 0, res.output
    return res, out


def independent_wmax(study, axis):
    """W_max of eq. 6 from the files, with numpy only: max over trials |H/H_ARM − 1|."""
    spec = pd.read_parquet(study / "spectra.parquet")
    sel = spec[(spec.level == "trial") & (spec.kind == "derived") & (spec.axis == axis)
               & (spec.out_axis == axis)]
    f = np.sort(sel.freq_hz.unique())
    nom = pd.read_csv(study / "nominal.csv").set_index("axis").loc[axis]
    hn = h_arm(f, nom.Ma, nom.k1, nom.k2, nom.b1, nom.b2)
    errs = [np.abs((g.sort_values("freq_hz").re.to_numpy() + 1j * g.sort_values(
        "freq_hz").im.to_numpy()) / hn - 1) for _, g in sel.groupby(["subject", "grip_N"])]
    return f, np.max(errs, axis=0), len(errs)


def wu_db_scipy(weight, f):
    z = np.concatenate([weight.zeros, weight.zeros.conj()])
    p = np.concatenate([weight.poles, weight.poles.conj()])
    _, h = signal.freqs_zpk(z, p, weight.gain, worN=2 * np.pi * f)
    return 20 * np.log10(np.abs(h))


def test_writes_table3_layout_stable_minimum_phase(default_run):
    _, out = default_run
    df = pd.read_csv(out)
    assert list(df.columns) == list(paper_table("uncertainty").columns)
    assert set(df.kind) == {"gain", "zero", "pole"}
    for axis, w in read_wu(out).items():
        # Root location: every zero and pole in the open left half plane.
        assert np.all(w.pole_roots.real < 0), axis
        assert np.all(w.zero_roots.real < 0), axis
        assert len(w.zeros) == len(w.poles) <= 5  # N_n = N_d, at most 5 pairs


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_coverage_on_simulated_study(study, default_run, axis):
    # |Wu| from the CSV (scipy) ≥ W_max recomputed from the files, at every grid point of
    # the band and on 20 points per interval between them (W_max interpolated log-log).
    _, out = default_run
    f, wm, n = independent_wmax(study, axis)
    assert n == 6  # 2 subjects × 3 grips
    band = (f >= BAND[0]) & (f <= BAND[1])
    f, wdb = f[band], 20 * np.log10(wm[band])
    w = read_wu(out)[axis]
    assert np.all(wu_db_scipy(w, f) >= wdb - 1e-7)
    fd = np.exp(np.linspace(np.log(f[0]), np.log(f[-1]), 20 * f.size))
    assert np.all(wu_db_scipy(w, fd) >= np.interp(np.log(fd), np.log(f), wdb) - 1e-7)


def test_summary_and_points_files(study, default_run):
    _, out = default_run
    summary = pd.read_csv(out.with_name("wu_summary.csv"))
    assert tuple(summary.columns) == WU_SUMMARY_COLUMNS
    fitted = summary[summary.weight == "fitted"]
    assert list(fitted.axis) == ["x", "y", "z"]
    assert (fitted.coverage_pct == 100).all() and (fitted.coverage_between_pct == 100).all()
    assert (fitted.band_lo_hz == BAND[0]).all() and (fitted.band_hi_hz == BAND[1]).all()
    # Table III evaluated side by side, one row per axis.
    assert list(summary[summary.weight == "paper"].axis) == ["x", "y", "z"]
    points = pd.read_csv(out.with_name("wu_wmax.csv"))
    f, wm, _ = independent_wmax(study, "y")
    np.testing.assert_allclose(points[points.axis == "y"].wmax_db, 20 * np.log10(wm),
                               rtol=1e-8)


def test_json_on_stdout_matches_files(default_run):
    res, out = default_run
    doc = json.loads(res.stdout)
    assert doc["command"] == "fit-uncertainty"
    weights = read_wu(out)
    for ax in doc["axes"]:
        assert ax["gain"] == pytest.approx(weights[ax["axis"]].gain, rel=1e-9)
        assert len(ax["poles"]) == ax["order"] == len(weights[ax["axis"]].poles)
    assert "Wu x:" in res.stderr and "Wu x:" not in res.stdout


def test_latex_table(study, default_run):
    tex = (study / "fit" / "wu.tex").read_text()
    assert r"Axis & $K$ & Zeros & Poles \\" in tex and r"\pm" in tex


def test_paper_cost_given_order(study, tmp_path):
    out = tmp_path / "wu.csv"
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal",
                 study / "nominal.csv", "-o", out, "--cost", "paper", "--order", 2)
    assert res.exit_code == 0, res.output
    df = pd.read_csv(out)
    assert (df.groupby("axis").kind.value_counts().unstack()[["zero", "pole"]] == 2).all().all()
    summary = pd.read_csv(tmp_path / "wu_summary.csv")
    assert set(summary.cost) == {"paper"} and set(summary.order) == {2}


def test_smoothing_band_and_order(study, tmp_path):
    out = tmp_path / "wu.csv"
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal",
                 study / "nominal.csv", "-o", out, "--smooth", "1/3", "--band", "0.5:20",
                 "--order", 1)
    assert res.exit_code == 0, res.output
    s = pd.read_csv(tmp_path / "wu_summary.csv")
    assert set(s.target) == {"wmax", "wmax_smoothed"}
    np.testing.assert_allclose(s.smooth_oct, 1 / 3, rtol=1e-9)  # CSV: 10 significant digits
    assert (s.band_lo_hz >= 0.5).all() and (s.band_hi_hz <= 20).all()
    # The fit envelopes its own (smoothed) target completely.
    assert (s[s.target == "wmax_smoothed"].coverage_pct == 100).all()


# --- error paths ------------------------------------------------------------------------

def test_existing_output_needs_overwrite(study, tmp_path):
    out = tmp_path / "wu.csv"
    out.write_text("keep")
    args = ["fit-uncertainty", study / "spectra.parquet", "--nominal", study / "nominal.csv",
            "-o", out, "--order", 0]
    res = invoke(*args)
    assert res.exit_code == 73 and "exists; pass --overwrite" in res.output
    assert out.read_text() == "keep" and not (tmp_path / "wu_summary.csv").exists()
    res = invoke(*args, "--overwrite")
    assert res.exit_code == 0, res.output
    assert pd.read_csv(out).kind.tolist() == ["gain"] * 3  # order 0: K only, per axis


def test_existing_sidecar_stops_before_writing(study, tmp_path):
    (tmp_path / "wu_wmax.csv").write_text("keep")
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal",
                 study / "nominal.csv", "-o", tmp_path / "wu.csv")
    assert res.exit_code == 73 and "wu_wmax.csv" in res.output
    assert not (tmp_path / "wu.csv").exists()


@pytest.mark.parametrize("extra, code, match", [
    (["--band", "30:1"], 2, "--band '30:1': expected LO:HI"),
    (["--smooth", "abc"], 2, "--smooth 'abc': expected a window width in octaves"),
    (["--order", "6"], 2, "0<=x<=5"),
    (["--cost", "minimax"], 2, "minimax"),
])
def test_usage_errors(study, tmp_path, extra, code, match):
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal",
                 study / "nominal.csv", "-o", tmp_path / "wu.csv", *extra)
    assert res.exit_code == code
    assert match in res.output and "Traceback" not in res.output
    assert not (tmp_path / "wu.csv").exists()


def test_missing_inputs_exit_66(study, tmp_path):
    res = invoke("fit-uncertainty", tmp_path / "none.parquet", "--nominal",
                 study / "nominal.csv", "-o", tmp_path / "wu.csv")
    assert res.exit_code == 66 and "none.parquet: no such spectra file" in res.output
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal",
                 tmp_path / "none.csv", "-o", tmp_path / "wu.csv")
    assert res.exit_code == 66 and "none.csv: no such params file" in res.output


def test_bad_check_weights_names_file_column_row(study, tmp_path):
    with resources.as_file(resources.files("armfit.data").joinpath(
            "table3_uncertainty_weights.csv")) as p:
        text = p.read_text()
    bad = tmp_path / "weights.csv"
    # x pole 3 is data row 9 (gain 1, zeros 2–6, poles 7–11)
    bad.write_text(text.replace("x,pole,3,", "x,pol,3,"))
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal",
                 study / "nominal.csv", "-o", tmp_path / "wu.csv", "--check-weights", bad)
    assert res.exit_code == 65
    assert f"{bad}, column 'kind', row 9: expected one of gain, zero, pole" in res.output
    assert not (tmp_path / "wu.csv").exists()


def test_grip_params_rejected(study, tmp_path):
    nominal = pd.read_csv(study / "nominal.csv")
    nominal.insert(1, "grip_N", 1.0)
    grip = tmp_path / "grip.csv"
    nominal.to_csv(grip, index=False)
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal", grip,
                 "-o", tmp_path / "wu.csv")
    assert res.exit_code == 65 and "column 'grip_N'" in res.output
    assert not (tmp_path / "wu.csv").exists()


def test_latex_must_differ_from_outputs(study, tmp_path):
    # the LaTeX table ends in .tex, so it cannot be one of the CSV outputs
    res = invoke("fit-uncertainty", study / "spectra.parquet", "--nominal",
                 study / "nominal.csv", "-o", tmp_path / "wu.csv", "--latex",
                 tmp_path / "wu_summary.csv")
    assert res.exit_code == 2 and "--latex" in res.output \
        and "fit-uncertainty writes .tex; not .csv" in res.output
