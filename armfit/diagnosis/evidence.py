"""The evidence for an effect and the adequacy of a fit: the likelihood-ratio statistic,
the practical size of an effect, and whether a fit is within the noise."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from armfit._order import nanmedian
from armfit.constants import PARAM_NAMES
from armfit.diagnosis.bands import (
    BandError,
    FailingBand,
    _runs,
    band_error,
    failing_bands,
    residuals,
    trial_statistics,
)
from armfit.diagnosis.joint import JointFit
from armfit.diagnosis.tuning import (
    BANDS,
    DROP_POINTS,
    MIN_EFFECT_DB,
    MIN_EFFECT_DEG,
    MIN_RUN,
    NOISE_TOL,
)
from armfit.models.effects import Effect

__all__ = [
    "Adequacy", "adequacy", "band_errors", "effect_size", "practical", "response_change",
    "delta_bic", "robust_lr", "union_bias",
]


def _point_ss(fit: JointFit, se_db, se_deg) -> np.ndarray:
    """Sum over trials of squared normalised residuals, per grid point (n,)."""
    z = np.concatenate([fit.r_db / se_db, fit.r_deg / se_deg], axis=0)
    return np.sum(np.where(np.isfinite(z), z * z, 0.0), axis=0)


def robust_lr(base: JointFit, fit: JointFit, se_db, se_deg) -> tuple[float, float]:
    """Likelihood-ratio statistic N_eff ln(RSS_base/RSS_effect), not resting on a few
    points: the :data:`DROP_POINTS` grid points whose improvement is largest are left out
    of both sums (an isolated outlier, e.g. at the edge of the excitation band, cannot
    make an effect significant; a real effect improves many points). Returns (D, N_eff,
    the fraction of the residual sum of squares the effect removes)."""
    ss0, ss1 = _point_ss(base, se_db, se_deg), _point_ss(fit, se_db, se_deg)
    keep = np.ones(ss0.size, bool)
    keep[np.argsort(ss0 - ss1)[::-1][:DROP_POINTS]] = False
    rho = float(np.clip(fit.rho, 0.0, 0.95))
    n_res = fit.n_res * keep.sum() / keep.size
    n_eff = n_res * (1 - rho) / (1 + rho)
    rss0, rss1 = float(ss0[keep].sum()), float(ss1[keep].sum())
    lr = n_eff * np.log(rss0 / rss1) if rss1 > 0 and rss0 > rss1 else 0.0
    return float(lr), float(n_eff), float(max(1.0 - rss1 / rss0, 0.0)) if rss0 > 0 else 0.0


def delta_bic(base: JointFit, fit: JointFit, se_db, se_deg, k: int | None = None
              ) -> tuple[float, float, float]:
    """ΔBIC of ``fit`` against the nested ``base``: D − k ln N_eff, with D and N_eff of
    :func:`robust_lr` and ``k`` the free parameters ``fit`` adds (default
    ``fit.n_free − base.n_free``). Returns (ΔBIC, D, the fraction of the cost removed)."""
    lr, n_eff, reduction = robust_lr(base, fit, se_db, se_deg)
    k = fit.n_free - base.n_free if k is None else k
    return float(lr - k * np.log(max(n_eff, 2.0))), lr, reduction


def union_bias(f, fit: JointFit, se_db, se_deg, ranges) -> float:
    """bias_norm (RMS of the trials' mean normalised residual) pooled over the union of
    ``ranges`` (Hz); NaN when there is none."""
    mask = np.zeros(f.size, bool)
    for lo, hi in ranges:
        mask |= (f >= lo) & (f <= hi)
    if not mask.any():
        return float("nan")
    m = np.concatenate([(fit.r_db / se_db).mean(axis=0)[mask],
                        (fit.r_deg / se_deg).mean(axis=0)[mask]])
    return float(np.sqrt(np.mean(m ** 2)))


def band_errors(f, fit: JointFit, se_db, se_deg, bands) -> tuple[BandError, ...]:
    """:func:`band_error` of ``fit`` in each (lo, hi) of ``bands`` (Hz), with the noise
    model's standard errors ``se_db``, ``se_deg`` on ``f``."""
    return tuple(band_error(f, fit.r_db, fit.r_deg, se_db, se_deg, lo, hi) for lo, hi in bands)


@dataclass(frozen=True)
class Adequacy:
    """Whether a fit is within the noise: per-band errors (:data:`BANDS` within the
    diagnosis band), the bands whose normalised error exceeds :data:`NOISE_TOL`
    (``over``), the failing bands of the t test (``failing``, with words), and the
    noise-weighted cost against its expected value (``cost``, ``cost_expected`` = ν,
    ``cost_sd`` = √(2ν), ν = residuals − parameters)."""

    adequate: bool
    overall: BandError
    bands: tuple[BandError, ...]
    over: tuple[BandError, ...]
    failing: tuple[FailingBand, ...]
    cost: float
    cost_expected: float
    cost_sd: float


def adequacy(f: np.ndarray, fit: JointFit, se_db: np.ndarray, se_deg: np.ndarray,
             band: tuple[float, float], n_params: int, min_db: float = MIN_EFFECT_DB,
             min_deg: float = MIN_EFFECT_DEG) -> Adequacy:
    """Judge ``fit`` (residuals (T, n) on ``f``) against the noise ``se_db``, ``se_deg``
    (the noise model's, (T, n)). Adequate when no band fails and every band is within the noise:
    its RMS normalised error is at most :data:`NOISE_TOL`, or its systematic part
    (``bias_norm``) at most 1. A band fails (:func:`failing_bands`) where the trials'
    t statistic exceeds :data:`T_FAIL` on :data:`MIN_RUN` consecutive points and the mean
    residual exceeds both one trial's noise and the practical floor ``min_db`` (dB) or
    ``min_deg`` (deg): a bias of a few hundredths of a dB is detectable with many
    trials but is no failure of the model."""
    overall = band_error(f, fit.r_db, fit.r_deg, se_db, se_deg, band[0], band[1])
    bands = tuple(b for b in (band_error(f, fit.r_db, fit.r_deg, se_db, se_deg,
                                         max(lo, band[0]), min(hi, band[1]))
                              for lo, hi in BANDS if hi > band[0] and lo < band[1])
                  if b.n_points >= MIN_RUN)
    # a band is within the noise when its RMS normalised error is at most NOISE_TOL, or
    # when its systematic part (bias_norm: RMS of the trials' mean normalised residual,
    # the only part a missing effect leaves) is within one trial's noise — there the
    # excess is noise that the standard errors underestimate, not a model error
    over = tuple(b for b in bands if np.isfinite(b.rms_norm) and b.rms_norm > NOISE_TOL
                 and not (np.isfinite(b.bias_norm) and b.bias_norm <= 1.0))
    # the normalised residuals of magnitude and phase, made once into one array (zdb,
    # zdeg: its halves): the finite ones counted; then, in place, NaN as 0 and ±inf as
    # the largest floats (np.nan_to_num) for the t statistics and the mean sizes; then
    # squared in place for the cost, whose sum is np.nansum's of the squares (NaN adds
    # 0, ±inf squares to inf either way)
    shape = np.shape(fit.r_db)
    z = np.empty(2 * fit.r_db.size)
    zdb, zdeg = z[:fit.r_db.size].reshape(shape), z[fit.r_db.size:].reshape(shape)
    np.divide(fit.r_db, se_db, out=zdb)
    np.divide(fit.r_deg, se_deg, out=zdeg)
    n_res = int(np.isfinite(z).sum())
    nu = max(n_res - n_params, 1)
    np.nan_to_num(z, copy=False)
    with np.errstate(all="ignore"):
        t_db, t_deg = trial_statistics(zdb, zdeg)
    m_db, m_deg = fit.r_db.mean(axis=0), fit.r_deg.mean(axis=0)
    fails = failing_bands(f, t_db, t_deg, m_db, m_deg,
                          size_db=np.where(np.abs(m_db) > min_db, zdb.mean(axis=0), 0.0),
                          size_deg=np.where(np.abs(m_deg) > min_deg, zdeg.mean(axis=0),
                                            0.0))
    del zdb, zdeg
    with np.errstate(over="ignore"):    # the largest float squared: inf
        np.multiply(z, z, out=z)
    return Adequacy(adequate=not fails and not over, overall=overall, bands=bands,
                    over=over, failing=tuple(fails), cost=float(np.sum(z)),
                    cost_expected=float(nu), cost_sd=float(np.sqrt(2.0 * nu)))


def effect_size(fit: JointFit, effect: Effect, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How much ``effect`` at its fitted values changes the fitted response: per grid
    point, the median over trials of |20 log10|H/H₀|| (dB) and |angle(H/H₀)| (deg), H₀
    the same fit with the effect at its null values (every other parameter unchanged)."""
    return response_change(fit, {f"{effect.name}.{k}": v for k, v in
                                 effect.null_values(fit.model.mp).items()}, f)


def response_change(fit: JointFit, values: dict[str, float], f: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """How much the fitted response changes when the effect parameters ``values``
    ({``effect.param``: value}) replace the fit's own (every other parameter unchanged):
    per grid point, the median over trials of |20 log10|H/H₀|| (dB) and |angle(H/H₀)|
    (deg), H the fit's response and H₀ the one with ``values``."""
    model = fit.model
    T = fit.base.shape[0]
    theta = {n: fit.base[:, i:i + 1] for i, n in enumerate(PARAM_NAMES)}
    theta.update({n: v[:, None] for n, v in fit.trial_values().items()})
    null = dict(theta)
    null.update({n: np.full((T, 1), v) for n, v in values.items()})
    with np.errstate(all="ignore"):
        d_db, d_deg = residuals(model.response(f, theta), model.response(f, null))
    return nanmedian(np.abs(d_db), axis=0), nanmedian(np.abs(d_deg), axis=0)


def practical(f, size_db, size_deg, se_db, se_deg, min_db: float, min_deg: float
              ) -> tuple[bool, float]:
    """Practical significance of an effect whose change of the response is ``size_db``,
    ``size_deg`` (n,): the change exceeds both the measurement noise (median over trials
    of the standard error) and the floor ``min_db`` / ``min_deg`` on at least
    :data:`MIN_RUN` consecutive grid points, in magnitude or in phase. Returns (holds,
    the largest ratio of change to threshold)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        thr_db = np.maximum(min_db, nanmedian(np.where(np.isfinite(se_db), se_db, np.nan),
                                                 axis=0))
        thr_deg = np.maximum(min_deg, nanmedian(np.where(np.isfinite(se_deg), se_deg,
                                                            np.nan), axis=0))
        r_db = np.nan_to_num(size_db / thr_db)
        r_deg = np.nan_to_num(size_deg / thr_deg)
    mask = (r_db > 1.0) | (r_deg > 1.0)
    return bool(_runs(mask, MIN_RUN)), float(np.max(np.maximum(r_db, r_deg), initial=0.0))
