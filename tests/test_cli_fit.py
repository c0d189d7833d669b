"""`armfit fit-grip` / `armfit fit-nominal` on spectra files in the SPECTRA_COLUMNS schema."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from armfit.cli.main import cli
from armfit.data import paper_table
from armfit.errors import BadInputError
from armfit.io.schema import SPECTRA_COLUMNS, params_columns
from armfit.models.arm import PARAM_NAMES, h_cl
from armfit.models.params import model_from_params, read_params
from armfit.spectra import Spectra, aggregate, aggregate_spread

PAPER_COLS = ["Ma_kg", "k1_N_per_m", "k2_N_per_m", "b1_Ns_per_m", "b2_Ns_per_m"]
MP = {"x": 0.09, "y": 0.095, "z": 0.091}  # paper eq. 2
GRID = np.geomspace(0.1, 30, 61)          # 25 points per decade, 0.1-30 Hz
SUBJECTS = ("S1", "S2", "S3", "S4")


def _block(level, subject, axis, grip, h, se_db, se_deg, n, run=None):
    db = 20 * np.log10(np.abs(h))
    return pd.DataFrame({
        "level": level, "subject": subject, "axis": axis, "grip_N": grip,
        "run": pd.array([run] * GRID.size, dtype="Int64"), "kind": "measured",
        "out_axis": axis, "method": "h1", "freq_hz": GRID, "re": h.real, "im": h.imag,
        "mag_db": db, "phase_deg": np.degrees(np.unwrap(np.angle(h))), "coherence": 0.99,
        "se_db": se_db, "se_deg": se_deg, "n": n, "q25_db": db, "q75_db": db,
        "q25_deg": 0.0, "q75_deg": 0.0, "flags": ""})


def _truth(table: str) -> dict:
    out = {}
    for _, r in paper_table(table).iterrows():
        key = (r["axis"], float(r["grip_N"])) if table == "grip" else r["axis"]
        out[key] = dict(zip(PARAM_NAMES, r[PAPER_COLS].astype(float), strict=True))
    return out


TABLE1 = _truth("grip")
TABLE2 = _truth("nominal")


@pytest.fixture(scope="module")
def spectra_file(tmp_path_factory):
    """A spectra file whose mean rows are exactly Table I's H_CL (eq. 4) and whose median
    rows are exactly Table II's. Trial rows: 4 subjects per axis x grip, each Table I's
    response times log-normal deviations (0.5 dB, 3 deg per bin) centred across subjects,
    so the mean of dB and of phase (armfit.spectra.aggregate) is the model's exactly."""
    rng = np.random.default_rng(0)
    blocks = []
    for (axis, grip), p in TABLE1.items():
        h0 = h_cl(GRID, mp=MP[axis], **p)
        d_db = rng.normal(0, 0.5, (len(SUBJECTS), GRID.size))
        d_deg = rng.normal(0, 3.0, (len(SUBJECTS), GRID.size))
        d_db -= d_db.mean(axis=0)
        d_deg -= d_deg.mean(axis=0)
        hs = h0 * 10 ** (d_db / 20) * np.exp(1j * np.radians(d_deg))
        for s, h in zip(SUBJECTS, hs, strict=True):
            blocks.append(_block("trial", s, axis, grip, h, np.nan, np.nan, 1, run=1))
        spread = aggregate_spread(hs, "mean")
        blocks.append(_block("mean", None, axis, grip, aggregate(hs, "mean"),
                             spread["se_db"], spread["se_deg"], len(SUBJECTS)))
    for axis, p in TABLE2.items():
        blocks.append(_block("median", None, axis, np.nan, h_cl(GRID, mp=MP[axis], **p),
                             0.3, 2.0, 12))
    df = pd.concat(blocks, ignore_index=True)[list(SPECTRA_COLUMNS)]
    path = tmp_path_factory.mktemp("spectra") / "spectra.parquet"
    Spectra.from_frame(df, meta={"method": "h1"}).write(path)
    return path


