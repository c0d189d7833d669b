"""Study simulator: raw trials with a known truth, following the paper's protocol.

Fu & Çavuşoğlu 2010 stimulate one axis at a time with Gaussian white-noise force,
low-passed to 30 Hz and limited to 5 N, while the subject holds the stylus at a target grip
force; the stylus position is logged at 1 kHz. This module generates such trials from the
closed-loop model X/F = H_CL (eqs. 2–4) with any effects of :mod:`armfit.models.effects`,
through :meth:`armfit.models.arm.ClosedLoopModel.response` — the same definitions the fits
and the diagnosis use.

Method (exact up to the force's band limit)
-------------------------------------------
Each trial of N samples is cut from a *periodic frame* of L = N + 10 s samples (rounded up
to a fast FFT length). The force on the frame is white Gaussian noise passed through an
ideal low-pass filter (DFT bins above 30 Hz and the DC bin set to zero), then scaled so
that its peak equals the force limit (5 N): a scaling, not a clipping, so the force stays
band-limited (only the force converter's quantisation, −84 dB re the force power,
reaches above 30 Hz).
Because the force is periodic with period L, the continuous-time force is the
trigonometric polynomial through its samples (band-limited to fs/2), and the
steady-state position of the continuous, stable system is exactly

    x(t) = Σ_k H(j 2π f_k) F_k exp(j 2π f_k t),    f_k = k fs / L,

i.e. ``x = irfft(H(f_k) · rfft(F))``. There is no start-up transient (the system has
been driven by the same periodic force forever) and no circular wrap-around error (the
input really is periodic), so the method is exact for any effect, including pure delays;
the recorded window [0, N) is shorter than the period, so within the record the force
looks like an ordinary stationary random signal and estimators see the usual leakage.
The only requirement is a stable closed loop: :func:`periodic_response` checks it through
the response's impulse response, which must be causal and decay within the frame.

Measurement chain on top of the exact motion (noise, quantisation and drift are
settable — ``--noise``, ``--quantum``, ``--drift`` — and 0 switches each off):

- commanded force quantised to ``force_step_N`` (default 2⁻¹² N ≈ 0.24 mN, a 16-bit
  converter spanning ±8 N); the position is computed from the quantised force;
- slow postural drift on every position axis: Gaussian, power spectrum
  1 / (1 + (f / 0.05 Hz)⁴), scaled to ``drift_m`` rms (mostly below 0.1 Hz, so the
  paper's lowest band, 0.1 Hz and up, stays usable);
- cross-axis motion: position axis j moves by ``CROSS_COUPLING[(i, j)]`` times the
  force-driven on-axis motion of the stimulated axis i (a constant real gain), plus its
  own drift and noise;
- white position sensor noise of ``noise_m`` rms, then encoder quantisation to
  ``quantum_m`` (PHANToM-like 0.03 mm), on every position axis;
- grip force: target + a slow wander (Gaussian below ~0.5 Hz, 0.2 N rms) + sensor noise
  (0.02 N rms), kept within target ± 0.5 N, quantised to 0.01 N and sampled-and-held at
  65 Hz (the force-sensitive resistor's rate).

Subjects: subject i has one multiplicative log-normal factor per arm parameter,
exp(variability · z), z ~ N(0, 1), shared by all of that subject's axes and grips, applied
to the (axis, grip) row of Table I; ``variability = 0`` gives every subject Table I.

Randomness: every random draw comes from a generator seeded with (seed, stream, subject,
axis, grip), so a trial's data depend only on the seed and its own identity and settings —
not on which other trials are simulated.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import fft as sfft

from armfit.data import paper_table
from armfit.errors import UsageError
from armfit.io.trials import AXES, GRIP_TOLERANCE_N, Trial, TrialMeta
from armfit.models.arm import DEVICE_MASS_KG, PARAM_NAMES, ClosedLoopModel
from armfit.models.effects import get_effect

#: Table I column of each arm parameter.
_TABLE1_COLUMNS = {"Ma": "Ma_kg", "k1": "k1_N_per_m", "k2": "k2_N_per_m",
                   "b1": "b1_Ns_per_m", "b2": "b2_Ns_per_m"}

#: Cross-axis coupling: position axis j moves by this gain (dimensionless, m/m) times the
#: force-driven motion of the stimulated axis i. Y–Z is the largest, as the paper suspects
#: Y–Z coupling through the arm's kinematics.
CROSS_COUPLING: dict[tuple[str, str], float] = {
    ("x", "y"): 0.03, ("x", "z"): 0.02,
    ("y", "x"): 0.02, ("y", "z"): 0.05,
    ("z", "x"): 0.02, ("z", "y"): 0.05,
}

#: Length of the part of each periodic frame that is not recorded, s.
PAD_S = 10.0
#: Corner of the postural drift spectrum, Hz.
DRIFT_CORNER_HZ = 0.05
#: Grip signal: sensor rate (Hz), wander and noise rms (N), quantisation step (N), wander
#: bandwidth (Hz); it stays within the reader's tolerance around the target
#: (:data:`armfit.io.trials.GRIP_TOLERANCE_N`).
GRIP_RATE_HZ = 65.0
GRIP_WANDER_N = 0.2
GRIP_NOISE_N = 0.02
GRIP_STEP_N = 0.01
GRIP_WANDER_HZ = 0.5

# Stream tags of the seeded generators (see module docstring).
_STREAM_SUBJECT, _STREAM_TRIAL = 1, 2


@dataclass(frozen=True)
class EffectSetting:
    """One effect added to the simulated dynamics: its name, values and the axes it acts on."""

    name: str
    values: tuple[tuple[str, float], ...]
    axes: tuple[str, ...] = AXES

    @classmethod
    def from_parsed(cls, name: str, values: Mapping[str, float],
                    axes: Sequence[str] = AXES) -> EffectSetting:
        effect = get_effect(name)
        return cls(effect.name, tuple((p, float(values[p])) for p in effect.param_names),
                   tuple(axes))

    def as_dict(self) -> dict:
        return {"name": self.name, "values": dict(self.values), "axes": list(self.axes)}


@dataclass(frozen=True)
class StudyConfig:
    """Settings of a simulated study (SI units). Defaults follow the paper's protocol."""

    subjects: int = 9
    axes: tuple[str, ...] = AXES
    grips_N: tuple[float, ...] = (1.0, 2.0, 3.0)
    duration_s: tuple[float, float] = (50.0, 100.0)
    fs: float = 1000.0
    seed: int = 0
    noise_m: float = 2e-6
    variability: float = 0.15
    drift_m: float = 2e-3
    quantum_m: float = 3e-5
    force_limit_N: float = 5.0
    force_band_hz: float = 30.0
    force_step_N: float = 2.0 ** -12
    effects: tuple[EffectSetting, ...] = field(default=())

    def __post_init__(self) -> None:
        table_grips = sorted(set(paper_table("grip")["grip_N"].astype(float)))
        if self.subjects < 1:
            raise UsageError(f"{{opt:subjects}} must be >= 1, got {self.subjects}")
        if not self.axes or any(a not in AXES for a in self.axes) \
                or len(set(self.axes)) != len(self.axes):
            raise UsageError(f"{{opt:axes}} must be distinct letters of xyz, got "
                             f"{''.join(self.axes)!r}")
        bad = [g for g in self.grips_N if g not in table_grips]
        if not self.grips_N or bad or len(set(self.grips_N)) != len(self.grips_N):
            raise UsageError(f"{{opt:grips_N}} must be distinct values among the rows of Table I "
                             f"({', '.join(f'{g:g}' for g in table_grips)} N), got "
                             f"{', '.join(f'{g:g}' for g in self.grips_N)}")
        lo, hi = self.duration_s
        if not (0 < lo <= hi):
            raise UsageError(f"{{opt:duration_s}} MIN,MAX needs 0 < MIN <= MAX, got "
                             f"{lo:g},{hi:g}")
        if not self.fs >= 4 * max(self.force_band_hz, GRIP_RATE_HZ):
            least = 4 * max(self.force_band_hz, GRIP_RATE_HZ)
            raise UsageError(f"{{opt:fs}} must be >= {least:g} Hz (4 x the force band and "
                             f"the grip rate), got {self.fs:g}")
        if round(lo * self.fs) < 2:
            raise UsageError(f"{{opt:duration_s}} {lo:g} s is shorter than two samples")
        for name in ("noise_m", "variability", "drift_m", "quantum_m", "force_step_N"):
            if not (getattr(self, name) >= 0 and np.isfinite(getattr(self, name))):
                raise UsageError(f"{name} must be a finite number >= 0, got "
                                 f"{getattr(self, name)}")
        if not self.force_limit_N > 0:
            raise UsageError(f"force limit must be > 0 N, got {self.force_limit_N}")
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise UsageError(f"{{opt:effects}} given twice: {', '.join(names)}")


