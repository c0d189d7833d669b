"""The ``armfit`` command group: global options, error handling, subcommand registry.

Data and ``--json`` go to stdout; progress, messages and errors go to stderr. A user's
mistake (any :class:`armfit.errors.ArmfitError`) is one line on stderr and its exit code;
the traceback is shown only with ``-v``.
"""

from __future__ import annotations

import importlib
import logging
import sys
import traceback

import click

from armfit._version import __version__
from armfit.cli.entry import stop_line, wrapped_stop
from armfit.cli.grammar import (
    add_verbosity_options,
    apply_verbosity,
    verbosity_options,
    written_verbosity,
)
from armfit.cli.messages import cli_message
from armfit.errors import EXIT_INTERNAL, ArmfitError
from armfit.workers import POOL_PRELOAD, RUN_FIGURES_PRELOAD, start_fork_server, stop_workers

log = logging.getLogger("armfit")


class ArmfitGroup(click.Group):
    """A group that turns domain errors into one stderr line and a documented exit code.

    Subcommands listed in :attr:`lazy` are imported when first used, so that a command
    starts without importing what only the others need (matplotlib, the fitting stack).
    """

    #: Subcommands imported on first use: name -> "module:attribute".
    lazy: dict[str, str] = {}
    #: One-line summaries of the subcommands, listed by ``--help`` without importing them.
    summaries: dict[str, str] = {}
    #: Subcommands that run their tasks on ``--jobs`` worker processes: name -> what
    #: their pool preloads (:data:`armfit.workers.POOL_PRELOAD`; ``()``: every engine
    #: module, ``run``'s one pool serving every stage).
    pools: dict[str, tuple[str, ...]] = {}

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *self.lazy})

    def get_command(self, ctx: click.Context, cmd_name: str):
        cmd = super().get_command(ctx, cmd_name)
        if cmd is None and cmd_name in self.lazy:
            module, attr = self.lazy[cmd_name].split(":")
            cmd = getattr(importlib.import_module(module), attr)
            if cmd_name in self.summaries:
                cmd.short_help = self.summaries[cmd_name]
            self.add_command(add_verbosity_options(cmd), cmd_name)
        return cmd

    def resolve_command(self, ctx: click.Context, args: list[str]):
        # a command asked for worker processes: their fork server starts now, and imports
        # what they run while this process imports the command's modules
        if args and args[0] in self.pools and not ctx.resilient_parsing \
                and wants_workers(args[1:]):
            start_fork_server(pool_preload(args[0], args[1:], self.pools[args[0]]))
        return super().resolve_command(ctx, args)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The command list of ``--help``, from :attr:`summaries`: no command module is
        imported to list the commands."""
        rows = [(name, self.summaries.get(name) or
                 self.get_command(ctx, name).get_short_help_str(formatter.width))
                for name in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        # -v/-q as written anywhere on the line, for an error raised while the options are
        # read, before the subcommand's own -v is processed (after an eager --effects)
        ctx.meta["armfit.verbosity_written"] = written_verbosity(args)
        return super().parse_args(ctx, args)

    def make_context(self, info_name, args, parent=None, **extra) -> click.Context:
        # a signal while the group's options are parsed: the same line and code as in a
        # subcommand (click would print "Aborted!" and exit 1)
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except KeyboardInterrupt as exc:
            stop_workers()
            sys.exit(stop_line(exc))

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except ArmfitError as exc:
            _report(ctx, exc)
            ctx.exit(exc.exit_code)
        except KeyboardInterrupt as exc:  # SIGINT, or SIGTERM (Terminated)
            stop_workers()
            ctx.exit(stop_line(exc))
        except (click.exceptions.Exit, click.exceptions.Abort, click.ClickException):
            raise
        except Exception as exc:  # a bug: say so in one line, traceback with -v
            stop = wrapped_stop(exc)  # a signal Python wrapped (a lazy import's class)
            if stop is not None:
                stop_workers()
                ctx.exit(stop_line(stop))
            _report(ctx, exc, internal=True)
            ctx.exit(EXIT_INTERNAL)


def requested_jobs(args: list[str]) -> int | None:
    """The value of the last ``-j``/``--jobs`` option of a subcommand's raw arguments
    (``-j N``, ``-jN``, ``--jobs N``, ``--jobs=N``; up to ``--``), read before the command
    is loaded; None when absent or not a whole number (the command's own parsing then
    reports it)."""
    jobs = None
    it = iter(args)
    for a in it:
        if a == "--":
            break
        if a in ("-j", "--jobs"):
            value = next(it, None)
        elif a.startswith("--jobs="):
            value = a[len("--jobs="):]
        elif a.startswith("-j") and not a.startswith("--"):
            value = a[2:]
        else:
            continue
        try:
            jobs = int(value)
        except (TypeError, ValueError):
            return None
    return jobs


def wants_workers(args: list[str]) -> bool:
    """Whether a subcommand's raw arguments ask for worker processes on this machine:
    ``--jobs`` N > 1 (:func:`requested_jobs`), neither ``--help`` nor ``--scheduler``
    (a dask cluster's workers instead)."""
    jobs = requested_jobs(args)
    return jobs is not None and jobs > 1 and not any(
        a in ("-h", "--help") or a.startswith("--scheduler") for a in args)


def pool_preload(name: str, args: list[str], preload: tuple[str, ...]) -> tuple[str, ...]:
    """What the fork server of subcommand ``name`` imports, given its raw arguments:
    ``preload`` (its pool's), except for a ``run`` that draws figures (no
    ``--no-figures`` before ``--``), whose workers draw them:
    :data:`armfit.workers.RUN_FIGURES_PRELOAD`."""
    if name == "run":
        own = args[:args.index("--")] if "--" in args else args
        if "--no-figures" not in own:
            return RUN_FIGURES_PRELOAD
    return preload


def _report(ctx: click.Context, exc: BaseException, internal: bool = False) -> None:
    verbosity = (ctx.obj or {}).get("verbosity", 0)
    written = ctx.meta.get("armfit.verbosity_written", 0)
    verbosity = -1 if written < 0 else max(verbosity, written)
    verbose = verbosity > 0
    if verbosity >= 0:  # the trials --skip-bad left out before the error, each with why
        for file, reason in getattr(exc, "skipped", ()):
            click.echo(f"skipped {file}: {reason}", err=True)
    if verbose:
        traceback.print_exception(type(exc), exc, exc.__traceback__, file=sys.stderr)
    # the command that raised names the options by its own flags, and none it lacks
    text = cli_message(exc, _raising_command(ctx, exc)) if isinstance(exc, ArmfitError) \
        else str(exc)
    msg = text.splitlines()[0] if text else type(exc).__name__
    if internal:
        msg = f"internal error ({type(exc).__name__}): {msg}" + (
            "" if verbose else " (run with -v for the traceback)")
    click.echo(f"armfit: error: {msg}", err=True)


def _raising_command(ctx: click.Context, exc: BaseException) -> click.Command | None:
    """The innermost command running when ``exc`` was raised (``plot bode``'s ``bode``):
    the last context on the traceback, else the group's subcommand."""
    found = None
    tb = exc.__traceback__
    while tb is not None:
        local = tb.tb_frame.f_locals.get("ctx")
        if isinstance(local, click.Context) and local.command is not None:
            found = local.command
        tb = tb.tb_next
    if found is not None and found is not ctx.command:
        return found
    name = ctx.invoked_subcommand
    return ctx.command.get_command(ctx, name) \
        if name and isinstance(ctx.command, click.Group) else None


def _with_verbosity(f):
    """The group's ``-v``/``-q`` (the same options every subcommand gets)."""
    f.__click_params__ = [*getattr(f, "__click_params__", []), *verbosity_options()[::-1]]
    return f


@click.group(cls=ArmfitGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="armfit")
@_with_verbosity
@click.pass_context
def cli(ctx: click.Context) -> None:
    """armfit — human arm and hand dynamics and variability models from stylus
    haptic-device trials (the method of Fu & Çavuşoğlu, ICRA 2010).

    -v and -q work before the command or anywhere after it.

    Exit codes (the same on every command): 0 success, 1 internal error (a bug),
    2 usage error, 3 fit did not converge, 65 bad input data, 66 input not found or
    unreadable, 73 output exists, is an input, or cannot be written (path and OS reason
    given), 130 interrupted (SIGINT), 143 terminated (SIGTERM).
    """
    apply_verbosity(ctx.ensure_object(dict))


#: The subcommands: name -> ("module:attribute", one-line summary). The summary is what
#: ``armfit --help`` lists (without importing any command module) and the command's own
#: ``short_help`` once it is loaded.
COMMANDS: dict[str, tuple[str, str]] = {
    "ingest": ("armfit.cli.ingest:command",
               "Read raw trial files into one canonical dataset."),
    "estimate": ("armfit.cli.estimate:command",
                 "Frequency responses of every trial, their mean and median."),
    "fit-grip": ("armfit.cli.fit:fit_grip_command",
                 "Fit the arm model to each axis x grip mean (Table I)."),
    "fit-nominal": ("armfit.cli.fit:fit_nominal_command",
                    "Fit the arm model to each axis median (Table II)."),
    "fit-trials": ("armfit.cli.stability:fit_trials_command",
                   "Fit the arm model to every trial."),
    "fit-uncertainty": ("armfit.cli.fit_uncertainty:command",
                        "Fit the uncertainty weight Wu per axis (Table III)."),
    "effects": ("armfit.cli.diagnose:effects_command",
                "List the physical effects the 5-parameter model lacks."),
    "compare": ("armfit.cli.diagnose:compare_command",
                "Compare a fitted model with the measurements."),
    "diagnose": ("armfit.cli.diagnose:diagnose_command",
                 "Find the physical effects the model is missing, per axis."),
    "stability": ("armfit.cli.stability:stability_command",
                  "K_max: the stiffest virtual wall rendered stably."),
    "export": ("armfit.cli.export:command",
               "Export fitted models and weights for MATLAB, Octave or JSON."),
    "plot": ("armfit.cli.plot:command",
             "Draw a figure of the paper or of a diagnosis."),
    "simulate": ("armfit.cli.simulate:command",
                 "Simulate a study of the paper's protocol with known truth."),
    "run": ("armfit.cli.run:command",
            "Every stage on raw trials: tables, figures, report."),
}


#: The subcommands with ``--jobs``: name -> the kind of their pool (None: ``run``'s).
POOLS: dict[str, str | None] = {
    "estimate": "estimate", "fit-trials": "fit", "fit-uncertainty": "uncertainty",
    "diagnose": "diagnosis", "run": None,
}


def _register() -> None:
    ArmfitGroup.lazy.update({name: target for name, (target, _) in COMMANDS.items()})
    ArmfitGroup.summaries.update({name: text for name, (_, text) in COMMANDS.items()})
    ArmfitGroup.pools.update({name: POOL_PRELOAD[kind] if kind else ()
                              for name, kind in POOLS.items()})


_register()


__all__ = [
    "log", "ArmfitGroup", "COMMANDS", "POOLS", "cli", "pool_preload", "requested_jobs",
    "wants_workers",
]
