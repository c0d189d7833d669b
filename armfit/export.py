"""Fitted models out of armfit: transfer functions for python-control, MATLAB and Octave.

A params row (Tables I and II, or the adopted model of ``armfit run``) is the closed loop
of eq. 4 of Fu & Çavuşoğlu 2010 with the effects the row lists. Every effect declares
its term as num/den·e^(−sτ) (eq. R1 of :mod:`armfit.models.effects`), so the model is

    X/F   = Π R_out(s) · e^(−s·T_out) / (Z_ARM + ΔZ_arm + Mp s² + ΔZ_dev)      (eq. 4)
    H_ARM = 1 / (Z_ARM + ΔZ_arm)                                             (eq. 3)

with Z_ARM = C1 (Ma s² + C2) / (Ma s² + C1 + C2), C1 = k1 + b1 s, C2 = k2 + b2 s
(:mod:`armfit.models.arm`), R_out the rational parts of the output factors (a low-pass,
a resonance), T_out the sum of their delays (a latency) and ΔZ the impedances of the arm
and device effects (a device's mass or damping, a reflex). :func:`rational_model` turns
that into polynomial coefficients in s (rad/s): every rational part exactly, the output
delay T_out kept apart (a transfer function's input–output delay, MATLAB's ``IODelay``),
and a delay inside an impedance (the reflex's) replaced by its [n/n] Padé approximant,
as the stability analysis does (:data:`armfit.loop.INTERNAL_DELAY_PADE_ORDER`): a
transfer function with an input–output delay cannot hold a delayed feedback.

:func:`export_variables` gathers the coefficients of every row of a params file, the
uncertainty weights Wu (eq. 7) as zeros, poles and gain, and the measured responses, as
named numpy arrays that :func:`write_export` writes (:func:`mat_bytes`: MATLAB's format
5, ``scipy.io.savemat``; :func:`json_text`); ``armfit export`` is the command. None of this needs
python-control; :meth:`armfit.api.ModelFit.to_control` builds its objects from the same
coefficients.

The Padé approximant of a latency. The [n/n] approximant P_n(s) = D_n(−sT)/D_n(sT) of
e^(−sT) is all-pass: |P_n(jω)| = 1 exactly, so only its phase is approximate. Its phase
error e_n(ωT) = ωT − 2 arg D_n(jωT) (rad) starts as c_n (ωT)^(2n+1),
c_n = (n!)² / ((2n)! (2n+1)!), the first term of its series; computed on
0 < ωT ≤ 2n + 4 for n = 1 … 10, it grows monotonically and stays below that first term
(:func:`pade_phase_bound_deg`). For the default n = 6 (c_6 = 1.74e-13) the error is below
2e-5° for ωT ≤ 3 (a 12 ms latency up to 40 Hz), below 1e-3° for ωT ≤ 4.2, below 0.1° for
ωT ≤ 6.2 and below 1° for ωT ≤ 7.7; for n = 1 it exceeds 1° from ωT = 0.61.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from armfit._version import __version__
from armfit.constants import AXES, PARAM_NAMES
from armfit.errors import UsageError
from armfit.io.atomic import atomic_path
from armfit.loop import INTERNAL_DELAY_PADE_ORDER, pade_delay, rational_sum
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import EFFECTS, Effect
from armfit.models.params import model_from_params
from armfit.spectra import Spectra
from armfit.uncertainty import WuWeight, arm_trials, derived_mass_kg, derived_trials

#: Default order n of the [n/n] Padé approximant that stands for a latency in a
#: python-control transfer function (and for a delay inside an impedance everywhere).
PADE_ORDER = INTERNAL_DELAY_PADE_ORDER

#: What a model's transfer function describes: the measured closed loop X/F of eq. 4
#: (device and arm, what the spectra measure) or the arm's own H_ARM (eq. 3).
KINDS: tuple[str, ...] = ("closed_loop", "arm")

#: Formats ``armfit export`` writes.
EXPORT_FORMATS: tuple[str, ...] = ("mat", "json")


@dataclass(frozen=True)
class RationalModel:
    """A model as num(s)/den(s) · e^(−s·delay_s): coefficients in powers of s (rad/s),
    highest first, den monic; the response in m/N.

    ``delay_s`` (s) is exact (the output delays, summed); ``inner_delays_s`` are the
    delays inside an impedance that num/den holds as [n/n] Padé approximants,
    n = ``pade_order`` (empty when there is none: num/den is then exact).
    """

    num: np.ndarray
    den: np.ndarray
    delay_s: float = 0.0
    inner_delays_s: tuple[float, ...] = ()
    pade_order: int = PADE_ORDER

    def response(self, omega_rad_s) -> np.ndarray:
        """num(jω)/den(jω) · e^(−jω·delay_s) at ``omega_rad_s`` (rad/s), m/N."""
        s = 1j * np.asarray(omega_rad_s, dtype=float)
        return np.polyval(self.num, s) / np.polyval(self.den, s) * np.exp(-s * self.delay_s)


def _term(e: Effect, values: Mapping[str, float], mp: float, what: str, hint: str
          ) -> tuple[np.ndarray, np.ndarray, float]:
    """(num, den, delay_s) of one effect's term (eq. R1); UsageError naming the effect,
    where it came from, the model (``what``) and ``hint`` when it declares none."""
    if e.rational is None:
        origin = EFFECTS.describe_origin(e.name) if EFFECTS.origin_of(e) is not None \
            else "no registered source"
        raise UsageError(f"{what}: effect {e.name!r} (from {origin}) declares no rational "
                         f"form num/den*exp(-s*tau), so the model is no transfer function; "
                         f"{hint}")
    return e.rational_form(values, mp)


def rational_model(model: ClosedLoopModel, theta, *, kind: str = "closed_loop",
                   pade_order: int = PADE_ORDER, what: str = "model",
                   hint: str = "add rational=... to its Effect "
                               "(docs/methods.md#your-own-effects)") -> RationalModel:
    """The closed loop X/F (eq. 4) or the arm's H_ARM (eq. 3) of a model as polynomials.

    Parameters
    ----------
    model : ClosedLoopModel
        The model of one params row (:func:`armfit.models.params.model_from_params`).
    theta : mapping or sequence
        Its parameter values (:meth:`ClosedLoopModel.values`).
    kind : {'closed_loop', 'arm'}
        'closed_loop': X/F with every effect, what :meth:`ClosedLoopModel.response`
        evaluates; 'arm': H_ARM with the arm-stage effects, as
        :meth:`ClosedLoopModel.arm_response`.
    pade_order : int
        Order n of the [n/n] Padé approximant of a delay inside an impedance.
    what, hint : str
        How a message names the model, and what it suggests, when an effect declares
        no rational form.

    Returns
    -------
    RationalModel
        Exact for every rational part (to rounding); the output delays summed into
        ``delay_s`` (none for 'arm').

    Raises
    ------
    UsageError
        An unknown ``kind``, a ``pade_order`` below 1, or an effect without a rational
        form (named, with where it came from).
    """
    if kind not in KINDS:
        raise UsageError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if isinstance(pade_order, bool) or not isinstance(pade_order, (int, np.integer)) \
            or pade_order < 1:
        raise UsageError(f"pade_order must be a whole number >= 1, got {pade_order!r}")
    values = {n: float(v) for n, v in model.values(theta).items()}
    Ma, k1, k2, b1, b2 = (values[n] for n in PARAM_NAMES)
    z = (np.polymul([b1, k1], [Ma, b2, k2]), np.array([Ma, b1 + b2, k1 + k2]))   # Z_ARM
    if kind == "closed_loop":
        z = rational_sum(z, (np.array([model.mp, 0.0, 0.0]), np.array([1.0])))          # + Mp s²
    out = (np.array([1.0]), np.array([1.0]))
    delay, inner = 0.0, []
    for e in model.effects:
        if kind == "arm" and e.stage != "arm":
            continue
        v = {p.name: values[f"{e.name}.{p.name}"] for p in e.params}
        num, den, tau = _term(e, v, model.mp, what, hint)
        if e.stage == "output":
            out = (np.polymul(out[0], num), np.polymul(out[1], den))
            delay += tau
            continue
        if tau > 0:
            pn, pd = pade_delay(tau, int(pade_order))
            num, den = np.polymul(num, pn), np.polymul(den, pd)
            inner.append(float(tau))
        z = rational_sum(z, (num, den))
    num = np.trim_zeros(np.polymul(out[0], z[1]), "f")
    den = np.trim_zeros(np.polymul(out[1], z[0]), "f")
    return RationalModel(num / den[0], den / den[0], float(delay), tuple(inner),
                         int(pade_order))


def device_impedance(model: ClosedLoopModel, theta, *, pade_order: int = PADE_ORDER,
                     what: str = "model",
                     hint: str = "add rational=... to its Effect "
                                 "(docs/methods.md#your-own-effects)") -> RationalModel:
    """The device's impedance Z_dev = Mp s² + ΔZ_dev (eq. 2 with the device effects of
    the model), N/m, as polynomials in s (rad/s), den monic: improper (degree 2 over
    0 for the bare device). With the arm's H_ARM of :func:`rational_model` and the output
    factors R e^(−sT), X/F = R e^(−sT) · H_ARM / (1 + Z_dev H_ARM) (eq. 4). A delay
    inside a device effect becomes its Padé approximant; raises as
    :func:`rational_model`."""
    values = {n: float(v) for n, v in model.values(theta).items()}
    z = (np.array([model.mp, 0.0, 0.0]), np.array([1.0]))
    inner = []
    for e in model.effects:
        if e.stage != "device":
            continue
        v = {p.name: values[f"{e.name}.{p.name}"] for p in e.params}
        num, den, tau = _term(e, v, model.mp, what, hint)
        if tau > 0:
            pn, pd = pade_delay(tau, int(pade_order))
            num, den = np.polymul(num, pn), np.polymul(den, pd)
            inner.append(float(tau))
        z = rational_sum(z, (num, den))
    num, den = np.trim_zeros(z[0], "f"), np.trim_zeros(z[1], "f")
    return RationalModel(num / den[0], den / den[0], 0.0, tuple(inner), int(pade_order))


def pade_phase_bound_deg(omega_T, order: int) -> np.ndarray:
    """Upper bound of the phase error of the [n/n] Padé approximant of e^(−sT), degrees.

    c_n (ωT)^(2n+1) in degrees, c_n = (n!)² / ((2n)! (2n+1)!): the first term of the
    series of the phase error, which bounds it on 0 < ωT ≤ 2n + 4 (see the module
    docstring; the magnitude of the approximant is exact).

    Parameters
    ----------
    omega_T : array_like
        ω·T: angular frequency (rad/s) times the delay (s), dimensionless.
    order : int
        n.

    Returns
    -------
    ndarray
        The bound, degrees, shaped as ``omega_T``.
    """
    n = int(order)
    c = math.factorial(n) ** 2 / (math.factorial(2 * n) * math.factorial(2 * n + 1))
    return np.degrees(c * np.abs(np.asarray(omega_T, dtype=float)) ** (2 * n + 1))


def weight_zpk(weight: WuWeight) -> tuple[np.ndarray, np.ndarray, float]:
    """Wu(s) = k Π(s − z)/Π(s − p) (eq. 7, s in rad/s) as (z, p, k): every zero and pole,
    each conjugate pair written out (r, r̄; a double real root twice), complex, in the
    order of the weight's pairs; k the gain."""
    def roots(pairs: np.ndarray) -> np.ndarray:
        pairs = np.asarray(pairs, dtype=complex)
        return np.ravel(np.column_stack([pairs, np.conj(pairs)])) if pairs.size \
            else np.zeros(0, complex)
    return roots(weight.zeros), roots(weight.poles), float(weight.gain)


