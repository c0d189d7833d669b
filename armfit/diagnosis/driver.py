"""The stepwise search's start: the axes read one after the other, each axis's base fit
handed to the workers as soon as its trials are, and only then the search's own
machinery (:mod:`armfit.diagnosis.search`) loaded, while those fits run.

The process that runs the diagnosis (``armfit diagnose``, ``armfit run``) would otherwise
import the search's modules (the evidence, the results, the joint fits: about 60 ms)
before it hands the workers their first fit; the workers' fork server has them
preloaded and is ready before, so the first fits waited for this process."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Executor
from dataclasses import replace
from typing import TYPE_CHECKING

from armfit.constants import AXES, axis_band
from armfit.diagnosis.responses import AxisData, axis_data, cross_coupling, has_axis
from armfit.diagnosis.schedule import task_queue
from armfit.diagnosis.tuning import MAX_STEPS, MIN_EFFECT_DB, MIN_EFFECT_DEG, SHARED_EFFECTS
from armfit.memory import release_memory, release_memory_after_task

if TYPE_CHECKING:
    from armfit.diagnosis.results import AxisDiagnosis
    from armfit.models.effects import Effect
    from armfit.spectra import Spectra

__all__ = ["LARGE_TASK_BYTES", "diagnose_axes"]

#: Priorities of the search's tasks (lower first): a candidate's joint fit on all trials
#: (its axis's next step waits for it), then base fits, then the screening fits, step by
#: step in the order the steps began (an axis's step ends when its last fit does), within
#: a step those of effects with more parameters (the longer fits) first.
_EXTEND, _BASE, _SCREEN = 0, 1, 2


#: A task carrying trials of at least this many bytes of arrays is handed over as large
#: (:class:`armfit.diagnosis.schedule.TaskQueue`): on 1,350 trials an axis's take 4.3 MB.
LARGE_TASK_BYTES = 1 << 20


def _large(data: AxisData) -> bool:
    return data.nbytes >= LARGE_TASK_BYTES


# The task below gives back the memory its fit freed once it has ended
# (:func:`armfit.memory.release_memory_after_task`), as the search's do.

def _base_task(args):
    """The base model's joint fit of an axis (:func:`armfit.diagnosis.fit.fit_base`)."""
    from armfit.diagnosis.fit import fit_base  # loaded in the workers already
    data, band = args
    try:
        return fit_base(data, band)
    finally:
        release_memory_after_task()


