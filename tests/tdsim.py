"""Time-domain study simulator, independent of armfit's closed-loop formula.

Test and validation infrastructure: it writes raw trial files of the data contract (one
file per trial, ``sub-<s>_axis-<a>_grip-<g>N.parquet``) whose truth is known, so the whole
path ``estimate → fit-grip/fit-nominal → diagnose`` can be checked on data that armfit's
own frequency-domain model did not make. Use from benchmarks by adding ``tests/`` to
``sys.path``.

How a trial is made
-------------------
1. The continuous closed loop as a rational transfer function in s (rad/s), built here
   from polynomials, not from :mod:`armfit.models`:

   * arm impedance (paper eq. 3 inverted) Z_A = C1 (Ma s² + C2) / (Ma s² + C1 + C2),
     C1 = k1 + b1 s, C2 = k2 + b2 s;
   * reflex (arm stage) g·exp(−s τ_r), the delay by a Padé approximant of order
     :data:`PADE_ORDER`;
   * device impedance m s² + B s + k (mass m = the axis's Mp unless ``device-mass``,
     damping B from ``device-damping``, spring k from ``device-spring``);
   * output factors: first-order lag ω_c/(s + ω_c) (``lowpass``), a structural mode
     (1 − w) + w ω_n²/(s² + 2ζω_n s + ω_n²) (``resonance``);

   X/F = R(s) / (Z_A + ΔZ_arm + Z_dev).
2. Discretisation with :func:`scipy.signal.cont2discrete` (``bilinear`` by default — a
   frequency warp of 0.3 % at 30 Hz), as zeros/poles/gain, run as second-order sections
   (:func:`scipy.signal.sosfilt`, the numerically safe form of ``lfilter``) on the
   sampled force, after a discarded lead-in of :data:`LEAD_S`. ``method="zoh"``: the
   force held constant over each sample period, as a servo loop holds its command (the
   half-sample lag a real device has); simulated by holding each force sample for
   :data:`ZOH_UPSAMPLE` sub-samples, filtering at that rate and sampling the position at
   the original instants (``cont2discrete(..., "zoh")`` of the whole loop is numerically
   ill-conditioned at this order).
3. An output delay (``delay``) as an integer number of samples plus a first-order Thiran
   all-pass for the fraction (fraction kept in [0.5, 1.5) samples so the all-pass is
   stable), not as exp(−sτ).
4. The measurement chain: position sensor noise (white, ``noise_m`` rms), slow postural
   drift (white noise through a 2nd-order Butterworth low-pass at 0.05 Hz, ``drift_m``
   rms), encoder quantisation (``quantum_m``), force quantisation (``force_step_N``).

Force: Gaussian white noise through an 8th-order Butterworth low-pass at ``band_hz``
(not armfit's ideal FFT low-pass), scaled to a peak of ``limit_N``; or, with
``input="steps"``, pseudo-random steps: levels uniform in ±``limit_N`` held for random
times uniform in ``hold_s`` (a non-white input whose power falls as 1/f² above a few Hz).

Subjects: log-normal factors exp(``variability`` · z) on the five arm parameters of the
paper's Table I row (axis, grip); seeds give reproducible studies. An effect parameter
may differ between subjects (``subject_effects``): each subject draws its own value,
uniform in a range, kept on every axis and grip.

Units: SI throughout (kg, N/m, N·s/m, s, Hz, m, N).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy import signal

#: Device mass per axis (kg), the paper's eq. 2 values.
MP_KG = {"x": 0.09, "y": 0.095, "z": 0.091}
#: Order of the Padé approximant of the reflex delay.
PADE_ORDER = 6
#: Rate multiple at which the zero-order hold is simulated (``method="zoh"``).
ZOH_UPSAMPLE = 8
#: Discarded lead-in before the recorded window (s), so the filters' start-up is gone.
LEAD_S = 8.0
#: Table I (Fu & Çavuşoğlu 2010): (axis, grip N) -> (Ma kg, k1, k2 N/m, b1, b2 N·s/m).
TABLE1: dict[tuple[str, float], tuple[float, ...]] = {}


def _table1() -> dict[tuple[str, float], tuple[float, ...]]:
    if not TABLE1:
        from armfit.data import paper_table
        for r in paper_table("grip").to_dict("records"):
            TABLE1[(r["axis"], float(r["grip_N"]))] = (
                float(r["Ma_kg"]), float(r["k1_N_per_m"]), float(r["k2_N_per_m"]),
                float(r["b1_Ns_per_m"]), float(r["b2_Ns_per_m"]))
    return TABLE1


@dataclass(frozen=True)
class Study:
    """Settings of one simulated study (SI units).

    effects: {effect name: {param: value}} with armfit's effect parameter names
    (``delay``: delay_s; ``lowpass``: cutoff_hz; ``device-damping``: damping_Ns_per_m;
    ``device-mass``: mass_kg; ``resonance``: freq_hz, zeta, weight; ``reflex``:
    gain_N_per_m, delay_s; ``device-spring``: k_N_per_m). effect_axes: the axes the
    effects act on (all by default). subject_effects: {effect name: {param: (lo, hi)}},
    parameters whose value each subject draws uniformly from [lo, hi]
    (:func:`subject_effect_values`), on top of (or instead of) ``effects``.
    """

    subjects: int = 4
    axes: tuple[str, ...] = ("x", "y", "z")
    grips_N: tuple[float, ...] = (1.0, 2.0, 3.0)
    duration_s: tuple[float, float] = (30.0, 40.0)
    fs: float = 1000.0
    seed: int = 0
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    effect_axes: tuple[str, ...] = ("x", "y", "z")
    method: str = "bilinear"
    input: str = "white"
    band_hz: float = 30.0
    limit_N: float = 5.0
    hold_s: tuple[float, float] = (0.03, 0.3)
    noise_m: float = 2e-6
    drift_m: float = 1e-3
    quantum_m: float = 3e-5
    force_step_N: float = 2.0 ** -12
    variability: float = 0.15
    subject_effects: Mapping[str, Mapping[str, tuple[float, float]]] = field(
        default_factory=dict)


def subject_effect_values(study: Study, subject: int) -> dict[str, dict[str, float]]:
    """The subject's own values of :attr:`Study.subject_effects` ({effect: {param:
    value}}), uniform in each range, the same on every axis and grip of the subject."""
    out: dict[str, dict[str, float]] = {}
    for i, (name, params) in enumerate(sorted(study.subject_effects.items())):
        for j, (param, (lo, hi)) in enumerate(sorted(params.items())):
            u = np.random.default_rng([study.seed, 3, subject, i, j]).uniform()
            out.setdefault(name, {})[param] = float(lo + (hi - lo) * u)
    return out


def arm_params(study: Study, subject: int, axis: str, grip: float) -> dict[str, float]:
    """The subject's five arm parameters on (axis, grip): Table I times its factors."""
    z = np.random.default_rng([study.seed, 1, subject]).standard_normal(5)
    row = _table1()[(axis, float(grip))]
    factors = np.exp(study.variability * z)
    return {n: float(v * g) for n, v, g in zip(("Ma", "k1", "k2", "b1", "b2"), row, factors,
                                                strict=True)}


