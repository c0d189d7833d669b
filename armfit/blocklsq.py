"""Bounded nonlinear least squares for block-arrow problems.

The joint fits of the diagnosis (:mod:`armfit.diagnosis`) have T trials, each with its own
``nb`` parameters, and ``k`` parameters shared by every trial. Their residual vector is
trial-major (T blocks of m residuals) and their Jacobian has a block-arrow shape::

    J = [ Jb_1            Js_1 ]
        [       Jb_2      Js_2 ]
        [            ...  ...  ]
        [            Jb_T Js_T ]

so the Gauss-Newton normal equations [[A, B], [Bᵀ, C]] δ = −g have a block-diagonal A
(T blocks of nb × nb). :func:`solve` eliminates the per-trial blocks (the Schur
complement S = C − Σ Bᵢᵀ Aᵢ⁻¹ Bᵢ, k × k) and solves each step exactly in
O(T·m·(nb + k)²) operations, vectorised over the trials, where a general sparse solver
iterates in Python.

**Grouped shared parameters.** A shared column may belong to a group of trials only
(a parameter with one value per subject, the subject's trials its group): then trial
``i``'s Jacobian holds ``kl`` local shared columns, and ``cols[i]`` (T, kl) names the
global shared parameters (0 … K − 1) they are. C and the Schur complement are summed
over the trials into K × K; every step is still solved exactly, the memory of the
Jacobian stays (T, m, kl), not (T, m, K). Without ``cols`` every trial's local columns
are the K shared ones (the code path, and the bits, of the plain block-arrow problem).

The method is the trust-region-reflective algorithm of
:func:`scipy.optimize.least_squares` (``method="trf"``) with every step solved exactly;
its termination tests and statuses are those of that function (``ftol``, ``xtol``,
``gtol``, ``max_nfev``; status 0 when the budget is spent).

**Memory.** The method needs the Jacobian only through the blocks of JᵀJ and Jᵀr: the
step is solved from them, and the model of the cost along a step (½‖J_h s‖²) is
sᵀ(J_hᵀJ_h)s from the same blocks. A caller that gives those blocks directly
(``normal``: made a few trials at a time) never holds the Jacobian, which is as large as
the residuals times the parameters of a trial; its memory is that of the residuals.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from armfit import _lapack

__all__ = ["BlockResult", "Groups", "Normal", "Resume", "normal_blocks", "normal_covariance",
           "solve"]

#: Residual function: x (T·nb + k,) -> r (T·m,), trial-major.
Fun = Callable[[np.ndarray], np.ndarray]
#: Jacobian blocks: x -> (Jb (T, m, nb), Js (T, m, k)).
Jac = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
#: The blocks of JᵀJ and Jᵀr (:func:`normal_blocks`): A (T, nb, nb), B (T, nb, kl),
#: C (K, K), gb (T, nb), gs (K,).
Normal = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
#: The blocks at x whose residuals are r (T, m): (x, r) -> Normal.
NormalFun = Callable[[np.ndarray, np.ndarray], Normal]


@dataclass(frozen=True)
class BlockResult:
    """The solution: ``x``, ``cost`` = ½‖r‖², the residuals ``fun`` and the blocks of
    JᵀJ at ``x`` (``normal``: A (T, nb, nb), B (T, nb, kl), C (K, K); enough for
    :func:`normal_covariance`; None when :func:`solve` was told not to make them at the
    end); ``status`` as :func:`scipy.optimize.least_squares` (0: evaluation budget
    spent; 1: gtol, 2: ftol, 3: xtol); ``nfev`` residual evaluations."""

    x: np.ndarray
    cost: float
    fun: np.ndarray
    normal: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    status: int
    nfev: int
    #: Given ``watch_ftol`` to :func:`solve`: the result the same run with ``ftol =
    #: watch_ftol`` (and any larger budget) returns, where it stops within this run's
    #: evaluations; else None.
    watched: BlockResult | None = None
    #: Where this run ended by its budget (status 0): the state a run with a larger
    #: budget has at that point (:func:`solve`'s ``resume``); else None.
    state: Resume | None = None


@dataclass(frozen=True)
class Resume:
    """The state of :func:`solve` at the end of its budget: ``x``, its residuals ``r`` and
    ``cost``, the blocks at ``x`` (:data:`Normal`; None when not made yet), the trust
    radius ``delta``, the last α and the evaluations made. Resumed, the run goes on
    exactly as one run with the larger budget would have, bit for bit."""

    x: np.ndarray
    r: np.ndarray
    cost: float
    blocks: Normal | None
    delta: float
    alpha: float
    nfev: int


class Groups:
    """Where each trial's local shared columns go: ``cols`` (T, kl) global indices of
    the K shared parameters (see the module docstring)."""

    def __init__(self, cols: np.ndarray, K: int):
        self.cols = np.asarray(cols, dtype=np.intp)
        self.K = int(K)

    def add_vectors(self, v: np.ndarray) -> np.ndarray:
        """Σ over trials of per-trial local vectors v (T, kl), scattered to (K,)."""
        out = np.zeros(self.K)
        np.add.at(out, self.cols, v)
        return out

    def add_matrices(self, m: np.ndarray) -> np.ndarray:
        """Σ over trials of per-trial local matrices m (T, kl, kl), scattered to (K, K)."""
        out = np.zeros((self.K, self.K))
        np.add.at(out, (self.cols[:, :, None], self.cols[:, None, :]), m)
        return out

    def take(self, v: np.ndarray) -> np.ndarray:
        """The global vector v (K,) seen by each trial, (T, kl)."""
        return v[self.cols]


def normal_blocks(chunks, n_trials: int, groups: Groups | None = None) -> Normal:
    """The blocks of JᵀJ and Jᵀr from the Jacobian given a few trials at a time.

    Parameters
    ----------
    chunks : iterable of (rows, jb, js, r)
        ``rows`` a slice of the trials, ``jb`` (t, m, nb) and ``js`` (t, m, kl) their
        Jacobian blocks, ``r`` (t, m) their residuals; every trial once.
    n_trials : int
        T.
    groups : Groups, optional
        Grouped shared parameters (the module docstring); C and gs are then global.

    Returns
    -------
    Normal
        A (T, nb, nb), B (T, nb, kl) per trial (B in its local shared columns), C (K, K)
        and gs (K,) summed over the trials, gb (T, nb); K = kl without ``groups``.
    """
    A = B = gb = Ct = gst = None
    for rows, jb, js, r in chunks:
        if A is None:
            nb, kl = jb.shape[2], js.shape[2]
            A, B = np.empty((n_trials, nb, nb)), np.empty((n_trials, nb, kl))
            gb = np.empty((n_trials, nb))
            Ct, gst = np.empty((n_trials, kl, kl)), np.empty((n_trials, kl))
        A[rows] = _lapack.einsum("tmp,tmq->tpq", jb, jb)
        B[rows] = _lapack.einsum("tmp,tmk->tpk", jb, js)
        gb[rows] = _lapack.einsum("tmp,tm->tp", jb, r)
        Ct[rows] = _lapack.einsum("tmk,tml->tkl", js, js)
        gst[rows] = _lapack.einsum("tmk,tm->tk", js, r)
    if groups is None:
        return A, B, Ct.sum(axis=0), gb, gst.sum(axis=0)
    return A, B, groups.add_matrices(Ct), gb, groups.add_vectors(gst)


def _normal(jb: np.ndarray, js: np.ndarray, r: np.ndarray, groups: Groups | None = None
            ) -> Normal:
    """:func:`normal_blocks` of the whole Jacobian (jb (T, m, nb), js (T, m, kl)) and the
    residuals r (T, m)."""
    return normal_blocks([(slice(None), jb, js, r)], jb.shape[0], groups)


class _Quadratic:
    """The model q(p) = ½‖J_h p‖² + ½pᵀdiag(c_h)p + g_hᵀp of a trust-region subproblem in
    the scaled ("hat") variables, as :func:`_select_step` uses it: a subclass gives
    :attr:`g_h` and :attr:`c_h` (flat, one entry per parameter) and either :meth:`jdot`
    (J_h·p, any shape) or its own :meth:`quadratic_1d` (:class:`_Scaled`: from JᵀJ)."""

    g_h: np.ndarray
    c_h: np.ndarray

    def jdot(self, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def quadratic_1d(self, s: np.ndarray, s0: np.ndarray | None = None):
        """(a, b, c) of q(s0 + t·s) = a t² + b t + c."""
        g, c = self.g_h, self.c_h
        js = self.jdot(s)
        a = 0.5 * (float((js * js).sum()) + float(s @ (c * s)))
        b = float(g @ s)
        cc = 0.0
        if s0 is not None:
            j0 = self.jdot(s0)
            b += float((js * j0).sum()) + float(s0 @ (c * s))
            cc = 0.5 * (float((j0 * j0).sum()) + float(s0 @ (c * s0))) + float(g @ s0)
        return a, b, cc

    def value(self, p: np.ndarray) -> float:
        """q(p)."""
        a, b, _ = self.quadratic_1d(p)
        return a + b


class _Scaled(_Quadratic):
    """The trust-region subproblem of one iteration in the scaled ("hat") variables of
    the trust-region-reflective method: J_h = J·diag(d), H_h = J_hᵀJ_h + diag(c),
    g_h = d·g, blocks as :func:`normal_blocks` (per-trial part first, then the shared
    one). ‖J_h s‖² is sᵀ(J_hᵀJ_h)s from the same blocks: the Jacobian is not needed."""

    def __init__(self, A, B, C, gb, gs, db, ds, cb, cs, groups: Groups | None = None):
        self.db, self.ds, self.cb, self.cs = db, ds, cb, cs
        self.groups = groups
        self.A = A * db[:, :, None] * db[:, None, :]
        dsl = ds[None, None, :] if groups is None else groups.take(ds)[:, None, :]
        self.B = B * db[:, :, None] * dsl
        self.C = C * np.outer(ds, ds)
        self.gb, self.gs = gb * db, gs * ds
        self.T, self.nb = gb.shape
        self.k = gs.size
        # (α, A + αI, its solve of B, the Schur complement) of the last solve, for the
        # next solve at the same α
        self._kept = None
        self._eye = np.eye(self.nb)

    def _local(self, vs: np.ndarray) -> np.ndarray:
        """The shared part ``vs`` (K,) as each trial's local columns see it, (T, kl)."""
        if self.groups is None:
            return np.broadcast_to(vs, (self.T, vs.size))
        return self.groups.take(vs)

    def hdot(self, p: np.ndarray, q: np.ndarray) -> float:
        """pᵀ(J_hᵀJ_h)q from the blocks (pᵀBq and qᵀBp made once when q is p)."""
        pb, ps = self._split(p)
        qb, qs = (pb, ps) if q is p else self._split(q)
        out = float((pb * _lapack.einsum("tpq,tq->tp", self.A, qb)).sum())
        if self.k:
            cross = float((pb * _lapack.einsum("tpk,tk->tp", self.B, self._local(qs))).sum())
            out += cross
            out += cross if q is p else float(
                (qb * _lapack.einsum("tpk,tk->tp", self.B, self._local(ps))).sum())
            out += float(ps @ self.C @ qs)
        return out

    def quadratic_1d(self, s: np.ndarray, s0: np.ndarray | None = None):
        """(a, b, c) of q(s0 + t·s) = a t² + b t + c."""
        g, c = self.g_h, self.c_h
        a = 0.5 * (self.hdot(s, s) + float(s @ (c * s)))
        b = float(g @ s)
        cc = 0.0
        if s0 is not None:
            b += self.hdot(s, s0) + float(s0 @ (c * s))
            cc = 0.5 * (self.hdot(s0, s0) + float(s0 @ (c * s0))) + float(g @ s0)
        return a, b, cc

    def solve(self, alpha: float, rb: np.ndarray, rs: np.ndarray):
        """y = (H_h + αI)⁻¹ (rb, rs) by eliminating the per-trial blocks.

        The blocks at α (the per-trial A + αI, their solves of B, the Schur complement)
        are kept for the next call at the same α, which solves only its own right-hand
        side: Moré's iteration (:meth:`trust_region`) asks twice at each α. The numbers
        are those made afresh: LAPACK's solve of several right-hand sides treats each
        column alone, so a column solved beside B (the first call) or beside a copy of
        itself (the next) comes out the same to the bit (checked over per-trial systems
        of 1-1,350 trials, 2-12 right-hand sides, condition numbers up to 1e12); one
        right-hand side alone would take another LAPACK path, hence the copy."""
        Air = None
        if self._kept is not None and self._kept[0] == alpha:
            _, Al, AiB, S = self._kept
        else:
            Al = self.A + self._eye * (self.cb + alpha)[:, None, :]
            AiB = S = None
            if self.k:
                Cl = self.C + np.diag(self.cs + alpha)
                kl = self.B.shape[2]
                sol = _lapack.linalg_solve(Al, np.concatenate([self.B, rb[..., None]], axis=2))
                AiB, Air = sol[..., :kl], sol[..., kl]
                S = Cl - (_lapack.einsum("tpk,tpl->kl", self.B, AiB) if self.groups is None else
                          self.groups.add_matrices(_lapack.einsum("tpk,tpl->tkl", self.B, AiB)))
            self._kept = (alpha, Al, AiB, S)
        if self.k == 0:
            return _lapack.linalg_solve(Al, rb[..., None])[..., 0], np.zeros(0)
        if Air is None:     # the blocks were kept: this right-hand side beside a copy
            pair = np.empty((*rb.shape, 2))    # np.stack([rb, rb], axis=2), made directly
            pair[..., 0] = rb
            pair[..., 1] = rb
            Air = _lapack.linalg_solve(Al, pair)[..., 0]
        g = self.groups
        if g is None:
            ys = _lapack.linalg_solve(S, rs - _lapack.einsum("tpk,tp->k", self.B, Air))
            return Air - AiB @ ys, ys
        ys = _lapack.linalg_solve(S, rs - g.add_vectors(_lapack.einsum("tpk,tp->tk", self.B, Air)))
        return Air - _lapack.einsum("tpk,tk->tp", AiB, g.take(ys)), ys

    @property
    def g_h(self) -> np.ndarray:
        return np.concatenate([self.gb.ravel(), self.gs])

    @property
    def c_h(self) -> np.ndarray:
        return np.concatenate([self.cb.ravel(), self.cs])

    def _split(self, v: np.ndarray):
        return v[: self.T * self.nb].reshape(self.T, self.nb), v[self.T * self.nb:]

    def trust_region(self, delta: float, alpha: float) -> tuple[np.ndarray, float]:
        """The minimiser p_h of q within ‖p_h‖ ≤ ``delta``: the Gauss-Newton step when it
        fits, else p(α) = −(H_h + αI)⁻¹g_h with ‖p(α)‖ = ``delta`` to 1 %, α by Moré's
        Newton iteration on ‖p(α)‖ (as :func:`scipy.optimize.least_squares`'s exact
        solver, with a solve in place of the SVD). ``alpha``: the previous α, the
        first guess. Returns (p_h, α).

        Its solves (:func:`armfit._lapack.linalg_solve`) hold ``numpy.linalg.solve``'s error
        state (:func:`armfit._lapack.solving`): the systems, A + αI with α > 0 and
        their Schur complement, are positive definite, and one found singular raises
        LinAlgError as ``numpy.linalg.solve`` would."""
        with _lapack.solving():
            return self._trust_region(delta, alpha)

    def _trust_region(self, delta: float, alpha: float) -> tuple[np.ndarray, float]:
        gb, gs = -self.gb, -self.gs
        g_norm = float(np.sqrt((gb * gb).sum() + gs @ gs))
        if g_norm == 0.0:
            return np.zeros(self.T * self.nb + self.k), 0.0
        diag = np.concatenate([np.diagonal(self.A, axis1=1, axis2=2).ravel(),
                               np.diag(self.C) if self.k else np.zeros(0)])
        floor = 1e-12 * max(float(diag.max(initial=0.0)), 1e-300)
        pb, ps = self.solve(floor, gb, gs)
        norm = float(np.sqrt((pb * pb).sum() + ps @ ps))
        if np.isfinite(norm) and norm <= delta:
            return np.concatenate([pb.ravel(), ps]), 0.0
        lo, hi = 0.0, g_norm / delta
        if not lo < alpha < hi:
            alpha = max(1e-3 * hi, np.sqrt(lo * hi))
        for _ in range(10):
            if not lo < alpha < hi:
                alpha = max(1e-3 * hi, np.sqrt(lo * hi))
            pb, ps = self.solve(alpha, gb, gs)
            norm = float(np.sqrt((pb * pb).sum() + ps @ ps))
            phi = norm - delta
            if phi < 0:
                hi = alpha
            qb, qs = self.solve(alpha, pb, ps)
            phi_prime = -float((pb * qb).sum() + ps @ qs) / norm
            ratio = phi / phi_prime
            lo = max(lo, alpha - ratio)
            alpha -= (phi + delta) * ratio / delta
            if abs(phi) < 0.01 * delta:
                break
        p = np.concatenate([pb.ravel(), ps])
        return p * (delta / _lapack.norm(p)), alpha


