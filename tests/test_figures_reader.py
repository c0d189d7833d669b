"""Tests of the figures as a reader sees them, and of the result objects' figures.

The figures' artists are inspected after drawing (no pixels): legends inside the figure,
shaded spans against the plotted curves, tick label text, marker placement. Inputs are
the small studies of test_figures (Table I models with a seeded error, in the schemas of
armfit's files) and the paper's tables; expected values come from the paper's equations,
the constructed inputs, independent numpy computations or matplotlib's own transforms.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.scale import SymmetricalLogTransform
from test_figures import (
    TABLE_COLS,
    F,
    legend_texts,
    lines,
    params_table,
    study_spectra,
    table1,
    table3_weights,
)

import armfit
from armfit import figures
from armfit.cli.main import cli
from armfit.data import paper_table
from armfit.errors import UsageError
from armfit.io.artifacts import write_params
from armfit.models.arm import h_arm, h_cl
from armfit.models.literature import literature_models
from armfit.spectra import Spectra


@pytest.fixture(scope="module")
def spectra() -> pd.DataFrame:
    return study_spectra()


@pytest.fixture(scope="module")
def grip() -> pd.DataFrame:
    return params_table(table1())


@pytest.fixture(scope="module")
def nominal() -> pd.DataFrame:
    return params_table(paper_table("nominal").rename(columns=TABLE_COLS))


@pytest.fixture(scope="module")
def delayed() -> pd.DataFrame:
    """An X-axis study whose true dynamics have a 10 ms delay the base model lacks."""
    return study_spectra(("x",), noise_db=0.3, noise_deg=1.0, delay_s=0.01, seed=3)


def drawn(fig: Figure) -> Figure:
    fig.canvas.draw()
    return fig


def legend_inside(fig: Figure) -> None:
    """Every legend of ``fig``, as drawn, lies within the figure."""
    renderer = drawn(fig).canvas.get_renderer()
    box = fig.bbox
    legends = list(fig.legends) + [a.get_legend() for a in fig.axes if a.get_legend()]
    assert legends
    for lg in legends:
        bb = lg.get_window_extent(renderer)
        assert bb.x0 >= box.x0 - 0.5 and bb.x1 <= box.x1 + 0.5, (bb, box)
        assert bb.y0 >= box.y0 - 0.5 and bb.y1 <= box.y1 + 0.5, (bb, box)


def close(got, want) -> None:
    """Two lists of (lo, hi) equal to 1e-9 (relative)."""
    assert len(got) == len(want), (got, want)
    np.testing.assert_allclose(np.array(got, float).reshape(-1, 2),
                               np.array(want, float).reshape(-1, 2), rtol=1e-9)


def spans(ax, prefix: str) -> list[tuple[float, float]]:
    """(lo, hi) in data x of the axvspans of ``ax`` whose gid starts with ``prefix``."""
    out = []
    for p in ax.patches:
        if (p.get_gid() or "").startswith(prefix):
            xs = p.get_path().transformed(p.get_patch_transform()).vertices[:, 0]
            out.append((float(xs.min()), float(xs.max())))
    return sorted(out)


# ---------------------------------------------------------------------------
# Legends of single-axis figures
# ---------------------------------------------------------------------------

def test_single_axis_figures_keep_their_legends_inside(spectra, grip, nominal, delayed):
    # One panel column is 3.5 in wide: every legend entry must be drawn within it.
    legend_inside(figures.bode_figure(spectra, grip, axis="x"))
    legend_inside(figures.uncertainty_figure(spectra, nominal, table3_weights(), axis="y"))
    base = params_table(table1()[table1().axis == "x"])
    legend_inside(figures.residual_figure(delayed, base, axis="x"))
    legend_inside(figures.literature_figure(grip.iloc[0]))
    legend_inside(figures.stability_figure(grip[grip.axis == "z"]))
    # and the three-axis figures as before
    legend_inside(figures.bode_figure(spectra, grip))


def test_plot_commands_single_axis_legends_inside(tmp_path, monkeypatch, runner, spectra,
                                                  grip, nominal):
    # `armfit plot bode --axis x` and `plot uncertainty --axis y`: the figure each writes,
    # captured before saving.
    sp, g, n = tmp_path / "s.parquet", tmp_path / "g.csv", tmp_path / "n.csv"
    Spectra.from_frame(spectra, meta={}).write(sp)
    write_params(grip, g)
    write_params(nominal, n)
    made: list[Figure] = []
    save = figures.save_figure
    monkeypatch.setattr(figures, "save_figure",
                        lambda fig, path, **kw: (made.append(fig), save(fig, path, **kw))[1])
    for args in (["bode", str(sp), "--model", str(g), "--axis", "x"],
                 ["uncertainty", str(sp), "--nominal", str(n), "--axis", "y"]):
        r = runner.invoke(cli, ["plot", *args, "-o", str(tmp_path / f"{args[0]}.png")])
        assert r.exit_code == 0, r.output
    assert len(made) == 2
    for fig in made:
        legend_inside(fig)
    texts = legend_texts(made[0])
    assert "1 N: mean ± SE" in texts and "single trials" in texts


# ---------------------------------------------------------------------------
# Residual figure: shading, scale and minus signs
# ---------------------------------------------------------------------------

def test_failing_spans_analytic():
    # Drawn straight between points on a log frequency axis: z = 0, 4, 0 at 1, 10, 100 Hz
    # crosses 2 half-way in log f, at sqrt(10) and sqrt(1000) Hz.
    close(figures.failing_spans([1.0, 10.0, 100.0], [0.0, 4.0, 0.0]),
          [(10 ** 0.5, 10 ** 1.5)])
    # Two curves: the union of where either is outside. The second, 0 to -3 between 10
    # and 100 Hz, crosses -2 two thirds of the way: from 10^(5/3) Hz to the end.
    got = figures.failing_spans([1.0, 10.0, 100.0], [[0.0, 4.0, 0.0], [0.0, 0.0, -3.0]])
    close(got, [(10 ** 0.5, 10 ** 1.5), (10 ** (5 / 3), 100.0)])
    got = figures.failing_spans([1.0, 10.0, 100.0], [[0.0, 4.0, 0.0], [0.0, 0.0, -5.0]])
    close(got, [(10 ** 0.5, 100.0)])     # -5: from 10^1.4 Hz, joining the first span
    # A jump from +5 to -5 between two points passes through the band: two spans.
    got = figures.failing_spans([1.0, 10.0], [5.0, -5.0])
    close(got, [(1.0, 10 ** 0.3), (10 ** 0.7, 10.0)])
    # On a symlog axis (linthresh 10, base 10, linscale 1) the drawn segment from 0 to
    # 100 is straight in the transformed coordinate: it crosses 2 where that coordinate
    # reaches T(2), i.e. at the fraction T(2)/T(100) of the segment.
    tr = SymmetricalLogTransform(10, 10, 1)
    frac = tr.transform(np.array([2.0]))[0] / tr.transform(np.array([100.0]))[0]
    got = figures.failing_spans([1.0, 10.0], [0.0, 100.0], forward=tr.transform)
    close(got, [(10 ** frac, 10.0)])
    assert figures.failing_spans([1.0, 10.0], [1.0, -1.5]) == []


def _expected_spans(ax, gid_prefix: str) -> list[tuple[float, float]]:
    """Where the drawn solid curves of ``ax`` are outside ±2, found independently on a
    fine grid: each line interpolated linearly in (log f, scale coordinate)."""
    tr = ax.yaxis.get_transform()
    t2 = tr.transform(np.array([2.0, -2.0]))
    u = None
    bad = None
    for ln in lines(ax, gid_prefix):
        f, z = (np.asarray(v, float) for v in ln.get_data())
        if u is None:
            u = np.linspace(np.log(f[0]), np.log(f[-1]), 200001)
            bad = np.zeros(u.size, bool)
        y = np.interp(u, np.log(f), tr.transform(z))
        bad |= (y > t2[0]) | (y < t2[1])
    edges = np.flatnonzero(np.diff(np.concatenate([[0], bad.astype(int), [0]])))
    starts, ends = edges[::2], edges[1::2]
    return [(float(np.exp(u[a])), float(np.exp(u[b - 1])))
            for a, b in zip(starts, ends, strict=True)]


def test_residual_shading_is_where_the_plotted_curve_fails(delayed):
    rows = table1()[table1().axis == "x"]
    base = params_table(rows)
    with_delay = params_table(rows, effects={"delay.delay_s": 0.01}, effect_name="delay")
    fig = drawn(figures.residual_figure(delayed, base, with_delay, axis="x"))
    for ax in fig.axes:
        got = spans(ax, "failing:x")
        want = _expected_spans(ax, "model:x")   # the solid curves, not the dashed model
        assert want, "the base model leaves the noise band on this study"
        assert len(got) == len(want)
        for (g0, g1), (w0, w1) in zip(got, want, strict=True):
            # the fine grid's step in log f is 2.5e-5: edges agree within it
            assert np.log(g0) == pytest.approx(np.log(w0), abs=1e-4)
            assert np.log(g1) == pytest.approx(np.log(w1), abs=1e-4)
    assert "solid model outside the noise band (|residual| > 2 SE)" in legend_texts(fig)


def test_run_and_plot_residual_shade_alike(tmp_path, monkeypatch, runner, delayed):
    # `armfit run` asks for its residual figure without bands (recorded here from its
    # residual stage), as `armfit plot residual` does without --band: both shade where
    # the plotted curve fails.
    from armfit import pipeline
    calls = []
    base = params_table(table1()[table1().axis == "x"])
    stub = SimpleNamespace(drawings=SimpleNamespace(
        draw=lambda folder, name, fn, *a, **kw: calls.append((fn, a, kw)) or name))
    models = SimpleNamespace(base_nominal=None, nominal=SimpleNamespace(table=base))
    diagnosed = SimpleNamespace(adoption=SimpleNamespace(adopted_axes=()),
                                diagnosis=SimpleNamespace(axes=(SimpleNamespace(axis="x"),)))
    pipeline._residuals(SimpleNamespace(folder=tmp_path), stub, delayed, models, diagnosed)
    ((fn, args, kw),) = calls
    assert fn == "residual_figure" and kw == {"axis": "x"}
    run_fig = getattr(figures, fn)(*args, **kw)
    sp, m = tmp_path / "s.parquet", tmp_path / "m.csv"
    Spectra.from_frame(delayed, meta={}).write(sp)
    write_params(base, m)
    made: list[Figure] = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, path, **kw: made.append(fig))
    r = runner.invoke(cli, ["plot", "residual", str(sp), "--model", str(m), "--axis", "x",
                            "-o", str(tmp_path / "r.png")])
    assert r.exit_code == 0, r.output
    for a, b in zip(run_fig.axes, made[0].axes, strict=True):
        close(spans(a, "failing:"), spans(b, "failing:"))
        assert spans(a, "failing:")


def test_residual_phase_scale_is_labelled_and_minus_signs_are_one_kind(delayed):
    base = params_table(table1()[table1().axis == "x"])
    fig = drawn(figures.residual_figure(delayed, base, axis="x"))
    mag, ph = fig.axes
    # the base model's phase residual reaches 108 deg / 1 deg-scale SE: symlog, said so
    assert ph.get_yscale() == "symlog"
    assert "linear within ±10, log beyond" in ph.get_ylabel()
    assert len(lines(ph, "symlog-edge")) == 2
    labels = [t.get_text() for t in ph.get_yticklabels() if t.get_text()]
    # 1-2-5 steps labelled beyond the linear band, with the typographic minus
    assert "\u221220" in labels and "\u2212100" in labels and "0" in labels
    for f in (fig, figures.bode_figure(delayed, base), figures.stability_figure(base)):
        for ax in drawn(f).axes:
            for t in ax.get_xticklabels() + ax.get_yticklabels():
                text = t.get_text()
                if text and not text.startswith("$"):   # mathtext draws its own minus
                    assert "-" not in text, text


# ---------------------------------------------------------------------------
# Fig. 5
# ---------------------------------------------------------------------------

def test_bode_model_is_a_distinct_solid_line_and_grips_stay_apart(spectra, grip):
    fig = drawn(figures.bode_figure(spectra, grip, axis="x"))
    mag = fig.axes[0]
    markers, places = set(), []
    for g in ("1N", "2N", "3N"):
        (mean,) = lines(mag, f"mean:x:{g}")
        (fit,) = lines(mag, f"fit:x:{g}")
        assert fit.get_linestyle() == "-"          # the model: solid
        assert mean.get_marker() not in (None, "None", "")
        # a darker shade of the grip's colour: each channel 0.55 of the mean's
        np.testing.assert_allclose(to_rgb(fit.get_color()),
                                   0.55 * np.asarray(to_rgb(mean.get_color())))
        assert fit.get_zorder() > mean.get_zorder()
        markers.add(mean.get_marker())
        first, step = mean.get_markevery()
        x = mean.get_xdata()[first::step]
        places.append(set(np.round(np.log10(x), 9)))
    assert len(markers) == 3                          # one marker shape per grip
    # the grips' markers stand at different frequencies: none on another's
    assert not (places[0] & places[1]) and not (places[1] & places[2]) \
        and not (places[0] & places[2])


def test_bode_model_dashed_beyond_its_fit_band(spectra, grip):
    # Z rows fitted on 0.1-10 Hz (the paper's Z band): solid there, dashed above.
    p = grip.copy()
    p["band_lo_hz"] = 0.1
    p["band_hi_hz"] = np.where(p.axis == "z", 10.0, 30.0)
    fig = figures.bode_figure(spectra, p, axis="z")
    mag = fig.axes[0]
    (inside,) = lines(mag, "fit:z:1N")
    (outside,) = lines(mag, "fit-outside:z:1N")
    f_in = inside.get_xdata()
    assert f_in.min() == pytest.approx(0.1) and f_in.max() == pytest.approx(10.0)
    f_out, y_out = (np.asarray(v, float) for v in outside.get_data())
    shown = np.isfinite(y_out)
    assert f_out[shown].min() == pytest.approx(10.0) and f_out[shown].max() == pytest.approx(
        30.0)
    assert outside.get_linestyle() not in ("-", "solid")
    # the dashed part is eq. 4 with Table I's Z 1 N row (Ma=4.374, k1=4877, k2=200.4,
    # b1=55.85, b2=32.96), Mp = 0.091 kg
    k = np.flatnonzero(shown)[-1]
    assert y_out[k] == pytest.approx(
        20 * np.log10(abs(h_cl(f_out[k], 4.374, 4877, 200.4, 55.85, 32.96, 0.091))),
        abs=1e-6)
    assert "model beyond its fit band" in legend_texts(fig)
    # a row without a band: solid throughout, nothing dashed
    fig = figures.bode_figure(spectra, grip, axis="z")
    assert not lines(fig.axes[0], "fit-outside:")


def test_bode_draws_each_shared_estimate_once(spectra, grip):
    # The X 1 N mean's first five points share one estimate (one coherence value, as
    # grid points that average the same native bins do): it is drawn once, at the run's
    # middle point (index 2); every other point is its own estimate.
    sp = spectra.copy()
    m = (sp.level == "mean") & (sp.axis == "x") & (sp.grip_N == 1)
    coh = np.linspace(0.5, 0.9, F.size)
    coh[:5] = 0.6
    sp.loc[m, "coherence"] = coh
    fig = figures.bode_figure(sp, grip, axis="x")
    (line,) = lines(fig.axes[0], "mean:x:1N")
    keep = np.r_[2, np.arange(5, F.size)]
    np.testing.assert_allclose(line.get_xdata(), F[keep])
    np.testing.assert_allclose(line.get_ydata(), sp.loc[m, "mag_db"].to_numpy()[keep],
                               atol=1e-12)
    assert list(figures.independent_points([0.6, 0.6, 0.6, 0.7, np.nan, np.nan])) == \
        [1, 3, 4, 5]


# ---------------------------------------------------------------------------
# Figs. 6 and 7
# ---------------------------------------------------------------------------

def test_uncertainty_axis_says_relative_and_dimensionless(spectra, nominal):
    fig = figures.uncertainty_figure(spectra, nominal, table3_weights(), axis="x")
    label = fig.axes[2].get_ylabel()
    assert "Relative uncertainty" in label and "dimensionless" in label


def test_literature_legend_names_sources():
    by_name = {m.name: m for m in literature_models()}
    # the paper's Sec. IV: "Speich et al. [18], Kosuge et al. [13], Lawrence [12], and
    # Tsuji et al. [10]"
    assert by_name["Speich X"].label == "Speich et al. [18] 2005, X axis"
    assert by_name["Kosuge"].label == "Kosuge et al. [13] 1993"
    assert by_name["Lawrence"].label == "Lawrence [12]"          # no year recorded
    assert by_name["Tsuji"].label == "Tsuji et al. [10] 1995"
    fig = figures.literature_figure(params_table(table1()).iloc[0])
    texts = legend_texts(fig)
    assert "Speich et al. [18] 2005, Z axis" in texts
    assert "[n]: reference n of Fu & Çavuşoğlu, ICRA 2010" in texts


# ---------------------------------------------------------------------------
# Stability figure
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def population() -> pd.DataFrame:
    """Table I's rows as a population of three subjects (each grip's row per subject,
    k1 scaled by 0.9, 1.0, 1.1), with subject and row columns as fit-trials writes."""
    rows = []
    for i, subj in enumerate(("s01", "s02", "s03")):
        t = table1().assign(subject=subj)
        t["k1"] = t["k1"] * (0.9 + 0.1 * i)
        rows.append(t)
    p = params_table(pd.concat(rows, ignore_index=True))
    p["subject"] = [s for s in ("s01", "s02", "s03") for _ in range(9)]
    return p


def test_stability_figure_reads_plainly(population):
    fig = drawn(figures.stability_figure(population))
    renderer = fig.canvas.get_renderer()
    assert fig._suptitle is None                        # no title over one row only
    top = fig.axes[:3]
    bottom = fig.axes[3:]
    for ax, axis in zip(top, "xyz", strict=True):
        assert "wall at T = 1 ms, d = 1, B = 0 N·s/m" in ax.get_title()
        assert ax.get_ylim()[0] == 0.0                  # K_max from 0
        # the minimum's value is written off the dashed line, not on it
        (kmin,) = lines(ax, f"kmin:{axis}")
        y_line = ax.transData.transform((0, kmin.get_ydata()[0]))[1]
        (label,) = [t for t in ax.texts if t.get_gid() == f"kmin-label:{axis}"]
        bb = label.get_window_extent(renderer)
        assert not (bb.y0 <= y_line <= bb.y1)
        # no marker on another: each (subject, grip) at its own x
        xs = [ln.get_xdata()[0] for ln in lines(ax, f"kmax:{axis}")]
        assert len(xs) == 9 and len(set(np.round(xs, 9))) == 9
        marks = {ln.get_marker() for ln in lines(ax, f"kmax:{axis}")}
        assert len(marks) == 3
    for ax in bottom:
        assert "B = 0 N·s/m" in ax.get_title()
        assert ax.get_yscale() == "log" or ax.get_ylim()[0] == 0.0
        assert lines(ax, "top-row-rate:")[0].get_xdata()[0] == pytest.approx(1000.0)
    texts = legend_texts(fig)
    assert "1/T of the top row (1000 Hz)" in texts
    assert "delay d = 0 samples: lowest model" in texts
    assert "delay d = 1 sample: lowest model" in texts
    assert "shaded: range over the models" in texts
    assert "lowest K_max of the models" in texts
    assert not any("(band: range)" in t for t in texts)


def test_stability_sweep_spanning_decades_is_log_and_says_so():
    # Table II's models alone: K_max grows about 40-fold from 250 Hz to 10 kHz (d = 0),
    # so the sweep is drawn on a log K_max axis, labelled as such.
    fig = drawn(figures.stability_figure(armfit.stability("nominal")))
    bottom = fig.axes[3:]
    assert all(ax.get_yscale() == "log" for ax in bottom)
    assert bottom[0].get_ylabel() == "K_max (kN/m, log scale)"


# ---------------------------------------------------------------------------
# Result objects: plot, notebook display, figure functions, the package's names
# ---------------------------------------------------------------------------

def test_modelfit_plot_one_axis(spectra, grip):
    fit = armfit.ModelFit(grip, "grip", spectra=Spectra.of(spectra))
    fig = fit.plot(axis="x")                       # the Bode pair of X, Fig. 5's column
    assert isinstance(fig, Figure) and len(fig.axes) == 2
    gids = {ln.get_gid() for a in fig.axes for ln in a.get_lines() if ln.get_gid()}
    assert {g for g in gids if g.startswith("fit:")} == {"fit:x:1N", "fit:x:2N", "fit:x:3N"}
    # one Axes: one panel (the magnitude by default; the phase when asked)
    canvas = Figure()
    FigureCanvasAgg(canvas)
    ax = canvas.add_subplot()
    assert fit.plot(axis="y", ax=ax) is ax
    (line,) = lines(ax, "fit:y:2N")
    f, y = line.get_data()
    k = len(f) // 2
    # eq. 4 with Table I's Y 2 N row (0.2984, 84.85, 779.8, 7.632, 4.919; Mp 0.095)
    h = h_cl(f[k], 0.2984, 84.85, 779.8, 7.632, 4.919, 0.095)
    assert y[k] == pytest.approx(20 * np.log10(abs(h)), abs=1e-9)
    ax2 = canvas.add_subplot(2, 1, 2)
    fit.plot(axis="y", ax=ax2, panel="phase")
    assert lines(ax2, "fit:y:2N")[0].get_ydata()[k] == pytest.approx(
        np.degrees(np.angle(h)), abs=1e-6)
    # two Axes: both panels
    pair = Figure().subplots(2)
    fit.plot(axis="z", ax=pair)
    assert lines(pair[0], "fit:z:3N") and lines(pair[1], "fit:z:3N")
    with pytest.raises(UsageError, match="choose one with axis="):
        fit.plot(ax=ax)
    with pytest.raises(UsageError, match="give as many Axes"):
        fit.plot(axis="x", ax=ax, panel="both")
    with pytest.raises(UsageError, match="panel must be one of"):
        fit.plot(axis="x", panel="bode")
    # without spectra: the models alone
    bare = armfit.ModelFit(grip, "grip").plot(axis="x")
    assert lines(bare.axes[0], "fit:x:1N") and not lines(bare.axes[0], "mean:")


def test_spectra_plot_bode_pair(spectra):
    means = Spectra.of(spectra).select(axis="x", kind="measured", level="mean")
    fig = means.plot()
    mag, ph = fig.axes
    assert mag.get_ylabel() == "Magnitude (dB re 1 m/N)" and ph.get_ylabel() == "Phase (deg)"
    assert len(mag.get_lines()) == 3 and len(ph.get_lines()) == 3
    np.testing.assert_allclose(ph.get_lines()[0].get_ydata(), means.phase_deg[0])
    ax = Figure().add_subplot()
    assert means.plot(ax=ax) is ax
    np.testing.assert_allclose(ax.get_lines()[1].get_ydata(), means.mag_db[1])
    with pytest.raises(UsageError, match="choose one with axis="):
        Spectra.of(spectra).plot()


def test_uncertainty_diagnosis_stability_plots(spectra, nominal):
    sp = Spectra.of(spectra)
    unc = armfit.fit_uncertainty(sp.select(axis="y"), nominal[nominal.axis == "y"])
    fig = unc.plot()                               # one axis held: Fig. 6 of Y
    assert len(fig.axes) == 3
    ax = Figure().add_subplot()
    unc.plot(ax=ax)                                # one Axes: W_max and |Wu|
    assert lines(ax, "wmax:y") and lines(ax, "wu:y")
    # Diagnosis.plot draws the residuals of its model on the axes it diagnosed
    diag = armfit.Diagnosis((SimpleNamespace(axis="x"),), sp,
                            armfit.ModelFit(params_table(table1()), "grip"))
    pair = Figure().subplots(2)
    diag.plot(ax=pair)
    assert len(lines(pair[0], "model:x:")) == 3 and len(lines(pair[1], "model:x:")) == 3
    st = armfit.stability("nominal")
    ax = Figure().add_subplot()
    st.plot(axis="z", ax=ax)                       # K_max of the Z model
    (k,) = lines(ax, "kmax:z")
    assert k.get_ydata()[0] * 1e3 == pytest.approx(
        float(st.table.loc[st.table.axis == "z", "k_max_N_per_m"].iloc[0]))
    assert len(st.plot(axis="x").axes) == 2


def test_figure_functions_take_result_objects(spectra, grip, nominal):
    sp = Spectra.of(spectra)
    fit = armfit.ModelFit(grip, "grip")
    a = figures.bode_figure(sp, fit, axis="y")
    b = figures.bode_figure(spectra, grip, axis="y")
    np.testing.assert_array_equal(lines(a.axes[0], "fit:y:1N")[0].get_ydata(),
                                  lines(b.axes[0], "fit:y:1N")[0].get_ydata())
    nom = armfit.ModelFit(nominal, "nominal")
    fig = figures.uncertainty_figure(sp, nom, table3_weights(), axis="z")
    (line,) = lines(fig.axes[0], "nominal:z")
    f, y = line.get_data()
    # eq. 3 with Table II's Z row (1.628, 564.7, 130.6, 37.14, 35.36)
    assert y[7] == pytest.approx(20 * np.log10(abs(h_arm(f[7], 1.628, 564.7, 130.6, 37.14,
                                                         35.36))), abs=1e-9)
    assert figures.residual_figure(sp, fit, axis="x").axes
    st = armfit.stability(nom)
    fig = figures.stability_figure(st)
    assert {ln.get_gid() for a in fig.axes for ln in lines(a, "kmin:")} == {
        "kmin:x", "kmin:y", "kmin:z"}


def test_results_show_a_compact_escaped_table(spectra, grip):
    fit = armfit.ModelFit(grip, "grip", source="<b>grip</b>.csv")
    text = fit._repr_html_()
    assert text.startswith("<div>") and "<table" in text
    assert "&lt;b&gt;grip&lt;/b&gt;.csv" in text and "<b>grip</b>" not in text
    assert text.count("<tr>") <= 1 + figures_rows()     # a header and a few rows
    assert "(3 more rows)" in text                      # 9 rows, 6 shown
    sp = Spectra.of(spectra)
    html = sp._repr_html_()
    assert f"{len(sp)} responses × {F.size} frequencies" in html
    st = armfit.stability("nominal")
    assert "3 model(s); T = 1 ms" in st._repr_html_()


def figures_rows() -> int:
    from armfit import api
    return api.HTML_ROWS


def test_package_lists_only_its_public_api():
    assert dir(armfit) == sorted(armfit.__all__)
    assert "import_module" not in dir(armfit) and not hasattr(armfit, "import_module")
    assert not hasattr(armfit, "lazy_exports")
