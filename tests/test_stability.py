"""Stability of the sampled virtual wall (armfit.loop) against analytic results and an
independent computation."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from scipy import signal

from armfit.data import paper_table
from armfit.errors import UsageError
from armfit.loop import (
    RationalPlant,
    WallSettings,
    closed_loop_stable,
    pade_delay,
    plant_from_model,
    robust_certificate,
    stability_table,
    wall_stability,
)
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import get_effect
from armfit.models.params import paper_params
from armfit.uncertainty import read_weights_and_bands

NAMES = ("Ma", "k1", "k2", "b1", "b2")


def _table2_models():
    out = {}
    for _, r in paper_params("nominal").iterrows():
        model = ClosedLoopModel.for_axis(r["axis"])
        out[r["axis"]] = (model, {n: float(r[n]) for n in NAMES})
    return out


TABLE2 = _table2_models()
TABLE1_Z = [(ClosedLoopModel.for_axis("z", mp=float(r["mp_kg"])),
             {n: float(r[n]) for n in ("Ma", "k1", "k2", "b1", "b2")})
            for _, r in paper_params("grip").iterrows() if r["axis"] == "z"]


def _independent_k_max(num, den, T, B, d, k_top=1e7):
    """K_max by another route: scipy.signal.cont2discrete (ZOH) to a z-domain transfer
    function, the characteristic polynomial den_z(z) z^(d+1) + num_z(z) ((K + B/T) z - B/T)
    built with numpy polynomials, its roots on a log scan of K (60 points per decade from
    10 N/m), then bisection of the first unstable scan step to 1e-6 relative."""
    numd, dend, _ = signal.cont2discrete((num, den), T, method="zoh")
    numd = np.trim_zeros(np.atleast_1d(np.squeeze(numd)), "f")
    dend = np.atleast_1d(np.squeeze(dend))
    base = np.polymul(dend, np.r_[1.0, np.zeros(d + 1)])

    def stable(K):
        ch = np.polyadd(base, np.polymul(numd, [K + B / T, -B / T]))
        return np.max(np.abs(np.roots(ch))) < 1.0

    ks = np.geomspace(10.0, k_top, 60 * 6)
    lo = 0.0
    for k in ks:
        if not stable(k):
            hi = k
            break
        lo = k
    else:
        return math.inf
    while hi - lo > 1e-6 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stable(mid) else (lo, mid)
    return lo


# ---------------------------------------------------------------------------
# Analytic anchors
# ---------------------------------------------------------------------------

def test_mass_damper_d0_meets_colgate_bound_and_exact_jury_limit():
    """P = 1/(m s² + b s), T = 1 ms, B = 0, d = 0. Jury's test on the second-order
    characteristic polynomial z² − (1 + γ − Kα/b) z + γ + Kβ/b (ZOH, γ = e^(−bT/m),
    α = T − (1−γ)m/b, β = (1−γ)m/b − Tγ) gives exactly K_max = b(1 − γ)/β, which tends
    to Colgate & Schenkel's 2b/T as bT/m → 0 (≈ (2b/T)(1 + bT/6m))."""
    T, b = 1e-3, 5.514
    for m, tol_colgate in ((1.0, 0.01), (0.09, 0.02)):
        res = wall_stability([RationalPlant(np.array([1.0]), np.array([m, b, 0.0]))],
                             WallSettings(T, 0.0, 0))[0]
        g = math.exp(-b * T / m)
        beta = (1 - g) * m / b - T * g
        assert res.k_max_N_per_m == pytest.approx(b * (1 - g) / beta, rel=1e-3)
        assert res.k_max_N_per_m == pytest.approx(2 * b / T, rel=tol_colgate)
        assert not res.unstable_at_zero


