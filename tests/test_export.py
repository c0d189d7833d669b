"""Fitted models out to python-control, MATLAB and Octave: ``ModelFit.to_control``,
``Uncertainty.to_control``, ``Spectra.to_frd`` and ``armfit export``.

The reference everywhere is armfit's own evaluation of a model at the grid points
(:meth:`armfit.ClosedLoopModel.response` and ``arm_response``, eqs. 3–4 with the
effects' terms, and :meth:`armfit.WuWeight.response`, eq. 7): an exported rational part
must give it back to rounding (rtol 1e-10); a latency's Padé approximant must keep the
magnitude exact and the phase within the bound the docstring of :mod:`armfit.export`
states.
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from locked import unlocked

import armfit
from armfit.cli.main import cli
from armfit.errors import UsageError
from armfit.export import pade_phase_bound_deg, rational_model
from armfit.loop import pade_delay
from armfit.models.params import model_from_params

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "sample_data" / "study"
F_HZ = np.geomspace(0.1, 30.0, 100)          # armfit's default grid, Hz
W = 2 * np.pi * F_HZ                         # the same, rad/s
RTOL = 1e-10

#: Models made by hand with every built-in effect (values inside each parameter's
#: physical range): X with a 12 ms latency and a sensor lag (output stage), Y with the
#: device's mass and damping (device stage) and a resonance (output), Z with a reflex
#: (a delay inside the arm's impedance).
HAND_ROWS = [
    dict(axis="x", Ma=0.2, k1=95.0, k2=714.0, b1=7.7, b2=2.8, mp_kg=0.09,
         effects="delay;lowpass", **{"delay.delay_s": 0.012, "lowpass.cutoff_hz": 40.0}),
    dict(axis="y", Ma=0.3, k1=98.0, k2=670.0, b1=7.8, b2=5.1, mp_kg=0.095,
         effects="device-mass;device-damping;resonance",
         **{"device-mass.mass_kg": 0.12, "device-damping.damping_Ns_per_m": 1.5,
            "resonance.freq_hz": 25.0, "resonance.zeta": 0.1, "resonance.weight": 0.3}),
    dict(axis="z", Ma=3.6, k1=3800.0, k2=160.0, b1=55.0, b2=33.0, mp_kg=0.091,
         effects="reflex", **{"reflex.gain_N_per_m": 200.0, "reflex.delay_s": 0.04}),
]


@pytest.fixture(scope="module")
def control():
    return pytest.importorskip("control")


@pytest.fixture(scope="module")
def hand() -> armfit.ModelFit:
    return armfit.ModelFit.of(pd.DataFrame(HAND_ROWS))


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """sample_data/study: its spectra, nominal (Table II), nominal with a latency, grip
    (Table I) fits and weights, as objects and as the files the commands write (about
    10 s)."""
    root = tmp_path_factory.mktemp("export_study")
    s = armfit.estimate(STUDY, jobs=2)      # (the results do not depend on jobs)
    m = armfit.fit_nominal(s, jobs=2)
    md = armfit.fit_nominal(s, effects=["delay"], jobs=2)
    g = armfit.fit_grip(s, jobs=2)
    files = {"spectra": s.write(root / "spectra.parquet"),
             "nominal": m.write(root / "nominal.csv"),
             "nominal_delay": md.write(root / "nominal_delay.csv"),
             "grip": g.write(root / "grip.csv")}
    # Wu of the nominal as its file holds it (10 digits), as fit-uncertainty fits it
    u = armfit.fit_uncertainty(s, armfit.read_model(files["nominal"]))
    files["wu"] = u.write(root / "wu.csv")[0]
    return {"spectra": s, "nominal": m, "nominal_delay": md, "grip": g, "wu": u,
            "files": files, "root": root}


def _invoke(*args):
    res = CliRunner().invoke(cli, [str(a) for a in args])
    return res


def _phase_error_deg(h, ref):
    return np.abs(np.degrees(np.angle(h / ref)))


# ---------------------------------------------------------------------------
# ModelFit.to_control
# ---------------------------------------------------------------------------

def test_closed_loop_and_arm_tfs_are_the_fitted_models(study, control):
    # the sample study's nominal fits (the paper's model, no effect): X/F of eq. 4 and
    # H_ARM of eq. 3 as transfer functions, equal to armfit's evaluation to rounding
    m = study["nominal"]
    f = study["spectra"].freq_hz
    for axis in "xyz":
        model, theta = model_from_params(m.row_for(axis))
        G = m.to_control(axis)
        H = m.to_control(axis, kind="arm")
        assert isinstance(G, control.TransferFunction)
        np.testing.assert_allclose(G(2j * np.pi * f), model.response(f, theta), rtol=RTOL)
        np.testing.assert_allclose(H(2j * np.pi * f), model.arm_response(f, theta),
                                   rtol=RTOL)
        # orders of eq. 3 and 4: H_ARM 2/3, X/F 2/4, strictly proper
        assert (len(H.num[0][0]), len(H.den[0][0])) == (3, 4)
        assert (len(G.num[0][0]), len(G.den[0][0])) == (3, 5)
        assert G.name == f"{axis}_closed_loop" and H.name == f"{axis}_arm"
        assert G.input_labels == ["F"] and G.output_labels == [axis]
        assert G.armfit_delays == {"delay_s": 0.0, "inner_delays_s": (), "pade_order": None}


def test_rational_effects_are_exact_coefficients(hand, control):
    # Y: device mass and damping (impedances) and a resonance (output factor), all
    # rational: the TF equals ClosedLoopModel.response at the grid to rounding
    model, theta = model_from_params(hand.row_for("y"))
    G = hand.to_control("y")
    np.testing.assert_allclose(G(1j * W), model.response(F_HZ, theta), rtol=RTOL)
    H = hand.to_control("y", kind="arm")       # no arm effect: the bare H_ARM
    np.testing.assert_allclose(H(1j * W), model.arm_response(F_HZ, theta), rtol=RTOL)
    assert G.name == "y_closed_loop"
    # degrees: Z_ARM + M s^2 + B s (3/2) and the resonance's 2/2 factor: num 2+2, den 4+2
    assert (len(G.num[0][0]) - 1, len(G.den[0][0]) - 1) == (4, 6)


def test_latency_becomes_a_pade_approximant_within_its_bound(hand, control):
    # X: 12 ms latency and a 40 Hz lag. The lag is exact; the latency is the [6/6] Padé
    # approximant: all-pass, so |TF| is exact, and its phase error stays below
    # c_6 (wT)^13 (the module docstring's bound) at every grid point.
    model, theta = model_from_params(hand.row_for("x"))
    ref = model.response(F_HZ, theta)
    G = hand.to_control("x")
    h = G(1j * W)
    np.testing.assert_allclose(np.abs(h), np.abs(ref), rtol=RTOL)
    bound6 = pade_phase_bound_deg(W * 0.012, 6)
    err6 = _phase_error_deg(h, ref)
    assert np.all(err6 <= bound6 + 1e-9)
    # the docstring's figure: below 2e-5 deg while wT <= 3 (here wT <= 2.26)
    assert W[-1] * 0.012 <= 3.0 and err6.max() < 2e-5
    assert G.name == "x_closed_loop_pade6"
    assert G.armfit_delays == {"delay_s": 0.012, "inner_delays_s": (), "pade_order": 6}
    # not vacuous: the [1/1] approximant breaks the order-6 bound at every point above
    # 0.3 Hz (its own error there is 0.3e-3 deg and more, up to 33 deg at 30 Hz)
    G1 = hand.to_control("x", pade_order=1)
    err1 = _phase_error_deg(G1(1j * W), ref)
    assert np.all(np.abs(np.abs(G1(1j * W)) / np.abs(ref) - 1) < RTOL)
    assert np.all(err1 <= pade_phase_bound_deg(W * 0.012, 1) + 1e-9)
    above = F_HZ > 0.3
    assert np.all(err1[above] > bound6[above]) and err1.max() > 30.0


def test_pade_bound_figures_of_the_docstring():
    # phase error of the [n/n] approximant computed independently: wT - 2 arg D_n(j wT),
    # D_n the denominator of armfit.loop.pade_delay (the coefficients of Padé's table)
    def err_deg(x, n):
        x = np.linspace(0.0, x, 4001)[1:]
        _, den = pade_delay(1.0, n)
        return np.degrees(x - 2 * np.unwrap(np.angle(np.polyval(den, 1j * x))))

    e6 = err_deg(8.0, 6)
    x = np.linspace(0.0, 8.0, 4001)[1:]
    assert e6[x <= 3.0].max() < 2e-5
    assert e6[x <= 4.2].max() < 1e-3
    assert e6[x <= 6.2].max() < 0.1
    assert e6[x <= 7.7].max() < 1.0 < e6[x <= 7.75].max()
    assert err_deg(0.62, 1)[-1] > 1.0 > err_deg(0.60, 1)[-1]
    for n in range(1, 11):                 # the bound holds on 0 < wT <= 2n + 4
        x = np.linspace(0.0, 2 * n + 4, 4001)[1:]
        e = err_deg(2 * n + 4, n)
        significant = np.radians(e) > 1e-12          # above rounding
        assert np.all(e[significant] <= pade_phase_bound_deg(x[significant], n))
    # c_6 = (6!)^2 / (12! 13!) = 1.74e-13
    assert math.isclose(np.radians(pade_phase_bound_deg(1.0, 6)), 1.7380e-13, rel_tol=1e-4)


def test_control_pade_is_the_approximant_armfit_uses(control):
    # control.pade (a latency in to_control) and armfit.loop.pade_delay (a delay inside
    # an impedance; the stability analysis) are the same [n/n] approximant
    for n in (1, 3, 6):
        pn, pd = control.pade(0.012, n)
        an, ad = pade_delay(0.012, n)
        s = 1j * W
        np.testing.assert_allclose(np.polyval(pn, s) / np.polyval(pd, s),
                                   np.polyval(an, s) / np.polyval(ad, s), rtol=1e-12)


def test_delay_inside_an_impedance_is_replaced_by_its_pade_approximant(hand, control):
    # Z: the reflex adds g e^(-s tau) to Z_ARM. Independently: eq. 4 with e^(-s tau)
    # replaced by the [6/6] approximant, evaluated term by term with numpy
    row = hand.row_for("z")
    s = 1j * W
    c1, c2 = row["k1"] + row["b1"] * s, row["k2"] + row["b2"] * s
    z_arm = c1 * (row["Ma"] * s**2 + c2) / (row["Ma"] * s**2 + c1 + c2)
    pn, pd = pade_delay(0.04, 6)
    reflex = 200.0 * np.polyval(pn, s) / np.polyval(pd, s)
    G = hand.to_control("z")
    H = hand.to_control("z", kind="arm")
    np.testing.assert_allclose(G(s), 1 / (z_arm + reflex + row["mp_kg"] * s**2), rtol=RTOL)
    np.testing.assert_allclose(H(s), 1 / (z_arm + reflex), rtol=RTOL)
    assert G.name == "z_closed_loop_pade6" and H.name == "z_arm_pade6"
    assert G.armfit_delays == {"delay_s": 0.0, "inner_delays_s": (0.04,), "pade_order": 6}


def test_exact_response_as_frd(hand, study, control):
    # exact=True: the model's own response, delays exact, on omega or the fitted grid
    for axis in "xyz":
        model, theta = model_from_params(hand.row_for(axis))
        F = hand.to_control(axis, exact=True, omega=W)
        assert isinstance(F, control.FrequencyResponseData)
        np.testing.assert_array_equal(F.omega, W)
        np.testing.assert_array_equal(F.frdata[0, 0], model.response(F_HZ, theta))
        A = hand.to_control(axis, kind="arm", exact=True, omega=W)
        np.testing.assert_array_equal(A.frdata[0, 0], model.arm_response(F_HZ, theta))
        assert F.name == f"{axis}_closed_loop_exact"
    F = study["nominal"].to_control("x", exact=True)           # the spectra's grid
    np.testing.assert_allclose(F.omega, 2 * np.pi * study["spectra"].freq_hz, rtol=1e-15)
    F = hand.to_control("x", exact=True)                        # the default grid
    np.testing.assert_allclose(F.omega, W, rtol=1e-12)
    with pytest.raises(UsageError, match="exact=True"):
        hand.to_control("x", omega=W)


def test_effect_without_rational_form_points_to_the_frd(control):
    def stiffness(s, v, mp):
        return v["c_N_per_m"] + 0.0 * s

    eff = armfit.Effect(name="extra-stiffness", stage="arm", term=stiffness, null=(1e-3,),
                        params=(armfit.Param("c_N_per_m", "N/m", 1e-3, 1e4, 10.0),))
    model = armfit.ClosedLoopModel.for_axis("x", [eff])
    theta = {"Ma": 0.2, "k1": 95.0, "k2": 714.0, "b1": 7.7, "b2": 2.8,
             "extra-stiffness.c_N_per_m": 50.0}
    with pytest.raises(UsageError, match=r"'extra-stiffness'.*no rational form.*exact=True"):
        rational_model(model, theta, hint="take to_control(..., exact=True)")


def test_grip_fits_by_grip(study, control):
    g = study["grip"]
    row = g.row_for("y", 2.0)
    model, theta = model_from_params(row)
    G = g.to_control("y", grip=2.0)
    np.testing.assert_allclose(G(1j * W), model.response(F_HZ, theta), rtol=RTOL)
    assert G.name == "y_grip2N_closed_loop"
    with pytest.raises(UsageError, match="grip= one of 1, 2, 3 N"):
        g.to_control("y")
    with pytest.raises(UsageError, match=r"no model of axis y, grip 2\.5 N"):
        g.to_control("y", grip=2.5)
    with pytest.raises(UsageError, match="give no grip="):
        study["nominal"].to_control("y", grip=2.0)


# ---------------------------------------------------------------------------
# Uncertainty.to_control and Spectra.to_frd
# ---------------------------------------------------------------------------

def test_weight_tf_is_wu(study, control):
    # eq. 7: Wu(s) = K prod(s - z)/prod(s - p); the zpk TF equals WuWeight.response
    u = study["wu"]
    for axis in "xyz":
        T = u.to_control(axis)
        wu = u.weights[axis]
        np.testing.assert_allclose(T(1j * W), wu.response(F_HZ), rtol=RTOL)
        assert np.all(T.poles().real < 0) and np.all(T.zeros().real < 0)  # as fitted
        assert len(T.poles()) == 2 * len(wu.poles) and T.name == f"Wu_{axis}"
    with pytest.raises(UsageError, match="no weight for axis 'w'"):
        u.to_control("w")


def test_spectra_rows_as_frd(study, control):
    s = study["spectra"]
    med = s.select(level="median", kind="measured", axis="x")
    F = s.to_frd(axis="x", level="median")
    np.testing.assert_array_equal(F.omega, 2 * np.pi * med.freq_hz)
    np.testing.assert_array_equal(F.frdata[0, 0], med.h[0])
    mean = s.select(level="mean", kind="derived", axis="z", grip=3.0)
    F = s.to_frd(axis="z", grip=3.0, kind="derived")
    np.testing.assert_array_equal(F.frdata[0, 0], mean.h[0])
    assert F.name == "z_derived_mean_grip-3N" and F.output_labels == ["z"]
    trial = s.select(level="trial", kind="measured", axis="y", grip=1.0, subject="02")
    F = s.to_frd(axis="y", grip=1.0, level="trial", subject="02")
    np.testing.assert_array_equal(F.frdata[0, 0], trial.h[0])
    with pytest.raises(UsageError, match=r"3 measured responses of level mean, axis x "
                                         r"in the spectra \(mean_grip-1N"):
        s.to_frd(axis="x")
    with pytest.raises(UsageError, match="0 measured responses"):
        s.to_frd(axis="x", grip=7.0)


def test_missing_extra_is_one_line(study, hand, monkeypatch):
    monkeypatch.setitem(sys.modules, "control", None)       # import control fails
    for call in (lambda: hand.to_control("x"), lambda: study["wu"].to_control("x"),
                 lambda: study["spectra"].to_frd(axis="x", level="median")):
        with pytest.raises(UsageError, match=r"needs the optional package 'control': "
                                             r"pip install armfit\[control\]$"):
            call()


# ---------------------------------------------------------------------------
# armfit export
# ---------------------------------------------------------------------------

def _tf_response(num, den, delay, w):
    """num(jw)/den(jw) e^(-jw d): what MATLAB's tf(num, den, 'IODelay', d) evaluates."""
    s = 1j * np.asarray(w)
    return np.polyval(np.ravel(num), s) / np.polyval(np.ravel(den), s) * np.exp(-s * delay)


