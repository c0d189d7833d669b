"""The one-shot pipeline of ``armfit run``: raw trials in, every table, figure and a report out.

Stages, each the library call of its own subcommand, in the order data flows (files
written into OUTDIR in brackets):

- ingest: :func:`armfit.io.trials.ingest` (trials.parquet);
- estimate: :func:`armfit.spectra.estimate_study` (spectra.parquet);
- fit-grip, fit-nominal: :func:`armfit.fitting.fit_study` and
  :func:`armfit.tables.latex_table` (grip_params.csv/.tex, nominal_params.csv/.tex);
- fit-uncertainty: :func:`armfit.uncertainty.fit_uncertainty` (wu.csv, wu_summary.csv,
  wu_wmax.csv, wu.tex);
- figures: Figs. 5–7 of :mod:`armfit.figures` (figures/bode.png, uncertainty.png,
  literature.png);
- diagnose: :func:`armfit.diagnose.diagnose` started from the grip fits (diagnosis.json);
- refit, when the diagnosis names an effect: :func:`armfit.fitting.fit_study` with that
  effect (nominal_params_<effect>.csv);
- compare: :func:`armfit.diagnose.compare` of each nominal model with the medians
  (compare.csv);
- residuals: :func:`armfit.figures.residual_figure` per axis (figures/residual_<axis>.png);
- fit-trials: :func:`armfit.fitting.fit_trials`, one fit per trial (trial_params.csv);
- stability: :func:`armfit.stability.stability_table` of the per-trial fits at the
  defaults (stability.csv), the certificate of the nominal models against Wu, and
  :func:`armfit.figures.stability_figure` (figures/stability.png);
- report: :func:`report_markdown` (report.md).

Every later stage reads the files the earlier ones wrote (as the subcommands do), so
``armfit run`` gives the same numbers as the subcommands run one after the other with
the same options. The whole folder is built in a temporary folder beside OUTDIR and
renamed onto it at the end (:func:`armfit.io.atomic.atomic_path`): a failure leaves no
OUTDIR, and an existing OUTDIR is replaced only with ``overwrite``.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

from armfit import __version__
from armfit.errors import ArmfitError, OutputError

#: Figures written (``figures`` on), relative to OUTDIR; residual_<axis>.png per axis.
FIGURES = ("figures/bode.png", "figures/uncertainty.png", "figures/literature.png")

#: Stage names, in the order they are reported (``refit`` only when an effect is named,
#: ``figures`` and ``residuals`` only with figures on). With jobs > 1 the diagnosis runs
#: in worker processes from the end of fit-grip on, alongside the stages before it.
STAGES = ("ingest", "estimate", "fit-grip", "fit-nominal", "fit-uncertainty", "figures",
          "diagnose", "refit", "compare", "residuals", "fit-trials", "stability", "report")

#: Columns of compare.csv.
COMPARE_COLUMNS = ("axis", "grip", "level", "model", "band", "rms_db", "rms_deg", "rms_norm")


@dataclass(frozen=True)
class RunOptions:
    """Options of :func:`run_pipeline`.

    manifest: trial manifest CSV (None: file names carry the identity); skip_bad: go on
    past bad trials; method: estimator of the measured dynamics ("h1" or "chebwin");
    cost: arm-fit cost ("complex" or "paper", eq. 5); wu_cost: Wu fit ("envelope" or
    "paper", eq. 7); jobs: worker processes (estimate, diagnose); figures: draw the
    figures; overwrite: replace an existing OUTDIR.
    """

    manifest: str | None = None
    skip_bad: bool = False
    method: str = "h1"
    cost: str = "complex"
    wu_cost: str = "envelope"
    jobs: int = 1
    figures: bool = True
    overwrite: bool = False


@dataclass(frozen=True)
class Stage:
    """One finished stage: its name, wall time (s) and a one-line summary."""

    name: str
    seconds: float
    summary: str


@dataclass(frozen=True)
class RunResult:
    """What :func:`run_pipeline` wrote.

    outdir: the folder; files: paths relative to it, sorted; trials: trials estimated;
    skipped: (file, reason) of trials left out with ``skip_bad``; verdicts: {axis:
    verdict sentence}; missing: {axis: effect name or None}; refitted: {effect: axes};
    stages: the stages run, in order, with their times (s; the diagnosis's time overlaps
    the stages before it when it ran in worker processes); wall_s: the whole run (s).
    """

    outdir: str
    files: tuple[str, ...]
    trials: int
    skipped: tuple[tuple[str, str], ...]
    verdicts: Mapping[str, str]
    missing: Mapping[str, str | None]
    refitted: Mapping[str, tuple[str, ...]]
    stages: tuple[Stage, ...] = field(default_factory=tuple)
    wall_s: float = 0.0


OnStage = Callable[[Stage], object]
Warn = Callable[[str], object]


# ---------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------

def check_outdir(outdir: str | os.PathLike, inputs: Sequence[str | os.PathLike], *,
                 manifest: str | os.PathLike | None = None, overwrite: bool = False) -> Path:
    """Refuse an OUTDIR that exists without ``overwrite``, is a file, or is or holds an
    input (replacing it would delete the input). Raises OutputError (exit 73)."""
    from armfit.io.atomic import check_output
    out = Path(outdir)
    named = [*inputs, *([manifest] if manifest is not None else [])]
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder; give a folder for OUTDIR")
    out_res = out.resolve()
    for inp in named:
        inp_res = Path(inp).resolve()
        if inp_res == out_res or out_res in inp_res.parents:
            raise OutputError(f"{out}: holds the input {inp}; choose another OUTDIR")
    check_output(out, overwrite=overwrite, inputs=inputs, manifest=manifest, folder=True)
    return out


def run_pipeline(inputs: Sequence[str | os.PathLike], outdir: str | os.PathLike,
                 options: RunOptions = RunOptions(), *, on_stage: OnStage | None = None,
                 warn: Warn | None = None) -> RunResult:
    """Run every stage on ``inputs`` (raw trial files, folders or a canonical dataset)
    and write the results into ``outdir``, atomically.

    ``on_stage(stage)`` is called after each stage (e.g. to print its time); ``warn``
    receives data warnings (saturation). Raises OutputError (exit 73) before any work
    if ``outdir`` cannot be written, and the error of the first failing stage otherwise
    (BadInputError 65, NoInputError 66, ConvergenceError 3, ...), leaving no new OUTDIR
    and an existing one untouched; a message naming a file of the temporary folder names
    it as it would have been in ``outdir``.
    """
    from armfit.io.atomic import atomic_path
    out = check_outdir(outdir, inputs, manifest=options.manifest, overwrite=options.overwrite)
    tmp: Path | None = None
    try:
        with atomic_path(out, overwrite=options.overwrite, folder=True) as tmp:
            result = _run_in(list(inputs), tmp, options, on_stage=on_stage, warn=warn)
    except ArmfitError as exc:
        # a message about a file of the temporary folder names it as it would be in OUTDIR
        text = str(exc)
        if tmp is None or str(tmp) not in text:
            raise
        raise type(exc)(text.replace(str(tmp), str(out))) from exc
    return replace(result, outdir=str(out))


# ---------------------------------------------------------------------------
# The stages, writing into a given (empty) folder
# ---------------------------------------------------------------------------

class _Clock:
    """Times stages and reports each one as it finishes: a stage lasts from the end of
    the previous one, unless it is given its own start (a stage that ran alongside)."""

    def __init__(self, on_stage: OnStage | None):
        self.stages: list[Stage] = []
        self.on_stage = on_stage
        self.start = self.t0 = time.perf_counter()

    def done(self, name: str, summary: str, *, since: float | None = None) -> None:
        now = time.perf_counter()
        stage = Stage(name, now - (self.t0 if since is None else since), summary)
        self.stages.append(stage)
        self.t0 = now
        if self.on_stage is not None:
            self.on_stage(stage)

    def wall(self) -> float:
        return time.perf_counter() - self.start


class _Diagnosis:
    """:func:`armfit.diagnose.diagnose` of every axis, started now (in a background thread
    that drives ``jobs`` worker processes, one task per axis and candidate effect) and
    collected by :meth:`results`, so the stages that do not need the diagnosis run
    meanwhile in this process; with ``jobs`` 1 the diagnosis runs when collected. The
    results are those of one ``diagnose(spectra, params)`` call, in x, y, z order."""

    def __init__(self, spectra, params, jobs: int):
        from concurrent.futures import ThreadPoolExecutor

        from armfit.diagnose import diagnose
        self.spectra, self.params = spectra, params
        self.axes = [a for a in ("x", "y", "z") if (params["axis"] == a).any()]
        self.thread = None
        self.started = time.perf_counter()
        if jobs > 1:
            self.thread = ThreadPoolExecutor(max_workers=1)
            self.task = self.thread.submit(diagnose, spectra, params, axes=self.axes,
                                           jobs=jobs)

    def results(self) -> list:
        from armfit.diagnose import diagnose
        if self.thread is None:
            self.started = time.perf_counter()
            return diagnose(self.spectra, self.params, axes=self.axes)
        try:
            return self.task.result()
        finally:
            self.close()

    def close(self) -> None:
        """Wait for the diagnosis thread (its worker processes end with it)."""
        if self.thread is not None:
            self.thread.shutdown(wait=True, cancel_futures=True)
            self.thread = None


def _run_in(inputs: list, folder: Path, options: RunOptions, *,
            on_stage: OnStage | None, warn: Warn | None) -> RunResult:
    import contextlib
    with contextlib.ExitStack() as stack:
        return _stages(inputs, folder, options, on_stage=on_stage, warn=warn, stack=stack)


def _stages(inputs: list, folder: Path, options: RunOptions, *, on_stage: OnStage | None,
            warn: Warn | None, stack) -> RunResult:
    from armfit.diagnose import compare, diagnosis_to_dict
    from armfit.fitting import fit_study
    from armfit.io.artifacts import (
        read_params,
        read_spectra,
        write_params,
        write_spectra,
        write_wu,
        write_wu_table,
        wu_latex,
        wu_sidecar_paths,
    )
    from armfit.io.atomic import write_text_atomic
    from armfit.io.trials import ingest
    from armfit.models.effects import get_effect
    from armfit.spectra import EstimateConfig, estimate_study, spectra_metadata
    from armfit.tables import caption_for, latex_table
    from armfit.uncertainty import fit_uncertainty, points_table, summary_table

    clock = _Clock(on_stage)
    files: list[str] = []

    def path(name: str) -> Path:
        files.append(name)
        return folder / name

    # ingest: validate the raw trials once, into the canonical dataset
    ing = ingest(inputs, path("trials.parquet"), manifest=options.manifest,
                 skip_bad=options.skip_bad, warn=warn)
    skipped = tuple((s.file, s.reason) for s in ing.skipped)
    clock.done("ingest", f"{len(ing.trials)} trial(s)"
               + (f", {len(skipped)} skipped" if skipped else ""))

    # estimate: from the same inputs, so that any message names the user's files
    config = EstimateConfig(method=options.method)
    est = estimate_study(inputs, config, manifest=options.manifest,
                         skip_bad=options.skip_bad, jobs=options.jobs)
    seen = {f for f, _ in skipped}
    skipped += tuple((f, r) for f, r in est.skipped if f not in seen)
    write_spectra(est.table, path("spectra.parquet"), meta=spectra_metadata(config, est))
    spectra = read_spectra(folder / "spectra.parquet")
    clock.done("estimate", f"{len(est.trials)} trial(s), method {config.method}, "
               f"{len(config.grid())} frequencies {config.fmin:g}-{config.fmax:g} Hz")

    # fit-grip and fit-nominal: Tables I and II; the diagnosis starts from the grip fits
    params: dict[str, object] = {}
    diag = None
    for which in ("grip", "nominal"):
        study = fit_study(spectra, which=which, cost=options.cost, source="spectra.parquet")
        df = study.table()
        _warn_at_bound(which, study, warn)
        write_params(df, path(f"{which}_params.csv"))
        write_text_atomic(path(f"{which}_params.tex"), latex_table(
            df, ci=True, caption=caption_for(which, [f.ci_method for f in study.fits]),
            label=f"tab:{which}"))
        params[which] = read_params(folder / f"{which}_params.csv")
        clock.done(f"fit-{which}", f"{len(df)} fit(s), cost {options.cost}, median rms "
                   f"{_median(df['rms_db']):.2f} dB")
        if which == "grip":
            diag = _Diagnosis(spectra, params["grip"], options.jobs)
            stack.callback(diag.close)
    grip, nominal = params["grip"], params["nominal"]

    # fit-uncertainty: W_max and Wu (Table III)
    wu_path = path("wu.csv")
    summary_path, points_path = wu_sidecar_paths(wu_path)
    files += [summary_path.name, points_path.name]
    unc = fit_uncertainty(spectra, nominal, cost=options.wu_cost)
    weights = {r.axis: r.result.weight for r in unc}
    summary = summary_table(unc)
    write_wu(weights, wu_path)
    write_wu_table(summary, summary_path)
    write_wu_table(points_table(unc), points_path)
    write_text_atomic(path("wu.tex"), wu_latex(weights))
    clock.done("fit-uncertainty", ", ".join(f"{r.axis}: {r.result.order} pair(s)"
                                            for r in unc) + f", cost {options.wu_cost}")

    # figures of the paper (Figs. 5-7): they need no diagnosis
    drawn: list[str] = []
    if options.figures:
        (folder / "figures").mkdir()
        drawn += _paper_figures(folder, spectra, grip, nominal, weights)
        clock.done("figures", f"{len(drawn)} figure(s): Figs. 5, 6, 7")

    # diagnose: per-trial fits started from the grip fits
    results = diag.results()
    doc = diagnosis_to_dict(results)
    write_text_atomic(path("diagnosis.json"), json.dumps(doc, indent=2) + "\n")
    # every effect the stepwise search named on an axis, in order ("delay+lowpass")
    missing = {a: "+".join(m["effect"] for m in d.get("missing_effects", []))
               or d["missing_effect"] for a, d in doc["axes"].items()}
    clock.done("diagnose", "; ".join(f"{a}: {e or 'no missing effect'}"
                                     for a, e in missing.items()), since=diag.started)

    # refit: the nominal fit again with each named effect, on the axes that name it and
    # over the band the diagnosis looked at (the paper's z band stops at 10 Hz because
    # of an effect the base model lacks; with the effect in the model it need not)
    refitted: dict[str, tuple[str, ...]] = {}
    for axis, eff in missing.items():
        if eff is not None:
            refitted[eff] = (*refitted.get(eff, ()), axis)
    extended: dict[str, object] = {}
    for eff, axes in refitted.items():
        sub = spectra[spectra["axis"].isin(axes)]
        bands = {a: tuple(doc["axes"][a]["band_hz"]) for a in axes}
        study = fit_study(sub, which="nominal", cost=options.cost,
                          effects=[get_effect(e) for e in eff.split("+")],
                          bands=bands, source="spectra.parquet")
        name = f"nominal_params_{eff}.csv"
        write_params(study.table(), path(name))
        extended[eff] = read_params(folder / name)
    if refitted:
        clock.done("refit", "; ".join(f"{e} on {', '.join(a)}" for e, a in refitted.items()))

    # compare: each nominal model (base, base + effect) against the axis medians
    rows = compare(spectra, nominal, level="median")
    for table in extended.values():
        rows += compare(spectra, table, level="median")
    comp = compare_frame(rows)
    with open(path("compare.csv"), "w", encoding="utf-8", newline="") as fh:
        comp.to_csv(fh, index=False, float_format="%.10g", lineterminator="\n")
    clock.done("compare", f"{len(rows)} model(s) x axis against the medians")

    # residual figures: need the diagnosis (failing bands) and the refits
    if options.figures:
        res = _residual_figures(folder, spectra, nominal, extended, refitted, doc)
        drawn += res
        clock.done("residuals", f"{len(res)} figure(s)")

    # fit-trials and stability: the per-trial population and the stiffest stable wall
    wall = _stability_stages(folder, spectra, nominal, weights, summary, options, path,
                             clock)
    if wall["figure"]:
        drawn.append(wall["figure"])
    files += drawn

    # report
    files.append("report.md")
    text = report_markdown(
        inputs=[str(p) for p in inputs], options=options, n_trials=len(est.trials),
        skipped=skipped, grip=grip, nominal=nominal, wu_summary=summary, weights=weights,
        diagnosis=doc, refitted=refitted, extended=extended, compare_rows=comp,
        figures=drawn, files=sorted(files), stability=wall)
    write_text_atomic(folder / "report.md", text)
    clock.done("report", "report.md")

    return RunResult(outdir=str(folder), files=tuple(sorted(files)),
                     trials=len(est.trials), skipped=skipped,
                     verdicts={a: d["verdict"] for a, d in doc["axes"].items()},
                     missing=missing, refitted=refitted, stages=tuple(clock.stages),
                     wall_s=clock.wall())


def _median(values) -> float:
    import numpy as np
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")


def compare_frame(rows):
    """compare.csv as a DataFrame (:data:`COMPARE_COLUMNS`) from
    :class:`armfit.diagnose.Comparison` rows: one row per comparison and band, band
    ``overall`` (the whole band compared) or ``LO-HI`` (Hz)."""
    import pandas as pd
    out = []
    for r in rows:
        for label, b in (("overall", r.overall),
                         *((f"{b.lo_hz:g}-{b.hi_hz:g}", b) for b in r.bands)):
            out.append({"axis": r.axis, "grip": r.grip_N, "level": r.level, "model": r.model,
                        "band": label, "rms_db": b.rms_db, "rms_deg": b.rms_deg,
                        "rms_norm": b.rms_norm})
    df = pd.DataFrame(out, columns=list(COMPARE_COLUMNS))
    order = {m: i for i, m in enumerate(dict.fromkeys(df["model"]))}
    df["_m"] = df["model"].map(order)
    df = df.sort_values(["axis", "_m"], kind="stable").drop(columns="_m")
    return df.reset_index(drop=True)


def _save(folder: Path, fig, name: str) -> str:
    import matplotlib.pyplot as plt

    from armfit.figures import save_figure
    save_figure(fig, folder / name)
    plt.close(fig)
    return name


def _paper_figures(folder: Path, spectra, grip, nominal, weights) -> list[str]:
    """Fig. 5 (bode: measured dynamics with the grip fits, all axes), Fig. 6 (derived
    dynamics, nominal H_ARM, W_max and |Wu|) and Fig. 7 (the X axis 1 N H_ARM, else the
    first grip fit, against Table IV). Returns the paths written, relative to ``folder``."""
    import numpy as np

    from armfit import figures as F
    rows = grip[(grip["axis"] == "x") & np.isclose(grip["grip_N"].to_numpy(float), 1.0)]
    return [_save(folder, F.bode_figure(spectra, grip), FIGURES[0]),
            _save(folder, F.uncertainty_figure(spectra, nominal, weights), FIGURES[1]),
            _save(folder, F.literature_figure((rows if len(rows) else grip).iloc[0]),
                  FIGURES[2])]


def _residual_figures(folder: Path, spectra, nominal, extended, refitted, doc) -> list[str]:
    """One residual figure per diagnosed axis: the nominal model solid, the nominal model
    with the axis's named effect dashed, the diagnosis's failing bands shaded."""
    from armfit import figures as F
    by_axis = {a: eff for eff, axes in refitted.items() for a in axes}
    out = []
    for axis in sorted(doc["axes"]):
        eff = by_axis.get(axis)
        bands = {axis: [(fb["lo_hz"], fb["hi_hz"]) for fb in doc["axes"][axis]
                        ["failing_bands"]]}
        fig = F.residual_figure(spectra, nominal, None if eff is None else extended[eff],
                                axis=axis, bands=bands)
        out.append(_save(folder, fig, f"figures/residual_{axis}.png"))
    return out


# ---------------------------------------------------------------------------
# report.md
# ---------------------------------------------------------------------------

def _md_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> list[str]:
    def cell(v) -> str:
        return str(v).replace("|", "\\|")
    lines = ["| " + " | ".join(header) + " |",
             "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in r) + " |" for r in rows]
    return lines + [""]


def _num(v, fmt: str = ".3g") -> str:
    if v is None:
        return "–"
    try:
        x = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "–" if not math.isfinite(x) else format(x, fmt)


def _params_rows(df) -> tuple[list[str], list[list[str]]]:
    from armfit.tables import param_names, sig4, unit_of
    names = param_names(df)
    grip = "grip_N" in df.columns
    header = ["axis"] + (["grip (N)"] if grip else []) + \
        [f"{n} ({unit_of(n).replace('*', '·')})" for n in names] + \
        ["rms dB", "rms deg", "rms × noise"]
    rows = []
    for _, r in df.iterrows():
        rows.append([str(r["axis"])] + ([f"{float(r['grip_N']):g}"] if grip else [])
                    + [sig4(float(r[n])) for n in names]
                    + [_num(r["rms_db"], ".2f"), _num(r["rms_deg"], ".1f"),
                       _num(r["rms_norm"], ".2f")])
    return header, rows


def _pairs_text(reps) -> str:
    return "; ".join(f"{r.real:.4g} ± {abs(r.imag):.4g}j" for r in reps) or "–"


def report_markdown(*, inputs: Sequence[str], options: RunOptions, n_trials: int,
                    skipped: Sequence[tuple[str, str]], grip, nominal, wu_summary, weights,
                    diagnosis: Mapping, refitted: Mapping[str, Sequence[str]],
                    extended: Mapping, compare_rows, figures: Sequence[str],
                    files: Sequence[str], stability: Mapping | None = None) -> str:
    """The text of report.md: what was done with which options, the tables, the
    diagnosis per axis in words, the figures. No timestamps or timings (re-running gives
    the same text)."""
    from armfit.diagnose import BANDS
    cmd = ["armfit run", *inputs, "-o OUTDIR"]
    if options.manifest:
        cmd.append(f"--manifest {options.manifest}")
    if options.skip_bad:
        cmd.append("--skip-bad")
    cmd += [f"--method {options.method}", f"--cost {options.cost}",
            f"--wu-cost {options.wu_cost}"]
    if not options.figures:
        cmd.append("--no-figures")
    L = ["# armfit report", "",
         f"armfit {__version__} — human arm dynamics and variability models by the method "
         "of Fu & Çavuşoğlu, ICRA 2010.", "",
         "```", " ".join(cmd), "```", "",
         "## What was done", ""]
    skipped_text = ""
    if skipped:
        skipped_text = f"; {len(skipped)} skipped: " + "; ".join(
            f"`{f}` ({r})" for f, r in skipped)
    refit_text = ("with " + "; ".join(f"`{e}` on axis {', '.join(a)}"
                                      for e, a in refitted.items())
                  if refitted else "not needed: no effect was named")
    steps = [
        f"**ingest** — {n_trials} trial(s) validated against the trial contract into "
        f"`trials.parquet`{skipped_text}.",
        f"**estimate** — measured dynamics X/F with the `{options.method}` estimator, "
        "derived arm dynamics Xa/Fa (tfestimate, 4 segments), on 40 points per decade "
        "0.1–30 Hz; mean per axis × grip and median per axis → `spectra.parquet`.",
        f"**fit-grip** — eq. 4 fitted to each axis × grip mean (Table I), cost "
        f"`{options.cost}`, bands x, y 0.1–30 Hz and z 0.1–10 Hz → `grip_params.csv/.tex`.",
        f"**fit-nominal** — eq. 4 fitted to each axis median (Table II), cost "
        f"`{options.cost}` → `nominal_params.csv/.tex`.",
        f"**fit-uncertainty** — W_max (eq. 6) of every trial's derived dynamics against "
        f"the nominal H_ARM, Wu (eq. 7) fitted with cost `{options.wu_cost}` → `wu.csv`, "
        "`wu_summary.csv`, `wu_wmax.csv`, `wu.tex`.",
        "**diagnose** — stepwise search over the whole grid, started from the grip fits: "
        "the base model and the effects added one at a time, fitted to every trial, "
        "until the model is within the noise → `diagnosis.json`.",
        f"**refit** — the nominal fit again with the named effect, over the band of the "
        f"diagnosis: {refit_text}.",
        "**compare** — each nominal model against the axis medians, overall and per band "
        "→ `compare.csv`.",
        ("**figures** — " + ", ".join(f"`{f}`" for f in figures) + ".") if figures
        else "**figures** — skipped (`--no-figures`).",
    ]
    L += [f"{i}. {s}" for i, s in enumerate(steps, 1)] + [""]

    L += ["## Grip-dependent parameters (Table I)", "",
          "Fits to the mean over subjects per axis and grip; 95 % intervals are in "
          "`grip_params.csv` and `grip_params.tex`.", ""]
    L += _md_table(*_params_rows(grip))
    L += ["## Nominal parameters (Table II)", "",
          "Fits to the median over all trials of an axis.", ""]
    L += _md_table(*_params_rows(nominal))
    for eff, table in extended.items():
        L += [f"With the effect `{eff}` (`nominal_params_{eff}.csv`):", ""]
        L += _md_table(*_params_rows(table))

    L += ["## Uncertainty weights (Table III)", "",
          "Wu(s) = K Π(s − z)/Π(s − p), s in rad/s; coverage is the share of grid points "
          "where |Wu| ≥ W_max, tightness 20 log10|Wu| − 20 log10 W_max.", ""]
    fitted = wu_summary[(wu_summary["weight"] == "fitted") & (wu_summary["target"] == "wmax")]
    rows = []
    for _, r in fitted.iterrows():
        w = weights[r["axis"]]
        rows.append([r["axis"], _num(r["n_trials"], "g"), _num(r["order"], "g"),
                     f"{w.gain:.4g}", _pairs_text(w.zeros), _pairs_text(w.poles),
                     f"{_num(r['band_lo_hz'], 'g')}–{_num(r['band_hi_hz'], 'g')}",
                     _num(r["coverage_pct"], ".1f"), _num(r["tightness_median_db"], ".2f"),
                     _num(r["tightness_max_db"], ".2f")])
    L += _md_table(["axis", "trials", "pairs", "K", "zeros (rad/s)", "poles (rad/s)",
                    "band (Hz)", "coverage %", "tightness median dB", "tightness max dB"],
                   rows)

    L += ["## Diagnosis", "",
          "Per axis: the base model fitted to every trial (arm parameters per trial), then "
          "effects added one at a time (parameters shared by the trials) while the model "
          "is not within the noise; an effect is named when its ΔBIC is significant and it "
          "changes the response by more than the noise (see `diagnosis.json`).", ""]
    for axis, d in diagnosis["axes"].items():
        L += [f"### Axis {axis.upper()}", "",
              f"**Verdict:** {d['verdict']}.", "",
              f"{d['n_trials']} trials, {_num(d['band_hz'][0], 'g')}–"
              f"{_num(d['band_hz'][1], 'g')} Hz; base model error "
              f"{_num(d['base_error']['rms_db'], '.2f')} dB / "
              f"{_num(d['base_error']['rms_deg'], '.1f')} deg / "
              f"{_num(d['base_error']['rms_norm'], '.2f')} × noise (RMS).", ""]
        if d["failing_bands"]:
            L += ["Where the base model fails:", ""]
            L += [f"- {_num(fb['lo_hz'], '.3g')}–{_num(fb['hi_hz'], '.3g')} Hz: "
                  f"{fb['description']}" for fb in d["failing_bands"]] + [""]
        else:
            L += ["The base model fails in no band (it fits within the noise).", ""]
        steps = d.get("steps", [])
        if len(steps) > 1:
            L += ["Stepwise search (one effect added per step, all added effects refitted "
                  "jointly); the error falls step by step:", ""]
            L += _md_table(["step", "effect added", "parameters", "RMS dB", "RMS deg",
                            "× noise", "ΔBIC"], [
                [str(i), st["effect"] or "base model",
                 ", ".join(f"{k}={v:.4g}" + (" (at bound)" if k in st["at_bound"] else "")
                           for k, v in st["params"].items()),
                 f"{st['rms_db']:.2f}", f"{st['rms_deg']:.1f}", f"{st['rms_norm']:.2f}",
                 "" if st["delta_bic"] is None else f"{st['delta_bic']:.1f}"]
                for i, st in enumerate(steps)])
        if "adequate" in d:
            L += [f"Adequate (within the noise in every band): "
                  f"{'yes' if d['adequate'] else 'no'}.", ""]
        if d["tied_with"]:
            L += ["About as good as the first effect: "
                  + ", ".join(f"`{t}`" for t in d["tied_with"]) + ".", ""]
        # candidates of the first step; those the screening left out have null errors
        cands = [[c["effect"], ", ".join(f"{k}={v:.4g}" for k, v in c["params"].items()),
                  f"{c['rms_db_before']:.2f} → {_num(c['rms_db_after'], '.2f')}",
                  f"{c['rms_deg_before']:.1f} → {_num(c['rms_deg_after'], '.1f')}",
                  _num(c["score"], ".1f"), "yes" if c["significant"] else "no"]
                 for c in d["candidates"]]
        if cands:
            L += _md_table(["candidate", "parameters", "RMS dB", "RMS deg", "ΔBIC",
                            "significant"], cands)

    L += ["### Nominal models against the medians (compare.csv)", "",
          "RMS magnitude error (dB) / phase error (deg) / normalised error (× noise) over "
          "the whole grid and per band.", ""]
    bands = [f"{lo:g}-{hi:g}" for lo, hi in BANDS]
    header = ["axis", "model", "overall"] + [f"{b} Hz" for b in bands]
    rows = []
    for (axis, model), g in compare_rows.groupby(["axis", "model"], sort=False):
        cells = {r["band"]: f"{_num(r['rms_db'], '.2f')} / {_num(r['rms_deg'], '.1f')} / "
                            f"{_num(r['rms_norm'], '.2f')}" for _, r in g.iterrows()}
        rows.append([axis, model, cells.get("overall", "–")]
                    + [cells.get(b, "–") for b in bands])
    L += _md_table(header, rows)

    if stability is not None:
        L += stability_markdown(stability)

    if figures:
        L += ["## Figures", ""]
        captions = {
            "figures/bode.png": "Measured dynamics X/F per axis with the grip fits "
                                "(the paper's Fig. 5)",
            "figures/uncertainty.png": "Derived arm dynamics with the nominal H_ARM, "
                                       "W_max and |Wu| (Fig. 6)",
            "figures/literature.png": "H_ARM of the X axis at 1 N grip against the "
                                      "literature models of Table IV (Fig. 7)",
            STABILITY_FIGURE: "Stiffest stable virtual wall per subject and grip, and "
                              "against servo rate for d = 0, 1, 2",
        }
        for f in figures:
            cap = captions.get(f)
            if cap is None:
                axis = f.rsplit("_", 1)[1].split(".")[0]
                eff = next((e for e, a in refitted.items() if axis in a), None)
                cap = (f"Normalised residual of the nominal model, axis {axis.upper()}"
                       + (f", with `{eff}` dashed" if eff else "")
                       + "; failing bands of the diagnosis shaded")
            L += [f"### {cap}", "", f"![{cap}]({f})", ""]

    L += ["## Files", ""] + [f"- `{f}`" for f in files] + [""]
    return "\n".join(L)


def _warn_at_bound(which: str, study, warn: Warn | None) -> None:
    """One warning per fit with a parameter at a physical bound (column ``at_bound``)."""
    if warn is None:
        return
    for (axis, grip), fit in zip(study.keys, study.fits, strict=True):
        if fit.at_bound:
            where = axis + ("" if grip is None else f" {grip:g} N")
            warn(f"fit-{which} {where}: {', '.join(fit.at_bound)} at a physical bound "
                 "(within 1 % of its range); the value is a limit, not an estimate")


# ---------------------------------------------------------------------------
# fit-trials and stability stages
# ---------------------------------------------------------------------------

#: The stability figure written by ``run`` (figures on), relative to OUTDIR.
STABILITY_FIGURE = "figures/stability.png"


def _stability_stages(folder: Path, spectra, nominal, weights, wu_summary,
                      options: RunOptions, path, clock) -> dict:
    """fit-trials (trial_params.csv) and stability at the defaults (stability.csv), the
    certificate of the nominal models against the fitted Wu, and the stability figure.
    Returns what the report needs."""
    import warnings

    from armfit.fitting import fit_trials, trial_fits_table
    from armfit.io.artifacts import write_params
    from armfit.io.atomic import write_text_atomic
    from armfit.io.paramsets import read_param_rows
    from armfit.stability import WallSettings, axis_summary, stability_table
    fits = fit_trials(spectra, cost=options.cost, jobs=options.jobs,
                      source="spectra.parquet")
    write_params(trial_fits_table(fits), path("trial_params.csv"))
    failed = [(f"{t.axis} {t.subject} {t.grip_N:g} N", t.reason) for t in fits
              if t.fit is None]
    clock.done("fit-trials", f"{len(fits) - len(failed)} trial fit(s)"
               + (f", {len(failed)} failed" if failed else ""))
    settings = WallSettings()
    rows = read_param_rows(str(folder / "trial_params.csv"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        table = stability_table(rows.table, settings, source="trial_params.csv")
    text = table.to_csv(index=False, float_format="%.10g", lineterminator="\n")
    write_text_atomic(path("stability.csv"), text)
    summary = axis_summary(table)
    bands = {}
    for _, r in wu_summary[(wu_summary["weight"] == "fitted")
                           & (wu_summary["target"] == "wmax")].iterrows():
        bands[r["axis"]] = (float(r["band_lo_hz"]), float(r["band_hi_hz"]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        cert = stability_table(nominal, settings, weights=weights, weights_band_hz=bands)
    figure = None
    if options.figures:
        from armfit import figures as F
        figure = _save(folder, F.stability_figure(rows.table, settings), STABILITY_FIGURE)
    clock.done("stability", "; ".join(f"{a}: K_max min {s['k_max_min_N_per_m'] / 1e3:.3g} "
                                      f"kN/m" for a, s in summary.items())
               + (f"; {figure}" if figure else ""))
    return {"settings": settings, "summary": summary, "failed": failed, "certificate": cert,
            "warnings": [str(w.message) for w in caught], "figure": figure,
            "n_models": len(table)}


def stability_markdown(wall: Mapping) -> list[str]:
    """The report's section on the stiffest stable virtual wall (lines of Markdown)."""
    st = wall["settings"]
    rate = 1.0 / st.sample_time_s
    L = ["## Stiffest stable virtual wall (stability.csv)", "",
         f"One fit per trial (`trial_params.csv`, {wall['n_models']} fitted), then K_max: "
         f"the largest wall stiffness K for which the sampled loop F[k] = −(K x[k−d] + "
         f"B (x[k−d] − x[k−d−1])/T) with each arm is stable for every K′ ≤ K (exact "
         f"zero-order-hold discretisation; see `armfit stability`). Defaults: "
         f"{rate:g} Hz servo, B = {st.damping_Ns_per_m:g} N·s/m, d = {st.delay_samples} "
         "sample(s).", ""]
    for axis, s in wall["summary"].items():
        L.append(f"- A {rate / 1e3:g} kHz device with {st.delay_samples} sample(s) of delay "
                 f"renders walls up to {s['k_max_min_N_per_m'] / 1e3:.3g} kN/m on "
                 f"{axis.upper()} for every subject and grip ({s['n_models']} trials; "
                 f"limited by {s['limiting']}); median {s['k_max_median_N_per_m'] / 1e3:.3g}"
                 f" kN/m, 5th percentile {s['k_max_p05_N_per_m'] / 1e3:.3g} kN/m.")
    L.append("")
    for who, why in wall["failed"]:
        L.append(f"- Trial {who} has no fit ({why}) and is not in the population.")
    for text in wall["warnings"]:
        L.append(f"- Warning: {text}.")
    cert = wall["certificate"]
    if "k_robust_N_per_m" in cert.columns:
        L += ["", "Robust certificate of the nominal models against the fitted Wu "
              "(max |Wu T| < 1, T the complementary sensitivity seen by the arm's "
              "multiplicative uncertainty):", ""]
        for _, r in cert.iterrows():
            if math.isfinite(r["k_robust_N_per_m"]):
                L.append(f"- {r['axis'].upper()}: holds for K up to "
                         f"{r['k_robust_N_per_m'] / 1e3:.3g} kN/m (peak at K = 0: "
                         f"{r['wu_t_peak_k0']:.2f}).")
            else:
                L.append(f"- {r['axis'].upper()}: holds for no K at all (max |Wu T| is "
                         f"{r['wu_t_peak_k0']:.2f} > 1 already at K = 0).")
    return L + [""]
