"""armfit — human arm and hand dynamics and variability models from stylus haptic trials.

Implements the method of M. J. Fu and M. C. Çavuşoğlu, "Three-Dimensional Human Arm and
Hand Dynamics and Variability Model for a Stylus-based Haptic Interface", ICRA 2010.

The Python API (the one backend of the ``armfit`` command line; docs/api.md)::

    import armfit
    s = armfit.estimate("sample_data/study")   # Spectra: every response, trials x frequency
    m = armfit.fit_nominal(s)                  # ModelFit: Table II
    d = armfit.diagnose(s, m)                  # Diagnosis: the missing effect per axis

Stages: :func:`read_trials`, :func:`estimate`, :func:`fit_grip`, :func:`fit_nominal`,
:func:`fit_trials`, :func:`fit_uncertainty`, :func:`compare`, :func:`diagnose`,
:func:`stability`, :func:`adopt_model`, :func:`simulate`, :func:`run`. Models: :class:`Effect`,
:class:`Param` and the effect library :data:`EFFECTS`.
"""

from armfit._lazy import lazy_exports
from armfit._version import __version__

#: The public names and the module each comes from. They are imported on first use, so
#: that ``import armfit.spectra`` (e.g. in a worker process) does not load the figures.
_EXPORTS: dict[str, str] = {
    # stages
    "read_trials": "armfit.api", "estimate": "armfit.api", "fit_grip": "armfit.api",
    "fit_nominal": "armfit.api", "fit_uncertainty": "armfit.api", "compare": "armfit.api",
    "diagnose": "armfit.api", "simulate": "armfit.api", "run": "armfit.pipeline",
    "fit_trials": "armfit.api", "stability": "armfit.api", "adopt_model": "armfit.api",
    # results and readers
    "Trials": "armfit.api", "Spectra": "armfit.spectra", "ModelFit": "armfit.api",
    "Uncertainty": "armfit.api", "Comparisons": "armfit.api", "Diagnosis": "armfit.api",
    "Simulation": "armfit.api", "WuWeight": "armfit.uncertainty",
    "TrialFits": "armfit.api", "Stability": "armfit.api", "AdoptedModel": "armfit.api",
    "read_spectra": "armfit.api", "read_model": "armfit.api", "read_weights": "armfit.api",
    # models and effects
    "ClosedLoopModel": "armfit.models.arm", "Param": "armfit.models.arm",
    "Effect": "armfit.models.effects", "EFFECTS": "armfit.models.effects",
    "get_effect": "armfit.models.effects",
    # errors
    "ArmfitError": "armfit.errors", "BadInputError": "armfit.errors",
    "ConvergenceError": "armfit.errors", "NoInputError": "armfit.errors",
    "OutputError": "armfit.errors", "UsageError": "armfit.errors",
}

__all__ = ["__version__", *_EXPORTS]


__getattr__ = lazy_exports(globals(), _EXPORTS)[0]
del lazy_exports


def __dir__() -> list[str]:
    """The public API (:data:`__all__`): no helper, submodule or imported name."""
    return sorted(__all__)
