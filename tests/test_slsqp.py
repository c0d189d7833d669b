"""armfit._slsqp.minimize_slsqp: scipy's SLSQP without importing scipy.optimize, and the
Wu fits' least-squares starts by armfit._trf with ``x_scale="jac"``.

The reference is an independent computation: scipy.optimize.minimize (method "SLSQP",
``jac=True``) and scipy.optimize.least_squares (method "trf", ``x_scale="jac"``) run on
the same problem with the same start, bounds, constraints, tolerances and budget. The
copies must give scipy's result to the bit (end point, objective, gradient, iterations,
exit mode), on every solve of the Wu fits armfit makes (Table III's weights and a noisy
W_max like the paper's) and on problems that end each way: converged, out of
iterations, and with constraints no point satisfies."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.optimize import least_squares as scipy_least_squares
from scipy.optimize import minimize as scipy_minimize

from armfit import _slsqp, _trf
from armfit.data import paper_table
from armfit.uncertainty import WuWeight, fit_wu

F_LOG = np.logspace(-2, np.log10(30.0), 140)


def _table3(axis: str) -> WuWeight:
    t = paper_table("uncertainty")
    t = t[t["axis"] == axis]
    z, p = t[t["kind"] == "zero"], t[t["kind"] == "pole"]
    return WuWeight(float(t.loc[t["kind"] == "gain", "real"].iloc[0]),
                    (z["real"] + 1j * z["imag"]).to_numpy(),
                    (p["real"] + 1j * p["imag"]).to_numpy())


def _scipy_slsqp(fun, x0, bounds, ineq, ineq_jac, maxiter, ftol):
    old = [(None if not np.isfinite(lo) else lo, None if not np.isfinite(hi) else hi)
           for lo, hi in zip(*bounds, strict=True)]
    return scipy_minimize(fun, x0, jac=True, method="SLSQP", bounds=old,
                          constraints=[{"type": "ineq", "fun": ineq, "jac": ineq_jac}],
                          options={"maxiter": maxiter, "ftol": ftol})


def _assert_same_slsqp(ours, theirs):
    assert np.array_equal(ours.x, theirs.x)
    assert ours.fun == theirs.fun
    assert np.array_equal(ours.jac, theirs.jac)
    assert (ours.nit, ours.status, ours.success) == (theirs.nit, theirs.status,
                                                      theirs.success)


def _checked(monkeypatch):
    """Every SLSQP and least-squares solve of the Wu fits compared with scipy's; returns
    the list of (kind, status) of the solves made."""
    seen = []
    slsqp, lsq = _slsqp.minimize_slsqp, _trf.bounded_least_squares

    def both_slsqp(fun, x0, bounds, ineq, ineq_jac, *, maxiter, ftol):
        ours = slsqp(fun, x0, bounds, ineq, ineq_jac, maxiter=maxiter, ftol=ftol)
        _assert_same_slsqp(ours, _scipy_slsqp(fun, x0, bounds, ineq, ineq_jac, maxiter,
                                              ftol))
        seen.append(("slsqp", ours.status))
        return ours

    def both_lsq(fun, x0, jac, bounds, **opts):
        ours = lsq(fun, x0, jac, bounds, **opts)
        theirs = scipy_least_squares(fun, x0, jac=jac, bounds=bounds, method="trf", **opts)
        for k in ("x", "cost", "fun", "jac", "grad", "optimality", "active_mask", "nfev",
                  "njev", "status"):
            assert np.array_equal(getattr(ours, k), theirs[k]), k
        seen.append(("lsq", ours.status))
        return ours

    monkeypatch.setattr(_slsqp, "minimize_slsqp", both_slsqp)
    monkeypatch.setattr(_trf, "bounded_least_squares", both_lsq)
    return seen


@pytest.mark.parametrize("axis", ["x", "z"])
def test_the_wu_fits_of_table3_weights_follow_scipy_to_the_bit(axis, monkeypatch):
    seen = _checked(monkeypatch)
    w = np.abs(_table3(axis).response(F_LOG))
    res = fit_wu(F_LOG, w, band=(0.01, 30.0))
    kinds = {k for k, _ in seen}
    assert kinds == {"slsqp", "lsq"} and len(seen) > 20
    assert res.coverage_pct == 100.0


def test_the_wu_fits_of_a_noisy_wmax_follow_scipy_to_the_bit(monkeypatch):
    # the maximum over 27 'trials' of a smooth relative error plus estimator noise (as
    # tests/test_uncertainty.py's noisy W_max), on the log grid: many local fits, some
    # stopped by their budget
    rng = np.random.default_rng(11)
    base = np.abs(_table3("y").response(F_LOG))
    errs = [base * np.abs(np.interp(np.log(F_LOG), np.linspace(np.log(0.01), np.log(30), 9),
                                    rng.uniform(0.2, 1.0, 9))
                          + 0.15 * (rng.standard_normal(F_LOG.size)
                                    + 1j * rng.standard_normal(F_LOG.size)))
            for _ in range(27)]
    seen = _checked(monkeypatch)
    fit_wu(F_LOG, np.max(errs, axis=0), band=(0.05, 30.0))
    fit_wu(F_LOG, np.max(errs, axis=0), band=(0.05, 30.0), cost="paper")
    assert {k for k, _ in seen} == {"slsqp", "lsq"}


def _rosenbrock_in_a_disc():
    """min Rosenbrock in n = 4 subject to |x|² ≤ r², bounds on two variables."""
    def fun(x):
        f = float(np.sum(100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2))
        g = np.zeros_like(x)
        g[:-1] = -400.0 * x[:-1] * (x[1:] - x[:-1] ** 2) - 2 * (1 - x[:-1])
        g[1:] += 200.0 * (x[1:] - x[:-1] ** 2)
        return f, g

    def ineq(x):
        return np.array([1.5 - x @ x, x[0] + 2.0])

    def ineq_jac(x):
        return np.vstack([-2 * x, [1.0, 0.0, 0.0, 0.0]])

    bounds = (np.array([-np.inf, -1.0, -np.inf, 0.0]), np.array([np.inf, 2.0, np.inf, 0.9]))
    return fun, ineq, ineq_jac, bounds


@pytest.mark.parametrize("x0, maxiter, status", [
    ([-1.2, 1.0, 0.5, 0.5], 100, 0),       # converges
    ([-1.2, 1.0, 0.5, 0.5], 5, 9),         # iteration limit
    ([3.0, -2.0, 0.1, 2.0], 100, 0),       # start outside the bounds: clipped
])
def test_a_constrained_problem_follows_scipy(x0, maxiter, status):
    fun, ineq, ineq_jac, bounds = _rosenbrock_in_a_disc()
    ours = _slsqp.minimize_slsqp(fun, np.array(x0), bounds, ineq, ineq_jac,
                                 maxiter=maxiter, ftol=1e-8)
    _assert_same_slsqp(ours, _scipy_slsqp(fun, np.array(x0), bounds, ineq, ineq_jac,
                                          maxiter, 1e-8))
    assert ours.status == status and ours.success == (status == 0)


def test_incompatible_constraints_follow_scipy():
    # x ≥ 1 and x ≤ −1 at once: no point satisfies both. scipy 1.17 relaxes the
    # linearised constraints and ends at the line search (exit mode 8), unsuccessful
    def fun(x):
        return float(x @ x), 2 * x

    def ineq(x):
        return np.array([x[0] - 1.0, -1.0 - x[0]])

    def ineq_jac(x):
        return np.array([[1.0, 0.0], [-1.0, 0.0]])

    bounds = (np.full(2, -np.inf), np.full(2, np.inf))
    ours = _slsqp.minimize_slsqp(fun, np.array([0.3, 0.2]), bounds, ineq, ineq_jac,
                                 maxiter=50, ftol=1e-8)
    _assert_same_slsqp(ours, _scipy_slsqp(fun, np.array([0.3, 0.2]), bounds, ineq,
                                          ineq_jac, 50, 1e-8))
    assert ours.status == 8 and not ours.success


def test_without_the_kernel_the_minimisation_is_scipys(monkeypatch):
    # a scipy other than the release the driver copies: scipy.optimize.minimize itself
    fun, ineq, ineq_jac, bounds = _rosenbrock_in_a_disc()
    monkeypatch.setattr(_slsqp, "load_kernel", lambda: None)
    x0 = np.array([-1.2, 1.0, 0.5, 0.5])
    ours = _slsqp.minimize_slsqp(fun, x0, bounds, ineq, ineq_jac, maxiter=100, ftol=1e-8)
    _assert_same_slsqp(ours, _scipy_slsqp(fun, x0, bounds, ineq, ineq_jac, 100, 1e-8))


def test_a_wu_fit_imports_no_scipy_optimize():
    # the reason the copies exist: a process that fits Wu (fit-uncertainty, a worker of
    # the run's pool) loads scipy's SLSQP kernel alone
    code = ("import sys, numpy as np\n"
            "from armfit.uncertainty import fit_wu\n"
            "f = np.logspace(-1, 1.4, 60)\n"
            "r = fit_wu(f, 0.3 + 0.1 * np.cos(f), band=(0.1, 25.0))\n"
            "print(r.coverage_pct, 'scipy.optimize' in sys.modules,\n"
            "      'scipy.optimize._slsqplib' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["100.0", "False", "True"]
