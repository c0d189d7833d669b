"""The built-in effect library: the first ``EFFECTS`` list the registry loads.

It is written exactly like a user's effect file (see :mod:`armfit.models.effects`) and
loaded, and checked, by the same path. ``term(s, values, mp)``: s in rad/s, ``values``
the effect's own parameter values, ``mp`` the device mass (kg). ``rational(values, mp)``:
the same term as (num, den[, delay_s]), num(s)/den(s)·exp(−s·delay_s) with coefficients
in s highest power first (eq. R1 of :mod:`armfit.models.effects`), for the stability
analysis; the registration check holds each equal to its term.
"""

from __future__ import annotations

import numpy as np

from armfit.models.arm import Param
from armfit.models.effects import Effect


def _delay(s, v, mp):
    return np.exp(-s * v["delay_s"])


def _delay_rational(v, mp):
    return 1.0, 1.0, v["delay_s"]                 # 1/1 · exp(−s τ)


def _lowpass(s, v, mp):
    return 1.0 / (1.0 + s / (2.0 * np.pi * v["cutoff_hz"]))


def _lowpass_rational(v, mp):
    return 1.0, (1.0 / (2.0 * np.pi * v["cutoff_hz"]), 1.0)    # 1/(s/ω_c + 1)


def _device_damping(s, v, mp):
    return v["damping_Ns_per_m"] * s


def _device_damping_rational(v, mp):
    return (v["damping_Ns_per_m"], 0.0), 1.0     # B s


def _device_mass(s, v, mp):
    return (v["mass_kg"] - mp) * s * s


def _device_mass_rational(v, mp):
    return (v["mass_kg"] - mp, 0.0, 0.0), 1.0    # (M − Mp) s²


def _resonance(s, v, mp):
    wn = 2.0 * np.pi * v["freq_hz"]
    mode = wn * wn / (s * s + 2.0 * v["zeta"] * wn * s + wn * wn)
    return (1.0 - v["weight"]) + v["weight"] * mode


def _resonance_rational(v, mp):
    wn = 2.0 * np.pi * v["freq_hz"]
    den = np.array([1.0, 2.0 * v["zeta"] * wn, wn * wn])    # s² + 2ζω_n s + ω_n²
    w = v["weight"]
    return np.polyadd((1 - w) * den, [w * wn * wn]), den   # ((1 − w) den + w ω_n²)/den


def _reflex(s, v, mp):
    return v["gain_N_per_m"] * np.exp(-s * v["delay_s"])


def _reflex_rational(v, mp):
    return v["gain_N_per_m"], 1.0, v["delay_s"]   # g/1 · exp(−s τ)


EFFECTS = [
    Effect(
        name="delay", stage="output",
        params=(Param("delay_s", "s", 0.0, 0.1, 0.01, "latency between force and position",
                      log=False),),
        term=_delay, rational=_delay_rational,
        summary="Transport, servo or sensor latency: X/F is multiplied by exp(-s*delay_s).",
        suspect_when="phase lags more and more with frequency (linearly in Hz) while the "
                     "magnitude fits",
        null=(0.0,), starts=((0.004,), (0.015,), (0.04,))),
    Effect(
        name="lowpass", stage="output",
        params=(Param("cutoff_hz", "Hz", 1.0, 1.0e5, 60.0, "corner frequency"),),
        term=_lowpass, rational=_lowpass_rational,
        summary="First-order sensor or amplifier lag: X/F is multiplied by "
                "1/(1 + s/(2*pi*cutoff_hz)).",
        suspect_when="magnitude droops and phase lags at high frequency, up to 90 deg past "
                     "the corner",
        null=(1.0e5,), starts=((8.0,), (25.0,), (80.0,))),
    Effect(
        name="device-damping", stage="device",
        params=(Param("damping_Ns_per_m", "N*s/m", 1e-4, 100.0, 2.0, "viscous friction"),),
        term=_device_damping, rational=_device_damping_rational,
        summary="Viscous friction in the device: its impedance becomes Mp*s^2 + B*s.",
        suspect_when="magnitude too low and phase lag too small in the mid band, as if the "
                     "hand damping grew",
        null=(1e-4,), starts=((1.0,), (5.0,))),
    Effect(
        name="device-mass", stage="device",
        params=(Param("mass_kg", "kg", 0.005, 3.0, 0.1, "actual moving mass of the device"),),
        term=_device_mass, rational=_device_mass_rational,
        summary="The device's moving mass differs from the paper's Mp (e.g. another stylus "
                "or gimbal): its impedance becomes mass_kg*s^2.",
        suspect_when="magnitude off by a constant in dB above ~15 Hz, where the -40 dB/dec "
                     "mass line dominates",
        # None: the null is the model's own device mass Mp
        null=(None,), starts=((0.05,), (0.2,))),
    Effect(
        name="resonance", stage="output",
        params=(Param("freq_hz", "Hz", 2.0, 300.0, 40.0, "natural frequency of the mode"),
                Param("zeta", "1", 0.02, 0.5, 0.1, "damping ratio of the mode"),
                Param("weight", "1", 1e-5, 1.0, 0.3, "share of the motion through the mode")),
        term=_resonance, rational=_resonance_rational,
        summary="An extra lightly damped mode (link, cable or tissue compliance) in the path "
                "to the measured point: X/F is multiplied by (1 - weight) + "
                "weight*wn^2/(s^2 + 2*zeta*wn*s + wn^2), wn = 2*pi*freq_hz.",
        suspect_when="magnitude rises above the model towards a peak (or a peak-notch pair) "
                     "with a phase swing; above 30 Hz only the rise shows (the paper's Z "
                     "axis)",
        null=(60.0, 0.3, 1e-5),
        starts=((8.0, 0.2, 0.3), (15.0, 0.2, 0.3), (30.0, 0.2, 0.3), (60.0, 0.2, 0.3),
                (120.0, 0.2, 0.5))),
    Effect(
        name="reflex", stage="arm",
        params=(Param("gain_N_per_m", "N/m", 1e-2, 5000.0, 200.0, "reflex stiffness"),
                Param("delay_s", "s", 0.005, 0.2, 0.04, "reflex loop delay")),
        term=_reflex, rational=_reflex_rational,
        summary="Delayed position feedback of the stretch reflex inside the arm: the arm "
                "impedance gains gain_N_per_m*exp(-s*delay_s).",
        suspect_when="a ripple in magnitude and phase whose spacing in Hz is 1/delay_s, "
                     "strongest in the 1-10 Hz band where the arm is compliant",
        null=(1e-2, 0.04),
        starts=((100.0, 0.02), (100.0, 0.04), (100.0, 0.07), (100.0, 0.12))),
]


__all__ = [
    "EFFECTS",
]
