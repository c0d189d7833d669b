"""Validation of the diagnosis's START_GAP: starts far behind after their brief try are
not refined.

A joint fit of the diagnosis tries every starting combination briefly on a subset of the
trials and refines the best :data:`armfit.diagnosis.tuning.REFINE_BEST` on all of them;
a start whose brief cost exceeds :data:`~armfit.diagnosis.tuning.START_GAP` times the
best one's is not refined. This script refines every kept start (the gap switched off)
over a corpus and reports what the gap would leave out:

* simulated studies (3 subjects × 3 axes × 3 grips, 30–45 s) with each effect of the
  library and two of them together, seeds 1 and 2, and without an effect;
* the two sample studies, ``sample_data/study`` and ``sample_data/hidden``;
* the real recordings of ``../shared/realdata`` (or ``$ARMFIT_REALDATA``) when present,
  read through the column maps of ``benchmarks/validate_real.py``.

For every joint fit with two or more refined starts it records each start's brief cost
(relative to the best one's), its final cost and the CPU its refinement and rescue took.
Printed: the largest brief-cost ratio of a start that ended materially better than the
first (by more than 1e-6 of the cost), the largest of one that ended better at all (by
rounding), and what a gap of 10, 30, 100, 300 would leave out (starts, CPU, and starts
that would have ended better). Takes about three minutes on 2 cores.

Run: .venv/bin/python benchmarks/validate_start_gap.py
"""

from __future__ import annotations

import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import validate_real  # noqa: E402  (its recordings and column maps)

import armfit.diagnosis.compare as compare_mod  # noqa: E402
import armfit.diagnosis.fit as fit_mod  # noqa: E402
import armfit.diagnosis.joint as joint  # noqa: E402
from armfit import api  # noqa: E402

ARMFIT = [sys.executable, "-c", "from armfit.cli.entry import main; main()"]
#: (label, --effect values) of the simulated studies, each with seeds 1 and 2
SIMULATED = [("none", []), ("delay 12 ms", ["delay=0.012"]), ("delay 30 ms", ["delay=0.03"]),
             ("lowpass 15 Hz", ["lowpass=15"]), ("device-mass 0.2 kg", ["device-mass=0.2"]),
             ("device-damping 5", ["device-damping=5"]),
             ("resonance 40 Hz", ["resonance=40,0.1,0.3"]), ("reflex", ["reflex=80,0.03"]),
             ("delay + lowpass", ["delay=0.008", "lowpass=20"])]


def _armfit(*args: str) -> None:
    res = subprocess.run([*ARMFIT, "-q", *args], capture_output=True, text=True)
    if res.returncode:
        raise SystemExit(f"armfit {args[0]} failed: {res.stderr.strip()}")


def corpus(tmp: Path) -> list[tuple[str, Path, Path]]:
    """(label, spectra file, params file) of every diagnosis of the corpus."""
    out = []
    for label, effects in SIMULATED:
        for seed in (1, 2):
            d = tmp / f"{label.replace(' ', '_')}_{seed}"
            _armfit("simulate", "-o", str(d), "--seed", str(seed), "--subjects", "3",
                    "--duration", "30,45", *[a for e in effects for a in ("--effect", e)])
            _armfit("estimate", str(d), "-o", f"{d}.parquet", "-j", "2")
            _armfit("fit-grip", f"{d}.parquet", "-o", f"{d}.csv")
            out.append((f"{label}, seed {seed}", Path(f"{d}.parquet"), Path(f"{d}.csv")))
    for name in ("study", "hidden"):
        d = tmp / name
        _armfit("estimate", str(ROOT / "sample_data" / name), "-o", f"{d}.parquet", "-j", "2")
        _armfit("fit-grip", f"{d}.parquet", "-o", f"{d}.csv")
        out.append((f"sample_data/{name}", Path(f"{d}.parquet"), Path(f"{d}.csv")))
    if validate_real.REAL.is_dir():
        for i, (label, data, map_text, est_opts, fit_opts, _) in enumerate(
                validate_real.CASES):
            folder = tmp / f"real{i}"
            folder.mkdir()
            (folder / "map.csv").write_text(map_text)
            source = validate_real.REAL / data
            inputs = [str(source)] if source.is_dir() else ["--manifest", str(folder / "m.csv")]
            if not source.is_dir():
                (folder / "m.csv").write_text(f"file,subject,axis,grip_N\n{source},s1,x,0\n")
            spectra = folder / "spectra.parquet"
            res = subprocess.run([*ARMFIT, "-q", "estimate", *inputs, "--map",
                                  str(folder / "map.csv"), "-o", str(spectra), *est_opts],
                                 capture_output=True, text=True)
            if res.returncode:      # a recording armfit refuses (reported by validate_real)
                continue
            _armfit("fit-nominal", str(spectra), "-o", f"{spectra}.csv", *fit_opts)
            out.append((label, spectra, Path(f"{spectra}.csv")))
    return out


