"""The adopted model: what the diagnosis finds becomes every product of ``armfit run``.

A study simulated with a latency of a whole number of samples (9 ms at 1 kHz) on every
axis and no subject variability, so that every trial's arm is the row of the paper's
Table I for its axis and grip (the simulator's known truth): 2 subjects × 3 axes × 3
grips, 26 s trials (the shortest that reach 0.1 Hz), seed 5. Run once per module.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from scipy import signal

from armfit.adopt import adopt
from armfit.cli.main import cli
from armfit.loop import WallSettings, stability_table
from armfit.models.arm import ClosedLoopModel
from armfit.models.params import paper_params, read_param_rows

TRUE_DELAY_S = 0.009
NAMES = ("Ma", "k1", "k2", "b1", "b2")


@pytest.fixture(scope="module")
def delayed(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("adopt")
    r = CliRunner()
    res = r.invoke(cli, ["-q", "simulate", "-o", str(root / "study"), "--subjects", "2",
                         "--duration", "26,26", "--seed", "5", "--variability", "0",
                         "--effect", f"delay={TRUE_DELAY_S}"])
    assert res.exit_code == 0, res.output
    res = r.invoke(cli, ["run", str(root / "study"), "-o", str(root / "out"), "--jobs", "2",
                         "--no-figures", "--json"])
    assert res.exit_code == 0, res.output
    return root / "out"


def _truth_rows() -> pd.DataFrame:
    """Table I of the paper: with --variability 0 every trial's arm (simulator's truth)."""
    return paper_params("grip")


def test_tables_carry_the_delay_and_the_true_arm(delayed):
    """Table I and II of the run carry the delay (held, within 0.3 ms of the simulated
    9 ms) and Table I's arm parameters are within 5 % of the paper's Table I, the
    simulator's truth."""
    grip = pd.read_csv(delayed / "grip_params.csv", keep_default_na=False)
    nominal = pd.read_csv(delayed / "nominal_params.csv", keep_default_na=False)
    for table in (grip, nominal):
        assert (table["effects"] == "delay").all()
        assert (table["held"] == "delay.delay_s").all()
        assert np.allclose(table["delay.delay_s"].astype(float), TRUE_DELAY_S, atol=3e-4)
    truth = _truth_rows()
    for _, row in grip.iterrows():
        t = truth[(truth["axis"] == row["axis"])
                  & np.isclose(truth["grip_N"], float(row["grip_N"]))].iloc[0]
        for n in NAMES:
            assert float(row[n]) == pytest.approx(float(t[n]), rel=0.05), \
                (row["axis"], row["grip_N"], n)
    # the base tables stay, without the effect; on x and y (0.1–30 Hz, where 9 ms is up
    # to 97 deg of phase) their fit is far from the noise (z's paper band ends at 10 Hz)
    base = pd.read_csv(delayed / "nominal_params_base.csv", keep_default_na=False)
    assert set(base["effects"]) == {""}
    xy = base["axis"].isin(["x", "y"]).to_numpy()
    assert (base["rms_norm"][xy] > 5 * nominal["rms_norm"][xy]).all()


def test_trial_rows_carry_the_delay(delayed):
    trials = pd.read_csv(delayed / "trial_params.csv", keep_default_na=False)
    ok = trials["converged"].astype(str) == "True"
    carry = ok & (trials["effects"] == "delay")
    assert carry.mean() >= 0.9
    assert np.allclose(trials.loc[carry, "delay.delay_s"].astype(float), TRUE_DELAY_S,
                       atol=3e-4)


def test_wmax_is_well_below_0_db_on_x_and_y(delayed):
    """With the latency removed from the derived arm dynamics, only the grip-to-grip
    spread and noise remain: W_max (dB) well below 0 over 0.3–30 Hz on x and y (below
    0.3 Hz a 26 s trial holds fewer than 8 cycles and the drift is of the same order),
    median below −15 dB. Without the adoption the 9 ms latency alone is |e^(−jωτ) − 1|
    = 2 sin(πfτ): −5 dB at 10 Hz, +3 dB at 30 Hz."""
    w = pd.read_csv(delayed / "wu_wmax.csv")
    for axis in "xy":
        g = w[(w["axis"] == axis) & (w["freq_hz"] >= 0.3)]
        assert g["wmax_db"].max() < -6.0, axis
        assert g["wmax_db"].median() < -15.0, axis


