"""Tests of armfit.figures: the Bode, residual, uncertainty and literature figures.

The inputs are small studies built here in the schemas of armfit's files (spectra table,
parameters CSV, Wu CSV) from the paper's tables: each trial's response is the model of a
Table I row (eq. 4, or eq. 3 for derived arm dynamics) times a seeded log-normal error.
Expected values come from the paper's tables evaluated with the paper's equations, or
from statistics of the constructed inputs computed here with numpy.
"""

from __future__ import annotations

from importlib import resources

import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure

from armfit import figures
from armfit.data import paper_table
from armfit.errors import BadInputError, OutputError, UsageError
from armfit.io.schema import SPECTRA_COLUMNS, params_columns
from armfit.models.arm import DEVICE_MASS_KG, h_arm, h_cl
from armfit.uncertainty import read_wu

#: A small frequency grid (Hz) shared by every row, as in a spectra file.
F = np.geomspace(0.1, 30.0, 40)
SUBJECTS = ("s01", "s02")
BASE = ("Ma", "k1", "k2", "b1", "b2")
TABLE_COLS = {"Ma_kg": "Ma", "k1_N_per_m": "k1", "k2_N_per_m": "k2", "b1_Ns_per_m": "b1",
              "b2_Ns_per_m": "b2"}


def table1() -> pd.DataFrame:
    """Table I with the parameter names of the parameters CSV."""
    return paper_table("grip").rename(columns=TABLE_COLS)


def params_table(rows: pd.DataFrame, *, effects: dict[str, float] | None = None,
                 effect_name: str = "") -> pd.DataFrame:
    """A parameters table in the params-CSV layout (columns of
    :func:`armfit.io.artifacts.params_columns`) from rows of the paper's tables; the
    intervals and fit statistics, which the figures do not read, are left empty."""
    out = rows.copy().reset_index(drop=True)
    for name, value in (effects or {}).items():
        out[name] = value
    out["mp_kg"] = [DEVICE_MASS_KG[a] for a in out["axis"]]
    out["effects"] = effect_name
    out["converged"] = True
    cols = params_columns(list(BASE) + list(effects or {}), grip="grip_N" in out.columns)
    return out.reindex(columns=cols)


def table3_weights() -> dict:
    """The paper's Table III as {axis: WuWeight}, read by the Wu-file reader."""
    with resources.as_file(resources.files("armfit.data")
                           .joinpath("table3_uncertainty_weights.csv")) as path:
        return read_wu(path)


def _rows(h: np.ndarray, **ident) -> pd.DataFrame:
    mag = 20 * np.log10(np.abs(h))
    ph = np.degrees(np.unwrap(np.angle(h)))
    d = {c: np.nan for c in SPECTRA_COLUMNS}
    d.update(level="trial", subject=None, run=pd.NA, out_axis=ident["axis"], method="h1",
             freq_hz=F, re=h.real, im=h.imag, mag_db=mag, phase_deg=ph, n=1, flags="")
    d.update(ident)
    return pd.DataFrame({c: d[c] if np.ndim(d[c]) else [d[c]] * F.size
                         for c in SPECTRA_COLUMNS})


def _aggregate(trials: list[np.ndarray], how: str) -> dict[str, np.ndarray]:
    """Mean (or median) of log-magnitude and unwrapped phase; SE = sample std/sqrt(n)."""
    mag = np.array([20 * np.log10(np.abs(h)) for h in trials])
    ph = np.array([np.degrees(np.unwrap(np.angle(h))) for h in trials])
    centre = np.mean if how == "mean" else np.median
    m, p = centre(mag, axis=0), centre(ph, axis=0)
    h = 10 ** (m / 20) * np.exp(1j * np.radians(p))
    n = len(trials)
    return dict(re=h.real, im=h.imag, mag_db=m, phase_deg=p, n=n,
                se_db=mag.std(axis=0, ddof=1) / np.sqrt(n),
                se_deg=ph.std(axis=0, ddof=1) / np.sqrt(n),
                q25_db=np.percentile(mag, 25, axis=0), q75_db=np.percentile(mag, 75, axis=0),
                q25_deg=np.percentile(ph, 25, axis=0), q75_deg=np.percentile(ph, 75, axis=0))


