"""``armfit stability``: the stiffest virtual wall a sampled haptic device renders stably
with these arms; ``armfit fit-trials``: one fit per trial, the population it needs.

Both check their outputs first, read their inputs, call the library
(:func:`armfit.loop.stability_table`, :func:`armfit.fitting.fit_trial_models`) and write
atomically.
"""

from __future__ import annotations

import math
import warnings

import click

from armfit.api import fit_trials as api_fit_trials
from armfit.cli.grammar import CSV, file_output_option
from armfit.cli.options import (
    Number,
    Whole,
    axis_bands_option,
    bands_by_axis,
    clean,
    cluster_executor,
    effect_items,
    effects_file_option,
    emit_json,
    fit_effect_option,
    jobs_option,
    json_option,
    message,
    outside_loop_option,
    overwrite_option,
    scheduler_option,
)
from armfit.constants import PAPER_BANDS
from armfit.errors import BadInputError, UsageError
from armfit.io.atomic import atomic_path, check_output
from armfit.loop import (
    DEFAULT_DAMPING_NS_PER_M,
    DEFAULT_DELAY_SAMPLES,
    DEFAULT_SAMPLE_TIME_S,
    WallSettings,
    axis_summary,
    stability_table,
)
from armfit.models.params import read_param_rows
from armfit.spectra import Spectra
from armfit.uncertainty import read_weights_and_bands


def _kn(v: float) -> str:
    if not math.isfinite(v):
        return "inf" if v > 0 else "-"
    return f"{v / 1000:.3g}"


def stability_document(table, summary, settings, *, params_label: str,
                       weights_label: str | None, skipped, notes=()) -> dict:
    """The ``--json`` document: settings, models (in PARAMS row order), axes, skipped,
    and ``notes`` (what the command said on stderr about the inputs) when there are any."""
    models = []
    for rec in table.to_dict("records"):
        models.append({k: clean(v) for k, v in rec.items()})
    axes = {a: {k: clean(v) for k, v in s.items()} for a, s in summary.items()}
    return {
        "settings": {**settings.as_dict(), "params": params_label, "weights": weights_label},
        "models": models,
        "axes": axes,
        "skipped": [{"row": r, "trial": who, "reason": why} for r, who, why in skipped],
    } | ({"notes": list(notes)} if notes else {})


def human_table(table, summary, settings) -> str:
    """A fixed-width text table of K_max per row and the per-axis summary."""
    cert = "k_robust_N_per_m" in table.columns
    head = f"{'row':>4} {'axis':<4} {'subject':<10} {'grip N':>6} {'K_max kN/m':>10} " \
           f"{'f Hz':>7}" + (f" {'|Wu T| K=0':>10} {'K_rob kN/m':>10}" if cert else "")
    lines = [f"virtual wall: T = {settings.sample_time_s * 1e3:g} ms "
             f"({1 / settings.sample_time_s:g} Hz), B = {settings.damping_Ns_per_m:g} N*s/m, "
             f"d = {settings.delay_samples} sample(s)", head]
    for r in table.to_dict("records"):
        g = r["grip_N"]
        line = (f"{r['row']:>4} {r['axis']:<4} {str(r['subject'] or '-'):<10} "
                f"{(f'{g:g}' if math.isfinite(g) else '-'):>6} {_kn(r['k_max_N_per_m']):>10} "
                f"{r['f_unstable_hz']:>7.1f}")
        if cert:
            line += f" {r['wu_t_peak_k0']:>10.3f} {_kn(r['k_robust_N_per_m']):>10}"
        lines.append(line)
    lines.append("")
    for axis, s in summary.items():
        lines.append(f"axis {axis}: K_max min {_kn(s['k_max_min_N_per_m'])} kN/m "
                     f"(row {s['limiting_row']}: {s['limiting']}), median "
                     f"{_kn(s['k_max_median_N_per_m'])}, 5th percentile "
                     f"{_kn(s['k_max_p05_N_per_m'])} kN/m over {s['n_models']} model(s)")
    return "\n".join(lines)


