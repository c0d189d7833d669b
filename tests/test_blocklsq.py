"""The block-arrow least-squares solver (armfit.blocklsq) on problems with a known answer.

The problem: T decays y_i(t) = a_i·exp(−c·t) + e_i with per-trial amplitude a_i and
offset e_i and a shared rate c (nb = 2, k = 1). Expected values: the truth the data were
made from (noise-free data), and scipy.optimize.least_squares on the same problem with
its dense Jacobian (noisy data, and a bound that is active at the optimum).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import optimize

from armfit import blocklsq

T_S = np.linspace(0.0, 4.0, 40)


def _problem(a, e, c, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    y = a[:, None] * np.exp(-c * T_S)[None] + e[:, None]
    y = y + noise * rng.standard_normal(y.shape)
    n = a.size

    def fun(x):
        ab, eb, cc = x[: 2 * n: 2], x[1: 2 * n: 2], x[-1]
        return (ab[:, None] * np.exp(-cc * T_S)[None] + eb[:, None] - y).ravel()

    def jac(x):
        ab, cc = x[: 2 * n: 2], x[-1]
        ex = np.broadcast_to(np.exp(-cc * T_S), (n, T_S.size))
        jb = np.stack([ex, np.ones_like(ex)], axis=-1)              # (T, m, 2)
        js = (-ab[:, None] * T_S[None] * ex)[..., None]             # (T, m, 1)
        return jb, js

    def dense(x):
        jb, js = jac(x)
        J = np.zeros((n * T_S.size, 2 * n + 1))
        for i in range(n):
            J[i * T_S.size:(i + 1) * T_S.size, 2 * i:2 * i + 2] = jb[i]
        J[:, -1] = js.reshape(-1)
        return J

    return fun, jac, dense


def _start(n, c0=0.3):
    return np.concatenate([np.tile([1.0, 0.0], n), [c0]])


def test_noise_free_problem_returns_the_truth():
    a, e, c = np.array([1.0, 2.5, 0.7, 4.0]), np.array([0.1, -0.2, 0.0, 0.3]), 1.3
    fun, jac, _ = _problem(a, e, c)
    n = a.size
    lo, hi = np.full(2 * n + 1, -10.0), np.full(2 * n + 1, 10.0)
    res = blocklsq.solve(fun, jac, _start(n), lo, hi, n_trials=n, n_block=2)
    assert res.status > 0
    np.testing.assert_allclose(res.x[-1], c, rtol=1e-7)
    np.testing.assert_allclose(res.x[: 2 * n: 2], a, rtol=1e-7)
    np.testing.assert_allclose(res.x[1: 2 * n: 2], e, atol=1e-7)
    assert res.cost < 1e-12


@pytest.mark.parametrize("c_hi", [10.0, 1.0])
def test_agrees_with_scipy_trf_with_noise_and_an_active_bound(c_hi):
    # c = 1.3 truth; with c <= 1 the optimum sits on the bound
    a, e, c = np.array([1.0, 2.5, 0.7]), np.array([0.1, -0.2, 0.0]), 1.3
    fun, jac, dense = _problem(a, e, c, noise=0.05, seed=3)
    n = a.size
    lo = np.full(2 * n + 1, -10.0)
    hi = np.concatenate([np.full(2 * n, 10.0), [c_hi]])
    x0 = _start(n)
    res = blocklsq.solve(fun, jac, x0, lo, hi, n_trials=n, n_block=2)
    ref = optimize.least_squares(fun, x0, jac=dense, bounds=(lo, hi), method="trf",
                                 x_scale=1.0, ftol=1e-12, xtol=1e-12, gtol=1e-12)
    np.testing.assert_allclose(res.cost, ref.cost, rtol=1e-6)
    np.testing.assert_allclose(res.x, ref.x, atol=1e-5)
    assert np.all(res.x >= lo) and np.all(res.x <= hi)
    if c_hi == 1.0:
        assert res.x[-1] == pytest.approx(1.0, abs=1e-6)


def test_budget_spent_is_status_zero():
    a, e, c = np.array([1.0, 2.5]), np.array([0.1, -0.2]), 1.3
    fun, jac, _ = _problem(a, e, c)
    n = a.size
    lo, hi = np.full(2 * n + 1, -10.0), np.full(2 * n + 1, 10.0)
    res = blocklsq.solve(fun, jac, _start(n, c0=5.0), lo, hi, n_trials=n, n_block=2,
                         max_nfev=2)
    assert res.status == 0 and res.nfev <= 2
    # never worse than the start
    x0 = _start(n, c0=5.0)
    assert res.cost <= 0.5 * float(fun(x0) @ fun(x0))


def test_shared_covariance_is_the_block_of_the_full_inverse():
    # linear algebra: the shared block of (JᵀJ)⁻¹ is the inverse of the Schur complement
    a, e, c = np.array([1.0, 2.5, 0.7]), np.array([0.1, -0.2, 0.0]), 1.3
    _, jac, dense = _problem(a, e, c)
    x = np.concatenate([np.ravel(np.column_stack([a, e])), [c]])
    jb, js = jac(x)
    J = dense(x)
    full = np.linalg.inv(J.T @ J)
    A, B, C, _, _ = blocklsq._normal(jb, js, np.zeros(jb.shape[:2]))
    np.testing.assert_allclose(blocklsq.normal_covariance(A, B, C), full[-1:, -1:],
                               rtol=1e-9)


# ---------------------------------------------------------------------------
# Grouped shared parameters: a rate per group of trials (one value per subject)
# ---------------------------------------------------------------------------

def _grouped(a, e, rates, group, offset, noise=0.0, seed=0):
    """Decays y_i = a_i·exp(−c_g(i)·t) + e_i + d·t: per-trial a_i, e_i (nb = 2), a rate
    per group c_g (grouped shared) and a slope d shared by all (global): x = [a_0, e_0,
    …, d, c_0, c_1, …]; each trial's local shared columns are (d, c_g(i))."""
    rng = np.random.default_rng(seed)
    c_t = rates[group]
    y = a[:, None] * np.exp(-c_t[:, None] * T_S) + e[:, None] + offset * T_S
    y = y + noise * rng.standard_normal(y.shape)
    n, G = a.size, rates.size
    cols = np.column_stack([np.zeros(n, int), 1 + group])

    def fun(x):
        ab, eb, d, cc = x[: 2 * n: 2], x[1: 2 * n: 2], x[2 * n], x[2 * n + 1:][group]
        return (ab[:, None] * np.exp(-cc[:, None] * T_S) + eb[:, None] + d * T_S
                - y).ravel()

    def jac(x):
        ab, cc = x[: 2 * n: 2], x[2 * n + 1:][group]
        ex = np.exp(-cc[:, None] * T_S)
        jb = np.stack([ex, np.ones_like(ex)], axis=-1)
        js = np.stack([np.broadcast_to(T_S, ex.shape), -ab[:, None] * T_S * ex], axis=-1)
        return jb, js

    def dense(x):
        jb, js = jac(x)
        J = np.zeros((n * T_S.size, 2 * n + 1 + G))
        for i in range(n):
            rows = slice(i * T_S.size, (i + 1) * T_S.size)
            J[rows, 2 * i:2 * i + 2] = jb[i]
            J[rows, 2 * n + cols[i]] = js[i]
        return J

    return fun, jac, dense, cols


