"""``armfit fit-grip`` and ``armfit fit-nominal``: the arm model fits of Tables I and II.

Each command checks its outputs, reads the spectra file, calls :func:`armfit.fit_grip`
or :func:`armfit.fit_nominal` and writes the params CSV (and optionally a LaTeX table)
atomically. If any fit fails to converge nothing is written (exit 3).
"""

from __future__ import annotations

import click

from armfit.api import fit_grip as api_fit_grip
from armfit.api import fit_nominal as api_fit_nominal
from armfit.cli.grammar import CSV, LATEX, file_output_option
from armfit.cli.options import Whole
from armfit.constants import PAPER_BANDS
from armfit.fitting import COSTS
from armfit.io.atomic import check_output
from armfit.spectra import Spectra

from .options import (
    axis_bands_option,
    bands_by_axis,
    clean,
    effect_items,
    effects_file_option,
    emit_json,
    fit_effect_option,
    json_option,
    message,
    overwrite_option,
)


def _options(f):
    for deco in reversed([
        click.argument("spectra", type=click.Path(dir_okay=False)),
        file_output_option("-o", "--output", "output", required=True, formats=CSV,
                           help="The params CSV to write (atomically)."),
        click.option("--cost", type=click.Choice(COSTS), default="complex", show_default=True,
                     help="complex: log-magnitude and phase errors, each divided by its "
                          "standard error; paper: dB magnitude error only (eq. 5, Wt = 1)."),
        axis_bands_option("Fit band in Hz, for one axis (AXIS=LO:HI) or every axis "
                          "(LO:HI); repeatable, later items win [default: "
                          "x=0.1:30,y=0.1:30,z=0.1:10, as the paper]; axes not named "
                          "keep the default."),
        click.option("--bootstrap", type=Whole(0, 100000), default=0,
                     show_default=True, metavar="N",
                     help="Resample subjects N times for percentile intervals "
                          "(0: intervals from the Jacobian)."),
        click.option("--seed", type=Whole(), default=0, show_default=True, metavar="N",
                     help="Seed of the bootstrap resampling (the fit itself uses none)."),
        fit_effect_option,
        effects_file_option,
        click.option("--method", default=None, metavar="NAME",
                     help="Estimator to fit when SPECTRA holds several (e.g. h1, chebwin)."),
        click.option("--max-nfev", type=Whole(1, None), default=None, metavar="N",
                     help="Evaluation budget of each final local fit [default: 200 per "
                          "parameter]; a fit that runs out exits 3."),
        file_output_option("--latex", "latex", formats=LATEX,
                           help="Also write a booktabs LaTeX table laid out like the "
                                "paper's."),
        json_option,
        overwrite_option,
    ]):
        f = deco(f)
    return f


def _run(which: str, spectra: str, output: str, cost: str, band, bootstrap: int,
         seed: int, effects: tuple[str, ...], method: str | None, max_nfev: int | None,
         latex: str | None, as_json: bool, overwrite: bool) -> None:
    bands = bands_by_axis(band, PAPER_BANDS)
    effect_objs = effect_items(effects)
    check_output(output, overwrite=overwrite, inputs=[spectra])
    if latex is not None:
        check_output(latex, overwrite=overwrite, inputs=[spectra, output])
    # the measured aggregates (and the trials only for the bootstrap's resamples)
    data = Spectra.read(spectra, kind="measured",
                        level=None if bootstrap else ("mean", "median"), estimators=False)

    def report(axis, grip, fit):
        where = f"{axis}" + (f" {grip:g} N" if grip is not None else "")
        message(f"fit {where}: rms {fit.rms_db:.3g} dB, {fit.rms_deg:.3g} deg, "
                f"{fit.n_points} bins {fit.band[0]:g}-{fit.band[1]:g} Hz")
        if fit.at_bound:
            message(f"warning: fit {where}: {', '.join(fit.at_bound)} at a physical bound "
                    "(within 1 % of its range); the value is a limit, not an estimate "
                    "(column at_bound)")

    fit = api_fit_grip if which == "grip" else api_fit_nominal
    model = fit(data, cost=cost, bands=bands, effects=effect_objs, bootstrap=bootstrap,
                seed=seed, method=method, max_nfev=max_nfev, on_fit=report)
    model.write(output, overwrite=overwrite, latex=latex)
    message(f"wrote {output} ({len(model.fits)} fits)")
    if latex is not None:
        message(f"wrote {latex}")
    if as_json:
        df = model.table
        emit_json({
            "command": f"fit-{which}", "spectra": spectra, "output": output,
            "latex": latex, "columns": list(df.columns),
            "fits": [dict({k: clean(v) for k, v in row.items()}, ci_method=f.ci_method,
                          objective=f.objective, message=f.message,
                          at_bound=list(f.at_bound))
                     for row, f in zip(df.to_dict("records"), model.fits, strict=True)],
        })


@click.command("fit-grip")
@_options
def fit_grip_command(**kw) -> None:
    """Fit the arm model to each axis x grip mean (Table I).

    SPECTRA is the Parquet file written by `armfit estimate`; its rows of level "mean" and
    kind "measured" are fitted with the closed loop of eq. 4 (9 fits for 3 axes x 3
    grips). Writes the parameters (SI units), their 95 % intervals and fit statistics.
    """
    _run("grip", **kw)


@click.command("fit-nominal")
@_options
def fit_nominal_command(**kw) -> None:
    """Fit the arm model to each axis median over all subjects and grips (Table II).

    SPECTRA is the Parquet file written by `armfit estimate`; its rows of level "median"
    and kind "measured" are fitted with the closed loop of eq. 4 (3 fits).
    """
    _run("nominal", **kw)


__all__ = ["fit_grip_command", "fit_nominal_command"]
