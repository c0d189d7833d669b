"""The one-shot pipeline of ``armfit run``: raw trials in, every table, figure and a report out.

The pipeline is a table of stages (:data:`PIPELINE`), each the API call of its own
subcommand, run in the order data flows (files written into OUTDIR in brackets):

- ingest: :func:`armfit.io.trials.ingest` (trials.parquet);
- estimate: :func:`armfit.api.estimate_study_result` (spectra.parquet);
- fit-grip, fit-nominal: :func:`armfit.fit_grip`, :func:`armfit.fit_nominal` of the
  paper's 5-parameter model (grip_params.csv/.tex, nominal_params.csv/.tex);
- diagnose: :func:`armfit.diagnose` started from the grip fits (diagnosis.json), and
  the adopted model of each axis, :func:`armfit.adopt.adopt` (adoption.csv);
- adopt, when an effect is adopted: Tables I and II again with the adopted model (the
  base model's move to grip_params_base.csv/.tex and nominal_params_base.csv/.tex);
- fit-uncertainty: :func:`armfit.fit_uncertainty` of the adopted nominal (wu.csv,
  wu_summary.csv, wu_wmax.csv, wu.tex), with the same convergence policy as ``armfit
  fit-uncertainty``;
- fit-trials: :func:`armfit.fitting.fit_trials` with the adopted model, one fit per
  trial, each started from its grip's fit (trial_params.csv);
- stability: :func:`armfit.loop.stability_table` of the per-trial fits at the
  defaults (stability.csv), the certificate of the nominal models against Wu capped by
  the trials (certificate.csv), and :func:`armfit.figures.stability_figure`
  (figures/stability.png);
- figures: Figs. 5–7 of :mod:`armfit.figures` (figures/bode.png, uncertainty.png,
  literature.png);
- compare: :func:`armfit.compare` of each nominal model (base, adopted) with the
  medians (compare.csv);
- residuals: :func:`armfit.figures.residual_figure` per axis (figures/residual_<axis>.png);
- report: :func:`report_markdown` (report.md), from the stages' typed results and the
  configuration they used.

Everything after the diagnosis uses the adopted model (the base model where nothing is
adopted), so the products are computed once, from the model that survived the
diagnosis. With ``jobs`` > 1 :func:`run_pipeline` starts one pool of ``jobs`` worker
processes for the run (:func:`armfit.workers.process_pool`) and hands it to every stage:
the estimate runs in it while this process ingests, the per-trial fits run in it while
this process fits Wu, and the figures are drawn and written in it while the later stages
go on (the report stage waits for them). Given an ``executor`` (e.g. a dask cluster's),
the stages run their tasks on it instead, and the figures are drawn here. The diagnosis,
which starts from the grip fits, runs in a thread of its own alongside Table II with
``jobs`` worker processes of its own. The results depend on neither ``jobs`` nor the
executor.

Every later stage reads the files the earlier ones wrote (as the subcommands do), so
``armfit run`` gives the same numbers as the subcommands run one after the other with
the same options. The whole folder is built in a temporary folder beside OUTDIR and
renamed onto it at the end (:func:`armfit.io.atomic.atomic_path`): a failure leaves no
OUTDIR, and an existing OUTDIR is replaced only with ``overwrite``.
"""

from __future__ import annotations

import contextlib
import importlib
import math
import os
import threading
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from armfit import api
from armfit._version import __version__
from armfit.adopt import Adoption, adopt
from armfit.api import compare_frame
from armfit.constants import AXES, PAPER_BANDS
from armfit.diagnosis import BANDS, diagnose_axes
from armfit.errors import ArmfitError, OutputError
from armfit.fitting import fit_trials, grip_fit_starts, trial_fits_table
from armfit.io.artifacts import write_params
from armfit.io.atomic import atomic_path, check_output, write_text_atomic
from armfit.io.schema import COMPARE_COLUMNS, wu_sidecar_paths
from armfit.io.trials import ingest
from armfit.loop import WallSettings, axis_summary, stability_table
from armfit.models.params import read_param_rows
from armfit.spectra import EstimateConfig, Spectra
from armfit.tables import param_names, sig4, unit_of
from armfit.workers import cancel_pools, executor_for

#: Figures written (``figures`` on), relative to OUTDIR; residual_<axis>.png per axis.
FIGURES = ("figures/bode.png", "figures/uncertainty.png", "figures/literature.png")

__all__ = ["COMPARE_COLUMNS", "FIGURES", "PIPELINE", "STAGES", "PipelineStage",
           "RunOptions", "RunResult", "Stage", "check_outdir", "compare_frame",
           "report_markdown", "run", "run_pipeline"]


