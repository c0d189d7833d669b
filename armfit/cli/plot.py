"""``armfit plot KIND``: Bode, residual, uncertainty and literature figures.

Each subcommand checks the output (extension, --overwrite) before reading anything, reads
its inputs, calls one function of :mod:`armfit.figures` and writes the figure atomically.
"""

from __future__ import annotations

import click
import numpy as np

from armfit import figures
from armfit.cli.grammar import FIGURE, file_output_option
from armfit.cli.options import Number, Whole
from armfit.constants import AXES, DEVICE_MASS_KG
from armfit.data import paper_table
from armfit.errors import BadInputError, UsageError
from armfit.io.atomic import check_output
from armfit.loop import WallSettings
from armfit.models.params import read_param_rows, read_params
from armfit.spectra import Spectra
from armfit.uncertainty import read_wu

from .options import (
    axis_bands_option,
    effects_file_option,
    message,
    outside_loop_option,
    overwrite_option,
)

AXIS_CHOICE = click.Choice(list(AXES))

#: ``-o`` of every figure: the format follows the extension.
_figure_output = file_output_option("-o", "--output", "output", required=True,
                                   formats=FIGURE, metavar="FIGURE",
                                   help="The figure to write (atomically): .png (300 dpi), "
                                        ".svg or .pdf.")


# ---------------------------------------------------------------------------
# Steps shared by the subcommands
# ---------------------------------------------------------------------------

def _with_file(exc: BadInputError, path: str) -> BadInputError:
    """``exc`` (raised on data already read) re-raised naming the file it came from."""
    if exc.file is not None:
        return exc
    return BadInputError(exc.reason, file=path, column=exc.column, row=exc.row)


def _prepare(output: str, overwrite: bool, inputs) -> None:
    figures.figure_format(output)
    check_output(output, overwrite=overwrite, inputs=[i for i in inputs if i])


def _save(fig, output: str, overwrite: bool) -> None:
    out = figures.save_figure(fig, output, overwrite=overwrite)
    message(f"wrote {out}")


# ---------------------------------------------------------------------------
# Commands
# ---------------------------------------------------------------------------

@click.group("plot")
def command() -> None:
    """Draw a figure: bode, residual, uncertainty, literature or stability.

    The format follows the -o extension: .png (300 dpi), .svg or .pdf. Files carry no
    timestamps: the same input gives byte-identical files.
    """


@command.command("bode", short_help="Measured dynamics X/F with the fits (Fig. 5).")
@effects_file_option
@click.argument("spectra", metavar="SPECTRA")
@click.option("--model", "model_path", metavar="FILE",
              help="Fitted parameters (fit-grip or fit-nominal output) to overlay.")
@click.option("--axis", type=AXIS_CHOICE, help="Only this axis (default: every axis).")
@click.option("--spread", type=click.Choice(["se", "quartiles"]), default="se",
              show_default=True, help="Shaded spread around each grip's mean.")
@click.option("--no-trials", is_flag=True, help="Leave out the single-trial responses.")
@_figure_output
@overwrite_option
def bode_command(spectra, model_path, axis, spread, no_trials, output, overwrite):
    """Measured dynamics X/F per axis with the model fits (the paper's Fig. 5)."""
    _prepare(output, overwrite, [spectra, model_path])
    df = Spectra.read(spectra, level=("trial", "mean"), kind="measured",
                      estimators=False)
    params = read_params(model_path) if model_path else None
    try:
        fig = figures.bode_figure(df, params, axis=axis, band=spread, trials=not no_trials)
    except BadInputError as exc:
        raise _with_file(exc, spectra) from None
    _save(fig, output, overwrite)


@command.command("residual", short_help="Normalised residuals and failing bands.")
@effects_file_option
@click.argument("spectra", metavar="SPECTRA")
@click.option("--model", "model_path", required=True, metavar="FILE",
              help="Fitted parameters: grip fits are compared with each grip's mean, "
                   "nominal fits with each axis's median.")
@click.option("--model2", "model2_path", metavar="FILE",
              help="A second parameters file (e.g. the model with an effect), dashed.")
@click.option("--axis", type=AXIS_CHOICE, help="Only this axis (default: every axis).")
@axis_bands_option("Band to shade, in Hz, for one axis (AXIS=LO:HI) or every axis "
                   "(LO:HI); repeatable. Default: where the first model's plotted "
                   "residual leaves the noise band |residual| <= 2 SE.", multiple=True)
@_figure_output
@overwrite_option
def residual_command(spectra, model_path, model2_path, axis, band, output, overwrite):
    """Normalised residual (measurement - model)/SE with the noise and failing bands."""
    _prepare(output, overwrite, [spectra, model_path, model2_path])
    df = Spectra.read(spectra, kind="measured", estimators=False)
    params = read_params(model_path)
    params2 = read_params(model2_path) if model2_path else None
    axes = [axis] if axis else [a for a in AXES if (params["axis"] == a).any()
                                and len(df.select(axis=a))]
    shaded: dict[str, list[tuple[float, float]]] | None = None
    if band:
        shaded = {a: [] for a in axes}
        for a_band, lo, hi in band:
            for a in ([a_band] if a_band else axes):
                shaded.setdefault(a, []).append((lo, hi))
    try:
        fig = figures.residual_figure(df, params, params2, axis=axis, bands=shaded)
    except BadInputError as exc:
        raise _with_file(exc, spectra) from None
    _save(fig, output, overwrite)