def _kmax_independent(axis: str, theta, delay_s: float, T: float = 1e-3, d: int = 1
                      ) -> float:
    """K_max of the wall K with d samples of computation delay on the true arm, with
    the latency inside the loop, computed independently of armfit.loop:
    P(s) = 1/(Z_ARM(s) + Mp s²) (eq. 3–4) discretised by scipy.signal.cont2discrete
    (zero-order hold), the latency m = τ/T whole samples as z^(−m), characteristic
    polynomial den(z)·z^(m+d) + K·num(z), stability by its roots, bisection to 0.1 %."""
    Ma, k1, k2, b1, b2 = (float(theta[n]) for n in NAMES)
    mp = ClosedLoopModel.for_axis(axis).mp
    z_num = np.polymul([b1, k1], [Ma, b2, k2])
    z_den = np.array([Ma, b1 + b2, k1 + k2])
    den = np.polyadd(z_num, np.polymul([mp, 0, 0], z_den))
    num_d, den_d, _ = signal.cont2discrete((z_den, den), T, method="zoh")
    num_d = np.trim_zeros(np.atleast_1d(np.squeeze(num_d)), "f")
    m = int(round(delay_s / T))
    shift = np.zeros(m + d + 1)
    shift[0] = 1.0

    def stable(K: float) -> bool:
        char = np.polyadd(np.polymul(den_d, shift), K * num_d)
        return bool(np.max(np.abs(np.roots(char))) < 1.0)
    lo, hi = 0.0, 1.0
    while stable(hi):
        lo, hi = hi, hi * 2
    while hi - lo > 1e-3 * hi:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if stable(mid) else (lo, mid)
    return lo


def test_kmax_is_that_of_the_true_arm_with_the_latency_in_the_loop(delayed):
    """The per-trial K_max minimum per axis within 10 % of the independent K_max of the
    true arms (Table I rows, every trial's truth) with the 9 ms inside the loop."""
    st = pd.read_csv(delayed / "stability.csv")
    truth = _truth_rows()
    for axis in "xyz":
        rows = truth[truth["axis"] == axis]
        expect = min(_kmax_independent(axis, r, TRUE_DELAY_S) for _, r in rows.iterrows())
        got = st.loc[st["axis"] == axis, "k_max_N_per_m"].min()
        assert got == pytest.approx(expect, rel=0.10), axis


def test_certificate_never_exceeds_the_trials(delayed):
    """Invariant: the certified K of each nominal model ≤ the smallest K_max of the
    trials Wu was built from, at the same settings."""
    cert = pd.read_csv(delayed / "certificate.csv")
    st = pd.read_csv(delayed / "stability.csv")
    for _, r in cert.iterrows():
        if np.isfinite(r["k_robust_N_per_m"]):
            assert r["k_robust_N_per_m"] <= st.loc[st["axis"] == r["axis"],
                                                   "k_max_N_per_m"].min() + 1e-9


def test_report_opens_with_the_adopted_model(delayed):
    report = (delayed / "report.md").read_text()
    head = report[:report.index("## What was done")]
    for axis in "XYZ":
        assert f"- {axis}: adopted delay; held at the diagnosis's joint fit" in head
    # K_max base vs adopted, from the nominal rows of both tables
    base = stability_table(read_param_rows(str(delayed / "nominal_params_base.csv")).table,
                           WallSettings())
    adopted = stability_table(read_param_rows(str(delayed / "nominal_params.csv")).table,
                              WallSettings())
    z_base = base.loc[base["axis"] == "z", "k_max_N_per_m"].iloc[0]
    z_adopted = adopted.loc[adopted["axis"] == "z", "k_max_N_per_m"].iloc[0]
    assert f"| Z | {z_base / 1e3:.3g} | {z_adopted / 1e3:.3g} |" in head
    assert z_adopted < 0.5 * z_base      # the latency in the loop lowers Z's wall


def test_adopted_tables_come_nominal_first_and_equal_the_separate_fits(delayed):
    """adopt_model hands Table II's fits to the executor before Table I's, all at once,
    and gives ``on_table`` Table II first: what needs only Table II (armfit run's W_max
    and Wu) starts while Table I's fits run. Each table equals the one fit_nominal and
    fit_grip make alone with the adopted effects and bands (an independent call: the
    same fits, whatever their company)."""
    from concurrent.futures import ThreadPoolExecutor

    import armfit

    class Recording(ThreadPoolExecutor):
        """A thread pool that records the group of each fit handed to it, in order."""

        def __init__(self) -> None:
            super().__init__(max_workers=2)
            self.handed: list[str] = []

        def submit(self, fn, /, *args, **kwargs):
            self.handed.append(args[0][0])     # _fit_group's task: (where, model, ...)
            return super().submit(fn, *args, **kwargs)

    sp = armfit.read_spectra(delayed / "spectra.parquet")
    diagnosis = armfit.diagnose(sp, armfit.read_model(delayed / "grip_params_base.csv"))
    seen: list[tuple[str, int]] = []
    with Recording() as ex:
        adopted = armfit.adopt_model(sp, diagnosis, trials=False, executor=ex,
                                     on_table=lambda which, m: seen.append(
                                         (which, len(ex.handed))))
    # 3 axes: Table II's 3 fits first, then Table I's 9, all handed before either table
    assert [w for w, _ in seen] == ["nominal", "grip"]
    assert all(n == 12 for _, n in seen)
    assert ex.handed[:3] == ["axis x", "axis y", "axis z"]
    assert all(", grip " in w for w in ex.handed[3:])
    ad = adopted.adoption
    assert ad.anything
    alone = {"nominal": armfit.fit_nominal(sp, bands=ad.bands, effects=ad.effects),
             "grip": armfit.fit_grip(sp, bands=ad.bands, effects=ad.effects)}
    for which in ("nominal", "grip"):
        pd.testing.assert_frame_equal(getattr(adopted, which).table, alone[which].table)


