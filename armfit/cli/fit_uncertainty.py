"""``armfit fit-uncertainty``: W_max and the uncertainty weight Wu of Table III (eqs. 6–7).

Checks every output first, reads the spectra and nominal-parameters files (and any
weights given to evaluate), calls :func:`armfit.fit_uncertainty`, then writes the Wu CSV,
its summary and W_max points beside it, and optionally a LaTeX table, each atomically.
With ``--cost paper`` a fit that does not converge writes nothing (exit 3).
"""

from __future__ import annotations

import math
from pathlib import Path

import click

from armfit.api import ModelFit
from armfit.api import fit_uncertainty as api_fit_uncertainty
from armfit.cli.grammar import CSV, LATEX, file_output_option
from armfit.cli.options import Whole
from armfit.data import paper_file
from armfit.errors import UsageError
from armfit.io.atomic import check_output
from armfit.io.numbers import parse_number
from armfit.io.schema import wu_sidecar_paths
from armfit.spectra import Spectra
from armfit.uncertainty import MAX_PAIRS, read_wu

from .options import (
    band_option,
    clean,
    cluster_executor,
    effects_file_option,
    emit_json,
    jobs_option,
    json_option,
    message,
    overwrite_option,
    scheduler_option,
)


def _parse_octaves(value: str | None) -> float | None:
    if value is None:
        return None
    num, sep, den = value.partition("/")
    try:
        width = parse_number(num) / parse_number(den) if sep else parse_number(num)
    except (ValueError, ZeroDivisionError):
        width = float("nan")
    if not (math.isfinite(width) and 0 < width <= 2):
        raise UsageError(f"--smooth {value!r}: expected a window width in octaves, "
                         "0 < width <= 2, e.g. 1/3 or 0.1")
    return width


def _check_path(value: str) -> tuple[str, Path]:
    """(label, path) of a --check-weights value; "paper" is the shipped Table III."""
    p = Path(value)
    if value == "paper" and not p.exists():
        return "paper", paper_file("uncertainty")
    return p.name, p


def _pairs(reps) -> list[list[float]]:
    return [[float(r.real), float(abs(r.imag))] for r in reps]


@click.command("fit-uncertainty")
@effects_file_option
@click.argument("spectra", type=click.Path(dir_okay=False))
@click.option("--nominal", required=True, type=click.Path(dir_okay=False),
              help="Nominal parameters CSV written by `armfit fit-nominal` (H_ARM per axis).")
@file_output_option("-o", "--output", "output", required=True, formats=CSV,
                    help="The Wu CSV to write (atomically); OUTPUT_summary.csv and "
                         "OUTPUT_wmax.csv are written beside it.")
@click.option("--cost", type=click.Choice(["envelope", "paper"]), default="envelope",
              show_default=True,
              help="envelope: |Wu| >= W_max on and between grid points, as tight as "
                   "possible; paper: dB least squares against W_max (no guarantee).")
@click.option("--order", type=Whole(0, MAX_PAIRS), default=None, metavar="N",
              help=f"Zero pairs = pole pairs of Wu, 0..{MAX_PAIRS} [default: the smallest "
                   "order within 0.1 dB of the best].")
@band_option("Band in Hz, for one axis (AXIS=LO:HI) or every axis (LO:HI); "
             "repeatable, later items win [default: 0.01:30 as the paper, limited to the "
             "spectra]; axes not named keep the default.")
@click.option("--smooth", default=None, metavar="OCT",
              help="Smooth each trial's relative error over a window OCT octaves wide "
                   "(e.g. 1/3) before taking W_max; raw W_max is still reported.")
@click.option("--method", default=None, metavar="NAME",
              help="Estimator of the derived spectra when SPECTRA holds several.")
@click.option("--check-weights", "check_weights", default=None, metavar="FILE|paper",
              help="Also evaluate this Wu CSV against the data ('paper': Table III).")
@file_output_option("--latex", "latex", formats=LATEX,
                    help="Also write a Table III-style LaTeX table of the fitted weights.")
