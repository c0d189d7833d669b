"""``armfit ingest``: raw trial files in, one canonical dataset (Parquet) out."""

from __future__ import annotations

import contextlib

import click

from armfit.cli.grammar import file_output_option, old_spelling
from armfit.cli.options import (
    Number,
    emit_json,
    json_option,
    manifest_option,
    map_note,
    map_option,
    message,
    overwrite_option,
    progress,
    skip_bad_option,
    verbosity,
)
from armfit.constants import FORCE_LIMIT_N, GRID_HZ
from armfit.io.trials import TrialStream, ingest


@click.command("ingest")
@click.argument("paths", nargs=-1, type=click.Path())
@file_output_option("-o", "--output", "output", required=True,
                    formats={".parquet": "the canonical dataset"},
                    help="The dataset to write (atomically).")
@manifest_option
@map_option
@skip_bad_option
@click.option("--resample", is_flag=True,
              help="Resample trials whose sampling rate differs to the most common rate "
                   "(default: such a trial is an error).")
@click.option("--fmin", type=Number(min=0, min_open=True), default=GRID_HZ[0],
              show_default=True, metavar="HZ",
              help="Lowest frequency to be estimated, Hz; a trial must last at least "
                   "2/HZ s.")
@old_spelling("--f-min", "--fmin")
@click.option("--force-limit", "force_limit", type=Number(min=0, min_open=True),
              default=FORCE_LIMIT_N, show_default=True, metavar="N",
              help="Device peak force, N; forces reaching it are warned about "
                   "(saturation).")
@overwrite_option
@json_option
def command(paths, output, manifest, column_map, skip_bad, resample, fmin, force_limit,
            overwrite, as_json):
    """Read raw trial files and folders (CSV, CSV.gz, Parquet) and write one canonical
    dataset, e.g. ``armfit ingest raw/ -o trials.parquet``.

    Trials are named sub-<label>_axis-<x|y|z>_grip-<g>N[_run-<k>].<csv|csv.gz|parquet>
    or listed in --manifest. A canonical dataset is accepted as input too. Files in a
    lab's own columns and units (CSV, Parquet, MATLAB .mat) are read through a column
    map (--map, or the manifest's column map).
    """
    if not paths and manifest is None:
        raise click.UsageError("give trial files or folders, or --manifest")

    with contextlib.ExitStack() as stack:
        bar = {}

        def on_open(stream: TrialStream) -> None:
            if verbosity() > 0:
                for p in stream.ignored:
                    message(f"ignored (not a trial name): {p}")
            bar["advance"] = stack.enter_context(progress(len(stream), "ingest"))

        result = ingest(paths, output, manifest=manifest, skip_bad=skip_bad,
                        resample=resample, f_min_hz=fmin, force_limit_N=force_limit,
                        overwrite=overwrite, warn=lambda text: message(f"warning: {text}"),
                        advance=lambda: bar["advance"](), on_open=on_open,
                        column_map=column_map, note=map_note)
    for s in result.skipped:
        message(f"skipped {s.file}: {s.reason}")
    message(f"ingested {len(result.trials)} trial(s) into {result.output}"
            + (f"; skipped {len(result.skipped)}" if result.skipped else ""))
    if as_json:
        emit_json({
            "trials": len(result.trials),
            "skipped": [{"file": s.file, "reason": s.reason} for s in result.skipped],
            "output": result.output,
            "ignored": list(result.ignored),
            "items": [{"subject": m.subject, "axis": m.axis, "grip_N": m.grip_N,
                       "run": m.run, "fs": m.fs, "n_samples": m.n_samples,
                       "duration_s": m.duration_s, "t0_s": m.t0_s, "source": m.source,
                       **({} if m.column_map is None
                          else {"column_map": m.column_map.path})}
                      for m in result.trials],
        })


__all__ = [
    "command",
]