def study_spectra(axes=("x", "y", "z"), *, noise_db: float = 1.0, noise_deg: float = 3.0,
                  delay_s: float = 0.0, seed: int = 1) -> pd.DataFrame:
    """A spectra table: per axis × grip × subject one measured trial (Table I model,
    eq. 4, times exp(-s delay_s) and a log-normal error) and one derived trial (eq. 3);
    the mean per axis × grip and the median per axis."""
    rng = np.random.default_rng(seed)
    s = 2j * np.pi * F
    parts = []
    for axis in axes:
        pooled = []
        for _, r in table1()[table1()["axis"] == axis].iterrows():
            theta = {k: r[k] for k in BASE}
            grip = float(r["grip_N"])
            measured = []
            for subj in SUBJECTS:
                err = (rng.normal(0, noise_db, F.size) / 20 * np.log(10)
                       + 1j * np.radians(rng.normal(0, noise_deg, F.size)))
                h = h_cl(F, **theta, mp=DEVICE_MASS_KG[axis]) * np.exp(-s * delay_s + err)
                measured.append(h)
                parts.append(_rows(h, axis=axis, grip_N=grip, subject=subj, kind="measured"))
                parts.append(_rows(h_arm(F, **theta) * np.exp(err), axis=axis, grip_N=grip,
                                   subject=subj, kind="derived", method="tfestimate"))
            pooled += measured
            parts.append(_rows(np.ones(F.size), axis=axis, grip_N=grip, kind="measured")
                         .assign(level="mean", **_aggregate(measured, "mean")))
        parts.append(_rows(np.ones(F.size), axis=axis, grip_N=np.nan, kind="measured")
                     .assign(level="median", **_aggregate(pooled, "median")))
    return pd.concat(parts, ignore_index=True)


@pytest.fixture(scope="module")
def spectra() -> pd.DataFrame:
    return study_spectra()


@pytest.fixture(scope="module")
def grip_params() -> pd.DataFrame:
    return params_table(table1())


def lines(ax, prefix: str) -> list:
    return [ln for ln in ax.get_lines() if (ln.get_gid() or "").startswith(prefix)]


def trial_sets(ax, prefix: str = "trial:") -> list[LineCollection]:
    """The single-trial LineCollections of a panel whose gid starts with ``prefix``."""
    return [c for c in ax.collections if isinstance(c, LineCollection)
            and (c.get_gid() or "").startswith(prefix)]


def n_trials(ax, prefix: str = "trial:") -> int:
    return sum(len(c.get_segments()) for c in trial_sets(ax, prefix))


def legend_texts(fig: Figure) -> list[str]:
    out = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
    for ax in fig.axes:
        if ax.get_legend() is not None:
            out += [t.get_text() for t in ax.get_legend().get_texts()]
    return out


# ---------------------------------------------------------------------------
# bode
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bode(spectra, grip_params) -> Figure:
    return figures.bode_figure(spectra, grip_params)


def test_bode_layout_and_labels(bode):
    axs = np.array(bode.axes).reshape(2, 3)
    assert [ax.get_title() for ax in axs[0]] == [figures.AXIS_TITLES[a] for a in "xyz"]
    assert axs[0, 0].get_ylabel() == "Magnitude (dB re 1 m/N)"
    assert axs[1, 0].get_ylabel() == "Phase (deg)"
    assert all(ax.get_xlabel() == "Frequency (Hz)" for ax in axs[1])
    assert all(ax.get_xscale() == "log" for ax in axs.flat)
    # One column per panel of 3.5 in, the journal column width.
    assert bode.get_figwidth() == pytest.approx(3 * 3.5)
    texts = legend_texts(bode)
    for g in (1, 2, 3):
        assert f"{g} N: mean ± SE" in texts
        assert f"{g} N: model" in texts
    assert "single trials" in texts


