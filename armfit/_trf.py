"""One least-squares fit by the trust-region-reflective method, as scipy makes it.

:func:`bounded_least_squares` is :func:`scipy.optimize.least_squares` with
``method="trf"``, a fixed ``x_scale`` or ``"jac"``, the linear loss and the exact
trust-region solver: the same operations in the same order (scipy 1.17's
``scipy/optimize/_lsq/trf.py`` and ``common.py``; its variant for a box with no finite
bound too), on arrays in the same memory order, so the same iterates to the bit
wherever :func:`numpy.linalg.svd` and :func:`scipy.linalg.svd` agree (both are LAPACK's
``gesdd``; ``tests/test_trf.py`` and ``tests/test_slsqp.py`` compare whole results with
scipy's).

It exists for start-up time. Importing :mod:`scipy.optimize` costs about half a second
(it imports :mod:`scipy.linalg`, :mod:`scipy.sparse` and formats the docstrings of its
array-API functions), more than a ``fit-grip`` or ``fit-nominal`` of one spectra file
spends fitting; its trust-region-reflective solver is a few hundred lines of numpy.

The code below follows scipy's, distributed under the BSD 3-clause licence (the
comment below).
"""

# Copyright (c) 2001-2002 Enthought, Inc. 2003, SciPy Developers.
# All rights reserved.
#
# Redistribution and use in source and binary forms, with or without
# modification, are permitted provided that the following conditions
# are met:
#
# 1. Redistributions of source code must retain the above copyright
#    notice, this list of conditions and the following disclaimer.
#
# 2. Redistributions in binary form must reproduce the above
#    copyright notice, this list of conditions and the following
#    disclaimer in the documentation and/or other materials provided
#    with the distribution.
#
# 3. Neither the name of the copyright holder nor the names of its
#    contributors may be used to endorse or promote products derived
#    from this software without specific prior written permission.
#
# THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS
# "AS IS" AND ANY EXPRESS OR IMPLIED WARRANTIES, INCLUDING, BUT NOT
# LIMITED TO, THE IMPLIED WARRANTIES OF MERCHANTABILITY AND FITNESS FOR
# A PARTICULAR PURPOSE ARE DISCLAIMED. IN NO EVENT SHALL THE COPYRIGHT
# OWNER OR CONTRIBUTORS BE LIABLE FOR ANY DIRECT, INDIRECT, INCIDENTAL,
# SPECIAL, EXEMPLARY, OR CONSEQUENTIAL DAMAGES (INCLUDING, BUT NOT
# LIMITED TO, PROCUREMENT OF SUBSTITUTE GOODS OR SERVICES; LOSS OF USE,
# DATA, OR PROFITS; OR BUSINESS INTERRUPTION) HOWEVER CAUSED AND ON ANY
# THEORY OF LIABILITY, WHETHER IN CONTRACT, STRICT LIABILITY, OR TORT
# (INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT OF THE USE
# OF THIS SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from math import copysign

import numpy as np

from armfit._lapack import norm, svd

__all__ = ["TrfResult", "bounded_least_squares"]

EPS = np.finfo(float).eps

#: scipy's messages for the termination statuses.
MESSAGES = {
    0: "The maximum number of function evaluations is exceeded.",
    1: "`gtol` termination condition is satisfied.",
    2: "`ftol` termination condition is satisfied.",
    3: "`xtol` termination condition is satisfied.",
    4: "Both `ftol` and `xtol` termination conditions are satisfied.",
}


