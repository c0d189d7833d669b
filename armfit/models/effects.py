"""Effects: physical effects the 5-parameter model of eq. 4 lacks, and their registry.

Each effect is a value that plugs into :class:`armfit.models.arm.ClosedLoopModel` at
one of three places (its ``stage``):

``arm``     an impedance (N/m) added to the arm's Z_ARM = 1/H_ARM;
``device``  an impedance (N/m) added to the device's Mp s²;
``output``  a dimensionless factor multiplying the measured X/F.

So with every effect present the measured dynamics are
X/F = Π R_out(s) / (Z_ARM + ΔZ_arm + Mp s² + ΔZ_dev).
The same definitions drive the simulator, the fits and the diagnosis.

Defining an effect (a user's file, an installed package, or the built-in library)::

    from armfit import Effect, Param

    def _spring(s, values, mp):
        return values["k_N_per_m"] + 0.0 * s

    def _spring_rational(values, mp):
        return values["k_N_per_m"], 1.0      # k/1: num(s) = k, den(s) = 1

    EFFECTS = [Effect(
        name="device-spring", stage="device",
        params=(Param("k_N_per_m", "N/m", 0.01, 5000.0, 50.0, "spring in the device"),),
        term=_spring, rational=_spring_rational,
        summary="A spring in the device: its impedance gains k.", null=(0.01,))]

``term(s, values, mp)`` gets s = j·2π·f (rad/s, a numpy array), ``values`` mapping the
effect's own parameter names to numbers (or to arrays that broadcast against s: the
fitter evaluates many points at once, so write it with numpy, not ``math``), and the
device mass ``mp`` (kg); it returns an array of the shape of s (add ``0.0 * s`` to a
constant). ``null`` gives the values at which the effect vanishes (``None``: the device
mass, for an effect that replaces Mp); nested fits start there. ``starts`` (optional)
gives further starting points, ``suspect_when`` (optional) the symptom, in words.

``rational(values, mp)`` (optional) states the same term as a rational function of s
times a delay, for the stability analysis (:mod:`armfit.loop`), which needs the
plant as polynomials: it gets ``values`` as plain floats and the device mass ``mp``
(kg) and returns ``(num, den)`` or ``(num, den, delay_s)``, polynomial coefficients in s
(rad/s), highest power first, such that

    term(s) = num(s) / den(s) · exp(−s · delay_s)                              (R1)

exactly (``delay_s`` ≥ 0, in s; 0 when left out; a number stands for a polynomial of
degree 0, as the spring's k/1 above). An effect without it is refused by ``armfit
stability`` with a message saying so; every other use ignores it.

The registry (:data:`EFFECTS`, a read-only mapping name → Effect) holds, in order: the
built-in library (:mod:`armfit.models.library`), the effects of installed packages (the
entry-point group ``armfit.effects``: each entry point names a module, or an object, with
an ``EFFECTS`` list), and the files loaded with :func:`load_effect_file` (the CLI's
``--effects FILE``). Every effect is checked when it is registered
(:func:`check_effect`); a bad one raises :class:`armfit.errors.EffectDefinitionError`
naming the file and what is wrong; with ``rational``, (R1) must hold on the probe grid
within :data:`RATIONAL_RTOL`.

Every model evaluates an effect through :meth:`Effect.evaluate`, the one place where a
user's code runs (with :meth:`Effect.rational_form` and the loading of its file): what
that code prints on stdout goes to stderr (stdout holds armfit's data, e.g. ``--json``),
an exception it raises becomes an :class:`~armfit.errors.EffectDefinitionError` naming
the file, the effect and the exception (exit 65; the traceback is chained to it), and a
term that is NaN or infinite at a frequency where its inputs are finite is refused the
same way, so that no fit, comparison, diagnosis or stability result is made of a
non-finite model.
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import sys
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from armfit.constants import GRID_HZ
from armfit.errors import EffectDefinitionError, NoInputError, UsageError, cell
from armfit.io.numbers import parse_number
from armfit.models.arm import BASE_PARAMS, DEVICE_MASS_KG, STAGE_NAMES, Param

TermFn = Callable[[np.ndarray, Mapping[str, float], float], np.ndarray]
RationalFn = Callable[[Mapping[str, float], float], tuple]

#: Entry-point group through which installed packages register effects.
ENTRY_POINT_GROUP = "armfit.effects"

#: Probe frequencies (Hz) of the registration checks: the paper's fit band, 0.1–30 Hz,
#: 40 points log-spaced.
PROBE_HZ = np.geomspace(*GRID_HZ, 40)

#: Largest relative change |H_null/H_base − 1| of the closed-loop response an effect may
#: cause at its null values (probe band, base parameters at their typical values, every
#: axis's device mass). 1e-3 is 0.009 dB and 0.06°, far below the noise of any measured
#: bin (0.1–1 dB), yet loose enough for effects whose null sits on a bound short of the
#: exact zero (a 100 kHz low-pass changes the response by 3e-4 at 30 Hz).
NULL_TOLERANCE = 1e-3

#: Largest difference between an effect's rational form (R1) and its ``term`` on the
#: probe grid, relative to the largest |term| there (at the same values and device
#: mass), plus :data:`RATIONAL_ATOL` (the term's own unit: N/m, or 1 for an output
#: factor). Both sides are the same function evaluated two ways, so they agree to
#: rounding (about 1e-15); 1e-9 leaves room for a polynomial evaluated at |s| up to
#: 190 rad/s and catches any wrong coefficient, sign or power of s.
RATIONAL_RTOL = 1e-9
RATIONAL_ATOL = 1e-12

_BAD_NAME_CHARS = ".;,:="


@dataclass(frozen=True, kw_only=True)
class Effect:
    """A named physical effect: its parameters, where it acts and what it does.

    Parameters
    ----------
    name : str
        Unique name (no spaces or ``. ; , : =``), e.g. ``"device-spring"``.
    stage : str
        ``"arm"`` or ``"device"`` (``term`` is an impedance in N/m added there) or
        ``"output"`` (``term`` is a dimensionless factor on X/F).
    params : tuple of Param
        The effect's parameters, with physical bounds and typical values.
    term : callable
        ``term(s, values, mp)`` → array of the shape of s (see the module docstring).
    null : tuple
        One value per parameter at which the effect vanishes (``None``: the device mass).
    summary : str, optional
        One sentence: what the effect is.
    starts : tuple of tuples, optional
        Further starting points of nested fits, one value per parameter.
    suspect_when : str, optional
        The symptom in the comparison that suggests this effect.
    rational : callable, optional
        ``rational(values, mp)`` → ``(num, den)`` or ``(num, den, delay_s)``: the same
        term as num(s)/den(s)·exp(−s·delay_s) (eq. R1 of the module docstring), with
        ``values`` plain floats, ``mp`` the device mass (kg), coefficients in powers of
        s (rad/s), highest first, ``delay_s`` ≥ 0 in s. Needed by the stability analysis
        only (:mod:`armfit.loop`); None (the default) when the effect has none.
    """

    name: str
    stage: str
    params: tuple[Param, ...]
    term: TermFn
    null: tuple[float | None, ...]
    summary: str = ""
    starts: tuple[tuple[float, ...], ...] = ()
    suspect_when: str = ""
    rational: RationalFn | None = None

    def __post_init__(self) -> None:
        # accept lists where tuples are documented (an Effect is immutable and hashable)
        for attr in ("params", "null"):
            v = getattr(self, attr)
            if isinstance(v, list):
                object.__setattr__(self, attr, tuple(v))
        if isinstance(self.starts, (list, tuple)):
            object.__setattr__(self, "starts", tuple(
                tuple(st) if isinstance(st, list) else st for st in self.starts))
        _check_structure(self)

    def null_values(self, mp: float) -> dict[str, float]:
        """The parameter values at which this effect leaves the model (nearly) unchanged,
        ``None`` entries of :attr:`null` replaced by the device mass ``mp`` (kg)."""
        return {p.name: (float(mp) if v is None else float(v))
                for p, v in zip(self.params, self.null, strict=True)}

    def start_points(self, mp: float) -> list[dict[str, float]]:
        """The null point, then the effect's further starting points, clipped to bounds."""
        pts = [self.null_values(mp)]
        for st in self.starts:
            pts.append({p.name: float(np.clip(v, p.lower, p.upper))
                        for p, v in zip(self.params, st, strict=True)})
        return pts

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def evaluate(self, s: np.ndarray, values: Mapping[str, np.ndarray | float], mp: float
                 ) -> np.ndarray:
        """The term at ``s``, as every model evaluates it: ``term(s, values, mp)``,
        checked.

        Parameters
        ----------
        s : ndarray
            j·2π·f, rad/s.
        values : mapping
            The effect's own parameter values: numbers, or arrays that broadcast
            against ``s``.
        mp : float
            Device mass, kg.

        Returns
        -------
        ndarray
            What ``term`` returned, as an array.

        Raises
        ------
        EffectDefinitionError
            ``term`` raised (the message names the file, the effect and the exception,
            which is chained to it), returned something other than numbers, or is NaN
            or infinite at a frequency f > 0 where every value is finite. A user's
            ``term`` runs with stdout sent to stderr.
        """
        if _builtin(self):
            out = self.term(s, values, mp)
        else:
            out = _call_user(self, "term", self.term, s, values, mp)
        arr = np.asarray(out)
        if arr.dtype.kind not in "biufc":
            raise EffectDefinitionError(f"effect {self.name!r}: term returned "
                                        f"{type(out).__name__} of {arr.dtype}, not numbers",
                                        file=_source(self))
        if not np.isfinite(arr).all():
            _refuse_non_finite(self, s, values, arr)
        return arr

    def rational_form(self, values: Mapping[str, float], mp: float
                      ) -> tuple[np.ndarray, np.ndarray, float]:
        """The term as (num, den, delay_s) with term(s) = num(s)/den(s)·exp(−s·delay_s)
        (eq. R1): coefficients in powers of s (rad/s), highest first, as float arrays;
        delay_s ≥ 0 (s).

        Parameters
        ----------
        values : mapping
            The effect's own parameter values (plain numbers).
        mp : float
            Device mass, kg.

        Raises
        ------
        UsageError
            The effect declares no ``rational``.
        EffectDefinitionError
            ``rational`` raised, or returned something other than finite real
            coefficients and a finite delay ≥ 0.
        """
        if self.rational is None:
            raise UsageError(f"effect {self.name!r} declares no rational form")
        try:
            return _rational_parts(self, {k: float(v) for k, v in values.items()},
                                   float(mp), "")
        except EffectDefinitionError as exc:
            if exc.file is not None:
                raise
            raise EffectDefinitionError(exc.detail, file=_source(self)) from exc

    def __reduce_ex__(self, protocol):
        # A registered effect travels to worker processes by reference (its name and
        # where it came from), so an effect defined in a user's file need not be
        # importable there: the worker loads that file itself.
        origin = EFFECTS.origin_of(self)
        if origin is not None:
            return (_restore_effect, (self.name, origin, EFFECTS.label_of(self.name)))
        return super().__reduce_ex__(protocol)


