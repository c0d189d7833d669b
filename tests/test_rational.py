"""Effects' rational forms (eq. R1 of armfit.models.effects) and the stability plant built
from them, against independent evaluations.

Expected values: the model's own frequency response (ClosedLoopModel.response, which
evaluates each effect's ``term``, not its rational form); scipy.interpolate.pade for the
reflex's internal delay; the modulus |e^(−jx) − R(jx)| = 2 |sin(Δφ/2)| of an all-pass
Padé approximant R; and, for K_max, scipy.signal.cont2discrete (ZOH) with the roots of
the closed-loop characteristic polynomial; exit codes from armfit.errors (2 usage, 65
bad input)."""

from __future__ import annotations

import json
import math
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import interpolate
from test_cli_stability import GRID  # noise-free spectra rows of one trial
from test_cli_stability import _trial as _spectra_rows
from test_stability import _independent_k_max as k_max_by_roots

from armfit.cli.main import cli
from armfit.errors import EffectDefinitionError, UsageError
from armfit.io.schema import params_columns
from armfit.loop import INTERNAL_DELAY_PADE_ORDER, plant_from_model
from armfit.models import library
from armfit.models.arm import ClosedLoopModel, Param
from armfit.models.effects import (
    EFFECTS,
    Effect,
    check_effect,
    get_effect,
    load_effect_file,
)
from armfit.models.params import paper_params
from armfit.spectra import Spectra

ROOT = Path(__file__).resolve().parents[1]
SPRING = ROOT / "examples" / "device_spring.py"
NAMES = ("Ma", "k1", "k2", "b1", "b2")

#: Table II of the paper (nominal parameters) per axis, and its device masses (kg).
TABLE2 = {r["axis"]: {n: float(r[n]) for n in NAMES}
          for _, r in paper_params("nominal").iterrows()}
MP = {r["axis"]: float(r["mp_kg"]) for _, r in paper_params("nominal").iterrows()}
#: Table I of the paper (grip-dependent parameters), keyed by (axis, grip in N).
TABLE1 = {(r["axis"], float(r["grip_N"])): {n: float(r[n]) for n in NAMES}
          for _, r in paper_params("grip").iterrows()}

F_BAND = np.geomspace(0.1, 100.0, 200)

#: A second point per library effect, away from its typical values (inside its bounds).
OTHER = {"delay": {"delay_s": 0.0371},
         "lowpass": {"cutoff_hz": 5.0},
         "device-damping": {"damping_Ns_per_m": 30.0},
         "device-mass": {"mass_kg": 0.5},
         "resonance": {"freq_hz": 120.0, "zeta": 0.05, "weight": 0.8},
         "reflex": {"gain_N_per_m": 1000.0, "delay_s": 0.01}}

RATIONAL_EFFECTS = [e.name for e in library.EFFECTS if e.name != "reflex"]


def _theta(axis, name, values):
    return {**TABLE2[axis], **{f"{name}.{k}": float(v) for k, v in values.items()}}


def _points(name):
    e = get_effect(name)
    return [("typical", {p.name: p.typical for p in e.params}), ("other", OTHER[name])]


# ---------------------------------------------------------------------------
# 1. The plant from the rational forms equals the model's response
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("axis", ["x", "y", "z"])
@pytest.mark.parametrize("name", RATIONAL_EFFECTS)
def test_plant_equals_model_response_for_every_library_effect(name, axis):
    """For every built-in effect whose form has no delay inside an impedance (output
    delays are kept exact as ``delay_s``), at its typical values and at a second point:
    the RationalPlant's response num/den·e^(−sτ) equals ClosedLoopModel.response (eq. 4
    with the effect's ``term``, an independent evaluation) on 0.1–100 Hz to 1e-9
    relative — both are the same function, so they agree to rounding."""
    model = ClosedLoopModel.for_axis(axis, effects=[get_effect(name)])
    for _, values in _points(name):
        theta = _theta(axis, name, values)
        plant = plant_from_model(model, theta)
        np.testing.assert_allclose(plant.response(F_BAND), model.response(F_BAND, theta),
                                   rtol=1e-9, atol=0)
        if name == "delay":     # an output delay is exact, not approximated
            assert plant.delay_s == values["delay_s"]
            assert plant.den.size == 5          # the base plant's fourth order, untouched