@dataclass
class TrfResult:
    """The result of :func:`bounded_least_squares`: scipy's ``OptimizeResult`` fields.

    Attributes
    ----------
    x : ndarray
        The solution.
    cost : float
        ½‖fun(x)‖².
    fun, jac, grad : ndarray
        Residuals, Jacobian and gradient Jᵀr at ``x``.
    optimality : float
        The largest component of the Coleman-Li scaled gradient.
    active_mask : ndarray of int
        −1 / 1 where a lower / upper bound is active, 0 elsewhere.
    nfev, njev : int
        Residual and Jacobian evaluations.
    status : int
        0: evaluation budget spent; 1: ``gtol``; 2: ``ftol``; 3: ``xtol``; 4: both
        ``ftol`` and ``xtol``.
    message : str
    success : bool
        ``status > 0``.
    """

    x: np.ndarray
    cost: float
    fun: np.ndarray
    jac: np.ndarray
    grad: np.ndarray
    optimality: float
    active_mask: np.ndarray
    nfev: int
    njev: int
    status: int
    message: str
    success: bool


def bounded_least_squares(fun: Callable[[np.ndarray], np.ndarray],
                  x0: np.ndarray, jac: Callable[[np.ndarray], np.ndarray],
                  bounds: tuple[np.ndarray, np.ndarray], *, max_nfev: int | None = None,
                  ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8,
                  x_scale: float | str = 1.0):
    """Minimise ½‖fun(x)‖² over the box ``bounds``: :func:`scipy.optimize.least_squares`
    (``method="trf"``) without importing :mod:`scipy.optimize`.

    Parameters
    ----------
    fun : callable
        x (n,) -> residuals (m,).
    x0 : array_like
        Start, inside the bounds (moved strictly inside them, as scipy moves it).
    jac : callable
        x (n,) -> the Jacobian (m, n).
    bounds : (array_like, array_like)
        Lower and upper bounds (scalars or (n,)), each lower bound below its upper one.
    max_nfev : int, optional
        Budget of residual evaluations (default 100·n).
    ftol, xtol, gtol : float
        Termination tolerances, as scipy's (at least one above machine epsilon).
    x_scale : float or "jac"
        The variables' scale, as scipy's: one positive number for all, or ``"jac"``,
        the inverse norms of the Jacobian's columns, never shrinking over the iterations.

    Returns
    -------
    TrfResult

    Raises
    ------
    ValueError
        As scipy: ``x0`` outside the bounds, inconsistent shapes, residuals not finite
        at the start, a Jacobian of the wrong shape, or all tolerances below epsilon.
    """
    x0 = np.atleast_1d(x0).astype(float)
    if x0.ndim > 1:
        raise ValueError("`x0` must have at most 1 dimension.")
    lb, ub = (np.asarray(b, dtype=float) for b in bounds)
    lb = np.resize(lb, x0.shape[0]) if lb.ndim == 0 else lb
    ub = np.resize(ub, x0.shape[0]) if ub.ndim == 0 else ub
    if max_nfev is not None and max_nfev <= 0:
        raise ValueError("`max_nfev` must be None or positive integer.")
    if lb.shape != x0.shape or ub.shape != x0.shape:
        raise ValueError("Inconsistent shapes between bounds and `x0`.")
    if np.any(lb >= ub):
        raise ValueError("Each lower bound must be strictly less than each upper bound.")
    if not _in_bounds(x0, lb, ub):
        raise ValueError("Initial guess is outside of provided bounds")
    ftol, xtol, gtol = (0 if t is None else t for t in (ftol, xtol, gtol))
    if ftol < EPS and xtol < EPS and gtol < EPS:
        raise ValueError("At least one of the tolerances must be higher than machine "
                         f"epsilon ({EPS:.2e}).")
    x0 = _make_strictly_feasible(x0, lb, ub)

    def f_of(x):          # copies in and out, in the arrays' own memory order, as scipy
        return np.atleast_1d(fun(x.copy())).copy(order="K")

    def j_of(x):
        J = np.atleast_2d(jac(x.copy()))
        return J.astype(J.dtype)

    f0 = f_of(x0)
    if f0.ndim != 1:
        raise ValueError(f"`fun` must return at most 1-d array_like. f0.shape: {f0.shape}")
    if not np.all(np.isfinite(f0)):
        raise ValueError("Residuals are not finite in the initial point.")
    J0 = j_of(x0)
    if J0.shape != (f0.size, x0.size):
        raise ValueError("The return value of `jac` has wrong shape: expected "
                         f"{(f0.size, x0.size)}, actual {J0.shape}.")
    if not (isinstance(x_scale, str) and x_scale == "jac"):
        x_scale = np.asarray(x_scale, dtype=float)
        if not (np.all(np.isfinite(x_scale)) and np.all(x_scale > 0)):
            raise ValueError("`x_scale` must be 'jac' or array_like with positive numbers.")
        if x_scale.ndim == 0:
            x_scale = np.resize(x_scale, x0.shape)
        if x_scale.shape != x0.shape:
            raise ValueError("Inconsistent shapes between `x_scale` and `x0`.")
    if np.all(lb == -np.inf) and np.all(ub == np.inf):
        return _trf_no_bounds(f_of, j_of, x0, f0, J0, ftol, xtol, gtol, max_nfev, x_scale)
    return _trf_bounds(f_of, j_of, x0, f0, J0, lb, ub, ftol, xtol, gtol, max_nfev, x_scale)


