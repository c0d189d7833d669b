"""Validation of the estimator checks: no alarm on open-loop studies, the alarm and an
unbiased estimate through the reference on a closed-loop rig.

Open loop (the force is the excitation): every study of ``validate_diagnose.py`` (the
null studies at several seeds and sizes, the zero-order-hold one, each single effect of
the library, the delay + lag pair, the device spring), the non-white pseudo-random
steps with a noisy sensor, and ``sample_data/`` (study, hidden, spring). For each, the
number of trials, the feedback test run on every trial (its smallest p-value and the
trials where it fires: none may), the trials where the estimator runs it (those where H2
exceeds H1 beyond the noise somewhere) and the trials with points flagged
``not_excitation`` (none may).

Closed loop (``tests/tdsim.py``'s rig: a PD controller on the measured position adds
to the commanded force, which is logged as the reference column): per axis, H1's error
against the simulator's truth below 0.3 Hz, the points flagged, the feedback test's
p-value, and the normalised error of the estimate through the reference over the grid,
rms of (estimate − truth)/se in dB and phase (se floored at 0.01 dB and 0.06°, the noise
model's floors), which must be about 1.

Prints a Markdown table. Takes about 3 minutes on 2 cores.

Run: .venv/bin/python benchmarks/validate_estimators.py
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

import tdsim  # noqa: E402
from validate_diagnose import CASES  # noqa: E402

import armfit  # noqa: E402
from armfit.feedback import FEEDBACK_ALPHA, feedback_test  # noqa: E402
from armfit.spectra import NOT_EXCITATION, EstimateConfig, estimate_study  # noqa: E402

#: The non-white study of validate_diagnose.py (its _nonwhite).
STEPS = ("steps 4 Hz lag, noisy sensor", dict(subjects=3, seed=141, axes=("x",),
                                             input="steps", hold_s=(0.3, 1.5), noise_m=5e-3,
                                             quantum_m=1e-4),
         {"lowpass": {"cutoff_hz": 4.0}})


def open_loop_row(label: str, folder: Path) -> list[str]:
    """One table row: trials; the feedback test run on every trial (its smallest p and
    the trials firing); the trials where the estimator needs it; trials flagged."""
    res = estimate_study([folder], EstimateConfig(), jobs=2)
    ps = [feedback_test(t.f, t.x, t.meta.fs, 30.0).p_value
          for t in armfit.read_trials(folder).trials]
    needed = sum(t.check.feedback is not None for t in res.trials)
    flagged = sum(any(NOT_EXCITATION in f for r in t.responses for f in r.flags)
                  for t in res.trials)
    return [label, str(len(res.trials)), f"{min(ps):.2g}",
            str(sum(p < FEEDBACK_ALPHA for p in ps)), str(needed), str(flagged)]


def rig_rows(tmp: Path) -> list[list[str]]:
    """Per axis of the closed-loop rig study: H1 and the estimate through the reference
    against the simulator's truth."""
    study = tdsim.Study(subjects=3, axes=("x", "y", "z"), grips_N=(1.0,),
                        duration_s=(60.0, 60.0), seed=21, drift_m=2e-3)
    folder = tdsim.write_rig_study(study, tdsim.Rig(), tmp / "rig")
    truth = json.loads((folder / "truth.json").read_text())["trials"]
    rows = []
    for use in (False, True):
        res = estimate_study([folder], EstimateConfig(reference=use), jobs=2)
        for axis in study.axes:
            errs, norms, flagged, ps = [], [], 0, []
            for tr, tt in zip(res.trials, truth, strict=True):
                if tr.axis != axis:
                    continue
                m = next(r for r in tr.responses if r.kind == "measured")
                true = tdsim.true_response(tt, tr.freq_hz)
                e_db = 20 * np.log10(np.abs(m.h / true))
                e_deg = np.degrees(np.angle(m.h / true))
                se_db, se_deg = np.maximum(m.se_db, 0.01), np.maximum(m.se_deg, 0.06)
                errs.append(np.median(e_db[tr.freq_hz < 0.3]))
                norms.append(np.nanmean(np.r_[(e_db / se_db) ** 2, (e_deg / se_deg) ** 2]))
                flagged += sum(NOT_EXCITATION in f for r in tr.responses for f in r.flags)
                ps.append(tr.check.feedback.p_value if tr.check.feedback else 1.0)
            rows.append([f"rig, axis {axis}, {'reference' if use else 'H1'}",
                         m.method, f"{np.mean(errs):+.1f}",
                         f"{np.sqrt(np.mean(norms)):.2f}", str(flagged), f"{max(ps):.1e}"])
    return rows


def main() -> None:
    t0 = time.perf_counter()
    head = ["study", "trials", "min feedback p (every trial)", "trials firing",
            "trials the estimator tests", "trials flagged"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    with tempfile.TemporaryDirectory() as tmp:
        for label, kw, truth in [*CASES, STEPS]:
            folder = tdsim.write_study(tdsim.Study(effects=truth, **kw),
                                       Path(tmp) / label.replace(" ", "_"))
            lines.append("| " + " | ".join(open_loop_row(label, folder)) + " |")
            print(lines[-1], flush=True)
        for name in ("study", "hidden", "spring"):
            lines.append("| " + " | ".join(open_loop_row(f"sample_data/{name}",
                                                         ROOT / "sample_data" / name)) + " |")
            print(lines[-1], flush=True)
        head = ["closed-loop rig", "method", "median error < 0.3 Hz, dB",
                "normalised error (rms)", "points flagged", "largest feedback p"]
        lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(r) + " |" for r in rig_rows(Path(tmp))]
    print("\n".join(lines))
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