def _pade_exp(order):
    """[n/n] Padé approximant of e^(−x) by scipy.interpolate.pade from the Taylor
    coefficients (−1)^k/k! (independent of armfit.loop.pade_delay)."""
    taylor = [(-1.0) ** k / math.factorial(k) for k in range(2 * order + 1)]
    return interpolate.pade(taylor, order, order)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_reflex_plant_is_the_pade_approximant_within_its_phase_bound(axis):
    """The reflex's delay sits inside the arm impedance, so the plant holds its
    [6/6] Padé approximant R (INTERNAL_DELAY_PADE_ORDER). (a) On 0.1–100 Hz the plant
    equals 1/(Z_ARM + Mp s² + g R(sτ)) with R from scipy.interpolate.pade, to 1e-9.
    (b) Against the exact model response: P_R/P − 1 = P_R g (e^(−sτ) − R(sτ)), and
    |R(jx)| = 1, so |P_R/P − 1| = g |P_R| 2|sin(Δφ/2)| ≤ g |P_R| 2 sin(0.5°) where the
    Padé phase error Δφ is below 1°, i.e. up to ω·τ = 7.7 (checked here too)."""
    assert INTERNAL_DELAY_PADE_ORDER == 6
    num_x, den_x = _pade_exp(6)
    model = ClosedLoopModel.for_axis(axis, effects=[get_effect("reflex")])
    s = 2j * np.pi * F_BAND
    for _, values in _points("reflex"):
        g, tau = values["gain_N_per_m"], values["delay_s"]
        theta = _theta(axis, "reflex", values)
        base = ClosedLoopModel.for_axis(axis).response(F_BAND, TABLE2[axis])
        p = plant_from_model(model, theta).response(F_BAND)
        ref = 1.0 / (1.0 / base + g * num_x(s * tau) / den_x(s * tau))
        np.testing.assert_allclose(p, ref, rtol=1e-9, atol=0)
        ok = 2 * np.pi * F_BAND * tau <= 7.7
        assert ok.sum() > 100          # most of the band (f ≤ 30.6 Hz at τ = 40 ms)
        phase = np.angle(num_x(s[ok] * tau) / den_x(s[ok] * tau) * np.exp(s[ok] * tau))
        assert np.degrees(np.max(np.abs(phase))) < 1.0
        exact = model.response(F_BAND, theta)
        err = np.abs(p / exact - 1.0)[ok]
        bound = g * np.abs(p[ok]) * 2 * math.sin(math.radians(0.5))
        assert np.all(err <= bound * (1 + 1e-9))


# ---------------------------------------------------------------------------
# 2. Registration refuses a wrong rational form
# ---------------------------------------------------------------------------

def _spring_term(s, v, mp):
    return v["k"] + 0.0 * s


def _damper_term(s, v, mp):
    return v["b"] * s


def _lag_term(s, v, mp):
    return 1.0 / (1.0 + s / (2.0 * np.pi * v["fc"]))


def _delay_term(s, v, mp):
    return np.exp(-s * v["tau"])


KINDS = {
    "spring": ("device", Param("k", "N/m", 0.01, 5000.0, 50.0, "spring"), (0.01,),
               _spring_term, lambda v, mp: (v["k"], 1.0)),
    "damper": ("device", Param("b", "N*s/m", 1e-4, 100.0, 2.0, "damper"), (1e-4,),
               _damper_term, lambda v, mp: ((v["b"], 0.0), 1.0)),
    "lag": ("output", Param("fc", "Hz", 1.0, 1e5, 60.0, "corner"), (1e5,),
            _lag_term, lambda v, mp: (1.0, (1.0 / (2 * np.pi * v["fc"]), 1.0))),
    "latency": ("output", Param("tau", "s", 0.0, 0.1, 0.01, "latency", log=False), (0.0,),
                _delay_term, lambda v, mp: (1.0, 1.0, v["tau"])),
}


def _effect(kind, rational, name=None):
    stage, param, null, term, _ = KINDS[kind]
    return Effect(name=name or f"test-{kind}", stage=stage, params=(param,), term=term,
                  rational=rational, null=null, summary="test effect")


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_right_rational_forms_pass_registration(kind):
    """The control for the refusals below: each test effect with its correct form
    (k/1, B s/1, 1/(s/ω_c + 1), 1/1·e^(−sτ)) passes check_effect, and its
    rational_form evaluates to its term."""
    e = _effect(kind, KINDS[kind][4])
    check_effect(e)
    v = {e.params[0].name: e.params[0].typical}
    num, den, tau = e.rational_form(v, 0.09)
    s = 2j * np.pi * np.array([0.3, 3.0, 30.0])
    np.testing.assert_allclose(np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * tau),
                               e.term(s, v, 0.09), rtol=1e-12)


