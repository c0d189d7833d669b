"""Speed of the study simulator: a paper-size study (81 trials, 9 subjects x 3 axes x 3
grips at 1 kHz), simulated in memory and written as Parquet by `armfit simulate`.

Run: .venv/bin/python benchmarks/bench_simulate.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from click.testing import CliRunner

from armfit.cli.main import cli
from armfit.simulation import StudyConfig, plan_study, simulate_trial


def simulate_only(duration: tuple[float, float]) -> tuple[float, float, float]:
    cfg = StudyConfig(duration_s=duration)
    t0, c0 = time.perf_counter(), time.process_time()
    plans = plan_study(cfg)
    for plan in plans:
        simulate_trial(plan, cfg)
    return (time.perf_counter() - t0, time.process_time() - c0,
            sum(p.duration_s for p in plans))


def simulate_and_write(fmt: str) -> tuple[float, int]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "study"
        t0 = time.perf_counter()
        res = CliRunner().invoke(cli, ["-q", "simulate", "-o", str(out), "--format", fmt])
        elapsed = time.perf_counter() - t0
        if res.exit_code != 0:
            raise SystemExit(res.output)
        size = sum(p.stat().st_size for p in out.iterdir())
    return elapsed, size


def main() -> None:
    for duration in ((100.0, 100.0), (50.0, 100.0)):
        elapsed, cpu, seconds = simulate_only(duration)
        print(f"simulate 81 trials of {duration[0]:g}-{duration[1]:g} s ({seconds:.0f} s of "
              f"data) in memory: {elapsed:.2f} s wall, {cpu:.2f} s CPU")
    for fmt in ("parquet", "csv.gz"):
        elapsed, size = simulate_and_write(fmt)
        print(f"armfit simulate (default 81 trials of 50-100 s) to {fmt}: {elapsed:.2f} s, "
              f"{size / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
