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
from armfit.fitting import analytic_guess
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
    bounds = [(p.lower, p.upper) for p in base_model.params]
    for i in range(data.h.shape[0]):
        with np.errstate(all="ignore"):
            hb = model.remove_effects(f, data.h[i, sel], effect_values) if effect_values \
                else data.h[i, sel]
            if not np.all(np.isfinite(hb)):
                continue
            best = None
            # the linear fit is sensitive to the noisy lowest frequencies: also try it
            # above 0.3 Hz and above 1 Hz, judge every candidate on the whole band
            cands = [c for lo_f in (0.0, 0.3, 1.0) if np.sum(f >= lo_f) > 10
                     for c in analytic_guess(f[f >= lo_f], hb[f >= lo_f], model.mp)]
            for cand in cands:
                row = np.array([np.clip(cand[n], lo, hi)
                                for n, (lo, hi) in zip(PARAM_NAMES, bounds, strict=True)])
                r_db, r_deg = residuals(hb, base_model.response(f, row))
                err = float(np.nanmean(r_db ** 2 + (r_deg / UNIT_DEG) ** 2))
                if np.isfinite(err) and (best is None or err < best[0]):
                    best = (err, row)
        if best is not None:
            out[i] = best[1]
    return out


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
