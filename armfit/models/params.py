"""Params files (written by fit-grip, fit-nominal, fit-trials and ``run``) read back into
models, and the paper's Tables I and II as params rows.

One reader, :func:`read_param_rows`, checks a params file against the models it
describes: the columns of the effects each row names, one row per model, and parameters,
device masses and grip forces that are numbers inside their physical ranges;
:func:`check_param_rows` applies the same checks to a table given to the Python API.
:func:`read_params` is that reader for a file of fits.
:func:`model_from_params` turns one row into the closed-loop model of eq. 4 and its
values.
"""

from __future__ import annotations

import csv
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from armfit.constants import AXES, DEVICE_MASS_KG
from armfit.data import paper_table
from armfit.errors import BadInputError, NoInputError, UsageError, cell
from armfit.io.numbers import parse_columns, parse_numbers
from armfit.io.ranges import (
    DEVICE_MASS_RANGE,
    GRIP_FORCE_RANGE,
    PhysicalRange,
    check_in_range,
)
from armfit.io.schema import (
    PARAMS_BASE,
    PARAMS_HELD,
    PARAMS_OPTIONAL,
    PARAMS_STATS,
    params_columns,
)
from armfit.models.arm import BASE_PARAMS, ClosedLoopModel, Param
from armfit.models.effects import get_effect

if TYPE_CHECKING:
    import pandas as pd

#: Names that stand for the paper's tables when no file of that name exists.
PAPER_PARAMS: dict[str, str] = {"nominal": "nominal", "table2": "nominal",
                                "grip": "grip", "table1": "grip"}

#: Fit statistics that are numbers (text in them is read by armfit.io.numbers).
_STAT_NUMBERS = ("rms_db", "rms_deg", "rms_norm", "band_lo_hz", "band_hi_hz", "n_points")

_PAPER_RENAME = {"Ma_kg": "Ma", "k1_N_per_m": "k1", "k2_N_per_m": "k2",
                 "b1_Ns_per_m": "b1", "b2_Ns_per_m": "b2"}


@dataclass(frozen=True)
class ParamRows:
    """Model rows of a parameters file: ``table`` (DataFrame with a 1-based ``row``
    column, the file's row number), ``skipped`` [(row, identity, reason)] of the rows
    without parameters, and ``label`` (file path, or the paper's table)."""

    table: pd.DataFrame
    skipped: tuple[tuple[int, str, str], ...]
    label: str


def paper_params(name: str) -> pd.DataFrame:
    """The paper's Table I ('grip') or II ('nominal') in the columns of a params file:
    axis[, grip_N], Ma..b2 (SI), mp_kg (eq. 2), effects ''."""
    table = paper_table(name).rename(columns=_PAPER_RENAME)
    table["mp_kg"] = table["axis"].map(DEVICE_MASS_KG)
    table["effects"] = ""
    table["converged"] = True
    return table


def read_param_rows(path_or_name: str | os.PathLike) -> ParamRows:
    """Read any params file armfit writes (fit-grip, fit-nominal, fit-trials, ``run``),
    or name one of the paper's tables, as one model per row: the one reader of params
    files, with every check.

    Parameters
    ----------
    path_or_name : str or os.PathLike
        The CSV, or ``nominal``/``table2``, ``grip``/``table1`` for the paper's Tables
        II and I (a file of that name wins).

    Returns
    -------
    ParamRows
        ``table``: one row per model with parameters (a 1-based ``row`` column first,
        the file's row; ``axis`` lower-case; parameters as float; ``effects``,
        ``at_bound`` and ``held`` as str; ``converged`` as bool). ``skipped``: the rows
        of a per-trial file whose fit failed (no parameters, not converged), with their
        reason. ``label``: the file, or the paper's table.

    Raises
    ------
    NoInputError
        The file is missing.
    BadInputError
        Naming the file, column and row: not a CSV, a missing column, an axis other than
        x, y or z, an unknown effect or an effect column no row lists, a value for an
        effect the row's model does not have, a parameter of a row's model that is not a
        number inside its physical range, a device mass or grip force outside its
        physical range (:mod:`armfit.io.ranges`), or a second row of one model (a
        nominal file has one row per axis, a grip file one per axis and grip, a
        per-trial file one per trial).
    """
    p = Path(path_or_name)
    if not p.exists() and str(path_or_name).lower() in PAPER_PARAMS:
        which = PAPER_PARAMS[str(path_or_name).lower()]
        table = paper_params(which)
        table.insert(0, "row", np.arange(1, len(table) + 1))
        label = "Table I of the paper" if which == "grip" else "Table II of the paper"
        return ParamRows(table, (), label)
    return check_param_rows(_read_csv(p), str(p))


