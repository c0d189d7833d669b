"""``armfit fit-grip`` and ``armfit fit-nominal``: the arm model fits of Tables I and II.

Each command checks its outputs, reads the spectra file, calls
:func:`armfit.fitting.fit_study` and writes the params CSV (and optionally a LaTeX
table) atomically. If any fit fails to converge nothing is written (exit 3).
"""

from __future__ import annotations

import math

import click

from armfit.fitting import COSTS, fit_study, parse_bands
from armfit.io.artifacts import read_spectra, write_params
from armfit.io.atomic import check_output, write_text_atomic
from armfit.models.effects import get_effect
from armfit.tables import caption_for, latex_table

from .options import (
    effect_option,
    effects_file_option,
    emit_json,
    json_option,
    message,
    output_option,
    overwrite_option,
)


def _options(f):
    for deco in reversed([
        click.argument("spectra", type=click.Path(dir_okay=False)),
        output_option,
        click.option("--cost", type=click.Choice(COSTS), default="complex", show_default=True,
                     help="complex: log-magnitude and phase errors, each divided by its "
                          "standard error; paper: dB magnitude error only (eq. 5, Wt = 1)."),
        click.option("--band", "band", metavar="AXIS=LO:HI[,...]", default=None,
                     help="Fit band per axis in Hz [default: x=0.1:30,y=0.1:30,z=0.1:10, "
                          "as the paper]; axes not named keep the default."),
        click.option("--bootstrap", type=click.IntRange(0, 100000), default=0,
                     show_default=True,
                     help="Resample subjects N times for percentile intervals "
                          "(0: intervals from the Jacobian)."),
        click.option("--seed", type=int, default=0, show_default=True,
                     help="Seed of the bootstrap resampling (the fit itself uses none)."),
        effect_option,
        effects_file_option,
        click.option("--method", default=None, metavar="NAME",
                     help="Estimator to fit when SPECTRA holds several (e.g. h1, chebwin)."),
        click.option("--max-nfev", type=click.IntRange(1, None), default=None, metavar="N",
                     help="Evaluation budget of each final local fit [default: 200 per "
                          "parameter]; a fit that runs out exits 3."),
        click.option("--latex", "latex", type=click.Path(dir_okay=False), default=None,
                     help="Also write a booktabs LaTeX table laid out like the paper's."),
        json_option,
        overwrite_option,
    ]):
        f = deco(f)
    return f


def _run(which: str, spectra: str, output: str, cost: str, band: str | None, bootstrap: int,
         seed: int, effects: tuple[str, ...], method: str | None, max_nfev: int | None,
         latex: str | None, as_json: bool, overwrite: bool) -> None:
    bands = parse_bands(band)
    effect_objs = [get_effect(n) for n in effects]
    check_output(output, overwrite=overwrite, inputs=[spectra])
    if latex is not None:
        check_output(latex, overwrite=overwrite, inputs=[spectra, output])
    table = read_spectra(spectra)

    def report(axis, grip, fit):
        where = f"{axis}" + (f" {grip:g} N" if grip is not None else "")
        message(f"fit {where}: rms {fit.rms_db:.3g} dB, {fit.rms_deg:.3g} deg, "
                f"{fit.n_points} bins {fit.band[0]:g}-{fit.band[1]:g} Hz")
        if fit.at_bound:
            message(f"warning: fit {where}: {', '.join(fit.at_bound)} at a physical bound "
                    "(within 1 % of its range); the value is a limit, not an estimate "
                    "(column at_bound)")

    study = fit_study(table, which=which, cost=cost, bands=bands, effects=effect_objs,
                      bootstrap=bootstrap, seed=seed, method=method, max_nfev=max_nfev,
                      source=spectra, on_fit=report)
    df = study.table()
    write_params(df, output, overwrite=overwrite)
    message(f"wrote {output} ({len(df)} fits)")
    ci_methods = [f.ci_method for f in study.fits]
    if latex is not None:
        write_text_atomic(latex, latex_table(df, ci=True, caption=caption_for(which, ci_methods),
                                             label=f"tab:{which}"), overwrite=overwrite)
        message(f"wrote {latex}")
    if as_json:
        emit_json({
            "command": f"fit-{which}", "spectra": spectra, "output": output,
            "latex": latex, "columns": list(df.columns),
            "fits": [dict({k: _clean(v) for k, v in row.items()}, ci_method=ci,
                          objective=fit.objective, message=fit.message,
                          at_bound=list(fit.at_bound))
                     for row, ci, fit in zip(df.to_dict("records"), ci_methods, study.fits,
                                             strict=True)],
        })


def _clean(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


@click.command("fit-grip")
@_options
def fit_grip(**kw) -> None:
    """Fit the arm model to each axis x grip mean (Table I).

    SPECTRA is the Parquet file written by `armfit estimate`; its rows of level "mean" and
    kind "measured" are fitted with the closed loop of eq. 4 (9 fits for 3 axes x 3
    grips). Writes the parameters (SI units), their 95 % intervals and fit statistics.
    """
    _run("grip", **kw)


@click.command("fit-nominal")
@_options
def fit_nominal(**kw) -> None:
    """Fit the arm model to each axis median over all subjects and grips (Table II).

    SPECTRA is the Parquet file written by `armfit estimate`; its rows of level "median"
    and kind "measured" are fitted with the closed loop of eq. 4 (3 fits).
    """
    _run("nominal", **kw)
