"""Library messages shown on the command line: each option named by its flag.

Library errors name options by their Python spelling (:class:`armfit.errors.ArmfitError`);
:func:`cli_message` writes the same message with the flags of the command that is
running, and names no option that command does not have. Kept apart from
:mod:`armfit.cli.options` so that the group can report errors without importing what the
subcommands need.
"""

from __future__ import annotations

import click

from armfit.errors import ArmfitError

#: The flag of each library option named in an error message (see
#: :meth:`armfit.errors.ArmfitError.render`); where commands spell it differently, every
#: spelling.
OPTION_FLAGS: dict[str, str | tuple[str, ...]] = {
    "overwrite": "--overwrite", "method": "--method", "n_boot": "--bootstrap",
    "level": "--level", "fmin": "--fmin", "fmax": "--fmax", "nperseg": "--nperseg",
    "n_pairs": "--order", "order": "--order", "band": "--band", "effects": "--effect",
    "smooth_oct": "--smooth", "grips_N": "--grips", "duration_s": "--duration",
    "noise_m": "--noise", "drift_m": "--drift", "quantum_m": "--quantum",
    "sample_time_s": "--sample-time", "damping_Ns_per_m": "--damping",
    "delay_samples": "--delay-samples", "effect_files": "--effects",
    "outside_loop": "--outside-loop", "members": "--members",
    "manifest": "--manifest", "skip_bad": "--skip-bad", "resample": "--resample",
    "column_map": "--map",
    "f_min_hz": "--fmin",
}


def _spellings(name: str) -> tuple[str, ...]:
    known = OPTION_FLAGS.get(name, f"--{name.replace('_', '-')}")
    return (known,) if isinstance(known, str) else known


def _running() -> list[click.Command]:
    """The commands of the current click context, innermost first."""
    out = []
    ctx = click.get_current_context(silent=True)
    while ctx is not None:
        if ctx.command is not None:
            out.append(ctx.command)
        ctx = ctx.parent
    return out


def flag(name: str, command: click.Command | None = None) -> str | None:
    """The command-line flag of the library option ``name``.

    Parameters
    ----------
    name : str
        The option's Python name (e.g. ``f_min_hz``).
    command : click.Command, optional
        The command whose flags to use; default: the commands of the current click
        context.

    Returns
    -------
    str or None
        The command's own spelling (of those listed for ``name``), None when it has no
        such option (``run`` has no ``--fmin``); outside any command, the usual flag.
    """
    spellings = _spellings(name)
    commands = [command] if command is not None else _running()
    if not commands:
        return spellings[0]
    for cmd in commands:
        opts = {o for p in cmd.params for o in getattr(p, "opts", ())}
        for spelled in spellings:
            if spelled in opts:
                return spelled
    return None


def cli_message(exc: ArmfitError, command: click.Command | None = None) -> str:
    """The message of ``exc`` with every option named by the flag of ``command`` (default:
    the command running); an option it lacks is not named (see
    :meth:`armfit.errors.ArmfitError.render`)."""
    return exc.render(lambda name, python: flag(name, command))


__all__ = ["OPTION_FLAGS", "cli_message", "flag"]
