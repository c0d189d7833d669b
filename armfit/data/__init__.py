"""The paper's tables (Fu & Çavuşoğlu 2010, Tables I–IV) as reference data."""

from __future__ import annotations

import csv
import functools
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

#: The folder of the data files: this package's own (installed as files, as pip installs
#: it). Not ``importlib.resources``, whose import (with ``tempfile``) cost every process
#: that loads the fits, the diagnosis's fork server among them, about 6 ms.
_FOLDER = Path(__file__).parent

TABLES = {
    "grip": "table1_grip_dependent.csv",
    "nominal": "table2_nominal.csv",
    "uncertainty": "table3_uncertainty_weights.csv",
    "literature": "table4_literature.csv",
}


def paper_file(name: str) -> Path:
    """The file of one of the paper's tables (a name of :data:`TABLES`): every reader of
    the shipped tables opens it from here."""
    return _FOLDER / TABLES[name]


def paper_table(name: str) -> pd.DataFrame:
    """Return one of the paper's tables: 'grip' (I), 'nominal' (II), 'uncertainty' (III),
    'literature' (IV), as printed (SI units)."""
    import pandas as pd
    with paper_file(name).open() as fh:
        return pd.read_csv(fh)


def paper_values(name: str, columns: Sequence[str]) -> np.ndarray:
    """Columns of one of the paper's tables (:func:`paper_table`'s names) as float64,
    shape (rows, len(columns)), in the file's row order: the numbers
    ``paper_table(name)[columns].to_numpy(float)`` gives (an empty cell is NaN), read
    without pandas (the fits' worker processes need the numbers only)."""
    with paper_file(name).open(newline="") as fh:
        header, *rows = list(csv.reader(fh))
    idx = [header.index(c) for c in columns]
    return np.array([[float(row[i]) if row[i].strip() else np.nan for i in idx]
                     for row in rows if row],
                    dtype=float).reshape(-1, len(idx))


#: Sobol direction numbers (Joe & Kuo 2008) of the first dimensions and bits: see the file.
SOBOL_DIRECTIONS = "sobol_directions.csv"


@functools.lru_cache(maxsize=1)
def _sobol_directions() -> np.ndarray:
    with _FOLDER.joinpath(SOBOL_DIRECTIONS).open() as fh:
        m = np.loadtxt(fh, delimiter=",", comments="#", dtype=np.int64, ndmin=2)
    m.setflags(write=False)
    return m


def sobol_points(n: int, d: int) -> np.ndarray | None:
    """The first ``n`` points of the unscrambled d-dimensional Sobol sequence in [0, 1),
    in the order ``scipy.stats.qmc.Sobol(d, scramble=False).random(n)`` gives them (Gray
    code order, 30-bit points), from the direction numbers of :data:`SOBOL_DIRECTIONS`.

    Parameters
    ----------
    n : int
        Points, at most 2^(bits in the file).
    d : int
        Dimensions, at most the file's rows.

    Returns
    -------
    ndarray, shape (n, d), or None
        None when the file holds too few dimensions or bits (use scipy then).
    """
    m = _sobol_directions()
    bits = max(1, int(n - 1).bit_length())
    if d > m.shape[0] or bits > m.shape[1]:
        return None
    v = m[:d, :bits] << (29 - np.arange(bits))                 # direction integers
    k = np.arange(n)
    gray = k ^ (k >> 1)
    on = ((gray[:, None] >> np.arange(bits)) & 1).astype(bool)  # (n, bits)
    x = np.bitwise_xor.reduce(np.where(on[:, None, :], v[None], 0), axis=2)
    return x / float(1 << 30)


__all__ = [
    "TABLES", "paper_file", "paper_table", "paper_values", "SOBOL_DIRECTIONS", "sobol_points",
]
