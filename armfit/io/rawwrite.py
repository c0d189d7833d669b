"""Write one trial as a raw trial file of the data contract (CSV, CSV.gz or Parquet).

The file is what a lab's logger would write: a header row and the columns ``time_s``,
``force_<a>_N``, ``pos_<a>_m`` (or ``pos_<a>_mm``) for each recorded axis a, and
``grip_N`` when a grip record exists; axes whose record is all NaN are left out. The
name is BIDS-style: ``sub-<label>_axis-<a>_grip-<g>N[_run-<k>].<ext>``.

Encodings: Parquet is zstd-compressed; columns with few distinct values (quantised
positions, held grip samples, constant forces) are dictionary-encoded and the others
byte-stream-split, which keeps quantised data small. CSV numbers are written with at most
9 decimals (1 nm, 1 nN, 1 ns; 6 decimals in mm), the shortest text that reads back to the
rounded value; CSV.gz uses gzip level 6.
"""

from __future__ import annotations

import os
from gzip import open as gzip_open
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from armfit._order import unique
from armfit.errors import UsageError
from armfit.io.atomic import atomic_path
from armfit.io.trials import AXES, Trial, TrialMeta

#: Raw formats this module writes, with their file-name endings.
RAW_FORMATS: dict[str, str] = {"parquet": ".parquet", "csv": ".csv", "csv.gz": ".csv.gz"}

#: Position units and the factor from metres.
POSITION_UNITS: dict[str, float] = {"m": 1.0, "mm": 1000.0}

#: Columns with at most this many distinct values are dictionary-encoded in Parquet.
_DICTIONARY_MAX_DISTINCT = 4096


def trial_filename(meta: TrialMeta, fmt: str = "parquet") -> str:
    """BIDS-style file name of a trial, e.g. ``sub-01_axis-x_grip-1N.parquet``."""
    _check_format(fmt)
    run = f"_run-{meta.run}" if meta.run is not None else ""
    return f"sub-{meta.subject}_axis-{meta.axis}_grip-{meta.grip_N:g}N{run}{RAW_FORMATS[fmt]}"


def trial_columns(trial: Trial, units: str = "m") -> dict[str, np.ndarray]:
    """The contract's columns of ``trial`` as float64 arrays, in file order.

    time_s (s) from ``meta.t0_s`` and ``meta.fs``; forces in N; positions in ``units``
    ('m' or 'mm'); grip in N. All-NaN axes and a missing grip record are left out.
    """
    if units not in POSITION_UNITS:
        raise UsageError(f"position units must be one of {', '.join(POSITION_UNITS)}, "
                         f"got {units!r}")
    meta = trial.meta
    cols = {"time_s": meta.t0_s + np.arange(meta.n_samples) / meta.fs}
    for j, a in enumerate(AXES):
        if not np.all(np.isnan(trial.force[:, j])):
            cols[f"force_{a}_N"] = trial.force[:, j]
    for j, a in enumerate(AXES):
        if not np.all(np.isnan(trial.pos[:, j])):
            cols[f"pos_{a}_{units}"] = trial.pos[:, j] * POSITION_UNITS[units]
    if trial.grip is not None:
        cols["grip_N"] = trial.grip
    return cols


def write_trial(trial: Trial, path: str | os.PathLike, *, fmt: str | None = None,
                units: str = "m", overwrite: bool = False) -> Path:
    """Write ``trial`` to ``path`` (atomically) in ``fmt`` (default: from the file name).

    Returns the path. Raises OutputError if it exists and ``overwrite`` is false.
    """
    path = Path(path)
    fmt = fmt or _format_of(path)
    _check_format(fmt)
    cols = trial_columns(trial, units)
    with atomic_path(path, overwrite=overwrite) as tmp:
        if fmt == "parquet":
            _write_parquet(cols, tmp)
        else:
            _write_csv(cols, tmp, gzip=(fmt == "csv.gz"), units=units)
    return path


def _write_parquet(cols: dict[str, np.ndarray], path: Path) -> None:
    few = [k for k, v in cols.items() if unique(v).size <= _DICTIONARY_MAX_DISTINCT]
    many = [k for k in cols if k not in few]
    pq.write_table(pa.table(cols), path, compression="zstd", compression_level=9,
                   use_dictionary=few, use_byte_stream_split=many or False)


def _write_csv(cols: dict[str, np.ndarray], path: Path, *, gzip: bool, units: str) -> None:
    decimals = {k: (6 if k.endswith("_mm") else 9) for k in cols}
    table = pa.table({k: np.round(v, decimals[k]) for k, v in cols.items()})
    header = (",".join(cols) + "\n").encode()
    sink = gzip_open(path, "wb", compresslevel=6) if gzip else open(path, "wb")
    with sink:
        sink.write(header)
        pacsv.write_csv(table, sink, pacsv.WriteOptions(include_header=False))


def _format_of(path: Path) -> str:
    name = path.name.lower()
    for fmt, ext in sorted(RAW_FORMATS.items(), key=lambda kv: -len(kv[1])):
        if name.endswith(ext):
            return fmt
    raise UsageError(f"{path}: cannot tell the format from the name; end it in "
                     f"{', '.join(RAW_FORMATS.values())}")


def _check_format(fmt: str) -> None:
    if fmt not in RAW_FORMATS:
        raise UsageError(f"format must be one of {', '.join(RAW_FORMATS)}, got {fmt!r}")


__all__ = [
    "RAW_FORMATS", "POSITION_UNITS", "trial_filename", "trial_columns", "write_trial",
]
