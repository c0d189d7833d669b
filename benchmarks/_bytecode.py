"""armfit's bytecode, compiled before a benchmark times armfit's commands.

An installed package has its bytecode written at install time; armfit installed in
editable mode (``make demo``) has it written by Python at first import, except where
that is turned off (``PYTHONDONTWRITEBYTECODE``, ``python -B``, a read-only tree): then
every ``armfit`` process, and every worker, compiles each module it imports from source
again, about half a second for a command's modules, and a module edited since the last
compilation alone costs 5-20 ms at every start. The timings would then measure the
compiler. ``make bench`` compiles first (``make compile``); a benchmark script run on its
own calls :func:`compile_armfit` first, which rewrites only the stale files.
"""

from __future__ import annotations

import compileall
import importlib.util
import os
from pathlib import Path


def compile_armfit() -> Path:
    """Compile the bytecode of every module of the armfit package that is imported (its
    source folder), where missing or older than its source; returns the folder."""
    spec = importlib.util.find_spec("armfit")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("armfit is not importable: run `make demo` first")
    folder = Path(next(iter(spec.submodule_search_locations)))
    if not compileall.compile_dir(str(folder), quiet=1):
        raise SystemExit(f"armfit's modules in {folder} do not compile")
    return folder


def start() -> None:
    """What a timing benchmark does first: :func:`compile_armfit`, then print the load
    average and the number of cores it runs with."""
    compile_armfit()    # stale bytecode would be timed too
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores")