def test_table2_anchors():
    """Table II, T = 1 ms, B = 0. d = 0: X ≈ 2 b1/T = 11.03 kN/m (Colgate & Schenkel; the
    arm's high-frequency damping is b1 — the arm mass moves little above the crossover —
    the mass-damper correction (1 + b1 T/6Mp) is 1 %); d = 1: about a third, X 3.6,
    Y 3.9, Z 27 kN/m as quoted to 2 significant figures (tolerance: half a unit of the
    last quoted digit)."""
    plants = {a: plant_from_model(*TABLE2[a]) for a in "xyz"}
    d0 = wall_stability([plants["x"]], WallSettings(1e-3, 0.0, 0))[0]
    assert d0.k_max_N_per_m == pytest.approx(2 * 5.514 / 1e-3, rel=0.01)
    d1 = wall_stability([plants[a] for a in "xyz"], WallSettings(1e-3, 0.0, 1))
    for r, quoted, half in zip(d1, (3600, 3900, 27000), (50, 50, 500), strict=True):
        assert abs(r.k_max_N_per_m - quoted) <= half
        assert 0 < r.f_unstable_hz < 500


@pytest.mark.parametrize("settings", [WallSettings(1e-3, 0.0, 1), WallSettings(5e-4, 5.0, 0),
                                      WallSettings(1e-3, 2.0, 2)])
def test_agrees_with_independent_computation(settings):
    """Every row of Tables I and II within 1 % of :func:`_independent_k_max`."""
    rows = list(paper_params("grip").iterrows()) + list(paper_params("nominal").iterrows())
    plants, indep = [], []
    for _, r in rows:
        model = ClosedLoopModel.for_axis(r["axis"])
        theta = {n: float(r[n]) for n in NAMES}
        p = plant_from_model(model, theta)
        plants.append(p)
        indep.append(_independent_k_max(p.num, p.den, settings.sample_time_s,
                                        settings.damping_Ns_per_m, settings.delay_samples))
    got = [r.k_max_N_per_m for r in wall_stability(plants, settings)]
    np.testing.assert_allclose(got, indep, rtol=0.01)


def test_a_loops_answer_does_not_depend_on_the_loops_analysed_with_it(monkeypatch):
    """wall_stability analyses at most WALL_BATCH loops together (the memory of a study's
    thousands of trial fits): with batches of 5, the 12 rows of Tables I and II and
    the same rows with output delays of 0 to 2 ms (loops of other shapes, so batches mix
    shapes) give each loop the K_max and frequency it gets analysed alone, to the bit;
    the rows without delay agree with :func:`_independent_k_max` within 1 %."""
    from armfit import loop
    rows = list(paper_params("grip").iterrows()) + list(paper_params("nominal").iterrows())
    plants = [plant_from_model(ClosedLoopModel.for_axis(r["axis"]),
                               {n: float(r[n]) for n in NAMES}) for _, r in rows]
    plants += [plant_from_model(ClosedLoopModel.for_axis(r["axis"], [get_effect("delay")]),
                                {**{n: float(r[n]) for n in NAMES},
                                 "delay.delay_s": 1e-3 * (i % 3)})
               for i, (_, r) in enumerate(rows)]
    st = WallSettings(1e-3, 2.0, 1)
    alone = [wall_stability([p], st)[0] for p in plants]
    monkeypatch.setattr(loop, "WALL_BATCH", 5)
    together = wall_stability(plants, st)
    assert [(r.k_max_N_per_m, r.f_unstable_hz) for r in together] == \
        [(r.k_max_N_per_m, r.f_unstable_hz) for r in alone]
    indep = [_independent_k_max(p.num, p.den, st.sample_time_s, st.damping_Ns_per_m,
                                st.delay_samples) for p in plants[:len(rows)]]
    assert len(rows) == 12
    np.testing.assert_allclose([r.k_max_N_per_m for r in together[:len(rows)]], indep,
                               rtol=0.01)


def test_k_max_is_the_first_loss_and_refined_to_a_tenth_of_a_percent():
    """Stable at 0.999 K_max, unstable at 1.001 K_max (closed-loop eigenvalues)."""
    p = plant_from_model(*TABLE2["y"])
    st = WallSettings(1e-3, 1.0, 1)
    k = wall_stability([p], st)[0].k_max_N_per_m
    assert closed_loop_stable(p, st, 0.999 * k)
    assert not closed_loop_stable(p, st, 1.001 * k)
    for frac in np.linspace(0.01, 0.99, 25):
        assert closed_loop_stable(p, st, frac * k)