@pytest.fixture(scope="module")
def grip_run(spectra_file, tmp_path_factory):
    from click.testing import CliRunner
    out = tmp_path_factory.mktemp("grip")
    res = CliRunner().invoke(cli, ["fit-grip", str(spectra_file), "-o", str(out / "g.csv"),
                                   "--latex", str(out / "g.tex"), "--json"])
    return res, out


def test_fit_grip_recovers_table_one(grip_run):
    res, out = grip_run
    assert res.exit_code == 0, res.output
    df = pd.read_csv(out / "g.csv")
    # the params CSV columns of docs/formats.md, in order
    assert list(df.columns) == params_columns(PARAM_NAMES, grip=True)
    assert len(df) == 9
    for _, row in df.iterrows():
        truth = TABLE1[(row["axis"], float(row["grip_N"]))]
        for n in PARAM_NAMES:
            # exact model response -> within the 0.1 % acceptance (Table I)
            assert row[n] == pytest.approx(truth[n], rel=1e-3), (row["axis"], n)
            assert row[f"{n}_lo"] <= row[n] <= row[f"{n}_hi"]
        # bands as the paper: X, Y 0.1-30 Hz; Z 0.1-10 Hz (nearest grid points inside)
        hi = 10.0 if row["axis"] == "z" else 30.0
        assert row["band_lo_hz"] == pytest.approx(0.1)
        assert hi / 10 ** (1 / 25) < row["band_hi_hz"] <= hi
        assert row["converged"]
        assert row["cost"] == "complex"  # the default
        assert row["mp_kg"] == MP[row["axis"]]
    assert df["effects"].isna().all()  # no effects: empty field


def test_fit_grip_json_and_latex(grip_run):
    res, out = grip_run
    payload = json.loads(res.stdout)
    assert payload["command"] == "fit-grip"
    assert len(payload["fits"]) == 9
    first = payload["fits"][0]
    assert first["axis"] == "x" and first["grip_N"] == 1.0
    assert first["ci_method"] == "jacobian"
    assert first["Ma"] == pytest.approx(0.1925, rel=1e-3)  # Table I, X 1 N
    tex = (out / "g.tex").read_text()
    for token in (r"\toprule", r"\midrule", r"\bottomrule", "Grip (N)", r"$M_a$ (kg)"):
        assert token in tex
    # one row per fit: 9 lines ending in \\ after the header line
    assert tex.count("\\\\") == 10


def test_fit_nominal_recovers_table_two(runner, spectra_file, tmp_path):
    out = tmp_path / "n.csv"
    res = runner.invoke(cli, ["fit-nominal", str(spectra_file), "-o", str(out),
                              "--cost", "paper"])
    assert res.exit_code == 0, res.output
    df = read_params(out)
    assert "grip_N" not in df.columns
    assert list(df["axis"]) == ["x", "y", "z"]
    for _, row in df.iterrows():
        for n in PARAM_NAMES:
            # Table II, exact response: within 0.1 %
            assert row[n] == pytest.approx(TABLE2[row["axis"]][n], rel=1e-3)
        # the model rebuilt from the file gives back eq. 4 at Table II
        model, theta = model_from_params(row)
        np.testing.assert_allclose(model.response(GRID, theta),
                                   h_cl(GRID, mp=MP[row["axis"]], **TABLE2[row["axis"]]),
                                   rtol=1e-3)
    # the cost used is recorded; exact data leave no magnitude error
    assert set(df["cost"]) == {"paper"}
    assert (df["rms_db"] < 1e-4).all()


def test_not_converging_exits_3_and_writes_nothing(runner, spectra_file, tmp_path,
                                                  solver_stops_at_budget):
    # The solver reports that it stopped at its evaluation budget (an injected result).
    out, tex = tmp_path / "g.csv", tmp_path / "g.tex"
    res = runner.invoke(cli, ["fit-grip", str(spectra_file), "-o", str(out), "--latex",
                              str(tex), "--max-nfev", "1"])
    assert res.exit_code == 3
    assert "did not converge" in res.stderr
    assert "axis x, grip 1 N" in res.stderr
    assert "Traceback" not in res.stderr
    assert res.stdout == ""
    assert not out.exists() and not tex.exists()
    assert list(tmp_path.iterdir()) == []  # no temporary left behind


