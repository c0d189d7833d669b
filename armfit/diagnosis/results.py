"""The diagnosis's results: a step of the stepwise search, an effect it added, a candidate's
evidence and the verdict of one axis."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from armfit.diagnosis.bands import BandError, FailingBand

__all__ = ["AxisDiagnosis", "Candidate", "FailedCandidate", "MissingEffect", "Step",
           "short_by_subject", "short_params"]


@dataclass(frozen=True)
class Candidate:
    """One candidate effect's evidence."""

    effect: str
    params: dict[str, float]
    params_lo: dict[str, float]
    params_hi: dict[str, float]
    rms_db_before: float
    rms_db_after: float
    rms_deg_before: float
    rms_deg_after: float
    rms_norm_before: float
    rms_norm_after: float
    failing_before: tuple[BandError, ...]
    failing_after: tuple[BandError, ...]
    failing_bias_before: float
    failing_bias_after: float
    lr: float
    score: float
    significant: bool
    rss_reduction: float = 0.0


@dataclass(frozen=True)
class FailedCandidate:
    """A candidate effect left out of the search because its own code broke the fit:
    its term raised, or was NaN or infinite on the band. ``reason``: the one-line
    message, naming the file that defines the effect."""

    effect: str
    reason: str


@dataclass(frozen=True)
class AxisDiagnosis:
    """Verdict for one axis: the missing effect (or None), candidates best first, and
    the candidates left out because their code failed (``failed_candidates``);
    ``excluded_trials`` trials had points left out of the evidence (flagged
    ``not_excitation``: the estimator, not the model, is off there), within the bands
    ``excluded_hz`` (Hz; the union over the trials)."""

    axis: str
    band: tuple[float, float]
    n_trials: int
    missing_effect: str | None
    tied_with: tuple[str, ...]
    candidates: tuple[Candidate, ...]
    failing: tuple[FailingBand, ...]
    base_error: BandError
    verdict: str
    coupling: dict[str, float] = field(default_factory=dict)
    missing_effects: tuple = ()
    error_steps: tuple[float, ...] = ()
    adequate: bool = False
    steps: tuple = ()
    final_error: BandError | None = None
    final_bands: tuple[BandError, ...] = ()
    final_failing: tuple[FailingBand, ...] = ()
    stop: str = ""
    shared: dict = field(default_factory=dict)
    failed_candidates: tuple[FailedCandidate, ...] = ()
    subject_tests: tuple = ()
    excluded_trials: int = 0
    excluded_hz: tuple[tuple[float, float], ...] = ()


@dataclass(frozen=True)
class Step:
    """One row of the stepwise search: the effect added (None for the base model), its
    parameters as fitted at this step (with 95 % intervals; ``at_bound``: those within
    1 % of a physical bound), the errors of the model after the step (RMS dB, deg and
    normalised), ΔBIC against the previous step and the change the effect makes
    (largest over the band, dB and deg). ``varying``: the effect's parameters with one
    value per subject (their ``params`` then the population value; the errors those of
    the per-subject form)."""

    effect: str | None
    params: dict[str, float]
    params_lo: dict[str, float]
    params_hi: dict[str, float]
    at_bound: tuple[str, ...]
    rms_db: float
    rms_deg: float
    rms_norm: float
    delta_bic: float
    change_db: float = float("nan")
    change_deg: float = float("nan")
    varying: tuple[str, ...] = ()


@dataclass(frozen=True)
class MissingEffect:
    """An effect the stepwise search added: its parameters in the final joint fit with
    95 % intervals, those at a bound, and the error/noise after the step that added it.

    An effect whose values differ between subjects (:mod:`armfit.diagnosis.subjects`):
    ``varying`` its parameters with one value per subject, ``by_subject`` {subject:
    {param: value}} with 95 % intervals (``by_subject_lo``, ``by_subject_hi``), ``spread``
    {param: {min, max, sd}} over the subjects; its ``params`` are then the population
    values (the subjects' mean, log-mean for a log parameter, with the 95 % interval of
    that mean)."""

    effect: str
    params: dict[str, float]
    params_lo: dict[str, float]
    params_hi: dict[str, float]
    at_bound: tuple[str, ...]
    rms_norm_after: float
    varying: tuple[str, ...] = ()
    by_subject: dict[str, dict[str, float]] = field(default_factory=dict)
    by_subject_lo: dict[str, dict[str, float]] = field(default_factory=dict)
    by_subject_hi: dict[str, dict[str, float]] = field(default_factory=dict)
    spread: dict[str, dict[str, float]] = field(default_factory=dict)


def short_params(d: Mapping[str, float], effect: str) -> dict[str, float]:
    pre = effect + "."
    return {k[len(pre):]: float(v) for k, v in d.items() if k.startswith(pre)}


def short_by_subject(d: Mapping[str, Mapping[str, float]], effect: str
                     ) -> dict[str, dict[str, float]]:
    """{subject: {param: value}} of ``effect``'s per-subject parameters (its own names),
    subjects without one left out."""
    out = {s: short_params(v, effect) for s, v in d.items()}
    return {s: v for s, v in out.items() if v}
