"""Fits of the measured-dynamics model H_CL (Fu & Çavuşoğlu 2010, eqs. 4–5) to responses.

Costs (residuals r_n; the fitter minimises Σ r_n²):

``"paper"``    eq. 5 with Wt(n) = 1 (the paper's weight is not specified):
               r_n = 20 log10|H_CL(jω_n)| − 20 log10|H_exp(jω_n)| in dB, magnitude only.
``"complex"``  the complex log error, magnitude and phase, each divided by the
               measurement's standard error: r = [ΔdB_n / se_db_n, Δdeg_n / se_deg_n],
               Δdeg_n = angle(H_CL / H_exp) in degrees. Without standard errors the weights
               are 1 dB and :data:`UNIT_SE_DEG` degrees, which makes the cost |ln(H_CL/H_exp)|²
               up to a constant (1 neper = 20/ln 10 dB ↔ 1 rad = 180/π deg).

Parameters are searched as log(θ) (θ > 0) inside the physical bounds of
:attr:`armfit.models.arm.ClosedLoopModel.params` with ``scipy.optimize.least_squares``'s
trust-region-reflective method (:func:`armfit._trf.bounded_least_squares`: the same iterates,
without importing :mod:`scipy.optimize`).
The global search needs no user starting values and no seed: (1) an analytic initial guess
(Levy's linear fit of the arm impedance Z_ARM = 1/H − Mp s², exact for noise-free data);
(2) the typical values of ClosedLoopModel.params and any warm start; (3) a fixed,
unscrambled Sobol set of 512 points over the log-bounds, screened in one vectorised
evaluation; (4) structured starts (:func:`_anchors`), screened apart: the arm rows of the
paper's Tables I and II and the analytic guess with the effects removed, with the effects
at their null, starting and typical values (the Sobol set is thin in the stiff-Z corner).
The starts of (1)–(2), the 3 best screened Sobol points and the 3 best structured starts
are refined on a log-spaced
subset of the band, both with the cost's weights and with unit weights (a smoother
landscape), all these local fits solved together by :mod:`armfit.multilsq` (the same
trust-region-reflective method, vectorised over the fits); the two best distinct end
points (by the full weighted cost) are polished on every bin of the band and the better
kept. Jacobians are analytic in the arm parameters (∂ ln H/∂θ of eq. 3) and central
differences in an effect's, evaluated in one vectorised batch. No random numbers are
drawn: the answer is the same on every run.

Convergence: a fit is converged when the optimiser is and, should it end more than
:data:`FAR_FROM_NOISE` times the noise, no point the search reached has a cost below
:data:`MARKEDLY_LOWER` of its own (a local fit from ``x0`` then also refines the cheapest
structured starts); otherwise its message names the local minimum and the better start.

The "complex" cost's standard errors are those of the noise model
(:func:`armfit.noise.standard_errors`: capped at pure noise, filled, pooled over
neighbouring bins, floored), and ``rms_norm`` is its "× noise" statistic
(:func:`armfit.noise.rms_norm`), the same number ``compare``, the diagnosis and the
figures report for the same model on the same bins.

Confidence intervals (95 %) are formed in log-parameter space and are the wider of two:

* noise: from the Jacobian at the optimum, cov = c·(1 + ρ)/(1 − ρ)·(JᵀJ)⁻¹, ρ the lag-1
  autocorrelation of the residuals along frequency (neighbouring bins are not
  independent). With the "complex" cost and measured standard errors the residuals are in
  units of the noise and c = max(1, χ²_red), χ²_red = Σ r²/(m − p) = rms_norm² (up to
  m/(m − p)): when the error exceeds the noise the intervals widen by √χ²_red, as lmfit's
  default ``scale_covar`` and the Particle Data Group's scale factor do; when it is below,
  they keep the width the measured noise implies (a chance low χ² is no evidence that the
  noise was smaller). Without measured standard errors (cost "paper", unit weights) c =
  χ²_red, the residual variance. Half-width t₀.₉₇₅(m − p)·√diag(cov).
* misfit, when the error exceeds the noise (χ²_red > 1, i.e. rms_norm > 1; always when
  there are no measured standard errors to tell): a delete-a-band jackknife
  (:func:`band_jackknife`), the fit repeated without each of :data:`JACKKNIFE_BANDS`
  contiguous bands, half-width t₀.₉₇₅(G − 1)·sd_j. A
  model that misses the data by more than the noise (a discretised device, an
  estimator's bias) moves its parameters by more than the noise interval says, and by
  about as much as leaving out part of the band does. On five time-domain simulated
  studies with no between-subject variability (225 true values, rms_norm 0.96–2.2) the
  noise intervals alone covered 68 % of the true values, the wider of the two 97 %
  (benchmarks/interval_coverage.py; docs/methods.md, "Intervals").

Transformed back: lo = θ·exp(−h), hi = θ·exp(+h) (asymmetric in θ, never negative).
Parameters declared ``log=False`` (e.g. a delay that may be 0) are searched, and their
intervals formed, on a linear scale across their bounds instead.
:func:`bootstrap_fit` replaces them by percentile intervals from resampled subjects,
never narrower than these.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from armfit import _trf, multilsq, noise
from armfit._order import median, percentile, unique
from armfit._student import t_quantile
from armfit.constants import DB_PER_NEPER, PAPER_BANDS, PARAM_NAMES, UNIT_SE_DEG
from armfit.data import sobol_points
from armfit.errors import BadInputError, ConvergenceError, EffectDefinitionError, UsageError
from armfit.io.schema import params_columns
from armfit.models.arm import ClosedLoopModel, at_bound, laplace, union_param_names
from armfit.models.effects import effects_by_axis, resolve_effects
from armfit.workers import POOL_PRELOAD, iter_tasks

if TYPE_CHECKING:   # imported where used: a fit's worker needs neither (see armfit.workers)
    from armfit.io.artifacts import RowTable
    from armfit.spectra import Spectra

COSTS: tuple[str, ...] = ("complex", "paper")

_N_SOBOL = 512          # screened candidate starts (2**9, fixed and unscrambled)
_N_REFINE = 3           # screened candidates refined locally, per weighting
_N_SUBSET = 160         # log-spaced bins used while refining candidates
_N_ANCHORS = 3          # structured starts (paper rows, effect-removed guess) refined
_MAX_EFFECT_POINTS = 64  # combinations of the effects' starting values among the anchors
_TOL = 1e-12            # ftol/xtol/gtol of the final polish
#: Contiguous frequency bands of the delete-a-band jackknife (:func:`band_jackknife`):
#: six bands of equal log width, about half a decade each over 0.1–30 Hz. Chosen on
#: time-domain simulated studies (benchmarks/interval_coverage.py): with 6 bands the
#: 95 % intervals covered 97 % of the true values, with 10 bands 92 % (16 bands: 75 % on
#: an exploratory subset).
JACKKNIFE_BANDS = 6


@dataclass(frozen=True)
class FitResult:
    """One fit of H_CL: parameters (SI: kg, N/m, N·s/m; effects in their own units), their
    95 % intervals, and fit statistics.

    ``rms_db``/``rms_deg``: RMS magnitude (dB) and phase (deg) error over the band, whatever
    the cost; ``rms_norm``: RMS of both errors divided by the measurement's standard errors
    (≈ 1 when the model fits within the noise; NaN without standard errors); ``at_bound``:
    the parameters within 1 % of a physical bound (:func:`armfit.models.arm.at_bound`);
    ``band``: the
    (lo, hi) band in Hz; ``n_points``: bins fitted; ``cost``: "complex" or "paper";
    ``ci_method``: "jacobian" or "bootstrap-<N>"; ``objective``: the minimised Σ r².
    """

    model: ClosedLoopModel
    params: dict[str, float]
    ci_lo: dict[str, float]
    ci_hi: dict[str, float]
    rms_db: float
    rms_deg: float
    rms_norm: float
    band: tuple[float, float]
    n_points: int
    cost: str
    converged: bool
    message: str
    nfev: int = 0
    ci_method: str = "jacobian"
    objective: float = field(default=float("nan"))
    #: Parameters within 1 % of a physical bound (:func:`armfit.models.arm.at_bound`):
    #: the data pushed them against the edge, so their values and intervals are not
    #: estimates of anything.
    at_bound: tuple[str, ...] = ()

    def row(self) -> dict[str, float | str | bool]:
        """Parameters, intervals and statistics as one flat dict (the params CSV column names,
        docs/formats.md "Params CSV")."""
        held = self.model.held_values
        out: dict[str, float | str | bool] = {
            n: held[n] if n in held else self.params[n] for n in self.model.all_param_names}
        nan = float("nan")
        for n in self.model.all_param_names:   # a held value is given, not estimated
            out[f"{n}_lo"] = nan if n in held else self.ci_lo[n]
            out[f"{n}_hi"] = nan if n in held else self.ci_hi[n]
        out.update(rms_db=self.rms_db, rms_deg=self.rms_deg, rms_norm=self.rms_norm,
                   band_lo_hz=self.band[0], band_hi_hz=self.band[1], n_points=self.n_points,
                   cost=self.cost, converged=self.converged, mp_kg=self.model.mp,
                   effects=";".join(e.name for e in self.model.effects),
                   at_bound=";".join(self.at_bound))
        if held:
            out["held"] = ";".join(held)
        return out


# ---------------------------------------------------------------------------
# Parameter transform (log for positive parameters, scaled-linear otherwise)
# ---------------------------------------------------------------------------

def _read_only(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class ParamSpace:
    names: tuple[str, ...]
    log: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def of(cls, model: ClosedLoopModel) -> ParamSpace:
        ps = model.params
        return cls(tuple(p.name for p in ps), np.array([p.log for p in ps]),
                   np.array([p.lower for p in ps], float), np.array([p.upper for p in ps], float))

    # the bounds in the fitter's coordinate, made once (every Jacobian and every fit of
    # the diagnosis asks for them) and read-only, as the fields they come from never change

    @functools.cached_property
    def zlo(self) -> np.ndarray:
        return _read_only(np.where(self.log, np.log(np.where(self.log, self.lower, 1.0)), 0.0))

    @functools.cached_property
    def zhi(self) -> np.ndarray:
        return _read_only(np.where(self.log, np.log(np.where(self.log, self.upper, 1.0)), 1.0))

    def to_theta(self, z: np.ndarray) -> np.ndarray:
        z = np.asarray(z, float)
        lin = self.lower + z * (self.upper - self.lower)
        return np.where(self.log, np.exp(np.where(self.log, z, 0.0)), lin)

    def to_z(self, theta: np.ndarray) -> np.ndarray:
        theta = np.clip(np.asarray(theta, float), self.lower, self.upper)
        lin = (theta - self.lower) / (self.upper - self.lower)
        return np.where(self.log, np.log(np.where(self.log, theta, 1.0)), lin)

    def clip_z(self, z: np.ndarray) -> np.ndarray:
        # keep starts strictly inside the bounds (least_squares requires it)
        span = self.zhi - self.zlo
        return np.clip(z, self.zlo + 1e-9 * span, self.zhi - 1e-9 * span)


# ---------------------------------------------------------------------------
# Residuals
# ---------------------------------------------------------------------------

def log_errors(model_h: np.ndarray, data_h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Magnitude error (dB) and phase error (deg, wrapped to ±180) of a model response
    against data: 20 log10|Hm/Hd| and angle(Hm/Hd) — the terms of eq. 5 and its phase
    counterpart."""
    ratio = model_h / data_h
    # np.angle's own arctan2 of (imag, real), without its argument handling
    return (DB_PER_NEPER * np.log(np.abs(ratio)),
            np.degrees(np.arctan2(ratio.imag, ratio.real)))


