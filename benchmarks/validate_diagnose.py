"""Validation of `armfit diagnose` against the simulator's truth: every effect of the
library at two magnitudes and several seeds, plus studies with no hidden effect.

For each study (3 subjects x 3 axes x 3 grips, 30-40 s trials, default noise and
between-subject variability) it prints, per axis, the verdict, whether it is right, the
recovered parameters against the truth, and the systematic error in the failing bands
before and after adding the effect. Takes several minutes; not part of the test suite.

Run: .venv/bin/python benchmarks/validate_diagnose.py [SEEDS]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from click.testing import CliRunner

from armfit.cli.main import cli
from armfit.diagnose import diagnose
from armfit.fitting import fit_study
from armfit.spectra import EstimateConfig, estimate_study

CASES = [
    (None, None),
    ("delay", "delay=0.005"), ("delay", "delay=0.012"),
    ("lowpass", "lowpass=15"), ("lowpass", "lowpass=25"),
    ("device-damping", "device-damping=2"), ("device-damping", "device-damping=4"),
    ("device-mass", "device-mass=0.13"), ("device-mass", "device-mass=0.2"),
    ("resonance", "resonance=40,0.1,0.3"), ("resonance", "resonance=25,0.15,0.2"),
    ("reflex", "reflex=40,0.04"), ("reflex", "reflex=60,0.03"),
]


def main() -> None:
    seeds = [int(s) for s in sys.argv[1].split(",")] if len(sys.argv) > 1 else [1, 2]
    right = total = 0
    for name, spec in CASES:
        for seed in seeds:
            with tempfile.TemporaryDirectory() as tmp:
                args = ["-q", "simulate", "-o", f"{tmp}/s", "--subjects", "3", "--duration",
                        "30,40", "--seed", str(seed)] + (["--effect", spec] if spec else [])
                res = CliRunner().invoke(cli, args)
                if res.exit_code:
                    print(f"{spec} seed {seed}: simulate refused: {res.stderr.strip()}")
                    continue
                spectra = estimate_study([Path(tmp) / "s"], EstimateConfig()).table
                params = fit_study(spectra, which="grip").table()
                for d in diagnose(spectra, params, jobs=2):
                    ok = d.missing_effect == name
                    right += ok
                    total += 1
                    best = d.candidates[0]
                    p = ", ".join(f"{k}={v:.4g}" for k, v in best.params.items())
                    print(f"{spec or 'none':24s} seed {seed} {d.axis}: "
                          f"{d.missing_effect or 'none':15s} {'ok ' if ok else 'MISS'} "
                          f"[{best.effect}: {p}] failing-band bias "
                          f"{best.failing_bias_before:.2f} -> {best.failing_bias_after:.2f}",
                          flush=True)
    print(f"right verdicts: {right} of {total}")


if __name__ == "__main__":
    main()
