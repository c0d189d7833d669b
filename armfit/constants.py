"""One home for the names and units every layer shares: axes, the arm parameters, the
device masses and the dB/neper conversion (Fu & Çavuşoğlu 2010).

Nothing here imports from armfit: every module may use it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

#: The device's Cartesian axes, in the order of every table and figure.
AXES: tuple[str, ...] = ("x", "y", "z")

#: Names of the five arm parameters, in the paper's order (Tables I and II); their units
#: and bounds are in :data:`armfit.models.arm.BASE_PARAMS`.
PARAM_NAMES: tuple[str, ...] = ("Ma", "k1", "k2", "b1", "b2")

#: Device (PHANToM Premium 1.5a) moving mass per axis in kg — paper eq. 2.
DEVICE_MASS_KG: dict[str, float] = {"x": 0.09, "y": 0.095, "z": 0.091}

#: dB per neper: 20 log10|H| = DB_PER_NEPER · ln|H| (20/ln 10 ≈ 8.686).
DB_PER_NEPER: float = 20.0 / math.log(10.0)

#: Phase (deg) weighted like 1 dB of magnitude: 1 rad ↔ 1 neper, i.e. (180/π)/DB_PER_NEPER.
UNIT_SE_DEG: float = math.degrees(1.0) / DB_PER_NEPER

#: The device's peak force, N (PHANToM Premium 1.5a): a larger recorded force is
#: warned about as saturation. The default of every reader and estimator.
FORCE_LIMIT_N: float = 8.5

#: The standard normal distribution's 97.5 % quantile (the half-width of a 95 % interval in
#: standard errors): ``scipy.special.ndtri(0.975)``, the same float.
Z_975: float = 1.959963984540054

#: The default frequency grid: from 0.1 Hz (the paper's lowest frequency; a trial must
#: last 2/f_min) to 30 Hz, 40 log-spaced points per decade.
GRID_HZ: tuple[float, float] = (0.1, 30.0)
POINTS_PER_DECADE: int = 40

#: Default fit bands (Hz) per axis, as the paper: X and Y 0.1–30 Hz, Z 0.1–10 Hz.
PAPER_BANDS: dict[str, tuple[float, float]] = {
    "x": (0.1, 30.0), "y": (0.1, 30.0), "z": (0.1, 10.0)}


def axis_band(band, axis: str):
    """The band of ``axis`` (Hz) in a stage's ``band`` argument: ``band`` itself when it
    is one (lo, hi) for every axis, ``band[axis]`` when it is a mapping {axis: (lo, hi)}
    (None for an axis it does not name), None when ``band`` is None (the stage's
    default then applies)."""
    if isinstance(band, Mapping):
        return band.get(axis)
    return band


__all__ = [
    "FORCE_LIMIT_N", "GRID_HZ", "POINTS_PER_DECADE",
    "AXES", "PARAM_NAMES", "DEVICE_MASS_KG", "DB_PER_NEPER", "UNIT_SE_DEG",
    "PAPER_BANDS", "Z_975", "axis_band",
]