def pade_delay(tau_s: float, order: int) -> tuple[np.ndarray, np.ndarray]:
    """(num, den) in s (highest power first) of the [order/order] Padé approximant of
    exp(−s τ): c_k = (2n − k)! n! / ((2n)! k! (n − k)!), num Σ c_k (−τ s)^k, den Σ c_k (τ s)^k."""
    from math import factorial
    n = order
    c = np.array([factorial(2 * n - k) * factorial(n)
                  / (factorial(2 * n) * factorial(k) * factorial(n - k)) for k in range(n + 1)])
    k = np.arange(n + 1)
    num = (c * (-tau_s) ** k)[::-1]
    den = (c * tau_s ** k)[::-1]
    return num, den


def closed_loop_tf(arm: Mapping[str, float], mp: float,
                   effects: Mapping[str, Mapping[str, float]]) -> tuple[np.ndarray, np.ndarray]:
    """(num, den) polynomials in s of X/F (m/N) without the output delay (see module
    docstring, step 1)."""
    pm = np.polymul
    c1, c2 = np.array([arm["b1"], arm["k1"]]), np.array([arm["b2"], arm["k2"]])
    ms2 = np.array([arm["Ma"], 0.0, 0.0])
    za_num = pm(c1, np.polyadd(ms2, c2))
    za_den = np.polyadd(ms2, np.polyadd(c1, c2))
    if "reflex" in effects:
        g, tau = effects["reflex"]["gain_N_per_m"], effects["reflex"]["delay_s"]
        pn, pd = pade_delay(tau, PADE_ORDER)
        za_num = np.polyadd(pm(za_num, pd), g * pm(pn, za_den))
        za_den = pm(za_den, pd)
    m = effects.get("device-mass", {}).get("mass_kg", mp)
    b = effects.get("device-damping", {}).get("damping_Ns_per_m", 0.0)
    k = effects.get("device-spring", {}).get("k_N_per_m", 0.0)
    zd = np.array([m, b, k])
    num, den = za_den, np.polyadd(za_num, pm(zd, za_den))
    if "lowpass" in effects:
        wc = 2 * np.pi * effects["lowpass"]["cutoff_hz"]
        num, den = num * wc, pm(den, [1.0, wc])
    if "resonance" in effects:
        r = effects["resonance"]
        wn, zeta, w = 2 * np.pi * r["freq_hz"], r["zeta"], r["weight"]
        mode = np.array([1.0, 2 * zeta * wn, wn * wn])
        num = pm(num, np.polyadd((1 - w) * mode, [w * wn * wn]))
        den = pm(den, mode)
    return np.asarray(num, float), np.asarray(den, float)


