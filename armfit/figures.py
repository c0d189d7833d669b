"""Publication figures: Bode, residual, uncertainty and literature plots.

Every figure function takes data in the shapes of armfit's own files — the spectra table
(:data:`armfit.io.artifacts.SPECTRA_COLUMNS`), a fitted-parameters table (one row per axis,
or per axis × grip) and uncertainty weights ({axis: WuWeight}) — or the result objects of
:mod:`armfit.api` that hold them (``Spectra``, ``ModelFit``, ``AdoptedModel``,
``TrialFits``, ``Uncertainty``, ``Stability``), and returns a
:class:`matplotlib.figure.Figure`; each ``*_axes`` function draws one axis of a figure
on Axes of your own (the result objects' ``plot``). Nothing here reads files or prints;
:func:`save_figure` is the only writer.

Figures are drawn on the Agg canvas (headless; pyplot is never used), sized for a journal
column (3.5 in per panel column, 8 pt text), with one consistent style and a fixed layout
computed once from the sizes of the texts around the panels (no layout engine at save),
legends kept within the figure's width, tick labels with one minus sign (U+2212). Each
plotted artist carries a ``gid`` naming what it shows (``trial:…``, ``mean:…``, ``fit:…``,
``fit-outside:…``, ``nominal:…``, ``wmax:…``, ``wu:…``, ``literature:…``, ``failing:…``,
``kmax:…``) so that a figure can be inspected;
single trials are one LineCollection per panel and grip (``trial:<axis>:<grip>N``; in
the uncertainty figure one per panel, ``trial:<axis>``), one line per trial in the order
of (grip, subject, run).

Phases: every phase curve is unwrapped from its low-frequency end, then shifted by whole
turns (360°) to lie nearest its model line (the grip's fit, else the nominal model; the
curves' own circular mean where there is no model), so that a trial whose stored phase
starts on another branch is not drawn a turn away from the others. Model lines are drawn
on top of the data.

Conventions: frequencies in Hz on a log axis; magnitudes 20 log10 |H| with H in m/N
(dB re 1 m/N); phases in degrees.
"""

from __future__ import annotations

import functools
import logging
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import matplotlib as mpl
import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.lines import TICKDOWN, TICKUP, Line2D
from matplotlib.patches import Patch
from matplotlib.ticker import (
    FixedLocator,
    FuncFormatter,
    Locator,
    LogLocator,
    NullFormatter,
    NullLocator,
)

from armfit import noise
from armfit._order import median, unique
from armfit.constants import AXES, GRID_HZ
from armfit.errors import BadInputError, UsageError
from armfit.io.atomic import atomic_path, check_output
from armfit.loop import (
    WallSettings,
    k_max_sweep,
    loop_model,
    plant_from_model,
    stability_table,
)
from armfit.models.arm import ClosedLoopModel
from armfit.models.literature import REFERENCES_NOTE, LiteratureModel, literature_models
from armfit.models.params import fit_band, model_from_params
from armfit.spectra import Spectra
from armfit.uncertainty import WuWeight, arm_trials, derived_mass_kg, w_max

# fontTools, which subsets fonts for PDF output, logs every table it prunes at INFO.
logging.getLogger("fontTools").setLevel(logging.WARNING)

#: Output formats by file extension.
FORMATS: dict[str, str] = {".png": "png", ".svg": "svg", ".pdf": "pdf"}

#: Width of one panel column (in), a journal's single column.
PANEL_WIDTH_IN = 3.5
#: Height of one panel row (in).
PANEL_HEIGHT_IN = 1.8
#: Raster resolution (dots per inch) of PNG output and of rasterised single-trial lines
#: inside SVG and PDF.
DPI = 300
#: Single-trial lines of a panel are rasterised inside SVG/PDF when they hold more points
#: than this (e.g. 27 trials on a 3000-point grid); otherwise everything is vector.
RASTER_POINTS = 20000

AXIS_TITLES = {"x": "X axis (left–right)", "y": "Y axis (up–down)", "z": "Z axis (forward–back)"}

MAG_LABEL = "Magnitude (dB re 1 m/N)"
PHASE_LABEL = "Phase (deg)"
FREQ_LABEL = "Frequency (Hz)"

#: Drawing order: data (single trials, means, bands) below, model lines on top of them.
DATA_ZORDER = 2.0
MODEL_ZORDER = 3.0

#: Colour-blind-safe palette (Okabe & Ito, with wine for their hard-to-see yellow); grips
#: take the first colours in order.
PALETTE = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#882255")

#: Half-width of the noise band of a normalised residual: |(measurement − model)/SE| ≤
#: this value is within the noise.
NOISE_BAND = 2.0
#: Colour of the bands where a model leaves the noise band.
FAILING_COLOUR = "#D55E00"
#: The minus sign of every tick label (matplotlib's own: U+2212).
MINUS = "\u2212"

#: Residual axes whose |z| exceeds 3× this value are linear for |z| ≤ this value and
#: logarithmic beyond (symlog), so the noise band stays readable next to residuals of
#: hundreds.
RESIDUAL_LINEAR_LIMIT = 10.0

#: rc settings every figure is drawn with.
STYLE: dict[str, Any] = {
    "font.family": "DejaVu Sans",
    "font.size": 8,
    "axes.titlesize": 8,
    "axes.labelsize": 8,
    "xtick.labelsize": 7,
    "ytick.labelsize": 7,
    "legend.fontsize": 7,
    "legend.frameon": False,
    "axes.linewidth": 0.6,
    "axes.grid": True,
    "axes.grid.which": "both",
    "grid.linewidth": 0.3,
    "grid.alpha": 0.5,
    "lines.linewidth": 1.0,
    "xtick.major.width": 0.6,
    "ytick.major.width": 0.6,
    "pdf.fonttype": 42,
    "svg.fonttype": "path",
    "svg.hashsalt": "armfit",
    "path.simplify": True,
}

_METADATA: dict[str, dict[str, Any]] = {
    "png": {"Software": "armfit"},
    "svg": {"Creator": "armfit", "Date": None},
    "pdf": {"Creator": "armfit", "Producer": "armfit", "CreationDate": None},
}

#: Writer options by format. PNG: zlib level 3 instead of Pillow's 6 — a third less time
#: to compress (the files differ in size by a few per cent either way); the pixels are
#: the same.
_SAVE_KW: dict[str, dict[str, Any]] = {"png": {"pil_kwargs": {"compress_level": 3}}}


def _styled(fn: Callable[..., Figure]) -> Callable[..., Figure]:
    """Draw the figure under :data:`STYLE` (rc values are read when artists are made)."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        with mpl.rc_context(STYLE):
            return fn(*args, **kwargs)
    return wrapper


# ---------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------

def figure_format(path: str | Path) -> str:
    """The format ('png', 'svg' or 'pdf') of ``path`` by its extension.

    Raises UsageError (exit 2) for any other extension.
    """
    ext = Path(path).suffix.lower()
    if ext not in FORMATS:
        raise UsageError(f"{path}: unknown figure extension {ext or '(none)'!r}; "
                         f"use one of {', '.join(FORMATS)}")
    return FORMATS[ext]


def save_figure(fig: Figure, path: str | Path, *, overwrite: bool = False) -> Path:
    """Write ``fig`` to ``path`` (PNG, SVG or PDF by extension), atomically.

    Single-trial lines of a panel with more than :data:`RASTER_POINTS` points are
    rasterised at :data:`DPI` inside SVG/PDF; the rest stays vector. Files are
    deterministic: the same figure gives byte-identical files (no timestamps; fixed
    creator; fixed SVG hash salt). Refuses an existing ``path`` unless ``overwrite``
    (OutputError, exit 73).
    """
    fmt = figure_format(path)
    out = check_output(path, overwrite=overwrite)
    with mpl.rc_context(STYLE), atomic_path(out, overwrite=overwrite) as tmp:
        fig.savefig(tmp, format=fmt, metadata=_METADATA[fmt], dpi=DPI, **_SAVE_KW.get(fmt, {}))
    return out


# ---------------------------------------------------------------------------
# Models from parameter rows
# ---------------------------------------------------------------------------

def model_from_row(row: Mapping[str, Any]) -> tuple[ClosedLoopModel, dict[str, float]]:
    """The closed-loop model and its parameters from one row of a parameters table.

    :func:`armfit.io.artifacts.model_from_params` (axis, ``Ma,k1,k2,b1,b2``, ``effects``,
    ``<effect>.<param>``, ``mp_kg``), with a missing or empty value reported as a
    BadInputError naming the column.
    """
    try:
        model, theta = model_from_params(row)
    except KeyError as exc:
        raise BadInputError(f"missing value for axis {row.get('axis')}",
                            column=str(exc.args[0])) from None
    for name, value in theta.items():
        if not np.isfinite(value):
            raise BadInputError(f"axis {row['axis']}: parameter is empty or not finite",
                                column=name)
    return model, theta


def _params_table(params, which: str = "grip") -> pd.DataFrame | None:
    """A params table from what the figures take: a DataFrame as it is, or a result
    object of :mod:`armfit.api` — a ``ModelFit`` (its table), an ``AdoptedModel`` (its
    ``which`` fits: "grip" or "nominal"), ``TrialFits`` (the converged fits) or
    ``Stability`` (the models it analysed). None stays None."""
    if params is None or isinstance(params, pd.DataFrame):
        return params
    if hasattr(params, "adoption"):                       # AdoptedModel
        return getattr(params, which).table
    if hasattr(params, "settings") and hasattr(params, "models"):   # Stability
        return params.models
    if isinstance(getattr(params, "table", None), pd.DataFrame):   # ModelFit
        return params.table
    if hasattr(params, "fits") and hasattr(params, "to_frame"):     # TrialFits
        rows = params.to_frame()
        return rows[rows["converged"].astype(bool)].reset_index(drop=True)
    raise UsageError(f"expected a params table or a fit, got {type(params).__name__}")


def _spectra_of(spectra) -> Spectra:
    """A :class:`Spectra` from a Spectra or its long table."""
    return Spectra.of(spectra)


def _weights_of(weights) -> Mapping[str, WuWeight] | None:
    """{axis: WuWeight} from a mapping or an ``Uncertainty`` result (its fitted weights)."""
    if weights is None or isinstance(weights, Mapping):
        return weights
    if hasattr(weights, "weights"):
        return weights.weights
    raise UsageError(f"expected {{axis: WuWeight}} or an uncertainty fit, "
                     f"got {type(weights).__name__}")


def _model_label(row: Mapping[str, Any]) -> str:
    names = row.get("effects", "")
    if names is None or (isinstance(names, float) and math.isnan(names)) or not str(names):
        return "model"
    return "model + " + " + ".join(n for n in str(names).split(";") if n)


def _db(x) -> np.ndarray:
    return 20.0 * np.log10(np.abs(x))


def _phase_deg(h: np.ndarray) -> np.ndarray:
    """Phase in degrees, unwrapped along frequency, starting in (−180, 180]."""
    return np.degrees(np.unwrap(np.angle(h)))


def _unwrap_deg(phase_deg: np.ndarray) -> np.ndarray:
    """A phase curve (deg, ordered by frequency) unwrapped from its low-frequency end.

    Steps larger than 180° between consecutive finite points become the step less a
    whole number of turns; non-finite points are skipped and stay as they are.
    """
    y = np.array(phase_deg, dtype=float)
    ok = np.isfinite(y)
    if ok.sum() > 1:
        y[ok] = np.unwrap(y[ok], period=360.0)
    return y


def _turns_to(phase_deg: np.ndarray, ref_deg: np.ndarray) -> float:
    """The whole-turn shift (a multiple of 360°) that brings ``phase_deg`` nearest to
    ``ref_deg``: 360° · round(median(ref − phase) / 360°) over the points where both are
    finite (the median, so that a slip in a noisy part of a curve cannot move the rest);
    0 where they share no finite point."""
    d = np.asarray(ref_deg, dtype=float) - np.asarray(phase_deg, dtype=float)
    d = d[np.isfinite(d)]
    return 360.0 * float(np.round(median(d) / 360.0)) if d.size else 0.0


@dataclass(frozen=True)
class _PhaseRef:
    """A reference phase curve (deg) along log frequency, to align phase curves with."""

    freq_hz: np.ndarray
    phase_deg: np.ndarray

    def at(self, f_hz: np.ndarray) -> np.ndarray:
        """The reference at ``f_hz`` (Hz), interpolated linearly in log frequency; NaN
        outside its range."""
        f_hz = np.asarray(f_hz, dtype=float)
        if self.freq_hz.size == 0:
            return np.full(f_hz.shape, np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.interp(np.log(f_hz), np.log(self.freq_hz), self.phase_deg,
                             left=np.nan, right=np.nan)


def _consensus_ref(curves: Sequence[Curve]) -> _PhaseRef:
    """The curves' own consensus phase, for panels without a model: the circular mean of
    the curves on the most common frequency grid, unwrapped from the low-frequency end."""
    if not curves:
        return _PhaseRef(np.empty(0), np.empty(0))
    sizes = [c.freq_hz.size for c in curves]
    n = max(set(sizes), key=sizes.count)
    same = [c for c in curves if c.freq_hz.size == n]
    f = same[0].freq_hz
    same = [c for c in same if np.allclose(c.freq_hz, f)]
    unit = np.exp(1j * np.radians(np.vstack([c.phase_deg for c in same])))
    with np.errstate(invalid="ignore"):
        centre = np.angle(np.nanmean(unit, axis=0))
    return _PhaseRef(f, _unwrap_deg(np.degrees(centre)))


def _aligned_phase(c: Curve, ref: _PhaseRef) -> tuple[np.ndarray, np.ndarray]:
    """The phase curve of ``c`` unwrapped from its low-frequency end and shifted by whole
    turns to lie nearest ``ref``. Returns (phase, phase − stored phase), in deg: the
    second, whole turns at every point, is what the curve's quartile band moves by."""
    ph = _unwrap_deg(c.phase_deg)
    ph = ph + _turns_to(ph, ref.at(c.freq_hz))
    return ph, ph - c.phase_deg


