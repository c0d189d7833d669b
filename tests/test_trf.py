"""armfit._trf.bounded_least_squares: scipy's trust-region-reflective solver without
importing scipy.optimize.

The reference is an independent computation: scipy.optimize.least_squares itself
(method "trf", x_scale 1 or "jac"), run on the same problem with the same start, bounds,
tolerances and budget. The copy must give its result to the bit (every field: the end
point, cost, residuals, Jacobian, gradient, optimality, active bounds, evaluations and
status), on the fits armfit makes and on problems that take each branch of the method:
reflections off a bound, rejected steps, residuals that are not finite, a rank-deficient
Jacobian, a spent budget, and a box with no finite bound (scipy's unbounded variant)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares as scipy_least_squares

from armfit import _trf, fitting
from armfit.fitting import fit_response
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import EFFECTS

FIELDS = ("x", "cost", "fun", "jac", "grad", "optimality", "active_mask", "nfev", "njev",
          "status", "message", "success")


def _scipy(fun, x0, jac, bounds, **opts):
    return scipy_least_squares(fun, x0, jac=jac, bounds=bounds, method="trf", x_scale=1.0,
                               **opts)


def _assert_same(ours, theirs):
    for k in FIELDS:
        assert np.array_equal(getattr(ours, k), theirs[k]), k


T = np.linspace(0.0, 4.0, 60)


def _decay(seed: int, amplitude: tuple[float, float] = (0.5, 3.0), noise: float = 0.01):
    """A noisy decay y = A exp(−k t) + c, A drawn from ``amplitude``: residuals and
    Jacobian of (A, k, c)."""
    rng = np.random.default_rng(seed)
    A, k, c = rng.uniform(*amplitude), rng.uniform(0.3, 2.5), rng.uniform(-1, 1)
    y = A * np.exp(-k * T) + c + noise * rng.standard_normal(T.size)

    def fun(x):
        return x[0] * np.exp(-x[1] * T) + x[2] - y

    def jac(x):
        e = np.exp(-x[1] * T)
        return np.column_stack([e, -x[0] * T * e, np.ones_like(e)])

    return fun, jac, rng


# bounds that cut off some optima (k ≤ 1.5, c ≥ −0.5): the reflective steps are taken
LB, UB = np.array([0.0, 0.0, -0.5]), np.array([5.0, 1.5, 2.0])


@pytest.mark.parametrize("opts", [
    {"max_nfev": 200, "ftol": 1e-10, "xtol": 1e-10, "gtol": 1e-10},
    {"max_nfev": 200, "ftol": 1e-6, "xtol": 1e-6},
    {"ftol": 1e-12, "xtol": 1e-12, "gtol": 1e-12},
    {"max_nfev": 6, "ftol": 1e-12, "xtol": 1e-12, "gtol": 1e-12},   # budget spent
])
def test_bounded_decays_follow_scipy_to_the_bit(opts, monkeypatch):
    reflected = []
    real = _trf._select_step
    monkeypatch.setattr(_trf, "_select_step",
                        lambda x, J_h, diag_h, g_h, p, *a: reflected.append(
                            not _trf._in_bounds(x + p, LB, UB)) or real(x, J_h, diag_h, g_h,
                                                                        p, *a))
    statuses = set()
    for seed in range(25):
        fun, jac, rng = _decay(seed)
        x0 = rng.uniform(LB, UB)
        if seed == 0:
            x0[1] = UB[1]          # on a bound: moved strictly inside, as scipy moves it
        ours = _trf.bounded_least_squares(fun, x0, jac, (LB, UB), **opts)
        _assert_same(ours, _scipy(fun, x0, jac, (LB, UB), **opts))
        statuses.add(ours.status)
    if opts.get("max_nfev") == 6:
        assert statuses == {0}
    else:
        assert 0 not in statuses
        assert any(reflected), "no step met a bound: the reflective path was not exercised"


@pytest.mark.parametrize("seed", range(6))
def test_jacobian_scaling_follows_scipy_to_the_bit(seed):
    # x_scale="jac" (the Wu fits' least-squares starts): the variables scaled by the
    # norms of the Jacobian's columns, here of very different sizes (A of 50-300
    # against k and c of about 1), the upper bound of k active for some seeds
    fun, jac, rng = _decay(seed, amplitude=(50.0, 300.0), noise=0.5)
    bounds = (np.array([0.0, 0.0, -np.inf]), np.array([400.0, 1.5, np.inf]))
    x0 = np.array([rng.uniform(1, 400), rng.uniform(0.1, 1.4), 0.0])
    opts = {"ftol": 1e-10, "xtol": 1e-10}
    ours = _trf.bounded_least_squares(fun, x0, jac, bounds, x_scale="jac", **opts)
    theirs = scipy_least_squares(fun, x0, jac=jac, bounds=bounds, method="trf",
                                 x_scale="jac", **opts)
    _assert_same(ours, theirs)
    assert ours.success


def test_rejected_and_non_finite_steps_follow_scipy():
    # residuals are not finite beyond x0 = 2 (inside the box), the optimum lies beyond:
    # steps there shrink the trust region without counting as a reduction
    def fun(x):
        r = np.array([x[0] - 3.0, 10 * (x[1] - x[0] ** 2), 1 - x[1]])
        return np.where(x[0] > 2.0, np.nan, r)

    def jac(x):
        return np.array([[1.0, 0.0], [-20 * x[0], 10.0], [0.0, -1.0]])

    shrunk = []
    for x0 in ([0.5, 0.2], [1.9, -1.0], [-1.5, 2.0]):
        bounds = (np.array([-2.0, -3.0]), np.array([4.0, 4.0]))
        ours = _trf.bounded_least_squares(fun, np.array(x0), jac, bounds, max_nfev=100)
        _assert_same(ours, _scipy(fun, np.array(x0), jac, bounds, max_nfev=100))
        shrunk.append(ours.nfev > ours.njev)
    assert any(shrunk), "no step was rejected"


def test_rank_deficient_jacobian_follows_scipy():
    # two parameters that enter only as their sum: the Jacobian has rank 1 of 2
    y = np.array([1.0, 2.0, 2.9, 4.2])
    t = np.arange(4.0)

    def fun(x):
        return (x[0] + x[1]) * t + 0.5 - y

    def jac(x):
        return np.column_stack([t, t])

    bounds = (np.array([0.0, -1.0]), np.array([2.0, 0.5]))
    ours = _trf.bounded_least_squares(fun, np.array([1.5, 0.4]), jac, bounds)
    _assert_same(ours, _scipy(fun, np.array([1.5, 0.4]), jac, bounds))
    assert ours.success


def test_fits_of_arm_responses_follow_scipy_to_the_bit(monkeypatch):
    """Every solve of armfit's fits (the global search's polish, and the local fits made
    one by one) on measured-like responses: the base model, the paper's cost, and a
    model with a delay (its Jacobian's columns joined from two arrays)."""
    calls = []
    real = _trf.bounded_least_squares

    def both(fun, x0, jac, bounds, **opts):
        ours = real(fun, x0, jac, bounds, **opts)
        _assert_same(ours, _scipy(fun, x0, jac, bounds, **opts))
        calls.append(ours.status)
        return ours

    monkeypatch.setattr(_trf, "bounded_least_squares", both)
    rng = np.random.default_rng(3)
    f = np.geomspace(0.1, 30.0, 60)
    truth = {"Ma": 0.18, "k1": 85.0, "k2": 650.0, "b1": 7.2, "b2": 3.1}
    base = ClosedLoopModel.for_axis("x")
    for model, extra in ((base, {}), (base.with_effect(EFFECTS["delay"]),
                                      {"delay.delay_s": 0.012})):
        h = model.response(f, {**truth, **extra}) * (
            1 + 0.02 * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)))
        for cost in ("complex", "paper"):
            fit_response(model, f, h, cost=cost, strict=False, jackknife_bands=0)
    # the fits with fewer than _MIN_TOGETHER starts are solved one by one
    prob, _, _ = fitting._problem(base, f, h, None, None, None, "complex")
    typical = prob.space.to_z(np.array([p.typical for p in base.params]))
    z0 = prob.space.clip_z(np.vstack([typical, typical + 0.3]))
    fitting.solve_together([prob], [z0], max_nfev=100, ftol=1e-8, xtol=1e-8)
    assert len(calls) >= 6 and any(s > 0 for s in calls)