def _is_number(v) -> bool:
    return (isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
            and bool(np.isfinite(v)))


# ---------------------------------------------------------------------------
# Running a user's code: stdout to stderr, exceptions and non-finite terms refused
# ---------------------------------------------------------------------------

#: The module of the built-in effects: their code is armfit's (an exception there is a
#: bug of armfit, not an error in a user's file).
_LIBRARY = "armfit.models.library"

_IN_USER_CODE = threading.local()     # .depth: user code running in this thread
_SWITCH_LOCK = threading.Lock()
_switch: _StdoutSwitch | None = None
_switch_users = 0


class _StdoutSwitch:
    """``sys.stdout`` while a user's effect code runs: what a thread inside that code
    writes goes to ``sys.stderr``, what the other threads write to the stdout it
    replaced (which holds armfit's data)."""

    def __init__(self, stdout) -> None:
        self.stdout = stdout

    def _target(self):
        return sys.stderr if getattr(_IN_USER_CODE, "depth", 0) else self.stdout

    def write(self, text):
        return self._target().write(text)

    def writelines(self, lines):
        return self._target().writelines(lines)

    def flush(self):
        return self._target().flush()

    def __getattr__(self, name):
        return getattr(self._target(), name)


@contextlib.contextmanager
def _user_stdout() -> Iterator[None]:
    """Send what this thread prints on stdout to stderr for the ``with`` block (a user's
    effect file loading, or its ``term`` or ``rational`` running); other threads keep
    their stdout."""
    global _switch, _switch_users
    with _SWITCH_LOCK:
        if _switch_users == 0:
            _switch = _StdoutSwitch(sys.stdout)
            sys.stdout = _switch
        _switch_users += 1
    _IN_USER_CODE.depth = getattr(_IN_USER_CODE, "depth", 0) + 1
    try:
        yield
    finally:
        _IN_USER_CODE.depth -= 1
        with _SWITCH_LOCK:
            _switch_users -= 1
            if _switch_users == 0:
                if sys.stdout is _switch:
                    sys.stdout = _switch.stdout
                _switch = None