def _log_grid(f: np.ndarray, n: int = 400) -> np.ndarray:
    f = f[f > 0]
    return np.geomspace(f.min(), f.max(), n)


# ---------------------------------------------------------------------------
# Spectra selection
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Curve:
    """One response of the spectra table along frequency (Hz), as stored."""

    key: tuple
    freq_hz: np.ndarray
    mag_db: np.ndarray
    phase_deg: np.ndarray
    h: np.ndarray
    se_db: np.ndarray
    se_deg: np.ndarray
    q_db: tuple[np.ndarray, np.ndarray]
    q_deg: tuple[np.ndarray, np.ndarray]
    coherence: np.ndarray | None = None


def _select(spectra: Spectra, *, level: str, kind: str, axis: str) -> Spectra:
    """The responses of ``axis`` of one level and kind on the axis's own position, at
    positive frequencies."""
    rows = spectra.select(level=level, kind=kind, axis=axis, out_axis=axis)
    return _positive(rows) if (rows.freq_hz <= 0).any() else rows


def _positive(rows: Spectra) -> Spectra:
    """``rows`` without frequencies at or below 0 Hz."""
    keep = rows.freq_hz > 0
    return replace(rows, freq_hz=rows.freq_hz[keep], h=rows.h[:, keep],
                   values={k: v[:, keep] for k, v in rows.values.items()},
                   flags=rows.flags[:, keep], present=rows.present[:, keep])


def _points(rows: Spectra) -> int:
    """Number of (response, frequency) values in ``rows``."""
    return int(rows.present.sum())


def _curves(rows: Spectra, by: Sequence[str]) -> list[Curve]:
    """One :class:`Curve` per row, ordered by the identity columns ``by``."""
    rows = rows.sorted(by)
    out = []
    for i in range(len(rows)):
        m = rows.present[i]
        v = rows.values
        key = tuple(None if v is None or v != v else v for v in (rows.key(c)[i] for c in by))
        out.append(Curve(key, rows.freq_hz[m],
                         v["mag_db"][i, m], v["phase_deg"][i, m], rows.h[i, m],
                         v["se_db"][i, m], v["se_deg"][i, m],
                         (v["q25_db"][i, m], v["q75_db"][i, m]),
                         (v["q25_deg"][i, m], v["q75_deg"][i, m]),
                         v["coherence"][i, m]))
    return out


def _axes_in(spectra: Spectra, kind: str, axis: str | None) -> list[str]:
    present = [a for a in AXES if len(spectra.select(kind=kind, axis=a))]
    if axis is not None:
        if axis not in AXES:
            raise UsageError(f"axis must be x, y or z, got {axis!r}")
        if axis not in present:
            raise BadInputError(f"no {kind} responses for axis {axis}", column="axis")
        return [axis]
    if not present:
        raise BadInputError(f"no {kind} responses", column="kind")
    return present


def _grip_key(g) -> float | None:
    return None if g is None or (isinstance(g, float) and math.isnan(g)) else float(g)


def _grip_text(g: float | None) -> str:
    return "all grips" if g is None else f"{g:g} N"


def _trial_gid(axis: str, grip: float | None, subject, run) -> str:
    """``trial:<axis>:<grip>N:<subject>[:run<k>]`` (missing parts left out)."""
    parts = ["trial", axis, _grip_text(grip).replace(" ", "")]
    if subject is not None and not pd.isna(subject):
        parts.append(str(subject))
    if run is not None and not pd.isna(run):
        parts.append(f"run{int(run)}")
    return ":".join(parts)


def _order(g: float | None) -> float:
    return 1e9 if g is None else g


def _grip_colours(grips: Sequence[float | None]) -> dict[float | None, str]:
    known = sorted(g for g in set(grips) if g is not None)
    out: dict[float | None, str] = {g: PALETTE[i % len(PALETTE)] for i, g in enumerate(known)}
    out[None] = "black"
    return out


def _params_for(params: pd.DataFrame | None, axis: str) -> list[tuple[float | None, Any]]:
    """(grip or None, row) for each parameter row of ``axis``, by grip."""
    if params is None:
        return []
    rows = params[params["axis"] == axis]
    out = []
    for _, r in rows.iterrows():
        g = _grip_key(r["grip_N"]) if "grip_N" in rows.columns else None
        out.append((g, r))
    return sorted(out, key=lambda t: (t[0] is None, t[0] or 0.0))


# ---------------------------------------------------------------------------
# Layout
# ---------------------------------------------------------------------------

class _InView(Locator):
    """A tick locator that keeps only the ticks of ``inner`` inside the view interval.

    Matplotlib makes, positions and labels a tick object for every location a locator
    returns and only then drops those outside the view; a log axis over 0.1-30 Hz gets
    about a third of its minor ticks beyond the view. Dropping them first draws the same
    figure with less work (each axis is updated some twenty times per layout and draw).
    """

    def __init__(self, inner: Locator) -> None:
        self.inner = inner

    def set_axis(self, axis) -> None:
        super().set_axis(axis)
        self.inner.set_axis(axis)

    def __call__(self):
        locs = np.asarray(self.inner(), dtype=float)
        lo, hi = sorted(self.axis.get_view_interval())
        span = 1e-9 * (hi - lo)
        return locs[(locs >= lo - span) & (locs <= hi + span)]

    def tick_values(self, vmin, vmax):
        return self.inner.tick_values(vmin, vmax)

    def nonsingular(self, v0, v1):
        return self.inner.nonsingular(v0, v1)

    def view_limits(self, vmin, vmax):
        return self.inner.view_limits(vmin, vmax)


def _ticks_in_view(ax) -> None:
    """Wrap the axes' tick locators in :class:`_InView` (same ticks drawn, less work)."""
    for axis in (ax.xaxis, ax.yaxis):
        for get, put in ((axis.get_major_locator, axis.set_major_locator),
                         (axis.get_minor_locator, axis.set_minor_locator)):
            if not isinstance(get(), _InView):
                put(_InView(get()))


def _log_labels_within_decades(axis, lo: float, hi: float) -> None:
    """On a log axis whose data span less than about two decades (no or one power of ten
    inside), label 1-2-5 steps in plain numbers instead of matplotlib's minor labels,
    which overlap each other and the axis label."""
    if not (np.isfinite(lo) and np.isfinite(hi) and lo > 0) or hi / lo >= 100:
        return
    axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    axis.set_minor_formatter(NullFormatter())


def _grid(nrows: int, ncols: int, *, legend_rows: int = 1) -> tuple[Figure, np.ndarray]:
    """A figure of ``nrows`` × ``ncols`` panels sharing x per column, log frequency on x.

    The panels are placed by :func:`_fixed_layout`, which every figure calls when its
    artists are in place. The figure is made at the PNG resolution (:data:`DPI`), so that
    the texts measured for the layout are the ones drawn (matplotlib caches text metrics
    by resolution)."""
    fig = Figure(figsize=(PANEL_WIDTH_IN * ncols,
                         PANEL_HEIGHT_IN * nrows + LEGEND_ROW_IN * legend_rows),
                 dpi=DPI)
    FigureCanvasAgg(fig)
    axs = np.atleast_2d(fig.subplots(nrows, ncols, sharex="col", squeeze=False))
    for ax in axs.flat:
        ax.set_xscale("log")
        _ticks_in_view(ax)
    for ax in axs[-1]:
        ax.set_xlabel(FREQ_LABEL)
    return fig, axs


