"""Residuals and their summaries: errors per band, failing bands in words, t statistics."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from armfit import noise
from armfit._order import median
from armfit.diagnosis.tuning import MIN_RUN, T_FAIL
from armfit.fitting import log_errors

__all__ = [
    "BandError", "FailingBand", "band_columns", "band_error", "describe_residual",
    "failing_bands",
    "residuals", "trial_statistics",
]


def residuals(h_meas: np.ndarray, h_model: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measured relative to model: (20 log10|Hm/Hmod| in dB, angle(Hm/Hmod) in deg)."""
    db, deg = log_errors(h_model, h_meas)
    return -db, -deg


@dataclass(frozen=True)
class BandError:
    """Error of a model in one band: RMS magnitude error (dB), RMS phase error (deg), the
    RMS of the residuals normalised by the measurement's standard error (1 ≈ noise), and
    ``bias_norm``, the RMS over the band of the trials' mean normalised residual (the
    systematic part of the error, which a missing effect leaves; noise averages out)."""

    lo_hz: float
    hi_hz: float
    rms_db: float
    rms_deg: float
    rms_norm: float
    n_points: int
    bias_norm: float = float("nan")


def band_columns(f_hz, lo: float, hi: float) -> tuple[slice | np.ndarray, int]:
    """The grid points ``lo <= f <= hi`` of ``f_hz`` (Hz) as an index of the last axis
    — a slice where they are contiguous (a band of a sorted grid always is), so that
    indexing gives views, not copies; else the boolean mask — and their number."""
    f = np.asarray(f_hz, float)
    sel = (f >= lo) & (f <= hi)
    idx = np.flatnonzero(sel)
    if idx.size and idx[-1] - idx[0] + 1 == idx.size:
        return slice(int(idx[0]), int(idx[-1]) + 1), int(idx.size)
    return sel, int(idx.size)


def band_error(f_hz, r_db, r_deg, se_db, se_deg, lo: float, hi: float) -> BandError:
    """RMS errors over ``lo <= f <= hi`` of residual arrays (…, n_freq), pooled.

    se_db, se_deg: the noise model's standard errors (:func:`armfit.noise.standard_errors`),
    broadcastable to the residuals; ``rms_norm`` is :func:`armfit.noise.rms_norm` (a point
    without a finite standard error or residual is left out, not counted as zero)."""
    sel, n_points = band_columns(f_hz, lo, hi)
    # views of the band (a band of 1,350 trials held four copies of 1.1 MB besides the
    # normalised residuals); what is computed from them is laid out column-major
    # (order="F"), as copies by a boolean mask of the last axis are, so that every sum
    # below adds its terms in the order it did on such copies
    rdb = np.asarray(r_db, float)[..., sel]
    rdeg = np.asarray(r_deg, float)[..., sel]
    if rdb.size == 0:
        nan = float("nan")
        return BandError(lo, hi, nan, nan, nan, 0)
    sdb = np.broadcast_to(np.asarray(se_db, float), np.shape(r_db))[..., sel]
    sdeg = np.broadcast_to(np.asarray(se_deg, float), np.shape(r_deg))[..., sel]
    with np.errstate(all="ignore"):     # as noise.normalised
        zdb, zdeg = np.divide(rdb, sdb, order="F"), np.divide(rdeg, sdeg, order="F")
    del sdb, sdeg
    rms_db = float(np.sqrt(np.mean(np.square(rdb, order="F"))))
    rms_deg = float(np.sqrt(np.mean(np.square(rdeg, order="F"))))
    del rdb, rdeg
    rms_norm = noise.rms_of_normalised(zdb, zdeg)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mdb = np.nanmean(np.atleast_2d(zdb), axis=0)
        mdeg = np.nanmean(np.atleast_2d(zdeg), axis=0)
        mall = np.concatenate([mdb, mdeg])
        bias = float(np.sqrt(np.nanmean(mall ** 2))) if np.isfinite(mall).any() \
            else float("nan")
    return BandError(lo, hi, rms_db, rms_deg, rms_norm, n_points, bias)


@dataclass(frozen=True)
class FailingBand:
    """A contiguous band where the residual is statistically significant, in words."""

    lo_hz: float
    hi_hz: float
    mean_db: float
    mean_deg: float
    description: str


