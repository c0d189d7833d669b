"""H1, H2 and the estimate through a reference column; the not_excitation flag.

Expected values come from the estimators' definitions (Bendat & Piersol, Random Data,
4th ed., ch. 6; Pintelon & Schoukens, System Identification, 2nd ed., ch. 2): with noise
on the force only, H1 = G·S_FF/(S_FF + S_mm) and H2 = G; with the reference r = F, the
reference estimate is H1 itself. The closed-loop cases use tests/tdsim.py's rig, whose
truth (the open loop's X/F, :func:`tdsim.true_response`) is computed from its own
polynomials, not by armfit.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import tdsim

import armfit.spectra as S
from armfit.cli.main import cli

FS = 1000.0
N = 120000          # 120 s
GRID = S.log_grid(0.1, 30.0, 40)


def _band_limited(rng, n: int, f_hi: float) -> np.ndarray:
    """White noise with the DFT bins above f_hi removed: a flat PSD up to f_hi."""
    spec = np.fft.rfft(rng.standard_normal(n))
    spec[np.fft.rfftfreq(n, 1 / FS) > f_hi] = 0.0
    return np.fft.irfft(spec, n)


def _second_order(f: np.ndarray) -> np.ndarray:
    """x = G F by the DFT (periodic, so exact at every bin): G = 1e-3/(1 + s/ω + s²/ω²)
    with ω = 2π 8 Hz, and G on the grid."""
    freq = np.fft.rfftfreq(f.size, 1 / FS)
    s = 2j * np.pi * freq / (2 * np.pi * 8.0)
    return np.fft.irfft(np.fft.rfft(f) * 1e-3 / (1 + s + s * s), f.size)


def _g(freq):
    s = 2j * np.pi * np.asarray(freq) / (2 * np.pi * 8.0)
    return 1e-3 / (1 + s + s * s)


def _norm_err(h, se_db, se_deg, truth):
    """rms of (estimate − truth)/se over dB and phase (se floored at 0.01 dB and 0.06°,
    the floors of docs/methods.md, "The noise model")."""
    e_db = 20 * np.log10(np.abs(h / truth))
    e_deg = np.degrees(np.angle(h / truth))
    z = np.r_[e_db / np.maximum(se_db, 0.01), e_deg / np.maximum(se_deg, 0.06)]
    return float(np.sqrt(np.nanmean(z ** 2)))


@pytest.fixture(scope="module")
def noisy_force():
    """Force noise only: x = G F0 exactly, the recorded force F0 + m (m white, its PSD a
    quarter of F0's in the band), the commanded force F0 as the reference."""
    rng = np.random.default_rng(11)
    f0 = _band_limited(rng, N, 40.0)
    x = _second_order(f0)
    m = rng.standard_normal(N) * f0.std() * np.sqrt(0.25 * (FS / 2) / 40.0)
    return f0, f0 + m, x


def test_h2_is_right_and_h1_low_when_the_noise_is_on_the_force(noisy_force):
    f0, f, x = noisy_force
    sp = S.welch_spectra(f, x, FS, nperseg=16384)
    h1 = S.to_grid(sp, GRID)
    h2 = S.h2_to_grid(sp, GRID)
    # H1 = G · S_FF/(S_FF + S_mm) = G / 1.25: -1.94 dB, the same phase (flat spectra),
    # less the small-sample bias of a ratio of averaged spectra, of order (1 − γ²)/n_d
    # (+0.2 dB here, γ² = 0.8 and n_d = 8…32)
    err1 = 20 * np.log10(np.abs(h1.h[0] / _g(GRID)))
    assert np.median(err1) == pytest.approx(20 * np.log10(1 / 1.25), abs=0.3)
    # H2 is unbiased: within its noise of G
    assert _norm_err(h2.h[0], h2.se_db[0], h2.se_deg[0], _g(GRID)) < 1.5
    # and H1/H2 = γ² ≤ 1 at the band level: H2 above H1 at (nearly) every point
    assert np.mean(np.abs(h2.h[0]) > np.abs(h1.h[0])) > 0.95


def test_the_reference_estimate_is_right_when_the_noise_is_on_the_force(noisy_force):
    f0, f, x = noisy_force
    sp = S.welch_spectra(f, x, FS, nperseg=16384)
    rsp = S.welch_spectra(f0, np.column_stack([f, x]), FS, nperseg=16384)
    g = S.reference_to_grid(rsp, sp, GRID)
    # S_rx/S_rF = G whatever the force's own noise: within the noise of the truth
    assert _norm_err(g.h[0], g.se_db[0], g.se_deg[0], _g(GRID)) < 1.5


def test_the_reference_estimate_through_the_force_itself_is_h1():
    # r = F: S_Fx/S_FF is H1, and the delta-method errors reduce to Bendat & Piersol's
    rng = np.random.default_rng(12)
    f = _band_limited(rng, 60000, 40.0)
    x = _second_order(f) + 2e-5 * rng.standard_normal(f.size)
    sp = S.welch_spectra(f, x, FS, nperseg=16384)
    rsp = S.welch_spectra(f, np.column_stack([f, x]), FS, nperseg=16384)
    g, r = S.to_grid(sp, GRID), S.reference_to_grid(rsp, sp, GRID)
    np.testing.assert_allclose(r.h, g.h, rtol=1e-12)
    np.testing.assert_allclose(r.se_db, g.se_db, rtol=5e-3)
    np.testing.assert_allclose(r.se_deg, g.se_deg, rtol=5e-3)


# ---------------------------------------------------------------------------
# The closed-loop rig (tests/tdsim.py)
# ---------------------------------------------------------------------------

RIG_STUDY = tdsim.Study(subjects=2, axes=("x", "z"), grips_N=(1.0,), duration_s=(60.0, 60.0),
                        seed=21, drift_m=2e-3)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """A rig study (a 300 N/m, 1 N·s/m controller on the measured position, the
    commanded force logged as ref_<a>_N) and its truth."""
    folder = tdsim.write_rig_study(RIG_STUDY, tdsim.Rig(),
                                   tmp_path_factory.mktemp("rig") / "study")
    truth = json.loads((folder / "truth.json").read_text())["trials"]
    return folder, truth


def _measured(tr: S.TrialResponses) -> S.Response:
    return next(r for r in tr.responses if r.kind == "measured")


def test_rig_h1_is_biased_and_flagged(rig):
    folder, truth = rig
    res = S.estimate_study([folder], S.EstimateConfig(reference=False))
    for tr, tt in zip(res.trials, truth, strict=True):
        m = _measured(tr)
        true = tdsim.true_response(tt, tr.freq_hz)
        low = tr.freq_hz < 0.3
        # the position's drift enters the force through the controller: below 0.3 Hz H1
        # tends to -1/C, several dB under the truth
        err = 20 * np.log10(np.abs(m.h / true))
        assert m.method == "h1" and np.median(err[low]) < -5.0
        assert tr.check.feedback.fires and tr.check.feedback.p_value < 1e-10
        flagged = np.array([S.NOT_EXCITATION in f for f in m.flags])
        assert flagged[low].sum() >= 5 and not flagged[tr.freq_hz > 1.0].any()
        # where flagged, H1 is below the truth by more than its own noise
        assert np.median(err[flagged] / m.se_db[flagged]) < -1.5
    assert len(res.warnings) == len(res.trials)
    assert all("feedback test p =" in w and "flagged not_excitation" in w
               and "ref_" in w for w in res.warnings)


def test_rig_estimate_through_the_reference_is_within_the_noise(rig):
    folder, truth = rig
    res = S.estimate_study([folder], S.EstimateConfig())
    for tr, tt in zip(res.trials, truth, strict=True):
        m = _measured(tr)
        true = tdsim.true_response(tt, tr.freq_hz)
        assert m.method == "ref" and tr.check.reference == f"ref_{tr.axis}_N"
        assert _norm_err(m.h, m.se_db, m.se_deg, true) < 1.5
        assert not any(S.NOT_EXCITATION in f for f in m.flags)
        # H1 is kept beside it, flagged where it is biased
        h1 = next(r for r in tr.responses if r.kind == "alternative" and r.method == "h1")
        assert any(S.NOT_EXCITATION in f for f in h1.flags)
    derived = [r for tr in res.trials for r in tr.responses if r.kind == "derived"]
    assert {r.method for r in derived} == {"tfestimate-ref"}


def test_open_loop_studies_are_not_flagged(tmp_path):
    # tdsim's open loop (the force is the excitation; postural drift, quantisation) and
    # the sample study: no trial fires (where the test is needed at all), no point is
    # flagged, nothing is said
    folder = tdsim.write_study(tdsim.Study(subjects=2, axes=("x", "z"), grips_N=(1.0,),
                                           seed=31), tmp_path / "null")
    tested = 0
    for source in (folder, "sample_data/study"):
        res = S.estimate_study([source], S.EstimateConfig())
        assert not res.warnings
        for tr in res.trials:
            fb = tr.check.feedback
            assert (fb is None) == (not tr.check.needs_feedback_test)
            tested += fb is not None
            assert (fb is None or not fb.fires) and tr.check.cause is None
            assert not any(S.NOT_EXCITATION in f for r in tr.responses for f in r.flags)
    assert tested > 0          # drift lifts H2 above H1 at low frequency in some trials


def test_the_feedback_test_is_quiet_on_every_open_loop_trial(tmp_path):
    # run on every trial of an open-loop study (where the estimator would skip it too):
    # the force is the excitation, p far above the threshold
    from armfit.feedback import FEEDBACK_ALPHA, feedback_test
    study = tdsim.Study(subjects=2, axes=("x", "z"), grips_N=(1.0, 2.0), seed=32)
    for s in range(study.subjects):
        for axis in study.axes:
            for grip in study.grips_N:
                f, x, _ = tdsim.simulate_trial(study, s, axis, grip)
                assert feedback_test(f, x, study.fs, 30.0).p_value > 100 * FEEDBACK_ALPHA


def test_estimate_command_on_the_rig(rig, runner, tmp_path):
    folder, _ = rig
    out = tmp_path / "s.parquet"
    res = runner.invoke(cli, ["estimate", str(folder), "-o", str(out), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    n = len(RIG_STUDY.axes) * RIG_STUDY.subjects
    assert doc["estimators"]["reference_trials"] == n
    assert doc["estimators"]["feedback_trials"] == n
    assert f"({n} through their reference column)" in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("warning: ")]
    assert len(lines) == len(doc["estimators"]["messages"])
    assert all(" estimated through the reference ref_" in ln for ln in lines)
    meta = S.Spectra.read(out).meta
    assert [e["method"] for e in meta["estimators"]] == ["ref"] * n
    assert all(e["feedback"]["fires"] for e in meta["estimators"])
    # --no-reference: H1, flagged on the measured rows
    res = runner.invoke(cli, ["estimate", str(folder), "-o", str(out), "--overwrite",
                              "--no-reference"])
    assert res.exit_code == 0, res.output
    sp = S.Spectra.read(out, level="trial", kind="measured")
    assert sp.values_of("method") == {"h1"}
    assert any(S.NOT_EXCITATION in f for f in sp.flags.ravel())


def test_run_on_the_rig_says_it_and_keeps_the_reference(rig, runner, tmp_path):
    # run ingests the reference into its dataset and estimates through it; the
    # estimator's lines come out among the run's warnings
    folder, _ = rig
    out = tmp_path / "run"
    res = runner.invoke(cli, ["run", str(folder), "-o", str(out), "--no-figures"])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.stderr.splitlines() if "estimated through the reference" in ln]
    assert len(lines) == len(RIG_STUDY.axes) * RIG_STUDY.subjects
    import pyarrow.parquet as pq
    assert pq.read_schema(out / "trials.parquet").names[-1] == "ref"
    sp = S.Spectra.read(out / "spectra.parquet", kind="measured")
    assert sp.values_of("method") == {"ref"}


def test_the_diagnosis_does_not_blame_an_effect_for_the_estimators_bias(rig, monkeypatch):
    # The rig's H1 is biased below 0.3 Hz (the force reacts to the position's drift) and
    # flagged not_excitation there. The diagnosis leaves those points out of its
    # evidence: the arm model is then adequate with nothing named (the simulator's truth:
    # the rig's arm is the 5-parameter model), and it says what it left out.
    from armfit import api
    from armfit.diagnosis import diagnose_axes, diagnosis_to_dict
    from armfit.diagnosis import responses as R
    folder, _ = rig
    spectra = api.estimate(str(folder), reference=False)
    grip = api.fit_grip(spectra).table
    result = diagnose_axes(spectra, grip)
    for d in result:
        assert d.missing_effects == () and d.adequate, d.verdict
        assert d.excluded_trials == 2 and all(hi < 1.0 for _, hi in d.excluded_hz)
        assert "left out of the evidence" in d.verdict and "not_excitation" in d.verdict
        doc = diagnosis_to_dict([d])["axes"][d.axis]
        assert doc["excluded"]["trials"] == 2
    # the same search with the flagged points kept (an independent run of the search on
    # the same responses): the estimator's bias then reads as a misfit of the model
    monkeypatch.setattr(R, "not_excitation", lambda rows: None)
    kept = diagnose_axes(spectra, grip)
    assert any(not d.adequate or d.missing_effects for d in kept)
    assert all(k.base_error.rms_norm > d.base_error.rms_norm
               for k, d in zip(kept, result, strict=True))
