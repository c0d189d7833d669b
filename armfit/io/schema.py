"""Schemas of armfit's own output files: the spectra table (Parquet), fitted parameters
(CSV), uncertainty weights (CSV) with their summary and W_max tables, and compare.csv.

Column names and their order are defined here once; readers and writers elsewhere
(:class:`armfit.spectra.Spectra`, :mod:`armfit.io.artifacts`) use these names. The
meaning and units of every column are documented in docs/formats.md.
"""

from __future__ import annotations

import math
from pathlib import Path

from armfit.constants import PARAM_NAMES

# ---------------------------------------------------------------------------
# Spectra (written by `armfit estimate`): one long-format Parquet table.
# ---------------------------------------------------------------------------

#: Columns of the spectra table, in order.
SPECTRA_COLUMNS: tuple[str, ...] = (
    "level",      # "trial" | "mean" | "median"
    "subject",    # subject label (null for aggregates)
    "axis",       # stimulated axis "x" | "y" | "z"
    "grip_N",     # target grip force, N (NaN at level "median": all grips pooled)
    "run",        # repeat index (nullable Int64)
    "kind",       # "measured" (X/F), "derived" (Xa/Fa, device removed), "cross", and at
                  # level "trial" "alternative" (X/F by the other estimators: H2, H1)
    "out_axis",   # position axis of the response (== axis except for kind "cross")
    "method",     # estimator name: "h1", "chebwin", "ref" (through the reference column),
                  # "tfestimate", "tfestimate-ref", "h2"; "h1+ref" for an aggregate of both
    "freq_hz",    # frequency, Hz
    "re", "im",   # complex response, m/N
    "mag_db",     # 20 log10 |H| with H in m/N
    "phase_deg",  # phase, deg (unwrapped along frequency)
    "coherence",  # magnitude-squared coherence 0..1 (NaN where not defined)
    "se_db",      # standard error of mag_db, dB
    "se_deg",     # standard error of phase_deg, deg
    "n",          # number of trials behind the value (1 at level "trial")
    "q25_db", "q75_db", "q25_deg", "q75_deg",  # quartiles across trials (aggregates)
    "flags",      # comma-separated: low_coherence, saturation, drift, no_signal,
                  # not_excitation (empty if none); not_excitation: the force is not a
                  # clean excitation there and H1 is biased beyond its noise (see
                  # docs/methods.md); no_signal: the cell carries no information (no force or no
                  # position power there, e.g. an unstimulated axis recorded as constant
                  # zero): re, im, mag_db, phase_deg, coherence, se_* are NaN, never ±inf,
                  # and aggregates leave the cell out (NaN and no_signal if no trial has it)
)

#: The columns that name one response (one curve along frequency), in file order.
SPECTRA_KEYS: tuple[str, ...] = ("level", "subject", "axis", "grip_N", "run", "kind",
                                 "out_axis", "method")

#: Real-valued columns held per response and frequency (besides re, im and flags).
SPECTRA_VALUES: tuple[str, ...] = ("mag_db", "phase_deg", "coherence", "se_db", "se_deg",
                                   "q25_db", "q75_db", "q25_deg", "q75_deg")

#: Columns held as text in the spectra table.
SPECTRA_TEXT: tuple[str, ...] = ("level", "subject", "axis", "kind", "out_axis", "method",
                                 "flags")

#: Flags a grid point can carry, in the order they are written.
FLAGS: tuple[str, ...] = ("low_coherence", "saturation", "drift", "no_signal",
                          "not_excitation")

#: The flags ``armfit estimate --json`` counts over the trial rows.
COUNTED_FLAGS: tuple[str, ...] = ("low_coherence", "saturation", "drift", "not_excitation")

#: Key of armfit's metadata (JSON) in the Parquet file's key-value metadata.
SPECTRA_META_KEY = b"armfit"

#: Key of the metadata's per-trial records (``estimators``, a list) in the Parquet file's
#: key-value metadata: their JSON compressed by zlib, in base64 (:func:`pack_records`).
#: Apart, so that a read that does not keep them never unpacks them; compressed, because
#: every open of the file holds the footer's text several times over (on 4,050
#: trials the JSON is 1.2 MB, 81 kB packed). Files written before hold the JSON as
#: it is under :data:`SPECTRA_ESTIMATORS_JSON_KEY`, or inside :data:`SPECTRA_META_KEY`'s.
SPECTRA_ESTIMATORS_KEY = b"armfit.estimators.zlib"

#: Key of the per-trial records as JSON text, in files written before they were
#: compressed (read, never written).
SPECTRA_ESTIMATORS_JSON_KEY = b"armfit.estimators"


def pack_records(text: bytes) -> bytes:
    """The value stored under :data:`SPECTRA_ESTIMATORS_KEY`: ``text`` (JSON, UTF-8)
    compressed by zlib (level 6), in base64 (ASCII, as text other readers of the footer
    can show)."""
    import base64
    import zlib
    return base64.b64encode(zlib.compress(text, 6))


def unpack_records(value: bytes) -> bytes:
    """The JSON text of a value written by :func:`pack_records`.

    Raises
    ------
    ValueError
        The value is not such a value (binascii.Error and zlib.error are ValueErrors
        here).
    """
    import base64
    import binascii
    import zlib
    try:
        return zlib.decompress(base64.b64decode(value, validate=True))
    except (binascii.Error, zlib.error) as exc:
        raise ValueError(str(exc)) from exc

# ---------------------------------------------------------------------------
# Fitted parameters (written by `armfit fit-grip` / `fit-nominal`): CSV.
# ---------------------------------------------------------------------------

