"""The one-shot pipeline of ``armfit run``: raw trials in, every table, figure and a report out.

Each stage is a function of the typed results of the stages before it, the run's frozen
configuration (:class:`RunConfig`: inputs, options, the estimator's configuration, the
paper's fit bands, the folder written) and where its tasks run (the run's executor); it
returns a frozen result. :func:`run_pipeline` calls them in the order data flows, in
one straight function, and times each one (files written into OUTDIR in brackets):

- ingest: :func:`armfit.io.trials.ingest` (trials.parquet) → :class:`Ingested`;
- estimate: :func:`armfit.api.estimate_study_result` (spectra.parquet) →
  :class:`Estimated`, with the aggregates read back (levels mean and median);
- fit-grip, fit-nominal: :func:`armfit.fit_grip`, :func:`armfit.fit_nominal` of the
  paper's 5-parameter model (grip_params.csv/.tex, nominal_params.csv/.tex) →
  :class:`GripFits` (with the diagnosis it starts), :class:`NominalFits`;
- diagnose: :func:`armfit.diagnose` started from the grip fits (diagnosis.json), and
  the adopted model of each axis, :func:`armfit.adopt.adopt` (adoption.csv) →
  :class:`Diagnosed`;
- adopt, when an effect is adopted: Tables I and II again with the adopted model (the
  base model's move to grip_params_base.csv/.tex and nominal_params_base.csv/.tex) →
  :class:`Models`, the model every later stage uses (the base model's when nothing is
  adopted);
- fit-uncertainty: :func:`armfit.fit_uncertainty` of the adopted nominal (wu.csv,
  wu_summary.csv, wu_wmax.csv, wu.tex), with the same convergence policy as ``armfit
  fit-uncertainty`` → :class:`UncertaintyFit` (with the per-trial fits it starts);
- fit-trials: :func:`armfit.fitting.fit_trial_models` with the adopted model, one fit per
  trial, each started from its grip's fit (trial_params.csv) → :class:`TrialsFitted`;
- stability: :func:`armfit.loop.stability_table` of the per-trial fits at the
  defaults (stability.csv), the certificate of the nominal models against Wu capped by
  the trials (certificate.csv), and :func:`armfit.figures.stability_figure`
  (figures/stability.png) → :class:`StabilityChecked`;
- figures: Figs. 5–7 of :mod:`armfit.figures` (figures/bode.png, uncertainty.png,
  literature.png) → :class:`Drawn`;
- compare: :func:`armfit.compare` of each nominal model (base, adopted) with the
  medians (compare.csv) → :class:`Compared`;
- residuals: :func:`armfit.figures.residual_figure` per axis (figures/residual_<axis>.png)
  → :class:`Drawn`;
- report: :func:`armfit.report.report_markdown` (report.md) of a
  :class:`armfit.report.RunRecord` made of the results above and the configuration.

Everything after the diagnosis uses the adopted model (the base model where nothing is
adopted), so the products are computed once, from the model that survived the
diagnosis. With ``jobs`` > 1 :func:`run_pipeline` starts one pool of ``jobs`` worker
processes for the run (:func:`armfit.workers.process_pool`) and hands it to every stage.
Work that runs alongside later stages is a future returned by the stage that starts it
and passed to the stage that needs its result, which waits for it: the ingest stage
starts the estimate (it runs in the pool while this process ingests), the fit-grip
stage starts the diagnosis (in a thread of its own, its fits in the pool, alongside
Table II's), the fit-uncertainty stage starts the per-trial fits (in
the pool while this process fits Wu); the figures are drawn and written in the pool
while the later stages go on, and the report stage waits for them. Given an
``executor`` (e.g. a dask cluster's), the stages run their tasks on it instead, and the
figures are drawn here. With neither (jobs 1) a future runs when it is waited on. The
results depend on neither ``jobs`` nor the executor. If a stage fails, the pool's
pending tasks are cancelled and the futures still running are stopped before the error
propagates.

Every later stage reads the files the earlier ones wrote (as the subcommands do), so
``armfit run`` gives the same numbers as the subcommands run one after the other with
the same options. Of spectra.parquet the run keeps only the aggregates; a stage that
needs trial rows reads those of the kind it uses from the file
(:meth:`armfit.spectra.Spectra.read`, a row group at a time) and lets them go when it
ends, and a figure drawn in a worker process reads its rows there, so the memory of a
run hardly grows with the number of trials. The whole folder is built in a temporary
folder beside OUTDIR and renamed onto it at the end (:func:`armfit.io.atomic.atomic_path`):
a failure leaves no OUTDIR, and an existing OUTDIR (also one another run wrote
meanwhile) is replaced only with ``overwrite``.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import threading
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Generic, TypeVar

import numpy as np

from armfit import api
from armfit import uncertainty as wu
from armfit._order import median
from armfit.adopt import Adoption, adopt
from armfit.api import compare_frame
from armfit.constants import AXES, FORCE_LIMIT_N, GRID_HZ, PAPER_BANDS
from armfit.diagnosis import diagnose_axes
from armfit.errors import ArmfitError, OutputError
from armfit.fitting import TrialFit, fit_trial_models, grip_fit_starts, trial_fits_table
from armfit.htmlreport import report_html
from armfit.io.artifacts import write_params
from armfit.io.atomic import (
    atomic_path,
    check_length,
    check_output,
    resolved_path,
    write_text_atomic,
)
from armfit.io.schema import COMPARE_COLUMNS, wu_sidecar_paths
from armfit.io.trials import Warn, ingest, with_map
from armfit.loop import WallSettings, axis_summary, stability_table, subject_summary
from armfit.memory import release_memory
from armfit.models.params import ParamRows, read_param_rows
from armfit.report import STABILITY_FIGURE, RunRecord, Wall, report_markdown
from armfit.spectra import (
    EstimateAlongside,
    EstimateConfig,
    Spectra,
    StudySpectra,
    estimator_summary,
)
from armfit.workers import RUN_FIGURES_PRELOAD, cancel_pools, executor_for, giving_way

#: Figures written (``figures`` on), relative to OUTDIR; residual_<axis>.png per axis.
FIGURES = ("figures/bode.png", "figures/uncertainty.png", "figures/literature.png")

#: The virtual wall of the stability stage (the defaults: T = 1 ms, B = 0, d = 1), whose
#: damping the stability figure's sweeps keep.
_WALL = WallSettings()

#: Stage names, in the order they are reported (``adopt`` only when an effect is adopted,
#: ``figures`` and ``residuals`` only with figures on). With jobs > 1 the diagnosis runs
#: in the run's worker processes from the end of fit-grip on, alongside fit-nominal.
STAGES: tuple[str, ...] = ("ingest", "estimate", "fit-grip", "fit-nominal", "diagnose",
                           "adopt", "fit-uncertainty", "fit-trials", "stability",
                           "figures", "compare", "residuals", "drawing", "report")

__all__ = ["COMPARE_COLUMNS", "FIGURES", "STABILITY_FIGURE", "STAGES", "Background",
           "Compared", "Diagnosed", "Drawn", "Estimated", "GripFits", "Ingested", "Models",
           "NominalFits", "Reported", "RunConfig", "RunOptions", "RunResult", "StabilityChecked",
           "Stage", "StageResult", "TrialsFitted", "UncertaintyFit", "check_outdir",
           "compare_frame", "run", "run_pipeline"]

_T = TypeVar("_T")


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
    apparatus effects the stability loop leaves out (:func:`armfit.loop.loop_model`);
    column_map: the column map (CSV) of every raw file without one in the manifest
    (None: the files have armfit's own columns); force_limit_N: the device's peak force
    (N), reached forces are warned about and flagged as saturation; fmin, fmax: the
    frequency grid (Hz; a trial must last 2/fmin s); bands: fit bands (axis, lo, hi) in
    Hz that replace the paper's of their axis (:data:`armfit.constants.PAPER_BANDS`);
    reference: estimate through a trial's reference column when it has one.
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
    column_map: str | None = None
    force_limit_N: float = FORCE_LIMIT_N
    fmin: float = GRID_HZ[0]
    fmax: float = GRID_HZ[1]
    bands: tuple[tuple[str, float, float], ...] = ()
    reference: bool = True

    @property
    def fit_bands(self) -> dict[str, tuple[float, float]]:
        """{axis: (lo, hi) Hz}: the paper's bands, with :attr:`bands` in their place."""
        out = dict(PAPER_BANDS)
        out.update({a: (lo, hi) for a, lo, hi in self.bands})
        return out


