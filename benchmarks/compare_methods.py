"""Which estimator is closest to the truth: `h1` (default) against the paper's `chebwin`.

Simulates a study (seed 11, 3 subjects x 3 axes x 3 grips, 50-100 s trials, the default
noise, drift and variability), estimates it with each method, and compares every trial's
measured response, and each axis x grip mean, with the simulator's true H_CL (eq. 4) over
0.1-30 Hz: rms error (dB, deg), median absolute error (dB), and the share of points
within 2 standard errors. The table in docs/methods.md ("Why H1 is the default") comes
from this script.

Run: .venv/bin/python benchmarks/compare_methods.py
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from armfit.cli.main import cli
from armfit.models.arm import ClosedLoopModel
from armfit.spectra import EstimateConfig, estimate_study


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        res = CliRunner().invoke(cli, ["-q", "simulate", "-o", str(d / "s"), "--subjects",
                                       "3", "--seed", "11"])
        if res.exit_code:
            raise SystemExit(res.stderr)
        truth = json.loads((d / "s.truth.json").read_text())
        for method in ("h1", "chebwin"):
            table = estimate_study([d / "s"], EstimateConfig(method=method)).table
            rows = table[(table["kind"] == "measured")]
            err_db, err_deg, z = [], [], []
            mean_db, mean_deg = [], []
            for tr in truth["trials"]:
                r = rows[(rows["level"] == "trial") & (rows["subject"] == tr["subject"])
                         & (rows["axis"] == tr["axis"]) & (rows["grip_N"] == tr["grip_N"])]
                r = r.sort_values("freq_hz")
                f = r["freq_hz"].to_numpy()
                h = r["re"].to_numpy() + 1j * r["im"].to_numpy()
                ht = ClosedLoopModel.for_axis(tr["axis"], mp=tr["mp_kg"]).response(
                    f, tr["params"])
                e_db = 20 * np.log10(np.abs(h / ht))
                e_deg = np.degrees(np.angle(h / ht))
                err_db.append(e_db)
                err_deg.append(e_deg)
                z.append(np.concatenate([e_db / r["se_db"].to_numpy(),
                                         e_deg / r["se_deg"].to_numpy()]))
            # means per axis x grip against the mean of the true responses (in dB/phase)
            for (axis, grip), r in rows[rows["level"] == "mean"].groupby(["axis", "grip_N"]):
                r = r.sort_values("freq_hz")
                f = r["freq_hz"].to_numpy()
                hs = [ClosedLoopModel.for_axis(axis, mp=t["mp_kg"]).response(f, t["params"])
                      for t in truth["trials"] if t["axis"] == axis and t["grip_N"] == grip]
                t_db = np.mean([20 * np.log10(np.abs(x)) for x in hs], axis=0)
                t_ph = np.angle(np.mean([x / np.abs(x) for x in hs], axis=0))
                h = r["re"].to_numpy() + 1j * r["im"].to_numpy()
                mean_db.append(20 * np.log10(np.abs(h)) - t_db)
                mean_deg.append(np.degrees(np.angle(h * np.exp(-1j * t_ph))))
            e_db, e_deg, z = np.concatenate(err_db), np.concatenate(err_deg), np.concatenate(z)
            m_db, m_deg = np.concatenate(mean_db), np.concatenate(mean_deg)
            print(f"{method:8s} per trial: rms {np.sqrt(np.mean(e_db**2)):.2f} dB, "
                  f"{np.sqrt(np.mean(e_deg**2)):.1f} deg; median |error| "
                  f"{np.median(np.abs(e_db)):.3f} dB; within 2 se "
                  f"{100 * np.mean(np.abs(z) <= 2):.0f} %; mean of 3 subjects: rms "
                  f"{np.sqrt(np.mean(m_db**2)):.2f} dB, {np.sqrt(np.mean(m_deg**2)):.1f} deg")


if __name__ == "__main__":
    main()
