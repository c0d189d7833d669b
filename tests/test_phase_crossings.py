"""The phase route to a sampled wall's crossing gains (armfit.loop._phase_crossings).

A long loop (many samples of latency) without virtual damping has its crossings found
from the phase H(θ) = Dθ − arg P(e^(jθ)) of the plant's poles and zeros instead of the
QZ of the (2N+1)-square pencil. Its answers are checked against two independent
computations: the pencil's generalised eigenvalues (LAPACK ggev, the route it replaces)
and a brute-force scan of the sign of Im g(e^(jθ)) on a fine grid of angles, each sign
change refined by scipy's brentq.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from armfit.loop import (
    MAX_LOOP_DELAY_SAMPLES,
    PHASE_ROUTE_MIN_STATES,
    RationalPlant,
    WallSettings,
    _crossing_gains_batch,
    _crossings,
    _distinct_sorted,
    _loops,
    _phase_crossings,
    closed_loop_stable,
    plant_from_model,
    wall_stability,
)
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import EFFECTS

#: Arms of the three axes (Ma kg, k1, k2 N/m, b1, b2 N·s/m): the compliant X and Y arms
#: and the stiff Z arm, as the paper's Table I spans them.
ARMS = {"x": (0.5, 120.0, 400.0, 8.0, 6.0), "y": (0.8, 90.0, 300.0, 5.0, 9.0),
        "z": (2.0, 2500.0, 150.0, 40.0, 30.0)}


def _plants() -> list[RationalPlant]:
    """Each arm alone, with an output delay of 3 to 12.3 ms (whole and fractional
    samples), with a delay and a lag, with a delay and a device resonance, and with a
    delayed reflex inside the arm (its Padé approximant): plants of order 4 to 10."""
    out = []
    for axis, arm in ARMS.items():
        base = dict(zip(("Ma", "k1", "k2", "b1", "b2"), arm, strict=True))
        out.append(plant_from_model(ClosedLoopModel.for_axis(axis), base))
        for tau in (0.003, 0.0071, 0.0123):
            out.append(plant_from_model(ClosedLoopModel.for_axis(axis, [EFFECTS["delay"]]),
                                        {**base, "delay.delay_s": tau}))
        m = ClosedLoopModel.for_axis(axis, [EFFECTS["delay"], EFFECTS["lowpass"]])
        out.append(plant_from_model(m, {**base, "delay.delay_s": 0.009,
                                        "lowpass.cutoff_hz": 40.0}))
        m = ClosedLoopModel.for_axis(axis, [EFFECTS["delay"], EFFECTS["resonance"]])
        out.append(plant_from_model(m, {**base, "delay.delay_s": 0.005,
                                        "resonance.freq_hz": 25.0, "resonance.zeta": 0.05,
                                        "resonance.weight": 0.3}))
        m = ClosedLoopModel.for_axis(axis, [EFFECTS["reflex"], EFFECTS["delay"]])
        theta = {**base, "delay.delay_s": 0.004,
                 **{f"reflex.{p.name}": p.typical for p in EFFECTS["reflex"].params}}
        out.append(plant_from_model(m, theta))
    return out


#: Servo rates from 250 Hz to 10 kHz and computation delays of 0 to 2 samples, without
#: virtual damping (the phase route's case).
SETTINGS = [WallSettings(1.0 / rate, 0.0, d) for rate in (250.0, 1000.0, 2828.4, 10000.0)
            for d in (0, 2)]


def _by_pencil(g) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pencil's crossing gains of each loop of ``g``, sorted, those within 1e-9 of
    the one below dropped (as :func:`armfit.loop._crossings` returns them)."""
    return [_distinct_sorted(K, th)
            for K, th in _crossing_gains_batch(g.M0, g.b, g.c, g_of=g.g)]


def _long_groups():
    for st in SETTINGS:
        for g in _loops(_plants(), st):
            # as wall_stability analyses them: at most MAX_LOOP_DELAY_SAMPLES of latency
            if g.M0.shape[1] >= PHASE_ROUTE_MIN_STATES and g.D <= MAX_LOOP_DELAY_SAMPLES:
                yield st, g


def test_the_phase_route_finds_every_crossing_the_pencil_finds():
    routed = doubted = more = 0
    for _, g in _long_groups():
        phase = _phase_crossings(g)
        for r, ((K, th), got) in enumerate(zip(_by_pencil(g), phase, strict=True)):
            if got is None:
                doubted += 1
                continue
            routed += 1
            Kp, thp = got
            # every crossing of the pencil is among the route's (the pencil's own roots
            # are accurate to about 1e-7 on the longest loops)
            near = np.abs(Kp[None, :] - K[:, None]) <= 1e-6 * K[:, None]
            assert near.any(axis=1).all(), (g.D, r)
            more += Kp.size - K.size
            # and each angle the route finds makes g real, to rounding or at least as
            # closely as the pencil's angles do
            gz = g.g(np.full(thp.size, r), np.exp(1j * thp))
            gp = g.g(np.full(th.size, r), np.exp(1j * th))
            worst = np.max(np.abs(gp.imag) / np.abs(gp))
            assert np.all(np.abs(gz.imag) <= max(1e-9, worst) * np.abs(gz))
    # the route answers most long loops (the others: a reflex's Padé poles and zeros
    # clustered near z = 1 at 2.8 and 10 kHz, whose phase misses g's by > 1e-4 rad)
    assert routed >= 80 and doubted <= routed // 5
    # at 10 kHz the pencil's eigenvalues stray more than 1e-6 from the unit circle and
    # miss crossings (the scan below finds them too): the route finds them
    assert more > 0


