"""Speed of the arm model fits: all 12 fits of a study (9 grip + 3 nominal).

Target: <= 2 s in total on 2 cores. The study is simulated (3 subjects, all axes and
grips, 50-100 s trials, default noise and between-subject variability) and estimated with
`armfit estimate` defaults (H1 on a 40-per-decade grid, 0.1-30 Hz); only the fits are
timed, with both costs. A second figure times the fits on the paper's own frequency grid
(0.01 Hz bins, 3000 points) from Table I / II exact responses.

Run: .venv/bin/python benchmarks/bench_fit.py
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from armfit.cli.main import cli
from armfit.data import paper_table
from armfit.fitting import PAPER_BANDS, fit_response, fit_study
from armfit.models.arm import PARAM_NAMES, ClosedLoopModel
from armfit.spectra import Spectra

REPEATS = 3


def make_spectra(folder: Path) -> Path:
    runner = CliRunner()
    for args in (["simulate", "-o", str(folder / "study"), "--subjects", "3", "--seed", "7"],
                 ["estimate", str(folder / "study"), "-o", str(folder / "spectra.parquet")]):
        res = runner.invoke(cli, ["-q", *args])
        if res.exit_code:
            raise SystemExit(f"{args[0]} failed: {res.stderr}")
    return folder / "spectra.parquet"


def time_study(spectra, cost: str) -> list[float]:
    out = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        grip = fit_study(spectra, which="grip", cost=cost)
        nominal = fit_study(spectra, which="nominal", cost=cost)
        out.append(time.perf_counter() - t0)
        assert len(grip.fits) == 9 and len(nominal.fits) == 3
    return out


def time_paper_grid(cost: str) -> float:
    f = np.arange(1, 3001) * 0.01
    cols = ["Ma_kg", "k1_N_per_m", "k2_N_per_m", "b1_Ns_per_m", "b2_Ns_per_m"]
    jobs = []
    for name in ("grip", "nominal"):
        for _, r in paper_table(name).iterrows():
            model = ClosedLoopModel.for_axis(r["axis"])
            truth = dict(zip(PARAM_NAMES, r[cols].astype(float), strict=True))
            jobs.append((model, model.response(f, truth), PAPER_BANDS[r["axis"]]))
    t0 = time.perf_counter()
    for model, h, band in jobs:
        fit_response(model, f, h, cost=cost, band=band)
    return time.perf_counter() - t0


def main() -> None:
    print(f"cores available: {os.cpu_count()}, load average: "
          f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        path = make_spectra(Path(tmp))
        print(f"simulated + estimated the study in {time.perf_counter() - t0:.1f} s (not timed "
              "below)")
        spectra = Spectra.read(path).to_frame()
        n_bins = int(((spectra["level"] == "mean") & (spectra["kind"] == "measured")
                      & (spectra["axis"] == "x") & (spectra["out_axis"] == "x")
                      & (spectra["grip_N"] == 1.0)).sum())
        print(f"grid: {n_bins} frequencies per response")
        for cost in ("complex", "paper"):
            times = time_study(spectra, cost)
            print(f"12 fits (9 grip + 3 nominal), cost={cost}: best {min(times):.2f} s, "
                  f"median {statistics.median(times):.2f} s over {REPEATS} runs "
                  f"(target <= 2 s)")
    for cost in ("complex", "paper"):
        print(f"12 fits of Table I/II exact responses on the paper's 3000-bin grid, "
              f"cost={cost}: {time_paper_grid(cost):.2f} s")


if __name__ == "__main__":
    main()
