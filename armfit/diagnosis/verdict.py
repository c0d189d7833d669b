"""The verdict of one axis in words."""

from __future__ import annotations

from collections.abc import Sequence

from armfit.diagnosis.bands import BandError, FailingBand
from armfit.diagnosis.evidence import Adequacy
from armfit.diagnosis.results import MissingEffect

__all__ = ["subject_words", "verdict_text"]


def _where(bands: Sequence[BandError], failing: Sequence[FailingBand]) -> str:
    parts = [f"{fb.lo_hz:.3g}–{fb.hi_hz:.3g} Hz ({fb.description})" for fb in failing]
    covered = [(fb.lo_hz, fb.hi_hz) for fb in failing]
    for b in bands:
        if not any(lo <= b.hi_hz and hi >= b.lo_hz for lo, hi in covered):
            parts.append(f"{b.lo_hz:g}–{b.hi_hz:g} Hz ({b.rms_norm:.1f}× noise, "
                         f"{b.rms_db:.2f} dB / {b.rms_deg:.1f} deg RMS)")
    return "; ".join(parts)


def subject_words(m: MissingEffect) -> str:
    """How an effect's values differ between subjects, in words ('' when shared):
    "delay differs between subjects: delay_s 0.00412–0.00981 (9 subjects)"."""
    if not m.varying:
        return ""
    parts = [f"{p} {m.spread[p]['min']:.3g}–{m.spread[p]['max']:.3g}" for p in m.varying]
    return (f"{m.effect} differs between subjects: {', '.join(parts)} "
            f"({len(m.by_subject)} subjects)")


def verdict_text(base: Adequacy, final: Adequacy, missing: Sequence[MissingEffect],
                 errors: Sequence[float], stop: str) -> str:
    """The verdict of one axis in words (see :func:`diagnose_axes`)."""
    def eff_words(m: MissingEffect) -> str:
        values = ", ".join(f"{k}={v:.4g}" for k, v in m.params.items())
        return m.effect + (f" (population {values}, one value per subject)" if m.varying
                           else f" ({values})")
    bounded = [m for m in missing if m.at_bound]
    if final.adequate and not missing:
        return (f"adequate: nothing missing — the 5-parameter model fits within the noise "
                f"in every band (error {errors[0]:.2f}× noise)")
    chain = " → ".join(f"{e:.3g}" for e in errors)
    differ = "; ".join(w for w in (subject_words(m) for m in missing) if w)
    if final.adequate and not bounded and differ:
        return (f"{differ}; adequate with one value per subject after adding "
                f"{', '.join(eff_words(m) for m in missing)}: error/noise {chain}, within "
                "the noise in every band")
    if final.adequate and not bounded:
        return (f"adequate after adding {', '.join(eff_words(m) for m in missing)}: "
                f"error/noise {chain}, within the noise in every band")
    text = ("still inadequate" if not final.adequate else "within the noise, but")
    if missing:
        text += f" after adding {', '.join(eff_words(m) for m in missing)} (error/noise {chain})"
    else:
        text += (f": error {errors[0]:.2f}× noise and no library effect improves it "
                 "significantly")
    if differ:
        text += f"; {differ}"
    if not final.adequate:
        where = _where(final.over, final.failing)
        text += f"; misfit remains in {where}" if where else ""
    for m in bounded:
        text += (f"; {m.effect} has {', '.join(m.at_bound)} at a physical bound, so it is "
                 f"only the library's nearest approximation, not the answer")
    if not final.adequate or bounded:
        text += ("; the missing physics may lie outside the effect library (write it as "
                 "an effect file and rerun with --effects FILE)")
        if stop == "max-steps":
            text += (f"; the search stopped at its limit of {len(missing)} effect(s) "
                     "(armfit diagnose --max-steps)")
    return text