def test_bode_line_counts(bode):
    # 2 subjects x 3 grips trials (one collection per grip), 3 grip means and 3 grip fits
    # per panel (Table I rows).
    for ax in bode.axes:
        assert n_trials(ax) == 6 and len(trial_sets(ax)) == 3
        assert n_trials(ax, "trial:x:1N") == (2 if ax in bode.axes[::3] else 0)
        assert len(lines(ax, "mean:")) == 3
        assert len(lines(ax, "fit:")) == 3


def test_bode_model_lines_on_top_of_the_data(bode):
    # Every model line is drawn above every data artist (trials, means, bands).
    for ax in bode.axes:
        fits = lines(ax, "fit:")
        data = lines(ax, "mean:") + trial_sets(ax) + [
            c for c in ax.collections if (c.get_gid() or "").startswith("band:")]
        assert min(f.get_zorder() for f in fits) > max(d.get_zorder() for d in data)


def test_bode_trial_curves_are_the_rows(bode, spectra):
    # The X 2 N collection holds subject s01's then s02's rows (sorted), as stored.
    (coll,) = trial_sets(bode.axes[0], "trial:x:2N")
    rows = spectra[(spectra.level == "trial") & (spectra.kind == "measured")
                   & (spectra.axis == "x") & (spectra.grip_N == 2)]
    segs = coll.get_segments()
    for seg, (_, g) in zip(segs, rows.groupby("subject"), strict=True):
        np.testing.assert_allclose(seg[:, 0], g.freq_hz.to_numpy())
        np.testing.assert_allclose(seg[:, 1], g.mag_db.to_numpy(), atol=1e-12)


def test_bode_phase_slip_is_moved_by_whole_turns(spectra, grip_params):
    # One X 1 N trial stored a turn off (its phase starting on the +180 branch, as a
    # noisy first point gives) and with a second 2 pi slip at 3 Hz: drawn, it is unwrapped
    # from its low-frequency end and moved by whole turns, so that it ends within 180
    # deg of the model (eq. 4, Table I X 1 N) and equals the stored curve less 360 deg.
    slipped = spectra.copy()
    m = ((slipped.level == "trial") & (slipped.kind == "measured") & (slipped.axis == "x")
         & (slipped.grip_N == 1) & (slipped.subject == "s01"))
    stored = slipped.loc[m, "phase_deg"].to_numpy()
    f = slipped.loc[m, "freq_hz"].to_numpy()
    bumped = stored + 360.0 + np.where(f > 3.0, 360.0, 0.0)  # 1 turn off, then 2
    slipped.loc[m, "phase_deg"] = bumped
    fig = figures.bode_figure(slipped, grip_params, axis="x")
    ph_ax = fig.axes[1]
    (coll,) = trial_sets(ph_ax, "trial:x:1N")
    seg = coll.get_segments()[0]  # s01
    model = h_cl(f, 0.1925, 85.48, 704.2, 7.410, 2.477, 0.09)
    model_deg = np.degrees(np.unwrap(np.angle(model)))
    assert abs(seg[-1, 1] - model_deg[-1]) < 180.0
    np.testing.assert_allclose(seg[:, 1], stored, atol=1e-9)
    # The same slip with no model: the curve joins the other trials instead.
    fig = figures.bode_figure(slipped, None, axis="x")
    (coll,) = trial_sets(fig.axes[1], "trial:x:1N")
    np.testing.assert_allclose(coll.get_segments()[0][:, 1], stored, atol=1e-9)


def test_bode_mean_band_moves_with_its_curve(spectra, grip_params):
    # A mean stored a turn off is drawn a turn back, with its quartile band.
    moved = spectra.copy()
    m = (moved.level == "mean") & (moved.axis == "z") & (moved.grip_N == 3)
    rows = moved[m]
    for c in ("phase_deg", "q25_deg", "q75_deg"):
        moved.loc[m, c] = moved.loc[m, c] - 360.0
    fig = figures.bode_figure(moved, grip_params, axis="z", band="quartiles")
    (line,) = lines(fig.axes[1], "mean:z:3N")
    np.testing.assert_allclose(line.get_ydata(), rows.phase_deg.to_numpy(), atol=1e-9)
    (band,) = [c for c in fig.axes[1].collections if c.get_gid() == "band:z:3N"]
    y = band.get_paths()[0].vertices[:, 1]
    assert y.max() == pytest.approx(rows.q75_deg.max(), abs=1e-9)