def test_narrow_unstable_window_is_not_stepped_over():
    """Table II's X plant times a lightly damped pole/zero pair (poles at 30 Hz, zeros
    0.5 % higher, ζ = 0.02): its Nyquist curve makes a small loop across the negative
    real axis, so at T = 1 ms, d = 0 the loop is unstable only for K in a narrow window
    (about 3.1–3.9 kN/m, found by closed-loop eigenvalues on a fine scan) and stable
    again up to about 11 kN/m. A scan stepping from inside the first stable range to
    past the window would report ~11 kN/m; K_max must be the window's start."""
    base = plant_from_model(*TABLE2["x"])
    zeta, wp = 0.02, 2 * np.pi * 30
    wz = 1.005 * wp
    p = RationalPlant(np.polymul(base.num, np.array([1, 2 * zeta * wz, wz * wz]) * (wp / wz) ** 2),
                      np.polymul(base.den, [1, 2 * zeta * wp, wp * wp]))
    st = WallSettings(1e-3, 0.0, 0)
    k = wall_stability([p], st)[0].k_max_N_per_m
    assert 3000 < k < 3200
    assert closed_loop_stable(p, st, 0.999 * k)
    assert not closed_loop_stable(p, st, 1.001 * k)
    assert not closed_loop_stable(p, st, 3500.0)
    assert closed_loop_stable(p, st, 5000.0)           # stable again past the window
    assert all(closed_loop_stable(p, st, f * k) for f in np.linspace(0.02, 0.98, 40))


def test_effects_rational_forms_match_the_model_response():
    """The rational plant equals ClosedLoopModel.response with each library effect (the
    reflex through its Padé approximant: exact magnitude, phase within 1° where
    ωτ ≤ 7.7)."""
    f = np.geomspace(0.1, 60, 50)
    base = TABLE2["x"][1]
    cases = {"lowpass": {"cutoff_hz": 40.0}, "device-damping": {"damping_Ns_per_m": 2.0},
             "device-mass": {"mass_kg": 0.12},
             "resonance": {"freq_hz": 45.0, "zeta": 0.1, "weight": 0.3},
             "delay": {"delay_s": 0.0123}}
    for name, v in cases.items():
        model = ClosedLoopModel.for_axis("x", [get_effect(name)])
        theta = {**base, **{f"{name}.{k}": x for k, x in v.items()}}
        p = plant_from_model(model, theta)
        np.testing.assert_allclose(p.response(f), model.response(f, theta), rtol=1e-9)
    num, den = pade_delay(0.04, 6)
    s = 2j * np.pi * np.geomspace(0.1, 7.7 / 0.04 / (2 * np.pi), 30)
    ph = np.angle(np.polyval(num, s) / np.polyval(den, s) / np.exp(-s * 0.04), deg=True)
    assert np.max(np.abs(ph)) < 1.0


def test_output_delay_is_exact_samples_plus_fraction():
    """An output delay of 1.5 samples: K_max between that of d = 1 and d = 2 without the
    delay, and with a whole 1.0-sample delay equal to the d = 2 result (1 + 1 samples)."""
    model = ClosedLoopModel.for_axis("x", [get_effect("delay")])
    theta = {**TABLE2["x"][1], "delay.delay_s": 1.0e-3}
    k_whole = wall_stability([plant_from_model(model, theta)], WallSettings(1e-3, 0, 1))[0]
    base = plant_from_model(*TABLE2["x"])
    k1, k2 = (wall_stability([base], WallSettings(1e-3, 0, d))[0].k_max_N_per_m
              for d in (1, 2))
    assert k_whole.k_max_N_per_m == pytest.approx(k2, rel=1e-6)
    theta["delay.delay_s"] = 1.5e-3
    k_half = wall_stability([plant_from_model(model, theta)],
                            WallSettings(1e-3, 0, 0))[0].k_max_N_per_m
    assert k2 < k_half < k1


