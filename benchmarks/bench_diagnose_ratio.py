"""Speed of `armfit diagnose` relative to `armfit estimate` on `sample_data/hidden`.

The README's tour, as a user runs it: `armfit estimate sample_data/hidden -o
spectra.parquet` (27 trials, 30-50 s at 1 kHz), `armfit fit-grip spectra.parquet -o
grip_params.csv`, then `armfit diagnose spectra.parquet --model grip_params.csv` (the
stepwise search over the whole effect library; it names the hidden delay on every axis).
The spectra and the grip fits are made once (not timed); then estimate and diagnose are
timed as whole processes (a fresh `armfit` each, wall time, both with --jobs N),
alternated A B A B ... so that both see the same machine load, and the ratio diagnose /
estimate is taken pair by pair; the median of the pairs is the figure. Target: <= 1.5.
The load average is printed before and after (a shared machine inflates both commands,
and not always alike).

Run: .venv/bin/python benchmarks/bench_diagnose_ratio.py [--jobs 2] [--repeat 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bytecode import compile_armfit

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "sample_data" / "hidden"


def armfit(*args: str) -> float:
    """Run ``armfit -q ARGS`` as a fresh process (outside any source tree); its wall time."""
    exe = Path(sys.executable).with_name("armfit")
    t = time.perf_counter()
    res = subprocess.run([str(exe), "-q", *args], capture_output=True, text=True,
                         cwd=tempfile.gettempdir())
    dt = time.perf_counter() - t
    if res.returncode:
        raise SystemExit(f"armfit {args[0]} failed: {res.stderr}")
    return dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=5, help="pairs timed (after one warm-up)")
    args = ap.parse_args()
    compile_armfit()    # stale bytecode would be timed too
    jobs = str(args.jobs)
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores",
          flush=True)
    with tempfile.TemporaryDirectory(prefix="armfit-bench-diag-") as tmp:
        spectra, grip = Path(tmp) / "spectra.parquet", Path(tmp) / "grip_params.csv"
        armfit("estimate", str(STUDY), "-o", str(spectra), "-j", jobs)
        armfit("fit-grip", str(spectra), "-o", str(grip))
        estimate = ("estimate", str(STUDY), "-o", str(Path(tmp) / "again.parquet"),
                    "-j", jobs, "--overwrite")
        diagnose = ("diagnose", str(spectra), "--model", str(grip), "-j", jobs)
        armfit(*estimate)      # warm-up: the file cache, the bytecode
        armfit(*diagnose)
        times: dict[str, list[float]] = {"estimate": [], "diagnose": []}
        for i in range(args.repeat):
            times["diagnose"].append(armfit(*diagnose))
            times["estimate"].append(armfit(*estimate))
            print(f"  pair {i + 1}: diagnose {times['diagnose'][-1]:.2f} s, estimate "
                  f"{times['estimate'][-1]:.2f} s", flush=True)
    ratios = [d / e for d, e in zip(times["diagnose"], times["estimate"], strict=True)]
    print(f"armfit diagnose SPECTRA --model GRIP -j {jobs} against "
          f"armfit estimate sample_data/hidden -o OUT -j {jobs}")
    for name, ts in times.items():
        print(f"  {name:8s} median {statistics.median(ts):.2f} s "
              f"(min {min(ts):.2f}, max {max(ts):.2f})")
    print(f"  diagnose / estimate: median of the pairs {statistics.median(ratios):.2f} "
          f"(min {min(ratios):.2f}, max {max(ratios):.2f}; target <= 1.5)")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
