"""From armfit's files to arrays: the trials of one axis on a common grid, and their
cross-axis motion."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from armfit import noise
from armfit._order import nanmedian
from armfit.constants import AXES, PARAM_NAMES
from armfit.models.params import FitStarts

if TYPE_CHECKING:   # imported where used: the diagnosis's workers need only AxisData
    from armfit.spectra import Spectra

__all__ = ["NOISE_KEPT_BYTES", "AxisData", "axis_data", "axis_grips", "comparison_notes",
           "cross_coupling",
           "has_axis",
           "not_excitation", "param_row",
           "select_rows", "trial_responses"]


#: Bytes of standard errors (dB and deg together) up to which an axis's noise model is
#: kept once made (:meth:`AxisData.noise_se`): 655 trials of 100 frequencies.
NOISE_KEPT_BYTES = 1 << 20


@dataclass(frozen=True)
class AxisData:
    """The trial-level measured responses of one axis on a common grid.

    f_hz (n,) Hz; h (T, n) complex X/F in m/N; se_db, se_deg (T, n) the trials' standard
    errors as the spectra file holds them (:meth:`noise_se`: the noise model's); starts:
    per trial the base parameters to start from (e.g. the grip fit of its grip; the
    trials of a grip may share one mapping, read, never changed); labels:
    per trial ``sub-<s>_grip-<g>N[_run-<k>]``; subjects: per trial its subject (empty:
    unknown, every trial its own); excluded: (T, n) bool, the points left out of the
    evidence because the estimator, not the model, is off there (flagged
    ``not_excitation``: the force is not a clean excitation and H1 is biased beyond its
    noise); None when there are none.
    """

    axis: str
    f_hz: np.ndarray
    h: np.ndarray
    se_db: np.ndarray
    se_deg: np.ndarray
    starts: tuple[Mapping[str, float], ...]
    labels: tuple[str, ...] = ()
    subjects: tuple[str, ...] = ()
    excluded: np.ndarray | None = None

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays (what a task carrying these trials pickles, about)."""
        return sum(a.nbytes for a in (self.f_hz, self.h, self.se_db, self.se_deg,
                                      self.excluded) if a is not None)

    def subset(self, idx: np.ndarray) -> AxisData:
        """The trials ``idx`` (an index array) of this axis."""
        return AxisData(self.axis, self.f_hz, self.h[idx], self.se_db[idx],
                        self.se_deg[idx], tuple(self.starts[i] for i in idx),
                        tuple(self.labels[i] for i in idx) if self.labels else (),
                        tuple(self.subjects[i] for i in idx) if self.subjects else (),
                        None if self.excluded is None else self.excluded[idx])

    def subject_of_trials(self) -> tuple[str, ...]:
        """Each trial's subject; a trial of unknown subject is its own (its label)."""
        if self.subjects:
            return self.subjects
        return self.labels or tuple(str(i) for i in range(self.h.shape[0]))

    def noise_se(self, sel: np.ndarray | slice = slice(None)
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The noise model's standard errors (dB, deg) of every trial, (T, n) on the
        grid points ``sel`` (computed on the whole grid, then restricted); NaN at the
        points :attr:`excluded` (no evidence: a NaN normalised residual is left out of
        every statistic, and a joint fit gives such a point no weight). Arrays of the
        caller's own.

        Those of up to :data:`NOISE_KEPT_BYTES` are made once and kept (a fit asks for
        them with each joint problem and each choice of starting rows, 0.2 ms a time on
        a few trials); larger ones are made at each call, not held for the data's
        lifetime (2.2 MB an axis of 1,350 trials of 100 frequencies). The kept ones are
        not pickled with the data."""
        kept = self.__dict__.get("_noise_kept")
        if kept is None:
            sdb, sdeg = noise.standard_errors(self.se_db, self.se_deg)   # arrays of its own
            if self.excluded is not None:
                sdb[self.excluded] = np.nan
                sdeg[self.excluded] = np.nan
            if sdb.nbytes + sdeg.nbytes > NOISE_KEPT_BYTES:
                return sdb[:, sel], sdeg[:, sel]
            # frozen: set as functools.cached_property sets its value
            kept = self.__dict__["_noise_kept"] = (sdb, sdeg)
        sdb, sdeg = kept
        if isinstance(sel, slice):
            return sdb[:, sel].copy(), sdeg[:, sel].copy()
        return sdb[:, sel], sdeg[:, sel]

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "_noise_kept"}


def select_rows(spectra, *, level: str, kind: str, axis: str, grip: float | None = None,
          out_axis: str | None = None) -> Spectra:
    from armfit.spectra import Spectra
    return Spectra.of(spectra).select(level=level, kind=kind, axis=axis, grip=grip,
                                      out_axis=out_axis)


#: The order of an axis's trials in the diagnosis's arrays.
_TRIAL_ORDER = ("subject", "grip_N", "run")


def _in_trial_order(rows: Spectra) -> tuple[Spectra, np.ndarray]:
    """``rows`` in :data:`_TRIAL_ORDER`, and their one grid (Hz; raises if the trials
    are on different grids)."""
    rows = rows.sorted(_TRIAL_ORDER)
    return rows, rows.common_grid("trials")


def trial_responses(rows: Spectra) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                          list]:
    """(f, H (T, n), se_db, se_deg, keys) of trial responses on one grid, in subject,
    grip, run order; keys are (subject, grip_N, run) per trial."""
    rows, f = _in_trial_order(rows)
    labels = list(zip(rows.key("subject"), rows.key("grip_N"), rows.key("run"), strict=True))
    return f, rows.h, rows.se_db, rows.se_deg, labels


#: Unflagged grid points between two flagged ones of a trial that are left out with them
#: (at most; an eighth of a decade on the default grid): an estimator's bias is smooth in
#: frequency, while the flag, a test per point, can miss a point or a few inside the band.
EXCLUDED_GAP = 5


def not_excitation(rows: Spectra) -> np.ndarray | None:
    """(T, n) bool, in :func:`trial_responses`'s order: the points flagged
    ``not_excitation`` (:data:`armfit.spectra.NOT_EXCITATION`), with the gaps of at most
    :data:`EXCLUDED_GAP` points between two flagged ones of a trial; None when no point
    is flagged."""
    from armfit.spectra import NOT_EXCITATION
    flags = rows.sorted(_TRIAL_ORDER).flags
    if flags is None:
        return None
    out = np.array([[NOT_EXCITATION in str(c).split(",") for c in row] for row in flags],
                   dtype=bool).reshape(np.shape(flags))
    if not out.any():
        return None
    for row in out:
        idx = np.flatnonzero(row)
        for a, b in zip(idx[:-1], idx[1:], strict=True):
            if 1 < b - a <= EXCLUDED_GAP + 1:
                row[a:b] = True
    return out


def has_axis(params, axis: str) -> bool:
    """Whether ``params`` (a params DataFrame, or the
    :class:`~armfit.models.params.FitStarts` of a file) has a row of ``axis``."""
    if isinstance(params, FitStarts):
        return params.has_axis(axis)
    return bool((params["axis"] == axis).any())


def axis_grips(params, axis: str) -> np.ndarray | None:
    """The grips (N) of the rows of ``axis`` in ``params`` (a params DataFrame, or the
    :class:`~armfit.models.params.FitStarts` of a file), in order; None when the rows
    have no grip (nominal fits)."""
    if isinstance(params, FitStarts):
        return params.grips(axis) if params.grip else None
    if "grip_N" not in params.columns:
        return None
    return params.loc[params["axis"] == axis, "grip_N"].to_numpy(float)


def param_row(params, axis: str, grip: float | None):
    """The row of ``params`` (a DataFrame, or the
    :class:`~armfit.models.params.FitStarts` of a file: then a dict) that a response of
    ``axis`` at ``grip`` (N) is compared with or started from: the axis's row of that
    grip, else of the nearest grip (the first of the axis without grips or ``grip``);
    None when the axis has no row."""
    if isinstance(params, FitStarts):
        own = params.of_axis(axis)
        pick = own.__getitem__
    else:
        own = params[params["axis"] == axis]
        pick = own.iloc.__getitem__
    if not len(own):
        return None
    grips = axis_grips(params, axis)
    if grip is None or grips is None:
        return pick(0)
    same = np.flatnonzero(np.isclose(grips, grip))
    # the row of that grip, else of the nearest grip of the same axis
    return pick(int(same[0]) if same.size else int(np.argmin(np.abs(grips - grip))))


def axis_data(spectra, params, axis: str) -> AxisData | None:
    """Trial-level measured responses of ``axis`` with per-trial starts from ``params``
    (the row of the trial's grip for grip fits, the axis row for nominal fits).
    None when the spectra hold no trials of the axis or the params no row for it."""
    rows = select_rows(spectra, level="trial", kind="measured", axis=axis)
    if len(rows) == 0 or not has_axis(params, axis):
        return None
    f, H, sdb, sdeg, labels = trial_responses(rows)
    # the row of each grip found once (as param_row finds it), not once per trial, and
    # its parameters held once: the trials of a grip share them (1,350 trials of an axis
    # held 1,350 dicts, 0.25 MB, and sent them all to the worker of the base fit)
    by_grip: dict[float, dict[str, float]] = {}
    starts = []
    for _subject, grip, _run in labels:
        g = float(grip)
        if g not in by_grip:
            r = param_row(params, axis, g)
            by_grip[g] = {n: float(r[n]) for n in PARAM_NAMES}
        starts.append(by_grip[g])
    names = tuple(f"sub-{s}_grip-{float(g):g}N" + ("" if run is None else f"_run-{run}")
                  for s, g, run in labels)
    return AxisData(axis, f, H, sdb, sdeg, tuple(starts), names,
                    tuple(str(s) for s, _, _ in labels), not_excitation(rows))


def cross_coupling(spectra, data: AxisData, band: tuple[float, float]) -> dict[str, float]:
    """Off-axis motion relative to on-axis motion for force on ``data.axis``, in dB.

    For each other position axis: the median over trials and over the band of
    20 log10(|X_other/F| / |X_axis/F|), the on-axis responses those of ``data``. Absent
    cross responses give no entry.
    """
    from armfit.spectra import Spectra
    out = {}
    axis, H_on = data.axis, data.h
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    lean = replace(Spectra.of(spectra), values={})   # the responses are all it uses
    for other in AXES:
        if other == axis:
            continue
        rows = select_rows(lean, level="trial", kind="cross", axis=axis, out_axis=other)
        if len(rows) == 0:
            continue
        H_c = _in_trial_order(rows)[0].h
        del rows
        if H_c.shape != H_on.shape:
            continue
        with np.errstate(all="ignore"):
            ratio = 20 * np.log10(np.abs(H_c[:, sel]) / np.abs(H_on[:, sel]))
        if not np.isfinite(ratio).any():  # no signal on that axis (cells flagged no_signal)
            continue
        out[other] = float(nanmedian(ratio))
    return out


def comparison_notes(spectra, params, level: str, *, spectra_label: str | None = None,
                     params_label: str | None = None, action: str = "compared"
                     ) -> list[str]:
    """What :func:`compare_models` leaves out or approximates, in sentences: an axis
    with measurements at ``level`` but no params row, a params row without such
    measurements, and (grip fits at level "mean") a grip mean compared with the row of
    the nearest grip because the file has no row of its own grip.

    Parameters
    ----------
    spectra : Spectra or pandas.DataFrame
    params : pandas.DataFrame or armfit.models.params.FitStarts
        The params table compared (or the base parameters of its file).
    level : {'mean', 'median', 'trial'}
    spectra_label, params_label : str, optional
        The files, named in the sentences.
    action : str
        What is done with an axis ("compared", "diagnosed"), for the sentences.

    Returns
    -------
    list of str
        In x, y, z order (empty when every axis and grip is compared with its own row).
    """
    from armfit.spectra import Spectra
    sl = spectra_label or "the spectra"
    pl = params_label or "the params table"
    spectra = Spectra.of(spectra)
    out = []
    for axis in AXES:
        rows = select_rows(spectra, level=level, kind="measured", axis=axis)
        has_row = has_axis(params, axis)
        if len(rows) and not has_row:
            out.append(f"axis {axis}: {sl} holds {level}-level measurements but {pl} has "
                       f"no row for it; axis {axis} is not {action}")
        elif has_row and not len(rows):
            out.append(f"axis {axis}: {pl} has a row but {sl} holds no {level}-level "
                       f"measured responses of it; axis {axis} is not {action}")
        own = axis_grips(params, axis)
        if not (has_row and len(rows) and level == "mean" and own is not None):
            continue
        for grip in sorted(float(g) for g in rows.values_of("grip_N")):
            if not np.isclose(own, grip).any():
                near = param_row(params, axis, grip)["grip_N"]
                out.append(f"axis {axis}: {pl} has no row for grip {grip:g} N; its mean "
                           f"is compared with the row of the nearest grip, {near:g} N")
    return out
