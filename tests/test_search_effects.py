"""The global search with an effect on the stiff Z arm, and honest convergence.

The study is simulated by armfit's own simulator with a first-order lag at 18 Hz on the
Z axis (``lowpass`` cutoff_hz=18) and no between-subject variability, so the truth of
every fit is known: the arm parameters of the paper's Table I, Z rows (k1 = 4877, 2196,
3289 N/m at 1, 2, 3 N) and the cutoff 18 Hz. Three subjects of 40 s trials on Z only
keep it small. With this seed the search before the structured starts (paper rows, the
analytic guess with the effect removed) ended the 1 N and 3 N fits at k1 ≈ 80–100 N/m,
50–70 times the noise, and called them converged.
"""

from __future__ import annotations

import numpy as np
import pytest

from armfit import api
from armfit.errors import ConvergenceError
from armfit.fitting import FAR_FROM_NOISE, MARKEDLY_LOWER, fit_response
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import EFFECTS
from armfit.models.params import paper_params
from armfit.simulation import EffectSetting

CUTOFF_HZ = 18.0
BAND_Z = (0.1, 30.0)
#: The far local minimum the search used to report for Z 2 N (the issue's numbers).
FAR_START = {"Ma": 6.5, "k1": 253.0, "k2": 485.0, "b1": 59.6, "b2": 42.0,
             "lowpass.cutoff_hz": 27.3}


@pytest.fixture(scope="module")
def lag_study():
    lag = EffectSetting.from_parsed("lowpass", {"cutoff_hz": CUTOFF_HZ}, axes=("z",))
    sim = api.simulate(subjects=3, axes=("z",), duration_s=(40.0, 40.0), seed=2,
                       variability=0.0, effects=(lag,))
    return api.estimate(list(sim.trials()))


def _truth(grip: float) -> dict[str, float]:
    t = paper_params("grip")
    row = t[(t["axis"] == "z") & (t["grip_N"] == grip)].iloc[0]
    return {n: float(row[n]) for n in ("Ma", "k1", "k2", "b1", "b2")}


def _mean_response(spectra, grip: float):
    m = spectra.select(kind="measured", level="mean", axis="z", grip=grip)
    m = m.take(m.key("out_axis") == m.key("axis"))
    return m.row(0)


def test_grip_fits_with_lowpass_reach_the_noise_at_the_true_stiffness(lag_study):
    """Every Z grip fit with the lag ends within the noise, at Table I's k1 and the
    simulated cutoff (truth: Table I Z rows, 18 Hz)."""
    table = api.fit_grip(lag_study, effects=["lowpass"], bands={"z": BAND_Z}).table
    assert sorted(table["grip_N"]) == [1.0, 2.0, 3.0]
    for _, row in table.iterrows():
        truth = _truth(row["grip_N"])
        assert row["converged"]
        assert row["rms_norm"] < 2.0, row.to_dict()
        assert row["k1"] == pytest.approx(truth["k1"], rel=0.1), row.to_dict()
        assert row["Ma"] == pytest.approx(truth["Ma"], rel=0.2), row.to_dict()
        assert row["lowpass.cutoff_hz"] == pytest.approx(CUTOFF_HZ, rel=0.1)


def test_diagnosis_names_the_lag_on_z_and_is_adequate(lag_study):
    """The diagnosis from the base grip fits (no effect, the paper's Z band) names
    lowpass on Z at the simulated 18 Hz and ends within the noise (truth: 18 Hz lag)."""
    base = api.fit_grip(lag_study)
    (d,) = api.diagnose(lag_study, base, effects=["delay", "lowpass", "device-mass"]).axes
    assert d.axis == "z"
    assert [m.effect for m in d.missing_effects] == ["lowpass"], d.verdict
    assert d.missing_effects[0].params["cutoff_hz"] == pytest.approx(CUTOFF_HZ, rel=0.1)
    assert d.adequate, d.verdict
    assert d.verdict.startswith("adequate after adding lowpass")


def test_local_fit_from_a_far_start_is_not_called_converged(lag_study):
    """A fit refined from the far local minimum (k1 = 253 N/m) stays there, several times
    the noise; the structured starts reach the noise, so it is reported not converged,
    with the reason, and the global search from the same data finds the truth (Table I
    Z 2 N, 18 Hz)."""
    f, h, se_db, se_deg = _mean_response(lag_study, 2.0)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["lowpass"]])
    kw = dict(se_db=se_db, se_deg=se_deg, band=BAND_Z)
    local = fit_response(model, f, h, x0=FAR_START, global_search=False, strict=False, **kw)
    assert local.rms_norm > FAR_FROM_NOISE
    assert local.params["k1"] < 1000.0
    assert not local.converged
    assert "local minimum" in local.message and "another start reaches" in local.message
    with pytest.raises(ConvergenceError, match="local minimum"):
        fit_response(model, f, h, x0=FAR_START, global_search=False, **kw)
    best = fit_response(model, f, h, **kw)
    assert best.converged and best.rms_norm < 2.0
    assert best.params["k1"] == pytest.approx(_truth(2.0)["k1"], rel=0.1)
    assert best.objective < MARKEDLY_LOWER * local.objective


