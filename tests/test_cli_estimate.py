"""`armfit estimate` end to end: simulated study in, spectra Parquet out."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from armfit.cli.main import cli
from armfit.errors import BadInputError
from armfit.io.schema import SPECTRA_COLUMNS
from armfit.models.arm import h_arm
from armfit.simulation import StudyConfig, plan_study
from armfit.spectra import Spectra

SIM = ["--subjects", "2", "--axes", "xz", "--grips", "1,2", "--duration", "30,40",
       "--seed", "5"]
SIM_CONFIG = StudyConfig(subjects=2, axes=("x", "z"), grips_N=(1.0, 2.0),
                         duration_s=(30.0, 40.0), seed=5)


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> dict[str, Path]:
    from click.testing import CliRunner
    root = tmp_path_factory.mktemp("est")
    res = CliRunner().invoke(cli, ["simulate", "-o", str(root / "study"), *SIM])
    assert res.exit_code == 0, res.output
    out = root / "spectra.parquet"
    res = CliRunner().invoke(cli, ["estimate", str(root / "study"), "-o", str(out),
                                   "--csv", str(root / "spectra.csv"), "--json"])
    assert res.exit_code == 0, res.output
    return {"root": root, "study": root / "study", "out": out, "csv": root / "spectra.csv",
            "json": json.loads(res.stdout)}


def test_output_schema_metadata_and_summary(study):
    df = Spectra.read(study["out"]).to_frame()
    assert list(df.columns) == list(SPECTRA_COLUMNS)
    meta = df.attrs["armfit"]
    assert meta["method"] == "h1" and meta["derived_method"] == "tfestimate"
    assert meta["mp_kg"] == {"x": 0.09, "y": 0.095, "z": 0.091}  # paper eq. 2
    assert len(meta["grid_hz"]) == 100  # 40 per decade over 0.1-30 Hz
    # 8 trials (2 subjects x 2 axes x 2 grips); each has measured, derived and 2 cross
    trials = df[df["level"] == "trial"]
    assert trials.groupby(["subject", "axis", "grip_N"]).ngroups == 8
    # the alternative rows: H2 of each trial's X/F, beside the measured H1
    assert sorted(trials["kind"].unique()) == ["alternative", "cross", "derived", "measured"]
    alt = trials[trials["kind"] == "alternative"]
    assert set(alt["method"]) == {"h2"} and len(alt) == len(trials[
        (trials["kind"] == "measured")])
    # the aggregates are of measured, derived and cross responses only
    assert "alternative" not in set(df[df["level"] != "trial"]["kind"])
    # mean: per axis x grip, n = 2 subjects; median: per axis, grip NaN, n = 4 trials
    mean = df[(df["level"] == "mean") & (df["kind"] == "measured")]
    assert mean.groupby(["axis", "grip_N"]).ngroups == 4 and set(mean["n"]) == {2}
    med = df[(df["level"] == "median") & (df["kind"] == "measured")]
    assert set(med["n"]) == {4} and med["grip_N"].isna().all()
    summary = study["json"]
    assert summary["trials"] == 8 and summary["rows"] == len(df)
    csv = pd.read_csv(study["csv"])
    assert list(csv.columns) == list(SPECTRA_COLUMNS) and len(csv) == len(df)


def test_estimate_matches_simulated_truth_within_error_bars(study):
    df = Spectra.read(study["out"]).to_frame()
    plans = {(p.subject, p.axis, p.grip_N): p for p in plan_study(SIM_CONFIG)}
    inside_m, inside_d = [], []
    for (subj, axis, grip), rows in df[df["level"] == "trial"].groupby(
            ["subject", "axis", "grip_N"]):
        plan = plans[(subj, axis, grip)]
        m = rows[rows["kind"] == "measured"]
        h = m["re"].to_numpy() + 1j * m["im"].to_numpy()
        truth = plan.response(m["freq_hz"].to_numpy())  # the simulator's known H_CL
        err = 20 * np.log10(np.abs(h / truth))
        inside_m.append(np.abs(err) <= 2 * m["se_db"].to_numpy())
        d = rows[rows["kind"] == "derived"]
        hd = d["re"].to_numpy() + 1j * d["im"].to_numpy()
        arm = h_arm(d["freq_hz"].to_numpy(), **dict(plan.params))  # analytic eq. 3
        inside_d.append(np.abs(20 * np.log10(np.abs(hd / arm))) <= 2 * d["se_db"].to_numpy())
    # 95 % of Gaussian errors fall within 2 se; >= 85 % leaves room for correlation
    # between neighbouring grid points and the coarse error bars of the lowest bands
    assert np.mean(inside_m) >= 0.85
    assert np.mean(inside_d) >= 0.85


def test_jobs_2_gives_the_same_table(runner, study, tmp_path):
    out = tmp_path / "j2.parquet"
    res = runner.invoke(cli, ["estimate", str(study["study"]), "-o", str(out), "-j", "2"])
    assert res.exit_code == 0, res.output
    a, b = Spectra.read(study["out"]).to_frame(), Spectra.read(out).to_frame()
    pd.testing.assert_frame_equal(a, b)  # same numbers, same order (deterministic)


def test_chebwin_method(runner, study, tmp_path):
    out = tmp_path / "cheb.parquet"
    res = runner.invoke(cli, ["estimate", str(study["study"]), "-o", str(out),
                              "--method", "chebwin", "--fmax", "10", "--per-decade", "10"])
    assert res.exit_code == 0, res.output
    df = Spectra.read(out).to_frame()
    assert set(df.loc[df["kind"] == "measured", "method"]) == {"chebwin"}
    # round(10 * log10(100)) + 1 = 21 grid points, 0.1 .. 10 Hz
    assert df["freq_hz"].nunique() == 21 and df["freq_hz"].max() == pytest.approx(10.0)


def test_existing_output_needs_overwrite(runner, study):
    res = runner.invoke(cli, ["estimate", str(study["study"]), "-o", str(study["out"])])
    assert res.exit_code == 73
    assert "exists; pass --overwrite" in res.stderr and "Traceback" not in res.stderr


def test_fmax_above_nyquist(runner, study, tmp_path):
    out = tmp_path / "s.parquet"
    res = runner.invoke(cli, ["estimate", str(study["study"]), "-o", str(out),
                              "--fmax", "600"])
    assert res.exit_code == 2  # usage error
    assert "above the Nyquist frequency 500 Hz" in res.stderr
    assert not out.exists()


def test_too_short_for_fmin(runner, study, tmp_path):
    out = tmp_path / "s.parquet"
    res = runner.invoke(cli, ["estimate", str(study["study"]), "-o", str(out),
                              "--fmin", "0.02"])  # needs 2/0.02 = 100 s, trials are 30-40 s
    assert res.exit_code == 65
    assert "sub-01_axis-x_grip-1N.parquet" in res.stderr and "too short" in res.stderr
    assert not out.exists()


def test_bad_trial_stops_or_is_skipped(runner, study, tmp_path):
    folder = tmp_path / "study"
    shutil.copytree(study["study"], folder)
    (folder / "sub-09_axis-x_grip-1N.csv").write_text("time_s,force_x_N\n0,1\n")
    out = tmp_path / "s.parquet"
    res = runner.invoke(cli, ["estimate", str(folder), "-o", str(out)])
    assert res.exit_code == 65
    assert "sub-09_axis-x_grip-1N.csv" in res.stderr and "pos_x" in res.stderr
    assert not out.exists()
    res = runner.invoke(cli, ["estimate", str(folder), "-o", str(out), "--skip-bad", "--json",
                              "--fmax", "10", "--per-decade", "5"])
    assert res.exit_code == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["trials"] == 8
    assert [s["file"] for s in summary["skipped"]] == [str(folder / "sub-09_axis-x_grip-1N.csv")]


def test_bad_mp_option(runner, study, tmp_path):
    res = runner.invoke(cli, ["estimate", str(study["study"]), "-o", str(tmp_path / "s.parquet"),
                              "--mp", "w=0.1"])
    assert res.exit_code == 2 and "AXIS=KG" in res.stderr


def test_mp_override_changes_derived_only(runner, study, tmp_path):
    out = tmp_path / "mp.parquet"
    res = runner.invoke(cli, ["estimate", str(study["study"]), "-o", str(out),
                              "--mp", "x=0.2"])
    assert res.exit_code == 0, res.stderr
    a, b = Spectra.read(study["out"]).to_frame(), Spectra.read(out).to_frame()
    assert b.attrs["armfit"]["mp_kg"]["x"] == 0.2
    sel = (a["level"] == "trial") & (a["axis"] == "x")
    meas = sel & (a["kind"] == "measured")
    np.testing.assert_array_equal(a.loc[meas, "re"], b.loc[meas, "re"])
    der = sel & (a["kind"] == "derived")
    assert not np.allclose(a.loc[der, "re"], b.loc[der, "re"])


def test_read_spectra_missing_column(tmp_path, study):
    df = pd.read_parquet(study["out"]).drop(columns=["se_db"])
    path = tmp_path / "bad.parquet"
    df.to_parquet(path)
    with pytest.raises(BadInputError, match=r"bad\.parquet, column 'se_db': missing column"):
        Spectra.read(path).to_frame()
