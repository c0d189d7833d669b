"""numpy.linalg.solve's LAPACK kernels called directly, for the many small systems of a
fit.

The diagnosis's joint fits solve thousands of small systems: each trust-region step's
5 × 5 blocks and its Schur complement, several times a step. On such systems
``numpy.linalg.solve`` spends 6 µs of a call's 10 in Python (checks, type conversions,
an error state set up anew each call): about 7 % of the fits' CPU time.
:func:`linalg_solve` calls the same LAPACK kernels (``numpy.linalg._umath_linalg``,
there since numpy 1.8) with the same arguments, so the numbers are the same to the bit
(``tests/test_lapack.py``); where numpy has no such module it calls
``numpy.linalg.solve`` instead. (``numpy.linalg.lstsq``'s wrapper costs 6 µs of 33 on
a Levy start's system: not worth a second private call.)

A singular matrix raises :class:`numpy.linalg.LinAlgError`, as ``numpy.linalg.solve``
does, under the error state it holds around its kernel: :func:`solving`, made once for
a caller's several solves in a row.

:func:`norm` is ``numpy.linalg.norm`` of a vector by numpy's own operations, without its
argument handling (3 µs a call): the solvers' iterations take tens of thousands.
"""

from __future__ import annotations

import numpy as np

try:    # numpy 1.8 and later; private, hence the fallbacks below
    from numpy.linalg import _umath_linalg
    _SOLVE = (_umath_linalg.solve, _umath_linalg.solve1)
except (ImportError, AttributeError):  # pragma: no cover - another numpy layout
    _SOLVE = None

__all__ = ["linalg_solve", "norm", "solving"]


def _singular(err: str, flag: int) -> None:
    raise np.linalg.LinAlgError("Singular matrix")


def solving() -> np.errstate:
    """The error state ``numpy.linalg.solve`` holds around its kernel, for the ``with``
    block of one or more :func:`linalg_solve` calls: a singular matrix raises
    LinAlgError; overflow, division and underflow are not reported.

    Returns
    -------
    numpy.errstate
    """
    return np.errstate(call=_singular, invalid="call", over="ignore", divide="ignore",
                       under="ignore")


def linalg_solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``numpy.linalg.solve(a, b)`` of float64 arrays, the same numbers.

    Parameters
    ----------
    a : ndarray, shape (..., n, n)
        Square matrices, float64.
    b : ndarray, shape (n,) or (..., n, k)
        One right-hand side (1-D: LAPACK's one-vector kernel, as numpy uses it), or a
        stack of matrices, float64.

    Returns
    -------
    ndarray
        The solutions, of ``b``'s shape. Call it inside :func:`solving` for a singular
        matrix to raise as ``numpy.linalg.solve`` does.
    """
    if _SOLVE is None:   # pragma: no cover - another numpy layout
        return np.linalg.solve(a, b)
    return _SOLVE[b.ndim == 1](a, b, signature="dd->d")


def norm(x: np.ndarray, ord=None) -> np.floating:
    """``numpy.linalg.norm(x, ord)`` of a real vector, the same number: the 2-norm
    (``ord`` None; the square root of the vector's dot product with itself, raveled as
    numpy ravels it) or the largest magnitude (``ord=np.inf``).

    Parameters
    ----------
    x : ndarray, shape (n,)
        Float64.
    ord : {None, numpy.inf}

    Returns
    -------
    numpy.float64
    """
    if ord is None:
        x = x.ravel(order="K")
        return np.sqrt(x.dot(x))
    return abs(x).max()
