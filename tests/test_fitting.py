"""Fits of H_CL (eqs. 4–5): recovery of the paper's parameters, intervals, bootstrap."""

from __future__ import annotations

import numpy as np
import pytest

from armfit import fitting
from armfit.data import paper_table
from armfit.errors import ConvergenceError, UsageError
from armfit.fitting import (
    PAPER_BANDS,
    UNIT_SE_DEG,
    analytic_guess,
    bootstrap_fit,
    fit_response,
    levy_candidates,
    levy_candidates_many,
    levy_rows,
    log_errors,
)
from armfit.models.arm import PARAM_NAMES, ClosedLoopModel, h_cl
from armfit.models.effects import get_effect
from armfit.spectra import aggregate

PAPER_COLS = ["Ma_kg", "k1_N_per_m", "k2_N_per_m", "b1_Ns_per_m", "b2_Ns_per_m"]
#: The paper's bins: 0.01 Hz apart up to 30 Hz (N = 1e5 samples at 1 kHz: 100 s records).
PAPER_GRID = np.arange(1, 3001) * 0.01
#: Table I, X axis, 1 N grip (paper).
X1 = dict(zip(PARAM_NAMES, (0.1925, 85.48, 704.2, 7.410, 2.477), strict=True))


def _rows():
    out = []
    for name in ("grip", "nominal"):
        for _, r in paper_table(name).iterrows():
            label = f"{name}-{r['axis']}" + (f"-{r['grip_N']:g}N" if name == "grip" else "")
            out.append(pytest.param(r["axis"], dict(zip(PARAM_NAMES, r[PAPER_COLS].astype(float),
                                                         strict=True)), id=label))
    return out


@pytest.mark.parametrize("cost", ["complex", "paper"])
@pytest.mark.parametrize(("axis", "truth"), _rows())
def test_recovers_every_paper_row(axis, truth, cost):
    # Truth: each row of Tables I and II (paper). Data: h_cl (eq. 4, written out
    # independently of ClosedLoopModel) on the paper's 0.01 Hz grid, fitted in the paper's
    # band. Exact data has a zero-cost optimum, so 0.1 % (the acceptance) is generous.
    mp = {"x": 0.09, "y": 0.095, "z": 0.091}[axis]  # paper eq. 2
    H = h_cl(PAPER_GRID, mp=mp, **truth)
    fit = fit_response(ClosedLoopModel.for_axis(axis), PAPER_GRID, H, cost=cost,
                       band=PAPER_BANDS[axis])
    assert fit.converged
    for n in PARAM_NAMES:
        assert fit.params[n] == pytest.approx(truth[n], rel=1e-3), n
    # the fitted band is the paper's: X, Y 0.1-30 Hz, Z 0.1-10 Hz (to the grid's 0.01 Hz)
    assert fit.band == pytest.approx(PAPER_BANDS[axis], abs=0.01)
    assert fit.rms_db < 1e-6


def test_analytic_guess_is_exact_on_noise_free_data():
    # Levy's linear fit of Z_ARM = 1/H - Mp s^2 is exact for eq. 4's response: one of its
    # candidates must equal Table I X 1 N (float64 round-off only, so 1e-6 relative).
    f = np.geomspace(0.1, 30, 80)
    cands = analytic_guess(f, h_cl(f, mp=0.09, **X1), 0.09)
    assert any(all(abs(c[n] / X1[n] - 1) < 1e-6 for n in PARAM_NAMES) for c in cands)


