"""report.md of ``armfit run``: the run's typed results in words and tables.

:func:`report_markdown` renders a :class:`RunRecord` — the configuration a run used and
the typed results of its stages (:class:`armfit.api.ModelFit`,
:class:`armfit.api.Uncertainty`, :class:`armfit.api.Diagnosis` with its
:class:`armfit.diagnosis.AxisDiagnosis`, :class:`armfit.adopt.Adoption`,
:class:`armfit.api.Comparisons` and the stability stage's :class:`Wall`) — section by
section, each section a function of the results it shows. The text holds no timestamps
or timings: the same results give the same bytes.
"""

from __future__ import annotations

import math
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from armfit import api
from armfit._version import __version__
from armfit.adopt import Adoption
from armfit.constants import AXES, FORCE_LIMIT_N, GRID_HZ, PAPER_BANDS
from armfit.diagnosis import BANDS, AxisDiagnosis, Candidate, Step
from armfit.io.schema import finite_or_none
from armfit.loop import WallSettings, certificate_status
from armfit.spectra import EstimateConfig
from armfit.tables import cell_names, param_names, sig4, unit_of

if TYPE_CHECKING:   # pandas is imported where a table is made (it takes ~0.15 s)
    import pandas as pd

__all__ = ["FIGURE_CAPTIONS", "STABILITY_FIGURE", "RunRecord", "RunSettings", "Wall",
           "adoption_markdown", "md_table", "params_markdown", "report_markdown",
           "stability_markdown"]

#: The stability figure written by ``armfit run`` (figures on), relative to OUTDIR.
STABILITY_FIGURE = "figures/stability.png"

#: Captions of the figures of ``armfit run`` (a residual figure's is made per axis).
FIGURE_CAPTIONS: Mapping[str, str] = {
    "figures/bode.png": "Measured dynamics X/F per axis with the grip fits "
                        "(the paper's Fig. 5)",
    "figures/uncertainty.png": "Derived arm dynamics with the nominal H_ARM, "
                               "W_max and |Wu| (Fig. 6)",
    "figures/literature.png": "H_ARM of the X axis at 1 N grip against the "
                              "literature models of Table IV (Fig. 7)",
    STABILITY_FIGURE: "Stiffest stable virtual wall per subject and grip, and "
                      "against servo rate for d = 0, 1, 2",
}


class RunSettings(Protocol):
    """The options of a run the report states (those of
    :class:`armfit.pipeline.RunOptions`)."""

    manifest: str | None
    skip_bad: bool
    method: str
    cost: str
    wu_cost: str
    figures: bool
    adopt: str
    outside_loop: tuple[str, ...]
    column_map: str | None
    force_limit_N: float
    fmin: float
    fmax: float
    bands: tuple[tuple[str, float, float], ...]


@dataclass(frozen=True)
class Wall:
    """The stability stage's results: the stiffest stable virtual wall.

    Attributes
    ----------
    settings : WallSettings
        Servo rate, damping and delay of the loop.
    summary : mapping
        Per axis, :func:`armfit.loop.axis_summary` of the per-trial fits (K_max minimum,
        median and 5th percentile in N/m, the number of trials, what limits it).
    failed : tuple of (str, str)
        Trials without a fit, with the reason.
    certificate : pandas.DataFrame
        The robust certificate of the nominal models (certificate.csv).
    warnings : tuple of str
        Warnings of the stability computation.
    figure : str or None
        The stability figure, relative to OUTDIR, when drawn.
    n_models : int
        Rows of stability.csv.
    base_nominal : pandas.DataFrame or None
        K_max of the base model's nominal fits, when an effect is adopted.
    in_loop : mapping
        {axis: the adopted effects inside the loop}.
    outside_loop : tuple of str
        Effects left out of the loop (``--outside-loop``).
    by_subject : mapping
        {axis: {subject: K_max N/m}} (:func:`armfit.loop.subject_summary`), for the axes
        whose adopted model has effect values per subject (empty otherwise).
    """

    settings: WallSettings
    summary: Mapping[str, Mapping[str, object]]
    failed: tuple[tuple[str, str], ...]
    certificate: pd.DataFrame
    warnings: tuple[str, ...]
    figure: str | None
    n_models: int
    base_nominal: pd.DataFrame | None
    in_loop: Mapping[str, tuple[str, ...]]
    outside_loop: tuple[str, ...]
    by_subject: Mapping[str, Mapping[str, float]] = field(default_factory=dict)


