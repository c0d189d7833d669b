"""The scipy functions of the uncertainty fits and the statistics, imported at their
first call.

Importing :mod:`scipy.optimize` takes about half a second and :mod:`scipy.special` a
quarter (they import :mod:`scipy.linalg`, :mod:`scipy.sparse` and the array-API layer);
the modules that use these functions are imported by commands that may never call them
(``diagnose`` takes no interval of a single-trial fit, ``--help`` calls nothing), so
each is imported here when first called. The functions are scipy's, unchanged. (The
fits' least-squares solver is :mod:`armfit._trf`, which needs no scipy, and the Wu
fits' SLSQP calls scipy's compiled kernel without :mod:`scipy.optimize`:
:mod:`armfit._slsqp`, whose fallback :func:`minimize` is.)
"""

from __future__ import annotations

__all__ = ["minimize", "stdtrit"]


def minimize(*args, **kwargs):
    """:func:`scipy.optimize.minimize`."""
    from scipy.optimize import minimize as fn
    return fn(*args, **kwargs)


def stdtrit(df, p):
    """:func:`scipy.special.stdtrit`: Student's t quantile ``p`` with ``df`` degrees of
    freedom."""
    from scipy.special import stdtrit as fn
    return fn(df, p)

