"""Memory armfit has freed, given back to the system.

A long process (``armfit run``) frees much memory at times: every trial's responses once
the spectra file is written, a stage's trial rows once the stage is done. Two allocators
keep such memory for themselves: Arrow's pool (mimalloc) keeps the buffers it freed, and
the GNU C library's ``malloc`` keeps the pages of small blocks freed amid others until
``malloc_trim`` returns them. Without asking them, a process stays at the largest size
any of its stages needed. :func:`release_memory` asks both; with another C library only
Arrow's pool is emptied.
"""

from __future__ import annotations

import ctypes
import functools

from armfit._lazy import loaded

__all__ = ["release_memory", "release_memory_after_task"]


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    """The GNU C library's ``malloc_trim``, or None elsewhere."""
    try:
        return ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError, TypeError):   # another C library, or no such call
        return None


def release_memory() -> None:
    """Give the memory freed so far back to the system: Arrow's unused buffers (when
    pyarrow is loaded) and the C library's free pages (``malloc_trim(0)``, GNU C library
    only). Safe from any thread; it changes no value held."""
    pa = loaded("pyarrow")
    if pa is not None:
        pa.default_memory_pool().release_unused()
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def release_memory_after_task() -> None:
    """:func:`release_memory` once the task now running has ended, in a pool's worker
    (:func:`armfit._pool.after_task`): then the memory of the task's result, pickled
    after the task function returns, and of its arguments, let go after the result is
    sent, is given back too. A worker of the diagnosis of 4,050 trials otherwise kept
    11 MB of the last task's arrays freed (57 MB against 46 MB). Elsewhere (a task run
    in the calling process) the memory is given back now."""
    pool = loaded("armfit._pool")
    if pool is None or not pool.after_task(release_memory):
        release_memory()
