"""Time `armfit plot`'s figures on a paper-size study and print the figures.

Paper size: 9 subjects x 3 grips x 3 axes = 81 measured and 81 derived trial responses,
the 9 grip means and 3 medians, on two grids: the log grid `armfit estimate` writes by
default (0.1-30 Hz, 40 points per decade: 100 points) and the paper's 0.01 Hz grid over
0.01-30 Hz (3000 points, the worst case). Each figure kind is drawn and written as PNG,
SVG and PDF; the script prints build and write times (s) and file sizes (kB).

Then the figures stage of `armfit run` on the log grid: Figs. 5, 6 and 7 (bode,
uncertainty, literature) built and written as PNG one after the other, best of --repeat
(wall and CPU seconds; target <= 2 s), and as `run --jobs 2` draws them (a task each in
2 worker processes, wall time); then the figures of its later stages (one
residual figure per axis, the stability figure of the grip fits), for reference. On a
loaded machine the wall times are inflated; the CPU times are the steadier measure.

    .venv/bin/python benchmarks/bench_plot.py [--repeat 3] [--stage-only]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from armfit import figures, workers
from armfit.data import paper_table
from armfit.io.schema import SPECTRA_COLUMNS
from armfit.models.arm import DEVICE_MASS_KG, h_arm, h_cl
from armfit.pipeline import _draw_task  # the task `run` submits for each figure
from armfit.uncertainty import read_wu

GRIDS = {"log grid, 100 points": np.geomspace(0.1, 30.0, 100),
         "0.01 Hz grid, 3000 points": np.arange(1, 3001) * 0.01}
F = GRIDS["log grid, 100 points"]
COLS = {"Ma_kg": "Ma", "k1_N_per_m": "k1", "k2_N_per_m": "k2", "b1_Ns_per_m": "b1",
        "b2_Ns_per_m": "b2"}


def frame(h, **ident):
    d = {c: np.nan for c in SPECTRA_COLUMNS}
    d.update(level="trial", subject=None, run=pd.NA, method="h1", freq_hz=F, re=h.real,
             im=h.imag, mag_db=20 * np.log10(np.abs(h)),
             phase_deg=np.degrees(np.unwrap(np.angle(h))), n=1, flags="")
    d.update(ident)
    d["out_axis"] = d["axis"]
    return pd.DataFrame({c: d[c] if np.ndim(d[c]) else [d[c]] * F.size
                         for c in SPECTRA_COLUMNS})


def agg(hs, **ident):
    mag = np.array([20 * np.log10(np.abs(h)) for h in hs])
    ph = np.array([np.degrees(np.unwrap(np.angle(h))) for h in hs])
    m, p = mag.mean(0), ph.mean(0)
    h = 10 ** (m / 20) * np.exp(1j * np.radians(p))
    return frame(h, **ident).assign(
        se_db=mag.std(0, ddof=1) / 3, se_deg=ph.std(0, ddof=1) / 3, n=len(hs),
        q25_db=np.percentile(mag, 25, 0), q75_db=np.percentile(mag, 75, 0),
        q25_deg=np.percentile(ph, 25, 0), q75_deg=np.percentile(ph, 75, 0))


def study() -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    rng = np.random.default_rng(0)
    grip = paper_table("grip").rename(columns=COLS)
    parts = []
    for axis in "xyz":
        pooled = []
        for _, r in grip[grip.axis == axis].iterrows():
            th = {k: r[k] for k in ("Ma", "k1", "k2", "b1", "b2")}
            hs = []
            for s in range(9):
                err = np.exp(rng.normal(0, 0.2, F.size) + 1j * rng.normal(0, 0.1, F.size))
                h = h_cl(F, **th, mp=DEVICE_MASS_KG[axis]) * err
                hs.append(h)
                parts.append(frame(h, axis=axis, grip_N=r.grip_N, subject=f"s{s}",
                                   kind="measured"))
                parts.append(frame(h_arm(F, **th) * err, axis=axis, grip_N=r.grip_N,
                                   subject=f"s{s}", kind="derived"))
            parts.append(agg(hs, axis=axis, grip_N=r.grip_N, kind="measured", level="mean"))
            pooled += hs
        parts.append(agg(pooled, axis=axis, grip_N=np.nan, kind="measured", level="median"))
    grip["mp_kg"] = [DEVICE_MASS_KG[a] for a in grip.axis]
    grip["effects"] = ""
    nominal = paper_table("nominal").rename(columns=COLS)
    nominal["mp_kg"] = [DEVICE_MASS_KG[a] for a in nominal.axis]
    nominal["effects"] = ""
    return pd.concat(parts, ignore_index=True), grip, nominal


def main() -> None:
    global F
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--stage-only", action="store_true",
                    help="only the figures stage of `armfit run`")
    args = ap.parse_args()
    if not args.stage_only:
        for name, grid in GRIDS.items():
            F = grid
            print(f"== {name}")
            bench()
    F = GRIDS["log grid, 100 points"]
    run_stage(args.repeat)


def run_stage(repeat: int) -> None:
    """The figures stage of `armfit run`: Figs. 5-7 as PNG, best of ``repeat``."""
    spectra, grip, nominal = study()
    with resources.as_file(resources.files("armfit.data")
                           .joinpath("table3_uncertainty_weights.csv")) as path:
        wu = read_wu(path)
    print("== figures stage of `armfit run` (bode, uncertainty, literature PNG; log grid)")
    walls, cpus = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(repeat):
            w0, c0 = time.perf_counter(), time.process_time()
            figures.save_figure(figures.bode_figure(spectra, grip), Path(tmp) / "bode.png",
                                overwrite=True)
            figures.save_figure(figures.uncertainty_figure(spectra, nominal, wu),
                                Path(tmp) / "uncertainty.png", overwrite=True)
            figures.save_figure(figures.literature_figure(grip.iloc[0]),
                                Path(tmp) / "literature.png", overwrite=True)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
            print(f"round {r + 1}: wall {walls[-1]:5.2f} s, CPU {cpus[-1]:5.2f} s")
    print(f"best: wall {min(walls):5.2f} s, CPU {min(cpus):5.2f} s (target <= 2 s)")
    # as `armfit run --jobs 2` draws them: each figure a task of the run's worker pool
    # (the figure's inputs travel to the worker)
    with workers.executor_for(jobs=2) as pool, tempfile.TemporaryDirectory() as tmp:
        tasks = [("bode_figure", (spectra, grip), Path(tmp) / "bode.png"),
                 ("uncertainty_figure", (spectra, nominal, wu), Path(tmp) / "unc.png"),
                 ("literature_figure", (grip.iloc[0],), Path(tmp) / "lit.png")]
        walls = []
        for _ in range(repeat):
            for t in tasks:
                t[2].unlink(missing_ok=True)
            w0 = time.perf_counter()
            for fut in [pool.submit(_draw_task, (fn, args, {}, path))
                        for fn, args, path in tasks]:
                fut.result()
            walls.append(time.perf_counter() - w0)
    print(f"in 2 worker processes, as `run --jobs 2` draws them: best wall "
          f"{min(walls):5.2f} s")
    print("== later figure stages of `armfit run` (residual per axis, stability PNG)")
    trials = grip.assign(subject=[f"s{i}" for i in range(len(grip))])
    walls, cpus = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeat):
            w0, c0 = time.perf_counter(), time.process_time()
            for axis in "xyz":
                figures.save_figure(figures.residual_figure(spectra, nominal, axis=axis),
                                    Path(tmp) / f"residual_{axis}.png", overwrite=True)
            figures.save_figure(figures.stability_figure(trials),
                                Path(tmp) / "stability.png", overwrite=True)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
    print(f"best: wall {min(walls):5.2f} s, CPU {min(cpus):5.2f} s")


def bench() -> None:
    t0 = time.perf_counter()
    spectra, grip, nominal = study()
    print(f"study: {len(spectra)} spectra rows, built in {time.perf_counter() - t0:.1f} s")
    with resources.as_file(resources.files("armfit.data")
                           .joinpath("table3_uncertainty_weights.csv")) as path:
        wu = read_wu(path)
    kinds = {
        "bode": lambda: figures.bode_figure(spectra, grip),
        # as `armfit plot residual` draws it without --band: the failing spans shaded
        "residual": lambda: figures.residual_figure(spectra, nominal),
        "uncertainty": lambda: figures.uncertainty_figure(spectra, nominal, wu),
        "literature": lambda: figures.literature_figure(grip.iloc[0]),
    }
    total = 0.0
    with tempfile.TemporaryDirectory() as tmp:
        for name, build in kinds.items():
            t = time.perf_counter()
            fig = build()
            t_build = time.perf_counter() - t
            cells = [f"{name:12s} build {t_build:5.2f} s"]
            total += t_build
            for ext in ("png", "svg", "pdf"):
                path = Path(tmp) / f"{name}.{ext}"
                t = time.perf_counter()
                figures.save_figure(fig, path)
                dt = time.perf_counter() - t
                total += dt
                cells.append(f"{ext} {dt:5.2f} s {path.stat().st_size / 1024:7.0f} kB")
            print(" | ".join(cells))
    print(f"total (4 kinds, 3 formats each): {total:.1f} s")


if __name__ == "__main__":
    main()