def discrete_sos(num, den, fs: float, method: str = "bilinear") -> np.ndarray:
    """Second-order sections of the discretised transfer function (cont2discrete, as
    zeros/poles/gain). Raises ValueError for an unstable loop."""
    z, p, k = signal.tf2zpk(num, den)
    if np.any(p.real >= 0):
        raise ValueError("the continuous closed loop is unstable")
    # time in units of 1/w0 (w0 = 2 pi 10 Hz) keeps the state-space form that
    # cont2discrete builds well conditioned: s' = s / w0, dt' = dt w0
    w0 = 2 * np.pi * 10.0
    k = k * w0 ** (z.size - p.size)
    zd, pd, kd, _ = signal.cont2discrete((z / w0, p / w0, k), w0 / fs, method=method)
    zd = np.atleast_1d(np.squeeze(zd))
    if np.any(np.abs(pd) >= 1):
        raise ValueError("the discretised closed loop is unstable")
    return signal.zpk2sos(zd, pd, float(np.squeeze(kd)))


def fractional_delay(x: np.ndarray, delay_samples: float) -> np.ndarray:
    """Delay ``x`` by a (non-integer) number of samples: integer shift plus a first-order
    Thiran all-pass (a + z⁻¹)/(1 + a z⁻¹), a = (1 − d)/(1 + d), d in [0.5, 1.5)."""
    n = int(np.floor(delay_samples))
    d = delay_samples - n
    if n >= 1 and d < 0.5:
        n, d = n - 1, d + 1.0
    y = x
    if d > 1e-9:
        if d < 0.5:  # total delay below half a sample: linear interpolation
            y = np.concatenate([[x[0]], (1 - d) * x[1:] + d * x[:-1]])
        else:
            a = (1 - d) / (1 + d)
            y = signal.lfilter([a, 1.0], [1.0, a], x)
    if n:
        y = np.concatenate([np.full(n, y[0]), y[:-n]])
    return y