def certificate_sentences(table, summary) -> list[str]:
    """Plain sentences on the robust certificate per axis: each axis's
    ``certificate_text`` of :func:`armfit.loop.axis_summary`, which the JSON holds too."""
    return [s["certificate_text"] for s in summary.values() if "certificate_text" in s]


@click.command("stability")
@click.argument("params", metavar="PARAMS")
@click.option("--sample-time", "sample_time", type=Number(), default=DEFAULT_SAMPLE_TIME_S,
              show_default=True, metavar="S", help="Servo period T in seconds (1e-3: 1 kHz).")
@click.option("--damping", type=Number(), default=DEFAULT_DAMPING_NS_PER_M, show_default=True,
              metavar="B", help="Virtual damping B of the wall, N*s/m.")
@click.option("--delay-samples", "delay", type=Whole(), default=DEFAULT_DELAY_SAMPLES,
              show_default=True, metavar="D", help="Computation delay d, whole samples.")
@click.option("--weights", "weights_path", default=None, metavar="FILE|paper",
              help="Also the robust certificate against these uncertainty weights "
                   "(fit-uncertainty output; 'paper': Table III).")
@click.option("--members", "members_path", default=None, metavar="FILE",
              help="With --weights: the per-trial fits the weight covers (fit-trials "
                   "output); the certificate never exceeds the smallest K_max among them.")
@outside_loop_option
@effects_file_option
@file_output_option("-o", "--output", "output", formats=CSV,
                    help="Write the per-model table as CSV (atomically) instead of "
                         "printing it.")
@json_option
@overwrite_option
def stability_command(params, sample_time, damping, delay, weights_path, members_path,
                      outside_loop, output, as_json, overwrite):
    """K_max: the stiffest virtual wall a sampled device renders stably with each arm.

    PARAMS is any parameters file armfit writes (fit-nominal, fit-grip, fit-trials) or a
    paper table by name (nominal, grip). The wall F[k] = -(K x[k-d] + B (x[k-d] -
    x[k-d-1])/T), held by a zero-order hold, acts on the measured dynamics of eq. 4 of
    each row, discretised exactly. Per row: K_max (N/m) and the frequency at which the
    loop first goes unstable; per axis: minimum, median and 5th percentile. Every
    effect of a row is in the loop unless named with --outside-loop. A params file with
    your own effects needs their --effects FILE, and each of them a rational form
    (docs/methods.md, "Your own effects").
    """

    settings = WallSettings(sample_time, damping, delay)
    if output is not None:
        check_output(output, overwrite=overwrite,
                     inputs=[p for p in (params, weights_path, members_path) if p])
    if members_path and not weights_path:
        raise UsageError("{opt:members} needs {opt:weights}: the members cap the robust "
                         "certificate")
    rows = read_param_rows(params)
    members = None
    if members_path:
        m_rows = read_param_rows(members_path)
        members = m_rows.table
        if m_rows.skipped:
            message(f"warning: {m_rows.label}: {len(m_rows.skipped)} member row(s) without "
                    "a fit left out of the certificate's cap")
    weights = bands = None
    weights_label = None
    if weights_path:
        weights, bands, weights_label = read_weights_and_bands(weights_path)
    for r, who, why in rows.skipped:
        message(f"warning: {rows.label}: row {r} ({who}) has no fit and is left out: {why}")
    if len(rows.table) == 0:
        raise BadInputError("no row with fitted parameters", file=rows.label)
    notes = []
    if members is not None:     # an axis without members: no cap, no check beyond the band
        have = set(members["axis"])
        for axis in sorted(set(rows.table["axis"]) & set(weights or {}) - have):
            notes.append(f"{m_rows.label} has no model of axis {axis}: its certificate is "
                         "neither capped at a member's K_max nor checked above the band")
    for text in notes:
        message(f"note: {text}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        table = stability_table(rows.table, settings, weights=weights,
                                weights_band_hz=bands, source=rows.label,
                                outside_loop=outside_loop, members=members)
    for w in caught:
        if issubclass(w.category, RuntimeWarning):
            message(f"warning: {w.message}")
    summary = axis_summary(table)
    if weights is not None:
        for text in certificate_sentences(table, summary):
            message(text)
    if output is not None:
        with atomic_path(output, overwrite=overwrite) as tmp:
            table.to_csv(tmp, index=False, float_format="%.10g")
        message(f"wrote {output} ({len(table)} models)")
    if as_json:
        emit_json(stability_document(table, summary, settings, params_label=rows.label,
                                     weights_label=weights_label, skipped=rows.skipped,
                                     notes=notes))
    elif output is None:
        click.echo(human_table(table, summary, settings))


