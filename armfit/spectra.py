"""Per-trial frequency responses, derived arm dynamics, the common grid, flags, aggregates.

Everything here is a pure function: arrays in, arrays or frozen dataclasses out. Units:
force in N, position in m, sampling rate ``fs`` in Hz, frequencies in Hz, responses
position/force in m/N, power spectral densities in unit²/Hz (one-sided, ``scaling=
"density"`` as in :func:`scipy.signal.welch`).

Estimators (Fu & Çavuşoğlu 2010, section III; docs/methods.md, "Estimating frequency
responses"):

``chebwin``     the paper's ratio H = FFT(w·x) / FFT(w·F) of the whole record, both
                signals weighted by a 100 dB Chebyshev window (MATLAB/Octave
                ``fft`` + ``chebwin`` semantics, symmetric window, no detrending).
``h1``          Welch's averaged cross-/auto-spectra, H1 = P_fx / P_ff with the
                definitions of :func:`scipy.signal.csd` / :func:`scipy.signal.welch`
                (Hann window, 50 % overlap, per-segment mean removal by default).
``tfestimate``  derived arm dynamics Xa/Fa (eq. 6 input), Fa = F − Mp·ẍ with ẍ the
                second difference; Welch with 4 Hamming segments, 50 % overlap, segment
                length floor(2N/5), nfft = max(256, next power of 2) (MATLAB
                ``tfestimate(Fa, xa, hamming(L), L/2, nfft)`` semantics).

Common grid: log-spaced points (``per_decade`` per decade, ``fmin``…``fmax``); each grid
point averages the native-bin auto- and cross-spectra that fall in its band
[f·r^-½, f·r^½), r = 10^(1/per_decade) (Daniell smoothing), then forms H and the
coherence from the averaged spectra. Where the native bins are coarser than the band,
the nearest native bins are averaged instead, as many as needed for ``min_avg``
equivalent independent averages. Bins above fmax (or without force power) are never
used. The band average belongs to its bins' P_ff-weighted centroid in ln f, so each value
is moved to its grid frequency along the bins' fitted straight line of ln H in ln f.
Standard errors follow Bendat & Piersol (Random Data, 4th ed., eqs. 9.52 and 9.65):
ε = sqrt(1 − γ²) / (|γ| sqrt(2 n_d)), se_db = 20/ln 10 · ε, se_deg = ε in degrees, with
n_d the equivalent number of independent averages behind the value and γ² the coherence
about that line; raised where the bins' scatter about the line is larger (:func:`to_grid`).
"""

from __future__ import annotations

import collections
import contextlib
import functools
import itertools
import math
import pickle
import tempfile
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Executor, Future
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from armfit import _shared
from armfit._order import median, nanmedian, nanpercentile, percentile, unique
from armfit._version import __version__
from armfit.constants import (
    AXES,
    DB_PER_NEPER,
    DEVICE_MASS_KG,
    FORCE_LIMIT_N,
    GRID_HZ,
    POINTS_PER_DECADE,
)
from armfit.errors import BadInputError, NoInputError, OutputError, UsageError, cell
from armfit.feedback import FEEDBACK_ALPHA, FeedbackTest, chi2_sf, feedback_test
from armfit.io.arrow import arrow_array, arrow_ints, arrow_numbers
from armfit.io.atomic import atomic_path
from armfit.io.numbers import parse_numbers
from armfit.io.ranges import DEVICE_MASS_RANGE, FREQUENCY_RANGE, check_in_range
from armfit.io.schema import (
    COUNTED_FLAGS,
    CSV_FLOAT_FORMAT,
    SPECTRA_COLUMNS,
    SPECTRA_ESTIMATORS_JSON_KEY,
    SPECTRA_ESTIMATORS_KEY,
    SPECTRA_KEYS,
    SPECTRA_META_KEY,
    SPECTRA_TEXT,
    SPECTRA_VALUES,
    json_default,
    pack_records,
    unpack_records,
)
from armfit.io.trials import (
    Trial,
    TrialStream,
    open_trials,
    peak_abs,
    read_trial,
    saturated_samples,
)
from armfit.memory import release_memory
from armfit.workers import POOL_PRELOAD, iter_tasks, read_ahead, start_workers

if TYPE_CHECKING:
    import pandas as pd

METHODS = ("h1", "chebwin")

#: Quantile of the sample median's standard error relative to the mean's for normal
#: data: sqrt(pi/2) (asymptotic efficiency of the median).
MEDIAN_SE_FACTOR = math.sqrt(math.pi / 2.0)


# ---------------------------------------------------------------------------
# Native-bin spectra
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class BinSpectra:
    """Auto- and cross-spectra of one trial on the estimator's native bins.

    freq_hz: (nb,) bin frequencies, Hz. p_ff: (nb,) force PSD, N²/Hz. p_fx: (k, nb)
    cross-spectral densities force → each of k positions, N·m/Hz (scipy ``csd(f, x)``
    convention, E[conj(F)·X]). p_xx: (k, nb) position PSDs, m²/Hz. n_avg: equivalent
    number of independent averages per bin (Welch 1967 overlap correction; 1 for a single
    window). enbw_bins: equivalent noise bandwidth of the window in bins (how many
    adjacent bins carry one independent value). method: estimator name. first_bin: the
    lowest bin free of the record's mean (DC leaks into the window's main lobe, so bins
    below it are never used on the grid).
    """

    freq_hz: np.ndarray
    p_ff: np.ndarray
    p_fx: np.ndarray
    p_xx: np.ndarray
    n_avg: float
    enbw_bins: float
    method: str
    first_bin: int = 2

    @property
    def h(self) -> np.ndarray:
        """H = P_fx / P_ff, (k, nb) complex, m/N."""
        return self.p_fx / self.p_ff

    @property
    def coherence(self) -> np.ndarray:
        """Magnitude-squared coherence |P_fx|² / (P_ff P_xx), (k, nb)."""
        return np.abs(self.p_fx) ** 2 / (self.p_ff * self.p_xx)


def _as_outputs(pos) -> np.ndarray | list[np.ndarray]:
    """The outputs one by one: rows of a (k, n) array, or the signals of a list."""
    if isinstance(pos, (list, tuple)):  # signals of one length, not stacked into a copy
        return [np.asarray(p, dtype=float) for p in pos]
    pos = np.asarray(pos, dtype=float)
    return pos[None, :] if pos.ndim == 1 else pos.T  # (k, n)


def _window(window, nperseg: int) -> np.ndarray:
    if isinstance(window, np.ndarray):
        if window.shape != (nperseg,):
            raise UsageError(f"window has {window.shape[0]} points, expected "
                             f"nperseg={cell(nperseg)}")
        return window.astype(float)
    return _cached_window(window, nperseg, True)  # periodic, as scipy.signal.welch


#: Windows computed here, as coefficients of cosines (scipy.signal.windows.general_cosine
#: with the coefficients scipy uses): the estimator's defaults need no scipy.signal.
_COSINE_WINDOWS = {"hann": (0.5, 1.0 - 0.5), "hamming": (0.54, 1.0 - 0.54)}


def _cosine_window(coefficients: Sequence[float], n: int, periodic: bool) -> np.ndarray:
    """Σ_k a_k cos(k·φ), φ from −π to π over n points (n + 1 if ``periodic``, the last
    dropped): the same operations, in the same order, as ``scipy.signal.get_window``."""
    if n <= 1:
        return np.ones(n)
    m = n + 1 if periodic else n
    phi = np.linspace(-np.pi, np.pi, m)
    # the k = 0 term: 0 + a_0·cos(0·φ) is a_0 exactly, without m cosines of zero
    w = np.full(m, float(coefficients[0]))
    for k, a in enumerate(coefficients[1:], start=1):
        w += a * np.cos(k * phi)
    return w[:n] if periodic else w


@functools.lru_cache(maxsize=16)
def _cached_window(name: str, n: int, periodic: bool) -> np.ndarray:
    """The window ``name`` of n points (periodic or symmetric), cached (trials of a
    study share segment lengths). Hann and Hamming are computed here; any other name is
    ``scipy.signal.get_window``'s, imported only then (scipy.signal loads scipy.stats)."""
    if name in _COSINE_WINDOWS:
        w = _cosine_window(_COSINE_WINDOWS[name], n, periodic)
    else:
        from scipy.signal import get_window
        w = get_window(name, n, fftbins=periodic)
    w.setflags(write=False)
    return w


def welch_overlap_factor(win: np.ndarray, step: int, n_seg: int) -> float:
    """Equivalent number of independent averages of ``n_seg`` overlapped segments.

    Welch (1967): Var ∝ [1 + 2 Σ_{j=1}^{K−1} (1 − j/K) ρ_j²] / K with ρ_j the window's
    correlation at lag j·step, ρ_j = Σ w[n] w[n + j·step] / Σ w². Returns K / [...].
    """
    norm = float(np.sum(win * win))
    total = 1.0
    for j in range(1, n_seg):
        lag = j * step
        if lag >= win.size:
            break
        rho = float(np.sum(win[:-lag] * win[lag:])) / norm  # (np.dot would go to BLAS)
        total += 2.0 * (1.0 - j / n_seg) * rho * rho
    return n_seg / total


def enbw_bins(win: np.ndarray, nfft: int | None = None) -> float:
    """Equivalent noise bandwidth of a window, in FFT bins of length ``nfft``.

    ENBW = N Σw² / (Σw)² for N = len(win); zero padding to nfft > N widens it by nfft/N.
    """
    n = win.size
    nfft = n if nfft is None else nfft
    return n * float(np.sum(win * win)) / float(np.sum(win)) ** 2 * nfft / n


def welch_spectra(force, pos, fs: float, *, nperseg: int, noverlap: int | None = None,
                  window="hann", nfft: int | None = None, detrend: bool = True,
                  method: str = "h1", first_bin: int | None = None,
                  fmax_hz: float | None = None) -> BinSpectra:
    """Welch auto- and cross-spectra of force (n,) and positions (n,), (n, k) or a list
    of k signals (n,).

    Same definitions as :func:`scipy.signal.csd` / :func:`scipy.signal.welch` with
    ``scaling="density"``, one-sided, ``average="mean"``: segments of ``nperseg`` samples
    every ``nperseg − noverlap`` (default 50 % overlap), mean removed per segment when
    ``detrend``, windowed, zero-padded to ``nfft``; P_xy = 2·mean(conj(X)·Y)/(fs Σw²)
    (DC and Nyquist not doubled). Each signal is transformed once (faster than calling
    scipy three times). Units: N²/Hz, N·m/Hz, m²/Hz. ``first_bin`` defaults to 2·nfft/
    nperseg (the main-lobe half-width of Hann and Hamming windows). ``fmax_hz`` (Hz):
    keep only the bins up to the first one above it (the common grid uses no higher bin;
    the kept bins' values are the same as without it).
    """
    f = np.asarray(force, dtype=float)
    y = _as_outputs(pos)
    n = f.size
    if nperseg > n:
        raise UsageError(f"nperseg={cell(nperseg)} exceeds the record length {n}")
    noverlap = nperseg // 2 if noverlap is None else int(noverlap)
    if not 0 <= noverlap < nperseg:
        raise UsageError(f"noverlap={cell(noverlap)} must be >= 0 and < "
                         f"nperseg={cell(nperseg)}")
    nfft = nperseg if nfft is None else int(nfft)
    if nfft < nperseg:
        raise UsageError(f"nfft={cell(nfft)} must be >= nperseg={cell(nperseg)}")
    win = _window(window, nperseg)
    step = nperseg - noverlap
    n_seg = (n - noverlap) // step
    freq = np.fft.rfftfreq(nfft, 1.0 / fs)
    # bins above fmax_hz are not needed: the first one above it is the last one kept
    nb = freq.size if fmax_hz is None else min(freq.size, int(np.searchsorted(
        freq, fmax_hz * (1.0 + 1e-9), side="right")) + 1)
    # the signals' segments, mean removed and windowed, zero-padded to nfft, in one buffer
    buf = np.empty((1 + len(y), n_seg, nfft))
    buf[..., nperseg:] = 0.0
    seg = buf[..., :nperseg]
    for s, x in enumerate((f, *y)):
        x = np.ascontiguousarray(x)
        view = np.lib.stride_tricks.sliding_window_view(x, nperseg)[::step][:n_seg]
        if detrend:
            np.subtract(view, view.mean(axis=-1, keepdims=True), out=seg[s])
        else:
            seg[s] = view
    seg *= win
    spec = np.fft.rfft(buf, axis=-1)[..., :nb]  # (1 + k, n_seg, nb)
    del buf, seg
    scale = 1.0 / (fs * float(np.sum(win * win)))
    fspec = spec[0]
    p_ff = np.mean(fspec.real ** 2 + fspec.imag ** 2, axis=0) * scale
    p_fx = np.mean(np.conj(fspec)[None] * spec[1:], axis=1) * scale
    p_xx = np.mean(spec[1:].real ** 2 + spec[1:].imag ** 2, axis=1) * scale
    onesided = np.full(p_ff.shape, 2.0)
    onesided[0] = 1.0
    if nfft % 2 == 0 and nb == nfft // 2 + 1:
        onesided[-1] = 1.0
    return BinSpectra(freq_hz=freq[:nb], p_ff=p_ff * onesided,
                   p_fx=p_fx * onesided, p_xx=p_xx * onesided,
                   n_avg=welch_overlap_factor(win, step, n_seg),
                   enbw_bins=enbw_bins(win, nfft), method=method,
                   first_bin=(math.ceil(2 * nfft / nperseg) if first_bin is None
                              else first_bin))


