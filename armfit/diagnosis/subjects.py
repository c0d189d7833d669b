"""Effects whose values differ between subjects: one shared value against one per subject.

The stepwise search (:mod:`armfit.diagnosis.search`) fits an effect with one value shared
by every trial of an axis. People differ, and so may an apparatus between sessions: for
an effect the search names, :func:`by_subject_search` tests, parameter by parameter,
whether the data demand one value per subject (each subject's trials share it; a subject
with one trial has its own). The test is the stepwise search's own, applied to the
nested pair "shared" ⊂ "per subject":

* statistically: ΔBIC = D − k ln N_eff > :data:`~armfit.diagnosis.tuning.SIGNIFICANT_BIC`
  with D the robust likelihood-ratio statistic (:func:`~armfit.diagnosis.evidence.robust_lr`)
  and k = S − 1 more parameters for S subjects, and at least
  :data:`~armfit.diagnosis.tuning.MIN_REDUCTION` of the cost removed;
* practically: the subjects' own values change the fitted responses — the median over
  trials of |20 log10(H/H₀)| or |angle(H/H₀)|, H the per-subject fit's response and H₀
  the same with the shared fit's value in place of the subjects' (every other parameter
  unchanged, as the search measures an effect against its null point:
  :func:`~armfit.diagnosis.evidence.effect_size`) — by more than the noise and the
  floors (``min_db``, ``min_deg``) on :data:`~armfit.diagnosis.tuning.MIN_RUN`
  consecutive grid points (:func:`~armfit.diagnosis.evidence.practical`).

Parameters are made per subject one at a time, the most significant first, while one
qualifies (a reflex's gain may differ between people while its delay does not); the
per-subject form is kept only when the data demand it. Every subject starts at the shared
value, so the per-subject fit is never worse than the shared one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from armfit.diagnosis.evidence import delta_bic, practical, response_change
from armfit.diagnosis.fit import fit_by_subject
from armfit.diagnosis.joint import JointFit
from armfit.diagnosis.responses import AxisData
from armfit.diagnosis.tuning import MIN_EFFECT_DB, MIN_EFFECT_DEG, MIN_REDUCTION, SIGNIFICANT_BIC
from armfit.models.arm import APPARATUS_STAGES
from armfit.models.effects import Effect
from armfit.noise import rms_norm

__all__ = ["SubjectTest", "SubjectTrial", "by_subject_search", "per_subject_default",
           "spread", "subjects_allow"]


@dataclass(frozen=True)
class SubjectTrial:
    """One parameter tried per subject: ``param`` (the effect's own name), ΔBIC against
    the form before it, the fraction of the cost it removes, whether its change of the
    responses is practically significant, the largest such change (dB, deg), and whether
    it was kept."""

    param: str
    delta_bic: float
    rss_reduction: float
    practical: bool
    change_db: float
    change_deg: float
    kept: bool


@dataclass(frozen=True)
class SubjectTest:
    """The per-subject test of one effect on one axis: the subjects, the parameters tried
    in order (:class:`SubjectTrial`), those kept per subject (``varying``, the effect's
    own names: empty when one shared value suffices) and the error/noise of the shared and
    of the chosen form."""

    effect: str
    n_subjects: int
    trials: tuple[SubjectTrial, ...]
    varying: tuple[str, ...]
    rms_norm_shared: float
    rms_norm_chosen: float

    @property
    def by_subject(self) -> bool:
        """Whether some parameter of the effect is per subject."""
        return bool(self.varying)


def subjects_allow(data: AxisData) -> bool:
    """Whether the data allow a per-subject form: at least two subjects on the axis."""
    return len(set(data.subject_of_trials())) >= 2


def per_subject_default(effect: Effect) -> bool:
    """Whether an effect is tested per subject before the step chooses among candidates:
    an effect of the arm (a person's reflex differs between people); an apparatus effect
    (output or device stage) starts shared and is tested once named."""
    return effect.stage not in APPARATUS_STAGES


def by_subject_search(data: AxisData, band: tuple[float, float], fit: JointFit,
                      effect: Effect, min_db: float = MIN_EFFECT_DB,
                      min_deg: float = MIN_EFFECT_DEG) -> tuple[JointFit, SubjectTest]:
    """Which parameters of ``effect`` (already in ``fit``'s model) differ between subjects
    (see the module docstring). Returns the chosen fit — ``fit`` itself when one shared
    value suffices — and the test's record.

    Parameters
    ----------
    data : AxisData
        The axis's trials, with their subjects.
    band : (float, float)
        The diagnosis band (Hz).
    fit : JointFit
        The joint fit with ``effect`` shared by every trial (other effects as they are).
    effect : Effect
    min_db, min_deg : float
        The practical floors (dB, deg).

    Returns
    -------
    (JointFit, SubjectTest)
    """
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    f = data.f_hz[sel]
    se_db, se_deg = data.noise_se(sel)
    n_subj = len(set(data.subject_of_trials()))
    shared_err = rms_norm(fit.r_db, fit.r_deg, se_db, se_deg)
    if n_subj < 2:
        return fit, SubjectTest(effect.name, n_subj, (), (), shared_err, shared_err)
    current = fit
    remaining = [p.name for p in effect.params]
    trials: list[SubjectTrial] = []
    while remaining:
        tried = []
        for p in remaining:
            cand = fit_by_subject(data, band, current, [f"{effect.name}.{p}"])
            tried.append((p, cand, *_evidence(current, cand, f, se_db, se_deg, min_db,
                                              min_deg)))
        ok = [t for t in tried if t[2] > SIGNIFICANT_BIC and t[3] >= MIN_REDUCTION and t[4]]
        best = max(ok, key=lambda t: t[2]) if ok else None
        trials += [SubjectTrial(p, score, red, prac, cdb, cdeg, best is not None and p == best[0])
                   for p, _, score, red, prac, cdb, cdeg in tried]
        if best is None:
            break
        current = best[1]
        remaining.remove(best[0])
    varying = tuple(p.name for p in effect.params
                    if f"{effect.name}.{p.name}" in current.varying)
    return current, SubjectTest(effect.name, n_subj, tuple(trials), varying, shared_err,
                                rms_norm(current.r_db, current.r_deg, se_db, se_deg))


def _evidence(before: JointFit, after: JointFit, f, se_db, se_deg, min_db, min_deg):
    """(ΔBIC, cost removed, practical, largest change dB, deg) of ``after`` against the
    nested ``before``: the robust likelihood-ratio statistic less k ln N_eff (k: the free
    parameters ``after`` adds), and the change the subjects' own values make to
    ``after``'s responses against ``before``'s shared values
    (:func:`~armfit.diagnosis.evidence.response_change`)."""
    score, _, reduction = delta_bic(before, after, se_db, se_deg)
    new = [n for n in after.varying if n not in before.varying]
    size_db, size_deg = response_change(after, {n: before.shared[n] for n in new}, f)
    prac, _ = practical(f, size_db, size_deg, se_db, se_deg, min_db, min_deg)
    return (score, float(reduction), bool(prac), float(np.nanmax(size_db, initial=0.0)),
            float(np.nanmax(size_deg, initial=0.0)))


def spread(by_subject: Mapping[str, Mapping[str, float]], params: Sequence[str]
           ) -> dict[str, dict[str, float]]:
    """The population spread of per-subject values: {param: {min, max, sd}} in the
    parameter's unit (sd over subjects, ddof 1; NaN for one subject)."""
    out = {}
    for p in params:
        v = np.array([b[p] for b in by_subject.values()], float)
        out[p] = {"min": float(v.min()), "max": float(v.max()),
                  "sd": float(np.std(v, ddof=1)) if v.size > 1 else math.nan}
    return out