# ---------------------------------------------------------------------------
# Bad settings and unstable rows
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("kw,text", [({"sample_time_s": 0.0}, "sample_time_s"),
                                     ({"sample_time_s": -1e-3}, "sample_time_s"),
                                     ({"delay_samples": -1}, "delay_samples"),
                                     ({"delay_samples": 1.5}, "delay_samples"),
                                     ({"damping_Ns_per_m": -0.1}, "damping")])
def test_bad_settings_refused(kw, text):
    with pytest.raises(UsageError, match=text):
        WallSettings(**kw)


def test_row_unstable_at_zero_reported_with_zero_and_named():
    """B = 500 N·s/m at 1 kHz with one sample of delay: the virtual damper alone
    destabilises the device mass (B T ≫ Mp), so every row has K_max = 0 and a warning."""
    table = paper_params("nominal")
    table.insert(0, "row", [1, 2, 3])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = stability_table(table, WallSettings(1e-3, 500.0, 1), source="t.csv")
    assert (out["k_max_N_per_m"] == 0).all() and out["unstable_at_zero"].all()
    texts = [str(w.message) for w in caught]
    assert any("t.csv: row 2 (axis y)" in t and "unstable" in t for t in texts)


# ---------------------------------------------------------------------------
# Robust certificate
# ---------------------------------------------------------------------------

def test_table3_certificate_fails_at_k0_on_every_axis():
    """Table III around Table II: at K = 0, T = Mp s² H_CL (the device's share of the
    impedance). Inside the fitted band max |Wu T| is 1.11 (X) and 1.15 (Y) (the values
    of the paper's weights over 0.01–30 Hz); up to the Nyquist frequency (500 Hz at
    T = 1 ms), where the sampled loop can go unstable, Table III's weights keep rising
    and Z's peak (0.77 in its band) passes 1 too, so no K is certified on any axis."""
    weights, bands, _ = read_weights_and_bands("paper")
    st = WallSettings()
    in_band = {"x": 1.11, "y": 1.15, "z": 0.77}
    for axis in "xyz":
        model, theta = TABLE2[axis]
        kmax = wall_stability([plant_from_model(model, theta)], st)[0].k_max_N_per_m
        band = robust_certificate(model, theta, weights[axis], st, band_hz=bands[axis],
                                  k_max_N_per_m=kmax, f_max_hz=bands[axis][1])
        assert band.peak_k0 == pytest.approx(in_band[axis], abs=0.01)
        full = robust_certificate(model, theta, weights[axis], st, band_hz=bands[axis],
                                  k_max_N_per_m=kmax)
        assert full.f_max_hz == pytest.approx(500.0)
        assert full.peak_k0 >= band.peak_k0 and full.peak_k0 > 1.0
        assert not full.holds and np.isnan(full.k_robust_N_per_m)


def _scaled(weight, factor):
    from armfit.uncertainty import WuWeight
    return WuWeight(weight.gain * factor, weight.zeros, weight.poles)


def test_certificate_k_robust_is_where_the_peak_reaches_one():
    """For Z with Table III's weight scaled to 0.3×: the peak of |Wu T| evaluated
    directly (T = Z_env/(Z_ARM + Z_env)) on a finer grid from the band's low edge to the
    Nyquist frequency is < 1 just below K_robust and ≥ 1 just above it (brute force,
    independent of the certificate's quadratic solution)."""
    from armfit.loop import environment_terms
    weights, bands, _ = read_weights_and_bands("paper")
    st = WallSettings()
    model, theta = TABLE2["z"]
    w_z = _scaled(weights["z"], 0.3)
    kmax = wall_stability([plant_from_model(model, theta)], st)[0].k_max_N_per_m
    cert = robust_certificate(model, theta, w_z, st, band_hz=bands["z"],
                              k_max_N_per_m=kmax)
    assert cert.holds and 0 < cert.k_robust_N_per_m < kmax
    f = np.geomspace(bands["z"][0], 500.0, 40000)
    z, a, c = environment_terms(f, model, theta, st)
    w = np.abs(w_z.response(f))

    def peak(K):
        return np.max(w * np.abs(a + K * c) / np.abs(z + a + K * c))
    k = cert.k_robust_N_per_m
    assert peak(0.99 * k) < 1.0 < peak(1.02 * k)


