"""Compare the model with the measurements, find where it fails, name the missing effect.

Residuals are "measured relative to model": r_dB = 20 log10|H_meas/H_model| (dB) and
r_deg = angle(H_meas/H_model) (deg); each divided by the measurement's standard error
(``se_db``, ``se_deg`` of the spectra file) gives the normalised residual z, which is
≈ N(0, 1) where the model fits within the noise.

Where the evidence is weighed (diagnosis)
-----------------------------------------
The median (or mean) of many subjects is not itself a 5-parameter response, and its
standard error is dominated by between-subject spread that is smooth in frequency: a
χ² test on an aggregate raises false alarms or misses effects depending on the spread.
So the diagnosis weighs the evidence **per trial**: every trial of an axis gets its own
five arm parameters (Ma, k1, k2, b1, b2 — subjects and grips differ), each judged against
its own measurement noise (Bendat & Piersol standard errors from coherence), while a
candidate effect's parameters are **shared** by all trials of the axis (a delay, a sensor
lag, the device's damping or mass, a structural mode are properties of the apparatus;
for the reflex this reads as the population's typical reflex). One joint least-squares
fit per candidate (T·5 + k parameters, a block-arrow Jacobian by vectorised forward
differences, solved by eliminating the trials' blocks: :mod:`armfit.blocklsq`) is
warm-started from the base
fit at the effect's null point (where it vanishes) and at the effect's own starting
points, so adding an effect never makes the fit worse.

Criterion: the likelihood-ratio statistic with unknown common noise scale,
D = N_eff · ln(RSS_base / RSS_effect), with N_eff = N (1 − ρ)/(1 + ρ) the number of
residuals corrected for their lag-1 autocorrelation ρ along frequency (neighbouring grid
points of the estimator are not fully independent, and a candidate that leaves a
systematic residual keeps ρ high); ΔBIC = D − k ln N_eff. A candidate is significant when
ΔBIC > :data:`SIGNIFICANT_BIC` (Kass & Raftery's "very strong" evidence) **and** it removes
at least :data:`MIN_REDUCTION` of the residual sum of squares: with many trials even a
consistent estimator bias of a few hundredths of a dB reaches any ΔBIC, while a physical
effect worth modelling explains a good part of the misfit. Two candidates whose ΔBIC differ
by less than :data:`TIE_BIC` (or :data:`TIE_FRACTION` of the best) "explain the data about
equally well".

Stepwise search and verdict: :func:`diagnose` adds effects one at a time while the model
is not adequate (:func:`adequacy`: every band within the noise, no band failing), each
significant both statistically (the criterion above) and practically (:func:`practical`:
it changes the response by more than the noise and a floor). Every standard error is the
noise model's (:func:`armfit.noise.standard_errors` of each trial, on the whole grid):
the joint fits, the screening and the rescue of a stuck trial weigh residuals by it, and
every "× noise" is :func:`armfit.noise.rms_norm`. The statistics and choices are
documented in docs/methods.md, "Diagnosis" and "The noise model".

Failing bands: per frequency, the mean over trials of the normalised residual of the base
fit, divided by its standard error across trials (a t statistic); runs of at least
:data:`MIN_RUN` grid points with |t| > :data:`T_FAIL` and a mean normalised residual above 1
(a systematic error larger than one trial's noise) are the bands where the model fails.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy import special

from armfit import blocklsq, noise
from armfit.constants import AXES, PARAM_NAMES, UNIT_SE_DEG
from armfit.errors import UsageError
from armfit.fitting import ParamSpace, analytic_guess, fit_response, log_errors
from armfit.io.schema import finite_or_none
from armfit.models.arm import ClosedLoopModel, at_bound
from armfit.models.effects import EFFECTS, Effect
from armfit.models.params import fit_band, model_from_params
from armfit.spectra import Spectra
from armfit.workers import process_pool

#: Standard error bands of the compare table (Hz).
BANDS: tuple[tuple[float, float], ...] = ((0.1, 1.0), (1.0, 3.0), (3.0, 10.0), (10.0, 30.0))
#: ΔBIC above which an effect is reported as significant.
SIGNIFICANT_BIC = 10.0
#: Fraction of the residual sum of squares an effect must remove to be reported: with
#: many trials a consistent estimator bias of a few hundredths of a dB reaches any ΔBIC,
#: but explains almost nothing.
MIN_REDUCTION = 0.05
#: A band is within the noise when its RMS normalised error is at most this (its
#: noise-weighted cost at most 2.25 times the expected value); see :func:`adequacy`.
NOISE_TOL = 1.5
#: Practical-significance floors: an effect must change the fitted response by more
#: than this much (and more than the noise) somewhere in the band; see :func:`practical`.
MIN_EFFECT_DB = 0.5
MIN_EFFECT_DEG = 3.0
#: Default maximum number of effects the stepwise search adds.
MAX_STEPS = 3
#: ΔBIC difference below which two candidates are reported as explaining the data alike
#: (absolute, or as a fraction of the best candidate's ΔBIC, whichever is larger).
TIE_BIC = 6.0
TIE_FRACTION = 0.05
#: |t| (or |z| for a single aggregate) above which a grid point fails.
T_FAIL = 4.0
#: Minimum number of consecutive failing grid points that make a failing band.
MIN_RUN = 3
#: Grid points with the largest improvement left out of the evidence (robustness).
DROP_POINTS = 2
#: Degrees weighted like 1 dB in unweighted comparisons (1 neper ↔ 1 rad).
UNIT_DEG = float(UNIT_SE_DEG)


# ---------------------------------------------------------------------------
# Residuals and error summaries
# ---------------------------------------------------------------------------

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


def band_error(f_hz, r_db, r_deg, se_db, se_deg, lo: float, hi: float) -> BandError:
    """RMS errors over ``lo <= f <= hi`` of residual arrays (…, n_freq), pooled.

    se_db, se_deg: the noise model's standard errors (:func:`armfit.noise.standard_errors`),
    broadcastable to the residuals; ``rms_norm`` is :func:`armfit.noise.rms_norm` (a point
    without a finite standard error or residual is left out, not counted as zero)."""
    f = np.asarray(f_hz, float)
    sel = (f >= lo) & (f <= hi)
    rdb = np.asarray(r_db)[..., sel]
    rdeg = np.asarray(r_deg)[..., sel]
    if rdb.size == 0:
        nan = float("nan")
        return BandError(lo, hi, nan, nan, nan, 0)
    sdb = np.broadcast_to(se_db, np.shape(r_db))[..., sel]
    sdeg = np.broadcast_to(se_deg, np.shape(r_deg))[..., sel]
    zdb, zdeg = noise.normalised(rdb, rdeg, sdb, sdeg)
    rms_norm = noise.rms_norm(rdb, rdeg, sdb, sdeg)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mdb = np.nanmean(np.atleast_2d(zdb), axis=0)
        mdeg = np.nanmean(np.atleast_2d(zdeg), axis=0)
        mall = np.concatenate([mdb, mdeg])
        bias = float(np.sqrt(np.nanmean(mall ** 2))) if np.isfinite(mall).any() \
            else float("nan")
    return BandError(lo, hi, float(np.sqrt(np.mean(rdb ** 2))),
                     float(np.sqrt(np.mean(rdeg ** 2))), rms_norm, int(sel.sum()), bias)


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


def describe(f_hz, r_db, r_deg, sig_db, sig_deg) -> str:
    """Words for a band's mean residual: sign and shape of magnitude and phase.

    f_hz, r_db (dB), r_deg (deg): the band's frequencies and mean residuals (measured
    relative to model); sig_db, sig_deg: per-point significance masks.
    """
    f = np.asarray(f_hz, float)
    parts = []
    if np.any(sig_db):
        peak = float(r_db[np.argmax(np.abs(r_db))])
        where = "above" if np.median(r_db) > 0 else "below"
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
        word = "lags" if np.median(r_deg) < 0 else "leads"
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
                               describe(f[sl], np.asarray(mean_db)[sl],
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


# ---------------------------------------------------------------------------
# Joint fit over the trials of one axis
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class AxisData:
    """The trial-level measured responses of one axis on a common grid.

    f_hz (n,) Hz; h (T, n) complex X/F in m/N; se_db, se_deg (T, n) the trials' standard
    errors as the spectra file holds them (:meth:`noise_se`: the noise model's); starts:
    per trial the base parameters to start from (e.g. the grip fit of its grip).
    """

    axis: str
    f_hz: np.ndarray
    h: np.ndarray
    se_db: np.ndarray
    se_deg: np.ndarray
    starts: tuple[Mapping[str, float], ...]
    labels: tuple[str, ...] = ()

    def noise_se(self, sel: np.ndarray | slice = slice(None)
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The noise model's standard errors (dB, deg) of every trial, (T, n) on the
        grid points ``sel`` (computed on the whole grid, then restricted)."""
        sdb, sdeg = noise.standard_errors(self.se_db, self.se_deg)
        return sdb[:, sel], sdeg[:, sel]


@dataclass(frozen=True)
class JointFit:
    """Result of one joint fit: per-trial base parameters (T, 5), shared effect
    parameters with 95 % intervals, residuals (T, n) and the residual sum of squares."""

    model: ClosedLoopModel
    base: np.ndarray
    shared: dict[str, float]
    shared_lo: dict[str, float]
    shared_hi: dict[str, float]
    r_db: np.ndarray
    r_deg: np.ndarray
    rss: float
    n_res: int
    rho: float
    converged: bool


class _Joint:
    """Residuals of T trials with per-trial base parameters and shared effect parameters."""

    def __init__(self, model: ClosedLoopModel, data: AxisData, sel: np.ndarray):
        self.model = model
        self.space = ParamSpace.of(model)
        self.f = data.f_hz[sel]
        self.h = data.h[:, sel]
        sdb, sdeg = data.noise_se(sel)
        self.w_db, self.w_deg = 1.0 / sdb, 1.0 / sdeg
        self.T = self.h.shape[0]
        self.nb = len(PARAM_NAMES)
        self.k = len(self.space.names) - self.nb
        self.base_idx = np.arange(self.nb)
        self.eff_idx = np.arange(self.nb, self.nb + self.k)

    def unpack(self, x: np.ndarray) -> np.ndarray:
        """x (T·5 + k) → z (T, P) in the transformed space."""
        zb = x[: self.T * self.nb].reshape(self.T, self.nb)
        ze = np.broadcast_to(x[self.T * self.nb:], (self.T, self.k))
        return np.concatenate([zb, ze], axis=1)

    def response(self, x: np.ndarray) -> np.ndarray:
        theta = self.space.to_theta(self.unpack(x))
        values = {n: theta[:, i:i + 1] for i, n in enumerate(self.space.names)}
        return self.model.response(self.f, values)

    def split_res(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        with np.errstate(all="ignore"):
            r_db, r_deg = residuals(self.h, self.response(x))
        return r_db, r_deg

    def fun(self, x: np.ndarray) -> np.ndarray:
        r_db, r_deg = self.split_res(x)
        r = np.concatenate([r_db * self.w_db, r_deg * self.w_deg], axis=1)
        return np.where(np.isfinite(r), r, 1e6).ravel()

    def jac(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward-difference Jacobian of :meth:`fun` as its blocks (per-trial
        (T, m, 5), shared (T, m, k); see :mod:`armfit.blocklsq`), all columns in one
        vectorised evaluation: column j of every trial is perturbed at once (the trials'
        blocks do not overlap), shared columns for all trials together. Steps
        √eps·max(1, |z|), taken backwards at an upper bound."""
        z = self.unpack(x)                                    # (T, P)
        T, P = z.shape
        h = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(z))
        h = np.where(z + h > self.space.zhi, -h, h)
        Z = np.repeat(z[None], P + 1, axis=0)                 # (P + 1, T, P)
        idx = np.arange(P)
        Z[idx + 1, :, idx] += h.T
        theta = self.space.to_theta(Z)
        values = {n: theta[..., i:i + 1] for i, n in enumerate(self.space.names)}
        with np.errstate(all="ignore"):
            r_db, r_deg = residuals(self.h[None], self.model.response(self.f, values))
            R = np.concatenate([r_db * self.w_db, r_deg * self.w_deg], axis=-1)
        R = np.where(np.isfinite(R), R, 1e6)
        D = (R[1:] - R[:1]) / h.T[:, :, None]                  # (P, T, m)
        D = np.moveaxis(D, 0, -1)                              # (T, m, P)
        return np.ascontiguousarray(D[..., : self.nb]), np.ascontiguousarray(D[..., self.nb:])

    def solve(self, x0: np.ndarray, max_nfev: int, **tol) -> blocklsq.BlockResult:
        """The joint least-squares fit from ``x0`` (:func:`armfit.blocklsq.solve`)."""
        lo, hi = self.bounds()
        return blocklsq.solve(self.fun, self.jac, x0, lo, hi, n_trials=self.T,
                              n_block=self.nb, max_nfev=max_nfev, **tol)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.concatenate([np.tile(self.space.zlo[: self.nb], self.T),
                             self.space.zlo[self.nb:]])
        hi = np.concatenate([np.tile(self.space.zhi[: self.nb], self.T),
                             self.space.zhi[self.nb:]])
        return lo, hi

    def pack(self, base: np.ndarray, shared: Mapping[str, float]) -> np.ndarray:
        full = np.zeros((self.T, len(self.space.names)))
        full[:, : self.nb] = base
        for j, n in enumerate(self.space.names[self.nb:]):
            full[:, self.nb + j] = shared[n]
        z = self.space.clip_z(self.space.to_z(full))
        return np.concatenate([z[:, : self.nb].ravel(), z[0, self.nb:]])


def _lag1(r: np.ndarray) -> float:
    """Mean lag-1 autocorrelation along frequency of residual rows (T, n)."""
    r = r - r.mean(axis=1, keepdims=True)
    num = np.sum(r[:, 1:] * r[:, :-1])
    den = np.sum(r * r)
    return float(num / den) if den > 0 else 0.0


def levy_starts(model: ClosedLoopModel, data: AxisData, band: tuple[float, float],
                 effect_values: Mapping[str, float], fallback: np.ndarray) -> np.ndarray:
    """Per-trial arm parameters (T, 5) from the analytic (Levy) guess of
    :func:`armfit.fitting.analytic_guess`, applied to each trial's response with the
    effects at ``effect_values`` removed (:meth:`ClosedLoopModel.remove_effects`); the
    candidate closest to the data in log error, or the ``fallback`` row where none is
    physical. A start that does not depend on a possibly distorted earlier fit."""
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    f = data.f_hz[sel]
    out = np.array(fallback, float, copy=True)
    base_model = ClosedLoopModel(mp=model.mp)
    bounds = [(p.lower, p.upper) for p in base_model.params]
    for i in range(data.h.shape[0]):
        with np.errstate(all="ignore"):
            hb = model.remove_effects(f, data.h[i, sel], effect_values) if effect_values \
                else data.h[i, sel]
            if not np.all(np.isfinite(hb)):
                continue
            best = None
            # the linear fit is sensitive to the noisy lowest frequencies: also try it
            # above 0.3 Hz and above 1 Hz, judge every candidate on the whole band
            cands = [c for lo_f in (0.0, 0.3, 1.0) if np.sum(f >= lo_f) > 10
                     for c in analytic_guess(f[f >= lo_f], hb[f >= lo_f], model.mp)]
            for cand in cands:
                row = np.array([np.clip(cand[n], lo, hi)
                                for n, (lo, hi) in zip(PARAM_NAMES, bounds, strict=True)])
                r_db, r_deg = residuals(hb, base_model.response(f, row))
                err = float(np.nanmean(r_db ** 2 + (r_deg / UNIT_DEG) ** 2))
                if np.isfinite(err) and (best is None or err < best[0]):
                    best = (err, row)
        if best is not None:
            out[i] = best[1]
    return out


def best_rows(model: ClosedLoopModel, data: AxisData, band: tuple[float, float],
              effect_values: Mapping[str, float], candidates: Sequence[np.ndarray]
              ) -> np.ndarray:
    """Per trial, the candidate row of arm parameters (each candidate (T, 5) or (5,))
    whose response, with the effects at ``effect_values``, is closest to the trial's data
    in normalised squared error. Returns (T, 5)."""
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    f = data.f_hz[sel]
    sdb, sdeg = data.noise_se(sel)
    T = data.h.shape[0]
    rows = [np.broadcast_to(np.asarray(c, float), (T, len(PARAM_NAMES))) for c in candidates]
    errs = []
    for r in rows:
        theta = {n: r[:, i:i + 1] for i, n in enumerate(PARAM_NAMES)}
        theta.update({k: v for k, v in effect_values.items()})
        if not model.effects:
            theta = {n: theta[n] for n in PARAM_NAMES}
        with np.errstate(all="ignore"):
            r_db, r_deg = residuals(data.h[:, sel], model.response(f, theta))
            e = np.nansum((r_db / sdb) ** 2 + (r_deg / sdeg) ** 2, axis=1)
        errs.append(np.where(np.isfinite(e), e, np.inf))
    pick = np.argmin(np.array(errs), axis=0)
    return np.array([rows[k][i] for i, k in enumerate(pick)])


def _start_rows(model, data, band, effect_values, given: Sequence[np.ndarray]) -> np.ndarray:
    """Best per-trial start among the given rows, the Levy guess with the effects removed,
    and the median Levy row over trials (robust to a trial whose own guess failed)."""
    levy = levy_starts(model, data, band, effect_values, given[0])
    return best_rows(model, data, band, effect_values,
                     [*given, levy, np.exp(np.median(np.log(levy), axis=0))])


def joint_fit(model: ClosedLoopModel, data: AxisData, band: tuple[float, float],
              base: np.ndarray, starts: Sequence[Mapping[str, float]] = ({},),
              max_nfev: int = 200, pairs: Sequence[tuple[np.ndarray, Mapping]] = (),
              refine_best: int | None = None, screen_nfev: int | None = None) -> JointFit:
    """Fit ``model`` to every trial of ``data`` at once: arm parameters per trial, effect
    parameters shared (see the module docstring). ``base`` (T, 5), or a list of such:
    starting arm parameters (SI units); ``starts``: candidate starting values of the shared
    effect parameters; ``pairs``: further (base, start) combinations. Every combination is
    tried briefly on a subset of trials, the best ``refine_best`` (default
    :data:`_REFINE_BEST`) refined on all, at most ``max_nfev`` evaluations each (the brief
    tries: ``screen_nfev``, default :data:`_SCREEN_NFEV`).
    """
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = _Joint(model, data, sel)
    bases = [base] if isinstance(base, np.ndarray) else list(base)
    combos = [(b, st) for b in bases for st in starts] + list(pairs)
    if len(combos) > 1:
        x0s = _screen(model, data, sel, combos, prob,
                      _REFINE_BEST if refine_best is None else refine_best,
                      _SCREEN_NFEV if screen_nfev is None else screen_nfev)
    else:
        x0s = [prob.pack(*combos[0])]
    res = None
    for x0 in x0s:
        r = _rescue(prob, model, data, sel, _refine(prob, x0, max_nfev), max_nfev)
        if res is None or r.cost < res.cost:
            res = r
    z = prob.unpack(res.x)
    theta = prob.space.to_theta(z)
    r_db, r_deg = prob.split_res(res.x)
    names = prob.space.names[prob.nb:]
    shared = {n: float(theta[0, prob.nb + j]) for j, n in enumerate(names)}
    s_lo, s_hi = _shared_ci(prob, res, names)
    zres = np.concatenate([r_db * prob.w_db, r_deg * prob.w_deg], axis=1)
    rho = (_lag1(r_db * prob.w_db) + _lag1(r_deg * prob.w_deg)) / 2
    return JointFit(model, theta[:, : prob.nb], shared, s_lo, s_hi, r_db, r_deg,
                    float(np.sum(zres[np.isfinite(zres)] ** 2)), int(zres.size), rho,
                    bool(res.status > 0))


def _refine(prob: _Joint, x0: np.ndarray, max_nfev: int) -> blocklsq.BlockResult:
    return prob.solve(x0, max_nfev, ftol=1e-8, xtol=1e-8)


#: A trial whose misfit exceeds this many times the median trial's is refitted globally.
_OUTLIER = 4.0


def _rescue(prob: _Joint, model: ClosedLoopModel, data: AxisData, sel, res, max_nfev: int):
    """Trials stuck in a poor local minimum of the joint fit (misfit far above the median
    trial's) get new arm parameters from a single-trial fit
    (:func:`armfit.fitting.fit_response`): first a local one from the median arm
    parameters of the trials that fit, then, for a trial still far off, the global
    search. The single-trial fit weighs the trial's residuals by the same noise model's
    standard errors as the joint fit (it is given the whole grid and the band). The joint
    fit is refined again; the better of the two results is returned."""
    per = (res.fun.reshape(prob.T, -1) ** 2).sum(axis=1)
    limit = _OUTLIER * max(np.median(per), 2.0 * prob.f.size)
    bad = np.flatnonzero(per > limit)
    if bad.size == 0:
        return res
    x0 = res.x.copy()
    zb = x0[: prob.T * prob.nb].reshape(prob.T, prob.nb)
    theta = prob.space.to_theta(prob.unpack(res.x))
    shared = theta[0, prob.nb:]
    good = np.setdiff1d(np.arange(prob.T), bad)
    typical = np.exp(np.median(np.log(theta[good, : prob.nb]), axis=0)) if good.size else None
    names = prob.space.names
    band = (float(prob.f[0]), float(prob.f[-1]))

    def place(i: int, fit) -> None:
        row = np.array([fit.params[n] for n in PARAM_NAMES])
        zb[i] = prob.space.clip_z(prob.space.to_z(np.concatenate([row, shared])))[: prob.nb]

    for i in bad:
        kw = dict(se_db=data.se_db[i], se_deg=data.se_deg[i], band=band, strict=False,
                  intervals=False)
        if typical is not None:
            start = dict(zip(names, np.concatenate([typical, shared]), strict=True))
            place(i, fit_response(model, data.f_hz, data.h[i], x0=start,
                                  global_search=False, **kw))
            r = prob.fun(x0).reshape(prob.T, -1)[i]
            if float(r @ r) <= limit:
                continue
        place(i, fit_response(model, data.f_hz, data.h[i], **kw))
    res2 = _refine(prob, x0, max_nfev)
    return res2 if res2.cost < res.cost else res


#: Trials used (at most) while screening starting points, and their evaluation budget.
_SCREEN_TRIALS = 9
_SCREEN_NFEV = 12
_REFINE_BEST = 2


def _screen(model, data: AxisData, sel, combos, prob: _Joint, keep: int = _REFINE_BEST,
            nfev: int = _SCREEN_NFEV) -> np.ndarray:
    """Short fits of every (base, start) pair on a spread-out subset of the trials;
    returns the full starting vectors built from the ``keep`` best."""
    T = data.h.shape[0]
    idx = np.unique(np.linspace(0, T - 1, min(T, _SCREEN_TRIALS)).round().astype(int))
    sub = AxisData(data.axis, data.f_hz, data.h[idx], data.se_db[idx], data.se_deg[idx],
                   tuple(data.starts[i] for i in idx))
    sprob = _Joint(model, sub, sel)
    scored = []
    for b, st in combos:
        r = sprob.solve(sprob.pack(b[idx], st), nfev)
        scored.append((r.cost, b, st, r.x))
    scored.sort(key=lambda t: t[0])
    out = []
    for _, b, st, xs in scored[:keep]:
        x0 = prob.pack(b, st)
        if prob.k:
            x0[-prob.k:] = xs[-prob.k:]
        out.append(x0)
    return out


def _shared_ci(prob: _Joint, res, names) -> tuple[dict[str, float], dict[str, float]]:
    """95 % intervals of the shared parameters from the Jacobian (Schur complement)."""
    if not names:
        return {}, {}
    m, p = res.fun.size, res.x.size
    s2 = 2 * res.cost / max(m - p, 1)
    k = len(names)
    var = s2 * np.diag(blocklsq.shared_covariance(res.jb, res.js))
    half = special.ndtri(0.975) * np.sqrt(np.maximum(var, 0))
    z = res.x[-k:]
    sp = prob.space
    zl = np.clip(z - half, sp.zlo[prob.nb:], sp.zhi[prob.nb:])
    zh = np.clip(z + half, sp.zlo[prob.nb:], sp.zhi[prob.nb:])
    full_l = np.tile(sp.zlo, 1).astype(float)
    full_h = full_l.copy()
    full_l[prob.nb:] = zl
    full_h[prob.nb:] = zh
    tl = sp.to_theta(full_l)[prob.nb:]
    th = sp.to_theta(full_h)[prob.nb:]
    return ({n: float(v) for n, v in zip(names, tl, strict=True)},
            {n: float(v) for n, v in zip(names, th, strict=True)})


# ---------------------------------------------------------------------------
# Diagnosis of one axis
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Candidate:
    """One candidate effect's evidence."""

    effect: str
    params: dict[str, float]
    params_lo: dict[str, float]
    params_hi: dict[str, float]
    rms_db_before: float
    rms_db_after: float
    rms_deg_before: float
    rms_deg_after: float
    rms_norm_before: float
    rms_norm_after: float
    failing_before: tuple[BandError, ...]
    failing_after: tuple[BandError, ...]
    failing_bias_before: float
    failing_bias_after: float
    lr: float
    score: float
    significant: bool
    rss_reduction: float = 0.0


@dataclass(frozen=True)
class AxisDiagnosis:
    """Verdict for one axis: the missing effect (or None), candidates best first."""

    axis: str
    band: tuple[float, float]
    n_trials: int
    missing_effect: str | None
    tied_with: tuple[str, ...]
    candidates: tuple[Candidate, ...]
    failing: tuple[FailingBand, ...]
    base_error: BandError
    verdict: str
    coupling: dict[str, float] = field(default_factory=dict)
    missing_effects: tuple = ()
    error_steps: tuple[float, ...] = ()
    adequate: bool = False
    steps: tuple = ()
    final_error: BandError | None = None
    final_bands: tuple[BandError, ...] = ()
    final_failing: tuple[FailingBand, ...] = ()
    stop: str = ""
    shared: dict = field(default_factory=dict)


def _point_ss(fit: JointFit, se_db, se_deg) -> np.ndarray:
    """Sum over trials of squared normalised residuals, per grid point (n,)."""
    z = np.concatenate([fit.r_db / se_db, fit.r_deg / se_deg], axis=0)
    return np.sum(np.where(np.isfinite(z), z * z, 0.0), axis=0)


def _robust_lr(base: JointFit, fit: JointFit, se_db, se_deg) -> tuple[float, float]:
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


def _union_bias(f, fit: JointFit, se_db, se_deg, ranges) -> float:
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


def _errors(f, fit: JointFit, data: AxisData, sel, bands) -> tuple[BandError, ...]:
    se_db, se_deg = data.noise_se(sel)
    return tuple(band_error(f, fit.r_db, fit.r_deg, se_db, se_deg, lo, hi) for lo, hi in bands)


def _start_array(data: AxisData) -> np.ndarray:
    return np.array([[s[n] for n in PARAM_NAMES] for s in data.starts], float)


def fit_base(data: AxisData, band: tuple[float, float]) -> JointFit:
    """The base model (eq. 4) fitted jointly to every trial of one axis."""
    base_model = ClosedLoopModel.for_axis(data.axis)
    start = _start_array(data)
    return joint_fit(base_model, data, band,
                     [start, _start_rows(base_model, data, band, {}, [start])])


def fit_candidate(data: AxisData, band: tuple[float, float], base: JointFit,
                  effect: Effect) -> JointFit:
    """Base + ``effect`` fitted jointly (effect shared), never worse than ``base``."""
    start = _start_array(data)
    model = ClosedLoopModel.for_axis(data.axis).with_effect(effect)
    starts = [{f"{effect.name}.{k}": v for k, v in st.items()}
              for st in effect.start_points(model.mp)]
    # from the base fit and from the given starts: a strong missing effect can pull
    # the base fit far from the arm parameters the extended model needs
    pairs = [(_start_rows(model, data, band, st, [start, base.base]), st)
             for st in starts[1:]]
    fit = joint_fit(model, data, band, [base.base, start], starts, pairs=pairs)
    if fit.rss > base.rss:  # nested: never worse than the base fit
        fit = JointFit(model, base.base, {f"{effect.name}.{k}": v
                                          for k, v in effect.null_values(model.mp).items()},
                       {}, {}, base.r_db, base.r_deg, base.rss, base.n_res, base.rho,
                       base.converged)
    return fit


def assess(data: AxisData, band: tuple[float, float], base: JointFit,
           fits: Sequence[tuple[Effect, JointFit]]) -> AxisDiagnosis:
    """Failing bands of the base fit, the evidence for each candidate fit, the verdict."""
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    f = data.f_hz[sel]
    se_db, se_deg = data.noise_se(sel)
    t_db, t_deg = trial_statistics(base.r_db / se_db, base.r_deg / se_deg)
    fails = failing_bands(f, t_db, t_deg, base.r_db.mean(axis=0), base.r_deg.mean(axis=0),
                          size_db=(base.r_db / se_db).mean(axis=0),
                          size_deg=(base.r_deg / se_deg).mean(axis=0))
    fail_ranges = [(fb.lo_hz, fb.hi_hz) for fb in fails]
    base_err = band_error(f, base.r_db, base.r_deg, se_db, se_deg, band[0], band[1])
    fail_before = _errors(f, base, data, sel, fail_ranges)

    cands = []
    for eff, fit in fits:
        lr, n_eff, reduction = _robust_lr(base, fit, se_db, se_deg)
        score = float(lr - len(eff.params) * np.log(n_eff))
        err = band_error(f, fit.r_db, fit.r_deg, se_db, se_deg, band[0], band[1])
        short = {n.split(".", 1)[1]: v for n, v in fit.shared.items()}
        cands.append(Candidate(
            effect=eff.name, params=short,
            params_lo={n.split(".", 1)[1]: v for n, v in fit.shared_lo.items()},
            params_hi={n.split(".", 1)[1]: v for n, v in fit.shared_hi.items()},
            rms_db_before=base_err.rms_db, rms_db_after=err.rms_db,
            rms_deg_before=base_err.rms_deg, rms_deg_after=err.rms_deg,
            rms_norm_before=base_err.rms_norm, rms_norm_after=err.rms_norm,
            failing_before=fail_before, failing_after=_errors(f, fit, data, sel, fail_ranges),
            failing_bias_before=_union_bias(f, base, se_db, se_deg, fail_ranges),
            failing_bias_after=_union_bias(f, fit, se_db, se_deg, fail_ranges),
            lr=float(lr), score=score, rss_reduction=reduction,
            significant=bool(score > SIGNIFICANT_BIC and reduction >= MIN_REDUCTION)))
    cands.sort(key=lambda c: c.score, reverse=True)
    best = cands[0] if cands and cands[0].significant else None
    tied = tuple(c.effect for c in cands[1:]
                 if best is not None and c.significant
                 and best.score - c.score < max(TIE_BIC, TIE_FRACTION * best.score))
    if best is None:
        verdict = ("no candidate effect improves the fit beyond the noise: the 5-parameter "
                   "model explains this axis")
    else:
        p = ", ".join(f"{k}={v:.4g}" for k, v in best.params.items())
        verdict = (f"missing effect: {best.effect} ({p}); error {best.rms_db_before:.2f} dB / "
                   f"{best.rms_deg_before:.1f} deg -> {best.rms_db_after:.2f} dB / "
                   f"{best.rms_deg_after:.1f} deg")
        if tied:
            verdict += f"; {', '.join(tied)} explain(s) the data about equally well"
    return AxisDiagnosis(axis=data.axis, band=(float(f[0]), float(f[-1])),
                         n_trials=int(data.h.shape[0]), missing_effect=None if best is None
                         else best.effect, tied_with=tied, candidates=tuple(cands),
                         failing=tuple(fails), base_error=base_err, verdict=verdict)


def diagnose_axis(data: AxisData, *, band: tuple[float, float],
                  effects: Sequence[Effect] | None = None, max_steps: int = MAX_STEPS,
                  min_effect_db: float = MIN_EFFECT_DB,
                  min_effect_deg: float = MIN_EFFECT_DEG) -> AxisDiagnosis:
    """The stepwise search of :func:`diagnose` on one axis.

    data: the axis's trial responses with per-trial base starts; band: (lo, hi) Hz;
    effects: candidates (default: the whole library). See the module docstring for the
    criteria.
    """
    effects = list(EFFECTS.values()) if effects is None else list(effects)
    search = _Search(data, band, effects, max_steps, min_effect_db, min_effect_deg)
    search.start(fit_base(data, band))
    while not search.done:
        screened = search.screen()
        keep = _keep(screened)
        search.take([(e, fit_extend(data, band, search.fits[-1], e, sc)) for e, sc in keep],
                    screened=screened[len(keep):])
    return search.result()


# ---------------------------------------------------------------------------
# From armfit's files to the arrays above
# ---------------------------------------------------------------------------

def _rows(spectra, *, level: str, kind: str, axis: str, grip: float | None = None,
          out_axis: str | None = None) -> Spectra:
    return Spectra.of(spectra).select(level=level, kind=kind, axis=axis, grip=grip,
                                      out_axis=out_axis)


def _trial_matrix(rows: Spectra) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          list]:
    """(f, H (T, n), se_db, se_deg, keys) of trial responses on one grid, in subject,
    grip, run order; keys are (subject, grip_N, run) per trial."""
    rows = rows.sorted(("subject", "grip_N", "run"))
    f = rows.common_grid("trials")
    labels = list(zip(rows.key("subject"), rows.key("grip_N"), rows.key("run"), strict=True))
    return f, rows.h, rows.se_db, rows.se_deg, labels


def _param_row(params, axis: str, grip: float | None):
    rows = params[params["axis"] == axis]
    if grip is not None and "grip_N" in params.columns:
        by_grip = rows[np.isclose(rows["grip_N"].to_numpy(float), grip)]
        if len(by_grip):
            return by_grip.iloc[0]
        # nearest grip of the same axis
        return rows.iloc[int(np.argmin(np.abs(rows["grip_N"].to_numpy(float) - grip)))]
    return rows.iloc[0] if len(rows) else None


def axis_data(spectra, params, axis: str) -> AxisData | None:
    """Trial-level measured responses of ``axis`` with per-trial starts from ``params``
    (the row of the trial's grip for grip fits, the axis row for nominal fits).
    None when the spectra hold no trials of the axis or the params no row for it."""
    rows = _rows(spectra, level="trial", kind="measured", axis=axis)
    if len(rows) == 0 or not (params["axis"] == axis).any():
        return None
    f, H, sdb, sdeg, labels = _trial_matrix(rows)
    starts = []
    for _subject, grip, _run in labels:
        r = _param_row(params, axis, float(grip))
        starts.append({n: float(r[n]) for n in PARAM_NAMES})
    names = tuple(f"sub-{s}_grip-{float(g):g}N" + ("" if run is None else f"_run-{run}")
                  for s, g, run in labels)
    return AxisData(axis, f, H, sdb, sdeg, tuple(starts), names)


def cross_coupling(spectra, data: AxisData, band: tuple[float, float]) -> dict[str, float]:
    """Off-axis motion relative to on-axis motion for force on ``data.axis``, in dB.

    For each other position axis: the median over trials and over the band of
    20 log10(|X_other/F| / |X_axis/F|), the on-axis responses those of ``data``. Absent
    cross responses give no entry.
    """
    out = {}
    axis, H_on = data.axis, data.h
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    for other in AXES:
        if other == axis:
            continue
        rows = _rows(spectra, level="trial", kind="cross", axis=axis, out_axis=other)
        if len(rows) == 0:
            continue
        _, H_c, *_ = _trial_matrix(rows)
        if H_c.shape != H_on.shape:
            continue
        with np.errstate(all="ignore"):
            ratio = 20 * np.log10(np.abs(H_c[:, sel]) / np.abs(H_on[:, sel]))
        if not np.isfinite(ratio).any():  # no signal on that axis (cells flagged no_signal)
            continue
        out[other] = float(np.nanmedian(ratio))
    return out


# ---------------------------------------------------------------------------
# Adequacy, practical significance and the stepwise search
# ---------------------------------------------------------------------------

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
    zdb, zdeg = fit.r_db / se_db, fit.r_deg / se_deg
    with np.errstate(all="ignore"):
        t_db, t_deg = trial_statistics(np.nan_to_num(zdb), np.nan_to_num(zdeg))
    m_db, m_deg = fit.r_db.mean(axis=0), fit.r_deg.mean(axis=0)
    fails = failing_bands(f, t_db, t_deg, m_db, m_deg,
                          size_db=np.where(np.abs(m_db) > min_db,
                                           np.nan_to_num(zdb).mean(axis=0), 0.0),
                          size_deg=np.where(np.abs(m_deg) > min_deg,
                                            np.nan_to_num(zdeg).mean(axis=0), 0.0))
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
    z = np.concatenate([zdb.ravel(), zdeg.ravel()])
    n_res = int(np.isfinite(z).sum())
    nu = max(n_res - n_params, 1)
    return Adequacy(adequate=not fails and not over, overall=overall, bands=bands,
                    over=over, failing=tuple(fails), cost=float(np.nansum(z * z)),
                    cost_expected=float(nu), cost_sd=float(np.sqrt(2.0 * nu)))


def effect_size(fit: JointFit, effect: Effect, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How much ``effect`` at its fitted values changes the fitted response: per grid
    point, the median over trials of |20 log10|H/H₀|| (dB) and |angle(H/H₀)| (deg), H₀
    the same fit with the effect at its null values (every other parameter unchanged)."""
    model = fit.model
    names = model.param_names
    T = fit.base.shape[0]
    theta = {n: fit.base[:, i:i + 1] for i, n in enumerate(PARAM_NAMES)}
    theta.update({n: np.full((T, 1), fit.shared[n]) for n in names if n not in theta})
    null = dict(theta)
    null.update({f"{effect.name}.{k}": np.full((T, 1), v)
                 for k, v in effect.null_values(model.mp).items()})
    with np.errstate(all="ignore"):
        d_db, d_deg = residuals(model.response(f, theta), model.response(f, null))
    return np.nanmedian(np.abs(d_db), axis=0), np.nanmedian(np.abs(d_deg), axis=0)


def practical(f, size_db, size_deg, se_db, se_deg, min_db: float, min_deg: float
              ) -> tuple[bool, float]:
    """Practical significance of an effect whose change of the response is ``size_db``,
    ``size_deg`` (n,): the change exceeds both the measurement noise (median over trials
    of the standard error) and the floor ``min_db`` / ``min_deg`` on at least
    :data:`MIN_RUN` consecutive grid points, in magnitude or in phase. Returns (holds,
    the largest ratio of change to threshold)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        thr_db = np.maximum(min_db, np.nanmedian(np.where(np.isfinite(se_db), se_db, np.nan),
                                                 axis=0))
        thr_deg = np.maximum(min_deg, np.nanmedian(np.where(np.isfinite(se_deg), se_deg,
                                                            np.nan), axis=0))
        r_db = np.nan_to_num(size_db / thr_db)
        r_deg = np.nan_to_num(size_deg / thr_deg)
    mask = (r_db > 1.0) | (r_deg > 1.0)
    return bool(_runs(mask, MIN_RUN)), float(np.max(np.maximum(r_db, r_deg), initial=0.0))


@dataclass(frozen=True)
class Step:
    """One row of the stepwise search: the effect added (None for the base model), its
    parameters as fitted at this step (with 95 % intervals; ``at_bound``: those within
    1 % of a physical bound), the errors of the model after the step (RMS dB, deg and
    normalised), ΔBIC against the previous step and the change the effect makes
    (largest over the band, dB and deg)."""

    effect: str | None
    params: dict[str, float]
    params_lo: dict[str, float]
    params_hi: dict[str, float]
    at_bound: tuple[str, ...]
    rms_db: float
    rms_deg: float
    rms_norm: float
    delta_bic: float
    change_db: float = float("nan")
    change_deg: float = float("nan")


def _short(d: Mapping[str, float], effect: str) -> dict[str, float]:
    pre = effect + "."
    return {k[len(pre):]: float(v) for k, v in d.items() if k.startswith(pre)}


def fit_extend(data: AxisData, band: tuple[float, float], current: JointFit,
               effect: Effect, screened: JointFit | None = None, *,
               quick: bool = False) -> JointFit:
    """``current``'s model plus ``effect``, all effects refitted jointly (shared across
    the trials), warm-started from ``current`` with the new effect at its null point and
    at the screening's values (:func:`screen`; or, without one, at the effect's starting
    points, also with each effect added before restarted at its own starting points);
    never worse than ``current``."""
    start = _start_array(data)
    model = current.model.with_effect(effect)
    null = {**current.shared, **{f"{effect.name}.{k}": v
                                 for k, v in effect.null_values(model.mp).items()}}
    def named(e: Effect, st: Mapping[str, float]) -> dict[str, float]:
        return {f"{e.name}.{k}": v for k, v in st.items()}

    fresh = []
    if screened is not None:
        starts = [null, dict(screened.shared)]
    else:
        starts = [{**current.shared, **named(effect, st)}
                  for st in effect.start_points(model.mp)]
        # an effect added before may have settled where it stood in for this one (a lag
        # for a delay): also start it afresh from its own starting points, one such
        # effect at a time, with each of this effect's
        fresh = [{**current.shared, **named(prev, pst), **named(effect, st)}
                 for prev in current.model.effects
                 for pst in prev.start_points(model.mp)[1:]
                 for st in effect.start_points(model.mp)[1:]]
    # from the current fit and from Levy starts with the effects removed: a strong
    # missing effect can pull the arm parameters far from those the extended model needs
    pairs = [(_start_rows(model, data, band, st, [start, current.base]), st)
             for st in starts[1:] + fresh]
    starts = starts + fresh
    opts = {"refine_best": _QUICK_BEST, "max_nfev": _QUICK_NFEV,
            "screen_nfev": _QUICK_SCREEN_NFEV} if quick else {}
    fit = joint_fit(model, data, band, [current.base], starts, pairs=pairs, **opts)
    if fit.rss > current.rss:  # nested: never worse than the current fit
        fit = JointFit(model, current.base, null, {}, {}, current.r_db, current.r_deg,
                       current.rss, current.n_res, current.rho, current.converged)
    return fit


#: Evaluations of the screening's refinement (``quick`` fits of :func:`fit_extend`): the
#: screening ranks candidates and gives the joint fit on all trials a start, which that
#: fit refines: every starting combination gets a few iterations, the best
#: :data:`_QUICK_BEST` are refined.
_QUICK_NFEV = 60
_QUICK_SCREEN_NFEV = 4
_QUICK_BEST = 2

#: Candidates per step that get the full joint fit after screening (see :func:`screen`).
SCREEN_KEEP = 2
#: Trials in the screening fits.
SCREEN_SUBSET = 3


#: A screened candidate whose subset cost exceeds the best one's by more than this factor
#: gets no joint fit on all trials (it cannot win: the joint fits rank as the screening
#: does when the gap is this large).
SCREEN_GAP = 2.0


def _keep(screened: Sequence[tuple[Effect, JointFit]]) -> list[tuple[Effect, JointFit]]:
    """The screened candidates (lowest subset cost first) that get the joint fit on all
    trials: at most :data:`SCREEN_KEEP`, within :data:`SCREEN_GAP` of the best."""
    if not screened:
        return []
    best = screened[0][1].rss
    return [c for c in screened[:SCREEN_KEEP] if c[1].rss <= SCREEN_GAP * best]


def _subset(data: AxisData, fit: JointFit, idx: np.ndarray,
            band: tuple[float, float]) -> tuple[AxisData, JointFit]:
    """The trials ``idx`` of ``data`` and of ``fit`` (its residuals on ``band``), the
    subset's residual sum of squares weighted as :func:`joint_fit` weighs it."""
    sub = AxisData(data.axis, data.f_hz, data.h[idx], data.se_db[idx], data.se_deg[idx],
                   tuple(data.starts[i] for i in idx))
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    sdb, sdeg = sub.noise_se(sel)
    z = np.concatenate([fit.r_db[idx] / sdb, fit.r_deg[idx] / sdeg], axis=1)
    return sub, JointFit(fit.model, fit.base[idx], fit.shared, fit.shared_lo, fit.shared_hi,
                         fit.r_db[idx], fit.r_deg[idx], float(np.sum(z[np.isfinite(z)] ** 2)),
                         int(z.size), fit.rho, fit.converged)


def screen(data: AxisData, band: tuple[float, float], current: JointFit,
           effect: Effect) -> JointFit:
    """A cheap fit of ``current``'s model plus ``effect``: the same joint fit as
    :func:`fit_extend` (arm parameters per trial, effects shared, from the effect's null
    and starting points) on :data:`SCREEN_SUBSET` trials spread over the axis (one per
    grip in the paper's design) instead of all. Candidates are ranked by the fraction of
    the subset's cost they remove; the best :data:`SCREEN_KEEP` get the joint fit on all
    trials, started from the screening's effect values. Returns the subset's fit."""
    T = data.h.shape[0]
    if T <= SCREEN_SUBSET:
        return fit_extend(data, band, current, effect)
    idx = np.unique(np.linspace(0, T - 1, SCREEN_SUBSET).round().astype(int))
    sub, cur = _subset(data, current, idx, band)
    return fit_extend(sub, band, cur, effect, quick=True)


def _rank(screened: list[tuple[Effect, JointFit]]) -> list[tuple[Effect, JointFit]]:
    """Screening fits lowest subset cost first (the same subset for every candidate;
    ties keep the library's order)."""
    return sorted(screened, key=lambda t: t[1].rss)


def _effect_params(model: ClosedLoopModel, name: str):
    for e in model.effects:
        if e.name == name:
            return e.params
    return ()


class _Search:
    """The state of the stepwise search on one axis (see :func:`diagnose`)."""

    def __init__(self, data: AxisData, band, effects, max_steps, min_db, min_deg):
        self.data, self.band, self.effects = data, band, list(effects)
        self.max_steps, self.min_db, self.min_deg = max_steps, min_db, min_deg
        self.sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
        self.f = data.f_hz[self.sel]
        self.se_db, self.se_deg = data.noise_se(self.sel)
        self.fits: list[JointFit] = []
        self.added: list[Effect] = []
        self.steps: list[Step] = []
        self.adequacies: list[Adequacy] = []
        self.first_candidates: tuple[Candidate, ...] = ()
        self.tied: tuple[str, ...] = ()
        self.stop = ""
        self.done = False

    def n_params(self, fit: JointFit) -> int:
        return fit.base.size + len(fit.shared)

    def start(self, base: JointFit) -> None:
        ad = self._adequacy(base)
        self.fits.append(base)
        self.adequacies.append(ad)
        self.steps.append(Step(None, {}, {}, {}, (), ad.overall.rms_db, ad.overall.rms_deg,
                               ad.overall.rms_norm, float("nan")))
        self._check_stop()

    def _check_stop(self) -> None:
        if self.adequacies[-1].adequate:
            self.done, self.stop = True, "adequate"
        elif len(self.added) >= self.max_steps:
            self.done, self.stop = True, "max-steps"
        elif not self.remaining():
            self.done, self.stop = True, "no-more-effects"

    def remaining(self) -> list[Effect]:
        # no effect twice: a second delay, lag or mass adds nothing a single one's
        # parameters cannot, and two copies of a resonance or reflex are not identifiable
        # from these responses (their order is arbitrary)
        names = {e.name for e in self.added}
        return [e for e in self.effects if e.name not in names]

    def screen(self) -> list[tuple[Effect, JointFit]]:
        """Screening fits (:func:`screen`) of the remaining effects, lowest cost first."""
        return _rank([(e, screen(self.data, self.band, self.fits[-1], e))
                      for e in self.remaining()])

    def take(self, fits: Sequence[tuple[Effect, JointFit]],
             screened: Sequence[tuple[Effect, JointFit]] = ()) -> None:
        """Evaluate this step's candidate fits (on all trials); add the best significant
        one or stop. ``screened``: candidates left at their screening fit (reported
        among the candidates of the first step, never added)."""
        cur = self.fits[-1]
        cands = []
        for eff, fit in fits:
            lr, n_eff, reduction = _robust_lr(cur, fit, self.se_db, self.se_deg)
            score = float(lr - len(eff.params) * np.log(max(n_eff, 2.0)))
            err = band_error(self.f, fit.r_db, fit.r_deg, self.se_db, self.se_deg,
                             *self.band)
            size_db, size_deg = effect_size(fit, eff, self.f)
            prac, _ = practical(self.f, size_db, size_deg, self.se_db, self.se_deg,
                                self.min_db, self.min_deg)
            stat = bool(score > SIGNIFICANT_BIC and reduction >= MIN_REDUCTION)
            cands.append((score, stat and prac, eff, fit, err, reduction, lr,
                          float(np.nanmax(size_db, initial=0.0)),
                          float(np.nanmax(size_deg, initial=0.0))))
        cands.sort(key=lambda c: c[0], reverse=True)
        if not self.added:
            self.first_candidates = tuple(self._candidate(c) for c in cands) + tuple(
                self._screened_candidate(e, sc) for e, sc in screened)
        # an effect with a parameter at a physical bound is only the library's nearest
        # approximation: take it only when no significant candidate is free of bounds
        free = [c for c in cands if c[1]
                and not at_bound(c[2].params, _short(c[3].shared, c[2].name))]
        best = free[0] if free else next((c for c in cands if c[1]), None)
        if not self.added and best is not None:
            self.tied = tuple(c[2].name for c in cands
                              if c[1] and c[2] is not best[2]
                              and best[0] - c[0] < max(TIE_BIC, TIE_FRACTION * best[0]))
        if best is None:
            self.done, self.stop = True, "nothing-significant"
            return
        score, _, eff, fit, _, _, _, cdb, cdeg = best
        self._append(eff, fit, self._adequacy(fit), score, cdb, cdeg)
        self._check_stop()

    def _adequacy(self, fit: JointFit) -> Adequacy:
        return adequacy(self.f, fit, self.se_db, self.se_deg, self.band, self.n_params(fit),
                        self.min_db, self.min_deg)

    def _append(self, eff: Effect, fit: JointFit, ad: Adequacy, score: float,
                change_db: float = float("nan"), change_deg: float = float("nan")) -> None:
        """Record a step: ``eff`` added, the joint fit with it and its adequacy."""
        err = ad.overall
        p = _short(fit.shared, eff.name)
        self.added.append(eff)
        self.fits.append(fit)
        self.adequacies.append(ad)
        self.steps.append(Step(eff.name, p, _short(fit.shared_lo, eff.name),
                               _short(fit.shared_hi, eff.name),
                               tuple(at_bound(eff.params, p)), err.rms_db, err.rms_deg,
                               err.rms_norm, float(score), change_db, change_deg))

    def _candidate(self, c) -> Candidate:
        score, ok, eff, fit, err, reduction, lr, _, _ = c
        base = self.fits[0]
        fail_ranges = [(fb.lo_hz, fb.hi_hz) for fb in self.adequacies[0].failing]
        be = self.adequacies[0].overall
        return Candidate(
            effect=eff.name, params=_short(fit.shared, eff.name),
            params_lo=_short(fit.shared_lo, eff.name),
            params_hi=_short(fit.shared_hi, eff.name),
            rms_db_before=be.rms_db, rms_db_after=err.rms_db,
            rms_deg_before=be.rms_deg, rms_deg_after=err.rms_deg,
            rms_norm_before=be.rms_norm, rms_norm_after=err.rms_norm,
            failing_before=_errors(self.f, base, self.data, self.sel, fail_ranges),
            failing_after=_errors(self.f, fit, self.data, self.sel, fail_ranges),
            failing_bias_before=_union_bias(self.f, base, self.se_db, self.se_deg,
                                            fail_ranges),
            failing_bias_after=_union_bias(self.f, fit, self.se_db, self.se_deg,
                                           fail_ranges),
            lr=float(lr), score=float(score), rss_reduction=float(reduction),
            significant=bool(ok))

    def borrow_model(self, agreement: Mapping[str, dict]) -> ClosedLoopModel | None:
        """The model to refit from the axes' common values, or None: for an axis that is
        not adequate, or that lacks a shared effect named on other axes."""
        have = {e.name for e in self.added}
        lack = [n for n in agreement if n not in have and n in EFFECTS
                and len(self.added) < self.max_steps]
        if self.adequacies[-1].adequate and not lack:
            return None
        if not agreement or (not lack and not any(n in have for n in agreement)):
            return None
        model = self.fits[-1].model
        for n in lack:
            if len(model.effects) < self.max_steps:
                model = model.with_effect(EFFECTS[n])
        return model

    def borrow(self, fit: JointFit) -> None:
        """Take the refit from the common values when it helps: same effects and a lower
        cost (the last step's errors improve), or new effects that are significant in both
        senses (each becomes a step)."""
        cur = self.fits[-1]
        new = [e for e in fit.model.effects if e.name not in {a.name for a in self.added}]
        if fit.rss >= cur.rss:
            return
        if new:
            lr, n_eff, reduction = _robust_lr(cur, fit, self.se_db, self.se_deg)
            k = sum(len(e.params) for e in new)
            score = float(lr - k * np.log(max(n_eff, 2.0)))
            prac = all(practical(self.f, *effect_size(fit, e, self.f), self.se_db,
                                 self.se_deg, self.min_db, self.min_deg)[0] for e in new)
            if not (score > SIGNIFICANT_BIC and reduction >= MIN_REDUCTION and prac):
                return
        ad = self._adequacy(fit)
        err = ad.overall
        if new:
            for e in new:
                self._append(e, fit, ad, score)
        else:
            last = self.steps[-1]
            p = _short(fit.shared, last.effect) if last.effect else {}
            self.steps[-1] = replace(last, params=p or last.params,
                                     params_lo=_short(fit.shared_lo, last.effect or ""),
                                     params_hi=_short(fit.shared_hi, last.effect or ""),
                                     rms_db=err.rms_db, rms_deg=err.rms_deg,
                                     rms_norm=err.rms_norm)
            self.fits[-1] = fit
            self.adequacies[-1] = ad
        self.stop = "adequate" if ad.adequate else self.stop

    def _screened_candidate(self, eff: Effect, fit: JointFit) -> Candidate:
        """A candidate that the screening ranked below the joint fits: its subset fit's
        parameters, not significant (its error fields are NaN: not fitted on all)."""
        nan = float("nan")
        be = self.adequacies[0].overall
        return Candidate(eff.name, _short(fit.shared, eff.name), {}, {}, be.rms_db, nan,
                         be.rms_deg, nan, be.rms_norm, nan, (), (), nan, nan, 0.0, nan,
                         False, nan)

    def result(self) -> AxisDiagnosis:
        final = self.fits[-1]
        ad = self.adequacies[-1]
        missing = []
        for i, eff in enumerate(self.added):
            p = _short(final.shared, eff.name)
            missing.append(MissingEffect(
                eff.name, p, _short(final.shared_lo, eff.name),
                _short(final.shared_hi, eff.name), tuple(at_bound(eff.params, p)),
                self.steps[i + 1].rms_norm))
        errors = [s.rms_norm for s in self.steps]
        for i in range(1, len(errors)):      # nested fits: never rises (guard rounding)
            errors[i] = min(errors[i], errors[i - 1])
        return AxisDiagnosis(
            axis=self.data.axis, band=(float(self.f[0]), float(self.f[-1])),
            n_trials=int(self.data.h.shape[0]),
            missing_effect=missing[0].effect if missing else None, tied_with=self.tied,
            candidates=self.first_candidates, failing=self.adequacies[0].failing,
            base_error=self.adequacies[0].overall,
            verdict=verdict_text(self.adequacies[0], ad, missing, errors, self.stop),
            missing_effects=tuple(missing), error_steps=tuple(errors),
            adequate=bool(ad.adequate), steps=tuple(self.steps),
            final_error=ad.overall, final_bands=ad.bands, final_failing=ad.failing,
            stop=self.stop)


@dataclass(frozen=True)
class MissingEffect:
    """An effect the stepwise search added: its parameters in the final joint fit with
    95 % intervals, those at a bound, and the error/noise after the step that added it."""

    effect: str
    params: dict[str, float]
    params_lo: dict[str, float]
    params_hi: dict[str, float]
    at_bound: tuple[str, ...]
    rms_norm_after: float


def _where(bands: Sequence[BandError], failing: Sequence[FailingBand]) -> str:
    parts = [f"{fb.lo_hz:.3g}–{fb.hi_hz:.3g} Hz ({fb.description})" for fb in failing]
    covered = [(fb.lo_hz, fb.hi_hz) for fb in failing]
    for b in bands:
        if not any(lo <= b.hi_hz and hi >= b.lo_hz for lo, hi in covered):
            parts.append(f"{b.lo_hz:g}–{b.hi_hz:g} Hz ({b.rms_norm:.1f}× noise, "
                         f"{b.rms_db:.2f} dB / {b.rms_deg:.1f} deg RMS)")
    return "; ".join(parts)


def verdict_text(base: Adequacy, final: Adequacy, missing: Sequence[MissingEffect],
                 errors: Sequence[float], stop: str) -> str:
    """The verdict of one axis in words (see :func:`diagnose`)."""
    def eff_words(m: MissingEffect) -> str:
        return m.effect + " (" + ", ".join(f"{k}={v:.4g}" for k, v in m.params.items()) + ")"
    bounded = [m for m in missing if m.at_bound]
    if final.adequate and not missing:
        return (f"adequate: nothing missing — the 5-parameter model fits within the noise "
                f"in every band (error {errors[0]:.2f}× noise)")
    chain = " → ".join(f"{e:.3g}" for e in errors)
    if final.adequate and not bounded:
        return (f"adequate after adding {', '.join(eff_words(m) for m in missing)}: "
                f"error/noise {chain}, within the noise in every band")
    text = ("still inadequate" if not final.adequate else "within the noise, but")
    if missing:
        text += f" after adding {', '.join(eff_words(m) for m in missing)} (error/noise {chain})"
    else:
        text += (f": error {errors[0]:.2f}× noise and no library effect improves it "
                 "significantly")
    if not final.adequate:
        where = _where(final.over, final.failing)
        text += f"; misfit remains in {where}" if where else ""
    for m in bounded:
        text += (f"; {m.effect} has {', '.join(m.at_bound)} at a physical bound, so it is "
                 f"only the library's nearest approximation, not the answer")
    if not final.adequate or bounded:
        text += ("; the missing physics may lie outside the effect library (write it as "
                 "an effect file and rerun with --effects FILE)")
        if stop == "max-steps":
            text += "; the search stopped at --max-steps"
    return text


def _base_task(args):
    data, band = args
    return fit_base(data, band)


def _screen_task(args):
    data, band, current, effect = args
    return screen(data, band, current, effect)


def _extend_task(args):
    data, band, current, effect, screened = args
    return fit_extend(data, band, current, effect, screened)


def diagnose(spectra, params, *, band: tuple[float, float] | None = None,
             axes: Sequence[str] = AXES,
             effects: Sequence[Effect] | None = None, jobs: int = 1,
             max_steps: int = MAX_STEPS, min_effect_db: float = MIN_EFFECT_DB,
             min_effect_deg: float = MIN_EFFECT_DEG,
             share: Sequence[str] | None = None) -> list[AxisDiagnosis]:
    """Diagnose every axis present in both ``spectra`` (a spectra DataFrame) and
    ``params`` (a params DataFrame, grip or nominal fits) by a stepwise search.

    Per axis: fit the base model to every trial (arm parameters per trial); while the
    model is not adequate (:func:`adequacy`), fit the current model plus each remaining
    effect (all effects refitted jointly, shared by the trials, warm-started), add the
    candidate with the highest ΔBIC among those significant in both senses — ΔBIC >
    :data:`SIGNIFICANT_BIC` with at least :data:`MIN_REDUCTION` of the cost removed, and
    a change of the response larger than the noise and than ``min_effect_db`` /
    ``min_effect_deg`` (:func:`practical`) — and repeat, at most ``max_steps`` times. No
    effect is added twice. ``share``: effects whose parameters the axes' fits are
    compared for agreement (default :data:`SHARED_EFFECTS`), see
    :func:`cross_axis_agreement`.

    ``band`` defaults to the whole grid of the spectra; ``jobs`` > 1 runs the fits of a
    step (one per axis and candidate) in parallel processes — the results do not depend
    on ``jobs``.
    """
    effects = list(EFFECTS.values()) if effects is None else list(effects)
    spectra = Spectra.of(spectra)
    searches: list[_Search] = []
    for axis in axes:
        data = axis_data(spectra, params, axis)
        if data is None:
            continue
        b = band or (float(data.f_hz[0]), float(data.f_hz[-1]))
        searches.append(_Search(data, b, effects, max_steps, min_effect_db, min_effect_deg))
    if not searches:
        return []
    pool = process_pool(jobs, preload=("armfit.diagnose",)) if jobs > 1 else None
    try:
        run = pool.map if pool is not None else map
        bases = list(run(_base_task, [(s.data, s.band) for s in searches]))
        for s, base in zip(searches, bases, strict=True):
            s.start(base)
        while True:
            live = [s for s in searches if not s.done]
            if not live:
                break
            # cheap screening of every remaining effect (one task per axis and effect,
            # in parallel with jobs > 1), then joint fits of the best
            stasks = [(s, e) for s in live for e in s.remaining()]
            sfits = list(run(_screen_task, [(s.data, s.band, s.fits[-1], e)
                                            for s, e in stasks]))
            screened = {id(s): _rank([(e, sc) for (t, e), sc
                                      in zip(stasks, sfits, strict=True) if t is s])
                        for s in live}
            tasks = [(s, e, sc) for s in live for e, sc in _keep(screened[id(s)])]
            fits = list(run(_extend_task, [(s.data, s.band, s.fits[-1], e, sc)
                                           for s, e, sc in tasks]))
            for s in live:
                full = {e.name: fit for (t, e, _), fit in zip(tasks, fits, strict=True)
                        if t is s}
                s.take([(e, full[e.name]) for e, _ in screened[id(s)] if e.name in full],
                       screened=[(e, sc) for e, sc in screened[id(s)]
                                 if e.name not in full])
        share = SHARED_EFFECTS if share is None else tuple(share)
        agreement = cross_axis_agreement([s.result() for s in searches], share)
        # an axis whose search ended inadequate, or without a shared effect the other
        # axes name, tries the axes' common values as a start (one joint fit each)
        tasks = [(s, s.borrow_model(agreement)) for s in searches]
        tasks = [(s, m) for s, m in tasks if m is not None]
        if tasks:
            fits = list(run(_borrow_task, [(s.data, s.band, s.fits[-1], m, agreement)
                                           for s, m in tasks]))
            for (s, _), fit in zip(tasks, fits, strict=True):
                s.borrow(fit)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    out = []
    for s in searches:
        d = s.result()
        out.append(replace(d, coupling=cross_coupling(spectra, s.data, s.band)))
    agreement = cross_axis_agreement(out, share)
    if agreement:
        out = [replace(d, shared=agreement) for d in out]
    return out


def _borrow_task(args):
    data, band, current, model, agreement = args
    return fit_borrowed(data, band, current, model, agreement)


def fit_borrowed(data: AxisData, band: tuple[float, float], current: JointFit,
                 model: ClosedLoopModel, agreement: Mapping[str, dict]) -> JointFit:
    """``model`` (``current``'s effects plus any shared effect it lacks) fitted jointly
    to the axis, started from the common values of the shared effects across axes
    (``agreement``, see :func:`cross_axis_agreement`) and from ``current``; all
    parameters free. Never worse than ``current`` on its own effects."""
    common = {f"{name}.{p}": v["common"] for name, e in agreement.items()
              for p, v in e["params"].items() if f"{name}.{p}" in model.param_names}
    null = {}
    for e in model.effects:
        null.update({f"{e.name}.{k}": v for k, v in e.null_values(model.mp).items()})
    st_common = {**null, **current.shared, **common}
    st_current = {**null, **current.shared}
    start = _start_array(data)
    pairs = [(_start_rows(model, data, band, st_common, [start, current.base]), st_common)]
    return joint_fit(model, data, band, [current.base], [st_common, st_current], pairs=pairs)


#: Apparatus effects (latency, sensor lag) that act alike on every axis: their fitted
#: parameters are compared across axes by default.
SHARED_EFFECTS: tuple[str, ...] = ("delay", "lowpass")


def cross_axis_agreement(results: Sequence[AxisDiagnosis], share: Sequence[str]
                         ) -> dict[str, dict]:
    """For each effect of ``share`` named on two or more axes: the precision-weighted
    common value of each parameter (weights from the 95 % intervals, in the fitter's
    search coordinate: log for log parameters), the χ² of the axes' values about it
    (degrees of freedom: axes − 1) and whether the axes disagree (p < 0.01). The common
    value is the one-step joint estimate: where each axis's cost is quadratic in the
    parameter, the joint minimum of the summed costs is this weighted mean."""
    out: dict[str, dict] = {}
    for name in share:
        named = [(d.axis, m) for d in results for m in d.missing_effects if m.effect == name]
        if len(named) < 2:
            continue
        try:
            eff = EFFECTS[name]
        except KeyError:
            continue
        entry: dict = {"axes": [a for a, _ in named], "params": {}, "disagree": False}
        for p in eff.params:
            vals, ws = [], []
            for _, m in named:
                v, lo, hi = (m.params.get(p.name), m.params_lo.get(p.name),
                             m.params_hi.get(p.name))
                if v is None or lo is None or hi is None:
                    continue
                tr = (lambda x: np.log(max(x, 1e-300))) if p.log else (lambda x: x)
                half = (tr(hi) - tr(lo)) / 2.0
                if not (np.isfinite(half) and half > 0):
                    continue
                sd = half / special.ndtri(0.975)
                vals.append(tr(v))
                ws.append(1.0 / sd ** 2)
            if len(vals) < 2:
                continue
            vals, ws = np.array(vals), np.array(ws)
            common = float(np.sum(ws * vals) / np.sum(ws))
            chi2 = float(np.sum(ws * (vals - common) ** 2))
            pval = float(special.chdtrc(len(vals) - 1, chi2))
            value = float(np.exp(common)) if p.log else common
            # practically different: the values spread by more than 10 % of the value
            # (log parameters) or than 10 % of the common value (linear ones)
            spread = float(np.max(vals) - np.min(vals))
            big = spread > (np.log(1.1) if p.log else 0.1 * abs(common))
            entry["params"][p.name] = {"common": value, "chi2": chi2,
                                       "dof": len(vals) - 1, "p": pval}
            entry["disagree"] = bool(entry["disagree"] or (pval < 0.01 and big))
        if entry["params"]:
            out[name] = entry
    return out


# compare: model against measurements, overall and per band
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Comparison:
    """Errors of one model against one set of measurements.

    level: "mean" | "median" | "trial"; model: "base" or "base+<effect>[+…]"; overall and
    per-band errors (:data:`BANDS`); failing: significant bands with words; params: the
    effect parameters fitted (empty for the base model).
    """

    axis: str
    grip_N: float | None
    level: str
    model: str
    overall: BandError
    bands: tuple[BandError, ...]
    failing: tuple[FailingBand, ...]
    params: dict[str, float]
    n_trials: int


def _summary(axis, grip, level, label, f, r_db, r_deg, se_db, se_deg, band, params, n,
             overall_band: tuple[float, float] | None = None) -> Comparison:
    """One :class:`Comparison` from residuals (dB, deg; (n,) or (T, n)) on ``f`` and the
    noise model's standard errors: failing bands and the :data:`BANDS` rows within
    ``band``, the overall row over ``overall_band`` (default ``band``)."""
    sel = (f >= band[0]) & (f <= band[1])
    r_db2, r_deg2 = np.atleast_2d(r_db)[:, sel], np.atleast_2d(r_deg)[:, sel]
    z_db, z_deg = noise.normalised(r_db2, r_deg2, np.atleast_2d(se_db)[:, sel],
                                   np.atleast_2d(se_deg)[:, sel])
    t_db, t_deg = trial_statistics(z_db, z_deg)
    fails = failing_bands(f[sel], t_db, t_deg, r_db2.mean(axis=0), r_deg2.mean(axis=0),
                          size_db=z_db.mean(axis=0), size_deg=z_deg.mean(axis=0))
    overall = band_error(f, r_db, r_deg, se_db, se_deg, *(overall_band or band))
    within = (f[sel], np.asarray(r_db)[..., sel], np.asarray(r_deg)[..., sel],
              np.asarray(se_db)[..., sel], np.asarray(se_deg)[..., sel])
    bands = tuple(band_error(*within, lo, hi) for lo, hi in BANDS
                  if hi > band[0] and lo < band[1])
    return Comparison(axis, grip, level, label, overall, bands, tuple(fails), params, n)



def _fit_effects_aggregate(base_model, theta, effects, f, h, se_db, se_deg, band):
    """Nested refit of base + effects on one aggregate, warm-started at the effects'
    null point and at their starting points; never worse than the base."""
    model = base_model
    for e in effects:
        model = model.with_effect(e)
    base = {n: theta[n] for n in PARAM_NAMES}
    best = None
    starts = model.start_points(base)
    # local refits from each starting point, and one global search warm-started at the
    # null point (a strong effect can make the given arm parameters a poor start)
    for i, start in enumerate([*starts, starts[0]]):
        fit = fit_response(model, f, h, se_db=se_db, se_deg=se_deg, band=band, x0=start,
                           global_search=i == len(starts), strict=False)
        if best is None or fit.objective < best.objective:
            best = fit
    return model, best.params


def compare(spectra, params, *, level: str = "mean", band: tuple[float, float] | None = None,
            effects: Sequence[Effect] = ()) -> list[Comparison]:
    """Compare the model(s) of ``params`` (a params DataFrame) with ``spectra``.

    level "mean": each axis × grip mean (the grip's row of grip fits, or the axis row of
    nominal fits); "median": each axis median (nominal fits); "trial": every trial of an
    axis, the five arm parameters refitted per trial from the model's values so that
    between-subject differences do not count as model error (significance by a t test
    across trials). ``effects``: add these effects and refit (nested, warm-started; shared
    across trials at level "trial"); both the base and the extended model are reported.
    ``band`` defaults to the whole grid; at levels "mean" and "median" the overall row of
    a params row's model is then taken over the band it was fitted on (:func:`fit_band`),
    so its ``rms_norm`` is the params file's (the same noise model on the same bins).
    """
    if level not in ("mean", "median", "trial"):
        raise UsageError(f"{{opt}} must be mean, median or trial, got {level!r}",
                         option="level=")
    spectra = Spectra.of(spectra)
    grip_model = "grip_N" in params.columns
    if level == "median" and grip_model:
        raise UsageError("grip fits are compared at {opt:level} mean or trial; the median "
                         "pools all grips (use nominal fits)")
    out: list[Comparison] = []
    for axis in AXES:
        if not (params["axis"] == axis).any():
            continue
        if level == "trial":
            data = axis_data(spectra, params, axis)
            if data is None:
                continue
            b = band or (float(data.f_hz[0]), float(data.f_hz[-1]))
            sel = (data.f_hz >= b[0]) & (data.f_hz <= b[1])
            f = data.f_hz[sel]
            start = _start_array(data)
            # the params' own model (its effects start at the params' values)
            base_model, theta0 = model_from_params(_param_row(params, axis, None))
            shared0 = {k: v for k, v in theta0.items() if k not in PARAM_NAMES}
            fit = joint_fit(base_model, data, b, start, [shared0])
            se = data.noise_se(sel)
            out.append(_summary(axis, None, level, model_label(base_model), f, fit.r_db,
                                fit.r_deg, *se, b, dict(fit.shared), data.h.shape[0]))
            if effects:
                model = base_model
                for e in effects:
                    model = model.with_effect(e)
                # nested: the fitted shared values, the new effects at null, then at each of
                # their starting points
                null = {k: v for k, v in model.null_theta(theta0).items()
                        if k not in PARAM_NAMES}
                starts = [{**null, **fit.shared}]
                for e in effects:
                    for st in e.start_points(model.mp)[1:]:
                        starts.append({**starts[0],
                                       **{f"{e.name}.{k}": v for k, v in st.items()}})
                fe = joint_fit(model, data, b, [fit.base, start], starts)
                if fe.rss > fit.rss:
                    fe = fit
                out.append(_summary(axis, None, level, model_label(model), f, fe.r_db,
                                    fe.r_deg, *se, b, dict(fe.shared), data.h.shape[0]))
            continue
        grips = [None]
        if level == "mean":
            rows = _rows(spectra, level="mean", kind="measured", axis=axis)
            grips = sorted(float(g) for g in rows.values_of("grip_N"))
        for grip in grips:
            rows = _rows(spectra, level=level, kind="measured", axis=axis, grip=grip)
            if len(rows) == 0:
                continue
            f, h, se_db, se_deg = rows.row(0)
            prow = _param_row(params, axis, grip)
            model, theta = model_from_params(prow)
            b = band or (float(f[0]), float(f[-1]))
            nse = noise.standard_errors(se_db, se_deg)
            with np.errstate(all="ignore"):
                r_db, r_deg = residuals(h, model.response(f, theta))
            n = int(rows.key("n")[0])
            out.append(_summary(axis, grip, level, model_label(model), f, r_db, r_deg, *nse,
                                b, {}, n, None if band else fit_band(prow, f)))
            if effects:
                model_e, th_e = _fit_effects_aggregate(model, theta, effects, f, h, se_db,
                                                       se_deg, b)
                with np.errstate(all="ignore"):
                    r_db, r_deg = residuals(h, model_e.response(f, th_e))
                eff_params = {k: v for k, v in th_e.items() if k not in PARAM_NAMES}
                out.append(_summary(axis, grip, level, model_label(model_e), f, r_db,
                                    r_deg, *nse, b, eff_params, n))
    return out


def model_label(model: ClosedLoopModel) -> str:
    """"base" or "base+<effect>+…"."""
    return "+".join(["base", *(e.name for e in model.effects)])


# ---------------------------------------------------------------------------
# JSON documents
# ---------------------------------------------------------------------------

def band_to_dict(b: BandError) -> dict:
    """A :class:`BandError` as a JSON-ready dict."""
    return {"lo_hz": b.lo_hz, "hi_hz": b.hi_hz, "rms_db": b.rms_db, "rms_deg": b.rms_deg,
            "rms_norm": b.rms_norm, "bias_norm": b.bias_norm, "n_points": b.n_points}


def diagnosis_to_dict(results: Sequence[AxisDiagnosis]) -> dict:
    """The JSON document of ``armfit diagnose`` (schema in docs/formats.md, "Diagnosis JSON")."""
    axes = {}
    for d in results:
        axes[d.axis] = {
            "missing_effect": d.missing_effect,
            "tied_with": list(d.tied_with),
            "verdict": d.verdict,
            "band_hz": list(d.band),
            "n_trials": d.n_trials,
            "base_error": band_to_dict(d.base_error),
            "failing_bands": [asdict(fb) for fb in d.failing],
            "cross_coupling_db": d.coupling,
            # a candidate the screening left out has no errors on all trials: null
            "candidates": [{
                "effect": c.effect, "params": c.params, "params_lo": c.params_lo,
                "params_hi": c.params_hi,
                "rms_db_before": c.rms_db_before, "rms_db_after": finite_or_none(c.rms_db_after),
                "rms_deg_before": c.rms_deg_before,
                "rms_deg_after": finite_or_none(c.rms_deg_after),
                "rms_norm_before": c.rms_norm_before,
                "rms_norm_after": finite_or_none(c.rms_norm_after),
                "failing_bias_before": finite_or_none(c.failing_bias_before),
                "failing_bias_after": finite_or_none(c.failing_bias_after),
                "failing_before": [band_to_dict(b) for b in c.failing_before],
                "failing_after": [band_to_dict(b) for b in c.failing_after],
                "lr": c.lr, "score": finite_or_none(c.score),
                "rss_reduction": finite_or_none(c.rss_reduction), "significant": c.significant,
            } for c in d.candidates],
            "missing_effects": [{
                "effect": m.effect, "params": m.params, "params_lo": m.params_lo,
                "params_hi": m.params_hi, "at_bound": list(m.at_bound),
                "rms_norm_after": m.rms_norm_after} for m in d.missing_effects],
            "error_steps": list(d.error_steps),
            "adequate": bool(d.adequate),
            "stop": d.stop,
            "steps": [{
                "effect": s.effect, "params": s.params, "params_lo": s.params_lo,
                "params_hi": s.params_hi, "at_bound": list(s.at_bound), "rms_db": s.rms_db,
                "rms_deg": s.rms_deg, "rms_norm": s.rms_norm,
                "delta_bic": finite_or_none(s.delta_bic),
                "change_db": finite_or_none(s.change_db),
                "change_deg": finite_or_none(s.change_deg),
            } for s in d.steps],
            "final_error": None if d.final_error is None else band_to_dict(d.final_error),
            "final_bands": [band_to_dict(b) for b in d.final_bands],
            "final_failing_bands": [asdict(fb) for fb in d.final_failing]}
    shared = next((d.shared for d in results if d.shared), {})
    return {"axes": axes, "shared_effects": shared}
