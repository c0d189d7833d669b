"""``armfit run``: the whole pipeline in one command, into one output folder."""

from __future__ import annotations

import click

from armfit.cli.options import (
    Number,
    axis_bands_option,
    bands_by_axis,
    cluster_executor,
    effects_file_option,
    emit_json,
    jobs_option,
    json_option,
    manifest_option,
    map_note,
    map_option,
    message,
    outside_loop_option,
    overwrite_option,
    scheduler_option,
    skip_bad_option,
)
from armfit.constants import FORCE_LIMIT_N, GRID_HZ, PAPER_BANDS
from armfit.errors import UsageError
from armfit.fitting import COSTS
from armfit.pipeline import run
from armfit.spectra import METHODS


@click.command("run")
@effects_file_option
@click.argument("inputs", nargs=-1, type=click.Path(), metavar="INPUT...")
@click.option("-o", "--output", "outdir", required=True, type=click.Path(), metavar="OUTDIR",
              help="Folder to write (built beside it, renamed into place at the end).")
@manifest_option
@map_option
@skip_bad_option
@click.option("--method", type=click.Choice(METHODS), default="h1", show_default=True,
              help="Measured-dynamics estimator (see `armfit estimate`).")
@click.option("--reference/--no-reference", default=True, show_default=True,
              help="Estimate X/F through a trial's reference column (ref_<a>_N or "
                   "ref_<a>_m) when it has one; --no-reference: H1 whatever the trials "
                   "hold (see `armfit estimate`).")
@click.option("--cost", type=click.Choice(COSTS), default="complex", show_default=True,
              help="Arm-fit cost: complex (dB and phase over their standard errors) or "
                   "paper (eq. 5, dB only).")
@click.option("--wu-cost", type=click.Choice(["envelope", "paper"]), default="envelope",
              show_default=True,
              help="Wu fit: envelope (|Wu| >= W_max guaranteed) or paper (dB least squares).")
@click.option("--adopt", type=click.Choice(["auto", "none"]), default="auto",
              show_default=True,
              help="auto: the effects the diagnosis names become the model of every "
                   "product; none: the paper's 5-parameter model throughout.")
@outside_loop_option
@click.option("--fmin", type=Number(min=0, min_open=True), default=GRID_HZ[0],
              show_default=True, metavar="HZ",
              help="Lowest grid frequency (a trial must last 2/HZ s).")
@click.option("--fmax", type=Number(min=0, min_open=True), default=GRID_HZ[1],
              show_default=True, metavar="HZ", help="Highest grid frequency (<= Nyquist).")
@axis_bands_option("Fit band in Hz, for one axis (AXIS=LO:HI) or every axis (LO:HI) "
                   "[default: x=0.1:30,y=0.1:30,z=0.1:10, as the paper]; axes not named "
                   "keep the default.")
@click.option("--force-limit", "force_limit", type=Number(min=0, min_open=True),
              default=FORCE_LIMIT_N, show_default=True, metavar="N",
              help="Device peak force; forces reaching it are warned about and flagged "
                   "saturation.")
@jobs_option
@scheduler_option
@click.option("--no-figures", is_flag=True, help="Skip the figures (faster).")
@overwrite_option
@json_option
def command(inputs, outdir, manifest, column_map, skip_bad, method, reference, cost, wu_cost,
            adopt,
            outside_loop, fmin, fmax, band, force_limit, jobs, scheduler, no_figures,
            overwrite, as_json):
    """Run every stage on raw trials and write all tables, figures and report.md into
    OUTDIR, e.g. ``armfit run raw/ -o results``.

    Stages, in order: ingest, estimate, fit-grip, fit-nominal, diagnose, adopt,
    fit-uncertainty, fit-trials, stability, figures, compare, residuals, drawing,
    report.
    adopt refits Tables I and II with the effects the diagnosis names (when it names
    any), and every stage after it uses that adopted model. INPUT are trial files,
    folders or an `armfit ingest` dataset. Nothing is left behind if a stage fails; an
    existing OUTDIR is replaced only with --overwrite.
    """
    if not inputs and manifest is None:
        raise click.UsageError("give trial files or folders, a dataset, or --manifest")
    if fmin >= fmax:
        raise UsageError(f"--fmin {fmin:g} Hz must be below --fmax {fmax:g} Hz")
    bands = bands_by_axis(band, PAPER_BANDS)
    with cluster_executor(scheduler) as executor:
        result = run(
            list(inputs), outdir, manifest=manifest, skip_bad=skip_bad, method=method,
            cost=cost, wu_cost=wu_cost, jobs=jobs, figures=not no_figures,
            overwrite=overwrite, adopt=adopt, outside_loop=outside_loop,
            on_stage=lambda s: message(s.line()),
            warn=lambda text: message(f"warning: {text}"), executor=executor,
            column_map=column_map, force_limit_N=force_limit, fmin=fmin, fmax=fmax,
            bands={a: b for a, b in bands.items() if b != PAPER_BANDS[a]}, note=map_note,
            reference=reference)
    for f, reason in result.skipped:
        message(f"skipped {f}: {reason}")
    for axis, verdict in result.verdicts.items():
        message(f"axis {axis}: {verdict}")
    for a in result.adoption.axes:
        if a.adopted or a.declined:
            message(f"adopted model, {a.sentence()}")
    message(f"wrote {len(result.files)} files into {result.outdir} in "
            f"{result.wall_s:.1f} s; see {result.outdir}/report.md")
    if as_json:
        emit_json({
            "outdir": result.outdir,
            "files": list(result.files),
            "trials": result.trials,
            "skipped": [{"file": f, "reason": r} for f, r in result.skipped],
            "diagnosis": {a: {"missing_effect": result.missing[a], "verdict": v}
                          for a, v in result.verdicts.items()},
            "refitted": {e: list(a) for e, a in result.refitted.items()},
            "adoption": result.adoption.to_dict(),
            "timings_s": {s.name: round(s.seconds, 3) for s in result.stages},
            "total_s": round(result.wall_s, 3),
        })


__all__ = [
    "command",
]
