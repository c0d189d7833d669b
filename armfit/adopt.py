"""The adopted model: what the diagnosis found becomes the model armfit delivers.

After :func:`armfit.diagnosis.diagnose_axes`, each axis's **adopted model** is the paper's
5-parameter model plus the effects the stepwise search added on that axis
(:func:`adopt`). Everything downstream — Tables I and II, the per-trial fits, the derived
arm dynamics, W_max and Wu, the comparison, K_max and the robust certificate, the figures
— is computed with it; ``armfit run`` keeps the base model's tables beside them, labelled
as such.

**Apparatus and arm.** An effect acts at a stage (:data:`armfit.models.arm.STAGE_NAMES`):

* ``output`` and ``device`` effects (a latency, a sensor lag, the device's mass, damping
  or spring, a linkage mode) belong to the **apparatus**. They are the same for every
  trial of an axis, so the adopted model **holds** them at the value of the diagnosis's
  joint fit over all trials of the axis (with its 95 % interval): the grip fits (Table
  I), the nominal fit (Table II) and every per-trial fit use that one value, and the
  tables mark it as held. The derived arm dynamics Fa = F − Mp·x″ (eq. 4) and W_max
  remove them first (:func:`armfit.uncertainty.arm_trials`), so that Wu describes how
  arms vary, not an unmodelled latency.
* ``arm`` effects (a stretch reflex) belong to the **person**: they are fitted freely in
  every fit, like the five arm parameters.

**Per subject.** An effect whose values the diagnosis found to differ between subjects
(:mod:`armfit.diagnosis.subjects`) carries them into the per-trial fits: every trial's fit
holds all of that effect's parameters at its subject's values (the per-subject ones at
the subject's, the others at the joint fit's), so the stability of each trial, and the
wall every subject renders stably, follow from them; W_max removes an apparatus effect
with each trial's own subject's values. The aggregate tables (Table I: grip means over
subjects; Table II: the axis median) hold an apparatus effect at the subjects' mean
(the population value of the diagnosis) and fit an arm effect freely, as above.

**Policy** (``auto``, the default of ``armfit run``): every effect the search added, in
order, up to the first that ended with a parameter at its bound — there the library's
effect is only the nearest approximation of what the data show, so it and the effects
after it are declined with that reason (define the effect that fits: ``--effects
FILE``). An axis still inadequate after its effects adopts them all the same (they
lowered the error) and says so: its tables carry the remaining error, and the report
names the bands that still fail. ``none`` adopts nothing: the base model throughout, as
the paper does.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from armfit.constants import AXES, GRID_HZ, PAPER_BANDS
from armfit.errors import UsageError
from armfit.models.arm import APPARATUS_STAGES
from armfit.models.effects import get_effect

if TYPE_CHECKING:   # pandas is imported where a table is made (it takes ~0.15 s)
    import pandas as pd

#: Adoption policies (``armfit run --adopt``).
POLICIES: tuple[str, ...] = ("auto", "none")

#: Columns of :meth:`Adoption.to_frame` (adoption.csv of ``armfit run``).
ADOPTION_COLUMNS: tuple[str, ...] = (
    "axis", "adopted", "effects", "held", "band_lo_hz", "band_hi_hz", "adequate",
    "rms_norm_base", "rms_norm_adopted", "declined", "reason")


@dataclass(frozen=True)
class HeldValue:
    """An apparatus parameter held in the adopted model: ``name`` (``effect.param``), its
    value and the 95 % interval of the diagnosis's joint fit (unit of the parameter)."""

    name: str
    value: float
    lo: float = math.nan
    hi: float = math.nan