def test_mat_file_gives_back_the_models(tmp_path):
    # a params file with every built-in effect; loadmat's coefficients and IODelay give
    # armfit's own evaluation at the grid points: exactly for X (latency exact as
    # IODelay) and Y; for Z the reflex's delay sits inside the impedance, where
    # num/den hold its [6/6] approximant (named in Gz_inner_delay_s)
    from scipy.io import loadmat

    params = tmp_path / "hand.csv"
    pd.DataFrame(HAND_ROWS).to_csv(params, index=False)
    res = _invoke("export", params, "-o", tmp_path / "hand.mat")
    assert res.exit_code == 0, res.output
    assert res.stderr.strip() == f"wrote {tmp_path / 'hand.mat'}: models x, y, z"
    S = loadmat(tmp_path / "hand.mat")
    m = armfit.ModelFit.of(pd.DataFrame(HAND_ROWS))
    for axis in "xy":
        model, theta = model_from_params(m.row_for(axis))
        g = _tf_response(S[f"G{axis}_num"], S[f"G{axis}_den"], S[f"G{axis}_delay_s"].item(), W)
        np.testing.assert_allclose(g, model.response(F_HZ, theta), rtol=RTOL)
        h = _tf_response(S[f"H{axis}_num"], S[f"H{axis}_den"], 0.0, W)
        np.testing.assert_allclose(h, model.arm_response(F_HZ, theta), rtol=RTOL)
        assert f"G{axis}_inner_delay_s" not in S
    assert S["Gx_delay_s"].item() == 0.012 and S["Gy_delay_s"].item() == 0.0
    assert S["Gz_inner_delay_s"].ravel().tolist() == [0.04] and S["pade_order"].item() == 6
    z = rational_model(*model_from_params(m.row_for("z")))
    np.testing.assert_allclose(_tf_response(S["Gz_num"], S["Gz_den"], 0.0, W),
                               z.response(W), rtol=RTOL)
    assert S["Gx_num"].shape[0] == 1                # row vectors, as tf() takes them
    # Y's device: its mass 0.12 kg replaces Mp and its damping adds 1.5 s (the library's
    # device-mass and device-damping): Z = 0.12 s^2 + 1.5 s, exactly
    np.testing.assert_allclose(S["Zy_num"].ravel(), [0.12, 1.5, 0.0], rtol=1e-15)
    np.testing.assert_array_equal(S["Zy_den"].ravel(), [1.0])
    assert "tf(num, den, 'IODelay', delay_s)" in str(S["readme"][0])