class _Recorder:
    """Every kept start of every joint fit: (brief cost, final cost, CPU s)."""

    def __init__(self) -> None:
        self.fits: list[list[tuple[float, float, float]]] = []
        self._stack: list[dict] = []

    def joint_fit(self, original):
        def wrapped(*args, **kwargs):
            self._stack.append({"briefs": [], "starts": []})
            try:
                return original(*args, **kwargs)
            finally:
                frame = self._stack.pop()
                if len(frame["starts"]) > 1:
                    self.fits.append(frame["starts"])
        return wrapped

    def screen_starts(self, original):
        def wrapped(model, data, sel, combos, prob, keep, nfev, by_subject=None):
            x0s = original(model, data, sel, combos, prob, keep, nfev, by_subject)
            # the brief costs of the starts kept, in order (the short fits again)
            T = data.h.shape[0]
            idx = np.unique(np.linspace(0, T - 1, min(T, joint.START_SCREEN_TRIALS))
                            .round().astype(int))
            sprob = joint.JointProblem(model, data.subset(idx), sel, prob.varying)
            costs = sorted(sprob.solve(sprob.pack(b[idx], st, by_subject), nfev).cost
                           for b, st in combos)
            seen, briefs = set(), []
            for c, x0 in zip(costs, x0s, strict=False):
                if x0.tobytes() not in seen:     # joint_fit refines a start once
                    seen.add(x0.tobytes())
                    briefs.append(c)
            frame = self._stack[-1]
            frame["briefs"] = briefs
            frame["t"] = time.process_time()
            return x0s
        return wrapped

    def rescue_trials(self, original):
        def wrapped(*args, **kwargs):
            res = original(*args, **kwargs)
            frame = self._stack[-1]
            if frame["briefs"]:
                now = time.process_time()
                i = len(frame["starts"])
                frame["starts"].append((frame["briefs"][i], res.cost, now - frame["t"]))
                frame["t"] = now
            return res
        return wrapped


def main() -> None:
    rec = _Recorder()
    joint.START_GAP = math.inf        # every kept start refined
    jf = rec.joint_fit(joint.joint_fit)
    joint.joint_fit = fit_mod.joint_fit = compare_mod.joint_fit = jf
    joint.screen_starts = rec.screen_starts(joint.screen_starts)
    joint.rescue_trials = rec.rescue_trials(joint.rescue_trials)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="armfit-start-gap-") as tmp:
        cases = corpus(Path(tmp))
        for label, spectra, params in cases:
            n = len(rec.fits)
            api.diagnose(str(spectra), pd.read_csv(params, dtype={"subject": str}), jobs=1)
            print(f"  {label}: {len(rec.fits) - n} joint fits with several starts", flush=True)
    # each later start: (brief cost / the first's, better than the first by more than
    # 1e-6 of the cost, better by rounding only, CPU s)
    later = [(b / s[0][0], s[0][1] / f - 1 > 1e-6, f < s[0][1] and s[0][1] / f - 1 <= 1e-6,
              t) for s in rec.fits if s[0][0] > 0 for b, f, t in s[1:]]
    material = max((x[0] for x in later if x[1]), default=0.0)
    rounding = max((x[0] for x in later if x[2]), default=0.0)
    cpu = sum(t for s in rec.fits for _, _, t in s)
    print(f"{len(cases)} diagnoses, {len(rec.fits)} joint fits with several starts, "
          f"{cpu:.1f} s CPU in their refinements")
    print(f"largest brief-cost ratio of a start that ended better than the first by more "
          f"than 1e-6: {material:.3g}; by rounding only: {rounding:.3g}")
    for gap in (10, 30, 100, 300):
        left = [x for x in later if x[0] > gap]
        print(f"  gap {gap:>4}: leaves out {len(left)} starts, "
              f"{sum(x[3] for x in left):.2f} s CPU; of them better than the first by "
              f"more than 1e-6: {sum(x[1] for x in left)}, by rounding only: "
              f"{sum(x[2] for x in left)}")
    print(f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
