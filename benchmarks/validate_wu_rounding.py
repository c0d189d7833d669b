"""Validation of the Wu envelope fit's steps (armfit.uncertainty.SEARCH_STEP_DB): does
the fitted weight move when W_max changes by rounding?

Eleven studies: eight simulated by `armfit simulate` (30-40 s trials; seeds 2-9: three
without an effect, one with more and one with less subject variability, coarse
quantisation with a noisy sensor, a 8 ms delay, a 15 ms delay on Z only, a reflex loop)
and sample_data/ (study, hidden, spring), each through `armfit run --no-figures`. Each
axis's W_max (wu_wmax.csv, its band from wu_summary.csv) is fitted as `fit-uncertainty`
fits it, then again from W_max times (1 + eps N(0, 1)) for three draws at eps 1e-9 and
1e-7, with the search on 0.01 dB steps and without steps (SEARCH_STEP_DB = 0). Prints,
per setting, how many of the 33 weights moved (mean gap changed by more than 1e-4 dB),
the largest change, and the mean gap averaged over the weights, then a table per weight.

Takes about 8 minutes on 2 cores.

Run: .venv/bin/python benchmarks/validate_wu_rounding.py [--work DIR]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd

from armfit import uncertainty as U

ROOT = Path(__file__).resolve().parents[1]
ARMFIT = str(Path(sys.executable).with_name("armfit"))
#: (name, `armfit simulate` options) of the simulated studies
SIMULATED = [
    ("null-2", ["--seed", "2"]),
    ("null-3-var0.3", ["--seed", "3", "--variability", "0.3"]),
    ("null-4-5subjects", ["--seed", "4", "--subjects", "5"]),
    ("delay-8ms", ["--seed", "5", "--effect", "delay=0.008"]),
    ("delay-15ms-z", ["--seed", "6", "--effect", "delay=0.015", "--effect-axes", "z"]),
    ("reflex", ["--seed", "7", "--effect", "reflex=gain_N_per_m:100,delay_s:0.03"]),
    ("null-8-var0.05", ["--seed", "8", "--variability", "0.05"]),
    ("quantum-0.1mm", ["--seed", "9", "--quantum", "1e-4", "--noise", "1e-5"]),
]
EPS = (1e-9, 1e-7)
DRAWS = 3
MOVED_DB = 1e-4


def run_studies(work: Path) -> list[Path]:
    """`armfit run` of every study into ``work`` (kept: a second call reuses them)."""
    outs = []
    for name, opts in SIMULATED:
        out = work / f"run-{name}"
        if not (out / "wu_summary.csv").exists():
            study = work / f"study-{name}"
            subprocess.run([ARMFIT, "-q", "simulate", "-o", str(study), "--duration", "30,40",
                            "--overwrite", *opts], check=True)
            subprocess.run([ARMFIT, "-q", "run", str(study), "-o", str(out), "--jobs", "2",
                            "--no-figures", "--overwrite"], check=True)
        outs.append(out)
    for name in ("study", "hidden", "spring"):
        out = work / f"run-sample-{name}"
        if not (out / "wu_summary.csv").exists():
            subprocess.run([ARMFIT, "-q", "run", str(ROOT / "sample_data" / name), "-o",
                            str(out), "--jobs", "2", "--no-figures", "--overwrite"], check=True)
        outs.append(out)
    return outs


def weights(outs: list[Path]) -> list[tuple[str, np.ndarray, np.ndarray, tuple]]:
    """(label, f_hz, W_max, band) of every axis of every run."""
    found = []
    for out in outs:
        pts = pd.read_csv(out / "wu_wmax.csv")
        summ = pd.read_csv(out / "wu_summary.csv")
        for _, row in summ[summ["weight"] == "fitted"].iterrows():
            a = pts[pts["axis"] == row["axis"]]
            found.append((f"{out.name.removeprefix('run-')}:{row['axis']}",
                          a["freq_hz"].to_numpy(), 10 ** (a["target_db"].to_numpy() / 20),
                          (float(row["band_lo_hz"]), float(row["band_hi_hz"]))))
    return found


def one(task) -> dict:
    """The mean gaps (dB) of one weight's fits: as given, then each draw of each eps."""
    label, f, w, band, step, seed = task
    U.SEARCH_STEP_DB = step
    rng = np.random.default_rng(seed)
    gaps = {"given": U.fit_wu(f, w, band=band).mean_gap_db}
    for eps in EPS:
        gaps[eps] = [U.fit_wu(f, w * (1 + eps * rng.standard_normal(w.size)),
                              band=band).mean_gap_db for _ in range(DRAWS)]
    return {"weight": label, "step_db": step, **gaps}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir())
                    / "armfit-validate-wu-rounding", help="folder for the studies and runs")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    found = weights(run_studies(args.work))
    tasks = [(label, f, w, band, step, i) for step in (U.SEARCH_STEP_DB, 0.0)
             for i, (label, f, w, band) in enumerate(found)]
    with ProcessPoolExecutor(2) as pool:
        rows = list(pool.map(one, tasks))
    print(f"{len(found)} weights; moved: mean gap changed by more than {MOVED_DB:g} dB "
          f"in any of {DRAWS} draws\n")
    print("| search | eps | weights moved | largest change (dB) | mean gap, mean over "
          "the weights (dB) |")
    print("|---|---|---|---|---|")
    table = []
    for step in (U.SEARCH_STEP_DB, 0.0):
        sel = [r for r in rows if r["step_db"] == step]
        what = f"{step:g} dB steps" if step else "no steps"
        mean_gap = np.mean([r["given"] for r in sel])
        for eps in EPS:
            change = np.array([max(abs(g - r["given"]) for g in r[eps]) for r in sel])
            print(f"| {what} | {eps:g} | {int(np.sum(change > MOVED_DB))} of {len(sel)} | "
                  f"{change.max():.4f} | {mean_gap:.4f} |")
        for r in sel:
            table.append((r["weight"], what, r["given"],
                          *(max(abs(g - r["given"]) for g in r[eps]) for eps in EPS)))
    print("\n| weight | search | mean gap (dB) | change at 1e-9 | change at 1e-7 |")
    print("|---|---|---|---|---|")
    for label, what, gap, c9, c7 in sorted(table):
        print(f"| {label} | {what} | {gap:.4f} | {c9:.2e} | {c7:.2e} |")


if __name__ == "__main__":
    main()