@jobs_option
@scheduler_option
@json_option
@overwrite_option
def command(spectra: str, nominal: str, output: str, cost: str, order: int | None,
            band, smooth: str | None, method: str | None,
            check_weights: str | None, latex: str | None, jobs: int,
            scheduler: str | None, as_json: bool, overwrite: bool) -> None:
    """Fit the multiplicative uncertainty weight Wu per axis (Table III).

    SPECTRA is the Parquet file of `armfit estimate`; its trial rows of kind "derived"
    (Xa/Fa) are compared with the nominal H_ARM of --nominal: W_max(w) = max over trials
    |H/H_ARM - 1| (eq. 6). Wu(s) = K prod(s - z)/prod(s - p) (eq. 7, s in rad/s) is
    stable and minimum phase. Writes OUTPUT (axis,kind,index,real,imag as Table III),
    OUTPUT_summary.csv (coverage and tightness per axis) and OUTPUT_wmax.csv (W_max and
    |Wu| in dB per frequency).
    """
    band_hz = band
    smooth_oct = _parse_octaves(smooth)
    summary_path, points_path = wu_sidecar_paths(output)
    inputs = [spectra, nominal] + ([check_weights] if check_weights else [])
    outputs = [output, summary_path, points_path] + ([latex] if latex else [])
    for path in outputs:
        check_output(path, overwrite=overwrite, inputs=inputs)

    # all W_max uses
    data = Spectra.read(spectra, level="trial", kind="derived", estimators=False)
    params = ModelFit.read(nominal)
    given = {}
    if check_weights:
        label, path = _check_path(check_weights)
        given[label] = read_wu(path)

    with cluster_executor(scheduler) as executor:
        unc = api_fit_uncertainty(data, params, cost=cost, order=order, band=band_hz,
                                  smooth_oct=smooth_oct, method=method, check=given,
                                  jobs=jobs, executor=executor)
    results = unc.axes
    for text in unc.notes:
        message(f"note: {text}")
    for r in results:
        res = r.result
        fitted = r.checks[("fitted", "wmax")]
        message(f"Wu {r.axis}: {res.order} pair(s), coverage {fitted.coverage_pct:.1f} % "
                f"(between points {fitted.coverage_between_pct:.1f} %), tightness median "
                f"{fitted.tightness_median_db:.2f} dB, max {fitted.tightness_max_db:.2f} dB "
                f"over {r.band_hz[0]:g}-{r.band_hz[1]:g} Hz, {r.n_trials} trials"
                + ("" if res.converged else
                   "; the shape optimiser stopped early (the envelope still holds)"))
        for (label, tname), c in r.checks.items():
            if label != "fitted" and tname == "wmax":
                message(f"  {label} {r.axis}: coverage {c.coverage_pct:.1f} %, tightness "
                        f"median {c.tightness_median_db:.2f} dB, max "
                        f"{c.tightness_max_db:.2f} dB")
    missing = [f"{label} has no {ax} weight" for label, ws in given.items()
               for ax in (r.axis for r in results) if ax not in ws]
    for text in missing:
        message(f"note: {text}")

    summary = unc.summary()
    unc.write(output, overwrite=overwrite, latex=latex)
    message(f"wrote {output}, {summary_path.name}, {points_path.name}"
            + (f", {latex}" if latex else ""))

    if as_json:
        emit_json({
            "command": "fit-uncertainty", "spectra": spectra, "nominal": nominal,
            "output": output, "summary": str(summary_path), "points": str(points_path),
            "latex": latex, "cost": cost, "smooth_oct": smooth_oct,
            "axes": [{
                "axis": r.axis, "n_trials": r.n_trials, "band_hz": list(r.band_hz),
                "order": r.result.order, "converged": r.result.converged,
                "gain": r.result.gain, "zeros": _pairs(r.result.zeros),
                "poles": _pairs(r.result.poles),
                "orders_tried": {str(k): v for k, v in r.result.orders_tried.items()},
            } for r in results],
            "summary_rows": [{k: clean(v) for k, v in row.items()}
                             for row in summary.to_dict("records")],
        } | ({"notes": list(unc.notes)} if unc.notes else {}))


__all__ = [
    "command",
]