def test_existing_output_needs_overwrite(runner, spectra_file, tmp_path):
    out = tmp_path / "n.csv"
    out.write_text("keep me")
    res = runner.invoke(cli, ["fit-nominal", str(spectra_file), "-o", str(out)])
    assert res.exit_code == 73
    assert "--overwrite" in res.stderr
    assert out.read_text() == "keep me"
    res = runner.invoke(cli, ["fit-nominal", str(spectra_file), "-o", str(out), "--overwrite"])
    assert res.exit_code == 0
    assert out.read_text().startswith("axis,Ma,k1,k2,b1,b2,")


def test_input_errors(runner, spectra_file, tmp_path):
    out = tmp_path / "n.csv"
    res = runner.invoke(cli, ["fit-nominal", str(tmp_path / "none.parquet"), "-o", str(out)])
    assert res.exit_code == 66 and "no such spectra file" in res.stderr
    res = runner.invoke(cli, ["fit-nominal", str(spectra_file), "-o", str(out), "--band",
                              "q=1:2"])
    assert res.exit_code == 2 and "expected AXIS=LO:HI" in res.stderr
    res = runner.invoke(cli, ["fit-nominal", str(spectra_file), "-o", str(out), "--effect",
                              "gremlin"])
    assert res.exit_code == 2 and "unknown effect 'gremlin'" in res.stderr
    # a spectra table without aggregates: exit 65 naming the file and the column
    df = pd.read_parquet(spectra_file)
    trials_only = tmp_path / "trials.parquet"
    Spectra.from_frame(df[df["level"] == "trial"], meta={}).write(trials_only)
    res = runner.invoke(cli, ["fit-nominal", str(trials_only), "-o", str(out)])
    assert res.exit_code == 65
    assert f"{trials_only}, column 'level'" in res.stderr
    assert "no rows with level 'median'" in res.stderr
    assert not out.exists()


def test_seed_does_not_change_the_fit(runner, spectra_file, tmp_path):
    # The fit uses no random numbers (fixed Sobol starts): --seed only drives bootstrap.
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    for path, seed in ((a, "1"), (b, "2")):
        res = runner.invoke(cli, ["fit-nominal", str(spectra_file), "-o", str(path),
                                  "--seed", seed])
        assert res.exit_code == 0
    assert a.read_text() == b.read_text()


def test_effect_adds_columns(runner, spectra_file, tmp_path):
    out = tmp_path / "n.csv"
    res = runner.invoke(cli, ["fit-nominal", str(spectra_file), "-o", str(out), "--effect",
                              "device-mass", "--band", "z=0.1:30"])
    assert res.exit_code == 0, res.stderr
    df = read_params(out)
    names = list(PARAM_NAMES) + ["device-mass.mass_kg"]
    assert list(df.columns) == params_columns(names, grip=False)
    assert set(df["effects"]) == {"device-mass"}
    for _, row in df.iterrows():
        # The data are eq. 4 with the paper's Mp (eq. 2): the fitted device mass is Mp and
        # the arm is Table II's, both within 0.1 %.
        assert row["device-mass.mass_kg"] == pytest.approx(MP[row["axis"]], rel=1e-3)
        for n in PARAM_NAMES:
            assert row[n] == pytest.approx(TABLE2[row["axis"]][n], rel=1e-3)
    # the band option applies to z only
    assert df.loc[df["axis"] == "z", "band_hi_hz"].item() == pytest.approx(30.0)
    assert df.loc[df["axis"] == "x", "band_hi_hz"].item() == pytest.approx(30.0)
    model, theta = model_from_params(df.iloc[0])
    assert [e.name for e in model.effects] == ["device-mass"]
    assert set(theta) == set(names)