def _runs(mask: np.ndarray, min_run: int) -> list[tuple[int, int]]:
    """(start, stop) index pairs of runs of True at least ``min_run`` long."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    d = np.diff(m.astype(int))
    starts, stops = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(int(a), int(b)) for a, b in zip(starts, stops, strict=True) if b - a >= min_run]


def _trend(f: np.ndarray, r: np.ndarray) -> str:
    """'more and more' / 'less and less' / '' from the residual's growth across the band."""
    if r.size < 3:
        return ""
    x = np.log10(f)
    slope = np.polyfit(x, np.abs(r), 1)[0] * (x[-1] - x[0])
    if abs(slope) < 0.5 * np.max(np.abs(r)):
        return ""
    return "more and more with frequency" if slope > 0 else "less and less with frequency"


def describe_residual(f_hz, r_db, r_deg, sig_db, sig_deg) -> str:
    """Words for a band's mean residual: sign and shape of magnitude and phase.

    f_hz, r_db (dB), r_deg (deg): the band's frequencies and mean residuals (measured
    relative to model); sig_db, sig_deg: per-point significance masks.
    """
    f = np.asarray(f_hz, float)
    parts = []
    if np.any(sig_db):
        peak = float(r_db[np.argmax(np.abs(r_db))])
        where = "above" if median(r_db) > 0 else "below"
        shape = _trend(f, r_db)
        mixed = np.any(r_db[sig_db] > 0) and np.any(r_db[sig_db] < 0)
        if mixed:
            parts.append(f"magnitude swings around the model (peak {peak:+.1f} dB)")
        else:
            parts.append(f"measured magnitude {where} the model"
                         + (f" {shape}" if shape else "") + f" (up to {peak:+.1f} dB)")
    else:
        parts.append("magnitude fine")
    if np.any(sig_deg):
        peak = float(r_deg[np.argmax(np.abs(r_deg))])
        word = "lags" if median(r_deg) < 0 else "leads"
        shape = _trend(f, r_deg)
        mixed = np.any(r_deg[sig_deg] > 0) and np.any(r_deg[sig_deg] < 0)
        if mixed:
            parts.insert(0, f"phase swings around the model (peak {peak:+.0f} deg)")
        else:
            parts.insert(0, f"phase {word} the model" + (f" {shape}" if shape else "")
                         + f" (up to {peak:+.0f} deg)")
    else:
        parts.append("phase fine")
    return ", ".join(parts)


def failing_bands(f_hz, stat_db, stat_deg, mean_db, mean_deg, *, threshold: float = T_FAIL,
                  min_run: int = MIN_RUN, size_db=None, size_deg=None
                  ) -> list[FailingBand]:
    """Bands where |stat| > threshold for at least ``min_run`` consecutive points.

    stat_*: test statistics per frequency (z or t); mean_*: mean residuals (dB, deg) used
    for the words; size_*: optional mean normalised residuals, which must also exceed 1
    (the systematic error is larger than one trial's noise — with many trials a bias far
    below the noise is "significant" yet not a failure of the model). Magnitude and phase
    failures are merged into one band list.
    """
    f = np.asarray(f_hz, float)
    sig_db = np.abs(stat_db) > threshold
    sig_deg = np.abs(stat_deg) > threshold
    if size_db is not None:
        sig_db &= np.abs(size_db) > 1.0
    if size_deg is not None:
        sig_deg &= np.abs(size_deg) > 1.0
    out = []
    for a, b in _runs(sig_db | sig_deg, min_run):
        sl = slice(a, b)
        out.append(FailingBand(float(f[a]), float(f[b - 1]), float(np.mean(mean_db[sl])),
                               float(np.mean(mean_deg[sl])),
                               describe_residual(f[sl], np.asarray(mean_db)[sl],
                                        np.asarray(mean_deg)[sl], sig_db[sl], sig_deg[sl])))
    return out


def trial_statistics(z_db: np.ndarray, z_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """t statistic per frequency of normalised residuals (n_trials, n_freq) across trials.

    t = mean / (sd / sqrt(T)); with a single trial (T = 1) the z values themselves.
    """
    def t(z):
        z = np.asarray(z, float)
        if z.shape[0] < 2:
            return z[0]
        sd = np.std(z, axis=0, ddof=1)
        return np.mean(z, axis=0) / np.maximum(sd, 1e-12) * np.sqrt(z.shape[0])
    return t(z_db), t(z_deg)
