"""The stepwise search: per axis, effects added one at a time while the model is not within
the noise, and the axes' shared effects compared."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from armfit.constants import Z_975
from armfit.diagnosis.bands import BandError, _runs, band_columns, band_error
from armfit.diagnosis.driver import (  # noqa: F401 (names of this module's API)
    _BASE,
    _EXTEND,
    _SCREEN,
    LARGE_TASK_BYTES,
    _base_task,
    _large,
    _trial_rows,
    diagnose_axes,
)
from armfit.diagnosis.evidence import (
    Adequacy,
    adequacy,
    band_errors,
    delta_bic,
    effect_size,
    practical,
    union_bias,
)
from armfit.diagnosis.fit import fit_borrowed, fit_extend
from armfit.diagnosis.joint import JointFit
from armfit.diagnosis.responses import AxisData
from armfit.diagnosis.results import (
    AxisDiagnosis,
    Candidate,
    FailedCandidate,
    MissingEffect,
    Step,
    short_by_subject,
    short_params,
)
from armfit.diagnosis.schedule import TaskQueue
from armfit.diagnosis.screen import (
    keep_screened,
    rank_screened,
    screen_candidate,
    screen_on,
    screen_trials,
)
from armfit.diagnosis.subjects import (
    SubjectTest,
    by_subject_search,
    per_subject_default,
    spread,
    subjects_allow,
)
from armfit.diagnosis.tuning import (
    MIN_REDUCTION,
    SIGNIFICANT_BIC,
    TIE_BIC,
    TIE_FRACTION,
)
from armfit.diagnosis.verdict import verdict_text
from armfit.errors import EffectDefinitionError
from armfit.feedback import chi2_sf
from armfit.memory import release_memory, release_memory_after_task
from armfit.models.arm import ClosedLoopModel, at_bound
from armfit.models.effects import EFFECTS, Effect

__all__ = ["CandidateFit", "cross_axis_agreement", "diagnose_axes"]


@dataclass(frozen=True)
class CandidateFit:
    """A candidate effect of one step, fitted on all trials, with its evidence against
    the current fit: ``score`` (ΔBIC), ``significant`` (statistically and practically),
    ``error`` (the fit's errors over the band), ``rss_reduction`` (fraction of the cost it
    removes), ``lr`` (the likelihood-ratio statistic D) and the largest change it makes
    to the response (``change_db`` dB, ``change_deg`` deg); ``subject_test``: the test of
    its per-subject form when it was made before the choice (an effect of the arm), the
    fit then being the form chosen."""

    effect: Effect
    fit: JointFit
    score: float
    significant: bool
    error: BandError
    rss_reduction: float
    lr: float
    change_db: float
    change_deg: float
    subject_test: SubjectTest | None = None

    @property
    def at_bound(self) -> bool:
        """Whether a parameter of the effect is within 1 % of a physical bound."""
        return bool(at_bound(self.effect.params, short_params(self.fit.shared,
                                                              self.effect.name)))


class _Search:
    """The state of the stepwise search on one axis (see :func:`diagnose_axes`)."""

    def __init__(self, data: AxisData, band, effects, max_steps, min_db, min_deg,
                 by_subject: bool = True):
        self.data, self.band, self.effects = data, band, list(effects)
        self.max_steps, self.min_db, self.min_deg = max_steps, min_db, min_deg
        # the band's grid points: a slice (a band of the sorted grid), so that indexing
        # gives views of the band, not copies
        self.cols = band_columns(data.f_hz, *band)[0]
        self.f = data.f_hz[self.cols]
        self.fits: list[JointFit] = []
        self.added: list[Effect] = []
        self.steps: list[Step] = []
        self.adequacies: list[Adequacy] = []
        self.first_candidates: tuple[Candidate, ...] = ()
        self.tied: tuple[str, ...] = ()
        self.failed: dict[str, str] = {}
        self.stop = ""
        self.done = False
        self.allow_subjects = by_subject and subjects_allow(data)
        self.subject_tests: list[SubjectTest] = []
        #: the apparatus effect just added, whose per-subject form is still to be tested,
        #: the step's other candidates fitted on all trials, and the test's outcome
        self.untested: Effect | None = None
        self.rivals: list[CandidateFit] = []
        self.winner: tuple | None = None

    def noise(self) -> tuple[np.ndarray, np.ndarray]:
        """The noise model's standard errors (dB, deg) of every trial on the band, (T, n),
        from :meth:`AxisData.noise_se`: an axis of more than
        :data:`~armfit.diagnosis.responses.NOISE_KEPT_BYTES` of them has them made when
        needed, not held for the search's length (on 1,350 trials of 100 frequencies,
        2.2 MB an axis besides the data's own), and gets views of the band, not copies of
        it (every statistic is taken of arrays computed from them); a smaller axis's are
        kept by its data, and each call gets copies of the band."""
        return self.data.noise_se(self.cols)

    def n_params(self, fit: JointFit) -> int:
        return fit.n_free

    def by_subject_now(self, effect: Effect) -> bool:
        """Whether a candidate's per-subject form is tested before the step's choice."""
        return self.allow_subjects and per_subject_default(effect)

    def start(self, base: JointFit) -> None:
        ad = self._adequacy(base)
        self.fits.append(base)
        self.adequacies.append(ad)
        self.steps.append(Step(None, {}, {}, {}, (), ad.overall.rms_db, ad.overall.rms_deg,
                               ad.overall.rms_norm, float("nan")))
        self._check_stop()

    def _check_stop(self) -> None:
        if self.adequacies[-1].adequate:
            self.done, self.stop = True, "adequate"
        elif len(self.added) >= self.max_steps:
            self.done, self.stop = True, "max-steps"
        elif not self.remaining():
            self.done, self.stop = True, "no-more-effects"

    def remaining(self) -> list[Effect]:
        # no effect twice: a second delay, lag or mass adds nothing a single one's
        # parameters cannot, and two copies of a resonance or reflex are not identifiable
        # from these responses (their order is arbitrary)
        names = {e.name for e in self.added} | set(self.failed)
        return [e for e in self.effects if e.name not in names]

    def fail(self, failure: FailedCandidate) -> None:
        """Leave a candidate out of this and every later step: its own code failed."""
        self.failed.setdefault(failure.effect, failure.reason)

    def screen_candidate(self) -> list[tuple[Effect, JointFit]]:
        """Screening fits (:func:`screen_candidate`) of the remaining effects, lowest cost first."""
        return rank_screened([(e, screen_candidate(self.data, self.band, self.fits[-1], e))
                      for e in self.remaining()])

    def evaluate(self, eff: Effect, fit: JointFit, cur: JointFit,
                 test: SubjectTest | None = None) -> CandidateFit:
        """The evidence for ``fit`` (``cur``'s model plus ``eff``) against ``cur``."""
        se_db, se_deg = self.noise()
        score, lr, reduction = delta_bic(cur, fit, se_db, se_deg)
        err = band_error(self.f, fit.r_db, fit.r_deg, se_db, se_deg, *self.band)
        size_db, size_deg = effect_size(fit, eff, self.f)
        prac, _ = practical(self.f, size_db, size_deg, se_db, se_deg,
                            self.min_db, self.min_deg)
        stat = bool(score > SIGNIFICANT_BIC and reduction >= MIN_REDUCTION)
        return CandidateFit(eff, fit, score, stat and prac, err, reduction, lr,
                            float(np.nanmax(size_db, initial=0.0)),
                            float(np.nanmax(size_deg, initial=0.0)), test)

    def take(self, fits: Sequence[tuple], screened: Sequence[tuple[Effect, JointFit]] = ()
             ) -> None:
        """Evaluate this step's candidate fits on all trials, each ``(effect, fit)`` or,
        tested per subject already, ``(effect, fit, test)``; add the best significant one
        or stop. ``screened``: candidates left at their screening fit (reported among
        the candidates of the first step, never added). An apparatus effect added
        shared is left :attr:`untested`: its per-subject test comes next
        (:meth:`tested`)."""
        cur = self.fits[-1]
        cands = [self.evaluate(eff, fit, cur, test[0] if test else None)
                 for eff, fit, *test in fits]
        cands.sort(key=lambda c: c.score, reverse=True)
        if not self.added:
            self.first_candidates = tuple(self._candidate(c) for c in cands) + tuple(
                self._screened_candidate(e, sc) for e, sc in screened)
        # an effect with a parameter at a physical bound is only the library's nearest
        # approximation: take it only when no significant candidate is free of bounds
        best = self._best(cands)
        if not self.added and best is not None:
            self.tied = tuple(c.effect.name for c in cands
                              if c.significant and c.effect is not best.effect
                              and best.score - c.score < max(TIE_BIC,
                                                             TIE_FRACTION * best.score))
        if best is None:   # (every candidate left may have failed: none remains)
            self.done = True
            self.stop = "nothing-significant" if self.remaining() else "no-more-effects"
            return
        self._append(best.effect, best.fit, self._adequacy(best.fit), best.score,
                     best.change_db, best.change_deg)
        if best.subject_test is not None:
            self.subject_tests.append(best.subject_test)
        elif self.allow_subjects:
            self.untested = best.effect     # an apparatus effect: test it per subject now
            self.rivals = [c for c in cands if c is not best and c.subject_test is None]
            return
        self._check_stop()

    @staticmethod
    def _best(cands: Sequence[CandidateFit]) -> CandidateFit | None:
        """The best significant candidate by ΔBIC, one free of physical bounds first."""
        ranked = sorted(cands, key=lambda c: c.score, reverse=True)
        free = [c for c in ranked if c.significant and not c.at_bound]
        return free[0] if free else next((c for c in ranked if c.significant), None)

    def tested(self, result: tuple[JointFit, SubjectTest] | None) -> list[CandidateFit]:
        """The per-subject test of the apparatus effect just added (:attr:`untested`;
        ``result`` None when its code failed in a per-subject fit: it stays shared).
        When the data demand one value per subject, the step's other candidates fitted
        on all trials (:attr:`rivals`) are returned to be tested per subject too — the
        step then compares every candidate in the form its data chose
        (:meth:`settle`); otherwise the step is settled and [] returned."""
        eff, self.untested = self.untested, None
        if result is None:
            self._check_stop()
            return []
        fit, test = result
        self.winner = (eff, fit, test)
        if test.by_subject and self.rivals:
            return list(self.rivals)
        self.settle([], [])
        return []

    def settle(self, rivals: Sequence[CandidateFit],
               results: Sequence[tuple[JointFit, SubjectTest] | None]) -> None:
        """End the step: among the effect added and the ``rivals``, each in the form its
        own test chose (``results``: one value per subject where the data demanded it,
        else shared), the best significant one against the fit before the step is the
        step's effect; the first step's ties are judged among the same forms."""
        eff, fit, test = self.winner
        prev = self.fits[-2]
        options = [self.evaluate(eff, fit, prev, test)]
        for c, r in zip(rivals, results, strict=True):
            if r is not None and r[1].by_subject:
                options.append(self.evaluate(c.effect, r[0], prev, r[1]))
            else:           # shared is its data's form (or its per-subject fit failed)
                options.append(replace(c, subject_test=r[1] if r is not None else None))
        best = self._best(options) or options[0]
        if best.subject_test is not None:
            self.subject_tests.append(best.subject_test)
        if len(self.added) == 1 and rivals:     # the first step's ties, in these forms
            self.tied = tuple(c.effect.name for c in options
                              if c.significant and c.effect is not best.effect
                              and best.score - c.score < max(TIE_BIC,
                                                             TIE_FRACTION * best.score))
        if best.effect is not eff or (best.subject_test is not None
                                      and best.subject_test.by_subject):
            self.added.pop()
            self.fits.pop()
            self.adequacies.pop()
            self.steps.pop()
            self._append(best.effect, best.fit, self._adequacy(best.fit), best.score,
                         best.change_db, best.change_deg)
        self._check_stop()

    def _adequacy(self, fit: JointFit) -> Adequacy:
        return adequacy(self.f, fit, *self.noise(), self.band, self.n_params(fit),
                        self.min_db, self.min_deg)

    def _append(self, eff: Effect, fit: JointFit, ad: Adequacy, score: float,
                change_db: float = float("nan"), change_deg: float = float("nan")) -> None:
        """Record a step: ``eff`` added, the joint fit with it and its adequacy."""
        err = ad.overall
        p = short_params(fit.shared, eff.name)
        self.added.append(eff)
        self.fits.append(fit)
        self.adequacies.append(ad)
        varying = tuple(short_params({n: 0.0 for n in fit.varying}, eff.name))
        self.steps.append(Step(eff.name, p, short_params(fit.shared_lo, eff.name),
                               short_params(fit.shared_hi, eff.name),
                               tuple(at_bound(eff.params, p)), err.rms_db, err.rms_deg,
                               err.rms_norm, float(score), change_db, change_deg, varying))

    def _candidate(self, c: CandidateFit) -> Candidate:
        eff, fit, err = c.effect, c.fit, c.error
        base = self.fits[0]
        fail_ranges = [(fb.lo_hz, fb.hi_hz) for fb in self.adequacies[0].failing]
        be = self.adequacies[0].overall
        se_db, se_deg = self.noise()
        return Candidate(
            effect=eff.name, params=short_params(fit.shared, eff.name),
            params_lo=short_params(fit.shared_lo, eff.name),
            params_hi=short_params(fit.shared_hi, eff.name),
            rms_db_before=be.rms_db, rms_db_after=err.rms_db,
            rms_deg_before=be.rms_deg, rms_deg_after=err.rms_deg,
            rms_norm_before=be.rms_norm, rms_norm_after=err.rms_norm,
            failing_before=band_errors(self.f, base, se_db, se_deg, fail_ranges),
            failing_after=band_errors(self.f, fit, se_db, se_deg, fail_ranges),
            failing_bias_before=union_bias(self.f, base, se_db, se_deg, fail_ranges),
            failing_bias_after=union_bias(self.f, fit, se_db, se_deg, fail_ranges),
            lr=float(c.lr), score=float(c.score), rss_reduction=float(c.rss_reduction),
            significant=bool(c.significant))

    def borrow_model(self, agreement: Mapping[str, dict]) -> ClosedLoopModel | None:
        """The model to refit from the axes' common values, or None: for an axis that is
        not adequate, or that lacks a shared effect named on other axes."""
        have = {e.name for e in self.added}
        lack = [n for n in agreement if n not in have and n in EFFECTS
                and len(self.added) < self.max_steps]
        if self.adequacies[-1].adequate and not lack:
            return None
        if not agreement or (not lack and not any(n in have for n in agreement)):
            return None
        model = self.fits[-1].model
        for n in lack:
            if len(model.effects) < self.max_steps:
                model = model.with_effect(EFFECTS[n])
        return model

    def borrow(self, fit: JointFit) -> None:
        """Take the refit from the common values when it helps: same effects and a lower
        cost (the last step's errors improve), or new effects that are significant in both
        senses (each becomes a step)."""
        cur = self.fits[-1]
        new = [e for e in fit.model.effects if e.name not in {a.name for a in self.added}]
        if fit.rss >= cur.rss:
            return
        if new:
            se_db, se_deg = self.noise()
            score, _, reduction = delta_bic(cur, fit, se_db, se_deg,
                                            k=sum(len(e.params) for e in new))
            prac = all(practical(self.f, *effect_size(fit, e, self.f), se_db, se_deg,
                                 self.min_db, self.min_deg)[0] for e in new)
            if not (score > SIGNIFICANT_BIC and reduction >= MIN_REDUCTION and prac):
                return
        ad = self._adequacy(fit)
        err = ad.overall
        if new:
            for e in new:
                self._append(e, fit, ad, score)
        else:
            last = self.steps[-1]
            p = short_params(fit.shared, last.effect) if last.effect else {}
            self.steps[-1] = replace(last, params=p or last.params,
                                     params_lo=short_params(fit.shared_lo, last.effect or ""),
                                     params_hi=short_params(fit.shared_hi, last.effect or ""),
                                     rms_db=err.rms_db, rms_deg=err.rms_deg,
                                     rms_norm=err.rms_norm)
            self.fits[-1] = fit
            self.adequacies[-1] = ad
        self.stop = "adequate" if ad.adequate else self.stop

    def _screened_candidate(self, eff: Effect, fit: JointFit) -> Candidate:
        """A candidate that the screening ranked below the joint fits: its subset fit's
        parameters, not significant (its error fields are NaN: not fitted on all)."""
        nan = float("nan")
        be = self.adequacies[0].overall
        return Candidate(eff.name, short_params(fit.shared, eff.name), {}, {}, be.rms_db, nan,
                         be.rms_deg, nan, be.rms_norm, nan, (), (), nan, nan, 0.0, nan,
                         False, nan)

    def result(self) -> AxisDiagnosis:
        final = self.fits[-1]
        ad = self.adequacies[-1]
        missing = []
        for i, eff in enumerate(self.added):
            p = short_params(final.shared, eff.name)
            varying = tuple(short_params({n: 0.0 for n in final.varying}, eff.name))
            by_subj = short_by_subject(final.by_subject, eff.name) if varying else {}
            missing.append(MissingEffect(
                eff.name, p, short_params(final.shared_lo, eff.name),
                short_params(final.shared_hi, eff.name), tuple(at_bound(eff.params, p)),
                self.steps[i + 1].rms_norm, varying, by_subj,
                short_by_subject(final.by_subject_lo, eff.name) if varying else {},
                short_by_subject(final.by_subject_hi, eff.name) if varying else {},
                spread(by_subj, varying) if varying else {}))
        errors = [s.rms_norm for s in self.steps]
        for i in range(1, len(errors)):      # nested fits: never rises (guard rounding)
            errors[i] = min(errors[i], errors[i - 1])
        ex = self.data.excluded
        n_ex, ex_hz = 0, ()
        if ex is not None and ex[:, self.cols].any():
            n_ex = int(ex[:, self.cols].any(axis=1).sum())
            ex_hz = tuple((float(self.f[a]), float(self.f[b - 1]))
                          for a, b in _runs(ex[:, self.cols].any(axis=0), 1))
        verdict = verdict_text(self.adequacies[0], ad, missing, errors, self.stop)
        if n_ex:
            verdict += (f"; {n_ex} of {self.data.h.shape[0]} trial(s) left out of the "
                        "evidence at " + ", ".join(f"{lo:.3g}–{hi:.3g} Hz" for lo, hi in ex_hz)
                        + ", where the force is not a clean excitation and H1 is biased "
                        "(flagged not_excitation): the estimator, not the model, misses there")
        return AxisDiagnosis(
            axis=self.data.axis, band=(float(self.f[0]), float(self.f[-1])),
            n_trials=int(self.data.h.shape[0]),
            missing_effect=missing[0].effect if missing else None, tied_with=self.tied,
            candidates=self.first_candidates, failing=self.adequacies[0].failing,
            base_error=self.adequacies[0].overall,
            verdict=verdict,
            missing_effects=tuple(missing), error_steps=tuple(errors),
            adequate=bool(ad.adequate), steps=tuple(self.steps),
            final_error=ad.overall, final_bands=ad.bands, final_failing=ad.failing,
            stop=self.stop, failed_candidates=tuple(FailedCandidate(n, r)
                                                    for n, r in self.failed.items()),
            subject_tests=tuple(self.subject_tests), excluded_trials=n_ex,
            excluded_hz=ex_hz)


# Each task gives back the memory its fit freed once it has ended
# (:func:`armfit.memory.release_memory_after_task`: in a worker, after its result is sent
# and its arguments, an axis's trials, are let go): a worker runs fit after fit over all
# of an axis's trials, and would otherwise keep the pages of every one.

def _screen_task(args):
    data, current, quick, band, effect, by_subject = args   # screen_trials' trials
    try:
        return screen_on(data, current, quick, band, effect, by_subject)
    except EffectDefinitionError as exc:     # the effect's own code broke the fit
        return FailedCandidate(effect.name, str(exc))
    finally:
        release_memory_after_task()


def _extend_task(args):
    """The candidate's joint fit on all trials; with ``subjects`` (min_db, min_deg) its
    per-subject test too, giving (fit of the form chosen, test)."""
    data, band, current, effect, screened, *subjects = args
    try:
        fit = fit_extend(data, band, current, effect, screened)
        if subjects:
            return by_subject_search(data, band, fit, effect, *subjects[0])
        return fit
    except EffectDefinitionError as exc:     # the effect's own code broke the fit
        return FailedCandidate(effect.name, str(exc))
    finally:
        release_memory_after_task()


def _subject_task(args):
    """The per-subject test of an effect just added: (fit of the form chosen, test)."""
    data, band, fit, effect, min_db, min_deg = args
    try:
        return by_subject_search(data, band, fit, effect, min_db, min_deg)
    except EffectDefinitionError:    # the effect's own code broke a fit: keep it shared
        return None
    finally:
        release_memory_after_task()


def _gather(n: int, then: Callable[[list], None]) -> list[Callable]:
    """``n`` continuations, the i-th storing result i; once all have been called,
    ``then(results)`` (at once when ``n`` is 0)."""
    out: list = [None] * n
    left = [n]

    def part(i: int, result) -> None:
        out[i] = result
        left[0] -= 1
        if not left[0]:
            then(out)

    if not n:
        then(out)
    return [lambda r, i=i: part(i, r) for i in range(n)]


class _Turns:
    """The turn of each step's screening among the steps waiting: the order the steps
    began in (an axis's base fit done first screens first), except that the last
    ``workers`` axes to begin their first step share one turn (:meth:`share_last`),
    their candidates taken alternately. An axis's joint fit on all trials and its
    per-subject test can start only once its screening is done and run alone then: the
    last axis, screened alone, ended the diagnosis on one worker while the others idled
    (about 50 ms of 0.65 s on ``sample_data/hidden``); screened together, the last
    axes reach those fits at about the same time and run them side by side. Every task's
    result depends only on its arguments: the turns change when a fit runs, not what it
    gives."""

    def __init__(self):
        self._count = itertools.count()
        self._shared_from: int | None = None

    def share_last(self, n_axes: int, workers: int) -> None:
        """The last ``workers`` of the ``n_axes`` axes share one turn."""
        self._shared_from = max(0, n_axes - workers)

    def __iter__(self) -> _Turns:
        return self

    def __next__(self) -> int:
        turn = next(self._count)
        return turn if self._shared_from is None else min(turn, self._shared_from)


class _AxisSteps:
    """One axis's search on the task queue, from its base fit's result (:meth:`_based`;
    the fit itself is handed over by :func:`armfit.diagnosis.driver.diagnose_axes`):
    step after step cheap screening of every remaining effect (one task each) and joint
    fits of the best (one task each), each step as soon as the axis's previous one has
    ended: the axes do not wait for each other."""

    def __init__(self, search: _Search, tasks: TaskQueue, steps: Iterator[int]):
        self.s, self.tasks, self.steps = search, tasks, steps
        self.large = _large(search.data)

    def _judging(self) -> None:
        """Before the evidence of this axis's fits is made: the memory freed since the
        last results were handed on goes back to the system (an axis of large data
        only). The results just received leave freed blocks too small for the evidence's
        arrays; given back, the evidence reuses their pages instead of growing the
        process (on 4,050 trials the main process's top during the evidence of the last
        axis's base fit fell from 175-180 MB to 168-170 MB)."""
        if self.large:
            release_memory()

    def _based(self, base: JointFit) -> None:
        self._judging()
        self.s.start(base)
        self._step()

    def _step(self) -> None:
        s = self.s
        if s.done:
            return
        effects = s.remaining()
        turn = next(self.steps)
        parts = _gather(len(effects), lambda sfits: self._screened(effects, sfits))
        # the trials every candidate is screened on, made once: a task carries only them
        trials = screen_trials(s.data, s.band, s.fits[-1])
        # the candidates of most parameters (the longest fits) first; axes sharing a
        # turn take theirs alternately
        rank = {i: r for r, i in enumerate(sorted(range(len(effects)),
                                                  key=lambda i: -len(effects[i].params)))}
        for i, (e, then) in enumerate(zip(effects, parts, strict=True)):
            self.tasks.add((_SCREEN, turn, rank[i]), _screen_task,
                           (*trials, s.band, e, s.by_subject_now(e)), then,
                           large=_large(trials[0]))

    def _screened(self, effects: Sequence[Effect], sfits: Sequence) -> None:
        s = self.s
        for sc in sfits:
            if isinstance(sc, FailedCandidate):
                s.fail(sc)
        screened = rank_screened([(e, sc) for e, sc in zip(effects, sfits, strict=True)
                                  if not isinstance(sc, FailedCandidate)])
        kept = keep_screened(screened)
        parts = _gather(len(kept), lambda fits: self._take(screened, kept, fits))
        for (e, sc), then in zip(kept, parts, strict=True):
            extra = ((s.min_db, s.min_deg),) if s.by_subject_now(e) else ()
            self.tasks.add((_EXTEND,), _extend_task,
                           (s.data, s.band, s.fits[-1], e, sc, *extra), then,
                           large=self.large)

    def _take(self, screened, kept, fits) -> None:
        self._judging()
        s = self.s
        for fit in fits:
            if isinstance(fit, FailedCandidate):
                s.fail(fit)
        full = {e.name: (fit if isinstance(fit, tuple) else (fit,))
                for (e, _), fit in zip(kept, fits, strict=True)
                if not isinstance(fit, FailedCandidate)}
        s.take([(e, *full[e.name]) for e, _ in screened if e.name in full],
               screened=[(e, sc) for e, sc in screened
                         if e.name not in full and e.name not in s.failed])
        if s.untested is not None:
            self.tasks.add((_EXTEND,), _subject_task,
                           (s.data, s.band, s.fits[-1], s.untested, s.min_db, s.min_deg),
                           self._tested, large=self.large)
            return
        self._step()

    def _tested(self, result) -> None:
        self._judging()
        s = self.s
        rivals = s.tested(result)
        if not rivals:
            self._step()
            return
        parts = _gather(len(rivals), lambda results: self._settled(rivals, results))
        for c, then in zip(rivals, parts, strict=True):
            self.tasks.add((_EXTEND,), _subject_task,
                           (s.data, s.band, c.fit, c.effect, s.min_db, s.min_deg), then,
                           large=self.large)

    def _settled(self, rivals, results) -> None:
        self._judging()
        self.s.settle(rivals, results)
        self._step()


def _borrow_step(searches: Sequence[_Search], run: Callable, share: Sequence[str]) -> None:
    """An axis whose search ended inadequate, or without a shared effect the other axes
    name, tries the axes' common values as a start (one joint fit each)."""
    agreement = cross_axis_agreement([s.result() for s in searches], share)
    tasks = [(s, s.borrow_model(agreement)) for s in searches]
    tasks = [(s, m) for s, m in tasks if m is not None]
    if tasks:
        fits = list(run(_borrow_task, [(s.data, s.band, s.fits[-1], m, agreement)
                                       for s, m in tasks]))
        for (s, _), fit in zip(tasks, fits, strict=True):
            if fit is not None:
                s.borrow(fit)


def _borrow_task(args):
    data, band, current, model, agreement = args
    try:
        return fit_borrowed(data, band, current, model, agreement)
    except EffectDefinitionError:   # an effect's own code broke the refit: keep the search's
        return None
    finally:
        release_memory_after_task()


def cross_axis_agreement(results: Sequence[AxisDiagnosis], share: Sequence[str]
                         ) -> dict[str, dict]:
    """For each effect of ``share`` named on two or more axes: the precision-weighted
    common value of each parameter (weights from the 95 % intervals, in the fitter's
    search coordinate: log for log parameters), the χ² of the axes' values about it
    (degrees of freedom: axes − 1) and whether the axes disagree (p < 0.01). The common
    value is the one-step joint estimate: where each axis's cost is quadratic in the
    parameter, the joint minimum of the summed costs is this weighted mean."""
    out: dict[str, dict] = {}
    for name in share:
        named = [(d.axis, m) for d in results for m in d.missing_effects if m.effect == name]
        if len(named) < 2:
            continue
        try:
            eff = EFFECTS[name]
        except KeyError:
            continue
        entry: dict = {"axes": [a for a, _ in named], "params": {}, "disagree": False}
        for p in eff.params:
            vals, ws = [], []
            for _, m in named:
                v, lo, hi = (m.params.get(p.name), m.params_lo.get(p.name),
                             m.params_hi.get(p.name))
                if v is None or lo is None or hi is None:
                    continue
                tr = (lambda x: np.log(max(x, 1e-300))) if p.log else (lambda x: x)
                half = (tr(hi) - tr(lo)) / 2.0
                if not (np.isfinite(half) and half > 0):
                    continue
                sd = half / Z_975
                vals.append(tr(v))
                ws.append(1.0 / sd ** 2)
            if len(vals) < 2:
                continue
            vals, ws = np.array(vals), np.array(ws)
            common = float(np.sum(ws * vals) / np.sum(ws))
            chi2 = float(np.sum(ws * (vals - common) ** 2))
            pval = chi2_sf(chi2, len(vals) - 1)
            value = float(np.exp(common)) if p.log else common
            # practically different: the values spread by more than 10 % of the value
            # (log parameters) or than 10 % of the common value (linear ones)
            spread = float(np.max(vals) - np.min(vals))
            big = spread > (np.log(1.1) if p.log else 0.1 * abs(common))
            entry["params"][p.name] = {"common": value, "chi2": chi2,
                                       "dof": len(vals) - 1, "p": pval}
            entry["disagree"] = bool(entry["disagree"] or (pval < 0.01 and big))
        if entry["params"]:
            out[name] = entry
    return out