def _chunked(jac, n, size, groups):
    """The ``normal`` of :func:`blocklsq.solve` from ``jac``, ``size`` trials at a time."""
    def normal(x, r):
        jb, js = jac(x)
        chunks = [(slice(a, a + size), jb[a:a + size], js[a:a + size], r[a:a + size])
                  for a in range(0, n, size)]
        return blocklsq.normal_blocks(chunks, n, groups)
    return normal


def test_grouped_rates_noise_free_return_the_truth():
    # truth: three groups of trials with their own rates, a slope shared by all
    a = np.array([1.0, 2.5, 0.7, 4.0, 1.5, 3.0])
    e = np.array([0.1, -0.2, 0.0, 0.3, 0.05, -0.1])
    group = np.array([0, 0, 1, 1, 2, 2])
    rates = np.array([0.8, 1.3, 2.1])
    fun, jac, _, cols = _grouped(a, e, rates, group, offset=0.02)
    n = a.size
    x0 = np.concatenate([np.tile([1.0, 0.0], n), [0.0], np.full(3, 1.0)])
    lo, hi = np.full(x0.size, -10.0), np.full(x0.size, 10.0)
    res = blocklsq.solve(fun, jac, x0, lo, hi, n_trials=n, n_block=2, cols=cols)
    assert res.status > 0 and res.cost < 1e-12
    np.testing.assert_allclose(res.x[2 * n + 1:], rates, rtol=1e-7)
    np.testing.assert_allclose(res.x[2 * n], 0.02, atol=1e-8)
    np.testing.assert_allclose(res.x[: 2 * n: 2], a, rtol=1e-7)