@dataclass(frozen=True)
class _Problem:
    model: ClosedLoopModel
    space: ParamSpace
    f: np.ndarray
    h: np.ndarray
    w_db: np.ndarray      # 1/se_db
    w_deg: np.ndarray     # 1/se_deg
    cost: str

    def theta_dict(self, theta: np.ndarray) -> dict[str, np.ndarray]:
        return {n: theta[..., i] for i, n in enumerate(self.space.names)}

    def residuals_batch(self, z: np.ndarray, idx: np.ndarray | slice = slice(None),
                        z_base: np.ndarray | None = None) -> np.ndarray:
        """Residuals for a batch of points z (k, p) → (k, m). ``z_base`` (k, n): Z_ARM +
        Mp s² of each point's base parameters, when known
        (:meth:`~armfit.models.arm.ClosedLoopModel.response_at_base`; the same values)."""
        theta = self.space.to_theta(z)
        values = {n: v[:, None] for n, v in self.theta_dict(theta).items()}
        hm = self.model.response(self.f[idx], values) if z_base is None \
            else self.model.response_at_base(self.f[idx], values, z_base)
        return self._weighted(hm, idx)

    def residuals(self, z: np.ndarray, idx: np.ndarray | slice = slice(None)) -> np.ndarray:
        theta = self.space.to_theta(z)
        hm = self.model.response(self.f[idx], self.theta_dict(theta))
        return self._weighted(hm, idx)

    def jacobian_batch(self, z: np.ndarray, idx: np.ndarray | slice = slice(None),
                       first: int = 0, z_base: np.ndarray | None = None) -> np.ndarray:
        """∂r/∂z by central differences (step 1e-6 in z) at a batch of points z (k, p) →
        (k, m, p − first): the columns of the parameters from ``first`` on, all their
        2k(p − first) points in one batch. ``z_base`` (k, n): Z_ARM + Mp s² at each
        point, when only effect parameters are stepped (``first`` past the base ones):
        the stepped points share it."""
        step = 1e-6
        k, p = z.shape
        q = p - first
        e = step * np.eye(p)[first:]
        pts = np.concatenate([z[:, None, :] + e, z[:, None, :] - e], axis=1)  # (k, 2q, p)
        r = self.residuals_batch(pts.reshape(2 * k * q, p), idx,
                                 None if z_base is None else np.repeat(z_base, 2 * q, axis=0)
                                 ).reshape(k, 2 * q, -1)
        return np.swapaxes(r[:, :q] - r[:, q:], 1, 2) / (2 * step)

    def jacobian_analytic(self, z: np.ndarray, idx: np.ndarray | slice = slice(None)
                          ) -> np.ndarray:
        """:meth:`jacobian_analytic_batch` at one point z (p,) → (m, p)."""
        return self.jacobian_analytic_batch(z[None], idx)[0]

    def jacobian_analytic_batch(self, z: np.ndarray, idx: np.ndarray | slice = slice(None)
                                ) -> np.ndarray:
        """∂r/∂z at a batch of points z (k, p) → (k, m, p), the arm parameters' columns
        analytic: r holds 20 log10|Hm/Hd| and angle(Hm/Hd) in deg times the weights, so
        an arm parameter's column is (DB_PER_NEPER Re, 180/π Im) of ∂ ln H/∂θ (eq. 3,
        :meth:`~armfit.models.arm.ClosedLoopModel.response_and_base_log_derivatives`)
        times the weights and dθ/dz (θ for a parameter fitted in log, else upper −
        lower). An effect's columns are central differences (:meth:`jacobian_batch`). A
        point whose residual is not finite (a constant in the residuals) has a zero row
        there."""
        k, p = z.shape
        nb = len(PARAM_NAMES)
        if self.space.names[:nb] != PARAM_NAMES:   # an arm parameter held: all differences
            return self.jacobian_batch(z, idx)
        theta = self.space.to_theta(z)
        values = {n: v[:, None] for n, v in self.theta_dict(theta).items()}
        f, h = self.f[idx], self.h[idx]
        with np.errstate(all="ignore"):
            hm, dlog, z_base = self.model.response_and_base_log_derivatives(
                f, values, with_base=True)                                   # (k, n)
            dz = np.where(self.space.log[:nb], theta[:, :nb],
                          self.space.upper[:nb] - self.space.lower[:nb]).T[:, :, None]
            d_db = DB_PER_NEPER * dlog.real * dz                             # (5, k, n)
            if self.cost == "paper":
                db = d_db
            else:
                db = np.concatenate([d_db * self.w_db[idx],
                                     np.degrees(dlog.imag) * dz * self.w_deg[idx]], axis=-1)
            size = np.abs(hm / h)         # the residuals are finite where ln|Hm/Hd| is
            finite = np.isfinite(size) & (size > 0)
        ok = finite if self.cost == "paper" else np.concatenate([finite, finite], axis=-1)
        jb = np.where(ok & np.isfinite(db), db, 0.0).transpose(1, 2, 0)    # (k, m, 5)
        if p == nb:
            return jb
        return np.concatenate([jb, self.jacobian_batch(z, idx, first=nb, z_base=z_base)],
                              axis=-1)

    def solve_many(self, z0: np.ndarray, idx: np.ndarray | slice = slice(None), *,
                   mask: np.ndarray | None = None, **opts) -> multilsq.ManyResult:
        """Local fits from the starts z0 (k, p), each as
        ``least_squares(self.residuals, z0[i], jac=self.jacobian_analytic, args=(idx,),
        bounds=(zlo, zhi), method="trf", x_scale=1.0, **opts)``, solved together
        (:func:`solve_together`). ``mask`` (k, m): residuals of fit i multiplied by
        mask[i] (0 leaves a point out)."""
        return solve_together([self], [z0], idx, mask=mask, **opts)

    def unweighted(self) -> _Problem:
        """The same problem with unit weights (1 dB, UNIT_SE_DEG): a smoother landscape
        for the global search."""
        return replace(self, w_db=np.ones_like(self.w_db),
                       w_deg=np.full_like(self.w_deg, 1.0 / UNIT_SE_DEG))

    def _weighted(self, hm: np.ndarray, idx) -> np.ndarray:
        with np.errstate(all="ignore"):
            db, deg = log_errors(hm, self.h[idx])
            if self.cost == "paper":
                r = db
            else:
                r = np.concatenate([db * self.w_db[idx], deg * self.w_deg[idx]], axis=-1)
        return np.where(np.isfinite(r), r, 1e6)


def solve_together(problems: Sequence[_Problem], z0: Sequence[np.ndarray],
                   idx: np.ndarray | slice = slice(None), *, mask: np.ndarray | None = None,
                   **opts) -> multilsq.ManyResult:
    """Local fits of several problems of one model (the same parameters and bins, e.g.
    one problem under two weightings) from their starts ``z0[j]`` (k_j, p), on the bins
    ``idx``, all solved together by :func:`armfit.multilsq.solve_many` (``opts``: its
    ``max_nfev``, ``ftol``, ``xtol``, ``gtol``): each as
    ``least_squares(problems[j].residuals, start, jac=problems[j].jacobian_analytic,
    args=(idx,), bounds=(zlo, zhi), method="trf", x_scale=1.0, **opts)``. The results'
    rows are the starts in order (problem 0's first). ``mask`` (Σk_j, m): residuals of
    fit i multiplied by mask[i] (0 leaves a point out). Fewer than :data:`_MIN_TOGETHER`
    fits are made one by one by :func:`armfit._trf.bounded_least_squares` (scipy's path; the
    same to rounding)."""
    owner = np.repeat(np.arange(len(problems)), [len(z) for z in z0])

    def each(x, rows, method):
        parts = [(j, owner[rows] == j) for j in range(len(problems))]
        vals = [(sel, method(problems[j], x[sel], idx)) for j, sel in parts if sel.any()]
        if len(vals) == 1:
            out = vals[0][1]
        else:
            out = np.empty((len(rows), *vals[0][1].shape[1:]))
            for sel, v in vals:
                out[sel] = v
        if mask is None:
            return out
        return out * mask[rows].reshape(len(rows), -1, *(1,) * (out.ndim - 2))

    def fun(x, rows):
        return each(x, rows, _Problem.residuals_batch)

    def jac(x, rows):
        return each(x, rows, _Problem.jacobian_analytic_batch)

    space = problems[0].space
    if owner.size < _MIN_TOGETHER:
        return _one_by_one(fun, jac, np.vstack(z0), space, opts)
    return multilsq.solve_many(fun, jac, np.vstack(z0), space.zlo, space.zhi, **opts)


