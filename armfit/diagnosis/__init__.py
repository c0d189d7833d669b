"""Compare the model with the measurements, find where it fails, name the missing effect.

Residuals are "measured relative to model": r_dB = 20 log10|H_meas/H_model| (dB) and
r_deg = angle(H_meas/H_model) (deg); each divided by the measurement's standard error
(``se_db``, ``se_deg`` of the spectra file) gives the normalised residual z, which is
≈ N(0, 1) where the model fits within the noise.

Where the evidence is weighed (diagnosis)
-----------------------------------------
The median (or mean) of many subjects is not itself a 5-parameter response, and its
standard error is dominated by between-subject spread that is smooth in frequency: a
χ² test on an aggregate raises false alarms or misses effects depending on the spread.
So the diagnosis weighs the evidence **per trial**: every trial of an axis gets its own
five arm parameters (Ma, k1, k2, b1, b2 — subjects and grips differ), each judged against
its own measurement noise (Bendat & Piersol standard errors from coherence), while a
candidate effect's parameters are **shared** by all trials of the axis (a delay, a sensor
lag, the device's damping or mass, a structural mode are properties of the apparatus;
for the reflex this reads as the population's typical reflex). One joint least-squares
fit per candidate (T·5 + k parameters, a block-arrow Jacobian by vectorised forward
differences, solved by eliminating the trials' blocks: :mod:`armfit.blocklsq`) is
warm-started from the base
fit at the effect's null point (where it vanishes) and at the effect's own starting
points, so adding an effect never makes the fit worse.

Criterion: the likelihood-ratio statistic with unknown common noise scale,
D = N_eff · ln(RSS_base / RSS_effect), with N_eff = N (1 − ρ)/(1 + ρ) the number of
residuals corrected for their lag-1 autocorrelation ρ along frequency (neighbouring grid
points of the estimator are not fully independent, and a candidate that leaves a
systematic residual keeps ρ high); ΔBIC = D − k ln N_eff. A candidate is significant when
ΔBIC > :data:`SIGNIFICANT_BIC` (Kass & Raftery's "very strong" evidence) **and** it removes
at least :data:`MIN_REDUCTION` of the residual sum of squares: with many trials even a
consistent estimator bias of a few hundredths of a dB reaches any ΔBIC, while a physical
effect worth modelling explains a good part of the misfit. Two candidates whose ΔBIC differ
by less than :data:`TIE_BIC` (or :data:`TIE_FRACTION` of the best) "explain the data about
equally well".

Stepwise search and verdict: :func:`diagnose_axes` adds effects one at a time while the model
is not adequate (:func:`adequacy`: every band within the noise, no band failing), each
significant both statistically (the criterion above) and practically (:func:`practical`:
it changes the response by more than the noise and a floor). Every standard error is the
noise model's (:func:`armfit.noise.standard_errors` of each trial, on the whole grid):
the joint fits, the screening and the rescue of a stuck trial weigh residuals by it, and
every "× noise" is :func:`armfit.noise.rms_norm`. The statistics and choices are
documented in docs/methods.md, "Diagnosis" and "The noise model".

Failing bands: per frequency, the mean over trials of the normalised residual of the base
fit, divided by its standard error across trials (a t statistic); runs of at least
:data:`MIN_RUN` grid points with |t| > :data:`T_FAIL` and a mean normalised residual above 1
(a systematic error larger than one trial's noise) are the bands where the model fails.

Modules: :mod:`~armfit.diagnosis.tuning` (every tuning constant, documented),
:mod:`~armfit.diagnosis.bands` (residuals, errors per band, failing bands in words),
:mod:`~armfit.diagnosis.responses` (the trials of an axis from the spectra),
:mod:`~armfit.diagnosis.joint` (the joint problem and fit), :mod:`~armfit.diagnosis.starts`
(its starting arm parameters), :mod:`~armfit.diagnosis.fit` (base, extended and borrowed
fits), :mod:`~armfit.diagnosis.screen` (screening of candidates),
:mod:`~armfit.diagnosis.evidence` (ΔBIC, practical size, adequacy),
:mod:`~armfit.diagnosis.results` (result records), :mod:`~armfit.diagnosis.verdict`
(verdicts in words), :mod:`~armfit.diagnosis.search` (the stepwise search) and
:mod:`~armfit.diagnosis.compare` (``armfit compare`` and the JSON documents). The stage
functions of the public API are :func:`armfit.diagnose` and :func:`armfit.compare`.
"""

