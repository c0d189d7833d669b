"""Schemas of armfit's own files: spectra (Parquet), fitted parameters (CSV), Wu (CSV).

Each schema is defined once here; writers and readers of each file live below its
schema. Readers validate and raise BadInputError naming the file and column.
"""

from __future__ import annotations

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
    "kind",       # "measured" (X/F), "derived" (Xa/Fa, device removed), "cross"
    "out_axis",   # position axis of the response (== axis except for kind "cross")
    "method",     # estimator name, e.g. "h1", "chebwin", "tfestimate"
    "freq_hz",    # frequency, Hz
    "re", "im",   # complex response, m/N
    "mag_db",     # 20 log10 |H| with H in m/N
    "phase_deg",  # phase, deg (unwrapped along frequency)
    "coherence",  # magnitude-squared coherence 0..1 (NaN where not defined)
    "se_db",      # standard error of mag_db, dB
    "se_deg",     # standard error of phase_deg, deg
    "n",          # number of trials behind the value (1 at level "trial")
    "q25_db", "q75_db", "q25_deg", "q75_deg",  # quartiles across trials (aggregates)
    "flags",      # comma-separated: low_coherence, saturation, drift, no_signal (empty if
                  # none); no_signal: the cell carries no information (no force or no
                  # position power there, e.g. an unstimulated axis recorded as constant
                  # zero): re, im, mag_db, phase_deg, coherence, se_* are NaN, never ±inf,
                  # and aggregates leave the cell out (NaN and no_signal if no trial has it)
)

#: Key of armfit's metadata (JSON) in the Parquet file's key-value metadata.
SPECTRA_META_KEY = b"armfit"


def write_spectra(df, path, *, meta: dict, overwrite: bool = False):
    """Write a spectra table (columns SPECTRA_COLUMNS, in order) as Parquet, atomically.

    ``meta`` (JSON-serialisable: method, options, grid, Mp, armfit version …) is stored as
    JSON under the key ``armfit`` of the file's key-value metadata. Returns the path.
    Raises OutputError (exit 73) if ``path`` exists and not ``overwrite``.
    """
    import json

    import pyarrow as pa
    import pyarrow.parquet as pq

    from armfit.io.atomic import atomic_path
    missing = [c for c in SPECTRA_COLUMNS if c not in df.columns]
    if missing:
        raise ValueError(f"spectra table lacks columns: {', '.join(missing)}")
    table = pa.Table.from_pandas(df[list(SPECTRA_COLUMNS)], preserve_index=False)
    kv = dict(table.schema.metadata or {})
    kv[SPECTRA_META_KEY] = json.dumps(meta, default=json_default).encode()
    table = table.replace_schema_metadata(kv)
    with atomic_path(path, overwrite=overwrite) as tmp:
        pq.write_table(table, tmp, compression="zstd")
    return path


def json_default(o):
    """``json.dumps`` default: numpy scalars and arrays as Python numbers and lists."""
    import numpy as np
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_spectra(path):
    """Read a spectra Parquet file; check its columns. Returns a pandas DataFrame with the
    file's armfit metadata (dict) in ``df.attrs["armfit"]`` ({} if absent).

    Raises NoInputError if the file is missing, BadInputError naming the file (and the
    missing column) if it is not a readable spectra table.
    """
    import json
    from pathlib import Path

    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from armfit.errors import BadInputError, NoInputError, cell
    p = Path(path)
    if not p.is_file():
        raise NoInputError(f"{p}: no such spectra file")
    try:
        table = pq.read_table(p)
    except (pa.ArrowException, OSError) as exc:
        raise BadInputError(f"not a readable Parquet spectra file ({str(exc).splitlines()[0]})"
                            "; make one with `armfit estimate`", file=str(p)) from None
    for c in SPECTRA_COLUMNS:
        if c not in table.column_names:
            raise BadInputError("missing column; not a spectra file written by "
                                "`armfit estimate`", file=str(p), column=c)
    kv = table.schema.metadata or {}
    try:
        meta = json.loads(kv[SPECTRA_META_KEY]) if SPECTRA_META_KEY in kv else {}
    except ValueError:
        meta = {}
    df = table.select(list(SPECTRA_COLUMNS)).to_pandas()
    for col in ("axis", "out_axis"):  # rows of another axis would be dropped silently
        bad = np.flatnonzero(~df[col].isin(["x", "y", "z"]).to_numpy())
        if bad.size:
            raise BadInputError(f"axis {cell(df[col].iloc[bad[0]])} is not x, y or z",
                                file=str(p), column=col, row=int(bad[0]) + 1)
    df.attrs["armfit"] = meta
    return df