def test_certificate_is_never_looser_than_a_member_of_its_set():
    """Invariant: the certified K never exceeds the K_max of a model in the covered set.
    Members: Table I's Z rows and Table II's Z with its damping halved (K_max 13.1 kN/m
    from the exact sampled loop, below the 26.6 kN/m the 0.01× weight alone admits).
    Evaluated up to the band's top (no frequency above it), the certificate is capped at
    that member and names it; evaluated up to the Nyquist frequency, the members depart
    from the nominal above the band by far more than the 0.01× weight (beyond_margin
    > 1), the assumption fails and the certificate is withheld: it claims no K at all."""
    from armfit.loop import WITHHELD
    weights, bands, _ = read_weights_and_bands("paper")
    st = WallSettings()
    model, theta = TABLE2["z"]

    def kmax_of(m, th):
        return wall_stability([plant_from_model(m, th)], st)[0].k_max_N_per_m
    soft = dict(theta, b1=theta["b1"] * 0.5, b2=theta["b2"] * 0.5)
    members = [(f"grip row {i + 1}", m, th, kmax_of(m, th))
               for i, (m, th) in enumerate(TABLE1_Z)]
    members.append(("half damping", model, soft, kmax_of(model, soft)))
    weight = _scaled(weights["z"], 0.01)
    alone = robust_certificate(model, theta, weight, st, band_hz=bands["z"],
                               k_max_N_per_m=kmax_of(model, theta))
    lowest = min(mm[3] for mm in members)
    assert lowest == pytest.approx(13100, rel=0.01)
    assert lowest < alone.k_robust_N_per_m
    in_band = robust_certificate(model, theta, weight, st, band_hz=bands["z"],
                                 k_max_N_per_m=kmax_of(model, theta), members=members,
                                 f_max_hz=bands["z"][1])
    assert in_band.k_robust_N_per_m == lowest
    assert (in_band.limited_by, in_band.limiting_member) == ("member", "half damping")
    cert = robust_certificate(model, theta, weight, st, band_hz=bands["z"],
                              k_max_N_per_m=kmax_of(model, theta), members=members)
    assert cert.beyond_margin > 1 and cert.limited_by == WITHHELD
    assert not cert.holds and cert.member_k_max_N_per_m == lowest


def test_paper_tables_by_name_match_the_shipped_csv():
    t = paper_table("nominal")
    p = paper_params("nominal")
    np.testing.assert_allclose(p["b1"], t["b1_Ns_per_m"])
    assert list(p["mp_kg"]) == [0.09, 0.095, 0.091]


def test_expm_batch_matches_scipy():
    """The batched scaling-and-squaring exponential against scipy.linalg.expm (Al-Mohy &
    Higham's Padé method) on random matrices of entries up to ~3 (the loops' are < 1)."""
    from scipy import linalg

    from armfit.loop import expm_batch
    rng = np.random.default_rng(0)
    M = rng.standard_normal((12, 6, 6)) * np.geomspace(0.01, 3, 12)[:, None, None]
    got = expm_batch(M)
    for i in range(12):
        ref = linalg.expm(M[i])
        assert np.max(np.abs(got[i] - ref)) <= 1e-12 * np.max(np.abs(ref))


