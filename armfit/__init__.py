"""armfit — human arm and hand dynamics and variability models from stylus haptic trials.

Implements the method of M. J. Fu and M. C. Çavuşoğlu, "Three-Dimensional Human Arm and
Hand Dynamics and Variability Model for a Stylus-based Haptic Interface", ICRA 2010.

The Python API (the one backend of the ``armfit`` command line; docs/api.md)::

    import armfit
    s = armfit.estimate("sample_data/study")   # Spectra: every response, trials x frequency
    m = armfit.fit_nominal(s)                  # ModelFit: Table II
    d = armfit.diagnose(s, m)                  # Diagnosis: the missing effect per axis

Stages: :func:`read_trials`, :func:`estimate`, :func:`fit_grip`, :func:`fit_nominal`,
:func:`fit_uncertainty`, :func:`compare`, :func:`diagnose`, :func:`simulate`,
:func:`run`. Models: :class:`Effect`, :class:`Param` and the effect library
:data:`EFFECTS`.
"""

from armfit._version import __version__
from armfit.api import (
    Comparisons,
    Diagnosis,
    ModelFit,
    Simulation,
    Trials,
    Uncertainty,
    compare,
    diagnose,
    estimate,
    fit_grip,
    fit_nominal,
    fit_uncertainty,
    read_model,
    read_spectra,
    read_trials,
    read_weights,
    simulate,
)
from armfit.errors import (
    ArmfitError,
    BadInputError,
    ConvergenceError,
    NoInputError,
    OutputError,
    UsageError,
)
from armfit.models import EFFECTS, ClosedLoopModel, Effect, Param, get_effect
from armfit.pipeline import run
from armfit.spectra import Spectra
from armfit.uncertainty import WuWeight

__all__ = [
    "__version__",
    # stages
    "read_trials", "estimate", "fit_grip", "fit_nominal", "fit_uncertainty", "compare",
    "diagnose", "simulate", "run",
    # results and readers
    "Trials", "Spectra", "ModelFit", "Uncertainty", "Comparisons", "Diagnosis",
    "Simulation", "WuWeight", "read_spectra", "read_model", "read_weights",
    # models and effects
    "ClosedLoopModel", "Effect", "Param", "EFFECTS", "get_effect",
    # errors
    "ArmfitError", "BadInputError", "ConvergenceError", "NoInputError", "OutputError",
    "UsageError",
]
