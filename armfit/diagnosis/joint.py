"""The joint problem of one axis: every trial's arm parameters and the shared effect
parameters in one least-squares fit (:mod:`armfit.blocklsq`), its starting points screened
on a subset of trials and its stuck trials rescued by single-trial fits."""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import special

from armfit import blocklsq
from armfit.constants import PARAM_NAMES
from armfit.diagnosis.bands import residuals
from armfit.diagnosis.responses import AxisData
from armfit.diagnosis.tuning import (
    OUTLIER,
    REFINE_BEST,
    START_SCREEN_NFEV,
    START_SCREEN_TRIALS,
)
from armfit.fitting import ParamSpace, fit_response
from armfit.models.arm import ClosedLoopModel

__all__ = ["CHUNK_TRIALS", "JointFit", "JointProblem", "joint_fit", "refine", "rescue_trials",
           "screen_starts", "trial_fit"]

#: Trials whose residuals and Jacobian blocks :class:`JointProblem` evaluates in one go:
#: enough to keep numpy's loops long, few enough that the temporaries (about 40 kB a
#: trial for the Jacobian) stay small for any study. Up to this many trials an axis's
#: values are those of one evaluation of all; beyond, they may differ from it in the
#: last bits (numpy's vector loops round the tail of an array alike, not bit for bit).
CHUNK_TRIALS = 64


@dataclass(frozen=True)
class JointFit:
    """Result of one joint fit: per-trial base parameters (T, 5), shared effect
    parameters with 95 % intervals, residuals (T, n) and the residual sum of squares."""

    model: ClosedLoopModel
    base: np.ndarray
    shared: dict[str, float]
    shared_lo: dict[str, float]
    shared_hi: dict[str, float]
    r_db: np.ndarray
    r_deg: np.ndarray
    rss: float
    n_res: int
    rho: float
    converged: bool