#: Fewer local fits than this are solved one by one (:func:`armfit._trf.bounded_least_squares`,
#: scipy's solver): vectorised over one or two fits, an iteration costs more than
#: scipy's (measured 1.5× for one fit).
_MIN_TOGETHER = 3


def _one_by_one(fun, jac, z0: np.ndarray, space: ParamSpace, opts) -> multilsq.ManyResult:
    """:func:`solve_together`'s fits (its ``fun`` and ``jac`` of rows) made one after the
    other by :func:`armfit._trf.bounded_least_squares` (scipy's solver)."""
    res = []
    for i, z in enumerate(z0):
        row = np.array([i])
        res.append(_trf.bounded_least_squares(lambda x, r=row: fun(x[None], r)[0], z,
                                              jac=lambda x, r=row: jac(x[None], r)[0],
                                              bounds=(space.zlo, space.zhi), **opts))
    return multilsq.ManyResult(*(np.array([getattr(r, k) for r in res])
                                 for k in ("x", "cost", "fun", "status", "nfev")))


def _weights(se_db, se_deg, order: np.ndarray, n: int
             ) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray, np.ndarray]:
    """The noise model's standard errors (dB, deg) of a response whose bins are put in
    frequency order by ``order`` (None without measured ones), and the standard errors
    that weight the cost: the noise model's, or 1 dB and :data:`UNIT_SE_DEG` where there
    is none (no standard errors given, or none valid)."""
    if se_db is None or se_deg is None:
        return None, None, np.ones(n), np.full(n, UNIT_SE_DEG)
    sdb, sdeg = noise.standard_errors(np.asarray(se_db, float).ravel()[order],
                                      np.asarray(se_deg, float).ravel()[order])
    return (sdb, sdeg, np.where(np.isfinite(sdb), sdb, 1.0),
            np.where(np.isfinite(sdeg), sdeg, UNIT_SE_DEG))


# ---------------------------------------------------------------------------
# Starts
# ---------------------------------------------------------------------------

def analytic_guess(f_hz: np.ndarray, h: np.ndarray, mp: float) -> list[dict[str, float]]:
    """Candidate arm parameters from a linear (Levy) fit of the arm impedance.

    Z_ARM = 1/H − Mp s² (eq. 4) = N(s)/D(s) with, normalised by Ma (eq. 3),
    D = s² + (b1+b2)/Ma s + (k1+k2)/Ma and N = b1 (s + k1/b1)(s² + b2/Ma s + k2/Ma).
    N − Z·D = 0 is linear in the six coefficients; each real root of N taken as −k1/b1
    gives one candidate (Ma from D's s-coefficient). Rows are weighted by 1/|Z s²| so every
    frequency counts alike. Returns the physically valid candidates (possibly none);
    exact for the noise-free response of eq. 4.
    """
    return levy_candidates(*levy_rows(f_hz, h, mp))


def levy_rows(f_hz: np.ndarray, h: np.ndarray, mp: float) -> tuple[np.ndarray, np.ndarray]:
    """The weighted rows of :func:`analytic_guess`'s linear system, one per frequency:
    (A (..., n, 6), b (..., n)), complex, for responses ``h`` (..., n) in m/N at ``f_hz``
    (n,). Each row depends only on its own frequency, so the rows of a band are those of
    the whole grid at the band's frequencies, and several responses are made at once."""
    s = laplace(f_hz)
    z = 1.0 / h - mp * s * s
    shape = np.shape(z)
    a = np.stack([np.broadcast_to(s**3, shape), np.broadcast_to(s**2, shape),
                  np.broadcast_to(s, shape), np.broadcast_to(np.ones_like(s), shape),
                  -z * s, -z], axis=-1)
    b = z * s * s
    w = 1.0 / np.abs(b)
    return a * w[..., None], b * w


def levy_candidates(a_w: np.ndarray, b_w: np.ndarray) -> list[dict[str, float]]:
    """:func:`analytic_guess`'s candidates from its weighted rows (:func:`levy_rows`,
    (n, 6) and (n,)): the least-squares solution of the real and imaginary parts."""
    coef = _levy_solution(a_w, b_w)
    if coef is None or not coef[0] > 0:
        return []
    return _levy_from_roots(coef, np.roots(list(coef[:4])))


def levy_candidates_many(systems: Sequence[tuple[np.ndarray, np.ndarray]]
                         ) -> list[list[dict[str, float]]]:
    """:func:`levy_candidates` of each of several systems (``(a_w, b_w)`` pairs), the
    same numbers: each system's least-squares solution on its own, then the roots of
    all their numerators N (cubics) at once, as :func:`numpy.roots` finds them (the
    eigenvalues of the companion matrix; one :func:`numpy.linalg.eigvals` of the stack
    instead of one call a cubic, each matrix solved alone by LAPACK). A cubic whose
    constant term is zero or whose coefficients are not all finite is left to
    :func:`numpy.roots` itself. The Levy starts of the diagnosis
    (:func:`armfit.diagnosis.starts.levy_starts`) take three band cuts of every trial:
    the per-cubic calls cost as much as the least-squares solutions."""
    coefs = [_levy_solution(a_w, b_w) for a_w, b_w in systems]
    roots: dict[int, np.ndarray] = {}
    many = [i for i, c in enumerate(coefs)
            if c is not None and c[0] > 0 and c[3] != 0 and np.all(np.isfinite(c[:4]))]
    if many:
        p = np.array([coefs[i][:4] for i in many])
        companion = np.zeros((len(many), 3, 3))
        companion[:, 1, 0] = companion[:, 2, 1] = 1.0
        companion[:, 0, :] = -p[:, 1:] / p[:, :1]
        roots = dict(zip(many, np.linalg.eigvals(companion), strict=True))
    out = []
    for i, c in enumerate(coefs):
        if c is None or not c[0] > 0:
            out.append([])
            continue
        r = roots.get(i)
        out.append(_levy_from_roots(c, np.roots(list(c[:4])) if r is None else r))
    return out


def _levy_solution(a_w: np.ndarray, b_w: np.ndarray) -> np.ndarray | None:
    """The coefficients (n3, n2, n1, n0, d1, d0) of :func:`levy_candidates`' system, or
    None when its rows are not all finite."""
    a_ri = np.concatenate([a_w.real, a_w.imag])
    b_ri = np.concatenate([b_w.real, b_w.imag])
    if not (np.all(np.isfinite(a_ri)) and np.all(np.isfinite(b_ri))):
        return None
    coef, *_ = np.linalg.lstsq(a_ri, b_ri, rcond=None)
    return coef


def _levy_from_roots(coef: np.ndarray, roots: np.ndarray) -> list[dict[str, float]]:
    """The physical candidates of :func:`levy_candidates` from its coefficients and the
    roots of its numerator (n3 > 0): each real negative root taken as −k1/b1."""
    n3, n2, n1, n0, d1, d0 = coef
    out = []
    for i, r in enumerate(roots):
        if abs(r.imag) > 1e-6 * max(abs(r), 1e-12) or not r.real < 0:
            continue
        others = np.delete(roots, i)
        p1 = float(-(others.sum()).real)   # b2/Ma
        p0 = float((others.prod()).real)   # k2/Ma
        b1 = float(n3)
        k1 = float(-r.real * b1)
        if not (d1 - p1) > 0:
            continue
        ma = b1 / (d1 - p1)
        cand = {"Ma": ma, "k1": k1, "k2": p0 * ma, "b1": b1, "b2": p1 * ma}
        if all(v > 0 and np.isfinite(v) for v in cand.values()):
            out.append(cand)
    return out


def _candidates(prob: _Problem, x0: Mapping[str, float] | None, n_sobol: int) -> np.ndarray:
    """The starts of :func:`_search`, in search coordinates: ``x0`` (when given), the
    typical values, and with a global search (``n_sobol`` > 0) the analytic guesses and
    ``n_sobol`` Sobol points. A local fit starts from the first only: its analytic
    guesses (a Levy fit, about 0.5 ms) are not made."""
    sp = prob.space
    typical = np.array([p.typical for p in prob.model.params])
    starts = [sp.to_z(typical)]
    base_idx = [sp.names.index(n) for n in PARAM_NAMES]
    for cand in analytic_guess(prob.f, prob.h, prob.model.mp) if n_sobol else ():
        theta = typical.copy()
        theta[base_idx] = [cand[n] for n in PARAM_NAMES]
        starts.append(sp.to_z(theta))
    if x0 is not None:
        theta = typical.copy()
        held = prob.model.held_values
        for n, v in x0.items():
            if n in held:       # a start may come from a fit that held the same values
                continue
            if n not in sp.names:
                raise UsageError(f"starting value for unknown parameter {n!r}; the model has "
                                 f"{', '.join(sp.names)}")
            theta[sp.names.index(n)] = v
        starts.insert(0, sp.to_z(theta))
    if n_sobol:
        u = sobol_points(n_sobol, len(sp.names))
        if u is None:      # more dimensions than armfit's table: scipy's (slow to import)
            from scipy.stats import qmc
            m = int(np.ceil(np.log2(n_sobol)))
            u = qmc.Sobol(d=len(sp.names), scramble=False).random_base2(m)[:n_sobol]
        starts.extend(sp.zlo + u * (sp.zhi - sp.zlo))
    return sp.clip_z(np.array(starts))


@lru_cache(maxsize=1)
def _paper_rows() -> np.ndarray:
    """The arm parameters (Ma, k1, k2, b1, b2; SI) of every row of the paper's Tables I
    and II, all axes: from the compliant X and Y arm (k1 ≈ 80 N/m) to the stiff Z arm
    (k1 ≈ 2000–5000 N/m)."""
    from armfit.data import paper_values  # tables read once, only by the global search

    cols = ["Ma_kg", "k1_N_per_m", "k2_N_per_m", "b1_Ns_per_m", "b2_Ns_per_m"]
    return np.vstack([paper_values(t, cols) for t in ("grip", "nominal")])


