"""The grammar every command shares: ``-v``/``-q`` anywhere on the line, old option
spellings kept as hidden aliases, output formats chosen by the file extension, and the
width of the terminal tables.

Imports only click and :mod:`armfit.errors` (rich on first use), so that the command
group (:mod:`armfit.cli.main`) can use it without loading what the subcommands need.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import click

from armfit.errors import UsageError

# ---------------------------------------------------------------------------
# -v / -q: before the subcommand or anywhere after it, with the same meaning
# ---------------------------------------------------------------------------

VERBOSE_HELP = "More messages on stderr (repeat for debug); tracebacks on errors."
QUIET_HELP = "Only errors on stderr (wins over -v)."


def apply_verbosity(obj: dict) -> int:
    """Set the ``verbosity`` of a command's shared ``ctx.obj`` from the ``-v`` count and
    ``-q`` given so far anywhere on the line (``-q`` wins: -1; else the count), and the
    level of armfit's log messages on stderr to match. Returns the verbosity."""
    verbosity = -1 if obj.get("quiet") else int(obj.get("verbose", 0))
    obj["verbosity"] = verbosity
    level = {-1: logging.ERROR, 0: logging.INFO}.get(verbosity, logging.DEBUG)
    logging.basicConfig(level=level, format="armfit: %(message)s", stream=sys.stderr,
                        force=True)
    logging.getLogger("armfit").setLevel(level)
    return verbosity


def _count_verbosity(ctx: click.Context, param: click.Parameter, value) -> None:
    obj = ctx.ensure_object(dict)
    if param.name == "quiet":
        obj["quiet"] = bool(obj.get("quiet")) or bool(value)
    else:
        obj["verbose"] = int(obj.get("verbose", 0)) + int(value or 0)
    apply_verbosity(obj)


def verbosity_options() -> list[click.Option]:
    """New ``-v/--verbose`` (a count) and ``-q/--quiet`` options. Each occurrence adds to
    the one level shared by the group and its subcommands (``ctx.obj``), so ``armfit -v
    estimate ...`` and ``armfit estimate ... -v`` mean the same; processed before the
    other options (eager), so that their messages already follow it."""
    return [
        click.Option(["-v", "--verbose"], count=True, is_eager=True, expose_value=False,
                     callback=_count_verbosity, help=VERBOSE_HELP),
        click.Option(["-q", "--quiet"], is_flag=True, is_eager=True, expose_value=False,
                     callback=_count_verbosity, help=QUIET_HELP),
    ]


def written_verbosity(args) -> int:
    """The verbosity ``-v``/``-q`` tokens of a command line give (up to a ``--``): -1
    with ``-q``/``--quiet``, else the number of v's of ``-v``, ``-vv``, ``--verbose``.
    Only for errors raised while the options are still being read."""
    count, quiet = 0, False
    for arg in args:
        if arg == "--":
            break
        if arg in ("-q", "--quiet"):
            quiet = True
        elif arg == "--verbose":
            count += 1
        elif len(arg) > 1 and arg[0] == "-" and set(arg[1:]) == {"v"}:
            count += len(arg) - 1
    return -1 if quiet else count


def add_verbosity_options(command: click.Command) -> click.Command:
    """``command`` with ``-v``/``-q`` among its options (once), and, for a group, every
    subcommand it holds too. Returns ``command``."""
    if not any(p.name == "verbose" for p in command.params):
        at = next((i for i, p in enumerate(command.params)
                   if isinstance(p, click.Option) and "--help" in p.opts), len(command.params))
        command.params[at:at] = verbosity_options()
    if isinstance(command, click.Group):
        for sub in command.commands.values():
            add_verbosity_options(sub)
    return command


# ---------------------------------------------------------------------------
# Renamed options: the old spelling still works for one release, hidden from --help
# ---------------------------------------------------------------------------

class OldSpelling(click.Option):
    """A hidden option that hands its value to the option named ``target`` (the new
    spelling ``new``), with a warning on stderr; both given is a usage error (exit 2).

    The value reaches the new option as the text given, so it is read (and refused) by
    the new option's own type.
    """

    def __init__(self, param_decls, *, target: str, new: str, **kwargs: Any):
        old = param_decls if isinstance(param_decls, str) else param_decls[0]
        super().__init__([old, f"_old_{target}"], hidden=True, expose_value=False,
                         **kwargs)
        self.target = target
        self.new = new
        self.old = old

    def handle_parse_result(self, ctx: click.Context, opts: Mapping[str, Any],
                            args: list[str]) -> tuple[Any, list[str]]:
        if self.name in opts:
            value = opts.pop(self.name)  # type: ignore[attr-defined]
            if self.target in opts:
                raise UsageError(f"{self.new} and {self.old} are one option ({self.old} "
                                 f"is its old spelling); give {self.new} once")
            opts[self.target] = value  # type: ignore[index]
            if (ctx.obj or {}).get("verbosity", 0) >= 0:
                click.echo(f"warning: {self.old} is now spelled {self.new}; the old "
                           "spelling will go in a later release", err=True)
        return None, args


