"""Speed of `armfit run` on a paper-size study (9 subjects x 3 axes x 3 grips, 50-100 s
trials at 1 kHz, as `armfit simulate` makes by default).

Simulates the study into a temporary folder first (not timed), then times
`armfit run STUDY -o OUT --jobs 2` as a user runs it (a fresh process, wall time) and
prints the per-stage times it reports and the diagnose/estimate ratio of the run.
Target: <= 12 s on 2 cores. The load average is printed (a shared machine inflates
the times).
Run: .venv/bin/python benchmarks/bench_run.py [--jobs N] [--seed S] [--no-figures]
     [--effect delay=0.012]  (a hidden effect: the diagnosis names it, one more refit)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def armfit(*args: str) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("armfit")
    return subprocess.run([str(exe), *args], capture_output=True, text=True, check=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--effect", default=None, help="simulate with this effect (NAME=VALUE)")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(prefix="armfit-bench-run-") as tmp:
        study, out = Path(tmp) / "study", Path(tmp) / "out"
        t0 = time.perf_counter()
        armfit("-q", "simulate", "-o", str(study), "--seed", str(args.seed),
               *(["--effect", args.effect] if args.effect else []))
        n = len(list(study.iterdir()))
        print(f"simulated {n} trials in {time.perf_counter() - t0:.1f} s (not timed below)")
        cmd = ["run", str(study), "-o", str(out), "--jobs", str(args.jobs), "--json"]
        if args.no_figures:
            cmd.append("--no-figures")
        t0 = time.perf_counter()
        res = armfit("-q", *cmd)
        wall = time.perf_counter() - t0
        doc = json.loads(res.stdout)
    print(f"armfit {' '.join(cmd[:1] + ['STUDY'] + cmd[2:3] + ['OUT'] + cmd[4:])}")
    for stage, sec in doc["timings_s"].items():
        print(f"  {stage:16s} {sec:6.1f} s")
    print("  (with --jobs > 1 the diagnosis overlaps the stages listed before it)")
    print(f"  {'run, wall':16s} {doc['total_s']:6.1f} s")
    print(f"  {'process, wall':16s} {wall:6.1f} s (target <= 12 s)")
    est, diag = doc["timings_s"].get("estimate"), doc["timings_s"].get("diagnose")
    if est and diag:
        print(f"  diagnose/estimate {diag / est:.2f} (the diagnose stage's own time)")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")
    for axis, d in doc["diagnosis"].items():
        print(f"  axis {axis}: {d['missing_effect'] or 'no missing effect'}")


if __name__ == "__main__":
    main()
