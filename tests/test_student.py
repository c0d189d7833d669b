"""armfit._student.t_quantile: Student's t quantiles without scipy.special."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.special import stdtrit

from armfit._student import MAX_SERIES_DOF, t_quantile

PROBS = [0.001, 0.025, 0.1, 0.3, 0.49, 0.51, 0.6, 0.75, 0.9, 0.95, 0.975, 0.99, 0.995, 0.999]


@pytest.mark.parametrize("nu", [*range(1, 31), 47, 99, 100, 333, 998, MAX_SERIES_DOF])
def test_quantiles_agree_with_scipys_stdtrit(nu):
    # an independent computation: scipy's cephes stdtrit
    for p in PROBS:
        assert t_quantile(nu, p) == pytest.approx(stdtrit(nu, p), rel=1e-12, abs=0), p


def test_closed_forms_and_table_values():
    # analytic: ν = 1 is Cauchy's tan(π(p − 1/2)); ν = 2 is (2p − 1)/√(2p(1 − p)); and the
    # t₀.₉₇₅ of printed tables (Abramowitz & Stegun, Table 26.10)
    for p in (0.6, 0.9, 0.975, 0.999):
        assert t_quantile(1, p) == pytest.approx(math.tan(math.pi * (p - 0.5)), rel=1e-15)
        assert t_quantile(2, p) == pytest.approx((2 * p - 1) / math.sqrt(2 * p * (1 - p)),
                                                 rel=1e-15)
    table = {1: 12.706, 2: 4.303, 3: 3.182, 5: 2.571, 8: 2.306, 10: 2.228, 30: 2.042,
             120: 1.980}
    for nu, t in table.items():
        assert round(t_quantile(nu, 0.975), 3) == t


def test_symmetry_and_the_middle():
    # t(1 − p) = −t(p); t(1/2) = 0; close to the middle, t ≈ (p − 1/2)/f(0) with
    # f(0) = Γ((ν+1)/2)/(√(νπ) Γ(ν/2)) (the density at 0)
    for nu in (3, 4, 17):
        assert t_quantile(nu, 0.5) == 0.0
        assert t_quantile(nu, 0.2) == -t_quantile(nu, 0.8)
        f0 = math.exp(math.lgamma((nu + 1) / 2) - math.lgamma(nu / 2)) / math.sqrt(nu * math.pi)
        assert t_quantile(nu, 0.5 + 1e-7) == pytest.approx(1e-7 / f0, rel=1e-6)


def test_arrays_broadcast_and_large_dof_are_scipys():
    got = t_quantile([[2], [9]], [0.9, 0.975])
    assert got.shape == (2, 2)
    assert got[1, 1] == pytest.approx(stdtrit(9, 0.975), rel=1e-12)
    big = MAX_SERIES_DOF + 1
    assert t_quantile(big, 0.975) == stdtrit(big, 0.975)


@pytest.mark.parametrize("df, p", [(0, 0.9), (2.5, 0.9), (3, 0.0), (3, 1.0), (3, np.nan)])
def test_refuses_what_it_cannot_answer(df, p):
    with pytest.raises(ValueError):
        t_quantile(df, p)


def test_no_scipy_is_imported():
    code = ("import sys; from armfit._student import t_quantile; t_quantile(5, 0.975); "
            "print(any(m.startswith('scipy') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "False"


def test_a_quantile_asked_again_is_the_one_computed():
    # the quantiles are kept between calls (a study's fits share a few degrees of
    # freedom); the reference: the same Newton solve run afresh, to the bit
    from armfit._student import _upper
    for nu, p in ((195, 0.975), (155, 0.975), (5, 0.975), (195, 0.9)):
        first = t_quantile(nu, p)
        assert t_quantile(nu, p) == first == _upper.__wrapped__(p, nu)
        assert t_quantile(nu, 1 - p) == -first
    assert t_quantile([195, 155], 0.975).tolist() == [_upper.__wrapped__(0.975, 195),
                                                     _upper.__wrapped__(0.975, 155)]