from __future__ import annotations

from armfit._lazy import lazy_exports

#: The package's names and the module each comes from, imported on first use (so
#: that importing one light module of the package does not load the others).
_EXPORTS: dict[str, str] = {
    "BandError": "armfit.diagnosis.bands",
    "FailingBand": "armfit.diagnosis.bands",
    "band_error": "armfit.diagnosis.bands",
    "describe_residual": "armfit.diagnosis.bands",
    "failing_bands": "armfit.diagnosis.bands",
    "residuals": "armfit.diagnosis.bands",
    "trial_statistics": "armfit.diagnosis.bands",
    "Comparison": "armfit.diagnosis.compare",
    "band_to_dict": "armfit.diagnosis.compare",
    "compare_models": "armfit.diagnosis.compare",
    "comparison_notes": "armfit.diagnosis.responses",
    "diagnosis_to_dict": "armfit.diagnosis.compare",
    "model_label": "armfit.diagnosis.compare",
    "Adequacy": "armfit.diagnosis.evidence",
    "adequacy": "armfit.diagnosis.evidence",
    "effect_size": "armfit.diagnosis.evidence",
    "practical": "armfit.diagnosis.evidence",
    "fit_base": "armfit.diagnosis.fit",
    "fit_borrowed": "armfit.diagnosis.fit",
    "fit_extend": "armfit.diagnosis.fit",
    "JointFit": "armfit.diagnosis.joint",
    "joint_fit": "armfit.diagnosis.joint",
    "AxisData": "armfit.diagnosis.responses",
    "axis_data": "armfit.diagnosis.responses",
    "cross_coupling": "armfit.diagnosis.responses",
    "AxisDiagnosis": "armfit.diagnosis.results",
    "Candidate": "armfit.diagnosis.results",
    "FailedCandidate": "armfit.diagnosis.results",
    "MissingEffect": "armfit.diagnosis.results",
    "Step": "armfit.diagnosis.results",
    "screen_candidate": "armfit.diagnosis.screen",
    "cross_axis_agreement": "armfit.diagnosis.search",
    "diagnose_axes": "armfit.diagnosis.driver",
    "best_rows": "armfit.diagnosis.starts",
    "levy_starts": "armfit.diagnosis.starts",
    "BANDS": "armfit.diagnosis.tuning",
    "MAX_STEPS": "armfit.diagnosis.tuning",
    "MIN_EFFECT_DB": "armfit.diagnosis.tuning",
    "MIN_EFFECT_DEG": "armfit.diagnosis.tuning",
    "MIN_REDUCTION": "armfit.diagnosis.tuning",
    "MIN_RUN": "armfit.diagnosis.tuning",
    "NOISE_TOL": "armfit.diagnosis.tuning",
    "SHARED_EFFECTS": "armfit.diagnosis.tuning",
    "SIGNIFICANT_BIC": "armfit.diagnosis.tuning",
    "T_FAIL": "armfit.diagnosis.tuning",
    "verdict_text": "armfit.diagnosis.verdict",
}


__all__ = [
    "Adequacy", "AxisData", "AxisDiagnosis", "BANDS", "BandError", "Candidate", "Comparison",
    "FailedCandidate", "FailingBand", "JointFit", "MAX_STEPS", "MIN_EFFECT_DB",
    "MIN_EFFECT_DEG", "MIN_REDUCTION", "MIN_RUN", "MissingEffect", "NOISE_TOL",
    "SHARED_EFFECTS", "SIGNIFICANT_BIC", "Step",
    "T_FAIL", "adequacy", "axis_data", "band_error", "band_to_dict", "best_rows",
    "compare_models", "comparison_notes", "cross_axis_agreement", "cross_coupling",
    "describe_residual",
    "diagnose_axes", "diagnosis_to_dict", "effect_size", "failing_bands", "fit_base",
    "fit_borrowed", "fit_extend", "joint_fit", "levy_starts", "model_label", "practical",
    "residuals", "screen_candidate", "trial_statistics", "verdict_text",
]


__getattr__, __dir__ = lazy_exports(globals(), _EXPORTS)