def test_reflex_at_null_gain_gives_the_base_k_max():
    """The reflex (through its Padé approximant) at its null gain 0.01 N/m, τ = 40 ms,
    changes Table II's X K_max (3.62 kN/m) by less than 0.01 %: the term is 10⁻⁴ of the
    arm's smallest stiffness; a strong reflex (1000 N/m, τ = 5 ms, where the Padé
    approximant is exact to 0.1°) makes the arm itself unstable: K_max = 0."""
    model = ClosedLoopModel.for_axis("x", [get_effect("reflex")])
    base = wall_stability([plant_from_model(*TABLE2["x"])], WallSettings())[0]
    theta = {**TABLE2["x"][1], "reflex.gain_N_per_m": 0.01, "reflex.delay_s": 0.04}
    got = wall_stability([plant_from_model(model, theta)], WallSettings())[0]
    assert got.k_max_N_per_m == pytest.approx(base.k_max_N_per_m, rel=1e-4)
    theta.update({"reflex.gain_N_per_m": 1000.0, "reflex.delay_s": 0.005})
    strong = wall_stability([plant_from_model(model, theta)], WallSettings())[0]
    assert strong.unstable_at_zero and strong.k_max_N_per_m == 0.0


def test_plant_products_are_numpys_polymul_to_the_bit():
    # plant_from_model multiplies its polynomials with loop._polymul (np.polymul without
    # its poly1d objects): the same bytes as np.polymul, leading zeros (and -0.0, and all
    # zeros) included
    from armfit.loop import _polymul
    rng = np.random.default_rng(7)
    trimmed = 0
    for _ in range(2000):
        a = rng.standard_normal(rng.integers(1, 8))
        b = rng.standard_normal(rng.integers(1, 8))
        if rng.random() < 0.3:
            a[:rng.integers(0, a.size + 1)] = 0.0
        if rng.random() < 0.3:
            b[:rng.integers(0, b.size + 1)] = -0.0
        trimmed += int(a[0] == 0 or b[0] == 0)
        want = np.polymul(a, b)
        got = _polymul(a, b)
        assert got.shape == want.shape and got.tobytes() == want.tobytes()
    assert trimmed > 100
    assert _polymul([0.5, 2.0], [3.0]).tolist() == np.polymul([0.5, 2.0], [3.0]).tolist()


def test_certificate_with_the_members_k_max_given_is_the_same_table():
    """The run computes the members' K_max once (stability.csv) and hands them to the
    certificate (``members_k_max``): the table must be the one the certificate makes
    computing them itself, to the bit (Table II around Table III's weights scaled to
    0.3x, so that certificates hold; Table I's fits as the members). A value given is the
    value used: a member said to reach 1 N/m caps its axis's certificate there."""
    import pandas as pd
    weights, bands, _ = read_weights_and_bands("paper")
    weights = {a: _scaled(w, 0.3) for a, w in weights.items()}
    nominal = paper_params("nominal").assign(row=[1, 2, 3])
    members = paper_params("grip").reset_index(drop=True)
    st = WallSettings()
    k_members = stability_table(members, st)["k_max_N_per_m"].to_numpy(float)
    full = stability_table(nominal, st, weights=weights, weights_band_hz=bands,
                           members=members)
    given = stability_table(nominal, st, weights=weights, weights_band_hz=bands,
                            members=members, members_k_max=k_members)
    pd.testing.assert_frame_equal(given, full, check_exact=True)
    assert (full["limited_by"] != "").all() and full["member_k_max_N_per_m"].notna().all()
    first_z = int(np.flatnonzero(members["axis"] == "z")[0])
    low = k_members.copy()
    low[first_z] = 1.0
    capped = stability_table(nominal, st, weights=weights, weights_band_hz=bands,
                             members=members, members_k_max=low).set_index("axis")
    # Z's certificate holds (17.1 kN/m, limited by the weight beyond its band); the
    # member said to reach 1 N/m now limits it
    assert full.set_index("axis").loc["z", "k_robust_N_per_m"] > 1e4
    assert capped.loc["z", "member_k_max_N_per_m"] == 1.0
    assert capped.loc["z", "k_robust_N_per_m"] == 1.0
    assert capped.loc["z", "limited_by"] == "member"
    with pytest.raises(ValueError, match="members_k_max has 2 values"):
        stability_table(nominal, st, weights=weights, members=members,
                        members_k_max=k_members[:2])