def frf_h1(force, pos, fs: float, nperseg: int, noverlap: int | None = None,
           window="hann") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Welch H1 estimate X/F = P_fx / P_ff and coherence, scipy.signal.csd/welch semantics.

    Returns (freq_hz, H in m/N, coherence), H and coherence (nb,) for 1-D ``pos`` or
    (k, nb) for (n, k) ``pos``.
    """
    sp = welch_spectra(force, pos, fs, nperseg=nperseg, noverlap=noverlap, window=window)
    h, coh = sp.h, sp.coherence
    if np.ndim(pos) == 1:
        h, coh = h[0], coh[0]
    return sp.freq_hz, h, coh


def chebwin_spectra(force, pos, fs: float, *, attenuation_db: float = 100.0,
                    detrend: bool = True) -> BinSpectra:
    """Single-window periodograms of the whole record, 100 dB Chebyshev window.

    The paper's estimator (section III): X = fft(w .* x), F = fft(w .* F) with
    w = chebwin(N, 100) (symmetric, as MATLAB/Octave), no averaging; P_fx = conj(F)·X
    etc. scaled as one-sided densities, so P_fx / P_ff = X / F exactly. ``detrend``
    removes the record's mean first (the posture offset would otherwise fill the wide
    main lobe); bins inside the main-lobe half-width acosh(10^(A/20))/π are not used.
    """
    f = np.asarray(force, dtype=float)
    y = _as_outputs(pos)
    from scipy.signal.windows import chebwin  # see _cached_window
    win = chebwin(f.size, attenuation_db, sym=True)
    lobe = math.acosh(10.0 ** (attenuation_db / 20.0)) / math.pi
    return welch_spectra(f, y.T, fs, nperseg=f.size, noverlap=0, window=win,
                         detrend=detrend, method="chebwin", first_bin=math.ceil(lobe) + 1)


def frf_chebwin(force, pos, fs: float, *, attenuation_db: float = 100.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """The paper's H_exp(jω) = FFT(w·x)/FFT(w·F), w = chebwin(N, 100), bins 0…fs/2.

    Returns (freq_hz (nb,), H in m/N (nb,) or (k, nb)); bin k is at k·fs/N Hz, the same
    numbers as Octave's ``fft(w.*x) ./ fft(w.*F)`` for k = 0…floor(N/2).
    """
    f = np.asarray(force, dtype=float)
    from scipy.signal.windows import chebwin  # see _cached_window
    win = chebwin(f.size, attenuation_db, sym=True)
    y = _as_outputs(pos)
    fx = np.fft.rfft(win * f)
    h = np.fft.rfft(win * y, axis=-1) / fx
    return np.fft.rfftfreq(f.size, 1.0 / fs), (h[0] if np.ndim(pos) == 1 else h)


def tfestimate_segment(n: int, segments: int = 4) -> tuple[int, int, int]:
    """MATLAB ``tfestimate``/``pwelch`` segmentation for ``segments`` 50 %-overlapped
    segments of an n-sample record: (nperseg = floor(2n/(K+1)), noverlap = floor(L/2),
    nfft = max(256, 2^ceil(log2 L)))."""
    nperseg = (2 * n) // (segments + 1)
    nfft = max(256, 1 << max(0, math.ceil(math.log2(max(nperseg, 1)))))
    return nperseg, nperseg // 2, nfft


def derived_arm_signals(force, pos, fs: float, mp: float) -> tuple[np.ndarray, np.ndarray]:
    """Arm-side force and position, Fu & Çavuşoğlu 2010, eqs. 1–2 (docs/methods.md, "Arm,
    device and closed loop").

    Fa[n] = F[n] − Mp·ẍ[n], ẍ[n] = (x[n+1] − 2x[n] + x[n−1])·fs² (m/s²); returns
    (Fa, xa) for n = 1…N−2 (first and last samples dropped), N and m; ``mp`` in kg.
    """
    f = np.asarray(force, dtype=float)
    x = np.asarray(pos, dtype=float)
    acc = (x[2:] - 2.0 * x[1:-1] + x[:-2]) * (fs * fs)
    return f[1:-1] - mp * acc, x[1:-1]


def derived_spectra(force, pos, fs: float, mp: float, *, segments: int = 4,
                    detrend: bool = True, fmax_hz: float | None = None) -> BinSpectra:
    """Derived arm dynamics spectra: Xa/Fa by Welch (MATLAB tfestimate semantics).

    Input Fa (N), output xa (m) from :func:`derived_arm_signals`; ``segments`` Hamming
    (symmetric, as MATLAB ``hamming``) segments with 50 % overlap, nfft per
    :func:`tfestimate_segment`. ``detrend`` removes each segment's mean (MATLAB does not;
    the record's posture offset otherwise leaks into the lowest bins). ``fmax_hz`` (Hz):
    keep only the bins up to the first one above it, as :func:`welch_spectra` (the
    nfft of tfestimate puts most bins far above the common grid).
    """
    fa, xa = derived_arm_signals(force, pos, fs, mp)
    nperseg, noverlap, nfft, win = _derived_segments(fa.size, segments)
    return welch_spectra(fa, xa, fs, nperseg=nperseg, noverlap=noverlap, window=win,
                         nfft=nfft, detrend=detrend, method="tfestimate", fmax_hz=fmax_hz)


def _derived_segments(n: int, segments: int) -> tuple[int, int, int, np.ndarray]:
    """The segmentation of :func:`derived_spectra` for derived signals of ``n`` samples
    (the record's less its first and last): nperseg, noverlap, nfft
    (:func:`tfestimate_segment`) and the symmetric Hamming window, cached."""
    nperseg, noverlap, nfft = tfestimate_segment(n, segments)
    return nperseg, noverlap, nfft, _cached_window("hamming", nperseg, False)


# ---------------------------------------------------------------------------
# Common grid
# ---------------------------------------------------------------------------

def log_grid(fmin: float = GRID_HZ[0], fmax: float = GRID_HZ[1],
             per_decade: int = POINTS_PER_DECADE) -> np.ndarray:
    """Log-spaced frequencies (Hz) from fmin to fmax inclusive, ``per_decade`` per decade
    (rounded so both ends are on the grid)."""
    if not 0 < fmin < fmax:
        raise UsageError(f"need 0 < fmin < fmax, got fmin={fmin} Hz, fmax={fmax} Hz")
    if per_decade < 1:
        raise UsageError(f"per_decade={cell(per_decade)} must be >= 1")
    n = max(2, int(round(per_decade * math.log10(fmax / fmin))) + 1)
    return np.geomspace(fmin, fmax, n)


@dataclass(frozen=True)
class GridResponse:
    """Responses of one trial on the common grid.

    freq_hz: (ng,) Hz. h: (k, ng) complex m/N. coherence: (k, ng). se_db, se_deg: (k, ng)
    standard errors of 20 log10|H| (dB) and of the phase (deg), Bendat & Piersol.
    n_avg: (ng,) equivalent number of independent averages behind each value.
    """

    freq_hz: np.ndarray
    h: np.ndarray
    coherence: np.ndarray
    se_db: np.ndarray
    se_deg: np.ndarray
    n_avg: np.ndarray


def band_bins(freq_native: np.ndarray, grid: np.ndarray, min_bins: int,
              max_bins: int | None = None, first_bin: int = 1, last_bin: int | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Native-bin index ranges [lo, hi) averaged at each grid point.

    The band of grid point g is [g/h, g·h] with h = r^½ (r the grid's ratio), narrowed
    to h = min(r^½, grid[-1]/g, g/grid[0]) near the ends so that it stays symmetric in
    log frequency (a one-sided average of a sloping response is biased); where it
    holds fewer than ``min_bins`` bins, the ``min_bins`` bins nearest
    to g are used instead; where it holds more than ``max_bins``, only the ``max_bins``
    bins nearest to g (less smoothing bias at sharp resonances). Only bins
    ``first_bin`` ≤ i < ``last_bin`` are ever used: ``first_bin`` (at least 1) keeps DC
    and the record mean's main lobe out; ``last_bin`` defaults to the first bin above the
    grid's top frequency, where the stimulus may stop (H of such bins is noise), so the
    top point's nearest bins all lie at or below it.
    """
    freq_native = np.asarray(freq_native, dtype=float)
    grid = np.asarray(grid, dtype=float)
    ratio = grid[1] / grid[0] if grid.size > 1 else 2.0
    # symmetric in log frequency, narrowed near the ends of the grid so that no band
    # is one-sided (a one-sided average of a sloping response is biased)
    half = np.minimum(math.sqrt(ratio), np.minimum(grid[-1] / grid, grid / grid[0]))
    first = max(1, first_bin)
    if last_bin is None:
        last_bin = int(np.searchsorted(freq_native, grid[-1] * (1.0 + 1e-9), side="right"))
    last = min(freq_native.size, int(last_bin))
    if last - first < 1:
        raise UsageError(f"no native bin between {freq_native[min(first, freq_native.size - 1)]:g}"
                         f" Hz and {grid[-1]:g} Hz")
    lo = np.clip(np.searchsorted(freq_native, grid / half, side="left"), first, last)
    hi = np.clip(np.searchsorted(freq_native, grid * half, side="right"), first, last)
    if max_bins is not None:
        centre = np.searchsorted(freq_native, grid)
        lo = np.maximum(lo, centre - max_bins // 2)
        hi = np.minimum(hi, lo + max_bins)
        hi = np.maximum(hi, lo)
    short = (hi - lo) < min_bins
    if np.any(short):
        m = min(min_bins, last - first)
        near = np.clip(np.searchsorted(freq_native, grid[short]), first, last - 1)
        # choose the nearer of the two neighbours as centre, then a window of m bins
        left_closer = (grid[short] - freq_native[near - 1]) < (freq_native[near] - grid[short])
        centre = np.where(left_closer & (near > first), near - 1, near)
        start = np.clip(centre - (m - 1) // 2, first, last - m)
        lo = lo.copy()
        hi = hi.copy()
        lo[short] = start
        hi[short] = start + m
    return lo, hi


def bendat_piersol_se(coherence: np.ndarray, n_avg) -> tuple[np.ndarray, np.ndarray]:
    """Standard errors of 20 log10|H| (dB) and phase (deg) of an H1 estimate.

    ε = sqrt(1 − γ²) / (|γ| sqrt(2 n_d)) — Bendat & Piersol, Random Data, eq. 9.52
    (normalised random error of |H|, also the phase's standard deviation in rad, eq. 9.65).
    Returns (20/ln10 · ε, 180/π · ε).
    """
    coh = np.clip(np.asarray(coherence, dtype=float), 1e-12, 1.0)
    eps = np.sqrt(1.0 - coh) / (np.sqrt(coh) * np.sqrt(2.0 * np.asarray(n_avg, dtype=float)))
    return DB_PER_NEPER * eps, np.degrees(eps)


def debiased_coherence(coherence, n_avg) -> np.ndarray:
    """Coherence corrected for its estimation bias with n_d averages.

    An estimate from n_d averages is biased up, E[γ̂²] ≈ γ² + (1 − γ²)/n_d (Carter, Knapp
    & Nuttall 1973, first order), so γ² ≈ (γ̂² − 1/n_d)/(1 − 1/n_d), floored at 1e-6.
    Used for the standard errors, where the raw estimate would make them too small.
    """
    n = np.maximum(np.asarray(n_avg, dtype=float), 1.0 + 1e-9)
    return np.clip((np.asarray(coherence, dtype=float) - 1.0 / n) / (1.0 - 1.0 / n), 1e-6, 1.0)


#: Force PSD below this fraction of its median over the grid's range counts as no
#: stimulus (−40 dB): such bins at the ends of the range are not used.
NEGLIGIBLE_FORCE_POWER = 1e-4


def usable_bins(sp: BinSpectra, grid: np.ndarray) -> tuple[int, int]:
    """Native-bin index range [first, last) that :func:`to_grid` may use.

    From ``sp.first_bin`` (DC and the mean's main lobe excluded) up to the last bin at or
    below the grid's top frequency; then trimmed at both ends while the force PSD there is
    below NEGLIGIBLE_FORCE_POWER × its median over the range (no stimulus: H is noise).
    """
    f = sp.freq_hz
    first = max(1, sp.first_bin)
    last = int(np.searchsorted(f, grid[-1] * (1.0 + 1e-9), side="right"))
    if last - first < 1:
        raise UsageError(f"no frequency bin of the spectra between {f[min(first, f.size - 1)]:g}"
                         f" Hz and {grid[-1]:g} Hz")
    p = sp.p_ff[first:last]
    live = np.flatnonzero(p >= NEGLIGIBLE_FORCE_POWER * median(p))
    if live.size:
        first, last = first + int(live[0]), first + int(live[-1]) + 1
    return first, last


def _line_fit(y: np.ndarray, u: np.ndarray, valid: np.ndarray
              ) -> tuple[np.ndarray, ...]:
    """Least-squares straight line y ≈ ȳ + b·(u − ū) per band.

    y: (k, ng, m) values, u: (ng, m) abscissae, valid: (ng, m) which entries belong to
    the band. Returns (slope b (k, ng), residual sum of squares (k, ng), S_uu (ng,) =
    Σ (u − ū)², ȳ (k, ng), ū (ng,)), means over the valid entries; slope 0 where the band
    has fewer than two distinct abscissae.
    """
    w = valid.astype(float)
    n = np.maximum(w.sum(axis=-1), 1.0)
    u_bar = (w * u).sum(axis=-1) / n
    du = (u - u_bar[:, None]) * w
    y = np.where(valid, y, 0.0)
    y_bar = y.sum(axis=-1) / n
    dy = (y - y_bar[..., None]) * w
    suu = np.sum(du * du, axis=-1)
    suy = np.sum(dy * du, axis=-1)
    syy = np.sum(dy * dy, axis=-1)
    pos = suu > 0
    slope = np.where(pos, suy / np.where(pos, suu, 1.0), 0.0)
    return slope, np.maximum(syy - slope * suy, 0.0), suu, y_bar, u_bar


#: Largest band variance (in units of the grid step², ln f) for which the curvature
#: correction is applied: full bands have about 1/12; wider fallback bands at the lowest
#: frequencies would amplify the noise of the second difference.
_CURVATURE_MAX_VAR = 1.0 / 6.0


@functools.lru_cache(maxsize=8)
def _uniform_log_step(grid: bytes) -> float | None:
    """The step in ln f of a grid (float64 bytes, Hz) uniform in ln f, else None."""
    step = np.diff(np.log(np.frombuffer(grid)))
    if not np.allclose(step, step.mean(), rtol=1e-6):
        return None
    return float(step.mean())


def _curvature_correction(h: np.ndarray, grid: np.ndarray, var_u: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Second-order correction of a band average for the response's curvature.

    The average of H over a band of variance var_u in u = ln f is H(ū)·(1 + ½(L'' + L'²)
    var_u) to second order, L = ln H (Taylor expansion of H = e^L); L' and L'' are taken
    from the grid values themselves by central differences (the grid must be uniform in
    ln f) and the average divided by that factor. Applied where var_u is at most
    :data:`_CURVATURE_MAX_VAR` grid steps² (a full band: 1/12). Returns the corrected H
    and the factor by which the standard errors grow from the noise of the second
    difference (√6 σ/Δ² · ½ var_u, in quadrature; ≈ 1.005 for a full band).
    """
    ng = grid.size
    ones = np.ones(ng)
    if ng < 3:
        return h, ones
    d = _uniform_log_step(np.ascontiguousarray(grid, dtype=float).tobytes())
    if d is None:
        return h, ones
    with np.errstate(divide="ignore", invalid="ignore"):
        L = np.log(np.abs(h)) + 1j * np.unwrap(np.angle(h), axis=-1)
    L1 = np.empty_like(L)
    L2 = np.empty_like(L)
    L1[..., 1:-1] = (L[..., 2:] - L[..., :-2]) / (2.0 * d)
    L2[..., 1:-1] = (L[..., 2:] - 2.0 * L[..., 1:-1] + L[..., :-2]) / (d * d)
    for arr in (L1, L2):  # ends: the neighbouring interior value
        arr[..., 0] = arr[..., 1]
        arr[..., -1] = arr[..., -2]
    corr = 0.5 * (L2 + L1 * L1) * var_u
    use = (var_u <= _CURVATURE_MAX_VAR * d * d) & np.isfinite(corr) & (np.abs(corr) < 0.05)
    h = h * np.exp(-np.where(use, corr, 0.0))
    gain = np.where(use, np.sqrt(1.0 + (0.5 * math.sqrt(6.0) * var_u / (d * d)) ** 2), 1.0)
    return h, gain


@dataclass(frozen=True)
class _Bands:
    """The native bins of each grid band (:func:`_grid_bands`): ranges [lo, hi), their
    counts (float), the end of the usable range, and the bins gathered into a padded
    (ng, width) block (:func:`_band_block`). Read-only: shared by the trials whose
    spectra have the same bins and bands."""

    lo: np.ndarray
    hi: np.ndarray
    count: np.ndarray
    last: int
    idx: np.ndarray
    valid: np.ndarray
    u: np.ndarray


def _grid_bands(sp: BinSpectra, grid: np.ndarray, min_avg: float, max_avg: float | None,
                bins: tuple[int, int] | None = None) -> _Bands:
    """The bands of each grid point in the native bins of ``sp`` (see :func:`to_grid`);
    ``bins`` overrides :func:`usable_bins`."""
    min_bins = max(1, math.ceil(min_avg * sp.enbw_bins / sp.n_avg))
    max_bins = None if max_avg is None else max(min_bins, math.ceil(
        max_avg * sp.enbw_bins / sp.n_avg))
    first, last = usable_bins(sp, grid) if bins is None else bins
    freq = np.ascontiguousarray(sp.freq_hz, dtype=float)
    grid = np.ascontiguousarray(grid, dtype=float)
    return _cached_bands(freq.tobytes(), grid.tobytes(), min_bins, max_bins, int(first),
                         int(last))


@functools.lru_cache(maxsize=32)
def _cached_bands(freq: bytes, grid: bytes, min_bins: int, max_bins: int | None,
                  first: int, last: int) -> _Bands:
    """:class:`_Bands` of native bins ``freq`` and grid ``grid`` (float64 bytes, Hz),
    made once: the trials of a study share their segment lengths and so their bins, and
    H1 and H2 of a trial share their bands."""
    freq_hz = np.frombuffer(freq)
    lo, hi = band_bins(freq_hz, np.frombuffer(grid), min_bins, max_bins, first, last)
    count = (hi - lo).astype(float)
    idx, valid, u = _band_block(freq_hz, lo, count, last)
    for a in (lo, hi, count, idx, valid, u):
        a.setflags(write=False)
    return _Bands(lo, hi, count, last, idx, valid, u)


def _band_means(lo: np.ndarray, hi: np.ndarray, count: np.ndarray):
    """The mean over each band [lo, hi) of a (…, nb) array, by cumulative sums."""
    def band_mean(a: np.ndarray) -> np.ndarray:
        c = np.concatenate([np.zeros(a.shape[:-1] + (1,), a.dtype), np.cumsum(a, axis=-1)],
                           axis=-1)
        return (c[..., hi] - c[..., lo]) / count
    return band_mean


def _band_block(freq_hz: np.ndarray, lo: np.ndarray, count: np.ndarray, last: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bins of each band gathered into a padded (ng, width) block: their indices,
    which entries belong to the band, and u = ln f of each."""
    width = int(count.max())
    idx = np.minimum(lo[:, None] + np.arange(width)[None, :], last - 1)
    valid = np.arange(width)[None, :] < count[:, None]
    return idx, valid, np.log(freq_hz[idx])


@dataclass(frozen=True)
class _BandLines:
    """The straight lines of ln|H| and of the phase (relative to the band's value) in
    u = ln f over each band's bins (:func:`_band_lines`)."""

    b_mag: np.ndarray
    rss_mag: np.ndarray
    suu: np.ndarray
    a_mag: np.ndarray
    u_bar: np.ndarray
    b_ph: np.ndarray
    rss_ph: np.ndarray
    a_ph: np.ndarray

    def trend(self, h: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The fitted response of each bin, (k, ng, width)."""
        return (h / np.abs(h))[..., None] * np.exp(
            (self.a_mag + 1j * self.a_ph)[..., None]
            + (self.b_mag + 1j * self.b_ph)[..., None] * (u - self.u_bar[:, None]))


def _band_lines(h: np.ndarray, h_bin: np.ndarray, u: np.ndarray, valid: np.ndarray
                ) -> _BandLines:
    """Line fits of the bins' ln|H| and phase (in (−π, π] about the band value ``h``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_mag = np.log(np.abs(h_bin))
        # phase relative to the band's value, in (−π, π]: no unwrapping needed
        dev = np.angle(h_bin * np.conj(h)[..., None])
    finite = valid & np.all(np.isfinite(ln_mag), axis=0)
    b_mag, rss_mag, suu, a_mag, u_bar = _line_fit(np.nan_to_num(ln_mag), u, finite)
    b_ph, rss_ph, _, a_ph, _ = _line_fit(np.nan_to_num(dev), u, finite)
    return _BandLines(b_mag, rss_mag, suu, a_mag, u_bar, b_ph, rss_ph, a_ph)


def _grid_finish(h: np.ndarray, grid: np.ndarray, lines: _BandLines, w: np.ndarray,
                 u: np.ndarray, se_db: np.ndarray, se_deg: np.ndarray, count: np.ndarray,
                 enbw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The band values moved to the grid frequencies and corrected for curvature, and
    their standard errors raised to the bins' scatter and for the move (:func:`to_grid`);
    ``w`` (ng, width): the bins' weights in the band's value. Returns (h, se_db,
    se_deg)."""
    centroid = np.sum(w * u, axis=-1) / np.sum(w, axis=-1)
    shift = np.log(grid) - centroid                             # (ng,)
    h = h * np.exp((lines.b_mag + 1j * lines.b_ph) * shift)
    var_u = np.sum(w * (u - centroid[:, None]) ** 2, axis=-1) / np.sum(w, axis=-1)
    h, curv_gain = _curvature_correction(h, grid, var_u)
    n_ind = count / enbw
    ok = n_ind >= 3.0
    dof = np.maximum(count - 2.0 * enbw, enbw)
    root = np.sqrt(n_ind)
    s_db = DB_PER_NEPER * np.sqrt(lines.rss_mag / dof)         # per-bin scatter, dB
    s_deg = np.degrees(np.sqrt(lines.rss_ph / dof))             # per-bin scatter, deg
    se_db = np.where(ok, np.maximum(se_db, s_db / root), se_db)
    se_deg = np.where(ok, np.maximum(se_deg, s_deg / root), se_deg)
    # the move along the fitted slope: var(b) = s² · ENBW / S_uu (correlated bins)
    suu = lines.suu
    with np.errstate(divide="ignore", invalid="ignore"):
        lever = np.where(suu > 0, shift * shift * enbw / np.where(suu > 0, suu, 1.0), 0.0)
    bin_db = np.where(ok, s_db, se_db * root)
    bin_deg = np.where(ok, s_deg, se_deg * root)
    se_db = np.sqrt(se_db ** 2 + lever * bin_db ** 2) * curv_gain
    se_deg = np.sqrt(se_deg ** 2 + lever * bin_deg ** 2) * curv_gain
    return h, se_db, se_deg


def to_grid(sp: BinSpectra, grid: np.ndarray, *, min_avg: float = 8.0,
            max_avg: float | None = None, bins: tuple[int, int] | None = None
            ) -> GridResponse:
    """Bring native-bin spectra to the common grid by band-averaging (module docstring).

    Averaged: P_ff, P_fx, P_xx over each grid point's bins (:func:`band_bins`, within
    :func:`usable_bins`, or the native-bin range ``bins`` = (first, last) when given);
    H = <P_fx>/<P_ff>, γ² = |<P_fx>|² / (<P_ff><P_xx>);
    n_d = n_avg · max(1, bins / ENBW). Where fewer than ceil(min_avg·ENBW/n_avg) bins fall
    in a band, that many nearest bins are used; no more than ceil(max_avg·ENBW/n_avg)
    bins are averaged (None: the whole band).

    Frequency of the value: <P_fx>/<P_ff> is the P_ff-weighted mean of the bins' H, so it
    belongs to the weighted centroid ū = Σ P_ff ln f / Σ P_ff of the bins, not to ln g
    (up to half a native bin away where the bins are coarser than the band, and one-sided
    at the grid's top). Each value is moved to its grid frequency along the bins' own
    straight-line trend of ln H in ln f: H(g) = H · exp((b_mag + j b_phase)(ln g − ū)).

    Standard errors: Bendat & Piersol's (eqs. 9.52, 9.65) from the debiased coherence,
    raised where the native bins' own scatter says the value is less certain (leakage,
    smoothing errors that the coherence does not see). The scatter is measured about the
    same straight line in ln f (dB and phase), so the response's own slope across the
    band (−40 dB/decade above the resonances) does not count as noise:
    s² = RSS / (bins − 2·ENBW) per bin, se = s / sqrt(n_ind) with n_ind = bins / ENBW
    independent bins; used where n_ind ≥ 3 (at least one independent residual after the
    line fit). The move's own uncertainty, (ln g − ū)² · s² · ENBW / S_uu, is added in
    quadrature (s² from the scatter, or from the coherence where n_ind < 3). Finally the
    average is corrected for the response's curvature across the band
    (:func:`_curvature_correction`).
    """
    bands = _grid_bands(sp, grid, min_avg, max_avg, bins)
    count, idx, valid, u = bands.count, bands.idx, bands.valid, bands.u
    band_mean = _band_means(bands.lo, bands.hi, count)
    p_ff = band_mean(sp.p_ff)
    p_fx = band_mean(sp.p_fx)
    p_xx = band_mean(sp.p_xx)
    h = p_fx / p_ff
    with np.errstate(invalid="ignore", divide="ignore"):
        coh = np.abs(p_fx) ** 2 / (p_ff * p_xx)
    coh = np.where(np.isfinite(coh), np.clip(coh, 0.0, 1.0), np.nan)
    n_d = sp.n_avg * np.maximum(1.0, count / sp.enbw_bins)
    w = np.where(valid, sp.p_ff[idx], 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        h_bin = sp.p_fx[:, idx] / sp.p_ff[idx]                  # (k, ng, width)
    lines = _band_lines(h, h_bin, u, valid)
    # Coherence about the line: output power left after removing the bins' fitted
    # response ln H_k = (a_mag + j a_ph) + (b_mag + j b_ph)(ln f_k − ū) (phase relative
    # to H), so that the response's own change across the band does not count as noise
    # (Bendat & Piersol's γ² of the band average would).
    trend = lines.trend(h, u)
    resid = (sp.p_xx[:, idx] - 2.0 * np.real(np.conj(trend) * sp.p_fx[:, idx])
             + np.abs(trend) ** 2 * sp.p_ff[idx])
    resid = np.sum(np.where(valid, resid, 0.0), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        coh_line = 1.0 - resid / (p_xx * count)
    coh_line = np.where(np.isfinite(coh_line), np.clip(coh_line, 0.0, 1.0), 0.0)
    se_db, se_deg = bendat_piersol_se(debiased_coherence(coh_line, n_d), n_d)
    h, se_db, se_deg = _grid_finish(h, grid, lines, w, u, se_db, se_deg, count,
                                    sp.enbw_bins)
    return GridResponse(freq_hz=grid, h=h, coherence=coh, se_db=se_db, se_deg=se_deg,
                        n_avg=n_d)


def h2_to_grid(sp: BinSpectra, grid: np.ndarray, *, min_avg: float = 8.0,
               max_avg: float | None = None, output: int = 0) -> GridResponse:
    """The H2 estimate X/F = <P_xx>/<P_xf> of one output on the common grid.

    H2 is the reciprocal of the H1 estimate of F/X (the position taken as the input), so
    it is :func:`to_grid` of the spectra with the roles of force and position exchanged:
    the same bands (the force's usable bins, :func:`usable_bins`), a value moved from the
    P_xx-weighted centroid of its bins, Bendat & Piersol's standard errors of F/X (those
    of ln X/F are the same numbers), the bins' scatter and the curvature correction.
    H1/H2 = γ² of the band average: H2 is unbiased when the noise is on the force only,
    H1 when it is on the position only (Bendat & Piersol, *Random Data*, 4th ed., ch. 6,
    systems with extraneous noise; Pintelon & Schoukens, *System Identification: A
    Frequency Domain Approach*, 2nd ed., ch. 2).

    Parameters
    ----------
    sp : BinSpectra
        The spectra of :func:`welch_spectra` (force → positions).
    grid : ndarray
        Grid frequencies, Hz.
    min_avg, max_avg : float
        As :func:`to_grid`.
    output : int
        Which position of ``sp`` (0: the first).

    Returns
    -------
    GridResponse
        h (1, ng) the H2 values, m/N; coherence, se_db, se_deg, n_avg as :func:`to_grid`.
    """
    swapped = BinSpectra(freq_hz=sp.freq_hz, p_ff=sp.p_xx[output],
                         p_fx=np.conj(sp.p_fx[output:output + 1]), p_xx=sp.p_ff[None, :],
                         n_avg=sp.n_avg, enbw_bins=sp.enbw_bins, method="h2",
                         first_bin=sp.first_bin)
    g = to_grid(swapped, grid, min_avg=min_avg, max_avg=max_avg,
                bins=usable_bins(sp, grid))
    with np.errstate(divide="ignore", invalid="ignore"):
        h = 1.0 / g.h
    return replace(g, h=h)


def reference_to_grid(rsp: BinSpectra, sp: BinSpectra, grid: np.ndarray, *,
                      min_avg: float = 8.0, max_avg: float | None = None) -> GridResponse:
    """X/F through the reference: H = <P_ry>/<P_rF> per grid band (docs/methods.md,
    "The reference estimator").

    With r the rig's excitation (a commanded force or a reference trajectory), F the
    measured force and y a position, Y = H F + E with E the part of Y that the force does
    not explain through H (noise anywhere in the loop, the force's own noise included):
    S_ry = H S_rF + S_rE, and H = S_ry/S_rF wherever E is uncorrelated with r — whatever
    the noise on F and whether or not F responds to y (the instrumental-variable or
    errors-in-variables estimator: Pintelon & Schoukens, *System Identification*, 2nd
    ed., ch. 2; Ljung, *System Identification*, 2nd ed., ch. 13, closed loop). Its variance,
    by the delta method, is Var(Ĥ)/|H|² = q / (n_d γ²_rF) with q = S_ee / (S_FF |H|²),
    S_ee the spectrum of Y − H F and γ²_rF the coherence of the reference and the force;
    for r = F, q = (1 − γ²)/γ² and it is Bendat & Piersol's (1 − γ²)/(n_d γ²). Half of it
    goes to ln|H|, half to the phase: ε² = q' / (2 n_d γ²_rF), se_db = 20/ln 10 · ε,
    se_deg = ε in degrees, with S_ee taken about the bins' straight line (as
    :func:`to_grid`), γ²_rF debiased (:func:`debiased_coherence`) and q corrected for
    its small-sample bias in the same way as the coherence of H1, q' = q/(1 − (1 + q)/n_d)
    (so that for r = F the standard errors are :func:`to_grid`'s). The bands, the move to
    the grid frequency, the bins' scatter and the curvature correction are those of
    :func:`to_grid`; a bin's weight is |P_rF|.

    Parameters
    ----------
    rsp : BinSpectra
        Spectra of the reference and [force, positions…] (:func:`welch_spectra` of r
        and the columns F, y₁, …): p_ff = P_rr, p_fx = [P_rF, P_ry₁, …], p_xx = [P_FF,
        P_y₁y₁, …].
    sp : BinSpectra
        Spectra of the force and the same positions on the same bins (P_Fy in p_fx).
    grid : ndarray
        Grid frequencies, Hz.
    min_avg, max_avg : float
        As :func:`to_grid`.

    Returns
    -------
    GridResponse
        h (k, ng), m/N; ``coherence``: the coherence an H1 estimate of the same standard
        error would have, 1/(1 + 2 n_d ε²); se_db, se_deg; n_avg.
    """
    f1, l1 = usable_bins(sp, grid)
    f2, l2 = usable_bins(rsp, grid)
    bins = (max(f1, f2), min(l1, l2)) if min(l1, l2) - max(f1, f2) >= 1 else (f1, l1)
    bands = _grid_bands(rsp, grid, min_avg, max_avg, bins)
    count, idx, valid, u = bands.count, bands.idx, bands.valid, bands.u
    band_mean = _band_means(bands.lo, bands.hi, count)
    p_rr = band_mean(rsp.p_ff)
    p_rf = band_mean(rsp.p_fx[0])
    p_ff = band_mean(rsp.p_xx[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        h = band_mean(rsp.p_fx[1:]) / p_rf
        coh_rf = np.abs(p_rf) ** 2 / (p_rr * p_ff)
    n_d = rsp.n_avg * np.maximum(1.0, count / rsp.enbw_bins)
    w = np.where(valid, np.abs(rsp.p_fx[0][idx]), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        h_bin = rsp.p_fx[1:][:, idx] / rsp.p_fx[0][idx]
    lines = _band_lines(h, h_bin, u, valid)
    trend = lines.trend(h, u)
    resid = (rsp.p_xx[1:][:, idx] - 2.0 * np.real(np.conj(trend) * sp.p_fx[:, idx])
             + np.abs(trend) ** 2 * rsp.p_xx[0][idx])
    s_ee = np.maximum(np.sum(np.where(valid, resid, 0.0), axis=-1) / count, 0.0)
    coh_rf = debiased_coherence(np.where(np.isfinite(coh_rf), coh_rf, 0.0), n_d)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = s_ee / (p_ff * np.abs(h) ** 2)
        shrink = 1.0 - (1.0 + q) / n_d
        eps2 = np.where(shrink > 0, q / shrink, np.inf) / (2.0 * n_d * coh_rf)
    eps2 = np.where(np.isfinite(eps2), eps2, np.inf)
    eps = np.sqrt(eps2)
    coh = 1.0 / (1.0 + 2.0 * n_d * eps2)
    h, se_db, se_deg = _grid_finish(h, grid, lines, w, u, DB_PER_NEPER * eps,
                                    np.degrees(eps), count, rsp.enbw_bins)
    return GridResponse(freq_hz=grid, h=h, coherence=coh, se_db=se_db, se_deg=se_deg,
                        n_avg=n_d)


# ---------------------------------------------------------------------------
# Flags
# ---------------------------------------------------------------------------

def saturated(force, limit_N: float) -> bool:
    """True when |F| reaches the device's force limit (N) anywhere in the record (the
    rule of :func:`armfit.io.trials.saturated_samples`), from the record's extremes
    unless a sample is NaN (which the rule passes over)."""
    f = np.asarray(force, dtype=np.float64)
    top = peak_abs(f)
    if top == top:     # no NaN: the extremes decide
        return bool(top >= limit_N)
    return bool(saturated_samples(f, limit_N).any())


def moving_mean(x: np.ndarray, width: int) -> np.ndarray:
    """Mean of ``width`` samples centred on each sample (the window of sample i is
    i − width//2 … i − width//2 + width − 1), the record's end values repeated beyond its
    ends: ``scipy.ndimage.uniform_filter1d(x, width, mode="nearest")``, by cumulative
    sums (equal to it within rounding).

    Parameters
    ----------
    x : ndarray, shape (n,)
        The signal.
    width : int
        Samples averaged, 1 … n.

    Returns
    -------
    ndarray, shape (n,)
    """
    x = np.asarray(x, dtype=float)
    n, left = x.size, width // 2
    # the cumulative sum of [0, x[0] × left, x, x[-1] × (width − 1 − left)], in place
    c = np.empty(n + width)
    c[0] = 0.0
    c[1:left + 1] = x[0]
    c[left + 1:left + 1 + n] = x
    c[left + 1 + n:] = x[-1]
    np.cumsum(c, out=c)
    out = c[width:] - c[:-width]
    out /= width
    return out


def drifting(pos, fs: float, fmin: float, factor: float = 3.0) -> bool:
    """True when slow postural drift dominates the position record.

    The slow part is the moving mean over one period of ``fmin`` (1/fmin s); the record
    drifts when the slow part's peak-to-peak exceeds ``factor`` × the standard deviation
    of the remaining (stimulus-driven) motion. Positions in m, fs and fmin in Hz.
    """
    x = np.asarray(pos, dtype=float)
    width = max(1, min(x.size, int(round(fs / fmin))))
    slow = moving_mean(x, width)
    fast = np.std(x - slow)
    return bool(np.ptp(slow[width // 2: x.size - width // 2 or None]) > factor * fast)


# ---------------------------------------------------------------------------
# One trial
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class EstimateConfig:
    """Options of ``armfit estimate`` (frequencies in Hz, masses in kg, forces in N).

    method: "h1" or "chebwin" (measured and cross responses). reference: estimate X/F
    through a trial's reference column when it has one (method "h1" only; False: H1
    whatever the trial holds). nperseg: H1 segment length in samples (None: see
    :meth:`h1_nperseg`). overlap: fraction 0…<1.
    window: H1 window name (scipy.signal.get_window). mp: device mass per axis (kg).
    coherence_min: below it a grid point is flagged low_coherence. drift_factor: see
    :func:`drifting`. force_limit_N: saturation threshold.
    """

    method: str = "h1"
    fmin: float = GRID_HZ[0]
    fmax: float = GRID_HZ[1]
    per_decade: int = POINTS_PER_DECADE
    nperseg: int | None = None
    overlap: float = 0.5
    window: str = "hann"
    min_avg: float = 8.0
    max_avg: float | None = 32.0
    derived_segments: int = 4
    mp: Mapping[str, float] = field(default_factory=lambda: dict(DEVICE_MASS_KG))
    coherence_min: float = 0.5
    drift_factor: float = 3.0
    force_limit_N: float = FORCE_LIMIT_N
    reference: bool = True

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise UsageError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if not 0 < self.fmin < self.fmax:
            raise UsageError(f"need 0 < fmin < fmax, got fmin={self.fmin} Hz, "
                             f"fmax={self.fmax} Hz")
        if not 0 <= self.overlap < 1:
            raise UsageError(f"overlap must be in [0, 1), got {self.overlap}")
        if self.nperseg is not None and self.nperseg < 8:
            raise UsageError(f"nperseg must be >= 8 samples, got {self.nperseg}")
        if self.derived_segments < 1:
            raise UsageError(f"derived segments must be >= 1, got {self.derived_segments}")
        lo, hi = DEVICE_MASS_RANGE.lower, DEVICE_MASS_RANGE.upper
        for ax, m in self.mp.items():   # the range every reader of the spectra applies
            if ax not in AXES or not lo <= m <= hi:
                raise UsageError(f"device mass must be given as axis x|y|z and a mass in "
                                 f"{DEVICE_MASS_RANGE.words()}, got {ax}={cell(m)}")

    def grid(self) -> np.ndarray:
        """The common grid, Hz (:func:`log_grid`); one read-only array shared by every
        trial estimated with these options."""
        return _shared_grid(self.fmin, self.fmax, self.per_decade)

    def h1_nperseg(self, fs: float, n_samples: int) -> int:
        """H1 segment length (samples): ``nperseg`` if given; else the smallest power of 2
        lasting ≥ 2/fmin (bins ≤ fmin/2 apart), halved while the record holds fewer than 4
        half-overlapped segments, but not below the power of 2 lasting ≥ 1/fmin."""
        if self.nperseg is not None:
            return int(self.nperseg)
        longest = 1 << math.ceil(math.log2(2.0 * fs / self.fmin))
        shortest = 1 << math.ceil(math.log2(fs / self.fmin))
        seg = longest
        while seg > shortest and (n_samples - seg // 2) // (seg // 2) < 4:
            seg //= 2
        return seg


@functools.lru_cache(maxsize=8)
def _shared_grid(fmin: float, fmax: float, per_decade: int) -> np.ndarray:
    grid = log_grid(fmin, fmax, per_decade)
    grid.setflags(write=False)
    return grid


@dataclass(frozen=True)
class Response:
    """One response of one trial on the grid: ``kind`` measured|cross|derived, the
    position axis ``out_axis``, the estimator ``method``, values (see GridResponse) and
    per-point flags (tuple of comma-joined strings, '' where none)."""

    kind: str
    out_axis: str
    method: str
    h: np.ndarray
    coherence: np.ndarray
    se_db: np.ndarray
    se_deg: np.ndarray
    flags: tuple[str, ...]


@dataclass(frozen=True)
class TrialResponses:
    """Everything ``estimate`` keeps of one trial: identity, grid, responses and what the
    estimators say of it (``check``, :class:`EstimatorCheck`; None when not made)."""

    subject: str
    axis: str
    grip_N: float
    run: int | None
    source: str
    freq_hz: np.ndarray
    responses: tuple[Response, ...]
    check: EstimatorCheck | None = None


def check_band(fs: float, n_samples: int, config: EstimateConfig, source: str = "") -> None:
    """Raise UsageError if fmax is above Nyquist, BadInputError if the record (or the
    estimator's segment) lasts less than one period of fmin."""
    # a command without --fmin/--fmax (armfit run: a fixed grid) names neither
    if config.fmax > fs / 2:
        raise UsageError(f"{source + ': ' if source else ''}{{?{{opt:fmax}} }}"
                         f"{config.fmax:g} Hz is above the Nyquist frequency {fs / 2:g} Hz "
                         f"(sampling rate {fs:g} Hz)")
    need = 1.0 / config.fmin
    low = f"too short for {{?{{opt:fmin}} }}{config.fmin:g} Hz"
    if config.method == "h1":
        seg = config.h1_nperseg(fs, n_samples)
        if seg > n_samples:
            raise BadInputError(
                f"{low}: {n_samples / fs:g} s, H1 segments need {seg / fs:g} s"
                "{?; raise {opt:fmin} or lower {opt:nperseg}}", file=source or None)
    if n_samples / fs < need:
        raise BadInputError(f"{low}: {n_samples / fs:g} s, needs at least {need:g} s",
                            file=source or None)
    seg = tfestimate_segment(n_samples - 2, config.derived_segments)[0]
    if seg / fs < need:
        raise BadInputError(
            f"{low}: derived-arm segments last {seg / fs:g} s (record "
            f"{n_samples / fs:g} s), need {need:g} s", file=source or None)


def _flag_strings(coh: np.ndarray, threshold: float, trial_flags: Sequence[str]
                  ) -> tuple[str, ...]:
    base = ",".join(trial_flags)
    low = ",".join(["low_coherence", *trial_flags])
    return tuple(low if c < threshold else base for c in np.nan_to_num(coh, nan=0.0))


# ---------------------------------------------------------------------------
# Estimator checks: is the force the excitation, and does it matter here?
# ---------------------------------------------------------------------------

#: Flag of a grid point where the force is not a clean excitation (it responds to the
#: position, or differs from the rig's commanded force) and H1 is biased there beyond
#: its noise (docs/methods.md, "Is the force the excitation?").
NOT_EXCITATION = "not_excitation"

#: A disagreement of H1 with H2 (or with the reference estimate) beyond this many
#: combined standard errors counts as a bias of H1.
BIAS_Z = 2.0

#: Below this coherence between a commanded force and the measured one (median over the
#: flagged points) the measured force is not the commanded force: a force-control loop
#: or a noisy force sensor.
REFERENCE_COHERENCE = 0.9

@dataclass(frozen=True)
class EstimatorCheck:
    """What the estimators say of one trial (:func:`check_estimators`).

    Attributes
    ----------
    method : str
        The estimator of the measured response (``h1``, ``chebwin``, ``ref``).
    reference : str or None
        The reference column estimated through (``ref_<a>_N``, ``ref_<a>_m``).
    feedback : armfit.feedback.FeedbackTest or None
        Whether the force responds to the position. None where the test was not run —
        H1 agrees with H2 (or with the reference estimate) within the noise at every point,
        so no point could be flagged (:attr:`needs_feedback_test`) — or where the record is
        too short for it.
    agreement_p : float or None
        With a reference: the p-value of "H1 equals the reference estimate" over the grid
        (χ² of the normalised differences of magnitude and phase).
    gap_db : ndarray, shape (ng,)
        Magnitude of H2 (or of the reference estimate) over H1, dB.
    gap_deg : ndarray, shape (ng,)
        Phase of H1 relative to the reference estimate, deg, in (−180, 180] (zeros
        against H2, whose phase is H1's).
    z : ndarray, shape (ng,)
        The largest of the disagreements in magnitude and phase, in combined standard
        errors (magnitude only against H2: H1/H2 = γ² is real).
    flagged : ndarray of bool, shape (ng,)
        The points flagged ``not_excitation``: evidence for the trial (the feedback test
        fires, or H1 disagrees with the reference estimate as a whole) and a bias of H1
        beyond :data:`BIAS_Z` there.
    ref_coherence : float or None
        Median coherence of a commanded force with the measured force over the flagged
        points (a force reference only).
    cause : str or None
        ``closed_loop``, ``noisy_force`` or ``biased`` where points are flagged.
    unused_reference : str or None
        The trial's reference column when it was not estimated through (``--no-reference``
        or ``--method chebwin``).
    """

    method: str
    reference: str | None
    feedback: FeedbackTest | None
    agreement_p: float | None
    gap_db: np.ndarray
    gap_deg: np.ndarray
    z: np.ndarray
    flagged: np.ndarray
    ref_coherence: float | None
    cause: str | None
    unused_reference: str | None = None

    @property
    def needs_feedback_test(self) -> bool:
        """Whether the feedback test can change what is flagged: some point where H1 is
        biased beyond its noise if the force is not the excitation (H2 above H1 by more
        than :data:`BIAS_Z`, or a disagreement with the reference estimate)."""
        return bool(np.any(np.isfinite(self.z) & (self.z > BIAS_Z)
                           & ((self.reference is not None) | (self.gap_db > 0))))

    def bands(self, freq_hz: np.ndarray) -> list[tuple[float, float]]:
        """The runs of flagged grid points as (first, last) frequencies, Hz."""
        out: list[tuple[float, float]] = []
        idx = np.flatnonzero(self.flagged)
        if idx.size:
            for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
                out.append((float(freq_hz[run[0]]), float(freq_hz[run[-1]])))
        return out

    def record(self, freq_hz: np.ndarray) -> dict[str, object]:
        """The check as JSON-ready values (the spectra file's metadata)."""
        fb = self.feedback
        gap = self.gap_db[self.flagged]
        return {
            "method": self.method, "reference": self.reference,
            "feedback": None if fb is None else {
                "statistic": fb.statistic, "dof": fb.dof, "p_value": fb.p_value,
                "fires": fb.fires},
            "agreement_p": self.agreement_p,
            "not_excitation_hz": [list(b) for b in self.bands(freq_hz)],
            "gap_db": [float(gap.min()), float(gap.max())] if gap.size else None,
            "gap_deg": (float(np.nanmax(np.abs(self.gap_deg[self.flagged])))
                        if gap.size else None),
            "ref_coherence": self.ref_coherence, "cause": self.cause,
            "unused_reference": self.unused_reference,
        }

    def message(self, label: str, freq_hz: np.ndarray, axis: str = "<a>") -> str | None:
        """One line for the user where points are flagged, else None: the file
        (``label``), the cause in words, the bands (Hz) and H1's gap to H2 or to the
        estimate through the reference (``axis``: the stimulated axis, in the hint)."""
        if self.cause is None:
            return None
        gap = -self.gap_db[self.flagged]             # H1 relative to the other estimate
        lo, hi = np.abs(gap).min(), np.abs(gap).max()
        if gap.max() < 0 or gap.min() > 0:
            size = f"{lo:.1f}–{hi:.1f} dB {'below' if gap.max() < 0 else 'above'}"
        else:
            size = f"off by up to {hi:.1f} dB from"
        where = ", ".join(f"{a:.3g}–{b:.3g} Hz" if a < b else f"{a:.3g} Hz"
                          for a, b in self.bands(freq_hz))
        fb, coh = self.feedback, self.ref_coherence
        low = coh is not None and coh < REFERENCE_COHERENCE
        if self.cause == "closed_loop":
            why = (f"the force responds to the position (feedback test p = "
                   f"{fb.p_value:.1e}): position-driven or closed loop, the force is a "  # type: ignore[union-attr]
                   "controller's output")
            if low:
                why += f", and follows the commanded force with coherence {coh:.2f} there"
        elif self.cause == "noisy_force":
            why = (f"the measured force is not the commanded one (coherence {coh:.2f} "
                   "there): force-control loop or noisy force")
        else:
            why = "H1 disagrees with the estimate through the reference"
        if self.reference is not None:
            turn = float(np.nanmax(np.abs(self.gap_deg[self.flagged])))
            return (f"{label}: estimated through the reference {self.reference} "
                    f"(S_xr/S_Fr); {why}; H1 would be {size} and up to {turn:.0f}° from "
                    f"that at {where}, beyond the noise (its alternative row flagged "
                    f"{NOT_EXCITATION})")
        hint = (f"its reference column {self.unused_reference} estimates through the rig's "
                "excitation with method h1 and without --no-reference"
                if self.unused_reference is not None else
                f"give the commanded force or trajectory as ref_{axis}_N or ref_{axis}_m to "
                "estimate through it")
        return (f"{label}: {why}; H1 is {size} H2 at {where}, beyond its noise (flagged "
                f"{NOT_EXCITATION}); {hint}")


def _phase_diff_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.degrees(np.angle(a * np.conj(b)))


def check_estimators(h1: GridResponse, h2: GridResponse, href: GridResponse | None,
                     feedback: FeedbackTest | None, *, method: str = "h1",
                     reference: str | None = None,
                     ref_force_coherence: np.ndarray | None = None) -> EstimatorCheck:
    """Compare H1 with H2 (and with the reference estimate) on the grid and flag where
    H1 is biased beyond its noise (docs/methods.md, "Is the force the excitation?").

    Without a reference, H1/H2 = γ²: their gap says there is noise, not where it enters,
    so it is a bias of H1 only where the force is not the excitation: the points flagged
    are those where the feedback test fires for the trial and H2 exceeds H1 by more than
    :data:`BIAS_Z` × √(se₁² + se₂²) (dB). With a reference, the estimate through it is
    unbiased under weaker assumptions, and H1's disagreement with it is a bias: the
    points flagged are those where the trial has evidence (the feedback test fires, or
    the χ² of the normalised differences of magnitude and phase over the grid has
    p < :data:`armfit.feedback.FEEDBACK_ALPHA`) and the magnitude or the phase differs by
    more than :data:`BIAS_Z` combined standard errors.

    Parameters
    ----------
    h1, h2, href : GridResponse
        The on-axis responses (row 0 is used): H1 (or the chebwin estimate), H2 and the
        estimate through the reference (None without one).
    feedback : FeedbackTest or None
        :func:`armfit.feedback.feedback_test` of the trial.
    method : str
        The estimator of ``h1``.
    reference : str or None
        The reference column's name, when ``href`` is given.
    ref_force_coherence : ndarray, optional
        Coherence of a commanded force with the measured force on the grid.

    Returns
    -------
    EstimatorCheck
    """
    a = h1.h[0]
    other = h2 if href is None else href
    turn = np.zeros(a.shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        gap = 20.0 * np.log10(np.abs(other.h[0]) / np.abs(a))
        se = np.hypot(h1.se_db[0], other.se_db[0])
        z = np.abs(gap) / se
        agreement = None
        if href is not None:
            turn = _phase_diff_deg(a, other.h[0])
            z_deg = np.abs(turn) / np.hypot(h1.se_deg[0], other.se_deg[0])
            ok = np.isfinite(z) & np.isfinite(z_deg)
            agreement = chi2_sf(float(np.sum(z[ok] ** 2 + z_deg[ok] ** 2)),
                                2 * int(ok.sum())) if ok.any() else None
            z = np.fmax(z, z_deg)
    fires = feedback is not None and feedback.fires
    evidence = fires or (agreement is not None and agreement < FEEDBACK_ALPHA)
    biased = np.isfinite(z) & (z > BIAS_Z) & (href is not None or gap > 0)
    flagged = biased & evidence
    ref_coh = None
    is_force_ref = reference is not None and reference.endswith("_N")
    if is_force_ref and ref_force_coherence is not None and flagged.any():
        ref_coh = float(nanmedian(ref_force_coherence[flagged]))
    cause = None
    if flagged.any():
        cause = ("closed_loop" if fires else "noisy_force"
                 if ref_coh is not None and ref_coh < REFERENCE_COHERENCE else "biased")
    return EstimatorCheck(method=method, reference=reference, feedback=feedback,
                          agreement_p=agreement, gap_db=gap, gap_deg=turn, z=z,
                          flagged=flagged,
                          ref_coherence=ref_coh, cause=cause)


def estimate_trial(force: np.ndarray, pos: np.ndarray, fs: float, axis: str,
                   config: EstimateConfig, *, source: str = "", ref: np.ndarray | None = None,
                   reference: str | None = None) -> tuple[Response, ...]:
    """All responses of one trial on ``config.grid()``.

    force, pos: (n, 3) N and m, columns x, y, z, NaN columns for unrecorded axes;
    ``axis`` the stimulated axis; ``ref`` (n,) the rig's excitation on that axis (a
    commanded force in N or a reference position in m) and ``reference`` its column name
    (``ref_<a>_N``, ``ref_<a>_m``), or None. Returns the measured response (X/F of the
    stimulated axis: ``config.method``, or through the reference, method ``ref``, when
    there is one and ``config.reference``), the derived arm dynamics Xa/Fa (tfestimate,
    Mp of the axis; ``tfestimate-ref`` through the reference), cross responses
    (stimulated force → each other recorded position, as the measured response), then
    the alternative estimates of X/F (kind ``alternative``: H2, and H1 when the measured
    response went through the reference). :func:`estimate_trial_checked` also returns
    what the estimators say of the trial.
    """
    return estimate_trial_checked(force, pos, fs, axis, config, source=source, ref=ref,
                                  reference=reference)[0]


def _welch(config: EstimateConfig, x, y, fs: float, n: int, grid: np.ndarray,
           method: str) -> BinSpectra:
    """Welch spectra of x → columns of y with the H1 segmentation of ``config``."""
    nper = config.h1_nperseg(fs, n)
    return welch_spectra(x, y, fs, nperseg=nper,
                         noverlap=min(nper - 1, int(round(config.overlap * nper))),
                         window=config.window, method=method, fmax_hz=grid[-1])


def _derived_reference(f: np.ndarray, x: np.ndarray, ref: np.ndarray, fs: float, mp: float,
                       dsp: BinSpectra, config: EstimateConfig, grid: np.ndarray
                       ) -> GridResponse:
    """Xa/Fa through the reference: :func:`reference_to_grid` of r against (Fa, xa) on
    the derived dynamics' own segments (:func:`derived_spectra`)."""
    fa, xa = derived_arm_signals(f, x, fs, mp)
    nperseg, noverlap, nfft, win = _derived_segments(fa.size, config.derived_segments)
    rsp = welch_spectra(ref[1:-1], [fa, xa], fs, nperseg=nperseg,
                        noverlap=noverlap, window=win, nfft=nfft, method="tfestimate-ref",
                        fmax_hz=grid[-1])
    return reference_to_grid(rsp, dsp, grid, min_avg=config.min_avg, max_avg=config.max_avg)


def estimate_trial_checked(force: np.ndarray, pos: np.ndarray, fs: float, axis: str,
                           config: EstimateConfig, *, source: str = "",
                           ref: np.ndarray | None = None, reference: str | None = None,
                           drift: Mapping[int, bool] | None = None
                           ) -> tuple[tuple[Response, ...], EstimatorCheck]:
    """:func:`estimate_trial` and what the estimators say of the trial
    (:class:`EstimatorCheck`: the feedback test, H1 against H2 or the reference
    estimate, the points flagged ``not_excitation``). ``drift``: the position columns'
    drift flags already found (:func:`drift_flags`), by column; those not given are
    found here."""
    check_band(fs, force.shape[0], config, source)
    i = AXES.index(axis)
    f = force[:, i]
    outs = [i] + [j for j in range(3) if j != i and np.all(np.isfinite(pos[:, j]))]
    y = [pos[:, j] for j in outs]     # the columns themselves, not a copy
    grid = config.grid()
    n = force.shape[0]
    use_ref = ref is not None and config.reference and config.method == "h1"
    sp = (_welch(config, f, y, fs, n, grid, "h1") if config.method == "h1"
          else chebwin_spectra(f, pos[:, outs], fs))
    _check_finite_spectra(sp, f, axis, source)
    opts = dict(min_avg=config.min_avg, max_avg=config.max_avg)
    mp = config.mp.get(axis, DEVICE_MASS_KG[axis])
    dsp = derived_spectra(f, pos[:, i], fs, mp, segments=config.derived_segments,
                          fmax_hz=grid[-1])
    _check_finite_spectra(dsp, f, axis, source)
    with np.errstate(all="ignore"):  # cells without signal are marked below (no_signal)
        g = to_grid(sp, grid, **opts)
        g2 = h2_to_grid(sp, grid, **opts)
        d = to_grid(dsp, grid, **opts)
        gr = dr = rf = None
        if use_ref:
            rsp = _welch(config, ref, [f, *y], fs, n, grid, "ref")
            _check_finite_spectra(rsp, f, axis, source)
            gr = reference_to_grid(rsp, sp, grid, **opts)
            dr = _derived_reference(f, pos[:, i], ref, fs, mp, dsp, config, grid)
            rf = to_grid(replace(rsp, p_fx=rsp.p_fx[:1], p_xx=rsp.p_xx[:1]), grid, **opts)
    check = check_estimators(g, g2, gr, None, method="ref" if use_ref else sp.method,
                             reference=reference if use_ref else None,
                             ref_force_coherence=None if rf is None else rf.coherence[0])
    if check.needs_feedback_test:   # else no point could be flagged whatever it says
        check = check_estimators(g, g2, gr, feedback_test(f, pos[:, i], fs, grid[-1]),
                                 method=check.method, reference=check.reference,
                                 ref_force_coherence=None if rf is None else rf.coherence[0])
    sat = ["saturation"] if saturated(f, config.force_limit_N) else []

    def trial_flags(j: int) -> list[str]:
        drifts = (drift[j] if drift is not None and j in drift
                  else drifting(pos[:, j], fs, config.fmin, config.drift_factor))
        return sat + (["drift"] if drifts else [])

    stim_flags = trial_flags(i)

    def flags(coh: np.ndarray, trial: list[str], biased: bool) -> tuple[str, ...]:
        out = _flag_strings(coh, config.coherence_min, trial)
        return _with_flag(out, check.flagged, NOT_EXCITATION) if biased else out

    meas, der = (gr, dr) if use_ref else (g, d)
    out = [Response("measured", axis, "ref" if use_ref else sp.method, meas.h[0],
                    meas.coherence[0], meas.se_db[0], meas.se_deg[0],
                    flags(meas.coherence[0], stim_flags, not use_ref)),
           Response("derived", axis, "tfestimate-ref" if use_ref else "tfestimate",
                    der.h[0], der.coherence[0], der.se_db[0], der.se_deg[0],
                    flags(der.coherence[0], stim_flags, not use_ref))]
    for k, j in enumerate(outs[1:], start=1):
        out.append(Response("cross", AXES[j], "ref" if use_ref else sp.method, meas.h[k],
                            meas.coherence[k], meas.se_db[k], meas.se_deg[k],
                            flags(meas.coherence[k], trial_flags(j), not use_ref)))
    out.append(Response("alternative", axis, "h2", g2.h[0], g2.coherence[0], g2.se_db[0],
                        g2.se_deg[0], flags(g2.coherence[0], stim_flags, False)))
    if use_ref:
        out.append(Response("alternative", axis, sp.method, g.h[0], g.coherence[0],
                            g.se_db[0], g.se_deg[0], flags(g.coherence[0], stim_flags, True)))
    if reference is not None and not use_ref:
        check = replace(check, unused_reference=reference)
    return tuple(_mark_no_signal(r) for r in out), check


def _with_flag(flags: tuple[str, ...], where: np.ndarray, flag: str) -> tuple[str, ...]:
    """``flags`` with ``flag`` added where ``where`` is True."""
    return tuple(",".join(filter(None, [fl, flag])) if w else fl
                 for fl, w in zip(flags, where, strict=True))


#: Flag of a grid cell without information (no force or no position power there, e.g.
#: an unstimulated axis whose position is recorded as constant zero): its values are NaN.
NO_SIGNAL = "no_signal"


def _check_finite_spectra(sp: BinSpectra, force: np.ndarray, axis: str, source: str) -> None:
    """Refuse a trial whose spectra overflowed (BadInputError naming the force column and
    the row of its largest value): input checks keep values far below that, so this only
    guards against a non-finite intermediate."""
    with np.errstate(all="ignore"):
        ok = (np.all(np.isfinite(sp.p_ff)) and np.all(np.isfinite(sp.p_xx))
              and np.all(np.isfinite(sp.p_fx)))
    if not ok:
        k = int(np.argmax(np.abs(force)))
        raise BadInputError(f"the spectra overflow (non-finite intermediate); the largest "
                            f"value is in row {k + 1}", file=source or None,
                            column=f"force_{axis}_N", row=k + 1)


def _mark_no_signal(r: Response) -> Response:
    """Cells whose response is zero or not finite carry no information: their values
    become NaN and their flags ``no_signal`` (plus the trial's own flags)."""
    with np.errstate(all="ignore"):
        empty = ~np.isfinite(r.h) | (r.h == 0)
    if not empty.any():
        return r
    nan = np.where(empty, np.nan, 1.0)
    flags = tuple(",".join([NO_SIGNAL, *[x for x in fl.split(",") if x and x != "low_coherence"]])
                  if e else fl for fl, e in zip(r.flags, empty, strict=True))
    return Response(r.kind, r.out_axis, r.method, np.where(empty, np.nan + 0j, r.h),
                    np.where(empty, np.nan, r.coherence), r.se_db * nan, r.se_deg * nan, flags)


def no_signal_messages(label: str, axis: str, responses: Sequence[Response]) -> list[str]:
    """One message per response of a trial with ``no_signal`` cells: what it means."""
    out = []
    for r in responses:
        k = sum(NO_SIGNAL in fl.split(",") for fl in r.flags)
        if not k:
            continue
        what = {"measured": "measured response X/F", "derived": "derived arm response Xa/Fa",
                "cross": f"cross response force {axis} -> position {r.out_axis}"}[r.kind]
        scope = "all" if k == len(r.flags) else f"{k} of {len(r.flags)}"
        cause = (f"position {r.out_axis} is constant: not recorded?"
                 if r.kind == "cross" and k == len(r.flags) else "no force or position power "
                 "there")
        out.append(f"{label}: {what}: {scope} frequencies carry no signal ({cause}); "
                   f"they are NaN, flagged {NO_SIGNAL}, and left out of the mean and median")
    return out


# ---------------------------------------------------------------------------
# Aggregation over trials
# ---------------------------------------------------------------------------

def _log_parts(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """20 log10|H| (dB) and phase (rad) of each trial, on one continuous branch: the
    circular mean of the trials is unwrapped along frequency and each trial's phase is
    taken within π of it at every frequency (so a 2π slip of one noisy trial cannot shift
    the aggregate). ``H``: (n_trials, n_freq), or a stack (..., n_trials, n_freq) of
    such sets, each taken on its own."""
    H = np.atleast_2d(np.asarray(H, dtype=complex))
    ok = np.isfinite(H) & (H != 0)
    if not ok.all():  # cells without signal (NaN): left out, NaN where none is left
        with np.errstate(all="ignore"):
            db = np.where(ok, 20.0 * np.log10(np.abs(H)), np.nan)
            unit = np.where(ok, H / np.abs(H), 0.0)
        centre = np.angle(unit.sum(axis=-2))
        ref = np.unwrap(centre)
        dev = np.where(ok, np.angle(unit * np.exp(-1j * centre[..., None, :])), np.nan)
        return db, ref[..., None, :] + dev
    db = 20.0 * np.log10(np.abs(H))
    unit = H / np.abs(H)
    centre = np.angle(np.mean(unit, axis=-2))           # circular mean per frequency
    ref = np.unwrap(centre)                              # continuous along frequency
    dev = np.angle(unit * np.exp(-1j * centre[..., None, :]))  # offsets, in (-π, π]
    return db, ref[..., None, :] + dev


def _nan_stat(x: np.ndarray, how: str, *, ddof: int = 0, q=None) -> np.ndarray:
    """Column statistic of ``x`` (n, m) over its finite entries, NaN where a column has
    too few (none; fewer than 2 for a standard deviation), without numpy warnings."""
    ok = np.isfinite(x)
    cnt = ok.sum(axis=0)
    need = 1 + ddof
    cols = cnt >= need
    shape = (len(q),) + x.shape[1:] if q is not None else x.shape[1:]
    out = np.full(shape, np.nan)
    if not cols.any():
        return out
    sub = x[:, cols]
    if how == "mean":
        out[cols] = np.where(ok[:, cols], sub, 0.0).sum(axis=0) / cnt[cols]
    elif how == "median":
        out[cols] = nanmedian(sub, axis=0)
    elif how == "std":
        out[cols] = np.nanstd(sub, axis=0, ddof=ddof)
    elif how == "percentile":
        out[:, cols] = nanpercentile(sub, q, axis=0)
    return out


def aggregate(H: np.ndarray, how: str) -> np.ndarray:
    """Mean or median of complex responses H (n_trials, n_freq), m/N → (n_freq,).

    Taken on log-magnitude and phase separately: 20 log10|H| (dB) and the phase (each
    trial taken within π of the trials' circular mean, itself unwrapped along frequency)
    are averaged (``"mean"``) or their medians taken (``"median"``), then
    recombined as 10^(dB/20)·e^(jφ). This matches the dB cost of eq. 5 and keeps a few
    outlying trials from pulling the magnitude. A stack (..., n_trials, n_freq) of
    such sets with signal everywhere gives each set's (..., n_freq).
    """
    db, ph = _log_parts(H)
    if how not in ("mean", "median"):
        raise UsageError(f"aggregate how must be 'mean' or 'median', got {how!r}")
    if not np.isfinite(db).all():
        m_db, m_ph = _nan_stat(db, how), _nan_stat(ph, how)
    elif how == "mean":
        m_db, m_ph = db.mean(axis=-2), ph.mean(axis=-2)
    else:
        m_db, m_ph = median(db, axis=-2), median(ph, axis=-2)
    return 10.0 ** (m_db / 20.0) * np.exp(1j * m_ph)


def aggregate_spread(H: np.ndarray, how: str = "mean") -> dict[str, np.ndarray]:
    """Spread of responses H (n_trials, n_freq) per frequency, on the scale of
    :func:`aggregate`.

    se_db, se_deg: standard error of the mean of dB and of phase (deg), s/√n with s the
    sample standard deviation (ddof = 1; NaN for n = 1); for ``how="median"`` multiplied by
    sqrt(π/2) (large-sample standard error of a median of normal data).
    q25_db, q75_db, q25_deg, q75_deg: quartiles (numpy's linear interpolation).
    """
    db, ph = _log_parts(H)
    deg = np.degrees(ph)
    n = db.shape[0]
    factor = MEDIAN_SE_FACTOR if how == "median" else 1.0
    if not np.isfinite(db).all():  # cells without signal: statistics of the rest
        cnt = np.isfinite(db).sum(axis=0)
        with np.errstate(all="ignore"):
            root = np.sqrt(cnt.astype(float))
        q_db = _nan_stat(db, "percentile", q=[25, 75])
        q_deg = _nan_stat(deg, "percentile", q=[25, 75])
        return {"se_db": factor * _nan_stat(db, "std", ddof=1) / root,
                "se_deg": factor * _nan_stat(deg, "std", ddof=1) / root,
                "q25_db": q_db[0], "q75_db": q_db[1], "q25_deg": q_deg[0],
                "q75_deg": q_deg[1]}
    if n > 1:
        se_db = factor * db.std(axis=0, ddof=1) / math.sqrt(n)
        se_deg = factor * deg.std(axis=0, ddof=1) / math.sqrt(n)
    else:
        se_db = np.full(db.shape[1], np.nan)
        se_deg = np.full(db.shape[1], np.nan)
    q_db = percentile(db, [25, 75], axis=0)
    q_deg = percentile(deg, [25, 75], axis=0)
    return {"se_db": se_db, "se_deg": se_deg, "q25_db": q_db[0], "q75_db": q_db[1],
            "q25_deg": q_deg[0], "q75_deg": q_deg[1]}


# ---------------------------------------------------------------------------
# The study's responses (the Spectra object, schema armfit.io.schema)
# ---------------------------------------------------------------------------

def _db(h: np.ndarray) -> np.ndarray:
    """20 log10|h| (dB); NaN, never -inf, where h is 0 or not finite (no signal)."""
    ok = np.isfinite(h) & (h != 0)
    if ok.all():
        return 20.0 * np.log10(np.abs(h))
    with np.errstate(all="ignore"):
        return np.where(ok, 20.0 * np.log10(np.abs(h)), np.nan)


def _unwrap_finite(ph: np.ndarray) -> np.ndarray:
    """np.unwrap over the finite entries only (a NaN cell would spoil every later one)."""
    ok = np.isfinite(ph)
    if ok.all():
        return np.unwrap(ph)
    out = np.full(ph.shape, np.nan)
    out[ok] = np.unwrap(ph[ok])
    return out


def _block(level: str, subject, axis: str, grip, run, kind: str, out_axis: str, method: str,
           freq: np.ndarray, h: np.ndarray, coherence: np.ndarray, se_db: np.ndarray,
           se_deg: np.ndarray, n: int, flags: Sequence[str], phase_rad: np.ndarray | None = None,
           spread: Mapping[str, np.ndarray] | None = None,
           mag_db: np.ndarray | None = None) -> dict[str, object]:
    ng = freq.size
    phase = _unwrap_finite(np.angle(h)) if phase_rad is None else phase_rad
    nan = np.full(ng, np.nan)
    spread = spread or {}
    return {
        "level": level, "subject": subject, "axis": axis, "grip_N": grip, "run": run,
        "kind": kind, "out_axis": out_axis, "method": method, "freq_hz": freq,
        "re": h.real, "im": h.imag, "mag_db": _db(h) if mag_db is None else mag_db,
        "phase_deg": np.degrees(phase), "coherence": coherence, "se_db": se_db,
        "se_deg": se_deg, "n": n,
        "q25_db": spread.get("q25_db", nan), "q75_db": spread.get("q75_db", nan),
        "q25_deg": spread.get("q25_deg", nan), "q75_deg": spread.get("q75_deg", nan),
        "flags": list(flags),
    }


#: The flags an aggregate can carry, in the order they are written.
_MAJORITY_FLAGS = ("low_coherence", "saturation", "drift", NO_SIGNAL, NOT_EXCITATION)


def _majority_flags(flag_rows: Sequence[Sequence[str]]) -> list[str]:
    """Per frequency, the flags carried by more than half of the responses.

    A response's flags at one frequency are one comma-separated string; a study holds
    few distinct ones, so each is parsed once: its count of each flag of
    :data:`_MAJORITY_FLAGS`, summed over the responses at every frequency at once.
    """
    n = len(flag_rows)
    if not n:
        return []
    index: dict[str, int] = {}
    codes = np.array([[index.setdefault(s, len(index)) for s in row] for row in flag_rows],
                     dtype=np.intp)
    occurs = np.array([[s.split(",").count(f) for f in _MAJORITY_FLAGS] for s in index],
                      dtype=np.intp)
    carried = occurs[codes].sum(axis=0) * 2 > n              # (frequencies, flags)
    names = {}
    out = []
    for row in carried:
        key = row.tobytes()
        if key not in names:
            names[key] = ",".join(f for f, c in zip(_MAJORITY_FLAGS, row, strict=True) if c)
        out.append(names[key])
    return out


def spectra_table(trials: Sequence[TrialResponses], meta: Mapping | None = None) -> Spectra:
    """The :class:`Spectra` of a study (``meta``: the metadata it carries).

    Rows at level ``trial`` for every response of every trial, then the aggregates of
    each kind (measured, derived, cross) and output axis:

    ``mean``    per axis × grip: each subject's runs are first combined with
                :func:`aggregate` ("mean"), then the subjects' responses are averaged;
                n = subjects, spread (se, quartiles) across subjects.
    ``median``  per axis over all its trials (every subject, grip and run): median of dB
                and of unwrapped phase; n = trials, se = sqrt(π/2)·s/√n.

    An aggregate's coherence is the mean of its trials' coherences; its flags are those
    carried by more than half of its trials at that frequency. Where an aggregate rests on
    a single response its se is that response's own (Bendat & Piersol) se.
    """
    return _stack_blocks([*_trial_blocks(trials), *_aggregate_blocks(trials)], meta)


def _trial_blocks(trials: Sequence[TrialResponses], batch: int = 64):
    """The trial-level blocks of :func:`spectra_table`, one per response, made as they are
    consumed, ``batch`` responses at a time: their magnitudes and unwrapped phases are
    computed together (the same operations on each row as one response alone)."""
    pairs = ((tr, r) for tr in trials for r in tr.responses)
    while chunk := list(itertools.islice(pairs, batch)):
        H = np.array([r.h for _, r in chunk])
        db = _db(H)
        phase = np.angle(H)
        whole = np.isfinite(phase).all(axis=1)
        phase[whole] = np.unwrap(phase[whole], axis=-1)
        for k in np.flatnonzero(~whole):
            phase[k] = _unwrap_finite(phase[k])
        for k, (tr, r) in enumerate(chunk):
            yield _block("trial", tr.subject, tr.axis, tr.grip_N, tr.run, r.kind,
                         r.out_axis, r.method, tr.freq_hz, r.h, r.coherence, r.se_db,
                         r.se_deg, 1, r.flags, phase_rad=phase[k], mag_db=db[k])


def _aggregate_blocks(trials: Sequence[TrialResponses], kinds: Sequence[str] | None = None,
                      made: dict[tuple, list[dict[str, object]]] | None = None
                      ) -> list[dict[str, object]]:
    """The aggregate blocks of :func:`spectra_table`, in the file's order: of the
    responses of ``kinds`` only (None: all).

    One group (axis, kind, position axis) at a time: its members' responses are taken
    from ``trials`` when the group is made and let go after, so that a study held in a
    :class:`SpooledTrials` is never in memory whole (the members, their order and the
    numbers are those of all trials at once). ``made`` {group: its blocks}: the groups
    made before, taken from there, and those made here added (a group's blocks are the
    same whichever others are made with it).
    """
    blocks: list[dict[str, object]] = []
    groups: dict[tuple, list[int]] = {}
    for i, (axis, kinds_i) in enumerate(_outlines(trials)):
        for kind, out_axis in dict.fromkeys(kinds_i):
            # the alternative estimates are not aggregated
            if kind != "alternative" and (kinds is None or kind in kinds):
                groups.setdefault((axis, kind, out_axis), []).append(i)
    made = {} if made is None else made
    for key, rows in sorted(groups.items()):
        if key not in made:
            made[key] = _group_blocks(trials, key, rows)
        blocks += made[key]
    return blocks


def _group_blocks(trials: Sequence[TrialResponses], key: tuple[str, str, str],
                  rows: Sequence[int]) -> list[dict[str, object]]:
    """The aggregate blocks of one group (axis, kind, position axis) of
    :func:`_aggregate_blocks`, whose members are the responses of the trials ``rows``:
    the mean of each grip, then the median of all."""
    axis, kind, out_axis = key
    blocks: list[dict[str, object]] = []
    members: list[tuple[float, str, Response]] = []
    freq = None
    for i in rows:
        tr = trials[i]
        if freq is None:
            freq = tr.freq_hz
        members += [(tr.grip_N, tr.subject, r) for r in tr.responses
                    if r.kind == kind and r.out_axis == out_axis]
    # trials estimated through their reference and others: both names
    method = "+".join(sorted({r.method for _, _, r in members}))
    by_grip: dict[float, dict[str, list[Response]]] = {}
    for grip, subject, r in members:
        by_grip.setdefault(grip, {}).setdefault(subject, []).append(r)
    for grip in sorted(by_grip):
        subjects = by_grip[grip]
        per_subject = _subject_means([np.array([r.h for r in rs])
                                      for rs in subjects.values()])
        rs_all = [r for rs in subjects.values() for r in rs]
        blocks.append(_aggregate_block("mean", axis, grip, kind, out_axis, method, freq,
                                       per_subject, rs_all, len(subjects)))
    rs_all = [r for _, _, r in members]
    blocks.append(_aggregate_block("median", axis, np.nan, kind, out_axis, method, freq,
                                   np.array([r.h for r in rs_all]), rs_all, len(rs_all)))
    return blocks


def _outlines(trials: Sequence[TrialResponses]):
    """(axis, ((kind, out_axis) of each response, in order)) of each trial: kept by a
    :class:`SpooledTrials`, so that no trial is read back for it."""
    if isinstance(trials, SpooledTrials):
        return trials.outlines()
    return [_outline(tr) for tr in trials]


def _outline(tr: TrialResponses) -> tuple[str, tuple[tuple[str, str], ...]]:
    return tr.axis, tuple((r.kind, r.out_axis) for r in tr.responses)


def _subject_means(runs: Sequence[np.ndarray]) -> np.ndarray:
    """:func:`aggregate` ("mean") of each subject's runs (one (n_runs, n_freq) array per
    subject), stacked (n_subjects, n_freq).

    The subjects with a single run and signal at every frequency are aggregated at
    once, as one stack (the same operations on each); the others one by one.
    """
    out = np.empty((len(runs), runs[0].shape[-1]), complex) if runs else np.zeros((0, 0))
    single = [k for k, h in enumerate(runs)
              if h.shape[0] == 1 and np.isfinite(h).all() and (h != 0).all()]
    if single:
        out[single] = aggregate(np.stack([runs[k] for k in single]), "mean")
    for k in sorted(set(range(len(runs))) - set(single)):
        out[k] = aggregate(runs[k], "mean")
    return out


def _aggregate_block(level: str, axis: str, grip: float, kind: str, out_axis: str,
                     method: str, freq: np.ndarray, H: np.ndarray, members: list[Response],
                     n: int) -> dict[str, object]:
    how = level
    value = aggregate(H, how)
    spread = aggregate_spread(H, how)
    _, ph = _log_parts(H)
    if np.isfinite(ph).all():
        phase = median(ph, axis=0) if how == "median" else ph.mean(axis=0)
    else:
        phase = _nan_stat(ph, how)
    se_db, se_deg = spread["se_db"], spread["se_deg"]
    if n == 1:
        se_db = np.mean([r.se_db for r in members], axis=0)
        se_deg = np.mean([r.se_deg for r in members], axis=0)
    coh = _nan_stat(np.array([r.coherence for r in members]), "mean")
    flags = _majority_flags([r.flags for r in members])
    empty = ~np.isfinite(value)
    if empty.any():  # no member has signal there: NaN, flagged no_signal
        value = np.where(empty, np.nan + 0j, value)
        flags = [",".join([NO_SIGNAL, *[x for x in fl.split(",") if x and x != NO_SIGNAL]])
                 if e else ",".join(x for x in fl.split(",") if x != NO_SIGNAL)
                 for fl, e in zip(flags, empty, strict=True)]
    return _block(level, None, axis, grip, None, kind, out_axis, method, freq, value, coh,
                  se_db, se_deg, n, flags, phase_rad=phase, spread=spread)


# ---------------------------------------------------------------------------
# The Spectra object: every response of a study as responses × frequency arrays
# ---------------------------------------------------------------------------

_EMPTY: dict[str, np.ndarray] = {}
#: Responses per row group of the spectra file (:meth:`Spectra.write`): a paper-size study
#: is written a group at a time (the sample studies are one group).
WRITE_ROWS = 256


@dataclass(frozen=True, eq=False)
class Spectra:
    """Every frequency response of a study, held once as responses × frequency arrays.

    One row per response (a trial's measured, derived or cross response, or an
    aggregate), one column per frequency of ``freq_hz``. The rows' identity is in
    ``keys`` (the columns :data:`armfit.io.schema.SPECTRA_KEYS` plus ``n``, the trials
    behind the value); :meth:`select` picks rows by it, so no stage filters a long table
    by strings. This is also the one reader and writer of the spectra Parquet file
    (:meth:`read`, :meth:`write`); :meth:`to_frame` gives the file's long table.

    Attributes
    ----------
    freq_hz : ndarray, shape (nf,)
        Frequencies, Hz, ascending.
    keys : dict of str to ndarray, each shape (nr,)
        level, subject (None for aggregates), axis, grip_N (NaN for the median), run
        (None if not repeated), kind, out_axis, method, n.
    h : ndarray, shape (nr, nf), complex
        Responses X/F (or Xa/Fa), m/N.
    values : dict of str to ndarray, each shape (nr, nf)
        mag_db (dB re 1 m/N), phase_deg (deg), coherence, se_db (dB), se_deg (deg) and
        the quartiles q25_db, q75_db, q25_deg, q75_deg across trials (aggregates).
    flags : ndarray, shape (nr, nf), object
        Comma-joined flags per point ('' where none).
    present : ndarray, shape (nr, nf), bool
        Where a response has a value (all True when every response is on one grid).
    meta : dict
        The file's metadata: estimator, options, grid, device masses, skipped trials.
    source : str or None
        The file it was read from (named in messages).
    """

    freq_hz: np.ndarray
    keys: Mapping[str, np.ndarray]
    h: np.ndarray
    values: Mapping[str, np.ndarray]
    flags: np.ndarray
    present: np.ndarray
    meta: Mapping[str, object] = field(default_factory=dict)
    source: str | None = None

    # -- shape and columns ---------------------------------------------------------

    def __len__(self) -> int:
        return int(self.h.shape[0])

    @property
    def mag_db(self) -> np.ndarray:
        """20 log10|H| (dB re 1 m/N), (nr, nf)."""
        return self.values["mag_db"]

    @property
    def phase_deg(self) -> np.ndarray:
        """Phase (deg) as estimated (unwrapped along frequency), (nr, nf)."""
        return self.values["phase_deg"]

    @property
    def se_db(self) -> np.ndarray:
        """Standard error of mag_db (dB), (nr, nf)."""
        return self.values["se_db"]

    @property
    def se_deg(self) -> np.ndarray:
        """Standard error of phase_deg (deg), (nr, nf)."""
        return self.values["se_deg"]

    @property
    def coherence(self) -> np.ndarray:
        """Magnitude-squared coherence 0…1, (nr, nf)."""
        return self.values["coherence"]

    def key(self, name: str) -> np.ndarray:
        """The identity column ``name`` (see :attr:`keys`) of every row, (nr,)."""
        return self.keys[name]

    def labels(self) -> list[str]:
        """A label per row: ``sub-<s>_grip-<g>N[_run-<k>]`` (trials) or ``<level>``."""
        out = []
        for lev, s, g, r in zip(self.keys["level"], self.keys["subject"],
                                self.keys["grip_N"], self.keys["run"], strict=True):
            if s is None:
                out.append(str(lev) + ("" if g != g else f"_grip-{float(g):g}N"))
            else:
                out.append(f"sub-{s}_grip-{float(g):g}N" + ("" if r is None else f"_run-{r}"))
        return out

    # -- selection -----------------------------------------------------------------

    def select(self, *, axis: str | None = None, grip: float | None = None,
               kind: str | None = None, level: str | None = None,
               out_axis: str | None = None, method: str | None = None,
               subject: str | None = None) -> Spectra:
        """The responses matching every criterion given (None: any).

        Parameters
        ----------
        axis : {'x', 'y', 'z'}, optional
            Stimulated axis.
        grip : float, optional
            Target grip force, N (compared with a relative tolerance of 1e-9).
        kind : {'measured', 'derived', 'cross'}, optional
            Response kind.
        level : {'trial', 'mean', 'median'}, optional
            Trials or an aggregate.
        out_axis : {'x', 'y', 'z'}, optional
            Position axis of the response (differs from ``axis`` for kind 'cross').
        method : str, optional
            Estimator, e.g. 'h1', 'chebwin', 'tfestimate'.
        subject : str, optional
            Subject label.

        Returns
        -------
        Spectra
            The rows in their order here, on the frequencies any of them has.
        """
        mask = np.ones(len(self), bool)
        for name, want in (("axis", axis), ("kind", kind), ("level", level),
                           ("out_axis", out_axis), ("method", method),
                           ("subject", subject)):
            if want is not None:
                mask &= self.keys[name] == want
        if grip is not None:
            mask &= np.isclose(self.keys["grip_N"].astype(float), float(grip), rtol=1e-9,
                               atol=0.0)
        return self.take(np.flatnonzero(mask))

    def take(self, rows) -> Spectra:
        """The rows ``rows`` (indices or a boolean mask), in that order, on the frequencies
        any of them has (``self`` when that is every row, in order, on every frequency:
        a Spectra is not changed in place)."""
        rows = np.asarray(rows)
        if rows.dtype == bool:
            rows = np.flatnonzero(rows)
        present = self.present[rows]
        cols = present.any(axis=0) if rows.size else np.zeros(self.freq_hz.size, bool)
        if (rows.size == len(self) and cols.all()
                and np.array_equal(rows, np.arange(len(self)))):
            return self
        if cols.all():
            def pick(a):
                return a[rows]
        else:
            def pick(a):
                return a[rows][:, cols]
        return replace(self, freq_hz=self.freq_hz[cols],
                       keys={k: v[rows] for k, v in self.keys.items()},
                       h=pick(self.h), values={k: pick(v) for k, v in self.values.items()},
                       flags=pick(self.flags), present=pick(self.present))

    def sorted(self, by: Sequence[str] = ("subject", "grip_N", "run")) -> Spectra:
        """The rows ordered by the identity columns ``by`` (missing values last, rows of
        equal keys in their order), as pandas' ``groupby(by, sort=True, dropna=False)``
        orders its groups: a stable sort of each row's (missing, value) pairs."""
        if len(self) == 0:
            return self

        def pairs(values):
            return [(1, 0) if v is None or v != v else (0, v) for v in values]

        rows = list(zip(*(pairs(self.keys[k]) for k in by), strict=True))
        order = sorted(range(len(rows)), key=rows.__getitem__)
        return self.take(np.asarray(order, dtype=np.intp))

    def values_of(self, name: str) -> set:
        """The distinct values of the identity column ``name``, missing ones left out."""
        return {v for v in self.keys[name] if v is not None and v == v}

    def repeated(self) -> bool:
        """Whether one response (the same identity but for ``method``) appears in more
        than one row: several estimates of it, e.g. files of two estimators joined. A
        study whose trials went through different estimators (some through their
        reference column) repeats nothing.

        Returns
        -------
        bool
        """
        names = [k for k in SPECTRA_KEYS if k != "method"]
        seen = {tuple(str(v) for v in row)
                for row in zip(*(self.keys[k] for k in names), strict=True)}
        return len(seen) < len(self)

    def common_grid(self, where: str = "") -> np.ndarray:
        """``freq_hz`` after checking that every row has a value at every frequency.

        Raises
        ------
        BadInputError
            Some response lacks a frequency the others have (column freq_hz).
        """
        if not self.present.all():
            raise BadInputError((f"{where}: " if where else "")
                                + "responses are not on one frequency grid",
                                file=self.source, column="freq_hz")
        return self.freq_hz

    def row(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(freq_hz, H, se_db, se_deg) of row ``i`` at the frequencies it has."""
        m = self.present[i]
        return self.freq_hz[m], self.h[i, m], self.se_db[i, m], self.se_deg[i, m]

    # -- the long table and the file -------------------------------------------------

    @classmethod
    def of(cls, spectra) -> Spectra:
        """``spectra`` itself, or a long table (pandas DataFrame with the columns of
        :data:`armfit.io.schema.SPECTRA_COLUMNS`) as a Spectra."""
        if isinstance(spectra, cls):
            return spectra
        return cls.from_frame(spectra, meta=getattr(spectra, "attrs", {}).get("armfit", {}))

    @classmethod
    def from_frame(cls, df, *, meta: Mapping | None = None, source: str | None = None
                   ) -> Spectra:
        """A Spectra from the long table (one row per response and frequency).

        Rows are grouped into responses by :data:`armfit.io.schema.SPECTRA_KEYS` in the
        order they first appear. Only level, axis, kind, freq_hz, re and im are required:
        a missing ``out_axis`` is taken as ``axis``, missing ``mag_db`` and ``phase_deg``
        are computed from re and im, ``n`` is 1, ``flags`` empty and any other column NaN.

        Raises
        ------
        BadInputError
            A required column is missing, or a response holds a frequency twice.
        """
        import pandas as pd
        for c in ("level", "axis", "kind", "freq_hz", "re", "im"):
            if c not in df.columns:
                raise BadInputError("missing column; not a spectra table written by "
                                    "`armfit estimate`", file=source, column=c)
        df = _complete(_numbers(df, source))
        # a negative, zero or non-finite frequency is bad data, not a usage error later
        check_in_range(df["freq_hz"].to_numpy(float), FREQUENCY_RANGE,
                       file=source, column="freq_hz", shown=list(df["freq_hz"]))
        keys_df = df[list(SPECTRA_KEYS)]
        if len(df):
            codes = keys_df.groupby(list(SPECTRA_KEYS), sort=False, dropna=False
                                    ).ngroup().to_numpy()
        else:
            codes = np.zeros(0, int)
        # one object per distinct flag text (a study has few), shared by its cells
        flag_codes, flag_texts = pd.factorize(df["flags"], use_na_sentinel=True)
        first = np.unique(codes, return_index=True)[1]
        keys = {}
        for c in SPECTRA_KEYS:
            col = keys_df[c].iloc[first].to_numpy(object)
            if c == "grip_N":
                keys[c] = [float(v) if v is not None and not pd.isna(v) else np.nan
                           for v in col]
            elif c == "run":
                keys[c] = [None if v is None or pd.isna(v) else int(v) for v in col]
            else:
                keys[c] = [None if v is None or pd.isna(v) else str(v) for v in col]
        keys["n"] = [int(v) for v in df["n"].iloc[first].to_numpy()]
        return _assemble(codes, df["freq_hz"].to_numpy(float),
                         lambda c: df[c].to_numpy(float), flag_codes, list(flag_texts),
                         keys, meta, source)

    def to_frame(self):
        """The long table of the spectra file: one row per response and frequency, columns
        :data:`armfit.io.schema.SPECTRA_COLUMNS` (text columns as pandas "string",
        ``run`` nullable Int64)."""
        import pandas as pd
        if len(self) == 0:
            return pd.DataFrame({c: [] for c in SPECTRA_COLUMNS})
        sizes = self.present.sum(axis=1)
        f = np.broadcast_to(self.freq_hz, self.present.shape)[self.present]
        cols: dict[str, object] = {}
        for c in SPECTRA_COLUMNS:
            if c in self.keys:
                col = np.repeat(np.array(list(self.keys[c]), dtype=object), sizes)
            elif c == "freq_hz":
                col = f
            elif c == "re":
                col = self.h.real[self.present]
            elif c == "im":
                col = self.h.imag[self.present]
            elif c == "flags":
                col = self.flags[self.present]
            else:
                col = self.values[c][self.present]
            cols[c] = pd.array(col, dtype="string") if c in SPECTRA_TEXT else col
        # the columns are fresh arrays: the frame takes them without another copy
        df = pd.DataFrame(cols, columns=list(SPECTRA_COLUMNS), copy=False)
        del cols
        df["grip_N"] = df["grip_N"].astype(float)
        df["run"] = pd.array([None if v is None or v != v else int(v) for v in df["run"]],
                             dtype="Int64")
        df["n"] = df["n"].astype("int64")
        df.attrs["armfit"] = dict(self.meta)
        return df

    @classmethod
    def read(cls, path, *, level=None, kind=None, axis=None, values=None,
             estimators: bool = True) -> Spectra:
        """Read a spectra Parquet file written by ``armfit estimate``, a row group at a time.

        Parameters
        ----------
        path : str or os.PathLike
            The file.
        level, kind, axis : str or sequence of str, optional
            Keep only the responses of these levels (``trial``, ``mean``, ``median``),
            kinds and stimulated axes (None: all). Every row is read and checked, kept
            or not, so the result and the errors are those of
            ``Spectra.read(path).select(...)``; the rows left out are never held.
        values : str or sequence of str, optional
            Keep only these of :data:`armfit.io.schema.SPECTRA_VALUES` in :attr:`values`
            (None: all); the responses, flags and the other values kept are the same.
            The values left out are not read from the file where it holds them as
            numbers (else never held for more than a row group).
        estimators : bool
            Keep the metadata's per-trial records (``meta["estimators"]``, what the
            estimators say of each trial; default True). False leaves them out, and a
            file armfit wrote then never has them parsed: at 4,050 trials they are
            1.2 MB of JSON, 3 MB and 32,000 objects once parsed.

        Returns
        -------
        Spectra
            With the file's metadata in :attr:`meta` and its name in :attr:`source`.

        Raises
        ------
        NoInputError
            The file is missing.
        BadInputError
            Naming the file (and the missing column) if it is not a spectra table, or the
            row of an axis other than x, y or z.

        Notes
        -----
        A file armfit wrote holds whole responses in each row group (:data:`WRITE_ROWS`
        per group), so the rows are turned into responses group by group and only one
        group of the long table is in memory besides the responses kept. A file whose
        response continues into a later group, or one that is unreadable or bad, is read
        whole instead, which gives the same responses or names what is wrong.
        """
        p = Path(path)
        if not p.is_file():
            raise NoInputError(f"{p}: no such spectra file")
        wanted = {k: (v,) if isinstance(v, str) else tuple(v)
                  for k, v in (("level", level), ("kind", kind), ("axis", axis))
                  if v is not None}
        if values is not None:
            values = (values,) if isinstance(values, str) else tuple(values)
            unknown = [v for v in values if v not in SPECTRA_VALUES]
            if unknown:
                raise UsageError(f"values: {', '.join(map(repr, unknown))} not among "
                                 f"{', '.join(SPECTRA_VALUES)}")
        try:
            return _read_by_group(p, wanted, values, estimators)
        except Exception:  # noqa: BLE001 - the whole read decides: same result or error
            pass
        whole = _read_whole(p, estimators)
        return _only_values(whole.take(_wanted_rows(whole, wanted)) if wanted else whole,
                            values)

    def write(self, path, *, overwrite: bool = False):
        """Write the spectra Parquet file (zstd), atomically, with :attr:`meta` as JSON
        under the key ``armfit`` of the file's key-value metadata.

        Parameters
        ----------
        path : str or os.PathLike
            Destination.
        overwrite : bool
            Replace an existing file.

        Returns
        -------
        str or os.PathLike
            ``path``.

        Raises
        ------
        OutputError
            ``path`` exists and not ``overwrite``.
        """
        # written WRITE_ROWS responses at a time (one row group each), so that the long
        # table and its Arrow copy never exist for the whole of a large study at once
        return write_parts(self.parts(), self.meta, path, overwrite=overwrite)

    def parts(self, rows: int | None = None):
        """The rows in order, ``rows`` (default :data:`WRITE_ROWS`) at a time, each a
        :class:`Spectra` (one part when there is no row)."""
        rows = rows or WRITE_ROWS
        n = len(self)
        if not n:
            yield self
        for i in range(0, n, rows):
            yield self.take(np.arange(i, min(i + rows, n)))

    def counts(self) -> dict[str, object]:
        """The rows of the spectra file, rows per level and flagged trial rows.

        Returns
        -------
        dict
            See :func:`row_counts`.
        """
        return row_counts([self])

    def write_csv(self, path, *, overwrite: bool = False):
        """Write :meth:`to_frame` as CSV (10 significant digits), atomically."""
        with atomic_path(path, overwrite=overwrite) as tmp:
            self.to_frame().to_csv(tmp, index=False, float_format=CSV_FLOAT_FORMAT)
        return path

    def axes(self) -> list[str]:
        """The stimulated axes with a response, in x, y, z order."""
        return [a for a in AXES if (self.keys["axis"] == a).any()]

    def plot(self, axis: str | None = None, ax=None, *, panel: str | None = None,
             kind: str = "measured"):
        """The Bode pair of one axis: magnitude (dB re 1 m/N) and phase (deg) of every
        row of ``kind`` on that axis's own position, against log frequency (Hz).

        Parameters
        ----------
        axis : {'x', 'y', 'z'}, optional
            Default: the only axis the rows hold.
        ax : matplotlib.axes.Axes or sequence of two, optional
            One Axes draws one panel (``panel``, default the magnitude); two draw
            magnitude and phase. Default: a new figure with the panels asked for.
        panel : {'magnitude', 'phase', 'both'}, optional
            Default 'both' (one Axes: 'magnitude').
        kind : {'measured', 'derived'}
            Which responses (cross-axis responses are left out).

        Returns
        -------
        matplotlib.figure.Figure or the ``ax`` given
            Each line is labelled by :meth:`labels`; trials thin, aggregates (mean,
            median) thick. The publication figures are :func:`armfit.figures.bode_figure`
            and the result objects' ``plot``.
        """
        have = self.axes()
        if axis is None:
            if len(have) != 1:
                raise UsageError(f"these spectra hold axes {', '.join(have) or 'none'}: "
                                 "choose one with axis=")
            axis = have[0]
        elif axis not in have:
            raise UsageError(f"no axis {axis!r} here (axes: {', '.join(have) or 'none'})")
        given = None if ax is None else (list(ax) if isinstance(ax, Sequence | np.ndarray)
                                         else [ax])
        panel = panel or ("magnitude" if given is not None and len(given) == 1 else "both")
        wanted = {"both": ("magnitude", "phase"), "magnitude": ("magnitude",),
                  "phase": ("phase",)}.get(panel)
        if wanted is None or (given is not None and len(given) != len(wanted)):
            raise UsageError(f"panel must be magnitude, phase or both (one Axes per panel), "
                             f"got {panel!r} with {len(given or ())} Axes")
        fig = None
        if given is None:
            from matplotlib.backends.backend_agg import FigureCanvasAgg
            from matplotlib.figure import Figure
            fig = Figure(figsize=(5.0, 1.9 * len(wanted) + 0.6), layout="constrained")
            FigureCanvasAgg(fig)
            given = list(fig.subplots(len(wanted), 1, sharex=True, squeeze=False)[:, 0])
        rows = self.select(axis=axis, kind=kind, out_axis=axis)
        for name, a in zip(wanted, given, strict=True):
            y = rows.mag_db if name == "magnitude" else rows.phase_deg
            for i, label in enumerate(rows.labels()):
                m = rows.present[i]
                a.plot(rows.freq_hz[m], y[i, m], label=label,
                       lw=0.6 if rows.keys["level"][i] == "trial" else 1.6)
            a.set_xscale("log")
            a.set_ylabel("Magnitude (dB re 1 m/N)" if name == "magnitude" else "Phase (deg)")
        given[-1].set_xlabel("Frequency (Hz)")
        return fig if ax is None else ax

    def _repr_html_(self) -> str:
        """A compact HTML table for notebooks: the size and band, then the identity of
        the first rows (escaped)."""
        import html

        import pandas as pd
        ids = pd.DataFrame({k: list(self.keys[k]) for k in
                            ("level", "axis", "grip_N", "subject", "run", "kind", "method",
                             "n")})
        band = (f", {self.freq_hz[0]:g}–{self.freq_hz[-1]:g} Hz" if self.freq_hz.size
                else "")
        more = f" ({len(self) - 6} more rows)" if len(self) > 6 else ""
        head = ids.head(6).to_html(escape=True, index=False, border=0)
        return (f"<div><p><b>Spectra</b>: {html.escape(str(len(self)))} responses × "
                f"{self.freq_hz.size} frequencies{html.escape(band)}"
                f"{html.escape(more)}</p>{head}</div>")

    # -- out to python-control ------------------------------------------------------

    def to_frd(self, *, axis: str, grip: float | None = None, level: str = "mean",
               kind: str = "measured", subject: str | None = None, run: int | None = None,
               out_axis: str | None = None, method: str | None = None):
        """One response as a python-control ``FrequencyResponseData`` (the optional
        extra ``armfit[control]``), frequencies in rad/s (ω = 2π f).

        The arguments pick one row, as :meth:`select` does: the mean of an axis × grip
        over subjects (``level='mean'``, the default: give ``grip``), the median of an
        axis over all trials (``level='median'``, no ``grip``), or one trial
        (``level='trial'``: ``subject`` and ``grip``, and ``run`` when the study
        repeats trials). ``kind``: 'measured' (X/F of eq. 4, the default), 'derived'
        (Xa/Fa, the arm without the device) or 'cross' (then ``out_axis``, the position
        axis). The frequencies where the response has no value (a cell without signal)
        are left out.

        Parameters
        ----------
        axis : {'x', 'y', 'z'}
            The stimulated axis.
        grip : float, optional
            Target grip force, N.
        level : {'mean', 'median', 'trial'}
        kind : {'measured', 'derived', 'cross'}
        subject : str, optional
        run : int, optional
        out_axis : {'x', 'y', 'z'}, optional
            Position axis (default ``axis``; required for 'cross').
        method : str, optional
            The estimator, when the spectra hold several.

        Returns
        -------
        control.FrequencyResponseData
            The response in m/N at ``omega`` (rad/s); named after the row
            (``x_measured_mean_grip-2N``), input ``F`` and output ``x`` (the axes').

        Raises
        ------
        UsageError
            python-control is not installed (``pip install armfit[control]``), or the
            arguments pick no response or several (the message lists them).
        """
        from armfit._lazy import import_extra

        control = import_extra("control", "control", "Spectra.to_frd")
        if level not in ("mean", "median", "trial"):
            raise UsageError(f"level must be mean, median or trial, got {level!r}")
        if kind == "cross" and out_axis is None:
            raise UsageError("kind 'cross' needs out_axis=, the position axis")
        sel = self.select(axis=axis, grip=grip, kind=kind, level=level,
                          out_axis=axis if out_axis is None else out_axis, method=method,
                          subject=subject)
        if run is not None:
            sel = sel.take(np.array([r is not None and int(r) == int(run)
                                     for r in sel.keys["run"]], bool))
        if len(sel) != 1:
            what = (f"{kind} responses of level {level}, axis {axis}"
                    + ("" if grip is None else f", grip {float(grip):g} N"))
            found = ", ".join(sel.labels()[:6]) + (", ..." if len(sel) > 6 else "")
            raise UsageError(f"{len(sel)} {what} in the spectra"
                             + (f" ({found}): give grip=, subject=, run= or method= to "
                                "pick one" if len(sel) else ""))
        f, h, _, _ = sel.row(0)
        keep = np.isfinite(h)
        if not keep.any():
            raise UsageError(f"the {kind} response {sel.labels()[0]} of axis {axis} has no "
                             "value at any frequency")
        name = f"{axis}_{kind}_{sel.labels()[0]}".replace(".", "p")
        return control.frd(h[keep], 2 * np.pi * f[keep], name=name, inputs=["F"],
                           outputs=[sel.keys["out_axis"][0]])


def _file_meta(kv: Mapping | None, p: Path, estimators: bool = True) -> dict:
    """armfit's metadata of a spectra file (``{}`` if absent or not JSON), its device
    masses checked against their range; with ``estimators`` False, without the per-trial
    records (``estimators``: those under their own key are not unpacked or parsed). The
    records are read from :data:`SPECTRA_ESTIMATORS_KEY` (compressed), else from
    :data:`SPECTRA_ESTIMATORS_JSON_KEY` or armfit's JSON (files written before); a value
    that does not unpack or parse is ignored, as armfit's JSON is."""
    import json
    kv = kv or {}
    try:
        meta = json.loads(kv[SPECTRA_META_KEY]) if SPECTRA_META_KEY in kv else {}
    except ValueError:
        meta = {}
    if isinstance(meta, dict):
        if not estimators:
            meta.pop("estimators", None)
        elif SPECTRA_ESTIMATORS_KEY in kv or SPECTRA_ESTIMATORS_JSON_KEY in kv:
            try:
                meta["estimators"] = json.loads(
                    unpack_records(kv[SPECTRA_ESTIMATORS_KEY])
                    if SPECTRA_ESTIMATORS_KEY in kv else kv[SPECTRA_ESTIMATORS_JSON_KEY])
            except ValueError:
                pass
    masses = meta.get("mp_kg") if isinstance(meta, dict) else None
    for axis, mp in masses.items() if isinstance(masses, dict) else ():
        # the device mass the derived dynamics were estimated with (fit-uncertainty)
        check_in_range(parse_numbers([mp], errors="coerce"),
                       DEVICE_MASS_RANGE, file=str(p),
                       column=None, name=f"the device mass of axis {axis} in the "
                       "metadata (mp_kg)", shown=[mp])
    return meta


def _check_axes(df, p: Path, first_row: int = 0) -> None:
    """Refuse a row whose ``axis`` or ``out_axis`` is not x, y or z (``first_row``: the
    file row before the frame's first)."""
    for col in ("axis", "out_axis"):  # rows of another axis would be dropped silently
        bad = np.flatnonzero(~df[col].isin(list(AXES)).to_numpy())
        if bad.size:
            raise BadInputError(f"axis {cell(df[col].iloc[bad[0]])} is not x, y or z",
                                file=str(p), column=col, row=first_row + int(bad[0]) + 1)


def _read_whole(p: Path, estimators: bool = True) -> Spectra:
    """The spectra file ``p`` read in one piece (see :meth:`Spectra.read`)."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    try:
        table = pq.read_table(p, use_threads=False)
    except (pa.ArrowException, OSError) as exc:
        raise BadInputError(f"not a readable Parquet spectra file "
                            f"({str(exc).splitlines()[0]}); make one with "
                            "`armfit estimate`", file=str(p)) from None
    for c in SPECTRA_COLUMNS:
        if c not in table.column_names:
            raise BadInputError("missing column; not a spectra file written by "
                                "`armfit estimate`", file=str(p), column=c)
    meta = _file_meta(table.schema.metadata, p, estimators)
    df = table.select(list(SPECTRA_COLUMNS)).to_pandas()
    del table
    _check_axes(df, p)
    return Spectra.from_frame(df, meta=meta, source=str(p))


class _NotByGroup(Exception):
    """The file cannot be read group by group (see :meth:`Spectra.read`)."""


def _wanted_rows(sp: Spectra, wanted: Mapping[str, tuple]) -> np.ndarray:
    """Indices of the responses of ``sp`` whose keys are among ``wanted``'s values."""
    keep = np.ones(len(sp), bool)
    for k, values in wanted.items():
        keep &= np.array([v in values for v in sp.keys[k]], bool)
    return np.flatnonzero(keep)


def _response_keys(sp: Spectra) -> set[tuple]:
    """The identities of ``sp``'s responses (a missing grip or run as None)."""
    cols = [[None if v is None or v != v else v for v in sp.keys[k]] for k in SPECTRA_KEYS]
    return set(zip(*cols, strict=True))


def _key_hashes(sp: Spectra) -> np.ndarray:
    """The hashes of :func:`_response_keys` of ``sp``, sorted and distinct (int64): what
    a read keeps of the responses it has seen, 8 bytes each (a set of the key tuples held
    2.1 MB at the end of a read of the 4,050-trial study). Equal keys have equal hashes;
    two keys that share a hash are told apart by nothing, so a read that finds a seen
    hash again takes the response for split over groups and reads the file whole (the
    same result)."""
    return unique(np.fromiter(map(hash, _response_keys(sp)), np.int64))


#: A read gives the memory it no longer needs back to the system
#: (:func:`armfit.memory.release_memory`) every this many row groups read
#: (:func:`_read_by_group`) and parts copied (:func:`_concat`).
_TRIM_EVERY = 8


def _only_values(sp: Spectra, values: tuple[str, ...] | None) -> Spectra:
    """``sp`` holding only the arrays of ``values`` in :attr:`Spectra.values` (None:
    ``sp`` itself)."""
    if values is None:
        return sp
    return replace(sp, values={c: a for c, a in sp.values.items() if c in values})


def _read_by_group(p: Path, wanted: Mapping[str, tuple],
                   values: tuple[str, ...] | None = None,
                   estimators: bool = True) -> Spectra:
    """:meth:`Spectra.read` of ``p`` a row group at a time, keeping the responses
    ``wanted`` selects, the ``values`` (None: all) and the metadata's per-trial records
    when ``estimators``; raises :class:`_NotByGroup` (or the error of a bad file) when
    the whole read must decide."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    # the text columns as Parquet holds them, dictionary-encoded (no text per row)
    pf = pq.ParquetFile(p, read_dictionary=list(SPECTRA_TEXT))
    schema = pf.schema_arrow
    if pf.num_row_groups == 0 or any(c not in schema.names for c in SPECTRA_COLUMNS):
        raise _NotByGroup
    meta = _file_meta(schema.metadata, p, estimators)
    # the value columns not wanted are not read where the file holds them as floats:
    # from_frame takes any float there, so they cannot change the responses or errors
    if values is not None and all(pa.types.is_floating(schema.field(c).type)
                                  for c in SPECTRA_VALUES if c not in values):
        columns = [c for c in SPECTRA_COLUMNS if c not in SPECTRA_VALUES or c in values]
    else:
        columns = list(SPECTRA_COLUMNS)
    parts: list[Spectra] = []
    seen = np.empty(0, np.int64)    # the responses read so far (:func:`_key_hashes`)
    first_row = 0
    empty = None
    for g in range(pf.num_row_groups):
        table = pf.read_row_group(g, columns=columns, use_threads=False)
        part = _group_spectra(table, meta, str(p), first_row,
                              lambda g=g: pf.read_row_group(
                                  g, columns=list(SPECTRA_COLUMNS), use_threads=False))
        first_row += table.num_rows
        del table
        keys = _key_hashes(part)
        if np.isin(keys, seen, assume_unique=True).any():
            raise _NotByGroup           # a response split over groups: read it whole
        seen = np.concatenate([seen, keys])     # disjoint (just checked): still distinct
        rows = _wanted_rows(part, wanted) if wanted else np.arange(len(part))
        part = _only_values(part, values)   # before the rows are copied
        if empty is None:
            empty = part.take(rows[:0])
        if rows.size:
            parts.append(part if rows.size == len(part) else part.take(rows))
        del part
        if g % _TRIM_EVERY == _TRIM_EVERY - 1:
            # Arrow's allocator (mimalloc) and the C library's keep the memory of the
            # groups read so far: give it back, so that a file of many groups needs no
            # more memory than a few of them besides the responses kept
            release_memory()
    return _concat(parts, meta, str(p)) if parts else empty


def _group_spectra(table, meta: Mapping, source: str, first_row: int,
                   whole_group: Callable[[], object] | None = None) -> Spectra:
    """The responses of one row group (an Arrow table of the spectra columns, every one
    or all but some value columns): :func:`_arrow_spectra` where the group is laid out
    as armfit writes it, else :meth:`Spectra.from_frame` of its long table of every
    column (``whole_group()``, when ``table`` lacks some; after :func:`_check_axes`),
    which then decides, or names what is wrong; the same responses either way."""
    part = _arrow_spectra(table, meta, source)
    if part is None:
        if table.num_columns < len(SPECTRA_COLUMNS):
            table = whole_group()
        df = _decoded(table).to_pandas()
        _check_axes(df, Path(source), first_row)
        part = Spectra.from_frame(df, meta=meta, source=source)
    return part


def _decoded(table):
    """``table`` with its dictionary-encoded columns as plain columns of their values
    (pandas would make them categorical)."""
    import pyarrow as pa
    for i, f in enumerate(table.schema):
        if pa.types.is_dictionary(f.type):
            table = table.set_column(i, f.name, table.column(i).cast(f.type.value_type))
    return table


def _arrow_spectra(table, meta: Mapping, source: str | None) -> Spectra | None:
    """:meth:`Spectra.from_frame` of ``table.to_pandas()``, made from the Arrow columns
    without the long table, for a table laid out as armfit writes it: the text columns
    as text (or dictionary-encoded text, as :func:`_read_by_group` reads them), the
    numeric ones as numbers (``run`` and ``n`` whole, ``n`` never missing, ``run`` never
    negative), every axis and output axis x, y or z, every frequency in range, and each
    response's rows together, each frequency once. The value columns may be only some
    of :data:`armfit.io.schema.SPECTRA_VALUES` (a read that keeps only those): the
    Spectra holds those. None otherwise (or without rows): :meth:`Spectra.from_frame`
    then gives the responses, or its error. Both end in :func:`_assemble`."""
    import pyarrow as pa
    n_rows = table.num_rows
    names = [c for c in table.column_names if c in SPECTRA_VALUES]
    if n_rows == 0 or table.column_names != [c for c in SPECTRA_COLUMNS
                                             if c not in SPECTRA_VALUES or c in names]:
        return None
    cols = {c: _one_chunk(table.column(c)) for c in table.column_names}
    for c, col in cols.items():
        t = col.type.value_type if pa.types.is_dictionary(col.type) and c in SPECTRA_TEXT \
            else col.type
        ok = (pa.types.is_string(t) or pa.types.is_large_string(t) if c in SPECTRA_TEXT
              else pa.types.is_integer(t) if c in ("run", "n") else pa.types.is_floating(t))
        if not ok:
            return None
    if cols["n"].null_count or (arrow_ints(cols["run"], missing=0) < 0).any():
        return None
    text = {c: _text_codes(cols[c]) for c in SPECTRA_TEXT}
    for c in ("axis", "out_axis"):
        if cols[c].null_count or not set(text[c][1]) <= set(AXES):
            return None
    freq = arrow_numbers(cols["freq_hz"])
    try:   # from_frame's check: it names the first bad cell
        check_in_range(freq, FREQUENCY_RANGE, file=source, column="freq_hz")
    except BadInputError:
        return None
    grip, run = arrow_numbers(cols["grip_N"]), arrow_ints(cols["run"])
    # a response starts where any key differs from the row before (missing = missing)
    change = np.zeros(n_rows, bool)
    change[0] = True
    for c in SPECTRA_KEYS:
        if c == "grip_N":
            change[1:] |= (grip[1:] != grip[:-1]) & ~(np.isnan(grip[1:]) & np.isnan(grip[:-1]))
        else:
            v = run if c == "run" else text[c][0]
            change[1:] |= v[1:] != v[:-1]
    first = np.flatnonzero(change)
    keys = {c: [None if i < 0 else text[c][1][i] for i in text[c][0][first].tolist()]
            for c in SPECTRA_KEYS if c in SPECTRA_TEXT}
    keys["grip_N"] = grip[first].tolist()
    keys["run"] = [None if v < 0 else v for v in run[first].tolist()]
    keys["n"] = arrow_ints(cols["n"])[first].tolist()
    try:
        sp = _assemble(np.cumsum(change) - 1, freq, lambda c: arrow_numbers(cols[c]),
                       *text["flags"], keys, meta, source, names)
    except BadInputError:            # a frequency twice in a response: from_frame says so
        return None
    # a response in two places, which from_frame groups into one
    return sp if len(_response_keys(sp)) == len(sp) else None


def _one_chunk(col):
    """A column of a table as one Arrow array (a dictionary-encoded column's chunks on
    one dictionary)."""
    import pyarrow as pa
    if col.num_chunks == 1:
        return col.chunk(0)
    if pa.types.is_dictionary(col.type):
        col = col.unify_dictionaries()
    return col.combine_chunks()


def _text_codes(col) -> tuple[np.ndarray, list[str]]:
    """A text column (plain or dictionary-encoded) as (each row's code, the distinct
    texts): the code of a row is the index of its text, −1 where it is missing; equal
    texts have equal codes."""
    import pyarrow as pa
    if not pa.types.is_dictionary(col.type):
        col = col.dictionary_encode()
    texts = col.dictionary.to_pylist()
    codes = arrow_ints(col.indices)
    first = {}
    for i, t in enumerate(texts):
        first.setdefault(t, i)
    if len(first) < len(texts):         # a text twice in the dictionary: one code each
        codes = np.append(np.array([first[t] for t in texts], np.int64), -1)[codes]
    return codes, texts


def _assemble(codes: np.ndarray, freq: np.ndarray, column: Callable[[str], np.ndarray],
              flag_codes: np.ndarray, flag_texts: Sequence[str],
              keys: Mapping[str, Sequence], meta: Mapping | None,
              source: str | None, values: Sequence[str] = SPECTRA_VALUES) -> Spectra:
    """The :class:`Spectra` of a long table's rows: ``codes`` the response of each row
    (0, 1, … in the order the responses first appear), ``freq`` its frequency (Hz),
    ``column(name)`` the row values of ``re``, ``im`` and each of ``values`` (of
    :data:`armfit.io.schema.SPECTRA_VALUES`; NaN where missing), ``flag_codes`` each
    row's index into ``flag_texts`` (−1: none), ``keys`` per response its key values
    (text or None, ``grip_N`` a float or NaN, ``run`` an int or None) and ``n``.

    Raises
    ------
    BadInputError
        A response holds a frequency twice (naming the row).
    """
    grid, fcode = np.unique(freq, return_inverse=True)
    nr, nf = (int(codes.max()) + 1 if codes.size else 0), grid.size
    flat = codes * nf + fcode
    if unique(flat).size != flat.size:
        dup = int(np.flatnonzero(np.bincount(flat, minlength=nr * nf)[flat] > 1)[0])
        raise BadInputError("a frequency appears twice in one response", file=source,
                            column="freq_hz", row=dup + 1)
    present = np.zeros((nr, nf), bool)
    present[codes, fcode] = True
    h = np.full((nr, nf), np.nan, complex)
    h.real[codes, fcode] = column("re")
    h.imag[codes, fcode] = column("im")
    arrays = {}
    for c in values:
        a = np.full((nr, nf), np.nan)
        a[codes, fcode] = column(c)
        arrays[c] = a
    flags = np.full((nr, nf), "", dtype=object)
    flags[codes, fcode] = np.array([*flag_texts, ""], dtype=object)[flag_codes]
    out = {c: np.array(keys[c], dtype=object) for c in (*SPECTRA_KEYS, "n")}
    missing_out = np.array([v is None for v in out["out_axis"]], bool)
    out["out_axis"][missing_out] = out["axis"][missing_out]
    return Spectra(grid, out, h, arrays, flags, present, dict(meta or {}), source)


def _concat(parts: list[Spectra], meta: Mapping, source: str) -> Spectra:
    """The responses of ``parts`` in order, on the union of their frequencies (each part
    is released as soon as it is copied)."""
    grid = unique(np.concatenate([p.freq_hz for p in parts]))
    nr, nf = sum(len(p) for p in parts), grid.size
    h = np.empty((nr, nf), complex)
    values = {c: np.empty((nr, nf)) for c in parts[0].values}
    flags = np.empty((nr, nf), object)
    present = np.empty((nr, nf), bool)
    keys = {k: np.concatenate([p.keys[k] for p in parts]) for k in parts[0].keys}
    i = 0
    parts.reverse()
    for copied in range(len(parts)):
        if copied and copied % _TRIM_EVERY == 0:
            # the parts copied so far are freed: their pages go back to the system, so
            # that the parts and the table they make are not held at once
            release_memory()
        part = parts.pop()
        rows = slice(i, i + len(part))
        i += len(part)
        if part.freq_hz.size == nf and np.array_equal(part.freq_hz, grid):
            cols = slice(None)
        else:   # on a grid of its own: the other frequencies absent
            cols = np.searchsorted(grid, part.freq_hz)
            h[rows], flags[rows], present[rows] = np.nan, "", False
            for c in values:
                values[c][rows] = np.nan
        h[rows, cols] = part.h
        flags[rows, cols] = part.flags
        present[rows, cols] = part.present
        for c in values:
            values[c][rows, cols] = part.values[c]
        del part
    return Spectra(grid, keys, h, values, flags, present, dict(meta), source)


#: Numeric columns of the spectra table; ``run`` and ``n`` hold whole numbers.
_NUMERIC: tuple[str, ...] = ("grip_N", "run", "freq_hz", "re", "im", *SPECTRA_VALUES, "n")


def _numbers(df, source: str | None):
    """``df`` with its numeric columns as numbers: a column held as text (a table read
    from CSV, a Parquet string column) is read by :func:`armfit.io.numbers.parse_numbers`,
    so ``1_5`` is refused, not read as 15. Raises BadInputError naming the column and
    row of a cell that is not a number (or, in ``run`` and ``n``, not a whole number)."""
    import pandas as pd
    out = {}
    for c in _NUMERIC:
        if c not in df.columns:
            continue
        dtype = df[c].dtype
        whole = c in ("run", "n")
        if pd.api.types.is_numeric_dtype(dtype) and not pd.api.types.is_bool_dtype(dtype) \
                and (not whole or pd.api.types.is_integer_dtype(dtype)):
            continue
        v = parse_numbers(df[c], file=source, column=c)
        if whole:
            bad = np.flatnonzero(~(np.isnan(v) if c == "run" else np.zeros(v.size, bool))
                                 & ~(np.isfinite(v) & (v == np.round(v)) & (v >= 0)))
            if bad.size:
                raise BadInputError(f"{cell(df[c].iloc[bad[0]])} is not a whole number",
                                    file=source, column=c, row=int(bad[0]) + 1)
            v = pd.arrays.IntegerArray(np.nan_to_num(v).astype(np.int64), np.isnan(v))
        out[c] = v
    return df.assign(**out) if out else df

def _complete(df):
    """``df`` with every spectra column, the optional ones filled (see
    :meth:`Spectra.from_frame`)."""
    missing = [c for c in SPECTRA_COLUMNS if c not in df.columns]
    if not missing:
        return df
    df = df.copy()
    h = df["re"].to_numpy(float) + 1j * df["im"].to_numpy(float)
    for c in missing:
        if c == "out_axis":
            df[c] = df["axis"]
        elif c == "mag_db":
            with np.errstate(divide="ignore"):
                df[c] = 20.0 * np.log10(np.abs(h))
        elif c == "phase_deg":
            df[c] = np.degrees(np.angle(h))
        elif c == "n":
            df[c] = 1
        elif c == "flags":
            df[c] = ""
        elif c in ("subject", "method", "run"):
            df[c] = None
        else:
            df[c] = np.nan
    return df


def write_parts(parts: Iterable[Spectra], meta: Mapping, path, *,
                overwrite: bool = False):
    """Write the spectra Parquet file from its rows in order, one row group per part.

    :meth:`Spectra.write` passes slices of itself; :meth:`StudySpectra.write` makes its
    parts as they are written. After each group, Arrow's allocator returns the freed
    buffers to the system.

    Parameters
    ----------
    parts : iterable of Spectra
        The file's rows, in order, on one grid.
    meta : mapping
        Written as JSON under the key ``armfit`` of the file's key-value metadata.
    path : str or os.PathLike
        Destination, written atomically (zstd compression).
    overwrite : bool
        Replace an existing file.

    Returns
    -------
    str or os.PathLike
        ``path``.

    Raises
    ------
    OutputError
        ``path`` exists and not ``overwrite``.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq
    with atomic_path(path, overwrite=overwrite) as tmp:
        writer = None
        try:
            for part in parts:
                if writer is None:
                    schema = _file_schema(part, meta)
                    # the metadata goes in once, as key-value metadata: Arrow's copy of
                    # the schema (store_schema) would hold it again, base64-encoded,
                    # and every reader that opens the file would decode both
                    writer = pq.ParquetWriter(tmp, schema.remove_metadata(),
                                              compression="zstd", store_schema=False)
                    writer.add_key_value_metadata(schema.metadata)
                writer.write_table(_arrow_table(part, schema))
                # Arrow's allocator (mimalloc) would keep each group's buffers: give
                # them back, so a file of many groups needs no more memory than one
                pa.default_memory_pool().release_unused()
        finally:
            if writer is not None:
                writer.close()
    return path


#: Arrow types of the spectra file's columns that are not float64.
_ARROW_TYPES = {**dict.fromkeys(SPECTRA_TEXT, "large_string"), "run": "int64", "n": "int64"}


def _pandas_metadata() -> bytes:
    """The ``pandas`` key of the spectra file's schema metadata, as
    ``pyarrow.Schema.from_pandas`` writes it for :meth:`Spectra.to_frame` (so that pandas
    reads the text columns back as strings and ``run`` as nullable Int64), made without
    importing pandas."""
    import json

    import pyarrow as pa

    def column(c: str) -> dict[str, object]:
        kind = _ARROW_TYPES.get(c, "float64")
        pandas_type, numpy_type = {"large_string": ("object", "string"),
                                   "int64": ("int64", "Int64" if c == "run" else "int64")
                                   }.get(kind, (kind, kind))
        return {"name": c, "field_name": c, "pandas_type": pandas_type,
                "numpy_type": numpy_type, "metadata": None}

    return json.dumps({"index_columns": [], "column_indexes": [],
                       "columns": [column(c) for c in SPECTRA_COLUMNS], "attributes": {},
                       "creator": {"library": "pyarrow", "version": pa.__version__},
                       "pandas_version": _installed_version("pandas")}).encode()


def _installed_version(name: str) -> str:
    """The version of the installed distribution ``name``, as
    ``importlib.metadata.version`` gives it: read from the ``METADATA`` of the one
    ``.dist-info`` beside the package, without importing it (importlib.metadata itself
    takes some 25 ms to import); importlib.metadata's answer when that is not found."""
    import importlib.util
    from pathlib import Path
    spec = importlib.util.find_spec(name)
    if spec is not None and spec.origin:
        found = list(Path(spec.origin).parent.parent.glob(f"{name}-*.dist-info"))
        if len(found) == 1 and (found[0] / "METADATA").is_file():
            with open(found[0] / "METADATA", encoding="utf-8") as fh:
                for line in fh:
                    if line.startswith("Version:"):
                        return line.split(":", 1)[1].strip()
                    if not line.strip():    # the headers end at the first blank line
                        break
    from importlib.metadata import version
    return version(name)


def _file_schema(part: Spectra, meta: Mapping):
    """The Arrow schema of the spectra file, with ``meta`` as JSON under its key, its
    per-trial records (``estimators``) under a key of their own."""
    import json

    import pyarrow as pa
    if len(part) == 0:     # no response: the schema pandas gives an empty table
        schema = pa.Schema.from_pandas(part.to_frame(), preserve_index=False)
        kv = dict(schema.metadata or {})
    else:
        schema = pa.schema([(c, getattr(pa, _ARROW_TYPES.get(c, "float64"))())
                            for c in SPECTRA_COLUMNS])
        kv = {b"pandas": _pandas_metadata()}
    meta = dict(meta)
    records = meta.pop("estimators", None)
    kv[SPECTRA_META_KEY] = json.dumps(meta, default=json_default).encode()
    if records is not None:
        kv[SPECTRA_ESTIMATORS_KEY] = pack_records(
            json.dumps(records, default=json_default).encode())
    return schema.with_metadata(kv)


def _arrow_table(part: Spectra, schema):
    """The rows of ``part`` as the Arrow table of the file's long table
    (:meth:`Spectra.to_frame`; NaN numbers are nulls, as ``Table.from_pandas`` makes
    them), made without pandas."""
    import pyarrow as pa
    if len(part) == 0:
        return pa.Table.from_pandas(part.to_frame(), schema=schema, preserve_index=False)
    present = part.present
    sizes = present.sum(axis=1)
    arrays = []
    for c in SPECTRA_COLUMNS:
        kind = _ARROW_TYPES.get(c, "float64")
        if c in part.keys:      # one value per response, repeated over its rows
            keys = list(part.keys[c])
            if c == "run":
                keys = [None if v is None or v != v else int(v) for v in keys]
            arrays.append(arrow_array(keys, kind, repeats=sizes))
            continue
        if c == "freq_hz":
            col = np.broadcast_to(part.freq_hz, present.shape)[present]
        elif c in ("re", "im"):
            col = getattr(part.h, "real" if c == "re" else "imag")[present]
        elif c == "flags":
            col = part.flags[present]
        else:
            col = part.values[c][present]
        arrays.append(arrow_array(col, kind))
    return pa.Table.from_arrays(arrays, schema=schema)


def row_counts(parts: Iterable[Spectra]) -> dict[str, object]:
    """Count the rows of a spectra file made of ``parts``.

    A row is one response at one frequency (a row of the long table).

    Parameters
    ----------
    parts : iterable of Spectra
        The file's rows, in order.

    Returns
    -------
    dict
        ``rows`` (all), ``levels`` (rows per level, most first) and
        ``flagged_trial_rows`` (trial rows carrying each flag of
        :data:`armfit.io.schema.COUNTED_FLAGS`), as ``armfit estimate --json`` reports
        them.
    """
    levels: dict[str, int] = {}
    flags = dict.fromkeys(COUNTED_FLAGS, 0)
    for part in parts:
        level = part.key("level")
        sizes = part.present.sum(axis=1)
        for k in dict.fromkeys(level):
            levels[k] = levels.get(k, 0) + int(sizes[level == k].sum())
        trial = level == "trial"
        point_flags = part.flags[trial][part.present[trial]]
        for f in COUNTED_FLAGS:
            flags[f] += int(sum(f in v for v in point_flags))
    return {"rows": sum(levels.values()),
            "levels": dict(sorted(levels.items(), key=lambda kv: -kv[1])),
            "flagged_trial_rows": flags}


def _stack_blocks(blocks: list[dict[str, object]], meta: Mapping | None = None) -> Spectra:
    """A Spectra from per-response blocks on one grid (see :func:`_block`)."""
    if not blocks:
        empty = np.zeros((0, 0))
        return Spectra(np.zeros(0), {k: np.zeros(0, object) for k in (*SPECTRA_KEYS, "n")},
                       empty.astype(complex), {c: empty for c in SPECTRA_VALUES},
                       empty.astype(object), empty.astype(bool), dict(meta or {}))
    freq = blocks[0]["freq_hz"]
    keys = {k: np.array([b[k] for b in blocks] + [None], dtype=object)[:-1]
            for k in (*SPECTRA_KEYS, "n")}
    h = np.empty((len(blocks), np.size(freq)), complex)
    h.real[:] = np.array([b["re"] for b in blocks])
    h.imag[:] = np.array([b["im"] for b in blocks])
    values = {c: np.array([b[c] for b in blocks], dtype=float) for c in SPECTRA_VALUES}
    flags = np.array([list(b["flags"]) for b in blocks], dtype=object)
    return Spectra(np.asarray(freq, float), keys, h, values, flags,
                   np.ones(h.shape, bool), dict(meta or {}))


# ---------------------------------------------------------------------------
# A study: read trials (in worker processes if asked), estimate, tabulate
# ---------------------------------------------------------------------------

class SpooledTrials(Sequence):
    """The trials' responses of a study (:class:`TrialResponses`, in order), all but the
    first few hundred held in an unnamed temporary file rather than in memory: a
    sequence whose items are read back one at a time, when asked for.

    What a study's estimate keeps grows with its trials (about 24 kB a trial, five
    responses on a 100-point grid); the spectra file and the aggregates take the trials
    one (or one group) at a time, so memory stays flat in the number of trials. The
    first :data:`HELD_TRIALS` trials are held as they are (about 6 MB at most: a
    paper-size study's trials are neither pickled nor read back); the others go to the
    file, which lies in the folder of :func:`tempfile.gettempdir` (``TMPDIR``); the
    system removes it when the sequence is let go or the process ends, also when it is
    killed. Each of those is stored pickled: what is read back is the trial appended,
    bit for bit. Safe to read from several threads at once. Pickled, it becomes a tuple.
    """

    #: Trials held in memory before the rest go to the temporary file.
    HELD_TRIALS = 256

    def __init__(self):
        self._file = None
        # a held trial, or the (start, size) of a pickled one in the file
        self._spans: list[TrialResponses | tuple[int, int]] = []
        self._outlines: list[tuple[str, tuple[tuple[str, str], ...]]] = []
        # each distinct outline held once: the trials of a study share a few (4,050
        # trials held 28,000 tuples, 1.7 MB, otherwise)
        self._distinct: dict = {}
        self._end = 0
        self._lock = threading.Lock()

    def append(self, trial: TrialResponses) -> None:
        """Store one more trial at the end.

        Raises
        ------
        armfit.errors.OutputError
            The temporary file cannot be made or written (the folder and the system's
            reason named).
        """
        outline = _outline(trial)
        outline = self._distinct.setdefault(outline, outline)
        if len(self._spans) < self.HELD_TRIALS:
            with self._lock:
                self._spans.append(trial)
                self._outlines.append(outline)
            return
        data = pickle.dumps(trial, protocol=pickle.HIGHEST_PROTOCOL)
        with self._lock:
            try:
                if self._file is None:
                    self._file = tempfile.TemporaryFile(prefix="armfit-trials-")
                self._file.seek(self._end)
                self._file.write(data)
            except OSError as exc:
                raise OutputError(
                    f"cannot keep the trials' responses in a temporary file in "
                    f"{tempfile.gettempdir()}: {exc.strerror or exc}; set TMPDIR to a "
                    "folder with room") from None
            self._spans.append((self._end, len(data)))
            self._end += len(data)
            self._outlines.append(outline)

    def outlines(self) -> list[tuple[str, tuple[tuple[str, str], ...]]]:
        """Each trial's axis and the (kind, out_axis) of its responses, in order, without
        reading a trial back."""
        return list(self._outlines)

    def __len__(self) -> int:
        return len(self._spans)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        span = self._spans[index]
        if isinstance(span, TrialResponses):     # one of the trials held
            return span
        start, size = span
        with self._lock:
            self._file.flush()
            self._file.seek(start)
            data = self._file.read(size)
        return pickle.loads(data)

    def __iter__(self) -> Iterator[TrialResponses]:
        for i in range(len(self)):
            yield self[i]

    def __reduce__(self):
        return (tuple, (tuple(self),))

    def __repr__(self) -> str:
        return f"SpooledTrials({len(self)} trial(s))"


@dataclass(frozen=True)
class StudySpectra:
    """Result of :func:`estimate_study`: the trials kept (their responses), what was left
    out (``skipped``: (file, reason)), the files found that are not trials, the common
    sampling rate (Hz), data warnings and the metadata of the spectra file.

    ``trials`` is a sequence of :class:`TrialResponses`: estimated from files
    (:func:`estimate_study`, :class:`EstimateAlongside`) a :class:`SpooledTrials`, whose
    trials wait in a temporary file and are read back one at a time. :attr:`spectra`
    (every response and the aggregates, :func:`spectra_table`) is made when first asked
    for; :meth:`write` writes the same file without making it whole, a row group at a
    time, and the aggregates take one group of responses at a time, so writing a large
    study's file takes about the same memory as a small one's.
    """

    trials: Sequence[TrialResponses]
    skipped: tuple[tuple[str, str], ...]
    ignored: tuple[str, ...]
    fs: float | None
    warnings: tuple[str, ...]
    meta: Mapping[str, object] = field(default_factory=dict)

    @functools.cached_property
    def spectra(self) -> Spectra:
        """The study's :class:`Spectra` (:func:`spectra_table`), with :attr:`meta`."""
        return _stack_blocks([*_trial_blocks(self.trials), *self._aggregates()], self.meta)

    @functools.cached_property
    def table(self) -> pd.DataFrame:
        """The long table of the spectra file (:meth:`Spectra.to_frame`)."""
        return self.spectra.to_frame()

    def _aggregates(self, kinds: Sequence[str] | None = None) -> list[dict[str, object]]:
        """The aggregate blocks of ``kinds`` (None: all), in the file's order; each group
        made once, at its first call, and kept (:attr:`_made`)."""
        return _aggregate_blocks(self.trials, kinds, made=self._made)

    @functools.cached_property
    def _made(self) -> dict[tuple, list[dict[str, object]]]:
        """The aggregate groups made so far (:func:`_aggregate_blocks`)."""
        return {}

    def parts(self, rows: int | None = None):
        """The rows of :attr:`spectra` in order, ``rows`` (default :data:`WRITE_ROWS`)
        responses at a time, each a :class:`Spectra` (made as they are consumed unless
        :attr:`spectra` exists)."""
        rows = rows or WRITE_ROWS
        if "spectra" in self.__dict__:
            yield from self.spectra.parts(rows)
            return
        blocks = itertools.chain(_trial_blocks(self.trials), self._aggregates())
        while chunk := list(itertools.islice(blocks, rows)):
            yield _stack_blocks(chunk, self.meta)

    def aggregates(self, kinds: Sequence[str] | None = None) -> Spectra:
        """The aggregate rows of the spectra file (levels mean and median), with
        :attr:`meta`, made without the trial rows.

        Parameters
        ----------
        kinds : sequence of str, optional
            Only the responses of these kinds (e.g. ``("measured",)``, what the fits of
            Tables I and II use); default all. The rows made here are not made again by
            a later call or by :meth:`write`.

        Returns
        -------
        Spectra
            What ``Spectra.read(path, level=("mean", "median"), kind=kinds)`` reads back
            from the file :meth:`write` writes: the same rows in the same order, bit for
            bit.
        """
        return _stack_blocks(self._aggregates(kinds), self.meta)

    def write(self, path, *, overwrite: bool = False):
        """Write the spectra file without making the whole :attr:`spectra`.

        The bytes are those of ``self.spectra.write(path)`` (:meth:`Spectra.write`); the
        rows of each row group are made just before it is written (:meth:`parts`).

        Parameters
        ----------
        path : str or os.PathLike
            Destination, written atomically.
        overwrite : bool
            Replace an existing file.

        Returns
        -------
        str or os.PathLike
            ``path``.
        """
        return write_parts(self.parts(), self.meta, path, overwrite=overwrite)

    def counts(self) -> dict[str, object]:
        """The file's rows, rows per level and flagged trial rows.

        Returns
        -------
        dict
            See :func:`row_counts`; computed part by part, like :meth:`write`.
        """
        return row_counts(self.parts())


def _estimate_source(source, config: EstimateConfig):
    """Worker: read one trial and estimate it. Returns ("ok", TrialResponses, fs, warnings)
    or ("bad", label, message, reason) for a BadInputError."""
    return _estimate_read(source.label, _read_source(source, config), config)


def _read_source(source, config: EstimateConfig):
    """The reading half of :func:`_estimate_source`: ("read", Trial, warnings, drift
    flags) or its ("bad", ...) result. The drift flags (:func:`drift_flags`) are found
    here, and the Hamming window of the trial's derived spectra (its length follows the
    record's, :func:`derived_spectra`) is made and cached (:func:`_derived_segments`): they
    need the samples' number or the samples only, and in a serial estimate this half
    runs in the reading thread while the trial before is estimated."""
    warnings: list[str] = []
    try:
        trial = read_trial(source, f_min_hz=config.fmin, force_limit_N=config.force_limit_N,
                           warn=warnings.append, grip=False)  # estimate needs no grip
    except BadInputError as exc:
        return ("bad", source.label, exc.template, exc.detail)
    drift = drift_flags(trial.pos, trial.meta.fs, config)
    if trial.force.shape[0] > 2:    # the derived spectra's window, made here (see above)
        _derived_segments(trial.force.shape[0] - 2, config.derived_segments)
    return ("read", trial, warnings, drift)


def drift_flags(pos: np.ndarray, fs: float, config: EstimateConfig) -> dict[int, bool]:
    """:func:`drifting` of each recorded (finite) position column of ``pos`` (n, 3), m,
    by column index, with ``config``'s lowest frequency and drift factor."""
    return {j: drifting(pos[:, j], fs, config.fmin, config.drift_factor)
            for j in range(pos.shape[1]) if np.all(np.isfinite(pos[:, j]))}


def _estimate_read(label: str, read, config: EstimateConfig):
    """The estimating half of :func:`_estimate_source`, from :func:`_read_source`'s
    ``read`` of the trial ``label`` names (its source's label, in messages)."""
    if read[0] == "bad":
        return read
    _, trial, warnings, drift = read
    try:
        m = trial.meta
        responses, check = estimate_trial_checked(trial.force, trial.pos, m.fs, m.axis,
                                                  config, source=label,
                                                  ref=trial.ref, reference=m.reference,
                                                  drift=drift)
        warnings += no_signal_messages(label, m.axis, responses)
        said = check.message(label, config.grid(), m.axis)
        if said is not None:
            warnings.append(said)
    except BadInputError as exc:
        return ("bad", label, exc.template, exc.detail)
    tr = TrialResponses(m.subject, m.axis, m.grip_N, m.run, label, config.grid(),
                        responses, check)
    return ("ok", tr, m.fs, tuple(warnings))


def _estimate_serially(sources, config: EstimateConfig) -> Iterator:
    """:func:`_estimate_source` of each source in this process, in order, each trial read
    (:func:`armfit.workers.read_ahead`) while the one before is estimated."""
    reads = read_ahead(functools.partial(_read_source, config=config), sources)
    try:
        for source, read in zip(sources, reads, strict=True):
            yield _estimate_read(source.label, read, config)
    finally:
        reads.close()


def estimate_study(inputs, config: EstimateConfig, *, manifest=None, skip_bad: bool = False,
                   jobs: int = 1, on_open=None, advance=None, warn=None,
                   executor=None, column_map=None, note=None) -> StudySpectra:
    """Estimate every trial of ``inputs`` (raw files, folders or a canonical dataset).

    Trials are found by :func:`armfit.io.trials.open_trials`, read and validated one by
    one by :func:`armfit.io.trials.read_trial` (on
    ``executor``, a :class:`concurrent.futures.Executor`, when given, else in ``jobs``
    worker processes when > 1, see :mod:`armfit.workers`; each task reads its trial file
    itself; results keep the input order), must share one sampling rate, and are
    checked for duplicates among the trials estimated. Without
    ``skip_bad`` the first bad trial raises BadInputError; with it, bad trials are listed
    in ``skipped``. ``warn(msg)`` receives saturation warnings,
    ``on_open(n)`` is told the number of trials found, ``advance()`` is called once per
    trial. ``column_map`` (a map file) is the column map of every raw file without one of
    its own in the manifest; ``note(msg)`` receives the conversions of each map, once
    (:func:`armfit.io.trials.open_trials`). When no trial is left, NoInputError, whose
    ``skipped`` lists the trials left out, each with its reason.
    """
    stream = open_trials(inputs, manifest=manifest, skip_bad=skip_bad, f_min_hz=config.fmin,
                         force_limit_N=config.force_limit_N, column_map=column_map,
                         note=note)
    kept = _Kept(stream, config, skip_bad=skip_bad, warn=warn)
    kept.skipped.extend((s.file, s.reason) for s in stream.skipped)
    sources = list(stream.sources)
    if on_open is not None:
        on_open(len(sources))
    if executor is None and jobs <= 1:   # here: the next trial is read meanwhile
        tasks = _estimate_serially(sources, config)
    else:
        tasks = iter_tasks(functools.partial(_estimate_source, config=config), sources, jobs,
                           preload=POOL_PRELOAD["estimate"], chunksize=2, executor=executor)
    # closed on a bad trial: the pending work is cancelled at once
    with contextlib.closing(tasks) as results:
        for res in results:
            kept.handle(res)
            if advance is not None:
                advance()
    return kept.result()


class _Kept:
    """The trials of a study estimated so far, handled in input order (:meth:`handle`):
    the responses kept, the trials skipped with their reasons, the data warnings, and
    the common sampling rate. ``admit``: also check each trial for a duplicate among
    those kept (:meth:`TrialStream.admit`; False when the reader of ``stream`` did)."""

    def __init__(self, stream: TrialStream, config: EstimateConfig, *, skip_bad: bool,
                 warn=None, admit: bool = True):
        self.stream, self.config, self.skip_bad = stream, config, skip_bad
        self.warn, self.admit = warn, admit
        self.skipped: list[tuple[str, str]] = []
        self.kept = SpooledTrials()
        self.warnings: list[str] = []
        self.ref: tuple[float, str] | None = None

    def handle(self, res) -> None:
        """Take one trial's result (of :func:`_estimate_read`): kept, or skipped with
        ``skip_bad`` (else BadInputError) when it is bad, of another sampling rate than
        the first kept, or a duplicate."""
        if res[0] == "bad":
            _, label, text, reason = res
            if not self.skip_bad:
                raise BadInputError(text)
            self.skipped.append((label, reason))
            return
        _, tr, fs, warns = res
        for w in warns:
            self.warnings.append(w)
            if self.warn is not None:
                self.warn(w)
        if self.ref is None:
            self.ref = (fs, tr.source)
        elif abs(fs - self.ref[0]) > 1e-6 * self.ref[0]:
            text = (f"{tr.source}, column 'time_s': sampling rate {fs:g} Hz differs from "
                    f"{self.ref[0]:g} Hz of {self.ref[1]}; estimate trials of one rate at a "
                    "time or resample them with `armfit ingest --resample`")
            if not self.skip_bad:
                raise BadInputError(text)
            self.skipped.append((tr.source, text.split(": ", 1)[1]))
            return
        if self.admit:
            try:    # a duplicate of a trial estimated before (not of one that was bad)
                self.stream.admit((tr.subject, tr.axis, tr.grip_N, tr.run), tr.source)
            except BadInputError as exc:
                if not self.skip_bad:
                    raise
                self.skipped.append((tr.source, exc.detail))
                return
        self.kept.append(tr)

    def result(self) -> StudySpectra:
        """The study's spectra; NoInputError, listing the trials skipped, when none is
        kept."""
        skipped = self.skipped
        if not self.kept:
            err = NoInputError("no trial could be estimated"
                               + (f" ({len(skipped)} skipped)" if skipped else ""))
            err.skipped = tuple(skipped)
            raise err
        fs = self.ref[0] if self.ref else None
        return StudySpectra(self.kept, tuple(skipped),
                            tuple(str(p) for p in self.stream.ignored), fs,
                            tuple(self.warnings),
                            study_metadata(self.config, fs, len(self.kept), skipped,
                                           self.kept))


#: Bytes of trial samples :class:`EstimateAlongside` holds, read ahead, while its pool's
#: workers start (44 trials of 60 s at 1 kHz).
READ_AHEAD_BYTES = 64 << 20


class EstimateAlongside:
    """Estimate the trials another reader reads, as it reads them: the reader (e.g.
    :func:`armfit.io.trials.ingest`, ``on_trial``) validates each trial once and hands
    it over (:meth:`add`), and its estimate runs meanwhile on ``executor`` (without one,
    here, at once), so that no trial file is read twice. At most ``2 × jobs`` trials are
    in flight: the reader waits for the oldest beyond that (its samples are held until
    sent). The results are taken in input order as they come, with the trials the
    reader's ``stream`` skipped in their places, as :func:`estimate_study` of the same
    inputs takes them (its sampling-rate check included; duplicates are the reader's to
    refuse); a bad trial's error (without ``skip_bad``) is raised by :meth:`result`,
    after the reader's own.

    On armfit's own process pool whose workers have not started, they start at once in
    a thread (:func:`armfit.workers.start_workers`) and the reader goes on meanwhile: the
    trials it reads are held, up to :data:`READ_AHEAD_BYTES` of samples (beyond that,
    the oldest is estimated here), and handed over once the workers are up, the oldest
    first, as many as are in flight otherwise; the reader then waits only while it holds
    more than it held when they came up. (The fork server of ``armfit run`` with figures
    imports matplotlib and pandas before it forks a worker: the run's process waited
    about 0.6 s at its first trial.) Where a trial is estimated never changes its
    result.

    The reader's read warnings are its own; the result's ``warnings`` hold the
    estimates'. On armfit's own process pool, a trial's samples reach the worker through
    a shared-memory block of this process rather than the pool's pipe
    (:class:`armfit._shared.Blocks`; `armfit run -j2` of 810 trials took 0.93 times as
    long); the values are the same.
    """

    def __init__(self, stream: TrialStream, config: EstimateConfig, *,
                 skip_bad: bool = False, jobs: int = 1, executor: Executor | None = None):
        self.config = config
        self.kept = _Kept(stream, config, skip_bad=skip_bad, admit=False)
        self.executor = executor
        self.blocks = _shared.for_executor(executor)
        self.window = 2 * max(1, jobs)
        # in input order, not yet taken: a Future, a result, or a skip of the reader's
        self.order: collections.deque = collections.deque()
        self.pending: collections.deque[Future] = collections.deque()
        # the trials read and not handed over yet, in order: (label, trial, its place in
        # ``order``: a Future given the outcome of the task it becomes)
        self.held: collections.deque = collections.deque()
        self.held_bytes = 0
        self.starting = start_workers(executor)
        # what the reader may hold: the read-ahead while the workers start, then no more
        # than it held when they came up, never more again
        self.cap = READ_AHEAD_BYTES if self.starting is not None else 0
        self.skips_seen = 0
        self.failed: Exception | None = None

    def _skips(self) -> None:
        skipped = self.kept.stream.skipped
        for s in skipped[self.skips_seen:]:
            self.order.append(("skip", s.file, s.reason))
        self.skips_seen = len(skipped)

    def _take(self, wait: bool) -> None:
        """Take the results at the head of :attr:`order` (``wait``: all, waiting for
        each), until one fails: its error is kept for :meth:`result`."""
        while self.order and self.failed is None:
            item = self.order[0]
            if isinstance(item, Future) and not (wait or item.done()):
                return
            self.order.popleft()
            try:
                if isinstance(item, Future):
                    item = item.result()
                if item[0] == "skip":
                    self.kept.skipped.append(item[1:])
                else:
                    self.kept.handle(item)
            except Exception as exc:
                self.failed = exc

    def _workers_starting(self) -> bool:
        if self.starting is not None and not self.starting.is_alive():
            self.starting = None
        return self.starting is not None

    def _hand_over(self) -> None:
        """Hand the held trials to the workers, the oldest first, up to :attr:`window` in
        flight (none while the workers start)."""
        if self._workers_starting():
            return
        while self.pending and self.pending[0].done():   # its outcome reaches its place
            self.pending.popleft()
        while self.held and len(self.pending) < self.window:
            label, trial, place = self.held.popleft()
            self.held_bytes -= _samples_bytes(trial)
            task = (label, trial)
            put = None if self.blocks is None else self.blocks.put(
                [trial.force, trial.pos, *([] if trial.ref is None else [trial.ref])])
            if put is not None:     # else no room in the shared memory: through the pipe
                task = (label, trial.meta, put[0])
            fut = self.executor.submit(_estimate_given, task, self.config)
            if put is not None:
                fut.add_done_callback(lambda _, block=put[1]: self.blocks.release(block))
            fut.add_done_callback(lambda f, place=place: _settle(place, f))
            self.pending.append(fut)

    def _make_room(self) -> None:
        """While the workers start, estimate the oldest trial held here; once they are
        up, wait for the oldest trial in flight."""
        if not self._workers_starting():
            self.pending.popleft().exception()   # waits; its outcome is taken in order
            return
        label, trial, place = self.held.popleft()
        self.held_bytes -= _samples_bytes(trial)
        try:
            place.set_result(_estimate_given((label, trial), self.config))
        except Exception as exc:    # taken in order, as a worker's would be
            place.set_exception(exc)

    def add(self, source, trial: Trial) -> None:
        """Estimate ``trial`` (read from ``source``, a :class:`TrialSource`) once the
        trials the reader skipped before it are placed."""
        self._skips()
        if self.failed is not None:     # the result is that error: nothing more to do
            return
        trial = replace(trial, grip=None)   # the estimate needs no grip
        if self.executor is None:
            self.order.append(_estimate_given((source.label, trial), self.config))
        else:
            place: Future = Future()
            self.order.append(place)
            self.held.append((source.label, trial, place))
            self.held_bytes += _samples_bytes(trial)
            while True:
                self._hand_over()
                if self.held_bytes <= self.cap:
                    if not self._workers_starting():
                        self.cap = self.held_bytes
                    break
                self._make_room()
        self._take(wait=False)

    def result(self) -> StudySpectra:
        """The study's spectra (:func:`estimate_study`'s :class:`StudySpectra`), once every
        trial is estimated; the first bad trial's BadInputError without ``skip_bad``."""
        try:
            self._skips()
            while self.held and self.failed is None:
                self._hand_over()
                if self.held:
                    self._make_room()
            self._take(wait=True)
            if self.failed is not None:
                raise self.failed
            return self.kept.result()
        finally:
            self.close()

    def close(self) -> None:
        """Cancel the estimates not started (after a failure) and remove the
        shared-memory blocks."""
        for fut in self.pending:
            fut.cancel()
        self.pending.clear()
        self.held.clear()
        self.held_bytes = 0
        self.order.clear()
        if self.blocks is not None:
            self.blocks.close()


def _samples_bytes(trial: Trial) -> int:
    """The bytes of a trial's samples (force, position and reference)."""
    return trial.force.nbytes + trial.pos.nbytes + (0 if trial.ref is None
                                                    else trial.ref.nbytes)


def _settle(place: Future, fut: Future) -> None:
    """Give ``place`` the outcome of ``fut``."""
    if fut.cancelled():
        place.cancel()
    elif fut.exception() is not None:
        place.set_exception(fut.exception())
    else:
        place.set_result(fut.result())


def _estimate_given(task, config: EstimateConfig):
    """Worker: estimate a trial read and validated by another reader (``task``: its
    label and :class:`Trial`, or its label, :class:`TrialMeta` and its force, position
    and reference samples in shared memory, :class:`armfit._shared.Shared`);
    :func:`_estimate_source`'s result."""
    if len(task) == 3:
        label, meta, shared = task
        force, pos, *ref = shared.take()
        trial = Trial(meta, force, pos, ref=ref[0] if ref else None)
    else:
        label, trial = task
    read = ("read", trial, [], drift_flags(trial.pos, trial.meta.fs, config))
    return _estimate_read(label, read, config)


def estimate_trials(trials: Sequence[Trial], config: EstimateConfig) -> StudySpectra:
    """Estimate trials already in memory (see :func:`estimate_study` for files).

    Parameters
    ----------
    trials : sequence of armfit.io.trials.Trial
        Trials of one sampling rate (e.g. from :func:`armfit.read_trials` or
        :func:`armfit.simulation.simulate_trial`).
    config : EstimateConfig
        Estimator options.

    Returns
    -------
    StudySpectra

    Raises
    ------
    NoInputError
        ``trials`` is empty.
    BadInputError
        The trials' sampling rates differ, or a trial is too short for the grid.
    """
    kept: list[TrialResponses] = []
    messages: list[str] = []
    fs = None
    for trial in trials:
        m = trial.meta
        if fs is None:
            fs = m.fs
        elif abs(m.fs - fs) > 1e-6 * fs:
            raise BadInputError(f"sampling rate {m.fs:g} Hz differs from {fs:g} Hz of the "
                                "first trial; estimate trials of one rate at a time",
                                file=m.source, column="time_s")
        responses, check = estimate_trial_checked(trial.force, trial.pos, m.fs, m.axis,
                                                  config, source=m.source, ref=trial.ref,
                                                  reference=m.reference)
        kept.append(TrialResponses(m.subject, m.axis, m.grip_N, m.run, m.source,
                                   config.grid(), responses, check))
        said = check.message(m.source, config.grid(), m.axis)
        if said is not None:
            messages.append(said)
    if not kept:
        raise NoInputError("no trial to estimate")
    return StudySpectra(tuple(kept), (), (), fs, tuple(messages),
                        study_metadata(config, fs, len(kept), [], kept))


def estimator_summary(trials: Sequence[TrialResponses]) -> dict[str, object]:
    """What the estimators say of a study's trials (``armfit estimate --json``).

    Parameters
    ----------
    trials : sequence of TrialResponses

    Returns
    -------
    dict
        ``reference_trials`` (estimated through their reference column),
        ``feedback_trials`` (the force responds to the position: the feedback test
        fires), ``not_excitation_trials`` (with points flagged ``not_excitation``) and
        ``messages`` (one line per such trial, as on stderr).
    """
    counts = {"reference_trials": 0, "feedback_trials": 0, "not_excitation_trials": 0}
    messages = []
    for t in trials:        # one trial at a time (a SpooledTrials reads each back)
        c = t.check
        if c is None:
            continue
        counts["reference_trials"] += c.reference is not None
        counts["feedback_trials"] += bool(c.feedback is not None and c.feedback.fires)
        counts["not_excitation_trials"] += bool(c.flagged.any())
        if (m := c.message(t.source, t.freq_hz, t.axis)) is not None:
            messages.append(m)
    return {**counts, "messages": messages}


def study_metadata(config: EstimateConfig, fs: float | None, n_trials: int,
                   skipped: Sequence[tuple[str, str]],
                   trials: Sequence[TrialResponses] = ()) -> dict:
    """The metadata a spectra file carries (JSON in its Parquet key-value metadata): the
    armfit version, the estimator and its options, the grid, Mp, the sampling rate ``fs``
    (Hz), the number of trials, what was skipped and, per trial of ``trials``, what the
    estimators say of it (``estimators``: :meth:`EstimatorCheck.record` with the trial's
    identity, subject, axis, grip_N and run, as its rows have it: no path, so that the
    file does not depend on where the trials lie)."""
    grid = config.grid()
    return {
        "armfit_version": __version__,
        "method": config.method,
        "derived_method": "tfestimate",
        "options": {"fmin_hz": config.fmin, "fmax_hz": config.fmax,
                    "per_decade": config.per_decade, "nperseg": config.nperseg,
                    "overlap": config.overlap, "window": config.window,
                    "derived_segments": config.derived_segments,
                    "coherence_min": config.coherence_min,
                    "force_limit_N": config.force_limit_N, "min_avg": config.min_avg,
                    "drift_factor": config.drift_factor, "reference": config.reference},
        "grid_hz": config.grid().tolist(),
        "mp_kg": dict(config.mp),
        "fs_hz": fs,
        "trials": n_trials,
        "skipped": [{"file": f, "reason": r} for f, r in skipped],
        "aggregation": "mean and median of 20 log10|H| and of the phase (each trial within "
                       "pi of the trials' circular mean)",
        "estimators": [{"subject": t.subject, "axis": t.axis, "grip_N": t.grip_N,
                        "run": t.run, **t.check.record(grid)}
                       for t in trials if t.check is not None],
    }


__all__ = [
    "METHODS", "MEDIAN_SE_FACTOR", "BinSpectra", "welch_overlap_factor", "enbw_bins",
    "welch_spectra", "frf_h1", "chebwin_spectra", "frf_chebwin", "tfestimate_segment",
    "derived_arm_signals", "derived_spectra", "log_grid", "GridResponse", "band_bins",
    "bendat_piersol_se", "debiased_coherence", "NEGLIGIBLE_FORCE_POWER", "usable_bins",
    "to_grid", "h2_to_grid", "reference_to_grid", "NOT_EXCITATION", "BIAS_Z",
    "REFERENCE_COHERENCE", "EstimatorCheck", "check_estimators", "estimate_trial_checked",
    "saturated", "moving_mean", "drifting", "EstimateConfig", "Response", "TrialResponses",
    "check_band", "estimate_trial", "NO_SIGNAL", "no_signal_messages", "aggregate",
    "aggregate_spread", "spectra_table", "WRITE_ROWS", "Spectra", "write_parts",
    "row_counts", "SpooledTrials", "StudySpectra", "estimate_study", "EstimateAlongside",
    "estimate_trials",
    "study_metadata", "estimator_summary",
]