def _effect_points(model: ClosedLoopModel, names: Sequence[str]) -> list[dict[str, float]]:
    """Values of the free effect parameters to start from: every combination of each
    effect's null point, its own starting points and its typical values (at most
    :data:`_MAX_EFFECT_POINTS` combinations; [{}] without free effect parameters)."""
    combos: list[dict[str, float]] = [{}]
    for e in model.effects:
        pts = e.start_points(model.mp) + [{p.name: p.typical for p in e.params}]
        opts = []
        for pt in pts:
            d = {f"{e.name}.{k}": float(v) for k, v in pt.items() if f"{e.name}.{k}" in names}
            if d and d not in opts:
                opts.append(d)
        if opts:
            combos = [{**c, **o} for c in combos for o in opts][:_MAX_EFFECT_POINTS]
    return combos


def _anchors(prob: _Problem) -> np.ndarray:
    """Structured starts of the global search, beside the Sobol set: the arm parameters
    of every row of the paper's Tables I and II (:func:`_paper_rows`) and of the analytic
    guess on the data with the effects removed (:meth:`ClosedLoopModel.remove_effects`),
    each with the effects at every point of :func:`_effect_points`. A Sobol set over the
    whole box is thin in a corner such as the stiff Z arm (k1 in the thousands, Ma in
    kg) and, once an effect can mimic part of the arm (a lag lowering the response like
    a mass), a start far from that corner may end in a distant local minimum."""
    sp, model = prob.space, prob.model
    typical = np.array([p.typical for p in model.params])
    base_idx = [sp.names.index(n) for n in PARAM_NAMES]
    rows = []
    for eff in _effect_points(model, sp.names):
        arm = [r for r in _paper_rows()]
        with np.errstate(all="ignore"):
            hb = model.remove_effects(prob.f, prob.h, eff) if eff else None
        # (without effects the analytic guess is among the fixed starts already)
        if hb is not None and np.all(np.isfinite(hb)):
            arm += [np.array([c[n] for n in PARAM_NAMES])
                    for c in analytic_guess(prob.f, hb, model.mp)]
        for a in arm:
            theta = typical.copy()
            theta[base_idx] = a
            for n, v in eff.items():
                theta[sp.names.index(n)] = v
            rows.append(sp.to_z(theta))
    return sp.clip_z(np.array(rows))


def _global_starts(prob: _Problem, starts: np.ndarray, n_fixed: int,
                   anchors: np.ndarray | None = None
                   ) -> tuple[list[np.ndarray], int, np.ndarray]:
    """The global stage: screen the Sobol starts (``starts[n_fixed:]``) and, apart, the
    structured ``anchors`` (:func:`_anchors`) on a log-spaced subset of bins, with the
    problem's weights and with unit weights; refine the fixed starts and the best
    screened ones of each set under both weightings (all these local fits solved
    together, :func:`solve_together`); return the two best distinct end
    points by the full weighted cost (the polish starts from each), the evaluations used
    and every end point."""
    sub = _subset(prob.f, _N_SUBSET)
    problems = [prob] if prob.cost == "paper" else [prob.unweighted(), prob]
    if anchors is None or not len(anchors):
        anchors = starts[:0]
    pool = np.vstack([starts, anchors])
    n_sobol = len(starts) - n_fixed
    z0 = []
    for p in problems:
        ss = np.sum(p.residuals_batch(pool[n_fixed:], sub) ** 2, axis=1)
        picks = list(range(n_fixed)) + [n_fixed + int(i)
                                         for i in np.argsort(ss[:n_sobol])[:_N_REFINE]]
        picks += [n_fixed + n_sobol + int(i)
                  for i in np.argsort(ss[n_sobol:])[:_N_ANCHORS]]
        z0.append(pool[picks])
    r = solve_together(problems, z0, sub, max_nfev=30 * starts.shape[1], ftol=1e-6,
                       xtol=1e-6)
    nfev = int(r.nfev.sum())
    ends_arr = r.x
    full = np.sum(prob.residuals_batch(ends_arr) ** 2, axis=1)
    order = np.argsort(full)
    chosen = [ends_arr[order[0]]]
    for i in order[1:]:
        if np.max(np.abs(ends_arr[i] - chosen[0])) > 1e-3:
            chosen.append(ends_arr[i])
            break
    return chosen, nfev, ends_arr


def _subset(f: np.ndarray, n: int) -> np.ndarray:
    """Indices of about n bins log-spaced across f (all bins if fewer)."""
    if f.size <= n:
        return np.arange(f.size)
    targets = np.geomspace(f[0], f[-1], n)
    return unique(np.searchsorted(f, targets).clip(0, f.size - 1))


# ---------------------------------------------------------------------------
# The fit
# ---------------------------------------------------------------------------

def fit_response(model: ClosedLoopModel, f_hz, H, *, se_db=None, se_deg=None,
                 cost: str = "complex", band: tuple[float, float] | None = None,
                 x0: Mapping[str, float] | None = None, global_search: bool = True,
                 max_nfev: int | None = None,
                 strict: bool = True, intervals: bool = True,
                 jackknife_bands: int = JACKKNIFE_BANDS,
                 second_opinion: bool = True) -> FitResult:
    """Fit ``model`` (H_CL of eq. 4 with its effects) to a measured response.

    f_hz: frequencies (Hz); H: complex response X/F (m/N); se_db, se_deg: standard errors
    of 20 log10|H| (dB) and of the phase (deg), used by the "complex" cost; band: (lo, hi)
    Hz, bins outside are ignored (default: all); x0: warm start {name: value} (missing names
    take the typical value); global_search: False refines from x0 (or the typical values)
    only; max_nfev: evaluation budget of the final polish (default 200 per parameter).
    The standard errors are the noise model's (:func:`armfit.noise.standard_errors`, on
    the whole grid given, then restricted to the band); ``rms_norm`` is its "× noise".

    intervals: False skips the 95 % intervals (NaN), e.g. for bootstrap replicates;
    jackknife_bands: bands of the delete-a-band jackknife that widens them
    (:func:`band_jackknife`; 0: the noise interval alone).

    second_opinion: a local fit (``global_search`` False) that ends more than
    :data:`FAR_FROM_NOISE` times the noise also refines the cheapest structured starts and
    is not converged when one of them reaches a cost below :data:`MARKEDLY_LOWER` of its
    own (the message says so); False skips that (bootstrap replicates, whose start is a
    checked global fit).

    Cost and intervals: see the module docstring (eq. 5 for ``cost="paper"``).
    Raises ConvergenceError (exit 3) if the optimiser stops before converging and
    ``strict`` (the default); UsageError for a bad cost, band or starting value.
    """
    if cost not in COSTS:
        raise UsageError(f"cost must be one of {', '.join(COSTS)}, got {cost!r}")
    prob, sel, (noise_db, noise_deg) = _problem(model, f_hz, H, se_db, se_deg, band, cost)
    space, m = prob.space, prob.f.size
    budget = 200 * len(space.names) if max_nfev is None else int(max_nfev)
    res, nfev, others = _search(prob, x0, global_search, budget)
    converged = bool(res.status > 0 and np.all(np.isfinite(res.x)))
    # Honest convergence: a fit far above the noise while another start reaches a
    # markedly lower cost is a local minimum, not converged. The global search refined
    # the structured starts already (and keeps its best end); a local fit from x0 gets
    # their second opinion here.
    not_best = ""
    measured = cost == "complex" and se_db is not None and se_deg is not None
    if converged and measured and _rms(res.fun) > FAR_FROM_NOISE:
        not_best, n_other = _better_start(prob, res, others,
                                          not global_search and second_opinion)
        nfev += n_other
        converged = not not_best
    band_used = (float(prob.f[0]), float(prob.f[-1]))
    if not converged and strict:
        why = not_best or f"{res.message}"
        raise ConvergenceError(f"fit did not converge in band {band_used[0]:g}-"
                               f"{band_used[1]:g} Hz after {res.nfev} evaluations "
                               f"({why}); no parameters reported")
    theta = space.to_theta(res.x)
    params = {n: float(v) for n, v in zip(space.names, theta, strict=True)}
    if intervals:
        ci_lo, ci_hi = _intervals(prob, res, measured, jackknife_bands)
    else:
        ci_lo = ci_hi = {n: float("nan") for n in space.names}

    hm = model.response(prob.f, params)
    with np.errstate(all="ignore"):
        db, deg = log_errors(hm, prob.h)
    rms_db = float(np.sqrt(np.mean(db**2)))
    rms_deg = float(np.sqrt(np.mean(deg**2)))
    rms_norm = float("nan") if noise_db is None else \
        noise.rms_norm(db, deg, noise_db[sel], noise_deg[sel])
    stuck = at_bound(model.params, params)
    msg = res.message + (f"; at physical bound: {', '.join(stuck)}" if stuck else "")
    if not_best:
        msg = f"not converged: {not_best}; optimiser: {msg}"
    return FitResult(model=model, params=params, ci_lo=ci_lo, ci_hi=ci_hi, rms_db=rms_db,
                     rms_deg=rms_deg, rms_norm=rms_norm, band=band_used, n_points=m,
                     cost=cost, converged=converged, message=msg, nfev=nfev,
                     objective=float(2 * res.cost), at_bound=tuple(stuck))