def force_signal(rng: np.random.Generator, n: int, study: Study) -> np.ndarray:
    """The commanded force (N), (n,): band-limited white noise or pseudo-random steps."""
    fs = study.fs
    if study.input == "white":
        sos = signal.butter(8, study.band_hz, fs=fs, output="sos")
        f = signal.sosfilt(sos, rng.standard_normal(n))
        f *= study.limit_N / np.max(np.abs(f))
    elif study.input == "steps":
        f = np.empty(n)
        i = 0
        while i < n:
            hold = int(max(1, round(rng.uniform(*study.hold_s) * fs)))
            f[i:i + hold] = rng.uniform(-study.limit_N, study.limit_N)
            i += hold
    else:
        raise ValueError(f"input must be 'white' or 'steps', got {study.input!r}")
    if study.force_step_N > 0:
        f = np.trunc(f / study.force_step_N) * study.force_step_N
    return f


def _trial_setup(study: Study, subject: int, axis: str, grip: float, stream: int):
    """(random generator, samples n, lead-in samples, arm parameters, effects) of one
    trial; ``stream`` keeps the open-loop and the rig's draws apart."""
    rng = np.random.default_rng([study.seed, stream, subject, "xyz".index(axis),
                                 int(round(grip * 1000))])
    n = int(round(rng.uniform(*study.duration_s) * study.fs))
    lead = int(round(LEAD_S * study.fs))
    effects = {k: dict(v) for k, v in study.effects.items()} if axis in study.effect_axes \
        else {}
    if axis in study.effect_axes:
        for name, values in subject_effect_values(study, subject).items():
            effects.setdefault(name, {}).update(values)
    return rng, n, lead, arm_params(study, subject, axis, grip), effects


def simulate_trial(study: Study, subject: int, axis: str, grip: float
                   ) -> tuple[np.ndarray, np.ndarray, dict]:
    """(force (n,) N, position (n,) m, truth dict) of one trial."""
    rng, n, lead, arm, effects = _trial_setup(study, subject, axis, grip, 2)
    fs = study.fs
    num, den = closed_loop_tf(arm, MP_KG[axis], effects)
    force = force_signal(rng, n + lead, study)
    if study.method == "zoh":
        # the force held over each sample period, simulated at ZOH_UPSAMPLE times the
        # rate (bilinear there: warp negligible) and sampled at the original instants
        sos = discrete_sos(num, den, fs * ZOH_UPSAMPLE, "bilinear")
        x = signal.sosfilt(sos, np.repeat(force, ZOH_UPSAMPLE))[::ZOH_UPSAMPLE]
    else:
        x = signal.sosfilt(discrete_sos(num, den, fs, study.method), force)
    if "delay" in effects:
        x = fractional_delay(x, effects["delay"]["delay_s"] * fs)
    x, force = x[lead:], force[lead:]
    if study.drift_m > 0:
        dsos = signal.butter(2, 0.05, fs=fs, output="sos")
        d = signal.sosfilt(dsos, rng.standard_normal(n + lead))[lead:]
        x = x + study.drift_m * d / max(np.std(d), 1e-30)
    x = x + study.noise_m * rng.standard_normal(n)
    if study.quantum_m > 0:
        x = np.round(x / study.quantum_m) * study.quantum_m
    truth = {"subject": subject, "axis": axis, "grip_N": grip, "arm": arm,
             "mp_kg": MP_KG[axis], "effects": effects, "n_samples": n}
    return force, x, truth