def _builtin(e: Effect) -> bool:
    """Whether ``e``'s term is armfit's own (the built-in library's)."""
    return getattr(e.term, "__module__", None) == _LIBRARY


def _source(e: Effect) -> str | None:
    """Where ``e`` was defined, for messages: the file as it was given (or the entry
    point) of a registered effect, the library's module for a built-in one, else the
    file of its ``term`` function."""
    label = EFFECTS.label_of(e.name) if EFFECTS.origin_of(e) is not None else None
    if label is None:
        code = getattr(e.term, "__code__", None)
        label = _LIBRARY if _builtin(e) else getattr(code, "co_filename", None)
    return label


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text.strip() else \
        type(exc).__name__


def _call_user(e: Effect, what: str, fn: Callable, *args, where: str = ""):
    """``fn(*args)``, the user's ``term`` or ``rational`` of ``e``, with stdout sent to
    stderr and numpy's floating-point warnings off (what it returns is checked); whatever
    it raises becomes one EffectDefinitionError line naming the file, the effect and the
    exception (chained to it, for the traceback of ``-v``)."""
    with _user_stdout(), np.errstate(all="ignore"):
        try:
            return fn(*args)
        except (Exception, SystemExit) as exc:  # the user's code: whatever it raised
            raise EffectDefinitionError(
                f"effect {e.name!r} raised {_first_line(exc)} (in its {what}"
                f"{', ' + where if where else ''})", file=_source(e)) from exc


def _refuse_non_finite(e: Effect, s, values: Mapping, out: np.ndarray) -> None:
    """Raise EffectDefinitionError for the first point where ``out`` (the term at ``s``
    and ``values``) is NaN or infinite while s ≠ 0 and every value is finite; return
    quietly when every such point has a non-finite input (not the term's doing)."""
    shape = out.shape
    try:
        sb = np.broadcast_to(np.asarray(s), shape)
        vb = {k: np.broadcast_to(np.asarray(v), shape) for k, v in values.items()}
    except ValueError:      # inputs that do not broadcast to the output: blame the term
        sb, vb = None, {}
    blame = ~np.isfinite(out)
    if sb is not None:
        blame &= np.isfinite(sb) & (sb != 0)
    for v in vb.values():
        blame &= np.isfinite(v)
    if not blame.any():
        return
    i = tuple(np.argwhere(blame)[0])
    what = "NaN" if np.isnan(out[i]) else "infinite"
    at = "" if sb is None else f" at {abs(complex(sb[i])) / (2 * np.pi):.4g} Hz"
    vals = ", ".join(f"{k}={float(np.real(v[i])):.6g}" for k, v in vb.items())
    raise EffectDefinitionError(
        f"effect {e.name!r} is {what}{at}{' (' + vals + ')' if vals else ''}; its term "
        "must be finite at every frequency of the band for every value within the "
        "parameters' bounds", file=_source(e))


