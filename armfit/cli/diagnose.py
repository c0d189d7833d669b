"""``armfit effects``, ``armfit compare`` and ``armfit diagnose``: where the model fails and
which physical effect is missing."""

from __future__ import annotations

from typing import TYPE_CHECKING

import click

from armfit.api import ModelFit
from armfit.api import compare as api_compare
from armfit.api import diagnose as api_diagnose
from armfit.cli.grammar import JSON, file_output_option, table_console
from armfit.cli.options import (
    Number,
    Whole,
    band_option,
    effects_file_option,
    emit_json,
    jobs_option,
    json_option,
    message,
    overwrite_option,
    verbosity,
)
from armfit.diagnosis import comparison_notes
from armfit.diagnosis.tuning import MAX_STEPS, MIN_EFFECT_DB, MIN_EFFECT_DEG, SHARED_EFFECTS
from armfit.errors import BadInputError, UsageError
from armfit.io.atomic import check_output
from armfit.models.effects import EFFECTS, get_effect
from armfit.spectra import Spectra

if TYPE_CHECKING:   # rich is imported when a table is printed, after the work is done
    from rich.table import Table

_BAND_HELP = ("Frequency band in Hz, for one axis (AXIS=LO:HI) or every axis (LO:HI); "
              "repeatable, later items win [default: the whole grid of the spectra "
              "file]; axes not named keep the default.")


def _effects(names) -> list:
    return [get_effect(n) for n in names]


def _console(stderr: bool = False):
    return table_console(stderr=stderr)


@click.command("effects")
@effects_file_option
@json_option
def effects_command(as_json):
    """List the physical effects the 5-parameter model lacks, with their parameters,
    physical ranges and when to suspect each, e.g. ``armfit effects``: the built-in
    library, effects of installed packages (entry-point group ``armfit.effects``) and of
    each ``--effects FILE`` (a Python file with a module-level EFFECTS list of
    ``armfit.Effect``; see ``examples/device_spring.py``)."""
    rows = [{"effect": e.name, "acts_on": e.stage, "summary": e.summary,
             "suspect_when": e.suspect_when, "source": EFFECTS.describe_origin(e.name),
             "params": [{"name": p.name, "unit": p.unit, "lower": p.lower, "upper": p.upper,
                         "description": p.description} for p in e.params]}
            for e in EFFECTS.values()]
    if as_json:
        emit_json({"effects": rows})
        return
    from rich.markup import escape
    from rich.table import Table
    t = Table(title="armfit effect library", show_lines=True)
    for c in ("effect", "parameters", "what it is", "suspect it when"):
        t.add_column(c, overflow="fold")
    for r in rows:
        params = "\n".join(escape(f"{p['name']} [{p['unit']}] {p['lower']:g}…{p['upper']:g}")
                           for p in r["params"])
        what = r["summary"] + ("" if r["source"] == "the built-in library"
                               else f" (from {r['source']})")
        t.add_row(r["effect"], params, escape(what), r["suspect_when"])
    _console().print(t)


@click.command("compare")
@effects_file_option
@click.argument("spectra", type=click.Path(dir_okay=False))
@click.option("--model", "model_path", required=True, type=click.Path(dir_okay=False),
              help="Params CSV from fit-grip or fit-nominal.")
@click.option("--level", type=click.Choice(["mean", "median", "trial"]), default=None,
              help="Measurements to compare with (default: mean for grip fits, median for "
                   "nominal fits).")
@click.option("--effect", "effect_names", multiple=True, metavar="NAME",
              help="Add this effect, refit, and show the error before and after (repeatable).")
@band_option(_BAND_HELP)
@json_option
def compare_command(spectra, model_path, level, effect_names, band, as_json):
    """Compare a fitted model with the measurements: RMS magnitude (dB), phase (deg) and
    noise-normalised error overall and per band, and where the model fails, in words.

    Example: ``armfit compare spectra.parquet --model nominal_params.csv --effect delay``
    """
    model = ModelFit.read(model_path)
    # all a comparison uses
    data = Spectra.read(spectra, kind="measured", estimators=False)
    result = api_compare(data, model, level=level, band=band,
                         effects=_effects(effect_names))
    level, rows = result.level, result.rows
    for text in result.notes:
        message(f"note: {text}")
    if not rows:
        raise UsageError(f"{spectra}: holds no {level}-level measured responses for the "
                         f"axes of {model_path}")
    if as_json:
        emit_json(result.to_dict())
        return
    title = f"model vs measurements ({level}); cells: RMS dB/deg/× noise"
    if band is None and level != "trial":
        title += "; overall: over each model's fit band"
    from rich.measure import Measurement
    con = _console()
    t = _compare_table(title, rows, "/")
    if Measurement.get(con, con.options.update_width(10**6), t).maximum > con.width:
        t = _compare_table(title, rows, "/ ")   # too wide: cells may wrap after a "/"
    con.print(t)
    for r in rows:
        head = f"{r.axis}" + ("" if r.grip_N is None else f" {r.grip_N:g} N") + f" {r.model}"
        if r.params:
            head += " (" + ", ".join(f"{k}={v:.4g}" for k, v in r.params.items()) + ")"
        if not r.failing:
            con.print(f"{head}: fits within the noise everywhere", highlight=False)
        for fb in r.failing:
            con.print(f"{head}: fails {fb.lo_hz:.3g}–{fb.hi_hz:.3g} Hz: {fb.description}",
                      highlight=False)


