"""One SLSQP minimisation as scipy makes it, without importing :mod:`scipy.optimize`.

:func:`minimize_slsqp` is :func:`scipy.optimize.minimize` with ``method="SLSQP"``, an
objective that returns its value and gradient (``jac=True``), bounds, and one vector of
inequality constraints with its Jacobian: the same calls of scipy's compiled SLSQP
(Kraft's algorithm, scipy's ``_slsqplib``) with the same arrays in the same order
(scipy 1.17's ``scipy/optimize/_slsqp_py.py``), so the same iterates to the bit
(``tests/test_slsqp.py`` compares whole results with scipy's).

It exists for start-up time. Importing :mod:`scipy.optimize` costs about a quarter of a
second more than :mod:`scipy.special` (it imports :mod:`scipy.linalg`,
:mod:`scipy.sparse` and formats the docstrings of its array-API functions), in every
process that fits Wu: the worker pools' fork server, ``fit-uncertainty``, a run with
``--jobs 1``. The compiled kernel itself loads in milliseconds: it is loaded from its
file, with only the top-level :mod:`scipy` package imported. Where the kernel or its
calling convention is not the one this module copies (a scipy other than 1.17), the
minimisation is scipy's own, through :func:`scipy.optimize.minimize`.

The driver below follows scipy's, distributed under the BSD 3-clause licence (the
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

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["SlsqpResult", "load_kernel", "minimize_slsqp"]

#: The scipy releases (major, minor) whose SLSQP driver this module copies.
KNOWN_SCIPY = ((1, 17),)

#: scipy's messages for the exit modes.
_EXIT_MODES = {-1: "Gradient evaluation required (g & a)",
            0: "Optimization terminated successfully",
            1: "Function evaluation required (f & c)",
            2: "More equality constraints than independent variables",
            3: "More than 3*n iterations in LSQ subproblem",
            4: "Inequality constraints incompatible",
            5: "Singular matrix E in LSQ subproblem",
            6: "Singular matrix C in LSQ subproblem",
            7: "Rank-deficient equality constraint subproblem HFTI",
            8: "Positive directional derivative for linesearch",
            9: "Iteration limit reached"}

_LOCK = threading.Lock()
_KERNEL: list = []          # [the kernel function or None], once looked for


@dataclass
class SlsqpResult:
    """The result of :func:`minimize_slsqp`: scipy's ``OptimizeResult`` fields.

    Attributes
    ----------
    x : ndarray
        The last iterate.
    fun : float
        The objective there.
    jac : ndarray
        The objective's gradient at the last point it was asked for.
    nit, nfev, njev : int
        Iterations; objective and gradient evaluations the solver asked for.
    status : int
        SLSQP's exit mode (0: converged; the message names the others).
    message : str
    success : bool
        ``status == 0``.
    """

    x: np.ndarray
    fun: float
    jac: np.ndarray
    nit: int
    nfev: int
    njev: int
    status: int
    message: str
    success: bool


def load_kernel() -> Callable | None:
    """scipy's compiled SLSQP step (``scipy.optimize._slsqplib.slsqp``), loaded from its
    file without importing :mod:`scipy.optimize`; None where scipy is not a release this
    module copies or the file is not there. Loaded once per process; the module is
    registered under its own name, so a later ``import scipy.optimize`` uses it too."""
    with _LOCK:
        if not _KERNEL:
            _KERNEL.append(_find_kernel())
        return _KERNEL[0]


def _find_kernel() -> Callable | None:
    import scipy

    from armfit import _scipy
    try:
        release = tuple(int(p) for p in scipy.__version__.split(".")[:2])
    except ValueError:
        return None
    if release not in KNOWN_SCIPY:
        return None
    return getattr(_scipy.compiled_module("scipy.optimize._slsqplib"), "slsqp", None)


def minimize_slsqp(fun: Callable[[np.ndarray], tuple[float, np.ndarray]], x0,
                   bounds: tuple[np.ndarray, np.ndarray],
                   ineq: Callable[[np.ndarray], np.ndarray],
                   ineq_jac: Callable[[np.ndarray], np.ndarray], *,
                   maxiter: int = 100, ftol: float = 1e-6) -> SlsqpResult:
    """Minimise ``fun`` subject to ``ineq(x) >= 0`` and the box ``bounds`` by SLSQP:
    ``scipy.optimize.minimize(fun, x0, jac=True, method="SLSQP", bounds=...,
    constraints=[{"type": "ineq", "fun": ineq, "jac": ineq_jac}],
    options={"maxiter": maxiter, "ftol": ftol})``, iterate for iterate.

    Parameters
    ----------
    fun : callable
        x (n,) -> (objective value, gradient (n,)).
    x0 : array_like
        Start (clipped into the bounds, as scipy clips it).
    bounds : (array_like, array_like)
        Lower and upper bounds (n,), −inf / inf where there is none; each lower bound
        below its upper one.
    ineq, ineq_jac : callable
        x (n,) -> constraint values (m,), each to be ≥ 0, and their Jacobian (m, n).
    maxiter : int
        Iterations at most.
    ftol : float
        SLSQP's accuracy goal (scipy's ``ftol``).

    Returns
    -------
    SlsqpResult
    """
    lb, ub = (np.asarray(b, dtype=float) for b in bounds)
    slsqp = load_kernel()
    if slsqp is None:
        return _with_scipy(fun, x0, lb, ub, ineq, ineq_jac, maxiter, ftol)
    x = np.asarray(x0, dtype=float).reshape(-1).copy()
    x = np.clip(x, lb, ub)
    n = x.size
    xl, xu = lb.copy(), ub.copy()
    xl[~np.isfinite(lb)] = np.nan            # the kernel takes NaN for no bound
    xu[~np.isfinite(ub)] = np.nan

    cache: list = [None, None, None]         # x, value, gradient of the last evaluation
    counts = [0, 0]

    def value(z):
        if cache[0] is None or not (z == cache[0]).all():
            f, g = fun(z.copy())
            cache[:] = [z.copy(), f, g]
            counts[0] += 1
        return cache[1]

    def grad(z):
        value(z)
        counts[1] += 1
        return np.atleast_1d(cache[2])

    m = len(np.atleast_1d(ineq(x)))
    acc = ftol
    state = {"acc": acc, "alpha": 0.0, "f0": 0.0, "gs": 0.0, "h1": 0.0, "h2": 0.0,
             "h3": 0.0, "h4": 0.0, "t": 0.0, "t0": 0.0, "tol": 10.0 * acc, "exact": 0,
             "inconsistent": 0, "reset": 0, "iter": 0, "itermax": int(maxiter),
             "line": 0, "m": m, "meq": 0, "mode": 0, "n": n}
    indices = np.zeros([max(m + 2 * n + 2, 1)], dtype=np.int32)
    meq = 0
    size = n * (n + 1) // 2 + 3 * m * n - (m + 5 * n + 7) * meq + 9 * m + 8 * n * n \
        + 35 * n + meq * meq + 28
    if m == 0:
        size += 2 * n * (n + 1)
    buffer = np.zeros(max(size, 1), dtype=np.float64)
    fx = value(x)
    g = grad(x)
    mult = np.zeros([max(1, m + 2 * n + 2)], dtype=np.float64)
    C = np.zeros([max(1, m), n], dtype=np.float64, order="F")
    d = np.zeros([max(1, m)], dtype=np.float64)
    if m:
        C[0:m, :] = np.atleast_2d(ineq_jac(x))
        d[0:m] = np.atleast_1d(ineq(x)).ravel()
    while True:
        slsqp(state, fx, g, C, d, x, mult, xl, xu, buffer, indices)
        if state["mode"] == 1:
            fx = value(x)
            if m:
                d[0:m] = np.atleast_1d(ineq(x)).ravel()
        if state["mode"] == -1:
            g = grad(x)
            if m:
                C[0:m, :] = np.atleast_2d(ineq_jac(x))
        if abs(state["mode"]) != 1:
            break
    mode = state["mode"]
    return SlsqpResult(x=x, fun=fx, jac=g, nit=state["iter"], nfev=counts[0],
                       njev=counts[1], status=mode, message=_EXIT_MODES[mode],
                       success=mode == 0)


def _with_scipy(fun, x0, lb, ub, ineq, ineq_jac, maxiter, ftol) -> SlsqpResult:
    """The same minimisation by :func:`scipy.optimize.minimize`."""
    from armfit import _scipy
    bounds = [(None if not np.isfinite(lo) else float(lo),
               None if not np.isfinite(hi) else float(hi))
              for lo, hi in zip(lb, ub, strict=True)]
    res = _scipy.minimize(fun, x0, jac=True, method="SLSQP", bounds=bounds,
                          constraints=[{"type": "ineq", "fun": ineq, "jac": ineq_jac}],
                          options={"maxiter": maxiter, "ftol": ftol})
    return SlsqpResult(x=res.x, fun=float(res.fun), jac=res.jac, nit=int(res.nit),
                       nfev=int(res.nfev), njev=int(res.njev), status=int(res.status),
                       message=str(res.message), success=bool(res.success))
