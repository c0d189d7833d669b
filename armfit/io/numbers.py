"""Text to numbers: the one strict parser behind every reader of numbers.

Every file armfit reads (raw trials in CSV and Parquet, manifests, the canonical
dataset's metadata, params and Wu files, spectra tables) turns its text into numbers
here, so that every reader accepts and refuses the same text.

A number is plain decimal ASCII: an optional sign, digits with an optional decimal point,
an optional exponent (``2``, ``-0.5``, ``.5``, ``5.``, ``1e-3``, ``2.5E+2``), or ``nan``,
``inf``, ``infinity`` in any case (optionally signed). Blanks around it are ignored; a
cell that is blank (or null) is a missing value, NaN. Anything else is refused, and in
particular what Python's ``float()`` and ``int()`` would read as some other number:
digit separators (``float("1_5")`` is 15.0, ``float("0_5")`` 5.0), digits of other
scripts (``٣``), superscripts (``²``, which ``str.isdigit`` accepts), hexadecimal,
thousands separators and decimal commas. A whole number (a run index, a count) is
ASCII digits only.

Numeric columns (integer, floating point, decimal) are taken as they are; a text
column is parsed cell by cell (vectorised, with Arrow's compute functions).
"""

from __future__ import annotations

import decimal
import math
import numbers
import re
from collections.abc import Iterable

import numpy as np

from armfit._lazy import loaded
from armfit.errors import BadInputError, cell
from armfit.io.arrow import arrow_numbers

#: A number as text (after its surrounding blanks are removed), case-insensitive.
NUMBER_PATTERN = (r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
                  r"|[+-]?(?:[nN][aA][nN]|[iI][nN][fF](?:[iI][nN][iI][tT][yY])?)")
#: A whole number as text: ASCII digits only.
WHOLE_PATTERN = r"[0-9]+"

_NUMBER = re.compile(NUMBER_PATTERN)
_WHOLE = re.compile(WHOLE_PATTERN)
# str.strip() would also remove blanks of other scripts; a cell's blanks are ASCII
_BLANKS = " \t\r\n\f\v"


def _hint(text: str) -> str:
    """Why a text that Python would read as a number is not one."""
    if "_" in text:
        return " (digit separators such as '_' are not read: write the plain number)"
    if any(ch.isdigit() and not ch.isascii() for ch in text):
        return " (only the digits 0-9 are read)"
    return ""


def parse_number(value) -> float:
    """One number: a text (see the module's rules) or a number (not a bool).

    Parameters
    ----------
    value : str or int or float
        The text of one cell, or a number already typed (e.g. a JSON number).

    Returns
    -------
    float
        The number (NaN, ±inf as written).

    Raises
    ------
    ValueError
        A blank text, a bool, or anything that is not a number by the module's rules;
        the message quotes the value and says why Python's own reading is refused.
    """
    if isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)):
        return float(value)
    if isinstance(value, str):
        text = value.strip(_BLANKS)
        if _NUMBER.fullmatch(text):
            return float(text)
        raise ValueError(f"{cell(value)} is not a number{_hint(text)}")
    raise ValueError(f"{cell(value)} is not a number")


def parse_whole(value) -> int:
    """One whole number ≥ 0: ASCII digits, or an integer already typed (not a bool).

    Parameters
    ----------
    value : str or int
        The text of one cell or name part, or an integer (e.g. a JSON number).

    Returns
    -------
    int

    Raises
    ------
    ValueError
        Anything else: a sign, a decimal point, a digit separator, a superscript or
        another script's digit, a bool, a negative integer.
    """
    if isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)):
        if value >= 0:
            return int(value)
    elif isinstance(value, str):
        text = value.strip(_BLANKS)
        if _WHOLE.fullmatch(text):
            return int(text)
        raise ValueError(f"{cell(value)} is not a whole number{_hint(text)}")
    raise ValueError(f"{cell(value)} is not a whole number")


