"""``armfit --help`` lists the commands from the registry of armfit.cli.main, without
importing any command module."""

from __future__ import annotations

import json
import subprocess
import sys

import click
import pytest

from armfit.cli.main import COMMANDS, cli


def test_help_lists_every_command_without_importing_them():
    # a fresh interpreter: the modules loaded by `armfit --help` (sys.modules after it)
    code = ("import sys, json\nfrom armfit.cli.main import cli\n"
            "try:\n    cli(['--help'], prog_name='armfit')\nexcept SystemExit:\n    pass\n"
            "print(json.dumps(sorted(sys.modules)), file=sys.stderr)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    loaded = set(json.loads(res.stderr.strip().splitlines()[-1]))
    command_modules = {target.split(":")[0] for target, _ in COMMANDS.values()}
    assert not loaded & command_modules, sorted(loaded & command_modules)
    # nor the numerical stack those modules need
    assert not loaded & {"numpy", "pandas", "scipy", "pyarrow", "matplotlib"}
    listed = res.stdout.split("Commands:")[1]
    for name, (_, summary) in COMMANDS.items():
        assert f"  {name} " in listed and summary in " ".join(listed.split()), name


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_a_loaded_command_shows_the_registry_summary(name):
    # the summary is the command's short help once it is imported (`armfit plot --help`
    # lists its own subcommands from their docstrings; this is the group's list)
    cmd = cli.get_command(click.Context(cli), name)
    assert cmd is not None and cmd.get_short_help_str() == COMMANDS[name][1]


def test_every_summary_fits_one_line_of_an_80_column_help():
    # click's definition list: 2 spaces, the longest name, 2 spaces, the text
    room = 80 - 2 - max(map(len, COMMANDS)) - 2
    assert all(len(summary) <= room for _, summary in COMMANDS.values())
