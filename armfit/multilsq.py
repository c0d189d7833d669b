"""Many small bounded nonlinear least-squares problems solved together.

The global search of :func:`armfit.fitting.fit_response` refines a dozen starts of the
same problem, and its band jackknife refits the same problem without each band: many
independent problems of the same size (p ≤ ~10 parameters, a few hundred residuals),
each a fraction of a millisecond of arithmetic. Solved one after the other, each
iteration's Python overhead costs more than its arithmetic. :func:`solve_many` runs them
in lock-step, every problem's iteration vectorised over the problems still running:
one evaluation of the residuals (and of the Jacobian) for all of them, one batched SVD.

Each problem follows its own path exactly as :func:`scipy.optimize.least_squares`
(``method="trf"``, ``x_scale=1``, ``tr_solver="exact"``, no loss function) would take
it: its own trust radius and Levenberg-Marquardt parameter, Coleman-Li scaling, the same
step selection (trust-region step, its reflection off a bound, or the scaled steepest
descent; :mod:`armfit.blocklsq`'s, with its Coleman-Li scaling and the step back inside
the bounds, which the joint fits use too), radius updates, termination tests and
statuses, and its own evaluation budget. Only the rounding differs (a batched SVD,
batched products): each problem takes the same number of evaluations and stops
converged or not alike, at an end point within the tolerances asked of scipy's
(``tests/test_multilsq.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from armfit._lapack import einsum, row_norms, svd
from armfit.blocklsq import _cl_scaling, _Quadratic, _select_step, _strictly_inside

__all__ = ["ManyResult", "solve_many"]

_EPS = np.finfo(float).eps

#: Residuals of several problems: (X (k, n) points, rows (k,) the problems' indices) ->
#: residuals (k, m).
FunMany = Callable[[np.ndarray, np.ndarray], np.ndarray]
#: Jacobians of several problems: (X (k, n), rows (k,)) -> (k, m, n).
JacMany = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class ManyResult:
    """The solutions of :func:`solve_many`, one row per problem: ``x`` (N, n), ``cost``
    ½‖r‖² (N,), residuals ``fun`` (N, m), ``status`` (N,) as
    :func:`scipy.optimize.least_squares` (0: evaluation budget spent; 1: gtol, 2: ftol,
    3: xtol, 4: ftol and xtol) and ``nfev`` (N,) residual evaluations."""

    x: np.ndarray
    cost: np.ndarray
    fun: np.ndarray
    status: np.ndarray
    nfev: np.ndarray


def _inside_start(x: np.ndarray, lb: np.ndarray, ub: np.ndarray,
                  rstep: float = 1e-10) -> np.ndarray:
    """Starts moved inside the bounds as scipy's ``least_squares`` moves them
    (``make_strictly_feasible``): at least ``rstep`` (relative) from a bound."""
    lower_dist, upper_dist = x - lb, ub - x
    lo = lower_dist <= np.minimum(upper_dist, rstep * np.maximum(1, np.abs(lb)))
    hi = upper_dist <= np.minimum(lower_dist, rstep * np.maximum(1, np.abs(ub)))
    x_new = np.where(lo, lb + rstep * np.maximum(1, np.abs(lb)), x)
    x_new = np.where(hi, ub - rstep * np.maximum(1, np.abs(ub)), x_new)
    return np.where((x_new < lb) | (x_new > ub), 0.5 * (lb + ub), x_new)


def _tr_steps(uf, s, V, delta, alpha, m: int, rtol: float = 0.01, max_iter: int = 10):
    """The trust-region steps p_h (k, n) and Levenberg-Marquardt parameters α of k
    problems from the SVDs of their scaled augmented Jacobians (``uf`` = Uᵀf (k, n),
    singular values ``s`` (k, n), right singular vectors ``V`` (k, n, n)): the
    Gauss-Newton step when it fits in the radius ``delta``, else Moré's iteration on
    ‖p(α)‖ = delta to ``rtol`` (scipy's ``solve_lsq_trust_region``, row by row).
    Called under :func:`solve_many`'s error state (division by zero and invalid
    operations not reported: a rank-deficient row's NaN is not chosen)."""
    n = s.shape[1]
    suf = s * uf
    full_rank = (s[:, -1] > _EPS * m * s[:, 0]) if m >= n else np.zeros(len(s), bool)
    p_gn = -einsum("kij,kj->ki", V, np.where(full_rank[:, None], uf / s, 0.0))
    gn = full_rank & (row_norms(p_gn) <= delta)
    if gn.all():
        return p_gn, np.zeros(len(s))

    def phi_and_derivative(a):
        denom = s ** 2 + a[:, None]
        p_norm = row_norms(suf / denom)
        return p_norm - delta, -(suf ** 2 / denom ** 3).sum(axis=1) / p_norm

    a_hi = row_norms(suf) / delta
    phi0, dphi0 = phi_and_derivative(np.zeros(len(s)))
    a_lo = np.where(full_rank, -phi0 / dphi0, 0.0)
    reset = ~full_rank & (alpha == 0)
    a = np.where(reset, np.maximum(0.001 * a_hi, np.sqrt(a_lo * a_hi)), alpha)
    live = ~gn
    for _ in range(max_iter):
        if not live.any():
            break
        out = (a < a_lo) | (a > a_hi)
        a = np.where(live & out, np.maximum(0.001 * a_hi, np.sqrt(a_lo * a_hi)), a)
        phi, dphi = phi_and_derivative(a)
        a_hi = np.where(live & (phi < 0), a, a_hi)
        ratio = phi / dphi
        a_lo = np.where(live, np.maximum(a_lo, a - ratio), a_lo)
        a = np.where(live, a - (phi + delta) * ratio / delta, a)
        live = live & ~(np.abs(phi) < rtol * delta)
    p = -einsum("kij,kj->ki", V, suf / (s ** 2 + a[:, None]))
    p *= (delta / row_norms(p))[:, None]
    return np.where(gn[:, None], p_gn, p), np.where(gn, 0.0, a)


class _Dense(_Quadratic):
    """One fit's trust-region subproblem, as :func:`armfit.blocklsq._select_step` takes
    it: J_h (m, n), g_h and the diagonal c_h (n,)."""

    def __init__(self, J_h: np.ndarray, g_h: np.ndarray, c_h: np.ndarray):
        self.J_h, self.g_h, self.c_h = J_h, g_h, c_h

    def jdot(self, p: np.ndarray) -> np.ndarray:
        return self.J_h @ p


def solve_many(fun: FunMany, jac: JacMany, x0: np.ndarray, lb: np.ndarray,
               ub: np.ndarray, *, max_nfev: int, ftol: float = 1e-8, xtol: float = 1e-8,
               gtol: float = 1e-8) -> ManyResult:
    """Minimise ½‖r_i(x)‖² over lb ≤ x ≤ ub for N independent problems at once.

    Each problem i behaves as ``scipy.optimize.least_squares(r_i, x0[i], jac=J_i,
    bounds=(lb, ub), method="trf", x_scale=1.0, max_nfev=max_nfev, ftol=ftol,
    xtol=xtol, gtol=gtol)`` (see the module docstring), but for one status: a step
    that stops the fit by ``ftol`` or ``xtol`` keeps that status, where scipy evaluates
    the Jacobian at the new point once more and reports ``gtol`` (1) when its gradient
    is also that small. No Jacobian is evaluated at a point where a fit stops.

    Parameters
    ----------
    fun : callable
        ``fun(X, rows)``: the residuals (k, m) of the problems ``rows`` (k,) at their
        points ``X`` (k, n); must be finite at the starts.
    jac : callable
        ``jac(X, rows)``: their Jacobians (k, m, n).
    x0 : ndarray, shape (N, n)
        Starts, inside the bounds (moved strictly inside, as scipy does).
    lb, ub : ndarray, shape (n,)
        Finite bounds, the same for every problem.
    max_nfev : int
        Residual evaluations per problem (the Jacobian's not counted).
    ftol, xtol, gtol : float
        scipy's termination tolerances.

    Returns
    -------
    ManyResult
    """
    lb, ub = np.asarray(lb, float), np.asarray(ub, float)
    st = _Fits(fun, jac, _inside_start(np.asarray(x0, float), lb, ub), lb, ub)
    # one error state for every iteration (a step's ratios divide by zero where a fit
    # predicts no reduction; the where()s choose the other branch there)
    with np.errstate(divide="ignore", invalid="ignore"):
        while st.ids.size:
            st.begin_iterations(gtol, max_nfev)
            # a fit whose budget ran out inside an outer iteration stops (status 0)
            st.retire(st.nfev >= max_nfev)
            if st.ids.size:
                st.try_steps(ftol, xtol)
    return st.out


class _Fits:
    """The state of :func:`solve_many`'s fits still running, one row each (scipy's
    ``trf`` variables: point, residuals, Jacobian, gradient, cost, radius Δ, α, and those
    of the current outer iteration: scaling d, diag_h, g_h, θ and the SVD of the
    augmented scaled Jacobian); ``ids`` their rows in ``x0``. A fit that stops is
    written to :attr:`out` and its row dropped, so that every step works on the running
    fits' rows without gathering them."""

    def __init__(self, fun: FunMany, jac: JacMany, x: np.ndarray, lb, ub):
        self.fun, self.jac, self.lb, self.ub = fun, jac, lb, ub
        N, n = x.shape
        self.ids = np.arange(N)
        self.x = x
        self.f = np.asarray(fun(x, self.ids), float)
        self.m = self.f.shape[1]
        self.J = np.asarray(jac(x, self.ids), float)
        self.nfev = np.ones(N, int)
        self.cost = 0.5 * einsum("km,km->k", self.f, self.f)
        self.g = einsum("kmn,km->kn", self.J, self.f)
        v, _ = _cl_scaling(x, self.g, lb, ub)
        self.delta = row_norms(x / np.sqrt(v))
        self.delta[self.delta == 0] = 1.0
        self.alpha = np.zeros(N)
        self.status = np.zeros(N, int)
        self.fresh = np.ones(N, bool)     # starting an outer iteration
        self.d, self.diag_h, self.g_h = (np.empty((N, n)) for _ in range(3))
        self.theta = np.empty(N)
        self.uf, self.sv = np.empty((N, n)), np.empty((N, n))
        self.V = np.empty((N, n, n))
        self.out = ManyResult(x.copy(), self.cost.copy(), self.f.copy(), np.zeros(N, int),
                              np.ones(N, int))

    _ROWS = ("x", "f", "J", "nfev", "cost", "g", "delta", "alpha", "status", "fresh", "d",
             "diag_h", "g_h", "theta", "uf", "sv", "V", "ids")

    def retire(self, stop: np.ndarray) -> None:
        """Write the fits ``stop`` (a mask of the running rows) to :attr:`out` and drop
        their rows."""
        if not stop.any():
            return
        o, i = self.out, self.ids[stop]
        o.x[i], o.cost[i], o.fun[i] = self.x[stop], self.cost[stop], self.f[stop]
        o.status[i], o.nfev[i] = self.status[stop], self.nfev[stop]
        keep = ~stop
        for name in self._ROWS:
            setattr(self, name, getattr(self, name)[keep])

    def begin_iterations(self, gtol: float, max_nfev: int) -> None:
        """Outer iterations of the fits that start one: the gtol and budget tests, then
        the scaling and the SVD of [J·d; diag(diag_h)^½] (scipy's ``trf_bounds`` loop
        head)."""
        new = np.flatnonzero(self.fresh)
        if not new.size:
            return
        self.fresh[new] = False
        v, dv = _cl_scaling(self.x[new], self.g[new], self.lb, self.ub)
        g_norm = np.abs(self.g[new] * v).max(axis=1)
        small_g = g_norm < gtol
        self.status[new[small_g]] = 1
        stop = small_g | (self.nfev[new] >= max_nfev)
        if stop.any():
            mask = np.zeros(self.ids.size, bool)
            mask[new[stop]] = True
            new, v, dv, g_norm = new[~stop], v[~stop], dv[~stop], g_norm[~stop]
            new = new - np.cumsum(mask)[new]      # rows after the drop
            self.retire(mask)
            if not new.size:
                return
        n = v.shape[1]
        d = np.sqrt(v)
        g = self.g[new]
        self.d[new], self.diag_h[new], self.g_h[new] = d, g * dv, d * g
        aug = np.concatenate([self.J[new] * d[:, None, :],
                              np.sqrt(g * dv)[:, None, :] * np.eye(n)], axis=1)
        U, s, VT = svd(aug)
        self.V[new] = np.swapaxes(VT, 1, 2)
        self.sv[new] = s
        self.uf[new] = einsum("kmi,km->ki", U[:, : self.m], self.f[new])
        self.theta[new] = np.maximum(0.995, 1 - g_norm)

    def _select(self):
        """The steps of the running fits (scipy's ``select_step``): (step, step_h,
        predicted reduction)."""
        lb, ub, d, diag_h, g_h = self.lb, self.ub, self.d, self.diag_h, self.g_h
        p_h, self.alpha = _tr_steps(self.uf, self.sv, self.V, self.delta, self.alpha, self.m)
        p = d * p_h
        J_h = self.J * d[:, None, :]
        js = einsum("kmn,kn->km", J_h, p_h)
        predicted = -(0.5 * (einsum("km,km->k", js, js)
                             + einsum("kn,kn->k", p_h * diag_h, p_h))
                      + einsum("kn,kn->k", g_h, p_h))
        xp = self.x + p
        for j in np.flatnonzero(~((xp >= lb) & (xp <= ub)).all(axis=1)):
            p[j], p_h[j], predicted[j] = _select_step(
                self.x[j], _Dense(J_h[j], g_h[j], diag_h[j]), d[j], p_h[j],
                self.delta[j], lb, ub, self.theta[j])
        return p, p_h, predicted

    def try_steps(self, ftol: float, xtol: float) -> None:
        """One step of each running fit: evaluated, the radius updated, the termination
        tests made, and the point accepted when the cost fell (scipy's inner loop, one
        pass; a fit whose step is refused tries again at the next call)."""
        step, step_h, predicted = self._select()
        x_new = _strictly_inside(self.x + step, self.lb, self.ub)
        f_new = np.asarray(self.fun(x_new, self.ids), float)
        self.nfev += 1
        step_h_norm = row_norms(step_h)
        finite = np.isfinite(f_new).all(axis=1)
        cost_new = 0.5 * einsum("km,km->k", f_new, f_new)
        actual = self.cost - cost_new
        ratio = np.where(predicted > 0, actual / predicted,
                         np.where((predicted == 0) & (actual == 0), 1.0, 0.0))
        dl = self.delta
        dl_new = np.where(ratio < 0.25, 0.25 * step_h_norm,
                          np.where((ratio > 0.75) & (step_h_norm > 0.95 * dl), 2.0 * dl, dl))
        small_f = (actual < ftol * self.cost) & (ratio > 0.25)
        small_x = (row_norms(step)
                   < xtol * (xtol + row_norms(self.x)))
        term = finite & (small_f | small_x)
        self.status = np.where(term, np.where(small_f & small_x, 4, np.where(small_f, 2, 3)),
                               self.status)
        go = finite & ~term
        self.alpha = np.where(go, self.alpha * dl / dl_new, self.alpha)
        # not finite: a quarter of the step as radius, and try again
        self.delta = np.where(go, dl_new, np.where(finite, dl, 0.25 * step_h_norm))
        accept = finite & (actual > 0)
        if accept.any():
            self.x[accept], self.f[accept] = x_new[accept], f_new[accept]
            self.cost[accept] = cost_new[accept]
            todo = np.flatnonzero(accept & ~term)   # a fit that stopped needs no Jacobian
            if todo.size:
                self.J[todo] = self.jac(self.x[todo], self.ids[todo])
                self.g[todo] = einsum("kmn,km->kn", self.J[todo], self.f[todo])
                self.fresh[todo] = True
        self.retire(term)