def _compare_table(title: str, rows, sep: str) -> Table:
    """The table of ``compare``: one row per comparison, one column per band of any row
    (a row's cell is empty for a band outside its own), cells ``dB{sep}deg{sep}× noise``."""
    from rich.table import Table
    spans = sorted({(b.lo_hz, b.hi_hz) for r in rows for b in r.bands})
    t = Table(title=title)
    for c in ("axis", "grip N", "model", "overall",
              *(f"{lo:g}–{hi:g} Hz" for lo, hi in spans)):
        t.add_column(c, overflow="fold")

    def cell(b):
        return sep.join((f"{b.rms_db:.2f}", f"{b.rms_deg:.1f}", f"{b.rms_norm:.2f}")) \
            if b.n_points else "–"

    for r in rows:
        by_span = {(b.lo_hz, b.hi_hz): cell(b) for b in r.bands}
        t.add_row(r.axis, "" if r.grip_N is None else f"{r.grip_N:g}", r.model,
                  cell(r.overall), *(by_span.get(span, "") for span in spans))
    return t


@click.command("diagnose")
@effects_file_option
@click.argument("spectra", type=click.Path(dir_okay=False))
@click.option("--model", "model_path", required=True, type=click.Path(dir_okay=False),
              help="Params CSV from fit-grip (preferred: per-grip starts) or fit-nominal.")
@band_option(_BAND_HELP)
@click.option("--effect", "effect_names", multiple=True, metavar="NAME",
              help="Only these candidates (repeatable; default: the whole effect library).")
@file_output_option("-o", "--output", "output", formats=JSON,
                    help="Also write the JSON document to this file (atomically).")
@jobs_option
@click.option("--max-steps", type=Whole(0, 10), default=MAX_STEPS, show_default=True,
              metavar="N", help="At most N effects added, one per step (0: only judge "
                                "the base model).")
@click.option("--min-effect-db", type=Number(0.0), default=MIN_EFFECT_DB,
              show_default=True, metavar="DB",
              help="Practical floor in magnitude, dB: an effect is named only if it "
                   "changes the fitted response by more than DB (and more than the noise) "
                   "somewhere in the band, or by more than --min-effect-deg in phase.")
@click.option("--min-effect-deg", type=Number(0.0), default=MIN_EFFECT_DEG,
              show_default=True, metavar="DEG",
              help="Practical floor in phase, deg: an effect is named only if it "
                   "changes the fitted phase by more than DEG (and more than the noise) "
                   "somewhere in the band, or the magnitude by more than the floor in dB.")
@click.option("--share", "share", multiple=True, metavar="NAME",
              help="Effects whose parameters are compared across axes (repeatable; default: "
                   f"{' and '.join(SHARED_EFFECTS)}, the apparatus effects).")
@click.option("--no-share", is_flag=True, help="Compare no effect across axes.")
@click.option("--shared-only", is_flag=True,
              help="Do not test effects for one value per subject: every effect is shared "
                   "by the trials of an axis.")