@dataclass(frozen=True)
class Stage:
    """One finished stage: its name, the run's wall time spent on it (s: from the end of
    the stage before to its own end, so that the stages' times add up to the run's), a
    one-line summary, and, for a stage that started alongside earlier ones, its own wall
    time from its start (``alongside_s``; None otherwise)."""

    name: str
    seconds: float
    summary: str
    alongside_s: float | None = None

    def line(self) -> str:
        """The stage's progress line: ``estimate: 2.1 s — ...`` (and ``(ran 3.0 s, from
        alongside the stages before)`` for a stage that started earlier)."""
        extra = ("" if self.alongside_s is None else
                 f" (ran {self.alongside_s:.1f} s, started alongside the stages before)")
        return f"{self.name}: {self.seconds:.1f} s — {self.summary}{extra}"


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


# ---------------------------------------------------------------------------
# Entry point
# ---------------------------------------------------------------------------

def check_outdir(outdir: str | os.PathLike, inputs: Sequence[str | os.PathLike], *,
                 manifest: str | os.PathLike | None = None, overwrite: bool = False,
                 column_map: str | os.PathLike | None = None) -> Path:
    """Refuse an OUTDIR whose name or path is over the system's limits, that exists
    without ``overwrite``, is a file or a symbolic link, is or holds an input (replacing
    it would delete the input), could not be removed whole to be replaced, or whose
    folder cannot be written (:func:`armfit.io.atomic.check_output`). Raises OutputError
    (exit 73)."""
    out = check_length(outdir, folder=True)
    inputs = with_map(inputs, column_map)
    named = [*inputs, *([manifest] if manifest is not None else [])]
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder; give a folder for OUTDIR")
    out_res = resolved_path(out)
    for inp in named:
        inp_res = resolved_path(inp)
        if inp_res == out_res or out_res in inp_res.parents:
            raise OutputError(f"{out}: holds the input {inp}; choose another OUTDIR")
    check_output(out, overwrite=overwrite, inputs=inputs, manifest=manifest, folder=True)
    return out


def run_pipeline(inputs: Sequence[str | os.PathLike], outdir: str | os.PathLike,
                 options: RunOptions = RunOptions(), *, on_stage: OnStage | None = None,
                 warn: Warn | None = None, executor: Executor | None = None,
                 note: Warn | None = None) -> RunResult:
    """Run every stage on ``inputs`` (raw trial files, folders or a canonical dataset)
    and write the results into ``outdir``, atomically.

    The stages' tasks run on ``executor`` when given (a
    :class:`concurrent.futures.Executor`, used as is and never shut down; the figures are
    then drawn in this process, and after a failure the tasks it already runs finish
    first), else in one pool of ``options.jobs`` worker processes made for the run (none
    with jobs 1), the diagnosis's among them.

    ``on_stage(stage)`` is called after each stage (e.g. to print its time); ``warn``
    receives data warnings (saturation); ``note`` the conversions of each column map,
    once. Raises OutputError (exit 73) before any work
    if ``outdir`` cannot be written, and the error of the first failing stage otherwise
    (BadInputError 65, NoInputError 66, ConvergenceError 3, ...), leaving no new OUTDIR
    and an existing one untouched; a message naming a file of the temporary folder names
    it as it would have been in ``outdir``.
    """
    out = check_outdir(outdir, inputs, manifest=options.manifest, overwrite=options.overwrite,
                       column_map=options.column_map)
    tmp: Path | None = None
    try:
        with atomic_path(out, overwrite=options.overwrite, folder=True) as tmp:
            result = _run_in(list(inputs), tmp, options, on_stage=on_stage, warn=warn,
                             executor=executor, note=note, outdir=str(outdir))
    except ArmfitError as exc:
        # a message about a file of the temporary folder names it as it would be in OUTDIR
        text = str(exc)
        if tmp is None or str(tmp) not in text:
            raise
        renamed = type(exc)(text.replace(str(tmp), str(out)))
        renamed.skipped = exc.skipped
        raise renamed from exc
    return replace(result, outdir=str(out))


# ---------------------------------------------------------------------------
# What the stages share: the configuration, and where their work runs
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class RunConfig:
    """The configuration of one run, read by every stage.

    inputs: the inputs as given; folder: the (empty) folder the stages write into;
    options: the run's options; estimate: the estimator's configuration; bands: the
    paper's fit bands {axis: (lo, hi) Hz}, those of the base model's fits; warn:
    receives data warnings (None: they are dropped); note: receives the conversions of
    each column map, once (None: dropped); outdir: the output folder as given (what
    report.md's command line shows).
    """

    inputs: tuple[str | os.PathLike, ...]
    folder: Path
    options: RunOptions
    estimate: EstimateConfig
    bands: Mapping[str, tuple[float, float]]
    warn: Warn | None = None
    note: Warn | None = None
    outdir: str = "OUTDIR"

    def path(self, name: str) -> Path:
        """``folder / name``."""
        return self.folder / name


class Background(Generic[_T]):
    """A future: ``fn(*args, **kwargs)``, started now in a thread of its own when
    ``parallel`` (the thread mostly waits for worker processes, so the stages that do not
    need the result run meanwhile in this process) and collected by :meth:`result`; else
    it runs when collected. ``started`` is when it began (s, perf_counter)."""

    def __init__(self, parallel: bool, fn: Callable[..., _T], /, *args, **kwargs):
        self.call = (fn, args, kwargs)
        self.thread: ThreadPoolExecutor | None = None
        self.ident: int | None = None       # of the thread, once it runs
        self.started = time.perf_counter()
        if parallel:
            self.thread = ThreadPoolExecutor(max_workers=1)
            self.task = self.thread.submit(self._in_thread, fn, args, kwargs)

    def _in_thread(self, fn: Callable[..., _T], args, kwargs) -> _T:
        self.ident = threading.get_ident()
        return fn(*args, **kwargs)

    def result(self) -> _T:
        """The result, once the call has ended (its error if it failed). It is collected
        once: the future keeps no reference to it, nor to the call, once returned."""
        if self.thread is None:
            self.started = time.perf_counter()
            fn, args, kwargs = self.call
            self.call = None
            return fn(*args, **kwargs)
        try:
            value = self.task.result()
        finally:
            self.close()
        self.task = self.call = None
        return value

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