def check_param_rows(table: pd.DataFrame, source: str | None = None) -> ParamRows:
    """The checks of :func:`read_param_rows` on a params table already in memory (e.g.
    a DataFrame given to the Python API instead of a file).

    Parameters
    ----------
    table : pandas.DataFrame
        Rows in the columns of a params file (:func:`armfit.io.schema.params_columns`);
        at least ``axis``, ``effects``, the parameters of the rows' models and ``mp_kg``.
    source : str, optional
        The file the table came from, named in messages.

    Returns
    -------
    ParamRows
        As :func:`read_param_rows` (``label``: ``source``, or "the params table").

    Raises
    ------
    BadInputError
        As :func:`read_param_rows`, naming ``source`` (when given), column and row.
    """
    p = source
    df = table.copy()
    for col in ("axis", "effects"):
        if col not in df.columns:
            raise BadInputError("missing column; expected a file written by fit-grip, "
                                "fit-nominal or fit-trials", file=p, column=col)
    df["effects"] = df["effects"].astype(object).fillna("").astype(str)
    # a table read before keeps its file's row numbers; messages count the table's rows
    numbers = df.pop("row").to_numpy() if "row" in df.columns else np.arange(1, len(df) + 1)
    df = df.reset_index(drop=True)
    uses = row_param_names(df, p)       # each row's own model (one per axis, say)
    bounds = param_bounds(df, p)
    _check_columns(df, p, bounds)
    df = parse_columns(df, ["grip_N", "run", *_STAT_NUMBERS,
                            *(f"{n}{sfx}" for n in bounds for sfx in ("_lo", "_hi"))],
                       file=str(p))
    df.insert(0, "row", np.arange(1, len(df) + 1))
    df["axis"] = _axes(df, p)
    _check_one_row_per_model(df, p)
    df["converged"] = df["converged"].astype(str).str.lower().isin(["true", "1"]) \
        if "converged" in df.columns else True
    values = {c: parse_numbers(df[c], errors="coerce") for c in bounds}
    used = {c: np.array([c in PARAMS_BASE or c in u for u in uses], bool) for c in bounds}
    empty = np.all([np.isnan(v) for v in values.values()], axis=0) \
        & ~df["converged"].to_numpy(bool)
    keep = ~empty
    for col, q in bounds.items():
        _check_values(df, p, col, q, values[col], used[col], keep)
        df[col] = values[col]
    mp = parse_numbers(df["mp_kg"], errors="coerce")
    check_in_range(mp, DEVICE_MASS_RANGE, file=p, column="mp_kg", where=keep,
                   shown=list(df["mp_kg"]))
    df["mp_kg"] = mp
    df["row"] = numbers
    skipped = tuple((int(numbers[i]), _identity(df.iloc[i]), _reason(df, i))
                    for i in np.flatnonzero(empty))
    return ParamRows(df[keep].reset_index(drop=True), skipped,
                     "the params table" if p is None else p)


