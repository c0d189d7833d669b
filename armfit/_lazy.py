"""Names of a package imported on first use (PEP 562 module ``__getattr__``).

A package lists its public names and the module each comes from; importing the package
then imports none of them, so that a worker process or a command that needs one light
module does not load the others (matplotlib, pandas, the fitting stack).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from importlib import import_module
from types import ModuleType

from armfit.errors import UsageError


def lazy_exports(namespace: dict, exports: Mapping[str, str]
                 ) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of a package whose ``exports`` (name -> module)
    are imported when first asked for.

    Parameters
    ----------
    namespace : dict
        The package's ``globals()``: a name, once imported, is stored there, so the
        next access does not come back here.
    exports : mapping of str to str
        Each public name and the module that defines it.

    Returns
    -------
    (callable, callable)
        ``__getattr__(name)`` (AttributeError naming the package for an unknown name)
        and ``__dir__()``.
    """
    package = namespace["__name__"]

    def __getattr__(name: str):
        if name in exports:
            value = getattr(import_module(exports[name]), name)
            namespace[name] = value
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__


def import_extra(module: str, extra: str, what: str) -> ModuleType:
    """The optional package ``module`` of the extra ``armfit[extra]``, imported.

    Parameters
    ----------
    module : str
        The package, e.g. ``"control"``.
    extra : str
        The extra that installs it, e.g. ``"control"``.
    what : str
        What needs it, named in the message (e.g. ``"ModelFit.to_control"``).

    Raises
    ------
    UsageError
        One line when it is not installed: ``<what> needs the optional package
        '<module>': pip install armfit[<extra>]`` (exit 2 on the command line).
    """
    try:
        return import_module(module)
    except ImportError:
        raise UsageError(f"{what} needs the optional package {module!r}: pip install "
                         f"armfit[{extra}]") from None


def loaded(name: str) -> ModuleType | None:
    """The module ``name`` if it is imported, else None, without importing it.

    A module another thread is importing is already in :data:`sys.modules`, but only in
    part: the names below the line its import has reached are not defined yet. Such a
    module counts as not imported: nothing made from it can exist yet. (A read of
    spectra.parquet in ``armfit run``'s diagnosis asked the half-imported pandas of the
    main thread for ``Series``; the read failed over to reading the whole file, 180 MB
    more at 810 trials.)

    Parameters
    ----------
    name : str
        The module's full name.

    Returns
    -------
    module or None
    """
    module = sys.modules.get(name)
    if module is None or getattr(getattr(module, "__spec__", None), "_initializing", False):
        return None
    return module


__all__ = ["lazy_exports", "import_extra", "loaded"]