def test_fit_studies_closed_early_leaves_the_later_fits_unrun(serial_spectra):
    """fit_studies yields each table as its own fits are done; a caller that stops after
    the first (an error there, say) leaves the fits not yet started unrun: of a small
    study's 1 nominal and 2 grip fits on one thread, at most the one running when the
    first table came back also runs."""
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from armfit.fitting import fit_studies, fit_study

    ran: list[str] = []
    lock = threading.Lock()

    def counted(fn, task):
        with lock:
            ran.append(task[0])
        return fn(task)

    class Counting(ThreadPoolExecutor):
        def submit(self, fn, /, *args, **kwargs):
            return super().submit(counted, fn, *args, **kwargs)

    with Counting(max_workers=1) as ex:
        studies = fit_studies(serial_spectra, ("nominal", "grip"), executor=ex)
        first = next(studies)
        studies.close()
    assert first.which == "nominal" and first.keys == (("x", None),)
    assert ran[0] == "axis x" and len(ran) <= 2
    # the table itself is the one fit_study makes alone (the same fit)
    alone = fit_study(serial_spectra, which="nominal")
    assert first.fits[0].params == alone.fits[0].params


def test_adopt_declines_an_effect_at_its_bound():
    """An effect whose parameter ended at its bound is declined (the library's effect is
    only the nearest approximation), and the effects after it too."""
    from types import SimpleNamespace

    from armfit.diagnosis import MissingEffect
    err = SimpleNamespace(rms_norm=50.0)
    m1 = MissingEffect("delay", {"delay_s": 0.01}, {"delay_s": 0.0099}, {"delay_s": 0.0101},
                       (), 5.0)
    m2 = MissingEffect("lowpass", {"cutoff_hz": 1.0}, {"cutoff_hz": 1.0},
                       {"cutoff_hz": 1.1}, ("cutoff_hz",), 3.0)
    m3 = MissingEffect("reflex", {"gain_N_per_m": 100.0, "delay_s": 0.03}, {}, {}, (), 1.0)
    d = SimpleNamespace(axis="x", band=(0.1, 30.0), missing_effects=(m1, m2, m3),
                        base_error=err, final_error=SimpleNamespace(rms_norm=1.0),
                        adequate=True, verdict="v")
    ad = adopt([d])
    x = ad["x"]
    assert x.effects == ("delay",) and not x.adequate
    assert x.rms_norm_adopted == 5.0          # the error after the last adopted step
    assert [e for e, _ in x.declined] == ["lowpass", "reflex"]
    assert x.items() == [("delay", {"delay_s": 0.01})]
    none = adopt([d], "none")
    assert not none.anything and [e for e, _ in none["x"].declined] == [
        "delay", "lowpass", "reflex"]


SAMPLES = Path(__file__).resolve().parents[1] / "sample_data"


@pytest.fixture(scope="module", params=["study", "hidden"])
def sample_run(request, sample_runs) -> tuple[str, Path]:
    return request.param, sample_runs(request.param)


def test_sample_certificate_never_exceeds_the_trials(sample_run):
    """Invariant on both sample studies: every certified K ≤ the smallest per-trial
    K_max of its axis at the same settings (the members Wu was built from)."""
    _, out = sample_run
    cert = pd.read_csv(out / "certificate.csv")
    st = pd.read_csv(out / "stability.csv")
    for _, r in cert.iterrows():
        kmin = st.loc[st["axis"] == r["axis"], "k_max_N_per_m"].min()
        assert r["member_k_max_N_per_m"] == pytest.approx(kmin, rel=1e-9)
        if np.isfinite(r["k_robust_N_per_m"]):
            assert r["k_robust_N_per_m"] <= kmin


def test_sample_studies_adopt_what_their_diagnosis_finds(sample_run):
    """study: nothing missing, nothing adopted (said once, no *_base tables); hidden: the
    12 ms latency adopted on every axis, and its K_max come from the adopted model."""
    name, out = sample_run
    report = (out / "report.md").read_text()
    if name == "study":
        assert report.count("Nothing adopted") == 1
        assert not (out / "grip_params_base.csv").exists()
        assert set(pd.read_csv(out / "trial_params.csv", keep_default_na=False)["effects"]) \
            == {""}
        return
    trials = pd.read_csv(out / "trial_params.csv", keep_default_na=False)
    assert (trials["effects"] == "delay").all()
    st = pd.read_csv(out / "stability.csv")
    # the report's K_max is that of the adopted per-trial models
    for axis in "xyz":
        kmin = st.loc[st["axis"] == axis, "k_max_N_per_m"].min()
        assert f"renders walls up to {kmin / 1e3:.3g} kN/m on {axis.upper()}" in report