@dataclass(frozen=True)
class AxisAdoption:
    """The adopted model of one axis.

    Attributes
    ----------
    axis : str
    effects : tuple of str
        The adopted effects, in the order the diagnosis added them (empty: base model).
    held : tuple of HeldValue
        The apparatus parameters held at the diagnosis's joint fit.
    band_hz : (float, float)
        Fit band of the adopted model (Hz): the band the diagnosis examined when an effect
        is adopted (the effect explains what made the paper narrow it), else the paper's.
    adequate : bool
        The diagnosis's verdict on the adopted model: within the noise in every band.
    rms_norm_base, rms_norm_adopted : float
        Error/noise of the base and of the adopted model in the diagnosis's joint fit.
    declined : tuple of (str, str)
        Effects the diagnosis added but this model leaves out, with the reason.
    verdict : str
        The diagnosis's verdict sentence.
    by_subject : dict
        {subject: {``effect.param``: value}} of the adopted effects whose values differ
        between subjects: every parameter of such an effect, held at these values in each
        subject's per-trial fits (empty when every effect is shared).
    varying : tuple of str
        The parameters (``effect.param``) with one value per subject.
    """

    axis: str
    effects: tuple[str, ...] = ()
    held: tuple[HeldValue, ...] = ()
    band_hz: tuple[float, float] = GRID_HZ
    adequate: bool = True
    rms_norm_base: float = math.nan
    rms_norm_adopted: float = math.nan
    declined: tuple[tuple[str, str], ...] = ()
    verdict: str = ""
    by_subject: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    varying: tuple[str, ...] = ()

    @property
    def adopted(self) -> bool:
        """Whether any effect was adopted."""
        return bool(self.effects)

    @property
    def apparatus(self) -> tuple[str, ...]:
        """The adopted effects of the apparatus (stage output or device)."""
        return tuple(e for e in self.effects if get_effect(e).stage in APPARATUS_STAGES)

    @property
    def arm(self) -> tuple[str, ...]:
        """The adopted effects of the arm (stage arm), fitted freely."""
        return tuple(e for e in self.effects if get_effect(e).stage not in APPARATUS_STAGES)

    def items(self) -> list:
        """The model as effect items for the fitters (:func:`armfit.models.effects.
        resolve_effects`): apparatus effects as (name, {param: held value}), arm effects
        by name."""
        out: list = []
        for name in self.effects:
            e = get_effect(name)
            if e.stage in APPARATUS_STAGES:
                values = {h.name.split(".", 1)[1]: h.value for h in self.held
                          if h.name.split(".", 1)[0] == name}
                out.append((name, values))
            else:
                out.append(name)
        return out

    @property
    def subject_effects(self) -> tuple[str, ...]:
        """The adopted effects whose values differ between subjects."""
        return tuple(dict.fromkeys(n.split(".", 1)[0] for n in self.varying))

    def items_for(self, subject: str) -> list:
        """The model of one subject's per-trial fits as effect items: :meth:`items`, with
        every parameter of an effect that differs between subjects held at the
        subject's values (:attr:`by_subject`); :meth:`items` for a subject the diagnosis
        did not see."""
        values = self.by_subject.get(str(subject))
        if not values:
            return self.items()
        per = set(self.subject_effects)
        out: list = []
        for item, name in zip(self.items(), self.effects, strict=True):
            if name in per:
                out.append((name, {k.split(".", 1)[1]: v for k, v in values.items()
                                   if k.split(".", 1)[0] == name}))
            else:
                out.append(item)
        return out

    def sentence(self) -> str:
        """What was adopted on this axis and why, in one sentence."""
        if not self.effects:
            why = ("; declined " + "; ".join(f"{e} ({r})" for e, r in self.declined)
                   if self.declined else "")
            return f"{self.axis.upper()}: base model (nothing adopted){why}"
        held = ", ".join(f"{h.name} = {h.value:.5g}" + (
            f" [{h.lo:.5g}, {h.hi:.5g}]" if math.isfinite(h.lo) and math.isfinite(h.hi)
            else "") for h in self.held if h.name not in self.varying)
        parts = [f"{self.axis.upper()}: adopted {' + '.join(self.effects)}"]
        if held:
            parts.append(f"held at the diagnosis's joint fit ({held})")
        for name in self.varying:
            vals = [v[name] for v in self.by_subject.values()]
            mean = next((h for h in self.held if h.name == name), None)
            parts.append(f"{name} one value per subject ({min(vals):.5g}–{max(vals):.5g} "
                         f"over {len(vals)} subjects), each subject's own in its per-trial "
                         "fits" + (f", the subjects' mean {mean.value:.5g} in Tables I and "
                                   "II" if mean is not None else ", fitted per row in "
                                   "Tables I and II"))
        per = self.subject_effects
        if self.arm and any(e not in per for e in self.arm):
            parts.append(f"{', '.join(e for e in self.arm if e not in per)} fitted per row "
                         "(an effect of the arm)")
        err = (f"error/noise {self.rms_norm_base:.3g} → {self.rms_norm_adopted:.3g}"
               if math.isfinite(self.rms_norm_base) else "")
        parts.append(("adequate" if self.adequate else "still inadequate")
                     + (f", {err}" if err else ""))
        if self.declined:
            parts.append("declined " + "; ".join(f"{e} ({r})" for e, r in self.declined))
        return "; ".join(parts)


