"""The joint fits of the diagnosis: the base model, the current model plus one effect, and a
refit from the values the axes share."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from armfit.constants import PARAM_NAMES
from armfit.diagnosis.joint import JointFit, joint_fit
from armfit.diagnosis.responses import AxisData
from armfit.diagnosis.starts import start_rows
from armfit.diagnosis.tuning import QUICK_BEST, QUICK_NFEV, QUICK_SCREEN_NFEV
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import Effect

__all__ = ["fit_base", "fit_borrowed", "fit_by_subject", "fit_extend", "start_array"]


def start_array(data: AxisData) -> np.ndarray:
    return np.array([[s[n] for n in PARAM_NAMES] for s in data.starts], float)


def fit_base(data: AxisData, band: tuple[float, float]) -> JointFit:
    """The base model (eq. 4) fitted jointly to every trial of one axis."""
    base_model = ClosedLoopModel.for_axis(data.axis)
    start = start_array(data)
    return joint_fit(base_model, data, band,
                     [start, start_rows(base_model, data, band, {}, [start])])


def fit_extend(data: AxisData, band: tuple[float, float], current: JointFit,
               effect: Effect, screened: JointFit | None = None, *,
               quick: bool = False, by_subject: bool = False) -> JointFit:
    """``current``'s model plus ``effect``, all effects refitted jointly (shared across
    the trials), warm-started from ``current`` with the new effect at its null point and
    at the screening's values (:func:`screen_candidate`; or, without one, at the effect's starting
    points, also with each effect added before restarted at its own starting points);
    never worse than ``current``. ``by_subject``: every parameter of ``effect`` with one
    value per subject (each subject starting at the same starting points)."""
    start = start_array(data)
    model = current.model.with_effect(effect)
    varying = tuple(current.varying) + (tuple(f"{effect.name}.{p}" for p in effect.param_names)
                                        if by_subject else ())
    null = {**current.shared, **{f"{effect.name}.{k}": v
                                 for k, v in effect.null_values(model.mp).items()}}
    def named(e: Effect, st: Mapping[str, float]) -> dict[str, float]:
        return {f"{e.name}.{k}": v for k, v in st.items()}

    fresh = []
    if screened is not None:
        starts = [null, dict(screened.shared)]
    else:
        starts = [{**current.shared, **named(effect, st)}
                  for st in effect.start_points(model.mp)]
        # an effect added before may have settled where it stood in for this one (a lag
        # for a delay): also start it afresh from its own starting points, one such
        # effect at a time, with each of this effect's
        fresh = [{**current.shared, **named(prev, pst), **named(effect, st)}
                 for prev in current.model.effects
                 for pst in prev.start_points(model.mp)[1:]
                 for st in effect.start_points(model.mp)[1:]]
    # from the current fit and from Levy starts with the effects removed: a strong
    # missing effect can pull the arm parameters far from those the extended model needs
    pairs = [(start_rows(model, data, band, st, [start, current.base]), st)
             for st in starts[1:] + fresh]
    starts = starts + fresh
    opts = {"refine_best": QUICK_BEST, "max_nfev": QUICK_NFEV,
            "screen_nfev": QUICK_SCREEN_NFEV} if quick else {}
    fit = joint_fit(model, data, band, [current.base], starts, pairs=pairs,
                    varying=varying, by_subject=current.by_subject, **opts)
    if fit.rss > current.rss:  # nested: never worse than the current fit
        fit = replace(current, model=model, shared=null,
                      shared_lo={}, shared_hi={})
    return fit


def fit_by_subject(data: AxisData, band: tuple[float, float], current: JointFit,
                   names: Sequence[str]) -> JointFit:
    """``current``'s model with the effect parameters ``names`` (``effect.param``) given
    one value per subject (besides those ``current`` already gives one), refitted jointly
    from ``current``: every subject starts at the shared value, so the fit is nested in
    ``current`` and never worse than it."""
    varying = tuple(n for n in current.model.param_names
                    if n in set(names) | set(current.varying))
    start = {n: {**{v: current.shared[v] for v in names}, **dict(b)}
             for n, b in current.by_subject.items()}
    fit = joint_fit(current.model, data, band, current.base, (dict(current.shared),),
                    varying=varying, by_subject=start or None)
    if fit.rss > current.rss:   # nested: never worse (a subject at the shared value)
        subjects = data.subject_of_trials()
        values = {s: {v: (current.by_subject.get(s, {}).get(v, current.shared[v]))
                      for v in varying} for s in dict.fromkeys(subjects)}
        fit = replace(current, varying=varying, subjects=tuple(subjects), by_subject=values,
                      by_subject_lo={}, by_subject_hi={})
    return fit


def fit_borrowed(data: AxisData, band: tuple[float, float], current: JointFit,
                 model: ClosedLoopModel, agreement: Mapping[str, dict]) -> JointFit:
    """``model`` (``current``'s effects plus any shared effect it lacks) fitted jointly
    to the axis, started from the common values of the shared effects across axes
    (``agreement``, see :func:`cross_axis_agreement`) and from ``current``; all
    parameters free. Never worse than ``current`` on its own effects."""
    common = {f"{name}.{p}": v["common"] for name, e in agreement.items()
              for p, v in e["params"].items() if f"{name}.{p}" in model.param_names}
    null = {}
    for e in model.effects:
        null.update({f"{e.name}.{k}": v for k, v in e.null_values(model.mp).items()})
    st_common = {**null, **current.shared, **common}
    st_current = {**null, **current.shared}
    start = start_array(data)
    pairs = [(start_rows(model, data, band, st_common, [start, current.base]), st_common)]
    return joint_fit(model, data, band, [current.base], [st_common, st_current], pairs=pairs,
                     varying=current.varying, by_subject=current.by_subject)
