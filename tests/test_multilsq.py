"""armfit.multilsq: many bounded least-squares problems solved together, each as
scipy.optimize.least_squares (method "trf", x_scale 1) solves it alone.

The reference is an independent computation: scipy's own solver run on every problem
separately, with the same starts, bounds, tolerances and budget. Only the rounding
differs (batched SVDs and products), and a path amplifies it: the ends agree to far
within the tolerances asked, with the same number of evaluations and the same stop."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

import armfit.multilsq as multilsq
from armfit.fitting import ParamSpace, _Problem, band_jackknife, solve_together
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import EFFECTS

T = np.linspace(0.0, 4.0, 60)


def _decays(n: int, seed: int):
    """n noisy exponential decays y = A exp(−k t) + c and their residual functions."""
    rng = np.random.default_rng(seed)
    A, k, c = rng.uniform(0.5, 3, n), rng.uniform(0.3, 2.5, n), rng.uniform(-1, 1, n)
    Y = A[:, None] * np.exp(-k[:, None] * T) + c[:, None] + 0.01 * rng.standard_normal((n, T.size))

    def fun(X, rows):
        return X[:, :1] * np.exp(-X[:, 1:2] * T) + X[:, 2:3] - Y[rows]

    def jac(X, rows):
        e = np.exp(-X[:, 1:2] * T)
        return np.stack([e, -X[:, :1] * T * e, np.ones_like(e)], axis=2)

    return fun, jac, rng


def _one(fun, i):
    return lambda x: fun(x[None], np.array([i]))[0]


# bounds that cut off some optima (k ≤ 1.5, c ≥ −0.5): the reflective steps are taken
LB, UB = np.array([0.0, 0.0, -0.5]), np.array([5.0, 1.5, 2.0])


@pytest.mark.parametrize("opts", [
    {"max_nfev": 200, "ftol": 1e-10, "xtol": 1e-10, "gtol": 1e-10},
    {"max_nfev": 200, "ftol": 1e-6, "xtol": 1e-6},
    {"max_nfev": 6, "ftol": 1e-12, "xtol": 1e-12, "gtol": 1e-12},   # budget spent
])
def test_each_problem_follows_scipys_path(opts, monkeypatch):
    fun, jac, rng = _decays(40, seed=0)
    x0 = rng.uniform(LB, UB, (40, 3))
    bounded = []
    real = multilsq._select_step
    monkeypatch.setattr(multilsq, "_select_step",
                        lambda *a: bounded.append(1) or real(*a))
    res = multilsq.solve_many(fun, jac, x0, LB, UB, **opts)
    assert bounded, "no step met a bound: the reflective path was not exercised"
    for i in range(40):
        ref = least_squares(_one(fun, i), x0[i], jac=_one(jac, i), bounds=(LB, UB),
                            method="trf", x_scale=1.0, **opts)
        np.testing.assert_allclose(res.x[i], ref.x, rtol=0, atol=1e-9)
        assert res.nfev[i] == ref.nfev
        assert res.cost[i] == pytest.approx(ref.cost, rel=1e-12, abs=1e-300)
        np.testing.assert_allclose(res.fun[i], ref.fun, rtol=0, atol=1e-9)
        # converged alike (which test stops the last, tiny step is a matter of the last
        # bits: ftol and xtol together or xtol alone; and scipy reports gtol (1) when the
        # gradient at the last accepted point is also below it, see solve_many)
        assert (res.status[i] > 0) == (ref.status > 0)
    if opts["max_nfev"] == 6:
        assert (res.status == 0).sum() > 0 and np.all(res.nfev[res.status == 0] == 6)


def test_non_finite_residuals_shrink_the_radius_as_scipy_does():
    """Residuals that overflow past x₁ > 2 (a start far out): the step is retried with a
    quarter of its length as radius, as in scipy."""
    fun0, jac0, rng = _decays(12, seed=3)

    def fun(X, rows):
        r = fun0(X, rows)
        return np.where(X[:, :1] > 2.0, np.inf, r)

    x0 = np.column_stack([rng.uniform(0.2, 1.9, 12), rng.uniform(0.1, 1.4, 12),
                          rng.uniform(-0.4, 1.9, 12)])
    res = multilsq.solve_many(fun, jac0, x0, LB, UB, max_nfev=100)
    for i in range(12):
        ref = least_squares(_one(fun, i), x0[i], jac=_one(jac0, i), bounds=(LB, UB),
                            method="trf", x_scale=1.0, max_nfev=100)
        np.testing.assert_allclose(res.x[i], ref.x, rtol=0, atol=1e-8)
        assert res.nfev[i] == ref.nfev


def _arm_problem():
    """The 5-parameter arm model plus a delay, fitted to a response with a 12 ms delay
    and 1 % multiplicative noise (the delay-and-arm problem of the diagnosis's adopt)."""
    model = ClosedLoopModel.for_axis("x").with_effect(EFFECTS["delay"])
    f = np.geomspace(0.1, 30, 100)
    truth = {"Ma": 0.18, "k1": 85.0, "k2": 650.0, "b1": 7.2, "b2": 3.1, "delay.delay_s": 0.012}
    rng = np.random.default_rng(5)
    h = model.response(f, truth) * (1 + 0.01 * (rng.standard_normal(100)
                                                + 1j * rng.standard_normal(100)))
    space = ParamSpace.of(model)
    prob = _Problem(model, space, f, h, np.full(100, 1 / 0.1), np.full(100, 1 / 0.6),
                    "complex")
    return prob, space, truth


@pytest.mark.parametrize("cost", ["complex", "paper"])
@pytest.mark.parametrize("effect", [None, *sorted(EFFECTS)])
def test_analytic_jacobian_is_the_central_differences(effect, cost):
    """The batched fits' Jacobian (the arm parameters' columns from ∂ ln H/∂θ of eq. 3)
    against central differences of the residuals (step 1e-6 in z, an independent
    computation), with every effect of the library, under both costs, at three points
    near Table I's values (an effect's parameters mid-range): within 1e-6 of each
    column's largest entry."""
    model = ClosedLoopModel.for_axis("y")
    if effect is not None:
        model = model.with_effect(EFFECTS[effect])
    space = ParamSpace.of(model)
    f = np.geomspace(0.1, 30, 80)
    rng = np.random.default_rng(3)
    arm = {"Ma": 0.18, "k1": 85.0, "k2": 650.0, "b1": 7.2, "b2": 3.1}   # Table I's size
    mid = space.to_z(np.array([arm.get(n, np.sqrt(lo * hi) if log else 0.5 * (lo + hi))
                               for n, log, lo, hi in zip(space.names, space.log, space.lower,
                                                         space.upper, strict=True)]))
    z = space.clip_z(mid + rng.uniform(-0.2, 0.2, (4, mid.size)) * (space.zhi - space.zlo)
                     / np.where(space.log, 10.0, 1.0))
    h = model.response(f, dict(zip(space.names, space.to_theta(z[0]), strict=True)))
    h = h * (1 + 0.05 * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)))
    prob = _Problem(model, space, f, h, np.full(f.size, 1 / 0.2), np.full(f.size, 1 / 1.5),
                    cost)
    got = prob.jacobian_analytic_batch(z[1:])
    want = prob.jacobian_batch(z[1:])
    assert got.shape == want.shape == (3, f.size * (1 if cost == "paper" else 2),
                                       len(space.names))
    scale = np.abs(want).max(axis=1, keepdims=True)
    assert np.all(scale[..., :5] > 0)
    assert np.all(np.abs(got - want) <= 1e-6 * scale)


