"""The public Python API: every stage of armfit as a function returning a typed result.

Each function below is what the subcommand of the same name does, without the command
line: it takes arrays, result objects or paths, and returns a frozen result object with
``to_frame()`` (a pandas DataFrame), ``write(path, overwrite=False)`` (the same files the
command writes) and, where a figure fits, ``plot(ax=None)``. The command line
(:mod:`armfit.cli`) only parses options, calls these functions and writes their results.

Example (from the repository root)::

    import armfit
    s = armfit.estimate("sample_data/study")     # Spectra
    m = armfit.fit_nominal(s)                    # ModelFit (Table II)
    d = armfit.diagnose(s, m)                    # Diagnosis
    print(d.to_frame())
    print(m.to_frame()[["axis", "Ma", "k1", "k2", "b1", "b2"]])

Equations cited are those of Fu & Çavuşoğlu, ICRA 2010 (see docs/methods.md).
"""

from __future__ import annotations

import html
import importlib
import json
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from armfit._lazy import loaded
from armfit.constants import AXES
from armfit.diagnosis.tuning import MAX_STEPS, MIN_EFFECT_DB, MIN_EFFECT_DEG
from armfit.errors import BadInputError, UsageError
from armfit.io.artifacts import RowTable as _RowTable
from armfit.io.atomic import atomic_outputs, atomic_path, write_text_atomic
from armfit.io.rawwrite import trial_filename, write_trial
from armfit.io.schema import COMPARE_COLUMNS, json_default, wu_sidecar_paths
from armfit.io.trials import Skipped, Trial, Warn, open_trials, write_dataset
from armfit.models.effects import Effect, get_effect
from armfit.spectra import EstimateConfig, Spectra, StudySpectra, estimate_study, estimate_trials


class _OnFirstUse:
    """A module imported when one of its attributes is first asked for.

    The stages below need pandas, scipy.optimize, the fitting and diagnosis stacks, the
    loop and the simulator, but each command needs only some of them: ``armfit estimate``
    of one trial should not pay for loading the fitting stack (a shell script calls it
    once per file). Importing is thread-safe (the import system's locks).
    """

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, attr: str):
        return getattr(importlib.import_module(self._name), attr)

    def __repr__(self) -> str:
        return f"<module {self._name!r}, imported on first use>"


pd = _OnFirstUse("pandas")
_adopt = _OnFirstUse("armfit.adopt")
_artifacts = _OnFirstUse("armfit.io.artifacts")
_diagnosis = _OnFirstUse("armfit.diagnosis")
_export = _OnFirstUse("armfit.export")
_fitting = _OnFirstUse("armfit.fitting")
_loop = _OnFirstUse("armfit.loop")
_params = _OnFirstUse("armfit.models.params")
_simulation = _OnFirstUse("armfit.simulation")
_tables = _OnFirstUse("armfit.tables")
_uncertainty = _OnFirstUse("armfit.uncertainty")

PathLike = str | os.PathLike
#: A band in Hz: one (lo, hi) for every axis, or {axis: (lo, hi)}.
_Band = tuple[float, float] | Mapping[str, tuple[float, float]]


def _figures():
    """:mod:`armfit.figures`, imported on first use: matplotlib takes a while to load, and
    only the ``plot`` methods need it."""
    return importlib.import_module("armfit.figures")


def _effects(effects: Iterable[Effect | str] | None) -> list[Effect]:
    """Effects given as objects or library names."""
    return [get_effect(e) if isinstance(e, str) else e for e in (effects or ())]


def _fit_effects(effects):
    """The fitters' ``effects`` as given: a mapping {axis: items} (one model per axis, as
    :attr:`armfit.adopt.Adoption.effects`), or items for every axis — an Effect, its
    name, ``"NAME=VALUES"`` or (effect, {param: value}) to hold an effect's parameters
    (:func:`armfit.models.effects.resolve_effects`)."""
    if isinstance(effects, AdoptedModel):
        return effects.adoption.effects
    adopt = loaded("armfit.adopt")   # not imported: no Adoption was made
    if adopt is not None and isinstance(effects, adopt.Adoption):
        return effects.effects
    if isinstance(effects, Mapping):
        return {a: list(v) for a, v in effects.items()}
    return [e for e in (effects or ())]


# ---------------------------------------------------------------------------
# Notebook display and figures of one axis
# ---------------------------------------------------------------------------

#: Rows of a result's table shown by its notebook display (``_repr_html_``).
HTML_ROWS = 6
#: Columns of that table (the others are elided).
HTML_COLUMNS = 10


class _HtmlTable:
    """A compact HTML display for notebooks (``_repr_html_``): a one-line summary and the
    first :data:`HTML_ROWS` rows of ``to_frame()``, all text escaped."""

    def _html_summary(self) -> str:
        return type(self).__name__

    def _repr_html_(self) -> str:
        frame = self.to_frame()
        head = frame.head(HTML_ROWS).to_html(escape=True, max_cols=HTML_COLUMNS,
                                             index=False, border=0, float_format="{:.4g}".format)
        more = f" ({len(frame) - HTML_ROWS} more rows)" if len(frame) > HTML_ROWS else ""
        return (f"<div><p><b>{html.escape(type(self).__name__)}</b>: "
                f"{html.escape(self._html_summary())}{html.escape(more)}</p>{head}</div>")


