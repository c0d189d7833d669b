"""Tests of armfit.models: the arm, device and closed-loop models and the effect library.

Expected values are analytic limits of the paper's equations (Fu & Çavuşoğlu 2010, eqs.
2–4) or closed forms of each effect; parameters are rows of the paper's Table I.
"""

import numpy as np
import pytest

from armfit.data import paper_table
from armfit.errors import UsageError
from armfit.models.arm import (
    DEVICE_MASS_KG,
    ClosedLoopModel,
    arm_tf,
    cl_tf,
    h_arm,
    h_cl,
    z_arm,
)
from armfit.models.effects import EFFECTS, get_effect, parse_effect_spec
from armfit.models.literature import literature_models

# Table I, X axis, 1 N grip.
X1 = dict(Ma=0.1925, k1=85.48, k2=704.2, b1=7.410, b2=2.477)
F = np.logspace(-2, np.log10(30), 200)


def test_arm_dc_is_series_springs():
    # At s = 0, eq. 3 reduces to (k1 + k2) / (k1 k2): the two springs in series.
    expected = (X1["k1"] + X1["k2"]) / (X1["k1"] * X1["k2"])
    assert h_arm(0.0, **X1).real == pytest.approx(expected, rel=1e-12)


def test_arm_high_frequency_is_hand_damper():
    # Relative degree 1 (docs/methods.md, "Arm, device and closed loop"):
    # H_ARM -> 1/(b1 s) as s -> inf.
    f = 1e6
    s = 2j * np.pi * f
    assert h_arm(f, **X1) * (X1["b1"] * s) == pytest.approx(1.0, rel=1e-4)


def test_closed_loop_high_frequency_is_device_plus_hand_mass_line():
    # Relative degree 2: H_CL -> 1/(Mp s²) as s -> inf (40 dB/dec).
    f = 1e6
    s = 2j * np.pi * f
    assert h_cl(f, **X1, mp=0.09) * (0.09 * s * s) == pytest.approx(1.0, rel=1e-3)


def test_polynomials_match_the_rational_forms_of_eqs_3_and_4():
    # eq. 3 written out as a ratio of polynomials (docs/methods.md) against the C1/C2 form.
    s = 2j * np.pi * F
    num, den = arm_tf(**X1)
    np.testing.assert_allclose(np.polyval(num, s) / np.polyval(den, s), h_arm(F, **X1),
                               rtol=1e-12)
    num, den = cl_tf(**X1, mp=0.09)
    assert len(den) == 5  # H_CL is fourth order (docs/methods.md)
    np.testing.assert_allclose(np.polyval(num, s) / np.polyval(den, s),
                               h_cl(F, **X1, mp=0.09), rtol=1e-12)


def test_closed_loop_is_eq4_feedback_form():
    # eq. 4: H_CL = H_ARM / (1 + H_ARM Mp s²).
    s = 2j * np.pi * F
    ha = h_arm(F, **X1)
    np.testing.assert_allclose(h_cl(F, **X1, mp=0.09), ha / (1 + ha * 0.09 * s * s), rtol=1e-12)


@pytest.mark.parametrize("row", range(9))
def test_every_table1_row_gives_a_stable_closed_loop(row):
    # Physical parameters (all positive) give a passive, hence stable, closed loop:
    # every root of the fourth-order denominator in the open left half plane.
    r = paper_table("grip").iloc[row]
    p = dict(Ma=r.Ma_kg, k1=r.k1_N_per_m, k2=r.k2_N_per_m, b1=r.b1_Ns_per_m, b2=r.b2_Ns_per_m)
    _, den = cl_tf(**p, mp=DEVICE_MASS_KG[r.axis])
    assert np.all(np.roots(den).real < 0)


def test_model_without_effects_is_h_cl_and_derived_is_h_arm():
    m = ClosedLoopModel.for_axis("x")
    np.testing.assert_allclose(m.response(F, X1), h_cl(F, **X1, mp=0.09), rtol=1e-12)
    # Xa/Fa = H/(1 − Mp s² H) inverts eq. 4 exactly when no effect is present.
    np.testing.assert_allclose(m.derived_arm_response(F, X1), h_arm(F, **X1), rtol=1e-10)
    np.testing.assert_allclose(m.arm_response(F, list(X1.values())), h_arm(F, **X1),
                               rtol=1e-12)


def _with(name, **values):
    m = ClosedLoopModel.for_axis("x", [get_effect(name)])
    theta = dict(X1, **{f"{name}.{k}": v for k, v in values.items()})
    return m.response(F, theta)