@pytest.mark.parametrize("given", ["jacobian", "blocks"])
@pytest.mark.parametrize("c_hi", [10.0, 1.5])
def test_grouped_rates_agree_with_scipy_trf(c_hi, given):
    # the same problem with noise, against scipy's trf on the dense Jacobian; with the
    # rates bounded by 1.5 the last group's (true 2.1) ends on the bound. The solver is
    # given the Jacobian's blocks, or the blocks of JᵀJ and Jᵀr made two trials at a
    # time; the covariance from the result's blocks is that of the dense Jacobian at
    # the solution
    a = np.array([1.0, 2.5, 0.7, 4.0, 1.5])
    e = np.array([0.1, -0.2, 0.0, 0.3, 0.05])
    group = np.array([0, 1, 1, 2, 2])
    rates = np.array([0.8, 1.3, 2.1])
    fun, jac, dense, cols = _grouped(a, e, rates, group, offset=0.02, noise=0.05, seed=5)
    n = a.size
    x0 = np.concatenate([np.tile([1.0, 0.0], n), [0.0], np.full(3, 0.5)])
    lo = np.full(x0.size, -10.0)
    hi = np.concatenate([np.full(2 * n + 1, 10.0), np.full(3, c_hi)])
    if given == "jacobian":
        res = blocklsq.solve(fun, jac, x0, lo, hi, n_trials=n, n_block=2, cols=cols)
    else:
        res = blocklsq.solve(fun, None, x0, lo, hi, n_trials=n, n_block=2, cols=cols,
                             normal=_chunked(jac, n, 2, blocklsq.Groups(cols, 4)))
    ref = optimize.least_squares(fun, x0, jac=dense, bounds=(lo, hi), method="trf",
                                 x_scale=1.0, ftol=1e-12, xtol=1e-12, gtol=1e-12)
    np.testing.assert_allclose(res.cost, ref.cost, rtol=1e-6)
    np.testing.assert_allclose(res.x, ref.x, atol=1e-5)
    if c_hi == 1.5:
        assert res.x[-1] == pytest.approx(1.5, abs=1e-6)
    J = dense(res.x)
    full = np.linalg.pinv(J.T @ J, rcond=1e-12)
    np.testing.assert_allclose(blocklsq.normal_covariance(*res.normal, cols),
                               full[-4:, -4:], rtol=1e-8, atol=1e-12)