def _new_axes(n: int):
    """A new matplotlib Figure (Agg canvas, no pyplot) with ``n`` panels one above the
    other; returns (figure, list of Axes)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    fig = Figure(figsize=(5.0, 1.9 * n + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    return fig, list(fig.subplots(n, 1, squeeze=False)[:, 0])


def _one_axis(axis: str | None, have: Sequence[str]) -> str | None:
    """``axis`` checked against the axes a result holds (``have``); None when not
    given and the result holds several."""
    if axis is not None:
        if axis not in AXES:
            raise UsageError(f"axis must be x, y or z, got {axis!r}")
        if axis not in have:
            raise UsageError(f"no axis {axis} here (axes: {', '.join(have) or 'none'})")
        return axis
    return have[0] if len(have) == 1 else None


def _panel_targets(ax, panel: str | None, names: Sequence[str], groups: Mapping[str, tuple],
                   single: str) -> tuple[object, dict]:
    """(figure or None, {panel name: Axes or None}) for a ``plot(axis, ax, panel)``.

    ``names``: the panels a result draws, top to bottom; ``groups``: names that stand
    for several (e.g. "both": magnitude and phase); ``single``: the panel a lone Axes
    gets. ``ax`` None: a new figure with the panels asked for; one Axes: one panel; a
    sequence of Axes: as many panels, in order ("both" for two)."""
    given = None if ax is None else (list(ax) if isinstance(ax, Sequence | np.ndarray)
                                     else [ax])
    if panel is None:
        n = len(names) if given is None else len(given)
        panel = single if n == 1 else next(
            (g for g, members in groups.items() if len(members) == n), "")
    wanted = groups.get(panel) or ((panel,) if panel in names else None)
    if not wanted:
        raise UsageError(f"panel must be one of {', '.join([*names, *groups])}, "
                         f"got {panel!r}")
    fig = None
    if given is None:
        fig, given = _new_axes(len(wanted))
    if len(given) != len(wanted):
        raise UsageError(f"panel {panel!r} draws {len(wanted)} panel(s); "
                         f"give as many Axes, got {len(given)}")
    targets = dict.fromkeys(names)
    targets.update(zip(wanted, given, strict=True))
    return fig, targets


def _label_panels(targets: Mapping[str, object], labels: Mapping[str, str],
                  entries: Mapping) -> None:
    """Y labels of the panels drawn, the x label of the lowest, and a legend of
    ``entries`` (artists or (handle, label) pairs) on the first."""
    drawn = [(name, a) for name, a in targets.items() if a is not None]
    for name, a in drawn:
        a.set_ylabel(labels.get(name, ""))
    if drawn and "x" in labels:
        drawn[-1][1].set_xlabel(labels["x"])
        pairs = [e if isinstance(e, tuple) else (e, e.get_label()) for e in entries.values()]
        pairs = [p for p in pairs if not isinstance(p[1], str) or p[1]]
        if pairs:
            drawn[0][1].legend([h for h, _ in pairs], [t for _, t in pairs], fontsize=6)


# ---------------------------------------------------------------------------
# Trials
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Trials(_HtmlTable):
    """Raw trials read and validated against the trial contract (docs/formats.md).

    Attributes
    ----------
    trials : tuple of armfit.io.trials.Trial
        The trials kept, in the order found.
    skipped : tuple of armfit.io.trials.Skipped
        Trials left out with ``skip_bad`` (file and reason).
    ignored : tuple of str
        Files found that are not trials.
    """

    trials: tuple[Trial, ...]
    skipped: tuple[Skipped, ...] = ()
    ignored: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.trials)

    def __iter__(self):
        return iter(self.trials)

    def to_frame(self) -> pd.DataFrame:
        """One row per trial: subject, axis, grip_N (N), run, fs (Hz), n_samples,
        duration_s (s), t0_s (s), source."""
        return pd.DataFrame(
            [{"subject": t.meta.subject, "axis": t.meta.axis, "grip_N": t.meta.grip_N,
              "run": t.meta.run, "fs": t.meta.fs, "n_samples": t.meta.n_samples,
              "duration_s": t.meta.duration_s, "t0_s": t.meta.t0_s, "source": t.meta.source}
             for t in self.trials],
            columns=["subject", "axis", "grip_N", "run", "fs", "n_samples", "duration_s",
                     "t0_s", "source"])

    def write(self, path: PathLike, *, overwrite: bool = False) -> Path:
        """Write the canonical dataset ``armfit ingest`` writes (Parquet), atomically."""
        write_dataset(self.trials, path, overwrite=overwrite)
        return Path(path)


def read_trials(paths: PathLike | Sequence[PathLike], *, manifest: PathLike | None = None,
                skip_bad: bool = False, resample: bool = False,
                f_min_hz: float = EstimateConfig.fmin,
                force_limit_N: float = EstimateConfig.force_limit_N,
                warn: Warn | None = None, column_map: PathLike | None = None,
                note: Warn | None = None) -> Trials:
    """Read raw trial files, folders or a canonical dataset into memory.

    Parameters
    ----------
    paths : path or sequence of paths
        Trial files (CSV, CSV.gz, Parquet) named ``sub-<s>_axis-<a>_grip-<g>N...``,
        folders holding them, or a dataset written by ``armfit ingest``.
    manifest : path, optional
        CSV with columns file, subject, axis, grip_N[, run][, map] (paths relative to
        it; ``map``: the column map of the row's file).
    skip_bad : bool
        Leave bad trials out (listed in ``skipped``) instead of raising.
    resample : bool
        Resample trials of another sampling rate to the most common one.
    f_min_hz : float
        Lowest frequency to be estimated, Hz: a trial must last at least 2/f_min_hz s.
    force_limit_N : float
        Device peak force, N; forces reaching it are warned about (saturation).
    warn : callable, optional
        Receives data warnings (saturation, resampling).
    column_map : path, optional
        Column map (CSV, see docs/formats.md) of every raw file without one of its own in
        the manifest: which of its columns or MATLAB variables are time, force and
        position, and in which units; needed for a MATLAB ``.mat`` file.
    note : callable, optional
        Receives, once per distinct column map, the conversions it makes.

    Returns
    -------
    Trials

    Raises
    ------
    NoInputError
        Nothing found.
    BadInputError
        A trial breaks the contract (without ``skip_bad``).
    """
    inputs = [paths] if isinstance(paths, str | os.PathLike) else list(paths)
    stream = open_trials(inputs, manifest=manifest, skip_bad=skip_bad, resample=resample,
                         f_min_hz=f_min_hz, force_limit_N=force_limit_N, warn=warn,
                         column_map=column_map, note=note)
    trials = tuple(stream)
    return Trials(trials, tuple(stream.skipped), tuple(str(p) for p in stream.ignored))


# ---------------------------------------------------------------------------
# Spectra
# ---------------------------------------------------------------------------

def estimate_config(*, method: str = EstimateConfig.method,
                    fmin: float = EstimateConfig.fmin, fmax: float = EstimateConfig.fmax,
                    per_decade: int = EstimateConfig.per_decade,
                    nperseg: int | None = None, overlap: float = EstimateConfig.overlap,
                    window: str = EstimateConfig.window,
                    mp: Mapping[str, float] | None = None,
                    coherence_min: float = EstimateConfig.coherence_min,
                    force_limit_N: float = EstimateConfig.force_limit_N,
                    reference: bool = EstimateConfig.reference
                    ) -> EstimateConfig:
    """The estimator options of :func:`estimate` as an :class:`EstimateConfig`
    (frequencies in Hz, masses in kg, forces in N; see :func:`estimate`)."""
    kw = {} if mp is None else {"mp": dict(mp)}
    return EstimateConfig(method=method, fmin=fmin, fmax=fmax, per_decade=per_decade,
                          nperseg=nperseg, overlap=overlap, window=window,
                          coherence_min=coherence_min, force_limit_N=force_limit_N,
                          reference=reference, **kw)


def estimate_study_result(source, config: EstimateConfig | None = None, *,
                          manifest: PathLike | None = None, skip_bad: bool = False,
                          jobs: int = 1, on_open: Callable[[int], object] | None = None,
                          advance: Callable[[], object] | None = None,
                          warn: Warn | None = None,
                          executor: Executor | None = None,
                          column_map: PathLike | None = None,
                          note: Warn | None = None) -> StudySpectra:
    """:func:`estimate` with everything it found: the spectra, the trials kept, the
    trials skipped and files ignored, the sampling rate and data warnings.

    ``source`` and the options are those of :func:`estimate`; ``on_open(n)`` is told the
    number of trials found and ``advance()`` called once per trial (for progress bars);
    ``executor`` as in :func:`estimate` (trials in memory are estimated here).
    """
    config = config or EstimateConfig()
    if isinstance(source, Trials) or (isinstance(source, Sequence)
                                      and source and isinstance(source[0], Trial)):
        return estimate_trials(list(source), config)
    if isinstance(source, str | os.PathLike):
        source = [source]
    return estimate_study(list(source), config, manifest=manifest, skip_bad=skip_bad,
                          jobs=jobs, on_open=on_open, advance=advance, warn=warn,
                          executor=executor, column_map=column_map, note=note)


def estimate(source, *, method: str = EstimateConfig.method,
             fmin: float = EstimateConfig.fmin, fmax: float = EstimateConfig.fmax,
             per_decade: int = EstimateConfig.per_decade, nperseg: int | None = None,
             overlap: float = EstimateConfig.overlap, window: str = EstimateConfig.window,
             mp: Mapping[str, float] | None = None,
             coherence_min: float = EstimateConfig.coherence_min,
             force_limit_N: float = EstimateConfig.force_limit_N,
             reference: bool = EstimateConfig.reference,
             manifest: PathLike | None = None, skip_bad: bool = False, jobs: int = 1,
             warn: Warn | None = None, executor: Executor | None = None,
             column_map: PathLike | None = None, note: Warn | None = None) -> Spectra:
    """Frequency responses of every trial, and their mean per axis × grip and median per
    axis (``armfit estimate``).

    Parameters
    ----------
    source : path, sequence of paths, Trials or sequence of Trial
        Raw trial files or folders, an ``armfit ingest`` dataset, or trials in memory.
    method : {'h1', 'chebwin'}
        Measured-dynamics estimator X/F: Welch H1, or the paper's whole-record FFT
        ratio with 100 dB Chebyshev windows.
    fmin, fmax : float
        Grid range, Hz (fmax at most the Nyquist frequency).
    per_decade : int
        Log-spaced grid points per decade.
    nperseg : int, optional
        H1 segment length, samples (default: a power of 2 lasting >= 2/fmin s).
    overlap : float
        H1 segment overlap, fraction 0…<1.
    window : str
        H1 window (scipy.signal.get_window name).
    mp : dict, optional
        Device mass per axis, kg, for the derived arm dynamics Xa/Fa with
        Fa = F − Mp·ẍ (eqs. 1–2); default the paper's.
    coherence_min : float
        Points of lower coherence are flagged ``low_coherence``.
    force_limit_N : float
        Device peak force, N; trials reaching it are flagged ``saturation``.
    reference : bool
        With ``method`` 'h1', estimate X/F through a trial's reference column
        (``ref_<a>_N``, a commanded force, or ``ref_<a>_m``, a reference trajectory) when
        it has one: S_xr/S_Fr, unbiased where the force is noisy or responds to the
        position (method ``ref``); False: H1 whatever the trials hold. Either way the
        spectra hold the alternative estimates (kind ``alternative``: H2, and H1 beside
        a reference estimate) and flag ``not_excitation`` where H1 is biased
        (docs/methods.md, "Is the force the excitation?").
    manifest : path, optional
        Trial manifest CSV.
    skip_bad : bool
        Leave bad trials out (listed in ``meta["skipped"]``) instead of raising.
    jobs : int
        Worker processes (one trial file each).
    warn : callable, optional
        Receives data warnings.
    executor : concurrent.futures.Executor, optional
        Estimates the trial files instead of ``jobs`` worker processes: a process pool of yours, or
        a ``dask.distributed`` client's ``client.get_executor()`` (used as is, never shut
        down; see :mod:`armfit.workers`). The result does not depend on it.
        Each task reads its trial file itself: on a cluster, give paths every machine
        can read.
    column_map : path, optional
        Column map of every raw file without one of its own (see :func:`read_trials`).
    note : callable, optional
        Receives, once per distinct column map, the conversions it makes.

    Returns
    -------
    Spectra
        Every response as responses × frequency arrays, with the file's metadata;
        ``.write(path)`` writes what ``armfit estimate -o path`` writes.
    """
    config = estimate_config(method=method, fmin=fmin, fmax=fmax, per_decade=per_decade,
                             nperseg=nperseg, overlap=overlap, window=window, mp=mp,
                             coherence_min=coherence_min, force_limit_N=force_limit_N,
                             reference=reference)
    return estimate_study_result(source, config, manifest=manifest, skip_bad=skip_bad,
                                 jobs=jobs, warn=warn, executor=executor,
                                 column_map=column_map, note=note).spectra


def read_spectra(path: PathLike) -> Spectra:
    """Read a spectra file written by ``armfit estimate`` (:meth:`Spectra.read`)."""
    return Spectra.read(path)


def _spectra(spectra) -> Spectra:
    if isinstance(spectra, str | os.PathLike):
        return Spectra.read(spectra)
    return Spectra.of(spectra)


# ---------------------------------------------------------------------------
# Arm-model fits (Tables I and II)
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class _ParamsFile:
    """A params file whose base parameters are read (``starts``) and whose table is
    read by :func:`armfit.models.params.read_params` when first asked for."""

    path: Path
    starts: _params.FitStarts

    def to_frame(self) -> pd.DataFrame:
        return _params.read_params(self.path)


@dataclass(frozen=True, eq=False)
class ModelFit(_HtmlTable):
    """Fitted arm models: one row per axis (nominal, Table II) or axis × grip (Table I).

    Attributes
    ----------
    table : pandas.DataFrame
        The params-file table (columns of :func:`armfit.io.schema.params_columns`):
        parameters in SI units (kg, N/m, N·s/m), 95 % intervals, fit statistics.
    which : {'grip', 'nominal'}
    fits : tuple of armfit.fitting.FitResult
        The fits behind the rows (empty for a model read from a file).
    spectra : Spectra or None
        What was fitted (for :meth:`plot`).
    source : str or None
        The file the model was read from.

    Notes
    -----
    A fit's ``table`` becomes a DataFrame when first asked for: :meth:`write` writes
    the rows without pandas (a third of a second to import), as `armfit fit-nominal`
    does.
    """

    table: pd.DataFrame
    which: str
    fits: tuple = ()
    spectra: Spectra | None = None
    source: str | None = None

    def __getattribute__(self, name: str):
        value = object.__getattribute__(self, name)
        if name == "table" and isinstance(value, _RowTable | _ParamsFile):  # on first use
            value = value.to_frame()
            object.__setattr__(self, "table", value)
        return value

    @classmethod
    def read(cls, path: PathLike) -> ModelFit:
        """A params CSV written by fit-grip or fit-nominal."""
        table = _params.read_params(path)
        return cls(table, "grip" if "grip_N" in table.columns else "nominal",
                   source=str(path))

    @classmethod
    def read_starts(cls, path: PathLike) -> ModelFit:
        """:meth:`read`, for a caller that may need only the base parameters
        (:attr:`start_rows`): a plain file of base-model fits is read without pandas
        (:func:`armfit.models.params.fit_starts`), and its ``table`` is read by
        :meth:`read`'s reader when first asked for (the same DataFrame). Any other file
        is read by :meth:`read` at once (the same checks and messages)."""
        starts = _params.fit_starts(path)
        if starts is None:
            return cls.read(path)
        return cls(_ParamsFile(Path(path), starts), "grip" if starts.grip else "nominal",
                   source=str(path))

    @property
    def start_rows(self):
        """The rows the diagnosis starts its fits from: ``table``, or, while a model
        read by :meth:`read_starts` has not made it, the file's base parameters
        (:class:`armfit.models.params.FitStarts`)."""
        value = object.__getattribute__(self, "table")
        return value.starts if isinstance(value, _ParamsFile) else self.table

    @classmethod
    def of(cls, model) -> ModelFit:
        """``model`` itself, a params DataFrame, or a params file's path, as a ModelFit.

        A DataFrame gets the checks of a params file
        (:func:`armfit.models.params.check_param_rows`): BadInputError (exit 65) naming
        the column and row of a value outside its physical range or a second row of a
        model."""
        if isinstance(model, cls):
            return model
        if isinstance(model, str | os.PathLike):
            return cls.read(model)
        table = _checked_rows(model)
        return cls(table, "grip" if "grip_N" in table.columns else "nominal")

    def to_frame(self) -> pd.DataFrame:
        """The params table (a copy): the rows of the CSV ``write`` writes."""
        return self.table.copy()

    def latex(self) -> str:
        """A booktabs LaTeX table laid out like the paper's Table I or II, with intervals."""
        caption = _tables.caption_for(self.which, [f.ci_method for f in self.fits])
        return _tables.latex_table(self.table, ci=True, caption=caption,
                                   label=f"tab:{self.which}")

    def write(self, path: PathLike, *, overwrite: bool = False,
              latex: PathLike | None = None) -> Path:
        """Write the params CSV (and with ``latex`` the LaTeX table): the files of
        ``armfit fit-grip`` / ``fit-nominal``, committed together (both or neither,
        :func:`armfit.io.atomic.atomic_outputs`)."""
        with atomic_outputs(overwrite=overwrite):
            _artifacts.write_params(object.__getattribute__(self, "table"), path,
                                    overwrite=overwrite)
            if latex is not None:
                write_text_atomic(latex, self.latex(), overwrite=overwrite)
        return Path(path)

    def axes(self) -> list[str]:
        """The axes with a model row, in x, y, z order."""
        return [a for a in AXES if (self.table["axis"] == a).any()]

    def plot(self, axis: str | None = None, ax=None, *, panel: str | None = None):
        """The Bode pair of one axis: the fitted spectra (single trials, grip means with
        their spread) and these models — the paper's Fig. 5 for that axis.

        Parameters
        ----------
        axis : {'x', 'y', 'z'}, optional
            The axis to draw; default the only one, or with ``ax`` None every axis
            (the whole Fig. 5).
        ax : matplotlib Axes or sequence of two, optional
            Draw on these: one Axes draws one panel (``panel``, default the
            magnitude), two draw magnitude and phase. Default: a new figure.
        panel : {'magnitude', 'phase', 'both'}, optional

        Returns
        -------
        matplotlib.figure.Figure or the ``ax`` given
            Without ``ax``, a new figure (:func:`armfit.figures.bode_figure` when both
            panels and spectra are there); else ``ax``, drawn on.
        """
        figures = _figures()
        one = _one_axis(axis, self.axes())
        if ax is None and panel in (None, "both") and self.spectra is not None:
            return figures.bode_figure(self.spectra, self.table, axis=one)
        if one is None:
            raise UsageError(f"this fit holds axes {', '.join(self.axes())}: choose one "
                             "with axis=")
        fig, t = _panel_targets(ax, panel, ("magnitude", "phase"),
                                {"both": ("magnitude", "phase")}, "magnitude")
        entries = figures.bode_axes(t["magnitude"], t["phase"], self.spectra, self.table,
                                    axis=one)
        _label_panels(t, {"magnitude": figures.MAG_LABEL, "phase": figures.PHASE_LABEL,
                          "x": figures.FREQ_LABEL}, entries)
        return fig if ax is None else ax

    def _html_summary(self) -> str:
        return (f"{self.which} fits, {len(self.table)} row(s), axes "
                f"{', '.join(self.axes()) or 'none'}"
                + (f", from {self.source}" if self.source else ""))

    def row_for(self, axis: str, grip: float | None = None):
        """The params row of ``axis`` (a nominal fit, ``grip`` None) or of ``axis`` and
        ``grip`` (N, a grip fit), as a pandas Series. UsageError naming the rows there
        are when there is none."""
        if axis not in AXES:
            raise UsageError(f"axis must be x, y or z, got {axis!r}")
        t = self.table
        is_grip = "grip_N" in t.columns
        if grip is None and is_grip:
            grips = ", ".join(f"{g:g}" for g in t.loc[t["axis"] == axis, "grip_N"])
            raise UsageError(f"these are grip fits (Table I): give grip= one of {grips or 'none'} "
                             f"N for axis {axis}; the nominal model is fit_nominal's")
        if grip is not None and not is_grip:
            raise UsageError("these are nominal fits (Table II, one per axis): give no grip=")
        mask = (t["axis"] == axis).to_numpy(copy=True)
        if grip is not None:
            mask &= np.isclose(t["grip_N"].to_numpy(float), float(grip), rtol=1e-9, atol=0)
        if not mask.any():
            have = ", ".join(_export.model_prefix(a, g) for a, g in zip(
                t["axis"], t["grip_N"] if is_grip else [None] * len(t), strict=True))
            raise UsageError(f"no model of axis {axis}"
                             + ("" if grip is None else f", grip {float(grip):g} N")
                             + f" (the models: {have or 'none'})")
        return t[mask].iloc[0]

    def to_control(self, axis: str, grip: float | None = None, *,
                   kind: str = "closed_loop", pade_order: int | None = None,
                   exact: bool = False, omega=None):
        """A model as a python-control system (the optional extra ``armfit[control]``).

        ``kind='closed_loop'``: the measured dynamics X/F of eq. 4, device and arm with
        every effect of the row, m/N (what the spectra measure and
        :meth:`armfit.ClosedLoopModel.response` evaluates); ``kind='arm'``: the arm's
        own H_ARM (eq. 3) with the arm effects of the row (what Wu multiplies). Each
        effect's rational form (eq. R1 of :mod:`armfit.models.effects`) enters exactly
        (a low-pass, a resonance, a device's mass or damping); a latency (the output
        delays, summed, T) becomes the [n/n] Padé approximant of e^(−sT),
        n = ``pade_order`` (``control.pade``), and a delay inside an impedance (a
        reflex) the same approximant (:func:`armfit.export.rational_model`).

        Padé error: the approximant is all-pass, so the magnitude is exact; the phase
        lags that of e^(−jωT) by less than c_n (ωT)^(2n+1) rad, c_n = (n!)²/((2n)!
        (2n+1)!) (:func:`armfit.export.pade_phase_bound_deg`). For n = 6: below 2e-5°
        while ωT ≤ 3 (a 12 ms latency up to 40 Hz, beyond the paper's 30 Hz band),
        below 0.1° while ωT ≤ 6.2, below 1° while ωT ≤ 7.7; raise n for a longer delay
        or a wider band, or take ``exact=True``.

        Parameters
        ----------
        axis : {'x', 'y', 'z'}
        grip : float, optional
            None: the nominal model (a fit_nominal result); a grip force (N): that grip's
            fit (a fit_grip result).
        kind : {'closed_loop', 'arm'}
        pade_order : int, optional
            n of the Padé approximants (default :data:`armfit.export.PADE_ORDER`, 6).
        exact : bool
            Return the exact response, delays included, as ``FrequencyResponseData``
            instead of a transfer function: what :meth:`armfit.ClosedLoopModel.response`
            (or ``arm_response``) gives, also for an effect that declares no rational form.
        omega : array_like, optional
            With ``exact``: the frequencies, rad/s. Default: the grid of the spectra the
            model was fitted to, else armfit's default grid (0.1–30 Hz, 40 per decade).

        Returns
        -------
        control.TransferFunction or control.FrequencyResponseData
            Input ``F``, output the axis (m/N). Its ``name`` is ``<m>_<kind>`` (``<m>``:
            ``x``, or ``x_grip2N``; a decimal point written ``p``), with ``_pade<n>``
            appended when a Padé approximant stands for a delay and ``_exact`` for the
            exact response; the attribute ``armfit_delays`` holds ``{"delay_s": T,
            "inner_delays_s": (...), "pade_order": n}`` (delays in s; T and the inner
            delays are the approximated ones, none with ``exact``).

        Raises
        ------
        UsageError
            python-control is not installed (one line: ``pip install armfit[control]``);
            no such row; an unknown ``kind``; an effect without a rational form
            (without ``exact``: the message points to ``exact=True``).
        """
        from armfit._lazy import import_extra

        control = import_extra("control", "control", "ModelFit.to_control")
        n = _export.PADE_ORDER if pade_order is None else pade_order
        row = self.row_for(axis, grip)
        model, theta = _params.model_from_params(row)
        g = None if "grip_N" not in row.index else float(row["grip_N"])
        base = f"{_export.model_prefix(axis, g)}_{kind}"
        if kind not in _export.KINDS:
            raise UsageError(f"kind must be one of {', '.join(_export.KINDS)}, got {kind!r}")
        if exact:
            w = self._omega(omega)
            f_hz = w / (2 * np.pi)
            h = model.response(f_hz, theta) if kind == "closed_loop" \
                else model.arm_response(f_hz, theta)
            sys = control.frd(h, w, name=f"{base}_exact", inputs=["F"], outputs=[axis])
            sys.armfit_delays = {"delay_s": 0.0, "inner_delays_s": (), "pade_order": None}
            return sys
        if omega is not None:
            raise UsageError("omega= is for exact=True (a transfer function has no grid)")
        rm = _export.rational_model(
            model, theta, kind=kind, pade_order=n, what=base,
            hint="take to_control(..., exact=True) for its exact frequency response "
                 "(FrequencyResponseData)")
        num, den = rm.num, rm.den
        if rm.delay_s > 0:
            pn, pd = control.pade(rm.delay_s, int(n))
            num, den = np.polymul(num, pn), np.polymul(den, pd)
        approx = rm.delay_s > 0 or bool(rm.inner_delays_s)
        sys = control.tf(num, den, name=base + (f"_pade{int(n)}" if approx else ""),
                         inputs=["F"], outputs=[axis])
        sys.armfit_delays = {"delay_s": rm.delay_s, "inner_delays_s": rm.inner_delays_s,
                             "pade_order": int(n) if approx else None}
        return sys

    def _omega(self, omega) -> np.ndarray:
        """The frequencies (rad/s) of an exact response: ``omega``, else the fitted
        spectra's grid, else the default grid."""
        if omega is not None:
            w = np.atleast_1d(np.asarray(omega, dtype=float))
            if w.ndim != 1 or w.size == 0 or not (np.isfinite(w).all() and (w > 0).all()):
                raise UsageError("omega must be frequencies > 0 rad/s")
            return w
        f = self.spectra.freq_hz if self.spectra is not None else EstimateConfig().grid()
        return 2 * np.pi * np.asarray(f, dtype=float)