def test_export_of_the_study_with_weights_and_spectra(study, tmp_path):
    from scipy.io import loadmat

    f = study["files"]
    out = tmp_path / "models.mat"
    res = _invoke("export", f["nominal"], "--weights", f["wu"], "--spectra", f["spectra"],
                  "-o", out)
    assert res.exit_code == 0, res.output
    assert res.stderr.strip() == (f"wrote {out}: models x, y, z; weights x, y, z; "
                                  "measured responses x, y, z; derived trials x, y, z")
    S = loadmat(out)
    s = study["spectra"]
    weights = armfit.read_weights(f["wu"])       # the file's 10 significant digits
    nominal = armfit.read_model(f["nominal"])
    for axis in "xyz":
        # the 5-parameter model: Z = Mp s^2, and X/F = H/(1 + Z H) (eq. 4)
        row = nominal.row_for(axis)
        np.testing.assert_array_equal(S[f"Z{axis}_num"].ravel(), [row["mp_kg"], 0.0, 0.0])
        h = _tf_response(S[f"H{axis}_num"], S[f"H{axis}_den"], 0.0, W)
        z = _tf_response(S[f"Z{axis}_num"], S[f"Z{axis}_den"], 0.0, W)
        g = _tf_response(S[f"G{axis}_num"], S[f"G{axis}_den"], 0.0, W)
        np.testing.assert_allclose(g, h / (1 + z * h), rtol=RTOL)
        wu = weights[axis]
        z, p, k = S[f"W{axis}_z"].ravel(), S[f"W{axis}_p"].ravel(), S[f"W{axis}_k"].item()
        jw = 1j * W
        wz = k * np.prod(jw[:, None] - z, axis=1) / np.prod(jw[:, None] - p, axis=1)
        np.testing.assert_allclose(wz, wu.response(F_HZ), rtol=RTOL)       # zpk(z, p, k)
        band = [r.band_hz for r in study["wu"].axes if r.axis == axis][0]
        np.testing.assert_allclose(S[f"W{axis}_band_rad_s"].ravel(),
                                   2 * np.pi * np.asarray(band), rtol=1e-9)
        med = s.select(level="median", kind="measured", axis=axis)
        np.testing.assert_array_equal(S[f"M{axis}_resp"].ravel(), med.h[0])
        np.testing.assert_allclose(S[f"M{axis}_w_rad_s"].ravel(), 2 * np.pi * med.freq_hz)
        # the derived trials as fit-uncertainty compares them with the nominal: no
        # apparatus effect in this model, so the estimates themselves, in subject order
        trials = s.select(level="trial", kind="derived", axis=axis).sorted()
        np.testing.assert_array_equal(S[f"D{axis}_resp"], trials.h)
        assert [c.item() for c in S[f"D{axis}_trials"].ravel()] == trials.labels()
    assert str(S["source_weights"][0]) == str(f["wu"])