@pytest.mark.parametrize("x_scale", [1.0, "jac"])
@pytest.mark.parametrize("seed", range(4))
def test_no_finite_bound_follows_scipys_unbounded_variant(seed, x_scale):
    # scipy solves a box with no finite bound by another variant (no reflections, no
    # Coleman-Li scaling); the Wu fits' order 0 is such a problem
    fun, jac, rng = _decay(seed)
    x0 = rng.uniform(LB, UB)
    bounds = (np.full(3, -np.inf), np.full(3, np.inf))
    ours = _trf.bounded_least_squares(fun, x0, jac, bounds, x_scale=x_scale)
    theirs = scipy_least_squares(fun, x0, jac=jac, bounds=bounds, method="trf",
                                 x_scale=x_scale)
    _assert_same(ours, theirs)
    assert ours.success


@pytest.mark.parametrize("x0, bounds, fun, match", [
    ([3.0], ([0.0], [1.0]), lambda x: x, "outside of provided bounds"),
    ([0.5], ([1.0], [1.0]), lambda x: x, "strictly less"),
    ([0.5, 0.5], ([0.0], [1.0]), lambda x: x, "Inconsistent shapes"),
    ([0.5], ([0.0], [1.0]), lambda x: x / 0.0 * 0.0, "not finite in the initial point"),
])
def test_bad_problems_raise_as_scipy(x0, bounds, fun, match):
    def jac(x):
        return np.ones((1, len(x)))
    with np.errstate(all="ignore"), pytest.raises(ValueError, match=match):
        _scipy(fun, np.array(x0), jac, bounds)
    with np.errstate(all="ignore"), pytest.raises(ValueError, match=match):
        _trf.bounded_least_squares(fun, np.array(x0), jac, bounds)

