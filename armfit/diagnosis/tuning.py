"""The diagnosis's tuning constants, in one place: what each controls and why its value.

Statistical thresholds first (they decide verdicts), then the search's budget (it decides
only how much work finds the same answer). The standard errors every statistic divides
by are the noise model's (:mod:`armfit.noise`), not tuned here.
"""

from __future__ import annotations

from armfit.constants import UNIT_SE_DEG

__all__ = [
    "BANDS", "CHUNK_TRIALS", "DROP_POINTS", "FTOL_VARIANCE", "MAX_STEPS", "MIN_EFFECT_DB",
    "MIN_EFFECT_DEG",
    "MIN_REDUCTION", "MIN_RUN", "NOISE_TOL", "OUTLIER", "QUICK_BEST", "QUICK_NFEV",
    "QUICK_SCREEN_NFEV", "REFINE_BEST", "SCREEN_GAP", "SCREEN_KEEP", "SCREEN_SUBSET",
    "SHARED_EFFECTS", "SIGNIFICANT_BIC", "START_GAP", "START_SCREEN_NFEV", "START_SCREEN_TRIALS",
    "TIE_BIC", "TIE_FRACTION", "TRIAL_FIT_NFEV", "T_FAIL", "UNIT_DEG",
]

# ---------------------------------------------------------------------------
# Evidence and verdicts
# ---------------------------------------------------------------------------

#: Bands (Hz) of the per-band errors, of adequacy and of the compare table: the paper's
#: 0.1–30 Hz in four parts, one per regime of the arm (posture, hand, arm, device).
BANDS: tuple[tuple[float, float], ...] = ((0.1, 1.0), (1.0, 3.0), (3.0, 10.0), (10.0, 30.0))
#: ΔBIC above which an effect is significant: Kass & Raftery's "very strong" evidence.
SIGNIFICANT_BIC = 10.0
#: Fraction of the residual sum of squares an effect must remove to be significant: with
#: many trials a consistent estimator bias of a few hundredths of a dB reaches any ΔBIC,
#: but explains almost nothing; a physical effect worth modelling explains a good part.
MIN_REDUCTION = 0.05
#: A band is within the noise when its "× noise" is at most this (its noise-weighted
#: cost at most 2.25 times the expected value: the Bendat–Piersol errors are themselves
#: uncertain by tens of per cent, and real data never match a model exactly).
NOISE_TOL = 1.5
#: Practical-significance floors (dB, deg): an effect must change the fitted response by
#: more than this (and more than the noise) on :data:`MIN_RUN` consecutive points — a
#: relative change of the response, so independent of the parameter's units; 0.5 dB and
#: 3 deg are about what the paper's figures can show.
MIN_EFFECT_DB = 0.5
MIN_EFFECT_DEG = 3.0
#: Default maximum number of effects the stepwise search adds: more than three effects
#: on top of five arm parameters are not identifiable from one axis's responses.
MAX_STEPS = 3
#: ΔBIC difference below which two candidates explain the data alike (absolute, or as a
#: fraction of the best ΔBIC, whichever is larger): 6 is "strong" evidence on Kass &
#: Raftery's scale, and 5 % keeps large ΔBICs of thousands from making every gap decisive.
TIE_BIC = 6.0
TIE_FRACTION = 0.05
#: |t| (or |z| for a single aggregate) above which a grid point fails: four standard
#: errors, so that over a grid of ~100 points chance alone makes no failing run.
T_FAIL = 4.0
#: Consecutive failing grid points that make a failing band (and consecutive points an
#: effect must change by more than the floors): neighbouring points are correlated, so a
#: single point is no band.
MIN_RUN = 3
#: Grid points with the largest improvement left out of the evidence, so that an
#: isolated outlier (e.g. at the edge of the excitation band) cannot make an effect.
DROP_POINTS = 2
#: Degrees weighted like 1 dB in unweighted comparisons (1 neper ↔ 1 rad), as the fits'
#: cost without standard errors.
UNIT_DEG = float(UNIT_SE_DEG)
#: Apparatus effects (latency, sensor lag) that act alike on every axis: their fitted
#: parameters are compared across axes by default.
SHARED_EFFECTS: tuple[str, ...] = ("delay", "lowpass")

