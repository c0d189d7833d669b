"""Validation of armfit on real recordings made by others, read through column maps.

The recordings of ``../shared/realdata`` (or ``$ARMFIT_REALDATA``; see its README.md and
each folder's README.txt) are read where they lie: this script writes a manifest and a
column map per recording into a temporary folder, then runs armfit's own commands,
``estimate`` → ``fit-nominal`` → ``diagnose`` (``--json``), and prints one table row per
recording: the grid, what the estimate shows, what the estimators say of the force (the
feedback test per trial, the points flagged ``not_excitation``, H1's gap; through the
reference where the map gives one), the fitted 5-parameter model (``*``: at a physical
bound), its error in units of the noise, and the diagnosis (verdict, effects named,
error/noise steps).

Recordings: EMPS (MATLAB v5; force = 35.15 N/V × vir; once more with its reference
trajectory qg as the reference column), the Silverbox (CSV in volts, no
time column; once with the 1 N/V, 1 m/V analogue and once scaled so that its moving mass
exceeds the device mass of eq. 4), the reklab ankle (torque in N·m and angle in rad at a
0.1 m lever) and the reklab parameter-varying ankle (MATLAB class objects: refused).
Takes about a minute on 2 cores.

Run: .venv/bin/python benchmarks/validate_real.py
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REAL = Path(os.environ.get("ARMFIT_REALDATA", ROOT.parent / "shared" / "realdata"))
ARMFIT = [sys.executable, "-c", "from armfit.cli.entry import main; main()"]

#: label, data file or folder (relative to REAL), column map, options of estimate and
#: fit-nominal, and what the recording's README says
CASES = [
    ("emps", "emps/raw/DATA_EMPS.mat",
     "quantity,source,unit,gain\ntime_s,t,s,\nforce_x_N,vir,V,35.15\npos_x_m,qm,m,\n",
     ["--fmin", "0.5", "--force-limit", "1000"], [],
     "95 kg + viscous 204 N·s/m + Coulomb friction, closed loop, extra lag"),
    ("emps through qg", "emps/raw/DATA_EMPS.mat",
     "quantity,source,unit,gain\ntime_s,t,s,\nforce_x_N,vir,V,35.15\npos_x_m,qm,m,\n"
     "ref_x_m,qg,m,\n",
     ["--fmin", "0.5", "--force-limit", "1000"], [],
     "the same, estimated through the position loop's reference trajectory"),
    ("silverbox (1 N/V, 1 m/V)", "silverbox/raw/SNLS80mV.csv",
     "quantity,source,unit,gain,value\nrate_Hz,,Hz,,610.3515625\nforce_x_N,V1,V,1,\n"
     "pos_x_m,V2,V,1,\n", ["--fmax", "150"], ["--band", "0.1:150"],
     "mass-spring-damper with a cubic spring, resonance ~70 Hz"),
    ("silverbox (100 N/V, 5 mm/V)", "silverbox/raw/SNLS80mV.csv",
     "quantity,source,unit,gain,value\nrate_Hz,,Hz,,610.3515625\nforce_x_N,V1,V,100,\n"
     "pos_x_m,V2,V,0.005,\n", ["--fmax", "150"], ["--band", "0.1:150"],
     "the same, scaled: 20 kN/m and 0.1 kg"),
    ("reklab-ankle (5 trials)", "reklab-ankle",
     "quantity,source,unit,lever_m\ntime_s,time_s,s,\nforce_x_N,force_x_N,N*m,0.1\n"
     "pos_x_m,pos_x_m,rad,0.1\n", ["--force-limit", "1000"], [],
     "ankle under position steps: torque is the response"),
    ("reklab-ankle-pv", "reklab-ankle-pv/raw/IEEETBME2022_PilotData_AV_PT1_UT2.mat",
     "quantity,source,unit,lever_m,value\nrate_Hz,,Hz,,1000\nforce_x_N,io:2,N*m,0.1,\n"
     "pos_x_m,io:1,rad,0.1,\n", [], [], "MATLAB nldat objects"),
]


def _armfit(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*ARMFIT, *args], capture_output=True, text=True)


def _measured(path: Path) -> dict[str, np.ndarray]:
    """Frequency (Hz), magnitude (dB), phase (deg) of the on-axis measured X/F medians."""
    with open(path, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r["level"] == "median"
                and r["kind"] == "measured" and r["out_axis"] == r["axis"]]
    return {k: np.array([float(r[c]) for r in rows])
            for k, c in (("f", "freq_hz"), ("db", "mag_db"), ("deg", "phase_deg"))}


def _shows(label: str, m: dict[str, np.ndarray]) -> str:
    """What the measured response shows, in numbers."""
    w = 2 * np.pi * m["f"]
    if label.startswith("emps"):
        band = (m["f"] >= 2) & (m["f"] <= 20)
        mass = 1.0 / (10 ** (m["db"][band] / 20) * w[band] ** 2)
        return (f"mass line 1/(ω² abs(X/F)) 2–20 Hz: median {np.median(mass):.1f} kg "
                f"({mass.min():.0f}–{mass.max():.0f}); phase {np.median(m['deg'][band]):.0f}° "
                f"(median), {np.median(m['deg'][m['f'] > 15]):.0f}° above 15 Hz")
    if label.startswith("silverbox"):
        k = int(np.argmax(m["db"]))
        low = m["f"] < 2
        return (f"peak {m['db'][k]:.1f} dB at {m['f'][k]:.1f} Hz over "
                f"{np.median(m['db'][low]):.1f} dB below 2 Hz")
    low = m["f"] < 2
    stiff = 0.1 ** 2 / 10 ** (np.median(m["db"][low]) / 20)
    return (f"X/F {np.median(m['db'][low]):.1f} dB below 2 Hz (K = lever²/abs(X/F) ≈ "
            f"{stiff:.0f} N·m/rad); phase {np.median(m['deg'][low]):.0f}°")


def _feedback_p(inputs: list[str], map_file: Path, est_opts: list[str]) -> list[float]:
    """The feedback test run on every trial (the estimator runs it only where H1 and H2
    disagree beyond the noise somewhere), read through the same map."""
    import armfit
    from armfit.feedback import feedback_test
    fmax = float(est_opts[est_opts.index("--fmax") + 1]) if "--fmax" in est_opts else 30.0
    manifest = inputs[1] if inputs[0] == "--manifest" else None
    trials = armfit.read_trials([] if manifest else inputs, manifest=manifest,
                                column_map=map_file, force_limit_N=1e9, f_min_hz=0.0)
    return [feedback_test(t.f, t.x, t.meta.fs, fmax).p_value for t in trials.trials]


def _estimators(spectra: Path, direct: list[float]) -> str:
    """What the estimators say of the force, from the spectra file's metadata; ``direct``:
    the feedback test's p-value of every trial."""
    import pyarrow.parquet as pq
    meta = json.loads(pq.read_schema(spectra).metadata[b"armfit"])
    checks = meta["estimators"]
    fires = sum(c["feedback"]["fires"] for c in checks if c["feedback"])
    needed = sum(c["feedback"] is not None for c in checks)
    flagged = [c for c in checks if c["not_excitation_hz"]]
    text = [f"method {'/'.join(sorted({c['method'] for c in checks}))}",
            f"feedback p {min(direct):.1g}" + (f"…{max(direct):.1g}" if len(direct) > 1
                                               else "")
            + f" (needed in {needed} of {len(checks)}, fires in {fires})"]
    if flagged:
        lo = min(c["gap_db"][0] for c in flagged)
        hi = max(c["gap_db"][1] for c in flagged)
        bands = sorted({(b[0], b[1]) for c in flagged for b in c["not_excitation_hz"]})
        what = "reference estimate − H1" if flagged[0]["reference"] else "H2 − H1"
        text.append(f"not_excitation in {len(flagged)}: {what} {lo:.1f}…{hi:.1f} dB at "
                    + ", ".join(f"{a:.2g}–{b:.2g}" if a < b else f"{a:.2g}"
                                for a, b in bands[:6]) + (" …" if len(bands) > 6 else "")
                    + " Hz; cause " + "/".join(sorted({c["cause"] for c in flagged})))
    return "; ".join(text)


