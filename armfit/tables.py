"""Tables of fitted parameters: the paper's Table I / II layout as CSV and LaTeX text.

Input is a params DataFrame (columns of :func:`armfit.io.artifacts.params_columns`:
``axis``, optional ``grip_N``, the parameters in SI units, ``<p>_lo``/``<p>_hi``, fit
statistics). Output is text; writing it is the caller's business.

Layout (Fu & Çavuşoğlu 2010, Tables I and II): one row per axis (Table II) or per
axis × grip force (Table I), columns Ma (kg), k1 (N/m), k2 (N/m), b1 (N·s/m), b2 (N·s/m),
then any effect parameters with their units. Values are printed with 4 significant
figures like the paper; intervals, when asked for, as ``[lo, hi]`` under each value.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

from armfit.models.arm import BASE_PARAMS
from armfit.models.effects import get_effect

if TYPE_CHECKING:   # pandas is imported where a table is made (it takes ~0.15 s)
    import pandas as pd

#: Column names of the paper's tables (as in armfit/data/*.csv) for the base parameters.
PAPER_COLUMNS: dict[str, str] = {
    "Ma": "Ma_kg", "k1": "k1_N_per_m", "k2": "k2_N_per_m",
    "b1": "b1_Ns_per_m", "b2": "b2_Ns_per_m"}

_LATEX_BASE = {"Ma": r"$M_a$", "k1": r"$k_1$", "k2": r"$k_2$", "b1": r"$b_1$",
               "b2": r"$b_2$"}
_LATEX_UNIT = {"kg": "kg", "N/m": "N/m", "N*s/m": r"N$\cdot$s/m", "s": "s", "Hz": "Hz",
               "1": "--"}


def param_names(df: pd.DataFrame) -> list[str]:
    """The parameter columns of a params DataFrame, in model order: the base parameters,
    then the parameters of each effect the rows list, in the order they first appear (a
    table may hold one model per axis; a row's cells of an effect it lacks are empty)."""
    names = [p.name for p in BASE_PARAMS]
    specs = df["effects"] if "effects" in df.columns else []
    for spec in dict.fromkeys(s for s in specs if isinstance(s, str)):
        for e in (get_effect(n) for n in spec.split(";") if n):
            names += [q for p in e.params if (q := f"{e.name}.{p.name}") not in names]
    return names


def cell_names(value) -> list[str]:
    """The parameter names of an ``at_bound`` or ``held`` cell of a params table
    (";"-separated; NaN, None or "" → none).

    Parameters
    ----------
    value : str or float or None

    Returns
    -------
    list of str
    """
    return [n for n in value.split(";") if n] if isinstance(value, str) else []


def unit_of(name: str) -> str:
    """SI unit of a parameter: a base parameter's, or an effect parameter's (``effect.param``)."""
    base = {p.name: p.unit for p in BASE_PARAMS}
    if name in base:
        return base[name]
    eff, _, par = name.partition(".")
    return {p.name: p.unit for p in get_effect(eff).params}[par]


def paper_layout(df: pd.DataFrame, *, ci: bool = False) -> pd.DataFrame:
    """The params in the paper's column names (``Ma_kg``, ``k1_N_per_m``, …; effect
    parameters keep ``<effect>.<param>``), ``grip_N`` only for grip fits; with ``ci``
    each value is followed by ``<col>_lo`` and ``<col>_hi``."""
    import pandas as pd
    out = pd.DataFrame({"axis": df["axis"].astype(str)})
    if "grip_N" in df.columns:
        out["grip_N"] = df["grip_N"].astype(float)
    for n in param_names(df):
        col = PAPER_COLUMNS.get(n, n)
        out[col] = df[n].astype(float)
        if ci:
            out[f"{col}_lo"] = df[f"{n}_lo"].astype(float)
            out[f"{col}_hi"] = df[f"{n}_hi"].astype(float)
    return out.reset_index(drop=True)


def csv_text(df: pd.DataFrame, *, ci: bool = False) -> str:
    """:func:`paper_layout` as CSV text (4 significant figures, as the paper)."""
    lay = paper_layout(df, ci=ci)
    for c in lay.columns[1:]:
        lay[c] = [f"{v:g}" if c == "grip_N" else sig4(v) for v in lay[c]]
    return lay.to_csv(index=False, lineterminator="\n")


def sig4(v: float) -> str:
    """A number with 4 significant figures, trailing zeros kept (7.410, 704.2, 4877);
    integers from 10⁴ up printed whole; NaN as an empty string."""
    if v is None or not math.isfinite(v):
        return ""
    if abs(v) >= 1e4:
        return f"{v:.0f}"
    return f"{v:#.4g}".rstrip(".")


def _tex(text: str) -> str:
    out = text.replace("\\", r"\textbackslash{}")
    for ch in "_&%#$":
        out = out.replace(ch, "\\" + ch)
    return out


def _header(name: str) -> str:
    label = _LATEX_BASE.get(name, r"\texttt{" + _tex(name) + "}")
    unit = unit_of(name)
    return f"{label} ({_LATEX_UNIT.get(unit, _tex(unit))})"


def latex_table(df: pd.DataFrame, *, ci: bool = False, caption: str | None = None,
                label: str | None = None) -> str:
    """A booktabs ``table`` laid out like the paper's Table I (with a grip column) or
    Table II (without). Axes are rows groups separated by ``\\midrule``; with ``ci`` the
    95 % interval ``[lo, hi]`` follows each value in small type. A value whose parameter
    is listed in the row's ``at_bound`` gets a dagger and the table a footnote. Needs
    ``\\usepackage{booktabs}`` in the document. A value listed in the row's ``held``
    (held fixed at a value estimated elsewhere, e.g. an apparatus latency estimated from
    every trial of the axis) gets a double dagger and no interval; an effect the row's
    model lacks, an empty cell."""
    names = param_names(df)
    grip = "grip_N" in df.columns
    first_cols = ["Axis"] + (["Grip (N)"] if grip else [])
    cols = "l" + ("c" if grip else "") + "r" * len(names)
    lines = [r"\begin{table}[t]", r"\centering"]
    if caption:
        lines.append(r"\caption{" + _tex(caption) + "}")
    if label:
        lines.append(r"\label{" + label + "}")
    lines += [r"\begin{tabular}{" + cols + "}", r"\toprule",
              " & ".join(first_cols + [_header(n) for n in names]) + r" \\", r"\midrule"]
    prev_axis = None
    any_stuck = any_held = False
    for _, row in df.iterrows():
        stuck = cell_names(row["at_bound"]) if "at_bound" in df.columns else []
        held = cell_names(row["held"]) if "held" in df.columns else []
        axis = str(row["axis"]).upper()
        if prev_axis is not None and axis != prev_axis:
            lines.append(r"\midrule")
        cells = [axis if axis != prev_axis else ""]
        prev_axis = axis
        if grip:
            cells.append(f"{float(row['grip_N']):g}")
        for n in names:
            cell = sig4(float(row[n]))
            if n in stuck:
                cell += r"$^\dagger$"
                any_stuck = True
            if n in held:
                cell += r"$^\ddagger$"
                any_held = True
            elif ci and cell:
                cell += (r" {\scriptsize[" + sig4(float(row[f'{n}_lo'])) + ", "
                         + sig4(float(row[f'{n}_hi'])) + "]}")
            cells.append(cell)
        lines.append(" & ".join(cells) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    if any_stuck:
        lines += [r"\par\smallskip{\footnotesize $^\dagger$ at a physical bound of the fit "
                  r"(within 1\,\% of its range): a limit, not an estimate.}"]
    if any_held:
        lines += [r"\par\smallskip{\footnotesize $^\ddagger$ held at the value estimated "
                  r"jointly from every trial of the axis (an effect of the apparatus, "
                  r"shared by the trials; for one whose values differ between subjects, "
                  r"the subjects' mean), not fitted here.}"]
    lines += [r"\end{table}"]
    return "\n".join(lines) + "\n"


def caption_for(which: str, ci_method: Sequence[str] = ()) -> str:
    """Default caption: what was fitted and how the intervals were obtained."""
    what = ("Grip-dependent arm parameters (fit to the mean per axis and grip force)"
            if which == "grip" else
            "Nominal arm parameters (fit to the median per axis)")
    names = {"jacobian": "from the Jacobian"}
    methods = sorted(set(ci_method))
    if methods:
        what += "; 95 % intervals " + ", ".join(
            names.get(m, m.replace("bootstrap-", "from a bootstrap over subjects, ")
                      + (" resamples" if m.startswith("bootstrap-") else ""))
            for m in methods)
    return what + "."


def wu_latex(weights, *, caption: str | None = None, label: str = "tab:uncertainty") -> str:
    """A Table III-style booktabs table of {axis: WuWeight}: per axis K, then one zero
    pair and one pole pair per line as a ± bj (rad/s), 4 significant figures."""

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


__all__ = [
    "PAPER_COLUMNS", "cell_names", "param_names", "unit_of", "paper_layout", "csv_text", "sig4",
    "latex_table", "caption_for", "wu_latex",
]