# ---------------------------------------------------------------------------
# The search's budget (how much work; the answers do not depend on it when it suffices)
# ---------------------------------------------------------------------------

#: A joint fit has converged when a step lowers its cost (½χ², noise-weighted) by less
#: than this fraction of the residual variance s² = χ²/(m − p): a change of the fit's
#: χ² by less than 2 % of one residual's share, nothing any statistic of the diagnosis
#: can show (the ΔBIC threshold is 10 and its values are printed to 0.1). A model far
#: from the data has s² of thousands, and its fit creeps along a flat valley of its
#: cost by steps of this order for a hundred evaluations; a model within the noise has
#: s² ≈ 1 and converges in a few steps, and stops within a small fraction of its
#: intervals of where a 1e-14 tolerance would (tests/test_diagnose_speedups.py).
FTOL_VARIANCE = 0.01
#: A trial whose misfit exceeds this many times the median trial's (and twice the
#: number of its residuals) is refitted on its own: it sits in a poor local minimum.
OUTLIER = 4.0
#: Evaluations per parameter of the final polish of that single-trial fit
#: (fit_response's default is 200, to 1e-12): it only gives the joint fit, which refines
#: every trial again, a start.
TRIAL_FIT_NFEV = 20
#: Trials (at most, spread over the axis) on which every starting combination of a joint
#: fit is tried briefly, and the evaluations each such try gets.
START_SCREEN_TRIALS = 9
START_SCREEN_NFEV = 12
#: Starting combinations, the best of the brief tries, refined on all trials.
REFINE_BEST = 2
#: A start whose brief try ends with a cost more than this factor above the best one's is
#: not refined. On the validation corpus (benchmarks/validate_start_gap.py: 25 diagnoses
#: of simulated studies over the effect library, the sample studies and the real
#: recordings; 386 joint fits with several starts refined) no start more than a factor
#: 4.01 behind ended better than the best one's by more than 1e-6 of the cost, and a few
#: more than 10 behind ended better by rounding only, on the same optimum; a start that
#: far behind creeps along a poor minimum for a hundred evaluations and its stuck trials
#: are refitted one by one, for nothing (a gap of 100 leaves out 27 starts, 18–19 % of the
#: refinements' CPU).
START_GAP = 100.0
#: The ``quick`` joint fits of the candidate screening: evaluations of the refinement,
#: of each brief try, and the combinations refined. The screening only ranks candidates
#: and gives the joint fit on all trials a start, which that fit refines.
QUICK_NFEV = 60
QUICK_SCREEN_NFEV = 4
QUICK_BEST = 2
#: Candidates per step that get the joint fit on all trials after the screening.
SCREEN_KEEP = 2
#: Trials in the screening fits (one per grip in the paper's design).
SCREEN_SUBSET = 3
#: A screened candidate whose subset cost exceeds the best one's by more than this factor
#: gets no joint fit on all trials: it cannot win (the joint fits rank as the screening
#: does when the gap is this large).
SCREEN_GAP = 2.0

#: Trials whose residuals and Jacobian blocks :class:`~armfit.diagnosis.joint.JointProblem`
#: evaluates in one go, and whose candidate start rows
#: :func:`~armfit.diagnosis.starts.best_rows` scores in one go: enough to keep numpy's
#: loops long, few enough that the temporaries (about 40 kB a trial for the Jacobian)
#: stay small for any study. Up to this many trials an axis's values are those of one
#: evaluation of all; beyond, they may differ from it in the last bits (numpy's vector
#: loops round the tail of an array alike, not bit for bit).
CHUNK_TRIALS = 64
