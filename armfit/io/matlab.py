"""MATLAB files: the variables a column map names, as signals.

A ``.mat`` file of version 4, 5, 6 or 7 is read with :func:`scipy.io.loadmat`; a
version 7.3 file (HDF5 with a 512-byte MATLAB header) with h5py, the optional extra
``hdf5`` (``pip install armfit[hdf5]``). MATLAB stores arrays column-major, so HDF5 holds
each one transposed: it is transposed back here, and a variable has MATLAB's shape in
either version. A signal is a numeric n×1 or 1×n variable, or one column ``name:k``
(MATLAB's ``name(:,k)``) of an n×k matrix. scipy.io and h5py are imported only here,
when a MATLAB file is read.

A file of MATLAB class objects (``classdef`` or MCOS objects such as ``nldat``,
``timeseries``) cannot be read outside MATLAB: it is refused with one line saying what to
save instead.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from armfit.errors import ArmfitError, BadInputError

#: The first bytes of an HDF5 file (at offset 0, or after a user block such as MATLAB's
#: 512-byte header).
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
#: MATLAB's classes of numeric arrays (the ``MATLAB_class`` attribute in a v7.3 file).
NUMERIC_CLASSES: tuple[str, ...] = (
    "double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
    "uint64", "logical")

_Source = tuple[str, int | None]


def is_hdf5_matlab(path: str | Path) -> bool:
    """True for a MATLAB v7.3 file: its header says "MATLAB 7.3", or HDF5's signature
    is at offset 0 or 512 (after MATLAB's user block)."""
    with open(path, "rb") as fh:
        head = fh.read(520)
    return (head.startswith(b"MATLAB 7.3") or head[:8] == HDF5_SIGNATURE
            or head[512:520] == HDF5_SIGNATURE)


def _save_hint(name: str) -> str:
    return (f"in MATLAB save plain arrays instead, e.g. {name} = double({name}); "
            f"save('file.mat', '{name}', '-v7')")


def _class_objects(name: str, classes: str, file: str) -> BadInputError:
    return BadInputError(f"variable '{name}' holds MATLAB class objects ({classes}) that "
                         f"cannot be read outside MATLAB; {_save_hint(name)}", file=file)


def _signal(arr, name: str, col: int | None, source: str, file: str) -> np.ndarray:
    """The samples of ``source`` from the array ``arr`` of variable ``name`` (MATLAB's
    shape), as float64."""
    a = np.asarray(arr)
    if a.dtype.names is not None or a.dtype.kind not in "biuf":
        what = ("complex" if a.dtype.kind == "c" else "text" if a.dtype.kind in "SU"
                else "a struct or cell array" if a.dtype.kind in "OV" else str(a.dtype))
        raise BadInputError(f"variable '{name}' is {what}, not a numeric array; save the "
                            "signal as a numeric vector (double)", file=file, column=source)
    if a.ndim > 2:
        raise BadInputError(f"variable '{name}' has {a.ndim} dimensions; a signal is a "
                            "vector or a column of a matrix", file=file, column=source)
    a = a.reshape(a.shape + (1,) * (2 - a.ndim))
    rows, cols = a.shape
    if a.size < 2:
        raise BadInputError(f"variable '{name}' holds {a.size} number(s), not a signal",
                            file=file, column=source)
    if col is None:
        if rows > 1 and cols > 1:
            raise BadInputError(f"variable '{name}' is a {rows}×{cols} matrix; name one of "
                                f"its columns, {name}:1 to {name}:{cols}", file=file,
                                column=source)
        return a.reshape(-1).astype(np.float64)
    if rows == 1 and cols > 1:
        raise BadInputError(f"variable '{name}' is a 1×{cols} row vector; name it without "
                            "a column index", file=file, column=source)
    if col > cols:
        raise BadInputError(f"variable '{name}' has {cols} column(s), not {col}", file=file,
                            column=source)
    return a[:, col - 1].astype(np.float64)


def _text(value) -> str:
    """The text of a name field of an opaque object (bytes or str, maybe nested in
    arrays)."""
    while isinstance(value, np.ndarray) and value.size:
        value = value.reshape(-1)[0]
    return value.decode("utf-8", "replace") if isinstance(value, bytes) else str(value)


def _opaque(path: Path, file: str) -> dict[str, str]:
    """{variable: class} of the MATLAB class objects of a v5 file, which scipy reads as
    ``MatlabOpaque`` (each variable read on its own: scipy names them all "None", so
    that one loaded file keeps only the last)."""
    from scipy.io.matlab import MatlabOpaque, varmats_from_mat
    out = {}
    with open(path, "rb") as fh:
        try:
            parts = list(varmats_from_mat(fh))
        except (ValueError, TypeError, OSError, EOFError, KeyError) as exc:
            raise BadInputError(f"unreadable MATLAB file: {exc}", file=file) from None
    for key, part in parts:
        for value in _loadmat(part, None, file).values():
            if isinstance(value, MatlabOpaque):
                fields = value.dtype.names or ()
                name = _text(value["s0"]) if "s0" in fields else key
                out[name] = _text(value["s2"]) if "s2" in fields else "object"
    return out


def _loadmat(path, names: Iterable[str] | None, file: str) -> dict:
    """scipy.io.loadmat of ``path`` (a path or an open binary file)."""
    import scipy.io
    from scipy.io.matlab import MatReadError
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")    # e.g. "duplicate variable name" of objects
            return scipy.io.loadmat(path if hasattr(path, "read") else str(path),
                                    variable_names=None if names is None else list(names))
    except (MatReadError, ValueError, TypeError, OSError, EOFError, NotImplementedError,
            IndexError, KeyError, AttributeError) as exc:
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BadInputError(f"unreadable MATLAB file: {text}", file=file) from None


def _variables(data: dict) -> list[str]:
    return sorted(k for k in data if not k.startswith("__"))


def _read_v5(path: Path, sources: Sequence[tuple[str, _Source]], file: str
             ) -> dict[str, np.ndarray]:
    names = {name for _, (name, _) in sources}
    data = _loadmat(path, names, file)
    missing = [s for s, (name, _) in sources if name not in data]
    if missing or any(type(data[n]).__name__ == "MatlabOpaque" for n in names if n in data):
        everything = _loadmat(path, None, file)
        opaque = _opaque(path, file)
        for _, (name, _col) in sources:
            if name in opaque:
                raise _class_objects(name, opaque[name], file)
        if missing:
            source = missing[0]
            name = dict(sources)[source][0]
            have = [v for v in _variables(everything) if v not in ("None",)]
            if opaque:
                held = ", ".join(f"{k}: {v}" for k, v in sorted(opaque.items()))
                first = sorted(opaque)[0]
                raise BadInputError(f"no variable '{name}'; the file holds MATLAB class "
                                    f"objects ({held}) that cannot be read outside MATLAB; "
                                    f"{_save_hint(first)}", file=file, column=source)
            raise BadInputError(f"no variable '{name}' in the file; it holds "
                                f"{', '.join(have) or 'no variables'}", file=file,
                                column=source)
    return {source: _signal(data[name], name, col, source, file)
            for source, (name, col) in sources}


def _read_v73(path: Path, sources: Sequence[tuple[str, _Source]], file: str
              ) -> dict[str, np.ndarray]:
    try:
        import h5py
    except ImportError:
        raise ArmfitError(f"{file}: a MATLAB v7.3 file is HDF5 and needs h5py: "
                          "pip install armfit[hdf5]") from None
    out: dict[str, np.ndarray] = {}
    try:
        fh = h5py.File(str(path), "r")
    except OSError as exc:
        raise BadInputError(f"unreadable MATLAB v7.3 (HDF5) file: {exc}", file=file) from None
    with fh:
        have = sorted(k for k in fh if not k.startswith("#"))
        for source, (name, col) in sources:
            if name not in fh:
                raise BadInputError(f"no variable '{name}' in the file; it holds "
                                    f"{', '.join(have) or 'no variables'}", file=file,
                                    column=source)
            obj = fh[name]
            cls = obj.attrs.get("MATLAB_class", b"double")
            cls = cls.decode() if isinstance(cls, bytes) else str(cls)
            if "MATLAB_object_decode" in obj.attrs or (
                    cls not in NUMERIC_CLASSES and cls not in ("char", "cell", "struct")):
                raise _class_objects(name, cls, file)
            if not isinstance(obj, h5py.Dataset) or cls not in NUMERIC_CLASSES:
                raise BadInputError(f"variable '{name}' is a MATLAB {cls}, not a numeric "
                                    "array; save the signal as a numeric vector (double)",
                                    file=file, column=source)
            if obj.attrs.get("MATLAB_empty", 0):
                raise BadInputError(f"variable '{name}' is empty", file=file, column=source)
            out[source] = _signal(np.asarray(obj[()]).T, name, col, source, file)
    return out


def read_matlab(path: str | Path, sources: Sequence[tuple[str, _Source]], *,
                file: str | None = None) -> dict[str, np.ndarray]:
    """Read the signals ``sources`` of a MATLAB file.

    Parameters
    ----------
    path : str or Path
        The ``.mat`` file (v4 to v7 read by scipy.io; v7.3, HDF5, by h5py).
    sources : sequence of (text, (variable, column))
        Each signal: the text a message names it by (``io:2``), the variable's name
        and the 1-based column of a matrix (None for a vector).
    file : str, optional
        How messages name the file (default ``path``).

    Returns
    -------
    dict
        {text: float64 samples}, one 1-D array per signal.

    Raises
    ------
    BadInputError
        Exit 65, naming the file and the signal: not a MATLAB file, no such variable, a
        variable that is not a numeric vector or matrix column, or MATLAB class objects.
    ArmfitError
        Exit 1: a v7.3 file without h5py installed ("pip install armfit[hdf5]").
    """
    p = Path(path)
    label = str(path) if file is None else file
    if is_hdf5_matlab(p):
        return _read_v73(p, sources, label)
    return _read_v5(p, sources, label)


__all__ = [
    "HDF5_SIGNATURE", "NUMERIC_CLASSES", "is_hdf5_matlab", "read_matlab",
]