@dataclass(frozen=True)
class Adoption:
    """The adopted model of every axis (:func:`adopt`).

    Attributes
    ----------
    axes : tuple of AxisAdoption
    policy : str
        ``auto`` or ``none`` (:data:`POLICIES`).
    """

    axes: tuple[AxisAdoption, ...]
    policy: str = "auto"

    def __getitem__(self, axis: str) -> AxisAdoption:
        """The adoption of ``axis`` (the base model for an axis the diagnosis lacks)."""
        return next((a for a in self.axes if a.axis == axis),
                    AxisAdoption(axis, band_hz=PAPER_BANDS[axis]))

    @property
    def adopted_axes(self) -> tuple[str, ...]:
        """The axes whose model has an effect."""
        return tuple(a.axis for a in self.axes if a.adopted)

    @property
    def anything(self) -> bool:
        """Whether any axis adopted an effect."""
        return bool(self.adopted_axes)

    @property
    def effects(self) -> dict[str, list]:
        """{axis: effect items} for the fitters' ``effects`` (axes not listed: base)."""
        return {a.axis: a.items() for a in self.axes if a.adopted}

    @property
    def bands(self) -> dict[str, tuple[float, float]]:
        """{axis: fit band (Hz)} of the adopted models, for x, y and z."""
        return {ax: tuple(self[ax].band_hz) for ax in AXES}

    @property
    def apparatus(self) -> dict[str, tuple[str, ...]]:
        """{axis: adopted apparatus effects}."""
        return {a.axis: a.apparatus for a in self.axes}

    @property
    def by_subject(self) -> dict[str, Mapping[str, Mapping[str, float]]]:
        """{axis: {subject: {``effect.param``: value}}} of the axes with an effect whose
        values differ between subjects (empty when every effect is shared)."""
        return {a.axis: a.by_subject for a in self.axes if a.by_subject}

    @property
    def subject_effects(self) -> dict[str, dict[str, list]]:
        """{axis: {subject: effect items}} of the per-trial fits of the axes with
        per-subject values (:meth:`AxisAdoption.items_for`)."""
        return {a.axis: {s: a.items_for(s) for s in a.by_subject} for a in self.axes
                if a.by_subject}

    def subjects_frame(self) -> pd.DataFrame:
        """One row per axis, subject and parameter of an effect whose values differ
        between subjects: ``axis, subject, effect, param, value, per_subject`` (False for
        a parameter of such an effect that the subjects share)."""
        import pandas as pd
        rows = [{"axis": a.axis, "subject": subj, "effect": n.split(".", 1)[0],
                 "param": n.split(".", 1)[1], "value": v, "per_subject": n in a.varying}
                for a in self.axes for subj, values in a.by_subject.items()
                for n, v in values.items()]
        return pd.DataFrame(rows, columns=["axis", "subject", "effect", "param", "value",
                                           "per_subject"])

    def to_frame(self) -> pd.DataFrame:
        """One row per axis: :data:`ADOPTION_COLUMNS` (``held``: ``name=value`` items
        separated by ';'; ``declined``: the effects left out, ';'-separated, with the
        reasons in ``reason``)."""
        import pandas as pd
        rows = [{
            "axis": a.axis, "adopted": a.adopted, "effects": ";".join(a.effects),
            "held": ";".join(f"{h.name}={h.value:.10g}" for h in a.held),
            "band_lo_hz": a.band_hz[0], "band_hi_hz": a.band_hz[1],
            "adequate": a.adequate, "rms_norm_base": a.rms_norm_base,
            "rms_norm_adopted": a.rms_norm_adopted,
            "declined": ";".join(e for e, _ in a.declined),
            "reason": "; ".join(f"{e}: {r}" for e, r in a.declined)} for a in self.axes]
        return pd.DataFrame(rows, columns=list(ADOPTION_COLUMNS))

    def to_dict(self) -> dict:
        """A JSON-ready document: policy and per axis the adopted model."""
        return {"policy": self.policy, "axes": {a.axis: {
            "effects": list(a.effects), "apparatus": list(a.apparatus), "arm": list(a.arm),
            "held": {h.name: {"value": h.value, "lo": _finite(h.lo), "hi": _finite(h.hi)}
                     for h in a.held},
            "band_hz": list(a.band_hz), "adequate": a.adequate,
            "rms_norm_base": _finite(a.rms_norm_base),
            "rms_norm_adopted": _finite(a.rms_norm_adopted),
            "declined": [{"effect": e, "reason": r} for e, r in a.declined],
            "sentence": a.sentence()} | ({"varying": list(a.varying),
                                          "by_subject": {s: dict(v) for s, v in
                                                         a.by_subject.items()}}
                                         if a.by_subject else {}) for a in self.axes}}