def _checked_rows(table: pd.DataFrame, *, keep_row: bool = False) -> pd.DataFrame:
    """A params table given as a DataFrame, with the checks of a params file
    (:func:`armfit.models.params.check_param_rows`: BadInputError naming column and
    row); every row must hold a fit. ``keep_row``: keep the ``row`` column."""
    rows = _params.check_param_rows(table)
    if rows.skipped:
        row, who, why = rows.skipped[0]
        raise BadInputError(f"a row without parameters ({who}: {why})", column="Ma",
                            row=row)
    return rows.table if keep_row else rows.table.drop(columns="row")


def _fit(which: str, spectra, *, cost: str, bands, effects, bootstrap: int, seed,
         method, max_nfev, on_fit, jobs: int, executor: Executor | None = None) -> ModelFit:
    (model,) = _table_fits((which,), spectra, cost=cost, bands=bands, effects=effects,
                           bootstrap=bootstrap, seed=seed, method=method,
                           max_nfev=max_nfev, on_fit=on_fit, jobs=jobs, executor=executor)
    return model


def _table_fits(whiches: Sequence[str], spectra, *, effects, **kwargs) -> Iterator[ModelFit]:
    """The :class:`ModelFit` of each of ``whiches`` ("grip", "nominal"), yielded as each
    is done, every fit handed to the workers at once in this order
    (:func:`armfit.fitting.fit_studies`; ``kwargs``: its options)."""
    sp = _spectra(spectra)
    for study in _fitting.fit_studies(sp, whiches, effects=_fit_effects(effects), **kwargs):
        yield ModelFit(study.row_table(), study.which, study.fits, sp)


