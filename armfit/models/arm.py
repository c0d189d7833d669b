"""The 5-parameter arm model, the device, and their closed loop (Fu & Çavuşoğlu 2010).

Conventions: frequencies ``f_hz`` in Hz, the Laplace variable ``s = j 2π f`` in rad/s,
responses position/force in m/N, impedances force/position in N/m. Every function is
vectorised over frequency and broadcasts over parameter arrays.

Free-body diagram (paper Fig. 3): the hand point x is joined to the arm mass Ma by a
spring k1 and damper b1 in parallel; Ma is joined to ground by k2 and b2 in parallel.
With C1 = k1 + b1 s and C2 = k2 + b2 s::

    H_ARM(s) = (Ma s² + C1 + C2) / (C1 (Ma s² + C2))            eq. 3
    H_dev(s) = Mp s²                                           eq. 2 (impedance, N/m)
    H_CL(s)  = H_ARM / (1 + H_ARM · Mp s²)                      eq. 4
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from armfit.constants import DEVICE_MASS_KG, PARAM_NAMES
from armfit.errors import EffectDefinitionError, UsageError, cell

if TYPE_CHECKING:  # pragma: no cover
    from armfit.models.effects import Effect

__all__ = ["APPARATUS_STAGES", "BASE_PARAMS", "DEVICE_MASS_KG", "PARAM_NAMES", "STAGE_NAMES",
           "ClosedLoopModel", "Param", "arm_tf", "cl_tf", "h_arm", "h_cl", "h_device",
           "laplace", "union_param_names", "z_arm"]


#: Default closeness (fraction of a parameter's range in its search coordinate) at which
#: a fitted value counts as being at a bound: see :meth:`Param.near_bound`.
AT_BOUND_REL = 0.01


@dataclass(frozen=True)
class Param:
    """One model parameter: name, SI unit, physical bounds and a typical value.

    ``Param(name, unit, lower, upper, typical, description="", log=True)``. ``log``
    parameters are positive and are searched on a log scale by the fitter; the others on
    a linear scale across their bounds. The bounds must hold ``lower < typical < upper``
    (all finite), else :class:`armfit.errors.EffectDefinitionError` (a ValueError).
    """

    name: str
    unit: str
    lower: float
    upper: float
    typical: float
    description: str = ""
    log: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise EffectDefinitionError(f"parameter name must be a non-empty string, "
                                        f"got {self.name!r}")
        for what in ("lower", "upper", "typical"):
            v = getattr(self, what)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating,
                                                         np.integer)) or not np.isfinite(v):
                raise EffectDefinitionError(f"parameter {self.name!r}: {what} must be a "
                                            f"finite number, got {cell(v)}")
        if not (self.lower < self.typical < self.upper):
            raise EffectDefinitionError(
                f"parameter {self.name!r}: bounds must hold lower < typical < upper, got "
                f"lower {self.lower:g}, typical {self.typical:g}, upper {self.upper:g}")
        if self.log and self.lower <= 0:
            raise EffectDefinitionError(f"parameter {self.name!r}: a log parameter needs "
                                        f"lower > 0 (got {self.lower:g}); give log=False "
                                        "for one that may be 0 or negative")

    def near_bound(self, value: float, rel: float = AT_BOUND_REL) -> str | None:
        """Which bound ``value`` lies within ``rel`` of, or None.

        The distance is measured in the fitter's search coordinate, as a fraction of the
        whole range: |ln v − ln bound| ≤ rel·(ln upper − ln lower) for a log parameter,
        |v − bound| ≤ rel·(upper − lower) for a linear one. With the default 1 %, b1 of
        the base model (0.05 … 1000 N·s/m) is flagged below 0.0552 N·s/m. Returns
        "lower" or "upper"; a NaN value is never at a bound.
        """
        v = float(value)
        if not np.isfinite(v):
            return None
        if self.log:
            if v <= 0:
                return "lower"
            x, lo, hi = np.log(v), np.log(self.lower), np.log(self.upper)
        else:
            x, lo, hi = v, self.lower, self.upper
        tol = rel * (hi - lo)
        if x - lo <= tol:
            return "lower"
        if hi - x <= tol:
            return "upper"
        return None


def at_bound(params: Sequence[Param], values: Mapping[str, float],
             rel: float = AT_BOUND_REL) -> list[str]:
    """Names of the parameters whose value in ``values`` lies within ``rel`` (default
    1 %) of a bound, in the order of ``params`` (see :meth:`Param.near_bound`). Names
    missing from ``values`` are skipped."""
    return [p.name for p in params
            if p.name in values and p.near_bound(values[p.name], rel) is not None]


#: The five arm parameters with physical bounds wide enough for every row of
#: Tables I, II and IV (Ma up to 17.5 kg in Lawrence's model, b up to 175 N·s/m).
BASE_PARAMS: tuple[Param, ...] = (
    Param("Ma", "kg", 0.01, 30.0, 0.3, "arm mass"),
    Param("k1", "N/m", 1.0, 3.0e4, 100.0, "hand (grip) stiffness, hand point to arm mass"),
    Param("k2", "N/m", 1.0, 3.0e4, 500.0, "arm stiffness, arm mass to ground"),
    Param("b1", "N*s/m", 0.05, 1000.0, 7.0, "hand (grip) damping"),
    Param("b2", "N*s/m", 0.05, 1000.0, 5.0, "arm damping"),
)


#: Where an effect acts: in the arm's impedance, in the device's, or on the output X/F.
STAGE_NAMES: tuple[str, ...] = ("arm", "device", "output")

#: The stages of the apparatus (the rig, the same for every trial of an axis), as opposed
#: to the arm's own effects (stage arm).
APPARATUS_STAGES: tuple[str, ...] = ("output", "device")


def union_param_names(models: Sequence[ClosedLoopModel]) -> tuple[str, ...]:
    """Every parameter of several models (held ones included), each once: the base names,
    then the effect parameters in the order they first appear — the parameter columns of
    a table holding one model per row."""
    names = list(PARAM_NAMES)
    for m in models:
        names += [n for n in m.all_param_names if n not in names]
    return tuple(names)


def laplace(f_hz: np.ndarray | float) -> np.ndarray:
    """Return s = j·2π·f (rad/s) for frequencies in Hz."""
    return 2j * np.pi * np.asarray(f_hz, dtype=float)


def z_arm(f_hz, Ma, k1, k2, b1, b2) -> np.ndarray:
    """Arm impedance F/X = 1/H_ARM in N/m — inverse of Fu & Çavuşoğlu 2010, eq. 3.

    Z_ARM = C1 (Ma s² + C2) / (Ma s² + C1 + C2), C1 = k1 + b1 s, C2 = k2 + b2 s.
    """
    return _z_arm_at(laplace(f_hz), Ma, k1, k2, b1, b2)


def _z_arm_at(s, Ma, k1, k2, b1, b2) -> np.ndarray:
    """:func:`z_arm` at s = j·2π·f (rad/s), for a caller that has s already."""
    c1, c2, ms2, den = _z_arm_terms(s, Ma, k1, k2, b1, b2)
    return c1 * (ms2 + c2) / den


def _z_arm_terms(s, Ma, k1, k2, b1, b2) -> tuple[np.ndarray, ...]:
    """C1, C2, Ma s² and the denominator D = Ma s² + C1 + C2 of Z_ARM (eq. 3) at s."""
    c1 = k1 + b1 * s
    c2 = k2 + b2 * s
    ms2 = Ma * s * s
    return c1, c2, ms2, ms2 + c1 + c2


def h_arm(f_hz, Ma, k1, k2, b1, b2) -> np.ndarray:
    """Arm dynamics H_ARM = Xa/Fa in m/N — Fu & Çavuşoğlu 2010, eq. 3."""
    return 1.0 / z_arm(f_hz, Ma, k1, k2, b1, b2)


def h_device(f_hz, mp) -> np.ndarray:
    """Device impedance H_PHANToM = Fp/Xp = Mp s² in N/m (mp in kg) — eq. 2."""
    s = laplace(f_hz)
    return mp * s * s


def h_cl(f_hz, Ma, k1, k2, b1, b2, mp) -> np.ndarray:
    """Measured-dynamics model H_CL = X/F in m/N — Fu & Çavuşoğlu 2010, eq. 4.

    H_CL = H_ARM / (1 + H_ARM · Mp s²) = 1 / (Z_ARM + Mp s²).
    """
    return 1.0 / (z_arm(f_hz, Ma, k1, k2, b1, b2) + h_device(f_hz, mp))


def arm_tf(Ma, k1, k2, b1, b2) -> tuple[np.ndarray, np.ndarray]:
    """Polynomial coefficients (highest power first, s in rad/s) of H_ARM — eq. 3.

    num = [Ma, b1+b2, k1+k2]; den = [b1 Ma, b1 b2 + k1 Ma, b2 k1 + b1 k2, k1 k2].
    """
    num = np.array([Ma, b1 + b2, k1 + k2], dtype=float)
    den = np.array([b1 * Ma, b1 * b2 + k1 * Ma, b2 * k1 + b1 * k2, k1 * k2], dtype=float)
    return num, den


def cl_tf(Ma, k1, k2, b1, b2, mp) -> tuple[np.ndarray, np.ndarray]:
    """Polynomial coefficients (s in rad/s) of the fourth-order H_CL — eq. 4.

    H_CL = num / (den + num · Mp s²) with num, den those of H_ARM.
    """
    num, den = arm_tf(Ma, k1, k2, b1, b2)
    den_cl = np.polyadd(den, np.polymul(num, [mp, 0.0, 0.0]))
    return num, den_cl


def _as_values(names: Sequence[str], theta) -> dict[str, float]:
    if isinstance(theta, Mapping):
        missing = [n for n in names if n not in theta]
        if missing:
            raise UsageError(f"missing model parameters: {', '.join(missing)}")
        return {n: theta[n] for n in names}
    arr = np.asarray(theta, dtype=float)
    if arr.shape[0] != len(names):
        raise UsageError(f"expected {len(names)} parameters ({', '.join(names)}), "
                         f"got {arr.shape[0]}")
    return dict(zip(names, arr, strict=True))


@dataclass(frozen=True)
class ClosedLoopModel:
    """The closed loop of eq. 4 for one axis, with optional effects plugged in.

    Effects act at one of three places (see :mod:`armfit.models.effects`):
    ``arm`` adds an impedance to Z_ARM, ``device`` adds an impedance to the device's
    Mp s², ``output`` multiplies X/F. The fitter, the tables and the CLI only see
    :attr:`params` and :meth:`response`; they never learn effect names.

    Every effect term is evaluated through :meth:`armfit.models.effects.Effect.evaluate`,
    which refuses a term that raises or is NaN or infinite (an EffectDefinitionError
    naming the effect and its file), so no response of the model is made of one.

    Parameter names: the five base names, then ``<effect>.<param>`` for each effect.
    ``held`` fixes some effect parameters at given values (pairs of a qualified name and
    its value): they are not searched by a fit (:attr:`params` and :attr:`param_names`
    leave them out), and :meth:`response` uses their held values whatever ``theta``
    says. :attr:`all_param_names` lists every parameter, held or not.
    """

    mp: float
    effects: tuple[Effect, ...] = field(default=())
    held: tuple[tuple[str, float], ...] = field(default=())

    def __post_init__(self) -> None:
        names = [e.name for e in self.effects]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise UsageError(f"effect given twice: {', '.join(dup)}")
        if not self.mp > 0:
            raise UsageError(f"device mass must be > 0 kg, got {self.mp}")
        held = tuple(self.held.items()) if isinstance(self.held, Mapping) else \
            tuple(self.held)
        known = set(self._effect_names())
        for n, _ in held:
            if n not in known:
                raise UsageError(f"cannot hold {n!r}: not a parameter of the model's "
                                 f"effects ({', '.join(sorted(known)) or 'none'})")
        object.__setattr__(self, "held", tuple((str(n), float(v)) for n, v in held))

    @classmethod
    def for_axis(cls, axis: str, effects: Sequence[Effect] = (), mp: float | None = None,
                 held: Mapping[str, float] | None = None) -> ClosedLoopModel:
        """The model of ``axis`` ('x', 'y', 'z') with the paper's Mp unless ``mp`` is given;
        ``held``: {``effect.param``: value} of effect parameters fixed at those values."""
        if axis not in DEVICE_MASS_KG:
            raise UsageError(f"axis must be x, y or z, got {axis!r}")
        return cls(mp=DEVICE_MASS_KG[axis] if mp is None else float(mp), effects=tuple(effects),
                   held=tuple((held or {}).items()))

    def with_effect(self, effect: Effect) -> ClosedLoopModel:
        """A new model with ``effect`` added (refused if already present)."""
        return ClosedLoopModel(mp=self.mp, effects=self.effects + (effect,), held=self.held)

    def _effect_names(self) -> list[str]:
        return [f"{e.name}.{p.name}" for e in self.effects for p in e.params]

    @property
    def held_values(self) -> dict[str, float]:
        """{``effect.param``: value} of the held parameters."""
        return dict(self.held)

    # The parameter lists below are made once per model (every evaluation of the
    # response asks for them) and kept on the instance: a model is immutable.

    def __getstate__(self) -> dict:
        """The fields only: a pickled model (every fit's result a worker sends back, and
        the per-trial fits of a study all kept) leaves out the parameter lists made
        from them, which it makes again when asked (2.6 kB of the 4.5 kB a trial's fit
        held without effects)."""
        return {"mp": self.mp, "effects": self.effects, "held": self.held}

    @functools.cached_property
    def all_params(self) -> tuple[Param, ...]:
        """Every parameter, held ones included: base first, effect parameters qualified as
        ``effect.param``."""
        out = list(BASE_PARAMS)
        for e in self.effects:
            for p in e.params:
                out.append(Param(f"{e.name}.{p.name}", p.unit, p.lower, p.upper, p.typical,
                                 p.description, p.log))
        return tuple(out)

    @functools.cached_property
    def params(self) -> tuple[Param, ...]:
        """The parameters a fit searches: :attr:`all_params` without the held ones."""
        held = self.held_values
        return tuple(p for p in self.all_params if p.name not in held)

    @functools.cached_property
    def param_names(self) -> tuple[str, ...]:
        """Names of :attr:`params` (the free parameters)."""
        return tuple(p.name for p in self.params)

    @functools.cached_property
    def all_param_names(self) -> tuple[str, ...]:
        """Names of :attr:`all_params` (free and held), the columns of a params table."""
        return tuple(p.name for p in self.all_params)

    def values(self, theta) -> dict[str, float]:
        """Every parameter's value: ``theta`` (a mapping or a sequence in the order of
        :attr:`param_names`) for the free ones, the held values for the others."""
        values = _as_values(self.param_names, theta)
        values.update(self.held_values)
        return values

    def null_theta(self, base: Mapping[str, float]) -> dict[str, float]:
        """Base parameters plus every free effect parameter at its null value: the base
        model's response (held parameters keep their values)."""
        theta = {n: float(base[n]) for n in PARAM_NAMES}
        held = self.held_values
        for e in self.effects:
            theta.update({k2: v for k, v in e.null_values(self.mp).items()
                          if (k2 := f"{e.name}.{k}") not in held})
        return theta

    def start_points(self, base: Mapping[str, float]) -> list[dict[str, float]]:
        """Starting points for a nested fit from a base fit: all effects at null first,
        then each effect's own starting points with the others at null."""
        null = self.null_theta(base)
        pts = [null]
        for e in self.effects:
            free = {p.name for p in e.params if f"{e.name}.{p.name}" in null}
            if not free:           # every parameter held: nothing to start
                continue
            for st in e.start_points(self.mp)[1:]:
                pts.append({**null, **{f"{e.name}.{k}": v for k, v in st.items()
                                       if k in free}})
        return pts

    def _split(self, theta) -> tuple[dict[str, float], list[dict[str, float]]]:
        values = self.values(theta)
        base = {n: values[n] for n in PARAM_NAMES}
        eff = [{p.name: values[f"{e.name}.{p.name}"] for p in e.params} for e in self.effects]
        return base, eff

    def arm_response(self, f_hz, theta) -> np.ndarray:
        """H_ARM (m/N) with arm-stage effects included (device and output excluded)."""
        base, eff = self._split(theta)
        s = laplace(f_hz)
        z = z_arm(f_hz, **base)
        for e, v in zip(self.effects, eff, strict=True):
            if e.stage == "arm":
                z = z + e.evaluate(s, v, self.mp)
        return 1.0 / z

    def response(self, f_hz, theta) -> np.ndarray:
        """Measured dynamics X/F (m/N): eq. 4 with every effect applied."""
        base, eff = self._split(theta)
        s = laplace(f_hz)
        # Z_ARM + H_dev (eq. 2), the effects' impedances added, the output factors
        factor, z = self._effect_terms(s, eff, STAGE_NAMES,
                                       _z_arm_at(s, **base) + self.mp * s * s)
        return factor / z

    def response_at_base(self, f_hz, theta, z_base: np.ndarray) -> np.ndarray:
        """:meth:`response` (the same values) where Z_ARM + Mp s² of ``theta``'s base
        parameters is ``z_base`` (N/m, as :meth:`response_and_base_log_derivatives` gives
        it) already: only the effects' terms are made, e.g. for effect values stepped
        with the base parameters fixed."""
        _, eff = self._split(theta)
        factor, z = self._effect_terms(laplace(f_hz), eff, STAGE_NAMES, z_base)
        return factor / z

    def response_and_base_log_derivatives(self, f_hz, theta, with_base: bool = False
                                          ) -> tuple[np.ndarray, ...]:
        """:meth:`response` H (the same values) and ∂ ln H/∂θ for each base parameter θ
        (Ma, k1, k2, b1, b2 in their units), analytically: H = R/Z with Z = Z_ARM + Mp s²
        + ΔZ, R and ΔZ the effects' terms (independent of the base parameters), so
        ∂ ln H/∂θ = −(∂Z_ARM/∂θ)/Z, and with Z_ARM = N/D (eq. 3), N = C1 (Ma s² + C2),
        D = Ma s² + C1 + C2, ∂Z_ARM/∂θ = (∂N/∂θ − Z_ARM ∂D/∂θ)/D. The derivatives are
        (5, ...) complex, the parameters first, then the broadcast shape of ``theta``'s
        values and the frequencies. ``with_base``: also Z_ARM + Mp s² (N/m), for
        :meth:`response_at_base`."""
        base, eff = self._split(theta)
        s = laplace(f_hz)
        c1, c2, ms2, den = _z_arm_terms(s, **base)
        z_arm = c1 * (ms2 + c2) / den
        z_base = z_arm + self.mp * s * s
        factor, z = self._effect_terms(s, eff, STAGE_NAMES, z_base)
        scale = -1.0 / (den * z)
        d_k1 = (ms2 + c2 - z_arm) * scale        # (∂N/∂k1 − Z_ARM ∂D/∂k1) · (−1/(D Z))
        d_k2 = (c1 - z_arm) * scale              # the same for k2
        # ∂/∂Ma = s² ∂/∂k2, ∂/∂b1 = s ∂/∂k1, ∂/∂b2 = s ∂/∂k2 (all five of the shape of
        # scale, which has s and every base value in it)
        out = (factor / z, np.array([s * s * d_k2, d_k1, d_k2, s * d_k1, s * d_k2]))
        return (*out, z_base) if with_base else out

    def _effect_terms(self, s, eff: Sequence[Mapping[str, float]], stages: Sequence[str],
                      z: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(R, ΔZ) at s (rad/s): the product of the output factors and the sum of the
        added impedances (N/m) of the effects whose stage is in ``stages``; ``eff`` holds
        each effect's own values, in the order of :attr:`effects`. Given an impedance
        ``z``, the impedances are added to it in turn (z + ΔZ₁ + ΔZ₂ …) and that sum is
        returned in place of ΔZ."""
        factor = None           # the first factor as it is, not times an array of ones
        dz = np.zeros_like(s) if z is None else z
        for e, v in zip(self.effects, eff, strict=True):
            if e.stage not in stages:
                continue
            if e.stage == "output":
                term = e.evaluate(s, v, self.mp)
                factor = term if factor is None else factor * term
            else:
                dz = dz + e.evaluate(s, v, self.mp)
        return (np.ones_like(s) if factor is None else factor), dz

    def remove_effects(self, f_hz, H, effect_values: Mapping[str, float]) -> np.ndarray:
        """The response eq. 4 would have without the effects, given a measured X/F (m/N)
        and values of the effect parameters (qualified names): the inverse of
        :meth:`response`, H_base = 1 / (R/H − ΔZ), R the output factors, ΔZ the added
        impedances."""
        values = {**effect_values, **self.held_values}
        eff = [{p.name: values[f"{e.name}.{p.name}"] for p in e.params} for e in self.effects]
        factor, dz = self._effect_terms(laplace(f_hz), eff, STAGE_NAMES)
        return 1.0 / (factor / np.asarray(H) - dz)

    @property
    def apparatus_effects(self) -> tuple[Effect, ...]:
        """The effects of the apparatus (:data:`APPARATUS_STAGES`), as opposed to the arm's
        own (stage arm): latency, sensor lag, the device's mass, damping or spring, a
        linkage mode. They are the same for every trial of an axis."""
        return tuple(e for e in self.effects if e.stage in APPARATUS_STAGES)

    def arm_from_derived(self, f_hz, H_derived, theta, mp_assumed: float | None = None
                         ) -> np.ndarray:
        """The arm's own dynamics (m/N) from a derived-arm estimate Xa/Fa, the apparatus
        effects of the model removed: the inverse of :meth:`derived_arm_response` for the
        output and device stages.

        With X/F = R/(Z_arm′ + Mp s² + ΔZ_dev) (Z_arm′ the arm impedance with arm-stage
        effects, R the output factors, ΔZ_dev the added device impedance) and the derived
        estimate D = (X/F)/(1 − Mp_a s² X/F) made with the device mass Mp_a (``mp_assumed``,
        default the model's), Z_arm′ = R/D + (R·Mp_a − Mp) s² − ΔZ_dev. Returns 1/Z_arm′;
        ``H_derived`` unchanged when the model has no apparatus effect and Mp_a = Mp.
        Broadcasts over trials (rows of ``H_derived``).
        """
        H = np.asarray(H_derived)
        mp_a = self.mp if mp_assumed is None else float(mp_assumed)
        if not self.apparatus_effects and mp_a == self.mp:
            return H
        _, eff = self._split(theta)
        s = laplace(f_hz)
        factor, dz = self._effect_terms(s, eff, APPARATUS_STAGES)
        return 1.0 / (factor / H + (factor * mp_a - self.mp) * s * s - dz)

    def derived_arm_response(self, f_hz, theta, mp_assumed: float | None = None) -> np.ndarray:
        """What the derived-arm estimate Xa/Fa, Fa = F − Mp ẍ, converges to (m/N).

        With H the measured X/F of :meth:`response`, Xa/Fa = H / (1 − Mp_assumed s² H)
        (docs/methods.md, "Arm, device and closed loop"). Without effects this equals H_ARM
        exactly.
        """
        h = self.response(f_hz, theta)
        mp = self.mp if mp_assumed is None else mp_assumed
        return h / (1.0 - h_device(f_hz, mp) * h)