def _svd(A):
    """``scipy.linalg.svd(A, full_matrices=False)`` as (U, s, V) with V = (Vᵀ)ᵀ: LAPACK's
    ``gesdd`` through numpy, U and Vᵀ in Fortran order as scipy returns them, so that the
    products with them take BLAS's same path (and rounding) as scipy's."""
    U, s, V = svd(A)
    U, V = np.asfortranarray(U), np.asfortranarray(V)
    return U, s, V.T


def _trf_no_bounds(fun, jac, x0, f0, J0, ftol, xtol, gtol, max_nfev, x_scale):
    """scipy's ``trf_no_bounds`` (linear loss, exact solver, no callback). Its loop
    repeats much of :func:`_trf_bounds`'s, as scipy's two functions do: each follows
    its own to the operation, so that the iterates are scipy's bits."""
    x = x0.copy()
    f = f0
    f_true = f.copy()
    nfev = 1
    J = J0
    njev = 1
    m, n = J.shape
    cost = 0.5 * np.dot(f, f)
    g = J.T.dot(f)
    jac_scale = isinstance(x_scale, str) and x_scale == "jac"
    if jac_scale:
        scale, scale_inv = _jac_scale(J)
    else:
        scale, scale_inv = x_scale, 1 / x_scale
    Delta = norm(x0 * scale_inv)
    if Delta == 0:
        Delta = 1.0
    if max_nfev is None:
        max_nfev = x0.size * 100
    alpha = 0.0
    termination_status = None
    while True:
        g_norm = norm(g, ord=np.inf)
        if g_norm < gtol:
            termination_status = 1
        if termination_status is not None or nfev == max_nfev:
            break
        d = scale
        g_h = d * g
        J_h = J * d
        U, s, V = _svd(J_h)
        uf = U.T.dot(f)
        actual_reduction = -1
        while actual_reduction <= 0 and nfev < max_nfev:
            step_h, alpha = _solve_lsq_trust_region(n, m, uf, s, V, Delta,
                                                    initial_alpha=alpha)
            predicted_reduction = -_evaluate_quadratic(J_h, g_h, step_h)
            step = d * step_h
            x_new = x + step
            f_new = fun(x_new)
            nfev += 1
            step_h_norm = norm(step_h)
            if not np.isfinite(f_new).all():
                Delta = 0.25 * step_h_norm
                continue
            cost_new = 0.5 * np.dot(f_new, f_new)
            actual_reduction = cost - cost_new
            Delta_new, ratio = _update_tr_radius(
                Delta, actual_reduction, predicted_reduction, step_h_norm,
                step_h_norm > 0.95 * Delta)
            step_norm = norm(step)
            termination_status = _check_termination(
                actual_reduction, cost, step_norm, norm(x), ratio, ftol, xtol)
            if termination_status is not None:
                break
            alpha *= Delta / Delta_new
            Delta = Delta_new
        if actual_reduction > 0:
            x = x_new
            f = f_new
            f_true = f.copy()
            cost = cost_new
            J = jac(x)
            njev += 1
            g = J.T.dot(f)
            if jac_scale:
                scale, scale_inv = _jac_scale(J, scale_inv)
    if termination_status is None:
        termination_status = 0
    return TrfResult(x=x, cost=cost, fun=f_true, jac=J, grad=g, optimality=g_norm,
                     active_mask=np.zeros_like(x), nfev=nfev, njev=njev,
                     status=termination_status, message=MESSAGES[termination_status],
                     success=termination_status > 0)