def model_prefix(axis: str, grip: float | None = None) -> str:
    """The name of a row's model in an export: the axis (``x``), or for a grip fit
    ``x_grip2N`` (a decimal point written ``p``: ``x_grip2p5N``)."""
    if grip is None or grip != grip:
        return str(axis)
    text = f"{float(grip):g}".replace(".", "p").replace("-", "m").replace("+", "")
    return f"{axis}_grip{text}N"


# ---------------------------------------------------------------------------
# The variables of an export
# ---------------------------------------------------------------------------

def _row_grip(row) -> float | None:
    g = row.get("grip_N") if hasattr(row, "get") else None
    return None if g is None or g != g else float(g)


def _model_variables(rows, pade_order: int, hint: str) -> tuple[dict, list[str]]:
    """G<p>_num/_den/_delay_s (X/F), H<p>_num/_den (H_ARM), G<p>_inner_delay_s where a
    delay sits inside an impedance; and the readme lines."""
    out: dict[str, object] = {}
    inner_any = False
    for _, row in rows.iterrows():
        p = model_prefix(row["axis"], _row_grip(row))
        model, theta = model_from_params(row)
        what = f"axis {row['axis']}" + ("" if _row_grip(row) is None
                                        else f", grip {_row_grip(row):g} N")
        g = rational_model(model, theta, kind="closed_loop", pade_order=pade_order,
                           what=what, hint=hint)
        h = rational_model(model, theta, kind="arm", pade_order=pade_order, what=what,
                           hint=hint)
        out[f"G{p}_num"], out[f"G{p}_den"], out[f"G{p}_delay_s"] = g.num, g.den, g.delay_s
        d = device_impedance(model, theta, pade_order=pade_order, what=what, hint=hint)
        out[f"H{p}_num"], out[f"H{p}_den"] = h.num, h.den
        out[f"Z{p}_num"], out[f"Z{p}_den"] = d.num, d.den
        if g.inner_delays_s:
            out[f"G{p}_inner_delay_s"] = np.array(g.inner_delays_s)
            inner_any = True
    lines = ["G<m>_num, G<m>_den, G<m>_delay_s: the closed loop X/F of eq. 4 (device and "
             "arm, what the spectra measure), m/N: tf(num, den, 'IODelay', delay_s).",
             "H<m>_num, H<m>_den: the arm's own dynamics H_ARM (eq. 3, with the arm "
             "effects of the model), m/N: tf(num, den).",
             "Z<m>_num, Z<m>_den: the device's impedance Mp s^2 (eq. 2, with the device "
             "effects of the model), N/m, improper: X/F = R exp(-s delay_s) H/(1 + Z H), R "
             "the model's output factors (none in the 5-parameter model)."]
    if inner_any:
        lines.append(f"G<m>_inner_delay_s: delays inside an impedance (a reflex), held in "
                     f"the G, H and Z polynomials as [n/n] Pade approximants, n = "
                     f"pade_order ({pade_order}).")
    return out, lines