def test_bootstrap_intervals(runner, spectra_file, tmp_path):
    out = tmp_path / "g.csv"
    res = runner.invoke(cli, ["fit-grip", str(spectra_file), "-o", str(out), "--bootstrap",
                              "20", "--seed", "3", "--json"])
    assert res.exit_code == 0, res.stderr
    fits = json.loads(res.stdout)["fits"]
    assert {f["ci_method"] for f in fits} == {"bootstrap-20"}
    df = read_params(out)
    for _, row in df.iterrows():
        truth = TABLE1[(row["axis"], float(row["grip_N"]))]
        for n in PARAM_NAMES:
            # the deviations are centred, so the full-sample fit is Table I; the percentile
            # interval of 20 resampled refits brackets it
            assert row[f"{n}_lo"] <= truth[n] * (1 + 1e-6)
            assert row[f"{n}_hi"] >= truth[n] * (1 - 1e-6)
            assert row[f"{n}_lo"] < row[f"{n}_hi"]


def test_read_params_errors(tmp_path, spectra_file, runner):
    good = tmp_path / "n.csv"
    assert runner.invoke(cli, ["fit-nominal", str(spectra_file), "-o", str(good)]
                         ).exit_code == 0
    df = pd.read_csv(good)
    missing = tmp_path / "missing.csv"
    df.drop(columns=["k2_hi"]).to_csv(missing, index=False)
    with pytest.raises(BadInputError, match=r"missing\.csv, column 'k2_hi'"):
        read_params(missing)
    negative = tmp_path / "negative.csv"
    df.assign(b1=[7.0, -1.0, 7.0]).to_csv(negative, index=False)
    # BASE_PARAMS bounds b1 to [0.05, 1000] N*s/m (armfit.models.arm)
    with pytest.raises(BadInputError, match=r"column 'b1', row 2: b1 = -1.0 N\*s/m is outside "
                                            r"its physical range \[0.05, 1000\]"):
        read_params(negative)


@pytest.fixture(scope="module")
def simulated_fits(tmp_path_factory):
    """A small simulated study without between-subject variability (4 subjects, grip 2 N
    only, 100 s trials, the simulator's default noise, drift and quantisation), estimated
    with `armfit estimate` defaults, then fitted by fit-grip and fit-nominal."""
    from click.testing import CliRunner
    runner = CliRunner()
    d = tmp_path_factory.mktemp("sim")
    steps = [
        ["simulate", "-o", str(d / "study"), "--subjects", "4", "--grips", "2",
         "--duration", "100,100", "--variability", "0", "--seed", "0"],
        ["estimate", str(d / "study"), "-o", str(d / "spectra.parquet")],
        ["fit-grip", str(d / "spectra.parquet"), "-o", str(d / "grip.csv")],
        ["fit-nominal", str(d / "spectra.parquet"), "-o", str(d / "nominal.csv")],
    ]
    for args in steps:
        res = runner.invoke(cli, ["-q", *args])
        assert res.exit_code == 0, (args[0], res.stderr)
    return read_params(d / "grip.csv"), read_params(d / "nominal.csv")


@pytest.mark.parametrize("which", ["grip", "nominal"])
def test_simulated_study_recovers_table_one(simulated_fits, which):
    # Truth: with variability 0 every simulated subject has Table I's 2 N row, so both the
    # mean per axis x grip and the median per axis (one grip simulated) are that row.
    df = simulated_fits[0 if which == "grip" else 1]
    assert list(df["axis"]) == ["x", "y", "z"]
    for _, row in df.iterrows():
        truth = TABLE1[(row["axis"], 2.0)]
        for n in PARAM_NAMES:
            est, lo, hi = row[n], row[f"{n}_lo"], row[f"{n}_hi"]
            # acceptance: within 2 %
            assert est == pytest.approx(truth[n], rel=0.02), (row["axis"], n)
            # acceptance: inside the reported 95 % interval (the estimator's band averages
            # are corrected for the response's curvature, so no systematic error is left
            # that the intervals would not cover)
            assert lo <= truth[n] <= hi, (row["axis"], n, lo, truth[n], hi)
            assert lo < est < hi