def test_levy_candidates_of_many_systems_at_once_are_those_one_by_one(monkeypatch):
    # levy_candidates_many finds the roots of all the numerators at once (one eigvals of
    # the stacked companion matrices); levy_candidates, numpy.roots one cubic at a time:
    # the candidates are the same bit for bit (independent computation of the roots).
    # Noisy responses of eq. 4 in the three band cuts of the diagnosis's starts, and a
    # system whose rows are not finite (no candidate)
    f = np.geomspace(0.1, 30, 120)
    rng = np.random.default_rng(11)
    systems = []
    for k in range(12):
        noise = 0.003 * k * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
        a_w, b_w = levy_rows(f, h_cl(f, mp=0.09, **X1) * (1 + noise), 0.09)
        systems += [(a_w[f >= lo_f], b_w[f >= lo_f]) for lo_f in (0.0, 0.3, 1.0)]
    systems.append((a_w * np.nan, b_w))
    want = [levy_candidates(a, b) for a, b in systems]
    assert sum(map(len, want)) > 10 and [] in want
    assert levy_candidates_many(systems) == want
    # the edge cases, by their coefficients (n3, n2, n1, n0, d1, d0): the numerator
    # (s+1)(s+2)(s+3), three physical candidates; s(s²+6s+11), a root at 0 (the cubic
    # left to numpy.roots; no candidate: k1 or k2 would be 0); (s+1)(s²+s+4), complex
    # roots beside a real one; no positive leading term
    coefs = {1: [1.0, 6.0, 11.0, 6.0, 20.0, 5.0], 2: [1.0, 6.0, 11.0, 0.0, 20.0, 5.0],
             3: [1.0, 2.0, 5.0, 4.0, 10.0, 1.0], 4: [-1.0, 6.0, 11.0, 6.0, 20.0, 5.0]}
    monkeypatch.setattr(fitting, "_levy_solution", lambda a, b: np.array(coefs[a]))
    want = [levy_candidates(i, None) for i in coefs]
    assert [len(w) for w in want] == [3, 0, 1, 0]
    assert levy_candidates_many([(i, None) for i in coefs]) == want
    # a coefficient that is not finite: both raise numpy.roots' error
    coefs[5] = [1.0, np.nan, 11.0, 6.0, 20.0, 5.0]
    for find in (lambda: levy_candidates(5, None), lambda: levy_candidates_many([(5, None)])):
        with pytest.raises(np.linalg.LinAlgError):
            find()


def test_same_answer_whatever_the_global_random_state():
    # The global search uses a fixed Sobol set and no random numbers: two fits of the
    # same noisy data after seeding numpy's global generator differently are identical.
    f = np.geomspace(0.1, 30, 120)
    rng = np.random.default_rng(5)
    H = h_cl(f, mp=0.09, **X1) * 10 ** (rng.normal(0, 0.5, f.size) / 20)
    model = ClosedLoopModel.for_axis("x")
    np.random.seed(1)
    a = fit_response(model, f, H, cost="paper")
    np.random.seed(2)
    b = fit_response(model, f, H, cost="paper")
    assert a.params == b.params


def test_log_errors_definition():
    # 20 log10 |2| = 6.0206 dB; angle(j) = 90 deg (definitions of eq. 5's terms).
    db, deg = log_errors(np.array([2.0, 1j]), np.array([1.0, 1.0]))
    assert db == pytest.approx([20 * np.log10(2.0), 0.0], abs=1e-12)
    assert deg == pytest.approx([0.0, 90.0], abs=1e-12)
    # 1 neper <-> 1 rad: the unweighted phase scale is (180/pi) / (20/ln 10) deg per dB
    assert UNIT_SE_DEG == pytest.approx(np.degrees(1) * np.log(10) / 20)


@pytest.fixture(scope="module")
def noisy_fits():
    # 40 realisations of Table I X 1 N with iid log-normal noise: 0.5 dB and 3 deg,
    # se given exactly. 200 log-spaced bins 0.1-30 Hz.
    f = np.geomspace(0.1, 30, 200)
    h0 = h_cl(f, mp=0.09, **X1)
    rng = np.random.default_rng(0)
    model = ClosedLoopModel.for_axis("x")
    fits = []
    for _ in range(40):
        H = h0 * 10 ** (rng.normal(0, 0.5, f.size) / 20) * np.exp(
            1j * np.radians(rng.normal(0, 3.0, f.size)))
        fits.append(fit_response(model, f, H, se_db=np.full(f.size, 0.5),
                                 se_deg=np.full(f.size, 3.0)))
    return fits


def test_jacobian_intervals_cover_the_truth(noisy_fits):
    # One realisation: every 95 % interval contains the truth (Table I X 1 N).
    first = noisy_fits[0]
    for n in PARAM_NAMES:
        assert first.ci_lo[n] <= X1[n] <= first.ci_hi[n], n
        assert first.ci_lo[n] < first.params[n] < first.ci_hi[n]
    # Over 40 realisations each interval covers the truth in >= 80 % of them: for a true
    # 95 % interval the count is Binomial(40, 0.95), P(count <= 31) ~ 1e-4.
    for n in PARAM_NAMES:
        cover = np.mean([f.ci_lo[n] <= X1[n] <= f.ci_hi[n] for f in noisy_fits])
        assert cover >= 0.8, (n, cover)