def diagnose_axes(spectra, params, *,
                  band: tuple[float, float] | Mapping[str, tuple[float, float]] | None = None,
                  axes: Sequence[str] = AXES,
                  effects: Sequence[Effect] | None = None, jobs: int = 1,
                  max_steps: int = MAX_STEPS, min_effect_db: float = MIN_EFFECT_DB,
                  min_effect_deg: float = MIN_EFFECT_DEG,
                  share: Sequence[str] | None = None,
                  executor: Executor | None = None,
                  by_subject: bool = True) -> list[AxisDiagnosis]:
    """Diagnose every axis present in both ``spectra`` (a Spectra, a spectra DataFrame,
    or the path of a spectra file) and ``params`` (a params DataFrame, grip or nominal
    fits, or the :class:`~armfit.models.params.FitStarts` of such a file) by a stepwise
    search. Of a file, the trial rows of one axis are read at a time
    (:meth:`armfit.spectra.Spectra.read`), and only the arrays the search uses and the
    axis's cross-axis coupling are kept (the memory of the rest is given back once every
    axis is read); the result is that of the file read whole. An axis's base fit is
    handed to the workers (or the executor) as soon as its arrays are made, and runs
    while the next axis is read.

    Per axis: fit the base model to every trial (arm parameters per trial); while the
    model is not adequate (:func:`adequacy`), fit the current model plus each remaining
    effect (all effects refitted jointly, shared by the trials, warm-started), add the
    candidate with the highest ΔBIC among those significant in both senses — ΔBIC >
    :data:`SIGNIFICANT_BIC` with at least :data:`MIN_REDUCTION` of the cost removed, and
    a change of the response larger than the noise and than ``min_effect_db`` /
    ``min_effect_deg`` (:func:`practical`) — and repeat, at most ``max_steps`` times. No
    effect is added twice. ``share``: effects whose parameters the axes' fits are
    compared for agreement (default :data:`SHARED_EFFECTS`), see
    :func:`cross_axis_agreement`.

    A candidate whose own code breaks its fit (an :class:`EffectDefinitionError`: its
    term raised, or was NaN or infinite on the band) is left out of this and every later
    step with the message as reason (:attr:`AxisDiagnosis.failed_candidates`); the
    search goes on with the other candidates.

    ``band`` (Hz), one (lo, hi) for every axis or {axis: (lo, hi)}, defaults to the
    whole grid of the spectra (for an axis a mapping does not name, too); ``jobs`` > 1
    runs the fits (one task per axis and candidate) in parallel processes, or ``executor`` (any
    :class:`concurrent.futures.Executor`, e.g. a dask client's) runs them — the results
    do not depend on ``jobs`` or the executor. Each axis goes on to its next step as soon
    as its own fits are done (:mod:`armfit.diagnosis.schedule`).

    ``by_subject`` (default True): where an axis has trials of two or more subjects,
    every named effect is also tested with one value per subject
    (:mod:`armfit.diagnosis.subjects`): an effect of the arm while the step chooses among
    the candidates (screened and fitted per subject), an apparatus effect once named
    (and then, if its values differ between subjects, the step's other candidates fitted
    on all trials too); the per-subject form is kept when it is significant in both
    senses. False: every effect shared by the trials of an axis.
    """
    given = None if effects is None else list(effects)
    trial_rows = _trial_rows(spectra)
    read: list[tuple[AxisData, tuple[float, float]]] = []
    coupling: dict[str, dict[str, float]] = {}
    axes = [axis for axis in axes if has_axis(params, axis)]
    if not axes:
        return []
    share = SHARED_EFFECTS if share is None else tuple(share)
    # the workers start while the axes are read; an axis's base fit starts as soon as
    # its data are ready, while the next axis is read; the search's own machinery is
    # loaded once they are handed over, while they run (its first use is their results)
    steps: list = []         # each axis's search on the task queue, once loaded

    def based(i: int) -> Callable:
        return lambda base: steps[i]._based(base)

    with task_queue(jobs, executor) as tasks:
        for axis in axes:
            data = axis_data(trial_rows(axis, "measured"), params, axis)
            release_memory()    # what reading the rows took, before the next read
            if data is not None:
                b = axis_band(band, axis) or (float(data.f_hz[0]), float(data.f_hz[-1]))
                tasks.add((_BASE,), _base_task, (data, b), based(len(read)),
                          large=_large(data))
                read.append((data, b))
                tasks.start_ready()
                coupling[axis] = cross_coupling(trial_rows(axis, "cross"), data, b)
                release_memory()
        if not read:
            return []
        from armfit.diagnosis import search
        from armfit.models.effects import EFFECTS

        # the library is listed while the base fits run, not before they start:
        # listing it looks through the installed packages (1 ms; 45 ms where one
        # declares effects)
        library = list(EFFECTS.values()) if given is None else given
        searches = [search._Search(data, b, library, max_steps, min_effect_db,
                                   min_effect_deg, by_subject) for data, b in read]
        turns = search._Turns()
        if executor is None and jobs > 1:
            turns.share_last(len(searches), jobs)
        steps.extend(search._AxisSteps(s, tasks, turns) for s in searches)
        tasks.run()
        large = any(_large(s.data) for s in searches)
        search._borrow_step(searches, lambda fn, items: tasks.map(fn, items, large=large),
                            share)
    return _results(searches, coupling, share)


def _results(searches: list, coupling: Mapping[str, dict[str, float]],
             share: Sequence[str]) -> list[AxisDiagnosis]:
    """Every axis's diagnosis with its cross-axis coupling, and the agreement of the
    effects in ``share`` across the axes (:func:`~armfit.diagnosis.search.cross_axis_agreement`)."""
    from armfit.diagnosis.search import cross_axis_agreement
    out = [replace(s.result(), coupling=coupling[s.data.axis]) for s in searches]
    agreement = cross_axis_agreement(out, share)
    return [replace(d, shared=agreement) for d in out] if agreement else out


def _trial_rows(spectra) -> Callable[[str, str], Spectra]:
    """``(axis, kind) ->`` responses of ``spectra`` holding the trial rows of that kind
    the diagnosis of that stimulated axis uses ("measured", or "cross" for the
    coupling): read from the file when ``spectra`` is a path, else ``spectra`` itself
    (the diagnosis selects them). Of a file, only the values the diagnosis uses are kept:
    the standard errors of the measured rows; the responses and their flags always are.
    The two kinds are read one after the other, the cross rows without values: read
    together, the rows of an axis of 1,350 trials held 20 MB (41 MB at the read's
    peak); one after the other 9 and 10 MB (18 and 21 MB at the peak). Each read scans
    the whole file, so this takes about 1.1 s an axis of the 4,050-trial study instead
    of 0.6 s, while the axis's base fit runs in the workers (the measured rows are read
    first, and the base fit starts on them); on 81 trials the run's time did not change
    (16 alternated pairs)."""
    from armfit.spectra import Spectra
    if isinstance(spectra, str | os.PathLike):
        def read(axis: str, kind: str) -> Spectra:
            return Spectra.read(spectra, level="trial", kind=kind, axis=axis,
                                values=("se_db", "se_deg") if kind == "measured" else (),
                                estimators=False)
        return read
    sp = Spectra.of(spectra)
    return lambda axis, kind: sp