def _finite(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def _axis_adoption(d, policy: str) -> AxisAdoption:
    """The adoption of one :class:`armfit.diagnosis.AxisDiagnosis`."""
    axis = d.axis
    base_err = float(d.base_error.rms_norm) if d.base_error is not None else math.nan
    final = d.final_error or d.base_error
    missing = [m for m in d.missing_effects if not isinstance(m, str)]
    if policy == "none" or not missing:
        declined = tuple((m.effect, "adoption off (--adopt none)") for m in missing) \
            if policy == "none" else ()
        return AxisAdoption(axis, band_hz=tuple(PAPER_BANDS[axis]),
                            adequate=bool(d.adequate) if not missing else False,
                            rms_norm_base=base_err, rms_norm_adopted=base_err,
                            declined=declined, verdict=d.verdict)
    taken, declined = [], []
    for m in missing:
        if declined:
            declined.append((m.effect, "follows a declined effect"))
        elif m.at_bound:
            declined.append((m.effect, f"{', '.join(m.at_bound)} at the bound of the "
                                       "library's range: the effect is only its nearest "
                                       "approximation (define yours: --effects FILE)"))
        else:
            taken.append(m)
    if not taken:
        return AxisAdoption(axis, band_hz=tuple(PAPER_BANDS[axis]), adequate=False,
                            rms_norm_base=base_err, rms_norm_adopted=base_err,
                            declined=tuple(declined), verdict=d.verdict)
    held = []
    by_subject: dict[str, dict[str, float]] = {}
    varying: list[str] = []
    for m in taken:
        if get_effect(m.effect).stage in APPARATUS_STAGES:
            for p, v in m.params.items():
                # 10 significant digits: the value the params files and adoption.csv
                # write, so that a fit from those files gives the same bits
                held.append(HeldValue(f"{m.effect}.{p}", float(f"{float(v):.10g}"),
                                      float(m.params_lo.get(p, math.nan)),
                                      float(m.params_hi.get(p, math.nan))))
        for subj, values in m.by_subject.items():
            row = by_subject.setdefault(subj, {})
            for p, v in m.params.items():
                row[f"{m.effect}.{p}"] = float(f"{float(values.get(p, v)):.10g}")
        varying += [f"{m.effect}.{p}" for p in m.varying]
    err = float(taken[-1].rms_norm_after) if declined else float(final.rms_norm)
    return AxisAdoption(axis, effects=tuple(m.effect for m in taken), held=tuple(held),
                        band_hz=tuple(map(float, d.band)),
                        adequate=bool(d.adequate) and not declined,
                        rms_norm_base=base_err, rms_norm_adopted=err,
                        declined=tuple(declined), verdict=d.verdict, by_subject=by_subject,
                        varying=tuple(varying))


def adopt(diagnosis, policy: str = "auto") -> Adoption:
    """The adopted model of each axis from a diagnosis (see the module docstring).

    Parameters
    ----------
    diagnosis : armfit.api.Diagnosis or sequence of armfit.diagnosis.AxisDiagnosis
        The diagnosis of the base model.
    policy : {'auto', 'none'}
        'auto': adopt the effects the diagnosis added, up to the first with a parameter
        at its bound; 'none': the base model on every axis.

    Returns
    -------
    Adoption

    Raises
    ------
    UsageError
        An unknown policy.
    """
    if policy not in POLICIES:
        raise UsageError(f"{{opt:adopt}} {policy!r}: choose one of {', '.join(POLICIES)}")
    axes = getattr(diagnosis, "axes", diagnosis)
    if not isinstance(axes, Sequence):
        axes = tuple(axes)
    return Adoption(tuple(_axis_adoption(d, policy) for d in axes), policy)


__all__ = ["ADOPTION_COLUMNS", "APPARATUS_STAGES", "Adoption", "AxisAdoption", "HeldValue",
           "POLICIES", "adopt"]
