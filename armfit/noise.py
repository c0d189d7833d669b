"""The noise model: the standard error of a response per bin, and the "× noise" statistic.

Every number armfit prints as "× noise" (``rms_norm`` of the params files, of
``compare`` and of the diagnosis, the verdicts, the residual figures' legends and the
report) is :func:`rms_norm` of residuals divided by :func:`standard_errors`; every fit
weighted by the measurement noise (the "complex" cost, the diagnosis's joint fits)
weights its residuals by 1/:func:`standard_errors`. One definition, so the same model on
the same bins reads the same number everywhere (docs/methods.md, "The noise model").

The raw standard errors come from the spectra file (:mod:`armfit.spectra`): for a single
trial Bendat & Piersol's ε = √(1 − γ²)/(|γ|√(2 n_d)) from the coherence (raised where the
bins scatter more), for an aggregate the spread across its trials (s/√n for a mean,
√(π/2)·s/√n for a median). Per response (along frequency, bins sorted by frequency),
:func:`standard_errors` then

1. **caps** each one at the spread of an estimate that is pure noise, :data:`SE_CAP_DB`
   (5.57 dB, the s.d. of 20 log10 of a Rayleigh variable) and :data:`SE_CAP_DEG`
   (103.9 deg = 180/√3, a uniform phase): Bendat & Piersol's formula is a large-sample
   result and runs to hundreds of dB where the coherence is near 0, where no estimate can
   be noisier than pure noise;
2. **fills** a bin without a valid standard error (NaN or ≤ 0) with the median of the
   response's valid ones;
3. **pools** the variance over :data:`POOL_BINS` neighbouring bins, se = √(moving mean of
   se²): a standard error estimated from a few trials (or averages) is itself noisy —
   with 3 subjects a bin's se can be 10× too small, and that bin would dominate a fit and
   the statistic — while the noise varies slowly with frequency (9 bins are a quarter of
   a decade on the default grid of 40 per decade);
4. **floors** the result at :data:`SE_FLOOR_DB` and :data:`SE_FLOOR_DEG`, so no bin can
   be near noiseless.

A response with no valid standard error at all has none (NaN): its "× noise" is NaN.
"""

from __future__ import annotations

import numpy as np

from armfit._order import nanmedian

__all__ = ["POOL_BINS", "SE_CAP_DB", "SE_CAP_DEG", "SE_FLOOR_DB", "SE_FLOOR_DEG",
           "normalised", "rms_norm", "rms_of_normalised", "standard_errors"]

#: Neighbouring bins over which a response's noise variance is pooled (step 3).
POOL_BINS = 9
#: Largest standard errors (dB, deg): those of an estimate that is pure noise (Rayleigh
#: magnitude: π/√6 · 20/ln 10 / 2 ≈ 5.57 dB; uniform phase: 180/√3 ≈ 103.9 deg).
SE_CAP_DB = 5.57
SE_CAP_DEG = 103.9
#: Smallest standard errors (dB, deg), so that a near-noiseless bin cannot dominate.
SE_FLOOR_DB = 0.01
SE_FLOOR_DEG = 0.06


def _moving_mean(x: np.ndarray, size: int) -> np.ndarray:
    """Mean of ``size`` neighbours along the last axis, the edge values repeated beyond
    the ends: ``scipy.ndimage.uniform_filter1d(x, size, axis=-1, mode="nearest")``, to
    the bit (the same window, a running sum added in the same order, divided once).
    Written with numpy because importing :mod:`scipy.ndimage` takes about 0.4 s, more
    than every use of it here. (:func:`armfit.spectra.moving_mean`, for long records, is
    faster and equal to it within rounding only.)

    Parameters
    ----------
    x : ndarray (..., n)
        Values (any unit; the result has the same).
    size : int
        Window length (points); for an even length the window holds one more point
        before a point than after it, as scipy's.

    Returns
    -------
    ndarray (..., n)
    """
    x = np.asarray(x, float)
    before = size // 2
    after = size - before - 1
    n = x.shape[-1]
    pad = np.concatenate([np.repeat(x[..., :1], before, axis=-1), x,
                          np.repeat(x[..., -1:], after, axis=-1)], axis=-1)
    # the first window's sum added left to right (a cumulative sum is sequential), then
    # one point in and one out per step, as scipy's running sum
    first = np.cumsum(pad[..., :size], axis=-1)[..., -1:]
    steps = pad[..., size:size + n - 1] - pad[..., :n - 1]
    del pad
    out = np.concatenate([first, steps], axis=-1)
    del steps
    # in place: the same sums and quotient as np.cumsum(...) / size, one array held
    np.cumsum(out, axis=-1, out=out)
    out /= size
    return out