def test_delay_is_pure_phase_lag():
    # e^{-sτ}: unit magnitude, phase −360° f τ.
    h = _with("delay", delay_s=0.01) / h_cl(F, **X1, mp=0.09)
    np.testing.assert_allclose(np.abs(h), 1.0, rtol=1e-12)
    np.testing.assert_allclose(np.exp(1j * np.angle(h)), np.exp(-2j * np.pi * F * 0.01),
                               atol=1e-12)


def test_lowpass_is_minus_3db_and_45deg_at_the_corner():
    # 1/(1 + s/ωc) at ω = ωc: magnitude 1/√2, phase −45°.
    m = ClosedLoopModel.for_axis("x", [get_effect("lowpass")])
    th = dict(X1, **{"lowpass.cutoff_hz": 20.0})
    r = m.response(20.0, th) / h_cl(20.0, **X1, mp=0.09)
    assert abs(r) == pytest.approx(2 ** -0.5, rel=1e-12)
    assert np.degrees(np.angle(r)) == pytest.approx(-45.0, abs=1e-9)


def test_device_mass_and_damping_change_the_device_impedance():
    # device-mass: H_CL with Mp replaced; device-damping: 1/(Z_ARM + Mp s² + B s).
    np.testing.assert_allclose(_with("device-mass", mass_kg=0.15), h_cl(F, **X1, mp=0.15),
                               rtol=1e-12)
    s = 2j * np.pi * F
    np.testing.assert_allclose(_with("device-damping", damping_Ns_per_m=3.0),
                               1 / (z_arm(F, **X1) + 0.09 * s * s + 3.0 * s), rtol=1e-12)


def test_resonance_limits():
    # (1 − w) + w ωn²/(s² + 2ζωn s + ωn²): 1 at DC, (1 − w) + w/(2jζ) at ωn.
    m = ClosedLoopModel.for_axis("x", [get_effect("resonance")])
    th = dict(X1, **{"resonance.freq_hz": 40.0, "resonance.zeta": 0.05,
                     "resonance.weight": 0.3})
    dc = m.response(1e-6, th) / h_cl(1e-6, **X1, mp=0.09)
    assert dc == pytest.approx(1.0, abs=1e-9)
    at = m.response(40.0, th) / h_cl(40.0, **X1, mp=0.09)
    assert at == pytest.approx(0.7 + 0.3 / (2j * 0.05), rel=1e-12)


def test_reflex_adds_delayed_stiffness_to_the_arm():
    # At DC the reflex gain g adds to the series stiffness k1 k2/(k1 + k2).
    g = 150.0
    m = ClosedLoopModel.for_axis("x", [get_effect("reflex")])
    th = dict(X1, **{"reflex.gain_N_per_m": g, "reflex.delay_s": 0.04})
    kser = X1["k1"] * X1["k2"] / (X1["k1"] + X1["k2"])
    assert m.response(0.0, th).real == pytest.approx(1 / (kser + g), rel=1e-12)
    # an arm-stage effect is part of H_ARM, so the derived arm response recovers it
    np.testing.assert_allclose(m.derived_arm_response(F, th), m.arm_response(F, th),
                               rtol=1e-10)


def test_model_parameter_names_are_qualified_and_clashes_refused():
    m = ClosedLoopModel.for_axis("z", [EFFECTS["reflex"], EFFECTS["delay"]])
    assert m.param_names == ("Ma", "k1", "k2", "b1", "b2", "reflex.gain_N_per_m",
                             "reflex.delay_s", "delay.delay_s")
    assert m.mp == DEVICE_MASS_KG["z"]
    with pytest.raises(UsageError, match="effect given twice: delay"):
        m.with_effect(EFFECTS["delay"])
    with pytest.raises(UsageError, match="axis must be x, y or z"):
        ClosedLoopModel.for_axis("w")


def test_parse_effect_spec_forms_and_errors():
    e, v = parse_effect_spec("delay=0.012")
    assert e.name == "delay" and v == {"delay_s": 0.012}
    e, v = parse_effect_spec("reflex=delay_s:0.05,gain_N_per_m:300")
    assert v == {"gain_N_per_m": 300.0, "delay_s": 0.05}
    e, v = parse_effect_spec("resonance=45,0.1,0.4")
    assert v == {"freq_hz": 45.0, "zeta": 0.1, "weight": 0.4}
    with pytest.raises(UsageError, match="unknown effect 'spring'"):
        parse_effect_spec("spring=3")
    with pytest.raises(UsageError, match="takes 3 value"):
        parse_effect_spec("resonance=45")
    with pytest.raises(UsageError, match="outside the physical range"):
        parse_effect_spec("delay=2")
    with pytest.raises(UsageError, match="is not a number"):
        parse_effect_spec("delay=abc")
    with pytest.raises(UsageError, match="has no parameter 'tau'"):
        parse_effect_spec("delay=tau:0.01")


