"""Order statistics with numpy's numbers, without :mod:`numpy.ma`.

:func:`numpy.median`, :func:`numpy.nanmedian`, :func:`numpy.percentile`,
:func:`numpy.nanpercentile` and :func:`numpy.unique` import :mod:`numpy.ma` at their
first call (numpy checks for a masked array; ``nanmedian`` of short rows works on one),
which adds about 25 ms to the start of every command that takes one: reading a trial
takes a median (its sampling period), a single trial's estimate quartiles. The functions
here give the same numbers bit for bit for real input:

- the median is the middle value of the sorted values, for an even count the two middle
  values added and halved, as numpy's mean of the two does;
- a percentile is numpy's default ("linear", Hyndman & Fan's 7th definition): the sorted
  values at ranks ⌊v⌋ and ⌊v⌋ + 1, v = (n − 1)·q/100, interpolated as numpy's ``_lerp``
  does (from the lower value below the middle, from the upper one above it);
- the NaN-aware forms leave NaN out, each row with its own count; the others give NaN
  where any value is NaN.
"""

from __future__ import annotations

import numpy as np

__all__ = ["median", "nanmedian", "nanpercentile", "percentile", "unique"]


def median(x, axis: int | None = None):
    """:func:`numpy.median` of real values, the same numbers: NaN where any value is NaN
    (or none is given; without numpy's warning).

    Parameters
    ----------
    x : array_like
        Real values (any unit; the result has the same).
    axis : int, optional
        The axis along which the median is taken; None: of all values.

    Returns
    -------
    numpy.float64 or ndarray
        The median; an array of the other axes' shape when ``axis`` is given.
    """
    a = np.asarray(x, dtype=float)
    if axis is None:
        a, axis = a.ravel(), 0
    n = a.shape[axis]
    if n == 0:                      # NaN, as numpy's (without its warning)
        return np.full(np.delete(a.shape, axis), np.nan)[()]
    h = n // 2
    part = np.partition(a, [h - 1, h, n - 1] if n % 2 == 0 else [h, n - 1], axis=axis)
    mid = np.take(part, h, axis=axis)
    if n % 2 == 0:
        mid = (np.take(part, h - 1, axis=axis) + mid) / 2
    last = np.take(part, n - 1, axis=axis)          # the largest, or a NaN
    return np.where(np.isnan(last), last, mid)[()]


def nanmedian(x, axis: int | None = None):
    """:func:`numpy.nanmedian` of real values, the same numbers: NaNs left out; NaN
    (without numpy's warning) where every value is NaN. Parameters and result as
    :func:`median`'s."""
    a = np.asarray(x, dtype=float)
    if axis is None:
        a, axis = a.ravel(), 0
    a = np.moveaxis(a, axis, -1)
    if a.shape[-1] == 0:
        return np.full(a.shape[:-1], np.nan)[()]
    s = np.sort(a, axis=-1)                                   # NaN sorted last
    n = np.count_nonzero(~np.isnan(a), axis=-1)[..., None]
    lo = np.take_along_axis(s, np.maximum(n - 1, 0) // 2, axis=-1)
    hi = np.take_along_axis(s, np.minimum(n // 2, a.shape[-1] - 1), axis=-1)
    return np.where(n > 0, (lo + hi) / 2, np.nan)[..., 0][()]


def _interpolated(s: np.ndarray, n: np.ndarray, q) -> np.ndarray:
    """The percentiles ``q`` (%) of each column of ``s`` (values sorted along axis 0, NaN
    last) whose first ``n`` values count: numpy's linear method, step for step."""
    q = np.true_divide(q, 100)
    if np.any((q < 0) | (q > 1)):
        raise ValueError("Percentiles must be in the range [0, 100]")
    qq = np.reshape(q, np.shape(q) + (1,) * (s.ndim - 1))
    v = (n - 1) * qq                                        # numpy's virtual index
    top = v >= n - 1
    below = np.where(top, -1.0, np.floor(v))                # numpy's previous index
    lo_i = np.where(top, n - 1, below).astype(np.intp)
    hi_i = np.where(top, n - 1, below + 1).astype(np.intp)
    shape = np.broadcast_shapes(lo_i.shape, s.shape[1:])
    lo_i = np.broadcast_to(lo_i, shape).clip(0)
    hi_i = np.broadcast_to(hi_i, shape).clip(0)
    a = np.take_along_axis(s, lo_i.reshape(-1, *s.shape[1:]), axis=0).reshape(shape)
    b = np.take_along_axis(s, hi_i.reshape(-1, *s.shape[1:]), axis=0).reshape(shape)
    t = v - below
    d = b - a
    return np.where(t >= 0.5, b - d * (1 - t), a + d * t)


def _percentiles(x, q, axis: int | None, skip_nan: bool):
    """The percentiles of :func:`percentile` (``skip_nan`` False) or of
    :func:`nanpercentile` (True)."""
    a = np.asarray(x, dtype=float)
    if axis is None:
        a, axis = a.ravel(), 0
    a = np.moveaxis(a, axis, 0)
    if a.shape[0] == 0:
        if not skip_nan:
            raise IndexError("percentile of no values")
        return np.full(np.shape(q) + a.shape[1:], np.nan)[()]
    s = np.sort(a, axis=0)                                    # NaN sorted last
    if skip_nan:
        n = np.count_nonzero(~np.isnan(a), axis=0)
        return np.where(n > 0, _interpolated(s, n, q), np.nan)[()]
    out = _interpolated(s, np.asarray(a.shape[0]), q)
    return np.where(np.isnan(s[-1]), s[-1], out)[()]


def percentile(x, q, axis: int | None = None):
    """:func:`numpy.percentile` of real values (its default linear method), the same
    numbers: NaN where any value is NaN.

    Parameters
    ----------
    x : array_like
        Real values (any unit; the result has the same).
    q : float or sequence of float
        Percentiles, 0 to 100.
    axis : int, optional
        The axis along which they are taken; None: of all values.

    Returns
    -------
    numpy.float64 or ndarray
        Shape ``q``'s shape + the other axes' shape, as numpy's.
    """
    return _percentiles(x, q, axis, skip_nan=False)


def nanpercentile(x, q, axis: int | None = None):
    """:func:`numpy.nanpercentile` of real values (its default linear method), the same
    numbers: NaNs left out; NaN (without numpy's warning) where every value is NaN.
    Parameters and result as :func:`percentile`'s."""
    return _percentiles(x, q, axis, skip_nan=True)


def unique(x) -> np.ndarray:
    """:func:`numpy.unique` of an array (no index, inverse or counts): its distinct
    values, sorted; NaNs, as numpy's, kept once.

    Parameters
    ----------
    x : array_like

    Returns
    -------
    ndarray
        1-D, of ``x``'s dtype.
    """
    s = np.sort(np.asarray(x).ravel())
    if s.size == 0:
        return s
    keep = np.empty(s.size, bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    if s.dtype.kind in "fc" and np.isnan(s[-1]):              # NaN last: keep the first
        nan = np.isnan(s)
        keep &= ~nan
        keep[np.argmax(nan)] = True
    return s[keep]