def _minor_ticks_as_lines(fig: Figure) -> None:
    """Draw the minor ticks and grid lines of log frequency axes as two artists per axes.

    Matplotlib keeps a tick object (two marks, a grid line, two labels) per minor tick and
    updates each of them some twenty times while laying out and drawing a figure; a log
    axis over 0.1-30 Hz has twenty. Where the view spans more than a decade the minor
    ticks carry no labels, so the same marks and grid lines are drawn here as one
    Line2D of tick markers and one of NaN-separated grid lines, at the locations the
    axis's own minor locator gives for the final view, with the rc tick and grid style,
    at the axis's zorder. Call it when every artist is in place (the view is final).
    """
    rc = mpl.rcParams
    marker = {"out": TICKDOWN, "in": TICKUP}.get(rc["xtick.direction"])
    bottom = rc["xtick.bottom"] and rc["xtick.minor.bottom"]
    top = rc["xtick.top"] and rc["xtick.minor.top"]
    if marker is None or not bottom or top:
        return
    done: dict = {}
    for ax in fig.axes:
        if ax.get_xscale() != "log" or not rc["axes.grid"] or \
                rc["axes.grid.which"] not in ("both", "minor") or \
                rc["axes.grid.axis"] not in ("both", "x"):
            continue
        view = ax.get_xlim()  # autoscaled to the data: final
        lo, hi = sorted(view)
        if not (lo > 0 and hi > 10.0 * lo):
            continue  # within a decade the minor ticks are labelled: leave them
        locs = np.asarray(ax.xaxis.get_minorticklocs(), dtype=float)
        locs = locs[(locs >= lo) & (locs <= hi)]
        z = ax.xaxis.get_zorder()
        gx = np.repeat(locs, 3)
        gx[2::3] = np.nan
        gy = np.tile([0.0, 1.0, np.nan], locs.size)
        ax.add_line(Line2D(gx, gy, transform=ax.get_xaxis_transform(which="grid"),
                           color=rc["grid.color"], linestyle=rc["grid.linestyle"],
                           linewidth=rc["grid.linewidth"], alpha=rc["grid.alpha"],
                           zorder=z, gid="minor-grid"))
        ax.add_line(Line2D(locs, np.zeros(locs.size), linestyle="none", marker=marker,
                           markersize=rc["xtick.minor.size"],
                           markeredgewidth=rc["xtick.minor.width"],
                           color=rc["xtick.color"], zorder=z, clip_on=False,
                           transform=ax.get_xaxis_transform(which="tick1"),
                           gid="minor-ticks"))
        done[ax] = view
    for ax, view in done.items():  # the view stays as it was, not widened by the lines
        ax.xaxis.set_minor_locator(NullLocator())
        ax.set_xlim(view)


#: Padding (in) around the figure and between panels (constrained layout's default, 3 pt).
LAYOUT_PAD_IN = 3.0 / 72.0


def _extent_in(text, renderer) -> tuple[float, float]:
    """Width and height (in) of a Text as drawn; (0, 0) if hidden or empty."""
    if not text.get_visible() or not text.get_text():
        return 0.0, 0.0
    bb = text.get_window_extent(renderer)
    return bb.width / renderer.dpi, bb.height / renderer.dpi


def _axis_room(axis, renderer) -> tuple[float, float, float]:
    """Room (in) the tick labels and label of ``axis`` take beside its axes (their width
    for a y axis, height for an x axis), and how far its tick labels reach past the
    ends of the axes (x: left and right; y: below and above)."""
    name = axis.axis_name
    labels = [t for t in axis.get_majorticklabels() if t.get_text()]
    boxes = [t.get_window_extent(renderer) for t in labels]
    dpi = renderer.dpi
    room = 0.0
    if boxes:
        rc = mpl.rcParams
        room = max(b.width if name == "y" else b.height for b in boxes) / dpi + \
            (rc[f"{name}tick.major.size"] + rc[f"{name}tick.major.pad"]) / 72.0
    w, h = _extent_in(axis.label, renderer)
    if w > 0:
        room += (w if name == "y" else h) + axis.labelpad / 72.0
    box = axis.axes.bbox
    if name == "x":
        lo = max((box.x0 - b.x0 for b in boxes), default=0.0)
        hi = max((b.x1 - box.x1 for b in boxes), default=0.0)
    else:
        lo = max((box.y0 - b.y0 for b in boxes), default=0.0)
        hi = max((b.y1 - box.y1 for b in boxes), default=0.0)
    return room, max(lo, 0.0) / dpi, max(hi, 0.0) / dpi


def _fixed_layout(fig: Figure, axs: np.ndarray) -> None:
    """Place the panels of ``axs`` (rows × columns) on ``fig`` from the sizes of their
    texts: tick labels, axis labels and titles, the figure's legend at the bottom and
    its suptitle at the top, with :data:`LAYOUT_PAD_IN` between them.

    The figure size is fixed (3.5 in per panel column), so this is one pass of text
    measurement instead of a layout solver run at every draw; panels of a column share
    their left edge and panels of a row their height, as a grid of subplots does. Call it
    when every artist is in place (tick labels follow the final view). It measures again
    when the panels' tick locations changed with their size (a locator picks ticks by the
    length of the axis); how far the labels reach past a panel's ends is kept from the
    first measure, made on smaller panels, so it errs on the side of room.
    """
    renderer = fig.canvas.get_renderer()
    width, height = fig.get_size_inches()
    nrows, ncols = axs.shape
    pad = LAYOUT_PAD_IN
    legend = fig.legends[0] if fig.legends else None
    sup = getattr(fig, "_suptitle", None)
    def tick_locs() -> list[np.ndarray]:
        return [loc for ax in axs.flat
                for loc in (ax.xaxis.get_majorticklocs(), ax.yaxis.get_majorticklocs())]

    for _ in range(2):
        measured = tick_locs()
        left, over = np.zeros(ncols), np.zeros(ncols)
        bottom, top = np.zeros(nrows), np.zeros(nrows)
        for i in range(nrows):
            for j in range(ncols):
                ax = axs[i, j]
                yroom, below, above = _axis_room(ax.yaxis, renderer)
                xroom, _, xover = _axis_room(ax.xaxis, renderer)
                left[j] = max(left[j], yroom)
                over[j] = max(over[j], xover)
                bottom[i] = max(bottom[i], xroom, below)
                _, th = _extent_in(ax.title, renderer)
                th = th + mpl.rcParams["axes.titlepad"] / 72.0 if th > 0 else 0.0
                top[i] = max(top[i], th, above)
        head = pad
        if sup is not None and sup.get_text():
            head += (1.0 - sup.get_position()[1]) * height + _extent_in(sup, renderer)[1]
        foot = pad
        if legend is not None:
            bb = legend.get_window_extent(renderer)
            foot += bb.height / renderer.dpi + \
                legend.borderaxespad * legend.prop.get_size_in_points() / 72.0
        aw = (width - pad * (ncols + 1) - left.sum() - over.sum()) / ncols
        gap = pad + np.where(bottom > 0, pad, 0.0)  # below a row: more below its x labels
        ah = (height - head - foot - gap[:-1].sum() - top.sum() - bottom.sum()) / nrows
        y = height - head
        for i in range(nrows):
            y -= top[i] + ah
            x = pad
            for j in range(ncols):
                x += left[j]
                axs[i, j].set_position([x / width, y / height, aw / width, ah / height])
                x += aw + over[j] + pad
            y -= bottom[i] + gap[i]
        if all(a.shape == b.shape and np.array_equal(a, b)
               for a, b in zip(measured, tick_locs(), strict=True)):
            break


#: Height (in) the figures are given per legend row they are made for (:func:`_grid`).
LEGEND_ROW_IN = 0.25


def _legend_layouts(handles: list, ncol: int | None) -> list[tuple[list, int]]:
    """The layouts :func:`_legend` tries, widest first: (entries in matplotlib's
    column-major order, columns). ``handles`` as a list of groups (lists): one column
    per group, then one row per group, then fewer columns; blank entries pad the groups
    to one length. A flat list: ``ncol`` columns (default up to 4), then fewer."""
    def pair(h):
        return h if isinstance(h, tuple) else (h, h.get_label())

    if handles and isinstance(handles[0], list):
        size = max(len(g) for g in handles)
        blank = (Line2D([], [], alpha=0.0), "")
        groups = [[pair(h) for h in g] + [blank] * (size - len(g)) for g in handles]
        flat = [e for g in groups for e in g]
        by_row = [g[j] for j in range(size) for g in groups]
        dense = [pair(h) for g in handles for h in g]     # no blanks once columns mix
        out = [(flat, len(groups)), (by_row, size)]
        return out + [(dense, n) for n in range(size - 1, 0, -1)]
    flat = [pair(h) for h in handles]
    return [(flat, n) for n in range(max(1, ncol or min(len(flat), 4)), 0, -1)]