@dataclass(frozen=True)
class TrialPlan:
    """The truth of one simulated trial: identity, length, device mass, parameters, effects.

    params: the five arm parameters (Ma kg, k1 k2 N/m, b1 b2 N·s/m); mp: device mass of
    eq. 2 (kg); effects: the effects acting on this trial's axis.
    """

    subject: str
    subject_index: int
    axis: str
    grip_N: float
    n_samples: int
    fs: float
    mp: float
    params: tuple[tuple[str, float], ...]
    effects: tuple[EffectSetting, ...]

    @property
    def duration_s(self) -> float:
        return self.n_samples / self.fs

    def model(self) -> ClosedLoopModel:
        """The closed-loop model (eq. 4 with this trial's effects)."""
        return ClosedLoopModel.for_axis(self.axis, [get_effect(e.name) for e in self.effects],
                                        mp=self.mp)

    def theta(self) -> dict[str, float]:
        """Parameter values for :meth:`ClosedLoopModel.response` of :meth:`model`."""
        theta = dict(self.params)
        for e in self.effects:
            theta.update({f"{e.name}.{p}": v for p, v in e.values})
        return theta

    def response(self, f_hz) -> np.ndarray:
        """The true measured dynamics X/F (m/N) at ``f_hz`` — eq. 4 with the effects."""
        return self.model().response(f_hz, self.theta())

    def as_dict(self) -> dict:
        return {"subject": self.subject, "axis": self.axis, "grip_N": self.grip_N,
                "duration_s": self.duration_s, "n_samples": self.n_samples,
                "mp_kg": self.mp, "params": dict(self.params),
                "effects": [e.as_dict() for e in self.effects]}


