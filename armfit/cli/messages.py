"""Library messages shown on the command line: each option named by its flag.

Library errors name options by their Python spelling (:class:`armfit.errors.ArmfitError`);
:func:`cli_message` writes the same message with the command line's flags. Kept apart
from :mod:`armfit.cli.options` so that the group can report errors without importing
what the subcommands need.
"""

from __future__ import annotations

import click

from armfit.errors import ArmfitError

#: The flag of each library option named in an error message (see
#: :meth:`armfit.errors.ArmfitError.render`).
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
    "f_min_hz": ("--f-min", "--fmin"),
}


def flag(name: str) -> str:
    """The command-line flag of the library option ``name`` (where commands spell it
    differently, the spelling of the command running)."""
    known = OPTION_FLAGS.get(name, f"--{name.replace('_', '-')}")
    if isinstance(known, str):
        return known
    ctx = click.get_current_context(silent=True)
    while ctx is not None and ctx.command is not None:
        opts = {o for p in ctx.command.params for o in getattr(p, "opts", ())}
        for spelled in known:
            if spelled in opts:
                return spelled
        ctx = ctx.parent
    return known[0]


def cli_message(exc: ArmfitError) -> str:
    """The message of ``exc`` with every option named by its command-line flag."""
    return exc.render(lambda name, python: flag(name))


__all__ = ["OPTION_FLAGS", "cli_message", "flag"]