def _to_bound(x, s, lower, upper) -> tuple[float, np.ndarray]:
    """Smallest t ≥ 0 with x + t·s on a bound, and which components hit it (±1)."""
    steps = np.full_like(x, np.inf)
    nz = s != 0
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        steps[nz] = np.maximum((lower - x)[nz] / s[nz], (upper - x)[nz] / s[nz])
    t = float(steps.min())
    return t, np.equal(steps, t) * np.sign(s).astype(int)


def _through_sphere(p: np.ndarray, s: np.ndarray, delta: float) -> float:
    """The t > 0 with ‖p + t·s‖ = ``delta``."""
    a, b, c = s @ s, p @ s, p @ p - delta ** 2
    disc = np.sqrt(max(b * b - a * c, 0.0))
    return float((-b + disc) / a) if a > 0 else np.inf


def _min_1d(a, b, lo, hi, c=0.0) -> tuple[float, float]:
    t = [lo, hi]
    if a != 0 and lo < -0.5 * b / a < hi:
        t.append(-0.5 * b / a)
    t = np.asarray(t, float)
    y = t * (a * t + b) + c
    i = int(np.argmin(y))
    return float(t[i]), float(y[i])


def _select_step(x, sub: _Quadratic, d, p_h, delta, lower, upper, theta):
    """The step of the trust-region-reflective method: the trust-region step if it stays
    in the box, otherwise the best of that step stopped short of the bound, its
    reflection off the bound, and the scaled steepest-descent step (Branch, Coleman &
    Li, SIAM J. Sci. Comput. 21, 1999). ``sub``: the subproblem's model (its J_h, g_h
    and diagonal), ``d`` the scaling, ``p_h`` the trust-region step (scaled), ``theta``
    the step-back factor from a bound. Returns (step, step_h, predicted reduction)."""
    p = d * p_h
    if ((x + p >= lower) & (x + p <= upper)).all():
        return p, p_h, -sub.value(p_h)
    stride, hits = _to_bound(x, p, lower, upper)
    r_h = p_h.copy()
    r_h[hits.astype(bool)] *= -1
    r = d * r_h
    p, p_h = p * stride, p_h * stride
    to_tr = _through_sphere(p_h, r_h, delta)
    to_bound, _ = _to_bound(x + p, r, lower, upper)
    r_stride = min(to_bound, to_tr)
    if r_stride > 0:
        lo = (1 - theta) * stride / r_stride
        hi = theta * to_bound if r_stride == to_bound else to_tr
    else:
        lo, hi = 0.0, -1.0
    if lo <= hi:
        a, b, c = sub.quadratic_1d(r_h, p_h)
        t, r_value = _min_1d(a, b, lo, hi, c)
        r_h = p_h + t * r_h
        r = d * r_h
    else:
        r_value = np.inf
    p, p_h = p * theta, p_h * theta
    p_value = sub.value(p_h)
    ag_h = -sub.g_h
    ag = d * ag_h
    to_tr = delta / _lapack.norm(ag_h)
    to_bound, _ = _to_bound(x, ag, lower, upper)
    ag_stride = theta * to_bound if to_bound < to_tr else to_tr
    a, b, _ = sub.quadratic_1d(ag_h)
    t, ag_value = _min_1d(a, b, 0.0, ag_stride)
    if p_value < r_value and p_value < ag_value:
        return p, p_h, -p_value
    if r_value < p_value and r_value < ag_value:
        return r, r_h, -r_value
    return t * ag, t * ag_h, -ag_value


