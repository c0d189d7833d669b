"""armfit — human arm and hand dynamics and variability models from stylus haptic trials.

Implements the method of M. J. Fu and M. C. Çavuşoğlu, "Three-Dimensional Human Arm and
Hand Dynamics and Variability Model for a Stylus-based Haptic Interface", ICRA 2010.
"""

__version__ = "0.1.0"

__all__ = ["Effect", "Param", "__version__"]


def __getattr__(name: str):
    # the plugin API, imported on first use so that `import armfit` stays light
    if name == "Effect":
        from armfit.models.effects import Effect
        return Effect
    if name == "Param":
        from armfit.models.arm import Param
        return Param
    raise AttributeError(f"module 'armfit' has no attribute {name!r}")