def _model(fit: dict) -> str:
    bound = set(fit.get("at_bound") or ())
    return ", ".join(f"{p} {fit[p]:.3g}{'*' if p in bound else ''}"
                     for p in ("Ma", "k1", "k2", "b1", "b2"))


def _diagnosis(doc: dict) -> tuple[str, str, str]:
    ax = doc["axes"]["x"]
    named = "; ".join(
        f"{m['effect']} ({', '.join(f'{k}={v:.3g}' for k, v in m['params'].items())})"
        + (" [at bound]" if m.get("at_bound") else "") for m in ax["missing_effects"]) or "—"
    steps = " → ".join(f"{e:.3g}" for e in ax["error_steps"])
    return ("adequate" if ax["adequate"] else "inadequate"), named, steps


def _case(tmp: Path, label, data, map_text, est_opts, fit_opts) -> list[str]:
    folder = tmp / label.split(" (")[0].replace(" ", "_")
    folder.mkdir(exist_ok=True)
    (folder / "map.csv").write_text(map_text)
    source = REAL / data
    inputs = [str(source)] if source.is_dir() else ["--manifest", str(folder / "m.csv")]
    if not source.is_dir():
        (folder / "m.csv").write_text(f"file,subject,axis,grip_N\n{source},s1,x,0\n")
    spectra = folder / "spectra.parquet"
    res = _armfit("estimate", *inputs, "--map", str(folder / "map.csv"), "-o", str(spectra),
                  "--csv", str(folder / "spectra.csv"), "-j", "2", "--overwrite", *est_opts)
    if res.returncode:
        return [f"exit {res.returncode}: " + res.stderr.strip().splitlines()[-1]
                .removeprefix("armfit: error: ").replace(str(REAL) + "/", "")] + [""] * 5
    grid = " ".join(est_opts[i] + " " + est_opts[i + 1] for i in range(0, len(est_opts), 2)
                    if est_opts[i] in ("--fmin", "--fmax")) or "default"
    shows = _shows(label, _measured(folder / "spectra.csv"))
    res = _armfit("fit-nominal", str(spectra), "-o", str(folder / "nominal.csv"), "--json",
                  "--overwrite", *fit_opts)
    fit = json.loads(res.stdout)["fits"][0]
    res = _armfit("diagnose", str(spectra), "--model", str(folder / "nominal.csv"), "--json",
                  "-j", "2")
    verdict, named, steps = _diagnosis(json.loads(res.stdout))
    direct = _feedback_p(inputs, folder / "map.csv", est_opts)
    return [f"{grid}; {shows}", _estimators(spectra, direct), _model(fit),
            f"{fit['rms_db']:.2f} dB, {fit['rms_deg']:.1f}°, {fit['rms_norm']:.1f}× noise",
            verdict, f"{named}; error/noise {steps}"]


def main() -> None:
    if not REAL.is_dir():
        sys.exit(f"no real recordings at {REAL} (set ARMFIT_REALDATA)")
    head = ["recording", "README", "estimate (grid; what it shows)", "the force",
            "fit-nominal (SI; * at bound)", "fit error", "diagnose", "effects named"]
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for label, data, map_text, est_opts, fit_opts, readme in CASES:
            row = [label, readme, *_case(Path(tmp), label, data, map_text, est_opts,
                                         fit_opts)]
            rows.append(row)
            print(" | ".join(row), flush=True)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    print()
    print("\n".join(lines))
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