def test_rms_norm_is_one_when_the_noise_matches_the_standard_errors(noisy_fits):
    # Normalised residuals are N(0, 1) at the truth; E[rms_norm^2] = (2m - 5)/(2m) ~ 0.99
    # at the optimum; over 40 fits the mean lies within +-0.05 (sd of one ~ 0.05).
    rms = np.mean([f.rms_norm for f in noisy_fits])
    assert rms == pytest.approx(1.0, abs=0.05)
    # and the dB/deg RMS errors are the noise levels 0.5 dB and 3 deg (+-10 %)
    assert np.mean([f.rms_db for f in noisy_fits]) == pytest.approx(0.5, rel=0.1)
    assert np.mean([f.rms_deg for f in noisy_fits]) == pytest.approx(3.0, rel=0.1)


#: A start far from Table I X 1 N: every parameter 20x off (Ma, k1, b1 up; k2, b2 down).
FAR = {"Ma": 20 * X1["Ma"], "k1": 20 * X1["k1"], "k2": X1["k2"] / 20, "b1": 20 * X1["b1"],
       "b2": X1["b2"] / 20}


def _log_misfit(f, params) -> float:
    """RMS of the dB error of eq. 4 at ``params`` against eq. 4 at Table I X 1 N."""
    db, _ = log_errors(h_cl(f, mp=0.09, **params), h_cl(f, mp=0.09, **X1))
    return float(np.sqrt(np.mean(db**2)))


def test_not_converging_raises():
    # A problem that truly cannot converge: a local polish from a start checked to be far
    # off (over 10 dB RMS from the exact data), with a budget of a single evaluation.
    f = np.geomspace(0.1, 30, 60)
    assert _log_misfit(f, FAR) > 10.0
    with pytest.raises(ConvergenceError, match="did not converge"):
        fit_response(ClosedLoopModel.for_axis("x"), f, h_cl(f, mp=0.09, **X1), x0=FAR,
                     global_search=False, max_nfev=1)


def test_solver_stopping_at_its_budget_raises(solver_stops_at_budget):
    f = np.geomspace(0.1, 30, 60)
    with pytest.raises(ConvergenceError, match="did not converge"):
        fit_response(ClosedLoopModel.for_axis("x"), f, h_cl(f, mp=0.09, **X1))


def test_non_strict_fit_reports_not_converged(solver_stops_at_budget):
    # Not converged is reported, with the best parameters found; here the global search
    # still reaches Table I X 1 N on exact data (eq. 4), within 0.1 %.
    f = np.geomspace(0.1, 30, 60)
    fit = fit_response(ClosedLoopModel.for_axis("x"), f, h_cl(f, mp=0.09, **X1),
                       strict=False)
    assert fit.converged is False
    for n in PARAM_NAMES:
        assert fit.params[n] == pytest.approx(X1[n], rel=1e-3)


def test_far_start_non_strict_is_far_and_not_converged():
    # The same far start, not strict: reported as not converged, and its misfit shows it.
    f = np.geomspace(0.1, 30, 60)
    fit = fit_response(ClosedLoopModel.for_axis("x"), f, h_cl(f, mp=0.09, **X1), x0=FAR,
                       global_search=False, max_nfev=1, strict=False)
    assert fit.converged is False
    assert fit.rms_db > 1.0


def test_fit_with_an_effect_recovers_its_parameter():
    # Truth: Table I Y 2 N with a 5 ms output delay (effect library: X/F * exp(-s*delay)).
    model = ClosedLoopModel.for_axis("y", [get_effect("delay")])
    truth = dict(zip(PARAM_NAMES, (0.2984, 84.85, 779.8, 7.632, 4.919), strict=True))
    truth["delay.delay_s"] = 0.005
    f = np.geomspace(0.1, 30, 150)
    fit = fit_response(model, f, model.response(f, truth))
    assert set(fit.params) == set(truth)
    for n, v in truth.items():
        assert fit.params[n] == pytest.approx(v, rel=1e-3), n


def test_warm_start_without_global_search():
    # Starting 20 % off the truth (Table I X 1 N), the local fit alone gets back to it.
    f = np.geomspace(0.1, 30, 100)
    x0 = {n: 1.2 * v for n, v in X1.items()}
    fit = fit_response(ClosedLoopModel.for_axis("x"), f, h_cl(f, mp=0.09, **X1), x0=x0,
                       global_search=False)
    for n in PARAM_NAMES:
        assert fit.params[n] == pytest.approx(X1[n], rel=1e-3), n