def test_grouped_covariance_is_the_block_of_the_full_inverse():
    # linear algebra, as for one shared column: the Schur complement's inverse equals
    # the shared block of the dense (JᵀJ)⁻¹
    a = np.array([1.0, 2.5, 0.7, 4.0])
    e = np.array([0.1, -0.2, 0.0, 0.3])
    group = np.array([0, 1, 1, 0])
    rates = np.array([0.8, 1.3])
    _, jac, dense, cols = _grouped(a, e, rates, group, offset=0.02)
    x = np.concatenate([np.ravel(np.column_stack([a, e])), [0.02], rates])
    jb, js = jac(x)
    J = dense(x)
    full = np.linalg.inv(J.T @ J)
    A, B, C, _, _ = blocklsq._normal(jb, js, np.zeros(jb.shape[:2]),
                                     blocklsq.Groups(cols, 3))
    np.testing.assert_allclose(blocklsq.normal_covariance(A, B, C, cols),
                               full[-3:, -3:], rtol=1e-9)


# ---------------------------------------------------------------------------
# The normal equations' blocks, made a few trials at a time (no Jacobian held)
# ---------------------------------------------------------------------------

def _grouped_at_truth():
    a = np.array([1.0, 2.5, 0.7, 4.0, 1.5])
    e = np.array([0.1, -0.2, 0.0, 0.3, 0.05])
    group = np.array([0, 1, 1, 2, 0])
    rates = np.array([0.8, 1.3, 2.1])
    fun, jac, dense, cols = _grouped(a, e, rates, group, offset=0.02, noise=0.05, seed=2)
    x = np.concatenate([np.ravel(np.column_stack([a, e])) * 1.1, [0.01], rates * 0.9])
    return fun, jac, dense, cols, x


