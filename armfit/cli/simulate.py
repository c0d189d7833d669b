"""``armfit simulate``: write a simulated study (raw trial files) and its truth file."""

from __future__ import annotations

from pathlib import Path

import click

from armfit.api import simulate
from armfit.cli.grammar import JSON, file_output_option
from armfit.cli.options import (
    Number,
    Whole,
    effect_files,
    effect_option,
    effects_file_option,
    emit_json,
    json_option,
    message,
    overwrite_option,
    progress,
)
from armfit.constants import AXES
from armfit.errors import UsageError
from armfit.io.atomic import check_output
from armfit.io.numbers import parse_number
from armfit.io.rawwrite import POSITION_UNITS, RAW_FORMATS
from armfit.models.effects import parse_effect_spec
from armfit.simulation import EffectSetting, StudyConfig

_DEFAULTS = StudyConfig()


def _numbers(text: str, option: str) -> tuple[float, ...]:
    try:
        return tuple(parse_number(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise UsageError(f"{option} {text!r}: expected comma-separated numbers") from None


def _axes(text: str, option: str) -> tuple[str, ...]:
    letters = tuple(c for c in text.lower() if c not in ", ")
    if not letters or any(c not in AXES for c in letters) or len(set(letters)) != len(letters):
        raise UsageError(f"{option} {text!r}: expected distinct letters of xyz, e.g. xyz or z")
    return letters


def build_config(*, subjects: int, axes: str, grips: str, duration: str, fs: float,
                 seed: int, noise: float, variability: float, drift: float, quantum: float,
                 effects: tuple[str, ...], effect_axes: str | None) -> StudyConfig:
    """Turn the command's option strings into a :class:`StudyConfig` (UsageError if bad)."""
    dur = _numbers(duration, "--duration")
    if len(dur) == 1:
        dur = (dur[0], dur[0])
    if len(dur) != 2:
        raise UsageError(f"--duration {duration!r}: give MIN,MAX in seconds, e.g. 50,100")
    on_axes = _axes(effect_axes, "--effect-axes") if effect_axes else AXES
    if effect_axes and not effects:
        raise UsageError("--effect-axes needs at least one --effect")
    settings = tuple(EffectSetting.from_parsed(e.name, v, on_axes)
                     for e, v in (parse_effect_spec(s) for s in effects))
    return StudyConfig(subjects=subjects, axes=_axes(axes, "--axes"),
                       grips_N=_numbers(grips, "--grips"), duration_s=(dur[0], dur[1]),
                       fs=fs, seed=seed, noise_m=noise, variability=variability,
                       drift_m=drift, quantum_m=quantum, effects=settings)


@click.command("simulate")
@effects_file_option
@click.option("-o", "--output", "output", required=True, type=click.Path(file_okay=False),
              metavar="DIR",
              help="Study folder to write (one file per trial; written atomically).")
@click.option("--subjects", type=Whole(1, 999), default=_DEFAULTS.subjects,
              show_default=True, metavar="N", help="Number of subjects.")
@click.option("--axes", default="xyz", show_default=True, metavar="AXES",
              help="Stimulated axes, e.g. xyz or z.")
@click.option("--grips", default="1,2,3", show_default=True, metavar="N[,N..]",
              help="Target grip forces in N (rows of the paper's Table I).")
@click.option("--duration", default="50,100", show_default=True, metavar="MIN,MAX",
              help="Trial lengths in s, drawn uniformly between MIN and MAX per trial.")
@click.option("--fs", type=Number(min=0, min_open=True), default=_DEFAULTS.fs,
              show_default=True, metavar="HZ", help="Sampling rate, Hz.")
@click.option("--seed", type=Whole(min=0), default=_DEFAULTS.seed, show_default=True,
              metavar="N", help="Random seed: the same seed gives identical files.")
@click.option("--noise", type=Number(min=0), default=_DEFAULTS.noise_m,
              show_default=True, metavar="M", help="Position sensor noise, m rms.")
@click.option("--quantum", type=Number(min=0), default=_DEFAULTS.quantum_m,
              show_default=True, metavar="M",
              help="Position encoder step, m (0: no quantisation).")
@click.option("--drift", type=Number(min=0), default=_DEFAULTS.drift_m,
              show_default=True, metavar="M",
              help="Slow postural drift (below ~0.1 Hz), m rms.")
@click.option("--variability", type=Number(0, 1), default=_DEFAULTS.variability,
              show_default=True, metavar="S",
              help="Log-sd of each subject's factor on each arm parameter (0: Table I).")
@click.option("--format", "fmt", type=click.Choice(list(RAW_FORMATS)), default="parquet",
              show_default=True, help="Trial file format.")
@click.option("--units", type=click.Choice(list(POSITION_UNITS)), default="m",
              show_default=True, help="Position units in the files.")
@effect_option
@click.option("--effect-axes", "effect_axes", default=None, metavar="AXES",
              help="Axes the effects act on, e.g. z (default: all).")
@file_output_option("--truth", "truth", formats=JSON,
                    help="Truth JSON file [default: <OUTPUT>.truth.json beside the study].")
@overwrite_option
@json_option
def command(output, subjects, axes, grips, duration, fs, seed, noise, quantum, drift,
            variability, fmt, units, effects, effect_axes, truth, overwrite, as_json):
    """Simulate a study of the paper's protocol with known truth, e.g.
    ``armfit simulate -o study --seed 1``.

    Writes one raw trial file per subject x axis x grip into OUTPUT
    (sub-01_axis-x_grip-1N.parquet, ...) and a truth JSON beside it with every parameter
    used. Effects: --effect NAME=V1[,V2..], e.g. --effect delay=0.012 or
    --effect reflex=gain_N_per_m:100,delay_s:0.03 (see `armfit effects`).
    """
    config = build_config(subjects=subjects, axes=axes, grips=grips, duration=duration,
                          fs=fs, seed=seed, noise=noise, variability=variability, drift=drift,
                          quantum=quantum, effects=effects, effect_axes=effect_axes)
    out = Path(output)
    truth_path = Path(truth) if truth else out.with_name(out.name + ".truth.json")
    if out.resolve() in truth_path.resolve().parents:
        raise UsageError(f"--truth {truth_path}: keep the truth file outside the study folder")
    check_output(out, overwrite=overwrite, folder=True)
    check_output(truth_path, overwrite=overwrite)

    sim = simulate(config)
    options = {"output": str(out), "subjects": subjects, "axes": axes, "grips": grips,
               "duration": duration, "fs": fs, "seed": seed, "noise": noise,
               "quantum": quantum, "drift": drift, "variability": variability,
               "format": fmt, "units": units, "effect": list(effects),
               "effect_axes": effect_axes, "effects_files": list(effect_files()),
               "truth": str(truth_path)}
    with progress(len(sim.plans), "simulate") as advance:
        files = sim.write(out, fmt=fmt, units=units, overwrite=overwrite, truth=truth_path,
                          options=options, advance=advance)
    seconds = sum(p.duration_s for p in sim.plans)
    message(f"simulated {len(sim.plans)} trial(s), {seconds:.0f} s of data, into {out}; "
            f"truth in {truth_path}")
    if as_json:
        emit_json({"output": str(out), "truth": str(truth_path), "trials": len(sim.plans),
                   "seconds": seconds, "format": fmt, "seed": seed, "files": files})


__all__ = [
    "build_config", "command",
]
