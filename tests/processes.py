"""Following the processes a command starts, through /proc (Linux): shared by the fault
tests of signals and workers."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

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
