"""Speed of `armfit diagnose` on a paper-size study, and its verdicts.

Target: <= 20 s on 2 cores. The study is simulated with the paper's protocol (9 subjects
x 3 axes x 3 grips, 50-100 s trials at 1 kHz, default noise, drift and between-subject
variability), estimated with `armfit estimate` defaults and fitted with `armfit
fit-grip`; only `diagnose` is timed, with --jobs 1 and --jobs 2. Pass an effect spec
(e.g. `delay=0.01`) as the first argument to hide an effect in the study.

Run: .venv/bin/python benchmarks/bench_diagnose.py [EFFECT]
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

from click.testing import CliRunner

from armfit.cli.main import cli


def run(args: list[str]) -> str:
    res = CliRunner().invoke(cli, ["-q", *args])
    if res.exit_code:
        raise SystemExit(f"{args[0]} failed: {res.stderr or res.output}")
    return res.stdout


def main() -> None:
    effect = sys.argv[1] if len(sys.argv) > 1 else None
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        sim = ["simulate", "-o", str(d / "study"), "--seed", "2026"]
        if effect:
            sim += ["--effect", effect]
        t = time.perf_counter()
        run(sim)
        run(["estimate", str(d / "study"), "-o", str(d / "spectra.parquet"), "-j", "2"])
        run(["fit-grip", str(d / "spectra.parquet"), "-o", str(d / "grip.csv")])
        print(f"set-up (simulate, estimate, fit-grip): {time.perf_counter() - t:.1f} s")
        for jobs in (1, 2):
            t = time.perf_counter()
            out = run(["diagnose", str(d / "spectra.parquet"), "--model", str(d / "grip.csv"),
                       "--json", "-j", str(jobs)])
            dt = time.perf_counter() - t
            doc = json.loads(out)
            verdicts = {a: v["missing_effect"] for a, v in doc["axes"].items()}
            print(f"diagnose --jobs {jobs}: {dt:.1f} s (target <= 20 s); "
                  f"hidden: {effect or 'none'}; verdicts: {verdicts}")


if __name__ == "__main__":
    main()