def test_literature_models():
    models = {m.name: m for m in literature_models()}
    assert len(models) == 7  # Table IV rows
    # three-parameter model 1/(m s² + b s + k): DC compliance 1/k (Kosuge: k = 243 N/m)
    assert models["Kosuge"].response(0.0).real == pytest.approx(1 / 243, rel=1e-12)
    # five-parameter models follow eq. 3 (Speich X row)
    sx = models["Speich X"]
    np.testing.assert_allclose(sx.response(F), h_arm(F, 0.85, 122, 330, 12.9, 12.9),
                               rtol=1e-12)


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_every_effect_vanishes_at_its_null_point(name):
    # Nested fits start at the null point: there the model must equal eq. 4 without the
    # effect, to 1e-3 relative (lowpass at 100 kHz: |1/(1 + j f/1e5)| − 1 ≈ 3e-4 at 30 Hz).
    m = ClosedLoopModel.for_axis("y", [EFFECTS[name]])
    theta = m.null_theta(X1)
    np.testing.assert_allclose(m.response(F, theta), h_cl(F, **X1, mp=0.095), rtol=1e-3)
    starts = m.start_points(X1)
    assert starts[0] == theta
    for st in starts:  # every start lies within the physical bounds
        for p in m.params:
            assert p.lower <= st[p.name] <= p.upper


def test_the_response_from_a_known_base_impedance_is_the_response():
    # to the bit, every library effect at once (each stage: arm, device, output): the
    # base impedance Z_ARM + Mp s² of two rows of arm parameters, then the effects' values
    # stepped with the arm parameters fixed (three steps per row), as the joint fits'
    # forward differences evaluate them
    m = ClosedLoopModel.for_axis("y", [EFFECTS[n] for n in sorted(EFFECTS)])
    theta = m.start_points(X1)[-1]
    rows = {n: np.array([[v], [1.3 * v]]) for n, v in theta.items()}
    h, _, z_base = m.response_and_base_log_derivatives(F, rows, with_base=True)
    assert np.array_equal(h, m.response(F, rows))
    # eq. 4: Z_ARM + Mp s² = 1/H_CL of the arm parameters alone
    np.testing.assert_allclose(z_base, 1.0 / h_cl(F, **{n: rows[n] for n in X1}, mp=m.mp),
                               rtol=1e-12)
    effect_names = [n for n in m.param_names if "." in n]
    stepped = {n: np.stack([rows[n]] * 3) for n in rows}           # (3, 2, 1)
    for i, n in enumerate(effect_names):
        stepped[n] = stepped[n] * (1.0 + 1e-3 * np.arange(1, 4))[:, None, None] ** (i + 1)
    assert np.array_equal(m.response_at_base(F, stepped, z_base), m.response(F, stepped))


@pytest.mark.parametrize("name", [None, *sorted(EFFECTS)])
def test_base_log_derivatives_are_those_of_the_response(name):
    # ∂ ln H/∂θ of the five arm parameters, analytic, against central differences of
    # ln H (step 1e-6 relative: truncation error ~1e-12 relative, round-off ~1e-16/step
    # absolute, 1e-8 of the largest derivative at most), with each
    # library effect at a start point away from its null (and the base model alone); the
    # parameters broadcast over rows, as the joint fits evaluate them
    effects = [] if name is None else [EFFECTS[name]]
    m = ClosedLoopModel.for_axis("y", effects)
    theta = m.start_points(X1)[-1]
    rows = {n: np.array([[v], [1.3 * v]]) for n, v in theta.items()}
    h, got = m.response_and_base_log_derivatives(F, rows)
    assert np.array_equal(h, m.response(F, rows))       # the response itself, to the bit
    assert got.shape == (5, 2, F.size)
    for j, n in enumerate(("Ma", "k1", "k2", "b1", "b2")):
        h = 1e-6 * rows[n]
        up, down = dict(rows), dict(rows)
        up[n], down[n] = rows[n] + h, rows[n] - h
        want = (np.log(m.response(F, up) / m.response(F, down))) / (2 * h)
        np.testing.assert_allclose(got[j], want, rtol=1e-6, atol=1e-7 * np.abs(want).max())