def _legend(fig: Figure, handles: list, ncol: int | None = None, *,
            sized_rows: int = 1) -> None:
    """The figure's legend below the panels, within the figure's width.

    ``handles``: artists with their labels, or (handle, label) pairs (a handle may be a
    tuple of artists, drawn on top of each other); or a list of groups of them (lists),
    each group a column where the figure is wide enough and a row otherwise.

    ``ncol`` columns (default: up to 4) unless the legend would be wider than the
    figure less its padding: then as many columns as fit (one at least), so a figure of
    one panel column never cuts a legend entry. A legend of more rows than the
    ``sized_rows`` the figure was made for makes the figure taller by the extra rows
    (the panels keep their height: :func:`_fixed_layout` places them after this)."""
    if not handles:
        return
    renderer = fig.canvas.get_renderer()
    room = fig.get_figwidth() - 2.0 * LAYOUT_PAD_IN
    layouts = _legend_layouts(handles, ncol)
    for k, (entries, n) in enumerate(layouts):
        legend = fig.legend([h for h, _ in entries], [t for _, t in entries],
                            loc="outside lower center", ncol=n)
        if k == len(layouts) - 1 or \
                legend.get_window_extent(renderer).width / renderer.dpi <= room:
            break
        legend.remove()
    rows = -(-len(entries) // n)
    if rows > sized_rows:
        width, height = fig.get_size_inches()
        per_row = legend.get_window_extent(renderer).height / renderer.dpi / rows
        fig.set_size_inches(width, height + (rows - sized_rows) * per_row, forward=False)


def _trial_lines(ax, xs: Sequence[np.ndarray], ys: Sequence[np.ndarray], *, color: str,
                 gid: str, rasterized: bool, lw: float = 0.4, alpha: float = 0.35
                 ) -> LineCollection:
    """Thin single-trial lines (one per pair of ``xs``, ``ys``) as one LineCollection.

    One artist per group instead of one Line2D per trial: the figure draws in a fraction of
    the time and looks the same (each line is stroked on its own, so overlaps darken as
    before). Drawn with the data (zorder :data:`DATA_ZORDER`), below the model lines.
    """
    segs = [np.column_stack([x, y]) for x, y in zip(xs, ys, strict=True)]
    coll = LineCollection(segs, colors=color, linewidths=lw, alpha=alpha, gid=gid,
                          zorder=DATA_ZORDER, label="_trial",
                          capstyle=mpl.rcParams["lines.solid_capstyle"],
                          joinstyle=mpl.rcParams["lines.solid_joinstyle"])
    coll.set_rasterized(rasterized)
    ax.add_collection(coll)
    return coll


# ---------------------------------------------------------------------------
# Fig. 5: Bode plot of measured dynamics with fits
# ---------------------------------------------------------------------------

#: Marker of each grip's mean (grips in ascending order), so that grips whose means
#: coincide stay apart; hollow, so that a marker drawn over another leaves it visible.
GRIP_MARKERS = ("o", "s", "^", "D", "v", "P", "X")
#: Size (pt) of the mean markers.
MEAN_MARKER_PT = 3.5
#: Markers per decade on each mean line (the line itself joins every distinct estimate).
MARKERS_PER_DECADE = 5


def _grip_markers(grips: Sequence[float | None]) -> dict[float | None, str]:
    known = sorted(g for g in set(grips) if g is not None)
    out: dict[float | None, str] = {g: GRIP_MARKERS[i % len(GRIP_MARKERS)]
                                    for i, g in enumerate(known)}
    out[None] = "o"
    return out


def _darker(colour, black: float = 0.45) -> tuple[float, float, float]:
    """``colour`` mixed with ``black`` (0…1) parts of black: a grip's model line."""
    r, g, b = mpl.colors.to_rgb(colour)
    return (r * (1.0 - black), g * (1.0 - black), b * (1.0 - black))


def independent_points(coherence: np.ndarray) -> np.ndarray:
    """Indices of the points of a response that stand for distinct estimates.

    At low frequencies, where the native bins are coarser than a grid point's band,
    consecutive grid points average the same nearest bins
    (:func:`armfit.spectra.band_bins`): one estimate, moved along its fitted slope to
    each grid frequency, and one coherence value. Such a run of points with the same
    (finite) coherence is one estimate: its middle point is kept; every other point is
    its own estimate.

    Parameters
    ----------
    coherence : array_like, shape (nf,)
        The response's coherence at its frequencies, ascending (NaN where unknown).

    Returns
    -------
    ndarray of int
        Ascending indices into the response's points.
    """
    c = np.asarray(coherence, dtype=float)
    if c.size == 0:
        return np.zeros(0, dtype=int)
    shares = np.isfinite(c[1:]) & (c[1:] == c[:-1])  # point i+1 shares point i's estimate
    starts = np.flatnonzero(np.concatenate([[True], ~shares]))
    ends = np.append(starts[1:], c.size)
    return starts + (ends - starts - 1) // 2


@dataclass(frozen=True)
class _BodeStyle:
    """How one panel column of the Bode plot is drawn: per grip a colour and a marker,
    the spread around the means ("se" or "quartiles") and whether single trials show."""

    colour: Mapping[float | None, str]
    marker: Mapping[float | None, str]
    band: str = "se"
    trials: bool = True


def _bode_style(spectra: Spectra | None, params: pd.DataFrame | None, band: str,
                trials: bool) -> _BodeStyle:
    grips = [] if spectra is None else \
        [_grip_key(g) for g in dict.fromkeys(spectra.key("grip_N"))]
    if params is not None and "grip_N" in params.columns:
        grips += [_grip_key(g) for g in params["grip_N"].unique()]
    return _BodeStyle(_grip_colours(grips), _grip_markers(grips), band, trials)


def _bode_models(params: pd.DataFrame | None, axis: str, f: np.ndarray) -> list[tuple]:
    """(grip, row, f, H, phase, fit band) of each model row of ``axis`` on the dense grid
    ``f`` (Hz), the edges of the row's fit band added to it."""
    out = []
    for g, row in _params_for(params, axis):
        model, theta = model_from_row(row)
        fb = fit_band(row)
        fd = f if fb is None else unique(np.concatenate([f, [x for x in fb if f[0] <= x <= f[-1]]]))
        h = model.response(fd, theta)
        out.append((g, row, fd, h, _phase_deg(h), fb))
    return out


def _draw_bode_trials(mag, ph, axis: str, curves: list[Curve], ref_for, style: _BodeStyle,
                      raster: bool) -> None:
    by_grip: dict[float | None, list[Curve]] = {}
    for c in curves:
        by_grip.setdefault(_grip_key(c.key[0]), []).append(c)
    for g, cs in by_grip.items():
        gid = _trial_gid(axis, g, None, None)
        for a, is_phase in ((mag, False), (ph, True)):
            if a is None:
                continue
            ys = [_aligned_phase(c, ref_for(g))[0] if is_phase else c.mag_db for c in cs]
            _trial_lines(a, [c.freq_hz for c in cs], ys, color=style.colour.get(g, "grey"),
                         gid=gid, rasterized=raster)


def _marker_steps(f: np.ndarray, g: float | None, style: _BodeStyle) -> tuple[int, int]:
    """(first, step) of the points of a mean that carry its grip's marker: about
    :data:`MARKERS_PER_DECADE` per decade, each grip starting at its own point so that
    the markers of grips whose means coincide stand side by side, not on each other."""
    decades = math.log10(f[-1] / f[0]) if f.size > 1 and f[0] > 0 else 1.0
    step = max(1, round(f.size / max(decades * MARKERS_PER_DECADE, 1.0)))
    known = sorted(k for k in style.marker if k is not None)
    i = known.index(g) if g in known else 0
    return (i * step) // max(len(known), 1), step


def _draw_bode_mean(mag, ph, axis: str, c: Curve, ref: _PhaseRef, style: _BodeStyle
                    ) -> tuple:
    """A grip's mean: a line through its distinct estimates (:func:`independent_points`)
    with its spread shaded, and its grip's marker on some of them (hollow). Returns its
    legend handle."""
    g = _grip_key(c.key[0])
    col, marker = style.colour.get(g, "black"), style.marker.get(g, "o")
    phase, moved = _aligned_phase(c, ref)
    lo_hi = ((c.mag_db - c.se_db, c.mag_db + c.se_db),
             (phase - c.se_deg, phase + c.se_deg)) if style.band == "se" \
        else (c.q_db, (c.q_deg[0] + moved, c.q_deg[1] + moved))
    keep = independent_points(c.coherence if c.coherence is not None
                              else np.full(c.freq_hz.size, np.nan))
    f = c.freq_hz[keep]
    tag = _grip_text(g).replace(" ", "")
    line = dict(lw=1.5, color=col, marker=marker, ms=MEAN_MARKER_PT, mfc="white", mec=col,
                mew=0.8)
    for a, y, (lo, hi) in ((mag, c.mag_db, lo_hi[0]), (ph, phase, lo_hi[1])):
        if a is None:
            continue
        a.fill_between(f, lo[keep], hi[keep], color=col, alpha=0.2, lw=0,
                       gid=f"band:{axis}:{tag}", zorder=DATA_ZORDER)
        a.plot(f, y[keep], **line, markevery=_marker_steps(f, g, style),
               gid=f"mean:{axis}:{tag}", zorder=DATA_ZORDER + 0.1)
    return (Patch(color=col, alpha=0.2, lw=0), Line2D([], [], **line))


def _draw_bode_model(mag, ph, axis: str, model: tuple, style: _BodeStyle) -> bool:
    """A model line: solid in a darker shade of its grip's colour over its fit band,
    dashed beyond it. Returns whether a dashed part was drawn."""
    g, _row, f, h, phase, fb = model
    col = _darker(style.colour.get(g, "black")) if g is not None else "black"
    inside = np.ones(f.size, bool) if fb is None else (f >= fb[0]) & (f <= fb[1])
    outside = ~inside
    outside[:-1] |= ~inside[1:]     # with the band's edge points, so the lines join
    outside[1:] |= ~inside[:-1]
    tag = _grip_text(g).replace(" ", "")
    for a, y in ((mag, _db(h)), (ph, phase)):
        if a is None:
            continue
        a.plot(f[inside], y[inside], lw=0.9, ls="-", color=col, zorder=MODEL_ZORDER,
               gid=f"fit:{axis}:{tag}")
        if not inside.all():
            a.plot(f, np.where(outside, y, np.nan), lw=0.9, ls=(0, (3, 2)), color=col,
                   zorder=MODEL_ZORDER, gid=f"fit-outside:{axis}:{tag}")
    return not inside.all()


def bode_axes(mag, ph, spectra=None, params=None, *, axis: str, band: str = "se",
              kind: str = "measured", trials: bool = True, style: _BodeStyle | None = None
              ) -> dict[tuple, Any]:
    """Draw the Bode pair of one axis — the column of Fig. 5 — on Axes of your own.

    Parameters
    ----------
    mag, ph : matplotlib.axes.Axes or None
        Where the magnitude (dB re 1 m/N) and the phase (deg) go; None leaves that
        panel out. Both get a log frequency axis.
    spectra : Spectra, pandas.DataFrame or None
        Single trials (level "trial") and grip means (level "mean") of ``kind``; None
        draws the models alone.
    params : pandas.DataFrame, ModelFit or AdoptedModel, optional
        Model rows (grip or nominal fits); those of ``axis`` are drawn.
    axis : {'x', 'y', 'z'}
    band, kind, trials
        As :func:`bode_figure`.

    Returns
    -------
    dict
        The legend entries drawn, {(grip order, entry order, …): handle}.
    """
    spectra = None if spectra is None else Spectra.of(spectra)
    params = _params_table(params, "grip")
    style = style or _bode_style(spectra, params, band, trials)
    mean_curves: list[Curve] = []
    trial_curves: list[Curve] = []
    raster = False
    f = np.geomspace(*GRID_HZ, 400)
    if spectra is not None:
        trial_rows = _select(spectra, level="trial", kind=kind, axis=axis)
        mean_rows = _select(spectra, level="mean", kind=kind, axis=axis)
        trial_curves = _curves(trial_rows, ("grip_N", "subject", "run")) if trials else []
        mean_curves = _curves(mean_rows, ("grip_N",))
        raster = _points(trial_rows) > RASTER_POINTS
        f_all = np.concatenate([trial_rows.freq_hz, mean_rows.freq_hz])
        f = _log_grid(f_all if f_all.size else spectra.freq_hz[spectra.freq_hz > 0])
    models = _bode_models(params, axis, f)     # the phase references of the data
    refs = {g: _PhaseRef(fd, p) for g, _, fd, _, p, _ in models}
    consensus = None if refs else _consensus_ref(trial_curves + mean_curves)

    def ref_for(g) -> _PhaseRef:
        if g in refs:
            return refs[g]
        if None in refs:
            return refs[None]
        return consensus if consensus is not None else next(iter(refs.values()))

    seen: dict[tuple, Any] = {}
    if trial_curves:
        _draw_bode_trials(mag, ph, axis, trial_curves, ref_for, style, raster)
        seen[(math.inf, 0)] = (Line2D([], [], lw=0.4, color="grey"), "single trials")
    spread = "± SE" if band == "se" else "quartiles"
    for c in mean_curves:
        g = _grip_key(c.key[0])
        handle = _draw_bode_mean(mag, ph, axis, c, ref_for(g), style)
        seen[(_order(g), 0)] = (handle, f"{_grip_text(g)}: mean {spread}")
    for model in models:
        g, row = model[0], model[1]
        label = (f"{_grip_text(g)}: " if g is not None else "") + _model_label(row)
        col = _darker(style.colour.get(g, "black")) if g is not None else "black"
        if _draw_bode_model(mag, ph, axis, model, style):
            seen[(math.inf, 1)] = (Line2D([], [], lw=1.0, ls=(0, (3, 2)), color="0.3"),
                                   "model beyond its fit band")
        seen[(_order(g), 1, label)] = (Line2D([], [], lw=1.0, color=col), label)
    _log_x(mag, ph)
    return dict(sorted(seen.items(), key=lambda kv: _entry_order(kv[0])))


def _entry_order(k: tuple) -> tuple:
    """Sort key of :func:`bode_axes`' legend entries: by grip, then mean before model."""
    return (k[0], k[1], str(k[2:]))


def _log_x(*axes) -> None:
    """A log frequency axis on each of ``axes`` that is not one yet (None skipped)."""
    for a in axes:
        if a is not None and a.get_xscale() != "log":
            a.set_xscale("log")


def _entries(seen: Mapping[tuple, Any]) -> list[list[tuple[Any, str]]]:
    """(handle, label) of :func:`bode_axes`' legend entries in groups, in the order of
    their keys: one group per grip (mean, model), then single trials and the dashed
    model."""
    groups: dict[float, list] = {}
    for k in sorted(seen, key=_entry_order):
        groups.setdefault(k[0], []).append(seen[k])
    return list(groups.values())


@_styled
def bode_figure(spectra, params=None, *, axis: str | None = None, band: str = "se",
                kind: str = "measured", trials: bool = True) -> Figure:
    """Bode plot per axis — the paper's Fig. 5.

    Each trial's response (level "trial") thin and light; each grip's mean (level
    "mean") as hollow markers, one marker shape per grip, at its distinct estimates only
    (:func:`independent_points`), with its spread shaded (``band`` "se": ± se_db /
    ± se_deg, or "quartiles": q25…q75); one model line per row of ``params`` (H_CL of
    eq. 4 with the row's effects, :meth:`ClosedLoopModel.response`) in a darker shade of
    its grip's colour, solid over the band it was fitted on (``band_lo_hz`` …
    ``band_hi_hz`` of the row) and dashed beyond it, on top of the data. Magnitude in
    dB re 1 m/N, phase in degrees, against frequency in Hz; each phase curve unwrapped
    from its low-frequency end and moved by whole turns to lie nearest the model of its
    grip (else the nominal row, else the curves' circular mean); a mean's band moves
    with it. ``axis`` None draws every axis present side by side. The single trials of
    a panel and grip are one LineCollection (gid ``trial:<axis>:<grip>N``).

    ``spectra`` is a :class:`~armfit.spectra.Spectra` or its long table; ``params`` a
    params table, a ``ModelFit`` or an ``AdoptedModel`` (its grip fits). One panel
    column per axis; :func:`bode_axes` draws one column on Axes of your own.
    """
    if band not in ("se", "quartiles"):
        raise UsageError(f"band must be 'se' or 'quartiles', got {band!r}")
    spectra = _spectra_of(spectra)
    params = _params_table(params, "grip")
    axes = _axes_in(spectra, kind, axis)
    style = _bode_style(spectra, params, band, trials)
    fig, axs = _grid(2, len(axes), legend_rows=2)
    seen: dict[tuple, Any] = {}
    for j, ax_name in enumerate(axes):
        axs[0, j].set_title(AXIS_TITLES[ax_name])
        seen.update(bode_axes(axs[0, j], axs[1, j], spectra, params, axis=ax_name,
                              band=band, kind=kind, trials=trials, style=style))
    axs[0, 0].set_ylabel(MAG_LABEL)
    axs[1, 0].set_ylabel(PHASE_LABEL)
    # One legend column per grip (mean above model), single trials last; one row per
    # grip where the figure is too narrow for that.
    _legend(fig, _entries(seen), sized_rows=2)
    _minor_ticks_as_lines(fig)
    _fixed_layout(fig, axs)
    return fig


# ---------------------------------------------------------------------------
# Residual figure
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Residuals:
    """Normalised residuals (measurement − model)/SE of one axis, per grip.

    ``z_db[i]`` is (mag_db − 20 log10|H_model|)/se_db and ``z_deg[i]`` is the phase
    difference, wrapped to (−180, 180], over se_deg, for grip ``grips[i]`` (None: the
    median over all grips), at ``freq_hz``; se_db, se_deg are the noise model's
    (:func:`armfit.noise.standard_errors`). Dimensionless; |z| ≤ 2 is the noise band.
    ``rms_norm[i]``: the model's "× noise" (:func:`armfit.noise.rms_norm`) over
    ``bands[i]``, the band its params row was fitted on (the whole grid when the row
    does not say) — the number the params file, ``compare`` and the report give.
    """

    axis: str
    freq_hz: np.ndarray
    grips: tuple[float | None, ...]
    z_db: np.ndarray
    z_deg: np.ndarray
    rms_norm: tuple[float, ...] = ()
    bands: tuple[tuple[float, float], ...] = ()


def normalised_residuals(spectra: pd.DataFrame, params: pd.DataFrame, axis: str, *,
                         kind: str = "measured") -> Residuals:
    """Residuals of the model rows of ``axis`` against the matching aggregate rows.

    A parameters table with ``grip_N`` (grip fits, Table I) is compared with the level
    "mean" rows of each grip; one without it (nominal fit, Table II) with the level
    "median" rows of the axis. The model is H_CL of eq. 4 (with the row's effects).
    """
    spectra = Spectra.of(spectra)
    pairs = _params_for(params, axis)
    if not pairs:
        raise BadInputError(f"no model row for axis {axis}", column="axis")
    grips, zdb, zdeg, freq, norms, bands = [], [], [], None, [], []
    for g, row in pairs:
        level = "median" if g is None else "mean"
        rows = _select(spectra, level=level, kind=kind, axis=axis)
        if g is not None:
            rows = rows.select(grip=g)
        curves = _curves(rows, ("axis",))
        if not curves:
            what = f"level '{level}'" + ("" if g is None else f", grip {g:g} N")
            raise BadInputError(f"no {kind} rows of {what} for axis {axis}", column="level")
        c = curves[0]
        if freq is not None and (c.freq_hz.shape != freq.shape
                                 or not np.allclose(c.freq_hz, freq)):
            raise BadInputError(f"axis {axis}: aggregates are on different frequency grids",
                                column="freq_hz")
        freq = c.freq_hz
        model, theta = model_from_row(row)
        h = model.response(c.freq_hz, theta)
        dphi = (c.phase_deg - np.degrees(np.angle(h)) + 180.0) % 360.0 - 180.0
        se_db, se_deg = noise.standard_errors(c.se_db, c.se_deg)
        with np.errstate(divide="ignore", invalid="ignore"):
            r_db = c.mag_db - _db(h)
        z_db, z_deg = noise.normalised(r_db, dphi, se_db, se_deg)
        zdb.append(z_db)
        zdeg.append(z_deg)
        band = fit_band(row, freq) or (float(freq[0]), float(freq[-1]))
        sel = (freq >= band[0]) & (freq <= band[1])
        norms.append(noise.rms_norm(r_db[sel], dphi[sel], se_db[sel], se_deg[sel]))
        bands.append(band)
        grips.append(g)
    return Residuals(axis, freq, tuple(grips), np.vstack(zdb), np.vstack(zdeg),
                     tuple(norms), tuple(bands))


def residual_labels(spectra: pd.DataFrame, params: pd.DataFrame, axis: str, *,
                    kind: str = "measured") -> dict[float | None, str]:
    """The legend labels of :func:`residual_figure` for the model rows of ``axis``.

    Parameters
    ----------
    spectra : pandas.DataFrame or Spectra
        The spectra the residuals are taken against.
    params : pandas.DataFrame
        A params table (grip fits or nominal fits).
    axis : str
        "x", "y" or "z".
    kind : str, optional
        Kind of the spectra rows ("measured" by default).

    Returns
    -------
    dict
        {grip in N (None for a nominal row): label}, e.g. ``"base (0.44× noise,
        0.1–30 Hz)"``: the row's model and its "× noise" over its fit band
        (:attr:`Residuals.rms_norm`, two decimals, as the report prints it).
    """
    res = normalised_residuals(spectra, params, axis, kind=kind)
    names = {g: _model_label(r) for g, r in _params_for(params, axis)}
    return {g: (f"{_grip_text(g)}: " if g is not None else "")
            + f"{names[g]} ({norm:.2f}× noise, {lo:.3g}–{hi:.3g} Hz)"
            for g, norm, (lo, hi) in zip(res.grips, res.rms_norm, res.bands, strict=True)}


def _residual_scale(ax) -> bool:
    """Symlog y (linear within ±RESIDUAL_LINEAR_LIMIT, logarithmic beyond) once the
    residuals drawn reach 3× that; labelled ticks at 0, ±half the limit, ±the limit and
    the 1-2-5 steps beyond (the other multiples unlabelled), with the typographic minus,
    and dotted lines where the scale turns logarithmic. Returns whether the axis is
    symlog."""
    ys = [np.abs(ln.get_ydata()) for ln in ax.get_lines() if len(ln.get_ydata()) > 1]
    top = max((float(np.nanmax(y)) for y in ys if np.isfinite(y).any()), default=0.0)
    lim = RESIDUAL_LINEAR_LIMIT
    if top <= 3 * lim:
        return False
    ax.set_yscale("symlog", linthresh=lim)
    first, last = int(math.log10(lim)) + 1, int(math.ceil(math.log10(top)))
    powers = [10.0 ** k for k in range(first, last + 1)]
    majors = [0.0, lim / 2, lim, *(m * p / 10 for p in powers for m in (2, 5, 10))]
    minors = [m * p / 10 for p in powers for m in (3, 4, 6, 7, 8, 9)]
    ax.yaxis.set_major_locator(_InView(FixedLocator(sorted({s * v for v in majors
                                                             for s in (-1, 1)}))))
    ax.yaxis.set_minor_locator(_InView(FixedLocator(sorted({s * v for v in minors
                                                             for s in (-1, 1)}))))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: _signed(v)))
    for y in (-lim, lim):
        ax.axhline(y, color="0.5", ls=":", lw=0.6, zorder=1, gid="symlog-edge")
    return True


