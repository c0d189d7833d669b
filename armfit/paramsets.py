"""Any parameters file armfit writes (nominal, grip or per-trial fits), or one of the
paper's tables by name, as model rows for analyses that take every row (stability).

Per-trial files (``armfit fit-trials``) may list trials whose fit failed: empty
parameters, ``converged`` false and a ``reason``. Those rows are returned apart, with
their reason, so that the caller can say which trials it leaves out.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from armfit.constants import DEVICE_MASS_KG
from armfit.data import paper_table
from armfit.errors import BadInputError, NoInputError
from armfit.io.schema import PARAMS_BASE, wu_sidecar_paths
from armfit.models.params import param_bounds, row_param_names
from armfit.uncertainty import PAPER_BAND_HZ, read_wu

#: Names that stand for the paper's tables when no file of that name exists.
PAPER_PARAMS: dict[str, str] = {"nominal": "nominal", "table2": "nominal",
                                "grip": "grip", "table1": "grip"}
#: Names that stand for the paper's Table III (uncertainty weights).
PAPER_WEIGHTS: tuple[str, ...] = ("paper", "table3")

_PAPER_RENAME = {"Ma_kg": "Ma", "k1_N_per_m": "k1", "k2_N_per_m": "k2",
                 "b1_Ns_per_m": "b1", "b2_Ns_per_m": "b2"}


@dataclass(frozen=True)
class ParamRows:
    """Model rows of a parameters file: ``table`` (DataFrame with a 1-based ``row``
    column, the file's row number), ``skipped`` [(row, identity, reason)] of the rows
    without parameters, and ``label`` (file path, or the paper's table)."""

    table: object
    skipped: tuple[tuple[int, str, str], ...]
    label: str


def paper_params(name: str):
    """The paper's Table I ('grip') or II ('nominal') in the columns of a params file:
    axis[, grip_N], Ma..b2 (SI), mp_kg (eq. 2), effects ''."""
    table = paper_table(name).rename(columns=_PAPER_RENAME)
    table["mp_kg"] = table["axis"].map(DEVICE_MASS_KG)
    table["effects"] = ""
    table["converged"] = True
    return table


def read_param_rows(path_or_name: str) -> ParamRows:
    """Read a params CSV written by fit-grip, fit-nominal or fit-trials, or name one of
    the paper's tables (``nominal``/``table2``, ``grip``/``table1``; a file of that name
    wins).

    Each row is its own model (its ``effects`` cell): a file may hold one model per axis.
    Raises NoInputError for a missing file; BadInputError naming the file, column and
    row for a missing column, an unknown effect, or a parameter of a row's model that is
    not a number inside its physical range in a row that claims a fit.
    """
    p = Path(path_or_name)
    if not p.exists() and str(path_or_name).lower() in PAPER_PARAMS:
        which = PAPER_PARAMS[str(path_or_name).lower()]
        table = paper_params(which)
        table.insert(0, "row", np.arange(1, len(table) + 1))
        label = "Table I of the paper" if which == "grip" else "Table II of the paper"
        return ParamRows(table, (), label)
    if not p.is_file():
        raise NoInputError(f"{p}: no such params file (or give nominal, grip: the "
                           "paper's Tables II, I)")
    try:
        df = pd.read_csv(p, dtype={"axis": str, "effects": str, "subject": str,
                                   "reason": str, "cost": str})
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError,
            ValueError) as exc:
        raise BadInputError(f"not a params CSV ({str(exc).splitlines()[0]})",
                            file=str(p)) from None
    for col in ("axis", *PARAMS_BASE, "mp_kg", "effects"):
        if col not in df.columns:
            raise BadInputError("missing column; expected a file written by fit-grip, "
                                "fit-nominal or fit-trials", file=str(p), column=col)
    df["effects"] = df["effects"].fillna("").astype(str)
    uses = row_param_names(df, p)       # each row's own model (one per axis, say)
    names = list(PARAMS_BASE) + list(dict.fromkeys(n for u in uses for n in sorted(u)))
    for col in names:
        if col not in df.columns:
            raise BadInputError("missing column of the model's effects", file=str(p),
                                column=col)
    df.insert(0, "row", np.arange(1, len(df) + 1))
    axes = df["axis"].astype(str).str.strip().str.lower()
    bad = np.flatnonzero(~axes.isin(["x", "y", "z"]).to_numpy())
    if bad.size:
        raise BadInputError(f"expected x, y or z, got {df['axis'].iloc[bad[0]]!r}",
                            file=str(p), column="axis", row=int(bad[0]) + 1)
    df["axis"] = axes
    conv = df["converged"].astype(str).str.lower().isin(["true", "1"]) \
        if "converged" in df.columns else pd.Series(True, index=df.index)
    values = {c: pd.to_numeric(df[c], errors="coerce").to_numpy(float) for c in names}
    empty = np.all([np.isnan(v) for v in values.values()], axis=0) & ~conv.to_numpy()
    skipped = []
    for i in np.flatnonzero(empty):
        reason = str(df["reason"].iloc[i]) if "reason" in df.columns \
            and isinstance(df["reason"].iloc[i], str) else "no parameters (fit failed)"
        skipped.append((int(i) + 1, _identity(df.iloc[i]), reason))
    keep = ~empty
    bounds = param_bounds(df, p)
    for col, v in values.items():
        used = keep & np.array([col in PARAMS_BASE or col in u for u in uses], bool)
        q = bounds[col]
        tol = 1e-9 * max(abs(q.lower), abs(q.upper))  # 10-digit rounding of a bound
        bad = np.flatnonzero(used & ~(np.isfinite(v) & (v >= q.lower - tol)
                                      & (v <= q.upper + tol) & ((v > 0) | (not q.log))))
        if bad.size:
            raise BadInputError(f"parameter must be a number in its physical range "
                                f"[{q.lower:g}, {q.upper:g}] {q.unit}, got "
                                f"{df[col].iloc[bad[0]]!r}", file=str(p), column=col,
                                row=int(bad[0]) + 1)
        df[col] = v
    mp = pd.to_numeric(df["mp_kg"], errors="coerce").to_numpy(float)
    bad = np.flatnonzero(keep & ~(np.isfinite(mp) & (mp > 0)))
    if bad.size:
        raise BadInputError(f"device mass must be a positive number (kg), got "
                            f"{df['mp_kg'].iloc[bad[0]]!r}", file=str(p), column="mp_kg",
                            row=int(bad[0]) + 1)
    df["mp_kg"] = mp
    return ParamRows(df[keep].reset_index(drop=True), tuple(skipped), str(p))


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


def read_weights(path_or_name: str):
    """({axis: WuWeight}, {axis: (lo, hi) Hz}, label) of a Wu CSV (fit-uncertainty
    output, Table III layout) or the paper's Table III by name (``paper``/``table3``;
    a file of that name wins). The band is the one the weight was fitted over, from the
    ``<stem>_summary.csv`` written beside it; without one, the paper's 0.01–30 Hz."""
    p = Path(path_or_name)
    if not p.exists() and str(path_or_name).lower() in PAPER_WEIGHTS:
        ref = resources.files("armfit.data").joinpath("table3_uncertainty_weights.csv")
        with resources.as_file(ref) as f:
            w = read_wu(f)
        return w, {a: PAPER_BAND_HZ for a in w}, "Table III of the paper"
    w = read_wu(p)
    bands = {a: PAPER_BAND_HZ for a in w}
    summary, _ = wu_sidecar_paths(p)
    if summary.is_file():
        try:
            s = pd.read_csv(summary)
            s = s[(s["weight"] == "fitted") & (s["target"] == "wmax")]
            for _, r in s.iterrows():
                lo, hi = float(r["band_lo_hz"]), float(r["band_hi_hz"])
                if r["axis"] in bands and 0 < lo < hi:
                    bands[r["axis"]] = (lo, hi)
        except (KeyError, ValueError, pd.errors.ParserError, pd.errors.EmptyDataError):
            pass
    return w, bands, str(p)
