"""armfit — human arm and hand dynamics and variability models from stylus haptic trials.

Implements the method of M. J. Fu and M. C. Çavuşoğlu, "Three-Dimensional Human Arm and
Hand Dynamics and Variability Model for a Stylus-based Haptic Interface", ICRA 2010.
"""

__version__ = "0.1.0"