def test_bode_fit_line_is_eq4_of_table1(bode):
    # The Y-axis 2 N fit line equals eq. 4 with Table I's Y 2 N row (Ma=0.2984, k1=84.85,
    # k2=779.8, b1=7.632, b2=4.919, Mp=0.095): same numbers, evaluated independently.
    mag_ax, ph_ax = bode.axes[1], bode.axes[4]
    (mag_line,) = [ln for ln in lines(mag_ax, "fit:y:2N")]
    (ph_line,) = [ln for ln in lines(ph_ax, "fit:y:2N")]
    f, y = mag_line.get_data()
    k = len(f) // 2
    h = h_cl(f[k], 0.2984, 84.85, 779.8, 7.632, 4.919, 0.095)
    assert y[k] == pytest.approx(20 * np.log10(abs(h)), abs=1e-9)
    assert ph_line.get_ydata()[k] == pytest.approx(np.degrees(np.angle(h)), abs=1e-6)
    # Relative degree 2 of eq. 4: phase heads to -180 deg; at 30 Hz it is past -90.
    assert ph_line.get_ydata()[-1] < -90


def test_bode_mean_line_and_se_band_are_the_aggregate_rows(bode, spectra):
    # The thick 1 N X line is the "mean" rows; the band spans mean ± se_db.
    rows = spectra[(spectra.level == "mean") & (spectra.axis == "x") & (spectra.grip_N == 1)]
    (line,) = lines(bode.axes[0], "mean:x:1N")
    np.testing.assert_allclose(line.get_ydata(), rows.mag_db.to_numpy(), rtol=0, atol=1e-12)
    (band,) = [c for c in bode.axes[0].collections if c.get_gid() == "band:x:1N"]
    y = band.get_paths()[0].vertices[:, 1]
    assert y.max() == pytest.approx((rows.mag_db + rows.se_db).max(), abs=1e-9)
    assert y.min() == pytest.approx((rows.mag_db - rows.se_db).min(), abs=1e-9)


def test_bode_quartile_band_one_axis(spectra, grip_params):
    fig = figures.bode_figure(spectra, grip_params, axis="z", band="quartiles")
    assert len(fig.axes) == 2
    rows = spectra[(spectra.level == "mean") & (spectra.axis == "z") & (spectra.grip_N == 3)]
    (band,) = [c for c in fig.axes[1].collections if c.get_gid() == "band:z:3N"]
    assert isinstance(band, PolyCollection)
    y = band.get_paths()[0].vertices[:, 1]
    assert y.max() == pytest.approx(rows.q75_deg.max(), abs=1e-9)
    assert y.min() == pytest.approx(rows.q25_deg.min(), abs=1e-9)
    assert "1 N: mean quartiles" in legend_texts(fig)


def test_bode_fit_includes_effects(spectra):
    # A row with the delay effect: X/F gets exp(-s tau), so the phase of the fit line is
    # that of eq. 4 minus 360 f tau degrees (tau = 0.01 s) and the magnitude unchanged.
    rows = table1()[(table1().axis == "x") & (table1().grip_N == 1)]
    p = params_table(rows, effects={"delay.delay_s": 0.01}, effect_name="delay")
    fig = figures.bode_figure(spectra, p, axis="x")
    (ph,) = lines(fig.axes[1], "fit:x:1N")
    f, y = ph.get_data()
    k = np.searchsorted(f, 20.0)
    h = h_cl(f[k], 0.1925, 85.48, 704.2, 7.410, 2.477, 0.09)
    expected = np.degrees(np.unwrap(np.angle(
        h_cl(f, 0.1925, 85.48, 704.2, 7.410, 2.477, 0.09))))[k] - 360 * f[k] * 0.01
    assert y[k] == pytest.approx(expected, abs=1e-6)
    (mag,) = lines(fig.axes[0], "fit:x:1N")
    assert mag.get_ydata()[k] == pytest.approx(20 * np.log10(abs(h)), abs=1e-9)
    assert "1 N: model + delay" in legend_texts(fig)