def fit_grip(spectra, *, cost: str = "complex",
             bands: Mapping[str, tuple[float, float]] | None = None,
             effects: Iterable[Effect | str] = (), bootstrap: int = 0, seed: int | None = 0,
             method: str | None = None, max_nfev: int | None = None,
             on_fit: Callable | None = None, jobs: int = 1,
             executor: Executor | None = None) -> ModelFit:
    """Fit the closed loop H_CL (eq. 4) to each axis × grip mean (Table I, ``armfit
    fit-grip``).

    Parameters
    ----------
    spectra : Spectra or path
        From :func:`estimate` or a spectra file.
    cost : {'complex', 'paper'}
        'complex': dB and phase errors over their standard errors; 'paper': dB error
        only (eq. 5, unit weights).
    bands : dict, optional
        Fit band per axis {axis: (lo, hi)} in Hz; default x, y 0.1–30 Hz, z 0.1–10 Hz.
    effects : sequence of Effect or str
        Physical effects added to the model (see :data:`armfit.EFFECTS`).
    bootstrap : int
        Subject resamples for percentile intervals (0: intervals from the Jacobian).
    seed : int, optional
        Seed of the resampling.
    method : str, optional
        Estimator to fit when the spectra hold several.
    max_nfev : int, optional
        Evaluation budget of each final local fit (default 200 per parameter).
    on_fit : callable, optional
        ``on_fit(axis, grip, FitResult)`` after each fit.
    jobs : int
        Worker processes (one aggregate each); the result does not depend on it.
    executor : concurrent.futures.Executor, optional
        Runs the tasks instead of ``jobs`` worker processes: a process pool of yours, or
        a ``dask.distributed`` client's ``client.get_executor()`` (used as is, never shut
        down; see :mod:`armfit.workers`). The result does not depend on it.

    Returns
    -------
    ModelFit

    Raises
    ------
    ConvergenceError
        A fit did not converge (nothing is returned).
    """
    return _fit("grip", spectra, cost=cost, bands=bands, effects=effects,
                bootstrap=bootstrap, seed=seed, method=method, max_nfev=max_nfev,
                on_fit=on_fit, jobs=jobs, executor=executor)


def fit_nominal(spectra, *, cost: str = "complex",
                bands: Mapping[str, tuple[float, float]] | None = None,
                effects: Iterable[Effect | str] = (), bootstrap: int = 0,
                seed: int | None = 0, method: str | None = None,
                max_nfev: int | None = None, on_fit: Callable | None = None,
                jobs: int = 1, executor: Executor | None = None) -> ModelFit:
    """Fit H_CL (eq. 4) to each axis median over all trials (Table II, ``armfit
    fit-nominal``). Parameters as :func:`fit_grip`.

    Returns
    -------
    ModelFit
        One row per axis; ``to_frame()`` has the columns of the CSV ``armfit
        fit-nominal`` writes (axis, Ma, k1, k2, b1, b2, intervals, statistics).
    """
    return _fit("nominal", spectra, cost=cost, bands=bands, effects=effects,
                bootstrap=bootstrap, seed=seed, method=method, max_nfev=max_nfev,
                on_fit=on_fit, jobs=jobs, executor=executor)


def read_model(path: PathLike) -> ModelFit:
    """Read a params CSV written by fit-grip or fit-nominal (:meth:`ModelFit.read`)."""
    return ModelFit.read(path)