def _strictly_inside(x, lower, upper) -> np.ndarray:
    """``x`` (any shape broadcasting with the bounds) with every value on or beyond a
    bound moved to the next float inside it."""
    x = np.where(x <= lower, np.nextafter(lower, upper), x)
    return np.where(x >= upper, np.nextafter(upper, lower), x)


def solve(fun: Fun, jac: Jac | None, x0: np.ndarray, lower: np.ndarray, upper: np.ndarray, *,
          n_trials: int, n_block: int, max_nfev: int = 200, ftol: float = 1e-8,
          xtol: float = 1e-8, gtol: float = 1e-8, cols: np.ndarray | None = None,
          normal: NormalFun | None = None, final_normal: bool = True,
          watch_ftol: float | None = None, resume: Resume | None = None) -> BlockResult:
    """Minimise ½‖fun(x)‖² over ``lower < x < upper`` for a block-arrow problem.

    The trust-region-reflective method of :func:`scipy.optimize.least_squares`
    (``method="trf"``, ``x_scale=1``, ``tr_solver="exact"``: Coleman-Li scaling near
    the bounds, the same step selection, radius updates and stopping tests), the
    subproblem solved by eliminating the per-trial blocks instead of an SVD.

    Parameters
    ----------
    fun : callable
        x (T·nb + k,) -> residuals (T·m,), trial-major: the first m belong to trial 0.
    jac : callable or None
        x -> (Jb (T, m, nb), Js (T, m, k)), the Jacobian's per-trial and shared blocks
        (None with ``normal``).
    x0 : ndarray
        Start, (T·nb + k,): the per-trial parameters trial by trial, then the shared ones;
        moved strictly inside the bounds.
    lower, upper : ndarray
        Finite bounds of every parameter (same shape as ``x0``).
    n_trials, n_block : int
        T and nb.
    max_nfev : int
        Budget of residual evaluations (the Jacobian calls are not counted).
    ftol, xtol, gtol : float
        Stop when a step lowers the cost by less than ``ftol``·cost (with a good
        agreement of the model), when it is below ``xtol``·(``xtol`` + ‖x‖), or when the
        scaled gradient's largest component is below ``gtol``.
    cols : ndarray of int, shape (T, kl), optional
        Grouped shared parameters (module docstring; ``jac`` returns Js (T, m, kl)).
    normal : callable, optional
        (x, r (T, m)) -> the blocks of JᵀJ and Jᵀr at x (:data:`Normal`, as
        :func:`normal_blocks` makes them), in place of ``jac``: the Jacobian is then
        never held whole (the module docstring's *Memory*).
    final_normal : bool
        False: when the evaluation budget ends with a step taken, the blocks at the
        new ``x`` are not made (the result's ``normal`` is then None and its status 0,
        even where that ``x``'s gradient would meet ``gtol``), for a caller that uses
        only ``x`` and ``cost`` (a brief try of a start). ``x``, ``cost`` and ``fun``
        are those of the default.
    watch_ftol : float, optional
        A larger ``ftol`` whose run this one follows: the result's ``watched`` is what
        the run with ``ftol = watch_ftol`` and the same start returns, where it stops
        within this run's evaluations; and where it does not, the result's ``state``
        resumes it. A brief try of a start so gives its refinement for nothing.
    resume : Resume, optional
        Go on from another run's ``state`` (``x0`` then unused) with this call's budget
        and tolerances: the result is that of one run from the first start.

    Returns
    -------
    BlockResult
    """
    T, nb = n_trials, n_block
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    size = np.size(x0) if resume is None else resume.x.size
    groups = None if cols is None else Groups(cols, size - T * nb)
    normal = normal or _from_jac(jac, groups)
    x, r, cost, blocks, delta, alpha, nfev = (
        _first_state(fun, normal, x0, lower, upper, T) if resume is None
        else _resumed_state(normal, resume, T))
    return _iterate(fun, normal, (x, r, cost, blocks, delta, alpha, nfev), lower, upper,
                    T, nb, groups, max_nfev, (ftol, xtol, gtol), final_normal, watch_ftol)


