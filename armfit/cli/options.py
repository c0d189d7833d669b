"""Options shared by several subcommands, defined once."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import click

from armfit.constants import AXES
from armfit.errors import UsageError
from armfit.io.numbers import parse_number, parse_whole
from armfit.io.schema import finite_or_none, json_default
from armfit.models.effects import EFFECTS, load_effect_files

_T = TypeVar("_T")

def _strict(value, parse, param, ctx, fail):
    """``value`` through armfit's one number parser when it is text (so an option
    reads numbers exactly as the files do: no digit separators, no other scripts'
    digits), else as given."""
    if not isinstance(value, str):
        return value
    try:
        return parse(value)
    except ValueError as exc:
        fail(str(exc), param, ctx)


def _signed_whole(text: str) -> int:
    body = text.strip()
    sign = -1 if body[:1] == "-" else 1
    return sign * parse_whole(body[1:] if body[:1] in "+-" else body)


def _range_text(lo, hi, lo_open: bool, hi_open: bool) -> str:
    """A range as --help shows it (``x>0``, ``0<=x<1``); empty when unbounded."""
    if lo is None and hi is None:
        return ""
    if lo is None:
        return f"x{'<' if hi_open else '<='}{hi:g}"
    if hi is None:
        return f"x{'>' if lo_open else '>='}{lo:g}"
    return f"{lo:g}{'<' if lo_open else '<='}x{'<' if hi_open else '<='}{hi:g}"


class Number(click.FloatRange):
    """A float option (optionally bounded, as :class:`click.FloatRange`) whose text is
    read by :func:`armfit.io.numbers.parse_number`."""

    name = "float"

    def convert(self, value, param, ctx):
        return super().convert(_strict(value, parse_number, param, ctx, self.fail),
                               param, ctx)

    def _describe_range(self) -> str:
        return _range_text(self.min, self.max, self.min_open, self.max_open)


class Whole(click.IntRange):
    """An integer option (optionally bounded, as :class:`click.IntRange`) whose text is
    ASCII digits with an optional sign (:func:`armfit.io.numbers.parse_whole`)."""

    name = "integer"

    def convert(self, value, param, ctx):
        return super().convert(_strict(value, _signed_whole, param, ctx, self.fail),
                               param, ctx)

    def _describe_range(self) -> str:
        return _range_text(self.min, self.max, self.min_open, self.max_open)


overwrite_option = click.option(
    "--overwrite", is_flag=True, help="Replace an existing output.")
json_option = click.option(
    "--json", "as_json", is_flag=True, help="Print a machine-readable summary on stdout.")
skip_bad_option = click.option(
    "--skip-bad", is_flag=True,
    help="Go on past bad trials, listing each with its reason (default: stop at the first).")
def _one_manifest(ctx, param, value):
    """The one ``--manifest`` given (None without): a second one is refused, not
    silently put in place of the first."""
    if len(value) > 1:
        raise click.BadParameter(f"given {len(value)} times ({', '.join(value)}); give one "
                                 "manifest (join the files into one CSV)", ctx, param)
    return value[0] if value else None


manifest_option = click.option(
    "--manifest", type=click.Path(dir_okay=False), multiple=True, callback=_one_manifest,
    help="CSV with columns file,subject,axis,grip_N[,run][,map]; paths relative to it. "
         "Once.")


def _one_map(ctx, param, value):
    """The one ``--map`` given (None without)."""
    if len(value) > 1:
        raise click.BadParameter(f"given {len(value)} times ({', '.join(value)}); give one "
                                 "map here, and a map per file in the manifest's column "
                                 "'map'", ctx, param)
    return value[0] if value else None


map_option = click.option(
    "--map", "column_map", type=click.Path(dir_okay=False), multiple=True,
    callback=_one_map, metavar="FILE",
    help="Column map (CSV quantity,source,unit[,gain][,lever_m][,sign][,value]) of every "
         "raw file without one in the manifest: which columns or MATLAB variables hold "
         "time, force and position, in which units. Once.")


def map_note(text: str) -> None:
    """A column map's conversions, on stderr as ``armfit: ...`` (silenced by -q)."""
    message(f"armfit: {text}")
jobs_option = click.option(
    "-j", "--jobs", type=Whole(1, 64), default=1, show_default=True, metavar="N",
    help="Worker processes.")
scheduler_option = click.option(
    "--scheduler", default=None, metavar="ADDRESS",
    help="Run the tasks on the dask cluster whose scheduler is at ADDRESS (e.g. "
         "tcp://host:8786) instead of --jobs worker processes; needs armfit[dask].")


