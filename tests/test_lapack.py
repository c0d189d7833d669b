"""armfit._lapack: numpy.linalg.solve's kernels called directly give numpy's numbers."""

from __future__ import annotations

import numpy as np
import pytest

from armfit import _lapack


def test_the_direct_solve_is_numpy_linalg_solve_bit_for_bit():
    # the trust-region step calls numpy.linalg.solve's LAPACK kernels without its
    # Python wrapper: the same numbers as numpy.linalg.solve (the reference), for a
    # stack of systems with several right-hand sides, one with a single right-hand side
    # column, and a single system with a vector; positive definite (A + αI, as in a
    # step) and badly conditioned ones
    rng = np.random.default_rng(21)
    for T, n, k, cond in ((1, 5, 3, 1e2), (9, 5, 2, 1e8), (64, 5, 1, 1e12), (3, 7, 4, 1.0)):
        q = np.linalg.qr(rng.standard_normal((T, n, n)))[0]
        a = q @ (np.logspace(0, np.log10(cond), n)[:, None] * np.swapaxes(q, 1, 2))
        a = a + 1e-3 * np.eye(n)
        b = rng.standard_normal((T, n, k))
        with _lapack.solving():
            got = _lapack.linalg_solve(a, b)
            one = _lapack.linalg_solve(a[0], b[0, :, 0])
        np.testing.assert_array_equal(got, np.linalg.solve(a, b))
        np.testing.assert_array_equal(one, np.linalg.solve(a[0], b[0, :, 0]))
    # a singular system raises as numpy.linalg.solve does
    with pytest.raises(np.linalg.LinAlgError), _lapack.solving():
        _lapack.linalg_solve(np.zeros((2, 3, 3)), np.ones((2, 3, 2)))


def test_without_numpys_kernels_module_the_solve_is_numpy_linalg_solve(monkeypatch):
    # another numpy layout (no numpy.linalg._umath_linalg): numpy.linalg.solve itself
    rng = np.random.default_rng(22)
    a = rng.standard_normal((4, 5, 5)) + 5 * np.eye(5)
    b = rng.standard_normal((4, 5, 2))
    monkeypatch.setattr(_lapack, "_SOLVE", None)
    np.testing.assert_array_equal(_lapack.linalg_solve(a, b), np.linalg.solve(a, b))


def test_norm_is_numpys_to_the_bit():
    """``norm`` (the trust-region and block solvers' norms) is numpy.linalg.norm's own
    operations without its argument handling: the same bits for the vectors it takes
    (contiguous, strided, with a zero, tiny and huge components, the empty vector) for
    the 2-norm and the largest magnitude."""
    norm = _lapack.norm
    rng = np.random.default_rng(3)
    vectors = [rng.normal(size=n) * 10.0 ** rng.integers(-150, 150, size=n)
               for n in (1, 2, 5, 21, 160, 1001)]
    vectors += [rng.normal(size=40)[::3], np.zeros(7), np.array([0.0, -0.0, 3.0]),
                rng.normal(size=(6, 5)).T[1], np.zeros(0), rng.normal(size=451) * 1e-9,
                np.array([3.0, 4.0])]
    for v in vectors:
        assert norm(v) == np.linalg.norm(v)
        assert type(norm(v)) is type(np.linalg.norm(v))
        if v.size:
            assert norm(v, ord=np.inf) == np.linalg.norm(v, ord=np.inf)


def test_row_norms_svd_and_einsum_are_numpys_to_the_bit():
    """The lock-step fits' row norms, reduced SVD and einsum (``armfit.multilsq``, the
    block solver, the trust-region solver) give numpy's own numbers: numpy.linalg.norm
    with axis=1, numpy.linalg.svd(full_matrices=False) and numpy.einsum are the
    references, on the shapes the fits use (a stack of augmented Jacobians, strided and
    badly scaled rows, a single fit) and on a rank-deficient matrix."""
    rng = np.random.default_rng(5)
    rows = [rng.normal(size=(14, 5)) * 10.0 ** rng.integers(-150, 150, size=(14, 5)),
            rng.normal(size=(1, 5)), rng.normal(size=(9, 12))[:, ::2], np.zeros((3, 5)),
            np.zeros((0, 5))]
    for x in rows:
        np.testing.assert_array_equal(_lapack.row_norms(x), np.linalg.norm(x, axis=1))
    stacks = [rng.normal(size=(14, 205, 5)), rng.normal(size=(1, 105, 6)) * 1e-8,
              rng.normal(size=(30, 5)), np.zeros((2, 10, 5))]
    stacks.append(np.repeat(rng.normal(size=(1, 40, 1)), 3, axis=2))   # rank one
    stacks.append(rng.normal(size=(4, 5, 40)).transpose(0, 2, 1))       # strided
    for a in stacks:
        got, ref = _lapack.svd(a), np.linalg.svd(a, full_matrices=False)
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_array_equal(g, r)
    with pytest.raises(np.linalg.LinAlgError):
        _lapack.svd(np.full((1, 6, 3), np.nan))
    V, u = rng.normal(size=(14, 5, 5)), rng.normal(size=(14, 5))
    J, f = rng.normal(size=(14, 200, 5)), rng.normal(size=(14, 200))
    for sub, ops in (("kij,kj->ki", (V, u)), ("kmn,km->kn", (J, f)), ("km,km->k", (f, f)),
                     ("tpk,tpq,tql->kl", (J[:, :5], V, J[:, :5]))):
        np.testing.assert_array_equal(_lapack.einsum(sub, *ops), np.einsum(sub, *ops))


def test_without_numpys_private_functions_svd_and_einsum_are_numpys(monkeypatch):
    # another numpy layout: numpy.linalg.svd and numpy.einsum themselves
    rng = np.random.default_rng(6)
    a = rng.normal(size=(3, 20, 4))
    monkeypatch.setattr(_lapack, "_SVD", None)
    monkeypatch.setattr(_lapack, "_C_EINSUM", None)
    for g, r in zip(_lapack.svd(a), np.linalg.svd(a, full_matrices=False), strict=True):
        np.testing.assert_array_equal(g, r)
    np.testing.assert_array_equal(_lapack.einsum("kmn,km->kn", a, a[:, :, 0]),
                                  np.einsum("kmn,km->kn", a, a[:, :, 0]))