def old_spelling(old: str, new: str, *, target: str | None = None, **kwargs: Any):
    """Decorator: accept ``old`` as a hidden alias of the option ``new`` (whose parameter
    name is ``target``, default ``new`` without dashes, ``-`` as ``_``). ``kwargs`` give
    the alias the shape of the new option (``multiple=True``, ``is_flag=True``)."""
    name = target or new.lstrip("-").replace("-", "_")
    return click.option(old, cls=OldSpelling, target=name, new=new, **kwargs)


# ---------------------------------------------------------------------------
# Output files: the format follows the extension; an extension not written is refused
# ---------------------------------------------------------------------------

def extension(path: str | os.PathLike) -> str:
    """The extension of ``path`` in lower case, with its dot (``''`` without one)."""
    return Path(path).suffix.lower()


class OutputFile(click.Path):
    """A file output whose extension must be one of ``formats`` ({extension: what is
    written}, e.g. ``{".csv": "CSV"}``): any other is a usage error (exit 2, one line
    naming the option, the extension and the extensions accepted), before anything is
    read or computed. The value stays the text given."""

    def __init__(self, formats: Mapping[str, str], **kwargs: Any):
        super().__init__(**kwargs)
        self.formats = dict(formats)

    def convert(self, value, param, ctx):
        value = super().convert(value, param, ctx)
        ext = extension(value)
        # an existing folder is left to the output check (exit 73: a file output never
        # replaces a folder)
        if ext not in self.formats and not os.path.isdir(value):
            flag = max(param.opts, key=len) if param is not None else "output"
            who = " ".join(ctx.command_path.split()[1:]) if ctx is not None else "armfit"
            exts = list(self.formats)
            accepted = ", ".join(exts[:-1]) + " or " + exts[-1] if len(exts) > 1 else exts[0]
            raise UsageError(f"{flag} {value}: {who or 'armfit'} writes {accepted}; "
                             + (f"not {ext}" if ext else "the name has no extension"))
        return value


#: The extensions of the file outputs: what each command writes, by kind.
CSV = {".csv": "CSV"}
LATEX = {".tex": "LaTeX"}
JSON = {".json": "JSON"}
FIGURE = {".png": "PNG, 300 dpi", ".svg": "SVG", ".pdf": "PDF"}


def output_metavar(formats: Mapping[str, str]) -> str:
    """``FILE.csv`` or ``FILE.parquet|.csv``: the metavar of a file output."""
    exts = list(formats)
    return "FILE" + exts[0] + "".join(f"|{e}" for e in exts[1:])


def file_output_option(*decls: str, formats: Mapping[str, str], help: str,
                       required: bool = False, metavar: str | None = None, **kwargs: Any):
    """A file output option (e.g. ``-o/--output`` or ``--latex``) that takes the
    extensions of ``formats`` only (:class:`OutputFile`); its metavar names them
    (:func:`output_metavar`) unless ``metavar`` is given."""
    return click.option(*decls, type=OutputFile(formats), required=required,
                        metavar=metavar or output_metavar(formats), default=None, help=help,
                        **kwargs)


# ---------------------------------------------------------------------------
# Terminal tables: as wide as the terminal; a fixed width when not a terminal
# ---------------------------------------------------------------------------

#: Width of the tables when the output is not a terminal (a pipe or a file) and COLUMNS
#: is not set: fixed, so that a piped output does not depend on the window it ran in.
PIPE_WIDTH = 120
#: The narrowest table drawn, whatever COLUMNS says.
MIN_WIDTH = 40


def table_width(stream=None) -> int:
    """Columns the tables of a command are drawn in: ``COLUMNS`` when it is set (a whole
    number), else the width of the terminal ``stream`` (default stdout) writes to, else
    :data:`PIPE_WIDTH`; at least :data:`MIN_WIDTH`."""
    stream = sys.stdout if stream is None else stream
    text = os.environ.get("COLUMNS", "").strip()
    if text.isascii() and text.isdigit() and int(text) > 0:
        return max(int(text), MIN_WIDTH)
    try:
        if stream.isatty():
            return max(os.get_terminal_size(stream.fileno()).columns, MIN_WIDTH)
    except (AttributeError, OSError, ValueError):
        pass
    return PIPE_WIDTH


def table_console(stderr: bool = False):
    """A rich console for tables on stdout (or stderr), :func:`table_width` wide; long
    lines are wrapped to that width."""
    from rich.console import Console
    return Console(soft_wrap=False, width=table_width(sys.stderr if stderr else sys.stdout),
                   stderr=stderr)


__all__ = [
    "VERBOSE_HELP", "QUIET_HELP", "apply_verbosity", "verbosity_options", "written_verbosity",
    "add_verbosity_options", "OldSpelling", "old_spelling", "extension", "OutputFile",
    "CSV", "LATEX", "JSON", "FIGURE",
    "output_metavar", "file_output_option", "PIPE_WIDTH", "MIN_WIDTH", "table_width",
    "table_console",
]