@command.command("uncertainty", short_help="Derived arm dynamics, W_max and |Wu| (Fig. 6).")
@effects_file_option
@click.argument("spectra", metavar="SPECTRA")
@click.option("--nominal", "nominal_path", required=True, metavar="FILE",
              help="Nominal fit (fit-nominal output): its H_ARM is the reference.")
@click.option("--weights", "weights_path", metavar="FILE",
              help="Uncertainty weights Wu (fit-uncertainty output, or Table III layout: "
                   "axis,kind,index,real,imag; pairs in rad/s).")
@click.option("--axis", type=AXIS_CHOICE, help="Only this axis (default: every axis).")
@_figure_output
@overwrite_option
def uncertainty_command(spectra, nominal_path, weights_path, axis, output, overwrite):
    """Derived arm dynamics with the nominal H_ARM, W_max and |Wu| (the paper's Fig. 6)."""
    _prepare(output, overwrite, [spectra, nominal_path, weights_path])
    df = Spectra.read(spectra, level="trial", kind="derived", estimators=False)
    nominal = read_params(nominal_path)
    weights = read_wu(weights_path) if weights_path else None
    try:
        fig = figures.uncertainty_figure(df, nominal, weights, axis=axis)
    except BadInputError as exc:
        raise _with_file(exc, spectra) from None
    _save(fig, output, overwrite)


@command.command("literature", short_help="H_ARM against Table IV's models (Fig. 7).")
@effects_file_option
@click.option("--model", "model_path", metavar="FILE",
              help="Fitted parameters; default: the paper's Table I.")
@click.option("--axis", type=AXIS_CHOICE, default="x", show_default=True,
              help="Axis of the row to draw.")
@click.option("--grip", type=Number(), default=1.0, show_default=True, metavar="N",
              help="Grip force, N, of the row to draw, when the file has grip fits.")
@_figure_output
@overwrite_option
def literature_command(model_path, axis, grip, output, overwrite):
    """This study's H_ARM against the literature models of Table IV (the paper's Fig. 7)."""
    _prepare(output, overwrite, [model_path])
    if model_path:
        params, source = read_params(model_path), model_path
    else:
        table = paper_table("grip").rename(columns={
            "Ma_kg": "Ma", "k1_N_per_m": "k1", "k2_N_per_m": "k2", "b1_Ns_per_m": "b1",
            "b2_Ns_per_m": "b2"})
        table["mp_kg"] = table["axis"].map(DEVICE_MASS_KG)
        table["effects"] = ""
        params, source = table, "Table I of the paper"
    rows = params[params["axis"] == axis]
    if "grip_N" in rows.columns and rows["grip_N"].notna().any():
        rows = rows[np.isclose(rows["grip_N"].to_numpy(float), grip)]
        if rows.empty:
            have = ", ".join(f"{g:g}" for g in sorted(params.loc[params["axis"] == axis,
                                                                 "grip_N"].dropna()))
            raise UsageError(f"{source}: no {axis} row with grip {grip:g} N "
                             f"(grips: {have or 'none'}); choose one with --grip")
    if rows.empty:
        raise UsageError(f"{source}: no row for axis {axis}; choose one with --axis")
    fig = figures.literature_figure(rows.iloc[0])
    _save(fig, output, overwrite)


@command.command("stability", short_help="K_max per subject and against servo rate.")
@effects_file_option
@click.argument("params", metavar="PARAMS")
@click.option("--sample-time", "sample_time", type=Number(), default=1e-3, show_default=True,
              metavar="S", help="Servo period T of the top row, s.")
@click.option("--damping", type=Number(), default=0.0, show_default=True, metavar="B",
              help="Virtual damping B, N*s/m.")
@click.option("--delay-samples", "delay", type=Whole(), default=1, show_default=True,
              metavar="D", help="Computation delay d of the top row, whole samples.")
@outside_loop_option
@_figure_output
@overwrite_option
def plot_stability_command(params, sample_time, damping, delay, outside_loop, output,
                           overwrite):
    """K_max per subject and grip, and against servo rate for d = 0, 1, 2.

    PARAMS: any parameters file armfit writes (fit-trials for the population), or a
    paper table by name (nominal, grip).
    """
    settings = WallSettings(sample_time, damping, delay)
    _prepare(output, overwrite, [params])
    rows = read_param_rows(params)
    for r, who, why in rows.skipped:
        message(f"warning: {rows.label}: row {r} ({who}) has no fit and is left out: {why}")
    fig = figures.stability_figure(rows.table, settings, outside_loop=outside_loop)
    _save(fig, output, overwrite)


__all__ = [
    "AXIS_CHOICE", "command", "bode_command", "residual_command", "uncertainty_command",
    "literature_command", "plot_stability_command",
]