@click.command("fit-trials")
@click.argument("spectra", type=click.Path(dir_okay=False))
@file_output_option("-o", "--output", "output", required=True, formats=CSV,
                    help="The per-trial params CSV to write (atomically).")
@click.option("--cost", type=click.Choice(["complex", "paper"]), default="complex",
              show_default=True,
              help="complex: log-magnitude and phase errors over their standard errors; "
                   "paper: dB magnitude error only (eq. 5).")
@axis_bands_option("Fit band in Hz, for one axis (AXIS=LO:HI) or every axis (LO:HI); "
                   "repeatable, later items win [default: x=0.1:30,y=0.1:30,z=0.1:10, as "
                   "the paper]; axes not named keep the default.")
@fit_effect_option
@effects_file_option
@click.option("--method", default=None, metavar="NAME",
              help="Estimator to fit when SPECTRA holds several (e.g. h1, chebwin).")
@click.option("--max-nfev", type=Whole(1, None), default=None, metavar="N",
              help="Evaluation budget of each final local fit [default: 200 per parameter].")
@jobs_option
@scheduler_option
@json_option
@overwrite_option
def fit_trials_command(spectra, output, cost, band, effects, method, max_nfev, jobs,
                       scheduler, as_json, overwrite):
    """Fit the arm model to every trial (subject x axis x grip [x run]).

    SPECTRA is the Parquet file of `armfit estimate`; its rows of level "trial" and kind
    "measured" are fitted one by one with the closed loop of eq. 4. OUTPUT has the
    layout of fit-grip plus subject, run and reason columns. A trial whose fit fails is
    listed (empty parameters, converged false, its reason) and named on stderr; the
    others are written all the same (exit 0).
    """
    bands = bands_by_axis(band, PAPER_BANDS)
    effect_objs = effect_items(effects)
    check_output(output, overwrite=overwrite, inputs=[spectra])
    # the trials, and the starts of their fits
    data = Spectra.read(spectra, level=("trial", "mean"), kind="measured",
                        estimators=False)

    def report(tf):
        who = f"{tf.axis} subject {tf.subject} {tf.grip_N:g} N" + (
            f" run {tf.run}" if tf.run is not None else "")
        if tf.fit is None:
            message(f"fit {who}: FAILED: {tf.reason}")
        else:
            message(f"fit {who}: rms {tf.fit.rms_db:.3g} dB, {tf.fit.rms_deg:.3g} deg")

    with cluster_executor(scheduler) as executor:
        result = api_fit_trials(data, cost=cost, bands=bands, effects=effect_objs,
                                method=method, max_nfev=max_nfev, jobs=jobs, on_fit=report,
                                executor=executor)
    fits = result.fits
    df = result.to_frame()
    result.write(output, overwrite=overwrite)
    failed = [tf for tf in fits if tf.fit is None]
    message(f"wrote {output} ({len(fits) - len(failed)} fits, {len(failed)} failed)")
    if as_json:
        emit_json({"command": "fit-trials", "spectra": spectra, "output": output,
                   "columns": list(df.columns),
                   "fits": [{k: clean(v) for k, v in row.items()}
                            for row in df.to_dict("records")]})
    for tf in failed:
        message(f"warning: trial {tf.axis} subject {tf.subject} {tf.grip_N:g} N"
                + (f" run {tf.run}" if tf.run is not None else "")
                + f" has no fit ({tf.reason}); listed in {output} with converged false")


__all__ = [
    "stability_document", "human_table", "certificate_sentences", "stability_command",
    "fit_trials_command",
]