WRONG = {
    "spring-sign": ("spring", lambda v, mp: (-v["k"], 1.0)),
    "spring-coefficient-1e-6": ("spring", lambda v, mp: (v["k"] * (1 + 1e-6), 1.0)),
    "spring-power-of-s": ("spring", lambda v, mp: ((v["k"], 0.0), 1.0)),
    "spring-spurious-delay": ("spring", lambda v, mp: (v["k"], 1.0, 1e-3)),
    "spring-negative-delay": ("spring", lambda v, mp: (v["k"], 1.0, -1e-3)),
    "spring-nan-num": ("spring", lambda v, mp: (math.nan, 1.0)),
    "spring-nan-delay": ("spring", lambda v, mp: (v["k"], 1.0, math.nan)),
    "spring-inf-den": ("spring", lambda v, mp: (v["k"], (math.inf, 1.0))),
    "spring-zero-den": ("spring", lambda v, mp: (v["k"], 0.0)),
    "spring-not-a-pair": ("spring", lambda v, mp: v["k"]),
    "spring-raises": ("spring", lambda v, mp: (v["stiffness"], 1.0)),
    "damper-s-squared": ("damper", lambda v, mp: ((v["b"], 0.0, 0.0), 1.0)),
    "damper-no-s": ("damper", lambda v, mp: ((v["b"],), 1.0)),
    "damper-sign": ("damper", lambda v, mp: ((-v["b"], 0.0), 1.0)),
    "lag-lowest-power-first": ("lag", lambda v, mp: (1.0, (1.0, 1.0 / (2 * np.pi * v["fc"])))),
    "lag-hz-not-rad": ("lag", lambda v, mp: (1.0, (1.0 / v["fc"], 1.0))),
    "latency-left-out": ("latency", lambda v, mp: (1.0, 1.0)),
    "latency-negative": ("latency", lambda v, mp: (1.0, 1.0, -v["tau"])),
    "latency-as-first-order-lag": ("latency", lambda v, mp: (1.0, (v["tau"], 1.0))),
}


@pytest.mark.parametrize("case", sorted(WRONG))
def test_wrong_rational_form_is_refused_naming_the_effect(case):
    """A form that is not the term (a wrong coefficient, sign or power of s, a delay
    where there is none or none where there is one, coefficients ordered lowest power
    first, ω_c in Hz instead of rad/s, a 1e-6 relative error — all far above
    RATIONAL_RTOL = 1e-9), or that is not a valid form (a negative or NaN delay, NaN or
    infinite coefficients, a zero denominator, not a pair, raising): check_effect raises
    EffectDefinitionError naming the effect; the same term with its right form passes
    (test_right_rational_forms_pass_registration)."""
    kind, rational = WRONG[case]
    e = _effect(kind, rational, name=f"bad-{case}")
    with pytest.raises(EffectDefinitionError) as info:
        check_effect(e)
    assert f"bad-{case}" in str(info.value)


def test_non_callable_rational_is_refused():
    """rational must be a function (or None): a tuple of coefficients is refused when the
    Effect is built, naming it."""
    with pytest.raises(EffectDefinitionError) as info:
        _effect("spring", (50.0, 1.0), name="tuple-rational")
    assert "tuple-rational" in str(info.value)


HEADER = "import numpy as np\nfrom armfit import Effect, Param\n\n"


def _effect_file(path, name, rational_src):
    """A user's effect file: a device spring named ``name``; ``rational_src`` is the
    source of its ``rational=`` argument (or None: no rational form)."""
    extra = f", rational={rational_src}" if rational_src is not None else ""
    path.write_text(HEADER + textwrap.dedent(f"""\
        def _term(s, values, mp):
            return values["k_N_per_m"] + 0.0 * s

        EFFECTS = [Effect(name={name!r}, stage="device",
                          params=(Param("k_N_per_m", "N/m", 0.01, 5000.0, 50.0, "spring"),),
                          term=_term, null=(0.01,), summary="a spring"{extra})]
        """))
    return path


@pytest.mark.parametrize("rational_src", ["lambda v, mp: (-v['k_N_per_m'], 1.0)",
                                          "lambda v, mp: ((v['k_N_per_m'], 0.0), 1.0)",
                                          "lambda v, mp: (v['k_N_per_m'], 1.0, -0.001)",
                                          "lambda v, mp: (float('nan'), 1.0)",
                                          "'k/1'"])
