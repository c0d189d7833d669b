"""Variability model: W_max and the multiplicative uncertainty weight Wu (Fu & Çavuşoğlu
2010, eqs. 6–7).

Conventions: frequencies ``f_hz`` in Hz; Wu's zeros, poles and the Laplace variable
``s = j 2π f`` in rad/s (the paper's Table III is read in rad/s: docs/methods.md, "Choices
where the paper is ambiguous"); magnitudes of
W_max and Wu are dimensionless (a relative error: 0 dB = 100 %).

The pieces:

* :func:`w_max` — W_max(ω) = max over trials |H_exp_ARM / H_ARM − 1| (eq. 6), with
  optional fractional-octave smoothing of each trial's relative error first.
* :func:`fit_wu` — Wu(s) = K Π(s − z_i) / Π(s − p_i) (eq. 7) as conjugate pairs, stable
  and minimum phase by construction, either the paper's dB least squares (``cost="paper"``)
  or a fit that guarantees |Wu| ≥ W_max on and between the grid points while staying as
  tight as it can (``cost="envelope"``, the default).
* :func:`check_envelope` — coverage and tightness of any weight against a W_max.
* :func:`nominal_arm_response`, :func:`derived_trials`, :func:`arm_trials`,
  :func:`fit_weights` — from a spectra table and a nominal-parameters table to the
  per-axis results (no file I/O); the nominal row's apparatus effects are removed from
  the trials' derived dynamics first (:func:`arm_trials`).

Parametrisation of Wu. Every zero or pole row is a conjugate pair r, r̄ with
r = −ω_n (cos φ ± j sin φ), i.e. the section s² + 2ζω_n s + ω_n² with ζ = cos φ, searched as
a = ln ω_n and φ ∈ [0, arccos ζ_min]. The real part −ω_n cos φ is therefore strictly
negative for every value the optimiser can reach: poles stable, zeros minimum phase. φ = 0
is a double real root. The numbers of zero and pole pairs are equal (N_n = N_d, biproper:
|Wu| tends to a constant above the band, so N_n ≥ N_d holds and Wu is proper).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Mapping, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from armfit import _slsqp, _trf
from armfit._order import median
from armfit.constants import AXES, axis_band
from armfit.data import paper_file
from armfit.errors import BadInputError, ConvergenceError, UsageError, cell
from armfit.io.artifacts import read_wu_rows
from armfit.io.numbers import parse_number, parse_numbers
from armfit.io.ranges import FREQUENCY_RANGE, check_in_range
from armfit.io.schema import WU_POINTS_COLUMNS, WU_SUMMARY_COLUMNS, wu_sidecar_paths
from armfit.models.params import model_from_params
from armfit.spectra import Spectra
from armfit.workers import POOL_PRELOAD, executor_for

#: The paper's band for Wu: 0.01–30 Hz (Sec. II-F).
PAPER_BAND_HZ: tuple[float, float] = (0.01, 30.0)
#: Names that stand for the paper's Table III (uncertainty weights).
PAPER_WEIGHTS: tuple[str, ...] = ("paper", "table3")

#: At most five zero pairs and five pole pairs (paper, Sec. II-F).
MAX_PAIRS = 5

#: Smallest damping ratio a fitted pair may have (keeps peaks resolvable on the grid).
ZETA_MIN = 0.01

#: Step (dB) of the W_max the envelope fit's shape search sees (its reduced points; see
#: :func:`fit_wu`). The search is a multi-start local optimisation whose end can jump
#: between near-equal optima when its data change by rounding (1e-9 relative); on that
#: step the data it sees do not change unless W_max moves by about 1e-7 relative or
#: more, so the weight is a reproducible function of the measurements. 0.01 dB is far
#: below W_max's own scatter; the gain and every check use the W_max not rounded.
#: (``benchmarks/validate_wu_rounding.py`` measures both; 0 turns the steps off.)
SEARCH_STEP_DB = 0.01

_DB = 10.0 / np.log(10.0)  # d(10 log10 Q) = _DB dQ/Q
_PHI_MAX = float(np.arccos(ZETA_MIN))


# ---------------------------------------------------------------------------
# The weight and its frequency response
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class WuWeight:
    """Wu(s) = K Π(s − z_i) / Π(s − p_i) — Fu & Çavuşoğlu 2010, eq. 7.

    ``zeros`` and ``poles`` (complex, rad/s) hold one representative per conjugate pair
    (imaginary part ≥ 0); each stands for the two roots r and r̄ (a double real root when
    the imaginary part is 0), exactly like the rows of the paper's Table III.
    """

    gain: float
    zeros: np.ndarray
    poles: np.ndarray

    def __post_init__(self) -> None:
        for name in ("zeros", "poles"):
            arr = np.atleast_1d(np.asarray(getattr(self, name), dtype=complex))
            arr = arr.real + 1j * np.abs(arr.imag)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "gain", float(self.gain))

    @property
    def zero_roots(self) -> np.ndarray:
        """All zeros (each pair expanded to r, r̄), rad/s."""
        return _expand(self.zeros)

    @property
    def pole_roots(self) -> np.ndarray:
        """All poles (each pair expanded to r, r̄), rad/s."""
        return _expand(self.poles)

    @property
    def is_stable(self) -> bool:
        """Every pole in the open left half plane."""
        return bool(np.all(self.pole_roots.real < 0))

    @property
    def is_minimum_phase(self) -> bool:
        """Every zero in the open left half plane."""
        return bool(np.all(self.zero_roots.real < 0))

    def response(self, f_hz) -> np.ndarray:
        """Wu(j2πf), dimensionless — eq. 7 with s in rad/s."""
        return wu_response(f_hz, self.gain, self.zeros, self.poles)

    def magnitude_db(self, f_hz) -> np.ndarray:
        """20 log10 |Wu(j2πf)|, dB."""
        return 20.0 * np.log10(np.abs(self.response(f_hz)))


def read_wu(path) -> dict[str, WuWeight]:
    """Read a Wu CSV (the layout of the paper's Table III) into weights.

    Parameters
    ----------
    path : str or os.PathLike
        The CSV written by ``armfit fit-uncertainty`` (or typed from Table III).

    Returns
    -------
    dict
        {axis: :class:`WuWeight`}, axes in x, y, z order.

    Raises
    ------
    NoInputError, BadInputError
        See :func:`armfit.io.artifacts.read_wu_rows`.
    """
    return {axis: WuWeight(*rows) for axis, rows in read_wu_rows(path).items()}


def _expand(pairs: np.ndarray) -> np.ndarray:
    pairs = np.asarray(pairs, dtype=complex)
    return np.concatenate([pairs, np.conj(pairs)])


def wu_response(f_hz, gain: float, zeros: Sequence[complex], poles: Sequence[complex]
                ) -> np.ndarray:
    """Wu(j2πf) = K Π(s − z)/Π(s − p), s = j2πf in rad/s — eq. 7.

    ``zeros``/``poles``: one representative per conjugate pair (see :class:`WuWeight`).
    """
    s = 2j * np.pi * np.asarray(f_hz, dtype=float)
    out = np.full(s.shape, complex(gain))
    for r in _expand(np.atleast_1d(zeros)):
        out = out * (s - r)
    for r in _expand(np.atleast_1d(poles)):
        out = out / (s - r)
    return out


# ---------------------------------------------------------------------------
# W_max (eq. 6)
# ---------------------------------------------------------------------------

def smooth_fractional_octave(f_hz: np.ndarray, y: np.ndarray, width_oct: float) -> np.ndarray:
    """RMS of ``y`` over a window ``width_oct`` octaves wide centred (geometrically) on each f.

    The window at f spans [f·2^(−width_oct/2), f·2^(+width_oct/2)] (1/3: third-octave
    smoothing); ``y`` may be (n_freq,) or (n_rows, n_freq) (smoothed along the last axis);
    NaNs are ignored. Units of ``y`` are kept.
    """
    if not (np.isfinite(width_oct) and width_oct > 0):
        raise UsageError(f"smoothing width must be > 0 octaves, got {width_oct}")
    f = np.asarray(f_hz, dtype=float)
    y = np.asarray(y, dtype=float)
    half = 2.0 ** (0.5 * width_oct)
    lo = np.searchsorted(f, f / half, side="left")
    hi = np.searchsorted(f, f * half, side="right")
    ok = np.isfinite(y)
    y2 = np.where(ok, y * y, 0.0)
    zero = np.zeros(y.shape[:-1] + (1,))
    c_sum = np.concatenate([zero, np.cumsum(y2, axis=-1)], axis=-1)
    c_cnt = np.concatenate([zero, np.cumsum(ok, axis=-1)], axis=-1)
    cnt = c_cnt[..., hi] - c_cnt[..., lo]
    tot = c_sum[..., hi] - c_sum[..., lo]
    return np.where(cnt > 0, np.sqrt(np.abs(tot) / np.maximum(cnt, 1)), np.nan)


def relative_error(H_derived: np.ndarray, H_nominal: np.ndarray) -> np.ndarray:
    """|H_exp_ARM / H_ARM − 1| per trial and frequency (dimensionless) — right side of eq. 6."""
    H = np.atleast_2d(np.asarray(H_derived, dtype=complex))
    Hn = np.asarray(H_nominal, dtype=complex)
    if H.shape[-1] != Hn.shape[-1]:
        raise UsageError(f"H_derived has {H.shape[-1]} frequencies, H_nominal {Hn.shape[-1]}")
    return np.abs(H / Hn - 1.0)


def w_max(H_derived: np.ndarray, H_nominal: np.ndarray, *, f_hz: np.ndarray | None = None,
          smooth_oct: float | None = None) -> np.ndarray:
    """W_max(ω) = max over trials |H_exp_ARM(jω)/H_ARM(jω) − 1| — Fu & Çavuşoğlu 2010, eq. 6.

    ``H_derived``: (n_trials, n_freq) derived arm dynamics Xa/Fa (m/N); ``H_nominal``:
    (n_freq,) nominal H_ARM (m/N) on the same grid. Returns (n_freq,), dimensionless.
    With ``smooth_oct`` (octaves, e.g. 1/3), each trial's relative error is first
    RMS-smoothed over a window that wide (:func:`smooth_fractional_octave`, needs
    ``f_hz``), which lowers the noise-driven spikes of the raw maximum; without it W_max
    is the raw maximum. Trials missing at a frequency (NaN)
    are skipped there; a frequency with no trial is NaN.
    """
    err = relative_error(H_derived, H_nominal)
    if smooth_oct is not None:
        if f_hz is None:
            raise UsageError("smoothing W_max needs the frequencies f_hz")
        err = smooth_fractional_octave(f_hz, err, smooth_oct)
    with np.errstate(invalid="ignore"):
        allnan = np.all(~np.isfinite(err), axis=0)
        out = np.nanmax(np.where(np.isfinite(err), err, -np.inf), axis=0)
    out[allnan] = np.nan
    return out


# ---------------------------------------------------------------------------
# Envelope check: coverage and tightness
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class EnvelopeCheck:
    """How a weight sits on a W_max over a band.

    coverage_pct: % of the band's grid points with |Wu| ≥ W_max;
    coverage_between_pct: the same on a dense grid between the points (W_max interpolated
    linearly in log f and dB);
    tightness_*_db: statistics over the band's grid points of 20log10|Wu| − 20log10 W_max
    (dB; negative where Wu fails to cover); mean_gap_db: that gap averaged over log
    frequency (the quantity the envelope fit minimises); n_points: grid points in the band.
    """

    coverage_pct: float
    coverage_between_pct: float
    tightness_median_db: float
    tightness_max_db: float
    tightness_min_db: float
    mean_gap_db: float
    n_points: int
    band_hz: tuple[float, float]


def _to_db(w: np.ndarray) -> np.ndarray:
    return 20.0 * np.log10(np.maximum(w, 1e-12))


def _band_points(f_hz, wmax, band) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    f = np.asarray(f_hz, dtype=float)
    w = np.asarray(wmax, dtype=float)
    if f.ndim != 1 or f.shape != w.shape:
        raise UsageError(f"f_hz and wmax must be 1-D of equal length, got {f.shape}, {w.shape}")
    if np.any(np.diff(f) <= 0):
        raise UsageError("f_hz must increase strictly")
    lo, hi = PAPER_BAND_HZ if band is None else band
    if not (0 < lo < hi):
        raise UsageError(f"band must satisfy 0 < lo < hi, got {lo}:{hi}")
    keep = (f >= lo * (1 - 1e-9)) & (f <= hi * (1 + 1e-9)) & np.isfinite(w)
    if keep.sum() < 2:
        raise UsageError(f"fewer than 2 frequencies with data in the band {lo:g}–{hi:g} Hz")
    fb, wb = f[keep], w[keep]
    return fb, wb, (float(fb[0]), float(fb[-1]))


def _dense(f: np.ndarray, wdb: np.ndarray, n_sub: int) -> tuple[np.ndarray, np.ndarray]:
    """Points between grid points (n_sub per interval, log-spaced) with W_max in dB
    interpolated linearly in log f."""
    lf = np.log(f)
    t = np.arange(n_sub + 1) / n_sub
    lfd = (lf[:-1, None] + np.diff(lf)[:, None] * t[None, :-1]).ravel()
    wd = (wdb[:-1, None] + np.diff(wdb)[:, None] * t[None, :-1]).ravel()
    return np.append(np.exp(lfd), f[-1]), np.append(wd, wdb[-1])


def _log_weights(f: np.ndarray) -> np.ndarray:
    """Trapezoid weights in log f, normalised to sum 1 (a mean over log frequency)."""
    lf = np.log(f)
    edges = np.concatenate([[lf[0]], 0.5 * (lf[1:] + lf[:-1]), [lf[-1]]])
    w = np.diff(edges)
    return w / w.sum()


def check_envelope(f_hz, wmax, weight: WuWeight, *, band: tuple[float, float] | None = None,
                   n_sub: int = 8) -> EnvelopeCheck:
    """Coverage and tightness of ``weight`` against ``wmax`` over ``band`` (Hz).

    Coverage on the grid points and on ``n_sub`` log-spaced points per interval between
    them (W_max interpolated log-log, as MATLAB's ``ucover`` promises the bound between
    frequency points). Tightness = 20log10|Wu| − 20log10 W_max at the grid points, dB.
    """
    f, w, b = _band_points(f_hz, wmax, band)
    wdb = _to_db(w)
    gap = weight.magnitude_db(f) - wdb
    fd, wd = _dense(f, wdb, n_sub)
    gapd = weight.magnitude_db(fd) - wd
    tol = 1e-9
    return EnvelopeCheck(
        coverage_pct=float(100.0 * np.mean(gap >= -tol)),
        coverage_between_pct=float(100.0 * np.mean(gapd >= -tol)),
        tightness_median_db=float(median(gap)),
        tightness_max_db=float(np.max(gap)),
        tightness_min_db=float(np.min(gap)),
        mean_gap_db=float(np.sum(_log_weights(f) * gap)),
        n_points=int(f.size),
        band_hz=b,
    )


# ---------------------------------------------------------------------------
# Fitting Wu (eq. 7)
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class WuResult:
    """A fitted weight (eq. 7) and how it sits on the W_max it was fitted to.

    gain: K; zeros, poles: one representative per conjugate pair, rad/s (imag ≥ 0);
    order: number of zero pairs (= number of pole pairs); cost: "envelope" | "paper";
    coverage_pct, coverage_between_pct, tightness_median_db, tightness_max_db,
    mean_gap_db: see :class:`EnvelopeCheck`; rms_db: RMS of the dB error (the paper's
    cost, eq. 7 fit, unit weights); converged: the optimiser met its stopping test;
    orders_tried: {order: mean_gap_db (envelope) or rms_db (paper)} of the order search.
    """

    gain: float
    zeros: np.ndarray
    poles: np.ndarray
    order: int
    cost: str
    coverage_pct: float
    coverage_between_pct: float
    tightness_median_db: float
    tightness_max_db: float
    mean_gap_db: float
    rms_db: float
    converged: bool
    band_hz: tuple[float, float]
    orders_tried: Mapping[int, float] = field(default_factory=dict)

    @property
    def weight(self) -> WuWeight:
        return WuWeight(self.gain, self.zeros, self.poles)


class _Sections:
    """dB response of n_z zero pairs and n_p pole pairs, normalised to 0 dB at DC, and its
    Jacobian, at fixed angular frequencies ω (rad/s).

    Parameters θ = [a_1, φ_1, …] (zeros first, then poles), ω_n = e^a, ζ = cos φ; the
    section (s² + 2ζω_n s + ω_n²)/ω_n² has |·|² = (1 − u²)² + 4ζ²u², u = ω/ω_n.
    """

    def __init__(self, omega: np.ndarray, n_pairs: int):
        self.omega = np.asarray(omega, dtype=float)
        self.n = n_pairs
        self.sign = np.concatenate([np.ones(n_pairs), -np.ones(n_pairs)])

    def value_jac(self, theta: np.ndarray, jac: bool = True):
        if self.n == 0:
            z = np.zeros(self.omega.size)
            return z, np.zeros((self.omega.size, 0))
        a = theta[0::2]
        phi = theta[1::2]
        wn = np.exp(a)
        zeta = np.cos(phi)
        u = self.omega[None, :] / wn[:, None]
        u2 = u * u
        one = 1.0 - u2
        z2 = (zeta * zeta)[:, None]
        q = one * one + 4.0 * z2 * u2
        g = self.sign @ (_DB * np.log(q))
        if not jac:
            return g, None
        dq_da = 4.0 * u2 * one - 8.0 * z2 * u2
        dq_dphi = -8.0 * (zeta * np.sin(phi))[:, None] * u2
        J = np.empty((self.omega.size, 2 * self.sign.size))
        J[:, 0::2] = (self.sign[:, None] * _DB * dq_da / q).T
        J[:, 1::2] = (self.sign[:, None] * _DB * dq_dphi / q).T
        return g, J


def _theta_to_weight(theta: np.ndarray, n: int, dc_db: float) -> WuWeight:
    a = theta[0::2]
    phi = theta[1::2]
    wn = np.exp(a)
    phi = np.where(phi < 1e-9, 0.0, phi)  # at the bound: a double real root, imag exactly 0
    reps = -wn * np.cos(phi) + 1j * wn * np.sin(phi)
    zeros, poles = reps[:n], reps[n:]
    # K: the normalised sections have unit DC gain; (s − r)(s − r̄) = ω_n² × section.
    log_k = dc_db / 20.0 * np.log(10.0) + 2.0 * (np.sum(a[n:]) - np.sum(a[:n]))
    return WuWeight(float(np.exp(log_k)), zeros, poles)


def _bounds(n: int, omega: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a_lo, a_hi = np.log(omega[0] / 10.0), np.log(omega[-1] * 10.0)
    lo = np.tile([a_lo, 0.0], 2 * n)
    hi = np.tile([a_hi, _PHI_MAX], 2 * n)
    return lo, hi


def _starts(n: int, omega: np.ndarray) -> list[np.ndarray]:
    """Starting points: pairs spread log-uniformly over the band, ζ = 0.5, zeros and poles
    interleaved (zeros lower in one start, poles lower in the other)."""
    if n == 0:
        return [np.zeros(0)]
    lw = np.log(omega)
    centres = np.linspace(lw[0], lw[-1], 2 * n + 2)[1:-1]
    phi0 = np.arccos(0.5)
    out = []
    for zero_first in (True, False):
        az = centres[0::2] if zero_first else centres[1::2]
        ap = centres[1::2] if zero_first else centres[0::2]
        th = np.empty(4 * n)
        th[0::2] = np.concatenate([az, ap])
        th[1::2] = phi0
        out.append(th)
    return out


@dataclass(frozen=True)
class _Target:
    """The band's data prepared for fitting: full grid and a log-binned reduction."""

    f: np.ndarray          # band grid, Hz
    wdb: np.ndarray        # W_max at f, dB
    w_log: np.ndarray      # log-frequency weights of f (sum 1)
    fr: np.ndarray         # reduced points (largest W_max per log bin), Hz
    wr: np.ndarray         # W_max at fr, dB, on steps of SEARCH_STEP_DB
    wr_w: np.ndarray       # log-frequency weight of each bin (sum 1)
    fd: np.ndarray         # dense grid (grid points and between), Hz
    wd: np.ndarray         # W_max interpolated on fd, dB


def _prepare(f_hz, wmax, band, n_bins: int, n_sub: int) -> _Target:
    f, w, _ = _band_points(f_hz, wmax, band)
    wdb = _to_db(w)
    # the search's points and values from W_max on steps of SEARCH_STEP_DB (ties: the
    # lowest frequency of the bin), so that rounding upstream does not move them
    step = SEARCH_STEP_DB
    wq = np.round(wdb / step) * step if step else wdb       # 0: no steps
    wl = _log_weights(f)
    lf = np.log(f)
    edges = np.linspace(lf[0], lf[-1], n_bins + 1)
    idx = np.clip(np.searchsorted(edges, lf, side="right") - 1, 0, n_bins - 1)
    order = np.lexsort((-wq, idx))            # within each bin, largest W_max first
    first = np.ones(order.size, dtype=bool)
    first[1:] = idx[order][1:] != idx[order][:-1]
    rep = order[first]
    bin_w = np.bincount(idx, weights=wl, minlength=n_bins)[idx[rep]]
    fd, wd = _dense(f, wdb, n_sub)
    return _Target(f, wdb, wl, f[rep], wq[rep], bin_w / bin_w.sum(), fd, wd)


def _finish_envelope(sec_d: _Sections, theta: np.ndarray, tgt: _Target) -> float:
    """DC gain (dB) that lifts the shape onto the envelope: the largest shortfall on the
    dense grid plus a margin for the dip of the shape between dense points.

    Between two dense points W_max (interpolated) is linear in log f, so the gap can dip
    below its end values only through the curvature of 20log10|Wu|: by about h²·|g''|/8,
    estimated as max |Δ²g|/8 with Δ²g the second difference over neighbouring dense points.
    """
    g, _ = sec_d.value_jac(theta, jac=False)
    short = tgt.wd - g
    curv = np.abs(np.diff(g, 2)).max() if g.size > 2 else 0.0
    return float(short.max() + curv / 8.0 + 1e-9)


def _envelope_opt(sec: _Sections, tgt: _Target, theta0: np.ndarray, lo, hi
                  ) -> tuple[np.ndarray, bool]:
    """Minimise the mean gap subject to the envelope on the reduced points (SLSQP).

    Variables (c, θ) with c the DC level in dB: minimise Σ w_i (c + g_i(θ) − W_i) subject
    to c + g_i(θ) − W_i ≥ 0 at every reduced point (the largest W_max of its bin).
    """
    if theta0.size == 0:
        return theta0, True
    W = tgt.wr
    w = tgt.wr_w
    ones = np.ones(W.size)
    # SLSQP asks for the objective, the constraints and their Jacobian at the same point:
    # the sections' values and Jacobian there are computed once (the same numbers)
    last: list = [None, None, None]

    def value_jac(x):
        key = x.tobytes()
        if last[0] != key:
            last[:] = [key, *sec.value_jac(x[1:])]
        return last[1], last[2]

    def fun(x):
        g, J = value_jac(x)
        return float(w @ (x[0] + g - W)), np.concatenate([[1.0], w @ J])

    def cons(x):
        g, _ = value_jac(x)
        return x[0] + g - W

    def cons_jac(x):
        _, J = value_jac(x)
        return np.column_stack([ones, J])

    bounds = (np.concatenate([[-np.inf], lo]), np.concatenate([[np.inf], hi]))
    theta = theta0
    ok = False
    for _ in range(3):  # restart from the last iterate when SLSQP stops early
        g0, _ = sec.value_jac(theta, jac=False)
        x0 = np.concatenate([[float(np.max(W - g0))], theta])
        res = _slsqp.minimize_slsqp(fun, x0, bounds, cons, cons_jac, maxiter=150, ftol=1e-5)
        if not np.all(np.isfinite(res.x)):
            break
        theta = np.clip(res.x[1:], lo, hi)
        ok = bool(res.success)
        if ok:
            break
    return theta, ok


def _ls_fit(sec: _Sections, W: np.ndarray, wts: np.ndarray, theta0: np.ndarray, lo, hi,
            max_nfev: int = 400) -> tuple[np.ndarray, float, bool, float]:
    """Weighted dB least squares: min Σ wts (dc + g − W)² over θ and dc (dB).

    Returns θ, dc_db, converged, weighted RMS (dB)."""
    sw = np.sqrt(wts)

    def resid(x):
        g, _ = sec.value_jac(x[1:], jac=False)
        return sw * (x[0] + g - W)

    def jac(x):
        _, J = sec.value_jac(x[1:])
        return sw[:, None] * np.column_stack([np.ones(W.size), J])

    g0, _ = sec.value_jac(theta0, jac=False)
    dc0 = float(np.sum(wts * (W - g0)) / np.sum(wts))
    x0 = np.concatenate([[dc0], theta0])
    lo_x = np.concatenate([[-np.inf], lo])
    hi_x = np.concatenate([[np.inf], hi])
    res = _trf.bounded_least_squares(resid, np.clip(x0, lo_x, hi_x), jac=jac,
                                     bounds=(lo_x, hi_x), x_scale="jac", max_nfev=max_nfev,
                                     ftol=1e-10, xtol=1e-10)
    rms = float(np.sqrt(np.sum(res.fun ** 2) / np.sum(wts)))
    return res.x[1:], float(res.x[0]), bool(res.status > 0), rms


def _grow(theta: np.ndarray, n: int, tgt: _Target) -> list[np.ndarray]:
    """Starts for n+1 pairs from an n-pair solution: add a coincident zero/pole pair (which
    cancels, so the start is as good as the n-pair fit) at a few frequencies."""
    out = []
    g, _ = _Sections(2 * np.pi * tgt.fr, n).value_jac(theta, jac=False)
    gap = (g - tgt.wr) - (g - tgt.wr).min()
    cands = [np.log(2 * np.pi * tgt.fr[np.argmax(gap)]),
             np.log(2 * np.pi * np.sqrt(tgt.fr[0] * tgt.fr[-1]))]
    for a in cands:
        z = theta[: 2 * n]
        p = theta[2 * n:]
        new = np.array([a, np.arccos(0.5)])
        out.append(np.concatenate([z, new, p, new]))
    return out


def _fit_order_envelope(n: int, tgt: _Target, prev: np.ndarray | None
                        ) -> tuple[np.ndarray, float, bool]:
    omega_r = 2 * np.pi * tgt.fr
    sec_r = _Sections(omega_r, n)
    sec_d = _Sections(2 * np.pi * tgt.fd, n)
    lo, hi = _bounds(n, omega_r)
    starts = []
    for th0 in _starts(n, omega_r):
        th, _, _, _ = _ls_fit(sec_r, tgt.wr, tgt.wr_w, th0, lo, hi, max_nfev=1000)
        starts.append(th)
    if prev is not None:
        starts.extend(np.clip(s, lo, hi) for s in _grow(prev, n - 1, tgt))
    sec_f = _Sections(2 * np.pi * tgt.f, n)
    best = None
    for th0 in starts:
        th, ok = _envelope_opt(sec_r, tgt, th0, lo, hi)
        for cand, cand_ok in ((th, ok), (th0, False)):  # never worse than the start
            dc = _finish_envelope(sec_d, cand, tgt)
            g, _ = sec_f.value_jac(cand, jac=False)
            mean_gap = float(tgt.w_log @ (dc + g - tgt.wdb))
            if best is None or mean_gap < best[1] - 1e-9:
                best = (cand, mean_gap, cand_ok, dc)
    th, _, ok, dc = best
    return th, dc, ok


def _fit_order_paper(n: int, tgt: _Target, prev: np.ndarray | None
                     ) -> tuple[np.ndarray, float, bool, float]:
    """The paper's cost on the full grid (unit weights), from the best of: least-squares
    fits on the reduced points, and the (n−1)-pair solution with a cancelling pair added
    (so the RMS error never grows with the order)."""
    omega_r = 2 * np.pi * tgt.fr
    sec_r = _Sections(omega_r, n)
    sec_f = _Sections(2 * np.pi * tgt.f, n)
    lo, hi = _bounds(n, omega_r)
    starts = [_ls_fit(sec_r, tgt.wr, tgt.wr_w, th0, lo, hi, max_nfev=200)[0]
              for th0 in _starts(n, omega_r)]
    if prev is not None:
        starts.extend(np.clip(s, lo, hi) for s in _grow(prev, n - 1, tgt))

    def full_rms(th):
        g, _ = sec_f.value_jac(th, jac=False)
        r = g - tgt.wdb
        return float(np.sqrt(np.mean((r - r.mean()) ** 2)))  # with the best DC level

    best = min(starts, key=full_rms)
    return _ls_fit(sec_f, tgt.wdb, np.ones(tgt.f.size), best, lo, hi, max_nfev=1000)


_BLAS_LOCK = threading.Lock()
_blas_users = 0
_blas_limits = None


@contextlib.contextmanager
def _one_blas_thread():
    """BLAS on one thread while any Wu fit of this process runs. The limit
    (``threadpoolctl``) is the process's, not the thread's: a fit that ended in one
    thread must not give BLAS its threads back while another thread's fit goes on, whose
    numbers would then change (the axes' fits on a pool of threads). OpenBLAS takes the
    limit only when the thread that started it sets it, so :func:`_fit_wu_axes` sets it
    in the calling thread too, for the fits it hands to a pool of threads."""
    global _blas_users, _blas_limits
    with _BLAS_LOCK:
        if _blas_users == 0:
            # the limit reaches only the libraries loaded when it is set: scipy's own
            # BLAS, which its SLSQP kernel calls, is loaded first (else a process's
            # first fit, loading the kernel, would run with BLAS's threads and end
            # elsewhere than every later fit)
            if _slsqp.load_kernel() is None:
                import scipy.optimize  # noqa: F401  (the fits' SLSQP is then scipy's)
            _blas_limits = threadpool_limits(limits=1, user_api="blas")
        _blas_users += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _blas_users -= 1
            if _blas_users == 0:
                _blas_limits.restore_original_limits()
                _blas_limits = None


def fit_wu(f_hz, wmax, *, n_pairs: int | None = None, cost: str = "envelope",
           band: tuple[float, float] | None = None, max_pairs: int = MAX_PAIRS,
           order_tol_db: float = 0.1, n_bins: int = 160, n_sub: int = 8) -> WuResult:
    """Fit Wu(s) = K Π(s − z_i)/Π(s − p_i) (eq. 7, s in rad/s) to W_max over ``band`` (Hz).

    ``wmax`` is dimensionless (not dB) on the grid ``f_hz`` (Hz); NaN points are skipped.
    ``n_pairs`` zero pairs and as many pole pairs (0–5), or ``None`` to choose the order.

    ``cost="envelope"`` (default): minimise the mean over log frequency of
    20log10|Wu| − 20log10 W_max subject to |Wu| ≥ W_max on every grid point of the band
    and between them (W_max interpolated log-log on ``n_sub`` points per interval, plus
    a margin for the curvature of |Wu| in between). The shape is optimised by SLSQP with
    the constraint on the largest W_max of each of ``n_bins`` log-frequency bins, from
    least-squares starts; the gain K is then raised exactly as far as the full dense
    check requires, so coverage is 100 % by construction. The search sees W_max on
    steps of :data:`SEARCH_STEP_DB` (0.01 dB), the gain and the checks the W_max given:
    a W_max that differs by rounding gives the same shape.
    Order: the smallest whose mean gap is within ``order_tol_db`` of the best order's.
    Orders are fitted upwards from 0 (each solution, with a cancelling zero/pole pair
    added, starts the next), also when ``n_pairs`` is given.

    ``cost="paper"``: the paper's fit, Σ_n [20log10|Wu(jω_n)| − 20log10 W_max(ω_n)]² over
    the grid points with unit weights (eq. 7 fit with Wt = 1); no envelope guarantee.
    Order: the smallest whose RMS error is within ``order_tol_db`` of the best.
    """
    return _fit_here(_plan(f_hz, wmax, n_pairs=n_pairs, cost=cost, band=band,
                           max_pairs=max_pairs, order_tol_db=order_tol_db, n_bins=n_bins,
                           n_sub=n_sub))


@dataclass(frozen=True, eq=False)
class _WuPlan:
    """One Wu fit's settings and data (:func:`_plan`): the target prepared, the orders
    whose scores choose (``orders``), and the highest order fitted (``last``; orders are
    fitted from 0 up to it, each from the one before)."""

    tgt: _Target
    orders: tuple[int, ...]
    cost: str
    order_tol_db: float
    n_sub: int

    @property
    def last(self) -> int:
        return max(self.orders)


@dataclass(frozen=True, eq=False)
class _OrderFit:
    """The fit of one order (:func:`_fit_order`): θ, the DC level (dB), whether the
    optimiser converged, and the order's score (mean gap or RMS error, dB)."""

    theta: np.ndarray
    dc_db: float
    converged: bool
    score: float


def _plan(f_hz, wmax, *, n_pairs: int | None = None, cost: str = "envelope",
          band: tuple[float, float] | None = None, max_pairs: int = MAX_PAIRS,
          order_tol_db: float = 0.1, n_bins: int = 160, n_sub: int = 8) -> _WuPlan:
    """:func:`fit_wu`'s arguments checked and its target prepared (no fit yet)."""
    if cost not in ("envelope", "paper"):
        raise UsageError(f"cost must be 'envelope' or 'paper', got {cost!r}")
    if n_pairs is not None and not (0 <= n_pairs <= max_pairs):
        raise UsageError(f"order must be 0..{max_pairs} pairs, got {n_pairs}")
    if not 0 <= max_pairs <= MAX_PAIRS:
        raise UsageError(f"max_pairs must be 0..{MAX_PAIRS}, got {max_pairs}")
    tgt = _prepare(f_hz, wmax, band, n_bins, n_sub)
    orders = (n_pairs,) if n_pairs is not None else tuple(range(max_pairs + 1))
    return _WuPlan(tgt, orders, cost, order_tol_db, n_sub)


def _fit_order(plan: _WuPlan, n: int, prev: np.ndarray | None) -> _OrderFit:
    """Order ``n`` of ``plan`` fitted, from the fit of order n − 1 (``prev``, its θ;
    None for order 0), and scored."""
    tgt = plan.tgt
    if plan.cost == "envelope":
        th, dc, ok = _fit_order_envelope(n, tgt, prev)
        g, _ = _Sections(2 * np.pi * tgt.f, n).value_jac(th, jac=False)
        return _OrderFit(th, dc, ok, float(tgt.w_log @ (dc + g - tgt.wdb)))
    th, dc, ok, rms = _fit_order_paper(n, tgt, prev)
    return _OrderFit(th, dc, ok, rms)


def _wu_result(plan: _WuPlan, fits: Sequence[_OrderFit]) -> WuResult:
    """The weight of the chosen order, from the fits of orders 0 to ``plan.last`` (in
    order): the smallest order of ``plan.orders`` whose score is within
    ``order_tol_db`` of the best, and its checks against the target."""
    tgt = plan.tgt
    scored = {n: fits[n].score for n in plan.orders}
    best = min(scored.values())
    chosen = min(n for n, v in scored.items() if v <= best + plan.order_tol_db)
    fit = fits[chosen]
    weight = _theta_to_weight(fit.theta, chosen, fit.dc_db)
    if not (weight.is_stable and weight.is_minimum_phase):  # guaranteed by the bounds
        raise ConvergenceError("Wu fit left the left half plane (internal bound failure)")
    chk = check_envelope(tgt.f, 10 ** (tgt.wdb / 20), weight, band=(tgt.f[0], tgt.f[-1]),
                         n_sub=plan.n_sub)
    err = weight.magnitude_db(tgt.f) - tgt.wdb
    return WuResult(
        gain=weight.gain, zeros=weight.zeros, poles=weight.poles, order=chosen,
        cost=plan.cost, coverage_pct=chk.coverage_pct,
        coverage_between_pct=chk.coverage_between_pct,
        tightness_median_db=chk.tightness_median_db, tightness_max_db=chk.tightness_max_db,
        mean_gap_db=chk.mean_gap_db, rms_db=float(np.sqrt(np.mean(err ** 2))),
        converged=fit.converged, band_hz=chk.band_hz, orders_tried=scored)


# ---------------------------------------------------------------------------
# From armfit's tables to per-axis inputs (DataFrames in, arrays out; no file I/O)
# ---------------------------------------------------------------------------

def nominal_arm_response(params_row: Mapping, f_hz) -> np.ndarray:
    """Nominal H_ARM (m/N, eq. 3) of one parameters-CSV row, arm-stage effects included
    (:meth:`ClosedLoopModel.arm_response`; device and output effects excluded)."""
    model, theta = model_from_params(params_row)
    return model.arm_response(f_hz, theta)


def arm_trials(params_row: Mapping, f_hz, H_derived, mp_assumed: float | None = None
               ) -> np.ndarray:
    """The trials' derived arm dynamics (m/N) with the apparatus effects of a nominal
    row removed (:meth:`ClosedLoopModel.arm_from_derived`): a latency, a sensor lag, a
    device's own mass, damping or spring are properties of the rig, not of the arm, and
    left in they would make W_max describe the rig rather than how arms differ.
    ``mp_assumed``: the device mass (kg) the estimate used for Fa = F − Mp ẍ (default the
    row's). Unchanged when the row has no apparatus effect."""
    model, theta = model_from_params(params_row)
    with np.errstate(all="ignore"):
        return model.arm_from_derived(f_hz, H_derived, theta, mp_assumed)


def label_subject(label: str) -> str:
    """The subject of a trial label ``sub-<s>_grip-<g>N[_run-<k>]``."""
    return label.split("_grip-", 1)[0].removeprefix("sub-")


def arm_trials_by_subject(params_row: Mapping, f_hz, H_derived, labels: Sequence[str],
                          by_subject: Mapping[str, Mapping[str, float]] | None,
                          mp_assumed: float | None = None) -> np.ndarray:
    """:func:`arm_trials` with each trial's own subject's effect values where the
    adopted model has them: ``by_subject`` {subject: {``effect.param``: value}} replaces
    the row's values for the trials of that subject (``labels``, one per row of
    ``H_derived``, as :func:`derived_trials` gives them). Without ``by_subject``, or for
    a subject it lacks, the row's own values."""
    if not by_subject:
        return arm_trials(params_row, f_hz, H_derived, mp_assumed)
    H_derived = np.asarray(H_derived)
    out = np.empty(H_derived.shape, dtype=complex)
    subjects = np.array([label_subject(lab) for lab in labels])
    for subj in dict.fromkeys(subjects):
        idx = np.flatnonzero(subjects == subj)
        row = dict(params_row)
        row.update(by_subject.get(str(subj), {}))
        out[idx] = arm_trials(row, f_hz, H_derived[idx], mp_assumed)
    return out


def derived_trials(spectra, axis: str, *, method: str | None = None
                   ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Per-trial derived arm dynamics of one axis.

    Parameters
    ----------
    spectra : armfit.spectra.Spectra or pandas.DataFrame
        The study's responses; rows of level "trial", kind "derived" and out_axis ==
        axis are used.
    axis : {'x', 'y', 'z'}
    method : str, optional
        The estimator, when the spectra hold several.

    Returns
    -------
    f_hz : ndarray, shape (n_freq,)
    H : ndarray, shape (n_trials, n_freq), complex
        m/N; NaN where a trial lacks a frequency.
    labels : list of str
        ``sub-<s>_grip-<g>N[_run-<k>]`` per trial, in subject, grip, run order.

    Raises
    ------
    BadInputError
        No such trials.
    UsageError
        Derived spectra of several estimators and no ``method``.
    """
    sel = Spectra.of(spectra).select(level="trial", kind="derived", axis=axis,
                                     out_axis=axis, method=method)
    if len(sel) == 0:
        raise BadInputError(f"no trial-level 'derived' spectra for axis {axis}"
                            + (f" with method {method!r}" if method else ""), column="kind")
    methods = sorted(sel.values_of("method"))
    if len(methods) > 1 and sel.repeated():
        raise UsageError(f"axis {axis}: derived spectra of several estimators "
                         f"({', '.join(methods)}); choose one with {{opt}}", option="method=")
    sel = sel.sorted(("subject", "grip_N", "run"))
    return sel.freq_hz, sel.h, sel.labels()


@dataclass(frozen=True, eq=False)
class AxisUncertainty:
    """Everything fit-uncertainty computes for one axis.

    f_hz: grid (Hz); wmax_raw: W_max of eq. 6 without smoothing; wmax: the target the
    weight was fitted to (smoothed if asked, else wmax_raw); band_hz; n_trials; result:
    the fitted :class:`WuResult`; checks: {(weight label, target): EnvelopeCheck} with
    label "fitted" or a given weight's label and target "wmax" (raw) or "wmax_smoothed".
    """

    axis: str
    f_hz: np.ndarray
    wmax_raw: np.ndarray
    wmax: np.ndarray
    band_hz: tuple[float, float]
    n_trials: int
    result: WuResult
    checks: Mapping[tuple[str, str], EnvelopeCheck]


def _fit_here(plan: _WuPlan) -> WuResult:
    """The Wu fit of ``plan`` in this thread, its orders in turn (BLAS on one thread)."""
    # thousands of tiny dense problems (SLSQP, trust-region SVDs of ~160 x 21 matrices):
    # BLAS worker threads cost far more than they save there (a fit runs tens of times
    # slower on a busy 2-core machine), whichever BLAS numpy and scipy load
    with _one_blas_thread():
        fits: list[_OrderFit] = []
        for n in range(plan.last + 1):
            fits.append(_fit_order(plan, n, fits[-1].theta if fits else None))
        return _wu_result(plan, fits)


def _order_task(args: tuple[_WuPlan, int, np.ndarray | None]) -> _OrderFit:
    """Worker: one order of a Wu fit (:func:`_fit_order`), BLAS on one thread."""
    plan, n, prev = args
    with _one_blas_thread():
        return _fit_order(plan, n, prev)


def _fit_chains(plans: Sequence[_WuPlan], executor: Executor) -> list[WuResult]:
    """The Wu fits of ``plans`` on ``executor``, an order a task: each order is handed
    over as soon as the order before it is done (it starts from that fit; the
    diagnosis's :class:`~armfit.diagnosis.schedule.TaskQueue` calls the continuation),
    so that the axes' chains of orders run side by side and the workers share them
    whatever their lengths. Each order is the same computation as in :func:`_fit_here`,
    so are the results. The first error of a task is raised; the tasks not yet done are
    then cancelled."""
    from armfit.diagnosis.schedule import TaskQueue
    fits: list[list[_OrderFit]] = [[] for _ in plans]
    queue = TaskQueue(executor)

    def hand(i: int) -> None:
        prev = fits[i][-1].theta if fits[i] else None
        queue.add(0, _order_task, (plans[i], len(fits[i]), prev),
                  lambda fit: took(i, fit))

    def took(i: int, fit: _OrderFit) -> None:
        fits[i].append(fit)
        if len(fits[i]) <= plans[i].last:
            hand(i)

    for i in range(len(plans)):
        hand(i)
    queue.run()
    return [_wu_result(plan, f) for plan, f in zip(plans, fits, strict=True)]


def _fit_wu_axes(tasks, jobs: int, executor) -> list[WuResult]:
    """:func:`fit_wu` of each task ``(f_hz, wmax, options)`` (an axis each), here in turn,
    or in ``jobs`` worker processes or on ``executor`` an order a task
    (:func:`_fit_chains`). On an executor other than a pool of processes, BLAS is held
    on one thread from this thread too: a fit handed to a pool of threads would
    otherwise run with BLAS's threads (its own limit ignored, see
    :func:`_one_blas_thread`), and differ from the fit in a process. Fits here, in turn,
    or in processes hold it themselves, and this process then needs no optimiser."""
    plans = [_plan(f, target, **kw) for f, target, kw in tasks]
    with executor_for(executor, jobs, tasks=len(plans),
                      preload=POOL_PRELOAD["uncertainty"]) as ex:
        if ex is None:
            return [_fit_here(plan) for plan in plans]
        if isinstance(ex, ProcessPoolExecutor):
            return _fit_chains(plans, ex)
        with _one_blas_thread():
            return _fit_chains(plans, ex)


@dataclass(frozen=True, eq=False)
class WmaxTarget:
    """One axis's W_max (eq. 6), all its Wu fit (eq. 7) needs (:func:`wmax_targets`):
    the grid ``f_hz`` (Hz), the trials behind it, W_max raw and the fit's target
    (``smoothed``: W_max smoothed, else the raw W_max), and the band (Hz) of the fit."""

    axis: str
    f_hz: np.ndarray
    n_trials: int
    wmax_raw: np.ndarray
    target: np.ndarray
    band: tuple[float, float]
    smoothed: bool = False


def wmax_targets(spectra, params, *,
                 band: tuple[float, float] | Mapping[str, tuple[float, float]] | None = None,
                 smooth_oct: float | None = None, method: str | None = None,
                 source: str | None = None,
                 by_subject: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None
                 ) -> list[WmaxTarget]:
    """W_max (eq. 6) of each axis with derived trial spectra and a nominal row: the first
    half of :func:`fit_weights` (its arguments, which see), made from the spectra alone.
    What it returns no longer refers to ``spectra``: a caller may let the trial rows go
    before the Wu fits (:func:`fit_targets`) run.

    Returns
    -------
    list of WmaxTarget
        One per axis, in x, y, z order.
    """
    if "grip_N" in params.columns:
        raise BadInputError("has a grip_N column (grip-dependent fits); give the "
                            "parameters file of fit-nominal", file=source, column="grip_N")
    trial_rows = Spectra.of(spectra).select(level="trial", kind="derived")
    have_spec = trial_rows.values_of("axis")
    have_par = set(params["axis"].astype(str))
    wanted = [a for a in AXES if a in have_spec and a in have_par]
    if not wanted:
        raise BadInputError(f"no axis has both derived trial spectra (axes: "
                            f"{', '.join(sorted(have_spec)) or 'none'}) and a nominal "
                            f"row (axes: {', '.join(sorted(have_par)) or 'none'})",
                            file=source, column="axis")
    out = []
    for axis in wanted:
        rows = params[params["axis"].astype(str) == axis]
        if len(rows) > 1:
            first, second = (int(i) for i in np.flatnonzero(params["axis"].astype(str)
                                                              == axis)[:2] + 1)
            raise BadInputError(f"axis {axis} has a second row (rows {first} and {second}); "
                                "a nominal params file has one row per axis",
                                file=source, column="axis", row=second)
        f, H, labels = derived_trials(trial_rows, axis, method=method)
        H = arm_trials_by_subject(rows.iloc[0], f, H, labels, (by_subject or {}).get(axis),
                                  derived_mass_kg(spectra, axis))
        Hn = nominal_arm_response(rows.iloc[0], f)
        lo, hi = axis_band(band, axis) or PAPER_BAND_HZ
        finite = f[np.isfinite(H).any(axis=0) & (f > 0)]
        if finite.size < 2:
            raise BadInputError(f"axis {axis}: derived spectra hold fewer than 2 finite "
                                "frequencies", column="re")
        b = (max(lo, float(finite[0])), min(hi, float(finite[-1])))
        if not b[0] < b[1]:
            raise UsageError(f"axis {axis}: band {lo:g}:{hi:g} Hz holds no spectra "
                             f"(they cover {finite[0]:g}-{finite[-1]:g} Hz)")
        raw = w_max(H, Hn)
        target = raw if smooth_oct is None else w_max(H, Hn, f_hz=f, smooth_oct=smooth_oct)
        out.append(WmaxTarget(axis, f, H.shape[0], raw, target, b, smooth_oct is not None))
    return out


def fit_targets(targets: Sequence[WmaxTarget], *, cost: str = "envelope",
                n_pairs: int | None = None,
                given: Mapping[str, Mapping[str, WuWeight]] | None = None,
                jobs: int = 1, executor=None) -> list[AxisUncertainty]:
    """Wu (eq. 7) fitted to each of ``targets`` (:func:`wmax_targets`), and the checks
    of the fitted and ``given`` weights against W_max (and against the smoothed W_max
    of a smoothed target): the second half of :func:`fit_weights` (its arguments, which
    see).

    Returns
    -------
    list of AxisUncertainty
        One per target, in their order.
    """
    tasks = [(t.f_hz, t.target, {"n_pairs": n_pairs, "cost": cost, "band": t.band})
             for t in targets]
    fits = _fit_wu_axes(tasks, jobs, executor)
    out = []
    for t, res in zip(targets, fits, strict=True):
        targets_by = {"wmax": t.wmax_raw} if not t.smoothed else {
            "wmax": t.wmax_raw, "wmax_smoothed": t.target}
        weights = {"fitted": res.weight}
        for label, by_axis in (given or {}).items():
            if t.axis in by_axis:
                weights[label] = by_axis[t.axis]
        checks = {(label, tname): check_envelope(t.f_hz, tw, w, band=t.band)
                  for label, w in weights.items() for tname, tw in targets_by.items()}
        out.append(AxisUncertainty(t.axis, t.f_hz, t.wmax_raw, t.target, t.band,
                                   t.n_trials, res, checks))
    return out


def require_converged(results: Sequence[AxisUncertainty], cost: str) -> None:
    """The one convergence policy of ``fit-uncertainty`` and ``run``: with cost 'paper',
    raise ConvergenceError naming the axes whose dB least-squares fit of Wu did not
    converge; the envelope fit holds its guarantee whether or not its shape optimiser
    converged."""
    bad = [r.axis for r in results if not r.result.converged]
    if bad and cost == "paper":
        raise ConvergenceError(f"the dB least-squares fit of Wu did not converge for axis "
                               f"{', '.join(bad)}; nothing written (try {{opt}})",
                               option="order=")


def fit_weights(spectra, params, *, cost: str = "envelope", n_pairs: int | None = None,
                    band: tuple[float, float] | Mapping[str, tuple[float, float]] | None = None,
                    smooth_oct: float | None = None,
                    method: str | None = None,
                    given: Mapping[str, Mapping[str, WuWeight]] | None = None,
                    jobs: int = 1, executor=None, source: str | None = None,
                    by_subject: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None
                    ) -> list[AxisUncertainty]:
    """W_max (eq. 6) and Wu (eq. 7) for each axis with derived trial spectra and a
    nominal row.

    ``spectra``: DataFrame in the spectra schema (trial rows of kind "derived" are used);
    ``params``: DataFrame in the parameters-CSV layout, one row per axis (a fit-nominal
    file); ``band``: Hz, one (lo, hi) for every axis or {axis: (lo, hi)}, default (also
    for an axis a mapping does not name) 0.01–30 Hz, limited to the frequencies the
    spectra hold;
    ``smooth_oct``: smoothing width in octaves (None: raw W_max); ``given``:
    {label: {axis: WuWeight}} weights to evaluate on the same data; ``jobs`` > 1: the
    axes' Wu fits in that many worker processes, or on ``executor`` (a
    :class:`concurrent.futures.Executor`, used as is; see :mod:`armfit.workers`) when
    given (the results depend on neither); ``source``: the file ``params`` came from,
    named in messages. An axis without both derived trials and a nominal row is left
    out (:func:`weight_axis_notes` says which). ``by_subject``: {axis: {subject:
    {``effect.param``: value}}} effect values per subject (the adopted model's), each
    trial's apparatus effects removed with its subject's (:func:`arm_trials_by_subject`).
    Returns one :class:`AxisUncertainty` per axis, in x, y, z order:
    :func:`fit_targets` of :func:`wmax_targets`.
    """
    targets = wmax_targets(spectra, params, band=band, smooth_oct=smooth_oct,
                           method=method, source=source, by_subject=by_subject)
    return fit_targets(targets, cost=cost, n_pairs=n_pairs, given=given, jobs=jobs,
                       executor=executor)


def weight_axis_notes(spectra, params, *, spectra_label: str | None = None,
                      params_label: str | None = None) -> list[str]:
    """What :func:`fit_weights` leaves out, in sentences: an axis with derived trial
    spectra but no nominal row (it gets no weight), and a nominal row without derived
    trials. A subset of the axes is a legitimate study; the notes say which.

    Parameters
    ----------
    spectra : Spectra or pandas.DataFrame
    params : pandas.DataFrame
        The nominal rows (a params table).
    spectra_label, params_label : str, optional
        The files, named in the sentences.

    Returns
    -------
    list of str
        One sentence per axis left out, in x, y, z order (empty when none is).
    """
    sl = spectra_label or "the spectra"
    pl = params_label or "the nominal parameters"
    have_spec = Spectra.of(spectra).select(level="trial", kind="derived").values_of("axis")
    have_par = set(params["axis"].astype(str))
    out = []
    for axis in AXES:
        if axis in have_spec and axis not in have_par:
            out.append(f"axis {axis}: {sl} holds derived trials but {pl} has no row for "
                       f"it; no weight is fitted for axis {axis}")
        elif axis in have_par and axis not in have_spec:
            out.append(f"axis {axis}: {pl} has a row but {sl} holds no derived trials of "
                       f"it; no weight is fitted for axis {axis}")
    return out


def derived_mass_kg(spectra, axis: str) -> float | None:
    """The device mass (kg) the spectra's derived dynamics were estimated with, from the
    file's metadata (None if it does not say)."""
    meta = getattr(spectra, "meta", None) or {}
    mp = (meta.get("mp_kg") or {}).get(axis) if isinstance(meta, Mapping) else None
    try:
        return None if mp is None else parse_number(mp)
    except ValueError:
        raise BadInputError(f"metadata 'mp_kg' of axis {axis}: {cell(mp)} is not a number",
                            file=getattr(spectra, "source", None)) from None


def summary_table(results: Sequence[AxisUncertainty], *, smooth_oct: float | None = None):
    """The per-axis summary (columns :data:`armfit.io.artifacts.WU_SUMMARY_COLUMNS`): one
    row per axis × weight × target with coverage (%) and tightness (dB)."""
    import pandas as pd  # here: the Wu fits' workers load no pandas

    rows = []
    for r in results:
        for (label, tname), c in r.checks.items():
            fitted = label == "fitted"
            rows.append({
                "axis": r.axis, "weight": label, "target": tname,
                "cost": r.result.cost if fitted else "",
                "order": r.result.order if fitted else np.nan,
                "n_trials": r.n_trials,
                "smooth_oct": np.nan if smooth_oct is None else smooth_oct,
                "band_lo_hz": c.band_hz[0], "band_hi_hz": c.band_hz[1],
                "n_points": c.n_points, "coverage_pct": c.coverage_pct,
                "coverage_between_pct": c.coverage_between_pct,
                "tightness_median_db": c.tightness_median_db,
                "tightness_max_db": c.tightness_max_db,
                "tightness_min_db": c.tightness_min_db, "mean_gap_db": c.mean_gap_db,
                "converged": r.result.converged if fitted else "",
            })
    return pd.DataFrame(rows, columns=list(WU_SUMMARY_COLUMNS))


def points_table(results: Sequence[AxisUncertainty]):
    """W_max points per axis (columns :data:`armfit.io.artifacts.WU_POINTS_COLUMNS`): raw
    W_max, the fitted target and the fitted |Wu| in dB at every grid frequency."""
    import pandas as pd  # here: the Wu fits' workers load no pandas

    parts = []
    for r in results:
        f = r.f_hz
        with np.errstate(divide="ignore", invalid="ignore"):
            parts.append(pd.DataFrame({
                "axis": r.axis, "freq_hz": f, "wmax_db": 20 * np.log10(r.wmax_raw),
                "target_db": 20 * np.log10(r.wmax), "wu_db": r.result.weight.magnitude_db(f),
                "in_band": (f >= r.band_hz[0]) & (f <= r.band_hz[1]),
            }, columns=list(WU_POINTS_COLUMNS)))
    return pd.concat(parts, ignore_index=True)


def read_weights_and_bands(path_or_name: str | Path):
    """({axis: WuWeight}, {axis: (lo, hi) Hz}, label) of a Wu CSV (fit-uncertainty
    output, Table III layout) or the paper's Table III by name (``paper``/``table3``;
    a file of that name wins). The band is the one the weight was fitted over, from the
    ``<stem>_summary.csv`` written beside it; without one, the paper's 0.01–30 Hz.

    Raises
    ------
    NoInputError, BadInputError
        As :func:`read_wu`; and naming the summary file, column and row when it is not a
        summary (a missing column), gives an axis two fitted bands, or a band that is
        not lo < hi inside the physical range of a frequency.
    """
    p = Path(path_or_name)
    if not p.exists() and str(path_or_name).lower() in PAPER_WEIGHTS:
        w = read_wu(paper_file("uncertainty"))
        return w, {a: PAPER_BAND_HZ for a in w}, "Table III of the paper"
    w = read_wu(p)
    bands = {a: PAPER_BAND_HZ for a in w}
    summary, _ = wu_sidecar_paths(p)
    if summary.is_file():
        bands.update(_summary_bands(summary, set(w)))
    return w, bands, str(p)


def _summary_bands(summary: Path, axes: set[str]) -> dict[str, tuple[float, float]]:
    """{axis: (lo, hi)} of the fitted weights' rows (target ``wmax``) of a Wu summary."""
    import pandas as pd  # here: the Wu fits' workers load no pandas

    try:
        s = pd.read_csv(summary, dtype={"axis": str, "weight": str, "target": str})
    except (ValueError, UnicodeDecodeError, pd.errors.ParserError,
            pd.errors.EmptyDataError) as exc:
        raise BadInputError(f"not a Wu summary CSV ({str(exc).splitlines()[0]})",
                            file=str(summary)) from None
    for col in ("axis", "weight", "target", "band_lo_hz", "band_hi_hz"):
        if col not in s.columns:
            raise BadInputError("missing column; expected the summary fit-uncertainty "
                                "writes beside its weights", file=str(summary), column=col)
    rows = np.flatnonzero(((s["weight"] == "fitted") & (s["target"] == "wmax")).to_numpy())
    out: dict[str, tuple[float, float]] = {}
    first: dict[str, int] = {}
    for i in rows:
        axis = str(s["axis"].iloc[i]).strip().lower()
        if axis not in axes:
            continue
        if axis in first:
            raise BadInputError(f"axis {axis} has a second fitted band (rows {first[axis]} "
                                f"and {i + 1})", file=str(summary), column="axis",
                                row=int(i) + 1)
        first[axis] = int(i) + 1
        lo, hi = (parse_numbers(s[c].iloc[[i]], file=str(summary), column=c,
                                first_row=int(i) + 1)
                  for c in ("band_lo_hz", "band_hi_hz"))
        for col, v in (("band_lo_hz", lo), ("band_hi_hz", hi)):
            check_in_range(v, FREQUENCY_RANGE, file=str(summary), column=col,
                           rows=[i + 1], shown=[s[col].iloc[i]])
        if not lo[0] < hi[0]:
            raise BadInputError(f"band {lo[0]:g}-{hi[0]:g} Hz of axis {axis} is empty; "
                                "expected band_lo_hz < band_hi_hz", file=str(summary),
                                column="band_hi_hz", row=int(i) + 1)
        out[axis] = (float(lo[0]), float(hi[0]))
    return out


__all__ = [
    "PAPER_BAND_HZ", "PAPER_WEIGHTS", "MAX_PAIRS", "ZETA_MIN", "WuWeight", "read_wu",
    "wu_response", "smooth_fractional_octave", "relative_error", "w_max",
    "EnvelopeCheck", "check_envelope", "WuResult", "fit_wu", "nominal_arm_response",
    "arm_trials", "arm_trials_by_subject", "derived_trials", "label_subject",
    "AxisUncertainty", "WmaxTarget", "wmax_targets", "fit_targets", "require_converged",
    "fit_weights",
    "derived_mass_kg", "weight_axis_notes", "summary_table", "points_table",
    "read_weights_and_bands",
]