def test_json_holds_the_same_variables(study, tmp_path):
    import json

    from scipy.io import loadmat

    f = study["files"]
    args = [f["grip"], "--spectra", f["spectra"]]
    assert _invoke("export", *args, "-o", tmp_path / "g.mat").exit_code == 0
    res = _invoke("export", *args, "--format", "json", "-o", tmp_path / "g.json")
    assert res.exit_code == 0, res.output
    S = loadmat(tmp_path / "g.mat")
    J = json.loads((tmp_path / "g.json").read_text())
    assert list(J) == [k for k in S if not k.startswith("__")]
    assert list(J)[:5] == ["Gx_grip1N_num", "Gx_grip1N_den", "Gx_grip1N_delay_s",
                           "Hx_grip1N_num", "Hx_grip1N_den"]
    for name, value in J.items():
        if isinstance(value, dict):
            value = np.asarray(value["re"]) + 1j * np.asarray(value["im"])
        if isinstance(value, str):
            assert str(S[name][0]) == value
        else:
            np.testing.assert_array_equal(np.ravel(value), np.ravel(S[name]))
    # a grip file: the means per axis x grip it was fitted to, no derived trials
    mean = study["spectra"].select(level="mean", kind="measured", axis="z", grip=2.0)
    np.testing.assert_array_equal(S["Mz_grip2N_resp"].ravel(), mean.h[0])
    assert not any(k.startswith("D") for k in J)