def _signed(v: float) -> str:
    """``v`` as %g with the typographic minus (U+2212), the sign matplotlib's own tick
    labels use."""
    return f"{v + 0.0:g}".replace("-", MINUS)   # + 0.0: no sign on a zero


def failing_spans(freq_hz, z, *, limit: float = NOISE_BAND, forward=None
                  ) -> list[tuple[float, float]]:
    """Where drawn residual curves leave the noise band.

    Each row of ``z`` is drawn as straight segments between its points on a log
    frequency axis and a y axis whose scale maps values by ``forward``; a span is where
    at least one curve, as drawn, lies beyond ±``limit``: its edges are where a segment
    crosses ±limit (interpolated in log frequency and in the scale's coordinate), or the
    curve's first or last point.

    Parameters
    ----------
    freq_hz : array_like, shape (nf,)
        Frequencies (Hz), ascending, positive.
    z : array_like, shape (nf,) or (k, nf)
        Normalised residuals (dimensionless; NaN where there is none).
    limit : float
        Half-width of the noise band (:data:`NOISE_BAND`).
    forward : callable, optional
        The y scale's forward map of an array (e.g. ``ax.yaxis.get_transform().transform``
        of a symlog axis); identity by default (a linear axis).

    Returns
    -------
    list of (float, float)
        Disjoint (lo_hz, hi_hz), ascending.
    """
    f = np.asarray(freq_hz, dtype=float)
    rows = np.atleast_2d(np.asarray(z, dtype=float))
    fwd = (lambda y: np.asarray(y, dtype=float)) if forward is None else forward
    u = np.log(f)
    pieces: list[tuple[float, float]] = []
    for row in rows:
        y = fwd(row)
        ok = np.isfinite(y)
        seg = ok[:-1] & ok[1:]
        for sign in (1.0, -1.0):
            thr = float(np.asarray(fwd(np.array([sign * limit])))[0])
            out = ok & (sign * (y - thr) > 0)
            a, b = out[:-1], out[1:]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.clip((thr - y[:-1]) / (y[1:] - y[:-1]), 0.0, 1.0)
            has = seg & (a | b)
            du = u[1:] - u[:-1]
            lo = u[:-1] + np.where(a, 0.0, t) * du
            hi = u[:-1] + np.where(b, 1.0, t) * du
            pieces += list(zip(lo[has], hi[has], strict=True))
            lone = out & ~np.concatenate([[False], seg]) & ~np.concatenate([seg, [False]])
            pieces += [(x, x) for x in u[lone]]
    merged: list[list[float]] = []
    for lo, hi in sorted(pieces):
        if merged and lo <= merged[-1][1] + 1e-12:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    return [(math.exp(lo), math.exp(hi)) for lo, hi in merged]


