"""Options shared by several subcommands, defined once."""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import click

from armfit.io.artifacts import json_default

T = TypeVar("T")

output_option = click.option(
    "-o", "--output", "output", required=True, type=click.Path(dir_okay=True),
    help="Output path (written atomically).")
overwrite_option = click.option(
    "--overwrite", is_flag=True, help="Replace an existing output.")
json_option = click.option(
    "--json", "as_json", is_flag=True, help="Print a machine-readable summary on stdout.")
skip_bad_option = click.option(
    "--skip-bad", is_flag=True,
    help="Go on past bad trials, listing each with its reason (default: stop at the first).")
manifest_option = click.option(
    "--manifest", type=click.Path(dir_okay=False),
    help="CSV with columns file,subject,axis,grip_N[,run]; paths relative to it.")
jobs_option = click.option(
    "-j", "--jobs", type=click.IntRange(1, 64), default=1, show_default=True,
    help="Worker processes.")
effect_option = click.option(
    "--effect", "effects", multiple=True, metavar="NAME",
    help="Add a physical effect to the model (repeatable; see `armfit effects`).")



def _load_effect_files(ctx: click.Context, param: click.Parameter, value) -> tuple:
    """Register the effects of each ``--effects FILE`` for this command (they are removed
    again when the command ends, so one process can run several commands)."""
    paths = tuple(value or ())
    ctx.meta["armfit.effect_files"] = paths
    if paths:
        from armfit.models.effects import EFFECTS, load_effect_files
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


def iterate(items: Iterable[T], total: int, description: str) -> Iterator[T]:
    """Iterate with a progress bar (see :func:`progress`)."""
    with progress(total, description) as advance:
        for item in items:
            yield item
            advance()