def _check_structure(e: Effect) -> None:
    """The checks that need no evaluation of ``term`` (run by the constructor)."""
    def fail(what: str) -> None:
        raise EffectDefinitionError(f"effect {e.name!r}: {what}")

    if not isinstance(e.name, str) or not e.name.strip():
        raise EffectDefinitionError(f"effect name must be a non-empty string, got {e.name!r}")
    bad = [c for c in e.name if c in _BAD_NAME_CHARS or c.isspace()]
    if bad:
        fail(f"its name may not hold {bad[0]!r} (no spaces or . ; , : =)")
    if e.stage not in STAGE_NAMES:
        fail(f"stage must be one of {', '.join(STAGE_NAMES)}, got {e.stage!r}")
    if not isinstance(e.params, tuple) or not e.params:
        fail("params must be a non-empty tuple of armfit.Param")
    for i, p in enumerate(e.params):
        if not isinstance(p, Param):
            fail(f"params[{i}] is a {type(p).__name__}, not an armfit.Param")
    names = [p.name for p in e.params]
    for n in names:
        bad = [c for c in n if c in _BAD_NAME_CHARS or c.isspace()]
        if bad:
            fail(f"parameter name {n!r} may not hold {bad[0]!r} (no spaces or . ; , : =)")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        fail(f"parameter {dup[0]!r} given twice")
    if not callable(e.term):
        fail(f"term must be a function term(s, values, mp), got {type(e.term).__name__}")
    if not isinstance(e.null, tuple) or len(e.null) != len(e.params):
        n = len(e.null) if isinstance(e.null, tuple) else "not a tuple"
        fail(f"null must give one value per parameter ({len(e.params)}: "
             f"{', '.join(names)}), got {n}")
    for p, v in zip(e.params, e.null, strict=True):
        if v is None:
            continue
        if not _is_number(v):
            fail(f"null value of {p.name} must be a number (or None for the device mass), "
                 f"got {cell(v)}")
        if not (p.lower <= v <= p.upper):
            fail(f"null value {v:g} of {p.name} lies outside its bounds "
                 f"[{p.lower:g}, {p.upper:g}] {p.unit}")
    if not isinstance(e.starts, tuple):
        fail("starts must be a tuple of starting points")
    for j, st in enumerate(e.starts):
        if not isinstance(st, tuple) or len(st) != len(e.params):
            fail(f"starts[{j}] must give one value per parameter ({len(e.params)})")
        for p, v in zip(e.params, st, strict=True):
            if not _is_number(v) or not (p.lower <= v <= p.upper):
                fail(f"starts[{j}]: {p.name}={cell(v)} is not a number inside its bounds "
                     f"[{p.lower:g}, {p.upper:g}] {p.unit}")
    for attr in ("summary", "suspect_when"):
        if not isinstance(getattr(e, attr), str):
            fail(f"{attr} must be a string")
    if e.rational is not None and not callable(e.rational):
        fail(f"rational must be a function rational(values, mp) or None, got "
             f"{type(e.rational).__name__}")


def _probe_term(e: Effect, values: Mapping[str, float], mp: float, where: str
                ) -> np.ndarray:
    s = 2j * np.pi * PROBE_HZ
    with np.errstate(all="ignore"):
        out = _call_user(e, "term", e.term, s, dict(values), mp, where=where)
    try:
        arr = np.asarray(out, dtype=complex)
    except (TypeError, ValueError):
        raise EffectDefinitionError(f"effect {e.name!r}: term returned "
                                    f"{type(out).__name__}, not numbers, {where}") from None
    if arr.shape != s.shape:
        raise EffectDefinitionError(
            f"effect {e.name!r}: term returned shape {arr.shape} for s of shape {s.shape} "
            f"{where}; return an array shaped like s (add 0.0 * s to a constant)")
    if not np.all(np.isfinite(arr)):
        bad = PROBE_HZ[~np.isfinite(arr)][0]
        raise EffectDefinitionError(f"effect {e.name!r}: term is NaN or infinite at "
                                    f"{bad:.3g} Hz {where}")
    return arr


def _coefficients(e: Effect, x, what: str, where: str) -> np.ndarray:
    """One polynomial of a rational form as a 1-D float array (a number is degree 0)."""
    def fail(why: str) -> None:
        raise EffectDefinitionError(f"effect {e.name!r}: rational returned {what} {why}"
                                    f"{' ' + where if where else ''}; give real polynomial "
                                    "coefficients in s, highest power first")
    try:
        arr = np.atleast_1d(np.asarray(x))
    except (TypeError, ValueError):
        fail(f"{type(x).__name__} that is not numbers")
    if np.iscomplexobj(arr):
        fail("with complex coefficients")
    if arr.dtype.kind not in "biuf" or arr.dtype == bool:
        fail(f"of {arr.dtype} that is not numbers")
    if arr.ndim != 1 or arr.size == 0:
        fail(f"of shape {arr.shape}, not a non-empty 1-D sequence")
    arr = arr.astype(float)
    if not np.all(np.isfinite(arr)):
        fail("with NaN or infinite coefficients")
    return arr


def _rational_parts(e: Effect, values: Mapping[str, float], mp: float, where: str
                    ) -> tuple[np.ndarray, np.ndarray, float]:
    """Call ``e.rational`` and check what it returns: (num, den, delay_s) (see
    :meth:`Effect.rational_form`); any problem is one EffectDefinitionError line."""
    at = f" {where}" if where else ""
    out = _call_user(e, "rational", e.rational, dict(values), mp, where=where)
    if not isinstance(out, (tuple, list)) or len(out) not in (2, 3):
        got = f"{len(out)} items" if isinstance(out, (tuple, list)) else type(out).__name__
        raise EffectDefinitionError(f"effect {e.name!r}: rational must return (num, den) or "
                                    f"(num, den, delay_s), got {got}{at}")
    num = _coefficients(e, out[0], "num", where)
    den = _coefficients(e, out[1], "den", where)
    if not np.any(den != 0.0):
        raise EffectDefinitionError(f"effect {e.name!r}: rational returned a zero "
                                    f"denominator{at}")
    delay = out[2] if len(out) == 3 else 0.0
    d = np.asarray(delay) if isinstance(delay, (int, float, np.number, np.ndarray)) else None
    if (d is None or d.ndim != 0 or d.dtype.kind not in "iuf" or not np.isfinite(d)
            or d < 0):
        raise EffectDefinitionError(f"effect {e.name!r}: rational returned delay_s "
                                    f"{cell(delay)}{at}; it must be a finite number >= 0 (s)")
    return num, den, float(d)