def _one(se: np.ndarray, cap: float, floor: float, pool: int) -> np.ndarray:
    """Steps 1–4 of the module docstring on standard errors (..., n_freq)."""
    # one array of the responses' size changed in place step by step (the same values
    # as a new array a step: on 1,350 trials of 100 bins the steps held 8 MB at once)
    se = np.array(se, float, ndmin=1)
    with np.errstate(invalid="ignore"):
        np.minimum(se, cap, out=se)                   # inf -> cap, NaN stays NaN
        ok = np.isfinite(se) & (se > 0)
    fill = nanmedian(np.where(ok, se, np.nan), axis=-1)[..., None]
    np.copyto(se, fill, where=~ok)
    del ok, fill
    if pool > 1:
        np.multiply(se, se, out=se)
        se = _moving_mean(se, pool)
        np.sqrt(se, out=se)
    np.maximum(se, floor, out=se)   # NaN (no valid se in the row) stays NaN
    return se


def standard_errors(se_db, se_deg, *, pool: int = POOL_BINS
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The noise model's standard errors of a response, per bin.

    Parameters
    ----------
    se_db, se_deg : array_like, shape (..., n_freq)
        Raw standard errors of 20 log10|H| (dB) and of the phase (deg) of one response
        (or of several, one per row: a trial each, or an aggregate), as the spectra file
        holds them, along a frequency grid sorted ascending.
    pool : int, optional
        Bins over which the variance is pooled (:data:`POOL_BINS`; 1: none). Every
        statistic armfit prints uses the default.

    Returns
    -------
    se_db, se_deg : ndarray, shape (..., n_freq)
        Capped, filled, pooled and floored standard errors (dB, deg); NaN for a row
        without any valid standard error.

    Notes
    -----
    The steps and their reasons are in the module docstring. The standard error of a
    bin depends on its neighbours, so it is computed on the whole grid of the response
    and then restricted to a band, never the other way round.
    """
    return (_one(se_db, SE_CAP_DB, SE_FLOOR_DB, pool),
            _one(se_deg, SE_CAP_DEG, SE_FLOOR_DEG, pool))


def normalised(r_db, r_deg, se_db, se_deg) -> tuple[np.ndarray, np.ndarray]:
    """Normalised residuals z = r/se of magnitude and phase.

    Parameters
    ----------
    r_db, r_deg : array_like
        Residuals in dB and deg (measured relative to model, or the other way round: the
        statistic squares them).
    se_db, se_deg : array_like
        The noise model's standard errors (:func:`standard_errors`), broadcastable to the
        residuals.

    Returns
    -------
    z_db, z_deg : ndarray
        Dimensionless; ≈ N(0, 1) where the model fits within the noise. NaN where a
        residual or a standard error is not finite.
    """
    with np.errstate(all="ignore"):
        return (np.asarray(r_db, float) / np.asarray(se_db, float),
                np.asarray(r_deg, float) / np.asarray(se_deg, float))


def rms_norm(r_db, r_deg, se_db, se_deg) -> float:
    """The "× noise" statistic: RMS of the normalised residuals, magnitude and phase pooled.

    Parameters
    ----------
    r_db, r_deg : array_like, shape (..., n)
        Residuals (dB, deg) over the bins (and trials) judged.
    se_db, se_deg : array_like
        The noise model's standard errors (:func:`standard_errors`), broadcastable.

    Returns
    -------
    float
        √(mean of z_db² and z_deg² over every finite entry); 1 means the model misses the
        data by as much as the noise, on average. NaN when no entry is finite.

    Notes
    -----
    Magnitude and phase count alike (two real residuals per bin); an entry whose residual
    or standard error is not finite carries no information and is left out (it is not
    counted as a zero residual).
    """
    return rms_of_normalised(*normalised(r_db, r_deg, se_db, se_deg))


def rms_of_normalised(z_db, z_deg) -> float:
    """:func:`rms_norm` of residuals already normalised (:func:`normalised`).

    Parameters
    ----------
    z_db, z_deg : array_like
        Normalised residuals of magnitude and phase.

    Returns
    -------
    float
        √(mean of z² over every finite entry of both, pooled); NaN when none is finite.
    """
    parts = [np.asarray(a, float) for a in (z_db, z_deg)]
    finite = [np.isfinite(a) for a in parts]
    counts = [int(m.sum()) for m in finite]
    if not sum(counts):
        return float("nan")
    # the finite values of both, in row-major order, copied into one array a part at a
    # time (not both whole, then joined, then selected), then squared in place
    z = np.empty(sum(counts))
    z[:counts[0]] = parts[0][finite[0]]
    z[counts[0]:] = parts[1][finite[1]]
    np.multiply(z, z, out=z)
    return float(np.sqrt(np.mean(z)))
