"""scipy's compiled modules loaded without their packages, and the Wu fits' fallback
optimiser, imported at its first call.

Importing :mod:`scipy.optimize` takes about half a second (it imports
:mod:`scipy.linalg`, :mod:`scipy.sparse` and the array-API layer); the modules that use
it are imported by commands that may never call it (``--help`` calls nothing), so it is
imported here when first called. The functions are scipy's, unchanged. (The fits'
least-squares solver is :mod:`armfit._trf`, which needs no scipy, their intervals' t
quantiles are :func:`armfit._student.t_quantile`, and the Wu fits' SLSQP calls scipy's
compiled kernel without :mod:`scipy.optimize`: :mod:`armfit._slsqp`, whose fallback
:func:`minimize` is.)
"""

from __future__ import annotations

__all__ = ["compiled_module", "minimize"]


def compiled_module(name: str):
    """The compiled module ``name`` of scipy (e.g. ``"scipy.linalg._flapack"``), loaded
    from its file without importing the package around it, whose ``__init__`` imports
    far more (:mod:`scipy.linalg` takes about 0.13 s, :mod:`scipy.optimize` 0.4 s); only
    the top-level :mod:`scipy` is imported. The module is registered under its own name,
    so a later import of its package uses it too. None where the file is not there or
    does not load."""
    import sys
    from importlib import machinery, util
    from pathlib import Path

    if name in sys.modules:
        return sys.modules[name]
    import scipy
    parts = name.split(".")
    if parts[0] != "scipy":
        raise ValueError(f"not a scipy module: {name}")
    folder = Path(scipy.__file__).parent.joinpath(*parts[1:-1])
    paths = [folder / f"{parts[-1]}{s}" for s in machinery.EXTENSION_SUFFIXES]
    path = next((p for p in paths if p.is_file()), None)
    if path is None:
        return None
    loader = machinery.ExtensionFileLoader(name, str(path))
    spec = util.spec_from_file_location(name, str(path), loader=loader)
    try:
        module = util.module_from_spec(spec)
        loader.exec_module(module)
    except ImportError:
        return None
    return sys.modules.setdefault(name, module)


def minimize(*args, **kwargs):
    """:func:`scipy.optimize.minimize`."""
    from scipy.optimize import minimize as fn
    return fn(*args, **kwargs)