# ---------------------------------------------------------------------------
# Uncertainty weights (Table III)
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Uncertainty(_HtmlTable):
    """W_max (eq. 6) and the fitted weight Wu (eq. 7) of every axis.

    Attributes
    ----------
    axes : tuple of armfit.uncertainty.AxisUncertainty
        Per axis: grid, W_max (raw and target), band, trials, fitted weight, checks.
    cost : {'envelope', 'paper'}
    smooth_oct : float or None
        Smoothing of W_max, octaves.
    spectra, nominal : Spectra, ModelFit
        The inputs (for :meth:`plot`).
    notes : tuple of str
        The axes left out, in sentences (:func:`armfit.uncertainty.weight_axis_notes`):
        derived trials without a nominal row, or a nominal row without derived trials.
    by_subject : dict
        {axis: {subject: {``effect.param``: value}}}: effect values per subject with
        which each trial's apparatus effects were removed (empty: the nominal row's).
    """

    axes: tuple[_uncertainty.AxisUncertainty, ...]
    cost: str
    smooth_oct: float | None = None
    spectra: Spectra | None = None
    nominal: ModelFit | None = None
    notes: tuple[str, ...] = ()
    by_subject: Mapping[str, Mapping[str, Mapping[str, float]]] = field(default_factory=dict)

    @property
    def weights(self) -> dict[str, _uncertainty.WuWeight]:
        """{axis: WuWeight}, the fitted weights."""
        return {r.axis: r.result.weight for r in self.axes}

    def to_frame(self) -> pd.DataFrame:
        """The Wu table (axis, kind, index, real, imag; the layout of Table III)."""
        return _artifacts.wu_frame(self.weights)

    def summary(self) -> pd.DataFrame:
        """Coverage (%) and tightness (dB) per axis × weight × target."""
        return _uncertainty.summary_table(list(self.axes), smooth_oct=self.smooth_oct)

    def points(self) -> pd.DataFrame:
        """W_max, target and |Wu| in dB at every grid frequency, per axis."""
        return _uncertainty.points_table(list(self.axes))

    def write(self, path: PathLike, *, overwrite: bool = False,
              latex: PathLike | None = None) -> tuple[Path, ...]:
        """Write the files of ``armfit fit-uncertainty``: the Wu CSV, ``<stem>_summary.csv``
        and ``<stem>_wmax.csv`` beside it (and with ``latex`` a Table III-style table),
        committed together (all or none, :func:`armfit.io.atomic.atomic_outputs`).
        Returns the paths written."""
        summary_path, points_path = wu_sidecar_paths(path)
        out = (Path(path), summary_path, points_path)
        with atomic_outputs(overwrite=overwrite):
            _artifacts.write_wu(self.weights, path, overwrite=overwrite)
            _artifacts.write_wu_table(self.summary(), summary_path, overwrite=overwrite)
            _artifacts.write_wu_table(self.points(), points_path, overwrite=overwrite)
            if latex is not None:
                write_text_atomic(latex, _tables.wu_latex(self.weights), overwrite=overwrite)
                out += (Path(latex),)
        return out

    def to_control(self, axis: str):
        """Wu of ``axis`` as a python-control ``TransferFunction`` (the optional extra
        ``armfit[control]``), built from its zeros, poles and gain:
        Wu(s) = K Π(s − z)/Π(s − p) (eq. 7, s in rad/s; ``control.zpk``), stable and
        minimum phase as armfit fits it. Named ``Wu_<axis>``.

        Raises
        ------
        UsageError
            python-control is not installed (``pip install armfit[control]``), or no
            weight was fitted for ``axis``.
        """
        from armfit._lazy import import_extra

        control = import_extra("control", "control", "Uncertainty.to_control")
        if axis not in self.weights:
            raise UsageError(f"no weight for axis {axis!r} (weights: "
                             f"{', '.join(self.weights) or 'none'})")
        z, p, k = _export.weight_zpk(self.weights[axis])
        return control.zpk(z, p, k, name=f"Wu_{axis}")

    def plot(self, axis: str | None = None, ax=None, *, panel: str | None = None):
        """One axis of the paper's Fig. 6: the derived arm dynamics with the nominal
        H_ARM (magnitude and phase), and W_max with |Wu| (relative uncertainty, dB).

        Parameters
        ----------
        axis : {'x', 'y', 'z'}, optional
            Default the only one, or with ``ax`` None every axis (the whole Fig. 6).
        ax : matplotlib Axes or sequence of them, optional
            One Axes draws one panel (``panel``, default 'uncertainty'), two the Bode
            pair, three all. Default: a new figure.
        panel : {'magnitude', 'phase', 'uncertainty', 'both', 'all'}, optional
            'both': magnitude and phase; 'all': the three.

        Returns
        -------
        matplotlib.figure.Figure or the ``ax`` given
        """
        figures = _figures()
        have = [r.axis for r in self.axes]
        one = _one_axis(axis, have)
        if self.spectra is None or self.nominal is None:
            raise UsageError("this result holds no spectra or nominal fit to draw")
        if ax is None and panel in (None, "all"):
            return figures.uncertainty_figure(self.spectra, self.nominal, self, axis=one)
        if one is None:
            raise UsageError(f"this fit holds axes {', '.join(have)}: choose one with axis=")
        names = ("magnitude", "phase", "uncertainty")
        fig, t = _panel_targets(ax, panel, names, {"both": names[:2], "all": names},
                                "uncertainty")
        entries = figures.uncertainty_axes(t["magnitude"], t["phase"], t["uncertainty"],
                                           self.spectra, self.nominal, self, axis=one)
        _label_panels(t, {"magnitude": figures.MAG_LABEL, "phase": figures.PHASE_LABEL,
                          "uncertainty": figures.UNCERTAINTY_LABEL,
                          "x": figures.FREQ_LABEL}, entries)
        return fig if ax is None else ax

    def _html_summary(self) -> str:
        orders = ", ".join(f"{r.axis}: {len(r.result.weight.zeros)} pair(s)"
                           for r in self.axes)
        return f"Wu per axis ({orders}), cost {self.cost}"


def fit_uncertainty(spectra, nominal, *, cost: str = "envelope", order: int | None = None,
                    band: _Band | None = None, smooth_oct: float | None = None,
                    method: str | None = None,
                    check: Mapping[str, Mapping[str, _uncertainty.WuWeight]] | None = None,
                    jobs: int = 1, executor: Executor | None = None,
                    by_subject: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None
                    ) -> Uncertainty:
    """W_max (eq. 6) of every trial's derived arm dynamics against the nominal H_ARM and
    the weight Wu(s) = K Π(s − z)/Π(s − p) (eq. 7, s in rad/s) per axis (Table III,
    ``armfit fit-uncertainty``).

    Parameters
    ----------
    spectra : Spectra or path
        With trial-level derived responses.
    nominal : ModelFit, AdoptedModel, DataFrame or path
        Nominal fits (one row per axis); their apparatus effects are removed from the
        derived arm dynamics first (:func:`armfit.uncertainty.arm_trials`).
    cost : {'envelope', 'paper'}
        'envelope': |Wu| >= W_max on and between grid points, as tight as possible;
        'paper': dB least squares against W_max (no guarantee).
    order : int, optional
        Zero pairs = pole pairs, 0..5 (default: the smallest within 0.1 dB of the best).
    band : (float, float) or dict, optional
        Band in Hz, (lo, hi) for every axis or {axis: (lo, hi)} (default 0.01–30 Hz, also
        for an axis the dict does not name; limited to the spectra).
    smooth_oct : float, optional
        Smooth each trial's relative error over this many octaves before W_max.
    method : str, optional
        Estimator of the derived spectra when several.
    check : dict, optional
        {label: {axis: WuWeight}} further weights to evaluate on the same data.
    jobs : int
        Worker processes (each order of an axis's Wu fit a task, the axes side by
        side); the result does not depend on it.
    executor : concurrent.futures.Executor, optional
        Runs the tasks instead of ``jobs`` worker processes: a process pool of yours, or
        a ``dask.distributed`` client's ``client.get_executor()`` (used as is, never shut
        down; see :mod:`armfit.workers`). The result does not depend on it.
    by_subject : dict, optional
        {axis: {subject: {``effect.param``: value}}}: effect values per subject; each
        trial's apparatus effects are removed with its subject's (default: an
        ``AdoptedModel``'s, :attr:`armfit.adopt.Adoption.by_subject`; else none).

    Returns
    -------
    Uncertainty

    Raises
    ------
    ConvergenceError
        With cost 'paper', the least-squares fit of an axis did not converge (the one
        convergence policy of ``fit-uncertainty`` and ``run``; the envelope fit holds its
        guarantee whether or not its shape optimiser converged).
    """
    sp = _spectra(spectra)
    nom = nominal.nominal if isinstance(nominal, AdoptedModel) else ModelFit.of(nominal)
    if by_subject is None and isinstance(nominal, AdoptedModel):
        by_subject = nominal.adoption.by_subject
    results = _uncertainty.fit_weights(sp, nom.table, cost=cost, n_pairs=order,
                                           band=band, smooth_oct=smooth_oct, method=method,
                                           given=check, jobs=jobs, executor=executor,
                                           source=nom.source, by_subject=by_subject)
    _uncertainty.require_converged(results, cost)
    notes = _uncertainty.weight_axis_notes(sp, nom.table, spectra_label=sp.source,
                                           params_label=nom.source)
    return Uncertainty(tuple(results), cost, smooth_oct, sp, nom, tuple(notes),
                       dict(by_subject or {}))


def read_weights(path: PathLike) -> dict[str, _uncertainty.WuWeight]:
    """Read a Wu CSV (fit-uncertainty output or Table III layout) as {axis: WuWeight}."""
    return _uncertainty.read_wu(path)