def test_no_converged_fit_sits_far_above_a_cheaper_start(lag_study):
    """Invariant: of local fits from a grid of starts (the far minimum, a compliant X/Y
    arm and two variants of it, each with cutoffs below, near and above the truth) and
    the global fit, none reported converged ends
    several times the noise at a cost more than 1/MARKEDLY_LOWER times the cheapest."""
    f, h, se_db, se_deg = _mean_response(lag_study, 3.0)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["lowpass"]])
    kw = dict(se_db=se_db, se_deg=se_deg, band=BAND_Z, strict=False, intervals=False)
    fits = [fit_response(model, f, h, **kw)]
    compliant = {"Ma": 0.3, "k1": 85.0, "k2": 700.0, "b1": 7.5, "b2": 4.0}  # an X/Y arm
    for arm in (FAR_START, compliant, {**compliant, "k1": 850.0}, {**compliant, "Ma": 3.0}):
        for fc in (8.0, 25.0, 80.0):
            x0 = {**arm, "lowpass.cutoff_hz": fc}
            fits.append(fit_response(model, f, h, x0=x0, global_search=False, **kw))
    cheapest = min(fit.objective for fit in fits)
    assert fits[0].objective == pytest.approx(cheapest, rel=1e-6)     # the global fit
    assert fits[0].params["k1"] == pytest.approx(_truth(3.0)["k1"], rel=0.1)
    far = [fit for fit in fits if fit.rms_norm > FAR_FROM_NOISE]
    assert far, "no start ended far from the noise: the check is not exercised"
    for fit in fits:
        if fit.converged and fit.rms_norm > FAR_FROM_NOISE:
            assert fit.objective <= cheapest / MARKEDLY_LOWER, fit.message
    # here every far end is a local minimum (or the optimiser ran out of evaluations)
    assert all(not fit.converged for fit in far)
    assert sum("local minimum" in fit.message for fit in far) >= len(far) // 2
    assert np.isfinite(cheapest)


#: Z grip fits with the lag that the search before the structured starts reported as
#: converged on the study of the next test (4 subjects, seed 1): 1 and 2 N in far local
#: minima (k1 357 and 252 N/m, 4.6 and 2.5 times the noise), 3 N right.
FAR_GRIP_FITS = {
    1.0: {"Ma": 7.739, "k1": 357.2, "k2": 286.3, "b1": 148.4, "b2": 36.79,
          "lowpass.cutoff_hz": 100.6},
    2.0: {"Ma": 5.569, "k1": 252.4, "k2": 333.1, "b1": 69.82, "b2": 46.01,
          "lowpass.cutoff_hz": 34.34},
    3.0: {"Ma": 3.27, "k1": 3566.0, "k2": 113.1, "b1": 50.41, "b2": 31.65,
          "lowpass.cutoff_hz": 18.01},
}


def test_diagnosis_on_the_paper_z_band_from_far_grip_fits():
    """The diagnosis over the paper's Z band (0.1–10 Hz), started from grip fits stuck
    in far local minima, still names lowpass at the simulated 18 Hz and ends within the
    noise (truth: 18 Hz lag on Z; subjects vary, 0.15 log-sd, as ``armfit simulate``'s
    default). Before, the joint fit kept the trials of those grips in the far minimum:
    cutoff 33.9 Hz, 'still inadequate' at 7.7 times the noise."""
    lag = EffectSetting.from_parsed("lowpass", {"cutoff_hz": CUTOFF_HZ})
    spectra = api.estimate(list(api.simulate(subjects=4, axes=("z",), seed=1,
                                             effects=(lag,)).trials()))
    table = api.fit_grip(spectra, effects=["lowpass"], bands={"z": BAND_Z}).table.copy()
    for grip, values in FAR_GRIP_FITS.items():
        for name, v in values.items():
            table.loc[table["grip_N"] == grip, name] = v
    (d,) = api.diagnose(spectra, table, band=(0.1, 10.0)).axes
    assert [m.effect for m in d.missing_effects] == ["lowpass"], d.verdict
    assert d.missing_effects[0].params["cutoff_hz"] == pytest.approx(CUTOFF_HZ, rel=0.1)
    assert d.adequate, d.verdict
