"""Writers of armfit's CSV outputs (fitted parameters, uncertainty weights, their
summaries) and the reader of the Wu layout.

The columns are those of :mod:`armfit.io.schema`. Readers validate and raise
BadInputError naming the file, column and row. The spectra table (Parquet) is read and
written by :class:`armfit.spectra.Spectra` alone; a params file is read by
:func:`armfit.models.params.read_params`, which checks it against the models.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from armfit.constants import AXES
from armfit.errors import BadInputError, NoInputError, cell
from armfit.io.atomic import atomic_path
from armfit.io.numbers import parse_numbers
from armfit.io.ranges import WU_GAIN_RANGE, WU_ROOT_RANGE, check_in_range
from armfit.io.schema import (
    CSV_FLOAT_FORMAT,
    PARAMS_HELD,
    WU_COLUMNS,
    params_columns,
)

if TYPE_CHECKING:
    import pandas as pd

# ---------------------------------------------------------------------------
# Fitted parameters (written by `armfit fit-grip` / `fit-nominal`)
# ---------------------------------------------------------------------------


def params_rows(rows: Iterable[Mapping], param_names, *, grip: bool) -> RowTable:
    """A params table from row dicts (one per fit), columns in file order
    (:func:`armfit.io.schema.params_columns`; the ``held`` column only when a row holds
    parameters); :meth:`RowTable.to_frame` makes its DataFrame."""
    rows = list(rows)
    held = any(r.get(PARAMS_HELD) for r in rows)
    return RowTable(tuple(rows), tuple(params_columns(param_names, grip=grip, held=held)))


@dataclass(frozen=True)
class RowTable:
    """A table as row dicts and its columns: what ``pandas.DataFrame(rows,
    columns=columns)`` would hold (a key a row lacks is a missing value), written as CSV
    without pandas.

    pandas takes a third of a second to import; a command that fits one spectra file
    and writes its parameters needs no more of it than this.
    """

    rows: tuple[Mapping, ...]
    columns: tuple[str, ...]

    def to_frame(self) -> pd.DataFrame:
        """The DataFrame of these rows."""
        import pandas as pd
        return pd.DataFrame(list(self.rows), columns=list(self.columns))

    def csv_text(self) -> str | None:
        """The CSV that ``to_frame().to_csv(index=False, float_format="%.10g")`` writes,
        or None for a column pandas would hold as objects other than text (then the
        caller writes the DataFrame): each column typed as pandas types it (all bool:
        True/False; all whole numbers: as written; numbers with missing values or
        fractions: 10 significant digits, a missing value empty; text: as is, a missing
        value empty), quoted as the csv module quotes minimally."""
        import csv
        import io
        cells = []
        for col in self.columns:
            fmt = _column_format([r.get(col) for r in self.rows])
            if fmt is None:
                return None
            cells.append(fmt)
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(self.columns)
        writer.writerows(zip(*cells, strict=True) if cells else ())
        return out.getvalue()


def _column_format(values: list) -> list[str] | None:
    """The CSV cells of one column as pandas would write them (see
    :meth:`RowTable.csv_text`), or None when pandas would hold it as non-text objects."""
    missing = [v is None or (isinstance(v, float | np.floating) and v != v) for v in values]
    if all(isinstance(v, bool | np.bool_) for v in values):
        return ["True" if v else "False" for v in values]
    numbers = [isinstance(v, int | float | np.integer | np.floating)
               and not isinstance(v, bool | np.bool_) for v in values]
    if all(n or m for n, m in zip(numbers, missing, strict=True)):
        if all(isinstance(v, int | np.integer) for v in values):
            return [str(int(v)) for v in values]
        return ["" if m else CSV_FLOAT_FORMAT % float(v)
                for v, m in zip(values, missing, strict=True)]
    if all(isinstance(v, str) or m for v, m in zip(values, missing, strict=True)):
        return ["" if m else v for v, m in zip(values, missing, strict=True)]
    return None


def write_table(df: pd.DataFrame | RowTable, path: str | os.PathLike, *, overwrite: bool = False
                ) -> str | os.PathLike:
    """Write a DataFrame as CSV atomically (10 significant digits, no index).

    Parameters
    ----------
    df : pandas.DataFrame or RowTable
        The table (a params, Wu, summary or W_max table); a :class:`RowTable` is written
        without pandas where :meth:`RowTable.csv_text` can, the same bytes.
    path : str or os.PathLike
        Destination.
    overwrite : bool
        Replace an existing file.

    Returns
    -------
    str or os.PathLike
        ``path``.

    Raises
    ------
    OutputError
        ``path`` exists and not ``overwrite``.
    """
    text = None
    if isinstance(df, RowTable):   # written without pandas where it can be
        text = df.csv_text()
        if text is None:
            df = df.to_frame()
    with atomic_path(path, overwrite=overwrite) as tmp:
        if text is None:
            df.to_csv(tmp, index=False, float_format=CSV_FLOAT_FORMAT)
        else:
            Path(tmp).write_text(text, encoding="utf-8")
    return path


#: A params file and a Wu summary or points table are written alike.
write_params = write_table
write_wu_table = write_table


# ---------------------------------------------------------------------------
# Uncertainty weights (written by `armfit fit-uncertainty`): the layout of Table III
# ---------------------------------------------------------------------------

#: One weight as read from a Wu file: (gain K, zero pairs, pole pairs), pairs complex
#: rad/s with imaginary part >= 0 (see :class:`armfit.uncertainty.WuWeight`).
WuRows = tuple[float, np.ndarray, np.ndarray]


def wu_frame(weights: Mapping) -> pd.DataFrame:
    """A Wu DataFrame (:data:`armfit.io.schema.WU_COLUMNS`) from {axis: weight}, axes in
    x, y, z order; a weight is anything with ``gain``, ``zeros`` and ``poles``."""
    rows = []
    for axis in sorted(weights):
        w = weights[axis]
        rows.append((axis, "gain", 0, float(w.gain), 0.0))
        for kind, reps in (("zero", w.zeros), ("pole", w.poles)):
            for i, r in enumerate(reps, start=1):
                rows.append((axis, kind, i, float(r.real), float(abs(r.imag))))
    import pandas as pd
    return pd.DataFrame(rows, columns=list(WU_COLUMNS))


def write_wu(weights: Mapping, path: str | os.PathLike, *, overwrite: bool = False):
    """Write {axis: weight} as a Wu CSV atomically (10 significant digits). Returns path.

    Raises OutputError (exit 73) if ``path`` exists and not ``overwrite``.
    """
    return write_table(wu_frame(weights), path, overwrite=overwrite)


def read_wu_rows(path: str | os.PathLike, *, require_stable: bool = True
                 ) -> dict[str, WuRows]:
    """Read a Wu CSV (the layout of the paper's Table III).

    Parameters
    ----------
    path : str or os.PathLike
        The CSV: columns axis, kind, index, real, imag.
    require_stable : bool
        Refuse a pole or zero with a real part >= 0 (an unstable or non-minimum-phase
        weight; eq. 7 allows neither), naming its row.

    Returns
    -------
    dict
        {axis: (K, zero pairs, pole pairs)}, pairs as complex rad/s ordered by index.

    Raises
    ------
    NoInputError
        The file is missing.
    BadInputError
        Naming the file, column and row (1-based data row) of anything that breaks the
        layout: a missing column, an axis other than x/y/z, a kind other than
        gain/zero/pole, a non-numeric or non-finite value, an axis without exactly one
        gain, two zero (or pole) rows of one index, a gain or a root magnitude outside
        its physical range (:mod:`armfit.io.ranges`), or more zero pairs than pole
        pairs (an improper weight).
    """
    p = Path(path)
    if not p.is_file():
        raise NoInputError(f"{p}: no such uncertainty-weights file")
    import pandas as pd
    try:
        df = pd.read_csv(p, dtype=str, keep_default_na=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
        raise BadInputError(f"not a weights CSV ({str(exc).splitlines()[0]})",
                            file=str(p)) from None
    for col in WU_COLUMNS:
        if col not in df.columns:
            raise BadInputError("missing column; expected axis,kind,index,real,imag "
                                "(the layout of the paper's Table III)", file=str(p),
                                column=col)
    if df.empty:
        raise BadInputError("no rows; expected a gain row and zero/pole rows per axis",
                            file=str(p))
    axis = df["axis"].str.strip().str.lower()
    kind = df["kind"].str.strip().str.lower()
    for col, values, allowed in (("axis", axis, AXES),
                                 ("kind", kind, ("gain", "zero", "pole"))):
        bad = np.flatnonzero(~values.isin(allowed).to_numpy())
        if bad.size:
            raise BadInputError(f"expected one of {', '.join(allowed)}, got "
                                f"{cell(df[col].iloc[bad[0]])}", file=str(p), column=col,
                                row=int(bad[0]) + 1)
    nums = {}
    for col in ("index", "real", "imag"):
        v = parse_numbers(df[col].str.strip().replace("", "0" if col == "imag" else "nan"),
                          errors="coerce")
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise BadInputError(f"expected a finite number, got {cell(df[col].iloc[bad[0]])}",
                                file=str(p), column=col, row=int(bad[0]) + 1)
        nums[col] = v
    out = {}
    kinds = kind.to_numpy()
    for ax in AXES:
        rows = np.flatnonzero(axis.to_numpy() == ax)
        if rows.size == 0:
            continue
        gains = rows[kinds[rows] == "gain"]
        if gains.size != 1:
            where = "" if gains.size < 2 else f" (rows {gains[0] + 1} and {gains[1] + 1})"
            raise BadInputError(f"axis {ax} has {gains.size} gain rows{where}; expected one",
                                file=str(p), column="kind",
                                row=int(gains[1] if gains.size > 1 else rows[0]) + 1)
        check_in_range(nums["real"][gains], WU_GAIN_RANGE, file=str(p), column="real",
                       rows=gains + 1)
        _check_pairs(p, ax, rows, kinds, nums, require_stable)
        reps = {}
        for k in ("zero", "pole"):
            r = rows[kinds[rows] == k]
            r = r[np.argsort(nums["index"][r], kind="stable")]
            reps[k] = nums["real"][r] + 1j * np.abs(nums["imag"][r])
        out[ax] = (float(nums["real"][gains[0]]), reps["zero"], reps["pole"])
    return out


def _check_pairs(p: Path, ax: str, rows: np.ndarray, kinds: np.ndarray,
                 nums: Mapping[str, np.ndarray], require_stable: bool) -> None:
    """The zero and pole rows of one axis of a Wu file: each root's magnitude inside its
    physical range, in the open left half plane (when ``require_stable``), one row per
    index, and no more zero pairs than pole pairs (a proper weight)."""
    zeros, poles = rows[kinds[rows] == "zero"], rows[kinds[rows] == "pole"]
    for k, r in (("zero", zeros), ("pole", poles)):
        check_in_range(np.hypot(nums["real"][r], nums["imag"][r]), WU_ROOT_RANGE,
                       file=str(p), column="real", rows=r + 1,
                       name=f"|{k}| of Wu of axis {ax}")
    for r, what in ((poles, "unstable: a pole"), (zeros, "not minimum phase: a zero")):
        bad = r[nums["real"][r] >= 0]
        if require_stable and bad.size:
            i = int(bad[0])
            raise BadInputError(
                f"Wu of axis {ax} is {what} at {cell(nums['real'][i])} ± "
                f"{cell(abs(nums['imag'][i]))}j rad/s is not in the open left half plane; "
                "an uncertainty weight must be stable and minimum phase",
                file=str(p), column="real", row=i + 1)
    for k, r in (("zero", zeros), ("pole", poles)):
        seen: dict[float, int] = {}
        for i in r:
            j = nums["index"][i]
            if j in seen:
                raise BadInputError(f"axis {ax} has a second {k} of index {j:g} (rows "
                                    f"{seen[j] + 1} and {i + 1}); each {k} pair is one row",
                                    file=str(p), column="index", row=int(i) + 1)
            seen[j] = int(i)
    if zeros.size > poles.size:
        raise BadInputError(f"Wu of axis {ax} has {zeros.size} zero pairs and {poles.size} "
                            "pole pairs: improper (|Wu| grows without bound with frequency); "
                            "an uncertainty weight has at most as many zeros as poles",
                            file=str(p), column="kind", row=int(zeros[poles.size]) + 1)


__all__ = [
    "params_rows", "RowTable", "write_table", "write_params",
    "write_wu_table", "WuRows",
    "wu_frame", "write_wu", "read_wu_rows",
]
