"""The effect library: physical effects the 5-parameter model of eq. 4 lacks.

Each effect is a value that plugs into :class:`armfit.models.arm.ClosedLoopModel` at
one of three places:

``arm``     an impedance (N/m) added to the arm's Z_ARM = 1/H_ARM;
``device``  an impedance (N/m) added to the device's Mp s²;
``output``  a dimensionless factor multiplying the measured X/F.

So with every effect present the measured dynamics are
X/F = Π R_out(s) / (Z_ARM + ΔZ_arm + Mp s² + ΔZ_dev).
The same definitions drive the simulator, the fits and the diagnosis.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from armfit.errors import UsageError
from armfit.models.arm import Param

TermFn = Callable[[np.ndarray, Mapping[str, float], float], np.ndarray]


@dataclass(frozen=True)
class Effect:
    """A named physical effect: its parameters, where it acts and what it does.

    ``term(s, values, mp)`` returns the impedance (N/m) for ``arm``/``device`` stages or
    the dimensionless factor for the ``output`` stage, at s in rad/s; ``values`` maps the
    effect's own (unqualified) parameter names to numbers; ``mp`` is the device mass (kg).
    """

    name: str
    stage: str
    params: tuple[Param, ...]
    summary: str
    suspect_when: str
    _term: TermFn
    #: Values at which the effect (nearly) vanishes; ``None`` means "the device mass"
    #: (for an effect that replaces Mp). Nested fits start here, so adding the effect
    #: never makes a fit worse.
    null_values: tuple[float | None, ...] = ()
    #: Further starting points (tuples in parameter order) for a global search.
    starts: tuple[tuple[float, ...], ...] = ()

    def term(self, s: np.ndarray, values: Mapping[str, float], mp: float) -> np.ndarray:
        return self._term(s, values, mp)

    def null(self, mp: float) -> dict[str, float]:
        """The parameter values at which this effect leaves the model (nearly) unchanged."""
        return {p.name: (mp if v is None else v)
                for p, v in zip(self.params, self.null_values, strict=True)}

    def start_points(self, mp: float) -> list[dict[str, float]]:
        """The null point, then the effect's further starting points, clipped to bounds."""
        pts = [self.null(mp)]
        for st in self.starts:
            pts.append({p.name: float(np.clip(v, p.lower, p.upper))
                        for p, v in zip(self.params, st, strict=True)})
        return pts

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)


def _delay(s, v, mp):
    return np.exp(-s * v["delay_s"])


def _lowpass(s, v, mp):
    return 1.0 / (1.0 + s / (2.0 * np.pi * v["cutoff_hz"]))


def _device_damping(s, v, mp):
    return v["damping_Ns_per_m"] * s


def _device_mass(s, v, mp):
    return (v["mass_kg"] - mp) * s * s


def _resonance(s, v, mp):
    wn = 2.0 * np.pi * v["freq_hz"]
    mode = wn * wn / (s * s + 2.0 * v["zeta"] * wn * s + wn * wn)
    return (1.0 - v["weight"]) + v["weight"] * mode


def _reflex(s, v, mp):
    return v["gain_N_per_m"] * np.exp(-s * v["delay_s"])


EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect(
        "delay", "output",
        (Param("delay_s", "s", 0.0, 0.1, 0.01, "latency between force and position", log=False),),
        "Transport, servo or sensor latency: X/F is multiplied by exp(-s*delay_s).",
        "phase lags more and more with frequency (linearly in Hz) while the magnitude fits",
        _delay, null_values=(0.0,), starts=((0.004,), (0.015,), (0.04,))),
    Effect(
        "lowpass", "output",
        (Param("cutoff_hz", "Hz", 1.0, 1.0e5, 60.0, "corner frequency"),),
        "First-order sensor or amplifier lag: X/F is multiplied by 1/(1 + s/(2*pi*cutoff_hz)).",
        "magnitude droops and phase lags at high frequency, up to 90 deg past the corner",
        _lowpass, null_values=(1.0e5,), starts=((8.0,), (25.0,), (80.0,))),
    Effect(
        "device-damping", "device",
        (Param("damping_Ns_per_m", "N*s/m", 1e-4, 100.0, 2.0, "viscous friction"),),
        "Viscous friction in the device: its impedance becomes Mp*s^2 + B*s.",
        "magnitude too low and phase lag too small in the mid band, as if the hand "
        "damping grew",
        _device_damping, null_values=(1e-4,), starts=((1.0,), (5.0,))),
    Effect(
        "device-mass", "device",
        (Param("mass_kg", "kg", 0.005, 3.0, 0.1, "actual moving mass of the device"),),
        "The device's moving mass differs from the paper's Mp (e.g. another stylus or "
        "gimbal): its impedance becomes mass_kg*s^2.",
        "magnitude off by a constant in dB above ~15 Hz, where the -40 dB/dec mass line "
        "dominates",
        _device_mass, null_values=(None,), starts=((0.05,), (0.2,))),
    Effect(
        "resonance", "output",
        (Param("freq_hz", "Hz", 2.0, 300.0, 40.0, "natural frequency of the mode"),
         Param("zeta", "1", 0.02, 0.5, 0.1, "damping ratio of the mode"),
         Param("weight", "1", 1e-5, 1.0, 0.3, "share of the motion through the mode")),
        "An extra lightly damped mode (link, cable or tissue compliance) in the path to the "
        "measured point: X/F is multiplied by (1 - weight) + weight*wn^2/(s^2 + "
        "2*zeta*wn*s + wn^2), wn = 2*pi*freq_hz.",
        "magnitude rises above the model towards a peak (or a peak-notch pair) with a "
        "phase swing; above 30 Hz only the rise shows (the paper's Z axis)",
        _resonance, null_values=(60.0, 0.3, 1e-5),
        starts=((8.0, 0.2, 0.3), (15.0, 0.2, 0.3), (30.0, 0.2, 0.3), (60.0, 0.2, 0.3),
                (120.0, 0.2, 0.5))),
    Effect(
        "reflex", "arm",
        (Param("gain_N_per_m", "N/m", 1e-2, 5000.0, 200.0, "reflex stiffness"),
         Param("delay_s", "s", 0.005, 0.2, 0.04, "reflex loop delay")),
        "Delayed position feedback of the stretch reflex inside the arm: the arm impedance "
        "gains gain_N_per_m*exp(-s*delay_s).",
        "a ripple in magnitude and phase whose spacing in Hz is 1/delay_s, strongest in "
        "the 1-10 Hz band where the arm is compliant",
        _reflex, null_values=(1e-2, 0.04),
        starts=((100.0, 0.02), (100.0, 0.04), (100.0, 0.07), (100.0, 0.12))),
)}


def get_effect(name: str) -> Effect:
    """Look an effect up by name; raise UsageError listing the known ones otherwise."""
    try:
        return EFFECTS[name]
    except KeyError:
        raise UsageError(f"unknown effect {name!r}; known effects: "
                         f"{', '.join(EFFECTS)} (see `armfit effects`)") from None


def parse_effect_spec(spec: str) -> tuple[Effect, dict[str, float]]:
    """Parse ``NAME=V1[,V2..]`` (values in the effect's parameter order) or
    ``NAME=param:V[,param:V..]`` into (effect, {param: value}).

    Values must lie inside the parameter's physical bounds.
    """
    name, sep, rest = spec.partition("=")
    effect = get_effect(name.strip())
    if not sep or not rest.strip():
        raise UsageError(f"--effect {spec!r}: give values as {effect.name}="
                         + ",".join(effect.param_names))
    items = [x.strip() for x in rest.split(",") if x.strip()]
    values: dict[str, float] = {}
    keyed = [":" in x for x in items]
    if any(keyed) and not all(keyed):
        raise UsageError(f"--effect {spec!r}: use either all positional or all param:value")
    if all(keyed):
        for item in items:
            k, _, v = item.partition(":")
            if k not in effect.param_names:
                raise UsageError(f"--effect {spec!r}: {effect.name} has no parameter {k!r}; "
                                 f"it has {', '.join(effect.param_names)}")
            values[k] = _number(spec, v)
    else:
        if len(items) != len(effect.params):
            raise UsageError(f"--effect {spec!r}: {effect.name} takes {len(effect.params)} "
                             f"value(s): {', '.join(effect.param_names)}")
        values = {p.name: _number(spec, v) for p, v in zip(effect.params, items, strict=True)}
    missing = [p for p in effect.param_names if p not in values]
    if missing:
        raise UsageError(f"--effect {spec!r}: missing {', '.join(missing)}")
    for p in effect.params:
        if not (p.lower <= values[p.name] <= p.upper):
            raise UsageError(f"--effect {spec!r}: {p.name}={values[p.name]} outside the "
                             f"physical range [{p.lower}, {p.upper}] {p.unit}")
    return effect, values


def _number(spec: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise UsageError(f"--effect {spec!r}: {text!r} is not a number") from None