def test_effect_file_with_wrong_rational_is_refused_and_not_registered(tmp_path,
                                                                      rational_src):
    """load_effect_file on a file whose spring has a wrong sign, a wrong power of s, a
    negative delay, a NaN coefficient or a non-callable rational: EffectDefinitionError
    naming the effect, and nothing registered. The same file with the right form
    (k/1) loads."""
    before = list(EFFECTS)
    bad = _effect_file(tmp_path / "bad.py", "file-spring", rational_src)
    with pytest.raises(EffectDefinitionError) as info:
        load_effect_file(bad)
    assert "file-spring" in str(info.value)
    assert list(EFFECTS) == before
    good = _effect_file(tmp_path / "good.py", "file-spring",
                        "lambda v, mp: (v['k_N_per_m'], 1.0)")
    try:
        (e,) = load_effect_file(good)
        assert EFFECTS["file-spring"] is e
    finally:
        EFFECTS.unregister(["file-spring"])


def test_plant_from_model_refuses_an_effect_without_rational():
    """An effect that declares no rational form cannot be put into the sampled plant:
    UsageError (exit 2) naming it; the same effect with its form gives the plant."""
    e = _effect("spring", None, name="no-rational-spring")
    model = ClosedLoopModel.for_axis("x", effects=[e])
    theta = {**TABLE2["x"], "no-rational-spring.k": 300.0}
    with pytest.raises(UsageError) as info:
        plant_from_model(model, theta)
    assert info.value.exit_code == 2 and "no-rational-spring" in str(info.value)
    ok = ClosedLoopModel.for_axis("x", effects=[_effect("spring", KINDS["spring"][4])])
    plant = plant_from_model(ok, {**TABLE2["x"], "test-spring.k": 300.0})
    np.testing.assert_allclose(plant.response(F_BAND), model.response(F_BAND, theta),
                               rtol=1e-9)


# ---------------------------------------------------------------------------
# 3. The device-spring example through `armfit stability`
# ---------------------------------------------------------------------------

def _independent_k_max(arm, mp, k_spring, T=1e-3):
    """K_max of the wall C(z) = K z⁻¹ (one sample of delay, B = 0) on
    X/F = 1/(Z_ARM + Mp s² + k), Z_ARM = (b1 s + k1)(Ma s² + b2 s + k2) /
    (Ma s² + (b1 + b2) s + k1 + k2) (eq. 3), built here from the formula; the sampled loop
    is then solved by test_stability's independent route (scipy.signal.cont2discrete ZOH,
    roots of the characteristic polynomial on a log scan of K, bisection)."""
    Ma, k1, k2, b1, b2 = (arm[n] for n in NAMES)
    zden = np.array([Ma, b1 + b2, k1 + k2])
    den = np.polyadd(np.polymul([b1, k1], [Ma, b2, k2]), np.polymul([mp, 0.0, k_spring], zden))
    return k_max_by_roots(zden, den, T, B=0.0, d=1)


#: Springs per axis of the hand-written params file (N/m).
SPRINGS = {"x": 4000.0, "y": 300.0, "z": 2000.0}


def _write_params(path, effect_name, springs=SPRINGS):
    """A params CSV in the layout of docs/formats.md ("Params CSV",
    armfit.io.schema.params_columns): Table II with a spring on each axis, the effects
    column naming ``effect_name`` (one effect: no ``;``), intervals left empty."""
    pname = f"{effect_name}.k_N_per_m"
    cols = params_columns(list(NAMES) + [pname], grip=False)
    rows = []
    for axis in "xyz":
        row = dict.fromkeys(cols, np.nan)
        row.update(TABLE2[axis])
        row.update({"axis": axis, pname: springs[axis], "rms_db": 0.1, "rms_deg": 1.0,
                    "rms_norm": 1.0, "band_lo_hz": 0.1, "band_hi_hz": 30.0, "n_points": 61,
                    "cost": "complex", "converged": True, "mp_kg": MP[axis],
                    "effects": effect_name, "at_bound": ""})
        rows.append(row)
    pd.DataFrame(rows, columns=cols).to_csv(path, index=False)
    return path


def _k_max_cli(runner, args):
    res = runner.invoke(cli, ["stability", *args, "--json"])
    assert res.exit_code == 0, res.stderr
    return [m["k_max_N_per_m"] for m in json.loads(res.stdout)["models"]]