def _check_rational(e: Effect, values: Mapping[str, float], mp: float,
                    term: np.ndarray, where: str) -> None:
    """(R1) on the probe grid: num/den·exp(−s·delay_s) equals ``term`` (the values of
    ``e.term`` there) within RATIONAL_RTOL·max|term| + RATIONAL_ATOL."""
    num, den, delay = _rational_parts(e, values, mp, where)
    s = 2j * np.pi * PROBE_HZ
    with np.errstate(all="ignore"):
        r = np.polyval(num, s) / np.polyval(den, s) * np.exp(-s * delay)
    if not np.all(np.isfinite(r)):
        bad = PROBE_HZ[~np.isfinite(r)][0]
        raise EffectDefinitionError(f"effect {e.name!r}: its rational form is NaN or "
                                    f"infinite at {bad:.3g} Hz (den(s) = 0) {where}")
    scale = float(np.max(np.abs(term)))
    err = np.abs(r - term)
    if np.any(err > RATIONAL_RTOL * scale + RATIONAL_ATOL):
        i = int(np.argmax(err))
        raise EffectDefinitionError(
            f"effect {e.name!r}: its rational form differs from term by {err[i]:.3g} "
            f"({err[i] / scale if scale > 0 else math.inf:.2g} of max |term|) at "
            f"{PROBE_HZ[i]:.3g} Hz {where}; rational(values, mp) must return num, den "
            "(and delay_s) with term(s) = num(s)/den(s)*exp(-s*delay_s), coefficients "
            "in s highest power first")


def check_effect(e: Effect) -> None:
    """Check an effect before registering it; raise EffectDefinitionError (without the
    file name: the loader adds it) when it breaks the contract.

    On the probe grid :data:`PROBE_HZ`, for the device mass of every axis: ``term`` must
    return finite values of the shape of s at the typical values, at the null values and
    at each start; it must also broadcast (values given as arrays of shape (2, 1) give a
    result of shape (2, n)), as the fitter evaluates many points at once; and at its null
    values the effect must leave the closed-loop response of the base model (typical
    parameters) unchanged within :data:`NULL_TOLERANCE`, so that fits with the effect
    nest the fit without it. With ``rational``, at the same values and device masses, it
    must return finite real coefficients and a finite delay ≥ 0 that give ``term``
    (eq. R1) within :data:`RATIONAL_RTOL` of max |term| plus :data:`RATIONAL_ATOL`.
    """
    from armfit.models.arm import ClosedLoopModel
    if not isinstance(e, Effect):
        raise EffectDefinitionError(f"{type(e).__name__} is not an armfit.Effect")
    typical = {p.name: float(p.typical) for p in e.params}
    base = {p.name: p.typical for p in BASE_PARAMS}
    for axis, mp in DEVICE_MASS_KG.items():
        null = e.null_values(mp)
        for p in e.params:
            if not (p.lower <= null[p.name] <= p.upper):
                raise EffectDefinitionError(
                    f"effect {e.name!r}: null value of {p.name} (the device mass of axis "
                    f"{axis}, {mp:g} kg) lies outside its bounds [{p.lower:g}, {p.upper:g}]")
        points = [(typical, "at the typical values"), (null, "at the null values")]
        points += [(st, f"at starts[{j}]") for j, st in enumerate(e.start_points(mp)[1:])]
        for values, where in points:
            term = _probe_term(e, values, mp, where)
            if e.rational is not None:
                _check_rational(e, values, mp, term,
                                f"{where} (axis {axis}, mp = {mp:g} kg)")
        s = 2j * np.pi * PROBE_HZ
        batch = {k: np.array([[v], [v]]) for k, v in typical.items()}
        try:
            with np.errstate(all="ignore"), _user_stdout():
                out = np.asarray(e.term(s, batch, mp))
            ok = out.shape == (2, s.size)
        except Exception:
            ok = False
        if not ok:
            raise EffectDefinitionError(
                f"effect {e.name!r}: term does not broadcast: with each value an array of "
                f"shape (2, 1) it must return shape (2, {s.size}); write it with numpy "
                "operations (np.exp, not math.exp)")
        model = ClosedLoopModel(mp=mp, effects=(e,))
        theta = {**base, **{f"{e.name}.{k}": v for k, v in null.items()}}
        with np.errstate(all="ignore"):
            h0 = ClosedLoopModel(mp=mp).response(PROBE_HZ, base)
            h1 = model.response(PROBE_HZ, theta)
            change = np.abs(h1 / h0 - 1.0)
            ht = model.response(PROBE_HZ, {**theta, **{f"{e.name}.{k}": v
                                                       for k, v in typical.items()}})
        if not np.all(np.isfinite(change)) or change.max() > NULL_TOLERANCE:
            worst = float(np.nanmax(np.where(np.isfinite(change), change, np.inf)))
            raise EffectDefinitionError(
                f"effect {e.name!r}: at its null values "
                f"({', '.join(f'{k}={v:g}' for k, v in null.items())}) it changes the "
                f"closed-loop response by {worst:.2g} (relative) on axis {axis}; the null "
                f"must leave the model unchanged (within {NULL_TOLERANCE:g})")
        if not np.all(np.isfinite(ht)) or np.any(ht == 0):
            raise EffectDefinitionError(
                f"effect {e.name!r}: at its typical values the closed-loop response is "
                "zero, NaN or infinite on the probe band")


# ---------------------------------------------------------------------------
# The registry
# ---------------------------------------------------------------------------

#: Where a registered effect came from: ("builtin", module), ("entry-point", label) or
#: ("file", absolute path).
Origin = tuple[str, str]