def test_normal_blocks_a_few_trials_at_a_time_are_those_of_the_dense_jacobian():
    # independent computation: JᵀJ and Jᵀr of the dense Jacobian, cut into the blocks
    # (per-trial A and B in the trial's local columns, C and gs over the shared values)
    fun, jac, dense, cols, x = _grouped_at_truth()
    n = cols.shape[0]
    J, r = dense(x), fun(x)
    H, g = J.T @ J, J.T @ r
    groups = blocklsq.Groups(cols, 4)
    A, B, C, gb, gs = _chunked(jac, n, 2, groups)(x, r.reshape(n, -1))
    for i in range(n):
        b = slice(2 * i, 2 * i + 2)
        np.testing.assert_allclose(A[i], H[b, b], rtol=1e-12)
        np.testing.assert_allclose(B[i], H[b][:, 2 * n + cols[i]], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(gb[i], g[b], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(C, H[2 * n:, 2 * n:], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(gs, g[2 * n:], rtol=1e-12, atol=1e-12)


def test_normal_blocks_of_one_shared_column_are_those_of_the_dense_jacobian():
    # the plain block-arrow problem (no groups), three trials then one at a time
    a, e, c = np.array([1.0, 2.5, 0.7, 4.0]), np.array([0.1, -0.2, 0.0, 0.3]), 1.3
    fun, jac, dense = _problem(a, e, c, noise=0.05, seed=1)
    n = a.size
    x = np.concatenate([np.ravel(np.column_stack([a, e])) * 0.9, [1.1]])
    J, r = dense(x), fun(x)
    H, g = J.T @ J, J.T @ r
    A, B, C, gb, gs = _chunked(jac, n, 3, None)(x, r.reshape(n, -1))
    for i in range(n):
        b = slice(2 * i, 2 * i + 2)
        np.testing.assert_allclose(A[i], H[b, b], rtol=1e-12)
        np.testing.assert_allclose(B[i], H[b, -1:], rtol=1e-12)
        np.testing.assert_allclose(gb[i], g[b], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(C, H[-1:, -1:], rtol=1e-12)
    np.testing.assert_allclose(gs, g[-1:], rtol=1e-12)


def test_the_model_of_the_cost_along_a_step_is_that_of_the_dense_jacobian():
    # q(s0 + t s) = a t² + b t + c with a = ½(‖J_h s‖² + sᵀdiag(c_h)s), ... from the
    # scaled dense Jacobian J_h = J diag(d): the blocks give the same numbers
    fun, jac, dense, cols, x = _grouped_at_truth()
    n = cols.shape[0]
    rng = np.random.default_rng(4)
    J, r = dense(x), fun(x)
    groups = blocklsq.Groups(cols, 4)
    A, B, C, gb, gs = blocklsq._normal(*jac(x), r.reshape(n, -1), groups)
    d, c = rng.uniform(0.5, 2.0, x.size), rng.uniform(0.0, 1.0, x.size)
    sub = blocklsq._Scaled(A, B, C, gb, gs, d[: 2 * n].reshape(n, 2), d[2 * n:],
                           c[: 2 * n].reshape(n, 2), c[2 * n:], groups)
    s, s0 = rng.standard_normal(x.size), rng.standard_normal(x.size)
    Jh, gh = J * d, d * (J.T @ r)
    want = (0.5 * (np.sum((Jh @ s) ** 2) + s @ (c * s)),
            gh @ s + (Jh @ s) @ (Jh @ s0) + s0 @ (c * s),
            0.5 * (np.sum((Jh @ s0) ** 2) + s0 @ (c * s0)) + gh @ s0)
    np.testing.assert_allclose(sub.quadratic_1d(s, s0), want, rtol=1e-10)
    np.testing.assert_allclose(sub.value(s), want[0] + gh @ s, rtol=1e-10)


@pytest.mark.parametrize("shared", ["none", "one", "grouped"])
def test_a_second_solve_at_the_same_alpha_is_that_of_a_fresh_subproblem(shared):
    # the subproblem keeps its blocks at α for the next solve at the same α (Moré's
    # iteration asks twice at each α): that solve is, bit for bit, the one a fresh
    # subproblem makes from scratch, and both are (H_h + αI)⁻¹ r of the dense scaled
    # Jacobian J_h = J·diag(d), H_h = J_hᵀJ_h + diag(c) (independent computation); so is
    # a solve at another α, and one back at the first. Shared parameters: none (the
    # base model's joint fit), one for all trials, or grouped
    if shared == "grouped":
        fun, jac, dense, cols, x = _grouped_at_truth()
        groups = blocklsq.Groups(cols, 4)
    else:
        a = np.array([1.0, 2.5, 0.7, 4.0])
        fun, jac, dense = _problem(a, a / 10, 0.9, noise=0.05, seed=3)
        x, cols, groups = _start(a.size, 0.7), None, None
    n = jac(x)[0].shape[0]
    A, B, C, gb, gs = blocklsq._normal(*jac(x), fun(x).reshape(n, -1), groups)
    J = dense(x)
    if shared == "none":       # the per-trial columns alone
        A, B, C, gs, J = A, B[..., :0], C[:0, :0], gs[:0], J[:, : 2 * n]
    rng = np.random.default_rng(8)
    d, c = rng.uniform(0.5, 2.0, J.shape[1]), rng.uniform(0.0, 1.0, J.shape[1])

    def fresh():
        return blocklsq._Scaled(A, B, C, gb, gs, d[: 2 * n].reshape(n, 2), d[2 * n:],
                                c[: 2 * n].reshape(n, 2), c[2 * n:], groups)

    Jh = J * d
    H = Jh.T @ Jh + np.diag(c)
    sub = fresh()
    rs = rng.standard_normal((3, J.shape[1]))
    for alpha, r in ((0.3, rs[0]), (0.3, rs[1]), (0.3, rs[2]), (0.05, rs[0]), (0.05, rs[2]),
                     (0.3, rs[1])):
        rb, rsh = r[: 2 * n].reshape(n, 2), r[2 * n:]
        got, want = sub.solve(alpha, rb, rsh), fresh().solve(alpha, rb, rsh)
        for p, q in zip(got, want, strict=True):
            np.testing.assert_array_equal(p, q)
        np.testing.assert_allclose(np.concatenate([got[0].ravel(), got[1]]),
                                   np.linalg.solve(H + alpha * np.eye(H.shape[0]), r),
                                   rtol=1e-9, atol=1e-12)


def test_the_cost_model_of_a_step_with_itself_is_that_of_a_step_with_its_copy():
    # q's curvature term sᵀHs takes the cross term of the shared block once when both
    # vectors are the same array: the same bits as for two equal arrays (the general
    # path, each cross term made on its own), whatever the grouping of the shared columns
    fun, jac, dense, cols, x = _grouped_at_truth()
    n = cols.shape[0]
    rng = np.random.default_rng(23)
    for groups in (blocklsq.Groups(cols, 4), None):
        jb, js = jac(x)
        if groups is None:
            js = js[..., :1]
        A, B, C, gb, gs = blocklsq._normal(jb, js, fun(x).reshape(n, -1), groups)
        k = gs.size
        d, c = rng.uniform(0.5, 2.0, 2 * n + k), rng.uniform(0.0, 1.0, 2 * n + k)
        sub = blocklsq._Scaled(A, B, C, gb, gs, d[: 2 * n].reshape(n, 2), d[2 * n:],
                               c[: 2 * n].reshape(n, 2), c[2 * n:], groups)
        s = rng.standard_normal(2 * n + k)
        assert sub.hdot(s, s) == sub.hdot(s, s.copy())
        Jh = (dense(x)[:, : 2 * n + k] if groups is None else dense(x)) * d
        np.testing.assert_allclose(sub.hdot(s, s), np.sum((Jh @ s) ** 2), rtol=1e-10)


def _same(a: blocklsq.BlockResult, b: blocklsq.BlockResult) -> None:
    """Bit for bit: the solution, its cost, residuals, blocks, status and evaluations."""
    np.testing.assert_array_equal(a.x, b.x)
    assert a.cost == b.cost and a.status == b.status and a.nfev == b.nfev
    np.testing.assert_array_equal(a.fun, b.fun)
    for p, q in zip(a.normal, b.normal, strict=True):
        np.testing.assert_array_equal(p, q)


@pytest.mark.parametrize("c_hi", [10.0, 1.0])
@pytest.mark.parametrize("ftol", [1e-8, 1e-5, 1e-3, 0.3])
def test_a_brief_run_that_watches_a_tolerance_gives_that_run_bit_for_bit(c_hi, ftol):
    # the reference: the long run made in one go from the same start (noisy data, and
    # with c <= 1 a bound the steps reflect off); a brief run of every budget from 1 to
    # 25 evaluations watching its ftol either saw it stop (watched) or resumes into it
    a, e, c = np.array([1.0, 2.5, 0.7]), np.array([0.1, -0.2, 0.0]), 1.3
    fun, jac, _ = _problem(a, e, c, noise=0.05, seed=3)
    n = a.size
    lo = np.full(2 * n + 1, -10.0)
    hi = np.concatenate([np.full(2 * n, 10.0), [c_hi]])
    for x0 in (_start(n), _start(n, c0=5.0)):
        kw = dict(n_trials=n, n_block=2)
        full = blocklsq.solve(fun, jac, x0, lo, hi, max_nfev=60, ftol=ftol, **kw)
        seen = set()
        for budget in range(1, 26):
            for final in (True, False):
                brief = blocklsq.solve(fun, jac, x0, lo, hi, max_nfev=budget,
                                       final_normal=final, watch_ftol=ftol, **kw)
                plain = blocklsq.solve(fun, jac, x0, lo, hi, max_nfev=budget, **kw)
                # watching, or leaving the last blocks out, changes nothing of the run
                np.testing.assert_array_equal(brief.x, plain.x)
                assert brief.cost == plain.cost and brief.nfev == plain.nfev
                assert brief.normal is not None or not final
                if brief.watched is not None:
                    _same(brief.watched, full)
                    seen.add("watched")
                else:
                    assert brief.state is not None and brief.status == 0
                    _same(blocklsq.solve(fun, jac, x0, lo, hi, max_nfev=60, ftol=ftol,
                                         resume=brief.state, **kw), full)
                    seen.add("resumed")
        # both ways are taken for every tolerance but the loosest (which stops at once)
        assert "watched" in seen and ("resumed" in seen or ftol == 0.3)
