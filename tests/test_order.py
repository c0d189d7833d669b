"""armfit._order against numpy's median and nanmedian (an independent computation), bit
for bit: the medians every command takes without importing numpy.ma."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest

from armfit._order import median, nanmedian, nanpercentile, percentile, unique


def _cases(seed: int, count: int = 300):
    """Arrays of 1-3 axes, odd and even lengths, ties, NaN scattered in some, an empty axis
    now and then, and a row of NaN only."""
    rng = np.random.default_rng(seed)
    for k in range(count):
        nd = int(rng.integers(1, 4))
        shape = tuple(int(s) for s in rng.integers(0 if k % 50 == 0 else 1, 9, size=nd))
        x = rng.normal(size=shape) * 10.0 ** int(rng.integers(-5, 5))
        if k % 7 == 0:
            x = np.round(x)
        if k % 3 == 0 and x.size:
            x.flat[rng.integers(0, x.size, size=int(rng.integers(1, 4)))] = np.nan
        if k % 11 == 0 and x.ndim == 2 and x.size:
            x[0] = np.nan
        yield x


def _same(got, want) -> bool:
    return (type(got) is type(want) and np.shape(got) == np.shape(want)
            and np.array_equal(got, want, equal_nan=True))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_median_and_nanmedian_are_numpys_bit_for_bit(seed):
    for x in _cases(seed):
        for axis in (None, *range(-x.ndim, x.ndim)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)   # numpy on all-NaN / empty
                want_med = np.median(x, axis=axis)
                want_nan = np.nanmedian(x, axis=axis)
            assert _same(median(x, axis=axis), want_med), (x.shape, axis)
            assert _same(nanmedian(x, axis=axis), want_nan), (x.shape, axis)


def test_long_rows_take_numpys_other_nanmedian_path_and_agree():
    # numpy's nanmedian drops the NaN and takes np.median for rows of 600 values or more
    rng = np.random.default_rng(7)
    for n in (600, 601, 2048, 2999):
        x = rng.normal(size=(2, n))
        x[:, rng.integers(0, n, 5)] = np.nan
        assert _same(nanmedian(x, axis=1), np.nanmedian(x, axis=1))
        assert _same(nanmedian(x[0]), np.nanmedian(x[0]))


@pytest.mark.parametrize("seed", [0, 1])
def test_percentiles_are_numpys_linear_ones_bit_for_bit(seed):
    # numpy's default method, on the quartiles armfit takes and on other percentiles
    # (scalar, the ends, a 2-D q); a column of NaN only among the NaN-aware ones
    qs = ([25, 75], 5, 50.0, [0, 100], [12.5, 37.5, 99.0], np.array([[10, 20], [30, 40]]))
    for x in _cases(seed, 40):
        if 0 in x.shape:
            continue
        for q in qs:
            for axis in (None, *range(-x.ndim, x.ndim)):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)   # numpy on all-NaN
                    want_p = np.percentile(x, q, axis=axis)
                    want_n = np.nanpercentile(x, q, axis=axis)
                assert _same(percentile(x, q, axis=axis), want_p), (x.shape, q, axis)
                assert _same(nanpercentile(x, q, axis=axis), want_n), (x.shape, q, axis)


def test_unique_is_numpys():
    # sorted distinct values of the array's dtype; NaN kept once, as numpy's equal_nan
    rng = np.random.default_rng(3)
    for x in (rng.integers(0, 5, 40), np.round(rng.normal(size=30), 1),
              np.array([3.0, np.nan, 1.0, np.nan, 3.0]), np.array([], float),
              np.array(["s2", "s1", "s2", "s10"]), np.array(["b", "a", "b"], object),
              rng.integers(0, 3, (4, 5))):
        want, got = np.unique(x), unique(x)
        assert got.dtype == want.dtype
        assert np.array_equal(got, want, equal_nan=x.dtype.kind == "f"), x


def test_percentile_refuses_what_numpy_refuses():
    with pytest.raises(ValueError):
        percentile([1.0, 2.0], 101)
    with pytest.raises(ValueError):
        nanpercentile([1.0, 2.0], -1)


def test_no_numpy_ma_is_imported():
    # the point of the module: numpy's median imports numpy.ma at its first call
    code = ("import sys, numpy as np; from armfit._order import *; "
            "x = np.array([[1.0, np.nan, 3.0], [4.0, 5.0, 6.0]]); "
            "median(x, axis=1); nanmedian(x, axis=0); nanmedian(x); percentile(x, [25, 75]); "
            "nanpercentile(x, 5, axis=1); unique(x); "
            "print('numpy.ma' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "False"


def test_reading_a_spectra_file_imports_no_numpy_ma(serial_spectra, tmp_path):
    # a spectra file read by group (Spectra.read, as diagnose, fit-* and run's stages
    # read theirs) tells its responses apart by their keys' distinct hashes: with
    # numpy's unique and union1d, that imported numpy.ma (11 ms of diagnose's start)
    path = tmp_path / "spectra.parquet"
    serial_spectra.write(path)
    code = ("import sys; from armfit.spectra import Spectra; "
            f"sp = Spectra.read({str(path)!r}, level='trial'); "
            "print(len(sp) > 0, 'numpy.ma' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.strip()
    assert out == "True False"