@dataclass(frozen=True)
class RunRecord:
    """What report.md shows: the configuration of a run and its stages' typed results.

    Attributes
    ----------
    inputs : tuple of str
        The inputs as given.
    outdir : str
        The output folder as given.
    options : RunSettings
        The run's options.
    config : EstimateConfig
        The estimator's configuration.
    n_trials : int
        Trials estimated.
    skipped : tuple of (str, str)
        (file, reason) of the trials left out.
    grip, nominal : armfit.api.ModelFit
        Tables I and II of the model every product uses (the adopted one).
    base_grip, base_nominal : armfit.api.ModelFit or None
        The base model's Tables I and II, when an effect is adopted.
    bands : mapping
        {axis: (lo, hi) Hz}, fit bands of ``grip`` and ``nominal``.
    uncertainty : armfit.api.Uncertainty
        W_max and Wu (Table III).
    diagnosis : armfit.api.Diagnosis
    adoption : Adoption
    comparisons : armfit.api.Comparisons
        The nominal models against the medians.
    wall : Wall
        The stability stage's results.
    figures : tuple of str
        Figures written, relative to OUTDIR, in the order they are shown.
    files : tuple of str
        Every file of OUTDIR, relative to it.
    """

    inputs: tuple[str, ...]
    outdir: str
    options: RunSettings
    config: EstimateConfig
    n_trials: int
    skipped: tuple[tuple[str, str], ...]
    grip: api.ModelFit
    nominal: api.ModelFit
    base_grip: api.ModelFit | None
    base_nominal: api.ModelFit | None
    bands: Mapping[str, tuple[float, float]]
    uncertainty: api.Uncertainty
    diagnosis: api.Diagnosis
    adoption: Adoption
    comparisons: api.Comparisons
    wall: Wall | None
    figures: tuple[str, ...]
    files: tuple[str, ...]


# ---------------------------------------------------------------------------
# Formatting
# ---------------------------------------------------------------------------