def test_bode_errors(spectra, grip_params):
    with pytest.raises(UsageError, match="band must be"):
        figures.bode_figure(spectra, grip_params, band="iqr")
    only_x = spectra[spectra.axis == "x"]
    with pytest.raises(BadInputError, match="no measured responses for axis y"):
        figures.bode_figure(only_x, grip_params, axis="y")
    p = grip_params.drop(columns=["k1"])
    with pytest.raises(BadInputError, match="column 'k1'"):
        figures.bode_figure(spectra, p)
    p = grip_params.copy()
    p.loc[2, "k2"] = np.nan
    with pytest.raises(BadInputError, match="column 'k2': axis x: parameter is empty"):
        figures.bode_figure(spectra, p)


# ---------------------------------------------------------------------------
# residual
# ---------------------------------------------------------------------------

def noise_se(se: np.ndarray, cap: float, floor: float) -> np.ndarray:
    """The noise model's standard errors (docs/methods.md, "The noise model"), computed
    here independently: capped, the variance averaged over 9 bins (the edge values
    repeated beyond the grid), floored."""
    var = np.pad(np.minimum(se, cap) ** 2, 4, mode="edge")
    pooled = np.convolve(var, np.ones(9) / 9, mode="valid")
    return np.maximum(np.sqrt(pooled), floor)


def test_normalised_residual_values(spectra):
    # A wrong model (Table I's X 1 N row with k1 doubled) against the 1 N mean:
    # z = (mean mag_db - 20 log10|H_CL|) / se_db, H_CL of eq. 4 evaluated here, se_db the
    # noise model's (cap 5.57 dB / 103.9 deg, pooled over 9 bins, floor 0.01 dB / 0.06 deg).
    rows = table1()[(table1().axis == "x") & (table1().grip_N == 1)].copy()
    rows["k1"] *= 2
    res = figures.normalised_residuals(spectra, params_table(rows), "x")
    mean = spectra[(spectra.level == "mean") & (spectra.axis == "x") & (spectra.grip_N == 1)]
    h = h_cl(F, 0.1925, 2 * 85.48, 704.2, 7.410, 2.477, 0.09)
    se_db = noise_se(mean.se_db.to_numpy(), 5.57, 0.01)
    se_deg = noise_se(mean.se_deg.to_numpy(), 103.9, 0.06)
    expected = (mean.mag_db.to_numpy() - 20 * np.log10(np.abs(h))) / se_db
    assert res.grips == (1.0,)
    np.testing.assert_allclose(res.z_db[0], expected, rtol=1e-9)
    dphi = mean.phase_deg.to_numpy() - np.degrees(np.angle(h))
    dphi = (dphi + 180) % 360 - 180
    np.testing.assert_allclose(res.z_deg[0], dphi / se_deg, rtol=1e-9)
    # the "× noise" of the row: RMS of both z over the whole grid (the row names no band)
    assert res.rms_norm[0] == pytest.approx(
        np.sqrt(np.mean(np.concatenate([expected, dphi / se_deg]) ** 2)), rel=1e-9)


def test_nominal_model_is_compared_with_the_median(spectra):
    # A table without grip_N (Table II layout) is compared with the axis's median rows.
    nominal = paper_table("nominal").rename(columns=TABLE_COLS)
    res = figures.normalised_residuals(spectra, params_table(nominal), "y")
    med = spectra[(spectra.level == "median") & (spectra.axis == "y")]
    h = h_cl(F, 0.4142, 98.27, 421.2, 5.720, 9.766, 0.095)  # Table II, Y axis; eq. 4
    expected = (med.mag_db.to_numpy() - 20 * np.log10(np.abs(h))) / \
        noise_se(med.se_db.to_numpy(), 5.57, 0.01)
    assert res.grips == (None,)
    np.testing.assert_allclose(res.z_db[0], expected, rtol=1e-9)