# ---------------------------------------------------------------------------
# Fitted parameters (written by `armfit fit-grip` / `fit-nominal`): CSV.
# ---------------------------------------------------------------------------

#: Base arm parameters of a params file, in the paper's order (SI: kg, N/m, N*s/m).
PARAMS_BASE: tuple[str, ...] = ("Ma", "k1", "k2", "b1", "b2")
#: Fit statistics closing every params row, in order.
PARAMS_STATS: tuple[str, ...] = ("rms_db", "rms_deg", "rms_norm", "band_lo_hz", "band_hi_hz",
                                 "n_points", "cost", "converged", "mp_kg", "effects",
                                 "at_bound")
#: Columns of :data:`PARAMS_STATS` that files written by older versions may lack, with the
#: value they take when read.
PARAMS_OPTIONAL: dict[str, str] = {"at_bound": ""}


def params_columns(param_names, *, grip: bool) -> list[str]:
    """Columns of a params file, in order: ``axis``, ``grip_N`` (grip fits only), the
    parameters (base then ``<effect>.<param>``), ``<p>_lo, <p>_hi`` for each (95 %
    interval), then :data:`PARAMS_STATS`."""
    names = list(param_names)
    cols = ["axis"] + (["grip_N"] if grip else []) + names
    for n in names:
        cols += [f"{n}_lo", f"{n}_hi"]
    return cols + list(PARAMS_STATS)


def params_frame(rows, param_names, *, grip: bool):
    """A params DataFrame from row dicts (one per fit), columns in file order."""
    import pandas as pd
    return pd.DataFrame(list(rows), columns=params_columns(param_names, grip=grip))


def write_params(df, path, *, overwrite: bool = False):
    """Write a params DataFrame as CSV atomically (full float precision). Returns the path.

    Raises OutputError (exit 73) if ``path`` exists and not ``overwrite``.
    """
    from armfit.io.atomic import atomic_path
    with atomic_path(path, overwrite=overwrite) as tmp:
        df.to_csv(tmp, index=False, float_format="%.10g")
    return path


def read_params(path):
    """Read a params CSV; check its columns. Returns a DataFrame (``effects`` as str,
    ``converged`` as bool, ``at_bound`` as str — the parameters at a physical bound,
    ";"-separated, empty when none or in a file written before the column existed —
    ``grip_N`` present only for grip fits).

    Raises NoInputError if the file is missing, BadInputError naming the file and the
    missing column, or the row and column of a non-numeric or non-positive parameter.
    """
    from pathlib import Path

    import numpy as np
    import pandas as pd

    from armfit.errors import BadInputError, NoInputError, cell
    p = Path(path)
    if not p.is_file():
        raise NoInputError(f"{p}: no such params file")
    try:
        df = pd.read_csv(p, dtype={"axis": str, "effects": str, "cost": str, "at_bound": str},
                         keep_default_na=True)
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
    base_cols = ["axis", *PARAMS_BASE]
    bounds = _param_bounds(df, p)
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
    bad = np.flatnonzero(~axes.isin(["x", "y", "z"]).to_numpy())
    if bad.size:
        raise BadInputError(f"axis {cell(df['axis'].iloc[bad[0]])} is not x, y or z",
                            file=str(p), column="axis", row=int(bad[0]) + 1)
    for col, par in bounds.items():
        vals = pd.to_numeric(df[col], errors="coerce").to_numpy(float)
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


