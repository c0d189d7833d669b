"""A model against the measurements, overall and per band (``armfit compare``), and the
JSON documents of the comparison and of the diagnosis."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from armfit import noise
from armfit.constants import AXES, PARAM_NAMES, axis_band
from armfit.diagnosis.bands import (
    BandError,
    FailingBand,
    band_error,
    failing_bands,
    residuals,
    trial_statistics,
)
from armfit.diagnosis.fit import start_array
from armfit.diagnosis.joint import joint_fit
from armfit.diagnosis.responses import axis_data, comparison_notes, param_row, select_rows
from armfit.diagnosis.results import AxisDiagnosis
from armfit.diagnosis.tuning import BANDS
from armfit.errors import UsageError
from armfit.fitting import fit_response
from armfit.io.schema import finite_or_none
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import Effect
from armfit.models.params import fit_band, model_from_params
from armfit.spectra import Spectra

__all__ = ["Comparison", "band_to_dict", "compare_models", "comparison_notes",
           "diagnosis_to_dict", "model_label"]


@dataclass(frozen=True)
class Comparison:
    """Errors of one model against one set of measurements.

    level: "mean" | "median" | "trial"; model: "base" or "base+<effect>[+…]"; overall and
    per-band errors (:data:`BANDS`); failing: significant bands with words; params: the
    effect parameters fitted (empty for the base model).
    """

    axis: str
    grip_N: float | None
    level: str
    model: str
    overall: BandError
    bands: tuple[BandError, ...]
    failing: tuple[FailingBand, ...]
    params: dict[str, float]
    n_trials: int


def _summary(axis, grip, level, label, f, r_db, r_deg, se_db, se_deg, band, params, n,
             overall_band: tuple[float, float] | None = None) -> Comparison:
    """One :class:`Comparison` from residuals (dB, deg; (n,) or (T, n)) on ``f`` and the
    noise model's standard errors: failing bands and the :data:`BANDS` rows within
    ``band``, the overall row over ``overall_band`` (default ``band``)."""
    sel = (f >= band[0]) & (f <= band[1])
    r_db2, r_deg2 = np.atleast_2d(r_db)[:, sel], np.atleast_2d(r_deg)[:, sel]
    z_db, z_deg = noise.normalised(r_db2, r_deg2, np.atleast_2d(se_db)[:, sel],
                                   np.atleast_2d(se_deg)[:, sel])
    t_db, t_deg = trial_statistics(z_db, z_deg)
    fails = failing_bands(f[sel], t_db, t_deg, r_db2.mean(axis=0), r_deg2.mean(axis=0),
                          size_db=z_db.mean(axis=0), size_deg=z_deg.mean(axis=0))
    overall = band_error(f, r_db, r_deg, se_db, se_deg, *(overall_band or band))
    within = (f[sel], np.asarray(r_db)[..., sel], np.asarray(r_deg)[..., sel],
              np.asarray(se_db)[..., sel], np.asarray(se_deg)[..., sel])
    bands = tuple(band_error(*within, lo, hi) for lo, hi in BANDS
                  if hi > band[0] and lo < band[1])
    return Comparison(axis, grip, level, label, overall, bands, tuple(fails), params, n)



def _fit_effects_aggregate(base_model, theta, effects, f, h, se_db, se_deg, band):
    """Nested refit of base + effects on one aggregate, warm-started at the effects'
    null point and at their starting points; never worse than the base."""
    model = base_model
    for e in effects:
        model = model.with_effect(e)
    base = {n: theta[n] for n in PARAM_NAMES}
    best = None
    starts = model.start_points(base)
    # local refits from each starting point, and one global search warm-started at the
    # null point (a strong effect can make the given arm parameters a poor start)
    for i, start in enumerate([*starts, starts[0]]):
        fit = fit_response(model, f, h, se_db=se_db, se_deg=se_deg, band=band, x0=start,
                           global_search=i == len(starts), strict=False)
        if best is None or fit.objective < best.objective:
            best = fit
    return model, best.params


def compare_models(spectra, params, *, level: str = "mean",
                   band: tuple[float, float] | Mapping[str, tuple[float, float]] | None = None,
                   effects: Sequence[Effect] = ()) -> list[Comparison]:
    """Compare the model(s) of ``params`` (a params DataFrame) with ``spectra``.

    level "mean": each axis × grip mean (the grip's row of grip fits, or the axis row of
    nominal fits); "median": each axis median (nominal fits); "trial": every trial of an
    axis, the five arm parameters refitted per trial from the model's values so that
    between-subject differences do not count as model error (significance by a t test
    across trials). ``effects``: add these effects and refit (nested, warm-started; shared
    across trials at level "trial"); both the base and the extended model are reported.
    ``band`` (Hz): one (lo, hi) for every axis or {axis: (lo, hi)}; it defaults to the
    whole grid (for an axis a mapping does not name, too); at levels "mean" and
    "median" the overall row of a params row's model is then taken over the band it was
    fitted on (:func:`fit_band`), so its ``rms_norm`` is the params file's (the same
    noise model on the same bins).
    """
    if level not in ("mean", "median", "trial"):
        raise UsageError(f"{{opt}} must be mean, median or trial, got {level!r}",
                         option="level=")
    spectra = Spectra.of(spectra)
    grip_model = "grip_N" in params.columns
    if level == "median" and grip_model:
        raise UsageError("grip fits are compared at {opt:level} mean or trial; the median "
                         "pools all grips (use nominal fits)")
    out: list[Comparison] = []
    for axis in AXES:
        if not (params["axis"] == axis).any():
            continue
        if level == "trial":
            data = axis_data(spectra, params, axis)
            if data is None:
                continue
            b = axis_band(band, axis) or (float(data.f_hz[0]), float(data.f_hz[-1]))
            sel = (data.f_hz >= b[0]) & (data.f_hz <= b[1])
            f = data.f_hz[sel]
            start = start_array(data)
            # the params' own model (its effects start at the params' values)
            base_model, theta0 = model_from_params(param_row(params, axis, None))
            shared0 = {k: v for k, v in theta0.items() if k not in PARAM_NAMES}
            fit = joint_fit(base_model, data, b, start, [shared0])
            se = data.noise_se(sel)
            out.append(_summary(axis, None, level, model_label(base_model), f, fit.r_db,
                                fit.r_deg, *se, b, dict(fit.shared), data.h.shape[0]))
            if effects:
                model = base_model
                for e in effects:
                    model = model.with_effect(e)
                # nested: the fitted shared values, the new effects at null, then at each of
                # their starting points
                null = {k: v for k, v in model.null_theta(theta0).items()
                        if k not in PARAM_NAMES}
                starts = [{**null, **fit.shared}]
                for e in effects:
                    for st in e.start_points(model.mp)[1:]:
                        starts.append({**starts[0],
                                       **{f"{e.name}.{k}": v for k, v in st.items()}})
                fe = joint_fit(model, data, b, [fit.base, start], starts)
                if fe.rss > fit.rss:
                    fe = fit
                out.append(_summary(axis, None, level, model_label(model), f, fe.r_db,
                                    fe.r_deg, *se, b, dict(fe.shared), data.h.shape[0]))
            continue
        grips = [None]
        if level == "mean":
            rows = select_rows(spectra, level="mean", kind="measured", axis=axis)
            grips = sorted(float(g) for g in rows.values_of("grip_N"))
        for grip in grips:
            rows = select_rows(spectra, level=level, kind="measured", axis=axis, grip=grip)
            if len(rows) == 0:
                continue
            f, h, se_db, se_deg = rows.row(0)
            prow = param_row(params, axis, grip)
            model, theta = model_from_params(prow)
            b = axis_band(band, axis) or (float(f[0]), float(f[-1]))
            nse = noise.standard_errors(se_db, se_deg)
            with np.errstate(all="ignore"):
                r_db, r_deg = residuals(h, model.response(f, theta))
            n = int(rows.key("n")[0])
            out.append(_summary(axis, grip, level, model_label(model), f, r_db, r_deg, *nse,
                                b, {}, n, None if axis_band(band, axis) else fit_band(prow, f)))
            if effects:
                model_e, th_e = _fit_effects_aggregate(model, theta, effects, f, h, se_db,
                                                       se_deg, b)
                with np.errstate(all="ignore"):
                    r_db, r_deg = residuals(h, model_e.response(f, th_e))
                eff_params = {k: v for k, v in th_e.items() if k not in PARAM_NAMES}
                out.append(_summary(axis, grip, level, model_label(model_e), f, r_db,
                                    r_deg, *nse, b, eff_params, n))
    return out


def model_label(model: ClosedLoopModel) -> str:
    """"base" or "base+<effect>+…"."""
    return "+".join(["base", *(e.name for e in model.effects)])


def band_to_dict(b: BandError) -> dict:
    """A :class:`BandError` as a JSON-ready dict."""
    return {"lo_hz": b.lo_hz, "hi_hz": b.hi_hz, "rms_db": b.rms_db, "rms_deg": b.rms_deg,
            "rms_norm": b.rms_norm, "bias_norm": b.bias_norm, "n_points": b.n_points}


def _missing_to_dict(m) -> dict:
    """A missing effect in the diagnosis JSON; ``by_subject`` (with its intervals, the
    parameters varying and their spread) only for an effect whose values differ between
    subjects."""
    out = {"effect": m.effect, "params": m.params, "params_lo": m.params_lo,
           "params_hi": m.params_hi, "at_bound": list(m.at_bound),
           "rms_norm_after": m.rms_norm_after}
    if m.varying:
        out.update(varying=list(m.varying), by_subject=m.by_subject,
                   by_subject_lo=m.by_subject_lo, by_subject_hi=m.by_subject_hi,
                   spread={p: {k: finite_or_none(v) for k, v in d.items()}
                           for p, d in m.spread.items()})
    return out


def _subject_test_to_dict(t) -> dict:
    """The per-subject test of one effect in the diagnosis JSON."""
    return {"effect": t.effect, "n_subjects": t.n_subjects, "varying": list(t.varying),
            "rms_norm_shared": finite_or_none(t.rms_norm_shared),
            "rms_norm_chosen": finite_or_none(t.rms_norm_chosen),
            "tried": [{"param": x.param, "delta_bic": finite_or_none(x.delta_bic),
                       "rss_reduction": finite_or_none(x.rss_reduction),
                       "practical": x.practical, "change_db": finite_or_none(x.change_db),
                       "change_deg": finite_or_none(x.change_deg), "kept": x.kept}
                      for x in t.trials]}


def diagnosis_to_dict(results: Sequence[AxisDiagnosis]) -> dict:
    """The JSON document of ``armfit diagnose`` (schema in docs/formats.md, "Diagnosis JSON")."""
    axes = {}
    for d in results:
        axes[d.axis] = {
            "missing_effect": d.missing_effect,
            "tied_with": list(d.tied_with),
            "verdict": d.verdict,
            "band_hz": list(d.band),
            "n_trials": d.n_trials,
            "base_error": band_to_dict(d.base_error),
            "failing_bands": [asdict(fb) for fb in d.failing],
            "cross_coupling_db": d.coupling,
            # a candidate the screening left out has no errors on all trials: null
            "candidates": [{
                "effect": c.effect, "params": c.params, "params_lo": c.params_lo,
                "params_hi": c.params_hi,
                "rms_db_before": c.rms_db_before, "rms_db_after": finite_or_none(c.rms_db_after),
                "rms_deg_before": c.rms_deg_before,
                "rms_deg_after": finite_or_none(c.rms_deg_after),
                "rms_norm_before": c.rms_norm_before,
                "rms_norm_after": finite_or_none(c.rms_norm_after),
                "failing_bias_before": finite_or_none(c.failing_bias_before),
                "failing_bias_after": finite_or_none(c.failing_bias_after),
                "failing_before": [band_to_dict(b) for b in c.failing_before],
                "failing_after": [band_to_dict(b) for b in c.failing_after],
                "lr": c.lr, "score": finite_or_none(c.score),
                "rss_reduction": finite_or_none(c.rss_reduction), "significant": c.significant,
            } for c in d.candidates],
            "missing_effects": [_missing_to_dict(m) for m in d.missing_effects],
            "error_steps": list(d.error_steps),
            "adequate": bool(d.adequate),
            "stop": d.stop,
            "steps": [{
                "effect": s.effect, "params": s.params, "params_lo": s.params_lo,
                "params_hi": s.params_hi, "at_bound": list(s.at_bound), "rms_db": s.rms_db,
                "rms_deg": s.rms_deg, "rms_norm": s.rms_norm,
                "delta_bic": finite_or_none(s.delta_bic),
                "change_db": finite_or_none(s.change_db),
                "change_deg": finite_or_none(s.change_deg),
            } | ({"varying": list(s.varying)} if s.varying else {}) for s in d.steps],
            "final_error": None if d.final_error is None else band_to_dict(d.final_error),
            "final_bands": [band_to_dict(b) for b in d.final_bands],
            "final_failing_bands": [asdict(fb) for fb in d.final_failing]}
        if d.failed_candidates:     # (only when one failed: other documents are unchanged)
            axes[d.axis]["failed_candidates"] = [
                {"effect": c.effect, "reason": c.reason} for c in d.failed_candidates]
        if d.excluded_trials:       # (only when points were left out of the evidence)
            axes[d.axis]["excluded"] = {"trials": d.excluded_trials,
                                        "bands_hz": [list(b) for b in d.excluded_hz],
                                        "flag": "not_excitation"}
        if d.subject_tests:         # (only when an effect was tested per subject)
            axes[d.axis]["subject_tests"] = [_subject_test_to_dict(t)
                                             for t in d.subject_tests]
    shared = next((d.shared for d in results if d.shared), {})
    return {"axes": axes, "shared_effects": shared}