def test_arm_fits_from_many_starts_match_scipy_one_by_one():
    """The global search's local fits (fitting._global_starts: the starts of the problem
    with unit weights and with its own, solved together) on the arm model: the batched
    Jacobians (analytic arm columns) and residuals give every start scipy's end on its
    own problem with the same functions: the same evaluations and stop, the cost to 1e-7
    (ftol 1e-6; an end in a flat valley may lie elsewhere along it, by 4e-5 in log
    coordinates measured)."""
    prob, space, _ = _arm_problem()
    rng = np.random.default_rng(1)
    z0 = space.clip_z(space.zlo + rng.uniform(0.2, 0.8, (10, len(space.names)))
                      * (space.zhi - space.zlo))
    opts = {"max_nfev": 30 * z0.shape[1], "ftol": 1e-6, "xtol": 1e-6}
    problems = [prob.unweighted(), prob]
    res = solve_together(problems, [z0[:4], z0[4:]], **opts)
    for i in range(len(z0)):
        p = problems[int(i >= 4)]
        ref = least_squares(p.residuals, z0[i], jac=p.jacobian_analytic,
                            bounds=(space.zlo, space.zhi), method="trf", x_scale=1.0,
                            **opts)
        assert (res.nfev[i], res.status[i]) == (ref.nfev, ref.status)
        assert res.cost[i] == pytest.approx(ref.cost, rel=1e-7)
        np.testing.assert_allclose(res.x[i], ref.x, rtol=0, atol=1e-3)