def _problem(model: ClosedLoopModel, f_hz, H, se_db, se_deg, band, cost: str):
    """The least-squares problem of :func:`fit_response` on the usable bins of the band:
    (problem, the selected bins of the frequency-sorted grid, the noise model's standard
    errors (dB, deg) on that grid or (None, None) without measured ones)."""
    f = np.asarray(f_hz, float).ravel()
    h = np.asarray(H, complex).ravel()
    if f.shape != h.shape:
        raise UsageError(f"{f.size} frequencies but {h.size} response values")
    order = np.argsort(f)
    f, h = f[order], h[order]
    lo, hi = (float(f.min()), float(f.max())) if band is None else map(float, band)
    if not (0 < lo < hi):
        raise UsageError(f"fit band must satisfy 0 < lo < hi Hz, got {lo}:{hi}")
    sel = (f >= lo) & (f <= hi) & np.isfinite(h) & (h != 0)
    space = ParamSpace.of(model)
    n_par = len(space.names)
    if sel.sum() <= n_par:
        raise UsageError(f"fit band {lo:g}-{hi:g} Hz holds {int(sel.sum())} usable bins; "
                         f"{n_par} parameters need at least {n_par + 1}")
    noise_db, noise_deg, wdb, wdeg = _weights(se_db, se_deg, order, f.size)
    prob = _Problem(model, space, f[sel], h[sel], 1.0 / wdb[sel], 1.0 / wdeg[sel], cost)
    return prob, sel, (noise_db, noise_deg)


def _search(prob: _Problem, x0: Mapping[str, float] | None, global_search: bool,
            budget: int):
    """The starts of :func:`fit_response` (global or from ``x0``) polished with at most
    ``budget`` evaluations each: (the best result — converged first, then lowest cost —,
    evaluations used, every point the search reached)."""
    space = prob.space
    starts = _candidates(prob, x0, _N_SOBOL if global_search else 0)
    bounds = (space.zlo, space.zhi)
    nfev = 0
    ends = np.empty((0, len(space.names)))
    if global_search:
        z_starts, nfev, ends = _global_starts(prob, starts, n_fixed=len(starts) - _N_SOBOL,
                                              anchors=_anchors(prob))
    else:
        z_starts = starts[:1]

    def polish(z0):
        return _trf.bounded_least_squares(prob.residuals, z0, jac=prob.jacobian_analytic,
                                          bounds=bounds, max_nfev=budget, ftol=_TOL,
                                          xtol=_TOL, gtol=_TOL)

    res = None
    others = [ends]          # every point the search reached (the polish's ends too)
    for z0 in z_starts:
        r = polish(z0)
        nfev += r.nfev
        others.append(r.x[None])
        if res is None or (r.status > 0, -r.cost) > (res.status > 0, -res.cost):
            res = r
    return res, nfev, others


def _better_start(prob: _Problem, res, others: list, ask: bool) -> tuple[str, int]:
    """Whether a point the search reached (``others``; with ``ask``, also the second
    opinion of the structured starts) has a cost below :data:`MARKEDLY_LOWER` of
    ``res``'s: (the message naming it, or "" when none has; evaluations used)."""
    n_other = 0
    if ask:
        other, n_other = _second_opinion(prob, res.x, _anchors(prob))
        if other is not None:
            others.append(other[None])
    pts = np.vstack(others)
    ss = np.sum(prob.residuals_batch(pts) ** 2, axis=1)
    i = int(np.argmin(ss))
    if ss[i] < MARKEDLY_LOWER * 2 * res.cost:
        return (f"a local minimum: this fit ends at {_rms(res.fun):.3g}× the "
                f"noise, another start reaches "
                f"{np.sqrt(ss[i] / res.fun.size):.3g}× "
                f"({_describe(prob.space, pts[i])})"), n_other
    return "", n_other


def _intervals(prob: _Problem, res, measured: bool, jackknife_bands: int):
    """95 % intervals of :func:`fit_response` (module docstring): residuals in units of
    measured noise widen by the jackknife only when the error exceeds the noise; without
    a noise reference, always."""
    n_par = len(prob.space.names)
    chi2_red = float(np.sum(res.fun ** 2)) / max(res.fun.size - n_par, 1)
    jk = (band_jackknife(prob, res.x, jackknife_bands)
          if jackknife_bands and (chi2_red > 1 or not measured) else None)
    return _jacobian_ci(prob.space, res.x, res.jac, res.fun.reshape(-1, prob.f.size),
                        absolute=measured, jackknife=jk)


#: A fit whose RMS normalised error exceeds this ("several times the noise") gets a
#: second opinion from the structured starts (:func:`_second_opinion`).
FAR_FROM_NOISE = 2.0
#: ... and is not the best fit when another start reaches a cost (Σ r²) below this
#: fraction of its own.
MARKEDLY_LOWER = 0.5
_N_CHECK = 2            # structured starts refined for the second opinion


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(r) ** 2)))


def _describe(space: ParamSpace, z: np.ndarray) -> str:
    theta = space.to_theta(z)
    return ", ".join(f"{n}={v:.4g}" for n, v in zip(space.names, theta, strict=True))


def _second_opinion(prob: _Problem, z: np.ndarray, anchors: np.ndarray):
    """The best local fit (on every bin, the problem's weights) from the :data:`_N_CHECK`
    structured starts of lowest cost that differ from ``z``, solved together
    (:meth:`_Problem.solve_many`): (its end point, evaluations used); (None, 0) without
    any start."""
    cand = anchors[np.max(np.abs(anchors - z), axis=1) > 1e-3]
    if not len(cand):
        return None, 0
    ss = np.sum(prob.residuals_batch(cand) ** 2, axis=1)
    r = prob.solve_many(cand[np.argsort(ss)[:_N_CHECK]], max_nfev=50 * cand.shape[1],
                        ftol=1e-8, xtol=1e-8)
    return r.x[int(np.argmin(r.cost))], int(r.nfev.sum())


def residual_correlation(blocks: np.ndarray) -> float:
    """Lag-1 autocorrelation ρ of residuals along frequency, pooled over the rows of
    ``blocks`` (magnitude, phase): Σ r_i r_(i+1) / Σ r_i², clipped to [0, 0.95]."""
    num = float(np.sum(blocks[:, 1:] * blocks[:, :-1]))
    den = float(np.sum(blocks * blocks))
    return float(np.clip(num / den, 0.0, 0.95)) if den > 0 else 0.0


