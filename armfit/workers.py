"""Worker processes: one way to start a pool, one way to stop every worker at once.

Pools fork their workers at once when the caller has no other thread (they inherit the
modules already imported), else use the ``forkserver`` start method where there is one
(safe when the caller has threads of its own), else ``spawn``. Within
:func:`shared_pool` (``armfit run``) every stage borrows one pool instead, forked once at
the start, before the caller has threads, so nothing is started or imported again per
stage. Workers ignore SIGINT: Ctrl-C at a terminal reaches the whole process group, and
only the main process decides what happens (it stops the workers with
:func:`stop_workers` and removes its partial outputs), so no worker prints a traceback
of its own.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading


def ignore_sigint() -> None:
    """Pool initializer: a worker leaves SIGINT to the main process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


#: The pool of :func:`shared_pool` while one is open.
_SHARED = None


class _Borrowed:
    """The shared pool as a stage sees it: submit and map go to the pool; shutting it
    down (or leaving its ``with`` block) is left to :func:`shared_pool`."""

    def __init__(self, pool):
        self._pool = pool

    def submit(self, fn, /, *args, **kwargs):
        return self._pool.submit(fn, *args, **kwargs)

    def map(self, fn, *iterables, timeout=None, chunksize=1):
        return self._pool.map(fn, *iterables, timeout=timeout, chunksize=chunksize)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Nothing: the pool outlives the stage."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        return None


@contextlib.contextmanager
def shared_pool(jobs: int):
    """Within the block, :func:`process_pool` hands out one pool of ``jobs`` workers
    (none when ``jobs`` <= 1), started now. Where the ``fork`` start method exists the
    workers are forked at once, so call this before starting threads; elsewhere they use
    the fork server. Yields the pool (None without one); it is shut down (pending tasks
    cancelled) at the end."""
    global _SHARED
    if jobs <= 1 or _SHARED is not None:
        yield None
        return
    import concurrent.futures as cf
    import multiprocessing as mp
    method = "fork" if "fork" in mp.get_all_start_methods() else None
    pool = (cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context(method),
                                   initializer=ignore_sigint)
            if method else process_pool(jobs))
    pool.submit(int).result()          # every fork happens here, before any thread
    _SHARED = pool
    try:
        yield pool
    finally:
        _SHARED = None
        pool.shutdown(wait=True, cancel_futures=True)


def process_pool(jobs: int, preload: tuple[str, ...] = ()):
    """A ProcessPoolExecutor of ``jobs`` workers that ignore SIGINT: forked at once when
    the caller has no other thread, else started by the fork server (``preload`` names
    modules it imports once for every worker), else spawned. Within :func:`shared_pool`,
    that pool instead (its shutdown is a no-op)."""
    import concurrent.futures as cf
    import multiprocessing as mp
    if _SHARED is not None:
        return _Borrowed(_SHARED)
    if "fork" in mp.get_all_start_methods() and threading.active_count() == 1:
        # no other thread: fork every worker now (they inherit the modules already
        # imported, where a fork server imports them again)
        pool = cf.ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("fork"),
                                      initializer=ignore_sigint)
        pool.submit(int).result()
        return pool
    if "forkserver" in mp.get_all_start_methods():
        ctx = mp.get_context("forkserver")
        if preload:
            ctx.set_forkserver_preload(list(preload))
    else:
        ctx = mp.get_context("spawn")
    return cf.ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=ignore_sigint)


def stop_workers() -> None:
    """Kill every worker process this process started (all pools) and the fork server.

    Safe to call from a signal handler and when no pool was ever started.
    """
    mp = sys.modules.get("multiprocessing")
    if mp is None:
        return
    try:
        children = mp.active_children()
    except Exception:  # pragma: no cover - interpreter shutting down
        children = []
    for p in children:
        try:
            p.kill()
        except Exception:  # pragma: no cover - already gone
            pass
    for p in children:
        try:
            p.join(timeout=2.0)
        except Exception:  # pragma: no cover
            pass
    fs = sys.modules.get("multiprocessing.forkserver")
    server = getattr(fs, "_forkserver", None)
    stop = getattr(server, "_stop_unlocked", None)
    lock = getattr(server, "_lock", None)
    if stop is not None and lock is not None and lock.acquire(blocking=False):
        try:
            stop()
        except Exception:  # pragma: no cover - already stopped
            pass
        finally:
            lock.release()