@dataclass(frozen=True)
class RunOptions:
    """Options of :func:`run_pipeline`.

    manifest: trial manifest CSV (None: file names carry the identity); skip_bad: go on
    past bad trials; method: estimator of the measured dynamics ("h1" or "chebwin");
    cost: arm-fit cost ("complex" or "paper", eq. 5); wu_cost: Wu fit ("envelope" or
    "paper", eq. 7); jobs: worker processes (every stage with tasks to share out;
    see :func:`run_pipeline` for an executor given instead); figures: draw the
    figures; overwrite: replace an existing OUTDIR; adopt: what the diagnosis found
    becomes the model ("auto") or not ("none"), see :mod:`armfit.adopt`; outside_loop:
    apparatus effects the stability loop leaves out (:func:`armfit.loop.loop_model`).
    """

    manifest: str | None = None
    skip_bad: bool = False
    method: str = "h1"
    cost: str = "complex"
    wu_cost: str = "envelope"
    jobs: int = 1
    figures: bool = True
    overwrite: bool = False
    adopt: str = "auto"
    outside_loop: tuple[str, ...] = ()


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
    verdict sentence}; missing: {axis: effect name or None}; refitted: {effects: axes}
    adopted ("delay+lowpass" for two); adoption: the adopted model per axis;
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
    adoption: Adoption | None = None
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
                 warn: Warn | None = None, executor: Executor | None = None) -> RunResult:
    """Run every stage on ``inputs`` (raw trial files, folders or a canonical dataset)
    and write the results into ``outdir``, atomically.

    The stages' tasks run on ``executor`` when given (a
    :class:`concurrent.futures.Executor`, used as is and never shut down; the figures are
    then drawn in this process, and after a failure the tasks it already runs finish
    first), else in one pool of ``options.jobs`` worker processes made for the run (none
    with jobs 1); the diagnosis has ``options.jobs`` worker processes of its own.

    ``on_stage(stage)`` is called after each stage (e.g. to print its time); ``warn``
    receives data warnings (saturation). Raises OutputError (exit 73) before any work
    if ``outdir`` cannot be written, and the error of the first failing stage otherwise
    (BadInputError 65, NoInputError 66, ConvergenceError 3, ...), leaving no new OUTDIR
    and an existing one untouched; a message naming a file of the temporary folder names
    it as it would have been in ``outdir``.
    """
    out = check_outdir(outdir, inputs, manifest=options.manifest, overwrite=options.overwrite)
    tmp: Path | None = None
    try:
        with atomic_path(out, overwrite=options.overwrite, folder=True) as tmp:
            result = _run_in(list(inputs), tmp, options, on_stage=on_stage, warn=warn,
                             executor=executor)
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


class _Background:
    """``fn(*args, **kwargs)``, started now in a thread of its own when ``parallel`` (the
    thread mostly waits for worker processes, so the stages that do not need the result
    run meanwhile in this process) and collected by :meth:`result`; else it runs when
    collected. ``started`` is when it began (s, perf_counter)."""

    def __init__(self, parallel: bool, fn: Callable, /, *args, **kwargs):
        self.call = (fn, args, kwargs)
        self.thread = None
        self.ident: int | None = None       # of the thread, once it runs
        self.started = time.perf_counter()
        if parallel:
            self.thread = ThreadPoolExecutor(max_workers=1)
            self.task = self.thread.submit(self._in_thread, fn, args, kwargs)

    def _in_thread(self, fn: Callable, args, kwargs):
        self.ident = threading.get_ident()
        return fn(*args, **kwargs)

    def result(self):
        if self.thread is None:
            self.started = time.perf_counter()
            fn, args, kwargs = self.call
            return fn(*args, **kwargs)
        try:
            return self.task.result()
        finally:
            self.close()

    def close(self) -> None:
        """Wait for the thread (after a failure elsewhere, its pending work in the run's
        pool has been cancelled, so it ends soon)."""
        if self.thread is not None:
            self.thread.shutdown(wait=True, cancel_futures=True)
            self.thread = None

    def stop(self) -> None:
        """After a failure elsewhere: cancel the pending work of the pools the call made
        for itself in its thread (:func:`armfit.workers.cancel_pools`; it then fails at
        its next task), again until it has ended, and wait for the thread."""
        if self.thread is None:
            return
        while not self.task.done():
            if self.ident is not None:
                cancel_pools(self.ident)
            with contextlib.suppress(BaseException):
                self.task.exception(timeout=0.05)
        self.close()


def _run_in(inputs: list, folder: Path, options: RunOptions, *,
            on_stage: OnStage | None, warn: Warn | None,
            executor: Executor | None = None) -> RunResult:
    # the caller's executor, or one pool of worker processes for every stage of the run
    with executor_for(executor, options.jobs) as pool, contextlib.ExitStack() as stack:
        own = pool is not None and pool is not executor
        ctx = _Context(inputs, folder, options, warn=warn, stack=stack,
                       config=EstimateConfig(method=options.method),
                       bands=dict(PAPER_BANDS), drawings=_Drawings(pool if own else None),
                       pool=pool)
        clock = _Clock(on_stage)
        try:
            for stage in PIPELINE:
                if stage.when(ctx):
                    summary, since = stage.run(ctx), ctx.since
                    ctx.since = None
                    clock.done(stage.name, summary, since=since)
        except BaseException:
            if own:   # the background stages stop at their next task
                pool.shutdown(wait=True, cancel_futures=True)
            raise
        return RunResult(outdir=str(folder), files=tuple(sorted(ctx.files)),
                         trials=len(ctx.estimated.trials), skipped=ctx.skipped,
                         verdicts={d.axis: d.verdict for d in ctx.diagnosis.axes},
                         missing=ctx.missing, refitted=ctx.refitted,
                         adoption=ctx.adoption, stages=tuple(clock.stages), wall_s=clock.wall())


# ---------------------------------------------------------------------------
# The stages as data: what each does, on what, and when it runs
# ---------------------------------------------------------------------------

