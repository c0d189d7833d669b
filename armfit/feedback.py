"""Is the force an external excitation? A time-domain test for a force that responds to
the position (docs/methods.md, "Is the force the excitation?").

H1 = P_fx/P_ff is unbiased when the force is the excitation: imposed from outside and
recorded without noise. On a position-controlled rig (the force is a controller's output)
or a position-driven one (the actuator imposes the position; the force is the response)
the force depends on the position's past, its noise included, and H1 is biased. Open and
closed loop differ in time, not in any one spectrum: with an exogenous force, the part
of the position that past and present forces do not explain (whatever its colour:
postural drift, sensor noise) is independent of the *future* force; when the force
responds to the position, future forces carry it (L. Ljung, *System Identification:
Theory for the User*, 2nd ed., 1999, §16.6, residual analysis; C. A. Sims, "Money,
income and causality", Am. Econ. Rev. 62, 1972, the two-sided regression).

The test (:func:`feedback_test`):

1. Force and position (their means removed) are brought to the analysis band by one FFT
   each: bins up to ``f_hi`` kept, a raised-cosine taper to zero at 1.5·``f_hi``, and
   resampled at 6·``f_hi`` (twice the taper's end: a causal relation sampled there stays
   causal to within what the noise of real records hides); the ends, where the circular
   filter wraps, are dropped. Both signals get the same linear filters, so a causal
   relation between them stays causal.
2. Least squares of the position on the force's past and present (a FIR of ``past_s``
   seconds, one coefficient per sample) and on its future (``future_s`` seconds as
   ``n_future`` log-spaced block averages, so that the few coefficients tested are
   well conditioned even where the force has no power).
3. A Wald test of the future coefficients against zero, with their covariance from the
   residual's own autocorrelation (the sandwich form, Bartlett lag window of ``hac_s``
   seconds: the residual is coloured, and the force too), χ² with ``n_future`` degrees of
   freedom.

Pure numpy (no scipy import on the estimator's path). Units: force N, position m, rates
and frequencies Hz, times s.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from armfit._order import unique

#: p-value below which a trial's force counts as responding to its position. The
#: statistic is conservative on open-loop data (docs/methods.md, measured by
#: benchmarks/validate_estimators.py): a false alarm is rarer than this per trial, while
#: the closed-loop and position-driven recordings give p < 1e-6.
FEEDBACK_ALPHA = 1e-4

#: Default lengths (s): the force's past in the model, the future tested, the lag window
#: of the residual's autocorrelation.
PAST_S = 1.0
FUTURE_S = 0.5
HAC_S = 2.0
#: Block averages spanning the future lags.
N_FUTURE = 6
#: Most FIR coefficients of the past (a fast analysis band shortens ``past_s``).
MAX_PAST = 256


@dataclass(frozen=True)
class FeedbackTest:
    """Result of :func:`feedback_test`.

    Attributes
    ----------
    statistic : float
        Wald χ² of the future coefficients.
    dof : int
        Its degrees of freedom (the future block averages).
    p_value : float
        P(χ²_dof ≥ statistic) under an exogenous force.
    rate_hz : float
        Sampling rate of the analysis, Hz.
    samples : int
        Equations of the least squares.
    past_s, future_s : float
        Lengths of the force's past and future in the model, s.
    """

    statistic: float
    dof: int
    p_value: float
    rate_hz: float
    samples: int
    past_s: float
    future_s: float

    @property
    def fires(self) -> bool:
        """True when p < :data:`FEEDBACK_ALPHA`: the force responds to the position."""
        return self.p_value < FEEDBACK_ALPHA


def chi2_sf(x: float, k: int) -> float:
    """P(χ²_k ≥ x), the survival function of a χ² variable with k ≥ 1 degrees of freedom.

    Closed forms of the regularised upper incomplete gamma function Q(k/2, x/2): for even
    k, Σ_{i<k/2} e^(−x/2) (x/2)^i / i!; for odd k, erfc(√(x/2)) + Σ_{i<(k−1)/2}
    e^(−x/2) (x/2)^(i+½) / Γ(i + 3/2) (Abramowitz & Stegun 26.4.4, 26.4.5); each term
    summed from its logarithm, so that large k and x neither overflow nor underflow early.

    Parameters
    ----------
    x : float
        The statistic (≥ 0).
    k : int
        Degrees of freedom.

    Returns
    -------
    float
    """
    if not x > 0:
        return 1.0
    if not math.isfinite(x):
        return 0.0
    h = 0.5 * x
    log_h = math.log(h)
    if k % 2 == 0:
        total = sum(math.exp(i * log_h - math.lgamma(i + 1.0) - h) for i in range(k // 2))
    else:
        total = math.erfc(math.sqrt(h)) + sum(
            math.exp((i + 0.5) * log_h - math.lgamma(i + 1.5) - h)
            for i in range((k - 1) // 2))
    return min(1.0, total)


def band_signals(force, pos, fs: float, f_hi: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Force and position in the analysis band, resampled (step 1 of :func:`feedback_test`).

    Parameters
    ----------
    force, pos : array_like, shape (n,)
        Force (N) and position (m) at ``fs`` Hz.
    fs : float
        Sampling rate, Hz.
    f_hi : float
        Top of the band, Hz: flat to ``f_hi``, raised-cosine taper to zero at 1.5·``f_hi``
        (or at the Nyquist frequency, if lower).

    Returns
    -------
    (ndarray, ndarray, float)
        The two signals, mean removed and their circularly wrapped ends dropped, and
        their sampling rate in Hz (about 6·``f_hi``, at most ``fs``).

    Notes
    -----
    Where ``fs`` is at least 8·``f_hi``, the signals are first decimated by the integer
    q = ⌊fs/(8·``f_hi``)⌋ with a fourth-order cascaded moving sum (a CIC filter: its
    response at the frequencies that fold onto 0…1.5·``f_hi`` is at least 50 dB down for
    q = 4), so that the FFT is a q-th as long. The record is then shortened to the
    nearest FFT length with prime factors 2, 3 and 5 only (by a few per cent at most).
    Every step is one linear filter applied to both signals alike.
    """
    sig = np.stack([np.asarray(force, dtype=float), np.asarray(pos, dtype=float)])
    q = int(fs // (8.0 * f_hi))
    if q > 1:
        sig, fs = _cic(sig, q), fs / q
    n = _smooth_below(sig.shape[1])         # FFT lengths with small prime factors only
    sig = sig[:, :n]
    sig -= sig.mean(axis=1, keepdims=True)
    keep = _smooth_below(2 * min(n // 2, int(math.floor(3.0 * f_hi * n / fs)))) // 2
    spec = np.fft.rfft(sig, axis=1)[:, :keep + 1]
    freq = np.arange(keep + 1) * (fs / n)
    stop = min(1.5 * f_hi, freq[-1])
    if stop > f_hi:
        ramp = np.clip((freq - f_hi) / (stop - f_hi), 0.0, 1.0)
        spec *= 0.5 * (1.0 + np.cos(np.pi * ramp))
    nd = 2 * keep
    out = np.fft.irfft(spec, nd, axis=1) * (nd / n)
    rate = fs * nd / n
    # the taper's kernel lasts about 2/(stop - f_hi) s; drop that at each (wrapped) end
    trim = int(math.ceil(2.0 * rate / max(stop - f_hi, 0.25 * f_hi)))
    return out[0, trim:nd - trim], out[1, trim:nd - trim], rate


def _cic(sig: np.ndarray, q: int, order: int = 4) -> np.ndarray:
    """Every q-th sample of the rows of ``sig`` after ``order`` moving averages of q
    samples (Hogenauer's cascaded integrator-comb decimator as one FIR h, the boxcars
    convolved), computed in polyphase form: y[m] = Σ_k h[k] x[qm − k] = Σ_j B[m − j] · w_j
    with B the record in blocks of q samples and w_j[r] = h[qj − r]. Only the outputs
    whose window lies inside the record are kept."""
    box = np.ones(q) / q
    h = box
    for _ in range(order - 1):
        h = np.convolve(h, box)
    n_sig, m = sig.shape[0], sig.shape[1] // q
    taps = (h.size + q - 2) // q + 1              # blocks each output reaches back over
    k = q * np.arange(taps)[None, :] - np.arange(q)[:, None]          # (q, taps)
    weights = np.where((k >= 0) & (k < h.size), h[np.clip(k, 0, h.size - 1)], 0.0)
    parts = (sig[:, :m * q].reshape(n_sig * m, q) @ weights).reshape(n_sig, m, taps)
    out = parts[:, taps - 1:, 0].copy()
    for j in range(1, taps):
        out += parts[:, taps - 1 - j:m - j, j]
    return out


def _smooth_below(n: int) -> int:
    """The largest 2^a·3^b·5^c ≤ n (n ≥ 1): an FFT length without large prime factors
    (for n ≥ 1000 at most 6 % below n, for n ≥ 5000 at most 2 %)."""
    best = 1
    p2 = 1
    while p2 <= n:
        p3 = p2
        while p3 <= n:
            p5 = p3
            while p5 * 5 <= n:
                p5 *= 5
            best = max(best, p5)
            p3 *= 3
        p2 *= 2
    return best


def _future_basis(k: int, blocks: int) -> np.ndarray:
    """(k, m) block averages over the future lags 1…k, log-spaced edges, unit norm each
    (m ≤ ``blocks``: edges that round to the same lag merge)."""
    edges = unique(np.round(np.geomspace(1.0, k + 1.0, blocks + 1)).astype(int))
    basis = np.zeros((k, edges.size - 1))
    for i, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        basis[a - 1:b - 1, i] = 1.0 / math.sqrt(b - a)
    return basis


def _smooth_above(n: int) -> int:
    """The smallest 2^a·3^b·5^c ≥ n: an FFT length without large prime factors."""
    best = 1 << max(0, (n - 1).bit_length())
    p3 = 1
    while p3 < best:
        p5 = p3
        while p5 < best:
            m = p5
            while m < n:
                m *= 2
            best = min(best, m)
            p5 *= 5
        p3 *= 3
    return best


def _window_gram(f: np.ndarray, p: int, rows: int, first: np.ndarray) -> np.ndarray:
    """G[i, j] = Σ_{s<rows} f[s + i] f[s + j] for i, j < p (the Gram matrix of the
    length-p windows of f starting at 0…rows−1), exactly, from its first row ``first``
    (Σ_{s<rows} f[s] f[s + j]) and the shift rule G[i+1, j+1] = G[i, j] − f[i] f[j] +
    f[rows+i] f[rows+j]."""
    gram = np.empty((p, p))
    gram[0] = first
    step = np.outer(f[rows:rows + p - 1], f[rows:rows + p - 1]) - np.outer(f[:p - 1],
                                                                            f[:p - 1])
    for i in range(1, p):
        gram[i, 1:] = gram[i - 1, :-1] + step[i - 1]
        gram[i, 0] = gram[0, i]
    return gram


@functools.lru_cache(maxsize=1)
def _blas():
    """The process's BLAS thread pools (threadpoolctl), made once: the test's small
    matrices run on one thread, so its numbers do not depend on how many threads BLAS
    would use (a multi-threaded product sums in another order)."""
    from threadpoolctl import ThreadpoolController
    return ThreadpoolController()


def feedback_test(force, pos, fs: float, f_hi: float, *, past_s: float = PAST_S,
                  future_s: float = FUTURE_S, n_future: int = N_FUTURE,
                  hac_s: float = HAC_S) -> FeedbackTest | None:
    """Test whether the force responds to the position (module docstring).

    Parameters
    ----------
    force, pos : array_like, shape (n,)
        The stimulated axis's force (N) and position (m) at ``fs`` Hz.
    fs : float
        Sampling rate, Hz.
    f_hi : float
        Top of the analysis band, Hz (the grid's highest frequency).
    past_s, future_s : float
        Lengths of the force's past (at most :data:`MAX_PAST` samples of the analysis
        rate) and future in the model, s.
    n_future : int
        Block averages spanning the future.
    hac_s : float
        Bartlett lag window of the residual's autocorrelation, s.

    Returns
    -------
    FeedbackTest or None
        None when the record is too short for the model (fewer than 4 equations per
        coefficient).
    """
    with _blas().limit(limits=1, user_api="blas"):
        f, x, rate = band_signals(force, pos, fs, f_hi)
        return _regression_test(f, x, rate, past_s, future_s, n_future, hac_s)


def _regression_test(f: np.ndarray, x: np.ndarray, rate: float, past_s: float,
                     future_s: float, n_future: int, hac_s: float) -> FeedbackTest | None:
    """Steps 2 and 3 of :func:`feedback_test` on the band signals ``f``, ``x`` (rate in
    Hz)."""
    n = f.size
    n_past = max(2, min(MAX_PAST, int(round(past_s * rate))))
    n_fut = max(n_future, int(round(future_s * rate)))
    p = n_past + n_fut
    rows = n - p + 1
    fut = _future_basis(n_fut, n_future)
    m = n_past + fut.shape[1]
    if rows < 4 * m:
        return None
    # Regressors of equation s (time t = s + n_past − 1), window index w = 0…p−1 holding
    # f[s + w]: w < n_past are the past and present (lag n_past − 1 − w), the rest the
    # future (lag w − n_past + 1 ≥ 1). Parameters: the past taps, then the future blocks.
    # every correlation below from one transform of f, zero-padded past the longest lag
    lag = max(1, min(rows - 1, int(round(hac_s * rate))))
    size = _smooth_above(n + lag + p)
    spec_f = np.fft.rfft(f, size)
    r_ff = np.fft.irfft(spec_f.real ** 2 + spec_f.imag ** 2, size)[:lag + p + 1]
    # the Gram matrix's first row, Σ_{s<rows} f[s] f[s+j]: the whole sum less the last
    # p − 1 samples' share
    tail = f[rows:]
    first = r_ff[:p].copy()
    first[:tail.size] -= np.correlate(tail, tail, "full")[tail.size - 1:]
    win = _window_gram(f, p, rows, first)
    cross = win[:n_past, n_past:] @ fut
    gram = np.block([[win[:n_past, :n_past], cross],
                     [cross.T, fut.T @ win[n_past:, n_past:] @ fut]])
    gram[np.diag_indices(m)] += 1e-6 * np.trace(gram) / m
    y = x[n_past - 1:n_past - 1 + rows]
    r = np.fft.irfft(np.conj(np.fft.rfft(y, size)) * spec_f, size)[:p]   # Σ_s y[s] f[s+w]
    rhs = np.concatenate([r[:n_past], r[n_past:] @ fut])
    # one factorisation: the coefficients and the columns of gram⁻¹ of the future ones
    unit = np.zeros((m, m - n_past))
    unit[n_past:] = np.eye(m - n_past)
    sol = np.linalg.solve(gram, np.column_stack([rhs, unit]))
    coef, cols = sol[:, 0], sol[:, 1:]
    taps = np.concatenate([coef[:n_past], fut @ coef[n_past:]])
    fitted = np.fft.irfft(spec_f * np.conj(np.fft.rfft(taps, size)), size)
    resid = y - fitted[:rows]
    # covariance of the future coefficients: (gram⁻¹ Φ'ΣΦ gram⁻¹)_future with
    # Φ'ΣΦ ≈ rows · Bᵀ T(c) B, c(d) = Σ_m w_m r_ee(m) r_ff(m + d) (r: autocovariances,
    # w: Bartlett weights, T: the symmetric Toeplitz matrix of c)
    size_e = _smooth_above(rows + lag + 1)
    spec_e = np.fft.rfft(resid, size_e)
    r_ee = np.fft.irfft(spec_e.real ** 2 + spec_e.imag ** 2, size_e)[:lag + 1] / rows
    r_ff = r_ff / n
    a = r_ee * (1.0 - np.arange(lag + 1) / (lag + 1.0))
    c = np.correlate(np.concatenate([r_ff[:0:-1], r_ff]), np.concatenate([a[:0:-1], a]),
                     "valid")[p:2 * p]                                  # d = 0…p−1
    spread = np.concatenate([cols[:n_past], fut @ cols[n_past:]])       # B gram⁻¹, future
    toeplitz = c[np.abs(np.arange(p)[:, None] - np.arange(p)[None, :])]
    cov = rows * (spread.T @ (toeplitz @ spread))
    b = coef[n_past:]
    try:
        stat = float(b @ np.linalg.solve(cov, b))
    except np.linalg.LinAlgError:
        return None
    dof = int(b.size)
    return FeedbackTest(statistic=stat, dof=dof, p_value=chi2_sf(stat, dof), rate_hz=rate,
                        samples=rows, past_s=n_past / rate, future_s=n_fut / rate)


__all__ = ["FEEDBACK_ALPHA", "PAST_S", "FUTURE_S", "HAC_S", "N_FUTURE", "MAX_PAST",
           "FeedbackTest", "chi2_sf", "band_signals", "feedback_test"]
