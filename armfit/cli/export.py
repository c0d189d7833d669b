"""``armfit export``: fitted models, uncertainty weights and measured responses as a
MATLAB (format 5) or JSON file, ready for ``tf``, ``zpk`` and ``frd``.

Checks the output first, reads the params file (and the weights and spectra given),
builds the variables with :func:`armfit.export.export_variables` (numpy coefficients:
python-control is not needed) and writes them atomically.
"""

from __future__ import annotations

import click

from armfit.cli.grammar import extension, file_output_option
from armfit.cli.options import (
    effects_file_option,
    message,
    overwrite_option,
)
from armfit.errors import UsageError
from armfit.export import EXPORT_FORMATS, export_variables, write_export
from armfit.io.atomic import check_output
from armfit.models.params import read_param_rows
from armfit.spectra import Spectra
from armfit.uncertainty import read_weights_and_bands


def _format(fmt: str | None, output: str) -> str:
    """The format the output's extension names (.mat, .json); a ``--format`` that names
    another is a usage error (exit 2)."""
    by_ext = extension(output).lstrip(".")
    if fmt is not None and fmt != by_ext:
        raise UsageError(f"--format {fmt} but -o {output} names a .{by_ext} file; the "
                         f"format follows the extension (give -o FILE.{fmt})")
    return by_ext


def _read_spectra(path: str, nominal: bool) -> Spectra:
    """What an export of a nominal file (medians and derived trials) or of a grip file
    (means) uses of the spectra file: its cross responses are never read."""
    if nominal:
        return Spectra.read(path, level=("median", "trial"), kind=("measured", "derived"),
                            estimators=False)
    return Spectra.read(path, level="mean", kind="measured", estimators=False)


@click.command("export")
@effects_file_option
@click.argument("params", type=click.Path(dir_okay=False))
@click.option("--weights", default=None, metavar="WU.csv",
              help="Also the uncertainty weights Wu as zeros, poles and gain (a "
                   "fit-uncertainty output; 'paper': Table III).")
@click.option("--spectra", "spectra_path", default=None, type=click.Path(dir_okay=False),
              help="Also the measured responses (frd data, rad/s): the median (nominal "
                   "fits) or means (grip fits), and the derived trials Wu covers.")
@click.option("--format", "fmt", type=click.Choice(list(EXPORT_FORMATS)), default=None,
              help="mat: MATLAB/Octave (format 5, scipy.io.savemat); json: the same "
                   "variables as JSON. Optional: the output's extension decides, and a "
                   "--format that names another is refused.")
@file_output_option("-o", "--output", "output", required=True,
                    formats={".mat": "MATLAB/Octave (format 5)", ".json": "JSON"},
                    help="The file to write (atomically); its format follows the extension.")
@overwrite_option
def command(params: str, weights: str | None, spectra_path: str | None, fmt: str | None,
            output: str, overwrite: bool) -> None:
    """Export fitted models for MATLAB, Octave or any JSON reader.

    PARAMS is a params file of fit-nominal or fit-grip (or run's nominal_params.csv,
    grip_params.csv; 'nominal'/'grip': the paper's Tables II, I). Per model it writes
    the closed loop X/F of eq. 4 and the arm's H_ARM (eq. 3) as numerator and
    denominator row vectors in s (rad/s), and the output delay in s (MATLAB's
    IODelay, exact): G = tf(Gx_num, Gx_den, 'IODelay', Gx_delay_s). A grip fit's
    names carry its grip (Gx_grip2N_num). The variable readme says what each holds.
    """
    fmt = _format(fmt, output)
    inputs = [p for p in (params, weights, spectra_path) if p]
    check_output(output, overwrite=overwrite, inputs=inputs)
    rows = read_param_rows(params)
    w = bands = None
    sources = {"params": rows.label}
    if weights is not None:
        w, bands, sources["weights"] = read_weights_and_bands(weights)
    spectra = None
    if spectra_path is not None:
        spectra = _read_spectra(spectra_path, "grip_N" not in rows.table.columns)
        sources["spectra"] = spectra_path
    variables, notes = export_variables(
        rows.table, weights=w, weight_bands=bands, spectra=spectra, sources=sources,
        hint="its model cannot be exported as coefficients (armfit.ModelFit.to_control("
             "..., exact=True) gives its exact frequency response)")
    for text in notes:
        message(f"note: {text}")
    write_export(variables, output, fmt, overwrite=overwrite)
    message(f"wrote {output}: " + "; ".join(_contents(variables)))


def _contents(variables) -> list[str]:
    """What an export holds, in words: the models, weights, measured responses and
    derived trials, each by name."""
    out = []
    for letter, suffix, what in (("G", "_num", "models"), ("W", "_k", "weights"),
                                 ("M", "_resp", "measured responses"),
                                 ("D", "_resp", "derived trials")):
        names = [k[1:-len(suffix)] for k in variables
                 if k.startswith(letter) and k.endswith(suffix)]
        if names:
            out.append(f"{what} {', '.join(names)}")
    return out


__all__ = ["command"]
