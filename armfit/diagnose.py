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
fit per candidate (T·5 + k parameters, block-sparse Jacobian by vectorised forward
differences) is warm-started from the base
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

Failing bands: per frequency, the mean over trials of the normalised residual of the base
fit, divided by its standard error across trials (a t statistic); runs of at least
:data:`MIN_RUN` grid points with |t| > :data:`T_FAIL` and a mean normalised residual above 1
(a systematic error larger than one trial's noise) are the bands where the model fails.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import optimize, sparse, stats

from armfit.fitting import ParamSpace, log_errors
from armfit.models.arm import PARAM_NAMES, ClosedLoopModel
from armfit.models.effects import EFFECTS, Effect

#: Standard error bands of the compare table (Hz).
BANDS: tuple[tuple[float, float], ...] = ((0.1, 1.0), (1.0, 3.0), (3.0, 10.0), (10.0, 30.0))
#: ΔBIC above which an effect is reported as significant.
SIGNIFICANT_BIC = 10.0
#: Fraction of the residual sum of squares an effect must remove to be reported: with
#: many trials a consistent estimator bias of a few hundredths of a dB reaches any ΔBIC,
#: but explains almost nothing.
MIN_REDUCTION = 0.05
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
#: Floors for standard errors (dB, deg), so a near-noiseless bin cannot dominate.
SE_FLOOR_DB = 0.01
SE_FLOOR_DEG = 0.06
#: Degrees weighted like 1 dB in unweighted comparisons (1 neper ↔ 1 rad).
UNIT_DEG = float(np.degrees(1.0) / (20.0 / np.log(10.0)))


# ---------------------------------------------------------------------------
# Residuals and error summaries
# ---------------------------------------------------------------------------

def residuals(h_meas: np.ndarray, h_model: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measured relative to model: (20 log10|Hm/Hmod| in dB, angle(Hm/Hmod) in deg)."""
    db, deg = log_errors(h_model, h_meas)
    return -db, -deg


def _floor(se_db, se_deg) -> tuple[np.ndarray, np.ndarray]:
    sdb = np.asarray(se_db, float)
    sdeg = np.asarray(se_deg, float)
    sdb = np.where(np.isfinite(sdb), np.maximum(sdb, SE_FLOOR_DB), np.inf)
    sdeg = np.where(np.isfinite(sdeg), np.maximum(sdeg, SE_FLOOR_DEG), np.inf)
    return sdb, sdeg


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
    """RMS errors over ``lo <= f <= hi`` of residual arrays (…, n_freq), pooled."""
    f = np.asarray(f_hz, float)
    sel = (f >= lo) & (f <= hi)
    sdb, sdeg = _floor(se_db, se_deg)
    rdb = np.asarray(r_db)[..., sel]
    rdeg = np.asarray(r_deg)[..., sel]
    if rdb.size == 0:
        nan = float("nan")
        return BandError(lo, hi, nan, nan, nan, 0)
    zdb = rdb / np.broadcast_to(sdb, np.shape(r_db))[..., sel]
    zdeg = rdeg / np.broadcast_to(sdeg, np.shape(r_deg))[..., sel]
    mdb, mdeg = np.atleast_2d(zdb).mean(axis=0), np.atleast_2d(zdeg).mean(axis=0)
    return BandError(lo, hi, float(np.sqrt(np.mean(rdb ** 2))),
                     float(np.sqrt(np.mean(rdeg ** 2))),
                     float(np.sqrt(np.mean(np.concatenate([zdb.ravel(), zdeg.ravel()]) ** 2))),
                     int(sel.sum()),
                     float(np.sqrt(np.mean(np.concatenate([mdb, mdeg]) ** 2))))


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

    f_hz (n,) Hz; h (T, n) complex X/F in m/N; se_db, se_deg (T, n) standard errors;
    starts: per trial the base parameters to start from (e.g. the grip fit of its grip).
    """

    axis: str
    f_hz: np.ndarray
    h: np.ndarray
    se_db: np.ndarray
    se_deg: np.ndarray
    starts: tuple[Mapping[str, float], ...]
    labels: tuple[str, ...] = ()


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
        sdb, sdeg = _floor(data.se_db[:, sel], data.se_deg[:, sel])
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

    def jac(self, x: np.ndarray) -> sparse.csr_matrix:
        """Forward-difference Jacobian of :meth:`fun`, all columns in one vectorised
        evaluation: column j of every trial is perturbed at once (the trials' blocks do
        not overlap), shared columns for all trials together. Steps √eps·max(1, |z|),
        taken backwards at an upper bound."""
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
        D = (R[1:] - R[:1]) / h.T[:, :, None]                  # (P, T, 2n)
        m = R.shape[-1]
        rows = (np.arange(T)[:, None, None] * m + np.arange(m)[None, None, :])
        rows = np.broadcast_to(rows, (T, self.nb, m))
        cols = np.broadcast_to((np.arange(T)[:, None] * self.nb
                                + np.arange(self.nb)[None, :])[:, :, None], (T, self.nb, m))
        data = np.transpose(D[: self.nb], (1, 0, 2))           # (T, nb, m)
        base = sparse.csr_matrix((data.ravel(), (rows.ravel(), cols.ravel())),
                                 shape=(T * m, T * self.nb))
        if not self.k:
            return base
        shared = D[self.nb:].reshape(self.k, T * m).T
        return sparse.hstack([base, sparse.csr_matrix(shared)]).tocsr()

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
    from armfit.fitting import analytic_guess
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
    sdb, sdeg = _floor(data.se_db[:, sel], data.se_deg[:, sel])
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
              max_nfev: int = 200, pairs: Sequence[tuple[np.ndarray, Mapping]] = ()
              ) -> JointFit:
    """Fit ``model`` to every trial of ``data`` at once: arm parameters per trial, effect
    parameters shared (see the module docstring). ``base`` (T, 5), or a list of such:
    starting arm parameters (SI units); ``starts``: candidate starting values of the shared
    effect parameters; ``pairs``: further (base, start) combinations. Every combination is
    tried briefly on a subset of trials, the best refined on all.
    """
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = _Joint(model, data, sel)
    bases = [base] if isinstance(base, np.ndarray) else list(base)
    combos = [(b, st) for b in bases for st in starts] + list(pairs)
    if len(combos) > 1:
        x0s = _screen(model, data, sel, combos, prob)
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


def _refine(prob: _Joint, x0: np.ndarray, max_nfev: int):
    lo, hi = prob.bounds()
    return optimize.least_squares(prob.fun, x0, bounds=(lo, hi), jac=prob.jac,
                                  method="trf", max_nfev=max_nfev, x_scale=1.0,
                                  tr_solver="lsmr", tr_options={"maxiter": _LSMR_ITER},
                                  ftol=1e-8, xtol=1e-8)


#: A trial whose misfit exceeds this many times the median trial's is refitted globally.
_OUTLIER = 4.0


def _rescue(prob: _Joint, model: ClosedLoopModel, data: AxisData, sel, res, max_nfev: int):
    """Trials stuck in a poor local minimum of the joint fit (misfit far above the median
    trial's) get arm parameters from a global single-trial fit
    (:func:`armfit.fitting.fit_response`), then the joint fit is refined again; the
    better of the two results is returned."""
    from armfit.fitting import fit_response
    per = (res.fun.reshape(prob.T, -1) ** 2).sum(axis=1)
    bad = np.flatnonzero(per > _OUTLIER * max(np.median(per), 2.0 * prob.f.size))
    if bad.size == 0:
        return res
    x0 = res.x.copy()
    zb = x0[: prob.T * prob.nb].reshape(prob.T, prob.nb)
    for i in bad:
        fit = fit_response(model, data.f_hz[sel], data.h[i, sel], se_db=data.se_db[i, sel],
                           se_deg=data.se_deg[i, sel], strict=False)
        row = np.array([fit.params[n] for n in PARAM_NAMES])
        full = np.concatenate([row, prob.space.to_theta(prob.unpack(res.x)[0])[prob.nb:]])
        zb[i] = prob.space.clip_z(prob.space.to_z(full))[: prob.nb]
    res2 = _refine(prob, x0, max_nfev)
    return res2 if res2.cost < res.cost else res


#: Trials used (at most) while screening starting points, and their evaluation budget.
_SCREEN_TRIALS = 9
_SCREEN_NFEV = 12
_REFINE_BEST = 2
#: Inner iterations of the sparse trust-region solver (enough for these block problems).
_LSMR_ITER = 25


def _screen(model, data: AxisData, sel, combos, prob: _Joint) -> np.ndarray:
    """Short fits of every (base, start) pair on a spread-out subset of the trials;
    returns the full starting vectors built from the :data:`_REFINE_BEST` best."""
    T = data.h.shape[0]
    idx = np.unique(np.linspace(0, T - 1, min(T, _SCREEN_TRIALS)).round().astype(int))
    sub = AxisData(data.axis, data.f_hz, data.h[idx], data.se_db[idx], data.se_deg[idx],
                   tuple(data.starts[i] for i in idx))
    sprob = _Joint(model, sub, sel)
    slo, shi = sprob.bounds()
    scored = []
    for b, st in combos:
        r = optimize.least_squares(sprob.fun, sprob.pack(b[idx], st), bounds=(slo, shi),
                                   jac=sprob.jac, method="trf", x_scale=1.0,
                                   max_nfev=_SCREEN_NFEV, tr_solver="lsmr",
                                   tr_options={"maxiter": _LSMR_ITER})
        scored.append((r.cost, b, st, r.x))
    scored.sort(key=lambda t: t[0])
    out = []
    for _, b, st, xs in scored[:_REFINE_BEST]:
        x0 = prob.pack(b, st)
        if prob.k:
            x0[-prob.k:] = xs[-prob.k:]
        out.append(x0)
    return out


def _shared_ci(prob: _Joint, res, names) -> tuple[dict[str, float], dict[str, float]]:
    """95 % intervals of the shared parameters from the Jacobian (Schur complement)."""
    if not names:
        return {}, {}
    J = res.jac.toarray() if sparse.issparse(res.jac) else np.asarray(res.jac)
    m, p = J.shape
    s2 = 2 * res.cost / max(m - p, 1)
    JTJ = J.T @ J
    try:
        cov = s2 * np.linalg.pinv(JTJ, rcond=1e-12)
    except np.linalg.LinAlgError:  # pragma: no cover - pinv is SVD based
        nan = {n: float("nan") for n in names}
        return nan, nan
    k = len(names)
    var = np.diag(cov)[-k:]
    half = stats.norm.ppf(0.975) * np.sqrt(np.maximum(var, 0))
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
    se_db, se_deg = data.se_db[:, sel], data.se_deg[:, sel]
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
    se_db, se_deg = _floor(data.se_db[:, sel], data.se_deg[:, sel])
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
                  effects: Sequence[Effect] | None = None) -> AxisDiagnosis:
    """Fit the base model and each candidate effect to every trial of one axis, rank.

    data: the axis's trial responses with per-trial base starts; band: (lo, hi) Hz;
    effects: candidates (default: the whole library). See the module docstring for the
    criterion.
    """
    effects = list(EFFECTS.values()) if effects is None else list(effects)
    base = fit_base(data, band)
    return assess(data, band, base, [(e, fit_candidate(data, band, base, e)) for e in effects])


