"""The joint problem of one axis: every trial's arm parameters and the shared effect
parameters in one least-squares fit (:mod:`armfit.blocklsq`), its starting points screened
on a subset of trials and its stuck trials rescued by single-trial fits.

An effect parameter is either **shared** by every trial of the axis or **per subject**
(``varying``): one value per subject, shared by that subject's trials (a subject with one
trial has its own value). Per-subject parameters are grouped shared columns of the
block-arrow problem (:class:`armfit.blocklsq.Groups`): each trial sees its own subject's."""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from armfit import blocklsq
from armfit._order import median, unique
from armfit._student import t_quantile
from armfit.constants import DB_PER_NEPER, PARAM_NAMES, Z_975
from armfit.diagnosis.bands import residuals
from armfit.diagnosis.responses import AxisData
from armfit.diagnosis.tuning import (
    CHUNK_TRIALS,
    FTOL_VARIANCE,
    OUTLIER,
    REFINE_BEST,
    START_GAP,
    START_SCREEN_NFEV,
    START_SCREEN_TRIALS,
    TRIAL_FIT_NFEV,
)
from armfit.fitting import ParamSpace, fit_response
from armfit.models.arm import ClosedLoopModel

__all__ = ["CHUNK_TRIALS", "JointFit", "JointProblem", "joint_fit", "refine", "rescue_trials",
           "screen_starts", "trial_fit"]

#: √eps of float64: the relative step of the forward differences of the Jacobian.
_SQRT_EPS = float(np.sqrt(np.finfo(float).eps))


@dataclass(frozen=True)
class JointFit:
    """Result of one joint fit: per-trial base parameters (T, 5), shared effect
    parameters with 95 % intervals, residuals (T, n) and the residual sum of squares.

    Per-subject parameters (``varying``, full names ``effect.param``): ``by_subject``
    {subject: {name: value}} with 95 % intervals (``by_subject_lo``, ``by_subject_hi``),
    ``subjects`` the subject of each trial; ``shared`` then holds their population value
    (the mean over subjects in the fitter's coordinate, log for log parameters) with the
    95 % interval of that mean from the subjects' spread."""

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
    varying: tuple[str, ...] = ()
    subjects: tuple[str, ...] = ()
    by_subject: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    by_subject_lo: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    by_subject_hi: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    @property
    def n_free(self) -> int:
        """Free parameters: the trials' arm parameters, the shared effect parameters and
        one value per subject of each per-subject one."""
        k = len(self.shared) - len(self.varying)
        return int(self.base.size + k + len(self.by_subject) * len(self.varying))

    def trial_values(self) -> dict[str, np.ndarray]:
        """Every effect parameter's value in each trial, {name: (T,)}: the shared value,
        or the trial's subject's."""
        T = self.base.shape[0]
        out = {n: np.full(T, float(v)) for n, v in self.shared.items()}
        for n in self.varying:
            out[n] = np.array([self.by_subject[s][n] for s in self.subjects], float)
        return out

    def subset(self, idx: np.ndarray, r_db: np.ndarray | None = None,
               r_deg: np.ndarray | None = None, rss: float | None = None,
               n_res: int | None = None) -> JointFit:
        """The trials ``idx`` of this fit (their subjects' values only); residuals and
        cost as given (default: the trials' rows, cost and count unchanged)."""
        subjects = tuple(self.subjects[i] for i in idx) if self.subjects else ()
        keep = set(subjects)

        def pick(d: Mapping) -> dict:
            return {k: v for k, v in d.items() if k in keep}

        return replace(self, base=self.base[idx],
                       r_db=self.r_db[idx] if r_db is None else r_db,
                       r_deg=self.r_deg[idx] if r_deg is None else r_deg,
                       rss=self.rss if rss is None else rss,
                       n_res=self.n_res if n_res is None else n_res, subjects=subjects,
                       by_subject=pick(self.by_subject),
                       by_subject_lo=pick(self.by_subject_lo),
                       by_subject_hi=pick(self.by_subject_hi))