@dataclass
class _Context:
    """What the stages of one run share: the inputs and options, the configuration they
    use, the files written so far, and each stage's typed result."""

    inputs: list
    folder: Path
    options: RunOptions
    warn: Warn | None
    stack: contextlib.ExitStack
    config: EstimateConfig
    bands: dict[str, tuple[float, float]]
    pool: Executor | None = None        # runs the stages' tasks (None: here, in turn)
    files: list[str] = field(default_factory=list)
    skipped: tuple[tuple[str, str], ...] = ()
    n_ingested: int = 0
    estimated: object = None            # spectra.StudySpectra
    spectra: Spectra | None = None      # as read back from spectra.parquet
    grip: api.ModelFit | None = None
    nominal: api.ModelFit | None = None
    estimating: _Background | None = None
    diagnosing: _Background | None = None       # the diagnosis
    trial_fits: _Background | None = None
    uncertainty: api.Uncertainty | None = None
    drawn: list[str] = field(default_factory=list)
    drawings: _Drawings | None = None
    diagnosis: api.Diagnosis | None = None
    refitted: dict[str, tuple[str, ...]] = field(default_factory=dict)
    adoption: Adoption | None = None
    base_grip: api.ModelFit | None = None       # the 5-parameter tables, when adopted
    base_nominal: api.ModelFit | None = None
    comparisons: api.Comparisons | None = None
    missing: dict[str, str | None] = field(default_factory=dict)
    trial_failed: list[tuple[str, str]] = field(default_factory=list)
    wall: dict | None = None            # the stability stage's results, for the report
    since: float | None = None          # start of a stage that ran alongside others

    @property
    def parallel(self) -> bool:
        """Whether the stages run alongside each other (their tasks go to :attr:`pool`)."""
        return self.pool is not None

    def background(self, fn: Callable, /, *args, **kwargs) -> _Background:
        """``fn(*args, **kwargs)`` as a :class:`_Background` of the run, stopped if the
        run fails first."""
        task = _Background(self.parallel, fn, *args, **kwargs)
        self.stack.callback(task.stop)
        return task

    def path(self, name: str) -> Path:
        """``folder / name``, recorded as a file of the run."""
        self.files.append(name)
        return self.folder / name


@dataclass(frozen=True)
class PipelineStage:
    """One stage of ``armfit run``: its name (as reported), the function that does it
    and returns a one-line summary, and when it runs."""

    name: str
    run: Callable[[_Context], str]
    when: Callable[[_Context], bool] = lambda ctx: True


def _ingest(ctx: _Context) -> str:
    """Validate the raw trials once, into the canonical dataset (trials.parquet); the
    estimate, which reads the same inputs, runs meanwhile in the worker processes."""
    o = ctx.options
    ctx.estimating = ctx.background(api.estimate_study_result, ctx.inputs, ctx.config,
                                    manifest=o.manifest, skip_bad=o.skip_bad, jobs=o.jobs,
                                    executor=ctx.pool)
    ing = ingest(ctx.inputs, ctx.path("trials.parquet"), manifest=o.manifest,
                 skip_bad=o.skip_bad, warn=ctx.warn)
    ctx.skipped = tuple((s.file, s.reason) for s in ing.skipped)
    ctx.n_ingested = len(ing.trials)
    return f"{len(ing.trials)} trial(s)" + (f", {len(ctx.skipped)} skipped"
                                            if ctx.skipped else "")


def _estimate(ctx: _Context) -> str:
    """Estimate from the same inputs (so that a message names the user's files) into
    spectra.parquet; later stages read that file back, as the subcommands do."""
    config = ctx.config
    est = ctx.estimating.result()
    ctx.since = ctx.estimating.started
    seen = {f for f, _ in ctx.skipped}
    ctx.skipped += tuple((f, r) for f, r in est.skipped if f not in seen)
    est.write(ctx.path("spectra.parquet"))
    ctx.estimated = est
    ctx.spectra = Spectra.read(ctx.folder / "spectra.parquet")
    return (f"{len(est.trials)} trial(s), method {config.method}, "
            f"{len(config.grid())} frequencies {config.fmin:g}-{config.fmax:g} Hz")


def _fit(which: str) -> Callable[[_Context], str]:
    def stage(ctx: _Context) -> str:
        """Tables I and II of the base model (params CSV and LaTeX); the diagnosis starts
        from the grip fits as soon as they exist."""
        fit = api.fit_grip if which == "grip" else api.fit_nominal
        model = fit(ctx.spectra, cost=ctx.options.cost, bands=ctx.bands,
                    jobs=ctx.options.jobs, executor=ctx.pool)
        _warn_at_bound(which, model, ctx.warn)
        model.write(ctx.path(f"{which}_params.csv"), latex=ctx.path(f"{which}_params.tex"))
        back = replace(api.ModelFit.read(ctx.folder / f"{which}_params.csv"),
                       fits=model.fits, spectra=ctx.spectra)
        setattr(ctx, which, back)
        if which == "grip":
            o = ctx.options
            axes = [a for a in AXES if (back.table["axis"] == a).any()]
            # the diagnosis has worker processes of its own: its steps are long, and
            # the stages that wait for their pool tasks should not queue behind them
            ctx.diagnosing = ctx.background(diagnose_axes, ctx.spectra, back.table,
                                            axes=axes, jobs=o.jobs)
        return (f"{len(back.table)} fit(s), cost {ctx.options.cost}, median rms "
                f"{_median(back.table['rms_db']):.2f} dB")
    return stage