def _trf_bounds(fun, jac, x0, f0, J0, lb, ub, ftol, xtol, gtol, max_nfev, x_scale):
    """scipy's ``trf_bounds`` (linear loss, exact solver, no callback)."""
    x = x0.copy()
    f = f0
    f_true = f.copy()
    nfev = 1
    J = J0
    njev = 1
    m, n = J.shape
    cost = 0.5 * np.dot(f, f)
    g = J.T.dot(f)
    jac_scale = isinstance(x_scale, str) and x_scale == "jac"
    if jac_scale:
        scale, scale_inv = _jac_scale(J)
    else:
        scale, scale_inv = x_scale, 1 / x_scale
    v, dv = _cl_scaling_vector(x, g, lb, ub)
    v[dv != 0] *= scale_inv[dv != 0]
    Delta = norm(x0 * scale_inv / v**0.5)
    if Delta == 0:
        Delta = 1.0
    g_norm = norm(g * v, ord=np.inf)
    f_augmented = np.zeros(m + n)
    J_augmented = np.empty((m + n, n))
    if max_nfev is None:
        max_nfev = x0.size * 100
    alpha = 0.0
    termination_status = None
    while True:
        v, dv = _cl_scaling_vector(x, g, lb, ub)
        g_norm = norm(g * v, ord=np.inf)
        if g_norm < gtol:
            termination_status = 1
        if termination_status is not None or nfev == max_nfev:
            break
        v[dv != 0] *= scale_inv[dv != 0]
        d = v**0.5 * scale
        diag_h = g * dv * scale
        g_h = d * g
        f_augmented[:m] = f
        J_augmented[:m] = J * d
        J_h = J_augmented[:m]
        J_augmented[m:] = np.diag(diag_h**0.5)
        U, s, V = _svd(J_augmented)
        uf = U.T.dot(f_augmented)
        theta = max(0.995, 1 - g_norm)
        actual_reduction = -1
        while actual_reduction <= 0 and nfev < max_nfev:
            p_h, alpha = _solve_lsq_trust_region(n, m, uf, s, V, Delta, initial_alpha=alpha)
            p = d * p_h
            step, step_h, predicted_reduction = _select_step(
                x, J_h, diag_h, g_h, p, p_h, d, Delta, lb, ub, theta)
            x_new = _make_strictly_feasible(x + step, lb, ub, rstep=0)
            f_new = fun(x_new)
            nfev += 1
            step_h_norm = norm(step_h)
            if not np.isfinite(f_new).all():
                Delta = 0.25 * step_h_norm
                continue
            cost_new = 0.5 * np.dot(f_new, f_new)
            actual_reduction = cost - cost_new
            Delta_new, ratio = _update_tr_radius(
                Delta, actual_reduction, predicted_reduction, step_h_norm,
                step_h_norm > 0.95 * Delta)
            step_norm = norm(step)
            termination_status = _check_termination(
                actual_reduction, cost, step_norm, norm(x), ratio, ftol, xtol)
            if termination_status is not None:
                break
            alpha *= Delta / Delta_new
            Delta = Delta_new
        if actual_reduction > 0:
            x = x_new
            f = f_new
            f_true = f.copy()
            cost = cost_new
            J = jac(x)
            njev += 1
            g = J.T.dot(f)
            if jac_scale:
                scale, scale_inv = _jac_scale(J, scale_inv)
    if termination_status is None:
        termination_status = 0
    active_mask = _find_active_constraints(x, lb, ub, rtol=xtol)
    return TrfResult(x=x, cost=cost, fun=f_true, jac=J, grad=g, optimality=g_norm,
                     active_mask=active_mask, nfev=nfev, njev=njev,
                     status=termination_status, message=MESSAGES[termination_status],
                     success=termination_status > 0)