def residual_axes(mag, ph, spectra, params, params2=None, *, axis: str,
                  bands: Sequence[tuple[float, float]] | None = None,
                  kind: str = "measured", colour: Mapping | None = None) -> dict[str, Any]:
    """Draw the normalised residuals of one axis — a column of :func:`residual_figure`
    — on Axes of your own.

    Parameters
    ----------
    mag, ph : matplotlib.axes.Axes or None
        Where the magnitude and the phase residual go; None leaves that panel out.
    spectra : Spectra or pandas.DataFrame
    params, params2 : pandas.DataFrame, ModelFit or AdoptedModel
        The models (solid) and optionally a second set (dashed); see
        :func:`normalised_residuals` for which rows are compared.
    axis : {'x', 'y', 'z'}
    bands : sequence of (lo_hz, hi_hz), optional
        Bands to shade instead of those where the solid curves leave the noise band.
    kind : str
        Kind of the spectra rows.

    Returns
    -------
    dict
        The legend entries of the shading, {name: (handle, label)}.
    """
    spectra = _spectra_of(spectra)
    params = _params_table(params, "nominal")
    params2 = _params_table(params2, "nominal")
    panels = [(a, attr) for a, attr in ((mag, "z_db"), (ph, "z_deg")) if a is not None]
    if colour is None:
        grips = [_grip_key(g) for g in params["grip_N"]] if "grip_N" in params.columns else []
        colour = _grip_colours(grips + [None])
    handles: dict[str, Any] = {"noise": (Patch(color="0.85", lw=0),
                                         f"noise band: |residual| ≤ {NOISE_BAND:g} SE")}
    for a, _ in panels:
        a.axhspan(-NOISE_BAND, NOISE_BAND, color="0.85", lw=0, zorder=0, gid=f"noise:{axis}")
        a.axhline(0.0, color="0.4", lw=0.5, zorder=1)
    first = None
    for which, table, ls in (("model", params, "-"), ("model2", params2, "--")):
        if table is None:
            continue
        res = normalised_residuals(spectra, table, axis, kind=kind)
        labels = residual_labels(spectra, table, axis, kind=kind)
        first = first or res
        for i, g in enumerate(res.grips):
            gid = f"{which}:{axis}:{_grip_text(g)}".replace(" ", "")
            for a, attr in panels:
                a.plot(res.freq_hz, getattr(res, attr)[i], ls=ls, lw=0.9 if ls == "-" else 1.1,
                       color=colour.get(g, "black"), gid=gid, label=labels[g])
    what = "band marked" if bands is not None else (
        ("solid " if params2 is not None else "")
        + f"model outside the noise band (|residual| > {NOISE_BAND:g} SE)")
    for a, attr in panels:
        _residual_scale(a)
        spans = bands if bands is not None else failing_spans(
            first.freq_hz, getattr(first, attr), forward=a.yaxis.get_transform().transform)
        for lo, hi in spans:
            a.axvspan(lo, hi, color=FAILING_COLOUR, alpha=0.15, lw=0, zorder=0,
                      gid=f"failing:{axis}:{lo:g}-{hi:g}")
            handles["failing"] = (Patch(color=FAILING_COLOUR, alpha=0.15, lw=0), what)
    if panels:
        panels[0][0].legend(loc="best", fontsize=6)
    _log_x(mag, ph)
    return handles


@_styled
def residual_figure(spectra, params, params2=None, *, axis: str | None = None,
                    bands: Mapping[str, Sequence[tuple[float, float]]] | None = None,
                    kind: str = "measured") -> Figure:
    """Normalised residuals (measurement − model)/SE against frequency, per axis.

    Top row magnitude (of 20 log10|H|), bottom row phase; one solid line per grip for
    ``params``, dashed for ``params2`` (e.g. the same model with an effect), each
    labelled with its "× noise" over its fit band (:func:`residual_labels`). The noise
    band |residual| ≤ :data:`NOISE_BAND` SE is shaded grey; shaded red, in each panel,
    the frequencies where a solid curve of that panel, as drawn, lies outside it
    (:func:`failing_spans`) — or, given ``bands`` ({axis: [(lo_hz, hi_hz), ...]}), those
    bands instead. A panel whose residuals pass 3 × :data:`RESIDUAL_LINEAR_LIMIT` has a
    symlog y axis, linear within ±that limit (dotted lines, and said in the axis label).
    See :func:`normalised_residuals` for which rows are compared. ``params`` and
    ``params2``: params tables, ``ModelFit`` or ``AdoptedModel`` (its nominal fits).
    """
    spectra = _spectra_of(spectra)
    params = _params_table(params, "nominal")
    params2 = _params_table(params2, "nominal")
    axes = [a for a in _axes_in(spectra, kind, axis)
            if axis is not None or (params["axis"] == a).any()]
    if not axes:
        raise BadInputError("the model has no row for any axis in the spectra", column="axis")
    grips = [_grip_key(g) for g in params["grip_N"]] if "grip_N" in params.columns else []
    colour = _grip_colours(grips + [None])
    fig, axs = _grid(2, len(axes), legend_rows=2)
    handles: dict[str, Any] = {}
    for j, ax_name in enumerate(axes):
        axs[0, j].set_title(AXIS_TITLES[ax_name])
        handles.update(residual_axes(axs[0, j], axs[1, j], spectra, params, params2,
                                     axis=ax_name, kind=kind, colour=colour,
                                     bands=None if bands is None else bands.get(ax_name, ())))
    for i, what in enumerate(("Magnitude", "Phase")):
        symlog = any(a.get_yscale() == "symlog" for a in axs[i])
        axs[i, 0].set_ylabel(f"{what} residual / SE" + (
            f"\n(linear within ±{RESIDUAL_LINEAR_LIMIT:g}, log beyond)" if symlog else ""))
    _legend(fig, list(handles.values()), ncol=2, sized_rows=2)
    _minor_ticks_as_lines(fig)
    _fixed_layout(fig, axs)
    return fig


# ---------------------------------------------------------------------------
# Fig. 6: derived arm dynamics, nominal model, W_max and |Wu|
# ---------------------------------------------------------------------------

#: The y label of W_max and |Wu|: magnitudes of a relative (dimensionless) error in dB.
UNCERTAINTY_LABEL = "Relative uncertainty\n(dB, dimensionless)"


def uncertainty_axes(mag, ph, unc, spectra, nominal, weights=None, *, axis: str,
                     by_subject: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None
                     ) -> dict[str, Any]:
    """Draw one axis of Fig. 6 — a column of :func:`uncertainty_figure` — on Axes of your
    own.

    Parameters
    ----------
    mag, ph, unc : matplotlib.axes.Axes or None
        Where the derived arm dynamics' magnitude (dB re 1 m/N) and phase (deg), and
        W_max with |Wu| (dB of a dimensionless ratio) go; None leaves a panel out.
    spectra : Spectra or pandas.DataFrame
        With the derived trials of ``axis``.
    nominal : pandas.DataFrame, ModelFit or AdoptedModel
        Nominal fits (its nominal, for an adopted model).
    weights : {axis: WuWeight} or Uncertainty, optional
    axis : {'x', 'y', 'z'}
    by_subject : dict, optional
        {axis: {subject: {``effect.param``: value}}}: effect values per subject, each
        trial's apparatus effects removed with its subject's (default: an
        ``Uncertainty``'s or ``AdoptedModel``'s own; else the nominal row's).

    Returns
    -------
    dict
        The legend entries drawn, {name: handle}.
    """
    if by_subject is None:
        by_subject = (getattr(weights, "by_subject", None)
                      or getattr(getattr(nominal, "adoption", None), "by_subject", None))
    subject_values = (by_subject or {}).get(axis) or {}
    spectra = _spectra_of(spectra)
    nominal = _params_table(nominal, "nominal")
    weights = _weights_of(weights)
    rows = _select(spectra, level="trial", kind="derived", axis=axis)
    curves = _curves(rows, ("grip_N", "subject", "run"))
    if not curves:
        raise BadInputError(f"no derived trial rows for axis {axis}", column="level")
    f = curves[0].freq_hz
    pairs = _params_for(nominal, axis)
    if not pairs:
        raise BadInputError(f"no nominal model row for axis {axis}", column="axis")
    model, theta = model_from_row(pairs[0][1])
    if model.apparatus_effects:    # the arm alone, as W_max sees it (arm_trials)
        curves = [_arm_curve(c, {**pairs[0][1], **subject_values.get(str(c.key[1]), {})},
                             spectra, axis) for c in curves]
    fd = _log_grid(f)
    h_nom = model.arm_response(fd, theta)
    ref = _PhaseRef(fd, _phase_deg(h_nom))
    handles: dict[str, Any] = {}
    raster = _points(rows) > RASTER_POINTS
    for a, is_phase in ((mag, False), (ph, True)):
        if a is None:
            continue
        ys = [_aligned_phase(c, ref)[0] if is_phase else c.mag_db for c in curves]
        _trial_lines(a, [c.freq_hz for c in curves], ys, color="#0072B2", alpha=0.4,
                     gid=f"trial:{axis}", rasterized=raster)
        a.plot(fd, ref.phase_deg if is_phase else _db(h_nom),
               color="black", ls="-.", lw=1.3, gid=f"nominal:{axis}", zorder=MODEL_ZORDER)
        handles["trials"] = Line2D([], [], lw=0.4, color="#0072B2",
                                   label="derived arm dynamics (trials)")
        handles["nominal"] = Line2D([], [], color="black", ls="-.", lw=1.3,
                                    label="nominal H_ARM")
    if unc is not None:
        if not all(c.freq_hz.shape == f.shape and np.allclose(c.freq_hz, f) for c in curves):
            raise BadInputError(f"axis {axis}: trials are on different frequency grids",
                                column="freq_hz")
        wm = w_max(np.vstack([c.h for c in curves]), model.arm_response(f, theta))
        unc.plot(f, _db(wm), ls="none", marker=".", ms=2.0, color="0.25", gid=f"wmax:{axis}")
        handles["wmax"] = Line2D([], [], ls="none", marker=".", color="0.25",
                                 label="W_max = max over trials |H/H_nom − 1|")
        if weights is not None and axis in weights:
            unc.plot(fd, _db(weights[axis].response(fd)), color="#D55E00", lw=1.3,
                     gid=f"wu:{axis}")
            handles["wu"] = Line2D([], [], color="#D55E00", lw=1.3, label="|Wu|")
    _log_x(mag, ph, unc)
    return handles