def write_study(study: Study, out: str | Path) -> Path:
    """Simulate every trial of ``study`` and write raw trial files (Parquet, the data
    contract's columns time_s, force_<a>_N, pos_<a>_m) and ``truth.json`` into ``out``.
    Returns the folder."""
    from armfit.io.rawwrite import trial_filename, write_trial
    from armfit.io.trials import Trial, TrialMeta
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    truths = []
    for s in range(study.subjects):
        for axis in study.axes:
            for grip in study.grips_N:
                force, x, truth = simulate_trial(study, s, axis, grip)
                j = "xyz".index(axis)
                F = np.full((x.size, 3), np.nan)
                P = np.full((x.size, 3), np.nan)
                F[:, j], P[:, j] = force, x
                meta = TrialMeta(subject=f"{s + 1:02d}", axis=axis, grip_N=float(grip),
                                 run=None, fs=study.fs, n_samples=x.size, t0_s=0.0,
                                 source="tdsim")
                write_trial(Trial(meta=meta, force=F, pos=P, grip=None),
                            out / trial_filename(meta))
                truths.append(truth)
    settings = asdict(study)
    settings["effects"] = {k: dict(v) for k, v in study.effects.items()}
    settings["subject_effects"] = {k: {p: list(r) for p, r in v.items()}
                                   for k, v in study.subject_effects.items()}
    (out / "truth.json").write_text(json.dumps({"generator": "tests/tdsim.py",
                                                "settings": settings, "trials": truths},
                                               indent=1))
    return out


def estimate_and_fit(folder: str | Path, which: str = "grip",
                     effects: Sequence = ()):
    """(spectra DataFrame, params DataFrame) of a written study: ``armfit estimate``
    defaults, then ``fit-grip`` (which="grip") or ``fit-nominal`` (which="nominal")."""
    from armfit.fitting import fit_study
    from armfit.spectra import EstimateConfig, estimate_study
    spectra = estimate_study([Path(folder)], EstimateConfig()).table
    params = fit_study(spectra, which=which).table()
    return spectra, params


# ---------------------------------------------------------------------------
# A closed-loop rig: the device's force responds to the measured position
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Rig:
    """A device that renders a virtual spring and damper on the measured position:
    F = r − C(z)·(x + d), C(z) = z⁻¹ (k + b·fs·(1 − z⁻¹)) (a PD controller one servo
    sample late), with r the commanded force (the study's force signal), x the true
    position and d what the position sensor adds (postural drift and sensor noise). The
    force applied to the stylus then depends on the sensor's noise through the loop, as
    on a position-controlled or impedance-rendering haptic device (the README's EMPS
    axis is the extreme case). ``k_N_per_m``, ``b_Ns_per_m``: the controller's stiffness
    and damping; ``reference``: log r as the trial's ``ref_<a>_N`` column;
    ``force_noise_N``: white noise (rms, N) on the recorded force only (a noisy force
    sensor)."""

    k_N_per_m: float = 300.0
    b_Ns_per_m: float = 1.0
    reference: bool = True
    force_noise_N: float = 0.0


