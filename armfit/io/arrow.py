"""Arrow arrays made from numpy arrays through their buffers, without pandas.

``pyarrow.array`` imports pandas on its first call (about a third of a second), which a
command that only reads trials and writes spectra does not otherwise need. The arrays
made here hold the same values, nulls and types as ``pyarrow.array`` (with
``from_pandas=True`` for floats: NaN is a null, in :func:`arrow_array`; without, NaN a
number, in :func:`numpy_array`), so the files written from them are the same bytes.
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


def numpy_array(values: np.ndarray):
    """``pyarrow.array(values)`` of a one-dimensional numpy array of numbers: the same
    values (NaN a number, not a null) in the same type, sharing the array's memory.

    Made from the array's buffer: :func:`pyarrow.array` imports pandas to look at its
    argument (about 0.15 s), which the process writing trials.parquet would pay at its
    first trial.

    Parameters
    ----------
    values : numpy.ndarray, shape (n,)
        Numbers (integers or floats); copied only if not contiguous.

    Returns
    -------
    pyarrow.Array
    """
    import pyarrow as pa
    a = np.ascontiguousarray(values)
    if a.ndim != 1 or a.dtype.kind not in "iuf":
        raise ValueError(f"a one-dimensional array of numbers, got {a.dtype} {a.shape}")
    return pa.Array.from_buffers(pa.from_numpy_dtype(a.dtype), a.size,
                                 [None, pa.py_buffer(a)])


def arrow_array(values: np.ndarray | Sequence, kind: str,
                repeats: np.ndarray | Sequence[int] | None = None):
    """An Arrow array of ``kind`` holding ``values``.

    Parameters
    ----------
    values : array_like, shape (n,)
        float64: numbers, NaN becoming null. int64: whole numbers or None (null).
        large_string: str or None (null).
    kind : {"float64", "int64", "large_string"}
        The Arrow type.
    repeats : array_like of int, shape (n,), optional
        Each value ``repeats[i]`` times in a row (as :func:`numpy.repeat`): a column
        holding one value per block of rows. Text is then encoded once per value, not
        once per row.

    Returns
    -------
    pyarrow.Array
        Equal to ``pyarrow.array(values, type=kind, from_pandas=True)`` (of the values
        repeated).
    """
    import pyarrow as pa
    if repeats is not None:
        counts = np.asarray(repeats, dtype=np.int64)
        if kind == "large_string":
            return _repeated_text(list(values), counts)
        cells = np.empty(len(values), dtype=object)
        cells[:] = list(values)
        values = np.repeat(cells, counts)
        if kind == "float64":
            values = values.astype(np.float64)
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


def _repeated_text(values: list, counts: np.ndarray):
    """The large_string array of ``values`` (str or None) each ``counts[i]`` times: the
    buffers of :func:`arrow_array` of the repeated cells, each value encoded once and its
    bytes copied to every row by one gather."""
    import pyarrow as pa
    encoded = [b"" if v is None else str(v).encode("utf-8") for v in values]
    validity, nulls = _validity(np.repeat(np.array([v is not None for v in values],
                                                   dtype=bool), counts))
    lengths = np.array([len(b) for b in encoded], dtype=np.int64)
    cell_lengths = np.repeat(lengths, counts)
    offsets = np.zeros(cell_lengths.size + 1, dtype=np.int64)
    np.cumsum(cell_lengths, out=offsets[1:])
    starts = np.cumsum(lengths) - lengths          # where each value's bytes begin
    # byte k of the data is byte (k - the row's offset) of the row's value
    shift = np.repeat(np.repeat(starts, counts) - offsets[:-1], cell_lengths)
    data = np.frombuffer(b"".join(encoded), dtype=np.uint8)[shift + np.arange(offsets[-1])]
    return pa.Array.from_buffers(pa.large_string(), cell_lengths.size,
                                 [validity, pa.py_buffer(offsets),
                                  pa.py_buffer(data.tobytes())], null_count=nulls)


def arrow_numbers(arr, dtype=np.float64, missing=np.nan) -> np.ndarray:
    """A pyarrow Array of a fixed-width float or integer type as a numpy array of
    ``dtype``, its nulls ``missing``, read from its data and validity buffers:
    ``Array.to_numpy`` and ``Array.fill_null`` import pandas.

    Parameters
    ----------
    arr : pyarrow.Array
        Floats or integers (a half-float array goes through ``to_numpy``).
    dtype : numpy dtype
        float64 (default) or an integer type for integer arrays.
    missing : scalar
        The value of a null (NaN by default).

    Returns
    -------
    numpy.ndarray
        ``arr.fill_null(missing).to_numpy(zero_copy_only=False)`` as ``dtype``.
    """
    import pyarrow as pa
    width = {8: "1", 16: "2", 32: "4", 64: "8"}.get(arr.type.bit_width)
    kind = "f" if pa.types.is_floating(arr.type) else \
        "i" if pa.types.is_signed_integer(arr.type) else "u"
    if width is None or (kind == "f" and width == "1"):
        return np.asarray(arr.fill_null(missing).to_numpy(zero_copy_only=False),
                          dtype=dtype)
    n, offset = len(arr), arr.offset
    validity, data = arr.buffers()[:2]
    if data is None:
        return np.full(n, missing, dtype=dtype)
    values = np.frombuffer(data, dtype=np.dtype(f"<{kind}{width}"),
                           count=offset + n)[offset:].astype(dtype, copy=False)
    if arr.null_count and validity is not None:
        valid = np.unpackbits(np.frombuffer(validity, dtype=np.uint8), bitorder="little",
                              count=offset + n)[offset:].astype(bool)
        values = np.where(valid, values, missing)
    return values


def arrow_ints(arr, missing: int = -1) -> np.ndarray:
    """A pyarrow Array of an integer type as int64, its nulls ``missing``
    (:func:`arrow_numbers`)."""
    return arrow_numbers(arr, np.int64, missing)


__all__ = ["ARROW_KINDS", "arrow_array", "arrow_ints", "arrow_numbers"]