@_styled
def uncertainty_figure(spectra, nominal, weights=None, *, axis: str | None = None,
                       by_subject: Mapping[str, Mapping[str, Mapping[str, float]]] | None = None
                       ) -> Figure:
    """Derived arm dynamics with the nominal H_ARM, and W_max with |Wu| — paper Fig. 6.

    Rows: magnitude and phase of every trial's derived arm dynamics Xa/Fa (kind
    "derived", level "trial"; thin; the nominal row's apparatus effects removed, as
    W_max removes them) with the nominal H_ARM (eq. 3 with arm-stage effects,
    :meth:`ClosedLoopModel.arm_response` of the ``nominal`` row of the axis; black
    dash-dot), then W_max = max over trials |H/H̄ − 1| in dB (eq. 6; dots) with |Wu(jω)|
    in dB (eq. 7, ``weights`` {axis: WuWeight} as :func:`armfit.io.artifacts.read_wu`
    returns, or an ``Uncertainty`` result; line), both ratios, dimensionless. ``nominal``:
    a params table, ``ModelFit`` or ``AdoptedModel``; ``by_subject``: effect values per
    subject (:func:`uncertainty_axes`).
    """
    spectra = _spectra_of(spectra)
    axes = _axes_in(spectra, "derived", axis)
    fig, axs = _grid(3, len(axes), legend_rows=1)
    handles: dict[str, Any] = {}
    for j, ax_name in enumerate(axes):
        axs[0, j].set_title(AXIS_TITLES[ax_name])
        handles.update(uncertainty_axes(*axs[:, j], spectra, nominal, weights, axis=ax_name,
                                        by_subject=by_subject))
    axs[0, 0].set_ylabel(MAG_LABEL)
    axs[1, 0].set_ylabel(PHASE_LABEL)
    axs[2, 0].set_ylabel(UNCERTAINTY_LABEL)
    _legend(fig, [handles[k] for k in ("trials", "nominal", "wmax", "wu") if k in handles],
            sized_rows=1)
    _minor_ticks_as_lines(fig)
    _fixed_layout(fig, axs)
    return fig


def _arm_curve(c: Curve, row: Mapping[str, Any], spectra: Spectra, axis: str) -> Curve:
    """A derived trial curve with the nominal row's apparatus effects removed
    (:func:`armfit.uncertainty.arm_trials`)."""
    h = arm_trials(row, c.freq_hz, c.h, derived_mass_kg(spectra, axis))
    return replace(c, h=h, mag_db=_db(h), phase_deg=np.degrees(np.angle(h)))


# ---------------------------------------------------------------------------
# Fig. 7: this model against the literature
# ---------------------------------------------------------------------------

@_styled
def literature_figure(row: Mapping[str, Any], *, label: str | None = None,
                      models: Sequence[LiteratureModel] | None = None,
                      f_hz: np.ndarray | None = None) -> Figure:
    """H_ARM of one parameters row against the literature models of Table IV — Fig. 7.

    The row's H_ARM (eq. 3, :meth:`ClosedLoopModel.arm_response`) is the black dashed
    line; each literature model (:func:`armfit.models.literature.literature_models`) a
    solid colour line, labelled with the authors, the paper's reference number and the
    year of its source
    (:attr:`~armfit.models.literature.LiteratureModel.label`). Magnitude in dB re
    1 m/N and phase in degrees over ``f_hz`` (default 0.1–30 Hz, the band of the fits).
    """
    f = np.geomspace(*GRID_HZ, 400) if f_hz is None else np.asarray(f_hz, dtype=float)
    lit = literature_models() if models is None else list(models)
    model, theta = model_from_row(row)
    if label is None:
        grip = row.get("grip_N")
        grip = None if grip is None or not np.isfinite(float(grip)) else float(grip)
        label = f"this study: {str(row['axis']).upper()} axis" + \
            ("" if grip is None else f", {grip:g} N grip")
    fig, axs = _grid(2, 1, legend_rows=3)
    mag, ph = axs[:, 0]
    for i, m in enumerate(lit):
        h = m.response(f)
        col = PALETTE[i % len(PALETTE)]
        ls = "-" if i < len(PALETTE) else ":"
        gid = f"literature:{m.name.replace(' ', '-')}"
        mag.plot(f, _db(h), color=col, ls=ls, lw=1.0, label=m.label, gid=gid)
        ph.plot(f, _phase_deg(h), color=col, ls=ls, lw=1.0, label=m.label, gid=gid)
    h = model.arm_response(f, theta)
    mag.plot(f, _db(h), color="black", ls="--", lw=1.5, label=label, gid="arm-model")
    ph.plot(f, _phase_deg(h), color="black", ls="--", lw=1.5, label=label, gid="arm-model")
    mag.set_ylabel(MAG_LABEL)
    ph.set_ylabel(PHASE_LABEL)
    mag.set_title("Arm dynamics H_ARM = Xa/Fa")
    handles, _ = mag.get_legend_handles_labels()
    # what the bracketed numbers of the labels are: the paper's references
    handles.append((Line2D([], [], alpha=0.0), REFERENCES_NOTE))
    _legend(fig, handles, ncol=2, sized_rows=3)
    _minor_ticks_as_lines(fig)
    _fixed_layout(fig, axs)
    return fig



# ---------------------------------------------------------------------------
# Stability of a virtual wall: K_max per subject and grip, and against the servo rate
# ---------------------------------------------------------------------------

#: Servo rates (Hz) of the K_max sweep: 250 Hz to 8 kHz in half-octave steps (so 500 Hz,
#: 1, 2 and 4 kHz are on it), and 10 kHz.
SWEEP_RATES_HZ = tuple(250.0 * 2.0 ** (k / 2) for k in range(11)) + (1.0e4,)
#: Most samples of latency a loop of the sweep may hold: the test's cost grows with the
#: cube of the loop's order (81 models with 50 samples take 3 s per servo rate and
#: delay), and the figure shows a trend, so longer loops are left out (a gap).
SWEEP_MAX_LATENCY_SAMPLES = 36
#: Computation delays (samples) of the sweep.
SWEEP_DELAYS = (0, 1, 2)
_DELAY_COLOURS = ("black", "#CC79A7", "#56B4E9")  # apart from the grip colours
#: A sweep whose K_max spans more than this ratio is drawn on a log K_max axis (a linear
#: one from 0 would flatten its low rates); a narrower one on a linear axis from 0.
SWEEP_LOG_RATIO = 10.0


def _stability_inputs(params, settings, outside_loop: Sequence[str] | None
                      ) -> tuple[pd.DataFrame, pd.DataFrame, WallSettings, tuple[str, ...]]:
    """(model rows with a ``row`` column, their stability table, the settings, the
    effects outside the loop) of what the stability figure takes: a params table (or
    fit), settings and the effects outside the loop (default none), or a ``Stability``
    result (its models, table, settings and effects outside the loop unless others are
    given)."""
    if hasattr(params, "settings") and hasattr(params, "models"):      # Stability
        own = tuple(getattr(params, "outside_loop", ()))
        loop = own if outside_loop is None else tuple(outside_loop)
        st = params.settings if settings is None else settings
        rows = params.models
        table = params.table if settings is None and loop == own else None
    else:
        loop = () if outside_loop is None else tuple(outside_loop)
        st = WallSettings() if settings is None else settings
        rows, table = _params_table(params, "grip"), None
    if "row" not in rows.columns:
        rows = rows.assign(row=np.arange(1, len(rows) + 1))
    if table is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # unstable at K = 0: K_max 0
            table = stability_table(rows, st, outside_loop=loop)
    return rows, table, st, loop


def _kmax_panel(top, t: pd.DataFrame, axis: str, colour: Mapping, marker: Mapping
                ) -> dict[tuple, Any]:
    """The top panel of one axis: K_max (kN/m) of each model, one column per subject (or
    row), each grip with its marker, side by side within the column; the lowest K_max as
    a dashed line, its value written just below it; the axis from 0."""
    has_subject = t["subject"].notna().any()
    labels = sorted(t["subject"].dropna().astype(str).unique()) if has_subject \
        else [str(r) for r in t["row"]]
    xpos = {lab: i for i, lab in enumerate(labels)}
    known = sorted({g for g in (_grip_key(v) for v in t["grip_N"]) if g is not None})
    width = 0.6 / max(len(known), 1)
    handles: dict[tuple, Any] = {}
    for _, r in t.iterrows():
        g = _grip_key(r["grip_N"])
        shift = (known.index(g) - (len(known) - 1) / 2) * width if g in known else 0.0
        x = xpos[str(r["subject"])] if has_subject else xpos[str(r["row"])]
        style = dict(ls="none", marker=marker.get(g, "o"), ms=4.0,
                     color=colour.get(g, "black"), mec="white", mew=0.4)
        top.plot([x + shift], [r["k_max_N_per_m"] / 1e3], **style,
                 gid=f"kmax:{axis}:row{int(r['row'])}")
        handles.setdefault((_order(g), 0), Line2D(
            [], [], **style, label=_grip_text(g) if g is not None else "model"))
    kmin = float(t["k_max_N_per_m"].min()) / 1e3
    kmax = float(t["k_max_N_per_m"].max()) / 1e3
    top.set_ylim(0.0, kmax * 1.12 if kmax > 0 else 1.0)
    top.axhline(kmin, color="0.3", ls="--", lw=0.8, gid=f"kmin:{axis}", zorder=1)
    room = kmin > 0.15 * top.get_ylim()[1]      # below the line, where no model lies
    top.annotate(f"lowest: {kmin:.3g} kN/m", (0.01, kmin),
                 xycoords=top.get_yaxis_transform(), xytext=(2, -3 if room else 3),
                 textcoords="offset points", va="top" if room else "bottom", fontsize=6,
                 gid=f"kmin-label:{axis}")
    handles[(math.inf, 0)] = Line2D([], [], color="0.3", ls="--", lw=0.8,
                                    label="lowest K_max of the models")
    top.set_xticks(range(len(labels)), labels, rotation=90 if len(labels) > 6 else 0)
    top.set_xlim(-0.6, len(labels) - 0.4)
    top.set_xlabel("Subject" if has_subject else "Row")
    return handles


def stability_sweep(rows: pd.DataFrame, settings: WallSettings | None = None, *,
                    rates_hz: Sequence[float] = SWEEP_RATES_HZ,
                    delays: Sequence[int] = SWEEP_DELAYS,
                    outside_loop: Sequence[str] = ()) -> np.ndarray:
    """K_max (N/m) of each model row at each servo rate and delay: what the bottom panel
    of :func:`stability_figure` draws for one axis.

    Parameters
    ----------
    rows : pandas.DataFrame
        Parameter rows of one axis (a params table's rows, as :func:`model_from_row`
        reads them).
    settings : armfit.loop.WallSettings, optional
        Its damping B is kept (default 0); T and d are swept.
    rates_hz, delays, outside_loop
        As :func:`stability_figure`.

    Returns
    -------
    numpy.ndarray
        (len(delays), len(rates_hz), len(rows)), N/m; NaN where the loop holds more than
        :data:`SWEEP_MAX_LATENCY_SAMPLES` samples of latency
        (:func:`armfit.loop.k_max_sweep`).
    """
    st = WallSettings() if settings is None else settings
    plants = [plant_from_model(*loop_model(*model_from_row(r), outside_loop))
              for _, r in rows.iterrows()]
    return k_max_sweep(plants, rates_hz, delays, damping_Ns_per_m=st.damping_Ns_per_m,
                       max_delay_samples=SWEEP_MAX_LATENCY_SAMPLES)