def _jac_scale(J, scale_inv_old=None):
    """scipy's ``compute_jac_scale``: the variables' scale from the norms of the
    Jacobian's columns (1 for a zero column at the start; never below the last)."""
    scale_inv = (J**2).sum(axis=0)**0.5
    if scale_inv_old is None:
        scale_inv[scale_inv == 0] = 1
    else:
        scale_inv = np.maximum(scale_inv, scale_inv_old)
    return 1 / scale_inv, scale_inv


def _select_step(x, J_h, diag_h, g_h, p, p_h, d, Delta, lb, ub, theta):
    """scipy's ``select_step``: the trust-region step if it stays inside the bounds,
    else the best of that step stopped short of the bound, its reflection, and the
    scaled steepest-descent step."""
    if _in_bounds(x + p, lb, ub):
        p_value = _evaluate_quadratic(J_h, g_h, p_h, diag=diag_h)
        return p, p_h, -p_value
    p_stride, hits = _step_size_to_bound(x, p, lb, ub)
    r_h = np.copy(p_h)
    r_h[hits.astype(bool)] *= -1
    r = d * r_h
    p *= p_stride
    p_h *= p_stride
    x_on_bound = x + p
    _, to_tr = _intersect_trust_region(p_h, r_h, Delta)
    to_bound, _ = _step_size_to_bound(x_on_bound, r, lb, ub)
    r_stride = min(to_bound, to_tr)
    if r_stride > 0:
        r_stride_l = (1 - theta) * p_stride / r_stride
        if r_stride == to_bound:
            r_stride_u = theta * to_bound
        else:
            r_stride_u = to_tr
    else:
        r_stride_l = 0
        r_stride_u = -1
    if r_stride_l <= r_stride_u:
        a, b, c = _build_quadratic_1d(J_h, g_h, r_h, s0=p_h, diag=diag_h)
        r_stride, r_value = _minimize_quadratic_1d(a, b, r_stride_l, r_stride_u, c=c)
        r_h *= r_stride
        r_h += p_h
        r = r_h * d
    else:
        r_value = np.inf
    p *= theta
    p_h *= theta
    p_value = _evaluate_quadratic(J_h, g_h, p_h, diag=diag_h)
    ag_h = -g_h
    ag = d * ag_h
    to_tr = Delta / norm(ag_h)
    to_bound, _ = _step_size_to_bound(x, ag, lb, ub)
    if to_bound < to_tr:
        ag_stride = theta * to_bound
    else:
        ag_stride = to_tr
    a, b = _build_quadratic_1d(J_h, g_h, ag_h, diag=diag_h)
    ag_stride, ag_value = _minimize_quadratic_1d(a, b, 0, ag_stride)
    ag_h *= ag_stride
    ag *= ag_stride
    if p_value < r_value and p_value < ag_value:
        return p, p_h, -p_value
    elif r_value < p_value and r_value < ag_value:
        return r, r_h, -r_value
    else:
        return ag, ag_h, -ag_value


def _intersect_trust_region(x, s, Delta):
    """The roots t of ‖x + s·t‖ = Delta (negative, positive)."""
    a = np.dot(s, s)
    if a == 0:
        raise ValueError("`s` is zero.")
    b = np.dot(x, s)
    c = np.dot(x, x) - Delta**2
    if c > 0:
        raise ValueError("`x` is not within the trust region.")
    d = np.sqrt(b*b - a*c)
    q = -(b + copysign(d, b))
    t1 = q / a
    t2 = c / q
    if t1 < t2:
        return t1, t2
    else:
        return t2, t1


