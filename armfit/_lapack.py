"""numpy's linear-algebra kernels called directly, for the many small systems of a fit:
numpy.linalg.solve's and svd's LAPACK kernels, numpy.linalg.norm's operations and the
compiled einsum, each without numpy's wrapper and with numpy's numbers.

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
:func:`row_norms` is the same for the rows of a matrix (``axis=1``), :func:`svd` the
reduced SVD's LAPACK kernel (``gesdd``) without ``numpy.linalg.svd``'s checks and
conversions (8 µs of a 20–30 µs call on a fit's Jacobian), and :func:`einsum` numpy's
compiled ``einsum``, which ``numpy.einsum`` calls when not asked to optimise (2 µs of its
4): the lock-step fits of :mod:`armfit.multilsq` make each of them several times an
iteration, tens of thousands of times in a run. Each gives the same numbers as the
numpy function (``tests/test_lapack.py``).
"""

from __future__ import annotations

import numpy as np

try:    # numpy 1.8 and later; private, hence the fallbacks below
    from numpy.linalg import _umath_linalg
    _SOLVE = (_umath_linalg.solve, _umath_linalg.solve1)
    _SVD = _umath_linalg.svd_s
except (ImportError, AttributeError):  # pragma: no cover - another numpy layout
    _SOLVE = _SVD = None

try:    # what numpy.einsum calls without optimize (numpy 2: _core; 1.x: core)
    from numpy._core.multiarray import c_einsum as _C_EINSUM
except ImportError:  # pragma: no cover - numpy 1.x
    try:
        from numpy.core.multiarray import c_einsum as _C_EINSUM
    except ImportError:
        _C_EINSUM = None

__all__ = ["einsum", "linalg_solve", "norm", "row_norms", "solving", "svd"]


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


def row_norms(x: np.ndarray) -> np.ndarray:
    """``numpy.linalg.norm(x, axis=1)`` of a real matrix, the same numbers: the square
    root of the sum of each row's squares.

    Parameters
    ----------
    x : ndarray, shape (k, n)
        Float64.

    Returns
    -------
    ndarray, shape (k,)
    """
    return np.sqrt(np.add.reduce(x * x, axis=1))


def _no_convergence(err: str, flag: int) -> None:
    raise np.linalg.LinAlgError("SVD did not converge")


def svd(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``numpy.linalg.svd(a, full_matrices=False)`` of float64 matrices, the same numbers.

    Parameters
    ----------
    a : ndarray, shape (..., m, n)
        Float64.

    Returns
    -------
    (U, s, Vh) : ndarrays, shapes (..., m, k), (..., k), (..., k, n), k = min(m, n)
        As numpy returns them; LinAlgError when LAPACK does not converge.
    """
    if _SVD is None:   # pragma: no cover - another numpy layout
        return tuple(np.linalg.svd(a, full_matrices=False))
    with np.errstate(call=_no_convergence, invalid="call", over="ignore", divide="ignore",
                     under="ignore"):
        return _SVD(a, signature="d->ddd")


def einsum(subscripts: str, *operands: np.ndarray) -> np.ndarray:
    """``numpy.einsum(subscripts, *operands)`` (not optimised, numpy's default), the same
    numbers: the compiled function numpy's wrapper calls.

    Parameters
    ----------
    subscripts : str
        As numpy's.
    *operands : ndarray

    Returns
    -------
    ndarray
    """
    if _C_EINSUM is None:   # pragma: no cover - another numpy layout
        return np.einsum(subscripts, *operands)
    return _C_EINSUM(subscripts, *operands)