class EffectRegistry(Mapping):
    """The known effects, name → :class:`Effect`, in registration order: built-ins, then
    installed packages (entry points), then loaded files. Read-only as a mapping; fills
    itself (built-ins and entry points) on first use.

    A built-in effect is found by name without the installed packages being looked
    through (about 55 ms: :mod:`importlib.metadata` reads every package's metadata), as
    a worker process does when a task hands it a built-in effect; no other effect may
    take a built-in's name, so the answer is the same. Listing, counting or any other
    name fills the registry whole. The built-ins are not put through
    :func:`check_effect` at every start (about 35 ms): they are armfit's own code, held
    to the contract by its tests."""

    def __init__(self) -> None:
        self._effects: dict[str, Effect] = {}
        self._origins: dict[str, Origin] = {}
        self._labels: dict[str, str] = {}
        self._files: dict[str, list[str]] = {}
        # "empty" → "loading" → "builtins" → "loading" → "ready"
        self._state = "empty"

    # -- Mapping --------------------------------------------------------------
    def _builtins(self) -> None:
        """Register the built-in library, once."""
        if self._state == "empty":
            self._state = "loading"
            try:
                from armfit.models import library
                self.register_source(library, ("builtin", library.__name__),
                                     label=library.__name__, check=False)
            finally:
                self._state = "builtins"

    def _ready(self) -> dict[str, Effect]:
        self._builtins()
        if self._state == "builtins":
            self._state = "loading"
            try:
                _load_entry_points(self)
            finally:
                self._state = "ready"
        return self._effects

    def __getitem__(self, name: str) -> Effect:
        self._builtins()
        origin = self._origins.get(name)
        if origin is not None and origin[0] == "builtin":
            return self._effects[name]
        return self._ready()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(list(self._ready()))

    def __len__(self) -> int:
        return len(self._ready())

    def __contains__(self, name) -> bool:
        return name in self._ready()

    # -- registration -----------------------------------------------------------
    def origin_of(self, effect: Effect) -> Origin | None:
        """Where ``effect`` was registered from, or None if it is not the registered one."""
        if self._effects.get(effect.name) is effect:
            return self._origins[effect.name]
        return None

    def label_of(self, name: str) -> str | None:
        """Where effect ``name`` came from, as messages name it: the file as it was
        given, the entry point and its package, or the built-in library's module (None
        for a name not registered)."""
        return self._labels.get(name)

    def describe_origin(self, name: str) -> str:
        """Where effect ``name`` came from, in words: "the built-in library", the entry
        point, or the file as it was given."""
        kind, where = self._origins[name]
        if kind == "builtin":
            return "the built-in library"
        return self._labels.get(name, where)

    def register_source(self, source, origin: Origin, *, label: str,
                        check: bool = True) -> list[Effect]:
        """Check and register the ``EFFECTS`` of ``source`` (a module or any object with
        an ``EFFECTS`` list or tuple): all of them or, on the first problem, none.
        Raises EffectDefinitionError naming ``label``. ``check``: also put each effect
        through :func:`check_effect` (False for the built-in library only)."""
        if isinstance(source, (list, tuple)):
            effects = source
        elif not hasattr(source, "EFFECTS"):
            raise EffectDefinitionError("defines no EFFECTS (a module-level list of "
                                        "armfit.Effect)", file=label)
        else:
            effects = source.EFFECTS
        return self.register(effects, origin, label=label, check=check)

    def register(self, effects: Sequence[Effect], origin: Origin, *, label: str,
                 check: bool = True) -> list[Effect]:
        """Check and register ``effects`` (all or none); see :meth:`register_source`."""
        self._ready()
        if not isinstance(effects, (list, tuple)):
            raise EffectDefinitionError(f"EFFECTS must be a list or tuple of armfit.Effect, "
                                        f"got {type(effects).__name__}", file=label)
        if not effects:
            raise EffectDefinitionError("EFFECTS is empty", file=label)
        seen: set[str] = set()
        for i, e in enumerate(effects):
            if not isinstance(e, Effect):
                raise EffectDefinitionError(f"EFFECTS[{i}] is a {type(e).__name__}, not an "
                                            "armfit.Effect", file=label)
            if e.name in self._effects:
                raise EffectDefinitionError(
                    f"effect name {e.name!r} is already taken by "
                    f"{self.describe_origin(e.name)}; choose another name", file=label)
            if e.name in seen:
                raise EffectDefinitionError(f"effect name {e.name!r} is defined twice",
                                            file=label)
            seen.add(e.name)
            if not check:
                continue
            try:
                check_effect(e)
            except EffectDefinitionError as exc:
                raise EffectDefinitionError(exc.detail, file=label) from exc
        for e in effects:
            self._effects[e.name] = e
            self._origins[e.name] = origin
            self._labels[e.name] = label
        return list(effects)

    def unregister(self, names: Iterable[str]) -> None:
        """Remove effects that came from files (built-ins and entry points stay)."""
        for n in list(names):
            origin = self._origins.get(n)
            if origin is None or origin[0] != "file":
                continue
            del self._effects[n], self._origins[n], self._labels[n]
            left = [k for k in self._files.get(origin[1], []) if k != n]
            if left:
                self._files[origin[1]] = left
            else:
                self._files.pop(origin[1], None)

    def load_file(self, path, *, label: str | None = None) -> list[Effect]:
        """See :func:`load_effect_file`; ``label``: how messages name the file (default
        ``path`` as given; a worker process names it as the command line did)."""
        self._ready()
        p = Path(path)
        label = str(p) if label is None else label
        if not p.is_file():
            raise NoInputError(f"{label}: no such effects file" + (" (it is a folder)"
                                                                  if p.is_dir() else ""))
        key = str(p.resolve())
        if key in self._files:
            return [self._effects[n] for n in self._files[key]]
        module = _import_file(p, key, label)
        effects = self.register_source(module, ("file", key), label=label)
        self._files[key] = [e.name for e in effects]
        return effects