def test_parameters_stay_within_physical_bounds():
    # Data from a pure compliance 1/(k s^0): not an arm; the fit must still keep every
    # parameter inside ClosedLoopModel.params' bounds.
    f = np.geomspace(0.1, 30, 60)
    model = ClosedLoopModel.for_axis("x")
    fit = fit_response(model, f, np.full(f.size, 1e-6 + 0j), cost="paper")
    for p in model.params:
        assert p.lower <= fit.params[p.name] <= p.upper


def test_bad_options():
    f = np.geomspace(0.1, 30, 60)
    H = h_cl(f, mp=0.09, **X1)
    model = ClosedLoopModel.for_axis("x")
    with pytest.raises(UsageError, match="cost must be one of"):
        fit_response(model, f, H, cost="l1")
    with pytest.raises(UsageError, match="holds 1 usable bins"):
        fit_response(model, f, H, band=(0.1, 0.105))
    with pytest.raises(UsageError, match="unknown parameter 'Mb'"):
        fit_response(model, f, H, x0={"Mb": 1.0})


def _subject_study(rng, n_subjects=9):
    # Table I X 1 N seen by n subjects, one trial each, with per-subject log-normal
    # deviations: 1 dB and 5 deg per bin plus a 0.8 dB gain offset per subject.
    f = np.geomspace(0.1, 30, 60)
    h0 = h_cl(f, mp=0.09, **X1)
    dev = rng.normal(0, 1.0, (n_subjects, f.size)) + rng.normal(0, 0.8, (n_subjects, 1))
    ph = rng.normal(0, 5.0, (n_subjects, f.size))
    return f, h0 * 10 ** (dev / 20) * np.exp(1j * np.radians(ph))


@pytest.fixture(scope="module")
def subject_study():
    f, hs = _subject_study(np.random.default_rng(3))
    return f, hs, np.array([f"S{i}" for i in range(hs.shape[0])])


def test_bootstrap_percentile_intervals(subject_study):
    f, hs, subjects = subject_study
    model = ClosedLoopModel.for_axis("x")
    base = fit_response(model, f, aggregate(hs, "mean"))
    agg = lambda H: aggregate(H, "mean")  # noqa: E731
    # the percentile intervals themselves (widen=False; the default also takes in the
    # base fit's own interval, checked below)
    boot = bootstrap_fit(base, f, hs, subjects, aggregate=agg, n_boot=40, seed=1,
                         widen=False)
    again = bootstrap_fit(base, f, hs, subjects, aggregate=agg, n_boot=40, seed=1,
                          widen=False)
    wide = bootstrap_fit(base, f, hs, subjects, aggregate=agg, n_boot=40, seed=1)
    for n in PARAM_NAMES:
        assert wide.ci_lo[n] == min(boot.ci_lo[n], base.ci_lo[n])
        assert wide.ci_hi[n] == max(boot.ci_hi[n], base.ci_hi[n])
    assert boot.ci_method == "bootstrap-40"
    assert boot.params == base.params
    # same seed, same intervals (numpy Generator determinism)
    assert boot.ci_lo == again.ci_lo and boot.ci_hi == again.ci_hi
    # Reference: the estimator's actual spread, by Monte Carlo over 40 fresh studies of
    # the same simulated population (log scale). A bootstrap over 9 subjects estimates
    # it with ~15 % noise and a sqrt(8/9) shrinkage: within a factor 2 is required.
    rng = np.random.default_rng(11)
    mc = np.array([[fit_response(model, f, aggregate(_subject_study(rng)[1], "mean"),
                                 global_search=False, x0=X1, intervals=False).params[n]
                    for n in PARAM_NAMES]
                   for _ in range(40)])
    sd_mc = np.log(mc).std(axis=0, ddof=1)
    for i, n in enumerate(PARAM_NAMES):
        # percentile intervals bracket the point fit
        assert boot.ci_lo[n] <= base.params[n] <= boot.ci_hi[n], n
        sd_boot = np.log(boot.ci_hi[n] / boot.ci_lo[n]) / (2 * 1.96)
        assert 0.5 < sd_boot / sd_mc[i] < 2.0, (n, sd_boot, sd_mc[i])


def test_bootstrap_needs_replicates(subject_study):
    f, hs, subjects = subject_study
    base = fit_response(ClosedLoopModel.for_axis("x"), f, aggregate(hs, "mean"))
    with pytest.raises(UsageError, match="at least 2 replicates"):
        bootstrap_fit(base, f, hs, subjects, aggregate=lambda H: H.mean(0), n_boot=1)