# ---------------------------------------------------------------------------
# compare and diagnose
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Comparisons(_HtmlTable):
    """Errors of models against measurements, overall and per band.

    Attributes
    ----------
    rows : tuple of armfit.diagnosis.Comparison
        One per axis (× grip) and model (the base, then with the effects asked for).
    level : {'mean', 'median', 'trial'}
    notes : tuple of str
        What was left out or approximated, in sentences
        (:func:`armfit.diagnosis.comparison_notes`): an axis measured but without a
        params row, a params row without measurements, a grip compared with the row of
        the nearest grip.
    """

    rows: tuple
    level: str
    notes: tuple[str, ...] = ()

    def to_frame(self) -> pd.DataFrame:
        """One row per comparison and band (columns of compare.csv: axis, grip, level,
        model, band ``overall`` or ``LO-HI`` Hz, rms_db, rms_deg, rms_norm)."""
        return compare_frame(self.rows)

    def to_dict(self) -> dict:
        """The JSON document of ``armfit compare --json``."""
        return {"level": self.level, "rows": [{
            "axis": r.axis, "grip_N": r.grip_N, "model": r.model, "params": r.params,
            "n_trials": r.n_trials, "overall": _diagnosis.band_to_dict(r.overall),
            "bands": [_diagnosis.band_to_dict(b) for b in r.bands],
            "failing": [asdict(fb) for fb in r.failing]} for r in self.rows]} \
            | ({"notes": list(self.notes)} if self.notes else {})

    def write(self, path: PathLike, *, overwrite: bool = False) -> Path:
        """Write :meth:`to_frame` as compare.csv (as ``armfit run`` does), atomically."""
        with atomic_path(path, overwrite=overwrite) as tmp, \
                open(tmp, "w", encoding="utf-8", newline="") as fh:
            self.to_frame().to_csv(fh, index=False, float_format="%.10g",
                                   lineterminator="\n")
        return Path(path)


def compare_frame(rows) -> pd.DataFrame:
    """compare.csv as a DataFrame (:data:`armfit.io.schema.COMPARE_COLUMNS`) from
    :class:`armfit.diagnosis.Comparison` rows: one row per comparison and band, band
    ``overall`` (the whole band compared) or ``LO-HI`` (Hz)."""
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


def compare(spectra, model, *, level: str | None = None,
            band: _Band | None = None,
            effects: Iterable[Effect | str] = ()) -> Comparisons:
    """Compare fitted models with the measurements (``armfit compare``): RMS magnitude
    (dB), phase (deg) and noise-normalised error overall and per band, and the bands
    where the model fails, in words.

    Parameters
    ----------
    spectra : Spectra or path
    model : ModelFit, DataFrame or path
        Grip or nominal fits.
    level : {'mean', 'median', 'trial'}, optional
        Measurements to compare with (default: mean for grip fits, median for nominal).
    band : (float, float) or dict, optional
        Band in Hz, (lo, hi) for every axis or {axis: (lo, hi)} (default: the whole
        grid, also for an axis the dict does not name).
    effects : sequence of Effect or str
        Add these effects, refit, and report the error before and after.

    Returns
    -------
    Comparisons
    """
    sp = _spectra(spectra)
    m = ModelFit.of(model)
    if level is None:
        level = "mean" if m.which == "grip" else "median"
    rows = _diagnosis.compare_models(sp, m.table, level=level, band=band, effects=_effects(effects))
    notes = _diagnosis.comparison_notes(sp, m.table, level, spectra_label=sp.source,
                             params_label=m.source)
    return Comparisons(tuple(rows), level, tuple(notes))


def _effect_name(m) -> str:
    """The name of a missing effect as the diagnosis lists it (a name or a record)."""
    return m if isinstance(m, str) else str(getattr(m, "effect", getattr(m, "name", m)))


@dataclass(frozen=True, eq=False)
class Diagnosis(_HtmlTable):
    """Which physical effect each axis's model is missing.

    Attributes
    ----------
    axes : tuple of armfit.diagnosis.AxisDiagnosis
        Per axis: the verdict, the missing effect (or None), candidates best first,
        failing bands, base error, cross-axis coupling, and the candidates left out
        because their own code failed (``failed_candidates``).
    spectra, model : Spectra, ModelFit
        The inputs (for :meth:`plot`).
    """

    axes: tuple
    spectra: Spectra | None = None
    model: ModelFit | None = None

    @property
    def missing(self) -> dict[str, str | None]:
        """{axis: missing effect or None}."""
        return {d.axis: d.missing_effect for d in self.axes}

    @property
    def added(self) -> dict[str, tuple[str, ...]]:
        """{axis: every effect the stepwise search added, in order} (empty when none)."""
        return {d.axis: tuple(_effect_name(m) for m in d.missing_effects)
                or ((d.missing_effect,) if d.missing_effect else ()) for d in self.axes}

    def to_dict(self) -> dict:
        """The JSON document of ``armfit diagnose --json`` (and of diagnosis.json)."""
        return _diagnosis.diagnosis_to_dict(list(self.axes))

    def to_frame(self) -> pd.DataFrame:
        """One row per axis: axis, n_trials, band_lo_hz, band_hi_hz, missing_effects (the
        effects added, ";"-separated), adequate (the final model fits within the noise),
        base and final rms_norm, failing_bands (count, base model), verdict."""
        added = self.added
        return pd.DataFrame([{
            "axis": d.axis, "n_trials": d.n_trials, "band_lo_hz": d.band[0],
            "band_hi_hz": d.band[1], "missing_effects": ";".join(added[d.axis]),
            "adequate": bool(d.adequate), "rms_norm_base": d.base_error.rms_norm,
            "rms_norm_final": (d.final_error or d.base_error).rms_norm,
            "failing_bands": len(d.failing), "verdict": d.verdict} for d in self.axes],
            columns=["axis", "n_trials", "band_lo_hz", "band_hi_hz", "missing_effects",
                     "adequate", "rms_norm_base", "rms_norm_final", "failing_bands",
                     "verdict"])

    def write(self, path: PathLike, *, overwrite: bool = False) -> Path:
        """Write the JSON document (``armfit diagnose -o``), atomically."""
        write_text_atomic(path, json.dumps(self.to_dict(), indent=2, default=json_default)
                          + "\n", overwrite=overwrite)
        return Path(path)

    def plot(self, axis: str | None = None, ax=None, *, panel: str | None = None):
        """Normalised residuals (measurement − model)/SE of the diagnosed model, one
        axis: shaded where they leave the noise band
        (:func:`armfit.figures.residual_figure`).

        Parameters
        ----------
        axis : {'x', 'y', 'z'}, optional
            Default the only one, or with ``ax`` None every axis diagnosed.
        ax : matplotlib Axes or sequence of two, optional
            One Axes draws one panel (``panel``, default the magnitude), two draw both.
            Default: a new figure.
        panel : {'magnitude', 'phase', 'both'}, optional

        Returns
        -------
        matplotlib.figure.Figure or the ``ax`` given
        """
        figures = _figures()
        have = [d.axis for d in self.axes]
        one = _one_axis(axis, have)
        if self.spectra is None or self.model is None:
            raise UsageError("this diagnosis holds no spectra or model to draw")
        table = self.model.table[self.model.table["axis"].isin(have)]
        if ax is None and panel in (None, "both"):
            return figures.residual_figure(self.spectra, table, axis=one)
        if one is None:
            raise UsageError(f"this diagnosis holds axes {', '.join(have)}: choose one "
                             "with axis=")
        fig, t = _panel_targets(ax, panel, ("magnitude", "phase"),
                                {"both": ("magnitude", "phase")}, "magnitude")
        entries = figures.residual_axes(t["magnitude"], t["phase"], self.spectra, table,
                                        axis=one)
        _label_panels(t, {"magnitude": "Magnitude residual / SE",
                          "phase": "Phase residual / SE", "x": figures.FREQ_LABEL},
                      entries)
        return fig if ax is None else ax

    def _html_summary(self) -> str:
        return "; ".join(f"{a}: {', '.join(e) or 'nothing missing'}"
                         for a, e in self.added.items())


def diagnose(spectra, model, *, band: _Band | None = None,
             effects: Iterable[Effect | str] | None = None, jobs: int = 1,
             max_steps: int = MAX_STEPS, min_effect_db: float = MIN_EFFECT_DB,
             min_effect_deg: float = MIN_EFFECT_DEG,
             share: Sequence[str] | None = None, executor: Executor | None = None,
             by_subject: bool = True) -> Diagnosis:
    """Find the physical effects the 5-parameter model is missing, per axis, step by step
    (``armfit diagnose``): while the model is not within the noise, add the library
    effect with the best significant ΔBIC that changes the response by more than the
    noise and the floors, refitting all added effects jointly.

    Parameters
    ----------
    spectra : Spectra or path
        With trial-level measured responses.
    model : ModelFit, DataFrame or path
        Grip fits (preferred: per-grip starts) or nominal fits.
    band : (float, float) or dict, optional
        Band in Hz, (lo, hi) for every axis or {axis: (lo, hi)} (default: the whole
        grid, also for an axis the dict does not name).
    effects : sequence of Effect or str, optional
        Candidates (default: the whole effect library). A candidate whose own code
        fails in its fit (its term raises, or is NaN or infinite on the band) is left
        out with the reason (``failed_candidates`` of its axis) and the search goes on
        with the others.
    jobs : int
        Worker processes; the result does not depend on it.
    max_steps : int
        At most this many effects added, one per step.
    min_effect_db, min_effect_deg : float
        Practical floors: an effect must change the response by more than this (dB, or
        deg in phase) and more than the noise somewhere in the band.
    share : sequence of str, optional
        Effects whose parameters are compared across axes (default: the apparatus
        effects delay and lowpass; ``()`` for none).
    executor : concurrent.futures.Executor, optional
        Runs the screening and joint fits instead of ``jobs`` (used as is, not shut
        down; e.g. ``client.get_executor()`` of dask.distributed); the result does not
        depend on it.
    by_subject : bool
        Test each named effect for one value per subject
        (:mod:`armfit.diagnosis.subjects`; default). False: every effect shared by the
        trials of an axis.

    Returns
    -------
    Diagnosis

    Raises
    ------
    BadInputError
        The spectra hold no trial-level measured responses for the model's axes.
    """
    sp = _spectra(spectra)
    m = ModelFit.of(model)
    results = _diagnosis.diagnose_axes(sp, m.start_rows, band=band,
                            effects=None if effects is None else _effects(effects),
                            jobs=jobs, max_steps=max_steps, min_effect_db=min_effect_db,
                            min_effect_deg=min_effect_deg, share=share,
                            executor=executor, by_subject=by_subject)
    if not results:
        raise BadInputError("holds no trial-level measured responses for the axes of the "
                            "model", file=sp.source, column="level")
    return Diagnosis(tuple(results), sp, m)


