"""Speed of `armfit diagnose` (stepwise search on) against `armfit estimate`.

Target: diagnose <= 2x estimate on `sample_data/hidden` (27 trials, 30-50 s), both timed
in the same run as a user runs them (a fresh process each, wall time, --jobs 2). With
``--paper`` it also simulates a paper-size study (9 subjects x 3 axes x 3 grips, 50-100 s
trials, `armfit simulate` defaults, not timed) and times estimate, fit-grip and diagnose
on it. On a shared machine the numbers are inflated by other load: say so when quoting.

``--ref DIR`` also times diagnose with the armfit source tree at DIR (e.g. a checkout of
an earlier commit, put first on PYTHONPATH) on the same files in the same run, so two
versions are compared under the same load. The load average is printed before and after.

Run: .venv/bin/python benchmarks/bench_diagnose.py [--paper] [--ref DIR]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def armfit(*args: str, ref: str | None = None) -> tuple[float, str]:
    exe = Path(sys.executable).with_name("armfit")
    env = dict(os.environ)
    if ref is not None:   # the source tree at ref first on the path (cwd outside any tree)
        env["PYTHONPATH"] = os.pathsep.join([ref, env.get("PYTHONPATH", "")]).rstrip(
            os.pathsep)
    t = time.perf_counter()
    res = subprocess.run([str(exe), "-q", *args], capture_output=True, text=True, env=env,
                         cwd=tempfile.gettempdir())
    dt = time.perf_counter() - t
    if res.returncode:
        raise SystemExit(f"armfit {args[0]} failed: {res.stderr}")
    return dt, res.stdout


def measure(study: Path, d: Path, label: str, ref: str | None = None) -> None:
    t_est, _ = armfit("estimate", str(study), "-o", str(d / "spectra.parquet"), "-j", "2")
    t_fit, _ = armfit("fit-grip", str(d / "spectra.parquet"), "-o", str(d / "grip.csv"))
    print(f"{label}: estimate {t_est:.1f} s, fit-grip {t_fit:.1f} s", flush=True)
    for name, tree in [("this tree", None)] + ([(f"ref {ref}", ref)] if ref else []):
        t_diag, out = armfit("diagnose", str(d / "spectra.parquet"), "--model",
                             str(d / "grip.csv"), "--json", "-j", "2", ref=tree)
        doc = json.loads(out)
        named = {a: [m["effect"] for m in v["missing_effects"]]
                 for a, v in doc["axes"].items()}
        steps = {a: [round(e, 2) for e in v["error_steps"]] for a, v in doc["axes"].items()}
        print(f"  diagnose ({name}) {t_diag:.1f} s = {t_diag / t_est:.2f}x estimate "
              f"(target <= 2x); named {named}; error/noise {steps}", flush=True)


def main() -> None:
    ref = None
    if "--ref" in sys.argv:
        ref = str(Path(sys.argv[sys.argv.index("--ref") + 1]).resolve())
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores",
          flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        (d / "hidden").mkdir()
        measure(ROOT / "sample_data" / "hidden", d / "hidden", "sample_data/hidden", ref)
        if "--paper" in sys.argv:
            (d / "paper").mkdir()
            armfit("simulate", "-o", str(d / "paper" / "study"), "--seed", "2026")
            measure(d / "paper" / "study", d / "paper", "paper-size study (81 trials)", ref)
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
