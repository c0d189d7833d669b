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
    "flags",      # comma-separated: low_coherence, saturation, drift (empty if none)
)

# ---------------------------------------------------------------------------
# Fitted parameters (written by `armfit fit-grip` / `fit-nominal`): CSV.
# ---------------------------------------------------------------------------
