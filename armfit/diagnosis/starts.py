"""Starting arm parameters of a joint fit: the analytic (Levy) guess of each trial with the
effects removed, and the best of several candidate rows per trial."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from armfit._order import median
from armfit.constants import PARAM_NAMES
from armfit.diagnosis.bands import residuals
from armfit.diagnosis.responses import AxisData
from armfit.diagnosis.tuning import CHUNK_TRIALS, UNIT_DEG
from armfit.fitting import levy_candidates_many, levy_rows
from armfit.models.arm import ClosedLoopModel

__all__ = ["best_rows", "levy_starts", "start_rows"]


def levy_starts(model: ClosedLoopModel, data: AxisData, band: tuple[float, float],
                 effect_values: Mapping[str, float], fallback: np.ndarray) -> np.ndarray:
    """Per-trial arm parameters (T, 5) from the analytic (Levy) guess of
    :func:`armfit.fitting.analytic_guess`, applied to each trial's response with the
    effects at ``effect_values`` removed (:meth:`ClosedLoopModel.remove_effects`); the
    candidate closest to the data in log error, or the ``fallback`` row where none is
    physical. A start that does not depend on a possibly distorted earlier fit."""
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    f = data.f_hz[sel]
    out = np.array(fallback, float, copy=True)
    base_model = ClosedLoopModel(mp=model.mp)
    lower, upper = (np.array([p.lower for p in base_model.params]),
                    np.array([p.upper for p in base_model.params]))
    # the linear fit is sensitive to the noisy lowest frequencies: also try it above
    # 0.3 Hz and above 1 Hz, judge every candidate on the whole band
    cuts = [f >= lo_f for lo_f in (0.0, 0.3, 1.0) if np.sum(f >= lo_f) > 10]
    for a in range(0, data.h.shape[0], CHUNK_TRIALS):
        chunk = slice(a, a + CHUNK_TRIALS)
        with np.errstate(all="ignore"):
            # the responses without the effects, and the rows of their linear systems,
            # of CHUNK_TRIALS trials at once (each value is that trial's own; the
            # temporaries do not grow with the number of trials)
            hbs = model.remove_effects(f, data.h[chunk, sel], effect_values) \
                if effect_values else data.h[chunk, sel]
            a_w, b_w = levy_rows(f, hbs, model.mp)
            # the candidates of every band cut of every trial of the chunk at once
            # (:func:`levy_candidates_many`: each system's own, the same numbers)
            finite = [i for i, hb in enumerate(hbs) if np.all(np.isfinite(hb))]
            found = iter(levy_candidates_many([(a_w[i][cut], b_w[i][cut])
                                               for i in finite for cut in cuts]))
        for i in finite:
            cands = [c for _ in cuts for c in next(found)]
            best = _levy_best(base_model, f, hbs[i], cands, lower, upper)
            if best is not None:
                out[a + i] = best
    return out


def _levy_best(base_model: ClosedLoopModel, f: np.ndarray, hb: np.ndarray,
               cands: Sequence[Mapping[str, float]], lower: np.ndarray,
               upper: np.ndarray) -> np.ndarray | None:
    """One trial's row of :func:`levy_starts` (None: no physical candidate): its Levy
    candidates ``cands`` (those of each band cut, in turn), clipped to the bounds, judged
    at once on the whole band; the first of the closest."""
    with np.errstate(all="ignore"):
        if not cands:
            return None
        rows = np.clip([[c[n] for n in PARAM_NAMES] for c in cands], lower, upper)
        r_db, r_deg = residuals(hb, base_model.response(
            f, {n: rows[:, j:j + 1] for j, n in enumerate(PARAM_NAMES)}))
        err = np.nanmean(r_db ** 2 + (r_deg / UNIT_DEG) ** 2, axis=1)
    ok = np.flatnonzero(np.isfinite(err))
    return rows[ok[np.argmin(err[ok])]] if ok.size else None


def best_rows(model: ClosedLoopModel, data: AxisData, band: tuple[float, float],
              effect_values: Mapping[str, float], candidates: Sequence[np.ndarray]
              ) -> np.ndarray:
    """Per trial, the candidate row of arm parameters (each candidate (T, 5) or (5,))
    whose response, with the effects at ``effect_values``, is closest to the trial's data
    in normalised squared error. Returns (T, 5)."""
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    f = data.f_hz[sel]
    sdb, sdeg = data.noise_se(sel)
    T = data.h.shape[0]
    rows = [np.broadcast_to(np.asarray(c, float), (T, len(PARAM_NAMES))) for c in candidates]
    errs = np.empty((len(rows), T))
    # CHUNK_TRIALS trials at a time: each trial's error is its own, whatever its company,
    # and the responses and residuals of all the trials are never held at once
    for a in range(0, T, CHUNK_TRIALS):
        t = slice(a, a + CHUNK_TRIALS)
        h = data.h[t, sel]
        for j, r in enumerate(rows):
            theta = {n: r[t, i:i + 1] for i, n in enumerate(PARAM_NAMES)}
            theta.update({k: v for k, v in effect_values.items()})
            if not model.effects:
                theta = {n: theta[n] for n in PARAM_NAMES}
            with np.errstate(all="ignore"):
                r_db, r_deg = residuals(h, model.response(f, theta))
                e = np.nansum((r_db / sdb[t]) ** 2 + (r_deg / sdeg[t]) ** 2, axis=1)
            errs[j, t] = np.where(np.isfinite(e), e, np.inf)
    pick = np.argmin(errs, axis=0)
    return np.array([rows[k][i] for i, k in enumerate(pick)])


def start_rows(model, data, band, effect_values, given: Sequence[np.ndarray]) -> np.ndarray:
    """Best per-trial start among the given rows, the Levy guess with the effects removed,
    and the median Levy row over trials (robust to a trial whose own guess failed)."""
    levy = levy_starts(model, data, band, effect_values, given[0])
    return best_rows(model, data, band, effect_values,
                     [*given, levy, np.exp(median(np.log(levy), axis=0))])