def _import_file(path: Path, key: str, label: str):
    """Execute a Python file as a fresh module (what it prints on stdout goes to
    stderr); any failure becomes one line naming it (``label``)."""
    import hashlib
    mod_name = "armfit_user_effects_" + hashlib.sha1(key.encode()).hexdigest()[:12]
    try:
        spec = importlib.util.spec_from_file_location(mod_name, path)
        if spec is None or spec.loader is None:
            raise EffectDefinitionError("cannot be imported as a Python file (give a .py "
                                        "file)", file=label)
        module = importlib.util.module_from_spec(spec)
        sys.modules[mod_name] = module
        with _user_stdout():
            spec.loader.exec_module(module)
    except EffectDefinitionError as exc:
        sys.modules.pop(mod_name, None)
        raise EffectDefinitionError(exc.detail if exc.file in (None, label, str(path))
                                    else str(exc), file=label) from exc
    except SyntaxError as exc:
        sys.modules.pop(mod_name, None)
        raise EffectDefinitionError(f"cannot import: SyntaxError: {exc.msg} (line "
                                    f"{exc.lineno})", file=label) from exc
    except (Exception, SystemExit) as exc:  # the user's code: whatever it raised
        sys.modules.pop(mod_name, None)
        raise EffectDefinitionError(f"cannot import: {_first_line(exc)}",
                                    file=label) from exc
    return module


def _entry_points():
    """The installed packages' entry points of :data:`ENTRY_POINT_GROUP`
    (:func:`importlib.metadata.entry_points`), or () when :func:`_may_declare_group`
    finds no package that could declare one: importing :mod:`importlib.metadata` and
    reading every package's metadata costs about 45 ms, where looking for the group's
    name in the packages' ``entry_points.txt`` costs about 1 ms."""
    if not _may_declare_group(ENTRY_POINT_GROUP):
        return ()
    from importlib.metadata import entry_points
    return entry_points(group=ENTRY_POINT_GROUP)


def _may_declare_group(group: str) -> bool:
    """False only when no installed package can declare an entry point of ``group``:
    no ``*.dist-info`` or ``*.egg-info`` folder on :data:`sys.path` (a path entry ``''``
    is the working folder, as for :mod:`importlib.metadata`) has an ``entry_points.txt``
    that holds the group's name. True (look with :mod:`importlib.metadata`) also
    wherever this look could miss a package that :mod:`importlib.metadata` finds: a path
    entry that is a file (a zip archive) or an egg, or a finder other than the standard
    path finder that finds distributions."""
    import importlib.machinery
    import os

    if any(getattr(f, "find_distributions", None) is not None
           and f is not importlib.machinery.PathFinder for f in sys.meta_path):
        return True
    name = group.encode()
    for entry in sys.path:
        root = os.fspath(entry) or "."
        if root.lower().endswith(".egg"):
            return True
        try:
            children = os.scandir(root)
        except NotADirectoryError:
            return True                   # a zip archive: importlib.metadata reads it
        except OSError:
            continue                      # a path entry that is not there
        with children:
            for child in children:
                if not child.name.lower().endswith((".dist-info", ".egg-info")):
                    continue
                try:
                    with open(os.path.join(child.path, "entry_points.txt"), "rb") as fh:
                        if name in fh.read():
                            return True
                except OSError:
                    continue              # no entry points (or an egg-info file)
    return False


def _load_entry_points(registry: EffectRegistry) -> None:
    for ep in sorted(_entry_points(), key=lambda ep: (ep.name, ep.value)):
        dist = getattr(ep, "dist", None)
        label = f"entry point '{ep.name} = {ep.value}'" + (
            f" of {dist.metadata['Name']} {dist.version}" if dist is not None else "")
        try:
            with _user_stdout():
                obj = ep.load()
        except EffectDefinitionError as exc:
            raise EffectDefinitionError(exc.detail, file=label) from exc
        except Exception as exc:  # an installed package's code: whatever it raised
            raise EffectDefinitionError(f"cannot import: {_first_line(exc)}",
                                        file=label) from exc
        registry.register_source(obj, ("entry-point", label), label=label)


#: The registry of known effects (name → Effect): built-ins, installed packages, files.
EFFECTS = EffectRegistry()


def load_effect_file(path) -> list[Effect]:
    """Load a Python file that defines a module-level ``EFFECTS`` list and register its
    effects (checked with :func:`check_effect`). Loading the same file again returns the
    same effects. Raises NoInputError if the file is missing, EffectDefinitionError (one
    line naming the file) if it cannot be imported, defines no EFFECTS, reuses a name
    already taken, or holds an effect that breaks the contract."""
    return EFFECTS.load_file(path)


def load_effect_files(paths: Iterable) -> list[str]:
    """Load several effect files (see :func:`load_effect_file`); returns the names of the
    effects newly registered (for :meth:`EffectRegistry.unregister`)."""
    before = set(EFFECTS)
    new: list[str] = []
    try:
        for p in paths:
            new += [e.name for e in load_effect_file(p) if e.name not in before]
    except BaseException:
        EFFECTS.unregister(new)      # all files or none
        raise
    return new


def _restore_effect(name: str, origin: Origin, label: str | None = None) -> Effect:
    """Unpickle a registered effect (see :meth:`Effect.__reduce_ex__`), loading the file
    it came from first when this process has not seen it (``label``: the file as the
    process that pickled it names it)."""
    if origin[0] == "file" and name not in EFFECTS:
        EFFECTS.load_file(origin[1], label=label)
    return EFFECTS[name]


def get_effect(name: str) -> Effect:
    """Look an effect up by name; raise UsageError listing the known ones otherwise."""
    try:
        return EFFECTS[name]
    except KeyError:
        raise UsageError(f"unknown effect {name!r}; known effects: "
                         f"{', '.join(EFFECTS)} (see `armfit effects`; an effect defined "
                         "in a file needs {opt:effect_files} FILE)") from None


