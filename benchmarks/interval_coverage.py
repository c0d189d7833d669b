"""Coverage of the fit's 95 % intervals on studies armfit's model did not make.

Each study is simulated in the time domain by ``tests/tdsim.py`` (the closed loop as a
rational transfer function, discretised with ``scipy.signal.cont2discrete``, run as
second-order sections; drift, sensor noise, quantisation) with no between-subject
variability, so the truth of every grip fit is the paper's Table I row of its axis and
grip. The studies are estimated with ``armfit estimate``'s defaults and fitted per axis
and grip (Table I); for each rule the script counts how many true values lie inside
their 95 % intervals:

* ``noise``: the Jacobian interval alone (``jackknife_bands=0``; with rms_norm > 1, as in
  every fit here, this equals the rule before the band jackknife existed);
* ``noise+jackknife (G)``: the wider of the Jacobian and the delete-a-band jackknife with
  G bands (G = 6 is the default, :data:`armfit.fitting.JACKKNIFE_BANDS`);
* ``bootstrap``: the subject bootstrap's percentile interval alone, and ``bootstrap ∪``
  the union with the default interval (what ``--bootstrap`` reports).

Usage: ``python benchmarks/interval_coverage.py [--quick] [--boot N]``. Several minutes on
2 cores (the bootstrap dominates); ``--quick`` runs one small study. Numbers measured on
a shared machine; coverage does not depend on the load.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import tdsim  # noqa: E402

from armfit.fitting import (  # noqa: E402
    PAPER_BANDS,
    bootstrap_fit,
    fit_response,
)
from armfit.models.arm import PARAM_NAMES, ClosedLoopModel  # noqa: E402
from armfit.spectra import EstimateConfig, aggregate, estimate_study  # noqa: E402

#: (seed, subjects, trial length range s) of the validation studies.
STUDIES = [(1, 4, (30.0, 40.0)), (2, 4, (30.0, 40.0)), (3, 6, (60.0, 60.0)),
           (4, 9, (30.0, 40.0)), (5, 3, (100.0, 100.0))]
QUICK = [(1, 3, (30.0, 30.0))]


def _sorted(g):
    g = g.sort_values("freq_hz")
    return (g["freq_hz"].to_numpy(float), (g["re"] + 1j * g["im"]).to_numpy(complex),
            g["se_db"].to_numpy(float), g["se_deg"].to_numpy(float))


def grip_cases(spectra):
    """Yield (axis, grip, f, H_mean, se_db, se_deg, H_trials, subjects) per axis × grip."""
    df = spectra[spectra["kind"] == "measured"]
    if "out_axis" in df.columns:
        df = df[df["out_axis"].isna() | (df["out_axis"] == df["axis"])]
    for (axis, grip), g in df[df["level"] == "mean"].groupby(["axis", "grip_N"]):
        f, h, sdb, sdeg = _sorted(g)
        tr = df[(df["level"] == "trial") & (df["axis"] == axis) & (df["grip_N"] == grip)]
        hs, subj = [], []
        for s, gt in tr.groupby(tr["subject"].astype(str)):
            hs.append(aggregate(np.array([_sorted(r)[1] for _, r in
                                          gt.groupby(gt["run"].fillna(-1))]), "mean"))
            subj.append(s)
        yield axis, float(grip), f, h, sdb, sdeg, np.array(hs), np.array(subj)


def run(studies, n_boot: int, bands=(0, 6, 10)) -> dict[str, list[bool]]:
    inside: dict[str, list[bool]] = {}
    table1 = tdsim._table1()
    rms = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed, subjects, dur in studies:
            t0 = time.perf_counter()
            folder = Path(tmp) / f"s{seed}"
            tdsim.write_study(tdsim.Study(subjects=subjects, seed=seed, variability=0.0,
                                          duration_s=dur), folder)
            spectra = estimate_study([folder], EstimateConfig()).table
            for axis, grip, f, h, sdb, sdeg, hs, subj in grip_cases(spectra):
                model = ClosedLoopModel.for_axis(axis)
                truth = dict(zip(PARAM_NAMES, table1[(axis, grip)], strict=True))
                fits = {}
                for g in bands:
                    fits[g] = fit_response(model, f, h, se_db=sdb, se_deg=sdeg,
                                           band=PAPER_BANDS[axis], jackknife_bands=g)
                    key = "noise" if g == 0 else f"noise+jackknife ({g})"
                    inside.setdefault(key, []).extend(
                        fits[g].ci_lo[n] <= truth[n] <= fits[g].ci_hi[n] for n in PARAM_NAMES)
                rms.append(fits[bands[0]].rms_norm)
                if n_boot:
                    def agg(H):
                        return aggregate(H, "mean")
                    for widen, key in ((False, "bootstrap"), (True, "bootstrap ∪ default")):
                        b = bootstrap_fit(fits[6], f, hs, subj, aggregate=agg, n_boot=n_boot,
                                          seed=seed, se_db=sdb, se_deg=sdeg, widen=widen)
                        inside.setdefault(key, []).extend(
                            b.ci_lo[n] <= truth[n] <= b.ci_hi[n] for n in PARAM_NAMES)
            print(f"study seed {seed}, {subjects} subjects, {dur[0]:g}-{dur[1]:g} s: "
                  f"{time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
    print(f"rms_norm of the fits: {min(rms):.2f}-{max(rms):.2f} (median "
          f"{np.median(rms):.2f})")
    return inside


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one small study")
    ap.add_argument("--boot", type=int, default=100, help="bootstrap resamples (0: skip)")
    args = ap.parse_args()
    inside = run(QUICK if args.quick else STUDIES, args.boot)
    print(f"{'rule':28s} {'inside':>8s} {'coverage':>9s}")
    for key, flags in inside.items():
        print(f"{key:28s} {sum(flags):4d}/{len(flags):<4d} {np.mean(flags):8.0%}")


if __name__ == "__main__":
    main()
