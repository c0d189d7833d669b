"""Stability of a virtual wall rendered by a sampled haptic device held by the modelled arm.

The loop (see docs/methods.md, "Stability", for the derivation and the choices):

* **Plant** — the measured dynamics of eq. 4 of Fu & Çavuşoğlu 2010 from one parameter
  row, P(s) = X/F = H_ARM / (1 + Mp s² H_ARM) in m/N, with the row's own device mass
  ``mp_kg`` and its effects, each through the rational form its definition declares
  (``Effect.rational``, eq. R1 of :mod:`armfit.models.effects`) (:func:`plant_from_model`).
* **Virtual wall** — the sampled controller
  F[k] = −(K x[k−d] + B (x[k−d] − x[k−d−1]) / T), i.e. C(z) = K + B (1 − z⁻¹)/T with
  d samples of computation delay, its force held by a zero-order hold (ZOH) over T.
* **Test** — P is discretised exactly with the ZOH at T (state space and matrix
  exponential); the loop is stable when every root of 1 + P_zoh(z) C(z) z^(−d) lies
  inside the unit circle (eigenvalues of the closed-loop state matrix).
* **K_max** — the largest wall stiffness K (N/m) such that the loop is stable for every
  K′ in [0, K]. The characteristic polynomial is affine in K, so a root can only cross
  |z| = 1 at a frequency where the open loop is real; every such crossing is found at
  once as a generalised eigenvalue of a symplectic-like pencil (:func:`crossing_gains`),
  which cannot step over a narrow stable or unstable gap; a long loop without virtual
  damping finds them from the phase of the plant's poles and zeros instead, on
  intervals where that phase is proven monotonic (:func:`_phase_crossings`: its work
  grows with the delay's samples, not with their cube). The gains between crossings
  are tested by closed-loop eigenvalues; the first loss of stability is verified to
  0.1 % (:data:`K_REL_TOL`) and refined by bisection if the check fails.

Effects that are not rational: an effect's form num/den·e^(−sτ) may hold a delay τ. On an
output-stage effect (e.g. ``delay``) it is exact — the plant's delays add up to
τ = m T + φ T with m whole samples added to d and the fraction φ ∈ [0, 1) handled by the
modified z-transform (the held force enters the plant partly from the previous sample).
A delay inside an arm or device impedance (e.g. the ``reflex``: a delayed feedback in
continuous time) has no finite sampled form: it is replaced by its [n/n] Padé
approximant, n = :data:`INTERNAL_DELAY_PADE_ORDER` (exact magnitude, phase error below 1°
up to ω·τ ≈ 7.7). An effect that declares no rational form is refused (UsageError).

Robust certificate (:func:`robust_certificate`): the arm's multiplicative uncertainty
H_ARM (1 + Wu Δ), ‖Δ‖∞ ≤ 1, sees the complementary sensitivity
T = Z_env / (Z_ARM + Z_env), Z_env = Mp s² + C_eq(jω) the impedance the device presents
to the hand; the sampler, controller, delay and hold enter as
C_eq(jω) = (1 − e^(−jωT))/(jωT) · C(e^(jωT)) · e^(−jωdT) (the base band of the sampled
loop; aliased terms are neglected, which is accurate in the band of the weight, far
below the Nyquist frequency). The loop is robustly stable if it is nominally stable and
max over the band of |Wu T| < 1.

Units: K in N/m, B in N·s/m, T in s, frequencies in Hz unless named ``_rad``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from armfit import _scipy
from armfit._order import median, percentile
from armfit.errors import UsageError, cell
from armfit.io.schema import is_missing
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import EFFECTS, Effect
from armfit.models.params import model_from_params
from armfit.uncertainty import PAPER_BAND_HZ

if TYPE_CHECKING:   # pandas is imported where a table is made (it takes ~0.15 s)
    pass

#: Defaults of the wall: a 1 kHz servo, no virtual damping, one sample of delay.
DEFAULT_SAMPLE_TIME_S = 1.0e-3
DEFAULT_DAMPING_NS_PER_M = 0.0
DEFAULT_DELAY_SAMPLES = 1

#: Order n of the [n/n] Padé approximant that replaces a delay inside an arm or device
#: impedance (e.g. the reflex's): exact magnitude, phase error below 1° up to ω·τ ≈ 7.7
#: (31 Hz for τ = 40 ms).
INTERNAL_DELAY_PADE_ORDER = 6

#: Most samples of latency (the plant's delay plus the computation delay d) a loop may
#: hold: each sample is a state of the sampled loop, and the eigenvalues that test it
#: lose their accuracy past about 80 such states (a shift register is a nilpotent block;
#: at 96 they report a stable loop unstable). A longer loop is refused, not answered.
MAX_LOOP_DELAY_SAMPLES = 64

#: Relative accuracy to which K_max is verified (and refined when needed): 0.1 %.
K_REL_TOL = 1.0e-3

#: Points per decade of the frequency grid of the robust certificate.
CERT_POINTS_PER_DECADE = 400

#: ``limited_by`` of a certificate withheld because, above the weight's band, a member
#: model departs from the nominal by more than |Wu| (``beyond_margin`` > 1).
WITHHELD = "withheld: members beyond weight"


@dataclass(frozen=True)
class WallSettings:
    """The sampled virtual wall: servo period ``sample_time_s`` (s), virtual damping
    ``damping_Ns_per_m`` (N·s/m) and computation delay ``delay_samples`` (whole samples).

    Raises UsageError (exit 2) for T ≤ 0 (or not finite), B < 0 (or not finite), d < 0 or
    a fractional d.
    """

    sample_time_s: float = DEFAULT_SAMPLE_TIME_S
    damping_Ns_per_m: float = DEFAULT_DAMPING_NS_PER_M
    delay_samples: int = DEFAULT_DELAY_SAMPLES

    def __post_init__(self) -> None:
        T, B, d = self.sample_time_s, self.damping_Ns_per_m, self.delay_samples
        if not (isinstance(T, (int, float)) and math.isfinite(T) and T > 0):
            raise UsageError(f"{{opt:sample_time_s}} must be a period > 0 s, got {cell(T)}")
        if not (isinstance(B, (int, float)) and math.isfinite(B) and B >= 0):
            raise UsageError(f"{{opt:damping_Ns_per_m}} must be >= 0 N*s/m (a virtual damper), "
                             f"got {cell(B)}")
        if isinstance(d, bool) or not isinstance(d, (int, np.integer)):
            if isinstance(d, float) and d.is_integer():
                object.__setattr__(self, "delay_samples", int(d))
                d = int(d)
            else:
                raise UsageError(f"{{opt:delay_samples}} must be a whole number of samples, "
                                 f"got {cell(d)}")
        if d < 0:
            raise UsageError(f"{{opt:delay_samples}} must be >= 0, got {d}")
        object.__setattr__(self, "sample_time_s", float(T))
        object.__setattr__(self, "damping_Ns_per_m", float(B))
        object.__setattr__(self, "delay_samples", int(d))

    def as_dict(self) -> dict[str, float | int]:
        """The settings with their units in the names (the JSON ``settings``)."""
        return {"sample_time_s": self.sample_time_s, "servo_rate_hz": 1.0 / self.sample_time_s,
                "damping_Ns_per_m": self.damping_Ns_per_m, "delay_samples": self.delay_samples}


# ---------------------------------------------------------------------------
# The plant as a rational function (plus an output delay)
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class RationalPlant:
    """P(s) = num(s)/den(s) · e^(−s·delay_s): coefficients highest power first, s in
    rad/s, P in m/N. Strictly proper (deg num < deg den)."""

    num: np.ndarray
    den: np.ndarray
    delay_s: float = 0.0

    def response(self, f_hz) -> np.ndarray:
        """P(j2πf) in m/N."""
        s = 2j * np.pi * np.asarray(f_hz, float)
        return np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay_s)


def pade_delay(delay_s: float, order: int) -> tuple[np.ndarray, np.ndarray]:
    """[n/n] Padé approximant of e^(−s·delay_s): (num, den), s in rad/s, highest first.

    c_k = (2n − k)! n! / ((2n)! k! (n − k)!); num = Σ c_k (−τ s)^k, den = Σ c_k (τ s)^k.
    """
    n = int(order)
    c = np.array([math.factorial(2 * n - k) * math.factorial(n)
                  / (math.factorial(2 * n) * math.factorial(k) * math.factorial(n - k))
                  for k in range(n + 1)])
    tk = c * delay_s ** np.arange(n + 1)
    num = (tk * (-1.0) ** np.arange(n + 1))[::-1]
    return num, tk[::-1].copy()


def _polymul(a, b) -> np.ndarray:
    """``np.polymul(a, b)`` of coefficient arrays (highest power first) without its
    ``poly1d`` objects: the leading zeros of each dropped (all zeros: [0]), then their
    convolution, the same numbers."""
    out = []
    for c in (a, b):
        c = np.atleast_1d(c)
        nz = np.flatnonzero(c)
        out.append(c[nz[0]:] if nz.size else np.zeros(1, c.dtype))
    return np.convolve(out[0], out[1])


def rational_sum(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """a + b of two rational functions given as (numerator, denominator) coefficients,
    highest power first.

    Parameters
    ----------
    a, b : tuple of numpy.ndarray

    Returns
    -------
    tuple of numpy.ndarray
    """
    return (np.polyadd(_polymul(a[0], b[1]), _polymul(b[0], a[1])),
            _polymul(a[1], b[1]))


def _effect_rational(e: Effect, values: Mapping[str, float], mp: float
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """(num, den, delay_s) of one effect's term (eq. R1 of :mod:`armfit.models.effects`):
    an impedance in N/m (stage arm or device) or an output factor. Raises UsageError
    (one line) naming the effect and where it came from when it declares no rational
    form."""
    if e.rational is None:
        origin = EFFECTS.describe_origin(e.name) if EFFECTS.origin_of(e) is not None \
            else "no registered source"
        raise UsageError(f"stability: effect {e.name!r} (from {origin}) declares no "
                         "rational form: add rational=... to its Effect; see "
                         "docs/methods.md#your-own-effects")
    return e.rational_form(values, mp)


def plant_from_model(model: ClosedLoopModel, theta: Mapping[str, float], *,
                     pade_order: int = INTERNAL_DELAY_PADE_ORDER) -> RationalPlant:
    """The measured dynamics X/F (eq. 4, with the model's effects) as a
    :class:`RationalPlant`.

    X/F = Π R_out / (Z_ARM + ΔZ_arm + Mp s² + ΔZ_dev) with Z_ARM = C1 (Ma s² + C2) /
    (Ma s² + C1 + C2) (eq. 3), exactly as :meth:`ClosedLoopModel.response`, each effect's
    term from its ``rational`` form num/den·e^(−sτ) (eq. R1 of
    :mod:`armfit.models.effects`). Delays of output effects are kept apart (summed) as
    ``delay_s``; a delay inside an arm or device impedance is replaced by its [n/n] Padé
    approximant, n = ``pade_order``.

    Raises
    ------
    UsageError
        An effect declares no rational form (named, with where it came from), or X/F
        is not strictly proper.
    """
    values = {n: float(v) for n, v in model.values(theta).items()}
    Ma, k1, k2, b1, b2 = (values[n] for n in ("Ma", "k1", "k2", "b1", "b2"))
    z = (_polymul([b1, k1], [Ma, b2, k2]), np.array([Ma, b1 + b2, k1 + k2]))
    z = rational_sum(z, (np.array([model.mp, 0.0, 0.0]), np.array([1.0])))
    out = (np.array([1.0]), np.array([1.0]))
    delay = 0.0
    for e in model.effects:
        v = {p.name: values[f"{e.name}.{p.name}"] for p in e.params}
        num, den, tau = _effect_rational(e, v, model.mp)
        if e.stage == "output":
            out = (_polymul(out[0], num), _polymul(out[1], den))
            delay += tau
            continue
        if tau > 0:
            pn, pd = pade_delay(tau, pade_order)
            num, den = _polymul(num, pn), _polymul(den, pd)
        z = rational_sum(z, (num, den))
    num = _polymul(out[0], z[1])
    den = _polymul(out[1], z[0])
    num = np.trim_zeros(num, "f")
    den = np.trim_zeros(den, "f")
    if num.size >= den.size:
        raise UsageError("stability: the plant X/F must be strictly proper")
    return RationalPlant(num, den, delay)


# ---------------------------------------------------------------------------
# Exact ZOH discretisation and the closed-loop state matrix
# ---------------------------------------------------------------------------

def _companion(num: np.ndarray, den: np.ndarray, T: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Controllable canonical form of num/den in normalised time t/T (ŝ = sT):
    (A, B, C) with P(s) = C (ŝ I − A)⁻¹ B."""
    n = den.size - 1
    numf = np.concatenate([np.zeros(n + 1 - num.size), num])
    scale = T ** np.arange(n + 1)            # coefficient of s^(n−k) times T^k
    a = den * scale
    bnum = numf * scale
    a, bnum = a / a[0], bnum / a[0]
    A = np.zeros((n, n))
    A[0, :] = -a[1:]
    A[1:, :-1] = np.eye(n - 1)
    B = np.zeros(n)
    B[0] = 1.0
    return A, B, bnum[1:].copy()


def expm_batch(M: np.ndarray) -> np.ndarray:
    """e^M for a stack of square matrices (..., n, n): scaling and squaring with a
    degree-18 Taylor polynomial after scaling to ‖M/2^s‖₁ ≤ 1/2 (truncation error below
    (1/2)^19/19! ≈ 2e-23, i.e. at rounding level), batched over the stack."""
    M = np.asarray(M, float)
    norm = np.max(np.sum(np.abs(M), axis=-2), axis=-1)
    sq = np.maximum(0, np.ceil(np.log2(np.maximum(norm, 1e-300) / 0.5))).astype(int)
    X = M / (2.0 ** sq)[..., None, None]
    eye = np.broadcast_to(np.eye(M.shape[-1]), M.shape)
    out = eye.copy()
    for k in range(18, 0, -1):           # Horner: I + X/1 (I + X/2 (I + ...))
        out = eye + (X @ out) / k
    for i in range(int(sq.max()) if sq.size else 0):
        more = sq > i
        out = np.where(more[..., None, None], out @ out, out)
    return out


@dataclass(frozen=True)
class _Group:
    """Loops of equal shape, stacked: A_cl(K) = M0 + K b cᵀ (R, N, N)."""

    rows: np.ndarray          # indices into the caller's list
    M0: np.ndarray            # (R, N, N)
    b: np.ndarray             # (R, N)
    c: np.ndarray             # (R, N)
    #: the sampled plant x[k+1] = Pd x[k] + Gd u[k], y = Cd x (n states, n ≤ N) and the
    #: controller's D and B/T, from which :meth:`g` takes g(z) = cᵀ(zI − M0)⁻¹b
    Pd: np.ndarray            # (R, n, n)
    Gd: np.ndarray            # (R, n)
    Cd: np.ndarray            # (R, n)
    D: int
    BT: float

    def g(self, idx: np.ndarray, z: np.ndarray) -> np.ndarray:
        """g(z) = cᵀ(zI − M0)⁻¹b of loops ``idx`` at ``z`` (one each), from the plant
        alone: the controller u = −(K + (B/T)(1 − z⁻¹)) z^(−D) y closes the loop, so with
        P(z) = Cd(zI − Pd)⁻¹Gd, 1 − K g(z) = 0 ⇔ z^(D+1) + ((B/T)(z − 1) + K z) P(z) = 0,
        i.e. g(z) = −z P(z) / (z^(D+1) + (B/T)(z − 1) P(z)). One solve of the plant's n
        states per point instead of the loop's N (the delay's shift register is the rest
        of M0)."""
        P = _g_of(self.Pd[idx], self.Gd[idx], self.Cd[idx], z)     # Cd(zI − Pd)⁻¹Gd
        with np.errstate(all="ignore"):
            return -z * P / (z ** (self.D + 1) + self.BT * (z - 1.0) * P)


def _loops(plants: Sequence[RationalPlant], settings: WallSettings) -> list[_Group]:
    """The closed-loop state matrices of every plant, grouped by shape and batched.

    Discrete plant (exact ZOH, modified z-transform for the fractional delay φ):
    x[k+1] = Φ x[k] + Γ0 u[k] + Γ1 u[k−1], y = C x, Φ = e^(A), Γ0 = Γ(1−φ),
    Γ1 = e^(A(1−φ)) Γ(φ), Γ(h) = ∫₀ʰ e^(Aη) dη B (normalised time), via the exponential
    of [[A, B], [0, 0]]. Controller state: q_i[k] = y[k−i], i = 1..D+1, D = d + m.
    """
    T = settings.sample_time_s
    BT = settings.damping_Ns_per_m / T
    items = []
    for i, p in enumerate(plants):
        tau = p.delay_s / T
        m = int(math.floor(tau + 1e-12))
        phi = tau - m
        if phi < 1e-9:
            phi = 0.0
        A, B, C = _companion(np.asarray(p.num, float), np.asarray(p.den, float), T)
        items.append((i, A, B, C, m, phi))
    keys: dict[tuple, list] = {}
    for it in items:
        keys.setdefault((it[1].shape[0], it[5] > 0, it[4]), []).append(it)
    groups = []
    for (n, frac, m), its in keys.items():
        R = len(its)
        A = np.stack([it[1] for it in its])
        Bv = np.stack([it[2] for it in its])
        C = np.stack([it[3] for it in its])
        phi = np.array([it[5] for it in its])
        E = np.zeros((R, n + 1, n + 1))
        E[:, :n, :n] = A
        E[:, :n, n] = Bv
        e_lo = expm_batch(E * (1.0 - phi)[:, None, None])
        Phi_hi = e_lo[:, :n, :n]
        G0 = e_lo[:, :n, n]
        if frac:
            e_phi = expm_batch(E * phi[:, None, None])
            Phi = Phi_hi @ e_phi[:, :n, :n]
            G1 = np.einsum("rij,rj->ri", Phi_hi, e_phi[:, :n, n])
            nd = n + 1
            Pd = np.zeros((R, nd, nd))
            Pd[:, :n, :n] = Phi
            Pd[:, :n, n] = G1
            Gd = np.concatenate([G0, np.ones((R, 1))], axis=1)
            Cd = np.concatenate([C, np.zeros((R, 1))], axis=1)
        else:
            nd, Pd, Gd, Cd = n, Phi_hi, G0, C
        D = settings.delay_samples + m
        N = nd + D + 1
        M0 = np.zeros((R, N, N))
        M0[:, :nd, :nd] = Pd
        M0[:, nd, :nd] = Cd
        for k in range(1, D + 1):
            M0[:, nd + k, nd + k - 1] = 1.0
        rD = np.zeros((R, N))
        if D == 0:
            rD[:, :nd] = Cd
        else:
            rD[:, nd + D - 1] = 1.0
        rD1 = np.zeros((R, N))
        rD1[:, nd + D] = 1.0
        M0[:, :nd, :] += BT * Gd[:, :, None] * (rD1 - rD)[:, None, :]
        b = np.concatenate([-Gd, np.zeros((R, D + 1))], axis=1)
        groups.append(_Group(np.array([it[0] for it in its]), M0, b, rD, Pd, Gd, Cd, D, BT))
    return groups


def _spectral_radius(g: _Group, idx: np.ndarray, K: np.ndarray) -> tuple[np.ndarray,
                                                                           np.ndarray]:
    """Largest |eigenvalue| of A_cl(K) and that eigenvalue, for loops ``idx`` at ``K``."""
    mats = g.M0[idx] + K[:, None, None] * g.b[idx][:, :, None] * g.c[idx][:, None, :]
    ev = np.linalg.eigvals(mats)
    j = np.argmax(np.abs(ev), axis=1)
    top = ev[np.arange(ev.shape[0]), j]
    return np.abs(top), top


def crossing_gains(M0: np.ndarray, b: np.ndarray, c: np.ndarray, *, tol: float = 1e-6
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Every gain K > 0 at which an eigenvalue of M0 + K b cᵀ lies on the unit circle.

    An eigenvalue z = e^(jθ) needs 1 = K g(z), g(z) = cᵀ (zI − M0)⁻¹ b, so g(e^(jθ))
    must be real: g(z) − g(1/z) = 0 (on |z| = 1, g(1/z) is g's conjugate). Its zeros are
    the finite generalised eigenvalues of the pencil z Ē − Ā with
    Ā = [[M0, 0, b], [0, −I, 0], [−cᵀ, cᵀ, 0]] and Ē = [[I, 0, 0], [0, −M0, −b], [0, 0, 0]]
    (rows: (zI − M0) x − b u = 0, (I − z M0) ξ − z b u = 0, cᵀx − cᵀξ = 0): all of them
    at once, so no crossing can be stepped over. Those within ``tol`` of the circle, and
    z = ±1 always, give K = 1/Re g(e^(jθ)). Returns (K, θ in rad per sample), K > 0.
    """
    (out,) = _crossing_gains_batch(M0[None], b[None], c[None], tol=tol)
    return out


def _pencils(M0: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pencils (Ā, Ē) of :func:`crossing_gains` for a stack of loops (R, N, N)."""
    R, N, _ = M0.shape
    n = 2 * N + 1
    A = np.zeros((R, n, n))
    E = np.zeros((R, n, n))
    eye = np.eye(N)
    A[:, :N, :N] = M0
    A[:, :N, 2 * N] = b
    A[:, N:2 * N, N:2 * N] = -eye
    A[:, 2 * N, :N] = -c
    A[:, 2 * N, N:2 * N] = c
    E[:, :N, :N] = eye
    E[:, N:2 * N, N:2 * N] = -M0
    E[:, N:2 * N, 2 * N] = -b
    return A, E


def _lapack_ggev(a: np.ndarray):
    """LAPACK's generalised eigenvalue routine for ``a``'s type, the function
    ``scipy.linalg.get_lapack_funcs(("ggev",), (a,))`` returns, from scipy's LAPACK
    module loaded alone (:func:`armfit._scipy.compiled_module`): importing :mod:`scipy.linalg`
    took about 0.13 s of every command's start-up that loads this module (``run``,
    ``stability``)."""
    prefix = {"f": "s", "d": "d", "F": "c", "D": "z"}.get(a.dtype.char)
    lapack = _scipy.compiled_module("scipy.linalg._flapack") if prefix else None
    fn = getattr(lapack, f"{prefix}ggev", None)
    if fn is None:
        from scipy import linalg
        fn, = linalg.get_lapack_funcs(("ggev",), (a,))
    return fn


def _eigvals(a: np.ndarray, e: np.ndarray) -> np.ndarray:
    """``scipy.linalg.eigvals(a, e)``: the pencil's eigenvalues where ggev itself
    reported a failure."""
    from scipy import linalg
    return linalg.eigvals(a, e)


def _crossing_gains_batch(M0: np.ndarray, b: np.ndarray, c: np.ndarray, *,
                          tol: float = 1e-6, g_of: Callable | None = None
                          ) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`crossing_gains` of each loop of a stack (M0 (R, N, N), b, c (R, N)): the
    pencils are built at once and g(e^(jθ)) of every candidate is solved in one batch;
    only the generalised eigenvalue problems (LAPACK ``ggev``) go one by one. ``g_of``
    (loop indices, z) → g(z) replaces that solve (:meth:`_Group.g`: from the plant's
    states alone)."""
    R, N, _ = M0.shape
    A, E = _pencils(M0, b, c)
    ggev = _lapack_ggev(A[0])
    rows, thetas, unique, inverse = [], [], [], []
    offset = 0
    for r in range(R):
        with np.errstate(all="ignore"):
            ar, ai, beta, _, _, _, info = ggev(A[r], E[r], compute_vl=0, compute_vr=0)
            ev = (ar + 1j * ai) / beta if info == 0 else _eigvals(A[r], E[r])
        ev = ev[np.isfinite(ev)]
        on = ev[np.abs(np.abs(ev) - 1.0) < tol]
        th = np.concatenate([np.abs(np.angle(on)), [0.0, np.pi]])
        rows.append(np.full(th.size, r))
        thetas.append(th)
        # a complex pair of eigenvalues gives the same θ twice: g is solved once for it
        u, inv = np.unique(th, return_inverse=True)
        inverse.append(inv + offset)
        unique.append(u)
        offset += u.size
    idx = np.concatenate(rows)
    theta = np.concatenate(thetas)
    u_idx = np.concatenate([np.full(u.size, r) for r, u in enumerate(unique)])
    zu = np.exp(1j * np.concatenate(unique))
    g = (_g_of(M0[u_idx], b[u_idx], c[u_idx], zu) if g_of is None else g_of(u_idx, zu))
    g = g[np.concatenate(inverse)]
    with np.errstate(all="ignore"):
        K = 1.0 / g.real
    ok = np.isfinite(K) & (K > 0) & (np.abs(g.imag) <= 1e-6 * np.abs(g) + 1e-300)
    return [(K[ok & (idx == r)], theta[ok & (idx == r)]) for r in range(R)]


def _g_of(M0, b, c, z):
    """g(z) = cᵀ (zI − M0)⁻¹ b for each row of the stacks M0 (P, N, N), b, c (P, N) at
    z (P,)."""
    N = M0.shape[-1]
    mats = z[:, None, None] * np.eye(N) - M0
    with np.errstate(all="ignore"):
        try:
            sol = np.linalg.solve(mats, b[..., None].astype(complex))[..., 0]
        except np.linalg.LinAlgError:
            sol = np.stack([np.linalg.lstsq(m, v, rcond=None)[0]
                            for m, v in zip(mats, b.astype(complex), strict=True)])
    return np.einsum("pn,pn->p", sol, c)


@dataclass(frozen=True)
class WallStability:
    """K_max of one loop: ``k_max_N_per_m`` (0 if unstable at K = 0; inf if never lost),
    ``f_unstable_hz`` (frequency of the root that leaves the unit circle at K_max, Hz;
    at K = 0 that of the outermost unstable root), ``unstable_at_zero``."""

    k_max_N_per_m: float
    f_unstable_hz: float
    unstable_at_zero: bool


def wall_stability(plants: Sequence[RationalPlant], settings: WallSettings
                   ) -> list[WallStability]:
    """K_max (N/m) and the frequency of the first instability for each plant.

    Stacked by shape: the closed-loop matrices of a group are built and tested together
    (batched matrix exponentials and eigenvalues), at most :data:`WALL_BATCH` plants at a
    time. See the module docstring.
    """
    T = settings.sample_time_s
    worst = max((loop_delay_samples(p, settings) for p in plants), default=0)
    if worst > MAX_LOOP_DELAY_SAMPLES:
        raise UsageError(f"the loop holds {worst} samples of latency (the model's delay at "
                         f"T = {T * 1e3:g} ms plus d = {settings.delay_samples}); armfit "
                         f"analyses up to {MAX_LOOP_DELAY_SAMPLES}: use a longer "
                         "{opt:sample_time_s}")
    plants = list(plants)
    out: list[WallStability] = []
    for start in range(0, len(plants), WALL_BATCH):
        out += _wall_stability(plants[start:start + WALL_BATCH], settings)
    return out


#: Loops :func:`wall_stability` analyses together at most (their matrices stacked): a
#: study's thousands of trial fits take the memory of this many at a time (4,050 fits
#: in one batch took 34 MB), each loop's answer the same.
WALL_BATCH = 256


def _wall_stability(plants: Sequence[RationalPlant], settings: WallSettings
                    ) -> list[WallStability]:
    """:func:`wall_stability` of ``plants``, all at once."""
    out: list[WallStability | None] = [None] * len(plants)
    T = settings.sample_time_s
    for g in _loops(plants, settings):
        R = g.M0.shape[0]
        cands, thetas = _crossings(g)
        # the usual case first: stable just below the first crossing gain K₁ and unstable
        # just above it (± K_REL_TOL/2, before the next crossing), all loops at once:
        # these two gains lie in the first two intervals between crossings, so they are
        # the interval test's gains and its check at once (K_max = K₁, as the interval
        # test finds it); any other loop is tested interval by interval
        rest = [r for r in range(R) if not cands[r].size]
        crossing = [r for r in range(R) if cands[r].size]
        if crossing:
            k1 = np.array([cands[r][0] for r in crossing])
            probe = np.stack([k1 * (1 - K_REL_TOL / 2), k1 * (1 + K_REL_TOL / 2)], 1).ravel()
            rho, _ = _spectral_radius(g, np.repeat(crossing, 2), probe)
            for i, r in enumerate(crossing):
                K = cands[r]
                if rho[2 * i] < 1.0 <= rho[2 * i + 1] and (K.size == 1
                                                           or probe[2 * i + 1] < K[1]):
                    out[g.rows[r]] = WallStability(float(K[0]),
                                                   float(thetas[r][0]) / (2 * np.pi * T), False)
                else:
                    rest.append(r)
        _by_intervals(g, sorted(rest), cands, thetas, T, out)
    return out  # type: ignore[return-value]


def _crossings(g: _Group) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Each loop's crossing gains (:func:`crossing_gains`, g from the plant alone)
    sorted, those within 1e-9 (relative) of the one below dropped, and their angles.

    Loops of at least :data:`PHASE_ROUTE_MIN_STATES` states without virtual damping take
    the phase route (:func:`_phase_crossings`); the others, and any loop that route
    cannot certify, the pencil's generalised eigenvalues (:func:`crossing_gains`)."""
    R, N = g.M0.shape[:2]
    found: list[tuple[np.ndarray, np.ndarray] | None] = [None] * R
    if g.BT == 0.0 and N >= PHASE_ROUTE_MIN_STATES:
        found = _phase_crossings(g)
    rest = np.array([r for r in range(R) if found[r] is None], int)
    if rest.size:
        for r, KT in zip(rest, _crossing_gains_batch(
                g.M0[rest], g.b[rest], g.c[rest], g_of=lambda i, z: g.g(rest[i], z)),
                strict=True):
            found[r] = KT
    cands, thetas = [], []
    for K, th in found:   # type: ignore[misc]
        K, th = _distinct_sorted(K, th)
        cands.append(K)
        thetas.append(th)
    return cands, thetas


def _distinct_sorted(K: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Crossing gains ``K`` sorted, those within 1e-9 (relative) of the one below
    dropped, and their angles ``theta``."""
    order = np.argsort(K)
    K, theta = K[order], theta[order]
    keep = np.concatenate([[True], np.diff(K) > 1e-9 * K[1:]]) if K.size else K > 0
    return K[keep], theta[keep]


#: Loops of at least this many states (plant, delay and controller) take the phase route
#: to their crossing gains when they have no virtual damping (:func:`_phase_crossings`):
#: its cost grows with the delay's samples, the QZ of the pencil's 2N + 1 rows with their
#: cube; below about twelve states the pencil is the cheaper (measured on the stability
#: figure's sweep).
PHASE_ROUTE_MIN_STATES = 12

#: Halvings of an interval the phase route tries before it leaves the loop to the pencil.
_PHASE_MAX_HALVINGS = 40
#: Largest error (rad) of the phase from the plant's poles and zeros, against that of g
#: from its states, with which the phase route still answers.
_PHASE_MAX_MISS = 1e-4


def _plant_roots(g: _Group) -> tuple[np.ndarray, np.ndarray]:
    """The poles and finite zeros of each loop's sampled plant P(z) = Cd (zI − Pd)⁻¹ Gd:
    (roots (R, k), weights (R, k): +1 a pole, −1 a zero, 0 padding). The poles are the
    eigenvalues of Pd; the zeros the finite generalised eigenvalues of the Rosenbrock
    pencil ([[Pd, Gd], [Cd, 0]], [[I, 0], [0, 0]]) (a huge one, an infinite eigenvalue
    found finite, adds a phase of about 1/|a|: nothing)."""
    R, nd = g.Pd.shape[:2]
    poles = np.linalg.eigvals(g.Pd)
    A = np.zeros((nd + 1, nd + 1))
    E = np.zeros((nd + 1, nd + 1))
    E[:nd, :nd] = np.eye(nd)
    ggev = _lapack_ggev(A)
    zeros = []
    for r in range(R):
        A[:nd, :nd] = g.Pd[r]
        A[:nd, nd] = g.Gd[r]
        A[nd, :nd] = g.Cd[r]
        with np.errstate(all="ignore"):
            ar, ai, beta, _, _, _, info = ggev(A, E, compute_vl=0, compute_vr=0)
            z = (ar + 1j * ai) / beta if info == 0 else _eigvals(A, E)
        zeros.append(z[np.isfinite(z)])
    k = nd + max(z.size for z in zeros)
    roots = np.zeros((R, k), complex)
    weight = np.zeros((R, k))
    roots[:, :nd] = poles
    weight[:, :nd] = 1.0
    for r, z in enumerate(zeros):
        roots[r, nd:nd + z.size] = z
        weight[r, nd:nd + z.size] = -1.0
    return roots, weight


class _Phase:
    """The phase H(θ) = D θ − arg P(e^(jθ)) of the loops of a group without virtual
    damping, from the plant's poles and zeros: there g(z) = −z^(−D) P(z), so g(e^(jθ)) is
    real exactly where H(θ) ∈ πℤ. Each root a gives arg(e^(jθ) − a) continuously in θ, up
    to a constant: θ + arg(1 − a e^(−jθ)) for |a| < 1, arg(1 − e^(jθ)/a) for |a| > 1 (the
    arguments of numbers with a positive real part); the constants sum to a multiple of π
    (conjugate pairs and real roots), and H(0) = 0.

    ``roots`` (R, k) complex and ``weight`` (R, k): +1 a pole, −1 a zero, 0 padding (a
    root at 0 of weight 0 adds nothing)."""

    def __init__(self, roots: np.ndarray, weight: np.ndarray, D: int) -> None:
        self.roots, self.weight, self.D = roots, weight, int(D)
        self.r, self.alpha = np.abs(roots), np.angle(roots)
        self.inside = self.r < 1.0
        with np.errstate(all="ignore"):
            self.c = np.where(self.inside, roots, 1.0 / np.where(self.inside, 1.0, roots))
        # H's slope from the roots inside (each adds θ), the rest from their arguments
        self.slope = self.D + np.sum(np.where(self.inside, weight, 0.0), axis=1)

    @classmethod
    def of(cls, g: _Group) -> _Phase:
        roots, weight = _plant_roots(g)
        return cls(roots, weight, g.D)

    def at(self, idx: np.ndarray, theta: np.ndarray, derivative: bool = False):
        """H(θ) of loops ``idx`` at ``theta`` (one each), and with ``derivative`` also
        H′(θ) = D + Σ ± Re(e^(jθ) / (e^(jθ) − a)) (+ for a pole, − for a zero)."""
        w, inside = self.weight[idx], self.inside[idx]
        e = np.exp(1j * theta)[:, None]
        u = 1.0 - self.c[idx] * np.where(inside, np.conj(e), e)
        h = self.slope[idx] * theta + np.sum(w * np.arctan2(u.imag, u.real), axis=1)
        if not derivative:
            return h
        with np.errstate(all="ignore"):
            terms = w * (e / (e - self.roots[idx])).real
        return h, self.D + np.sum(terms, axis=1)

    def slope_bounds(self, idx: np.ndarray, lo: np.ndarray, hi: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of H′ over the intervals [lo, hi] of loops ``idx``. Each root's term
        Re(e^(jθ) / (e^(jθ) − a)) = (1 − r c) / (1 − 2 r c + r²), c = cos(θ − arg a), is
        monotonic in c (rising for r = |a| < 1, falling for r > 1), so its extremes over
        an interval lie where c does: at 1 or −1 when the interval holds arg a or
        arg a + π, else at an end. A root on the circle whose angle the interval holds
        leaves it unbounded."""
        w, r, alpha = self.weight[idx], self.r[idx], self.alpha[idx]
        lo, hi = lo[:, None], hi[:, None]
        width = hi - lo
        c_lo, c_hi = np.cos(lo - alpha), np.cos(hi - alpha)
        holds = np.mod(alpha - lo, 2 * np.pi) <= width
        holds_opposite = np.mod(alpha + np.pi - lo, 2 * np.pi) <= width
        c_max = np.where(holds, 1.0, np.maximum(c_lo, c_hi))
        c_min = np.where(holds_opposite, -1.0, np.minimum(c_lo, c_hi))
        with np.errstate(all="ignore"):
            at_max = (1 - r * c_max) / (1 - 2 * r * c_max + r * r)
            at_min = (1 - r * c_min) / (1 - 2 * r * c_min + r * r)
        t_lo = np.where(r < 1, at_min, at_max)
        t_hi = np.where(r < 1, at_max, at_min)
        on_circle = (np.abs(r - 1) < 1e-9) & holds
        t_lo = np.where(on_circle, -np.inf, t_lo)
        t_hi = np.where(on_circle, np.inf, t_hi)
        s_lo = np.where(w > 0, t_lo, np.where(w < 0, -t_hi, 0.0))
        s_hi = np.where(w > 0, t_hi, np.where(w < 0, -t_lo, 0.0))
        return self.D + np.sum(s_lo, axis=1), self.D + np.sum(s_hi, axis=1)


def _phase_crossings(g: _Group) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """The crossing gains of each loop of a group without virtual damping (B = 0), as
    :func:`crossing_gains` finds them, from the phase H(θ) of :class:`_Phase`: every
    θ ∈ (0, π) with H(θ) ∈ πℤ, and θ = 0 and π; K = 1/Re g(e^(jθ)) from the plant's
    states (:meth:`_Group.g`). None for a loop the route cannot certify.

    [0, π] is cut into intervals on each of which H is proven monotonic (the bounds of
    H′ of :meth:`_Phase.slope_bounds` exclude 0) or proven to hold no root (H at the
    middle is farther from πℤ than the largest |H′| times the half-width allows); an
    interval neither proves is halved, at most :data:`_PHASE_MAX_HALVINGS` times. On a
    monotonic interval each multiple of π between its ends' H is one root, found by
    Newton's method kept inside its bracket (bisection when a step leaves it). So no
    crossing can be missed, as with the pencil's eigenvalues, while the work grows with
    the delay's samples instead of their cube. A loop is left to the pencil when an
    interval stays unproven (a root of the plant on the unit circle, a tangential
    crossing), when H misses the phase of g from the plant's states by more than
    :data:`_PHASE_MAX_MISS` at the grid or at a root (poles and zeros not found to that
    accuracy), or when a decision lies within ten times that miss of a multiple of π."""
    R, N = g.M0.shape[:2]
    ph = _Phase.of(g)
    m = max(16, N)      # the first grid: an interval per state of the loop, at least 16
    grid = np.linspace(0.0, np.pi, m + 1)
    at = np.repeat(np.arange(R), m + 1)
    H = ph.at(at, np.tile(grid, R)).reshape(R, m + 1)
    # g(e^(jθ)) = −e^(−jDθ) P: its angle is π − H, so sin(H + angle g) vanishes; what it
    # leaves at the grid (and at the roots, below) measures how far the poles and zeros
    # miss the plant's states, and every decision keeps ten times that from a level
    with np.errstate(all="ignore"):
        gz = g.g(at, np.exp(1j * np.tile(grid, R))).reshape(R, m + 1)
        miss = np.abs(np.sin(H + np.angle(gz)))
    miss = np.max(np.where(np.isfinite(gz), miss, 0.0), axis=1)
    H[:, 0] = 0.0
    H[:, -1] = np.pi * np.round(H[:, -1] / np.pi)    # P(−1) is real
    pieces, (f_idx, slack), unproven = _phase_intervals(
        ph, H, grid, 10.0 * np.minimum(miss, _PHASE_MAX_MISS) + 1e-9)
    r_idx, theta = _phase_roots(ph, pieces)
    # one step on the phase of g itself, from the plant's states: the root then owes
    # nothing to the accuracy of the poles and zeros
    if theta.size:
        with np.errstate(all="ignore"):
            gz = g.g(r_idx, np.exp(1j * theta))
            _, slope = ph.at(r_idx, theta, derivative=True)
            off = np.arctan(gz.imag / gz.real)
        np.maximum.at(miss, r_idx, np.where(np.isfinite(off), np.abs(off), np.inf))
        theta = theta + np.where(np.isfinite(off / slope), off / slope, 0.0)
    # what is proven holds with ten times the error of H found at the grid and the roots
    doubt = ~(miss <= _PHASE_MAX_MISS)
    doubt[unproven] = True
    tol = 10.0 * np.where(doubt, 0.0, miss) + 1e-9
    doubt[f_idx[~(slack > tol[f_idx])]] = True
    # an inner end of a monotonic interval as near a level as H's error: on which side
    # the root lies (if any, at an extremum) is not proven
    p_idx, p_lo, p_hi, p_hlo, p_hhi = pieces
    for ends, h in ((p_lo, p_hlo), (p_hi, p_hhi)):
        near = np.abs(h - np.pi * np.round(h / np.pi)) <= tol[p_idx]
        doubt[p_idx[near & (ends > 0.0) & (ends < np.pi)]] = True
    # and θ = 0 and π, where g is real for every loop
    r_idx = np.concatenate([r_idx, np.arange(R), np.arange(R)])
    theta = np.concatenate([theta, np.zeros(R), np.full(R, np.pi)])
    gz = g.g(r_idx, np.exp(1j * theta))
    with np.errstate(all="ignore"):
        K = 1.0 / gz.real
    ok = np.isfinite(K) & (K > 0) & (np.abs(gz.imag) <= 1e-6 * np.abs(gz) + 1e-300)
    return [None if doubt[r] else (K[ok & (r_idx == r)], theta[ok & (r_idx == r)])
            for r in range(R)]


def _phase_intervals(ph: _Phase, H: np.ndarray, grid: np.ndarray, tol: np.ndarray):
    """The intervals of :func:`_phase_crossings`: from the grid's (H (R, m + 1) at
    ``grid``), halved until each is proven monotonic or free of roots by more than
    ``tol`` (per loop). Returns the monotonic ones (loop, lo, hi, H(lo), H(hi)), the free
    ones (loop, how far beyond the proof their H stays from πℤ) and the loops of any
    interval still unproven after :data:`_PHASE_MAX_HALVINGS` halvings."""
    R, m = H.shape[0], grid.size - 1
    idx = np.repeat(np.arange(R), m)
    lo, hi = np.tile(grid[:-1], R), np.tile(grid[1:], R)
    h_lo, h_hi = H[:, :-1].ravel(), H[:, 1:].ravel()
    pieces, free = [], []
    for _ in range(_PHASE_MAX_HALVINGS):
        s_lo, s_hi = ph.slope_bounds(idx, lo, hi)
        margin = 1e-9 * (np.abs(s_lo) + np.abs(s_hi) + ph.D + 1.0)
        monotonic = (s_lo > margin) | (s_hi < -margin)
        pieces.append((idx[monotonic], lo[monotonic], hi[monotonic], h_lo[monotonic],
                       h_hi[monotonic]))
        open_ = ~monotonic
        idx, lo, hi, h_lo, h_hi, s_lo, s_hi = (x[open_] for x in
                                               (idx, lo, hi, h_lo, h_hi, s_lo, s_hi))
        mid = 0.5 * (lo + hi)
        h_mid = ph.at(idx, mid)
        reach = np.maximum(np.abs(s_lo), np.abs(s_hi)) * 0.5 * (hi - lo)
        away = np.abs(h_mid - np.pi * np.round(h_mid / np.pi))
        split = ~(away > reach * (1 + 1e-9) + tol[idx])
        free.append((idx[~split], away[~split] - reach[~split] * (1 + 1e-9)))
        if not split.any():
            idx = idx[:0]
            break
        idx, lo, hi, h_lo, h_hi, h_mid, mid = (x[split] for x in
                                               (idx, lo, hi, h_lo, h_hi, h_mid, mid))
        idx = np.concatenate([idx, idx])
        lo, hi = np.concatenate([lo, mid]), np.concatenate([mid, hi])
        h_lo, h_hi = np.concatenate([h_lo, h_mid]), np.concatenate([h_mid, h_hi])
    return (tuple(np.concatenate(x) for x in zip(*pieces, strict=True)),
            tuple(np.concatenate(x) for x in zip(*free, strict=True)), idx)


def _phase_roots(ph: _Phase, pieces) -> tuple[np.ndarray, np.ndarray]:
    """The roots (loop, θ) of H(θ) ∈ πℤ on the monotonic intervals ``pieces`` of
    :func:`_phase_intervals`: each multiple Lπ an interval crosses, rising
    H(lo) < L ≤ H(hi), falling H(hi) ≤ L < H(lo) (a root on a shared end counted once;
    at θ = π, H(π) itself is the end, not an inner root), solved by
    :func:`_bracketed_newton` from the chord's crossing."""
    p_idx, p_lo, p_hi, p_hlo, p_hhi = pieces
    rising = p_hhi > p_hlo
    end = p_hi >= np.pi
    first = np.where(rising, np.floor(p_hlo / np.pi) + 1,
                     np.where(end, np.floor(p_hhi / np.pi) + 1, np.ceil(p_hhi / np.pi)))
    last = np.where(rising, np.where(end, np.ceil(p_hhi / np.pi) - 1,
                                     np.floor(p_hhi / np.pi)),
                    np.ceil(p_hlo / np.pi) - 1)
    n = np.maximum(0, last - first + 1).astype(int)
    r_idx = np.repeat(p_idx, n)
    a, b = np.repeat(p_lo, n), np.repeat(p_hi, n)
    level = np.pi * (np.repeat(first, n) + np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n))
    h_a, h_b = np.repeat(p_hlo, n), np.repeat(p_hhi, n)
    theta = _bracketed_newton(ph, r_idx, level, a, b, np.repeat(rising, n),
                              a + (b - a) * np.clip((level - h_a) / (h_b - h_a), 0, 1))
    return r_idx, theta


def _bracketed_newton(ph: _Phase, idx: np.ndarray, level: np.ndarray, a: np.ndarray,
                      b: np.ndarray, rising: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """θ in [a, b] with H(θ) = ``level`` for loops ``idx``, H monotonic on each bracket
    (rising or not), from ``theta`` (in the bracket): Newton's steps, a bisection where a
    step would leave the bracket, which shrinks to the root, until the steps stop moving
    (at most 80 rounds)."""
    for _ in range(80):
        h, slope = ph.at(idx, theta, derivative=True)
        f = h - level
        beyond = np.where(rising, f > 0, f < 0)
        b = np.where(beyond, theta, b)
        a = np.where(beyond, a, theta)
        with np.errstate(all="ignore"):
            step = theta - f / slope
        step = np.where((step >= a) & (step <= b), step, 0.5 * (a + b))
        done = (np.abs(step - theta) <= 1e-15 * np.maximum(1.0, theta)) | (f == 0)
        theta = step
        if done.all():
            break
    return theta


def _by_intervals(g: _Group, rows: Sequence[int], cands: Sequence[np.ndarray],
                  thetas: Sequence[np.ndarray], T: float, out: list) -> None:
    """K_max of the loops ``rows`` of ``g`` from their sorted crossing gains ``cands``
    (and angles ``thetas``), into ``out``: one gain inside each interval between
    crossings (and beyond the last) tested in order of K up to the first unstable one;
    the loss of stability at the crossing below it checked, else bisected."""
    if not rows:
        return
    # test one gain inside each interval between crossings (and beyond the last), in
    # order of K, up to the first unstable one
    mids = {r: _interval_gains(cands[r]) for r in rows}
    first, top_first = _first_unstable(g, [mids[r] for r in rows], rows)
    pending = []
    for i, r in enumerate(rows):
        K, j, Ks = cands[r], int(first[i]), mids[r]
        if j < 0:
            out[g.rows[r]] = WallStability(math.inf, math.nan, False)
            continue
        if j == 0:
            rho0, top0 = _spectral_radius(g, np.array([r]), np.array([0.0]))
            if rho0[0] < 1.0:
                # stable at K = 0 yet not below the first crossing: the crossings missed
                # one (eigenvalues that strayed from the unit circle): K_max lies in
                # (0, Ks[0]), found by halving down to a stable gain, then bisection
                out[g.rows[r]] = _below_first(g, r, float(Ks[0]), top_first[i], T)
                continue
            out[g.rows[r]] = WallStability(0.0, abs(float(np.angle(top0[0])))
                                           / (2 * np.pi * T), True)
            continue
        pending.append((r, float(K[j - 1]), float(thetas[r][j - 1]),
                        float(Ks[j - 1]), float(Ks[j])))
    # check stability just below and loss just above each K* (± K_REL_TOL/2), all
    # loops at once; where the check fails, bisect between the stable and the
    # unstable test gains
    if pending:
        rs = np.repeat([p[0] for p in pending], 2)
        probe = np.array([[p[1] * (1 - K_REL_TOL / 2), p[1] * (1 + K_REL_TOL / 2)]
                          for p in pending]).ravel()
        rho, _ = _spectral_radius(g, rs, probe)
        for i, (r, k_star, th, k_lo, k_hi) in enumerate(pending):
            if rho[2 * i] < 1.0 <= rho[2 * i + 1]:
                out[g.rows[r]] = WallStability(k_star, th / (2 * np.pi * T), False)
            else:
                out[g.rows[r]] = _bisect(g, r, k_lo, k_hi, T)


def _interval_gains(K: np.ndarray) -> np.ndarray:
    """One test gain inside each interval between the sorted crossing gains ``K`` (the
    midpoints, from 0), and beyond the last (twice it); [1] without crossings."""
    if not K.size:
        return np.array([1.0])
    edges = np.concatenate([[0.0], K])
    return np.concatenate([0.5 * (edges[:-1] + edges[1:]), [2.0 * K[-1]]])


def _first_unstable(g: _Group, mids: Sequence[np.ndarray],
                    rows: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For each loop of ``g`` (``rows``: those of these indices into the group, in this
    order; default all): the index of the first gain of its ``mids`` (in order) at which
    the loop is unstable (−1 if at none), and the outermost eigenvalue at its first
    gain. The gains are tested in rounds, the i-th gain of every loop still stable
    through its first i in one batch, so that a loop stops at its first unstable gain:
    with a long delay a loop crosses the unit circle at dozens of gains, of which the
    answer needs the first two or three. Each matrix's eigenvalues are those a test of
    every gain at once would give."""
    R = len(mids)
    at = np.arange(R) if rows is None else np.asarray(rows, int)
    first = np.full(R, -1)
    top_first = np.zeros(R, complex)
    live = np.arange(R)
    i = 0
    while live.size:
        rho, top = _spectral_radius(g, at[live], np.array([mids[r][i] for r in live]))
        if i == 0:
            top_first[live] = top
        unstable = rho >= 1.0
        first[live[unstable]] = i
        i += 1
        live = np.array([r for r, u in zip(live, unstable, strict=True)
                         if not u and i < mids[r].size], int)
    return first, top_first


def loop_delay_samples(plant: RationalPlant, settings: WallSettings) -> int:
    """Whole samples of latency in the sampled loop: ⌈plant delay / T⌉ + d."""
    return int(math.ceil(plant.delay_s / settings.sample_time_s - 1e-12)) + \
        int(settings.delay_samples)


def _below_first(g: _Group, r: int, k_hi: float, top: complex, T: float) -> WallStability:
    """K_max of loop ``r``, stable at K = 0 and unstable at ``k_hi`` (its outermost
    eigenvalue there ``top``): the unstable gain halved until the loop is stable (at most
    60 times; none stable: K_max = 0 at the frequency of ``top``), then bisected."""
    for _ in range(60):
        k_lo = 0.5 * k_hi
        rho, top_lo = _spectral_radius(g, np.array([r]), np.array([k_lo]))
        if rho[0] < 1.0:
            return _bisect(g, r, k_lo, k_hi, T)
        k_hi, top = k_lo, top_lo[0]
    return WallStability(0.0, abs(float(np.angle(top))) / (2 * np.pi * T), False)


def _bisect(g: _Group, r: int, k_lo: float, k_hi: float, T: float) -> WallStability:
    """K_max of loop ``r`` by bisection between the stable ``k_lo`` and the unstable
    ``k_hi`` (to K_REL_TOL)."""
    while k_hi - k_lo > K_REL_TOL * k_lo:
        mid = 0.5 * (k_lo + k_hi)
        rm, _ = _spectral_radius(g, np.array([r]), np.array([mid]))
        if rm[0] < 1.0:
            k_lo = mid
        else:
            k_hi = mid
    _, top = _spectral_radius(g, np.array([r]), np.array([k_hi]))
    return WallStability(k_lo, abs(float(np.angle(top[0]))) / (2 * np.pi * T), False)


def closed_loop_stable(plant: RationalPlant, settings: WallSettings, k_N_per_m: float
                       ) -> bool:
    """Whether the sampled loop with wall stiffness ``k_N_per_m`` is stable."""
    g = _loops([plant], settings)[0]
    rho, _ = _spectral_radius(g, np.array([0]), np.array([float(k_N_per_m)]))
    return bool(rho[0] < 1.0)


# ---------------------------------------------------------------------------
# The robust certificate
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Certificate:
    """Robust stability of the wall against the arm's multiplicative uncertainty Wu.

    The small-gain test max |Wu T| < 1 is evaluated from the low edge of the weight's
    band to ``f_max_hz``, the Nyquist frequency of the wall (every frequency at which the
    sampled loop can lose stability). Above the weight's band (``band_hz``, where it was
    fitted to data) Wu is its own continuation: the stated assumption that the arm's
    relative uncertainty stays within |Wu| there too.

    Attributes
    ----------
    peak_k0 : float
        max |Wu T| at K = 0 (with the settings' B and d) over the evaluated range.
    f_peak_k0_hz : float
        Where (Hz).
    k_weight_N_per_m : float
        The largest K with the loop nominally stable and max |Wu T| < 1 for every K′ in
        [0, K] (NaN when that holds for no K): what the weight alone certifies.
    f_binding_hz : float
        The frequency where |Wu T| reaches 1 at ``k_weight_N_per_m`` (NaN when the
        nominal K_max or nothing binds).
    binding_in_band : bool
        Whether ``f_binding_hz`` lies inside ``band_hz`` (proven by the data) or above it
        (resting on the assumption).
    member_k_max_N_per_m : float
        The smallest K_max of the member models (the trials the weight was built from),
        at the same settings; NaN when no members were given.
    limiting_member : str
        Which member that is ('' without members).
    beyond_margin : float
        Over the members and the frequencies above ``band_hz`` up to ``f_max_hz``, the
        largest |H_i/H̄ − 1| / |Wu| (H the arm responses, H̄ the nominal): ≤ 1 when the
        members' own models agree with the assumption beyond the band; NaN without
        members.
    k_robust_N_per_m : float
        The certified K: ``k_weight_N_per_m`` capped at ``member_k_max_N_per_m`` (a
        certificate never admits a K at which a member of the set it covers is
        unstable); NaN when it holds for no K, and NaN when ``beyond_margin`` > 1 (the
        members contradict the assumption the certificate rests on: it is withheld).
    limited_by : str
        What sets ``k_robust_N_per_m``: "weight" (|Wu T| reaches 1 inside the band),
        "weight beyond band" (above it, on the assumption), "nominal K_max", "member",
        :data:`WITHHELD` (the members go beyond the weight above the band) or "" when
        it holds for no K.
    band_hz, f_max_hz
        The weight's band and the top of the evaluated range (Hz).
    """

    peak_k0: float
    f_peak_k0_hz: float
    k_robust_N_per_m: float
    band_hz: tuple[float, float]
    f_max_hz: float = math.nan
    k_weight_N_per_m: float = math.nan
    f_binding_hz: float = math.nan
    binding_in_band: bool = False
    member_k_max_N_per_m: float = math.nan
    limiting_member: str = ""
    beyond_margin: float = math.nan
    limited_by: str = ""

    @property
    def holds(self) -> bool:
        """Whether the certificate holds for some K ≥ 0."""
        return bool(np.isfinite(self.k_robust_N_per_m))


def environment_terms(f_hz, model: ClosedLoopModel, theta: Mapping[str, float],
                      settings: WallSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Z_ARM, a, c) in N/m at f_hz with Z_env(K) = a + K c the impedance the device and
    the wall present to the hand.

    a = Mp s² + ΔZ_dev + R · H_zoh · (B/T)(1 − e^(−jωT)) e^(−jωdT), c = R · H_zoh ·
    e^(−jωdT), H_zoh = (1 − e^(−jωT))/(jωT), R the output factors of the model's effects;
    Z_ARM = 1/H_ARM with arm-stage effects (:meth:`ClosedLoopModel.arm_response`).
    """
    f = np.asarray(f_hz, float)
    s = 2j * np.pi * f
    T, B, d = settings.sample_time_s, settings.damping_Ns_per_m, settings.delay_samples
    z_arm = 1.0 / model.arm_response(f, theta)
    z_all_inv = model.response(f, theta)          # R / (Z_arm + Z_dev)
    # R and Z_dev from the model's own response: R/(Z_arm + Z_dev) with no output effect
    base = ClosedLoopModel(mp=model.mp, effects=tuple(e for e in model.effects
                                                      if e.stage != "output"))
    every = model.values(theta)
    theta_base = {n: every[n] for n in base.param_names}
    z_total = 1.0 / base.response(f, theta_base)   # Z_arm + Z_dev
    R = z_all_inv * z_total
    z_dev = z_total - z_arm
    eT = np.exp(-s * T)
    hold = np.where(f > 0, (1 - eT) / np.where(f > 0, s * T, 1.0), 1.0)
    delay = np.exp(-s * d * T)
    c = R * hold * delay
    a = z_dev + c * (B / T) * (1 - eT)
    return z_arm, a, c


def robust_certificate(model: ClosedLoopModel, theta: Mapping[str, float], weight,
                       settings: WallSettings, *, band_hz: tuple[float, float],
                       k_max_N_per_m: float, members: Sequence[tuple] = (),
                       f_max_hz: float | None = None) -> Certificate:
    """The small-gain certificate max |Wu T| < 1, sound for the sampled loop.

    Parameters
    ----------
    model, theta : ClosedLoopModel, mapping
        The nominal model (its loop as :func:`environment_terms` sees it) and its values.
    weight : armfit.uncertainty.WuWeight
        Wu, fitted over ``band_hz`` (Hz).
    settings : WallSettings
    band_hz : (float, float)
        Where the weight was fitted to data (Hz).
    k_max_N_per_m : float
        The nominal model's K_max (N/m) at ``settings``.
    members : sequence of (label, ClosedLoopModel, theta, K_max)
        The models the weight was built from (one per trial) with their K_max at the
        same settings: the certified K is capped at the smallest, and their arm
        responses above the band check the assumption (``beyond_margin``).
    f_max_hz : float, optional
        Top of the evaluated range (Hz); default the Nyquist frequency 1/(2T).

    Returns
    -------
    Certificate

    Notes
    -----
    T = Z_env/(Z_ARM + Z_env), Z_env = a + K c (:func:`environment_terms`). At each
    frequency |Wu| |a + Kc| < |Z_ARM + a + Kc| is a quadratic inequality α K² + β K + γ
    < 0 in K, solved exactly; K_weight is the smallest K ≥ 0 that violates it anywhere on
    the grid (:data:`CERT_POINTS_PER_DECADE` log-spaced points from the band's low edge
    to ``f_max_hz``), capped at ``k_max_N_per_m``. The sampled loop can lose stability at
    any frequency up to the Nyquist frequency, and does (a wall on a stiff or delayed arm
    goes unstable above the 30 Hz of a typical measured band), so a test limited to the
    band would certify gains at which a member of the set is unstable.
    """
    lo, hi = map(float, band_hz)
    top = 0.5 / settings.sample_time_s if f_max_hz is None else float(f_max_hz)
    top = max(top, hi)
    n = max(int(CERT_POINTS_PER_DECADE * np.log10(top / lo)) + 1, 2)
    f = np.geomspace(lo, top, n)
    z, a, c = environment_terms(f, model, theta, settings)
    # a weight too large for floating point gives a |Wu T| that is not a finite
    # number: handled below (it certifies nothing), not warned about
    with np.errstate(over="ignore", invalid="ignore"):
        wr = np.abs(weight.response(f))
        w2 = wr ** 2
        ratio0 = wr * np.abs(a) / np.abs(z + a)
        alpha = (w2 - 1.0) * np.abs(c) ** 2
        beta = 2.0 * np.real((w2 * np.conj(a) - np.conj(z + a)) * c)
        gamma = w2 * np.abs(a) ** 2 - np.abs(z + a) ** 2
        k_first = _first_violation(alpha, beta, gamma)
    i0 = int(np.argmax(ratio0))
    peak0 = float(ratio0[i0])
    j = int(np.argmin(k_first))
    k_w, f_bind = float(k_first[j]), float(f[j])
    limited = "weight" if f_bind <= hi else "weight beyond band"
    # a |Wu T| that is not a finite number proves nothing: no K is certified
    if not (k_max_N_per_m > 0) or not (np.isfinite(ratio0).all() and peak0 < 1.0):
        k_w, f_bind, limited = math.nan, math.nan, ""
    elif k_w >= k_max_N_per_m:
        k_w, f_bind, limited = float(k_max_N_per_m), math.nan, "nominal K_max"
    m_k, m_who, margin = math.nan, "", math.nan
    if members:
        labels = [m[0] for m in members]
        ks = np.array([float(m[3]) for m in members])
        i = int(np.argmin(ks))
        m_k, m_who = float(ks[i]), str(labels[i])
        margin = _beyond_margin(model, theta, members, f[f > hi], wr[f > hi])
    k_rob = k_w
    if np.isfinite(k_rob) and np.isfinite(m_k) and m_k < k_rob:
        k_rob, limited = m_k, "member"
    if not math.isnan(k_rob) and not margin <= 1.0 and members and np.any(f > hi):
        # above the band the members depart from the nominal by more than |Wu| (or by
        # an amount that is not a number): the weight continued there does not cover
        # them, the assumption the certificate rests on fails, and it is withheld
        k_rob, limited = math.nan, WITHHELD
    return Certificate(peak0, float(f[i0]), k_rob, (lo, hi), f_max_hz=top, k_weight_N_per_m=k_w,
                       f_binding_hz=f_bind, binding_in_band=bool(f_bind <= hi),
                       member_k_max_N_per_m=m_k, limiting_member=m_who, beyond_margin=margin,
                       limited_by=limited)


def _beyond_margin(model: ClosedLoopModel, theta: Mapping[str, float], members, above,
                   w_above) -> float:
    """max over ``members`` and the frequencies ``above`` the band of
    |H_member/H̄ − 1| / |Wu| (NaN when there is no frequency above the band)."""
    if not above.size:
        return math.nan
    h_nom = model.arm_response(above, theta)
    with np.errstate(all="ignore"):
        dev = np.max([np.abs(mm.arm_response(above, th) / h_nom - 1.0)
                      for _, mm, th, _ in members], axis=0)
        ratio = dev / w_above
    return float(np.nanmax(ratio)) if np.isfinite(ratio).any() else math.nan


def _first_violation(alpha, beta, gamma) -> np.ndarray:
    """Per frequency, the smallest K ≥ 0 with α K² + β K + γ ≥ 0 (inf if none)."""
    out = np.full(np.shape(alpha), math.inf)
    out[gamma >= 0] = 0.0
    neg = gamma < 0
    scale = np.abs(alpha) + np.abs(beta) + np.abs(gamma)
    lin = neg & (np.abs(alpha) <= 1e-14 * scale)
    with np.errstate(all="ignore"):
        kl = -gamma / beta
    out[lin & (beta > 0)] = kl[lin & (beta > 0)]
    quad = neg & ~lin
    disc = beta * beta - 4 * alpha * gamma
    with np.errstate(all="ignore"):
        sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
        r1 = (-beta - sq) / (2 * alpha)
        r2 = (-beta + sq) / (2 * alpha)
    roots = np.stack([r1, r2])
    roots = np.where(np.isfinite(roots) & (roots >= 0), roots, np.inf)
    first = np.min(roots, axis=0)
    out[quad & (disc >= 0)] = first[quad & (disc >= 0)]
    return out


# ---------------------------------------------------------------------------
# A parameters table in, a stability table out
# ---------------------------------------------------------------------------

#: Columns of the stability table (CSV of ``armfit stability -o``), in order; the
#: certificate's (:data:`CERTIFICATE_COLUMNS`) follow with weights.
STABILITY_COLUMNS: tuple[str, ...] = (
    "row", "axis", "grip_N", "subject", "run", "k_max_N_per_m", "f_unstable_hz",
    "unstable_at_zero")

#: Columns of the robust certificate in a stability table (see :class:`Certificate`).
CERTIFICATE_COLUMNS: tuple[str, ...] = (
    "wu_t_peak_k0", "f_peak_k0_hz", "k_robust_N_per_m", "limited_by", "k_weight_N_per_m",
    "f_binding_hz", "binding_in_band", "member_k_max_N_per_m", "limiting_member",
    "beyond_margin")


def loop_model(model: ClosedLoopModel, theta: Mapping[str, float],
               outside_loop: Sequence[str] = ()) -> tuple[ClosedLoopModel, dict[str, float]]:
    """The model as the haptic loop sees it, and its values.

    Every effect is in the loop unless named in ``outside_loop``: an apparatus effect
    (stage output or device) that the measurement saw but the rendering loop does not
    (e.g. a latency that is only a misalignment of the force and position logs). A
    latency or lag in the position path is in the loop by default, since the wall reads
    the same sensor; the arm's own effects (stage arm) always are. Raises UsageError for
    an arm-stage effect named in ``outside_loop``.
    """
    drop = set(outside_loop)
    for e in model.effects:
        if e.name in drop and e.stage == "arm":
            raise UsageError(f"{{opt:outside_loop}} {e.name}: an effect of the arm (stage "
                             "arm) is part of the person and always in the loop")
    values = model.values(theta)
    if not drop & {e.name for e in model.effects}:
        return model, values
    kept = ClosedLoopModel(mp=model.mp, effects=tuple(e for e in model.effects
                                                      if e.name not in drop))
    return kept, {n: values[n] for n in kept.param_names}


def stability_table(params, settings: WallSettings, *, weights=None,
                    weights_band_hz: Mapping[str, tuple[float, float]] | None = None,
                    source: str | None = None, outside_loop: Sequence[str] = (),
                    members=None, members_k_max=None):
    """K_max for every row of a parameters table, in row order, and with ``weights``
    the robust certificate of each row.

    Parameters
    ----------
    params : pandas.DataFrame
        Rows as :func:`armfit.models.params.read_param_rows` returns them (optionally with
        ``subject``, ``run`` and ``row`` columns); each row its own model.
    settings : WallSettings
    weights : dict, optional
        {axis: WuWeight}: adds :data:`CERTIFICATE_COLUMNS` (NaN for an axis without a
        weight), see :func:`robust_certificate`.
    weights_band_hz : dict, optional
        {axis: (lo, hi)} the band each weight was fitted over (Hz; default the paper's
        0.01–30 Hz).
    source : str, optional
        Names the file in warnings.
    outside_loop : sequence of str
        Apparatus effects left out of the loop (:func:`loop_model`).
    members : pandas.DataFrame, optional
        The models each weight was built from (the per-trial fits), rows like
        ``params``: each row's certificate is capped at the smallest K_max of its axis's
        members and checked against their models above the band.
    members_k_max : sequence of float, optional
        K_max (N/m) of each row of ``members``, as this function gave them for
        ``members`` with the same ``settings`` and ``outside_loop`` (its
        ``k_max_N_per_m`` column): not computed again.

    Returns
    -------
    pandas.DataFrame
        :data:`STABILITY_COLUMNS`, then with weights :data:`CERTIFICATE_COLUMNS`. A row
        unstable at K = 0 gets K_max = 0 and a ``RuntimeWarning`` naming it.
    """
    import pandas as pd
    # the rows as records: a DataFrame's iterrows and iloc cost about 0.15 ms a row
    rows = params.to_dict("records")
    models, res = _k_max_rows(rows, settings, outside_loop)
    by_axis: dict[str, list] = {}
    if weights is not None and members is not None and len(members):
        m_rows = members.to_dict("records")
        if members_k_max is None:
            m_models, m_res = _k_max_rows(m_rows, settings, outside_loop)
            m_k = [r.k_max_N_per_m for r in m_res]
        else:
            m_models, m_k = _loop_models(m_rows, outside_loop), list(members_k_max)
            if len(m_k) != len(m_models):
                raise ValueError(f"members_k_max has {len(m_k)} values for "
                                 f"{len(m_models)} members")
        for (mm, th), k, row in zip(m_models, m_k, m_rows, strict=True):
            rec = {"axis": str(row["axis"]), "grip_N": _num(row.get("grip_N")),
                   "subject": _text(row.get("subject")), "run": _num(row.get("run"))}
            by_axis.setdefault(rec["axis"], []).append((describe(rec), mm, th, float(k)))
    recs = []
    for i, ((model, theta), r, row) in enumerate(zip(models, res, rows, strict=True)):
        rec = {"row": int(row["row"]) if "row" in params.columns else i + 1,
               "axis": str(row["axis"]),
               "grip_N": _num(row.get("grip_N")), "subject": _text(row.get("subject")),
               "run": _num(row.get("run")), "k_max_N_per_m": r.k_max_N_per_m,
               "f_unstable_hz": r.f_unstable_hz, "unstable_at_zero": r.unstable_at_zero}
        if r.unstable_at_zero:
            warnings.warn(f"{source + ': ' if source else ''}row {rec['row']} "
                          f"({describe(rec)}): the loop is unstable already at K = 0 "
                          f"(B = {settings.damping_Ns_per_m:g} N*s/m, d = "
                          f"{settings.delay_samples}); K_max = 0", RuntimeWarning,
                          stacklevel=2)
        if weights is not None:
            w = weights.get(rec["axis"])
            if w is None:
                rec.update({c: math.nan for c in CERTIFICATE_COLUMNS})
                rec.update(limited_by="", limiting_member="")
            else:
                band = (weights_band_hz or {}).get(rec["axis"], PAPER_BAND_HZ)
                cert = robust_certificate(model, theta, w, settings, band_hz=band,
                                          k_max_N_per_m=r.k_max_N_per_m,
                                          members=by_axis.get(rec["axis"], ()))
                rec.update({c: (cert.peak_k0 if c == "wu_t_peak_k0" else getattr(cert, c))
                            for c in CERTIFICATE_COLUMNS})
        recs.append(rec)
    cols = list(STABILITY_COLUMNS) + (list(CERTIFICATE_COLUMNS) if weights is not None
                                      else [])
    return pd.DataFrame(recs, columns=cols)


def _loop_models(rows: Sequence[Mapping], outside_loop: Sequence[str]) -> list:
    """[(loop model, values)], one per row of a params table (records)
    (:func:`loop_model`)."""
    return [loop_model(*model_from_params(row), outside_loop) for row in rows]


def _k_max_rows(rows: Sequence[Mapping], settings: WallSettings,
                outside_loop: Sequence[str]):
    """[(loop model, values)] and their :class:`WallStability`, one per row of a params
    table (records)."""
    models = _loop_models(rows, outside_loop)
    return models, wall_stability([plant_from_model(m, th) for m, th in models], settings)


def describe(rec: Mapping) -> str:
    """'axis x, subject S1, grip 2 N, run 1' from a stability record (parts present)."""
    parts = [f"axis {rec['axis']}"]
    if rec.get("subject") is not None:
        parts.append(f"subject {rec['subject']}")
    g = rec.get("grip_N")
    if g is not None and np.isfinite(g):
        parts.append(f"grip {g:g} N")
    run = rec.get("run")
    if run is not None and np.isfinite(run):
        parts.append(f"run {int(run)}")
    return ", ".join(parts)


def _num(v) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        return math.nan
    return x


def _text(v) -> str | None:
    return None if is_missing(v) else str(v)


def axis_summary(table) -> dict[str, dict]:
    """Per axis (x, y, z order): minimum, median and 5th percentile (linear
    interpolation) of K_max over the rows, their number, and the row that limits it
    (the minimum; first in file order on ties). With certificate columns also the
    smallest K_robust (NaN when it holds for no row), the largest peak at K = 0, and
    the certificate in words: ``certificate`` (:func:`certificate_status` of the axis:
    "holds" when it holds on every row, else the first of the rows' other statuses)
    and ``certificate_text`` (:func:`certificate_sentence`), the one source of what the
    command line prints and its JSON holds."""
    out = {}
    for axis in ("x", "y", "z"):
        g = table[table["axis"] == axis]
        if g.empty:
            continue
        k = g["k_max_N_per_m"].to_numpy(float)
        i = int(np.argmin(k))
        lim = g.iloc[i]
        entry = {"k_max_min_N_per_m": float(k.min()),
                 "k_max_median_N_per_m": float(median(k)),
                 "k_max_p05_N_per_m": float(percentile(k, 5)),
                 "n_models": int(k.size),
                 "limiting_row": int(lim["row"]),
                 "limiting": describe(lim)}
        if "k_robust_N_per_m" in g.columns:
            recs = g.to_dict("records")
            states = [certificate_status(r) for r in recs]
            kr = g["k_robust_N_per_m"].to_numpy(float)
            entry["k_robust_min_N_per_m"] = float(np.min(kr)) \
                if all(st == "holds" for st in states) else math.nan
            entry["wu_t_peak_k0_max"] = float(np.nanmax(g["wu_t_peak_k0"].to_numpy(float))) \
                if np.isfinite(g["wu_t_peak_k0"].to_numpy(float)).any() else math.nan
            entry["certificate"] = next((st for st in CERTIFICATE_STATUSES[1:]
                                         if st in states), "holds")
            entry["certificate_text"] = certificate_sentence(axis, recs)
        out[axis] = entry
    return out


def subject_summary(table) -> dict[str, dict[str, float]]:
    """Per axis (x, y, z order) and subject (in order of appearance): the smallest K_max
    (N/m) over the subject's rows — the stiffest wall the subject renders stably with
    every grip. The axis's minimum over subjects is :func:`axis_summary`'s: the wall
    every subject renders stably follows from the subjects' own."""
    out: dict[str, dict[str, float]] = {}
    if "subject" not in table.columns:
        return out
    for axis in ("x", "y", "z"):
        g = table[table["axis"] == axis]
        if g.empty:
            continue
        k = g["k_max_N_per_m"].to_numpy(float)
        subj = g["subject"].astype(str).to_numpy()
        out[axis] = {str(s_): float(k[subj == s_].min()) for s_ in dict.fromkeys(subj)}
    return out


#: What a row's robust certificate says (:func:`certificate_status`), best first.
CERTIFICATE_STATUSES: tuple[str, ...] = (
    "holds", "withheld", "fails at K = 0", "unstable at K = 0", "no weight")


def certificate_status(rec: Mapping) -> str:
    """What the robust certificate of one row of a stability table says.

    Parameters
    ----------
    rec : Mapping
        A row with :data:`CERTIFICATE_COLUMNS` and ``k_max_N_per_m``.

    Returns
    -------
    str
        One of :data:`CERTIFICATE_STATUSES`: "holds" (for K up to
        ``k_robust_N_per_m``), "withheld" (the members go beyond the weight above its
        band, ``limited_by`` :data:`WITHHELD`), "fails at K = 0" (max |Wu T| ≥ 1, or not
        a number, already at K = 0), "unstable at K = 0" (the nominal loop itself) or
        "no weight" (no weight for the row's axis).
    """
    if not math.isfinite(_num(rec.get("f_peak_k0_hz"))):
        return "no weight"
    if math.isfinite(_num(rec.get("k_robust_N_per_m"))) or \
            _num(rec.get("k_robust_N_per_m")) == math.inf:
        return "holds"
    if rec.get("limited_by") == WITHHELD:
        return "withheld"
    if not _num(rec.get("k_max_N_per_m")) > 0:
        return "unstable at K = 0"
    return "fails at K = 0"


def certificate_sentence(axis: str, rows: Sequence[Mapping]) -> str:
    """The robust certificate of one axis's rows in one sentence (the text ``armfit
    stability --weights`` prints and its JSON's ``certificate_text``).

    Parameters
    ----------
    axis : str
    rows : sequence of Mapping
        The axis's rows of a stability table with certificate columns.

    Returns
    -------
    str
        "axis x: …": the smallest certified K (kN/m) and what bounds it when the
        certificate holds on every row; else on how many rows it fails, and why.
    """
    states = [certificate_status(r) for r in rows]
    n = len(rows)
    if all(st == "no weight" for st in states):
        return f"axis {axis}: no uncertainty weight for this axis; no certificate"
    if all(st == "holds" for st in states):
        i = int(np.argmin([_num(r["k_robust_N_per_m"]) for r in rows]))
        return (f"axis {axis}: the robust certificate max |Wu T| < 1 holds for K up to "
                f"{_kn(rows[i]['k_robust_N_per_m'])} kN/m on every model"
                + _limit_words(rows[i]))
    clauses = []
    peak = [r for r, st in zip(rows, states, strict=True) if st == "fails at K = 0"]
    if peak:
        top = np.array([_num(r["wu_t_peak_k0"]) for r in peak])
        worst = f"{np.nanmax(top):.3f} > 1" if np.isfinite(top).any() else "not a number"
        clauses.append(f"holds for no K at all on {len(peak)} of {n} model(s): max |Wu T| "
                       f"is already {worst} at K = 0 (the weight allows more than 100 % "
                       "relative uncertainty where the device's own impedance dominates)")
    unstable = states.count("unstable at K = 0")
    if unstable:
        clauses.append(f"holds for no K on {unstable} of {n} model(s): the nominal loop is "
                       "unstable already at K = 0")
    held = [r for r, st in zip(rows, states, strict=True) if st == "withheld"]
    if held:
        margin = max(_num(r["beyond_margin"]) for r in held)
        clauses.append(f"is withheld on {len(held)} of {n} model(s): above the weight's "
                       f"band the member models depart from the nominal by up to "
                       f"{margin:.4f} × |Wu| (beyond_margin > 1), so the weight does not "
                       "cover them there and the assumption the certificate rests on "
                       "does not hold")
    missing = states.count("no weight")
    if missing:
        clauses.append(f"has no weight for {missing} of {n} model(s)")
    return f"axis {axis}: the robust certificate " + "; it ".join(clauses)


def _kn(v) -> str:
    """N/m as kN/m with 3 significant digits ('inf', or '-' when not a number)."""
    v = _num(v)
    if not math.isfinite(v):
        return "inf" if v > 0 else "-"
    return f"{v / 1000:.3g}"


def _limit_words(rec: Mapping) -> str:
    """What bounds one row's certified K, in words (empty when the weight does)."""
    why = str(rec.get("limited_by") or "")
    if why == "member":
        return (f" (capped at member {rec['limiting_member']}, whose K_max is "
                f"{_kn(rec['member_k_max_N_per_m'])} kN/m)")
    if why == "weight beyond band":
        return (f" (bound at {_num(rec['f_binding_hz']):.3g} Hz, above the weight's band: "
                "there Wu is its fitted form continued)")
    if why == "nominal K_max":
        return " (the nominal model's own K_max)"
    return ""


def k_max_sweep(plants: Sequence[RationalPlant], rates_hz: Sequence[float],
                delays: Sequence[int], *, damping_Ns_per_m: float = 0.0,
                max_delay_samples: int = MAX_LOOP_DELAY_SAMPLES) -> np.ndarray:
    """K_max (N/m) of each plant at each servo rate (Hz) and delay (samples):
    array (n_delays, n_rates, n_plants); NaN where the loop holds more than
    ``max_delay_samples`` (at most :data:`MAX_LOOP_DELAY_SAMPLES`) samples of latency."""
    cap = min(int(max_delay_samples), MAX_LOOP_DELAY_SAMPLES)
    out = np.full((len(delays), len(rates_hz), len(plants)), np.nan)
    for i, d in enumerate(delays):
        for j, rate in enumerate(rates_hz):
            st = WallSettings(1.0 / float(rate), damping_Ns_per_m, int(d))
            ok = [k for k, p in enumerate(plants)
                  if loop_delay_samples(p, st) <= cap]
            if ok:
                out[i, j, ok] = [r.k_max_N_per_m
                                 for r in wall_stability([plants[k] for k in ok], st)]
    return out


__all__ = [
    "rational_sum",
    "CERTIFICATE_COLUMNS", "CERTIFICATE_STATUSES", "CERT_POINTS_PER_DECADE", "Certificate",
    "WITHHELD", "certificate_sentence", "certificate_status", "DEFAULT_DAMPING_NS_PER_M",
    "DEFAULT_DELAY_SAMPLES", "DEFAULT_SAMPLE_TIME_S", "INTERNAL_DELAY_PADE_ORDER",
    "K_REL_TOL", "MAX_LOOP_DELAY_SAMPLES",
    "RationalPlant", "STABILITY_COLUMNS", "WallSettings", "WallStability", "axis_summary",
    "closed_loop_stable", "crossing_gains", "describe", "environment_terms", "expm_batch",
    "k_max_sweep", "loop_delay_samples", "loop_model",
    "pade_delay", "plant_from_model", "robust_certificate", "stability_table",
    "subject_summary", "wall_stability",
]