def test_mat_bytes_do_not_depend_on_the_time(study, tmp_path):
    f = study["files"]
    a, b = tmp_path / "a.mat", tmp_path / "b.mat"
    assert _invoke("export", f["nominal"], "-o", a).exit_code == 0
    assert _invoke("export", f["nominal"], "-o", b).exit_code == 0
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes().startswith(b"MATLAB 5.0 MAT-file, written by armfit")


def test_export_refusals(study, tmp_path):
    f = study["files"]
    out = tmp_path / "m.mat"
    assert _invoke("export", f["nominal"], "-o", out).exit_code == 0
    res = _invoke("export", f["nominal"], "-o", out)                    # exists
    assert res.exit_code == 73 and "--overwrite" in res.stderr
    assert _invoke("export", f["nominal"], "-o", out, "--overwrite").exit_code == 0
    res = _invoke("export", f["nominal"], "-o", tmp_path / "m.txt")     # which format?
    assert res.exit_code == 2 and "export writes .mat or .json; not .txt" in res.stderr
    res = _invoke("export", f["nominal"], "--format", "json", "-o", tmp_path / "m2.mat")
    assert res.exit_code == 2 and "the format follows the extension" in res.stderr
    res = _invoke("export", tmp_path / "none.csv", "-o", tmp_path / "n.mat")
    assert res.exit_code == 66
    res = _invoke("export", f["nominal"], "-o", tmp_path / "n.json", "--overwrite")
    assert res.exit_code == 0                                            # a new file
    as_input = tmp_path / "params.json"
    as_input.write_bytes(Path(f["nominal"]).read_bytes())
    res = _invoke("export", as_input, "-o", as_input, "--overwrite")    # the input
    assert res.exit_code == 73
    bad = tmp_path / "bad.csv"
    pd.DataFrame([{**HAND_ROWS[0], "Ma": -1.0}]).to_csv(bad, index=False)
    res = _invoke("export", bad, "-o", tmp_path / "b.mat")
    assert res.exit_code == 65 and "column 'Ma', row 1" in res.stderr
    trials = tmp_path / "trials.csv"
    pd.DataFrame([{**HAND_ROWS[1], "subject": "01", "grip_N": 2.0}]).to_csv(trials,
                                                                            index=False)
    res = _invoke("export", trials, "-o", tmp_path / "t.mat")
    assert res.exit_code == 2 and "per-trial params file" in res.stderr