def _arrow(values):
    """``values`` as one pyarrow Array (a column of a table, a pandas Series or a sequence
    of cells), or as a float64 numpy array if they are numbers already (an integer or
    float numpy array, or a sequence of Python numbers): ``pyarrow.array`` imports pandas
    (a third of a second), which a command reading one number of a file's metadata does
    not otherwise need."""
    import pyarrow as pa
    if isinstance(values, pa.ChunkedArray):
        return values.combine_chunks() if values.num_chunks != 1 else values.chunk(0)
    if isinstance(values, pa.Array):
        return values
    pd = loaded("pandas")   # not imported (or half, by another thread): no pandas object
    if pd is not None and isinstance(values, pd.Series | pd.Index):
        if pd.api.types.is_numeric_dtype(values.dtype) \
                and not pd.api.types.is_bool_dtype(values.dtype):
            return np.array(values.to_numpy(dtype=np.float64, na_value=np.nan))
        values = values.to_numpy(dtype=object)
    arr = np.asarray(values) if not isinstance(values, np.ndarray) else values
    if arr.dtype.kind in "iuf":
        return arr.astype(np.float64)
    cells = [None if _missing(v) else v if isinstance(v, str) else _as_text(v)
             for v in (arr.tolist() if arr.dtype != object else arr)]
    return pa.array(cells, type=pa.large_string())


def _missing(v) -> bool:
    if v is None:
        return True
    if isinstance(v, float):
        return math.isnan(v)
    # pandas's missing values exist only once pandas is imported: not imported here for
    # them (a third of a second)
    pd = loaded("pandas")
    return pd is not None and (v is pd.NA or v is pd.NaT)


def _as_text(v) -> str:
    """A non-text cell of a text column as the text it stands for: a number as its
    shortest form, anything else (a bool, a date) as a text no number matches."""
    if isinstance(v, decimal.Decimal):
        return str(v)
    if isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)):
        return repr(float(v))
    return f"\0{v}"


def _parse_text(arr, raise_at):
    """(float64 values, bad mask) of a text column; ``raise_at(index, text)`` is called
    at the first bad cell when given.

    Arrow's conversion of text to float64 reads exactly the texts :data:`NUMBER_PATTERN`
    matches (tests/test_faults_readers.py checks it on every short text of digits,
    signs, points, exponents, separators and the letters of nan/infinity), so a column
    of numbers is converted in one call; the pattern finds the cell that is not one.
    """
    import pyarrow as pa
    import pyarrow.compute as pc
    if pa.types.is_dictionary(arr.type):
        arr = arr.dictionary_decode()
    trimmed = pc.utf8_trim(arr, characters=_BLANKS)
    blank = pc.fill_null(pc.equal(trimmed, ""), True)
    cells = pc.if_else(blank, pa.scalar(None, trimmed.type), trimmed)
    try:
        out = pc.cast(cells, pa.float64())
        return (np.asarray(out.to_numpy(zero_copy_only=False), dtype=np.float64),
                np.zeros(len(arr), bool))
    except pa.ArrowInvalid:
        pass
    ok = pc.fill_null(pc.match_substring_regex(cells, f"^(?:{NUMBER_PATTERN})$"), True)
    bad = ~np.asarray(ok.to_numpy(zero_copy_only=False), dtype=bool)
    if raise_at is not None and bad.any():
        i = int(np.argmax(bad))
        raise_at(i, arr[i].as_py())
    good = pc.if_else(pa.array(bad), pa.scalar(None, cells.type), cells)
    out = pc.cast(good, pa.float64()).to_numpy(zero_copy_only=False)
    return np.asarray(out, dtype=np.float64), bad