# ---------------------------------------------------------------------------
# Per-trial fits and the stiffest stable virtual wall
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class TrialFits(_HtmlTable):
    """One fit of H_CL (eq. 4) per trial (``armfit fit-trials``).

    Attributes
    ----------
    fits : tuple of armfit.fitting.TrialFit
        Per trial (axis, subject, grip, run order): its FitResult, or None and the reason
        the fit failed.
    effects : tuple of Effect
        The effects in the model.
    spectra : Spectra or None
        What was fitted.
    """

    fits: tuple
    effects: tuple = ()
    spectra: Spectra | None = None

    @property
    def failed(self) -> list[tuple[str, str, float, int | None, str]]:
        """(axis, subject, grip_N, run, reason) of every trial whose fit failed."""
        return [(t.axis, t.subject, t.grip_N, t.run, t.reason) for t in self.fits
                if t.fit is None]

    def to_frame(self) -> pd.DataFrame:
        """The table ``armfit fit-trials`` writes: the params-file columns with ``subject``
        (and ``run``) after ``grip_N`` and a last column ``reason``."""
        return _fitting.trial_fits_table(list(self.fits), self.effects)

    def write(self, path: PathLike, *, overwrite: bool = False) -> Path:
        """Write :meth:`to_frame` as CSV (the file of ``armfit fit-trials``), atomically."""
        _artifacts.write_params(self.to_frame(), path, overwrite=overwrite)
        return Path(path)


def fit_trials(spectra, *, cost: str = "complex",
               bands: Mapping[str, tuple[float, float]] | None = None,
               effects: Iterable[Effect | str] = (), method: str | None = None,
               max_nfev: int | None = None, jobs: int = 1,
               on_fit: Callable | None = None,
               executor: Executor | None = None) -> TrialFits:
    """Fit H_CL (eq. 4) to every trial's measured response (``armfit fit-trials``): the
    population of arms that :func:`stability` takes.

    Parameters
    ----------
    spectra : Spectra or path
    cost, bands, effects, method, max_nfev
        As :func:`fit_grip`.
    jobs : int
        Worker processes; the result does not depend on it.
    on_fit : callable, optional
        Called with each :class:`armfit.fitting.TrialFit`.
    executor : concurrent.futures.Executor, optional
        Runs the tasks instead of ``jobs`` worker processes: a process pool of yours, or
        a ``dask.distributed`` client's ``client.get_executor()`` (used as is, never shut
        down; see :mod:`armfit.workers`). The result does not depend on it.

    Returns
    -------
    TrialFits
        A failed fit is kept with its reason, not raised.
    """
    sp = _spectra(spectra)
    objs = _fit_effects(effects)
    fits = _fitting.fit_trial_models(sp, cost=cost, bands=bands, effects=objs, method=method,
                               max_nfev=max_nfev, jobs=jobs, on_fit=on_fit,
                               executor=executor)
    return TrialFits(tuple(fits), objs, sp)


@dataclass(frozen=True, eq=False)
class AdoptedModel:
    """The model the diagnosis found, fitted: what ``armfit run`` delivers.

    Attributes
    ----------
    adoption : armfit.adopt.Adoption
        Per axis the adopted effects, the apparatus values held and why.
    grip, nominal : ModelFit
        Tables I and II of the adopted model.
    trials : TrialFits or None
        One fit of the adopted model per trial (the population :func:`stability` uses).
    base_grip : ModelFit or None
        Table I of the paper's 5-parameter model, which the diagnosis started from.
    diagnosis : Diagnosis or None

    Pass it on as a model: :func:`fit_uncertainty` (its nominal, apparatus effects
    removed from the derived arm dynamics), :func:`stability` (its trials; with weights,
    the certificate of its nominal capped by its trials), and the fitters' ``effects``.
    """

    adoption: _adopt.Adoption
    grip: ModelFit
    nominal: ModelFit
    trials: TrialFits | None = None
    base_grip: ModelFit | None = None
    diagnosis: Diagnosis | None = None


def adopt_model(spectra, diagnosis: Diagnosis | None = None, *, policy: str = "auto",
                cost: str = "complex", trials: bool = True, jobs: int = 1,
                executor: Executor | None = None,
                on_table: Callable[[str, ModelFit], None] | None = None) -> AdoptedModel:
    """Fit the adopted model (:mod:`armfit.adopt`): the paper's model plus the effects
    the diagnosis names per axis, apparatus effects held at the diagnosis's joint fit.

    Parameters
    ----------
    spectra : Spectra or path
        With trial-level measured and derived responses.
    diagnosis : Diagnosis, optional
        Of the base model (default: fit Table I and diagnose it here).
    policy : {'auto', 'none'}
        See :func:`armfit.adopt.adopt`.
    cost : {'complex', 'paper'}
        As :func:`fit_grip`.
    trials : bool
        Also fit every trial (needed by :func:`stability`).
    jobs : int
        Worker processes; the result does not depend on it.
    executor : concurrent.futures.Executor, optional
        Runs the fits instead of ``jobs`` worker processes: a process pool of yours, or
        a ``dask.distributed`` client's ``client.get_executor()`` (used as is, never shut
        down; see :mod:`armfit.workers`). The result does not depend on it.
        The diagnosis, which takes no executor, runs in ``jobs`` worker processes.
    on_table : callable, optional
        ``on_table(which, model)`` as each adopted table is fitted: ``"nominal"`` (Table
        II, whose fits run first) while Table I's fits still run, then ``"grip"``. What
        needs only Table II (its W_max and Wu, say) can start there.

    Returns
    -------
    AdoptedModel
    """
    sp = _spectra(spectra)
    base = None
    if diagnosis is None:
        base = fit_grip(sp, cost=cost, jobs=jobs, executor=executor)
        diagnosis = diagnose(sp, base, jobs=jobs)
    elif diagnosis.model is not None and diagnosis.model.which == "grip":
        base = diagnosis.model
    ad = _adopt.adopt(diagnosis, policy)
    bands = ad.bands
    grip, nominal = _adopted_tables(sp, ad, cost, jobs, executor, on_table)
    per_trial = None
    if trials:
        keys = zip(grip.table["axis"], grip.table["grip_N"], strict=True)
        starts = _fitting.grip_fit_starts(keys, grip.fits)
        effects = ad.effects
        fits = _fitting.fit_trial_models(sp, cost=cost, bands=bands, effects=effects,
                                   jobs=jobs, starts=starts, executor=executor,
                                   subject_effects=ad.subject_effects or None)
        per_trial = TrialFits(tuple(fits), effects, sp)
    return AdoptedModel(ad, grip, nominal, per_trial, base, diagnosis)


def _adopted_tables(sp: Spectra, ad: _adopt.Adoption, cost: str, jobs: int,
                    executor: Executor | None,
                    on_table: Callable[[str, ModelFit], None] | None = None
                    ) -> tuple[ModelFit, ModelFit]:
    """Tables I and II of the adopted model (:func:`adopt_model`), on one set of workers:
    Table II's fits handed to them first and Table I's at once behind them, so that
    neither table's tasks wait for the other's last one (the same fits, in any order: the
    same results), and ``on_table`` has Table II while Table I's fits run."""
    from armfit.workers import POOL_PRELOAD, executor_for

    fitted = {}
    with executor_for(executor, jobs, preload=POOL_PRELOAD["fit"]) as pool:
        for model in _table_fits(("nominal", "grip"), sp, cost=cost, bands=ad.bands,
                                 effects=ad.effects, executor=pool):
            fitted[model.which] = model
            if on_table is not None:
                on_table(model.which, model)
    return fitted["grip"], fitted["nominal"]


