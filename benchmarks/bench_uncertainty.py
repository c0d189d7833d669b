"""Speed of the uncertainty-weight fit: W_max from 27 trials per axis and Wu for all three
axes (target: <= 5 s on 2 cores).

Trials are synthetic derived arm dynamics: H_ARM of a Table I row (axis x grip) with each
parameter scaled by a per-subject log-normal factor (sd 0.15), times (1 + estimator noise
of 5 % rms); the nominal is Table II. Two grids: the log grid `armfit estimate` writes
(40 points per decade, 0.1–30 Hz) and the paper's 0.01 Hz bins (0.01–30 Hz, 3000 bins).
Timed: `fit_weights` from in-memory tables (W_max, automatic order search over 0–5
pairs, envelope checks), default envelope cost and the paper's cost.

Run: .venv/bin/python benchmarks/bench_uncertainty.py
"""

from __future__ import annotations

import time

import numpy as np
import pandas as pd

from armfit.data import paper_table
from armfit.models.arm import h_arm
from armfit.uncertainty import fit_weights

COLS = dict(Ma="Ma_kg", k1="k1_N_per_m", k2="k2_N_per_m", b1="b1_Ns_per_m", b2="b2_Ns_per_m")


def study_tables(f_hz: np.ndarray, seed: int = 0) -> tuple[pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(seed)
    grip = paper_table("grip")
    nominal = paper_table("nominal")
    parts = []
    for axis in "xyz":
        for s in range(9):
            factors = np.exp(0.15 * rng.standard_normal(5))
            for _, row in grip[grip["axis"] == axis].iterrows():
                theta = {k: row[c] * fac for (k, c), fac in zip(COLS.items(), factors,
                                                                strict=True)}
                noise = 0.05 * (rng.standard_normal(f_hz.size)
                                + 1j * rng.standard_normal(f_hz.size)) / np.sqrt(2)
                h = h_arm(f_hz, **theta) * (1 + noise)
                parts.append(pd.DataFrame({
                    "level": "trial", "subject": f"{s + 1:02d}", "axis": axis,
                    "grip_N": float(row["grip_N"]), "run": pd.NA, "kind": "derived",
                    "out_axis": axis, "method": "tfestimate", "freq_hz": f_hz,
                    "re": h.real, "im": h.imag}))
    params = pd.DataFrame([{"axis": r["axis"], **{k: r[c] for k, c in COLS.items()},
                            "mp_kg": np.nan, "effects": ""} for _, r in nominal.iterrows()])
    params["mp_kg"] = [0.09, 0.095, 0.091]
    return pd.concat(parts, ignore_index=True), params


def main() -> None:
    grids = {
        "estimate log grid (0.1-30 Hz, 40/decade)": np.logspace(-1, np.log10(30), 100),
        "paper grid (0.01-30 Hz, 0.01 Hz bins)": np.arange(1, 3001) * 0.01,
    }
    for name, f in grids.items():
        spectra, params = study_tables(f)
        n_tr = spectra.groupby(["axis", "subject", "grip_N"]).ngroups // 3
        print(f"{name}: {f.size} frequencies, {n_tr} trials per axis")
        for cost in ("envelope", "paper"):
            best, best_cpu = np.inf, np.inf
            for _ in range(2):
                t0, c0 = time.perf_counter(), time.process_time()
                res = fit_weights(spectra, params, cost=cost)
                best = min(best, time.perf_counter() - t0)
                best_cpu = min(best_cpu, time.process_time() - c0)
            orders = ", ".join(f"{r.axis}:{r.result.order}" for r in res)
            cover = ", ".join(f"{r.checks[('fitted', 'wmax')].coverage_pct:.0f}%" for r in res)
            med = ", ".join(f"{r.checks[('fitted', 'wmax')].tightness_median_db:.2f}"
                            for r in res)
            print(f"  cost={cost:8s} all 3 axes: {best:5.2f} s wall, {best_cpu:5.2f} s CPU "
                  f"(best of 2)  orders {orders}  coverage {cover}  median gap dB {med}")


if __name__ == "__main__":
    main()