def _fit_uncertainty(ctx: _Context) -> str:
    """W_max and Wu (Table III) of the adopted nominal, apparatus effects removed: wu.csv,
    wu_summary.csv, wu_wmax.csv, wu.tex. The per-trial fits run meanwhile in the worker
    processes."""
    o = ctx.options
    # each trial's fit starts from its grip's fit, as `armfit fit-trials` does
    starts = grip_fit_starts(zip(ctx.grip.table["axis"], ctx.grip.table["grip_N"], strict=True),
                             ctx.grip.fits)
    ctx.trial_fits = ctx.background(fit_trials, ctx.spectra, cost=o.cost, jobs=o.jobs,
                                    source="spectra.parquet", starts=starts,
                                    bands=ctx.bands, effects=_effects_of(ctx),
                                    executor=ctx.pool)
    wu_path = ctx.path("wu.csv")
    ctx.files += [p.name for p in wu_sidecar_paths(wu_path)]
    unc = api.fit_uncertainty(ctx.spectra, ctx.nominal, cost=ctx.options.wu_cost,
                              jobs=ctx.options.jobs, executor=ctx.pool)
    unc.write(wu_path, latex=ctx.path("wu.tex"))
    ctx.uncertainty = unc
    return ", ".join(f"{r.axis}: {r.result.order} pair(s)" for r in unc.axes) + \
        f", cost {ctx.options.wu_cost}"


def _figures(ctx: _Context) -> str:
    """The paper's Figs. 5-7 (they need no diagnosis)."""
    (ctx.folder / "figures").mkdir(exist_ok=True)  # the stability figure may be there
    paper = _paper_figures(ctx)
    ctx.drawn += paper
    return f"{len(paper)} figure(s): Figs. 5, 6, 7"


def _diagnose(ctx: _Context) -> str:
    """The diagnosis started from the grip fits (diagnosis.json) and the adopted model of
    each axis (adoption.csv)."""
    results = ctx.diagnosing.result()
    ctx.diagnosis = api.Diagnosis(tuple(results), ctx.spectra, ctx.grip)
    ctx.diagnosis.write(ctx.path("diagnosis.json"))
    ctx.since = ctx.diagnosing.started
    # every effect the stepwise search named on an axis, in order ("delay+lowpass")
    ctx.missing = {a: "+".join(names) or None for a, names in ctx.diagnosis.added.items()}
    ctx.adoption = adopt(ctx.diagnosis, ctx.options.adopt)
    text = ctx.adoption.to_frame().to_csv(index=False, float_format="%.10g",
                                          lineterminator="\n")
    write_text_atomic(ctx.path("adoption.csv"), text)
    for a in ctx.adoption.axes:
        if a.adopted:
            key = "+".join(a.effects)
            ctx.refitted[key] = (*ctx.refitted.get(key, ()), a.axis)
    return "; ".join(f"{a}: {e or 'no missing effect'}" for a, e in ctx.missing.items())


def _effects_of(ctx: _Context):
    """The fitters' ``effects`` of the adopted model ({axis: items}; () for none)."""
    return ctx.adoption.effects if ctx.adoption is not None and ctx.adoption.anything \
        else ()


def _adopt(ctx: _Context) -> str:
    """Tables I and II again with the adopted model (the band of the diagnosis on the
    adopted axes, apparatus effects held at its joint fit); the base model's tables are
    kept as grip_params_base.csv/.tex and nominal_params_base.csv/.tex."""
    ad = ctx.adoption
    ctx.base_grip, ctx.base_nominal = ctx.grip, ctx.nominal
    for which in ("grip", "nominal"):
        for ext in (".csv", ".tex"):
            src = ctx.folder / f"{which}_params{ext}"
            os.replace(src, ctx.path(f"{which}_params_base{ext}"))
    ctx.bands = ad.bands
    fitted = api.adopt_model(ctx.spectra, ctx.diagnosis, policy=ad.policy,
                             cost=ctx.options.cost, trials=False, jobs=ctx.options.jobs,
                             executor=ctx.pool)
    for which in ("grip", "nominal"):
        model = getattr(fitted, which)
        _warn_at_bound(which, model, ctx.warn)
        model.write(ctx.folder / f"{which}_params.csv",
                    latex=ctx.folder / f"{which}_params.tex")
        setattr(ctx, which, replace(api.ModelFit.read(ctx.folder / f"{which}_params.csv"),
                                    fits=model.fits, spectra=ctx.spectra))
    return "; ".join(f"{' + '.join(ad[a].effects)} on {a}" for a in ad.adopted_axes)


def _compare(ctx: _Context) -> str:
    """Each nominal model (base, and adopted where it differs) against the axis medians
    (compare.csv)."""
    base = ctx.base_nominal or ctx.nominal
    rows = list(api.compare(ctx.spectra, base, level="median").rows)
    if ctx.base_nominal is not None:
        adopted = ctx.nominal.table[ctx.nominal.table["axis"].isin(
            ctx.adoption.adopted_axes)]
        rows += api.compare(ctx.spectra, replace(ctx.nominal, table=adopted),
                            level="median").rows
    ctx.comparisons = api.Comparisons(tuple(rows), "median")
    ctx.comparisons.write(ctx.path("compare.csv"))
    return f"{len(rows)} model(s) x axis against the medians"


def _residuals(ctx: _Context) -> str:
    """Residual figures: they need the diagnosis (failing bands) and the refits."""
    res = _residual_figures(ctx)
    ctx.drawn += res
    return f"{len(res)} figure(s)"


