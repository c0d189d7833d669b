"""``armfit estimate``: trials in, per-trial and aggregate frequency responses out."""

from __future__ import annotations

import contextlib

import click

from armfit.api import estimate_config, estimate_study_result
from armfit.cli.grammar import extension, file_output_option, old_spelling
from armfit.cli.options import (
    Number,
    Whole,
    cluster_executor,
    emit_json,
    jobs_option,
    json_option,
    manifest_option,
    map_note,
    map_option,
    message,
    overwrite_option,
    progress,
    scheduler_option,
    skip_bad_option,
)
from armfit.constants import AXES, DEVICE_MASS_KG
from armfit.errors import UsageError
from armfit.io.atomic import atomic_outputs, check_output
from armfit.io.numbers import parse_number
from armfit.io.trials import with_map
from armfit.spectra import EstimateConfig, estimator_summary

WINDOWS = ("hann", "hamming", "blackman", "blackmanharris", "boxcar")


#: The defaults of every option: those of the estimator configuration.
_DEFAULTS = EstimateConfig()


def _parse_mp(ctx, param, value: str | None) -> dict[str, float]:
    mp = dict(DEVICE_MASS_KG)
    if not value:
        return mp
    for item in value.split(","):
        axis, sep, num = item.partition("=")
        axis = axis.strip().lower()
        try:
            mass = parse_number(num)
        except ValueError:
            mass = float("nan")
        if not sep or axis not in AXES or not mass > 0:
            raise click.BadParameter(f"expected AXIS=KG items like x=0.09,y=0.095 with AXIS "
                                     f"x, y or z and KG > 0, got {item!r}")
        mp[axis] = mass
    return mp


#: What ``-o`` writes, by extension.
_FORMATS = {".parquet": "the spectra file the later commands read",
                  ".csv": "the same table as CSV, for other tools"}


@click.command("estimate")
@click.argument("paths", nargs=-1, type=click.Path())
@file_output_option("-o", "--output", "output", required=True, formats=_FORMATS,
                    help="The spectra table to write (atomically); its format follows "
                         "the extension.")
@manifest_option
@map_option
@skip_bad_option
@click.option("--method", type=click.Choice(["h1", "chebwin"]), default=_DEFAULTS.method,
              show_default=True,
              help="Measured-dynamics estimator: Welch H1 (best on simulated truth) or the "
                   "paper's whole-record FFT ratio with 100 dB Chebyshev windows.")
@click.option("--reference/--no-reference", default=_DEFAULTS.reference, show_default=True,
              help="With h1: estimate X/F through a trial's reference column (ref_<a>_N, "
                   "the commanded force, or ref_<a>_m, the reference trajectory) when it "
                   "has one, S_xr/S_Fr; --no-reference: H1 whatever the trials hold.")
@click.option("--fmin", type=Number(min=0, min_open=True), default=_DEFAULTS.fmin,
              show_default=True, metavar="HZ", help="Lowest grid frequency, Hz.")
@click.option("--fmax", type=Number(min=0, min_open=True), default=_DEFAULTS.fmax,
              show_default=True, metavar="HZ",
              help="Highest grid frequency, Hz (<= Nyquist).")
@click.option("--per-decade", type=Whole(1, 1000), default=_DEFAULTS.per_decade,
              show_default=True, metavar="N",
              help="Grid points per decade (log-spaced, band-averaged).")
@click.option("--nperseg", type=Whole(8), default=None, metavar="SAMPLES",
              help="H1 segment length [default: power of 2 lasting >= 2/fmin, halved down "
                   "to 1/fmin while a trial holds fewer than 4 segments].")
@click.option("--overlap", type=Number(0, 1, max_open=True), default=_DEFAULTS.overlap,
              show_default=True, metavar="F", help="H1 segment overlap (fraction).")
@click.option("--window", type=click.Choice(WINDOWS), default=_DEFAULTS.window,
              show_default=True,
              help="H1 window.")
@click.option("--mp", "mp", callback=_parse_mp, metavar="AXIS=KG,...",
              help="Device mass per axis for the derived arm dynamics [default: the paper's "
                   "x=0.09,y=0.095,z=0.091].")