def _unknown_effect_column(col: str, df) -> str:
    """Why the column ``<effect>.<param>`` does not belong to the file's model."""
    from armfit.errors import UsageError
    from armfit.models.effects import get_effect
    name = col.split(".", 1)[0]
    spec = next(iter(set(df["effects"])), "") or "none"
    try:
        get_effect(name)
    except UsageError:
        return (f"unknown effect '{name}' (not built in, and no loaded effect has that "
                f"name); the file's model lists effects: {spec}")
    return (f"parameter of the effect '{name}', which the column 'effects' does not list "
            f"({spec}); the model would ignore it")


def _param_bounds(df, path) -> dict:
    """{column: Param} of the base parameters, then of each listed effect's parameters."""
    from armfit.models.arm import BASE_PARAMS
    from armfit.models.effects import get_effect
    out = {q.name: q for q in BASE_PARAMS}
    for name in _effect_param_names(df, path):
        eff = get_effect(name.split(".", 1)[0])
        out[name] = next(q for q in eff.params if f"{eff.name}.{q.name}" == name)
    return out


def _effect_param_names(df, path) -> list[str]:
    from armfit.errors import BadInputError, UsageError
    from armfit.models.effects import get_effect
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


def model_from_params(row):
    """(ClosedLoopModel, theta) from one params row (a pandas Series or a dict): the
    model of the row's axis with its effects and device mass ``mp_kg``, and the fitted
    values {name: value} (base then ``<effect>.<param>``)."""
    from armfit.models.arm import ClosedLoopModel
    from armfit.models.effects import get_effect
    spec = row["effects"] if isinstance(row["effects"], str) else ""
    effects = [get_effect(n) for n in spec.split(";") if n]
    model = ClosedLoopModel.for_axis(str(row["axis"]), effects, mp=float(row["mp_kg"]))
    return model, {n: float(row[n]) for n in model.param_names}

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


def wu_sidecar_paths(path) -> tuple:
    """(summary, points) paths written beside the Wu file ``path``:
    ``<stem>_summary.csv`` and ``<stem>_wmax.csv`` in the same folder."""
    from pathlib import Path
    p = Path(path)
    stem = p.name[:-4] if p.name.lower().endswith(".csv") else p.name
    return p.with_name(f"{stem}_summary.csv"), p.with_name(f"{stem}_wmax.csv")


def wu_frame(weights):
    """A Wu DataFrame (:data:`WU_COLUMNS`) from {axis: WuWeight}, axes in x, y, z order."""
    import pandas as pd
    rows = []
    for axis in sorted(weights):
        w = weights[axis]
        rows.append((axis, "gain", 0, float(w.gain), 0.0))
        for kind, reps in (("zero", w.zeros), ("pole", w.poles)):
            for i, r in enumerate(reps, start=1):
                rows.append((axis, kind, i, float(r.real), float(abs(r.imag))))
    return pd.DataFrame(rows, columns=list(WU_COLUMNS))


def write_wu(weights, path, *, overwrite: bool = False):
    """Write {axis: WuWeight} as a Wu CSV atomically (10 significant digits). Returns path.

    Raises OutputError (exit 73) if ``path`` exists and not ``overwrite``.
    """
    from armfit.io.atomic import atomic_path
    with atomic_path(path, overwrite=overwrite) as tmp:
        wu_frame(weights).to_csv(tmp, index=False, float_format="%.10g")
    return path