@contextmanager
def cluster_executor(address: str | None) -> Iterator[Any]:
    """The executor of a ``dask.distributed`` client connected to the scheduler at
    ``address`` for the ``with`` block (closed at its end), or None without an address.
    Raises UsageError (exit 2, one line) when dask.distributed is not installed or the
    scheduler cannot be reached."""
    if address is None:
        yield None
        return
    try:
        from distributed import Client
    except ImportError:
        raise UsageError("--scheduler needs dask.distributed: pip install armfit[dask]"
                         ) from None
    try:
        client = Client(address)
    except (OSError, ValueError, TypeError) as exc:
        raise UsageError(f"--scheduler {address}: cannot reach the dask scheduler "
                         f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
                         ) from None
    with client:
        yield client.get_executor()
effect_option = click.option(
    "--effect", "effects", multiple=True, metavar="NAME=VALUES",
    help="Add a physical effect with its values: NAME=V1[,V2..] in parameter order "
         "or NAME=PARAM:V[,PARAM:V..], e.g. delay=0.012 (repeatable; see `armfit "
         "effects`).")

outside_loop_option = click.option(
    "--outside-loop", "outside_loop", multiple=True, metavar="EFFECT",
    help="An apparatus effect (stage output or device) the rendering loop does not see, "
         "e.g. a latency that only offsets the logs; repeatable.")

fit_effect_option = click.option(
    "--effect", "effects", multiple=True, metavar="[AXIS:]NAME[=VALUES]",
    help="Add a physical effect to the model, fitted (NAME) or held at given values "
         "(NAME=VALUES, e.g. delay=0.012); AXIS: on that axis only (e.g. z:delay). "
         "Repeatable; see `armfit effects`.")


def effect_items(values: Iterable[str]):
    """The fitters' ``effects`` from ``--effect`` values ``[AXIS:]NAME[=VALUES]``: a list
    of items for every axis, or {axis: items} when some value names an axis (items without
    one apply to every axis). Raises UsageError for an unknown effect or value."""
    from armfit.models.effects import effects_by_axis
    common: list[str] = []
    per_axis: dict[str, list[str]] = {}
    for text in values:
        t = text.strip()
        if len(t) > 2 and t[1] == ":" and t[0].lower() in AXES:
            per_axis.setdefault(t[0].lower(), []).append(t[2:].strip())
        else:
            common.append(t)
    items = {a: common + per_axis.get(a, []) for a in AXES} if per_axis else common
    effects_by_axis(items)      # every item checked here, with its message
    return items


# ---------------------------------------------------------------------------
# Bands: one grammar, LO:HI in Hz, optionally for one axis as AXIS=LO:HI
# ---------------------------------------------------------------------------

BAND_HELP = "LO:HI in Hz (0 < LO < HI)"


def parse_band(text: str, *, per_axis: bool = False, option: str = "--band"
               ) -> tuple[str | None, float, float]:
    """Parse one band: ``LO:HI`` (Hz), or with ``per_axis`` also ``AXIS=LO:HI``.

    Returns (axis or None, lo, hi). Raises UsageError naming ``option`` and the value
    unless 0 < LO < HI (finite) and AXIS is x, y or z.
    """
    axis, sep, rng = text.strip().partition("=")
    if not sep:
        axis, rng = None, text.strip()
    else:
        axis = axis.strip().lower()
    lo_s, colon, hi_s = rng.partition(":")
    try:
        lo, hi = parse_number(lo_s), parse_number(hi_s)
    except ValueError:
        lo = hi = float("nan")
    ok = colon and 0 < lo < hi < float("inf")
    if axis is not None and (not per_axis or axis not in AXES):
        ok = False
    if not ok:
        if per_axis and (axis is not None or not colon):
            raise UsageError(f"{option} {text!r}: expected AXIS=LO:HI or LO:HI in Hz with "
                             "AXIS x, y or z and 0 < LO < HI, e.g. z=0.1:10")
        raise UsageError(f"{option} {text!r}: expected LO:HI in Hz with 0 < LO < HI, "
                         "e.g. 0.1:30")
    return axis, lo, hi


def parse_bands(values, *, option: str = "--band") -> list[tuple[str | None, float, float]]:
    """Parse repeated and comma-separated ``[AXIS=]LO:HI`` items (see :func:`parse_band`)."""
    if isinstance(values, str):
        values = [values]
    return [parse_band(item, per_axis=True, option=option)
            for v in values or () for item in v.split(",") if item.strip()]


def band_spec(items) -> tuple[float, float] | dict[str, tuple[float, float]] | None:
    """The ``band`` of a command that takes one band per axis over the data's whole grid
    by default (compare, diagnose, fit-uncertainty), from parsed ``[AXIS=]LO:HI`` items:
    None without items, (lo, hi) when no item names an axis (the last wins), else
    {axis: (lo, hi)} (an item without an axis sets every axis, later items win; an axis
    not named keeps the command's default)."""
    items = list(items or ())
    if not items:
        return None
    if all(axis is None for axis, _, _ in items):
        return items[-1][1:]
    bands: dict[str, tuple[float, float]] = {}
    for axis, lo, hi in items:
        for a in ([axis] if axis else AXES):
            bands[a] = (lo, hi)
    return bands


