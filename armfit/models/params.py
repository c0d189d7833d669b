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

from armfit.errors import BadInputError, NoInputError, UsageError
from armfit.io.schema import PARAMS_BASE, PARAMS_STATS
from armfit.models.arm import ClosedLoopModel
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
        One row per fit; ``effects`` as str, ``converged`` as bool, ``grip_N`` present
        only for grip fits.

    Raises
    ------
    NoInputError
        The file is missing.
    BadInputError
        Naming the file and the missing column, or the row and column of a non-numeric
        or non-positive parameter.
    """
    p = Path(path)
    if not p.is_file():
        raise NoInputError(f"{p}: no such params file")
    try:
        df = pd.read_csv(p, dtype={"axis": str, "effects": str, "cost": str},
                         keep_default_na=True)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError,
            ValueError) as exc:
        raise BadInputError(f"not a params CSV ({str(exc).splitlines()[0]})", file=str(p)
                            ) from None
    if "effects" not in df.columns:
        raise BadInputError("missing column; expected a file written by fit-grip or "
                            "fit-nominal", file=str(p), column="effects")
    df["effects"] = df["effects"].fillna("").astype(str)
    base_cols = ["axis", *PARAMS_BASE]
    names = list(PARAMS_BASE) + _effect_param_names(df, p)
    expected = base_cols + names[len(PARAMS_BASE):] + [
        f"{n}{sfx}" for n in names for sfx in ("_lo", "_hi")] + list(PARAMS_STATS)
    for col in expected:
        if col not in df.columns:
            raise BadInputError("missing column; expected a file written by fit-grip or "
                                "fit-nominal", file=str(p), column=col)
    for col in names:
        vals = pd.to_numeric(df[col], errors="coerce").to_numpy(float)
        bad = np.flatnonzero(~(np.isfinite(vals) & (vals > 0)))
        if bad.size:
            raise BadInputError(f"parameter must be a positive number, got "
                                f"{df[col].iloc[bad[0]]!r}", file=str(p), column=col,
                                row=int(bad[0]) + 1)
    df["converged"] = df["converged"].astype(str).str.lower().isin(["true", "1"])
    return df


def _effect_param_names(df: pd.DataFrame, path: Path) -> list[str]:
    """The ``<effect>.<param>`` names of the effects the rows name (one model per file)."""
    specs = set(df["effects"])
    if len(specs) > 1:
        raise BadInputError(f"rows list different effects ({' | '.join(sorted(specs))}); "
                            "one params file holds one model", file=str(path),
                            column="effects")
    spec = next(iter(specs), "")
    out = []
    for name in [n for n in spec.split(";") if n]:
        try:
            eff = get_effect(name)
        except UsageError as exc:
            raise BadInputError(str(exc), file=str(path), column="effects") from None
        out += [f"{eff.name}.{q.name}" for q in eff.params]
    return out


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
        raise BadInputError(str(exc), column="effects") from None
    model = ClosedLoopModel.for_axis(str(row["axis"]), effects, mp=float(row["mp_kg"]))
    return model, {n: float(row[n]) for n in model.param_names}
