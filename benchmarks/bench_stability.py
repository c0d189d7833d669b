"""Benchmark: K_max of every row of a paper-size per-trial params file (81 models).

The 81 rows are Table I's nine models, each varied per simulated subject (9 subjects,
parameters scaled by a fixed log-normal factor, sd 20 %), so the loops differ as real
per-trial fits do. Target: <= 2 s for all 81 rows at the defaults (T = 1 ms, B = 0,
d = 1), with and without the robust certificate. Run: .venv/bin/python
benchmarks/bench_stability.py
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from armfit.loop import WallSettings, stability_table
from armfit.models.params import paper_params
from armfit.uncertainty import read_weights_and_bands


def per_trial_table(n_subjects: int = 9, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    base = paper_params("grip")
    rows = []
    for s in range(n_subjects):
        t = base.copy()
        for n in ("Ma", "k1", "k2", "b1", "b2"):
            t[n] = t[n] * np.exp(0.2 * rng.standard_normal(len(t)))
        t["subject"] = f"S{s + 1:02d}"
        rows.append(t)
    out = pd.concat(rows, ignore_index=True)
    out.insert(0, "row", np.arange(1, len(out) + 1))
    return out


def main() -> None:
    table = per_trial_table()
    weights, bands, _ = read_weights_and_bands("paper")
    st = WallSettings()
    stability_table(table.iloc[:3], st)            # warm-up (imports)
    for label, kw in (("K_max", {}), ("K_max + certificate",
                                       {"weights": weights, "weights_band_hz": bands})):
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            res = stability_table(table, st, **kw)
            times.append(time.perf_counter() - t0)
        print(f"{label}: {len(res)} models in {min(times):.3f} s (best of 3; target 2 s); "
              f"K_max x min {res.loc[res.axis == 'x', 'k_max_N_per_m'].min():.0f} N/m")


if __name__ == "__main__":
    main()