def test_the_crossings_are_those_of_a_scan_of_the_sign_of_im_g():
    """Brute force: Im g(e^(jθ)) on 100,001 angles of [0, π]; each sign change refined
    by brentq is a crossing; its gain is 1/Re g where positive."""
    checked = 0
    theta = np.linspace(0.0, np.pi, 100_001)
    for _, g in _long_groups():
        routed = [r for r, x in enumerate(_phase_crossings(g)) if x is not None]
        cands, _ = _crossings(g)
        for r in routed[::4]:
            def im_g(t, r=r, g=g):
                return float(g.g(np.array([r]), np.exp(1j * np.atleast_1d(t))).imag[0])
            v = g.g(np.full(theta.size, r), np.exp(1j * theta)).imag
            # the ends are crossings of every loop (g real at z = ±1)
            sc = np.flatnonzero(np.sign(v[1:-2]) * np.sign(v[2:-1]) < 0) + 1
            roots = np.array([brentq(im_g, theta[i], theta[i + 1], xtol=1e-15) for i in sc])
            z = np.concatenate([roots, [0.0, np.pi]])
            gz = g.g(np.full(z.size, r), np.exp(1j * z))
            pos = gz.real > 0
            K, _ = _distinct_sorted(1.0 / gz.real[pos], z[pos])
            np.testing.assert_allclose(cands[r], K, rtol=1e-7)
            checked += 1
    assert checked >= 25


def test_a_plant_root_on_the_unit_circle_leaves_the_loop_to_the_pencil():
    # a mass alone, 1/(m s²): its sampled poles sit at z = 1 (twice), its zero at −1
    mass = RationalPlant(np.array([1.0]), np.array([0.5, 0.0, 0.0]))
    arm = plant_from_model(ClosedLoopModel.for_axis("x"),
                           dict(zip(("Ma", "k1", "k2", "b1", "b2"), ARMS["x"], strict=True)))
    st = WallSettings(1e-3, 0.0, 12)
    (g_mass,), (g_arm,) = _loops([mass], st), _loops([arm], st)
    assert min(g_mass.M0.shape[1], g_arm.M0.shape[1]) >= PHASE_ROUTE_MIN_STATES
    assert _phase_crossings(g_mass) == [None]
    assert _phase_crossings(g_arm)[0] is not None
    # the doubted loop gets the pencil's answer as it is
    cands, thetas = _crossings(g_mass)
    ((K, th),) = _by_pencil(g_mass)
    np.testing.assert_array_equal(cands[0], K)
    np.testing.assert_array_equal(thetas[0], th)
    assert K.size > 3


@pytest.mark.parametrize("settings", SETTINGS[:4])
def test_k_max_is_the_pencils_on_long_loops(settings, monkeypatch):
    plants = _plants()
    got = wall_stability(plants, settings)
    import armfit.loop as loop
    monkeypatch.setattr(loop, "PHASE_ROUTE_MIN_STATES", 10**9)   # every loop by pencil
    want = wall_stability(plants, settings)
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a.k_max_N_per_m, b.k_max_N_per_m, rtol=1e-6)
        np.testing.assert_allclose(a.f_unstable_hz, b.f_unstable_hz, rtol=1e-6)
        assert a.unstable_at_zero == b.unstable_at_zero


def test_a_crossing_the_pencil_misses_at_10_khz_is_found():
    """The X arm with a 5 ms delay and a device resonance at 10 kHz: 50 samples of
    latency. The pencil's eigenvalues of the first crossings stray beyond 1e-6 from the
    unit circle, so it misses them, and K_max came out 0, "unstable at K = 0". The
    closed-loop eigenvalues (closed_loop_stable) prove the loop stable at K = 0 and
    up to K_max, and unstable just above it."""
    plant = _plants()[5]
    st = WallSettings(1e-4, 0.0, 0)
    (got,) = wall_stability([plant], st)
    assert closed_loop_stable(plant, st, 0.0)
    assert not got.unstable_at_zero
    assert 1000.0 < got.k_max_N_per_m < 1300.0
    assert closed_loop_stable(plant, st, got.k_max_N_per_m * (1 - 1e-3))
    assert not closed_loop_stable(plant, st, got.k_max_N_per_m * (1 + 1e-3))
    (g,) = _loops([plant], st)
    assert _by_pencil(g)[0][0][0] > 100 * got.k_max_N_per_m     # what the pencil saw


def test_a_loop_stable_at_zero_whose_pencil_misses_a_crossing_gets_k_max_by_bisection(
        monkeypatch):
    """With the pencil alone (the route of a doubted loop), the same loop: stable at
    K = 0 but unstable below the first crossing the pencil found, so a crossing was
    missed; K_max is bisected to 0.1 % instead of reported as 0."""
    plant = _plants()[5]
    st = WallSettings(1e-4, 0.0, 0)
    (want,) = wall_stability([plant], st)
    import armfit.loop as loop
    monkeypatch.setattr(loop, "PHASE_ROUTE_MIN_STATES", 10**9)
    (got,) = wall_stability([plant], st)
    assert not got.unstable_at_zero
    assert want.k_max_N_per_m * (1 - 1e-3) <= got.k_max_N_per_m <= want.k_max_N_per_m
    assert closed_loop_stable(plant, st, got.k_max_N_per_m)
    np.testing.assert_allclose(got.f_unstable_hz, want.f_unstable_hz, rtol=0.01)