@pytest.fixture(scope="module")
def delayed():
    """An X-axis study whose true dynamics have a 10 ms delay the base model lacks."""
    return study_spectra(("x",), noise_db=0.3, noise_deg=1.0, delay_s=0.01, seed=3)


def test_residual_figure(delayed):
    rows = table1()[table1().axis == "x"]
    base = params_table(rows)
    with_delay = params_table(rows, effects={"delay.delay_s": 0.01}, effect_name="delay")
    fig = figures.residual_figure(delayed, base, with_delay, bands={"x": [(5.0, 30.0)]})
    top, bot = fig.axes
    assert top.get_ylabel() == "Magnitude residual / SE"
    # the phase axis passes |z| = 30: symlog, its linear band said in its label
    assert bot.get_ylabel() == "Phase residual / SE\n(linear within ±10, log beyond)"
    assert bot.get_xlabel() == "Frequency (Hz)"
    assert len(lines(top, "model:")) == 3 and len(lines(top, "model2:")) == 3
    assert all(ln.get_linestyle() == "--" for ln in lines(bot, "model2:"))
    # Noise band: the axhspan from -2 to 2; failing band: the given 5-30 Hz.
    (noise,) = [p for p in top.patches if p.get_gid() == "noise:x"]
    assert noise.get_path().transformed(noise.get_patch_transform()).vertices[:, 1].min() \
        == pytest.approx(-2.0)
    (fail,) = [p for p in bot.patches if p.get_gid() == "failing:x:5-30"]
    xs = fail.get_path().transformed(fail.get_patch_transform()).vertices[:, 0]
    assert (xs.min(), xs.max()) == pytest.approx((5.0, 30.0))
    texts = legend_texts(fig)
    assert "noise band: |residual| ≤ 2 SE" in texts and "band marked" in texts
    # the legend gives each model's "× noise" over its band (here the whole grid)
    res = figures.normalised_residuals(delayed, with_delay, "x")
    label = f"1 N: model + delay ({res.rms_norm[0]:.2f}× noise, 0.1–30 Hz)"
    assert label in texts
    # The simulator's truth has the delay: the phase residual of the base model grows to
    # 360 * 30 Hz * 0.01 s = 108 deg at 30 Hz, i.e. far outside the noise band, while the
    # model with the delay stays near it (data noise 1 deg per trial).
    z_base = np.abs(lines(bot, "model:x:1N")[0].get_ydata())
    z_delay = np.abs(lines(bot, "model2:x:1N")[0].get_ydata())
    assert z_base[-1] > 20
    # Beyond |z| = 30 the residual axis turns symlog (linear within ±10).
    assert bot.get_yscale() == ("symlog" if z_base.max() > 30 else "linear")
    assert np.sqrt(np.mean(z_delay ** 2)) < 0.2 * np.sqrt(np.mean(z_base ** 2))


def test_residual_missing_aggregate(spectra):
    no_means = spectra[spectra.level != "mean"]
    with pytest.raises(BadInputError, match="no measured rows of level 'mean', grip 1 N"):
        figures.residual_figure(no_means, params_table(table1()), axis="x")


# ---------------------------------------------------------------------------
# uncertainty
# ---------------------------------------------------------------------------

def wu_table3_x(f_hz):
    """|Wu| of Table III's X axis (rad/s pairs) via polynomials from the roots."""
    t = paper_table("uncertainty")
    t = t[t.axis == "x"]
    z = t[t.kind == "zero"]
    p = t[t.kind == "pole"]
    zeros = np.concatenate([z.real + 1j * z.imag, z.real - 1j * z.imag])
    poles = np.concatenate([p.real + 1j * p.imag, p.real - 1j * p.imag])
    s = 2j * np.pi * f_hz
    k = float(t[t.kind == "gain"].real.iloc[0])
    return k * np.polyval(np.poly(zeros), s) / np.polyval(np.poly(poles), s)