@overwrite_option
@json_option
def diagnose_command(spectra, model_path, band, effect_names, output, jobs, max_steps,
                     min_effect_db, min_effect_deg, share, no_share, shared_only, overwrite,
                     as_json):
    """Find the physical effects the 5-parameter model is missing, per axis, step by step.

    Fits the base model to every trial (arm parameters per trial); while the model is not
    within the noise, adds the library effect with the best ΔBIC that is significant and
    changes the response by more than the noise and the floors, refitting all added
    effects jointly (parameters shared by the trials, or one value per subject where the
    data demand it). Prints one row per step and the verdict: adequate, or how much
    misfit remains and where. Example:
    ``armfit diagnose spectra.parquet --model grip_params.csv``
    """
    if output:
        check_output(output, overwrite=overwrite, inputs=[spectra, model_path])
    if no_share and share:
        raise UsageError("give --share or --no-share, not both")
    # a plain file of base-model fits is read without pandas: the diagnosis needs only
    # its base parameters
    model = ModelFit.read_starts(model_path)
    # the trials' on-axis responses, and their cross-axis ones for the coupling
    data = Spectra.read(spectra, level="trial", kind=("measured", "cross"),
                        estimators=False)
    notes = comparison_notes(data, model.start_rows, "trial", spectra_label=spectra,
                             params_label=model_path, action="diagnosed")
    for text in notes:
        message(f"note: {text}")
    try:
        result = api_diagnose(data, model, band=band, jobs=jobs,
                              effects=_effects(effect_names) if effect_names else None,
                              max_steps=max_steps, min_effect_db=min_effect_db,
                              min_effect_deg=min_effect_deg,
                              share=() if no_share else ([get_effect(n).name for n in share]
                                                         if share else None),
                              by_subject=not shared_only)
    except BadInputError as exc:
        if exc.column != "level":
            raise
        raise UsageError(f"{spectra}: holds no trial-level measured responses for the axes "
                         f"of {model_path}") from None
    results = result.axes
    if output:
        result.write(output, overwrite=overwrite)
    doc = result.to_dict()
    if as_json:
        emit_json(doc | ({"notes": notes} if notes else {}))
        # the steps still reach the user, on stderr (stdout holds the JSON)
        if verbosity() >= 0:
            _print_steps(results, doc, _console(stderr=True))
        return
    _print_steps(results, doc, _console())
    message("diagnosis done")


def _print_steps(results, doc, con) -> None:
    """One table per axis, one row per step, then the failing bands and the verdict."""
    from rich.table import Table
    for d in results:
        t = Table(title=f"axis {d.axis}: {d.n_trials} trials, "
                        f"{d.band[0]:.3g}–{d.band[1]:.3g} Hz — stepwise search")
        for c in ("step", "effect added", "parameters (95 % interval)", "RMS dB",
                  "RMS deg", "× noise", "ΔBIC"):
            t.add_column(c, overflow="fold")
        for i, st in enumerate(d.steps):
            ps = ", ".join(
                f"{k}={v:.4g}" + (f" ({st.params_lo[k]:.4g}…{st.params_hi[k]:.4g})"
                                  if k in st.params_lo and k in st.params_hi else "")
                + (" [mean of the subjects']" if k in st.varying else "")
                + (" [at bound]" if k in st.at_bound else "")
                for k, v in st.params.items())
            t.add_row(str(i), st.effect or "base model", ps, f"{st.rms_db:.2f}",
                      f"{st.rms_deg:.1f}", f"{st.rms_norm:.2f}",
                      "" if st.effect is None else f"{st.delta_bic:.1f}")
        con.print(t)
        for fb in d.failing:
            con.print(f"  base model fails {fb.lo_hz:.3g}–{fb.hi_hz:.3g} Hz: "
                      f"{fb.description}", highlight=False)
        if d.coupling:
            con.print("  cross-axis motion (off-axis / on-axis, median): " + ", ".join(
                f"{k} {v:+.1f} dB" for k, v in d.coupling.items()), highlight=False)
        con.print(f"  verdict: {d.verdict}", highlight=False)
        for m in d.missing_effects:
            for p in m.varying:
                con.print(f"  {m.effect} {p} per subject (95 % interval): " + ", ".join(
                    f"{subj} {v[p]:.4g} ({m.by_subject_lo[subj][p]:.4g}…"
                    f"{m.by_subject_hi[subj][p]:.4g})" for subj, v in m.by_subject.items())
                    + f"; spread sd {m.spread[p]['sd']:.3g}", highlight=False,
                    soft_wrap=True)
        for test in d.subject_tests:
            if not test.by_subject:
                tried = ", ".join(f"{x.param} ΔBIC {x.delta_bic:.1f}" for x in test.trials)
                con.print(f"  {test.effect}: one shared value suffices ({test.n_subjects} "
                          f"subjects; one value per subject: {tried})", highlight=False)
        for c in d.failed_candidates:
            con.print(f"  candidate {c.effect} left out: {c.reason}", highlight=False,
                      markup=False, soft_wrap=True)
    for name, e in doc.get("shared_effects", {}).items():
        vals = ", ".join(f"{p} {v['common']:.4g} (χ² {v['chi2']:.1f}, p {v['p']:.2g})"
                         for p, v in e["params"].items())
        word = "disagree" if e["disagree"] else "agree"
        con.print(f"{name} on axes {', '.join(e['axes'])}: the axes {word}; common value "
                  f"{vals}", highlight=False)


__all__ = [
    "effects_command", "compare_command", "diagnose_command",
]