def subject_label(index: int, n_subjects: int) -> str:
    """BIDS-style subject label: zero-padded 1-based index, at least two digits."""
    return f"{index + 1:0{max(2, len(str(n_subjects)))}d}"


def _rng(config: StudyConfig, *tags: int) -> np.random.Generator:
    return np.random.default_rng([int(config.seed), *tags])


def subject_factors(config: StudyConfig) -> np.ndarray:
    """Per-subject multiplicative factors, shape (subjects, 5) in the order of PARAM_NAMES.

    Log-normal with log-sd ``config.variability`` and median 1.
    """
    z = np.stack([_rng(config, _STREAM_SUBJECT, s).standard_normal(len(PARAM_NAMES))
                  for s in range(config.subjects)])
    return np.exp(config.variability * z)


def plan_study(config: StudyConfig) -> tuple[TrialPlan, ...]:
    """The truth of every trial of the study, subject by subject, axis, then grip."""
    table = paper_table("grip")
    rows = {(r["axis"], float(r["grip_N"])): [float(r[_TABLE1_COLUMNS[n]]) for n in PARAM_NAMES]
            for r in table.to_dict("records")}
    factors = subject_factors(config)
    lo, hi = config.duration_s
    plans = []
    for s in range(config.subjects):
        for axis in config.axes:
            for grip in config.grips_N:
                params = tuple((n, rows[(axis, float(grip))][i] * float(factors[s, i]))
                               for i, n in enumerate(PARAM_NAMES))
                rng = _trial_rng(config, s, axis, grip)
                n = int(round(rng.uniform(lo, hi) * config.fs))
                effects = tuple(e for e in config.effects if axis in e.axes)
                plans.append(TrialPlan(subject_label(s, config.subjects), s, axis,
                                       float(grip), n, float(config.fs),
                                       DEVICE_MASS_KG[axis], params, effects))
    return tuple(plans)


def _trial_rng(config: StudyConfig, s: int, axis: str, grip: float) -> np.random.Generator:
    return _rng(config, _STREAM_TRIAL, s, AXES.index(axis), int(round(grip * 1000)))


# ---------------------------------------------------------------------------
# Signal building blocks (pure)
# ---------------------------------------------------------------------------

def frame_length(n_samples: int, fs: float, pad_s: float = PAD_S) -> int:
    """Length of the periodic frame holding a record of ``n_samples``: N + pad, FFT-fast."""
    return int(sfft.next_fast_len(n_samples + int(round(pad_s * fs)), real=True))