@pytest.fixture(scope="module")
def unc(spectra):
    nominal = params_table(paper_table("nominal").rename(columns=TABLE_COLS))
    return figures.uncertainty_figure(spectra, nominal, table3_weights())


def test_uncertainty_figure(unc, spectra):
    axs = np.array(unc.axes).reshape(3, 3)
    assert axs[0, 0].get_ylabel() == "Magnitude (dB re 1 m/N)"
    assert axs[2, 0].get_ylabel() == "Relative uncertainty\n(dB, dimensionless)"
    assert axs[2, 1].get_xlabel() == "Frequency (Hz)"
    for j, a in enumerate("xyz"):
        assert n_trials(axs[0, j], f"trial:{a}") == 6  # 2 subjects x 3 grips
        assert len(lines(axs[0, j], f"nominal:{a}")) == 1
        # the nominal model is drawn over the trials
        (nom,) = lines(axs[1, j], f"nominal:{a}")
        assert nom.get_zorder() > trial_sets(axs[1, j])[0].get_zorder()
        assert len(lines(axs[2, j], f"wmax:{a}")) == 1
        assert len(lines(axs[2, j], f"wu:{a}")) == 1
    texts = legend_texts(unc)
    assert {"nominal H_ARM", "W_max = max over trials |H/H_nom − 1|", "|Wu|"} <= set(texts)
    # Nominal line = eq. 3 with Table II's Z row (Ma=1.628, k1=564.7, k2=130.6,
    # b1=37.14, b2=35.36).
    (nom,) = lines(axs[0, 2], "nominal:z")
    f, y = nom.get_data()
    assert y[7] == pytest.approx(20 * np.log10(abs(h_arm(f[7], 1.628, 564.7, 130.6, 37.14,
                                                         35.36))), abs=1e-9)
    # |Wu| line = Table III X weight (eq. 7, pairs in rad/s), evaluated here from the
    # polynomials of its roots.
    (wu,) = lines(axs[2, 0], "wu:x")
    f, y = wu.get_data()
    np.testing.assert_allclose(y, 20 * np.log10(np.abs(wu_table3_x(f))), atol=1e-9)
    # W_max dots: max over the 6 derived trials of |H/H_nom - 1| (eq. 6), in dB.
    d = spectra[(spectra.kind == "derived") & (spectra.axis == "y")]
    h = np.vstack([g.re.to_numpy() + 1j * g.im.to_numpy()
                   for _, g in d.groupby(["grip_N", "subject"])])
    nom_y = h_arm(F, 0.4142, 98.27, 421.2, 5.720, 9.766)
    (wm,) = lines(axs[2, 1], "wmax:y")
    np.testing.assert_allclose(wm.get_ydata(), 20 * np.log10(np.abs(h / nom_y - 1).max(0)),
                               atol=1e-9)


def test_uncertainty_needs_nominal_row(spectra):
    nominal = params_table(paper_table("nominal").rename(columns=TABLE_COLS))
    with pytest.raises(BadInputError, match="no nominal model row for axis z"):
        figures.uncertainty_figure(spectra, nominal[nominal.axis != "z"], axis="z")


# ---------------------------------------------------------------------------
# literature
# ---------------------------------------------------------------------------