class JointProblem:
    """Residuals of T trials with per-trial base parameters and shared effect parameters
    (``varying``: the effect parameters with one value per subject instead).

    The parameter vector x is the trials' base parameters (T·5), then the K values of the
    effect parameters: the shared ones in the model's order, then per subject (in order of
    first appearance) its values of the varying ones. ``cols`` (T, k) maps each trial's k
    effect parameters to those K (None when nothing varies: K = k)."""

    def __init__(self, model: ClosedLoopModel, data: AxisData, sel: np.ndarray,
                 varying: Sequence[str] = ()):
        self.model = model
        self.space = ParamSpace.of(model)
        # on the whole grid (the default band) the data's own arrays, not copies of them
        # (1,350 trials' responses take 2.2 MB)
        sel = slice(None) if np.all(sel) else sel
        self.f = data.f_hz[sel]
        self.h = data.h[:, sel]
        sdb, sdeg = data.noise_se(sel)
        self.w_db, self.w_deg = 1.0 / sdb, 1.0 / sdeg
        # the points left out of the evidence (AxisData.excluded: NaN standard errors)
        # weigh nothing in the fit; elsewhere a non-finite residual is a model's blow-up
        used = np.concatenate([np.isfinite(self.w_db), np.isfinite(self.w_deg)], axis=1)
        self.unused = None if used.all() else np.where(used, 1e6, 0.0)
        self.T = self.h.shape[0]
        self.nb = len(PARAM_NAMES)
        self.k = len(self.space.names) - self.nb
        self.base_idx = np.arange(self.nb)
        self.eff_idx = np.arange(self.nb, self.nb + self.k)
        self.effect_names = tuple(self.space.names[self.nb:])
        want = set(varying)
        self.varying = tuple(n for n in self.effect_names if n in want)
        self.trial_subjects = tuple(data.subject_of_trials())
        self.subjects = tuple(dict.fromkeys(self.trial_subjects))
        self.fixed = tuple(n for n in self.effect_names if n not in want)
        if self.varying:
            sidx = np.array([self.subjects.index(s) for s in self.trial_subjects])
            kf, kv = len(self.fixed), len(self.varying)
            cols = np.empty((self.T, self.k), dtype=np.intp)
            for j, n in enumerate(self.effect_names):
                cols[:, j] = (self.fixed.index(n) if n not in want
                              else kf + sidx * kv + self.varying.index(n))
            self.cols = cols
            self.K = kf + len(self.subjects) * kv
            self.local = np.empty(self.K, dtype=np.intp)   # global value -> local column
            self.local[cols] = np.broadcast_to(np.arange(self.k), cols.shape)
        else:
            self.cols, self.K, self.local = None, self.k, np.arange(self.k)
        self.groups = None if self.cols is None else blocklsq.Groups(self.cols, self.K)

    def unpack(self, x: np.ndarray) -> np.ndarray:
        """x (T·5 + K) → z (T, P) in the transformed space."""
        n = self.T * self.nb
        z = np.empty((self.T, self.nb + self.k))
        z[:, : self.nb] = x[:n].reshape(self.T, self.nb)
        z[:, self.nb:] = x[n:] if self.cols is None else x[n:][self.cols]
        return z

    def effect_values(self, x: np.ndarray) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
        """The effect parameters at ``x`` (their units): ({name: value} of the shared
        ones, {subject: {name: value}} of the varying ones)."""
        theta = self.space.to_theta(self.unpack(x))
        shared = {n: float(theta[0, self.nb + j]) for j, n in enumerate(self.effect_names)
                  if n not in self.varying}
        by_subject: dict[str, dict[str, float]] = {}
        for i, subj in enumerate(self.trial_subjects):
            if self.varying and subj not in by_subject:
                by_subject[subj] = {n: float(theta[i, self.nb + self.effect_names.index(n)])
                                    for n in self.varying}
        return shared, by_subject

    def response(self, x: np.ndarray, rows: slice = slice(None)) -> np.ndarray:
        """The model's response of the trials ``rows`` at ``x``, (t, n)."""
        theta = self.space.to_theta(self.unpack(x)[rows])
        values = {n: theta[:, i:i + 1] for i, n in enumerate(self.space.names)}
        return self.model.response(self.f, values)

    def _chunk_res(self, x: np.ndarray):
        """(rows, residuals in dB, in deg) at ``x``, :data:`CHUNK_TRIALS` trials at a
        time (each trial's are its own, whatever its company)."""
        for a in range(0, self.T, CHUNK_TRIALS):
            rows = slice(a, a + CHUNK_TRIALS)
            with np.errstate(all="ignore"):
                yield (rows, *residuals(self.h[rows], self.response(x, rows)))

    def split_res(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residuals (dB, deg) of every trial at ``x``, (T, n), made
        :data:`CHUNK_TRIALS` trials at a time."""
        r_db, r_deg = np.empty(self.h.shape), np.empty(self.h.shape)
        for rows, db, deg in self._chunk_res(x):
            r_db[rows], r_deg[rows] = db, deg
        return r_db, r_deg

    def fun(self, x: np.ndarray) -> np.ndarray:
        """The weighted residuals (dB, then deg, of each trial) at ``x``, (T·m,); a
        residual that is not finite is replaced by a constant. Made in place,
        :data:`CHUNK_TRIALS` trials at a time: besides the result, only those trials'
        residuals in dB and deg are held."""
        n = self.h.shape[1]
        r = np.empty((self.T, 2 * n))
        for rows, r_db, r_deg in self._chunk_res(x):
            np.multiply(r_db, self.w_db[rows], out=r[rows, :n])
            np.multiply(r_deg, self.w_deg[rows], out=r[rows, n:])
        bad = ~np.isfinite(r)
        if bad.any():
            r[bad] = 1e6 if self.unused is None else self.unused[bad]
        return r.ravel()

    def jac(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The Jacobian of :meth:`fun` as its blocks (per-trial (T, m, 5), shared
        (T, m, k); see :mod:`armfit.blocklsq`): the arm parameters' columns analytic
        (:meth:`armfit.models.arm.ClosedLoopModel.response_and_base_log_derivatives`), the effect
        parameters' by forward differences, all of these in one vectorised evaluation
        (column j of every trial perturbed at once: the trials' blocks do not overlap;
        shared columns for all trials together), steps √eps·max(1, |z|), taken backwards
        at an upper bound. The trials are taken :data:`CHUNK_TRIALS` at a time, so the
        temporaries do not grow with the number of trials."""
        m = 2 * self.f.size
        jb, js = np.empty((self.T, m, self.nb)), np.empty((self.T, m, self.k))
        for rows, jb_rows, js_rows in self._jac_chunks(x):
            jb[rows], js[rows] = jb_rows, js_rows
        return jb, js

    def normal(self, x: np.ndarray, r: np.ndarray) -> blocklsq.Normal:
        """The blocks of JᵀJ and Jᵀr (:func:`armfit.blocklsq.normal_blocks`) at ``x``,
        whose residuals (:meth:`fun`) are ``r`` (T, m): :meth:`jac`'s Jacobian made
        :data:`CHUNK_TRIALS` trials at a time and reduced at once, so that the Jacobian
        (about 40 kB a trial) is never held whole."""
        return blocklsq.normal_blocks(((rows, jb, js, r[rows])
                                       for rows, jb, js in self._jac_chunks(x)),
                                      self.T, self.groups)

    def _jac_chunks(self, x: np.ndarray):
        """(rows, Jb (t, m, 5), Js (t, m, k)) of :meth:`jac`, :data:`CHUNK_TRIALS` trials
        at a time."""
        z = self.unpack(x)                                    # (T, P)
        for a in range(0, self.T, CHUNK_TRIALS):
            rows = slice(a, a + CHUNK_TRIALS)
            D = self._jac_rows(z[rows], rows)                 # (t, m, P)
            yield rows, D[..., : self.nb], D[..., self.nb:]

    def _jac_rows(self, z: np.ndarray, rows: slice) -> np.ndarray:
        """The Jacobian of the trials ``rows`` (their parameters ``z``), (t, m, P).

        The residuals are r = (−20 log10|H/H_meas|, −angle(H/H_meas) in deg) times the
        weights, so an arm parameter's column is (−DB_PER_NEPER Re, −180/π Im) of
        ∂ ln H/∂θ times the weights and dθ/dz (θ for a parameter fitted in log, else
        upper − lower); the effect parameters' columns are forward differences. A point
        whose residual is not finite (replaced by a constant in :meth:`fun`) has a zero
        row."""
        t, P = z.shape
        nb, k = self.nb, P - self.nb
        h = _SQRT_EPS * np.maximum(1.0, np.abs(z[:, nb:]))
        h = np.where(z[:, nb:] + h > self.space.zhi[nb:], -h, h)
        Z = np.repeat(z[None], k + 1, axis=0)                 # (k + 1, t, P)
        idx = np.arange(k)
        Z[idx + 1, :, nb + idx] += h.T
        theta = self.space.to_theta(Z)
        values = {n: theta[..., i:i + 1] for i, n in enumerate(self.space.names)}
        w_db, w_deg = self.w_db[rows], self.w_deg[rows]
        fill = 1e6 if self.unused is None else self.unused[rows]
        with np.errstate(all="ignore"):
            # the response at z and the base derivatives there, then at the k steps
            h0, dlog, z_base = self.model.response_and_base_log_derivatives(
                self.f, {n: v[0] for n, v in values.items()}, with_base=True)
            # (t, n), (5, t, n), (t, n); the steps change only effect parameters: their
            # responses share the base impedance
            hm = h0[None] if not k else np.concatenate([h0[None], self.model.response_at_base(
                self.f, {n: v[1:] for n, v in values.items()}, z_base)])
            r_db, r_deg = residuals(self.h[None, rows], hm)
            R = np.concatenate([r_db * w_db, r_deg * w_deg], axis=-1)
            dz = np.where(self.space.log[:nb], theta[0, :, :nb],
                          self.space.upper[:nb] - self.space.lower[:nb])  # dθ/dz, (t, 5)
            Db = np.concatenate([-DB_PER_NEPER * dlog.real * w_db,
                                 -np.degrees(dlog.imag) * w_deg], axis=-1) * dz.T[:, :, None]
        ok = np.isfinite(R[0])
        Db = np.where(ok & np.isfinite(Db), Db, 0.0)                   # (5, t, m)
        R = np.where(np.isfinite(R), R, fill)
        De = (R[1:] - R[:1]) / h.T[:, :, None]                         # (k, t, m)
        return np.concatenate([Db, De]).transpose(1, 2, 0)             # (t, m, P)

    def solve(self, x0: np.ndarray, max_nfev: int, **opts) -> blocklsq.BlockResult:
        """The joint least-squares fit from ``x0`` (:func:`armfit.blocklsq.solve`, given
        ``opts``: its tolerances, ``final_normal``)."""
        lo, hi = self.bounds()
        return blocklsq.solve(self.fun, None, x0, lo, hi, n_trials=self.T,
                              n_block=self.nb, max_nfev=max_nfev, cols=self.cols,
                              normal=self.normal, **opts)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.concatenate([np.tile(self.space.zlo[: self.nb], self.T),
                             self.space.zlo[self.nb:][self.local]])
        hi = np.concatenate([np.tile(self.space.zhi[: self.nb], self.T),
                             self.space.zhi[self.nb:][self.local]])
        return lo, hi

    def pack(self, base: np.ndarray, shared: Mapping[str, float],
             by_subject: Mapping[str, Mapping[str, float]] | None = None) -> np.ndarray:
        """x from the trials' base parameters (T, 5) and the effect values: ``shared``
        {name: value}, and for a varying parameter its subject's value of ``by_subject``
        where given, else the ``shared`` one."""
        full = np.zeros((self.T, len(self.space.names)))
        full[:, : self.nb] = base
        for j, n in enumerate(self.effect_names):
            full[:, self.nb + j] = shared[n]
            if n in self.varying and by_subject:
                full[:, self.nb + j] = [by_subject.get(s, {}).get(n, shared[n])
                                        for s in self.trial_subjects]
        z = self.space.clip_z(self.space.to_z(full))
        if self.cols is None:
            tail = z[0, self.nb:]
        else:
            tail = np.empty(self.K)
            tail[self.cols] = z[:, self.nb:]
        return np.concatenate([z[:, : self.nb].ravel(), tail])


def _lag1(r: np.ndarray) -> float:
    """Mean lag-1 autocorrelation along frequency of residual rows (T, n)."""
    r = r - r.mean(axis=1, keepdims=True)
    num = np.sum(r[:, 1:] * r[:, :-1])
    den = np.sum(r * r)
    return float(num / den) if den > 0 else 0.0


def joint_fit(model: ClosedLoopModel, data: AxisData, band: tuple[float, float],
              base: np.ndarray, starts: Sequence[Mapping[str, float]] = ({},),
              max_nfev: int = 200, pairs: Sequence[tuple[np.ndarray, Mapping]] = (),
              refine_best: int | None = None, screen_nfev: int | None = None,
              varying: Sequence[str] = (),
              by_subject: Mapping[str, Mapping[str, float]] | None = None) -> JointFit:
    """Fit ``model`` to every trial of ``data`` at once: arm parameters per trial, effect
    parameters shared (see the module docstring). ``base`` (T, 5), or a list of such:
    starting arm parameters (SI units); ``starts``: candidate starting values of the shared
    effect parameters; ``pairs``: further (base, start) combinations. Every combination is
    tried briefly on a subset of trials, the best ``refine_best`` (default
    :data:`REFINE_BEST`) refined on all, at most ``max_nfev`` evaluations each (the brief
    tries: ``screen_nfev``, default :data:`START_SCREEN_NFEV`). ``varying``: effect
    parameters (``effect.param``) with one value per subject, started at their subject's
    value of ``by_subject`` {subject: {name: value}} where given, else at the start's.
    Each refined start's stuck trials are rescued (:func:`rescue_trials`, the best fit
    of the starts before it the ``prior``).
    """
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = JointProblem(model, data, sel, varying)
    bases = [base] if isinstance(base, np.ndarray) else list(base)
    combos = [(b, st) for b in bases for st in starts] + list(pairs)
    briefs: dict[bytes, blocklsq.BlockResult] = {}
    if len(combos) > 1:
        x0s = screen_starts(model, data, sel, combos, prob,
                      REFINE_BEST if refine_best is None else refine_best,
                      START_SCREEN_NFEV if screen_nfev is None else screen_nfev,
                      by_subject, briefs=briefs)
    else:
        x0s = [prob.pack(*combos[0], by_subject)]
    best = clear = None
    seen = set()
    for x0 in x0s:
        if x0.tobytes() in seen:   # the same start ends where it ended before: no better
            continue
        seen.add(x0.tobytes())
        r = rescue_trials(prob, model, data, sel,
                          refine(prob, x0, max_nfev, briefs.get(x0.tobytes())), max_nfev,
                          prior=clear)
        if best is None or r.cost < best.cost:
            # the best fit so far is kept without its weighted residuals (one array as
            # large as the trials' residuals in dB and in deg together: 2.2 MB for the
            # base fit of an axis of 1,350 trials, held while the next start was
            # refined); _result makes the residuals anew
            clear = None if _stuck(prob, r).size else r.x
            best = _Best(r.x, r.cost, r.normal, r.status)
        del r
    return _result(prob, best)


class _Best(NamedTuple):
    """What :func:`_result` takes of a joint fit's solution (a
    :class:`armfit.blocklsq.BlockResult` without its residuals)."""

    x: np.ndarray
    cost: float
    normal: tuple[np.ndarray, np.ndarray, np.ndarray]
    status: int


def _result(prob: JointProblem, res: _Best | blocklsq.BlockResult) -> JointFit:
    """The :class:`JointFit` of the solution ``res`` of ``prob``."""
    theta = prob.space.to_theta(prob.unpack(res.x))
    r_db, r_deg = prob.split_res(res.x)
    shared, by_subject = prob.effect_values(res.x)
    lo, hi = _effect_ci(prob, res)
    s_lo = {n: lo[n] for n in shared}
    s_hi = {n: hi[n] for n in shared}
    b_lo = {s: {n: lo[(s, n)] for n in prob.varying} for s in by_subject}
    b_hi = {s: {n: hi[(s, n)] for n in prob.varying} for s in by_subject}
    for n in prob.varying:
        shared[n], s_lo[n], s_hi[n] = _population(prob.space, n, by_subject)
    shared = {n: shared[n] for n in prob.effect_names}
    nf = r_db.shape[1]
    zres = np.concatenate([r_db * prob.w_db, r_deg * prob.w_deg], axis=1)
    zdb, zdeg = zres[:, :nf], zres[:, nf:]
    if prob.unused is not None:     # the points left out count as nothing
        zdb, zdeg = np.nan_to_num(zdb), np.nan_to_num(zdeg)
    rho = (_lag1(zdb) + _lag1(zdeg)) / 2
    finite = np.isfinite(zres)
    n_res = int(zres.size if prob.unused is None else finite.sum())
    # the squares of the finite residuals in order (in place when all are finite)
    sq = np.square(zres, out=zres).ravel() if finite.all() else np.square(zres[finite])
    del zres, zdb, zdeg, finite
    return JointFit(prob.model, theta[:, : prob.nb], shared,
                    {n: s_lo[n] for n in shared}, {n: s_hi[n] for n in shared}, r_db, r_deg,
                    float(np.sum(sq)), n_res, rho,
                    bool(res.status > 0), prob.varying,
                    prob.trial_subjects if prob.varying else (), by_subject, b_lo, b_hi)


def _population(space: ParamSpace, name: str, by_subject: Mapping[str, Mapping[str, float]]
                ) -> tuple[float, float, float]:
    """The population value of a per-subject parameter: the mean of the subjects' values
    in the fitter's coordinate (log for a log parameter), with the 95 % interval of that
    mean from their spread (Student's t, subjects − 1 degrees of freedom)."""
    j = space.names.index(name)
    vals = np.array([v[name] for v in by_subject.values()], float)
    full = np.tile(space.to_theta(space.zlo), (vals.size, 1))
    full[:, j] = vals
    z = space.to_z(full)[:, j]
    m = float(np.mean(z))
    n = z.size
    half = (float(t_quantile(n - 1, 0.975) * np.std(z, ddof=1) / np.sqrt(n))
            if n > 1 else float("nan"))
    pts = np.tile(space.to_theta(space.zlo), (3, 1))
    zz = space.to_z(pts)
    zz[:, j] = [m, m - half, m + half]
    zz[1:, j] = np.clip(zz[1:, j], space.zlo[j], space.zhi[j])
    th = space.to_theta(zz)[:, j]
    return float(th[0]), float(th[1]), float(th[2])


def refine(prob: JointProblem, x0: np.ndarray, max_nfev: int,
           brief: blocklsq.BlockResult | None = None) -> blocklsq.BlockResult:
    """The joint fit from ``x0`` (:meth:`JointProblem.solve`).

    The fit stops when a step lowers the cost by less than :data:`FTOL_VARIANCE` of the
    residual variance s² = 2·cost/(m − p) (``ftol`` = 2·FTOL_VARIANCE/(m − p), at least
    1e-8, :func:`refine_ftol`), or moves the parameters by less than 1e-8 of their size.

    ``brief``: a brief try of the same problem from the same ``x0`` that watched this
    fit's ``ftol`` (:func:`screen_starts`): the fit is then the one the brief try saw
    stop, or goes on from where the brief try ended, the same fit bit for bit without
    making the brief try's evaluations again."""
    ftol = refine_ftol(prob, x0.size)
    if brief is not None and brief.watched is not None:
        return brief.watched
    if brief is not None and brief.state is not None:
        return prob.solve(x0, max_nfev, ftol=ftol, xtol=1e-8, resume=brief.state)
    return prob.solve(x0, max_nfev, ftol=ftol, xtol=1e-8)


def refine_ftol(prob: JointProblem, n_x: int) -> float:
    """The ``ftol`` of :func:`refine` on ``prob`` with ``n_x`` parameters."""
    m = 2 * prob.f.size * prob.T
    return max(1e-8, 2.0 * FTOL_VARIANCE / max(m - n_x, 1))


def _misfit_limit(prob: JointProblem, res) -> tuple[np.ndarray, float]:
    """Each trial's misfit in ``res`` (its sum of squared weighted residuals) and the
    limit above which it is stuck: :data:`OUTLIER` times the median trial's, and at
    least twice the number of its residuals."""
    per = (res.fun.reshape(prob.T, -1) ** 2).sum(axis=1)
    return per, OUTLIER * max(float(median(per)), 2.0 * prob.f.size)


def _stuck(prob: JointProblem, res) -> np.ndarray:
    """The stuck trials of ``res`` (:func:`_misfit_limit`)."""
    per, limit = _misfit_limit(prob, res)
    return np.flatnonzero(per > limit)


def rescue_trials(prob: JointProblem, model: ClosedLoopModel, data: AxisData, sel, res,
                  max_nfev: int, prior: np.ndarray | None = None):
    """Trials stuck in a poor local minimum of the joint fit (misfit far above the median
    trial's) get new arm parameters from a single-trial fit (:func:`trial_fit`): first a
    local one from the median arm parameters of the trials that fit, then, for a trial
    still far off, the global search. The single-trial fit weighs the trial's residuals
    by the same noise model's standard errors as the joint fit (it is given the whole
    grid and the band). The joint fit is refined again; the better of the two results is
    returned.

    ``prior``: the parameters (x) of the best fit of another start of the same problem,
    made already, when it has no trial stuck (None: no such fit). The stuck trials then
    first take their arm parameters there and the joint fit is refined; when that leaves
    no trial stuck, it is the rescue (the better of it and ``res``), and no single-trial
    fit is made. A start that ends with its effects in another valley leaves trials
    stuck that fit well in the prior's."""
    per, limit = _misfit_limit(prob, res)
    bad = np.flatnonzero(per > limit)
    if bad.size == 0:
        return res
    if prior is not None:
        x1 = res.x.copy()
        n = prob.T * prob.nb
        x1[:n].reshape(prob.T, prob.nb)[bad] = prior[:n].reshape(prob.T, prob.nb)[bad]
        res1 = refine(prob, x1, max_nfev)
        if not _stuck(prob, res1).size:
            return res1 if res1.cost < res.cost else res
    x0 = res.x.copy()
    zb = x0[: prob.T * prob.nb].reshape(prob.T, prob.nb)
    theta = prob.space.to_theta(prob.unpack(res.x))
    keep = np.ones(prob.T, bool)
    keep[bad] = False
    good = np.flatnonzero(keep)
    typical = np.exp(median(np.log(theta[good, : prob.nb]), axis=0)) if good.size else None
    names = prob.space.names
    band = (float(prob.f[0]), float(prob.f[-1]))

    def place(i: int, fit) -> None:
        row = np.array([fit.params[n] for n in PARAM_NAMES])
        zb[i] = prob.space.clip_z(prob.space.to_z(np.concatenate(
            [row, theta[i, prob.nb:]])))[: prob.nb]

    for i in bad:
        if typical is not None:
            start = dict(zip(names, np.concatenate([typical, theta[i, prob.nb:]]),
                             strict=True))
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
    this process is returned again (the fit is deterministic: the same result). Its
    final polish has :data:`TRIAL_FIT_NFEV` evaluations per parameter."""
    key = (model, band, None if start is None else tuple(start.items()),
           data.f_hz.tobytes(), data.h[i].tobytes(), data.se_db[i].tobytes(),
           data.se_deg[i].tobytes())
    with _TRIAL_FITS_LOCK:
        fit = _TRIAL_FITS.get(key)
    if fit is None:
        fit = fit_response(model, data.f_hz, data.h[i], se_db=data.se_db[i],
                           se_deg=data.se_deg[i], band=band, x0=start,
                           global_search=start is None, strict=False, intervals=False,
                           second_opinion=False,
                           max_nfev=TRIAL_FIT_NFEV * len(model.param_names))
        with _TRIAL_FITS_LOCK:
            while len(_TRIAL_FITS) >= _TRIAL_FITS_KEPT:
                del _TRIAL_FITS[next(iter(_TRIAL_FITS))]
            _TRIAL_FITS[key] = fit
    return fit


def screen_starts(model, data: AxisData, sel, combos, prob: JointProblem, keep: int = REFINE_BEST,
                  nfev: int = START_SCREEN_NFEV,
                  by_subject: Mapping[str, Mapping[str, float]] | None = None,
                  briefs: dict[bytes, blocklsq.BlockResult] | None = None) -> np.ndarray:
    """Short fits of every (base, start) pair on a spread-out subset of the trials;
    returns the full starting vectors built from the ``keep`` best, less those whose cost
    exceeds :data:`START_GAP` times the best one's (their effect values,
    and the per-subject values of the subset's subjects, from the short fit; the other
    subjects' from ``by_subject``).

    ``briefs``: filled with the short fit of each returned start that is one (the
    subset is every trial, and the start is the pair's own: no effect value moved),
    by the start's bytes; that short fit watched :func:`refine`'s ``ftol``, so the
    refinement goes on from it (:func:`refine`'s ``brief``)."""
    T = data.h.shape[0]
    idx = unique(np.linspace(0, T - 1, min(T, START_SCREEN_TRIALS)).round().astype(int))
    # on every trial, the short fits are of the problem itself: a refinement may go on
    # from one
    whole = idx.size == T
    sprob = prob if whole else JointProblem(model, data.subset(idx), sel, prob.varying)
    scored = []
    tried: dict[bytes, blocklsq.BlockResult] = {}
    for b, st in combos:
        # combinations that pack to the same start (e.g. a Levy row that is the given
        # row on every trial) have the same short fit: made once
        x = sprob.pack(b[idx], st, by_subject)
        r = tried.get(x.tobytes())
        if r is None:
            # only its cost and end are used (not the blocks of JᵀJ at the end), and
            # on every trial where the refinement would stop
            r = tried[x.tobytes()] = sprob.solve(
                x, nfev, final_normal=False,
                watch_ftol=refine_ftol(prob, x.size) if whole else None)
        scored.append((r.cost, b, st, r.x, x, r))
    scored.sort(key=lambda t: t[0])
    out = []
    for cost, b, st, xs, x, r in scored[:keep]:
        if cost > START_GAP * scored[0][0]:     # far behind the best: not refined
            break
        if not prob.varying:
            x0 = prob.pack(b, st)
            if prob.k:
                x0[-prob.k:] = xs[-prob.k:]
        else:
            shared, subs = sprob.effect_values(xs)
            x0 = prob.pack(b, {**st, **shared}, {**(by_subject or {}), **subs})
        if whole and briefs is not None and x0.tobytes() == x.tobytes():
            briefs[x0.tobytes()] = r
        out.append(x0)
    return out


def _effect_ci(prob: JointProblem, res) -> tuple[dict, dict]:
    """95 % intervals of the effect parameters from JᵀJ (Schur complement):
    {name: value} of the shared ones and {(subject, name): value} of the varying ones,
    lower and upper."""
    if not prob.k:
        return {}, {}
    m, p = 2 * prob.f.size * prob.T, res.x.size       # residuals: dB and deg of each trial
    s2 = 2 * res.cost / max(m - p, 1)
    K = prob.K
    var = s2 * np.diag(blocklsq.normal_covariance(*res.normal, prob.cols))
    half = Z_975 * np.sqrt(np.maximum(var, 0))
    z = res.x[-K:]
    sp = prob.space
    zlo, zhi = sp.zlo[prob.nb:][prob.local], sp.zhi[prob.nb:][prob.local]
    lo_t, hi_t = {}, {}
    for bound, out in ((np.clip(z - half, zlo, zhi), lo_t), (np.clip(z + half, zlo, zhi), hi_t)):
        if prob.cols is None:
            full = np.tile(sp.zlo, 1).astype(float)
            full[prob.nb:] = bound
            th = sp.to_theta(full)[prob.nb:]
            out.update({n: float(v) for n, v in zip(prob.effect_names, th, strict=True)})
            continue
        full = np.tile(sp.zlo, (prob.T, 1)).astype(float)
        full[:, prob.nb:] = bound[prob.cols]
        th = sp.to_theta(full)[:, prob.nb:]
        for j, n in enumerate(prob.effect_names):
            if n in prob.varying:
                for i, subj in enumerate(prob.trial_subjects):
                    out[(subj, n)] = float(th[i, j])
            else:
                out[n] = float(th[0, j])
    return lo_t, hi_t