def _solve_lsq_trust_region(n, m, uf, s, V, Delta, initial_alpha=None, rtol=0.01,
                            max_iter=10):
    """The trust-region subproblem from one SVD of the Jacobian (Moré 1977, as MINPACK):
    (step, Levenberg-Marquardt parameter)."""
    def phi_and_derivative(alpha, suf, s, Delta):
        denom = s**2 + alpha
        p_norm = norm(suf / denom)
        phi = p_norm - Delta
        phi_prime = -(suf ** 2 / denom**3).sum() / p_norm
        return phi, phi_prime

    suf = s * uf
    if m >= n:
        threshold = EPS * m * s[0]
        full_rank = s[-1] > threshold
    else:
        full_rank = False
    if full_rank:
        p = -V.dot(uf / s)
        if norm(p) <= Delta:
            return p, 0.0
    alpha_upper = norm(suf) / Delta
    if full_rank:
        phi, phi_prime = phi_and_derivative(0.0, suf, s, Delta)
        alpha_lower = -phi / phi_prime
    else:
        alpha_lower = 0.0
    if initial_alpha is None or not full_rank and initial_alpha == 0:
        alpha = max(0.001 * alpha_upper, (alpha_lower * alpha_upper)**0.5)
    else:
        alpha = initial_alpha
    for _ in range(max_iter):
        if alpha < alpha_lower or alpha > alpha_upper:
            alpha = max(0.001 * alpha_upper, (alpha_lower * alpha_upper)**0.5)
        phi, phi_prime = phi_and_derivative(alpha, suf, s, Delta)
        if phi < 0:
            alpha_upper = alpha
        ratio = phi / phi_prime
        alpha_lower = max(alpha_lower, alpha - ratio)
        alpha -= (phi + Delta) * ratio / Delta
        if np.abs(phi) < rtol * Delta:
            break
    p = -V.dot(suf / (s**2 + alpha))
    p *= Delta / norm(p)
    return p, alpha


def _update_tr_radius(Delta, actual_reduction, predicted_reduction, step_norm, bound_hit):
    """The new trust radius and the agreement ratio of a step."""
    if predicted_reduction > 0:
        ratio = actual_reduction / predicted_reduction
    elif predicted_reduction == actual_reduction == 0:
        ratio = 1
    else:
        ratio = 0
    if ratio < 0.25:
        Delta = 0.25 * step_norm
    elif ratio > 0.75 and bound_hit:
        Delta *= 2.0
    return Delta, ratio


def _build_quadratic_1d(J, g, s, diag=None, s0=None):
    """(a, b[, c]) of the model along s0 + t·s."""
    v = J.dot(s)
    a = np.dot(v, v)
    if diag is not None:
        a += np.dot(s * diag, s)
    a *= 0.5
    b = np.dot(g, s)
    if s0 is not None:
        u = J.dot(s0)
        b += np.dot(u, v)
        c = 0.5 * np.dot(u, u) + np.dot(g, s0)
        if diag is not None:
            b += np.dot(s0 * diag, s)
            c += 0.5 * np.dot(s0 * diag, s0)
        return a, b, c
    else:
        return a, b


def _minimize_quadratic_1d(a, b, lb, ub, c=0):
    """The minimum (t, value) of a·t² + b·t + c over [lb, ub]."""
    t = [lb, ub]
    if a != 0:
        extremum = -0.5 * b / a
        if lb < extremum < ub:
            t.append(extremum)
    t = np.asarray(t)
    y = t * (a * t + b) + c
    min_index = np.argmin(y)
    return t[min_index], y[min_index]