# ---------------------------------------------------------------------------
# From armfit's files to the arrays above
# ---------------------------------------------------------------------------

def _rows(spectra, *, level: str, kind: str, axis: str, grip: float | None = None,
          out_axis: str | None = None):
    sel = ((spectra["level"] == level) & (spectra["kind"] == kind)
           & (spectra["axis"] == axis))
    if out_axis is not None:
        sel &= spectra["out_axis"] == out_axis
    if grip is not None:
        sel &= np.isclose(spectra["grip_N"].to_numpy(float), grip)
    return spectra[sel]


def _trial_matrix(rows) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list]:
    """(f, H (T, n), se_db, se_deg, keys) from long-format trial rows on one grid."""
    keys = ["subject", "grip_N", "run"]
    rows = rows.sort_values(keys + ["freq_hz"], na_position="first")
    groups = list(rows.groupby(keys, dropna=False, sort=True))
    f = groups[0][1]["freq_hz"].to_numpy(float)
    H, sdb, sdeg, labels = [], [], [], []
    for key, g in groups:
        if g.shape[0] != f.size or not np.allclose(g["freq_hz"].to_numpy(float), f):
            raise ValueError("trials are not on one frequency grid")
        H.append(g["re"].to_numpy(float) + 1j * g["im"].to_numpy(float))
        sdb.append(g["se_db"].to_numpy(float))
        sdeg.append(g["se_deg"].to_numpy(float))
        labels.append(key)
    return f, np.array(H), np.array(sdb), np.array(sdeg), labels


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
    if rows.empty or not (params["axis"] == axis).any():
        return None
    f, H, sdb, sdeg, labels = _trial_matrix(rows)
    starts = []
    for _subject, grip, _run in labels:
        r = _param_row(params, axis, float(grip))
        starts.append({n: float(r[n]) for n in PARAM_NAMES})
    import pandas as pd
    names = tuple(f"sub-{s}_grip-{float(g):g}N" + ("" if pd.isna(run) else f"_run-{run}")
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
    for other in ("x", "y", "z"):
        if other == axis:
            continue
        rows = _rows(spectra, level="trial", kind="cross", axis=axis, out_axis=other)
        if rows.empty:
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


def _base_task(args):
    data, band = args
    return fit_base(data, band)


def _candidate_task(args):
    data, band, base, effect = args
    return fit_candidate(data, band, base, effect)


def diagnose(spectra, params, *, band: tuple[float, float] | None = None,
             axes: Sequence[str] = ("x", "y", "z"),
             effects: Sequence[Effect] | None = None, jobs: int = 1) -> list[AxisDiagnosis]:
    """Diagnose every axis present in both ``spectra`` (a spectra DataFrame) and
    ``params`` (a params DataFrame, grip or nominal fits): see :func:`diagnose_axis`.
    ``band`` defaults to the whole grid of the spectra (the point is to look beyond the
    paper's fit bands); ``jobs`` > 1 runs the base fits (one per axis), then the candidate
    fits (one per axis and effect) in parallel processes — the results do not depend on
    ``jobs``."""
    effects = list(EFFECTS.values()) if effects is None else list(effects)
    tasks = []
    for axis in axes:
        data = axis_data(spectra, params, axis)
        if data is None:
            continue
        b = band or (float(data.f_hz[0]), float(data.f_hz[-1]))
        tasks.append((data, b))
    if not tasks:
        return []
    pool = None
    if jobs > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor
        # forkserver: safe when the caller has threads of its own (the run pipeline)
        method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        from armfit.workers import ignore_sigint  # Ctrl-C is the main process's to handle
        pool = ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context(method),
                                   initializer=ignore_sigint)
    try:
        run = pool.map if pool is not None else map
        bases = list(run(_base_task, tasks))
        cand_tasks = [(data, b, base, e) for (data, b), base in zip(tasks, bases, strict=True)
                      for e in effects]
        fits = list(run(_candidate_task, cand_tasks))
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    out = []
    n = len(effects)
    for i, ((data, b), base) in enumerate(zip(tasks, bases, strict=True)):
        d = assess(data, b, base, list(zip(effects, fits[i * n:(i + 1) * n], strict=True)))
        out.append(AxisDiagnosis(**{**d.__dict__,
                                    "coupling": cross_coupling(spectra, data, b)}))
    return out