def _sweep_panel(bot, rows: pd.DataFrame, axis: str, st: WallSettings,
                 rates_hz: Sequence[float], delays: Sequence[int],
                 sweep: np.ndarray | None = None, outside_loop: Sequence[str] = ()
                 ) -> dict[tuple, Any]:
    """The bottom panel of one axis: K_max (kN/m, from 0) against the servo rate 1/T
    (Hz, log) for each delay — the lowest over the models (line) and their range (band)
    — and the top row's 1/T (dotted). ``sweep``: :func:`stability_sweep` of ``rows``,
    computed here when not given."""
    shape = (len(delays), len(rates_hz), len(rows))
    if sweep is None:
        sweep = stability_sweep(rows, st, rates_hz=rates_hz, delays=delays,
                                outside_loop=outside_loop)
    elif np.shape(sweep) != shape:
        raise UsageError(f"stability figure: the sweep of axis {axis} has the shape "
                         f"{np.shape(sweep)}, not {shape} (delays, rates, rows)")
    handles: dict[tuple, Any] = {}
    for i, d in enumerate(delays):
        col = _DELAY_COLOURS[i % len(_DELAY_COLOURS)]
        with warnings.catch_warnings():   # a rate whose loop is too long: a gap
            warnings.simplefilter("ignore", RuntimeWarning)
            lo = np.nanmin(sweep[i], axis=1) / 1e3
            hi = np.nanmax(sweep[i], axis=1) / 1e3
        bot.fill_between(rates_hz, lo, hi, color=col, alpha=0.2, lw=0,
                         gid=f"sweep-range:{axis}:d{d}")
        bot.plot(rates_hz, lo, color=col, lw=1.2, marker=".", ms=2.5,
                 gid=f"sweep-min:{axis}:d{d}")
        handles[(math.inf, 1, d)] = Line2D(
            [], [], color=col, lw=1.2,
            label=f"delay d = {d} sample{'' if d == 1 else 's'}: lowest model")
    handles[(math.inf, 2)] = Patch(color="0.5", alpha=0.3, lw=0,
                                   label="shaded: range over the models")
    bot.set_xscale("log")
    # the whole swept range, also where a long latency leaves gaps
    bot.set_xlim(rates_hz[0] / 1.1, rates_hz[-1] * 1.1)
    if np.isnan(sweep).any():
        bot.annotate(f"gaps: more than {SWEEP_MAX_LATENCY_SAMPLES} samples of latency, "
                     "not analysed", (0.98, 0.04), xycoords="axes fraction",
                     ha="right", fontsize=6, gid=f"sweep-gap:{axis}")
    rate = 1.0 / st.sample_time_s
    bot.axvline(rate, color="0.5", ls=":", lw=0.8, gid=f"top-row-rate:{axis}")
    handles[(math.inf, 3)] = Line2D([], [], color="0.5", ls=":", lw=0.8,
                                    label=f"1/T of the top row ({rate:g} Hz)")
    bot.set_xlabel("Servo rate 1/T (Hz)")
    return handles


def _sweep_span(bot) -> tuple[float, float]:
    """The smallest positive and the largest K_max (kN/m) of a sweep panel's bands."""
    ys = [p.vertices[:, 1] for c in bot.collections
          if (c.get_gid() or "").startswith("sweep-range:") for p in c.get_paths()]
    y = np.concatenate(ys) if ys else np.zeros(0)
    y = y[np.isfinite(y) & (y > 0)]
    return (float(y.min()), float(y.max())) if y.size else (np.nan, np.nan)


def _sweep_log(bot) -> bool:
    """Whether a sweep panel wants a log K_max axis: when its K_max spans more than
    :data:`SWEEP_LOG_RATIO` (a linear axis from 0 would flatten its low rates)."""
    lo, hi = _sweep_span(bot)
    return bool(np.isfinite(lo) and hi / lo > SWEEP_LOG_RATIO)


def _sweep_scale(bot, log: bool) -> None:
    """The K_max axis of a sweep panel: from 0 (linear), or logarithmic with plain-number
    labels (:func:`_log_labels_within_decades`) and "log scale" in its label."""
    lo, hi = _sweep_span(bot)
    if log:
        bot.set_yscale("log")
        _log_labels_within_decades(bot.yaxis, lo, hi)
        bot.set_ylabel("K_max (kN/m, log scale)")
    else:
        bot.set_yscale("linear")
        bot.set_ylim(bottom=0.0)
        bot.set_ylabel("K_max (kN/m)")


def stability_axes(top, bot, params, settings=None, *, axis: str,
                   rates_hz: Sequence[float] = SWEEP_RATES_HZ,
                   delays: Sequence[int] = SWEEP_DELAYS,
                   outside_loop: Sequence[str] | None = None) -> dict[tuple, Any]:
    """Draw one axis of :func:`stability_figure` on Axes of your own.

    Parameters
    ----------
    top, bot : matplotlib.axes.Axes or None
        Where K_max per model and K_max against the servo rate go; None leaves that
        panel out.
    params : pandas.DataFrame, ModelFit, TrialFits, AdoptedModel or Stability
        The models (a ``Stability`` result brings its settings too).
    settings : armfit.loop.WallSettings, optional
        The top panel's wall (default T = 1 ms, B = 0, d = 1).
    axis : {'x', 'y', 'z'}
    rates_hz, delays, outside_loop
        As :func:`stability_figure`.

    Returns
    -------
    dict
        The legend entries drawn.
    """
    rows, table, st, loop = _stability_inputs(params, settings, outside_loop)
    return _stability_column(top, bot, rows, table, st, axis=axis, rates_hz=rates_hz,
                             delays=delays, scale=True, outside_loop=loop)


def _stability_column(top, bot, rows, table, st, *, axis: str, rates_hz, delays,
                      scale: bool, sweep: np.ndarray | None = None,
                      outside_loop: Sequence[str] = ()) -> dict[tuple, Any]:
    """One axis of the stability figure from its inputs already computed
    (:func:`_stability_inputs`); ``scale``: set the sweep's K_max scale from this panel
    alone (the whole figure sets one scale for its row instead); ``sweep``: the bottom
    panel's :func:`stability_sweep`, if computed already."""
    sel = (table["axis"] == axis).to_numpy()
    if not sel.any():
        raise BadInputError(f"no model row for axis {axis}", column="axis")
    grips = [_grip_key(g) for g in table["grip_N"]]
    handles: dict[tuple, Any] = {}
    if top is not None:
        handles.update(_kmax_panel(top, table[sel], axis, _grip_colours(grips),
                                   _grip_markers(grips)))
        top.set_ylabel("K_max (kN/m)")
    if bot is not None:
        handles.update(_sweep_panel(bot, rows[sel], axis, st, rates_hz, delays, sweep,
                                    outside_loop))
        if scale:
            _sweep_scale(bot, _sweep_log(bot))
    return handles


@_styled
def stability_figure(params, settings=None, *,
                     rates_hz: Sequence[float] = SWEEP_RATES_HZ,
                     delays: Sequence[int] = SWEEP_DELAYS,
                     sweeps: Mapping[str, np.ndarray] | None = None,
                     outside_loop: Sequence[str] | None = None) -> Figure:
    """The stiffest stable virtual wall per arm model, and its sensitivity to T and d.

    Top row, per axis: K_max (kN/m, from 0; :func:`armfit.loop.stability_table` at
    ``settings``, default T = 1 ms, B = 0, d = 1, stated in the row's titles) of each
    row of ``params`` (any parameters table or fit: per-trial fits with ``subject``,
    grip or nominal fits; or a ``Stability`` result), one column per subject (or per
    row), each grip with its colour and marker, side by side, with the lowest K_max as a
    dashed line and its value below it. Bottom row: K_max (kN/m, from 0) against servo
    rate 1/T (``rates_hz``, log) for each delay d in ``delays`` — the lowest over the
    rows (line) and their range (band), the top row's 1/T dotted; a rate at which a
    model's latency exceeds :data:`SWEEP_MAX_LATENCY_SAMPLES` samples is left out (a
    gap). ``sweeps``: {axis: :func:`stability_sweep` of that axis's rows, in order},
    computed elsewhere (e.g. in worker processes, an axis each); an axis not in it is
    computed here. ``outside_loop``: the apparatus effects the rendering loop does not
    see (:func:`armfit.loop.loop_model`), left out of both rows as
    :func:`armfit.loop.stability_table` leaves them out (default none, or a
    ``Stability`` result's own).
    """
    rows, table, st, loop = _stability_inputs(params, settings, outside_loop)
    sweeps = {} if sweeps is None else sweeps
    axes = [a for a in AXES if (table["axis"] == a).any()]
    if not axes:
        raise BadInputError("no model rows", column="axis")
    fig = Figure(figsize=(PANEL_WIDTH_IN * len(axes), PANEL_HEIGHT_IN * 2 + 0.5), dpi=DPI)
    FigureCanvasAgg(fig)
    axs = np.atleast_2d(fig.subplots(2, len(axes), squeeze=False))
    handles: dict[tuple, Any] = {}
    wall = (f"T = {st.sample_time_s * 1e3:g} ms, d = {st.delay_samples}, "
            f"B = {st.damping_Ns_per_m:g} N·s/m")
    for j, axis in enumerate(axes):
        handles.update(_stability_column(axs[0, j], axs[1, j], rows, table, st, axis=axis,
                                         rates_hz=rates_hz, delays=delays, scale=False,
                                         sweep=sweeps.get(axis), outside_loop=loop))
        axs[0, j].set_title(f"{AXIS_TITLES[axis]}\nwall at {wall}")
        axs[1, j].set_title(f"against servo rate, B = {st.damping_Ns_per_m:g} N·s/m")
    # one K_max scale for the whole bottom row: log if any axis's sweep needs it
    log = any(_sweep_log(ax) for ax in axs[1])
    for ax in axs[1]:
        _sweep_scale(ax, log)
    for ax in axs[:, 1:].flat:
        ax.set_ylabel("")
    # legend columns: the grips, the lowest K_max, the delays, the shading and the
    # top row's rate (keys of _kmax_panel and _sweep_panel)
    keys = sorted(handles, key=lambda k: (k[0], k[1], k[2:]))
    columns = [[handles[k] for k in keys if k[0] != math.inf],
               [handles[k] for k in keys if k[:2] == (math.inf, 0)],
               [handles[k] for k in keys if k[:2] == (math.inf, 1)],
               [handles[k] for k in keys if k[0] == math.inf and k[1] >= 2]]
    columns = [c for c in columns if c]
    _legend(fig, columns, sized_rows=2)
    for ax in axs.flat:
        _ticks_in_view(ax)
    _fixed_layout(fig, axs)
    return fig

__all__ = [
    "FORMATS", "Residuals", "bode_figure", "figure_format",
    "literature_figure", "model_from_row", "normalised_residuals", "residual_figure",
    "residual_labels",
    "save_figure", "stability_figure", "stability_sweep", "uncertainty_figure",
]