def md_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> list[str]:
    """A Markdown table (lines, a blank one last); a ``|`` in a cell is written ``\\|``.

    Parameters
    ----------
    header : sequence of str
        Column titles.
    rows : sequence of sequences
        Cells, shown with ``str``.

    Returns
    -------
    list of str
    """
    def cell(v) -> str:
        return str(v).replace("|", "\\|")
    lines = ["| " + " | ".join(header) + " |",
             "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return lines + [""]


def _num(v, fmt: str = ".3g") -> str:
    """``v`` formatted, "–" for a missing or infinite value."""
    if v is None:
        return "–"
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "–" if not math.isfinite(x) else format(x, fmt)


def _kn(v) -> str:
    """N/m as kN/m."""
    return _num(float(v) / 1e3 if v is not None else None, ".3g")


#: the footnotes of a parameter table's marks, as the LaTeX tables word them
_MARK_NOTES = {"†": "† at a physical bound of the fit (within 1 % of its range): a limit, "
                    "not an estimate.",
               "‡": "‡ held at the value estimated jointly from every trial of the axis (an "
                    "effect of the apparatus, shared by the trials; for one whose values "
                    "differ between subjects, the subjects' mean, each subject's own being "
                    "held in its per-trial fits), not fitted here."}


def _params_rows(df: pd.DataFrame) -> tuple[list[str], list[list[str]], set[str]]:
    """Header, rows and the marks used (``†`` a value at a physical bound, ``‡`` a value
    held at the diagnosis's) of a parameter table (Table I or II)."""
    names = param_names(df)
    grip = "grip_N" in df.columns
    header = ["axis"] + (["grip (N)"] if grip else []) + \
        [f"{n} ({unit_of(n).replace('*', '·')})" for n in names] + \
        ["rms dB", "rms deg", "rms × noise"]
    rows, marks = [], set()
    for _, r in df.iterrows():
        stuck = cell_names(r.get("at_bound"))
        held = cell_names(r.get("held"))
        cells = []
        for n in names:
            mark = ("†" if n in stuck else "") + ("‡" if n in held else "")
            marks.update(mark)
            cells.append(sig4(float(r[n])) + mark)
        rows.append([str(r["axis"])] + ([f"{float(r['grip_N']):g}"] if grip else [])
                    + cells + [_num(r["rms_db"], ".2f"), _num(r["rms_deg"], ".1f"),
                               _num(r["rms_norm"], ".2f")])
    return header, rows, marks


def params_markdown(df: pd.DataFrame) -> list[str]:
    """A parameter table (Table I or II) in Markdown with its marks' footnotes.

    Parameters
    ----------
    df : pandas.DataFrame
        A params table (the params CSV's columns; ``at_bound`` and ``held`` optional).

    Returns
    -------
    list of str
        The table's lines, then one line per mark used (``†`` at a physical bound, ``‡``
        held at the diagnosis's value).
    """
    header, rows, marks = _params_rows(df)
    notes = [_MARK_NOTES[m] for m in ("†", "‡") if m in marks]
    return md_table(header, rows) + ([" ".join(notes), ""] if notes else [])


def _pairs_text(reps) -> str:
    """Each root pair of a Wu as Table III writes it: ``re ± im j``, a double real root
    (imaginary part 0, as ``wu.csv`` stores it) as ``re (double)``."""
    return "; ".join(f"{r.real:.4g} (double)" if r.imag == 0
                     else f"{r.real:.4g} ± {abs(r.imag):.4g}j" for r in reps) or "–"


def _bands_text(bands: Mapping[str, tuple[float, float]]) -> str:
    """Fit bands in words, axes of one band together: "x, y 0.1–30 Hz and z 0.1–10 Hz"."""
    groups: dict[tuple[float, float], list[str]] = {}
    for axis in AXES:
        if axis in bands:
            groups.setdefault(tuple(bands[axis]), []).append(axis)
    return " and ".join(f"{', '.join(axes)} {lo:g}–{hi:g} Hz"
                        for (lo, hi), axes in groups.items())


# ---------------------------------------------------------------------------
# The sections, in the order of the report
# ---------------------------------------------------------------------------

def report_markdown(record: RunRecord) -> str:
    """The text of report.md.

    What was done with the configuration each stage used, the tables, the diagnosis per
    axis in words, the stiffest stable wall, the figures and the files; no timestamps or
    timings (the same results give the same text).

    Parameters
    ----------
    record : RunRecord
        The run's configuration and typed results.

    Returns
    -------
    str
    """
    adopted = bool(record.adoption.adopted_axes)
    lines = _heading(record)
    lines += adoption_markdown(record.adoption, record.wall)
    lines += _what_was_done(record)
    lines += _parameter_tables(record, adopted)
    lines += _uncertainty_table(record.uncertainty)
    lines += _diagnosis_section(record.diagnosis)
    lines += _compare_section(record.comparisons)
    if record.wall is not None:
        lines += stability_markdown(record.wall)
    if record.figures:
        lines += _figures_section(record.figures, record.adoption)
    lines += ["## Files", ""] + [f"- `{f}`" for f in sorted(record.files)] + [""]
    return "\n".join(lines)


def _command(inputs: Sequence[str], outdir: str, options: RunSettings) -> str:
    """The command line that makes the run, with the output folder as given and every
    option that shapes the results (those at their defaults written out too), each
    argument quoted as a shell needs it."""
    cmd = ["armfit run", *map(shlex.quote, inputs), f"-o {shlex.quote(outdir)}"]
    if options.manifest:
        cmd.append(f"--manifest {shlex.quote(str(options.manifest))}")
    if options.column_map:
        cmd.append(f"--map {shlex.quote(str(options.column_map))}")
    if options.force_limit_N != FORCE_LIMIT_N:
        cmd.append(f"--force-limit {options.force_limit_N:g}")
    if (options.fmin, options.fmax) != GRID_HZ:
        cmd.append(f"--fmin {options.fmin:g} --fmax {options.fmax:g}")
    if options.bands:
        cmd.append("--band " + ",".join(f"{a}={lo:g}:{hi:g}" for a, lo, hi in options.bands))
    if options.skip_bad:
        cmd.append("--skip-bad")
    cmd += [f"--method {options.method}", f"--cost {options.cost}",
            f"--wu-cost {options.wu_cost}"]
    if not getattr(options, "reference", True):
        cmd.append("--no-reference")
    if not options.figures:
        cmd.append("--no-figures")
    if options.adopt != "auto":
        cmd.append(f"--adopt {options.adopt}")
    cmd += [f"--outside-loop {e}" for e in options.outside_loop]
    return " ".join(cmd)


def _heading(record: RunRecord) -> list[str]:
    """Title, version and the command of the run."""
    return ["# armfit report", "",
            f"armfit {__version__} — human arm dynamics and variability models by the "
            "method of Fu & Çavuşoğlu, ICRA 2010.", "",
            "```", _command(record.inputs, record.outdir, record.options), "```", ""]


def adoption_markdown(adoption: Adoption, wall: Wall | None) -> list[str]:
    """The report's opening section: the adopted model per axis, why, and what changed
    because of it.

    Parameters
    ----------
    adoption : Adoption
        The adopted model of each axis.
    wall : Wall or None
        The stability stage's results (for K_max of the base and adopted models).

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    ad = adoption
    L = ["## Adopted model", ""]
    if not ad.anything:
        why = ("adoption is off (`--adopt none`)" if ad.policy == "none"
               else "the diagnosis found nothing missing")
        L += [f"Nothing adopted: {why}. Every table, weight and stability answer below "
              "comes from the paper's 5-parameter model.", ""]
        declined = [a for a in ad.axes if a.declined]
        L += [f"- {a.sentence()}." for a in declined]
        return L + ([""] if declined else [])
    L += ["The diagnosis's model becomes the model of every product below (Tables I–III, "
          "per-trial fits, compare, K_max, certificate, figures); the paper's 5-parameter "
          "tables are kept as `*_base` files. Apparatus effects (stage output or device) "
          "are held at the diagnosis's joint fit over all trials of the axis; arm effects "
          "are fitted per row (`adoption.csv`).", ""]
    L += [f"- {a.sentence()}." for a in ad.axes]
    L.append("")
    if wall is not None and wall.base_nominal is not None:
        L += _adoption_walls(ad, wall)
    return L


def _adoption_walls(ad: Adoption, wall: Wall) -> list[str]:
    """K_max of the base and the adopted nominal models per adopted axis."""
    base, cert = wall.base_nominal, wall.certificate
    rows = []
    for axis in ad.adopted_axes:
        b = base[base["axis"] == axis]["k_max_N_per_m"]
        c = cert[cert["axis"] == axis]["k_max_N_per_m"]
        t = wall.summary.get(axis, {}).get("k_max_min_N_per_m", math.nan)
        loop = wall.in_loop.get(axis, ())
        rows.append([axis.upper(), _kn(b.iloc[0] if len(b) else math.nan),
                     _kn(c.iloc[0] if len(c) else math.nan), _kn(t),
                     ", ".join(loop) or "none"])
    return ["What changed because of it — the stiffest stable wall at the defaults "
            "(1 kHz, B = 0, d = 1):", ""] + md_table(
        ["axis", "K_max base nominal (kN/m)", "K_max adopted nominal (kN/m)",
         "K_max min over trials, adopted (kN/m)", "adopted effects in the loop"], rows)


def _what_was_done(record: RunRecord) -> list[str]:
    """The stages in words, each with the configuration it used and the files it wrote."""
    options, config, adoption = record.options, record.config, record.adoption
    skipped_text = ""
    if record.skipped:
        skipped_text = f"; {len(record.skipped)} skipped: " + "; ".join(
            f"`{f}` ({r})" for f, r in record.skipped)
    adopted = adoption.adopted_axes
    adopt_text = ("; ".join(f"`{' + '.join(adoption[a].effects)}` on {a}" for a in adopted)
                  if adopted else "nothing adopted")
    base = "_base" if adopted else ""
    steps = [
        f"**ingest** — {record.n_trials} trial(s) validated against the trial contract "
        f"into `trials.parquet`{skipped_text}.",
        f"**estimate** — measured dynamics X/F with the `{config.method}` estimator, "
        f"derived arm dynamics Xa/Fa (tfestimate, {config.derived_segments} segments), on "
        f"{config.per_decade} points per decade {config.fmin:g}–{config.fmax:g} Hz; mean "
        "per axis × grip and median per axis → `spectra.parquet`.",
        f"**fit-grip** — eq. 4 (the paper's 5-parameter model) fitted to each axis × grip "
        f"mean (Table I), cost `{options.cost}`, bands {_bands_text(PAPER_BANDS)}"
        f" → `grip_params{base}.csv/.tex`.",
        f"**fit-nominal** — the same fitted to each axis median (Table II) → "
        f"`nominal_params{base}.csv/.tex`.",
        "**diagnose** — stepwise search over the whole grid, started from the grip fits: "
        "the base model and the effects added one at a time, fitted to every trial, "
        "until the model is within the noise → `diagnosis.json`.",
        f"**adopt** — the model the diagnosis found becomes the model of the products "
        f"below: {adopt_text} → `adoption.csv`"
        + (f"; Tables I and II refitted with it, bands {_bands_text(record.bands)} → "
           "`grip_params.csv/.tex`, `nominal_params.csv/.tex`." if adopted else "."),
        f"**fit-uncertainty** — W_max (eq. 6) of every trial's derived arm dynamics "
        f"against the nominal H_ARM{' (apparatus effects removed)' if adopted else ''}, "
        f"Wu (eq. 7) fitted with cost `{options.wu_cost}` → `wu.csv`, "
        "`wu_summary.csv`, `wu_wmax.csv`, `wu.tex`.",
        "**fit-trials** — the same model fitted to every trial → `trial_params.csv`.",
        "**stability** — K_max of every trial's model and the robust certificate of the "
        "nominal models → `stability.csv`, `certificate.csv`.",
        "**compare** — each nominal model against the axis medians, overall and per band "
        "→ `compare.csv`.",
        ("**figures** — " + ", ".join(f"`{f}`" for f in record.figures) + ".")
        if record.figures else "**figures** — skipped (`--no-figures`).",
    ]
    return ["## What was done", ""] + [f"{i}. {s}" for i, s in enumerate(steps, 1)] + [""]


def _parameter_tables(record: RunRecord, adopted: bool) -> list[str]:
    """Tables I and II of the model every product uses, and the base model's when an
    effect is adopted."""
    which = "adopted model" if adopted else "the paper's 5-parameter model"
    L = [f"## Grip-dependent parameters (Table I, {which})", "",
         "Fits to the mean over subjects per axis and grip; 95 % intervals are in "
         "`grip_params.csv` and `grip_params.tex`.", ""]
    L += params_markdown(record.grip.table)
    L += [f"## Nominal parameters (Table II, {which})", "",
          "Fits to the median over all trials of an axis.", ""]
    L += params_markdown(record.nominal.table)
    if adopted:
        L += ["## The paper's 5-parameter model (base model, not adopted)", "",
              "Kept for comparison with the paper: the same fits without the adopted "
              "effects (`grip_params_base.csv`, `nominal_params_base.csv`). On the "
              "adopted axes the diagnosis found this model inadequate: its parameters "
              "partly imitate the missing effects.", "", "Table I, base model:", ""]
        L += params_markdown(record.base_grip.table)
        L += ["Table II, base model:", ""]
        L += params_markdown(record.base_nominal.table)
    return L


def _uncertainty_table(uncertainty: api.Uncertainty) -> list[str]:
    """Table III: the fitted Wu of each axis with its coverage and tightness."""
    summary, weights = uncertainty.summary(), uncertainty.weights
    L = ["## Uncertainty weights (Table III)", "",
         "Wu(s) = K Π(s − z)/Π(s − p), s in rad/s; coverage is the share of grid points "
         "where |Wu| ≥ W_max, tightness 20 log10|Wu| − 20 log10 W_max.", ""]
    fitted = summary[(summary["weight"] == "fitted") & (summary["target"] == "wmax")]
    rows = []
    for _, r in fitted.iterrows():
        w = weights[r["axis"]]
        rows.append([r["axis"], _num(r["n_trials"], "g"), _num(r["order"], "g"),
                     f"{w.gain:.4g}", _pairs_text(w.zeros), _pairs_text(w.poles),
                     f"{_num(r['band_lo_hz'], 'g')}–{_num(r['band_hi_hz'], 'g')}",
                     _num(r["coverage_pct"], ".1f"), _num(r["tightness_median_db"], ".2f"),
                     _num(r["tightness_max_db"], ".2f")])
    return L + md_table(["axis", "trials", "pairs", "K", "zeros (rad/s)", "poles (rad/s)",
                         "band (Hz)", "coverage %", "tightness median dB",
                         "tightness max dB"], rows)


def _diagnosis_section(diagnosis: api.Diagnosis) -> list[str]:
    """The diagnosis of every axis in words."""
    L = ["## Diagnosis", "",
         "Per axis: the base model fitted to every trial (arm parameters per trial), then "
         "effects added one at a time (parameters shared by the trials) while the model "
         "is not within the noise; an effect is named when its ΔBIC is significant and it "
         "changes the response by more than the noise (see `diagnosis.json`).", ""]
    for d in diagnosis.axes:
        L += _axis_diagnosis(d)
    return L


def _axis_diagnosis(d: AxisDiagnosis) -> list[str]:
    """One axis: verdict, base error, failing bands, the stepwise search, adequacy, ties,
    the first step's candidates and those left out because their code failed."""
    e = d.base_error
    L = [f"### Axis {d.axis.upper()}", "",
         f"**Verdict:** {d.verdict}.", "",
         f"{d.n_trials} trials, {_num(d.band[0], 'g')}–{_num(d.band[1], 'g')} Hz; base "
         f"model error {_num(e.rms_db, '.2f')} dB / {_num(e.rms_deg, '.1f')} deg / "
         f"{_num(e.rms_norm, '.2f')} × noise (RMS).", ""]
    if d.failing:
        L += ["Where the base model fails:", ""]
        L += [f"- {_num(fb.lo_hz, '.3g')}–{_num(fb.hi_hz, '.3g')} Hz: {fb.description}"
              for fb in d.failing] + [""]
    else:
        L += ["The base model fails in no band (it fits within the noise).", ""]
    if len(d.steps) > 1:
        L += ["Stepwise search (one effect added per step, all added effects refitted "
              "jointly); the error falls step by step:", ""]
        L += md_table(["step", "effect added", "parameters", "RMS dB", "RMS deg",
                       "× noise", "ΔBIC"], [_step_row(i, st) for i, st in enumerate(d.steps)])
    L += [f"Adequate (within the noise in every band): {'yes' if d.adequate else 'no'}.",
          ""]
    L += _subject_lines(d)
    if d.tied_with:
        L += ["About as good as the first effect: "
              + ", ".join(f"`{t}`" for t in d.tied_with) + ".", ""]
    # candidates of the first step; those the screening left out have no errors
    if d.candidates:
        L += ["Candidates of the first step. Each is fitted first on a few trials spread "
              "over the axis (screening); the best of them are then fitted on every trial. "
              "A candidate the screening left out has no error after it or ΔBIC on all "
              "trials (–): \"screened out\".", ""]
        L += md_table(["candidate", "parameters", "RMS dB", "RMS deg", "ΔBIC",
                       "significant"], [_candidate_row(c) for c in d.candidates])
    if d.failed_candidates:
        L += ["Candidates left out (their own code failed):", ""]
        L += [f"- `{c.effect}`: {c.reason}" for c in d.failed_candidates] + [""]
    return L


def _subject_lines(d: AxisDiagnosis) -> list[str]:
    """The effects tested per subject: the values of those that differ between subjects,
    and a line for those one shared value suffices."""
    L: list[str] = []
    for m in d.missing_effects:
        for p in m.varying:
            L += [f"`{m.effect}` differs between subjects: one value of {p} per subject "
                  f"(95 % interval; spread {m.spread[p]['min']:.4g}–{m.spread[p]['max']:.4g},"
                  f" sd {m.spread[p]['sd']:.3g}; the tables hold the subjects' mean, each "
                  "subject's per-trial fits its own):", ""]
            L += md_table(["subject", p, "95 % interval"], [
                [subj, f"{v[p]:.4g}",
                 f"{m.by_subject_lo[subj][p]:.4g} … {m.by_subject_hi[subj][p]:.4g}"]
                for subj, v in m.by_subject.items()])
    shared = [t for t in d.subject_tests if not t.by_subject and t.trials]
    if shared:
        L += ["Tested for one value per subject, one shared value suffices: " + "; ".join(
            f"`{t.effect}` ({t.n_subjects} subjects; "
            + ", ".join(f"{x.param} ΔBIC {x.delta_bic:.1f}" for x in t.trials) + ")"
            for t in shared) + ".", ""]
    return L


def _step_row(i: int, st: Step) -> list[str]:
    """A row of the stepwise search's table."""
    delta = finite_or_none(st.delta_bic)
    return [str(i), st.effect or "base model",
            ", ".join(f"{k}={v:.4g}" + (" (mean of the subjects')" if k in st.varying else "")
                      + (" (at bound)" if k in st.at_bound else "")
                      for k, v in st.params.items()),
            f"{st.rms_db:.2f}", f"{st.rms_deg:.1f}", f"{st.rms_norm:.2f}",
            "" if delta is None else f"{delta:.1f}"]


def _candidate_row(c: Candidate) -> list[str]:
    """A row of the first step's candidates."""
    return [c.effect, ", ".join(f"{k}={v:.4g}" for k, v in c.params.items()),
            f"{c.rms_db_before:.2f} → {_num(c.rms_db_after, '.2f')}",
            f"{c.rms_deg_before:.1f} → {_num(c.rms_deg_after, '.1f')}",
            _num(c.score, ".1f"),
            "yes" if c.significant else
            "no (screened out)" if not math.isfinite(c.rms_db_after) else "no"]


def _compare_section(comparisons: api.Comparisons) -> list[str]:
    """The nominal models against the medians, overall and per band (the rows of
    compare.csv: axes in order, each axis's models in the order first compared)."""
    L = ["### Nominal models against the medians (compare.csv)", "",
         "RMS magnitude error (dB) / phase error (deg) / normalised error (× noise); "
         "overall over each model's fit band (the rms × noise of Table II), and per band "
         "over the whole grid.", ""]
    models = {m: i for i, m in enumerate(dict.fromkeys(r.model for r in comparisons.rows))}
    ordered = sorted(comparisons.rows, key=lambda r: (r.axis, models[r.model]))
    cells: dict[tuple[str, str], dict[str, str]] = {}
    for r in ordered:
        group = cells.setdefault((r.axis, r.model), {})
        for label, b in (("overall", r.overall),
                         *((f"{b.lo_hz:g}-{b.hi_hz:g}", b) for b in r.bands)):
            group[label] = (f"{_num(b.rms_db, '.2f')} / {_num(b.rms_deg, '.1f')} / "
                            f"{_num(b.rms_norm, '.2f')}")
    bands = [f"{lo:g}-{hi:g}" for lo, hi in BANDS]
    header = ["axis", "model", "overall"] + [f"{b} Hz" for b in bands]
    rows = [[axis, model, c.get("overall", "–")] + [c.get(b, "–") for b in bands]
            for (axis, model), c in cells.items()]
    return L + md_table(header, rows)


def stability_markdown(wall: Wall) -> list[str]:
    """The report's section on the stiffest stable virtual wall (stability.csv).

    Parameters
    ----------
    wall : Wall
        The stability stage's results.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    st = wall.settings
    rate = 1.0 / st.sample_time_s
    L = ["## Stiffest stable virtual wall (stability.csv)", "",
         f"One fit per trial (`trial_params.csv`, {wall.n_models} fitted), then K_max: "
         f"the largest wall stiffness K for which the sampled loop F[k] = −(K x[k−d] + "
         f"B (x[k−d] − x[k−d−1])/T) with each arm is stable for every K′ ≤ K (exact "
         f"zero-order-hold discretisation; see `armfit stability`). Defaults: "
         f"{rate:g} Hz servo, B = {st.damping_Ns_per_m:g} N·s/m, d = {st.delay_samples} "
         "sample(s).", ""]
    for axis, s in wall.summary.items():
        L.append(f"- A {rate / 1e3:g} kHz device with {st.delay_samples} sample(s) of delay "
                 f"renders walls up to {s['k_max_min_N_per_m'] / 1e3:.3g} kN/m on "
                 f"{axis.upper()} for every subject and grip ({s['n_models']} trials; "
                 f"limited by {s['limiting']}); median {s['k_max_median_N_per_m'] / 1e3:.3g}"
                 f" kN/m, 5th percentile {s['k_max_p05_N_per_m'] / 1e3:.3g} kN/m.")
    L.append("")
    if wall.by_subject:
        L += _subject_walls(wall)
    for who, why in wall.failed:
        L.append(f"- Trial {who} has no fit ({why}) and is not in the population.")
    for text in wall.warnings:
        L.append(f"- Warning: {text}.")
    if any(wall.in_loop.values()) or wall.outside_loop:
        L += ([""] if L[-1] else []) + [_loop_effects_text(wall)]
    if "k_robust_N_per_m" in wall.certificate.columns:
        L += ([""] if L[-1] else []) + _certificate_lines(wall.certificate)
    return L + [""]


def _subject_walls(wall: Wall) -> list[str]:
    """K_max per subject (the smallest over the subject's trials), for the axes whose
    adopted model has effect values per subject."""
    axes = list(wall.by_subject)
    subjects = list(dict.fromkeys(s for a in axes for s in wall.by_subject[a]))
    rows = [[s] + [_kn(wall.by_subject[a].get(s, math.nan)) for a in axes] for s in subjects]
    return ["Each subject's per-trial fits hold the subject's own effect values, so the "
            "wall follows subject by subject; the wall every subject renders stably is "
            "the smallest (kN/m, the minimum over the subject's grips):", ""] + md_table(
        ["subject"] + [f"K_max {a.upper()} (kN/m)" for a in axes], rows) + [""]


def _loop_effects_text(wall: Wall) -> str:
    """The adopted effects inside the stability loop, per axis, in one sentence."""
    return "Effects in the loop: " + "; ".join(
        f"{a.upper()} {', '.join(e) or 'none'}" for a, e in wall.in_loop.items()) + (
        " (left out with --outside-loop: " + ", ".join(wall.outside_loop) + ")"
        if wall.outside_loop else
        " (a latency or lag in the position path is in the loop, since the wall "
        "reads the same sensor; `--outside-loop EFFECT` leaves one out)") + "."


def _certificate_lines(cert: pd.DataFrame) -> list[str]:
    """The robust certificate of each nominal model, in words (certificate.csv)."""
    L = ["Robust certificate of the nominal models against the fitted Wu "
         "(max |Wu T| < 1, T the complementary sensitivity seen by the arm's "
         "multiplicative uncertainty; `certificate.csv`), evaluated from the band's "
         "low edge up to the Nyquist frequency, Wu continued beyond its band, and "
         "capped at the smallest K_max of the trials it covers:", ""]
    for _, r in cert.iterrows():
        status = certificate_status(r)
        if status == "withheld":
            L.append(f"- {r['axis'].upper()}: withheld: above the weight's band the trials' "
                     f"models depart from the nominal by up to {r['beyond_margin']:.4f} × "
                     "|Wu|, so the weight does not cover them there and the assumption the "
                     "certificate rests on does not hold (what the weight alone would "
                     f"certify: {r['k_weight_N_per_m'] / 1e3:.3g} kN/m).")
            continue
        if status == "no weight":
            L.append(f"- {r['axis'].upper()}: no weight for this axis; no certificate.")
            continue
        if status == "unstable at K = 0":
            L.append(f"- {r['axis'].upper()}: holds for no K at all (the nominal loop is "
                     "unstable already at K = 0).")
            continue
        if not math.isfinite(r["k_robust_N_per_m"]):
            L.append(f"- {r['axis'].upper()}: holds for no K at all (max |Wu T| is "
                     f"{r['wu_t_peak_k0']:.2f} > 1 already at K = 0, at "
                     f"{r['f_peak_k0_hz']:.3g} Hz).")
            continue
        why = {"member": f"capped at trial {r['limiting_member']} (its K_max)",
               "weight beyond band": f"bound at {r['f_binding_hz']:.3g} Hz, above "
                                     "the weight's band",
               "weight": f"bound at {r['f_binding_hz']:.3g} Hz",
               "nominal K_max": "the nominal's own K_max"}.get(r["limited_by"], "")
        margin = r.get("beyond_margin", math.nan)
        check = ""
        if isinstance(margin, float) and math.isfinite(margin):   # <= 1: else withheld
            check = f"; above the band the trials stay within {margin:.4f} × |Wu|"
        L.append(f"- {r['axis'].upper()}: holds for K up to "
                 f"{r['k_robust_N_per_m'] / 1e3:.3g} kN/m ({why}; peak at K = 0: "
                 f"{r['wu_t_peak_k0']:.2f}{check}).")
    return L


def _figures_section(figures: Sequence[str], adoption: Adoption) -> list[str]:
    """Each figure with its caption."""
    L = ["## Figures", ""]
    for f in figures:
        cap = FIGURE_CAPTIONS.get(f)
        if cap is None:
            axis = f.rsplit("_", 1)[1].split(".")[0]
            eff = " + ".join(adoption[axis].effects)
            cap = (f"Normalised residual of the nominal model, axis {axis.upper()}"
                   + (f", adopted model with `{eff}` dashed" if eff else "")
                   + "; shaded where the solid curve leaves the noise band (±2 SE)")
        L += [f"### {cap}", "", f"![{cap}]({f})", ""]
    return L