def read_params(path: str | os.PathLike) -> pd.DataFrame:
    """A params file of fits (fit-grip, fit-nominal): :func:`read_param_rows` of the
    file, which must have a fit in every row and the columns of a fit (each
    parameter's interval ``_lo``/``_hi`` and the fit statistics).

    Parameters
    ----------
    path : str or os.PathLike
        The CSV.

    Returns
    -------
    pandas.DataFrame
        One row per fit, the columns of the file (no ``row`` column); as
        :func:`read_param_rows` reads them. ``grip_N`` is present only for grip fits.

    Raises
    ------
    NoInputError, BadInputError
        As :func:`read_param_rows`; also naming the file and column of a missing
        interval or statistic column, and the row of a fit without parameters.
    """
    p = Path(path)
    if not p.is_file():
        raise NoInputError(f"{p}: no such params file")
    rows = read_param_rows(p)
    table = rows.table
    for col, default in PARAMS_OPTIONAL.items():   # absent in files of older versions
        if col not in table.columns:
            table[col] = default
    names = list(param_bounds(table, p))
    for col in [f"{n}{sfx}" for n in names for sfx in ("_lo", "_hi")] + list(PARAMS_STATS):
        if col not in table.columns:
            raise BadInputError("missing column; expected a file written by fit-grip or "
                                "fit-nominal", file=str(p), column=col)
    if rows.skipped:
        row, who, _ = rows.skipped[0]
        raise BadInputError(f"a fit without parameters ({who})", file=str(p),
                            column=PARAMS_BASE[0], row=row)
    return table.drop(columns="row")


#: A number as armfit writes it (and as pandas and Python's ``float`` read alike).
_NUMBER = re.compile(r"-?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\Z")
#: The columns of a file of base-model fits (fit-grip, fit-nominal) :func:`fit_starts`
#: reads; a file with any other column is left to :func:`read_params`.
_BASE_FIT_COLUMNS = frozenset(params_columns(PARAMS_BASE, grip=True, held=True))


@dataclass(frozen=True)
class FitStarts:
    """The base parameters of a params file of base-model fits, one row per model, read
    without pandas (:func:`fit_starts`): what the diagnosis starts its fits from.

    Attributes
    ----------
    rows : tuple of dict
        Per row: ``axis``, ``grip_N`` (grip fits), and ``Ma, k1, k2, b1, b2`` (SI), as
        floats equal to those :func:`read_params` reads.
    grip : bool
        The file holds grip fits (a ``grip_N`` column).
    """

    rows: tuple[dict, ...]
    grip: bool

    def has_axis(self, axis: str) -> bool:
        return any(r["axis"] == axis for r in self.rows)

    def grips(self, axis: str) -> np.ndarray:
        """The grips (N) of the axis's rows, in file order."""
        return np.array([r["grip_N"] for r in self.rows if r["axis"] == axis], float)

    def of_axis(self, axis: str) -> list[dict]:
        return [r for r in self.rows if r["axis"] == axis]


def fit_starts(path: str | os.PathLike) -> FitStarts | None:
    """The base parameters of a params file of base-model fits, without pandas.

    For a file that :func:`read_params` reads without complaint and whose cells are
    plain: the columns armfit writes for base-model grip or nominal fits, axes written
    x, y or z, no effect, every number written as a decimal number, each inside its
    physical range, one row per model. Its values are those :func:`read_params` gives
    (Python's ``float`` and pandas' parser read such numbers to the same bits).

    Parameters
    ----------
    path : str or os.PathLike
        The CSV.

    Returns
    -------
    FitStarts or None
        None for anything else (a missing or unreadable file, a file with effects,
        another layout, a cell that is not plain, a value out of range): that file goes
        to :func:`read_params`, which reads or refuses it with its messages.
    """
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            lines = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError, csv.Error):
        return None
    if len(lines) < 2 or any(len(r) != len(lines[0]) for r in lines):
        return None
    header, body = lines[0], lines[1:]
    cols = set(header)
    grip = "grip_N" in cols
    need = set(params_columns(PARAMS_BASE, grip=grip)) - set(PARAMS_OPTIONAL)
    if len(cols) != len(header) or not need <= cols <= _BASE_FIT_COLUMNS:
        return None
    table = {c: [r[i] for r in body] for i, c in enumerate(header)}
    if any(a not in AXES for a in table["axis"]) or any(table["effects"]):
        return None
    numbers = [c for c in header if c not in ("axis", "cost", "converged", "effects",
                                              "at_bound", PARAMS_HELD)]
    if any(not _NUMBER.match(v) for c in numbers for v in table[c]
           if v or c in (*PARAMS_BASE, "mp_kg", "grip_N")):
        return None
    values = {c: np.array([float(v) for v in table[c]], float)
              for c in (*PARAMS_BASE, "mp_kg", *(("grip_N",) if grip else ()))}
    keys = list(zip(table["axis"], values["grip_N"] if grip else table["axis"], strict=True))
    if len(set(keys)) != len(keys):
        return None
    try:
        for q in BASE_PARAMS:
            check_in_range(values[q.name], PhysicalRange(q.name, q.unit, q.lower, q.upper),
                           file=None, column=q.name, tolerance=1e-9)
        check_in_range(values["mp_kg"], DEVICE_MASS_RANGE, file=None, column="mp_kg")
        if grip:
            check_in_range(values["grip_N"], GRIP_FORCE_RANGE, file=None, column="grip_N")
    except BadInputError:
        return None
    rows = tuple({"axis": a, **({"grip_N": float(values["grip_N"][i])} if grip else {}),
                  **{n: float(values[n][i]) for n in PARAMS_BASE}}
                 for i, a in enumerate(table["axis"]))
    return FitStarts(rows, grip)