def _z_polys(num, den, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """(b, a) in powers of z⁻¹ of the bilinear discretisation of num/den (s), a[0] = 1."""
    z, p, k = signal.tf2zpk(num, den)
    w0 = 2 * np.pi * 10.0   # as discrete_sos: time in units of 1/w0
    k = k * w0 ** (z.size - p.size)
    zd, pd, kd, _ = signal.cont2discrete((z / w0, p / w0, k), w0 / fs, method="bilinear")
    b = float(np.squeeze(kd)) * np.poly(np.atleast_1d(np.squeeze(zd)))
    a = np.poly(pd)
    b = np.concatenate([np.zeros(a.size - b.size), b])
    return np.real(b), np.real(a)


def simulate_rig_trial(study: Study, rig: Rig, subject: int, axis: str, grip: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(force (n,) N, position (n,) m, commanded force r (n,) N, truth) of one trial on
    the closed-loop rig. The loop is solved exactly in z: with G = B/A (X/F, bilinear)
    and C = c₁z⁻¹ + c₂z⁻², F = A (r − C d)/(A + C B) and x = B (r − C d)/(A + C B).
    The recorded position is x + d, quantised; the recorded force is F (plus the rig's
    force-sensor noise). The truth's X/F is the open loop's (:func:`closed_loop_tf`):
    what an unbiased estimator of the measured dynamics must find. Only the bilinear
    method and effects without the output ``delay`` are simulated."""
    if study.method != "bilinear" or "delay" in study.effects \
            or "delay" in study.subject_effects:
        raise ValueError("the rig simulates the bilinear method without a delay effect")
    rng, n, lead, arm, effects = _trial_setup(study, subject, axis, grip, 3)
    fs = study.fs
    b, a = _z_polys(*closed_loop_tf(arm, MP_KG[axis], effects), fs)
    r = force_signal(rng, n + lead, study)
    d = np.zeros(n + lead)
    if study.drift_m > 0:
        dsos = signal.butter(2, 0.05, fs=fs, output="sos")
        drift = signal.sosfilt(dsos, rng.standard_normal(n + lead))
        d += study.drift_m * drift / max(np.std(drift[lead:]), 1e-30)
    d += study.noise_m * rng.standard_normal(n + lead)
    c = np.array([0.0, rig.k_N_per_m + rig.b_Ns_per_m * fs, -rig.b_Ns_per_m * fs])
    den = np.polyadd(a[::-1], np.convolve(c, b)[:a.size + 2][::-1])[::-1]  # A + C B
    if np.any(np.abs(np.roots(den)) >= 1.0):
        raise ValueError("the rig's loop is unstable")
    u = r - signal.lfilter(c, [1.0], d)
    force = signal.sosfilt(signal.tf2sos(np.concatenate([a, [0.0, 0.0]]), den), u)
    x = signal.sosfilt(signal.tf2sos(np.concatenate([b, [0.0, 0.0]]), den), u) + d
    x, force, r = x[lead:], force[lead:], r[lead:]
    if study.quantum_m > 0:
        x = np.round(x / study.quantum_m) * study.quantum_m
    if rig.force_noise_N > 0:
        force = force + rig.force_noise_N * rng.standard_normal(n)
    truth = {"subject": subject, "axis": axis, "grip_N": grip, "arm": arm,
             "mp_kg": MP_KG[axis], "effects": effects, "n_samples": n,
             "rig": asdict(rig)}
    return force, x, r, truth


def write_rig_study(study: Study, rig: Rig, out: str | Path) -> Path:
    """Simulate every trial of ``study`` on the closed-loop ``rig`` and write raw trial
    files (Parquet: time_s, force_<a>_N, pos_<a>_m and, with ``rig.reference``, the
    commanded force as ref_<a>_N) and ``truth.json`` into ``out``. Returns the folder."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    truths = []
    for s in range(study.subjects):
        for axis in study.axes:
            for grip in study.grips_N:
                force, x, r, truth = simulate_rig_trial(study, rig, s, axis, grip)
                cols = {"time_s": np.arange(x.size) / study.fs, f"force_{axis}_N": force,
                        f"pos_{axis}_m": x}
                if rig.reference:
                    cols[f"ref_{axis}_N"] = r
                pq.write_table(pa.table(cols),
                               out / f"sub-{s + 1:02d}_axis-{axis}_grip-{grip:g}N.parquet")
                truths.append(truth)
    settings = asdict(study)
    settings["effects"] = {k: dict(v) for k, v in study.effects.items()}
    (out / "truth.json").write_text(json.dumps({"generator": "tests/tdsim.py (rig)",
                                                "settings": settings, "rig": asdict(rig),
                                                "trials": truths}, indent=1))
    return out


def true_response(truth: Mapping, freq_hz: np.ndarray) -> np.ndarray:
    """The true X/F (m/N) of a trial's ``truth`` at ``freq_hz``: :func:`closed_loop_tf`
    evaluated at s = j2πf (without an output delay)."""
    num, den = closed_loop_tf(truth["arm"], truth["mp_kg"], truth["effects"])
    s = 2j * np.pi * np.asarray(freq_hz, dtype=float)
    return np.polyval(num, s) / np.polyval(den, s)