def test_stability_cli_with_the_device_spring_matches_independent_k_max(runner, tmp_path):
    """`armfit stability P.csv --effects examples/device_spring.py` (T = 1 ms, B = 0,
    d = 1): each row's K_max within 1 % of _independent_k_max for Table II plus that
    row's spring. The spring is really in the plant: on X (4 kN/m) K_max is more than
    3 % above the value without it (3.62 kN/m, the same independent computation)."""
    params = _write_params(tmp_path / "spring.csv", "device-spring")
    got = _k_max_cli(runner, [str(params), "--effects", str(SPRING)])
    want = [_independent_k_max(TABLE2[a], MP[a], SPRINGS[a]) for a in "xyz"]
    np.testing.assert_allclose(got, want, rtol=0.01)
    bare = _independent_k_max(TABLE2["x"], MP["x"], 0.0)
    assert got[0] > 1.03 * bare


def test_stability_cli_without_the_effects_file_is_one_line_exit_65(runner, tmp_path):
    """Without --effects the params file names an unknown effect: bad input (exit 65,
    docs/formats.md "Params CSV"), one line naming the effect, no traceback."""
    params = _write_params(tmp_path / "spring.csv", "device-spring")
    res = runner.invoke(cli, ["stability", str(params)])
    assert res.exit_code == 65
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr
    assert "device-spring" in lines[0]
    assert res.stdout == ""


@pytest.mark.parametrize("command", [["stability"], ["plot", "stability"]])
def test_effect_without_rational_is_a_usage_error(runner, tmp_path, command):
    """A user effect with no rational form: `armfit stability` and `armfit plot
    stability` exit 2 (usage error) with one line naming it. The control: the same file
    with rational k/1 added runs (exit 0), and `stability` gives exactly the K_max of
    the example's device-spring (the same term)."""
    params = _write_params(tmp_path / "p.csv", "plain-spring")
    png = tmp_path / "k.png"
    out = ["-o", str(png)] if command[0] == "plot" else []
    bare = _effect_file(tmp_path / "bare.py", "plain-spring", None)
    res = runner.invoke(cli, [*command, str(params), "--effects", str(bare), *out])
    assert res.exit_code == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr
    assert "plain-spring" in lines[0]
    assert not png.exists()
    good = _effect_file(tmp_path / "good.py", "plain-spring",
                        "lambda v, mp: (v['k_N_per_m'], 1.0)")
    res = runner.invoke(cli, [*command, str(params), "--effects", str(good), *out])
    assert res.exit_code == 0, res.stderr
    if command[0] == "plot":
        assert png.stat().st_size > 0
    else:
        example = _write_params(tmp_path / "example.csv", "device-spring")
        got = _k_max_cli(runner, [str(params), "--effects", str(good)])
        assert got == pytest.approx(_k_max_cli(runner, [str(example), "--effects",
                                                        str(SPRING)]), rel=1e-9)
    assert "plain-spring" not in EFFECTS        # the command unregistered its file


# ---------------------------------------------------------------------------
# 4. fit-trials with a user effect, then stability on its output
# ---------------------------------------------------------------------------

def test_fit_trials_with_the_device_spring_then_stability(runner, tmp_path):
    """One noise-free trial: Table I (X, 2 N, Mp = 0.09 kg) plus a 300 N/m device spring
    (the model's response with the example's effect). `fit-trials --effects FILE
    --effect device-spring` recovers the spring and the arm to 1e-3, and `stability` on
    its output gives K_max within 1 % of _independent_k_max for those true values."""
    truth = TABLE1[("x", 2.0)]
    (e,) = load_effect_file(SPRING)
    try:
        model = ClosedLoopModel.for_axis("x", effects=[e])
        h = model.response(GRID, {**truth, "device-spring.k_N_per_m": 300.0})
    finally:
        EFFECTS.unregister(["device-spring"])
    spectra, trials = tmp_path / "s.parquet", tmp_path / "trials.csv"
    Spectra.from_frame(_spectra_rows("S1", "x", 2.0, h), meta={}).write(spectra)
    res = runner.invoke(cli, ["fit-trials", str(spectra), "-o", str(trials),
                              "--effects", str(SPRING), "--effect", "device-spring"])
    assert res.exit_code == 0, res.stderr
    df = pd.read_csv(trials)
    assert df["effects"].iloc[0] == "device-spring"
    assert df["device-spring.k_N_per_m"].iloc[0] == pytest.approx(300.0, rel=1e-3)
    for n in NAMES:
        assert df[n].iloc[0] == pytest.approx(truth[n], rel=1e-3)
    (k,) = _k_max_cli(runner, [str(trials), "--effects", str(SPRING)])
    assert k == pytest.approx(_independent_k_max(truth, 0.09, 300.0), rel=0.01)