#: Base arm parameters of a params file, in the paper's order (SI: kg, N/m, N*s/m).
PARAMS_BASE: tuple[str, ...] = PARAM_NAMES
#: Fit statistics closing every params row, in order.
PARAMS_STATS: tuple[str, ...] = ("rms_db", "rms_deg", "rms_norm", "band_lo_hz", "band_hi_hz",
                                 "n_points", "cost", "converged", "mp_kg", "effects",
                                 "at_bound")
#: Columns of :data:`PARAMS_STATS` that files written by older versions may lack, with the
#: value they take when read.
PARAMS_OPTIONAL: dict[str, str] = {"at_bound": ""}


#: Column closing a params row when some parameters were held fixed (only then written):
#: the ``effect.param`` names held, ";"-separated.
PARAMS_HELD = "held"


def params_columns(param_names, *, grip: bool, held: bool = False) -> list[str]:
    """Columns of a params file, in order.

    Parameters
    ----------
    param_names : sequence of str
        The model's parameters: the base names, then ``<effect>.<param>``.
    grip : bool
        True for grip-dependent fits (a ``grip_N`` column after ``axis``).
    held : bool
        True when some rows hold parameters fixed (a last column :data:`PARAMS_HELD`).

    Returns
    -------
    list of str
        ``axis``, ``grip_N`` (grip fits only), the parameters, ``<p>_lo, <p>_hi`` for
        each (95 % interval), then :data:`PARAMS_STATS` (and ``held``).
    """
    names = list(param_names)
    cols = ["axis"] + (["grip_N"] if grip else []) + names
    for n in names:
        cols += [f"{n}_lo", f"{n}_hi"]
    return cols + list(PARAMS_STATS) + ([PARAMS_HELD] if held else [])


# ---------------------------------------------------------------------------
# Uncertainty weights (written by `armfit fit-uncertainty`): CSV in the layout of the
# paper's Table III, plus a per-axis summary CSV and a W_max points CSV beside it.
# ---------------------------------------------------------------------------

#: Columns of a Wu file, in order. kind: "gain" (index 0, K in `real`), "zero", "pole"
#: (index 1..n; each row the conjugate pair real ± j·imag, rad/s; imag 0 is a double root).
WU_COLUMNS: tuple[str, ...] = ("axis", "kind", "index", "real", "imag")

#: Columns of the summary written beside a Wu file (``<stem>_summary.csv``), in order.
WU_SUMMARY_COLUMNS: tuple[str, ...] = (
    "axis", "weight", "target", "cost", "order", "n_trials", "smooth_oct",
    "band_lo_hz", "band_hi_hz", "n_points", "coverage_pct", "coverage_between_pct",
    "tightness_median_db", "tightness_max_db", "tightness_min_db", "mean_gap_db",
    "converged",
)

#: Columns of the W_max points written beside a Wu file (``<stem>_wmax.csv``), in order.
WU_POINTS_COLUMNS: tuple[str, ...] = ("axis", "freq_hz", "wmax_db", "target_db", "wu_db",
                                      "in_band")


def wu_sidecar_paths(path) -> tuple[Path, Path]:
    """The summary and W_max files written beside the Wu file ``path``.

    Parameters
    ----------
    path : str or os.PathLike
        The Wu CSV.

    Returns
    -------
    (Path, Path)
        ``<stem>_summary.csv`` and ``<stem>_wmax.csv`` in the same folder.
    """
    p = Path(path)
    stem = p.name[:-4] if p.name.lower().endswith(".csv") else p.name
    return p.with_name(f"{stem}_summary.csv"), p.with_name(f"{stem}_wmax.csv")


# ---------------------------------------------------------------------------
# compare.csv (written by `armfit run`)
# ---------------------------------------------------------------------------

#: Columns of compare.csv.
COMPARE_COLUMNS: tuple[str, ...] = ("axis", "grip", "level", "model", "band", "rms_db",
                                    "rms_deg", "rms_norm")

#: Float format of every CSV armfit writes (10 significant digits).
CSV_FLOAT_FORMAT = "%.10g"

# ---------------------------------------------------------------------------
# JSON documents (--json, diagnosis.json)
# ---------------------------------------------------------------------------


def json_default(o):
    """``json.dumps`` default: numpy scalars and arrays as Python numbers and lists."""
    import numpy as np
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def is_missing(v) -> bool:
    """Whether a table cell holds no value: None, NaN or pandas' NA."""
    if v is None:
        return True
    if isinstance(v, float):
        return math.isnan(v)
    import pandas as pd
    try:
        return bool(pd.isna(v))
    except (TypeError, ValueError):  # not a scalar
        return False


def finite_or_none(v):
    """A missing value (:func:`is_missing`) or an infinite float as None (JSON has
    neither NaN nor NA); anything else as is."""
    if is_missing(v) or (isinstance(v, float) and not math.isfinite(v)):
        return None
    return v


__all__ = [
    "SPECTRA_COLUMNS", "SPECTRA_KEYS", "SPECTRA_VALUES", "SPECTRA_TEXT", "FLAGS",
    "COUNTED_FLAGS", "SPECTRA_META_KEY", "SPECTRA_ESTIMATORS_KEY",
    "SPECTRA_ESTIMATORS_JSON_KEY", "pack_records", "unpack_records", "PARAMS_BASE",
    "PARAMS_STATS", "PARAMS_OPTIONAL", "PARAMS_HELD", "params_columns", "WU_COLUMNS",
    "WU_SUMMARY_COLUMNS", "WU_POINTS_COLUMNS", "wu_sidecar_paths", "COMPARE_COLUMNS",
    "CSV_FLOAT_FORMAT", "json_default", "is_missing", "finite_or_none",
]