def _report(ctx: _Context) -> str:
    """report.md, from the results above and the configuration they used."""
    ctx.drawings.wait()
    if ctx.wall and ctx.wall["figure"]:
        ctx.drawn.append(ctx.wall["figure"])
    ctx.files += ctx.drawn
    ctx.files.append("report.md")
    write_text_atomic(ctx.folder / "report.md", report_markdown(ctx))
    return "report.md"


def _fit_trials(ctx: _Context) -> str:
    """One fit per trial (trial_params.csv): the population the stability stage uses."""
    fits = ctx.trial_fits.result()
    ctx.since = ctx.trial_fits.started
    write_params(trial_fits_table(fits), ctx.path("trial_params.csv"))
    ctx.trial_failed = [(f"{t.axis} {t.subject} {t.grip_N:g} N", t.reason) for t in fits
                        if t.fit is None]
    return f"{len(fits) - len(ctx.trial_failed)} trial fit(s)" + (
        f", {len(ctx.trial_failed)} failed" if ctx.trial_failed else "")


def _stability(ctx: _Context) -> str:
    """The stiffest stable virtual wall of every trial's fit at the defaults
    (stability.csv), the certificate of the nominal models against the fitted Wu, capped
    by the trials it covers (certificate.csv), K_max of the base and adopted nominal
    models, and the stability figure."""
    settings = WallSettings()
    loop = ctx.options.outside_loop
    rows = read_param_rows(str(ctx.folder / "trial_params.csv"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        table = stability_table(rows.table, settings, source="trial_params.csv",
                                outside_loop=loop)
    text = table.to_csv(index=False, float_format="%.10g", lineterminator="\n")
    write_text_atomic(ctx.path("stability.csv"), text)
    summary = axis_summary(table)
    wu_summary = ctx.uncertainty.summary()
    bands = {}
    for _, r in wu_summary[(wu_summary["weight"] == "fitted")
                           & (wu_summary["target"] == "wmax")].iterrows():
        bands[r["axis"]] = (float(r["band_lo_hz"]), float(r["band_hi_hz"]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        cert = stability_table(ctx.nominal.table, settings, weights=ctx.uncertainty.weights,
                               weights_band_hz=bands, outside_loop=loop,
                               members=rows.table)
        base = None
        if ctx.base_nominal is not None:
            base = stability_table(ctx.base_nominal.table, settings)
    text = cert.to_csv(index=False, float_format="%.10g", lineterminator="\n")
    write_text_atomic(ctx.path("certificate.csv"), text)
    figure = None
    if ctx.options.figures:
        figure = ctx.drawings.draw(ctx.folder, STABILITY_FIGURE, "stability_figure",
                                   rows.table, settings)
        # listed after the paper's and the residual figures (see _report)
    ctx.wall = {"settings": settings, "summary": summary, "failed": ctx.trial_failed,
                "certificate": cert, "warnings": [str(w.message) for w in caught],
                "figure": figure, "n_models": len(table), "base_nominal": base,
                "in_loop": _loop_effects(ctx), "outside_loop": tuple(loop)}
    return "; ".join(f"{a}: K_max min {s['k_max_min_N_per_m'] / 1e3:.3g} kN/m"
                     for a, s in summary.items()) + (f"; {figure}" if figure else "")


def _loop_effects(ctx: _Context) -> dict[str, tuple[str, ...]]:
    """{axis: the adopted effects inside the stability loop}."""
    if ctx.adoption is None:
        return {}
    drop = set(ctx.options.outside_loop)
    return {a.axis: tuple(e for e in a.effects if e not in drop) for a in ctx.adoption.axes}


#: The stages of ``armfit run``, in the order they run; names as reported (:data:`STAGES`).
PIPELINE: tuple[PipelineStage, ...] = (
    PipelineStage("ingest", _ingest),
    PipelineStage("estimate", _estimate),
    PipelineStage("fit-grip", _fit("grip")),
    PipelineStage("fit-nominal", _fit("nominal")),
    PipelineStage("diagnose", _diagnose),
    PipelineStage("adopt", _adopt, lambda ctx: ctx.adoption.anything),
    PipelineStage("fit-uncertainty", _fit_uncertainty),
    PipelineStage("fit-trials", _fit_trials),
    PipelineStage("stability", _stability),
    PipelineStage("figures", _figures, lambda ctx: ctx.options.figures),
    PipelineStage("compare", _compare),
    PipelineStage("residuals", _residuals, lambda ctx: ctx.options.figures),
    PipelineStage("report", _report),
)

#: Stage names, in the order they are reported (``adopt`` only when an effect is adopted,
#: ``figures`` and ``residuals`` only with figures on). With jobs > 1 the diagnosis runs
#: in worker processes from the end of fit-grip on, alongside fit-nominal.
STAGES: tuple[str, ...] = tuple(stage.name for stage in PIPELINE)


def _median(values) -> float:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")


def _draw_task(args) -> None:
    """Worker: draw the figure ``figures.<fn>(*args, **kwargs)`` and write it to ``path``.
    :mod:`armfit.figures` (and matplotlib) is imported here, on first use: with worker
    processes only they load it, off the run's critical path."""
    fn, fargs, kwargs, path = args
    figures = importlib.import_module("armfit.figures")
    figures.save_figure(getattr(figures, fn)(*fargs, **kwargs), path)


class _Drawings:
    """Figures drawn and written by the run's worker pool while the stages go on (with no
    pool of the run's own, at once, here); :meth:`wait` returns when all are written and
    raises the first failure."""

    def __init__(self, pool):
        self.pool = pool
        self.pending: list = []

    def draw(self, folder: Path, name: str, fn: str, *args, **kwargs) -> str:
        """Draw ``figures.<fn>(*args, **kwargs)`` into ``folder / name``; returns ``name``."""
        task = (fn, args, kwargs, folder / name)
        if self.pool is None:
            _draw_task(task)
        else:
            self.pending.append(self.pool.submit(_draw_task, task))
        return name

    def wait(self) -> None:
        pending, self.pending = self.pending, []
        for fut in pending:
            fut.result()


def _paper_figures(ctx: _Context) -> list[str]:
    """Fig. 5 (bode: measured dynamics with the grip fits, all axes), Fig. 6 (derived
    dynamics, nominal H_ARM, W_max and |Wu|) and Fig. 7 (the X axis 1 N H_ARM, else the
    first grip fit, against Table IV). Returns the paths written, relative to OUTDIR."""
    grip, draw = ctx.grip.table, ctx.drawings.draw
    rows = grip[(grip["axis"] == "x") & np.isclose(grip["grip_N"].to_numpy(float), 1.0)]
    return [draw(ctx.folder, FIGURES[0], "bode_figure", ctx.spectra, grip),
            draw(ctx.folder, FIGURES[1], "uncertainty_figure", ctx.spectra,
                 ctx.nominal.table, ctx.uncertainty.weights),
            draw(ctx.folder, FIGURES[2], "literature_figure",
                 (rows if len(rows) else grip).iloc[0])]


def _residual_figures(ctx: _Context) -> list[str]:
    """One residual figure per diagnosed axis: the base nominal model solid, the adopted
    nominal model dashed where it differs, the diagnosis's failing bands shaded."""
    base = (ctx.base_nominal or ctx.nominal).table
    adopted = ctx.adoption.adopted_axes if ctx.adoption is not None else ()
    out = []
    for d in sorted(ctx.diagnosis.axes, key=lambda d: d.axis):
        bands = {d.axis: [(fb.lo_hz, fb.hi_hz) for fb in d.failing]}
        out.append(ctx.drawings.draw(ctx.folder, f"figures/residual_{d.axis}.png",
                                     "residual_figure", ctx.spectra, base,
                                     ctx.nominal.table if d.axis in adopted else None,
                                     axis=d.axis, bands=bands))
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


def _bands_text(bands: Mapping[str, tuple[float, float]]) -> str:
    """Fit bands in words, axes of one band together: "x, y 0.1–30 Hz and z 0.1–10 Hz"."""
    groups: dict[tuple[float, float], list[str]] = {}
    for axis in AXES:
        if axis in bands:
            groups.setdefault(tuple(bands[axis]), []).append(axis)
    return " and ".join(f"{', '.join(axes)} {lo:g}–{hi:g} Hz"
                        for (lo, hi), axes in groups.items())


def adoption_markdown(run: _Context) -> list[str]:
    """The report's opening section: the adopted model per axis, why, and what changed
    because of it (lines of Markdown)."""
    ad = run.adoption
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
    wall = run.wall or {}
    base, cert = wall.get("base_nominal"), wall.get("certificate")
    if base is not None and cert is not None:
        rows = []
        for axis in ad.adopted_axes:
            b = base[base["axis"] == axis]["k_max_N_per_m"]
            c = cert[cert["axis"] == axis]["k_max_N_per_m"]
            t = wall["summary"].get(axis, {}).get("k_max_min_N_per_m", math.nan)
            loop = wall.get("in_loop", {}).get(axis, ())
            rows.append([axis.upper(), _kn(b.iloc[0] if len(b) else math.nan),
                         _kn(c.iloc[0] if len(c) else math.nan), _kn(t),
                         ", ".join(loop) or "none"])
        L += ["What changed because of it — the stiffest stable wall at the defaults "
              "(1 kHz, B = 0, d = 1):", ""]
        L += _md_table(["axis", "K_max base nominal (kN/m)",
                        "K_max adopted nominal (kN/m)",
                        "K_max min over trials, adopted (kN/m)",
                        "adopted effects in the loop"], rows)
    return L


def _kn(v) -> str:
    return _num(float(v) / 1e3 if v is not None else None, ".3g")


def report_markdown(run: _Context) -> str:
    """The text of report.md: what was done with the configuration each stage used, the
    tables, the diagnosis per axis in words, the figures. Built from the stages' typed
    results; no timestamps or timings (re-running gives the same text)."""
    options, config = run.options, run.config
    inputs = [str(p) for p in run.inputs]
    n_trials, skipped = len(run.estimated.trials), run.skipped
    grip, nominal = run.grip.table, run.nominal.table
    wu_summary, weights = run.uncertainty.summary(), run.uncertainty.weights
    diagnosis = run.diagnosis.to_dict()
    adoption = run.adoption
    compare_rows = run.comparisons.to_frame()
    figures, files = run.drawn, sorted(run.files)
    cmd = ["armfit run", *inputs, "-o OUTDIR"]
    if options.manifest:
        cmd.append(f"--manifest {options.manifest}")
    if options.skip_bad:
        cmd.append("--skip-bad")
    cmd += [f"--method {options.method}", f"--cost {options.cost}",
            f"--wu-cost {options.wu_cost}"]
    if not options.figures:
        cmd.append("--no-figures")
    if options.adopt != "auto":
        cmd.append(f"--adopt {options.adopt}")
    cmd += [f"--outside-loop {e}" for e in options.outside_loop]
    L = ["# armfit report", "",
         f"armfit {__version__} — human arm dynamics and variability models by the method "
         "of Fu & Çavuşoğlu, ICRA 2010.", "",
         "```", " ".join(cmd), "```", ""]
    L += adoption_markdown(run)
    L += ["## What was done", ""]
    skipped_text = ""
    if skipped:
        skipped_text = f"; {len(skipped)} skipped: " + "; ".join(
            f"`{f}` ({r})" for f, r in skipped)
    adopted = adoption.adopted_axes
    adopt_text = ("; ".join(f"`{' + '.join(adoption[a].effects)}` on {a}" for a in adopted)
                  if adopted else "nothing adopted")
    steps = [
        f"**ingest** — {n_trials} trial(s) validated against the trial contract into "
        f"`trials.parquet`{skipped_text}.",
        f"**estimate** — measured dynamics X/F with the `{config.method}` estimator, "
        f"derived arm dynamics Xa/Fa (tfestimate, {config.derived_segments} segments), on "
        f"{config.per_decade} points per decade {config.fmin:g}–{config.fmax:g} Hz; mean "
        "per axis × grip and median per axis → `spectra.parquet`.",
        f"**fit-grip** — eq. 4 (the paper's 5-parameter model) fitted to each axis × grip "
        f"mean (Table I), cost `{options.cost}`, bands {_bands_text(PAPER_BANDS)}"
        f" → `grip_params{'_base' if adopted else ''}.csv/.tex`.",
        f"**fit-nominal** — the same fitted to each axis median (Table II) → "
        f"`nominal_params{'_base' if adopted else ''}.csv/.tex`.",
        "**diagnose** — stepwise search over the whole grid, started from the grip fits: "
        "the base model and the effects added one at a time, fitted to every trial, "
        "until the model is within the noise → `diagnosis.json`.",
        f"**adopt** — the model the diagnosis found becomes the model of the products "
        f"below: {adopt_text} → `adoption.csv`"
        + (f"; Tables I and II refitted with it, bands {_bands_text(run.bands)} → "
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
        ("**figures** — " + ", ".join(f"`{f}`" for f in figures) + ".") if figures
        else "**figures** — skipped (`--no-figures`).",
    ]
    L += [f"{i}. {s}" for i, s in enumerate(steps, 1)] + [""]

    which = "adopted model" if adopted else "the paper's 5-parameter model"
    L += [f"## Grip-dependent parameters (Table I, {which})", "",
          "Fits to the mean over subjects per axis and grip; 95 % intervals are in "
          "`grip_params.csv` and `grip_params.tex`" + (" (‡: held at the diagnosis's "
                                                         "value)" if adopted else "")
          + ".", ""]
    L += _md_table(*_params_rows(grip))
    L += [f"## Nominal parameters (Table II, {which})", "",
          "Fits to the median over all trials of an axis.", ""]
    L += _md_table(*_params_rows(nominal))
    if adopted:
        L += ["## The paper's 5-parameter model (base model, not adopted)", "",
              "Kept for comparison with the paper: the same fits without the adopted "
              "effects (`grip_params_base.csv`, `nominal_params_base.csv`). On the "
              "adopted axes the diagnosis found this model inadequate: its parameters "
              "partly imitate the missing effects.", "", "Table I, base model:", ""]
        L += _md_table(*_params_rows(run.base_grip.table))
        L += ["Table II, base model:", ""]
        L += _md_table(*_params_rows(run.base_nominal.table))

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
          "RMS magnitude error (dB) / phase error (deg) / normalised error (× noise); "
          "overall over each model's fit band (the rms × noise of Table II), and per band "
          "over the whole grid.", ""]
    bands = [f"{lo:g}-{hi:g}" for lo, hi in BANDS]
    header = ["axis", "model", "overall"] + [f"{b} Hz" for b in bands]
    rows = []
    for (axis, model), g in compare_rows.groupby(["axis", "model"], sort=False):
        cells = {r["band"]: f"{_num(r['rms_db'], '.2f')} / {_num(r['rms_deg'], '.1f')} / "
                            f"{_num(r['rms_norm'], '.2f')}" for _, r in g.iterrows()}
        rows.append([axis, model, cells.get("overall", "–")]
                    + [cells.get(b, "–") for b in bands])
    L += _md_table(header, rows)

    if run.wall is not None:
        L += stability_markdown(run.wall)

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
                eff = " + ".join(adoption[axis].effects)
                cap = (f"Normalised residual of the nominal model, axis {axis.upper()}"
                       + (f", adopted model with `{eff}` dashed" if eff else "")
                       + "; failing bands of the diagnosis shaded")
            L += [f"### {cap}", "", f"![{cap}]({f})", ""]

    L += ["## Files", ""] + [f"- `{f}`" for f in files] + [""]
    return "\n".join(L)


def run(inputs, outdir, *, manifest=None, skip_bad: bool = False, method: str = "h1",
        cost: str = "complex", wu_cost: str = "envelope", jobs: int = 1,
        figures: bool = True, overwrite: bool = False, adopt: str = "auto",
        outside_loop: Sequence[str] = (), on_stage: OnStage | None = None,
        warn: Warn | None = None, executor: Executor | None = None) -> RunResult:
    """Run every stage on raw trials and write all tables, figures and report.md into
    ``outdir`` (``armfit run``).

    Parameters
    ----------
    inputs : path or sequence of paths
        Trial files, folders or an ``armfit ingest`` dataset.
    outdir : path
        Folder to write (built beside it, renamed into place at the end).
    manifest : path, optional
        Trial manifest CSV.
    skip_bad : bool
        Go on past bad trials, listing each with its reason.
    method : {'h1', 'chebwin'}
        Measured-dynamics estimator (see :func:`armfit.estimate`).
    cost : {'complex', 'paper'}
        Arm-fit cost (see :func:`armfit.fit_grip`).
    wu_cost : {'envelope', 'paper'}
        Wu fit (see :func:`armfit.fit_uncertainty`).
    jobs : int
        Worker processes: one pool for the stages' tasks (estimate, fits, Wu, figures),
        and as many for the diagnosis.
    figures : bool
        Draw the figures.
    overwrite : bool
        Replace an existing ``outdir``.
    adopt : {'auto', 'none'}
        Whether the model the diagnosis finds becomes the model of every product
        (:mod:`armfit.adopt`).
    outside_loop : sequence of str
        Adopted apparatus effects the stability loop leaves out.
    on_stage : callable, optional
        Called with each finished :class:`Stage`.
    warn : callable, optional
        Receives data warnings.
    executor : concurrent.futures.Executor, optional
        Runs the stages' tasks instead of a pool of ``jobs`` workers, e.g. a
        ``dask.distributed`` client's ``client.get_executor()`` (used as is, never shut
        down; see :func:`run_pipeline`). The trial files are read by its workers: on a
        cluster, give paths every machine can read. The outputs do not depend on it.

    Returns
    -------
    RunResult
    """
    items = [inputs] if isinstance(inputs, str | os.PathLike) else list(inputs)
    options = RunOptions(manifest=manifest, skip_bad=skip_bad, method=method, cost=cost,
                         wu_cost=wu_cost, jobs=jobs, figures=figures, overwrite=overwrite,
                         adopt=adopt, outside_loop=tuple(outside_loop))
    return run_pipeline(items, outdir, options, on_stage=on_stage, warn=warn,
                        executor=executor)
def _warn_at_bound(which: str, model: api.ModelFit, warn: Warn | None) -> None:
    """One warning per fit with a parameter at a physical bound (column ``at_bound``)."""
    if warn is None:
        return
    grips = model.table["grip_N"] if "grip_N" in model.table.columns else [None] * len(
        model.table)
    for axis, grip, fit in zip(model.table["axis"], grips, model.fits, strict=True):
        if fit.at_bound:
            where = axis + ("" if grip is None else f" {grip:g} N")
            warn(f"fit-{which} {where}: {', '.join(fit.at_bound)} at a physical bound "
                 "(within 1 % of its range); the value is a limit, not an estimate")


# ---------------------------------------------------------------------------
# fit-trials and stability stages
# ---------------------------------------------------------------------------

#: The stability figure written by ``run`` (figures on), relative to OUTDIR.
STABILITY_FIGURE = "figures/stability.png"


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
    loop = wall.get("in_loop") or {}
    if any(loop.values()) or wall.get("outside_loop"):
        L += ([""] if L[-1] else []) + ["Effects in the loop: " + "; ".join(
            f"{a.upper()} {', '.join(e) or 'none'}" for a, e in loop.items())
            + (" (left out with --outside-loop: " + ", ".join(wall["outside_loop"]) + ")"
               if wall.get("outside_loop") else
               " (a latency or lag in the position path is in the loop, since the wall "
               "reads the same sensor; `--outside-loop EFFECT` leaves one out)") + "."]
    cert = wall["certificate"]
    if "k_robust_N_per_m" in cert.columns:
        L += ([""] if L[-1] else []) + [
              "Robust certificate of the nominal models against the fitted Wu "
              "(max |Wu T| < 1, T the complementary sensitivity seen by the arm's "
              "multiplicative uncertainty; `certificate.csv`), evaluated from the band's "
              "low edge up to the Nyquist frequency, Wu continued beyond its band, and "
              "capped at the smallest K_max of the trials it covers:", ""]
        for _, r in cert.iterrows():
            if math.isfinite(r["k_robust_N_per_m"]):
                why = {"member": f"capped at trial {r['limiting_member']} (its K_max)",
                       "weight beyond band": f"bound at {r['f_binding_hz']:.3g} Hz, above "
                                             "the weight's band",
                       "weight": f"bound at {r['f_binding_hz']:.3g} Hz",
                       "nominal K_max": "the nominal's own K_max"}.get(r["limited_by"], "")
                margin = r.get("beyond_margin", math.nan)
                check = ""
                if isinstance(margin, float) and math.isfinite(margin):
                    check = (f"; above the band the trials stay within "
                             f"{margin:.4f} × |Wu|" + ("" if margin <= 1 else
                                                       " — beyond the weight: the "
                                                       "assumption does not hold"))
                L.append(f"- {r['axis'].upper()}: holds for K up to "
                         f"{r['k_robust_N_per_m'] / 1e3:.3g} kN/m ({why}; peak at K = 0: "
                         f"{r['wu_t_peak_k0']:.2f}{check}).")
            else:
                L.append(f"- {r['axis'].upper()}: holds for no K at all (max |Wu T| is "
                         f"{r['wu_t_peak_k0']:.2f} > 1 already at K = 0, at "
                         f"{r['f_peak_k0_hz']:.3g} Hz).")
    return L + [""]
