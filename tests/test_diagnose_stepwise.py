"""Tests of the stepwise diagnosis on studies armfit did not model.

Every study is made by the time-domain simulator of ``tests/tdsim.py`` (rational closed
loop discretised with cont2discrete, run with sosfilt; delay as integer + Thiran
fractional delay), estimated and fitted with armfit's defaults, then diagnosed. The
expected values are the simulator's known truth: the effects hidden and their values.
Studies are small (two subjects, one axis, 30–35 s trials) to keep each test short.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
import pytest
import tdsim

from armfit.diagnosis import (
    NOISE_TOL,
    diagnose_axes,
    diagnosis_to_dict,
    practical,
)
from armfit.diagnosis import compare_models as compare
from armfit.models.effects import EFFECTS

# on two worker processes unless told (the results do not depend on the number:
# test_diagnose_speedups)
diagnose = partial(diagnose_axes, jobs=2)

SMALL = dict(subjects=2, axes=("x",), duration_s=(30.0, 35.0))


def _study(tmp_path, which="grip", **kw):
    folder = tdsim.write_study(tdsim.Study(**{**SMALL, **kw}), tmp_path / "raw")
    return tdsim.estimate_and_fit(folder, which)


def _monotone(d):
    e = np.array(d.error_steps)
    assert len(e) == 1 + len(d.missing_effects)
    assert np.all(np.diff(e) <= 1e-12), e


def test_null_study_names_nothing_and_is_adequate(tmp_path):
    # no hidden effect: the 5-parameter model is adequate, whatever ΔBIC says
    spectra, params = _study(tmp_path, seed=31)
    (d,) = diagnose(spectra, params)
    assert d.adequate, d.verdict
    assert d.missing_effects == () and d.missing_effect is None
    assert d.verdict.startswith("adequate: nothing missing")
    assert d.error_steps[0] <= NOISE_TOL
    _monotone(d)


def test_delay_and_lag_both_named(tmp_path):
    # truth: 5 ms delay and a 20 Hz first-order lag (the compound case); the
    # resonance is a distractor that can mimic part of both
    spectra, params = _study(tmp_path, seed=32, effects={"delay": {"delay_s": 0.005},
                                                          "lowpass": {"cutoff_hz": 20.0}})
    (d,) = diagnose(spectra, params, effects=[EFFECTS[n] for n in
                                              ("delay", "lowpass", "resonance")])
    named = {m.effect: m for m in d.missing_effects}
    assert set(named) == {"delay", "lowpass"}, d.verdict
    assert named["delay"].params["delay_s"] == pytest.approx(0.005, abs=1.5e-3)
    assert named["lowpass"].params["cutoff_hz"] == pytest.approx(20.0, rel=0.2)
    assert d.adequate and d.error_steps[-1] <= 1.5, d.verdict
    assert d.error_steps[0] > 10.0          # the base model was far off
    _monotone(d)


def test_out_of_library_spring_is_not_adequate_then_the_plugin_fits(tmp_path):
    # truth: a 150 N/m spring in the device, not in the library
    spectra, params = _study(tmp_path, seed=33, effects={"device-spring": {"k_N_per_m": 150.0}})
    (d,) = diagnose(spectra, params, effects=[EFFECTS[n] for n in
                                              ("delay", "device-mass", "reflex")])
    _monotone(d)
    # never adequate while more than 1.5x the noise remains
    assert d.adequate == (d.error_steps[-1] <= NOISE_TOL and not d.final_failing
                          and not any(b.rms_norm > NOISE_TOL for b in d.final_bands))
    if not d.adequate:
        assert "still inadequate" in d.verdict and "outside the effect library" in d.verdict
    # the reflex can only mimic a spring with its delay at the 5 ms lower bound: flagged
    reflex = [m for m in d.missing_effects if m.effect == "reflex"]
    if reflex:
        assert "delay_s" in reflex[0].at_bound
        assert "not the answer" in d.verdict
    assert reflex or not d.adequate
    # with the user's effect file (the example in the docs) the spring is found
    from armfit.models.effects import load_effect_file
    path = Path(__file__).resolve().parents[1] / "examples" / "device_spring.py"
    (spring,) = load_effect_file(path)
    try:
        (d2,) = diagnose(spectra, params, effects=[EFFECTS["delay"], spring])
    finally:
        EFFECTS.unregister([spring.name])
    assert [m.effect for m in d2.missing_effects] == ["device-spring"], d2.verdict
    assert d2.missing_effects[0].params["k_N_per_m"] == pytest.approx(150.0, rel=0.15)
    assert d2.adequate and d2.error_steps[-1] <= 1.5
    _monotone(d2)


def test_json_keys(tmp_path):
    spectra, params = _study(tmp_path, seed=34, effects={"delay": {"delay_s": 0.01}})
    res = diagnose(spectra, params, effects=[EFFECTS["delay"], EFFECTS["lowpass"]])
    doc = diagnosis_to_dict(res)["axes"]["x"]
    for key in ("missing_effect", "tied_with", "verdict", "candidates", "base_error",
                "failing_bands", "missing_effects", "error_steps", "adequate"):
        assert key in doc
    assert doc["missing_effect"] == doc["missing_effects"][0]["effect"] == "delay"
    m = doc["missing_effects"][0]
    assert set(m) == {"effect", "params", "params_lo", "params_hi", "at_bound",
                      "rms_norm_after"}
    assert m["params_lo"]["delay_s"] < m["params"]["delay_s"] < m["params_hi"]["delay_s"]
    assert len(doc["error_steps"]) == 1 + len(doc["missing_effects"])
    assert isinstance(doc["adequate"], bool)


def test_non_white_input_diagnose_agrees_with_compare(tmp_path):
    # pseudo-random steps (power falling as 1/f² above ~1 Hz), a noisy sensor (coherence
    # far below 0.5 above ~10 Hz) and a 4 Hz lag the model lacks: diagnose's base error
    # and compare's on the median must agree within a factor 2
    spectra, params = _study(tmp_path, which="nominal", seed=35, subjects=3, input="steps",
                             hold_s=(0.3, 1.5), noise_m=5e-3, quantum_m=1e-4,
                             effects={"lowpass": {"cutoff_hz": 4.0}})
    (row,) = compare(spectra, params, level="median")
    (d,) = diagnose(spectra, params, max_steps=0)
    ratio = d.error_steps[0] / row.overall.rms_norm
    assert 0.5 <= ratio <= 2.0, (d.error_steps[0], row.overall.rms_norm)
    assert not d.adequate
    # max_steps=0 stops the search before its first step; the verdict says so in words
    # that hold for `run` too (which has no --max-steps of its own)
    assert d.verdict.endswith("the search stopped at its limit of 0 effect(s) "
                              "(armfit diagnose --max-steps)"), d.verdict


def test_practical_needs_a_run_above_noise_and_floor():
    f = np.geomspace(1, 30, 20)
    se = np.full((2, 20), 0.1)
    size = np.zeros(20)
    size[10:13] = 0.6      # 3 points above the 0.5 dB floor and the 0.1 dB noise
    ok, ratio = practical(f, size, np.zeros(20), se, se * 10, 0.5, 3.0)
    assert ok and ratio == pytest.approx(1.2)
    size[11] = 0.4         # the run is broken
    assert not practical(f, size, np.zeros(20), se, se * 10, 0.5, 3.0)[0]
