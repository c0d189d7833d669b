"""armfit's Welch spectra against GNU Octave's on one simulated trial.

The reference numbers come from Octave itself (signal package ``tfestimate``,
``mscohere``, ``pwelch``), run by the test on a 20 s trial at 1 kHz; the test runs only
where Octave is on PATH (it is optional: benchmarks/bench_octave.py times the same
computation on a whole study). Octave used when this test was written: GNU Octave 7.3.0,
signal package 1.4.3 (Debian 12 packages octave 7.3.0-2 and octave-signal 1.4.3-1),
run as

    octave-cli --norc --quiet --no-history --eval "<OCTAVE_CODE with its paths filled in>"

(``octave --no-gui`` in place of ``octave-cli`` where only that is installed).
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from armfit.constants import DEVICE_MASS_KG
from armfit.simulation import StudyConfig, plan_study, simulate_trial
from armfit.spectra import EstimateConfig, derived_spectra, welch_spectra

OCTAVE = shutil.which("octave-cli") or shutil.which("octave")
pytestmark = pytest.mark.skipif(OCTAVE is None, reason="GNU Octave is not on PATH")

#: Relative difference allowed between Octave's and armfit's H and coherence.
TOLERANCE = 1e-6

#: The Octave computation. ``pwelch("R12+")`` selects MATLAB's argument conventions
#: (overlap in samples; no mean removal unless asked). Per nperseg in SEGS: tfestimate and
#: mscohere of the force to the three positions (periodic Hann, 50 % overlap, nfft =
#: nperseg), as armfit's H1; then the derived arm dynamics Xa/Fa, Fa = F - Mp x'' (4
#: half-overlapped symmetric Hamming segments, each segment's mean removed: 'short'),
#: as armfit.spectra.derived_spectra. Written as float64 columns to OUT.
OCTAVE_CODE = """
pkg load signal; pwelch("R12+");
fid = fopen("{data}", "r"); d = fread(fid, [{n}, 4], "double"); fclose(fid);
F = d(:, 1); X = d(:, 2:4); fs = {fs!r}; cols = [];
for seg = [{segs}]
  for k = 1:3
    [H, f] = tfestimate(F, X(:, k), hann(seg, "periodic"), seg / 2, seg, fs);
    C = mscohere(F, X(:, k), hann(seg, "periodic"), seg / 2, seg, fs);
    cols = [cols; f; real(H); imag(H); C];
  end
end
x = X(:, {axis});
Fa = F(2:end-1) - {mp!r} * (x(3:end) - 2 * x(2:end-1) + x(1:end-2)) * fs ^ 2;
xa = x(2:end-1); L = floor(2 * numel(Fa) / 5); nfft = max(256, 2 ^ nextpow2(L));
[S, f] = pwelch(Fa, xa, hamming(L), floor(L / 2), nfft, fs, "short", "trans", "coher");
cols = [cols; f; real(S(:, 1)); imag(S(:, 1)); S(:, 2)];
fid = fopen("{out}", "w"); fwrite(fid, cols, "double"); fclose(fid);
"""


def run_octave(code: str) -> None:
    cmd = [OCTAVE, "--norc", "--quiet", "--no-history"]
    if OCTAVE.endswith("octave"):
        cmd.append("--no-gui")
    res = subprocess.run([*cmd, "--eval", code], capture_output=True, text=True)
    if res.returncode != 0 and "package" in res.stderr and "signal" in res.stderr:
        pytest.skip("Octave's signal package is not installed")
    assert res.returncode == 0, res.stderr


def max_rel(octave: np.ndarray, armfit: np.ndarray, use: np.ndarray) -> float:
    return float(np.max(np.abs(octave - armfit)[use] / np.abs(armfit)[use]))


def test_welch_spectra_and_derived_spectra_match_octave(tmp_path):
    cfg = StudyConfig(subjects=1, axes=("y",), grips_N=(2.0,), duration_s=(20.0, 20.0),
                      seed=5)
    trial = simulate_trial(plan_study(cfg)[0], cfg)
    fs, n, i = trial.meta.fs, trial.meta.n_samples, trial.meta.axis_index
    f = trial.f
    # armfit's own segment length for this record (16384: 2 segments), and a short one
    # (24 segments)
    segs = [EstimateConfig().h1_nperseg(fs, n), 2048]
    data, out = tmp_path / "trial.f64", tmp_path / "octave.f64"
    np.vstack([f, trial.pos.T]).astype("<f8").tofile(data)
    mp = DEVICE_MASS_KG[trial.meta.axis]
    run_octave(OCTAVE_CODE.format(data=data, n=n, fs=fs, segs=" ".join(map(str, segs)),
                                  axis=i + 1, mp=mp, out=out))
    got = np.fromfile(out, dtype="<f8")
    pos = 0
    for seg in segs:
        sp = welch_spectra(f, trial.pos, fs, nperseg=seg)
        for k in range(3):
            nb = sp.freq_hz.size
            fr, re, im, coh = got[pos:pos + 4 * nb].reshape(4, nb)
            pos += 4 * nb
            np.testing.assert_allclose(fr, sp.freq_hz, rtol=1e-12)
            # Octave keeps each segment's mean and armfit removes it: with a periodic Hann
            # window that changes only bins below first_bin, which armfit never uses
            use = (sp.coherence[k] > 0.5) & (np.arange(nb) >= sp.first_bin)
            assert use.sum() > 50
            assert max_rel(re + 1j * im, sp.h[k], use) < TOLERANCE
            assert max_rel(coh, sp.coherence[k], use) < TOLERANCE
    dsp = derived_spectra(f, trial.pos[:, i], fs, mp)
    nb = dsp.freq_hz.size
    assert got.size == pos + 4 * nb
    fr, re, im, coh = got[pos:].reshape(4, nb)
    np.testing.assert_allclose(fr, dsp.freq_hz, rtol=1e-12)
    use = (dsp.coherence[0] > 0.5) & (np.arange(nb) >= dsp.first_bin)
    assert use.sum() > 50
    assert max_rel(re + 1j * im, dsp.h[0], use) < TOLERANCE
    assert max_rel(coh, dsp.coherence[0], use) < TOLERANCE