@dataclass(frozen=True)
class _Rows:
    """Responses of a spectra file to read where they are used (:meth:`Spectra.read` of
    ``path`` with ``level`` and ``kind``): a figure's trial rows are read by the worker
    that draws it, never held or sent by the run's own process."""

    path: Path
    level: tuple[str, ...]
    kind: str

    def read(self) -> Spectra:
        return Spectra.read(self.path, level=self.level, kind=self.kind, estimators=False)


def _draw_task(args) -> None:
    """Worker: draw the figure ``figures.<fn>(*args, **kwargs)`` and write it to ``path``
    (an argument that is a :class:`_Rows` is read first). :mod:`armfit.figures` (and
    matplotlib) is imported here, on first use, unless the worker has it already (the
    run's own pool preloads it: :data:`armfit.workers.RUN_FIGURES_PRELOAD`); the run's
    own process never imports it."""
    fn, fargs, kwargs, path = args
    fargs = tuple(a.read() if isinstance(a, _Rows) else a for a in fargs)
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


@dataclass(frozen=True)
class _Workers:
    """Where the stages' work runs: ``executor`` runs their tasks (None: here, in turn),
    ``later`` those no stage waits for soon (the per-trial fits; on the run's own pool
    they give way to the others: :func:`armfit.workers.giving_way`), ``drawings`` draws
    the figures (giving way too), and ``stack`` stops the background work still running
    when the run ends (:meth:`Background.stop`)."""

    executor: Executor | None
    later: Executor | None
    drawings: _Drawings
    stack: contextlib.ExitStack

    def start(self, fn: Callable[..., _T], /, *args, **kwargs) -> Background[_T]:
        """``fn(*args, **kwargs)`` as a :class:`Background` of the run (alongside the next
        stages when the run has an executor), stopped if the run fails first."""
        task = Background(self.executor is not None, fn, *args, **kwargs)
        self.stack.callback(task.stop)
        return task


# ---------------------------------------------------------------------------
# The stages' results
# ---------------------------------------------------------------------------

@dataclass(frozen=True, kw_only=True)
class StageResult:
    """What every stage returns besides its own results: the files it wrote (relative to
    OUTDIR), a one-line summary, and when it started if it ran alongside earlier stages
    (s, perf_counter; None: it started when the stage before it ended)."""

    files: tuple[str, ...] = ()
    summary: str = ""
    started: float | None = None


@dataclass(frozen=True)
class Ingested(StageResult):
    """ingest: trials validated into trials.parquet, those skipped (file, reason), and the
    estimate started alongside (a future of the study's spectra)."""

    n_trials: int
    skipped: tuple[tuple[str, str], ...]
    estimating: _Alongside


@dataclass(frozen=True)
class Estimated(StageResult):
    """estimate: the trials estimated, the aggregates of the measured responses (what
    the fits of Tables I and II use), every trial left out (ingest's, then the
    estimate's), and the aggregates of every kind made and spectra.parquet written (a
    future: :meth:`written` waits for it)."""

    n_trials: int
    measured: Spectra
    skipped: tuple[tuple[str, str], ...]
    writing: Background[Spectra]

    def written(self) -> Spectra:
        """Wait until spectra.parquet is written (its error if the write failed); the
        estimate's trial responses are let go then. Returns the aggregates of
        spectra.parquet (levels mean and median, every kind: the rows the file holds;
        the trial rows stay in the file, read by the stages that use them). Called
        once: the fit-grip stage hands them on (:attr:`GripFits.spectra`)."""
        spectra = self.writing.result()
        release_memory()
        return spectra


@dataclass(frozen=True)
class GripFits(StageResult):
    """fit-grip: Table I of the base model (as read back from grip_params.csv), the
    diagnosis started from it and the fits of Table II (futures), and the aggregates of
    spectra.parquet, written meanwhile (:meth:`Estimated.written`)."""

    grip: api.ModelFit
    diagnosing: Background[tuple]
    nominal: Background[api.ModelFit]
    spectra: Spectra


@dataclass(frozen=True)
class NominalFits(StageResult):
    """fit-nominal: Table II of the base model (as read back from nominal_params.csv)."""

    nominal: api.ModelFit


@dataclass(frozen=True)
class Diagnosed(StageResult):
    """diagnose: the diagnosis, the adopted model of each axis, {axis: the effects the
    search added, "+"-joined, or None} and {effects: axes} adopted."""

    diagnosis: api.Diagnosis
    adoption: Adoption
    missing: Mapping[str, str | None]
    refitted: Mapping[str, tuple[str, ...]]


@dataclass(frozen=True)
class Models(StageResult):
    """The model every stage after the diagnosis uses: Tables I and II (the adopted
    model's after adopt), the base model's when an effect is adopted, and the fit bands
    of ``grip`` and ``nominal``."""

    grip: api.ModelFit
    nominal: api.ModelFit
    bands: Mapping[str, tuple[float, float]]
    base_grip: api.ModelFit | None = None
    base_nominal: api.ModelFit | None = None
    #: The Wu fits the adopt stage started (None: the uncertainty stage starts them).
    weights: Background[_Weights] | None = None


@dataclass(frozen=True)
class UncertaintyFit(StageResult):
    """fit-uncertainty: W_max and Wu (Table III), and the per-trial fits started
    alongside (a future of :class:`_TrialFits`)."""

    uncertainty: api.Uncertainty
    trial_fits: Background[_TrialFits]


@dataclass(frozen=True)
class TrialsFitted(StageResult):
    """fit-trials: trial_params.csv written, and read back (``rows``: the population of
    the stability stage); the trials without a fit (who, reason), and the stability
    figure's sweeps being computed in the worker pool ({axis: future}; empty when the
    figure computes them itself)."""

    failed: tuple[tuple[str, str], ...]
    rows: ParamRows
    sweeps: Mapping[str, Future] = field(default_factory=dict)


@dataclass(frozen=True)
class StabilityChecked(StageResult):
    """stability: the stiffest stable wall of every trial's fit and the certificate;
    ``figure_task``: the stability figure being drawn once the worker pool has its
    sweeps (:func:`_draw_when_swept`), or None."""

    wall: Wall
    figure_task: Background[None] | None = None


@dataclass(frozen=True)
class Drawn(StageResult):
    """figures, residuals: the figures drawn (relative to OUTDIR; written once the
    drawing stage has waited for them)."""

    figures: tuple[str, ...] = ()


@dataclass(frozen=True)
class Compared(StageResult):
    """compare: each nominal model against the axis medians."""

    comparisons: api.Comparisons


@dataclass(frozen=True)
class Reported(StageResult):
    """report: report.md written (``files`` also lists the figures, written by then)."""


# ---------------------------------------------------------------------------
# The stages, in the order they run
# ---------------------------------------------------------------------------

