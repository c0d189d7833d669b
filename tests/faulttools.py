"""Helpers of the fault tests: the installed command, the temporaries it leaves, and the
processes it starts (followed through /proc, Linux)."""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path

import pytest

#: The installed command line, beside the interpreter that runs the tests.
ARMFIT = str(Path(sys.executable).with_name("armfit"))
#: An armfit temporary or set-aside name (:func:`armfit.io.atomic.temp_name`).
TEMP = re.compile(r"^\..*\.\d+\.[0-9a-f]{8}\.(tmp|old)$")

#: Tests that follow child processes through /proc.
needs_proc = pytest.mark.skipif(not Path("/proc/self/task").exists(),
                                reason="needs /proc to follow child processes")


def descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (children, their children, ...)."""
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        try:
            kids = Path(f"/proc/{p}/task/{p}/children").read_text().split()
        except OSError:
            kids = []
        out |= {int(k) for k in kids}
        todo += [int(k) for k in kids]
    return out


def running(pid: int) -> bool:
    """``pid`` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def wait_for(pred, timeout: float = 60.0, step: float = 0.002) -> bool:
    """Poll ``pred`` until it is true (True) or ``timeout`` seconds pass (False)."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return True
        time.sleep(step)
    return False


def temps(folder: Path) -> list[str]:
    """armfit temporaries (and set-aside folders) in ``folder``."""
    return sorted(p.name for p in Path(folder).iterdir() if TEMP.match(p.name))
