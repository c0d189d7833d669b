"""Speed of `armfit run` on a paper-size study (9 subjects x 3 axes x 3 grips, 50-100 s
trials at 1 kHz, as `armfit simulate` makes by default).

Simulates the study into a temporary folder first (not timed), then times
`armfit run STUDY -o OUT --jobs 2` as a user runs it (a fresh process, wall time), with
the adopted model (`--adopt auto`) and with the base model throughout (`--adopt none`),
alternated, best of --repeat each, and prints the per-stage times and the ratio
adopted / none: what the adopted model's refits cost. Targets: <= 12 s on 2 cores;
adopted / none <= 1.30 with a hidden effect. The load average is printed (a shared
machine inflates the times).

With ``--against-null`` (and ``--effect``) it compares what a user sees instead: the
study with the hidden effect against the same study simulated without it (same seed),
both with ``--adopt auto``, alternated: effect / null is what the diagnosis, the adopted
model and everything computed with it cost. Target: effect / null <= 1.30.
Run: .venv/bin/python benchmarks/bench_run.py [--jobs N] [--seed S] [--no-figures]
     [--effect delay=0.012]  (a hidden effect: the diagnosis names it, adopted)
     [--against-null]        (with --effect: effect study vs null study, both adopted)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bytecode import start


def armfit(*args: str) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("armfit")
    return subprocess.run([str(exe), *args], capture_output=True, text=True, check=True)


def timed_run(study: Path, out: Path, args, adopt: str) -> tuple[float, dict]:
    """One `armfit run` as a user runs it (a fresh process): (wall s, its --json)."""
    cmd = ["run", str(study), "-o", str(out), "--jobs", str(args.jobs), "--json",
           "--adopt", adopt]
    if args.no_figures:
        cmd.append("--no-figures")
    t0 = time.perf_counter()
    res = armfit("-q", *cmd)
    return time.perf_counter() - t0, json.loads(res.stdout)


def simulate(study: Path, args, effect: str | None) -> None:
    t0 = time.perf_counter()
    armfit("-q", "simulate", "-o", str(study), "--seed", str(args.seed),
           *(["--effect", effect] if effect else []))
    n = len(list(study.iterdir()))
    print(f"simulated {n} trials{' with ' + effect if effect else ''} in "
          f"{time.perf_counter() - t0:.1f} s (not timed below)")


def against_null(args) -> None:
    """The study with the effect against the study without it, both adopted."""
    times: dict[str, list[float]] = {"effect": [], "null": []}
    docs: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="armfit-bench-run-") as tmp:
        studies = {"effect": Path(tmp) / "effect", "null": Path(tmp) / "null"}
        simulate(studies["effect"], args, args.effect)
        simulate(studies["null"], args, None)
        for i in range(args.repeat):
            # the two in turn, the first of a pair alternating between pairs
            for name in ("effect", "null") if i % 2 == 0 else ("null", "effect"):
                wall, docs[name] = timed_run(studies[name], Path(tmp) / f"out-{name}-{i}",
                                             args, "auto")
                times[name].append(wall)
                print(f"  run {i + 1} {name:6s} {wall:6.1f} s", flush=True)
    ratios = [e / n for e, n in zip(times["effect"], times["null"], strict=True)]
    print(f"armfit run STUDY -o OUT --jobs {args.jobs} --json"
          + (" --no-figures" if args.no_figures else "") + " (--adopt auto)")
    for name in ("effect", "null"):
        stages = ", ".join(f"{k} {v:.1f}" for k, v in docs[name]["timings_s"].items())
        print(f"  {name:6s} median {statistics.median(times[name]):6.1f} s "
              f"(min {min(times[name]):.1f}); last run's stages: {stages}")
    print(f"  effect / null: median of the pairs {statistics.median(ratios):.2f} "
          f"(each pair: {', '.join(f'{r:.2f}' for r in ratios)}; target <= 1.30)")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")
    print("  adopted: " + "; ".join(f"{a}: {'+'.join(v['effects']) or 'base'}"
                                    for a, v in docs["effect"]["adoption"]["axes"].items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--effect", default=None, help="simulate with this effect (NAME=VALUE)")
    ap.add_argument("--against-null", action="store_true",
                    help="with --effect: the effect study against the null study, both "
                         "--adopt auto")
    ap.add_argument("--repeat", type=int, default=2,
                    help="runs of each variant, alternated; the best of each is reported")
    args = ap.parse_args()
    start()
    if args.against_null:
        if not args.effect:
            ap.error("--against-null needs --effect")
        against_null(args)
        return
    with tempfile.TemporaryDirectory(prefix="armfit-bench-run-") as tmp:
        study = Path(tmp) / "study"
        simulate(study, args, args.effect)
        # the adopted model (auto) against the base model throughout (none), alternated
        # in one session so that both see the same machine load
        best: dict[str, tuple[float, dict]] = {}
        for i in range(args.repeat):
            for adopt in ("auto", "none"):
                wall, doc = timed_run(study, Path(tmp) / f"out-{adopt}-{i}", args, adopt)
                if adopt not in best or wall < best[adopt][0]:
                    best[adopt] = (wall, doc)
    wall, doc = best["auto"]
    print(f"armfit run STUDY -o OUT --jobs {args.jobs} --json"
          + (" --no-figures" if args.no_figures else "") + " (--adopt auto)")
    for stage, sec in doc["timings_s"].items():
        print(f"  {stage:16s} {sec:6.1f} s")
    print("  (with --jobs > 1 the diagnosis overlaps fit-nominal)")
    print(f"  {'run, wall':16s} {doc['total_s']:6.1f} s")
    print(f"  {'process, wall':16s} {wall:6.1f} s (target <= 12 s)")
    base = best["none"][0]
    print(f"  --adopt none    {base:6.1f} s; adopted / none {wall / base:.2f} "
          "(the refits of the adopted model; target <= 1.30 with an effect)")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")
    for axis, d in doc["diagnosis"].items():
        print(f"  axis {axis}: {d['missing_effect'] or 'no missing effect'}")
    print("  adopted: " + "; ".join(f"{a}: {'+'.join(v['effects']) or 'base'}"
                                    for a, v in doc["adoption"]["axes"].items()))


if __name__ == "__main__":
    main()
