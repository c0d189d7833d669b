"""Domain exceptions and the exit codes the command line maps them to.

Every exception a user can cause subclasses :class:`ArmfitError` (itself a ValueError).
The CLI prints ``str(exc)`` as one line on stderr and exits with ``exc.exit_code``.

Exit codes (documented in docs/cli.md, "Conventions"):

==== =========================================================
0    success
1    internal error (a bug: please report it with ``-v`` output)
2    usage error: bad option, bad combination of options
3    a fit did not converge (no numbers are printed or written)
65   bad input data (file content breaks the data contract)
66   input not found, or nothing to read
73   output cannot be written: it exists without --overwrite, it is (or would be
     picked up as) an input, or the system refused the write (the message gives
     the path and the OS reason: no space, permission, not a folder, ...); also
     standard output closed, full or a broken pipe ("standard output: ...")
130  interrupted (SIGINT, Ctrl-C): workers stopped, partial outputs removed
143  terminated (SIGTERM): workers stopped, partial outputs removed
==== =========================================================

The same fault gives the same code on every command.
"""

from __future__ import annotations

import re
from collections.abc import Callable

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_USAGE = 2
EXIT_NOT_CONVERGED = 3
EXIT_DATAERR = 65
EXIT_NOINPUT = 66
EXIT_CANTCREAT = 73
EXIT_INTERRUPTED = 130
EXIT_TERMINATED = 143


class ArmfitError(ValueError):
    """Base class of every error a user's input or options can cause.

    Messages name options by their Python spelling, never by a command-line flag: the
    text may hold ``{opt}``, filled with ``option`` (e.g. ``overwrite=True`` or
    ``method=``), and ``{opt:NAME}``, filled with the bare parameter name NAME. The
    command line shows the same message with each option's flag instead
    (:meth:`render`), and a command that has no such option names none: a part of the
    message written ``{?...}`` (e.g. ``{?; lower {opt:fmin}}``) is left out when an
    option in it cannot be named.
    """

    exit_code = EXIT_INTERNAL
    #: The trials left out (``skip_bad``) before this error ended the work, each as
    #: (file, reason): the command line lists them, one line each, before the error.
    skipped: tuple[tuple[str, str], ...] = ()

    def __init__(self, message: str = "", *, option: str | None = None):
        self.template = message
        self.option = option
        super().__init__(self.render(lambda name, python: python))

    @property
    def option_name(self) -> str | None:
        """The main option's parameter name (``option`` up to any ``=``), or None."""
        return None if self.option is None else self.option.split("=", 1)[0]

    def render(self, spell: Callable[[str, str], str | None]) -> str:
        """The message with every option written as ``spell(name, python_spelling)``.

        ``spell`` returns None for an option that cannot be named (a command without
        it): a ``{?...}`` part holding it is left out; elsewhere the option's Python
        name is written bare (never a flag the command lacks)."""
        def fill(m: re.Match) -> str:
            if m.group(1) is None:          # {opt}
                if self.option is None:
                    return m.group(0)
                return spell(self.option_name, self.option) or self.option_name
            return spell(m.group(1), m.group(1)) or m.group(1)

        def clause(m: re.Match) -> str:
            names = [(n, n) if n else (self.option_name, self.option)
                     for n in re.findall(_OPT, m.group(1))]
            if any(p is None or spell(n, p) is None for n, p in names):
                return ""
            return re.sub(_OPT, fill, m.group(1))

        text = re.sub(_CLAUSE, clause, self.template)
        return re.sub(_OPT, fill, text)

    def with_option(self, spelling: str) -> str:
        """The message with the main option written as ``spelling`` (e.g. a flag)."""
        return self.render(lambda name, python: spelling if name == self.option_name
                           else python)


#: ``{opt}`` or ``{opt:NAME}`` in a message; a ``{?...}`` part of a message.
_OPT = r"\{opt(?::([A-Za-z_][A-Za-z0-9_]*))?\}"
_CLAUSE = r"\{\?((?:[^{}]|\{opt(?::[A-Za-z_][A-Za-z0-9_]*)?\})*)\}"


class UsageError(ArmfitError):
    """Options that do not fit together or are out of range."""

    exit_code = EXIT_USAGE


class BadInputError(ArmfitError):
    """Input data that breaks the data contract.

    The message names the file, the column and the row (1-based data row, header not
    counted) where they apply, then what was expected and what to do.
    """

    exit_code = EXIT_DATAERR

    def __init__(self, message: str, *, file: str | None = None, column: str | None = None,
                 row: int | None = None, reason: str | None = None,
                 option: str | None = None):
        self.file = file
        self.column = column
        self.row = row
        self.reason = reason or message
        where = []
        if file is not None:
            where.append(str(file))
        if column is not None:
            where.append(f"column '{column}'")
        if row is not None:
            where.append(f"row {row}")
        prefix = ": ".join([", ".join(where)]) + ": " if where else ""
        super().__init__(prefix + message, option=option)

    @property
    def detail(self) -> str:
        """The message without its leading file name (column, row and what is wrong): the
        reason a skipped trial is listed with. It names no option (a ``{?...}`` part of
        the message is left out), since it is read apart from the command that runs."""
        text = self.render(lambda name, python: None)
        if self.file and text.startswith(self.file):
            text = text[len(self.file):].lstrip(",: ")
        return text


class NoInputError(ArmfitError):
    """An input path does not exist, or a search found nothing to read."""

    exit_code = EXIT_NOINPUT


class OutputError(ArmfitError):
    """An output exists (and overwriting was not asked for), or would overwrite an input."""

    exit_code = EXIT_CANTCREAT


class ConvergenceError(ArmfitError):
    """An optimiser did not converge; no result is reported."""

    exit_code = EXIT_NOT_CONVERGED


class EffectDefinitionError(BadInputError):
    """A user-defined effect (or its parameters) that breaks the effect contract of
    :mod:`armfit.models.effects`: the message names the file or entry point that defined
    it and what is wrong (exit 65, as any other input whose content is bad)."""


class Terminated(KeyboardInterrupt):
    """SIGTERM received: unwinds like Ctrl-C (partial outputs removed), exit 143."""

    exit_code = EXIT_TERMINATED


#: Longest cell text echoed in a message; longer cells are cut (with "…").
CELL_CHARS = 80


def cell(value, limit: int = CELL_CHARS) -> str:
    """A data cell as a message shows it: numbers as plain numbers (never
    ``np.float64(...)``), text quoted and cut at ``limit`` characters."""
    import math
    import numbers
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        x = float(value)
        return repr(x) if math.isfinite(x) else str(x)
    text = "" if value is None else str(value)
    if len(text) > limit:
        text = text[:limit] + f"… ({len(text)} characters)"
    return repr(text) if len(text) <= limit else "'" + text + "'"


__all__ = [
    "EXIT_OK", "EXIT_INTERNAL", "EXIT_USAGE", "EXIT_NOT_CONVERGED", "EXIT_DATAERR",
    "EXIT_NOINPUT", "EXIT_CANTCREAT", "EXIT_INTERRUPTED", "EXIT_TERMINATED",
    "ArmfitError", "UsageError", "BadInputError", "NoInputError", "OutputError",
    "ConvergenceError", "EffectDefinitionError", "Terminated", "CELL_CHARS", "cell",
]