def _iterate(fun: Fun, normal: NormalFun, state: tuple, lower, upper, T: int, nb: int,
             groups: Groups | None, max_nfev: int, tols: tuple[float, float, float],
             final_normal: bool, watch_ftol: float | None) -> BlockResult:
    """:func:`solve`'s iterations from ``state`` (x, r, cost, blocks, trust radius, α,
    evaluations made) until a stop or the budget."""
    x, r, cost, blocks, delta, alpha, nfev = state
    ftol, xtol, gtol = tols
    status = 0
    watched: BlockResult | None = None
    watch_status = 0        # the watched run stops at the step being taken, so
    while True:
        A, B, C, gb, gs = blocks
        g = np.concatenate([gb.ravel(), gs])
        v, dv = _cl_scaling(x, g, lower, upper)
        g_norm = float(np.abs(g * v).max(initial=0.0))
        if watch_status and watched is None:
            watched = BlockResult(x, cost, r, blocks[:3], 1 if g_norm < gtol else watch_status,
                                  nfev)
        if g_norm < gtol:
            status = 1
        if status or nfev >= max_nfev:
            break
        d = np.sqrt(v)
        c = g * dv
        sub = _Scaled(A, B, C, gb, gs, d[: T * nb].reshape(T, nb), d[T * nb:],
                      c[: T * nb].reshape(T, nb), c[T * nb:], groups)
        theta = max(0.995, 1.0 - g_norm)
        actual = -1.0
        while actual <= 0 and nfev < max_nfev:
            p_h, alpha = sub.trust_region(delta, alpha)
            step, step_h, predicted = _select_step(x, sub, d, p_h, delta, lower, upper,
                                                   theta)
            x_new = _strictly_inside(x + step, lower, upper)
            r_new = fun(x_new)
            nfev += 1
            step_h_norm = _lapack.norm(step_h)
            cost_new = 0.5 * float(r_new @ r_new)
            if not np.isfinite(cost_new):
                delta = 0.25 * step_h_norm
                continue
            actual = cost - cost_new
            ratio, new_delta = _radius(actual, predicted, step_h_norm, delta)
            step_norm = _lapack.norm(step)
            small_f = actual < ftol * cost and ratio > 0.25
            small_x = step_norm < xtol * (xtol + _lapack.norm(x))
            if watch_ftol is not None and watched is None and not watch_status:
                watch_status = _stop_status(actual < watch_ftol * cost and ratio > 0.25,
                                            small_x)
                if watch_status and actual <= 0:       # it stops where it is
                    watched = BlockResult(x, cost, r, blocks[:3], watch_status, nfev)
            if small_f or small_x:
                status = _stop_status(small_f, small_x)
                break
            if new_delta > 0:
                alpha *= delta / new_delta
            delta = new_delta
        if actual > 0:
            x, r, cost = x_new, r_new, cost_new
            sub = blocks = None    # the old blocks go before the new ones are made
            if (not final_normal and not status and nfev >= max_nfev
                    and (watch_ftol is None or watched is not None or not watch_status)):
                return BlockResult(x, cost, r, None, 0, nfev, watched,
                                   Resume(x, r, cost, None, delta, alpha, nfev))
            blocks = normal(x, r.reshape(T, -1))
    if watch_ftol is not None and watched is None and status:
        watched = BlockResult(x, cost, r, blocks[:3], status, nfev)   # stops here too
    state = None if status else Resume(x, r, cost, blocks, delta, alpha, nfev)
    return BlockResult(x, cost, r, blocks[:3], status, nfev, watched, state)