def parse_numbers(values, *, file: str | None = None, column: str | None = None,
                  first_row: int = 1, errors: str = "raise", hint: str = "") -> np.ndarray:
    """A column of numbers as float64, blank (or null) cells as NaN.

    Parameters
    ----------
    values : pyarrow.Array or pyarrow.ChunkedArray or pandas.Series or array_like
        The column: numbers (integer, floating point or decimal) are taken as they are;
        text is parsed by the module's rules.
    file, column : str, optional
        Where the column comes from, for the message.
    first_row : int
        The row number of the first value (1: the first data row).
    errors : {"raise", "coerce"}
        "raise": refuse the first cell that is not a number; "coerce": make it NaN (for
        a reader that names the bad cell in its own words).
    hint : str
        Appended to the message (e.g. what a missing value looks like).

    Returns
    -------
    numpy.ndarray
        float64, one value per cell.

    Raises
    ------
    BadInputError
        With ``errors="raise"``, naming the file, column and row of the first cell that is
        not a number (a bool, a date, or text such as ``n/a`` or ``1_5``).
    """
    import pyarrow as pa
    if errors not in ("raise", "coerce"):
        raise ValueError(f"errors must be 'raise' or 'coerce', got {errors!r}")
    arr = _arrow(values)
    if isinstance(arr, np.ndarray):
        return arr
    t = arr.type

    def raise_at(i: int, v) -> None:
        text = v if isinstance(v, str) else str(v)
        typed = "" if pa.types.is_string(t) or pa.types.is_large_string(t) \
            or pa.types.is_dictionary(t) or t == pa.null() else f" (column type {t})"
        shown = text[1:] if text.startswith("\0") else text
        raise BadInputError(f"non-numeric value {cell(shown)}{typed}; expected a number"
                            f"{_hint(text)}{hint}", file=file, column=column,
                            row=first_row + i)

    if pa.types.is_floating(t) or pa.types.is_integer(t):
        return arrow_numbers(arr)
    if pa.types.is_decimal(t):   # through its text: the nearest float64, as written
        return np.asarray(arr.cast(pa.string()).cast(pa.float64())
                          .to_numpy(zero_copy_only=False), dtype=np.float64)
    if t == pa.null():
        return np.full(len(arr), np.nan)
    if pa.types.is_string(t) or pa.types.is_large_string(t) or (
            pa.types.is_dictionary(t) and (pa.types.is_string(t.value_type)
                                           or pa.types.is_large_string(t.value_type))):
        return _parse_text(arr, raise_at if errors == "raise" else None)[0]
    # bool, dates, binary, nested: no cell is a number; nulls are missing values
    valid = np.asarray(arr.is_valid().to_numpy(zero_copy_only=False), dtype=bool)
    if errors == "raise" and valid.any():
        i = int(np.argmax(valid))
        raise_at(i, str(arr[i].as_py()))
    return np.full(len(arr), np.nan)


def parse_columns(df, columns: Iterable[str], *, file: str | None = None):
    """A table with its numeric columns held as numbers.

    Parameters
    ----------
    df : pandas.DataFrame
        A table as read (e.g. by ``pandas.read_csv``, which leaves a column holding a
        cell such as ``1_5`` or ``n/a`` as text).
    columns : iterable of str
        The columns that hold numbers; those absent are left out.
    file : str, optional
        The file, for the message.

    Returns
    -------
    pandas.DataFrame
        ``df`` itself when every such column is numeric already; else a copy with each
        text column read by :func:`parse_numbers` (float64, blank cells NaN).

    Raises
    ------
    BadInputError
        Naming the file, column and row of the first cell that is not a number.
    """
    import pandas as pd
    out = {}
    for c in columns:
        if c not in df.columns:
            continue
        dtype = df[c].dtype
        if pd.api.types.is_numeric_dtype(dtype) and not pd.api.types.is_bool_dtype(dtype):
            continue
        out[c] = parse_numbers(df[c], file=file, column=c)
    if not out:
        return df
    df = df.copy()
    for c, v in out.items():
        df[c] = v
    return df


__all__ = [
    "NUMBER_PATTERN", "WHOLE_PATTERN", "parse_number", "parse_whole", "parse_numbers",
    "parse_columns",
]
