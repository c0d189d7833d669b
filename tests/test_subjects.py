"""Effects whose values differ between subjects (armfit.diagnosis.subjects and the adopted
model that carries them).

Studies simulated in the time domain by tests/tdsim.py (rational closed loop discretised
and run sample by sample, delays as integer + Thiran fractional delays, drift, sensor
noise and quantisation: not armfit's frequency-domain model), so the truth the
diagnosis must find is the simulator's:

* a latency that differs between subjects (uniform 4–10 ms, everything else in the
  model; 6 subjects here, the 9 of the paper's design in benchmarks/validate_diagnose.py):
  ``delay`` named on every axis with one value per subject, each within 0.5 ms of the
  subject's truth, adequate, nothing else named;
* a stretch reflex whose gain differs between subjects (9 subjects, 50–300 N/m, delay
  40 ms shared; Z, whose stiff hand keeps such reflexes stable — on X and Y the paper's
  arms go unstable above about 100 N/m at 40 ms): ``reflex`` with one gain per subject,
  each within 20 % of the truth, its delay shared, adequate;
* studies whose effects are shared (sample_data/hidden: one 12 ms latency) or absent
  (sample_data/study): exactly the diagnosis of the shared-only search.
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import tdsim  # noqa: E402

from armfit import api  # noqa: E402
from armfit.adopt import adopt  # noqa: E402
from armfit.diagnosis import diagnose_axes, diagnosis_to_dict  # noqa: E402
from armfit.diagnosis.fit import fit_base, fit_by_subject, fit_extend  # noqa: E402
from armfit.diagnosis.responses import axis_data  # noqa: E402
from armfit.models.effects import EFFECTS  # noqa: E402
from armfit.spectra import Spectra  # noqa: E402
from armfit.uncertainty import arm_trials, arm_trials_by_subject  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _truth(folder: Path) -> dict[str, dict]:
    """{subject label: {effect: {param: value}}} of a tdsim study (its truth.json)."""
    trials = json.loads((folder / "truth.json").read_text())["trials"]
    return {f"{t['subject'] + 1:02d}": t["effects"] for t in trials}


def _study(tmp_path_factory, name: str, study: tdsim.Study):
    folder = tdsim.write_study(study, tmp_path_factory.mktemp(name))
    spectra, params = tdsim.estimate_and_fit(folder)
    return folder, spectra, params


@pytest.fixture(scope="module")
def latency(tmp_path_factory):
    """6 subjects whose latency is uniform in 4–10 ms; the diagnosis of all three axes."""
    folder, spectra, params = _study(tmp_path_factory, "latency", tdsim.Study(
        subjects=6, seed=261, subject_effects={"delay": {"delay_s": (0.004, 0.010)}}))
    return folder, spectra, params, diagnose_axes(spectra, params, jobs=2)


@pytest.fixture(scope="module")
def reflex(tmp_path_factory):
    """9 subjects on Z whose reflex gain is uniform in 50–300 N/m, delay 40 ms shared."""
    folder, spectra, params = _study(tmp_path_factory, "reflex", tdsim.Study(
        subjects=9, seed=264, axes=("z",), duration_s=(50.0, 100.0),
        effects={"reflex": {"delay_s": 0.04}},
        subject_effects={"reflex": {"gain_N_per_m": (50.0, 300.0)}}))
    return folder, spectra, params, diagnose_axes(spectra, params, jobs=2)


def test_a_latency_that_differs_between_subjects_is_named_per_subject(latency):
    folder, _, _, result = latency
    truth = _truth(folder)
    assert [d.axis for d in result] == ["x", "y", "z"]
    for d in result:
        # nothing but the delay, per subject, and the model within the noise
        assert [m.effect for m in d.missing_effects] == ["delay"], d.verdict
        (m,) = d.missing_effects
        assert m.varying == ("delay_s",) and d.adequate, d.verdict
        assert set(m.by_subject) == set(truth)
        for subj, values in m.by_subject.items():
            # the simulator's truth, to 0.5 ms (the tolerance)
            assert abs(values["delay_s"] - truth[subj]["delay"]["delay_s"]) < 5e-4, subj
            assert m.by_subject_lo[subj]["delay_s"] <= values["delay_s"] \
                <= m.by_subject_hi[subj]["delay_s"]
        # the verdict says what happened, with the spread of the subjects' values
        assert d.verdict.startswith("delay differs between subjects: delay_s ")
        assert "adequate with one value per subject" in d.verdict
        lo, hi = m.spread["delay_s"]["min"], m.spread["delay_s"]["max"]
        assert lo == min(v["delay_s"] for v in m.by_subject.values())
        assert hi == max(v["delay_s"] for v in m.by_subject.values())
        # the population value is the subjects' mean (delay is a linear parameter)
        assert m.params["delay_s"] == pytest.approx(
            np.mean([v["delay_s"] for v in m.by_subject.values()]), rel=1e-9)


def test_the_json_records_by_subject_under_the_effect(latency):
    _, _, _, result = latency
    doc = json.loads(json.dumps(diagnosis_to_dict(result)))
    for axis in "xyz":
        (eff,) = doc["axes"][axis]["missing_effects"]
        assert eff["varying"] == ["delay_s"]
        assert set(eff["by_subject"]) == {f"{i:02d}" for i in range(1, 7)}
        assert all(set(v) == {"delay_s"} for v in eff["by_subject"].values())
        (test,) = doc["axes"][axis]["subject_tests"]
        assert test["effect"] == "delay" and test["varying"] == ["delay_s"]
        assert test["tried"][0]["kept"] and test["tried"][0]["delta_bic"] > 10


def test_a_reflex_gain_that_differs_between_subjects(reflex):
    folder, _, _, (d,) = reflex
    truth = _truth(folder)
    assert [m.effect for m in d.missing_effects] == ["reflex"], d.verdict
    (m,) = d.missing_effects
    # the gain per subject, the delay shared (as simulated), the model adequate
    assert m.varying == ("gain_N_per_m",) and d.adequate, d.verdict
    assert m.params["delay_s"] == pytest.approx(0.04, abs=0.002)
    for subj, values in m.by_subject.items():
        g = truth[subj]["reflex"]["gain_N_per_m"]
        assert abs(values["gain_N_per_m"] / g - 1) < 0.2, (subj, values, g)
    # the delay was tested per subject too, and one value suffices
    (test,) = d.subject_tests
    assert [(x.param, x.kept) for x in test.trials if x.kept] == [("gain_N_per_m", True)]
    assert any(x.param == "delay_s" and not x.kept for x in test.trials)


@pytest.mark.parametrize("name", ["hidden", "study"])
def test_shared_and_absent_effects_give_the_shared_only_diagnosis(name, sample_runs):
    # sample_data/hidden: one 12 ms latency for every subject; sample_data/study: the
    # paper's model. The search with the per-subject tests gives exactly the diagnosis
    # of the search without them (no by_subject anywhere), only recording its tests;
    # an effect of the arm screened out of the first step differs only in its screening
    # fit's values (screened with one value per subject).
    out = sample_runs(name)      # the sample's spectra and base grip fits, run once
    grip = out / ("grip_params_base.csv" if name == "hidden" else "grip_params.csv")
    spectra, params = out / "spectra.parquet", api.read_model(grip).table
    with_tests = diagnose_axes(spectra, params)
    without = diagnose_axes(spectra, params, by_subject=False)

    def same(d):
        return replace(d, subject_tests=(), candidates=tuple(
            c for c in d.candidates if EFFECTS[c.effect].stage != "arm"))

    # (repr: NaN fields compare equal only as text)
    assert repr([same(d) for d in with_tests]) == repr([same(d) for d in without])
    for a, b in zip(with_tests, without, strict=True):
        assert [c.effect for c in a.candidates] == [c.effect for c in b.candidates]
    for d in with_tests:
        assert all(not m.varying and not m.by_subject for m in d.missing_effects)
        assert "by_subject" not in json.dumps(diagnosis_to_dict([d]))
        if name == "hidden":
            # the delay was tested and one shared value sufficed on every axis
            (test,) = d.subject_tests
            assert test.effect == "delay" and test.varying == ()
            assert test.trials[0].delta_bic < 10
        else:
            assert d.subject_tests == ()     # adequate: no search, nothing to test


def test_one_value_per_subject_is_never_worse_than_one_shared(reflex):
    # the per-subject fit starts every subject at the shared value: nested, its cost is
    # never above the shared fit's, whatever the data (here: a latency and a lag the
    # study does not hold, whose subjects' values can only fit noise)
    _, spectra, params, _ = reflex
    data = axis_data(Spectra.of(spectra), params, "z")
    band = (float(data.f_hz[0]), float(data.f_hz[-1]))
    base = fit_base(data, band)
    for name in ("delay", "lowpass"):
        shared = fit_extend(data, band, base, EFFECTS[name])
        per = fit_by_subject(data, band, shared, [f"{name}.{EFFECTS[name].params[0].name}"])
        assert per.rss <= shared.rss * (1 + 1e-12)
        assert per.n_free - shared.n_free == len(per.by_subject) - 1 == 8


def test_adopted_model_holds_each_subjects_values_in_its_trial_fits(latency):
    _, _, _, result = latency
    ad = adopt(result)
    x = ad["x"]
    assert x.varying == ("delay.delay_s",)
    (m,) = result[0].missing_effects
    for subj, values in m.by_subject.items():
        # 10 significant digits, as the files carry them
        assert x.items_for(subj) == [("delay", {"delay_s": float(f"{values['delay_s']:.10g}")})]
    # Tables I and II hold the subjects' mean; a subject the diagnosis did not see too
    assert x.items() == [("delay", {"delay_s": float(f"{m.params['delay_s']:.10g}")})]
    assert x.items_for("99") == x.items()
    frame = ad.subjects_frame()
    assert len(frame) == 18 and set(frame["axis"]) == {"x", "y", "z"}
    assert frame["per_subject"].all()


def test_apparatus_removed_with_each_subjects_own_values():
    # arm_trials_by_subject against arm_trials row by row (independent: one row per
    # trial with its subject's delay written in)
    f = np.geomspace(0.1, 30, 50)
    rng = np.random.default_rng(0)
    H = (rng.standard_normal((4, f.size)) + 1j * rng.standard_normal((4, f.size))) * 1e-3
    row = {"axis": "x", "Ma": 0.2, "k1": 90.0, "k2": 700.0, "b1": 7.5, "b2": 2.5,
           "mp_kg": 0.09, "effects": "delay", "delay.delay_s": 0.007}
    labels = ["sub-01_grip-1N", "sub-02_grip-1N", "sub-01_grip-2N", "sub-03_grip-1N"]
    by_subject = {"01": {"delay.delay_s": 0.004}, "02": {"delay.delay_s": 0.010}}
    got = arm_trials_by_subject(row, f, H, labels, by_subject, 0.09)
    want = [arm_trials({**row, **by_subject.get(lab[4:6], {})}, f, H[i:i + 1], 0.09)[0]
            for i, lab in enumerate(labels)]
    np.testing.assert_allclose(got, np.array(want), rtol=1e-13)
    # subject 03 has no value of its own: the row's
    np.testing.assert_allclose(got[3], arm_trials(row, f, H[3:4], 0.09)[0], rtol=1e-13)


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    """``armfit run`` on 3 subjects (X only, grips 1 and 2 N) whose latencies are 4.9,
    7.6 and 9.6 ms (uniform 4–10 ms, seed 265)."""
    from click.testing import CliRunner

    from armfit.cli.main import cli
    folder = tdsim.write_study(tdsim.Study(
        subjects=3, axes=("x",), grips_N=(1.0, 2.0), seed=265,
        subject_effects={"delay": {"delay_s": (0.004, 0.010)}}),
        tmp_path_factory.mktemp("run_study"))
    out = tmp_path_factory.mktemp("run") / "out"
    res = CliRunner().invoke(cli, ["-q", "run", str(folder), "-o", str(out), "--no-figures",
                                   "--jobs", "2"])
    assert res.exit_code == 0, res.output
    return folder, out


def test_run_carries_each_subjects_values_to_trial_fits_and_walls(run_folder):
    import pandas as pd

    from armfit.loop import subject_summary
    folder, out = run_folder
    truth = _truth(folder)
    subjects = pd.read_csv(out / "adoption_subjects.csv", dtype={"subject": str})
    per = dict(zip(subjects["subject"], subjects["value"], strict=True))
    for subj, value in per.items():
        assert abs(value - truth[subj]["delay"]["delay_s"]) < 5e-4
    # every trial's fit holds its own subject's latency, as adoption_subjects.csv says
    trials = pd.read_csv(out / "trial_params.csv", dtype={"subject": str})
    assert len(trials) == 6
    for _, r in trials.iterrows():
        assert r["delay.delay_s"] == per[r["subject"]]
        assert "delay.delay_s" in str(r["held"])
    # the walls per subject: the smallest K_max over each subject's trials (an
    # independent minimum of stability.csv), in report.md; the population's is theirs
    stab = pd.read_csv(out / "stability.csv", dtype={"subject": str})
    walls = {s: g["k_max_N_per_m"].min() for s, g in stab.groupby("subject")}
    assert subject_summary(stab)["x"] == pytest.approx(walls)
    report = (out / "report.md").read_text()
    for subj, k in walls.items():
        assert f"| {subj} | {k / 1e3:.3g} |" in report
    assert f"walls up to {min(walls.values()) / 1e3:.3g} kN/m on X" in report
    # Table II holds the subjects' mean latency
    nominal = pd.read_csv(out / "nominal_params.csv")
    assert nominal["delay.delay_s"].iloc[0] == pytest.approx(np.mean(list(per.values())),
                                                             rel=1e-6)