def _first_state(fun: Fun, normal: NormalFun, x0, lower, upper, T: int) -> tuple:
    """:func:`solve`'s state at ``x0`` (moved strictly inside the bounds): x, r, cost,
    the blocks, the first trust radius, α = 0 and one evaluation."""
    x = _strictly_inside(np.clip(np.asarray(x0, float), lower, upper), lower, upper)
    r = fun(x)
    blocks = normal(x, r.reshape(T, -1))
    v, _ = _cl_scaling(x, np.concatenate([blocks[3].ravel(), blocks[4]]), lower, upper)
    return (x, r, 0.5 * float(r @ r), blocks, _lapack.norm(x / np.sqrt(v)) or 1.0,
            0.0, 1)


def _resumed_state(normal: NormalFun, resume: Resume, T: int) -> tuple:
    """:func:`solve`'s state from ``resume`` (the blocks made if it has none)."""
    blocks = resume.blocks
    if blocks is None:
        blocks = normal(resume.x, resume.r.reshape(T, -1))
    return (resume.x, resume.r, resume.cost, blocks, resume.delta, resume.alpha,
            resume.nfev)


def _stop_status(small_f: bool, small_x: bool) -> int:
    """The status of a stop by ``ftol`` (2), ``xtol`` (3) or both (4); 0: no stop."""
    return 4 if small_f and small_x else 2 if small_f else 3 if small_x else 0