def _read_csv(p: Path) -> pd.DataFrame:
    """The CSV as text columns where they are text, optional columns filled."""
    import pandas as pd  # here: the fits' and Wu fits' workers load no pandas

    if not p.is_file():
        raise NoInputError(f"{p}: no such params file (or give nominal, grip: the "
                           "paper's Tables II, I)")
    try:
        df = pd.read_csv(p, dtype={"axis": str, "effects": str, "subject": str,
                                   "reason": str, "cost": str, "at_bound": str,
                                   PARAMS_HELD: str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError,
            ValueError) as exc:
        raise BadInputError(f"not a params CSV ({str(exc).splitlines()[0]})",
                            file=str(p)) from None
    for col, default in PARAMS_OPTIONAL.items():
        if col in df.columns:
            df[col] = df[col].fillna(default).astype(str)
    if PARAMS_HELD in df.columns:
        df[PARAMS_HELD] = df[PARAMS_HELD].fillna("").astype(str)
    return df


def _check_columns(df: pd.DataFrame, p: str | None, bounds: dict[str, Param]) -> None:
    """Every parameter column of the rows' models and ``mp_kg`` present; no column of an
    effect that no row lists."""
    for col in (*bounds, "mp_kg"):
        if col not in df.columns:
            raise BadInputError("missing column; expected a file written by fit-grip, "
                                "fit-nominal or fit-trials", file=p, column=col)
    known = {f"{n}{sfx}" for n in bounds for sfx in ("", "_lo", "_hi")}
    for col in df.columns:  # an effect parameter the models would silently ignore
        if "." in str(col) and str(col) not in known:
            raise BadInputError(_unknown_effect_column(str(col), df),
                                file=p, column=str(col))


def _axes(df: pd.DataFrame, p: str | None) -> pd.Series:
    """The ``axis`` column, lower-case; BadInputError at the first that is not x, y, z."""
    axes = df["axis"].fillna("").astype(str).str.strip().str.lower()
    bad = np.flatnonzero(~axes.isin(list(AXES)).to_numpy())
    if bad.size:
        raise BadInputError(f"axis {cell(df['axis'].iloc[bad[0]])} is not x, y or z",
                            file=p, column="axis", row=int(bad[0]) + 1)
    return axes


def _check_values(df: pd.DataFrame, p: str | None, col: str, q: Param, v: np.ndarray,
                  used: np.ndarray, keep: np.ndarray) -> None:
    """The parameter ``col`` is a number inside its physical range in every kept row
    whose model has it, and empty in the rows whose model does not."""
    bad = np.flatnonzero(~used & np.isfinite(v))
    if bad.size:
        raise BadInputError(f"value {cell(df[col].iloc[bad[0]])} for an effect this "
                            f"row's model does not have (its effects: "
                            f"{df['effects'].iloc[bad[0]] or 'none'}); the model would "
                            "ignore it", file=p, column=col, row=int(bad[0]) + 1)
    bad = np.flatnonzero(used & keep & ~np.isfinite(v))
    if bad.size:
        kind = "a positive number" if q.log else "a number"
        raise BadInputError(f"parameter must be {kind}, got {cell(df[col].iloc[bad[0]])}",
                            file=p, column=col, row=int(bad[0]) + 1)
    # a bound written with 10 significant digits stays inside
    check_in_range(v, PhysicalRange(col, q.unit, q.lower, q.upper), file=p, column=col,
                   where=used & keep, tolerance=1e-9)


def _check_one_row_per_model(df: pd.DataFrame, p: str | None) -> None:
    """One row per model: per axis in a nominal file, per axis and grip in a grip file,
    per trial (axis, subject, grip, run) in a per-trial file; the grip forces inside
    their physical range. BadInputError at the second row of a model, naming both."""
    if "grip_N" in df.columns:
        import pandas as pd

        grips = pd.to_numeric(df["grip_N"], errors="coerce").to_numpy(float)
        check_in_range(grips, GRIP_FORCE_RANGE, file=p, column="grip_N",
                       shown=list(df["grip_N"]))
    if "subject" in df.columns:
        keys, column, what = ("axis", "subject", "grip_N", "run"), "subject", \
            "a per-trial params file has one row per trial (axis, subject, grip, run)"
    elif "grip_N" in df.columns:
        keys, column, what = ("axis", "grip_N"), "grip_N", \
            "a grip params file has one row per axis and grip"
    else:
        keys, column, what = ("axis",), "axis", "a nominal params file has one row per axis"
    first: dict[tuple, int] = {}
    for i, rec in enumerate(df[[k for k in keys if k in df.columns]].to_dict("records")):
        key = tuple(_key_value(rec.get(k), k != "subject") for k in keys)
        if key in first:
            raise BadInputError(f"{_identity(df.iloc[i])} has a second row (rows "
                                f"{first[key]} and {i + 1}); {what}", file=p,
                                column=column, row=i + 1)
        first[key] = i + 1


def _key_value(v, number: bool):
    """A cell of a model's identity, comparable across rows (a grip or run as float, a
    subject as text, a missing value as None)."""
    if v is None or str(v).strip() in ("", "nan", "<NA>", "None"):
        return None
    if number:
        try:
            return float(v)
        except (TypeError, ValueError):
            pass
    return str(v).strip()


def _file(path) -> str | None:
    return None if path is None else str(path)


def _reason(df: pd.DataFrame, i: int) -> str:
    """Why row ``i`` of a per-trial file has no parameters."""
    r = df["reason"].iloc[i] if "reason" in df.columns else None
    return r if isinstance(r, str) else "no parameters (fit failed)"


def _identity(row) -> str:
    parts = [f"axis {row['axis']}"]
    for col, fmt in (("subject", "subject {}"), ("grip_N", "grip {} N"), ("run", "run {}")):
        v = row.get(col)
        if v is not None and str(v) not in ("", "nan", "<NA>", "None"):
            try:
                v = f"{float(v):g}"
            except (TypeError, ValueError):
                pass
            parts.append(fmt.format(v))
    return ", ".join(parts)


def _unknown_effect_column(col: str, df: pd.DataFrame) -> str:
    """Why the column ``<effect>.<param>`` does not belong to the file's models."""
    name = col.split(".", 1)[0]
    spec = " | ".join(sorted(set(df["effects"]) - {""})) or "none"
    try:
        get_effect(name)
    except UsageError:
        return (f"unknown effect '{name}' (not built in, and no loaded effect has that "
                f"name); the file's models list effects: {spec}")
    return (f"parameter of the effect '{name}', which no row lists in the column "
            f"'effects' ({spec}); the models would ignore it")


def param_bounds(df: pd.DataFrame, path) -> dict[str, Param]:
    """{column: Param} of the base parameters, then of each effect any row lists."""
    out = {q.name: q for q in BASE_PARAMS}
    for effects in row_effects(df, path):
        for eff in effects:
            for q in eff.params:
                out.setdefault(f"{eff.name}.{q.name}", q)
    return out


def row_effects(df: pd.DataFrame, path) -> list[list]:
    """The effects of each row's model, from its ``effects`` cell (``;``-separated
    names; a params file may hold one model per axis, e.g. the models ``armfit run``
    adopts). Raises BadInputError naming the file, column ``effects`` and row of an
    effect no loaded library holds."""
    out = []
    cache: dict[str, list] = {}
    for i, spec in enumerate(df["effects"].fillna("").astype(str)):
        if spec not in cache:
            try:
                cache[spec] = [get_effect(n) for n in spec.split(";") if n]
            except UsageError as exc:
                raise BadInputError(exc.template, file=_file(path), column="effects",
                                    row=i + 1) from None
        out.append(cache[spec])
    return out


def row_param_names(df: pd.DataFrame, path) -> list[set[str]]:
    """Per row, the ``<effect>.<param>`` names of its model's effects."""
    return [{f"{e.name}.{q.name}" for e in effects for q in e.params}
            for effects in row_effects(df, path)]


def model_from_params(row) -> tuple[ClosedLoopModel, dict[str, float]]:
    """The closed-loop model and its fitted values from one row of a params table.

    Parameters
    ----------
    row : pandas.Series or Mapping
        A row of a params file (:func:`armfit.io.schema.params_columns`): ``axis``,
        ``Ma, k1, k2, b1, b2``, ``effects`` (``;``-separated names), the effect
        parameters ``<effect>.<param>`` and the device mass ``mp_kg``.

    Returns
    -------
    (ClosedLoopModel, dict)
        The model of the row's axis with its effects and device mass (eq. 4), and the
        values {name: value}, base parameters then ``<effect>.<param>``.

    Raises
    ------
    BadInputError
        The row names an effect the library does not know (column ``effects``).
    """
    spec = row["effects"] if isinstance(row["effects"], str) else ""
    try:
        effects = [get_effect(n) for n in spec.split(";") if n]
    except UsageError as exc:
        raise BadInputError(exc.template, column="effects") from None
    model = ClosedLoopModel.for_axis(str(row["axis"]), effects, mp=float(row["mp_kg"]))
    return model, {n: float(row[n]) for n in model.param_names}


def fit_band(row, f_hz=None) -> tuple[float, float] | None:
    """The band a params row's model was fitted on.

    Parameters
    ----------
    row : pandas.Series or Mapping
        A row of a params file, with ``band_lo_hz`` and ``band_hi_hz`` (Hz): the first
        and last frequency the fit used.
    f_hz : array_like, optional
        A frequency grid (Hz): the band is then given as its first and last grid point
        within the row's band. A params file stores the band to 10 significant digits,
        so a grid point within 1e-9 (relative) of an edge counts as inside.

    Returns
    -------
    (float, float) or None
        (lo, hi) in Hz; None when the row does not say (no such columns, not a finite
        band with lo < hi, or no grid point inside it).
    """
    try:
        lo, hi = float(row["band_lo_hz"]), float(row["band_hi_hz"])
    except (KeyError, TypeError, ValueError):
        return None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        return None
    if f_hz is None:
        return lo, hi
    f = np.asarray(f_hz, float)
    inside = f[(f >= lo * (1 - 1e-9)) & (f <= hi * (1 + 1e-9))]
    return (float(inside.min()), float(inside.max())) if inside.size else None


__all__ = [
    "PAPER_PARAMS", "ParamRows", "paper_params", "read_param_rows", "check_param_rows",
    "read_params", "FitStarts", "fit_starts",
    "param_bounds", "row_effects", "row_param_names", "model_from_params", "fit_band",
]