def _ingest(config: RunConfig, workers: _Workers) -> Ingested:
    """Validate the raw trials once, into the canonical dataset (trials.parquet), and
    estimate each trial as it is read, meanwhile, in the worker processes: each trial
    file is read once (:class:`armfit.spectra.EstimateAlongside`). (Estimating from
    trials.parquet instead would wait for the dataset to be complete, when ingest ends:
    the two would run one after the other, and the run would take longer.)"""
    o = config.options
    estimating = _Alongside(config, workers)
    try:
        ing = ingest(list(config.inputs), config.path("trials.parquet"),
                     manifest=o.manifest, skip_bad=o.skip_bad, warn=config.warn,
                     column_map=o.column_map, force_limit_N=o.force_limit_N,
                     f_min_hz=o.fmin, note=config.note, on_open=estimating.open,
                     on_trial=estimating.add)
    except BaseException:
        estimating.close()
        raise
    # what reading the trials kept (Arrow's pages, returned only every few trials) and
    # the dataset writer's metadata of every row group, closed: given back before the
    # stages that hold the study's responses
    release_memory()
    skipped = tuple((s.file, s.reason) for s in ing.skipped)
    return Ingested(len(ing.trials), skipped, estimating, files=("trials.parquet",),
                    summary=f"{len(ing.trials)} trial(s)"
                    + (f", {len(skipped)} skipped" if skipped else ""))


class _Alongside:
    """The estimate of the trials ingest reads (:class:`EstimateAlongside`), started
    when ingest opens its inputs; a future of the study's spectra (:meth:`result`)."""

    def __init__(self, config: RunConfig, workers: _Workers):
        self.config, self.workers = config, workers
        self.started = time.perf_counter()
        self.along: EstimateAlongside | None = None

    def open(self, stream) -> None:
        o = self.config.options
        self.along = EstimateAlongside(stream, self.config.estimate, skip_bad=o.skip_bad,
                                       jobs=o.jobs, executor=self.workers.executor)

    def add(self, source, trial) -> None:
        self.along.add(source, trial)

    def result(self) -> StudySpectra:
        along, self.along = self.along, None
        return along.result()

    def close(self) -> None:
        if self.along is not None:
            self.along.close()


def _estimate(config: RunConfig, workers: _Workers, ingested: Ingested) -> Estimated:
    """Wait for the estimate ingest started (from the same inputs, so that a message
    names the user's files) and write spectra.parquet, in a thread of its own: the grip
    fits start meanwhile from the aggregates, the rows the file holds
    (:meth:`StudySpectra.aggregates`). The stages after them read the file's trial rows,
    as the subcommands do, once it is written (:meth:`Estimated.written`)."""
    est = ingested.estimating.result()
    started = ingested.estimating.started
    if config.warn is not None:     # what the estimators say of the force, per trial
        for line in estimator_summary(est.trials)["messages"]:
            config.warn(line)
    seen = {f for f, _ in ingested.skipped}
    skipped = ingested.skipped + tuple((f, r) for f, r in est.skipped if f not in seen)
    # the fits' rows first: they start from these while the other kinds' aggregates are
    # made, and the file written, in a thread (the workers waited about 0.1 s for all)
    measured = _without_records(est.aggregates(kinds=("measured",)))
    n_trials = len(est.trials)
    writing = workers.start(_aggregate_and_write, est, config.path("spectra.parquet"))
    del est   # held by the write until the file is written
    c = config.estimate
    return Estimated(n_trials, measured, skipped, writing, files=("spectra.parquet",),
                     started=started,
                     summary=f"{n_trials} trial(s), method {c.method}, "
                             f"{len(c.grid())} frequencies {c.fmin:g}-{c.fmax:g} Hz")


def _fit_base(which: str, config: RunConfig, workers: _Workers,
              spectra: Spectra) -> api.ModelFit:
    """The fits of Table I ("grip") or II ("nominal") of the base model."""
    fit = api.fit_grip if which == "grip" else api.fit_nominal
    return fit(spectra, cost=config.options.cost, bands=config.bands,
               jobs=config.options.jobs, executor=workers.executor)


def _params_csv(which: str, config: RunConfig, model: api.ModelFit) -> Path:
    """Table I ("grip") or II ("nominal") of the base model fitted (``model``) written as
    its params CSV (no pandas needed); its path."""
    path = config.path(f"{which}_params.csv")
    model.write(path)
    return path


def _table(which: str, config: RunConfig, model: api.ModelFit,
           spectra: Spectra) -> api.ModelFit:
    """The rest of Table I or II once its params CSV is written (:func:`_params_csv`):
    the warnings of its fits at a bound, its LaTeX table, and the table read back from
    the CSV, as the subcommands do."""
    _warn_at_bound(which, model, config.warn)
    write_text_atomic(config.path(f"{which}_params.tex"), model.latex())
    return replace(api.ModelFit.read(config.path(f"{which}_params.csv")),
                   fits=model.fits, spectra=spectra)


def _fit_summary(model: api.ModelFit, cost: str) -> str:
    return (f"{len(model.table)} fit(s), cost {cost}, median rms "
            f"{_median(model.table['rms_db']):.2f} dB")


def _diagnosis(path: Path, starts, executor: Executor | None) -> tuple:
    """The diagnosis's axes started from the grip fits ``starts`` (as grip_params.csv
    gives them: :attr:`armfit.api.ModelFit.start_rows`): the trial rows of the spectra
    file ``path``, read an axis at a time, its fits on the run's ``executor`` (here when
    it is None)."""
    axes_done = tuple(diagnose_axes(path, starts, executor=executor))
    release_memory()
    return axes_done


def _import_meanwhile(name: str) -> threading.Thread:
    """Import the module ``name`` in a thread of its own (returned, started) while this
    one waits for the workers; its first user imports it as ever (waiting for the import
    under way). A failure here is left to that user to report."""
    def load() -> None:
        with contextlib.suppress(Exception):
            importlib.import_module(name)

    thread = threading.Thread(target=load, daemon=True, name=f"armfit-import-{name}")
    thread.start()
    return thread


def _without_records(spectra: Spectra) -> Spectra:
    """``spectra`` without the per-trial records of its metadata: they are the file's (no
    stage uses them), and the aggregates the run holds to its end go without them (3 MB
    at 4,050 trials)."""
    return replace(spectra, meta={k: v for k, v in spectra.meta.items()
                                  if k != "estimators"})


def _aggregate_and_write(est: StudySpectra, path: Path) -> Spectra:
    """The aggregates of every kind (:meth:`StudySpectra.aggregates`; those made before
    are not made again), then spectra.parquet written: in one thread, which alone reads
    the trials' responses meanwhile."""
    spectra = _without_records(est.aggregates())
    est.write(path)
    return spectra