# ---------------------------------------------------------------------------
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


def _summary(axis, grip, level, label, f, r_db, r_deg, se_db, se_deg, band, params, n):
    sdb, sdeg = _floor(se_db, se_deg)
    r_db2, r_deg2 = np.atleast_2d(r_db), np.atleast_2d(r_deg)
    z_db, z_deg = r_db2 / np.atleast_2d(sdb), r_deg2 / np.atleast_2d(sdeg)
    t_db, t_deg = trial_statistics(z_db, z_deg)
    fails = failing_bands(f, t_db, t_deg, r_db2.mean(axis=0), r_deg2.mean(axis=0),
                          size_db=z_db.mean(axis=0), size_deg=z_deg.mean(axis=0))
    overall = band_error(f, r_db, r_deg, se_db, se_deg, band[0], band[1])
    bands = tuple(band_error(f, r_db, r_deg, se_db, se_deg, lo, hi) for lo, hi in BANDS
                  if hi > band[0] and lo < band[1])
    return Comparison(axis, grip, level, label, overall, bands, tuple(fails), params, n)


def _fit_effects_aggregate(base_model, theta, effects, f, h, se_db, se_deg, band):
    """Nested refit of base + effects on one aggregate, warm-started at the effects'
    null point and at their starting points; never worse than the base."""
    from armfit.fitting import fit_response
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
    ``band`` defaults to the whole grid.
    """
    from armfit.errors import UsageError
    from armfit.io.artifacts import model_from_params
    if level not in ("mean", "median", "trial"):
        raise UsageError(f"--level must be mean, median or trial, got {level!r}")
    grip_model = "grip_N" in params.columns
    if level == "median" and grip_model:
        raise UsageError("grip fits are compared at --level mean or trial; the median "
                         "pools all grips (use nominal fits)")
    out: list[Comparison] = []
    for axis in ("x", "y", "z"):
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
            se = (data.se_db[:, sel], data.se_deg[:, sel])
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
            grips = sorted(set(rows["grip_N"].astype(float)))
        for grip in grips:
            rows = _rows(spectra, level=level, kind="measured", axis=axis, grip=grip)
            if rows.empty:
                continue
            rows = rows.sort_values("freq_hz")
            f = rows["freq_hz"].to_numpy(float)
            h = rows["re"].to_numpy(float) + 1j * rows["im"].to_numpy(float)
            se_db, se_deg = rows["se_db"].to_numpy(float), rows["se_deg"].to_numpy(float)
            prow = _param_row(params, axis, grip)
            model, theta = model_from_params(prow)
            b = band or (float(f[0]), float(f[-1]))
            sel = (f >= b[0]) & (f <= b[1])
            with np.errstate(all="ignore"):
                r_db, r_deg = residuals(h[sel], model.response(f[sel], theta))
            n = int(rows["n"].iloc[0]) if "n" in rows else 1
            out.append(_summary(axis, grip, level, model_label(model), f[sel], r_db, r_deg,
                                se_db[sel], se_deg[sel], b, {}, n))
            if effects:
                model_e, th_e = _fit_effects_aggregate(model, theta, effects, f, h, se_db,
                                                       se_deg, b)
                with np.errstate(all="ignore"):
                    r_db, r_deg = residuals(h[sel], model_e.response(f[sel], th_e))
                eff_params = {k: v for k, v in th_e.items() if k not in PARAM_NAMES}
                out.append(_summary(axis, grip, level, model_label(model_e), f[sel], r_db,
                                    r_deg, se_db[sel], se_deg[sel], b, eff_params, n))
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
            "candidates": [{
                "effect": c.effect, "params": c.params, "params_lo": c.params_lo,
                "params_hi": c.params_hi,
                "rms_db_before": c.rms_db_before, "rms_db_after": c.rms_db_after,
                "rms_deg_before": c.rms_deg_before, "rms_deg_after": c.rms_deg_after,
                "rms_norm_before": c.rms_norm_before, "rms_norm_after": c.rms_norm_after,
                "failing_bias_before": c.failing_bias_before,
                "failing_bias_after": c.failing_bias_after,
                "failing_before": [band_to_dict(b) for b in c.failing_before],
                "failing_after": [band_to_dict(b) for b in c.failing_after],
                "lr": c.lr, "score": c.score, "rss_reduction": c.rss_reduction,
                "significant": c.significant,
            } for c in d.candidates]}
    return {"axes": axes}