def test_band_jackknife_is_the_refits_without_each_band():
    """band_jackknife (the bands left out by a zero mask, refitted together) against
    scipy's refits on the bins kept, one band at a time, from the same optimum."""
    prob, space, truth = _arm_problem()
    z_true = space.to_z(np.array([truth[n] for n in space.names]))
    best = least_squares(prob.residuals, space.clip_z(z_true),
                         jac=prob.jacobian_analytic, bounds=(space.zlo, space.zhi),
                         method="trf", x_scale=1.0, ftol=1e-12, xtol=1e-12, gtol=1e-12)
    sd, g = band_jackknife(prob, best.x, 6)
    ends = []
    m = prob.f.size
    for part in np.array_split(np.arange(m), g):
        keep = np.setdiff1d(np.arange(m), part)
        r = least_squares(prob.residuals, space.clip_z(best.x),
                          jac=prob.jacobian_analytic, args=(keep,),
                          bounds=(space.zlo, space.zhi), method="trf", x_scale=1.0,
                          max_nfev=50 * best.x.size, ftol=1e-10, xtol=1e-10, gtol=1e-10)
        ends.append(r.x)
    ends = np.array(ends)
    ref = np.sqrt((g - 1) / g * np.sum((ends - ends.mean(axis=0)) ** 2, axis=0))
    assert g == 6
    np.testing.assert_allclose(sd, ref, rtol=1e-6)
    assert np.all(sd > 0)


def test_two_fits_are_scipys_one_by_one():
    """Fewer than three fits (the second opinion's two) go to scipy one by one, through
    the same residuals and masks as a batch: each is scipy's fit of its own problem (the
    second with a band left out by a zero mask, against scipy on the bins kept): the
    same evaluations and stop, the cost to 1e-9, the end within 1e-5 in log coordinates
    (ftol 1e-8 leaves a flat direction free to that order: 1.5e-6 measured)."""
    prob, space, _ = _arm_problem()
    rng = np.random.default_rng(4)
    z0 = space.clip_z(space.zlo + rng.uniform(0.3, 0.7, (2, len(space.names)))
                      * (space.zhi - space.zlo))
    m = prob.f.size
    keep = np.ones((2, m))
    keep[1, 40:60] = 0.0
    opts = {"max_nfev": 300, "ftol": 1e-8, "xtol": 1e-8}
    res = solve_together([prob], [z0], mask=np.concatenate([keep, keep], axis=1), **opts)
    bins = [np.arange(m), np.flatnonzero(keep[1])]
    for i in range(2):
        ref = least_squares(prob.residuals, z0[i], jac=prob.jacobian_analytic,
                            args=(bins[i],), bounds=(space.zlo, space.zhi), method="trf",
                            x_scale=1.0, **opts)
        assert (res.nfev[i], res.status[i]) == (ref.nfev, ref.status)
        assert res.cost[i] == pytest.approx(ref.cost, rel=1e-9)
        np.testing.assert_allclose(res.x[i], ref.x, rtol=0, atol=1e-5)