def _fit_grip(config: RunConfig, workers: _Workers, estimated: Estimated) -> GripFits:
    """Table I of the base model; the diagnosis starts from it at once, from
    spectra.parquet written. Table II's fits start as soon as Table I's are done, while
    Table I is written. Both run on the run's worker processes: the diagnosis's fits are
    handed to the pool as they become ready, after Table II's. A pool of the diagnosis's
    own, as ``armfit diagnose`` starts, adds two processes to the run's and gains no time
    on two cores: with one, a run of 81 trials took 3.04 s and peaked at 528 MB summed
    over its processes; without, 2.87 s and 422 MB."""
    measured = estimated.measured
    if workers.executor is not None:
        # Table I's DataFrame below needs pandas (about 0.4 s to import): loaded while
        # this process waits for the grip fits, not after them while the workers wait
        # (a run of 81 trials: 3 % shorter)
        _import_meanwhile("pandas")
    fitted = _fit_base("grip", config, workers, measured)
    nominal = workers.start(_fit_base, "nominal", config, workers, measured)
    # grip_params.csv first, and the diagnosis starts from it as read back (its base
    # parameters, read without pandas); Table I's warnings, LaTeX table and DataFrame
    # are made meanwhile. Made before the diagnosis started, they left the workers idle
    # once Table II's fits were done
    starts = api.ModelFit.read_starts(_params_csv("grip", config, fitted)).start_rows
    spectra = estimated.written()     # every later stage reads the file
    diagnosing = workers.start(_diagnosis, config.path("spectra.parquet"), starts,
                               workers.executor)
    grip = _table("grip", config, fitted, spectra)
    return GripFits(grip, diagnosing, nominal, spectra,
                    files=("grip_params.csv", "grip_params.tex"),
                    summary=_fit_summary(grip, config.options.cost))


def _fit_nominal(config: RunConfig, grip: GripFits, spectra: Spectra) -> NominalFits:
    """Table II of the base model, from the fits fit-grip started."""
    fitted = grip.nominal.result()
    _params_csv("nominal", config, fitted)
    nominal = _table("nominal", config, fitted, spectra)
    return NominalFits(nominal, files=("nominal_params.csv", "nominal_params.tex"),
                       started=grip.nominal.started,
                       summary=_fit_summary(nominal, config.options.cost))


def _diagnose(config: RunConfig, grip: GripFits) -> Diagnosed:
    """Wait for the diagnosis fit-grip started (diagnosis.json) and adopt the model of
    each axis (adoption.csv)."""
    # the aggregates are kept with it (all its plot needs)
    diagnosis = api.Diagnosis(grip.diagnosing.result(), grip.grip.spectra, grip.grip)
    diagnosis.write(config.path("diagnosis.json"))
    for d in diagnosis.axes:
        for c in d.failed_candidates:
            if config.warn is not None:
                config.warn(f"diagnose {d.axis}: candidate {c.effect} left out: {c.reason}")
    # every effect the stepwise search named on an axis, in order ("delay+lowpass")
    missing = {a: "+".join(names) or None for a, names in diagnosis.added.items()}
    adoption = adopt(diagnosis, config.options.adopt)
    text = adoption.to_frame().to_csv(index=False, float_format="%.10g",
                                      lineterminator="\n")
    write_text_atomic(config.path("adoption.csv"), text)
    files = ("diagnosis.json", "adoption.csv")
    if adoption.by_subject:     # effect values per subject: one row per value
        text = adoption.subjects_frame().to_csv(index=False, float_format="%.10g",
                                                lineterminator="\n")
        write_text_atomic(config.path("adoption_subjects.csv"), text)
        files += ("adoption_subjects.csv",)
    refitted: dict[str, tuple[str, ...]] = {}
    for a in adoption.axes:
        if a.adopted:
            key = "+".join(a.effects)
            refitted[key] = (*refitted.get(key, ()), a.axis)
    return Diagnosed(diagnosis, adoption, missing, refitted, files=files,
                     started=grip.diagnosing.started,
                     summary="; ".join(f"{a}: {e or 'no missing effect'}"
                                       for a, e in missing.items()))


def _base_models(config: RunConfig, grip: GripFits, nominal: NominalFits) -> Models:
    """The model of every later stage when nothing is adopted: the base model's."""
    return Models(grip.grip, nominal.nominal, config.bands)


def _adopt(config: RunConfig, workers: _Workers, spectra: Spectra, grip: GripFits,
           nominal: NominalFits, diagnosed: Diagnosed) -> Models:
    """Tables I and II again with the adopted model (the band of the diagnosis on the
    adopted axes, apparatus effects held at its joint fit); the base model's tables are
    kept as grip_params_base.csv/.tex and nominal_params_base.csv/.tex. Table II's fits
    run first: once it is written, its W_max is made and its Wu fits
    (:func:`_fit_weights`) start, queued behind Table I's fits, so that no worker waits
    for Table I's slowest fit."""
    ad, o = diagnosed.adoption, config.options
    files = []
    for which in ("grip", "nominal"):
        for ext in (".csv", ".tex"):
            os.replace(config.path(f"{which}_params{ext}"),
                       config.path(f"{which}_params_base{ext}"))
            files.append(f"{which}_params_base{ext}")
    refit: dict[str, api.ModelFit] = {}
    weights: list[Background[_Weights]] = []

    def on_table(which: str, model: api.ModelFit) -> None:
        _warn_at_bound(which, model, config.warn)
        model.write(config.path(f"{which}_params.csv"),
                    latex=config.path(f"{which}_params.tex"))
        refit[which] = replace(api.ModelFit.read(config.path(f"{which}_params.csv")),
                               fits=model.fits, spectra=spectra)
        if which == "nominal":
            weights.append(workers.start(_fit_weights, config, workers,
                                         _wmax(config, refit["nominal"], ad)))

    api.adopt_model(spectra, diagnosed.diagnosis, policy=ad.policy, cost=o.cost,
                    trials=False, jobs=o.jobs, executor=workers.executor,
                    on_table=on_table)
    return Models(refit["grip"], refit["nominal"], ad.bands, grip.grip, nominal.nominal,
                  weights=weights[0], files=tuple(files),
                  summary="; ".join(f"{' + '.join(ad[a].effects)} on {a}"
                                    for a in ad.adopted_axes))


def _effects_of(adoption: Adoption):
    """The fitters' ``effects`` of the adopted model ({axis: items}; () for none)."""
    return adoption.effects if adoption.anything else ()


def _fit_uncertainty(config: RunConfig, workers: _Workers, models: Models,
                     adoption: Adoption) -> UncertaintyFit:
    """W_max and Wu (Table III) of the adopted nominal, apparatus effects removed: wu.csv,
    wu_summary.csv, wu_wmax.csv, wu.tex (:func:`_wmax`, :func:`_fit_weights`; with an
    adopted model, started by the adopt stage as soon as its Table II was written). The
    per-trial fits start once W_max is made (their own read of the file's measured rows
    would otherwise overlap the derived rows) and run in the worker processes whenever
    the Wu fits leave one free (they give way: the stability stage needs both, and the
    Wu fits are the longer chain). The result is :func:`armfit.api.fit_uncertainty`'s,
    without the spectra."""
    o = config.options
    # with an adopted model the adopt stage has made W_max and started the Wu fits
    targets = _wmax(config, models.nominal, adoption) if models.weights is None else None
    # each trial's fit starts from its grip's fit, as `armfit fit-trials` does
    grip = models.grip
    starts = grip_fit_starts(zip(grip.table["axis"], grip.table["grip_N"], strict=True),
                             grip.fits)
    per_subject = {"subject_effects": adoption.subject_effects} if adoption.by_subject \
        else {}
    trial_fits = workers.start(_trial_fits, config, workers.drawings.pool,
                               config.path("spectra.parquet"), cost=o.cost,
                               jobs=o.jobs, source="spectra.parquet", starts=starts,
                               bands=models.bands, effects=_effects_of(adoption),
                               executor=workers.later, **per_subject)
    done = (_fit_weights(config, workers, targets) if models.weights is None
            else models.weights.result())
    unc = done.uncertainty
    return UncertaintyFit(unc, trial_fits, files=done.files,
                          summary=", ".join(f"{r.axis}: {r.result.order} pair(s)"
                                            for r in unc.axes) + f", cost {o.wu_cost}")