def shaped_noise(rng: np.random.Generator, n: int, fs: float, gain, count: int = 1
                 ) -> np.ndarray:
    """Periodic Gaussian noise of length ``n``: white noise filtered in the DFT domain.

    The DFT of white Gaussian noise has independent complex Gaussian bins, so the bins
    are drawn directly and multiplied by ``gain(f_hz)``, the filter's magnitude (its
    square is the power spectrum's shape); the DC bin is zeroed. Returns ``count``
    independent signals, shape (count, n), each scaled to unit rms over the period (left
    at zero if the gain is zero everywhere).
    """
    f = sfft.rfftfreq(n, 1.0 / fs)
    g = np.asarray(gain(f), dtype=float)
    g[0] = 0.0
    z = rng.standard_normal((count, 2, f.size))
    out = sfft.irfft((z[:, 0] + 1j * z[:, 1]) * g, n, axis=-1)
    rms = np.sqrt(np.mean(out * out, axis=-1, keepdims=True))
    return np.divide(out, rms, out=out, where=rms > 0)


def band_limited_force(rng: np.random.Generator, n: int, fs: float, band_hz: float,
                       limit_N: float, step_N: float = 0.0) -> np.ndarray:
    """Gaussian white noise ideally low-passed to ``band_hz`` and scaled to peak ``limit_N``.

    The paper's stimulation (Gaussian white noise, low-pass 30 Hz, |F| ≤ 5 N). Periodic
    with period ``n``. Optionally quantised to ``step_N`` (the force converter's step),
    which keeps |F| ≤ limit. Returns force in N, shape (n,).
    """
    f = shaped_noise(rng, n, fs, lambda fr: (fr <= band_hz).astype(float))[0]
    f *= limit_N / np.max(np.abs(f))
    if step_N > 0:
        f = np.trunc(f / step_N) * step_N  # toward zero: never beyond the limit
    return f


def periodic_response(force: np.ndarray, fs: float, response) -> np.ndarray:
    """Steady-state output of a stable continuous LTI system driven by a periodic force.

    ``force`` (N) is one period of a periodic, band-limited signal sampled at ``fs`` (Hz);
    ``response(f_hz)`` is the system's frequency response (m/N), e.g.
    :meth:`ClosedLoopModel.response` (eq. 4). Returns the position (m) at the same
    instants: x = irfft(H(f_k) · rfft(F)), exact for the periodic input (see the module
    docstring). Raises UsageError if the impulse response is not causal or does not decay
    within the period, i.e. the closed loop is unstable or decays too slowly.
    """
    n = force.shape[-1]
    f = sfft.rfftfreq(n, 1.0 / fs)
    h = np.asarray(response(f), dtype=complex)
    h[0] = h[0].real
    if n % 2 == 0:
        h[-1] = h[-1].real
    _check_stable(h, n, fs)
    return sfft.irfft(h * sfft.rfft(force), n)