def band_jackknife(prob: _Problem, z: np.ndarray, groups: int | None = None
                   ) -> tuple[np.ndarray, int]:
    """Delete-a-band jackknife of the fit in search coordinates: the band's bins (sorted
    by frequency, log-spaced) are cut into ``groups`` contiguous bands
    (:data:`JACKKNIFE_BANDS`), the fit is repeated without each band (a local refit from
    ``z``; the G refits solved together, :meth:`_Problem.solve_many`, a band's points
    left out by a zero weight), and the spread of the G answers gives the standard error
    sd_j = √((G − 1)/G · Σ (z_g − z̄)²) (Quenouille–Tukey; deleting contiguous blocks
    keeps it valid for residuals correlated along frequency, Künsch 1989). Returns
    (sd_j per parameter, G)."""
    g = JACKKNIFE_BANDS if groups is None else int(groups)
    m = prob.f.size
    g = min(g, m // (z.size + 1))
    if g < 3:
        return np.full(z.size, np.nan), g
    z0 = prob.space.clip_z(z)
    keep = np.ones((g, m))
    for i, part in enumerate(np.array_split(np.arange(m), g)):
        keep[i, part] = 0.0
    mask = keep if prob.cost == "paper" else np.concatenate([keep, keep], axis=1)
    ends = prob.solve_many(np.tile(z0, (g, 1)), mask=mask, max_nfev=50 * z.size,
                           ftol=1e-10, xtol=1e-10, gtol=1e-10).x
    return np.sqrt((g - 1) / g * np.sum((ends - ends.mean(axis=0)) ** 2, axis=0)), g


def _jacobian_ci(space: ParamSpace, z: np.ndarray, jac: np.ndarray, blocks: np.ndarray,
                 level: float = 0.95, *, absolute: bool = False,
                 jackknife: tuple[np.ndarray, int] | None = None
                 ) -> tuple[dict[str, float], dict[str, float]]:
    """95 % intervals from J (residuals × search coordinates): see the module docstring.

    ``blocks``: the residuals at the optimum, one row per block (magnitude, phase).
    Noise part: cov = c · (1 + ρ)/(1 − ρ) · (JᵀJ)⁻¹, ρ the residuals' lag-1
    autocorrelation along frequency (:func:`residual_correlation`; neighbouring bins are
    not independent, and this is the variance factor of an AR(1) sequence). With
    ``absolute`` (residuals divided by measured standard errors) c = max(1, χ²_red),
    χ²_red = Σ r²/(m − p): widened when the error exceeds the noise, never narrowed below
    what the measured noise implies; otherwise (unit weights) c = χ²_red, the residual
    variance. Half-width t₀.₉₇₅(m − p)·√diag(cov), or, when wider, the band jackknife's
    t₀.₉₇₅(G − 1)·sd_j (``jackknife`` = (sd_j, G) of :func:`band_jackknife`), which
    follows the misfit the noise does not explain. Directions the data do not determine
    (singular values below 1e-10 of the largest) give the parameters involved NaN
    intervals.
    """
    p = z.size
    dof = max(blocks.size - p, 1)
    rho = residual_correlation(blocks)
    chi2 = float(np.sum(blocks * blocks)) / dof
    c = max(1.0, chi2) if absolute else chi2
    s2 = c * (1 + rho) / (1 - rho)
    _, sv, vt = np.linalg.svd(np.asarray(jac, float), full_matrices=False)
    ok = sv > 1e-10 * sv.max() if sv.size and sv.max() > 0 else np.zeros(p, bool)
    inv = np.where(ok, 1.0 / np.where(ok, sv, 1.0) ** 2, 0.0)
    var = s2 * np.einsum("ki,k,ki->i", vt, inv, vt)
    undetermined = np.any(np.abs(vt[~ok]) > 1e-8, axis=0)
    half = t_quantile(dof, 0.5 + level / 2) * np.sqrt(var)
    if jackknife is not None and jackknife[1] >= 3:
        sd_j, g = jackknife
        half_j = t_quantile(g - 1, 0.5 + level / 2) * sd_j
        half = np.where(np.isfinite(half_j), np.maximum(half, half_j), half)
    lo = space.to_theta(np.clip(z - half, space.zlo, space.zhi))
    hi = space.to_theta(np.clip(z + half, space.zlo, space.zhi))
    lo = np.where(undetermined, np.nan, lo)
    hi = np.where(undetermined, np.nan, hi)
    return ({n: float(v) for n, v in zip(space.names, lo, strict=True)},
            {n: float(v) for n, v in zip(space.names, hi, strict=True)})


# ---------------------------------------------------------------------------
# Bootstrap over subjects
# ---------------------------------------------------------------------------

Aggregator = Callable[[np.ndarray], np.ndarray]


def bootstrap_fit(base: FitResult, f_hz, H_trials, subjects: Sequence[str], *,
                  aggregate: Aggregator, n_boot: int, seed: int | None = 0,
                  se_db=None, se_deg=None, level: float = 0.95,
                  max_failed: float = 0.1, widen: bool = True) -> FitResult:
    """Percentile intervals by resampling subjects with replacement.

    H_trials: (n_trials, n_freq) complex trial responses (m/N) on the grid f_hz; subjects:
    the subject of each trial. Each replicate draws as many subjects as there are, with
    replacement, pools all their trials, aggregates them with ``aggregate`` (the same rule
    as the fitted aggregate, e.g. ``lambda H: armfit.spectra.aggregate(H, "mean")``),
    and refits from ``base``'s parameters with ``base``'s cost, band and the given standard
    errors (held fixed). Returns ``base`` with ``ci_lo``/``ci_hi`` replaced by the
    (1−level)/2 and (1+level)/2 percentiles and ``ci_method`` "bootstrap-<n_boot>";
    with ``widen`` (the default) each interval is the union of the percentile interval
    and ``base``'s own (noise and band-jackknife) interval, since a subject bootstrap
    cannot see a misfit all subjects share.
    Replicates that do not converge are dropped; more than ``max_failed`` of them raises
    ConvergenceError. Deterministic for a given ``seed``.
    """
    if n_boot < 2:
        raise UsageError(f"{{opt}} needs at least 2 replicates, got {n_boot}",
                         option="n_boot=")
    H_trials = np.asarray(H_trials, complex)
    subjects = np.asarray(subjects)
    if H_trials.ndim != 2 or H_trials.shape[0] != subjects.size:
        raise UsageError("bootstrap needs one subject label per trial response")
    labels = unique(subjects)
    members = [np.flatnonzero(subjects == s) for s in labels]
    rng = np.random.default_rng(seed)
    names = list(base.params)
    draws = []
    failed = 0
    for _ in range(n_boot):
        pick = rng.integers(0, labels.size, labels.size)
        rows = np.concatenate([members[i] for i in pick])
        hb = aggregate(H_trials[rows])
        try:
            fit = fit_response(base.model, f_hz, hb, se_db=se_db, se_deg=se_deg,
                               cost=base.cost, band=base.band, x0=base.params,
                               global_search=False, intervals=False,
                               second_opinion=False)
        except ConvergenceError:
            failed += 1
            continue
        draws.append([fit.params[n] for n in names])
    if failed > max_failed * n_boot:
        raise ConvergenceError(f"bootstrap: {failed} of {n_boot} refits did not converge")
    arr = np.array(draws)
    q_lo, q_hi = percentile(arr, [50 * (1 - level), 50 * (1 + level)], axis=0)
    if widen:
        # never narrower than base's interval (noise and band jackknife): resampling
        # subjects sees their spread, not the misfit every subject shares
        q_lo = np.fmin(q_lo, [base.ci_lo[n] for n in names])
        q_hi = np.fmax(q_hi, [base.ci_hi[n] for n in names])
    return replace(base, ci_lo=dict(zip(names, map(float, q_lo), strict=True)),
                   ci_hi=dict(zip(names, map(float, q_hi), strict=True)),
                   ci_method=f"bootstrap-{n_boot}")


# ---------------------------------------------------------------------------
# A study's fits from a spectra table (Tables I and II)
# ---------------------------------------------------------------------------

#: What each set of fits uses: aggregate level of the spectra table and its aggregation
#: rule ("grip": Table I, mean per axis × grip; "nominal": Table II, median per axis).
STUDY_FITS: dict[str, str] = {"grip": "mean", "nominal": "median"}


@dataclass(frozen=True)
class StudyFit:
    """The fits of one set ("grip" or "nominal"): one FitResult per (axis, grip_N)
    (grip_N None for nominal fits), in axis then grip order."""

    which: str
    keys: tuple[tuple[str, float | None], ...]
    fits: tuple[FitResult, ...]

    def table(self):
        """The params table (columns of :func:`armfit.io.schema.params_columns`;
        docs/formats.md, "Params CSV")."""
        return self.row_table().to_frame()

    def row_table(self) -> RowTable:
        """:meth:`table` before it becomes a DataFrame."""
        rows = []
        for (axis, grip), fit in zip(self.keys, self.fits, strict=True):
            row = {"axis": axis, **fit.row()}
            if self.which == "grip":
                row["grip_N"] = grip
            rows.append(row)
        from armfit.io.artifacts import params_rows
        names = union_param_names([f.model for f in self.fits])
        return params_rows(rows, names, grip=self.which == "grip")


def _check_method(rows, method: str | None, source: str | None) -> str | None:
    """The estimator ``method`` to select among ``rows`` (None: the only one they hold).

    Raises UsageError when ``rows`` hold several estimates of the same responses
    (:meth:`armfit.spectra.Spectra.repeated`) and none is chosen, or when the chosen one is
    not among them."""
    methods = sorted(rows.values_of("method"))
    if method is None and len(methods) > 1 and rows.repeated():
        raise UsageError(f"{source or 'spectra'} holds several estimators "
                         f"({', '.join(methods)}); choose one with {{opt}}", option="method=")
    if method is not None and method not in methods:
        raise UsageError(f"{{opt}}{method}: not in {source or 'spectra'} (it has "
                         f"{', '.join(methods)})", option="method=")
    return method


def fit_study(spectra, *, which: str, cost: str = "complex",
              bands: Mapping[str, tuple[float, float]] | None = None,
              effects: Sequence = (), bootstrap: int = 0, seed: int | None = 0,
              method: str | None = None, max_nfev: int | None = None,
              source: str | None = None,
              on_fit: Callable[[str, float | None, FitResult], None] | None = None,
              jobs: int = 1, executor=None) -> StudyFit:
    """Fit H_CL (eq. 4, plus ``effects``) to every aggregate of a study's spectra.

    Parameters
    ----------
    spectra : armfit.spectra.Spectra or pandas.DataFrame
        The study's responses (a long table in the spectra-file schema is accepted).
    which : {'grip', 'nominal'}
        'grip': kind "measured", level "mean", one fit per axis × grip (Table I);
        'nominal': level "median", one per axis (Table II).
    cost : {'complex', 'paper'}
        See the module docstring (eq. 5 for 'paper').
    bands : dict, optional
        {axis: (lo, hi) Hz}; default :data:`PAPER_BANDS`.
    effects : sequence or mapping
        Effects added to every model (a sequence of Effect, names or held specs
        ``NAME=VALUES``; see :func:`armfit.models.effects.resolve_effects`), or one
        sequence per axis {axis: sequence} (axes not named: the base model).
    bootstrap : int
        Number of subject resamples (0: Jacobian intervals), aggregated with
        :func:`armfit.spectra.aggregate`.
    seed : int or None
        Seed of the resampling.
    method : str, optional
        Estimator to use when the spectra hold several.
    max_nfev : int, optional
        Evaluation budget of each final local fit.
    source : str, optional
        File name for messages (default: the file the spectra were read from).
    on_fit : callable, optional
        ``on_fit(axis, grip, fit)`` after each fit.
    jobs : int
        Worker processes (one aggregate each); the result does not depend on it.
    executor : concurrent.futures.Executor, optional
        Runs the fits instead (used as is, see :mod:`armfit.workers`).

    Returns
    -------
    StudyFit

    Raises
    ------
    BadInputError
        The spectra have no such aggregates.
    UsageError
        Several estimators and no ``method``, or a ``method`` the spectra lack.
    ConvergenceError
        A fit did not converge (exit 3).
    """
    (study,) = fit_studies(spectra, (which,), cost=cost, bands=bands, effects=effects,
                           bootstrap=bootstrap, seed=seed, method=method, max_nfev=max_nfev,
                           source=source, on_fit=on_fit, jobs=jobs, executor=executor)
    return study


def fit_studies(spectra, whiches: Sequence[str], *, cost: str = "complex",
                bands: Mapping[str, tuple[float, float]] | None = None,
                effects: Sequence = (), bootstrap: int = 0, seed: int | None = 0,
                method: str | None = None, max_nfev: int | None = None,
                source: str | None = None,
                on_fit: Callable[[str, float | None, FitResult], None] | None = None,
                jobs: int = 1, executor=None) -> Iterator[StudyFit]:
    """:func:`fit_study` of each set of ``whiches`` (e.g. ``("nominal", "grip")``), with
    the same model, band and options: every fit of every set handed to the workers at
    once, in this order, and each set's :class:`StudyFit` yielded as soon as its own fits
    are done, while the next sets' fits go on. Work that needs only the first set (Table
    II's W_max, say) can then start while the others run, and queue behind them instead
    of waiting for the slowest. Each fit is the one :func:`fit_study` makes (the same
    task, in any company). Parameters as :func:`fit_study`; the generator, closed early,
    cancels the fits not yet started.

    Yields
    ------
    StudyFit
        One per set, in the order of ``whiches``.
    """
    from armfit.spectra import Spectra
    for which in whiches:
        if which not in STUDY_FITS:
            raise UsageError(f"which must be one of {', '.join(STUDY_FITS)}, "
                             f"got {which!r}")
    bands = dict(PAPER_BANDS) if bands is None else dict(bands)
    specs = effects_by_axis(effects)
    sp = Spectra.of(spectra)
    source = source if source is not None else sp.source
    sets, tasks = [], []
    for which in whiches:
        agg, measured = _study_aggregates(sp, STUDY_FITS[which], method, source)
        keys, set_tasks = _study_tasks(agg, measured, which, source, bands=bands,
                                       specs=specs, bootstrap=(bootstrap, seed),
                                       options={"cost": cost, "max_nfev": max_nfev})
        sets.append((which, keys))
        tasks += set_tasks
    done = iter_tasks(_fit_group, tasks, jobs, preload=POOL_PRELOAD["fit"],
                      executor=executor)
    del tasks
    try:
        for which, keys in sets:
            fits = []
            for (axis, grip), fit in zip(keys, done, strict=False):
                fits.append(fit)
                if on_fit is not None:
                    on_fit(axis, grip, fit)
            yield StudyFit(which, tuple(keys), tuple(fits))
    finally:
        done.close()        # closed early: the fits not yet started are cancelled


def _study_aggregates(sp: Spectra, how: str, method: str | None, source: str | None
                      ) -> tuple[Spectra, Spectra]:
    """The measured on-axis aggregates of level ``how`` of a study's spectra, and every
    measured on-axis row (for the bootstrap's trials), of estimator ``method`` when the
    spectra hold several."""
    measured = sp.select(kind="measured")
    measured = measured.take(measured.key("out_axis") == measured.key("axis"))
    agg = measured.select(level=how)
    if len(agg) == 0:
        raise BadInputError(f"no rows with level '{how}' and kind 'measured'; run "
                            "`armfit estimate` to write the aggregates", file=source,
                            column="level")
    if _check_method(agg, method, source) is not None:
        agg = agg.select(method=method)
        measured = measured.select(method=method)
    return agg, measured


def _study_tasks(agg: Spectra, measured: Spectra, which: str, source: str | None, *,
                 bands: Mapping[str, tuple[float, float]], specs: Mapping,
                 bootstrap: tuple[int, int | None], options: Mapping
                 ) -> tuple[list[tuple[str, float | None]], list[tuple]]:
    """The (axis, grip) keys and the :func:`_fit_group` tasks of :func:`fit_study`: one
    per aggregate (axis × grip for 'grip', axis for 'nominal'), in key order; with
    ``bootstrap`` (replicates, seed) replicates > 0, each with its trials."""
    how = STUDY_FITS[which]
    group_cols = ("axis", "grip_N") if which == "grip" else ("axis",)
    agg = agg.sorted(group_cols)
    groups: dict[tuple, list[int]] = {}
    for i in range(len(agg)):
        key = tuple(agg.key(c)[i] for c in group_cols)
        groups.setdefault(key, []).append(i)
    keys: list[tuple[str, float | None]] = []
    tasks = []
    n_boot, seed = bootstrap
    for key, rows in groups.items():
        axis = str(key[0])
        grip = float(key[1]) if which == "grip" else None
        if len(rows) > 1:
            raise BadInputError(f"repeated frequencies in the {how} of axis {axis}"
                                + (f", grip {grip:g} N" if grip is not None else ""),
                                file=source, column="freq_hz")
        f, h, se_db, se_deg = agg.row(rows[0])
        where = f"axis {axis}" + (f", grip {grip:g} N" if grip is not None else "")
        boot = None
        if n_boot:
            trials = measured.select(level="trial", axis=axis, grip=grip)
            boot = (*_trial_matrix(trials, f, source, where, how), how, n_boot, seed)
        keys.append((axis, grip))
        model = ClosedLoopModel.for_axis(axis, specs[axis][0], held=specs[axis][1])
        tasks.append((where, model, (f, h, se_db, se_deg),
                      {"cost": options["cost"], "band": bands[axis],
                       "max_nfev": options["max_nfev"]}, boot))
    return keys, tasks


def _fit_group(task) -> FitResult:
    """One aggregate's fit (a task of :func:`fit_study`); errors name the group."""
    where, model, (f, h, se_db, se_deg), kw, boot = task
    try:
        fit = fit_response(model, f, h, se_db=se_db, se_deg=se_deg, **kw)
        if boot is not None:
            hs, subjects, how, n_boot, seed = boot
            fit = bootstrap_fit(fit, f, hs, subjects, aggregate=_aggregator(how),
                                n_boot=n_boot, seed=seed, se_db=se_db, se_deg=se_deg)
    except ConvergenceError as exc:
        raise ConvergenceError(f"{where}: {exc}") from None
    except UsageError as exc:
        raise UsageError(f"{where}: {exc}") from None
    return fit


def _aggregator(how: str) -> Aggregator:
    from armfit.spectra import aggregate
    return lambda H: aggregate(H, how)


def _trial_matrix(trials: Spectra, f: np.ndarray, source: str | None, where: str, how: str
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(n_trials, n_freq) responses on grid f and the subject of each trial. For the
    mean, each subject's runs at one grip are first combined into one response (their
    mean), as `armfit estimate` does before averaging over subjects."""
    if len(trials) == 0:
        raise BadInputError(f"{where}: a bootstrap needs the per-trial rows (level 'trial')",
                            file=source, column="level")
    subj, grips, runs = (trials.key(c) for c in ("subject", "grip_N", "run"))
    order = sorted(range(len(trials)), key=lambda i: (
        str(subj[i]), float(grips[i]), -1 if runs[i] is None else runs[i]))
    hs, subjects = [], []
    for i in order:
        ft, ht, _, _ = trials.row(i)
        if ft.shape != f.shape or not np.allclose(ft, f, rtol=1e-9):
            raise BadInputError(f"{where}: trial of subject {subj[i]} is not on the common "
                                "frequency grid", file=source, column="freq_hz")
        hs.append(ht)
        subjects.append((str(subj[i]), float(grips[i])))
    if how == "mean":
        from armfit.spectra import aggregate
        keys = list(dict.fromkeys(subjects))
        hs = [aggregate(np.array([h for h, k in zip(hs, subjects, strict=True) if k == key]),
                        "mean") for key in keys]
        subjects = keys
    return np.array(hs), np.array([s for s, _ in subjects])


def exact_response(model: ClosedLoopModel, f_hz, params: Mapping[str, float]) -> np.ndarray:
    """Convenience: the model's X/F (m/N) at ``params`` — eq. 4 (with effects)."""
    return model.response(np.asarray(f_hz, float), dict(params))



# ---------------------------------------------------------------------------
# One fit per trial (the population of real people, not of means)
# ---------------------------------------------------------------------------

#: Identity columns of a per-trial params file, before the parameters.
TRIAL_KEYS: tuple[str, ...] = ("axis", "subject", "grip_N", "run")


@dataclass(frozen=True)
class TrialFit:
    """The fit of one trial: its identity, the FitResult (None when it failed) and the
    reason it failed ("" when it did not)."""

    axis: str
    subject: str
    grip_N: float
    run: int | None
    fit: FitResult | None
    reason: str = ""


def trial_groups(spectra, *, method: str | None = None, source: str | None = None
                 ) -> list[tuple[tuple[str, str, float, int | None], tuple]]:
    """The measured trial responses of a study, one per (axis, subject, grip_N, run),
    sorted in that order: [(key, (f_hz, H, se_db, se_deg))]. ``spectra``: a Spectra, a
    long table, or the path of a spectra file (only its measured trial rows are read, and
    let go once their arrays are taken). Raises BadInputError if there are none,
    UsageError if several estimators are present and ``method`` is not given."""
    # of a file, only the values the fits use (the other seven would more than double
    # what a study's trial rows hold)
    sp = _read_or_of(spectra, level="trial", kind="measured", values=("se_db", "se_deg"))
    source = source if source is not None else sp.source
    tr = sp.select(kind="measured", level="trial")
    tr = tr.take(tr.key("out_axis") == tr.key("axis"))
    if len(tr) == 0:
        raise BadInputError("no rows with level 'trial' and kind 'measured'; make the file "
                            "with `armfit estimate`", file=source, column="level")
    if _check_method(tr, method, source) is not None:
        tr = tr.select(method=method)
    keys = [(str(a), str(s), float(g), r) for a, s, g, r in zip(
        tr.key("axis"), tr.key("subject"), tr.key("grip_N"), tr.key("run"), strict=True)]
    order = sorted(range(len(tr)), key=lambda i: (*keys[i][:3], -1 if keys[i][3] is None
                                                  else keys[i][3]))
    # a response on every frequency of the grid is a view of the read's arrays, not a
    # copy of them (the same values): the read's arrays and copies of them are never held
    # at once (33 against 17 MB for the 4,050 trials of a study on 100 frequencies)
    whole = tr.present.all(axis=1)

    def row(i: int) -> tuple:
        return (tr.freq_hz, tr.h[i], tr.se_db[i], tr.se_deg[i]) if whole[i] else tr.row(i)
    return [(keys[i], row(i)) for i in order]


def fit_trial(key: tuple[str, str, float, int | None], rows, *, cost: str = "complex",
              band: tuple[float, float] | None = None, effects: Sequence = (),
              max_nfev: int | None = None, x0: Mapping[str, float] | None = None,
              held: Mapping[str, float] | None = None) -> TrialFit:
    """Fit H_CL (eq. 4, plus ``effects``) to one trial's measured response ``rows`` =
    (f_hz, H in m/N, se_db, se_deg), as :func:`trial_groups` gives it, with
    :func:`fit_response`: with the global search, or with ``x0`` a local fit from those
    parameter values only (kept even when it did not converge: :func:`fit_trial_models`
    decides). A fit that fails (no convergence, too few usable bins, repeated
    frequencies) is returned with ``fit`` None and its reason, not raised. ``held``:
    {``effect.param``: value} of effect parameters held fixed."""
    axis, subject, grip, run = key
    band = PAPER_BANDS[axis] if band is None else band
    try:
        model = ClosedLoopModel.for_axis(axis, effects, held=held)
        f, h, se_db, se_deg = rows
        if unique(f).size != f.size:
            raise BadInputError("repeated frequencies in the trial's response",
                                column="freq_hz")
        fit = fit_response(model, f, h, se_db=se_db, se_deg=se_deg, cost=cost, band=band,
                           max_nfev=max_nfev, x0=x0, global_search=x0 is None,
                           strict=x0 is None)
    except EffectDefinitionError:   # the model itself is broken, not this trial's data
        raise
    except (ConvergenceError, UsageError, BadInputError) as exc:
        return TrialFit(axis, subject, grip, run, None, str(exc).splitlines()[0])
    return TrialFit(axis, subject, grip, run, fit)


def _fit_trial_task(args):
    key, rows, kw = args
    return fit_trial(key, rows, **kw)


#: A trial's local fit (from its grip's fit) whose RMS normalised error exceeds this many
#: times the median of its axis's local fits (and :data:`LOCAL_NOISE_TOL`) gets the
#: global search as well.
LOCAL_OUTLIER = 1.5
#: Normalised RMS error under which a local fit is accepted whatever its axis's median.
LOCAL_NOISE_TOL = 1.5


def _needs_global(tf: TrialFit, median: float, start_bounds: Sequence[str] = ()) -> bool:
    """Whether a trial's local fit also gets the global search: it failed, did not
    converge, has a parameter at a bound that its start (the grip's fit) is not at, or
    misfits (see :data:`LOCAL_OUTLIER`). A bound the grip's fit shares comes from the
    model and the data, not from a poor local minimum of this trial."""
    fit = tf.fit
    if fit is None or not fit.converged or set(fit.at_bound) - set(start_bounds):
        return True
    return bool(_misfit(fit) > max(LOCAL_NOISE_TOL, LOCAL_OUTLIER * median))


def _misfit(fit: FitResult) -> float:
    """A fit's RMS normalised error (its RMS dB error without standard errors)."""
    return fit.rms_norm if np.isfinite(fit.rms_norm) else fit.rms_db


def fit_trial_models(spectra, *, cost: str = "complex",
               bands: Mapping[str, tuple[float, float]] | None = None,
               effects: Sequence = (), method: str | None = None,
               max_nfev: int | None = None, jobs: int = 1, source: str | None = None,
               starts: Mapping[tuple[str, float], Mapping[str, float]] | None = None,
               on_fit: Callable[[TrialFit], None] | None = None,
               executor=None,
               subject_effects: Mapping[str, Mapping[str, Sequence]] | None = None
               ) -> list[TrialFit]:
    """One fit of H_CL per trial (axis × subject × grip [× run]) of a spectra table, in
    that order (:func:`trial_groups`). Failed fits are kept, with their reason. ``jobs``
    > 1 fits in that many worker processes, a :class:`concurrent.futures.Executor`
    ``executor`` on it instead (:mod:`armfit.workers`); the results depend on neither.

    The trials of one axis and grip are alike, so each trial is first fitted locally
    from its grip's fit (``starts``: {(axis, grip_N): parameters}; by default the grip
    fits of :func:`fit_study` on the same spectra). A trial whose local fit did not
    converge, has a parameter at a bound its grip's fit is not at, or misfits by more
    than :data:`LOCAL_OUTLIER` times its axis's median RMS normalised error (and more
    than :data:`LOCAL_NOISE_TOL`) gets the global search of :func:`fit_response` too, and
    keeps the better fit; so does a trial without a start.

    ``spectra`` may be the path of a spectra file: its measured trial rows are read (and
    the grip means, without ``starts``), and only each trial's arrays are kept.

    ``subject_effects``: {axis: {subject: effect items}}, the model of a subject's trials
    where it differs from ``effects`` (effect values per subject, held:
    :meth:`armfit.adopt.AxisAdoption.items_for`).
    """
    bands = dict(PAPER_BANDS) if bands is None else dict(bands)
    specs = effects_by_axis(effects)
    per_subject = {(axis, str(subj)): resolve_effects(items)
                   for axis, by in (subject_effects or {}).items()
                   for subj, items in by.items()}
    groups = trial_groups(spectra, method=method, source=source)
    if starts is None:
        starts = _grip_starts(spectra, cost, bands, effects, method, source)
    base = {"cost": cost, "max_nfev": max_nfev}

    def spec(key) -> tuple:
        return per_subject.get((key[0], str(key[1])), specs[key[0]])

    keys = [key for key, _ in groups]
    # each trial's arrays are kept only while its fit may still need the global search
    # (below); the tasks handed to the workers are let go as they are done
    rows: list[tuple | None] = [r for _, r in groups]
    del groups
    kws = [{**base, "band": bands[key[0]], "effects": spec(key)[0], "held": spec(key)[1],
            "x0": starts.get((key[0], float(key[2])))} for key in keys]
    # the parameters each start has at a bound (a bound shared with the start is no
    # reason for the global search)
    start_bounds = {k: at_bound(ClosedLoopModel.for_axis(k[0], specs[k[0]][0],
                                                         held=specs[k[0]][1]).params, v)
                    for k, v in starts.items()}

    def needs_global(i: int, tf: TrialFit, median: float) -> bool:
        return kws[i]["x0"] is not None and _needs_global(
            tf, median, start_bounds[(keys[i][0], float(keys[i][2]))])

    def run(indices: list[int], **kw) -> Iterator[TrialFit]:
        return iter_tasks(_fit_trial_task, [(keys[i], rows[i], {**kws[i], **kw})
                                            for i in indices], jobs,
                          preload=POOL_PRELOAD["fit"], chunksize=4, executor=executor)

    out = []
    for i, tf in enumerate(run(list(range(len(keys))))):
        out.append(tf)
        # a local fit that needs no global search with a median of 0 needs none with
        # its axis's (the threshold only rises with it): its arrays are not needed again
        if not needs_global(i, tf, 0.0):
            rows[i] = None
    medians = {}
    for axis in {t.axis for t in out}:
        errs = [_misfit(t.fit) for t in out if t.axis == axis and t.fit is not None]
        medians[axis] = float(median(errs)) if errs else np.inf
    again = [i for i, t in enumerate(out) if needs_global(i, t, medians[t.axis])]
    glob = run(again, x0=None)
    for i, tf in zip(again, glob, strict=True):
        if _rank(tf) > _rank(out[i]):
            out[i] = tf
    for tf in out:
        if on_fit is not None:
            on_fit(tf)
    return out


def _rank(tf: TrialFit) -> tuple[int, float]:
    """Order of trial fits, best highest: a converged fit (then the lower objective), a
    failure with its reason, a fit that did not converge."""
    if tf.fit is None:
        return (1, 0.0)
    return (2, -tf.fit.objective) if tf.fit.converged else (0, 0.0)


def _grip_starts(spectra, cost, bands, effects, method, source
                 ) -> dict[tuple[str, float], dict[str, float]]:
    """{(axis, grip_N): parameters} of the grip fits of ``spectra`` (none where they
    cannot be made: every trial then gets the global search)."""
    try:
        study = fit_study(_read_or_of(spectra, level="mean", kind="measured"), which="grip",
                          cost=cost, bands=bands, effects=effects, method=method,
                          source=source)
    except EffectDefinitionError:   # the model itself is broken, not the grip fits' data
        raise
    except (ConvergenceError, UsageError, BadInputError):
        return {}
    return grip_fit_starts(study.keys, study.fits)


def _read_or_of(spectra, *, level: str, kind: str,
                values: Sequence[str] | None = None) -> Spectra:
    """The responses of level ``level`` and kind ``kind`` of the spectra file ``spectra``
    (a path; with ``values`` only those of the values, and without the metadata's
    per-trial records), or ``spectra`` itself (a Spectra or a long table) as a
    Spectra."""
    from armfit.spectra import Spectra
    if isinstance(spectra, str | os.PathLike):
        return Spectra.read(spectra, level=level, kind=kind, values=values,
                            estimators=False)
    return Spectra.of(spectra)


def grip_fit_starts(keys, fits: Sequence[FitResult]) -> dict[tuple[str, float], dict[str, float]]:
    """{(axis, grip_N): parameters} of converged grip fits, the starts of
    :func:`fit_trial_models`; ``keys`` (axis, grip_N) in the order of ``fits`` (the fits
    themselves, not a rounded CSV: the same start, the same bits)."""
    return {(axis, float(grip)): dict(fit.params)
            for (axis, grip), fit in zip(keys, fits, strict=True)
            if fit.converged and grip is not None}


def trial_fits_table(fits: Sequence[TrialFit], effects=()):
    """The per-trial params table: the layout of a grip fit
    (:func:`armfit.io.artifacts.params_columns`) with ``subject`` after ``axis``, ``run``
    after ``grip_N`` and a last column ``reason`` (empty for a fit; for a failed trial its
    reason, with empty parameters and ``converged`` false). ``effects``: the models'
    effects as :func:`fit_trial_models` took them (names the effects of a failed trial)."""
    import pandas as pd

    specs = effects_by_axis(effects)
    present = {tf.axis for tf in fits}
    models = [ClosedLoopModel.for_axis(a, e, held=h) for a, (e, h) in specs.items()
              if a in present]
    models += [tf.fit.model for tf in fits if tf.fit is not None]
    names = union_param_names(models)
    held = any(m.held for m in models)
    cols = params_columns(names, grip=True, held=held)
    cols = cols[:1] + ["subject"] + cols[1:2] + ["run"] + cols[2:] + ["reason"]
    rows = []
    for tf in fits:
        row: dict = {"axis": tf.axis, "subject": tf.subject, "grip_N": tf.grip_N,
                     "run": tf.run, "reason": tf.reason}
        if tf.fit is not None:
            row.update(tf.fit.row())
        else:
            row.update(converged=False,
                       effects=";".join(e.name for e in specs[tf.axis][0]),
                       mp_kg=ClosedLoopModel.for_axis(tf.axis).mp, cost="")
        rows.append(row)
    df = pd.DataFrame(rows, columns=cols)
    df["run"] = df["run"].astype("Int64")
    return df

__all__ = ["COSTS", "PAPER_BANDS", "STUDY_FITS", "FitResult", "StudyFit", "analytic_guess",
           "bootstrap_fit", "exact_response", "fit_response", "fit_study", "fit_studies",
           "log_errors",
           "TRIAL_KEYS", "TrialFit", "fit_trial", "fit_trial_models",
           "trial_fits_table", "trial_groups"]
