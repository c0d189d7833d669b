"""Screening of candidate effects: each fitted jointly on a few trials spread over the axis,
ranked by the cost it leaves; the best get the joint fit on all trials."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from armfit._order import unique
from armfit.diagnosis.fit import fit_extend
from armfit.diagnosis.joint import JointFit
from armfit.diagnosis.responses import AxisData
from armfit.diagnosis.tuning import SCREEN_GAP, SCREEN_KEEP, SCREEN_SUBSET
from armfit.models.effects import Effect

__all__ = ["keep_screened", "rank_screened", "screen_candidate", "screen_on", "screen_trials"]


def keep_screened(screened: Sequence[tuple[Effect, JointFit]]) -> list[tuple[Effect, JointFit]]:
    """The screened candidates (lowest subset cost first) that get the joint fit on all
    trials: at most :data:`SCREEN_KEEP`, within :data:`SCREEN_GAP` of the best."""
    if not screened:
        return []
    best = screened[0][1].rss
    return [c for c in screened[:SCREEN_KEEP] if c[1].rss <= SCREEN_GAP * best]


def _trial_subset(data: AxisData, fit: JointFit, idx: np.ndarray,
            band: tuple[float, float]) -> tuple[AxisData, JointFit]:
    """The trials ``idx`` of ``data`` and of ``fit`` (its residuals on ``band``), the
    subset's residual sum of squares weighted as :func:`joint_fit` weighs it."""
    sub = data.subset(idx)
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    sdb, sdeg = sub.noise_se(sel)
    z = np.concatenate([fit.r_db[idx] / sdb, fit.r_deg[idx] / sdeg], axis=1)
    return sub, fit.subset(idx, rss=float(np.sum(z[np.isfinite(z)] ** 2)), n_res=int(z.size))


def screen_candidate(data: AxisData, band: tuple[float, float], current: JointFit,
           effect: Effect, by_subject: bool = False) -> JointFit:
    """A cheap fit of ``current``'s model plus ``effect``: the same joint fit as
    :func:`fit_extend` (arm parameters per trial, effects shared, from the effect's null
    and starting points) on :data:`SCREEN_SUBSET` trials spread over the axis (one per
    grip in the paper's design) instead of all. Candidates are ranked by the fraction of
    the subset's cost they remove; the best :data:`SCREEN_KEEP` get the joint fit on all
    trials, started from the screening's effect values. ``by_subject``: the effect with
    one value per subject (an effect of the arm, :mod:`armfit.diagnosis.subjects`): on
    the subset, whose trials are of different subjects in the paper's design, one value
    per trial. Returns the subset's fit."""
    return screen_on(*screen_trials(data, band, current), band, effect, by_subject)


def screen_trials(data: AxisData, band: tuple[float, float], current: JointFit
                  ) -> tuple[AxisData, JointFit, bool]:
    """What every candidate of a step is screened on (:func:`screen_candidate`): the
    :data:`SCREEN_SUBSET` trials spread over the axis and ``current``'s fit of them,
    ``quick`` True; or all the trials and ``current`` when there are no more, ``quick``
    False. The same for every candidate, so it is made once a step and the screening
    fits are handed only these trials."""
    T = data.h.shape[0]
    if T <= SCREEN_SUBSET:
        return data, current, False
    idx = unique(np.linspace(0, T - 1, SCREEN_SUBSET).round().astype(int))
    return (*_trial_subset(data, current, idx, band), True)


def screen_on(data: AxisData, current: JointFit, quick: bool, band: tuple[float, float],
              effect: Effect, by_subject: bool = False) -> JointFit:
    """The screening fit of ``effect`` on :func:`screen_trials`' trials ``data`` and fit
    ``current`` (``quick``: a subset's)."""
    return fit_extend(data, band, current, effect, quick=quick, by_subject=by_subject)


def rank_screened(screened: list[tuple[Effect, JointFit]]) -> list[tuple[Effect, JointFit]]:
    """Screening fits lowest subset cost first (the same subset for every candidate;
    ties keep the library's order)."""
    return sorted(screened, key=lambda t: t[1].rss)
