"""Faults in the params, Wu and spectra files a lab pipeline feeds back to armfit, and what
armfit does with the models they hold: a second row of one model, axes left out, values
no arm or device has, a weight that is not a weight, a certificate its own members
contradict, and messages that must show numbers as numbers.

The expected values come from the contract: the exit codes of armfit.errors (65 bad
data), the one-row-per-model rule of docs/formats.md ("Params CSV"), the ranges of
armfit.io.ranges and armfit.models.arm.BASE_PARAMS (docs/formats.md, "Physical
ranges"), and the row and column where each test writes the bad value.
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

import armfit
from armfit.cli.main import cli
from armfit.errors import EXIT_DATAERR, BadInputError, UsageError
from armfit.io import ranges
from armfit.loop import (
    WITHHELD,
    WallSettings,
    axis_summary,
    certificate_sentence,
    plant_from_model,
    robust_certificate,
    stability_table,
    wall_stability,
)
from armfit.models.arm import ClosedLoopModel, Param
from armfit.models.params import model_from_params, paper_params
from armfit.uncertainty import WuWeight

REPO = Path(__file__).resolve().parents[1]
TABLE3 = REPO / "armfit" / "data" / "table3_uncertainty_weights.csv"

# a small simulated study: 2 subjects x axes x, z x grips 1, 2 N


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def error_line(res) -> str:
    """The one stderr line of a refused command (no traceback)."""
    assert "Traceback" not in res.stderr, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert lines and lines[-1].startswith("armfit:"), res.stderr
    return lines[-1]


def edited(src: Path, dest: Path, edit) -> Path:
    """``src`` (a CSV) with ``edit(DataFrame) -> DataFrame`` applied, written to ``dest``."""
    edit(pd.read_csv(src, dtype={"effects": str, "at_bound": str})).to_csv(dest, index=False)
    return dest


def paper_nominal(tmp_path: Path, **changes) -> Path:
    """Table II as a params file (x, y, z rows), with ``changes`` {column: (row, value)}."""
    df = paper_params("nominal")
    for col, (row, value) in changes.items():
        df[col] = df[col].astype(object)
        df.loc[row - 1, col] = value
    path = tmp_path / "table2.csv"
    df.to_csv(path, index=False)
    return path


# ---------------------------------------------------------------------------
# One row per model: a second row of an axis (grip, trial) is refused by every reader
# ---------------------------------------------------------------------------

def _commands(spectra, path, tmp_path):
    return {
        "compare": ["compare", spectra, "--model", path],
        "fit-uncertainty": ["fit-uncertainty", spectra, "--nominal", path, "-o",
                            tmp_path / "wu.csv"],
        "stability": ["stability", path],
        "plot bode": ["plot", "bode", spectra, "--model", path, "-o", tmp_path / "b.png"],
        "plot uncertainty": ["plot", "uncertainty", spectra, "--nominal", path, "-o",
                             tmp_path / "u.png"],
    }


@pytest.mark.parametrize("command", ["compare", "fit-uncertainty", "stability", "plot bode",
                                     "plot uncertainty"])
def test_a_second_row_of_an_axis_in_a_nominal_file_is_refused(command, spectra, nominal,
                                                               tmp_path):
    # the x row repeated with another arm mass: which model is x? (docs/formats.md: a
    # nominal file has one row per axis); before, compare and stability used the first
    # row (exit 0) and fit-uncertainty named no file
    bad = edited(nominal, tmp_path / "dup.csv",
                 lambda df: pd.concat([df.iloc[:1], df.iloc[:1].assign(Ma=0.3), df.iloc[1:]]))
    res = invoke(*_commands(spectra, bad, tmp_path)[command])
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(
        f"{bad}, column 'axis', row 2: axis x has a second row (rows 1 and 2); a nominal "
        "params file has one row per axis")
    assert not (tmp_path / "wu.csv").exists()


def test_a_second_row_of_a_grip_is_refused(spectra, grip, tmp_path):
    # rows 1 and 3 of the edited file are both axis x at 1 N (one row per axis and grip)
    bad = edited(grip, tmp_path / "dup.csv",
                 lambda df: pd.concat([df.iloc[:2], df.iloc[:1], df.iloc[2:]]))
    res = invoke("compare", spectra, "--model", bad)
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(
        f"{bad}, column 'grip_N', row 3: axis x, grip 1 N has a second row (rows 1 and 3); "
        "a grip params file has one row per axis and grip")


def test_a_second_row_of_a_trial_is_refused(tmp_path):
    # a per-trial file (subject column) with trial x / S1 / 1 N in rows 1 and 2
    rows = paper_params("nominal").iloc[[0, 0, 2]].assign(subject=["S1", "S1", "S1"],
                                                          grip_N=1.0, run=np.nan)
    bad = tmp_path / "trials.csv"
    rows.to_csv(bad, index=False)
    res = invoke("stability", bad)
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(
        f"{bad}, column 'subject', row 2: axis x, subject S1, grip 1 N has a second row "
        "(rows 1 and 2); a per-trial params file has one row per trial (axis, subject, "
        "grip, run)")


def test_a_second_row_given_to_the_python_api_is_refused(spectra, nominal):
    # a DataFrame gets the checks of a file (before: the first x row was used)
    df = pd.read_csv(nominal)
    dup = pd.concat([df.iloc[:1], df], ignore_index=True)
    with pytest.raises(BadInputError, match=r"column 'axis', row 2: axis x has a second row"):
        armfit.compare(spectra, dup)
    with pytest.raises(BadInputError, match=r"column 'axis', row 2: axis x has a second row"):
        armfit.stability(dup)


# ---------------------------------------------------------------------------
# A subset of the axes is a legitimate study: said on stderr and in --json
# ---------------------------------------------------------------------------

def test_fit_uncertainty_says_which_axes_get_no_weight(spectra, nominal, tmp_path):
    only_x = edited(nominal, tmp_path / "only_x.csv", lambda df: df[df["axis"] == "x"])
    out = tmp_path / "wu.csv"
    res = invoke("fit-uncertainty", spectra, "--nominal", only_x, "-o", out, "--json")
    assert res.exit_code == 0, res.stderr
    # the spectra hold derived trials of x and z (FAULT_SIM); the file has no z row
    note = (f"axis z: {spectra} holds derived trials but {only_x} has no row for it; no "
            "weight is fitted for axis z")
    assert f"note: {note}" in res.stderr
    doc = json.loads(res.stdout)
    assert doc["notes"] == [note]
    assert [a["axis"] for a in doc["axes"]] == ["x"]


def test_compare_says_which_axes_and_grips_are_not_compared_with_their_own_row(
        spectra, nominal, grip, tmp_path):
    only_x = edited(nominal, tmp_path / "only_x.csv", lambda df: df[df["axis"] == "x"])
    res = invoke("compare", spectra, "--model", only_x, "--json")
    assert res.exit_code == 0, res.stderr
    note = (f"axis z: {spectra} holds median-level measurements but {only_x} has no row "
            "for it; axis z is not compared")
    assert f"note: {note}" in res.stderr
    assert json.loads(res.stdout)["notes"] == [note]
    # a grip file without the 2 N rows: the 2 N means are compared with the 1 N rows
    one_n = edited(grip, tmp_path / "one_n.csv", lambda df: df[df["grip_N"] == 1.0])
    res = invoke("compare", spectra, "--model", one_n, "--json")
    assert res.exit_code == 0, res.stderr
    notes = json.loads(res.stdout)["notes"]
    assert notes == [f"axis {a}: {one_n} has no row for grip 2 N; its mean is compared "
                     "with the row of the nearest grip, 1 N" for a in "xz"]


def test_diagnose_says_which_axes_it_leaves_out(spectra, nominal, tmp_path):
    only_x = edited(nominal, tmp_path / "only_x.csv", lambda df: df[df["axis"] == "x"])
    res = invoke("diagnose", spectra, "--model", only_x, "--max-steps", "0", "--effect",
                 "delay", "--json")
    assert res.exit_code == 0, res.stderr
    note = (f"axis z: {spectra} holds trial-level measurements but {only_x} has no row "
            "for it; axis z is not diagnosed")
    assert f"note: {note}" in res.stderr
    doc = json.loads(res.stdout)
    assert doc["notes"] == [note] and list(doc["axes"]) == ["x"]


def test_a_complete_file_gives_no_notes(spectra, nominal):
    # the JSON of a normal run is unchanged: no "notes" key (tests/test_output_hashes.py)
    res = invoke("compare", spectra, "--model", nominal, "--json")
    assert res.exit_code == 0
    assert "notes" not in json.loads(res.stdout) and "note:" not in res.stderr


# ---------------------------------------------------------------------------
# Physical ranges: one check wherever params are read
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("value, shown", [(-0.3, "-0.3 kg"), ("nan", "nan"),
                                          (1e300, "1e+300 kg")])
@pytest.mark.parametrize("command", ["compare", "fit-uncertainty", "stability", "plot bode"])
def test_device_mass_outside_its_range(command, value, shown, spectra, nominal, tmp_path):
    # row 2 (axis z) of the nominal file; the range is armfit.io.ranges.DEVICE_MASS_RANGE.
    # Before: 1e300 gave K_max 0 with exit 0 in stability
    bad = edited(nominal, tmp_path / "mp.csv",
                 lambda df: df.assign(mp_kg=df["mp_kg"].astype(object)).pipe(
                     lambda d: d.assign(mp_kg=[d["mp_kg"].iloc[0], value])))
    res = invoke(*_commands(spectra, bad, tmp_path)[command])
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(
        f"{bad}, column 'mp_kg', row 2: device mass = {shown} is outside its physical "
        "range [0.0001, 1000] kg")


@pytest.mark.parametrize("column, value, expect", [
    # armfit.models.arm.BASE_PARAMS: k1 in [1, 30000] N/m, Ma in [0.01, 30] kg
    ("k1", 1e300, "k1 = 1e+300 N/m is outside its physical range [1, 30000] N/m"),
    ("Ma", -0.3, "Ma = -0.3 kg is outside its physical range [0.01, 30] kg"),
    ("mp_kg", -0.3, "device mass = -0.3 kg is outside its physical range [0.0001, 1000] kg"),
])
def test_stability_refuses_absurd_params(column, value, expect, tmp_path):
    bad = paper_nominal(tmp_path, **{column: (3, value)})
    for args in (["stability", bad], ["stability", "nominal", "--weights", "paper",
                                      "--members", bad]):
        res = invoke(*args)
        assert res.exit_code == EXIT_DATAERR
        assert error_line(res).endswith(f"{bad}, column '{column}', row 3: {expect}")


def test_grip_force_outside_its_range(spectra, grip, tmp_path):
    # armfit.io.ranges.GRIP_FORCE_RANGE: [0, 1000] N
    bad = edited(grip, tmp_path / "g.csv", lambda df: df.assign(
        grip_N=[-1.0] + list(df["grip_N"].iloc[1:])))
    res = invoke("compare", spectra, "--model", bad)
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(f"{bad}, column 'grip_N', row 1: grip force = -1.0 N is "
                                    "outside its physical range [0, 1000] N")


def test_device_mass_given_to_the_python_api_is_bad_data_not_usage(tmp_path):
    # the same fault through the API: BadInputError (exit 65) naming column and row,
    # as the files; before, the model's own check raised UsageError (exit 2)
    df = paper_params("nominal")
    df.loc[1, "mp_kg"] = -0.3
    with pytest.raises(BadInputError) as info:
        armfit.stability(df)
    assert not isinstance(info.value, UsageError)
    assert str(info.value) == ("column 'mp_kg', row 2: device mass = -0.3 kg is outside its "
                               "physical range [0.0001, 1000] kg")


# ---------------------------------------------------------------------------
# Wu files: the same check, and a weight that is a weight
# ---------------------------------------------------------------------------

def _table3_with(tmp_path: Path, edit) -> Path:
    lines = TABLE3.read_text().splitlines()
    path = tmp_path / "wu_bad.csv"
    path.write_text("\n".join(edit(lines)) + "\n")
    return path


WU_FAULTS = {
    # data row 1 is x's gain (Table III layout); the range is io.ranges.WU_GAIN_RANGE.
    # Before: exit 0, the JSON claiming the certificate up to K_max, the text none
    "gain 1e300": (lambda ls: [ls[0], "x,gain,0,1e300,0", *ls[2:]],
                   "column 'real', row 1: Wu gain K = 1e+300 is outside its physical "
                   "range [1e-06, 1e+06]"),
    "gain -2": (lambda ls: [ls[0], "x,gain,0,-2,0", *ls[2:]],
                "column 'real', row 1: Wu gain K = -2.0 is outside its physical range "
                "[1e-06, 1e+06]"),
    # x's fifth zero pair (data row 6) repeated at the end (row 30); before: accepted,
    # a sixth zero that changes the certificate
    "duplicate row": (lambda ls: [*ls, ls[6]],
                      "column 'index', row 30: axis x has a second zero of index 5 (rows 6 "
                      "and 30); each zero pair is one row"),
    # a fourth zero pair on z, which has three pole pairs (rows 24-29): improper
    "improper": (lambda ls: [*ls, "z,zero,4,-3,1"],
                 "column 'kind', row 30: Wu of axis z has 4 zero pairs and 3 pole pairs: "
                 "improper (|Wu| grows without bound with frequency); an uncertainty "
                 "weight has at most as many zeros as poles"),
    # z's first pole pair (data row 27) at -1e300 rad/s: io.ranges.WU_ROOT_RANGE
    "pole 1e300": (lambda ls: [*ls[:27], "z,pole,1,-1e300,19.85", *ls[28:]],
                   "column 'real', row 27: |pole| of Wu of axis z = 1e+300 rad/s is outside "
                   "its physical range [0.0001, 1e+07] rad/s"),
}


@pytest.mark.parametrize("fault", list(WU_FAULTS))
@pytest.mark.parametrize("command", ["stability", "fit-uncertainty", "plot uncertainty"])
def test_absurd_or_malformed_wu_is_refused(fault, command, spectra, nominal, tmp_path):
    edit, expect = WU_FAULTS[fault]
    wu = _table3_with(tmp_path, edit)
    args = {"stability": ["stability", "nominal", "--weights", wu, "--json"],
            "fit-uncertainty": ["fit-uncertainty", spectra, "--nominal", nominal, "-o",
                                tmp_path / "wu.csv", "--check-weights", wu],
            "plot uncertainty": ["plot", "uncertainty", spectra, "--nominal", nominal,
                                 "--weights", wu, "-o", tmp_path / "u.png"]}[command]
    res = invoke(*args)
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(f"{wu}, {expect}")
    assert res.stdout == ""
    assert not (tmp_path / "wu.csv").exists() and not (tmp_path / "u.png").exists()


SUMMARY = ("axis,weight,target,cost,order,n_trials,smooth_oct,band_lo_hz,band_hi_hz,"
           "n_points,coverage_pct,coverage_between_pct,tightness_median_db,"
           "tightness_max_db,tightness_min_db,mean_gap_db,converged\n")


@pytest.mark.parametrize("rows, expect", [
    # the band x's weight was fitted over, given twice (rows 1 and 2): which one?
    (["x,fitted,wmax,envelope,5,4,,0.1,30,100,100,100,0.3,1,0,0.4,True",
      "x,fitted,wmax,envelope,5,4,,0.1,10,100,100,100,0.3,1,0,0.4,True"],
     "column 'axis', row 2: axis x has a second fitted band (rows 1 and 2)"),
    # a band edge of 1e300 Hz: armfit.io.ranges.FREQUENCY_RANGE
    (["x,fitted,wmax,envelope,5,4,,0.1,1e300,100,100,100,0.3,1,0,0.4,True"],
     "column 'band_hi_hz', row 1: frequency = 1e+300 Hz is outside its physical range "
     "[1e-06, 1e+06] Hz"),
])
def test_a_wu_summary_that_does_not_say_one_band_is_refused(rows, expect, tmp_path):
    # the summary beside a Wu file sets the band the certificate trusts; before, a bad
    # one was used (the last row) or silently replaced by the paper's 0.01-30 Hz
    wu = tmp_path / "wu.csv"
    shutil.copy(TABLE3, wu)
    summary = tmp_path / "wu_summary.csv"
    summary.write_text(SUMMARY + "\n".join(rows) + "\n")
    res = invoke("stability", "nominal", "--weights", wu)
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(f"{summary}, {expect}")
    summary.write_text("axis,weight\nx,fitted\n")
    res = invoke("stability", "nominal", "--weights", wu)
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(f"{summary}, column 'target': missing column; expected "
                                    "the summary fit-uncertainty writes beside its weights")


# ---------------------------------------------------------------------------
# The certificate: JSON and text from one source, never more than the data prove
# ---------------------------------------------------------------------------

def test_json_and_text_of_stability_say_the_same(tmp_path):
    # Table III around Table II (docs/methods.md: the certificate holds for no K on any
    # axis, peaks 1.22, 1.15, 1.78); the JSON's certificate_text is the stderr line
    res = invoke("stability", "nominal", "--weights", "paper", "--json")
    assert res.exit_code == 0, res.stderr
    doc = json.loads(res.stdout)
    said = [ln for ln in res.stderr.splitlines() if ln.startswith("axis ")]
    assert said == [doc["axes"][a]["certificate_text"] for a in "xyz"]
    for a in "xyz":
        assert doc["axes"][a]["certificate"] == "fails at K = 0"
        assert doc["axes"][a]["k_robust_min_N_per_m"] is None
        assert all(m["k_robust_N_per_m"] is None for m in doc["models"])


def test_a_weight_whose_t_is_not_a_number_certifies_nothing():
    # |Wu T| overflows (a gain of 1e300 given through the API, past the file check):
    # before, the certificate claimed K up to the nominal K_max while the text said none
    model, theta = model_from_params(paper_params("nominal").iloc[0])
    settings = WallSettings()
    k_max = wall_stability([plant_from_model(model, theta)], settings)[0].k_max_N_per_m
    huge = WuWeight(1e300, np.array([-2 + 3j] * 5), np.array([-5 + 1j] * 5))
    with np.errstate(all="ignore"):
        cert = robust_certificate(model, theta, huge, settings, band_hz=(0.01, 30.0),
                                  k_max_N_per_m=k_max)
    assert not cert.holds and cert.limited_by == ""
    table = stability_table(paper_params("nominal").assign(row=[1, 2, 3]).iloc[:1],
                            settings, weights={"x": huge})
    summary = axis_summary(table)
    assert summary["x"]["certificate"] == "fails at K = 0"
    assert math.isnan(summary["x"]["k_robust_min_N_per_m"])


def _members_file(tmp_path: Path, b1_factor: float) -> Path:
    """Two per-trial models of axis x around Table II's: the hand damping b1 scaled by
    ``b1_factor`` and by 1 (above the arm's corner the arm is the hand: |H/H̄ − 1| tends
    to |1/b1_factor − 1|)."""
    x = paper_params("nominal").iloc[[0, 0]].reset_index(drop=True)
    x["b1"] = x["b1"] * np.array([b1_factor, 1.0])
    x = x.assign(subject=["S1", "S2"], grip_N=1.0, run=np.nan)
    path = tmp_path / f"members_{b1_factor:g}.csv"
    x.to_csv(path, index=False)
    return path


def test_certificate_is_withheld_when_members_go_beyond_the_weight(tmp_path):
    # a constant weight |Wu| = 0.3 (gain only): a member whose b1 is half the nominal's
    # departs by |1/0.5 - 1| = 1 > 0.3 above the band, so beyond_margin > 1 and the
    # certificate's assumption fails; before, k_robust was finite (and the report said
    # "holds for K up to ... — beyond the weight")
    wu = tmp_path / "wu.csv"
    wu.write_text("axis,kind,index,real,imag\nx,gain,0,0.3,0\n")
    params = paper_nominal(tmp_path)
    members = _members_file(tmp_path, 0.5)
    out = tmp_path / "st.csv"
    res = invoke("stability", params, "--weights", wu, "--members", members, "-o", out)
    assert res.exit_code == 0, res.stderr
    row = pd.read_csv(out, keep_default_na=False).iloc[0]
    assert row["axis"] == "x" and row["k_robust_N_per_m"] == ""
    assert row["limited_by"] == WITHHELD
    assert float(row["beyond_margin"]) > 1.0 and float(row["k_weight_N_per_m"]) > 0
    assert (f"axis x: the robust certificate is withheld on 1 of 1 model(s): above the "
            f"weight's band the member models depart from the nominal by up to "
            f"{float(row['beyond_margin']):.4f} × |Wu|") in res.stderr
    doc = json.loads(invoke("stability", params, "--weights", wu, "--members", members,
                            "--json").stdout)
    assert doc["axes"]["x"]["certificate"] == "withheld"
    assert doc["axes"]["x"]["k_robust_min_N_per_m"] is None
    assert doc["models"][0]["k_robust_N_per_m"] is None
    # members within the weight (b1 x 0.9: |1/0.9 - 1| = 0.11 < 0.3): it holds
    res = invoke("stability", params, "--weights", wu, "--members",
                 _members_file(tmp_path, 0.9), "--json")
    doc = json.loads(res.stdout)
    assert doc["axes"]["x"]["certificate"] == "holds"
    assert doc["models"][0]["beyond_margin"] <= 1.0
    assert doc["models"][0]["k_robust_N_per_m"] > 0


def test_members_without_an_axis_are_said(tmp_path):
    # the members cap and check the certificate of their own axis only: y and z of
    # Table II have weights (Table III) but no member
    members = _members_file(tmp_path, 0.9)
    res = invoke("stability", "nominal", "--weights", "paper", "--members", members,
                 "--json")
    assert res.exit_code == 0, res.stderr
    notes = json.loads(res.stdout)["notes"]
    assert notes == [f"{members} has no model of axis {a}: its certificate is neither "
                     "capped at a member's K_max nor checked above the band" for a in "yz"]
    assert all(f"note: {n}" in res.stderr for n in notes)


def test_certificate_sentence_counts_every_reason():
    rows = [{"f_peak_k0_hz": 5.0, "k_robust_N_per_m": math.nan, "limited_by": WITHHELD,
             "k_max_N_per_m": 900.0, "wu_t_peak_k0": 0.4, "beyond_margin": 1.25},
            {"f_peak_k0_hz": 5.0, "k_robust_N_per_m": math.nan, "limited_by": "",
             "k_max_N_per_m": 900.0, "wu_t_peak_k0": 1.5, "beyond_margin": 0.5}]
    assert certificate_sentence("y", rows) == (
        "axis y: the robust certificate holds for no K at all on 1 of 2 model(s): max |Wu "
        "T| is already 1.500 > 1 at K = 0 (the weight allows more than 100 % relative "
        "uncertainty where the device's own impedance dominates); it is withheld on 1 of "
        "2 model(s): above the weight's band the member models depart from the nominal by "
        "up to 1.2500 × |Wu| (beyond_margin > 1), so the weight does not cover them there "
        "and the assumption the certificate rests on does not hold")


def test_report_says_why_a_certificate_holds_for_no_k():
    # one line per nominal model of certificate.csv, its reason from the same status
    # (armfit.loop.certificate_status) as the stability command's text and JSON
    from armfit.report import _certificate_lines
    nan = math.nan
    cert = pd.DataFrame([
        {"axis": "x", "k_max_N_per_m": 900.0, "wu_t_peak_k0": 1.2, "f_peak_k0_hz": 8.0,
         "k_robust_N_per_m": nan, "limited_by": "", "k_weight_N_per_m": nan,
         "beyond_margin": 0.5},
        {"axis": "y", "k_max_N_per_m": 900.0, "wu_t_peak_k0": 0.4, "f_peak_k0_hz": 8.0,
         "k_robust_N_per_m": nan, "limited_by": WITHHELD, "k_weight_N_per_m": 91.6,
         "beyond_margin": 1.0023},
        {"axis": "z", "k_max_N_per_m": nan, "wu_t_peak_k0": nan, "f_peak_k0_hz": nan,
         "k_robust_N_per_m": nan, "limited_by": "", "k_weight_N_per_m": nan,
         "beyond_margin": nan}])
    lines = _certificate_lines(cert)[2:]
    assert lines == [
        "- X: holds for no K at all (max |Wu T| is 1.20 > 1 already at K = 0, at 8 Hz).",
        "- Y: withheld: above the weight's band the trials' models depart from the nominal "
        "by up to 1.0023 × |Wu|, so the weight does not cover them there and the "
        "assumption the certificate rests on does not hold (what the weight alone would "
        "certify: 0.0916 kN/m).",
        "- Z: no weight for this axis; no certificate."]


@pytest.mark.slow
def test_hidden_study_withholds_the_z_certificate(tmp_path):
    # sample_data/hidden: on Z the trials depart from the nominal above the weight's band
    # by 1.0023 x |Wu| (beyond_margin); before, certificate.csv claimed K up to 0.0916
    # kN/m there and the report said it held
    out = tmp_path / "h"
    res = invoke("run", REPO / "sample_data" / "hidden", "-o", out, "--no-figures")
    assert res.exit_code == 0, res.stderr
    cert = pd.read_csv(out / "certificate.csv", keep_default_na=False).set_index("axis")
    z = cert.loc["z"]
    assert float(z["beyond_margin"]) > 1.0
    assert z["k_robust_N_per_m"] == "" and z["limited_by"] == WITHHELD
    report = (out / "report.md").read_text()
    assert "- Z: withheld: above the weight's band the trials' models depart" in report
    assert "- Z: holds for K up to" not in report


# ---------------------------------------------------------------------------
# Spectra files: bad frequencies are bad data
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("value, shown", [(-0.3, "-0.3 Hz"), (0.0, "0.0 Hz"),
                                          (np.inf, "inf")])
@pytest.mark.parametrize("command", ["fit-nominal", "compare", "fit-uncertainty"])
def test_spectra_with_a_bad_frequency(command, value, shown, spectra, nominal, tmp_path):
    # row 4 of the spectra table; armfit.io.ranges.FREQUENCY_RANGE. Before: a negative
    # frequency was fitted (exit 0) or refused as a usage error (exit 2)
    df = pd.read_parquet(spectra)
    df.loc[df.index[3], "freq_hz"] = value
    bad = tmp_path / "s.parquet"
    df.to_parquet(bad)
    args = {"fit-nominal": ["fit-nominal", bad, "-o", tmp_path / "n.csv"],
            "compare": ["compare", bad, "--model", nominal],
            "fit-uncertainty": ["fit-uncertainty", bad, "--nominal", nominal, "-o",
                                tmp_path / "wu.csv"]}[command]
    res = invoke(*args)
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(f"{bad}, column 'freq_hz', row 4: frequency = {shown} "
                                    "is outside its physical range [1e-06, 1e+06] Hz")


def test_spectra_metadata_with_a_negative_device_mass(spectra, nominal, tmp_path):
    # the device mass the derived dynamics were estimated with (metadata mp_kg), used by
    # fit-uncertainty to remove the apparatus: the same range as a params file's
    import pyarrow.parquet as pq
    table = pq.read_table(spectra)
    meta = json.loads(table.schema.metadata[b"armfit"])
    meta["mp_kg"]["x"] = -0.3
    bad = tmp_path / "s.parquet"
    pq.write_table(table.replace_schema_metadata({b"armfit": json.dumps(meta)}), bad)
    res = invoke("fit-uncertainty", bad, "--nominal", nominal, "-o", tmp_path / "wu.csv")
    assert res.exit_code == EXIT_DATAERR
    assert error_line(res).endswith(
        f"{bad}: the device mass of axis x in the metadata (mp_kg) = -0.3 kg is outside "
        "its physical range [0.0001, 1000] kg")


def test_estimate_refuses_a_device_mass_no_reader_accepts(study, tmp_path):
    # the option is a usage error (exit 2), with the range of io.ranges.DEVICE_MASS_RANGE
    # that every reader of the spectra applies; before, 1e300 kg was written (exit 0)
    out = tmp_path / "s.parquet"
    res = invoke("estimate", study, "-o", out, "--mp", "x=1e300")
    assert res.exit_code == 2
    assert error_line(res).endswith("device mass must be given as axis x|y|z and a mass in "
                                    "[0.0001, 1000] kg, got x=1e+300")
    assert not out.exists()


# ---------------------------------------------------------------------------
# Messages show numbers as numbers (numpy >= 2 writes np.float64(-0.3) for repr)
# ---------------------------------------------------------------------------

def test_messages_show_numpy_numbers_plainly():
    cases = [
        (lambda: WallSettings(sample_time_s=np.float64(-0.3)), "got -0.3"),
        (lambda: WallSettings(damping_Ns_per_m=np.float64(-0.3)), "got -0.3"),
        (lambda: WallSettings(delay_samples=np.float64(0.5)), "got 0.5"),
        (lambda: Param("m", "kg", np.float64(np.nan), 1.0, 0.5), "got nan"),
        (lambda: armfit.stability(paper_params("nominal"), sample_time_s=np.float64(-0.3)),
         "got -0.3"),
    ]
    for call, expect in cases:
        with pytest.raises(armfit.ArmfitError) as info:
            call()
        assert expect in str(info.value) and "np." not in str(info.value), str(info.value)


def test_spectra_option_messages_show_numpy_integers_plainly():
    from armfit.spectra import log_grid, welch_spectra
    with pytest.raises(UsageError) as info:
        log_grid(0.1, 30.0, np.int64(0))
    assert str(info.value) == "per_decade=0 must be >= 1"
    with pytest.raises(UsageError) as info:
        welch_spectra(np.zeros(16), np.zeros(16), 1.0, nperseg=np.int64(32))
    assert str(info.value) == "nperseg=32 exceeds the record length 16"


def test_no_message_formats_a_value_with_the_debug_specifier():
    # f"{x=}" writes repr(x): np.int64(5) for a numpy integer; every message of the
    # package writes its numbers through format or armfit.errors.cell instead
    import ast
    found = []
    for path in sorted((REPO / "armfit").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.JoinedStr):
                parts = node.values
                for a, b in zip(parts, parts[1:], strict=False):
                    if isinstance(a, ast.Constant) and isinstance(b, ast.FormattedValue) \
                            and str(a.value).endswith("=") and b.conversion == ord("r") \
                            and str(a.value).rstrip("=").split()[-1:] == \
                            [ast.unparse(b.value)]:
                        found.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert found == []


# ---------------------------------------------------------------------------
# The ranges are documented where the formats are
# ---------------------------------------------------------------------------

def test_physical_ranges_table_in_formats_md_matches_the_code():
    text = (REPO / "docs" / "formats.md").read_text(encoding="utf-8")
    section = text.split("## Physical ranges", 1)[1].split("\n## ", 1)[0]
    for rng in (ranges.DEVICE_MASS_RANGE, ranges.GRIP_FORCE_RANGE, ranges.WU_GAIN_RANGE,
                ranges.WU_ROOT_RANGE, ranges.FREQUENCY_RANGE):
        assert re.search(rf"\| {re.escape(rng.words().split(' ')[0])}", section) or \
            rng.words() in section, rng
    from armfit.models.arm import BASE_PARAMS
    for q in BASE_PARAMS:
        assert f"`{q.name}`" in section and f"[{q.lower:g}, {q.upper:g}]" in section, q.name


def test_a_good_study_is_read_unchanged(spectra, nominal, grip, tmp_path):
    # the checks refuse nothing armfit writes: every command above on the study's own
    # files exits 0
    shutil.copy(nominal, tmp_path / "n.csv")
    for args in (["compare", spectra, "--model", nominal],
                 ["compare", spectra, "--model", grip],
                 ["stability", nominal, "--weights", "paper"],
                 ["fit-uncertainty", spectra, "--nominal", tmp_path / "n.csv", "-o",
                  tmp_path / "wu.csv"]):
        res = invoke(*args)
        assert res.exit_code == 0, (args, res.stderr)
    res = invoke("stability", tmp_path / "n.csv", "--weights", tmp_path / "wu.csv")
    assert res.exit_code == 0, res.stderr


def test_model_of_a_row_keeps_the_closed_loop_device_mass():
    # the range admits the paper's device (0.09 kg, eq. 2): the model is built with it
    model, _ = model_from_params(paper_params("nominal").iloc[0])
    assert isinstance(model, ClosedLoopModel) and model.mp == pytest.approx(0.09)