@click.option("--min-coherence", type=Number(0, 1), default=_DEFAULTS.coherence_min,
              show_default=True, metavar="F",
              help="Grid points with lower coherence (0..1) are flagged low_coherence.")
@old_spelling("--coherence-min", "--min-coherence")
@click.option("--force-limit", "force_limit", type=Number(min=0, min_open=True),
              default=_DEFAULTS.force_limit_N, show_default=True, metavar="N",
              help="Device peak force, N; trials reaching it are flagged saturation.")
@file_output_option("--csv", "csv_path", formats={".csv": "the table as CSV"},
                    help="Also write the table as CSV.")
@jobs_option
@scheduler_option
@overwrite_option
@json_option
def command(paths, output, manifest, column_map, skip_bad, method, reference, fmin, fmax,
            per_decade, nperseg, overlap, window, mp, min_coherence, force_limit, csv_path,
            jobs, scheduler, overwrite, as_json):
    """Estimate frequency responses of every trial and their mean and median, e.g.
    ``armfit estimate trials.parquet -o spectra.parquet``.

    PATHS are raw trial files, folders, or a canonical dataset from `armfit ingest`.
    Per trial: measured dynamics X/F (and cross-axis responses), derived arm dynamics
    Xa/Fa with Fa = F - Mp*x'' (tfestimate semantics); on a log grid fmin..fmax, with
    coherence, standard errors and flags. Aggregates: mean per axis x grip over subjects,
    median per axis over all trials. Output: one table (see docs/formats.md), Parquet
    for the later commands (OUTPUT.parquet) or CSV (OUTPUT.csv).
    """
    if not paths and manifest is None:
        raise click.UsageError("give trial files or folders, a dataset, or --manifest")
    if fmin >= fmax:
        raise UsageError(f"--fmin {fmin:g} Hz must be below --fmax {fmax:g} Hz")
    inputs = with_map(paths, column_map)
    check_output(output, overwrite=overwrite, inputs=inputs, manifest=manifest)
    if csv_path is not None:
        check_output(csv_path, overwrite=overwrite, inputs=inputs + [output],
                     manifest=manifest)
    config = estimate_config(method=method, fmin=fmin, fmax=fmax, per_decade=per_decade,
                             nperseg=nperseg, overlap=overlap, window=window, mp=mp,
                             coherence_min=min_coherence, force_limit_N=force_limit,
                             reference=reference)
    with contextlib.ExitStack() as stack:
        executor = stack.enter_context(cluster_executor(scheduler))
        bar = {}

        def on_open(n_trials: int) -> None:
            bar["advance"] = stack.enter_context(progress(n_trials, "estimate"))

        result = estimate_study_result(list(paths), config, manifest=manifest,
                                       skip_bad=skip_bad, jobs=jobs, on_open=on_open,
                                       advance=lambda: bar["advance"](),
                                       warn=lambda text: message(f"warning: {text}"),
                                       executor=executor, column_map=column_map,
                                       note=map_note)
    meta = result.meta
    with atomic_outputs(overwrite=overwrite):  # the table and the CSV, or neither
        if extension(output) == ".csv":
            result.spectra.write_csv(output, overwrite=overwrite)
        else:
            result.write(output, overwrite=overwrite)
        if csv_path is not None:
            result.spectra.write_csv(csv_path, overwrite=overwrite)
    for f, r in result.skipped:
        message(f"skipped {f}: {r}")
    through = sum(t.check is not None and t.check.reference is not None
                  for t in result.trials)
    message(f"estimated {len(result.trials)} trial(s) into {output}"
            + (f" ({through} through their reference column)" if through else "")
            + (f"; skipped {len(result.skipped)}" if result.skipped else ""))
    if as_json:
        counts = result.counts()
        emit_json({
            "output": str(output),
            "csv": csv_path,
            "method": config.method,
            "trials": len(result.trials),
            "skipped": meta["skipped"],
            "ignored": list(result.ignored),
            "fs_hz": result.fs,
            "grid": {"fmin_hz": fmin, "fmax_hz": fmax, "points": len(meta["grid_hz"])},
            **counts,
            "estimators": estimator_summary(result.trials),
        })


__all__ = [
    "WINDOWS", "command",
]