def test_literature_figure():
    row = params_table(table1()).iloc[0]  # Table I, X axis, 1 N
    fig = figures.literature_figure(row)
    mag, ph = fig.axes
    assert mag.get_ylabel() == "Magnitude (dB re 1 m/N)"
    assert ph.get_ylabel() == "Phase (deg)" and ph.get_xlabel() == "Frequency (Hz)"
    # Seven Table IV models plus this study's H_ARM.
    assert len(lines(mag, "literature:")) == 7 and len(lines(mag, "arm-model")) == 1
    texts = legend_texts(fig)
    # each model named by its source (author and year where recorded), else Table IV
    assert {"Speich et al. [18] 2005, X axis", "Speich et al. [18] 2005, Y axis",
            "Speich et al. [18] 2005, Z axis", "Speich et al. [18] 2005, 1 DOF",
            "Kosuge et al. [13] 1993", "Lawrence [12]", "Tsuji et al. [10] 1995"} <= set(texts)
    assert "this study: X axis, 1 N grip" in texts
    (arm,) = lines(mag, "arm-model")
    assert arm.get_linestyle() == "--" and arm.get_color() == "black"  # as in Fig. 7
    f, y = arm.get_data()
    assert y[100] == pytest.approx(20 * np.log10(abs(h_arm(f[100], 0.1925, 85.48, 704.2,
                                                            7.410, 2.477))), abs=1e-9)
    # Table IV: Speich X (eq. 3 with 0.85, 122, 330, 12.9, 12.9) and Kosuge, a
    # three-parameter model 1/(m s^2 + b s + k) with m=11.6, b=17, k=243.
    (speich,) = lines(mag, "literature:Speich-X")
    assert speich.get_ydata()[50] == pytest.approx(
        20 * np.log10(abs(h_arm(f[50], 0.85, 122, 330, 12.9, 12.9))), abs=1e-9)
    (kosuge,) = lines(ph, "literature:Kosuge")
    s = 2j * np.pi * f[300]
    assert kosuge.get_ydata()[300] == pytest.approx(
        np.degrees(np.angle(1 / (11.6 * s * s + 17 * s + 243))) % -360, abs=1e-6)


# ---------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------

MAGIC = {"png": b"\x89PNG\r\n\x1a\n", "pdf": b"%PDF-", "svg": b"<?xml"}


@pytest.mark.parametrize("ext", ["png", "svg", "pdf"])
def test_save_is_deterministic(tmp_path, ext):
    # Two figures built separately from the same input give byte-identical files.
    row = params_table(table1()).iloc[3]
    a, b = tmp_path / f"a.{ext}", tmp_path / f"b.{ext}"
    figures.save_figure(figures.literature_figure(row), a)
    figures.save_figure(figures.literature_figure(row), b)
    data = a.read_bytes()
    assert data.startswith(MAGIC[ext])
    assert data == b.read_bytes()
    # No timestamps: PDF has no CreationDate, PNG no tIME chunk, SVG no dc:date.
    assert b"CreationDate" not in data and b"tIME" not in data and b"<dc:date>" not in data
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary left behind


def test_save_refuses_overwrite_and_bad_extension(tmp_path):
    fig = figures.literature_figure(params_table(table1()).iloc[0])
    out = tmp_path / "fig.png"
    out.write_bytes(b"keep")
    with pytest.raises(OutputError, match="exists; pass overwrite=True"):
        figures.save_figure(fig, out)
    assert out.read_bytes() == b"keep"
    figures.save_figure(fig, out, overwrite=True)
    assert out.read_bytes().startswith(MAGIC["png"])
    with pytest.raises(UsageError, match="unknown figure extension '.jpg'"):
        figures.save_figure(fig, tmp_path / "fig.jpg")
    assert not (tmp_path / "fig.jpg").exists()


@pytest.mark.parametrize("ext", ["svg", "pdf"])
def test_dense_trials_rasterised_and_deterministic(tmp_path, monkeypatch, spectra, ext):
    # Above RASTER_POINTS points per panel the single trials are rasterised inside vector
    # files (lowered here to 10 so the small study crosses it); the file is still
    # byte-identical on a second build, and other lines stay vector.
    monkeypatch.setattr(figures, "RASTER_POINTS", 10)
    paths = []
    for name in ("a", "b"):
        fig = figures.bode_figure(spectra, axis="x")
        assert trial_sets(fig.axes[0])
        assert all(c.get_rasterized() for c in trial_sets(fig.axes[0]))
        assert not any(ln.get_rasterized() for ln in lines(fig.axes[0], "mean:"))
        paths.append(figures.save_figure(fig, tmp_path / f"{name}.{ext}"))
    assert paths[0].read_bytes() == paths[1].read_bytes()
    assert (b"<image" if ext == "svg" else b"/Subtype /Image") in paths[0].read_bytes()