BANDS_METAVAR = "[AXIS=]LO:HI[,...]"


def band_option(help_text: str):
    """``--band [AXIS=]LO:HI[,...]`` (repeatable) for a command whose default is the
    data's whole grid: the value is :func:`band_spec` of the items."""
    def convert(ctx, param, value):
        return band_spec(parse_bands(value))
    return click.option("--band", "band", metavar=BANDS_METAVAR, multiple=True,
                        callback=convert, help=help_text)


def axis_bands_option(help_text: str, *, multiple: bool = True):
    """``--band [AXIS=]LO:HI[,...]`` (repeatable): bands in Hz, each for one axis or for
    every axis; the value is a list of (axis or None, lo, hi), in the order given."""
    def convert(ctx, param, value):
        return parse_bands(value)
    return click.option("--band", "band", metavar=BANDS_METAVAR, multiple=multiple,
                        default=None, callback=convert, help=help_text)


def bands_by_axis(items, defaults) -> dict[str, tuple[float, float]]:
    """{axis: (lo, hi)}: ``defaults`` overridden by each item, in order (an item without
    an axis applies to every axis)."""
    bands = dict(defaults)
    for axis, lo, hi in items or ():
        for a in ([axis] if axis else list(bands)):
            bands[a] = (lo, hi)
    return bands


def clean(value):
    """A value for a JSON document: NaN and infinities as null."""
    return finite_or_none(value)

def _load_effect_files(ctx: click.Context, param: click.Parameter, value) -> tuple:
    """Register the effects of each ``--effects FILE`` for this command (they are removed
    again when the command ends, so one process can run several commands)."""
    paths = tuple(value or ())
    ctx.meta["armfit.effect_files"] = paths
    if paths:
        names = load_effect_files(paths)
        ctx.call_on_close(lambda: EFFECTS.unregister(names))
    return paths


effects_file_option = click.option(
    "--effects", "effect_files", multiple=True, metavar="FILE", is_eager=True,
    expose_value=False, callback=_load_effect_files,
    type=click.Path(dir_okay=False),
    help="Python file defining more effects in a module-level EFFECTS list (repeatable; "
         "see `armfit effects`). Loaded before the other options.")


def effect_files() -> tuple[str, ...]:
    """The ``--effects`` files given to the current command (empty if none)."""
    ctx = click.get_current_context(silent=True)
    return tuple(ctx.meta.get("armfit.effect_files", ())) if ctx is not None else ()


def verbosity() -> int:
    """The group's -v/-q level: -1 quiet, 0 normal, >0 verbose."""
    ctx = click.get_current_context(silent=True)
    while ctx is not None:
        if ctx.obj and "verbosity" in ctx.obj:
            return ctx.obj["verbosity"]
        ctx = ctx.parent
    return 0


def message(text: str) -> None:
    """A progress or status message on stderr (silenced by -q)."""
    if verbosity() >= 0:
        click.echo(text, err=True)


def emit_json(obj: Any) -> None:
    """Write ``obj`` as JSON on stdout."""
    click.echo(json.dumps(obj, indent=2, sort_keys=False, default=json_default))


@contextmanager
def progress(total: int, description: str) -> Iterator[Any]:
    """A rich progress bar on stderr when stderr is a terminal (and not -q); else silent.

    Yields an ``advance()`` callable.
    """
    if verbosity() < 0 or not sys.stderr.isatty():
        yield lambda n=1: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn
    with Progress("[progress.description]{task.description}", BarColumn(),
                  MofNCompleteColumn(), TimeElapsedColumn(),
                  console=Console(stderr=True), transient=True) as bar:
        task = bar.add_task(description, total=total)
        yield lambda n=1: bar.advance(task, n)


def iterate(items: Iterable[_T], total: int, description: str) -> Iterator[_T]:
    """Iterate with a progress bar (see :func:`progress`)."""
    with progress(total, description) as advance:
        for item in items:
            yield item
            advance()


__all__ = [
    "Number", "Whole",
    "overwrite_option", "json_option", "skip_bad_option",
    "manifest_option", "map_option", "map_note", "jobs_option", "scheduler_option",
    "cluster_executor",
    "effect_option", "outside_loop_option", "fit_effect_option", "effect_items",
    "BAND_HELP", "parse_band", "parse_bands", "band_spec", "BANDS_METAVAR", "band_option",
    "axis_bands_option",
    "bands_by_axis", "clean", "effects_file_option", "effect_files", "verbosity",
    "message", "emit_json", "progress", "iterate",
]