class JointProblem:
    """Residuals of T trials with per-trial base parameters and shared effect parameters."""

    def __init__(self, model: ClosedLoopModel, data: AxisData, sel: np.ndarray):
        self.model = model
        self.space = ParamSpace.of(model)
        self.f = data.f_hz[sel]
        self.h = data.h[:, sel]
        sdb, sdeg = data.noise_se(sel)
        self.w_db, self.w_deg = 1.0 / sdb, 1.0 / sdeg
        self.T = self.h.shape[0]
        self.nb = len(PARAM_NAMES)
        self.k = len(self.space.names) - self.nb
        self.base_idx = np.arange(self.nb)
        self.eff_idx = np.arange(self.nb, self.nb + self.k)

    def unpack(self, x: np.ndarray) -> np.ndarray:
        """x (T·5 + k) → z (T, P) in the transformed space."""
        zb = x[: self.T * self.nb].reshape(self.T, self.nb)
        ze = np.broadcast_to(x[self.T * self.nb:], (self.T, self.k))
        return np.concatenate([zb, ze], axis=1)

    def response(self, x: np.ndarray, rows: slice = slice(None)) -> np.ndarray:
        """The model's response of the trials ``rows`` at ``x``, (t, n)."""
        theta = self.space.to_theta(self.unpack(x)[rows])
        values = {n: theta[:, i:i + 1] for i, n in enumerate(self.space.names)}
        return self.model.response(self.f, values)

    def split_res(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (dB, deg) of every trial at ``x``, (T, n), :data:`CHUNK_TRIALS`
        trials at a time (each trial's are its own, whatever its company)."""
        r_db, r_deg = np.empty(self.h.shape), np.empty(self.h.shape)
        for a in range(0, self.T, CHUNK_TRIALS):
            rows = slice(a, a + CHUNK_TRIALS)
            with np.errstate(all="ignore"):
                r_db[rows], r_deg[rows] = residuals(self.h[rows], self.response(x, rows))
        return r_db, r_deg

    def fun(self, x: np.ndarray) -> np.ndarray:
        r_db, r_deg = self.split_res(x)
        r = np.concatenate([r_db * self.w_db, r_deg * self.w_deg], axis=1)
        return np.where(np.isfinite(r), r, 1e6).ravel()

    def jac(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward-difference Jacobian of :meth:`fun` as its blocks (per-trial
        (T, m, 5), shared (T, m, k); see :mod:`armfit.blocklsq`), all columns in one
        vectorised evaluation: column j of every trial is perturbed at once (the trials'
        blocks do not overlap), shared columns for all trials together. Steps
        √eps·max(1, |z|), taken backwards at an upper bound. The trials are taken
        :data:`CHUNK_TRIALS` at a time, so the temporaries do not grow with the number of
        trials."""
        z = self.unpack(x)                                    # (T, P)
        m = 2 * self.f.size
        jb, js = np.empty((self.T, m, self.nb)), np.empty((self.T, m, self.k))
        for a in range(0, self.T, CHUNK_TRIALS):
            rows = slice(a, a + CHUNK_TRIALS)
            D = self._jac_rows(z[rows], rows)                 # (t, m, P)
            jb[rows], js[rows] = D[..., : self.nb], D[..., self.nb:]
        return jb, js

    def _jac_rows(self, z: np.ndarray, rows: slice) -> np.ndarray:
        """The Jacobian of the trials ``rows`` (their parameters ``z``), (t, m, P)."""
        t, P = z.shape
        h = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(z))
        h = np.where(z + h > self.space.zhi, -h, h)
        Z = np.repeat(z[None], P + 1, axis=0)                 # (P + 1, t, P)
        idx = np.arange(P)
        Z[idx + 1, :, idx] += h.T
        theta = self.space.to_theta(Z)
        values = {n: theta[..., i:i + 1] for i, n in enumerate(self.space.names)}
        with np.errstate(all="ignore"):
            r_db, r_deg = residuals(self.h[None, rows], self.model.response(self.f, values))
            R = np.concatenate([r_db * self.w_db[rows], r_deg * self.w_deg[rows]], axis=-1)
        R = np.where(np.isfinite(R), R, 1e6)
        D = (R[1:] - R[:1]) / h.T[:, :, None]                  # (P, t, m)
        return np.moveaxis(D, 0, -1)                           # (t, m, P)

    def solve(self, x0: np.ndarray, max_nfev: int, **tol) -> blocklsq.BlockResult:
        """The joint least-squares fit from ``x0`` (:func:`armfit.blocklsq.solve`)."""
        lo, hi = self.bounds()
        return blocklsq.solve(self.fun, self.jac, x0, lo, hi, n_trials=self.T,
                              n_block=self.nb, max_nfev=max_nfev, **tol)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.concatenate([np.tile(self.space.zlo[: self.nb], self.T),
                             self.space.zlo[self.nb:]])
        hi = np.concatenate([np.tile(self.space.zhi[: self.nb], self.T),
                             self.space.zhi[self.nb:]])
        return lo, hi

    def pack(self, base: np.ndarray, shared: Mapping[str, float]) -> np.ndarray:
        full = np.zeros((self.T, len(self.space.names)))
        full[:, : self.nb] = base
        for j, n in enumerate(self.space.names[self.nb:]):
            full[:, self.nb + j] = shared[n]
        z = self.space.clip_z(self.space.to_z(full))
        return np.concatenate([z[:, : self.nb].ravel(), z[0, self.nb:]])


def _lag1(r: np.ndarray) -> float:
    """Mean lag-1 autocorrelation along frequency of residual rows (T, n)."""
    r = r - r.mean(axis=1, keepdims=True)
    num = np.sum(r[:, 1:] * r[:, :-1])
    den = np.sum(r * r)
    return float(num / den) if den > 0 else 0.0


def joint_fit(model: ClosedLoopModel, data: AxisData, band: tuple[float, float],
              base: np.ndarray, starts: Sequence[Mapping[str, float]] = ({},),
              max_nfev: int = 200, pairs: Sequence[tuple[np.ndarray, Mapping]] = (),
              refine_best: int | None = None, screen_nfev: int | None = None) -> JointFit:
    """Fit ``model`` to every trial of ``data`` at once: arm parameters per trial, effect
    parameters shared (see the module docstring). ``base`` (T, 5), or a list of such:
    starting arm parameters (SI units); ``starts``: candidate starting values of the shared
    effect parameters; ``pairs``: further (base, start) combinations. Every combination is
    tried briefly on a subset of trials, the best ``refine_best`` (default
    :data:`REFINE_BEST`) refined on all, at most ``max_nfev`` evaluations each (the brief
    tries: ``screen_nfev``, default :data:`START_SCREEN_NFEV`).
    """
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = JointProblem(model, data, sel)
    bases = [base] if isinstance(base, np.ndarray) else list(base)
    combos = [(b, st) for b in bases for st in starts] + list(pairs)
    if len(combos) > 1:
        x0s = screen_starts(model, data, sel, combos, prob,
                      REFINE_BEST if refine_best is None else refine_best,
                      START_SCREEN_NFEV if screen_nfev is None else screen_nfev)
    else:
        x0s = [prob.pack(*combos[0])]
    res = None
    seen = set()
    for x0 in x0s:
        if x0.tobytes() in seen:   # the same start ends where it ended before: no better
            continue
        seen.add(x0.tobytes())
        r = rescue_trials(prob, model, data, sel, refine(prob, x0, max_nfev), max_nfev)
        if res is None or r.cost < res.cost:
            res = r
    z = prob.unpack(res.x)
    theta = prob.space.to_theta(z)
    r_db, r_deg = prob.split_res(res.x)
    names = prob.space.names[prob.nb:]
    shared = {n: float(theta[0, prob.nb + j]) for j, n in enumerate(names)}
    s_lo, s_hi = _shared_ci(prob, res, names)
    zres = np.concatenate([r_db * prob.w_db, r_deg * prob.w_deg], axis=1)
    rho = (_lag1(r_db * prob.w_db) + _lag1(r_deg * prob.w_deg)) / 2
    return JointFit(model, theta[:, : prob.nb], shared, s_lo, s_hi, r_db, r_deg,
                    float(np.sum(zres[np.isfinite(zres)] ** 2)), int(zres.size), rho,
                    bool(res.status > 0))


def refine(prob: JointProblem, x0: np.ndarray, max_nfev: int) -> blocklsq.BlockResult:
    """The joint fit from ``x0``, without its Jacobian blocks (``jb``, ``js`` None): a
    joint fit holds several results at once, each block as large as the study, and the
    intervals evaluate the Jacobian again at the solution (:func:`_shared_ci`; the same
    values, :meth:`JointProblem.jac` being a function of the parameters alone)."""
    return replace(prob.solve(x0, max_nfev, ftol=1e-8, xtol=1e-8), jb=None, js=None)


def rescue_trials(prob: JointProblem, model: ClosedLoopModel, data: AxisData, sel, res,
                  max_nfev: int):
    """Trials stuck in a poor local minimum of the joint fit (misfit far above the median
    trial's) get new arm parameters from a single-trial fit
    (:func:`armfit.fitting.fit_response`): first a local one from the median arm
    parameters of the trials that fit, then, for a trial still far off, the global
    search. The single-trial fit weighs the trial's residuals by the same noise model's
    standard errors as the joint fit (it is given the whole grid and the band). The joint
    fit is refined again; the better of the two results is returned."""
    per = (res.fun.reshape(prob.T, -1) ** 2).sum(axis=1)
    limit = OUTLIER * max(np.median(per), 2.0 * prob.f.size)
    bad = np.flatnonzero(per > limit)
    if bad.size == 0:
        return res
    x0 = res.x.copy()
    zb = x0[: prob.T * prob.nb].reshape(prob.T, prob.nb)
    theta = prob.space.to_theta(prob.unpack(res.x))
    shared = theta[0, prob.nb:]
    good = np.setdiff1d(np.arange(prob.T), bad)
    typical = np.exp(np.median(np.log(theta[good, : prob.nb]), axis=0)) if good.size else None
    names = prob.space.names
    band = (float(prob.f[0]), float(prob.f[-1]))

    def place(i: int, fit) -> None:
        row = np.array([fit.params[n] for n in PARAM_NAMES])
        zb[i] = prob.space.clip_z(prob.space.to_z(np.concatenate([row, shared])))[: prob.nb]

    for i in bad:
        if typical is not None:
            start = dict(zip(names, np.concatenate([typical, shared]), strict=True))
            place(i, trial_fit(model, data, i, band, start))
            r = prob.fun(x0).reshape(prob.T, -1)[i]
            if float(r @ r) <= limit:
                continue
        place(i, trial_fit(model, data, i, band))
    res2 = refine(prob, x0, max_nfev)
    return res2 if res2.cost < res.cost else res


#: The single-trial fits of :func:`rescue_trials` made in this process, by their inputs
#: (the last :data:`_TRIAL_FITS_KEPT`): the same trial is often rescued with the same
#: model again, by another start of the same joint fit, or by the fit on all trials after
#: the screening's on a subset.
_TRIAL_FITS: dict[tuple, object] = {}
_TRIAL_FITS_KEPT = 64
_TRIAL_FITS_LOCK = threading.Lock()     # an executor may run tasks in threads


def trial_fit(model: ClosedLoopModel, data: AxisData, i: int, band: tuple[float, float],
              start: Mapping[str, float] | None = None):
    """The single-trial fit of :func:`rescue_trials`: ``model`` fitted to trial ``i`` of
    ``data`` over ``band`` (:func:`armfit.fitting.fit_response`, weighted by the trial's
    standard errors), locally from ``start``, or by the global search without one. Only
    its parameters are used: no intervals, no second opinion on its convergence (which
    would change its message and flag only). A fit with the same inputs made before in
    this process is returned again (the fit is deterministic: the same result)."""
    key = (model, band, None if start is None else tuple(start.items()),
           data.f_hz.tobytes(), data.h[i].tobytes(), data.se_db[i].tobytes(),
           data.se_deg[i].tobytes())
    with _TRIAL_FITS_LOCK:
        fit = _TRIAL_FITS.get(key)
    if fit is None:
        fit = fit_response(model, data.f_hz, data.h[i], se_db=data.se_db[i],
                           se_deg=data.se_deg[i], band=band, x0=start,
                           global_search=start is None, strict=False, intervals=False,
                           second_opinion=False)
        with _TRIAL_FITS_LOCK:
            while len(_TRIAL_FITS) >= _TRIAL_FITS_KEPT:
                del _TRIAL_FITS[next(iter(_TRIAL_FITS))]
            _TRIAL_FITS[key] = fit
    return fit


def screen_starts(model, data: AxisData, sel, combos, prob: JointProblem, keep: int = REFINE_BEST,
            nfev: int = START_SCREEN_NFEV) -> np.ndarray:
    """Short fits of every (base, start) pair on a spread-out subset of the trials;
    returns the full starting vectors built from the ``keep`` best."""
    T = data.h.shape[0]
    idx = np.unique(np.linspace(0, T - 1, min(T, START_SCREEN_TRIALS)).round().astype(int))
    sub = AxisData(data.axis, data.f_hz, data.h[idx], data.se_db[idx], data.se_deg[idx],
                   tuple(data.starts[i] for i in idx))
    sprob = JointProblem(model, sub, sel)
    scored = []
    tried: dict[bytes, blocklsq.BlockResult] = {}
    for b, st in combos:
        # combinations that pack to the same start (e.g. a Levy row that is the given
        # row on every trial) have the same short fit: made once
        x = sprob.pack(b[idx], st)
        r = tried.get(x.tobytes())
        if r is None:
            r = tried[x.tobytes()] = sprob.solve(x, nfev)
        scored.append((r.cost, b, st, r.x))
    scored.sort(key=lambda t: t[0])
    out = []
    for _, b, st, xs in scored[:keep]:
        x0 = prob.pack(b, st)
        if prob.k:
            x0[-prob.k:] = xs[-prob.k:]
        out.append(x0)
    return out


def _shared_ci(prob: JointProblem, res, names) -> tuple[dict[str, float], dict[str, float]]:
    """95 % intervals of the shared parameters from the Jacobian (Schur complement)."""
    if not names:
        return {}, {}
    m, p = res.fun.size, res.x.size
    s2 = 2 * res.cost / max(m - p, 1)
    k = len(names)
    jb, js = (res.jb, res.js) if res.jb is not None else prob.jac(res.x)
    var = s2 * np.diag(blocklsq.shared_covariance(jb, js))
    half = special.ndtri(0.975) * np.sqrt(np.maximum(var, 0))
    z = res.x[-k:]
    sp = prob.space
    zl = np.clip(z - half, sp.zlo[prob.nb:], sp.zhi[prob.nb:])
    zh = np.clip(z + half, sp.zlo[prob.nb:], sp.zhi[prob.nb:])
    full_l = np.tile(sp.zlo, 1).astype(float)
    full_h = full_l.copy()
    full_l[prob.nb:] = zl
    full_h[prob.nb:] = zh
    tl = sp.to_theta(full_l)[prob.nb:]
    th = sp.to_theta(full_h)[prob.nb:]
    return ({n: float(v) for n, v in zip(names, tl, strict=True)},
            {n: float(v) for n, v in zip(names, th, strict=True)})
