"""The test of a force that responds to the position (armfit.feedback).

Synthetic records at 1 kHz: a second-order system X/F (scipy's bilinear Butterworth, 8 Hz)
driven by a band-limited force (8th-order Butterworth at 30 Hz); the position carries
slow coloured noise (an AR(1) random drift) and white sensor noise. In open loop the
force is generated first (exogenous); in closed loop it is a commanded force minus a
spring on the measured position one sample late; position-driven, the position is
generated first and the force is a stiffness and damper on it plus noise.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal, stats

from armfit.feedback import (
    FEEDBACK_ALPHA,
    band_signals,
    chi2_sf,
    feedback_test,
)

FS = 1000.0
N = 40000        # 40 s


def _force(rng) -> np.ndarray:
    sos = signal.butter(8, 30.0, fs=FS, output="sos")
    return signal.sosfilt(sos, rng.standard_normal(N))


def _noise(rng) -> np.ndarray:
    """Position noise, m: an AR(1) drift (pole 0.999, 1 mm rms) and 5 µm white."""
    drift = signal.lfilter([1.0], [1.0, -0.999], rng.standard_normal(N))
    return 1e-3 * drift / drift.std() + 5e-6 * rng.standard_normal(N)


_B, _A = signal.butter(2, 8.0, fs=FS)     # X/F = 1e-3 m/N at DC, 8 Hz corner


@pytest.mark.parametrize(("x", "k"), [(0.3, 1), (4.0, 1), (2.0, 2), (7.5, 2), (5.0, 3),
                                       (12.0, 6), (212.8, 6), (300.0, 200)])
def test_chi2_survival_function(x, k):
    # against scipy.stats.chi2.sf, an independent implementation of the same function
    assert chi2_sf(x, k) == pytest.approx(stats.chi2.sf(x, k), rel=1e-10)


def test_chi2_survival_closed_forms():
    # k = 2: exp(-x/2); k = 1: erfc(sqrt(x/2)) (Abramowitz & Stegun 26.4.4-5)
    for x in (0.1, 1.0, 9.0, 100.0):
        assert chi2_sf(x, 2) == pytest.approx(math.exp(-x / 2), rel=1e-12)
        assert chi2_sf(x, 1) == pytest.approx(math.erfc(math.sqrt(x / 2)), rel=1e-12)
    assert chi2_sf(0.0, 6) == 1.0 and chi2_sf(5000.0, 6) == 0.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_exogenous_force_does_not_fire(seed):
    # open loop: whatever the position noise's colour, the residual is independent of
    # the future force; the test is conservative (p above FEEDBACK_ALPHA by far)
    rng = np.random.default_rng(seed)
    f = _force(rng)
    x = 1e-3 * signal.lfilter(_B, _A, f) + _noise(rng)
    res = feedback_test(f, x, FS, 30.0)
    assert res is not None and not res.fires
    assert res.p_value > 100 * FEEDBACK_ALPHA
    assert res.dof == 6


def test_a_force_that_responds_to_the_position_fires():
    # closed loop: F[t] = r[t] - k (x[t-1] + noise[t-1]); the sensor's noise enters the
    # force, so the future force carries the position's residual
    rng = np.random.default_rng(4)
    r, d = _force(rng), _noise(rng)
    g_b, g_a = 1e-3 * _B, _A
    # x = G F, F = r - k z^-1 (x + d): solved as one filter of u = r - k z^-1 d
    k = 200.0
    den = np.polyadd(g_a, k * np.concatenate([[0.0], g_b])[:g_a.size + 1][:g_a.size])
    u = r - k * np.concatenate([[0.0], d[:-1]])
    x = signal.lfilter(g_b, den, u) + d
    f = signal.lfilter(g_a, den, u)
    res = feedback_test(f, x, FS, 30.0)
    assert res is not None and res.fires and res.p_value < 1e-8


def test_a_force_measured_as_the_response_of_an_imposed_position_fires():
    # position-driven: x is imposed (random steps held 0.1-0.3 s), F = K x + B x' plus
    # noise (the torque of a joint driven by a position actuator). The regression of x on
    # F is then an errors-in-variables one; its bias leaves the imposed position's own
    # colour in the residual, which the future force carries: the test sees it when the
    # force's noise is not negligible (here 1 N white, about 0.25 N rms in the band, a
    # tenth of the 3 N of K x)
    rng = np.random.default_rng(5)
    holds = rng.integers(100, 300, size=N // 100)
    x = np.repeat(rng.uniform(-1e-3, 1e-3, holds.size), holds)[:N]
    x = signal.lfilter(*signal.butter(2, 20.0, fs=FS), x)
    f = 3000.0 * x + 20.0 * np.gradient(x) * FS + 1.0 * rng.standard_normal(N)
    res = feedback_test(f, x, FS, 30.0)
    assert res is not None and res.fires and res.p_value < 1e-6


def test_a_record_too_short_for_the_model_gives_none():
    # 1.5 s at 1 kHz: ~270 samples at the analysis rate for 186 coefficients
    rng = np.random.default_rng(6)
    f = rng.standard_normal(1500)
    assert feedback_test(f, np.cumsum(f), FS, 30.0) is None


def test_band_signals_keep_the_band_and_resample():
    # a 10 Hz sine inside the band keeps its amplitude but for the fourth-order moving
    # averages of the decimation by q = 4 (1000 Hz / 240 Hz), whose gain is
    # |sin(pi f q / fs) / (q sin(pi f / fs))|^4 (the taper starts at f_hi = 30 Hz);
    # a 60 Hz one (beyond 1.5 f_hi) is gone; the rate is about 6 f_hi
    t = np.arange(N) / FS
    f, x, rate = band_signals(np.sin(2 * np.pi * 10 * t), np.sin(2 * np.pi * 60 * t), FS, 30.0)
    assert rate == pytest.approx(180.0, rel=0.05) and f.size == x.size
    gain = abs(math.sin(math.pi * 10 * 4 / FS) / (4 * math.sin(math.pi * 10 / FS))) ** 4
    assert np.sqrt(2) * f.std() == pytest.approx(gain, rel=1e-3)
    assert x.std() < 1e-3