def _from_jac(jac: Jac, groups: Groups | None) -> NormalFun:
    """:func:`solve`'s ``normal`` from the Jacobian's blocks ``jac`` (all trials at once)."""
    def normal(x: np.ndarray, r: np.ndarray) -> Normal:
        return _normal(*jac(x), r, groups)
    return normal


def _radius(actual: float, predicted: float, step_h_norm: float, delta: float
            ) -> tuple[float, float]:
    """The agreement ratio of a step (actual / predicted reduction) and the trust radius
    it gives (scipy's ``update_tr_radius``)."""
    if predicted > 0:
        ratio = actual / predicted
    else:
        ratio = 1.0 if predicted == actual == 0 else 0.0
    if ratio < 0.25:
        return ratio, 0.25 * step_h_norm
    if ratio > 0.75 and step_h_norm > 0.95 * delta:
        return ratio, 2.0 * delta
    return ratio, delta


def _cl_scaling(x, g, lower, upper) -> tuple[np.ndarray, np.ndarray]:
    """Coleman-Li scaling: v is the distance to the bound the gradient points towards
    (1 without one), dv its derivative's sign; ``x`` and ``g`` of any shape broadcasting
    with the bounds (a row per problem, say)."""
    up = (g < 0) & np.isfinite(upper)
    low = (g > 0) & np.isfinite(lower)
    with np.errstate(invalid="ignore"):
        v = np.where(up, upper - x, np.where(low, x - lower, 1.0))
    return v, np.where(up, -1.0, np.where(low, 1.0, 0.0))


def normal_covariance(A: np.ndarray, B: np.ndarray, C: np.ndarray,
                      cols: np.ndarray | None = None) -> np.ndarray:
    """The shared parameters' block of (JᵀJ)⁺, (K, K), from the blocks of JᵀJ (A (T, nb,
    nb), B (T, nb, kl), C (K, K): :attr:`BlockResult.normal`): the inverse of the Schur
    complement C − Σ Bᵢᵀ Aᵢ⁺ Bᵢ (pseudo-inverses, so a parameter the data do not
    determine gets a large variance instead of an error). Multiply by σ² for a
    covariance. ``cols``: grouped shared parameters (:func:`solve`'s ``cols``)."""
    groups = None if cols is None else Groups(cols, C.shape[0])
    Ai = np.linalg.pinv(A, rcond=1e-12)
    if groups is None:
        S = C - _lapack.einsum("tpk,tpq,tql->kl", B, Ai, B)
    else:
        S = C - groups.add_matrices(_lapack.einsum("tpk,tpq,tql->tkl", B, Ai, B))
    return np.linalg.pinv(S, rcond=1e-12)