def read_wu(path, *, require_stable: bool = True):
    """Read a Wu CSV (the layout of the paper's Table III). Returns {axis: WuWeight}.

    With ``require_stable`` (default) a pole or zero with a real part >= 0 (an unstable
    or non-minimum-phase weight, eq. 7 requires neither) is refused, naming its row.

    Raises NoInputError if the file is missing; BadInputError naming the file, column and
    row (1-based data row) of anything that breaks the layout: a missing column, an axis
    other than x/y/z, a kind other than gain/zero/pole, a non-numeric or non-finite
    value, or an axis without exactly one positive gain.
    """
    from pathlib import Path

    import numpy as np
    import pandas as pd

    from armfit.errors import BadInputError, NoInputError, cell
    from armfit.uncertainty import WuWeight
    p = Path(path)
    if not p.is_file():
        raise NoInputError(f"{p}: no such uncertainty-weights file")
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
    for col, values, allowed in (("axis", axis, ("x", "y", "z")),
                                 ("kind", kind, ("gain", "zero", "pole"))):
        bad = np.flatnonzero(~values.isin(allowed).to_numpy())
        if bad.size:
            raise BadInputError(f"expected one of {', '.join(allowed)}, got "
                                f"{cell(df[col].iloc[bad[0]])}", file=str(p), column=col,
                                row=int(bad[0]) + 1)
    nums = {}
    for col in ("index", "real", "imag"):
        v = pd.to_numeric(df[col].str.strip().replace("", "0" if col == "imag" else "nan"),
                          errors="coerce").to_numpy(float)
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise BadInputError(f"expected a finite number, got {cell(df[col].iloc[bad[0]])}",
                                file=str(p), column=col, row=int(bad[0]) + 1)
        nums[col] = v
    out = {}
    for ax in ("x", "y", "z"):
        rows = np.flatnonzero(axis.to_numpy() == ax)
        if rows.size == 0:
            continue
        gains = rows[kind.to_numpy()[rows] == "gain"]
        if gains.size != 1:
            raise BadInputError(f"axis {ax} has {gains.size} gain rows; expected one",
                                file=str(p), column="kind",
                                row=int((gains if gains.size else rows)[0]) + 1)
        if not nums["real"][gains[0]] > 0:
            raise BadInputError(f"gain K must be > 0, got {nums['real'][gains[0]]:g}",
                                file=str(p), column="real", row=int(gains[0]) + 1)
        reps = {}
        for k in ("zero", "pole"):
            r = rows[kind.to_numpy()[rows] == k]
            r = r[np.argsort(nums["index"][r], kind="stable")]
            reps[k] = nums["real"][r] + 1j * np.abs(nums["imag"][r])
        for k, what in (("pole", "unstable: a pole"), ("zero", "not minimum phase: a zero")):
            r = rows[kind.to_numpy()[rows] == k]
            bad = r[nums["real"][r] >= 0]
            if require_stable and bad.size:
                i = int(bad[0])
                raise BadInputError(
                    f"Wu of axis {ax} is {what} at {cell(nums['real'][i])} ± "
                    f"{cell(abs(nums['imag'][i]))}j rad/s is not in the open left half plane; "
                    "an uncertainty weight must be stable and minimum phase",
                    file=str(p), column="real", row=i + 1)
        out[ax] = WuWeight(float(nums["real"][gains[0]]), reps["zero"], reps["pole"])
    return out


def write_wu_table(df, path, *, overwrite: bool = False):
    """Write a summary or points DataFrame as CSV atomically (10 significant digits)."""
    from armfit.io.atomic import atomic_path
    with atomic_path(path, overwrite=overwrite) as tmp:
        df.to_csv(tmp, index=False, float_format="%.10g")
    return path


def wu_latex(weights, *, caption: str | None = None, label: str = "tab:uncertainty") -> str:
    """A Table III-style booktabs table of {axis: WuWeight}: per axis K, then one zero
    pair and one pole pair per line as a ± bj (rad/s), 4 significant figures."""
    from armfit.tables import sig4

    def pair(r) -> str:
        return f"${sig4(r.real)} \\pm {sig4(abs(r.imag))}j$"

    cap = caption or (r"Uncertainty weights $W_u(s) = K \prod_i (s - z_i) / \prod_i (s - p_i)$"
                      r" (eq.~7), $s$ in rad/s; each zero and pole is a conjugate pair.")
    lines = [r"\begin{table}[t]", r"\centering", f"\\caption{{{cap}}}", f"\\label{{{label}}}",
             r"\begin{tabular}{cccc}", r"\toprule", r"Axis & $K$ & Zeros & Poles \\",
             r"\midrule"]
    for i, axis in enumerate(sorted(weights)):
        w = weights[axis]
        n = max(len(w.zeros), len(w.poles), 1)
        for k in range(n):
            cells = [axis.upper() if k == 0 else "", sig4(w.gain) if k == 0 else "",
                     pair(w.zeros[k]) if k < len(w.zeros) else "",
                     pair(w.poles[k]) if k < len(w.poles) else ""]
            lines.append(" & ".join(cells) + r" \\")
        if i < len(weights) - 1:
            lines.append(r"\midrule")
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}", ""]
    return "\n".join(lines)