@dataclass(frozen=True)
class _Targets:
    """W_max of each axis (:func:`armfit.uncertainty.wmax_targets`), the notes on the
    weights, and the nominal model and per-subject effect values they were made with."""

    targets: list
    notes: list
    nominal: api.ModelFit
    by_subject: Mapping


@dataclass(frozen=True)
class _Weights:
    """Wu fitted (Table III) and the files it was written to."""

    uncertainty: api.Uncertainty
    files: tuple[str, ...]


def _wmax(config: RunConfig, nominal: api.ModelFit, adoption: Adoption) -> _Targets:
    """W_max (eq. 6) of ``nominal`` and the notes on the weights, from the derived trial
    rows of spectra.parquet, read here and let go at once: the Wu fits need W_max only,
    and the trial fits' read never overlaps them."""
    by_subject = adoption.by_subject
    # the responses only: W_max (eq. 6) uses no other value of the rows, and the values
    # would more than double what the rows hold
    derived = Spectra.read(config.path("spectra.parquet"), level="trial", kind="derived",
                           values=(), estimators=False)
    # W_max (eq. 6) and the notes are all that is made of the derived rows, and then
    # they are let go: the Wu fits and the trial fits' read never hold them (13 MB at
    # 4,050 trials)
    targets = wu.wmax_targets(derived, nominal.table, source=nominal.source,
                              by_subject=by_subject)
    notes = wu.weight_axis_notes(derived, nominal.table, spectra_label=derived.source,
                                 params_label=nominal.source)
    del derived
    release_memory()
    return _Targets(targets, notes, nominal, by_subject)


def _fit_weights(config: RunConfig, workers: _Workers, made: _Targets) -> _Weights:
    """Wu (eq. 7) fitted to the W_max of :func:`_wmax` on the run's workers, written as
    wu.csv (and its side files) and wu.tex."""
    o = config.options
    results = wu.fit_targets(made.targets, cost=o.wu_cost, jobs=o.jobs,
                             executor=workers.executor)
    wu.require_converged(results, o.wu_cost)
    unc = api.Uncertainty(tuple(results), o.wu_cost, None, None, made.nominal,
                          tuple(made.notes), dict(made.by_subject or {}))
    wu_path = config.path("wu.csv")
    unc.write(wu_path, latex=config.path("wu.tex"))
    return _Weights(unc, ("wu.csv", *(p.name for p in wu_sidecar_paths(wu_path)), "wu.tex"))


@dataclass(frozen=True)
class _TrialFits:
    """The per-trial fits, trial_params.csv written and read back, and the stability
    figure's sweeps started on the worker pool (see :class:`TrialsFitted`)."""

    fits: list[TrialFit]
    rows: ParamRows
    sweeps: Mapping[str, Future]


def _trial_fits(config: RunConfig, pool: Executor | None, spectra: Path,
                **kwargs) -> _TrialFits:
    """:func:`armfit.fitting.fit_trial_models` of ``spectra``, written to
    trial_params.csv and read back (the rows the stability stage analyses, as
    ``armfit stability`` reads the file); with figures and a worker pool of the run's
    own, the stability figure's sweep of each axis (:func:`_sweep_task`, the figure's
    costliest part: a K_max per model, servo rate and delay) starts on it at once."""
    fits = fit_trial_models(spectra, **kwargs)
    release_memory()
    path = config.path("trial_params.csv")
    write_params(trial_fits_table(fits), path)
    read = read_param_rows(str(path))
    sweeps: dict[str, Future] = {}
    if config.options.figures and pool is not None:
        rows = read.table
        for axis in AXES:
            sel = rows[rows["axis"] == axis]
            if len(sel):
                sweeps[axis] = pool.submit(_sweep_task, (sel, _WALL,
                                                         tuple(config.options.outside_loop)))
    return _TrialFits(fits, read, sweeps)


def _sweep_task(args) -> np.ndarray:
    """Worker: :func:`armfit.figures.stability_sweep` of one axis's rows (imported here,
    as :func:`_draw_task` imports the figures)."""
    rows, settings, outside_loop = args
    return importlib.import_module("armfit.figures").stability_sweep(
        rows, settings, outside_loop=outside_loop)


def _fit_trials(config: RunConfig, uncertainty: UncertaintyFit) -> TrialsFitted:
    """Wait for the per-trial fits fit-uncertainty started (trial_params.csv): the
    population the stability stage uses."""
    done = uncertainty.trial_fits.result()
    fits = done.fits
    failed = tuple((f"{t.axis} {t.subject} {t.grip_N:g} N", t.reason) for t in fits
                   if t.fit is None)
    return TrialsFitted(failed, done.rows, files=("trial_params.csv",), sweeps=done.sweeps,
                     started=uncertainty.trial_fits.started,
                     summary=f"{len(fits) - len(failed)} trial fit(s)"
                     + (f", {len(failed)} failed" if failed else ""))