@dataclass(frozen=True, eq=False)
class Stability(_HtmlTable):
    """The stiffest virtual wall a sampled haptic device renders stably with each arm
    model (``armfit stability``).

    Attributes
    ----------
    table : pandas.DataFrame
        One row per model: K_max (N/m), the frequency where the loop first goes unstable,
        and with weights the robust certificate (columns of
        :data:`armfit.loop.STABILITY_COLUMNS`).
    settings : armfit.loop.WallSettings
        Servo period (s), virtual damping (N·s/m), computation delay (samples).
    models : pandas.DataFrame
        The parameter rows analysed (for :meth:`plot`).
    outside_loop : tuple of str
        The apparatus effects left out of the loop (:func:`armfit.loop.loop_model`); the
        plot leaves them out too.
    """

    table: pd.DataFrame
    settings: object
    models: pd.DataFrame
    outside_loop: tuple[str, ...] = ()

    def summary(self) -> dict[str, dict]:
        """Per axis: minimum, median and 5th percentile of K_max (N/m), and what limits it."""
        return _loop.axis_summary(self.table)

    def to_frame(self) -> pd.DataFrame:
        """The table (a copy): the rows of the CSV ``write`` writes."""
        return self.table.copy()

    def write(self, path: PathLike, *, overwrite: bool = False) -> Path:
        """Write the table as CSV (``armfit stability -o``), atomically."""
        with atomic_path(path, overwrite=overwrite) as tmp:
            self.table.to_csv(tmp, index=False, float_format="%.10g")
        return Path(path)

    def plot(self, axis: str | None = None, ax=None, *, panel: str | None = None):
        """K_max of each model, and against the servo rate, for one axis
        (:func:`armfit.figures.stability_figure`).

        Parameters
        ----------
        axis : {'x', 'y', 'z'}, optional
            Default the only one, or with ``ax`` None every axis.
        ax : matplotlib Axes or sequence of two, optional
            One Axes draws one panel (``panel``, default 'kmax'), two draw both.
            Default: a new figure.
        panel : {'kmax', 'sweep', 'both'}, optional
            'kmax': K_max per model at the settings; 'sweep': against servo rate 1/T
            for computation delays of 0, 1 and 2 samples.

        Returns
        -------
        matplotlib.figure.Figure or the ``ax`` given
        """
        figures = _figures()
        have = [a for a in AXES if (self.table["axis"] == a).any()]
        one = _one_axis(axis, have)
        if ax is None and panel in (None, "both"):
            rows = self.models if one is None else \
                self.models[(self.models["axis"] == one).to_numpy()]
            return figures.stability_figure(rows, self.settings,
                                            outside_loop=self.outside_loop)
        if one is None:
            raise UsageError(f"this result holds axes {', '.join(have)}: choose one "
                             "with axis=")
        fig, t = _panel_targets(ax, panel, ("kmax", "sweep"), {"both": ("kmax", "sweep")},
                                "kmax")
        entries = figures.stability_axes(t["kmax"], t["sweep"], self, axis=one)
        _label_panels(t, {}, entries)
        return fig if ax is None else ax

    def _html_summary(self) -> str:
        st = self.settings
        return (f"{len(self.table)} model(s); T = {st.sample_time_s * 1e3:g} ms, "
                f"B = {st.damping_Ns_per_m:g} N·s/m, d = {st.delay_samples}")


def stability(model, *, weights=None, sample_time_s: float | None = None,
              damping_Ns_per_m: float | None = None,
              delay_samples: int | None = None, members=None,
              outside_loop: Sequence[str] = ()) -> Stability:
    """K_max: the stiffest virtual wall F[k] = −(K x[k−d] + B (x[k−d] − x[k−d−1])/T), held
    by a zero-order hold, that a device sampling every T renders stably with each arm
    model (exact discretisation of eq. 4) (``armfit stability``).

    Parameters
    ----------
    model : ModelFit, TrialFits, AdoptedModel, DataFrame, path or str
        The arm models: fits, a params file, or a paper table by name ('nominal',
        'grip'). An AdoptedModel stands for its per-trial fits, or with ``weights`` for
        its nominal, its trials the members. A DataFrame (and a ``members`` DataFrame)
        gets the checks of a params file.
    weights : Uncertainty, dict or path, optional
        Uncertainty weights Wu for the robust certificate (a fit, {axis: WuWeight}, a Wu
        CSV or 'paper' for Table III).
    sample_time_s, damping_Ns_per_m, delay_samples : optional
        The wall (default 1 ms, 0 N·s/m, 1 sample).
    members : TrialFits, DataFrame or path, optional
        With ``weights``: the models the weight covers; the certificate is capped at
        their smallest K_max (:func:`armfit.loop.robust_certificate`).
    outside_loop : sequence of str
        Apparatus effects the rendering loop does not see
        (:func:`armfit.loop.loop_model`).

    Returns
    -------
    Stability

    Raises
    ------
    BadInputError
        A params or weights file (or DataFrame) breaks its contract, naming the file,
        column and row (:func:`armfit.models.params.read_param_rows`,
        :func:`armfit.io.artifacts.read_wu_rows`).
    """
    kw = {k: v for k, v in (("sample_time_s", sample_time_s),
                            ("damping_Ns_per_m", damping_Ns_per_m),
                            ("delay_samples", delay_samples)) if v is not None}
    settings = _loop.WallSettings(**kw)
    if isinstance(model, AdoptedModel):
        if weights is not None:
            members = model.trials if members is None else members
            model = model.nominal
        elif model.trials is not None:
            model = model.trials
        else:
            raise UsageError("this adopted model has no per-trial fits; give weights for "
                             "the certificate of its nominal, or adopt_model(trials=True)")
    if isinstance(model, ModelFit):
        rows, label = model.table, model.source
    elif isinstance(model, TrialFits):
        rows, label = model.to_frame(), None
        rows = rows[rows["converged"].astype(bool)]
    elif isinstance(model, pd.DataFrame):
        rows, label = _checked_rows(model, keep_row=True), None
    else:
        pr = _params.read_param_rows(str(model))
        rows, label = pr.table, pr.label
    w = bands = None
    if isinstance(weights, Uncertainty):
        w = weights.weights
        bands = {r.axis: tuple(r.band_hz) for r in weights.axes}
    elif isinstance(weights, Mapping):
        w = dict(weights)
    elif weights is not None:
        w, bands, _ = _uncertainty.read_weights_and_bands(str(weights))
    member_rows = None
    if isinstance(members, TrialFits):
        member_rows = members.to_frame()
        member_rows = member_rows[member_rows["converged"].astype(bool)]
    elif isinstance(members, pd.DataFrame):
        member_rows = _params.check_param_rows(members).table
    elif members is not None:
        member_rows = _params.read_param_rows(str(members)).table
    table = _loop.stability_table(rows, settings, weights=w, weights_band_hz=bands,
                            source=label, members=member_rows,
                            outside_loop=tuple(outside_loop))
    return Stability(table, settings, rows, tuple(outside_loop))


# ---------------------------------------------------------------------------
# simulate
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Simulation(_HtmlTable):
    """A simulated study of the paper's protocol with known truth.

    Attributes
    ----------
    config : armfit.simulation.StudyConfig
        Every setting (SI units).
    plans : tuple of armfit.simulation.TrialPlan
        The truth of each trial (identity, length, parameters, effects).
    """

    config: _simulation.StudyConfig
    plans: tuple = field(default=())

    def trials(self):
        """Yield the trials (armfit.io.trials.Trial), simulated one at a time."""
        for plan in self.plans:
            yield _simulation.simulate_trial(plan, self.config)

    def to_frame(self) -> pd.DataFrame:
        """One row per trial's truth (subject, axis, grip, duration, parameters …)."""
        return pd.DataFrame([p.as_dict() for p in self.plans])

    def truth(self, options: Mapping[str, object] | None = None) -> dict:
        """The truth document (the JSON ``armfit simulate`` writes beside the study)."""
        return _simulation.truth_dict(self.config, self.plans, options)

    def write(self, folder: PathLike, *, fmt: str = "parquet", units: str = "m",
              overwrite: bool = False, truth: PathLike | None = None,
              options: Mapping[str, object] | None = None,
              advance: Callable[[], object] | None = None) -> list[str]:
        """Write one raw trial file per trial into ``folder`` and the truth JSON beside it
        (default ``<folder>.truth.json``), committed together (both or neither,
        :func:`armfit.io.atomic.atomic_outputs`). Returns the file names."""
        out = Path(folder)
        truth_path = Path(truth) if truth else out.with_name(out.name + ".truth.json")
        files = []
        with atomic_outputs(overwrite=overwrite), \
                atomic_path(truth_path, overwrite=overwrite) as truth_tmp, \
                atomic_path(out, overwrite=overwrite, folder=True) as tmp:
            for trial in self.trials():
                name = trial_filename(trial.meta, fmt)
                write_trial(trial, tmp / name, fmt=fmt, units=units)
                files.append(name)
                if advance is not None:
                    advance()
            truth_tmp.write_text(json.dumps(self.truth(options), indent=1) + "\n",
                                 encoding="utf-8")
        return files


def simulate(config: _simulation.StudyConfig | None = None, **settings) -> Simulation:
    """Plan a simulated study with known truth (``armfit simulate``).

    Parameters
    ----------
    config : armfit.simulation.StudyConfig, optional
        Every setting; or give them as keywords (subjects, axes, grips_N, duration_s,
        fs, seed, noise_m, variability, drift_m, quantum_m, effects, …).

    Returns
    -------
    Simulation
        ``.trials()`` simulates the trials one at a time (feed them to
        :func:`estimate`); ``.write(folder)`` writes the study as ``armfit simulate``.
    """
    if config is None:
        config = _simulation.StudyConfig(**settings)
    elif settings:
        raise UsageError("give either a StudyConfig or settings, not both")
    return Simulation(config, _simulation.plan_study(config))


__all__ = [
    "AXES", "AdoptedModel", "Comparisons", "Diagnosis", "ModelFit", "Simulation", "Spectra",
    "Trials",
    "Uncertainty", "Stability", "TrialFits", "compare", "compare_frame", "diagnose",
    "adopt_model", "estimate", "estimate_config", "estimate_study_result", "fit_grip",
    "fit_nominal",
    "fit_trials", "fit_uncertainty", "read_model", "read_spectra", "read_trials",
    "read_weights", "simulate", "stability",
]