def _weight_variables(weights: Mapping[str, WuWeight],
                      bands: Mapping[str, tuple[float, float]] | None) -> dict:
    out: dict[str, object] = {}
    for axis in AXES:
        if axis not in weights:
            continue
        z, p, k = weight_zpk(weights[axis])
        out[f"W{axis}_z"], out[f"W{axis}_p"], out[f"W{axis}_k"] = z, p, k
        if bands and axis in bands:
            out[f"W{axis}_band_rad_s"] = 2 * np.pi * np.asarray(bands[axis], dtype=float)
    return out


def _one_response(sp: Spectra, where: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(ω rad/s, H) of the only row of ``sp`` at its finite frequencies; None when
    there is no row. UsageError when several estimators give several rows."""
    if len(sp) == 0:
        return None
    if len(sp) > 1:
        raise UsageError(f"{where}: the spectra hold {len(sp)} such responses "
                         f"(estimators {', '.join(sorted(sp.values_of('method')))})")
    f, h, _, _ = sp.row(0)
    keep = np.isfinite(h)
    return 2 * np.pi * f[keep], h[keep]


def _spectra_variables(rows, spectra: Spectra) -> tuple[dict, list[str], list[str]]:
    """M<p>_resp/_w_rad_s (the measured response each row was fitted to) and, for a
    nominal file, D<axis>_resp/_w_rad_s/_trials (the derived arm dynamics of the
    trials, as fit-uncertainty uses them)."""
    out: dict[str, object] = {}
    notes: list[str] = []
    nominal = "grip_N" not in rows.columns
    measured = spectra.select(kind="measured")
    for _, row in rows.iterrows():
        axis, grip = str(row["axis"]), _row_grip(row)
        p = model_prefix(axis, grip)
        sel = measured.select(axis=axis, out_axis=axis,
                              level="median" if grip is None else "mean",
                              grip=grip)
        label = f"axis {axis}" + ("" if grip is None else f", grip {grip:g} N")
        got = _one_response(sel, label)
        if got is None:
            notes.append(f"{label}: the spectra hold no measured "
                         f"{'median' if grip is None else 'mean'}; M{p} left out")
            continue
        out[f"M{p}_w_rad_s"], out[f"M{p}_resp"] = got
    lines = ["M<m>_resp, M<m>_w_rad_s: the measured X/F the model was fitted to ("
             + ("median over all trials of the axis" if nominal else
                "mean over subjects per axis and grip") + "), m/N, at w rad/s: "
             "frd(resp, w)."]
    if nominal:
        trials = spectra.select(level="trial", kind="derived")
        for _, row in rows.iterrows():
            axis = str(row["axis"])
            if axis not in trials.values_of("axis"):
                notes.append(f"axis {axis}: the spectra hold no derived trials; D{axis} "
                             "left out")
                continue
            f, H, labels = derived_trials(trials, axis)
            H = arm_trials(row, f, H, derived_mass_kg(spectra, axis))
            out[f"D{axis}_w_rad_s"] = 2 * np.pi * f
            out[f"D{axis}_resp"] = H
            out[f"D{axis}_trials"] = np.array(labels, dtype=object)
        lines.append("D<a>_resp (trials x frequencies), D<a>_w_rad_s, D<a>_trials: every "
                     "trial's derived arm dynamics Xa/Fa, m/N, with the apparatus "
                     "effects of the axis's model removed: what Wu covers (eq. 6).")
    return out, lines, notes


def export_variables(rows, *, weights: Mapping[str, WuWeight] | None = None,
                     weight_bands: Mapping[str, tuple[float, float]] | None = None,
                     spectra: Spectra | None = None, pade_order: int = PADE_ORDER,
                     sources: Mapping[str, str] | None = None,
                     hint: str = "add rational=... to its Effect "
                                 "(docs/methods.md#your-own-effects)"
                     ) -> tuple[dict[str, object], list[str]]:
    """The variables of an export (``armfit export``): MATLAB names and numpy values.

    Parameters
    ----------
    rows : pandas.DataFrame
        A nominal params table (one row per axis) or a grip table (one per axis and
        grip), as :func:`armfit.models.params.read_param_rows` reads them.
    weights : {axis: WuWeight}, optional
        Uncertainty weights Wu (eq. 7).
    weight_bands : {axis: (lo, hi)}, optional
        The band each weight was fitted over, Hz.
    spectra : Spectra, optional
        The measured responses (median or means, and derived trials).
    pade_order : int
        Order of the Padé approximant of a delay inside an impedance.
    sources : {name: path}, optional
        The input files, written as ``source_<name>``.
    hint : str
        What a message suggests when an effect declares no rational form.

    Returns
    -------
    (dict, list of str)
        {name: value} in the order written (per row ``G<m>_num``, ``G<m>_den``,
        ``G<m>_delay_s``, ``H<m>_num``, ``H<m>_den``, ``Z<m>_num``, ``Z<m>_den`` and,
        with a delay inside an impedance, ``G<m>_inner_delay_s``; per axis ``W<a>_z``, ``W<a>_p``,
        ``W<a>_k``, ``W<a>_band_rad_s``; ``M<m>_resp``, ``M<m>_w_rad_s``; ``D<a>_*``;
        then ``readme``, ``armfit_version``, ``pade_order``, ``source_*``), ``<m>`` the
        row's :func:`model_prefix`; and notes on what was left out.

    Raises
    ------
    UsageError
        A per-trial params table, or an effect without a rational form.
    """
    if "subject" in rows.columns:
        raise UsageError("a per-trial params file (fit-trials) cannot be exported; give "
                         "the params file of fit-nominal or fit-grip")
    variables, lines = _model_variables(rows, pade_order, hint)
    notes: list[str] = []
    if weights:
        variables.update(_weight_variables(weights, weight_bands))
        lines.append("W<a>_z, W<a>_p, W<a>_k: the uncertainty weight Wu of eq. 7 (stable, "
                     "minimum phase), zeros and poles in rad/s: zpk(z, p, k); "
                     "W<a>_band_rad_s: the band it was fitted over.")
    if spectra is not None:
        more, more_lines, notes = _spectra_variables(rows, spectra)
        variables.update(more)
        lines += more_lines
    variables["readme"] = _readme(rows, lines)
    variables["armfit_version"] = __version__
    variables["pade_order"] = float(pade_order)
    for name, path in (sources or {}).items():
        variables[f"source_{name}"] = str(path)
    return variables, notes


def _readme(rows, lines: Sequence[str]) -> str:
    models = ", ".join(model_prefix(r["axis"], _row_grip(r)) for _, r in rows.iterrows())
    head = [f"armfit {__version__}: fitted human-arm models (Fu & Cavusoglu, ICRA 2010).",
            f"Models <m>: {models}; axes <a>: x, y, z. Polynomials in s (rad/s), highest "
            "power first; frequencies w in rad/s; delays in s.",
            "S = load(file); G = tf(S.Gx_num, S.Gx_den, 'IODelay', S.Gx_delay_s);"]
    return "\n".join(head + list(lines))


# ---------------------------------------------------------------------------
# Writers
# ---------------------------------------------------------------------------

def _mat_value(v):
    if isinstance(v, str):
        return v
    if isinstance(v, np.ndarray) and v.dtype == object:
        return v                                    # a cell array of strings
    return np.asarray(v, dtype=complex if np.iscomplexobj(v) else float)


def mat_bytes(variables: Mapping[str, object]) -> bytes:
    """The variables as a MATLAB format-5 file (``scipy.io.savemat``, one-dimensional
    arrays as row vectors, strings as char arrays, labels as cell arrays). The header's
    text names armfit instead of the time of writing, so the same variables give the
    same bytes."""
    from scipy.io import savemat

    for name in variables:
        if not (name.isidentifier() and name.isascii() and name[0].isalpha()
                and len(name) <= 63):
            raise UsageError(f"{name!r} is not a MATLAB variable name")
    buf = io.BytesIO()
    savemat(buf, {k: _mat_value(v) for k, v in variables.items()}, format="5",
            oned_as="row", do_compression=False)
    data = bytearray(buf.getvalue())
    text = f"MATLAB 5.0 MAT-file, written by armfit {__version__}".encode("ascii")
    data[:116] = text.ljust(116, b" ")
    return bytes(data)


def _json_value(v):
    if isinstance(v, str):
        return v
    a = np.asarray(v)
    if a.dtype == object:
        return [str(x) for x in a.tolist()]
    if np.iscomplexobj(a):
        return {"re": _json_value(a.real), "im": _json_value(a.imag)}
    a = a.astype(float)
    if a.ndim == 0:
        return float(a) if np.isfinite(a) else None
    return np.where(np.isfinite(a), a, None).tolist() if not np.isfinite(a).all() \
        else a.tolist()


def json_text(variables: Mapping[str, object]) -> str:
    """The variables as one JSON object (the same names): numbers as numbers, arrays as
    lists (a matrix as a list of rows), complex arrays as ``{"re": [...], "im": [...]}``,
    NaN as null, full precision."""
    return json.dumps({k: _json_value(v) for k, v in variables.items()}, indent=1) + "\n"


def write_export(variables: Mapping[str, object], path, fmt: str, *,
                 overwrite: bool = False):
    """Write the variables as ``fmt`` ('mat' or 'json') to ``path``, atomically
    (:func:`armfit.io.atomic.atomic_path`; OutputError when it exists without
    ``overwrite``). Returns the path."""
    if fmt not in EXPORT_FORMATS:
        raise UsageError(f"format must be one of {', '.join(EXPORT_FORMATS)}, got {fmt!r}")
    data = mat_bytes(variables) if fmt == "mat" else json_text(variables).encode("utf-8")
    with atomic_path(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
    return path


__all__ = [
    "PADE_ORDER", "KINDS", "EXPORT_FORMATS", "RationalModel", "rational_model", "device_impedance",
    "pade_phase_bound_deg", "weight_zpk", "model_prefix", "export_variables", "mat_bytes",
    "json_text", "write_export",
]