def _stability(config: RunConfig, workers: _Workers, models: Models, adoption: Adoption,
               uncertainty: api.Uncertainty, trials: TrialsFitted) -> StabilityChecked:
    """The stiffest stable virtual wall of every trial's fit at the defaults
    (stability.csv), the certificate of the nominal models against the fitted Wu, capped
    by the trials it covers (certificate.csv), K_max of the base and adopted nominal
    models, and the stability figure."""
    settings = _WALL
    loop = config.options.outside_loop
    rows = trials.rows
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        table = stability_table(rows.table, settings, source="trial_params.csv",
                                outside_loop=loop)
    text = table.to_csv(index=False, float_format="%.10g", lineterminator="\n")
    write_text_atomic(config.path("stability.csv"), text)
    summary = axis_summary(table)
    wu_summary = uncertainty.summary()
    bands = {}
    for _, r in wu_summary[(wu_summary["weight"] == "fitted")
                           & (wu_summary["target"] == "wmax")].iterrows():
        bands[r["axis"]] = (float(r["band_lo_hz"]), float(r["band_hi_hz"]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        cert = stability_table(models.nominal.table, settings, weights=uncertainty.weights,
                               weights_band_hz=bands, outside_loop=loop,
                               members=rows.table,
                               members_k_max=table["k_max_N_per_m"].to_numpy(float))
        base = None
        if models.base_nominal is not None:
            base = stability_table(models.base_nominal.table, settings)
    text = cert.to_csv(index=False, float_format="%.10g", lineterminator="\n")
    write_text_atomic(config.path("certificate.csv"), text)
    figure = task = None
    # the figure is drawn from this stage's own table (stability.csv), not a recomputed one
    drawn = api.Stability(table=table, settings=settings, models=rows.table,
                          outside_loop=tuple(loop))
    if config.options.figures and trials.sweeps:
        # drawn in the worker pool as soon as it has the sweeps, ahead of the figures
        # still waiting (they give way): the run's last dependency, and a long drawing
        figure = STABILITY_FIGURE
        task = workers.start(_draw_when_swept, workers.executor, trials.sweeps,
                             ("stability_figure", (drawn,), {}, config.folder / figure))
    elif config.options.figures:
        # listed after the paper's and the residual figures (see _report)
        figure = workers.drawings.draw(config.folder, STABILITY_FIGURE, "stability_figure",
                                       drawn)
    per_subject = subject_summary(table)
    wall = Wall(settings=settings, summary=summary, failed=trials.failed, certificate=cert,
                warnings=tuple(str(w.message) for w in caught), figure=figure,
                n_models=len(table), base_nominal=base,
                in_loop=_loop_effects(adoption, loop), outside_loop=tuple(loop),
                by_subject={a: per_subject[a] for a in adoption.by_subject
                            if a in per_subject})
    return StabilityChecked(wall, files=("stability.csv", "certificate.csv"),
                            figure_task=task,
                     summary="; ".join(f"{a}: K_max min {s['k_max_min_N_per_m'] / 1e3:.3g} "
                                       "kN/m" for a, s in summary.items())
                     + (f"; {figure}" if figure else ""))


def _loop_effects(adoption: Adoption, outside: Sequence[str]) -> dict[str, tuple[str, ...]]:
    """{axis: the adopted effects inside the stability loop}."""
    drop = set(outside)
    return {a.axis: tuple(e for e in a.effects if e not in drop) for a in adoption.axes}


def _figures(config: RunConfig, workers: _Workers, spectra: Spectra, models: Models,
             uncertainty: api.Uncertainty) -> Drawn:
    """The paper's Figs. 5-7 (they need no diagnosis): Fig. 5 (bode: measured dynamics
    with the grip fits, all axes), Fig. 6 (derived dynamics, nominal H_ARM, W_max and
    |Wu|) and Fig. 7 (the X axis 1 N H_ARM, else the first grip fit, against Table IV)."""
    config.path("figures").mkdir(exist_ok=True)  # the stability figure may be there
    grip, draw, folder = models.grip.table, workers.drawings.draw, config.folder
    rows = grip[(grip["axis"] == "x") & np.isclose(grip["grip_N"].to_numpy(float), 1.0)]
    path = config.path("spectra.parquet")
    paper = (draw(folder, FIGURES[0], "bode_figure",
                  _Rows(path, ("trial", "mean"), "measured"), grip),
             draw(folder, FIGURES[1], "uncertainty_figure", _Rows(path, ("trial",), "derived"),
                  models.nominal.table, uncertainty.weights,
                  **({"by_subject": uncertainty.by_subject} if uncertainty.by_subject
                     else {})),
             draw(folder, FIGURES[2], "literature_figure",
                  (rows if len(rows) else grip).iloc[0]))
    return Drawn(figures=paper, summary=f"{len(paper)} figure(s): Figs. 5, 6, 7")


def _compare(config: RunConfig, spectra: Spectra, models: Models,
             adoption: Adoption) -> Compared:
    """Each nominal model (base, and adopted where it differs) against the axis medians
    (compare.csv)."""
    base = models.base_nominal or models.nominal
    rows = list(api.compare(spectra, base, level="median").rows)
    if models.base_nominal is not None:
        nominal = models.nominal
        adopted = nominal.table[nominal.table["axis"].isin(adoption.adopted_axes)]
        rows += api.compare(spectra, replace(nominal, table=adopted), level="median").rows
    comparisons = api.Comparisons(tuple(rows), "median")
    comparisons.write(config.path("compare.csv"))
    return Compared(comparisons, files=("compare.csv",),
                    summary=f"{len(rows)} model(s) x axis against the medians")


def _residuals(config: RunConfig, workers: _Workers, spectra: Spectra, models: Models,
               diagnosed: Diagnosed) -> Drawn:
    """One residual figure per diagnosed axis (they need the diagnosis and the refits):
    the base nominal model solid, the adopted nominal model dashed where it differs,
    shaded where the solid curve leaves the noise band (as `armfit plot residual`
    shades)."""
    base = (models.base_nominal or models.nominal).table
    adopted = diagnosed.adoption.adopted_axes
    out = []
    for d in sorted(diagnosed.diagnosis.axes, key=lambda d: d.axis):
        out.append(workers.drawings.draw(config.folder, f"figures/residual_{d.axis}.png",
                                         "residual_figure", spectra, base,
                                         models.nominal.table if d.axis in adopted else None,
                                         axis=d.axis))
    return Drawn(figures=tuple(out), summary=f"{len(out)} figure(s)")


def _draw_when_swept(pool: Executor, sweeps: Mapping[str, Future], task: tuple) -> None:
    """In a thread of the run: wait for the stability figure's sweeps, then have the
    worker pool draw the figure ``task`` (:func:`_draw_task`) from them, and wait for it.
    Sent to the pool itself as soon as the sweeps are done, the drawing runs ahead of the
    figures that still wait (:attr:`_Workers.later`)."""
    fn, args, kwargs, path = task
    done = {axis: fut.result() for axis, fut in sweeps.items()}
    pool.submit(_draw_task, (fn, args, {**kwargs, "sweeps": done}, path)).result()


def _drawing(workers: _Workers, paper: Drawn, residuals: Drawn,
             stability: StabilityChecked) -> Drawn:
    """Wait for the figures the worker pool draws alongside the stages (Figs. 5-7, the
    residual figures and the stability figure)."""
    if stability.figure_task is not None:
        stability.figure_task.result()
    workers.drawings.wait()
    n = len(paper.figures) + len(residuals.figures) + bool(stability.wall.figure)
    return Drawn(summary=f"{n} figure(s) drawn")


def _report(config: RunConfig, written: Sequence[str],
            estimated: Estimated, diagnosed: Diagnosed, models: Models,
            uncertainty: api.Uncertainty, stability: StabilityChecked, compared: Compared,
            drawn: Sequence[str]) -> Reported:
    """Write report.md and report.html from the results above and the configuration they
    used (``written``: the files of the stages before; every figure is written by then:
    the drawing stage waited for them)."""
    wall = stability.wall
    figures = (*drawn, *((wall.figure,) if wall.figure else ()))
    record = RunRecord(
        inputs=tuple(str(p) for p in config.inputs), outdir=config.outdir,
        options=config.options,
        config=config.estimate, n_trials=estimated.n_trials,
        skipped=estimated.skipped, grip=models.grip, nominal=models.nominal,
        base_grip=models.base_grip, base_nominal=models.base_nominal, bands=models.bands,
        uncertainty=uncertainty, diagnosis=diagnosed.diagnosis,
        adoption=diagnosed.adoption, comparisons=compared.comparisons, wall=wall,
        figures=figures, files=(*written, *figures, "report.md", "report.html"))
    text = report_markdown(record)
    write_text_atomic(config.path("report.md"), text)
    write_text_atomic(config.path("report.html"), report_html(text, config.folder))
    return Reported(files=(*figures, "report.md", "report.html"),
                    summary="report.md, report.html")


# ---------------------------------------------------------------------------
# The run: the stages in order, timed
# ---------------------------------------------------------------------------

R = TypeVar("R", bound=StageResult)


class _Clock:
    """Times stages and reports each one as it finishes: a stage's time is the run's wall
    time from the end of the previous stage to its own end (the times add up to the
    run's); a stage that started earlier, alongside others, also has its own duration.
    Keeps the files the stages wrote."""

    def __init__(self, on_stage: OnStage | None):
        self.stages: list[Stage] = []
        self.files: list[str] = []
        self.on_stage = on_stage
        self.start = self.t0 = time.perf_counter()

    def done(self, name: str, result: R) -> R:
        """Record the stage ``name`` that returned ``result``; returns ``result``."""
        now = time.perf_counter()
        alongside = (now - result.started if result.started is not None
                     and result.started < self.t0 else None)
        stage = Stage(name, now - self.t0, result.summary, alongside)
        self.stages.append(stage)
        self.files += result.files
        self.t0 = now
        # what the stage freed goes back to the system before the next one: this process
        # keeps up to 128 MiB of freed memory otherwise (armfit.workers.tune_allocator),
        # and the later stages would peak on top of it (`armfit run` of 4,050 trials: the
        # stability stage's peak summed over the processes fell from 381 to 366 MB)
        release_memory()
        if self.on_stage is not None:
            self.on_stage(stage)
        return result

    def wall(self) -> float:
        return time.perf_counter() - self.start


def _run_in(inputs: list, folder: Path, options: RunOptions, *,
            on_stage: OnStage | None, warn: Warn | None,
            executor: Executor | None = None, note: Warn | None = None,
            outdir: str = "OUTDIR") -> RunResult:
    config = RunConfig(tuple(inputs), folder, options,
                       EstimateConfig(method=options.method, fmin=options.fmin,
                                      fmax=options.fmax, force_limit_N=options.force_limit_N,
                                      reference=options.reference),
                       options.fit_bands, warn, note, outdir)
    # the caller's executor, or one pool of worker processes for every stage of the run
    # (its workers start with every engine module imported: workers.PRELOAD, and with
    # figures the figures' module too, imported once by the fork server)
    preload = RUN_FIGURES_PRELOAD if options.figures else ()
    with executor_for(executor, options.jobs, preload=preload) as pool, \
            contextlib.ExitStack() as stack:
        own = pool is not None and pool is not executor
        later = giving_way(pool)
        workers = _Workers(pool, later, _Drawings(later if own else None), stack)
        try:
            return _stages(config, workers, _Clock(on_stage))
        except BaseException:
            if own:   # the background stages stop at their next task
                pool.shutdown(wait=True, cancel_futures=True)
            raise


def _stages(config: RunConfig, workers: _Workers, clock: _Clock) -> RunResult:
    """Every stage of :data:`STAGES`, in order, each given the results it needs."""
    figures = config.options.figures
    ingested = clock.done("ingest", _ingest(config, workers))
    estimated = clock.done("estimate", _estimate(config, workers, ingested))
    grip = clock.done("fit-grip", _fit_grip(config, workers, estimated))
    spectra = grip.spectra
    nominal = clock.done("fit-nominal", _fit_nominal(config, grip, spectra))
    diagnosed = clock.done("diagnose", _diagnose(config, grip))
    adoption = diagnosed.adoption
    models = (clock.done("adopt", _adopt(config, workers, spectra, grip, nominal, diagnosed))
              if adoption.anything else _base_models(config, grip, nominal))
    unc = clock.done("fit-uncertainty",
                     _fit_uncertainty(config, workers, models, adoption))
    trials = clock.done("fit-trials", _fit_trials(config, unc))
    stability = clock.done("stability", _stability(config, workers, models, adoption,
                                                   unc.uncertainty, trials))
    paper = (clock.done("figures", _figures(config, workers, spectra, models,
                                            unc.uncertainty)) if figures else Drawn())
    compared = clock.done("compare", _compare(config, spectra, models, adoption))
    residuals = (clock.done("residuals", _residuals(config, workers, spectra, models,
                                                    diagnosed)) if figures else Drawn())
    if figures:
        clock.done("drawing", _drawing(workers, paper, residuals, stability))
    clock.done("report", _report(config, tuple(clock.files), estimated, diagnosed,
                                 models, unc.uncertainty, stability, compared,
                                 (*paper.figures, *residuals.figures)))
    return RunResult(outdir=str(config.folder), files=tuple(sorted(clock.files)),
                     trials=estimated.n_trials, skipped=estimated.skipped,
                     verdicts={d.axis: d.verdict for d in diagnosed.diagnosis.axes},
                     missing=diagnosed.missing, refitted=diagnosed.refitted,
                     adoption=adoption, stages=tuple(clock.stages), wall_s=clock.wall())


def run(inputs, outdir, *, manifest=None, skip_bad: bool = False, method: str = "h1",
        cost: str = "complex", wu_cost: str = "envelope", jobs: int = 1,
        figures: bool = True, overwrite: bool = False, adopt: str = "auto",
        outside_loop: Sequence[str] = (), on_stage: OnStage | None = None,
        warn: Warn | None = None, executor: Executor | None = None,
        column_map=None, force_limit_N: float = FORCE_LIMIT_N,
        fmin: float = GRID_HZ[0], fmax: float = GRID_HZ[1],
        bands: Mapping[str, tuple[float, float]] | None = None,
        note: Warn | None = None, reference: bool = True) -> RunResult:
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
    column_map : path, optional
        Column map (CSV) of every raw file without one of its own in the manifest
        (see :func:`armfit.read_trials`).
    force_limit_N : float
        The device's peak force, N: forces reaching it are warned about and flagged
        ``saturation``.
    fmin, fmax : float
        The frequency grid, Hz (see :func:`armfit.estimate`); a trial must last 2/fmin s.
    bands : dict, optional
        Fit band per axis {axis: (lo, hi)} in Hz, in place of the paper's (x, y 0.1–30
        Hz, z 0.1–10 Hz) for the axes it names.
    note : callable, optional
        Receives, once per distinct column map, the conversions it makes.
    reference : bool
        Estimate X/F through a trial's reference column when it has one (False: H1
        whatever the trials hold; see :func:`armfit.estimate`).

    Returns
    -------
    RunResult
    """
    items = [inputs] if isinstance(inputs, str | os.PathLike) else list(inputs)
    options = RunOptions(manifest=manifest, skip_bad=skip_bad, method=method, cost=cost,
                         wu_cost=wu_cost, jobs=jobs, figures=figures, overwrite=overwrite,
                         adopt=adopt, outside_loop=tuple(outside_loop),
                         column_map=None if column_map is None else str(column_map),
                         force_limit_N=force_limit_N, fmin=fmin, fmax=fmax,
                         bands=tuple((a, float(lo), float(hi))
                                     for a, (lo, hi) in (bands or {}).items()),
                         reference=reference)
    return run_pipeline(items, outdir, options, on_stage=on_stage, warn=warn,
                        executor=executor, note=note)

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



def _median(values) -> float:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(median(v)) if v.size else float("nan")
