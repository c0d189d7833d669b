"""Params files (written by fit-grip and fit-nominal) read back into models.

A params file is checked against the models it describes: the columns of the effects it
names, and parameters that are positive numbers. :func:`model_from_params` turns one row
into the closed-loop model of eq. 4 and its values.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

from armfit.constants import AXES
from armfit.errors import BadInputError, NoInputError, UsageError, cell
from armfit.io.schema import PARAMS_BASE, PARAMS_HELD, PARAMS_OPTIONAL, PARAMS_STATS
from armfit.models.arm import BASE_PARAMS, ClosedLoopModel, Param
from armfit.models.effects import get_effect


def read_params(path: str | os.PathLike) -> pd.DataFrame:
    """Read a params CSV written by fit-grip or fit-nominal and check its columns.

    Parameters
    ----------
    path : str or os.PathLike
        The CSV.

    Returns
    -------
    pandas.DataFrame
        One row per fit; ``effects`` as str (the row's model: a file may hold one model
        per axis), ``converged`` as bool, ``at_bound`` as str (the parameters at a
        physical bound, ";"-separated, empty when none or in a file written before the
        column existed), ``held`` as str when present (the parameters held fixed),
        ``grip_N`` present only for grip fits.

    Raises
    ------
    NoInputError
        The file is missing.
    BadInputError
        Naming the file and the missing column, an unknown or unlisted effect column, an
        axis other than x, y or z, or the row and column of a parameter of the row's model
        that is not a number inside its physical range, or of a value given for an effect
        the row's model does not have.
    """
    p = Path(path)
    if not p.is_file():
        raise NoInputError(f"{p}: no such params file")
    try:
        df = pd.read_csv(p, dtype={"axis": str, "effects": str, "cost": str, "at_bound": str,
                                   PARAMS_HELD: str}, keep_default_na=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError,
            ValueError) as exc:
        raise BadInputError(f"not a params CSV ({str(exc).splitlines()[0]})", file=str(p)
                            ) from None
    if "effects" not in df.columns:
        raise BadInputError("missing column; expected a file written by fit-grip or "
                            "fit-nominal", file=str(p), column="effects")
    df["effects"] = df["effects"].fillna("").astype(str)
    for col, default in PARAMS_OPTIONAL.items():
        df[col] = df[col].fillna(default).astype(str) if col in df.columns else default
    if PARAMS_HELD in df.columns:
        df[PARAMS_HELD] = df[PARAMS_HELD].fillna("").astype(str)
    base_cols = ["axis", *PARAMS_BASE]
    bounds = param_bounds(df, p)
    names = list(bounds)
    expected = base_cols + names[len(PARAMS_BASE):] + [
        f"{n}{sfx}" for n in names for sfx in ("_lo", "_hi")] + list(PARAMS_STATS)
    for col in expected:
        if col not in df.columns:
            raise BadInputError("missing column; expected a file written by fit-grip or "
                                "fit-nominal", file=str(p), column=col)
    known = set(expected)
    for col in df.columns:  # an effect parameter the model would silently ignore
        if "." in str(col) and str(col) not in known:
            raise BadInputError(_unknown_effect_column(str(col), df),
                                file=str(p), column=str(col))
    axes = df["axis"].fillna("").astype(str).str.strip()
    bad = np.flatnonzero(~axes.isin(list(AXES)).to_numpy())
    if bad.size:
        raise BadInputError(f"axis {cell(df['axis'].iloc[bad[0]])} is not x, y or z",
                            file=str(p), column="axis", row=int(bad[0]) + 1)
    uses = row_param_names(df, p)
    for col, par in bounds.items():
        vals = pd.to_numeric(df[col], errors="coerce").to_numpy(float)
        used = np.array([col in PARAMS_BASE or col in u for u in uses], bool)
        bad = np.flatnonzero(~used & np.isfinite(vals))
        if bad.size:
            raise BadInputError(f"value {cell(df[col].iloc[bad[0]])} for an effect this "
                                f"row's model does not have (its effects: "
                                f"{df['effects'].iloc[bad[0]] or 'none'}); the model would "
                                "ignore it", file=str(p), column=col, row=int(bad[0]) + 1)
        vals = np.where(used, vals, par.typical)   # cells the row's model does not use
        bad = np.flatnonzero(~np.isfinite(vals))
        if bad.size:
            raise BadInputError(f"parameter must be a positive number, got "
                                f"{cell(df[col].iloc[bad[0]])}", file=str(p), column=col,
                                row=int(bad[0]) + 1)
        tol = 1e-9 * max(abs(par.lower), abs(par.upper))  # 10-digit rounding of a bound
        bad = np.flatnonzero((vals < par.lower - tol) | (vals > par.upper + tol))
        if bad.size:
            raise BadInputError(f"{col} = {cell(vals[bad[0]])} {par.unit} is outside its "
                                f"physical range [{par.lower:g}, {par.upper:g}] {par.unit}",
                                file=str(p), column=col, row=int(bad[0]) + 1)
    df["converged"] = df["converged"].astype(str).str.lower().isin(["true", "1"])
    return df


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
                raise BadInputError(exc.template, file=str(path), column="effects",
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
