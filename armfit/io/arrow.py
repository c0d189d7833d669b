"""Arrow arrays made from numpy arrays through their buffers, without pandas.

``pyarrow.array`` imports pandas on its first call (about a third of a second), which a
command that only reads trials and writes spectra does not otherwise need. The arrays
made here hold the same values, nulls and types as ``pyarrow.array`` (with
``from_pandas=True`` for floats: NaN is a null), so the files written from them are the
same bytes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: The Arrow types :func:`arrow_array` makes, by name.
ARROW_KINDS = ("float64", "int64", "large_string")


def _validity(valid: np.ndarray):
    """(validity buffer or None, null count) of a boolean mask of valid values."""
    import pyarrow as pa
    nulls = int(valid.size - np.count_nonzero(valid))
    if not nulls:
        return None, 0
    return pa.py_buffer(np.packbits(valid, bitorder="little")), nulls


def arrow_array(values: np.ndarray | Sequence, kind: str):
    """An Arrow array of ``kind`` holding ``values``.

    Parameters
    ----------
    values : array_like, shape (n,)
        float64: numbers, NaN becoming null. int64: whole numbers or None (null).
        large_string: str or None (null).
    kind : {"float64", "int64", "large_string"}
        The Arrow type.

    Returns
    -------
    pyarrow.Array
        Equal to ``pyarrow.array(values, type=kind, from_pandas=True)``.
    """
    import pyarrow as pa
    if kind == "float64":
        data = np.ascontiguousarray(values, dtype=np.float64)
        validity, nulls = _validity(~np.isnan(data))
        return pa.Array.from_buffers(pa.float64(), data.size,
                                     [validity, pa.py_buffer(data)], null_count=nulls)
    cells = list(values)
    valid = np.array([v is not None for v in cells], dtype=bool)
    validity, nulls = _validity(valid)
    if kind == "int64":
        data = np.array([0 if v is None else v for v in cells], dtype=np.int64)
        return pa.Array.from_buffers(pa.int64(), data.size,
                                     [validity, pa.py_buffer(data)], null_count=nulls)
    if kind == "large_string":
        encoded = [b"" if v is None else str(v).encode("utf-8") for v in cells]
        offsets = np.zeros(len(encoded) + 1, dtype=np.int64)
        np.cumsum([len(b) for b in encoded], out=offsets[1:])
        return pa.Array.from_buffers(pa.large_string(), len(encoded),
                                     [validity, pa.py_buffer(offsets),
                                      pa.py_buffer(b"".join(encoded))], null_count=nulls)
    raise ValueError(f"kind must be one of {', '.join(ARROW_KINDS)}, got {kind!r}")


__all__ = ["ARROW_KINDS", "arrow_array"]