def test_effect_without_rational_form_is_refused_by_export(tmp_path):
    effects = tmp_path / "stiff.py"
    effects.write_text(
        "import armfit\n\n"
        "def _term(s, v, mp):\n    return v['c_N_per_m'] + 0.0 * s\n\n"
        "EFFECTS = [armfit.Effect(name='hand-stiffness', stage='arm', term=_term,\n"
        "    null=(1e-3,), params=(armfit.Param('c_N_per_m', 'N/m', 1e-3, 1e4, 10.0),))]\n")
    params = tmp_path / "p.csv"
    pd.DataFrame([{**{k: v for k, v in HAND_ROWS[1].items() if "." not in k},
                   "effects": "hand-stiffness", "hand-stiffness.c_N_per_m": 20.0}]
                 ).to_csv(params, index=False)
    res = _invoke("export", "--effects", effects, params, "-o", tmp_path / "p.mat")
    assert res.exit_code == 2
    (line,) = res.stderr.strip().splitlines()
    assert re.search(r"axis y: effect 'hand-stiffness' \(from .*stiff\.py\) declares no "
                     r"rational form.*exact=True", line), line
    assert not (tmp_path / "p.mat").exists()


def test_export_needs_no_python_control(study, tmp_path):
    # the command builds its coefficients with numpy: it runs with python-control
    # unimportable, and does not import it when it is there
    code = ("import sys\nsys.modules['control'] = None\n"
            "from click.testing import CliRunner\nfrom armfit.cli.main import cli\n"
            f"r = CliRunner().invoke(cli, ['export', {str(study['files']['nominal'])!r}, "
            f"'--weights', {str(study['files']['wu'])!r}, '-o', "
            f"{str(tmp_path / 'x.json')!r}])\n"
            "assert r.exit_code == 0, r.output\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
    code = ("import sys\nfrom click.testing import CliRunner\n"
            "from armfit.cli.main import cli\n"
            f"r = CliRunner().invoke(cli, ['export', {str(study['files']['nominal'])!r}, "
            f"'-o', {str(tmp_path / 'y.json')!r}])\n"
            "assert r.exit_code == 0, r.output\nassert 'control' not in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


# ---------------------------------------------------------------------------
# Octave reads the file
# ---------------------------------------------------------------------------

#: Frequencies (rad/s) at which Octave evaluates the exported models: 0.5, 5 and 25 Hz.
OCTAVE_W = 2 * np.pi * np.array([0.5, 5.0, 25.0])


def octave_script(mat: Path, names: list[str]) -> str:
    """An Octave script that loads ``mat``, builds each model ``G<name>`` as
    tf(num, den, 'IODelay', d) and each weight ``W<axis>`` as zpk(z, p, k), and prints
    their responses at :data:`OCTAVE_W`; each measured response ``M<name>`` as
    frd(resp, w), printed at its first three frequencies. The control package of Octave 3.4 has no
    IODelay: there the script applies the delay as the factor e^(-jwd) (and says so)."""
    w = " ".join(repr(float(x)) for x in OCTAVE_W)
    lines = ["pkg load control", f"S = load('{mat}');", f"w = [{w}];"]
    for n in names:
        if n.startswith("M"):
            lines += [f"h = squeeze(freqresp(frd(S.{n}_resp, S.{n}_w_rad_s), "
                      f"S.{n}_w_rad_s(1:3)));",
                      f"printf('{n} frd'); printf(' %.17g %.17g', [real(h(:)) imag(h(:))].');"
                      " printf('\\n');"]
            continue
        if n.startswith("W"):
            lines += [f"h = squeeze(freqresp(zpk(S.{n}_z, S.{n}_p, S.{n}_k), w));",
                      f"printf('{n} zpk'); printf(' %.17g %.17g', [real(h(:)) imag(h(:))].');"
                      " printf('\\n');"]
            continue
        lines += [
            "try",
            f"  h = squeeze(freqresp(tf(S.{n}_num, S.{n}_den, 'IODelay', S.{n}_delay_s), w));"
            " how = 'IODelay';",
            "catch",
            f"  h = squeeze(freqresp(tf(S.{n}_num, S.{n}_den), w)) .* "
            f"exp(-1i * w(:) * S.{n}_delay_s); how = 'exp';",
            "end",
            f"printf('{n} %s', how); printf(' %.17g %.17g', [real(h(:)) imag(h(:))].');"
            " printf('\\n');"]
    return "\n".join(lines) + "\n"


def parse_octave(text: str) -> dict[str, np.ndarray]:
    out = {}
    for line in text.strip().splitlines():
        name, _, *nums = line.split()
        v = np.array([float(x) for x in nums])
        out[name] = v[0::2] + 1j * v[1::2]
    return out


def _armfit_values(study) -> dict[str, np.ndarray]:
    """armfit's own evaluation at OCTAVE_W of the sample study's nominal models with a
    latency (Gx, Gy, Gz) and of its weights (Wx, Wy, Wz), as their files hold them."""
    m = armfit.read_model(study["files"]["nominal_delay"])
    weights = armfit.read_weights(study["files"]["wu"])
    out = {}
    for axis in "xyz":
        model, theta = model_from_params(m.row_for(axis))
        out[f"G{axis}"] = model.response(OCTAVE_W / (2 * np.pi), theta)
        out[f"W{axis}"] = weights[axis].response(OCTAVE_W / (2 * np.pi))
    return out


#: What Octave 7.3.0 (control 3.4.0) printed for the export of the sample study's nominal
#: fits with a latency and its weights, made and evaluated with:
#:
#:     armfit estimate sample_data/study -o spectra.parquet
#:     armfit fit-nominal spectra.parquet -o nominal.csv
#:     armfit fit-nominal spectra.parquet --effect delay -o nominal_delay.csv
#:     armfit fit-uncertainty spectra.parquet --nominal nominal.csv -o wu.csv
#:     armfit export nominal_delay.csv --weights wu.csv -o study.mat
#:     octave-cli --no-gui --quiet check.m     # check.m: octave_script(study.mat, ...)
#:
#: (the models' delays are 26 us, 0.2 us and 0.34 ms: applied as e^(-jwd), Octave's
#: control package having no IODelay). Responses at 0.5, 5, 25 Hz, m/N; Wu dimensionless.
OCTAVE_PRINTED: dict[str, list[complex]] = {
    "Gx": [complex(0.011388835067783817, -0.0025960241532989575),
           complex(0.0015839504983167396, -0.0063038908736522473),
           complex(-0.00033650671692851144, -0.00015747147781266548)],
    "Gy": [complex(0.011170447179273339, -0.0024573500214311169),
           complex(0.00086284447809060615, -0.0073882685144787278),
           complex(-0.00032922410046426481, -0.0001593895978172502)],
    "Gz": [complex(0.0049983394001600701, -0.0040083869093928935),
           complex(-5.1909015320988287e-05, -0.00017837378954395399),
           complex(3.3197513544951029e-06, -0.0001099314627120776)],
    "Wx": [complex(0.43804103509218367, -0.19645650109182991),
           complex(0.26246514504505741, 0.028963631075762369),
           complex(0.2146960694762573, 0.011512294187692009)],
    "Wy": [complex(0.40712123019378882, -0.12059604125060448),
           complex(0.33751491265509831, 0.026575117139041222),
           complex(0.24933599838450196, 0.08656878644803602)],
    "Wz": [complex(0.43395397220898585, -0.17496733751538304),
           complex(1.6140092175034488, 0.24561761460737647),
           complex(0.58752542445386291, -0.098341838877610083)],
}


def test_octave_evaluates_the_exported_file(study, tmp_path):
    if shutil.which("octave-cli") is None:
        pytest.skip("octave-cli is not installed")
    f = study["files"]
    mat = tmp_path / "study.mat"
    res = _invoke("export", f["nominal_delay"], "--weights", f["wu"], "--spectra",
                  f["spectra"], "-o", mat)
    assert res.exit_code == 0, res.output
    names = ["Gx", "Gy", "Gz", "Wx", "Wy", "Wz", "Mx", "My", "Mz"]
    script = tmp_path / "check.m"
    script.write_text(octave_script(mat, names))
    run = subprocess.run(["octave-cli", "--no-gui", "--quiet", str(script)],
                         capture_output=True, text=True, timeout=300)
    if run.returncode != 0 and "control" in run.stderr and "pkg" in run.stderr:
        pytest.skip("Octave's control package is not installed")
    assert run.returncode == 0, run.stderr
    got = parse_octave(run.stdout)
    want = _armfit_values(study)
    for axis in "xyz":
        want[f"M{axis}"] = study["spectra"].select(level="median", kind="measured",
                                                   axis=axis).h[0, :3]
    for name in names:
        np.testing.assert_allclose(got[name], want[name], rtol=1e-12, err_msg=name)


def test_octave_printed_numbers_are_armfit_s(study):
    # the numbers Octave printed (OCTAVE_PRINTED) against armfit's evaluation now:
    # the same fits on the locked libraries, to the fits' convergence (1e-7): the
    # spectra's last bits move with the processor's vector instructions, which numpy
    # and OpenBLAS pick at run time, and the optimiser then stops a few 1e-10 away; on
    # another set of libraries its last digits move further
    want = _armfit_values(study)
    rtol = 1e-7 if not unlocked() else 1e-5
    for name, values in OCTAVE_PRINTED.items():
        np.testing.assert_allclose(np.array(values), want[name], rtol=rtol, err_msg=name)
    assert set(OCTAVE_PRINTED) == set(want)


# ---------------------------------------------------------------------------
# The snippets of docs/api.md
# ---------------------------------------------------------------------------

def _api_block(lang: str, marker: str) -> str:
    from test_docs import blocks_of
    for b in blocks_of(REPO / "docs" / "api.md") if lang == "python" else []:
        if marker in "\n".join(b.lines):
            return "\n".join(b.lines)
    text = (REPO / "docs" / "api.md").read_text(encoding="utf-8")
    for m in re.finditer(rf"```{lang}\n(.*?)```", text, flags=re.S):
        if marker in m.group(1):
            return m.group(1)
    raise AssertionError(f"docs/api.md has no {lang} block with {marker!r}")


def test_python_control_snippet_runs(study, control):
    # the python-control block of docs/api.md (shown, not run by test_docs: it needs
    # the extra), with the names the page's earlier blocks define: s (the sample
    # study's spectra), m, m_delay, g (its nominal, nominal with a latency and grip
    # fits) and u (its weights)
    code = _api_block("python", "to_control(")
    namespace: dict = {"__name__": "__docs__", "armfit": armfit, "s": study["spectra"],
                       "m": study["nominal"], "m_delay": study["nominal_delay"],
                       "g": study["grip"], "u": study["wu"]}
    exec(compile(code, "docs/api.md", "exec"), namespace)  # noqa: S102
    assert isinstance(namespace["G"], control.TransferFunction)
    assert namespace["Gd"].name == "x_closed_loop_pade6"
    assert isinstance(namespace["E"], control.FrequencyResponseData)


def test_matlab_snippet_names_the_variables_written(study, tmp_path):
    # every S.<name> of the MATLAB block of docs/api.md is a variable of the export the
    # block loads (nominal fits, weights and spectra of the study)
    from scipy.io import loadmat

    code = _api_block("matlab", "load(")
    f = study["files"]
    out = tmp_path / "models.mat"
    assert _invoke("export", f["nominal"], "--weights", f["wu"], "--spectra",
                   f["spectra"], "-o", out).exit_code == 0
    names = set(re.findall(r"\bS\.(\w+)", code))
    assert names and names <= set(loadmat(out))