def parse_effect_spec(spec: str) -> tuple[Effect, dict[str, float]]:
    """Parse ``NAME=V1[,V2..]`` (values in the effect's parameter order) or
    ``NAME=param:V[,param:V..]`` into (effect, {param: value}).

    Values must lie inside the parameter's physical bounds.
    """
    name, sep, rest = spec.partition("=")
    effect = get_effect(name.strip())
    if not sep or not rest.strip():
        raise UsageError(f"{{opt:effects}} {spec!r}: give values as {effect.name}="
                         + ",".join(effect.param_names))
    items = [x.strip() for x in rest.split(",") if x.strip()]
    values: dict[str, float] = {}
    keyed = [":" in x for x in items]
    if any(keyed) and not all(keyed):
        raise UsageError(f"{{opt:effects}} {spec!r}: use either all positional or all param:value")
    if all(keyed):
        for item in items:
            k, _, v = item.partition(":")
            if k not in effect.param_names:
                raise UsageError(f"{{opt:effects}} {spec!r}: {effect.name} has no parameter {k!r}; "
                                 f"it has {', '.join(effect.param_names)}")
            values[k] = _number(spec, v)
    else:
        if len(items) != len(effect.params):
            raise UsageError(f"{{opt:effects}} {spec!r}: {effect.name} takes {len(effect.params)} "
                             f"value(s): {', '.join(effect.param_names)}")
        values = {p.name: _number(spec, v) for p, v in zip(effect.params, items, strict=True)}
    missing = [p for p in effect.param_names if p not in values]
    if missing:
        raise UsageError(f"{{opt:effects}} {spec!r}: missing {', '.join(missing)}")
    for p in effect.params:
        if not (p.lower <= values[p.name] <= p.upper):
            raise UsageError(f"{{opt:effects}} {spec!r}: {p.name}={values[p.name]} outside the "
                             f"physical range [{p.lower}, {p.upper}] {p.unit}")
    return effect, values


def _number(spec: str, text: str) -> float:
    try:
        return parse_number(text)
    except ValueError as exc:
        raise UsageError(f"{{opt:effects}} {spec!r}: {exc}") from None


#: What may name an effect wherever a model takes effects: an :class:`Effect`, its name
#: (the effect is fitted), ``"NAME=V1[,V2..]"`` or ``"NAME=param:V,.."`` (held at those
#: values), or a pair (Effect or name, {param: value}) (held).
EffectItem = "Effect | str | tuple[Effect | str, Mapping[str, float]]"


def resolve_effects(items: Iterable | None) -> tuple[tuple[Effect, ...], dict[str, float]]:
    """Effects and held values from the ways a user names them (:data:`EffectItem`).

    Parameters
    ----------
    items : iterable
        Each an :class:`Effect` or its name (fitted), a spec ``"NAME=V1[,V2..]"`` or
        ``"NAME=param:V,.."`` (see :func:`parse_effect_spec`), or a pair (effect or name,
        {param: value}) — the last two hold the effect's parameters at those values.

    Returns
    -------
    (tuple of Effect, dict)
        The effects in order, and {``effect.param``: value} of the held parameters (for
        :class:`armfit.models.arm.ClosedLoopModel`'s ``held``).

    Raises
    ------
    UsageError
        An unknown effect, a value outside its physical range, or an effect named twice.
    """
    effects: list[Effect] = []
    held: dict[str, float] = {}
    for item in items or ():
        values = None
        if isinstance(item, tuple) and len(item) == 2:
            item, values = item
        if isinstance(item, str) and "=" in item:
            effect, values = parse_effect_spec(item)
        elif isinstance(item, str):
            effect = get_effect(item.strip())
        elif isinstance(item, Effect):
            effect = item
        else:
            raise UsageError(f"{cell(item)} does not name an effect (give an Effect, its name, "
                             "or NAME=VALUES)")
        if any(e.name == effect.name for e in effects):
            raise UsageError(f"effect given twice: {effect.name}")
        effects.append(effect)
        if values is not None:
            for p in effect.params:
                if p.name not in values:
                    raise UsageError(f"{{opt:effects}} {effect.name}: give every parameter "
                                     f"to hold it ({', '.join(effect.param_names)})")
                v = _number(f"{effect.name}={values[p.name]}", values[p.name])
                if not (p.lower <= v <= p.upper):
                    raise UsageError(f"{{opt:effects}} {effect.name}: {p.name}={v:g} outside "
                                     f"the physical range [{p.lower:g}, {p.upper:g}] {p.unit}")
                held[f"{effect.name}.{p.name}"] = v
    return tuple(effects), held


def effects_by_axis(effects) -> dict[str, tuple[tuple[Effect, ...], dict[str, float]]]:
    """Per axis, the effects and held values of :func:`resolve_effects`.

    ``effects``: None or a sequence of :data:`EffectItem` (the same model on every axis),
    or a mapping {axis: sequence} (one model per axis; axes not named take the base
    model). Returns {axis: (effects, held)} for x, y and z.
    """
    from armfit.constants import AXES
    if isinstance(effects, Mapping):
        unknown = sorted(set(effects) - set(AXES))
        if unknown:
            raise UsageError(f"effects given for unknown axis {unknown[0]!r}; axes are "
                             f"{', '.join(AXES)}")
        return {a: resolve_effects(effects.get(a, ())) for a in AXES}
    same = resolve_effects(effects)
    return {a: same for a in AXES}


__all__ = [
    "TermFn", "RationalFn", "ENTRY_POINT_GROUP", "PROBE_HZ", "NULL_TOLERANCE",
    "RATIONAL_RTOL", "RATIONAL_ATOL", "Effect", "check_effect", "Origin",
    "EffectRegistry", "EFFECTS", "load_effect_file", "load_effect_files", "get_effect",
    "parse_effect_spec", "EffectItem", "resolve_effects", "effects_by_axis",
]