def _check_stable(h: np.ndarray, n: int, fs: float) -> None:
    """Refuse a response whose impulse response has energy at negative times / the far tail.

    The impulse response of a stable causal system lives at small positive times, so its
    periodised version (the inverse DFT of ``h``) has almost no energy in the second half
    of the period, which holds the negative times and the times beyond half a period. In
    the stable closed loops of Table I with any effect in its physical range that share
    is below 1e-4 (it comes from the band edge at fs/2); an unstable loop shows a
    non-causal impulse response and a share of order 0.1–1.
    """
    imp = sfft.irfft(h, n)
    energy = imp * imp
    tail = energy[n // 2:].sum() / energy.sum()
    if not tail < 1e-3:
        raise UsageError("the simulated closed loop is unstable with these effects (or "
                         f"rings longer than {n / fs / 2:.0f} s): its impulse response is "
                         "not causal; use a smaller reflex gain or delay, or more damping")


def quantise(x: np.ndarray, step: float) -> np.ndarray:
    """Round to the nearest multiple of ``step`` (no-op for step 0)."""
    return np.round(x / step) * step if step > 0 else x


def sample_and_hold(x: np.ndarray, fs: float, rate_hz: float) -> np.ndarray:
    """Sample ``x`` (at ``fs``) at the instants k / rate_hz and hold each value.

    The value held from sample n is x[m], m the first sample at or after the last sensor
    instant k / rate_hz ≤ n / fs.
    """
    n = np.arange(x.shape[-1])
    k = np.floor(n * rate_hz / fs + 1e-9)
    m = np.minimum(np.ceil(k * fs / rate_hz - 1e-9).astype(int), x.shape[-1] - 1)
    return x[..., m]


def grip_signal(rng: np.random.Generator, n: int, fs: float, target_N: float) -> np.ndarray:
    """The grip-force sensor record (N): target ± 0.5 N, 0.01 N steps, held at 65 Hz."""
    wander = GRIP_WANDER_N * shaped_noise(
        rng, n, fs, lambda f: 1.0 / (1.0 + (f / GRIP_WANDER_HZ) ** 4))[0]
    g = wander + GRIP_NOISE_N * rng.standard_normal(n)
    g = np.clip(g, -GRIP_TOLERANCE_N, GRIP_TOLERANCE_N)
    g = np.clip(quantise(target_N + g, GRIP_STEP_N), target_N - GRIP_TOLERANCE_N,
                target_N + GRIP_TOLERANCE_N)
    return sample_and_hold(g, fs, GRIP_RATE_HZ)


# ---------------------------------------------------------------------------
# Trials
# ---------------------------------------------------------------------------

def simulate_trial(plan: TrialPlan, config: StudyConfig) -> Trial:
    """Simulate one trial: forces (N), positions (m) and grip (N), shape (n, 3) / (n,).

    Force only on the stimulated axis (the commanded force on the others is 0). The
    on-axis position is the exact steady-state response of eq. 4 with the plan's effects
    (see the module docstring) plus drift, noise and quantisation.
    """
    fs = config.fs
    n = plan.n_samples
    length = frame_length(n, fs)
    rng = _trial_rng(config, plan.subject_index, plan.axis, plan.grip_N)
    rng.uniform()  # the duration draw of plan_study
    i = AXES.index(plan.axis)
    force_frame = band_limited_force(rng, length, fs, config.force_band_hz,
                                     config.force_limit_N, config.force_step_N)
    motion = periodic_response(force_frame, fs, plan.response)[:n]

    drift = config.drift_m * shaped_noise(
        rng, length, fs, lambda f: 1.0 / np.sqrt(1.0 + (f / DRIFT_CORNER_HZ) ** 4), 3)
    noise = config.noise_m * rng.standard_normal((3, n))
    gains = np.array([1.0 if a == plan.axis else CROSS_COUPLING[(plan.axis, a)]
                      for a in AXES])
    pos = quantise((gains[:, None] * motion + drift[:, :n] + noise).T, config.quantum_m)

    force = np.zeros((n, 3))
    force[:, i] = force_frame[:n]
    grip = grip_signal(rng, n, fs, plan.grip_N)
    meta = TrialMeta(subject=plan.subject, axis=plan.axis, grip_N=plan.grip_N, run=None,
                     fs=fs, n_samples=n, t0_s=0.0, source="simulated")
    return Trial(meta=meta, force=force, pos=pos, grip=grip)


def simulate_study(config: StudyConfig) -> Iterator[tuple[TrialPlan, Trial]]:
    """Yield (truth, trial) for every trial of the study, one at a time."""
    for plan in plan_study(config):
        yield plan, simulate_trial(plan, config)


def truth_dict(config: StudyConfig, plans: Sequence[TrialPlan],
               options: Mapping[str, object] | None = None) -> dict:
    """Everything needed to recompute the true response of every trial, as plain JSON data."""
    settings = asdict(config)
    settings["effects"] = [e.as_dict() for e in config.effects]
    return {
        "generator": "armfit simulate",
        "model": "X/F = H_CL (Fu & Cavusoglu 2010, eq. 4) with effects "
                 "(armfit.models.arm.ClosedLoopModel.response)",
        "seed": config.seed,
        "options": dict(options or {}),
        "config": settings,
        "effects": [e.as_dict() for e in config.effects],
        "cross_coupling": {f"{i}->{j}": g for (i, j), g in CROSS_COUPLING.items()},
        "grip_signal": {"rate_hz": GRIP_RATE_HZ, "tolerance_N": GRIP_TOLERANCE_N,
                        "wander_rms_N": GRIP_WANDER_N, "noise_rms_N": GRIP_NOISE_N,
                        "step_N": GRIP_STEP_N},
        "drift_corner_hz": DRIFT_CORNER_HZ,
        "subject_factors": {subject_label(s, config.subjects): dict(zip(PARAM_NAMES, row,
                                                                        strict=True))
                            for s, row in enumerate(subject_factors(config).tolist())},
        "trials": [p.as_dict() for p in plans],
    }


__all__ = [
    "CROSS_COUPLING", "PAD_S", "DRIFT_CORNER_HZ", "GRIP_RATE_HZ", "GRIP_WANDER_N",
    "GRIP_NOISE_N", "GRIP_STEP_N", "GRIP_WANDER_HZ", "EffectSetting", "StudyConfig",
    "TrialPlan", "subject_label", "subject_factors", "plan_study", "frame_length",
    "shaped_noise", "band_limited_force", "periodic_response", "quantise",
    "sample_and_hold", "grip_signal", "simulate_trial", "simulate_study", "truth_dict",
]