def _evaluate_quadratic(J, g, s, diag=None):
    """½ sᵀ(JᵀJ + diag)s + gᵀs for one step s."""
    Js = J.dot(s)
    q = np.dot(Js, Js)
    if diag is not None:
        q += np.dot(s * diag, s)
    l_ = np.dot(s, g)
    return 0.5 * q + l_


def _in_bounds(x, lb, ub):
    return ((x >= lb) & (x <= ub)).all()


def _step_size_to_bound(x, s, lb, ub):
    """The smallest t ≥ 0 with x + s·t on a bound, and which components hit it (±1)."""
    non_zero = np.nonzero(s)
    s_non_zero = s[non_zero]
    steps = np.empty_like(x)
    steps.fill(np.inf)
    with np.errstate(over='ignore'):
        steps[non_zero] = np.maximum((lb - x)[non_zero] / s_non_zero,
                                     (ub - x)[non_zero] / s_non_zero)
    min_step = steps.min()
    return min_step, np.equal(steps, min_step) * np.sign(s).astype(int)


def _find_active_constraints(x, lb, ub, rtol=1e-10):
    """−1 / 1 where x is within ``rtol`` (relative) of its lower / upper bound."""
    active = np.zeros_like(x, dtype=int)
    if rtol == 0:
        active[x <= lb] = -1
        active[x >= ub] = 1
        return active
    lower_dist = x - lb
    upper_dist = ub - x
    lower_threshold = rtol * np.maximum(1, np.abs(lb))
    upper_threshold = rtol * np.maximum(1, np.abs(ub))
    lower_active = (np.isfinite(lb) &
                    (lower_dist <= np.minimum(upper_dist, lower_threshold)))
    active[lower_active] = -1
    upper_active = (np.isfinite(ub) &
                    (upper_dist <= np.minimum(lower_dist, upper_threshold)))
    active[upper_active] = 1
    return active


def _make_strictly_feasible(x, lb, ub, rstep=1e-10):
    """x with every component at least ``rstep`` (relative; the next float when 0) inside
    its bounds."""
    x_new = x.copy()
    active = _find_active_constraints(x, lb, ub, rstep)
    lower_mask = np.equal(active, -1)
    upper_mask = np.equal(active, 1)
    if rstep == 0:
        x_new[lower_mask] = np.nextafter(lb[lower_mask], ub[lower_mask])
        x_new[upper_mask] = np.nextafter(ub[upper_mask], lb[upper_mask])
    else:
        x_new[lower_mask] = (lb[lower_mask] +
                             rstep * np.maximum(1, np.abs(lb[lower_mask])))
        x_new[upper_mask] = (ub[upper_mask] -
                             rstep * np.maximum(1, np.abs(ub[upper_mask])))
    tight_bounds = (x_new < lb) | (x_new > ub)
    x_new[tight_bounds] = 0.5 * (lb[tight_bounds] + ub[tight_bounds])
    return x_new


def _cl_scaling_vector(x, g, lb, ub):
    """Coleman-Li scaling: v the distance to the bound the gradient points towards (1
    without one), dv its derivative."""
    v = np.ones_like(x)
    dv = np.zeros_like(x)
    mask = (g < 0) & np.isfinite(ub)
    v[mask] = ub[mask] - x[mask]
    dv[mask] = -1
    mask = (g > 0) & np.isfinite(lb)
    v[mask] = x[mask] - lb[mask]
    dv[mask] = 1
    return v, dv


def _check_termination(dF, F, dx_norm, x_norm, ratio, ftol, xtol):
    """The ftol / xtol termination status of a step (None when neither holds)."""
    ftol_satisfied = dF < ftol * F and ratio > 0.25
    xtol_satisfied = dx_norm < xtol * (xtol + x_norm)
    if ftol_satisfied and xtol_satisfied:
        return 4
    elif ftol_satisfied:
        return 2
    elif xtol_satisfied:
        return 3
    else:
        return None
