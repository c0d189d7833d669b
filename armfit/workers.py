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
import contextvars
import signal
import sys
import threading


def ignore_sigint() -> None:
    """Pool initializer: a worker leaves SIGINT to the main process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


#: The pools of :func:`shared_pool` while one is open, by lane.
_SHARED: dict | None = None
#: The lane whose pool :func:`process_pool` hands out (see :func:`in_lane`).
_LANE: contextvars.ContextVar[str] = contextvars.ContextVar("armfit_pool_lane",
                                                            default="main")


def in_lane(lane: str, fn, /, *args, **kwargs):
    """``fn(*args, **kwargs)`` with :func:`process_pool` handing out the shared pool of
    ``lane`` (a stage that runs in the background uses its own workers, so the stages
    waited for are not queued behind it)."""
    token = _LANE.set(lane)
    try:
        return fn(*args, **kwargs)
    finally:
        _LANE.reset(token)


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
def shared_pool(jobs: int, lanes: tuple[str, ...] = ("main",)):
    """Within the block, :func:`process_pool` hands out a pool of ``jobs`` workers per
    lane (none when ``jobs`` <= 1), all started now; code run with :func:`in_lane` gets
    that lane's pool, other code the first lane's. Where the ``fork`` start method exists
    the workers are forked at once, so call this before starting threads; elsewhere they
    use the fork server. More workers than cores is deliberate: the system shares the
    cores between the lanes, where one queue would make the waited-for tasks wait behind
    the background ones. Yields the first lane's pool (None without one); all are shut
    down (pending tasks cancelled) at the end."""
    global _SHARED
    if jobs <= 1 or _SHARED is not None:
        yield None
        return
    pools = {lane: _new_pool(jobs) for lane in lanes}   # before any thread: forked now
    _SHARED = pools
    try:
        yield _Lanes(pools)
    finally:
        _SHARED = None
        for pool in pools.values():
            pool.shutdown(wait=True, cancel_futures=True)


class _Lanes:
    """The pools of :func:`shared_pool` as its caller holds them: shutting down stops
    every lane."""

    def __init__(self, pools: dict):
        self._pools = pools

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        for pool in self._pools.values():
            pool.shutdown(wait=wait, cancel_futures=cancel_futures)

    def submit(self, fn, /, *args, **kwargs):
        return next(iter(self._pools.values())).submit(fn, *args, **kwargs)


def process_pool(jobs: int, preload: tuple[str, ...] = ()):
    """A ProcessPoolExecutor of ``jobs`` workers that ignore SIGINT: forked at once when
    the caller has no other thread, else started by the fork server (``preload`` names
    modules it imports once for every worker), else spawned. Within :func:`shared_pool`,
    that pool instead (its shutdown is a no-op)."""
    if _SHARED is not None:
        return _Borrowed(_SHARED.get(_LANE.get(), next(iter(_SHARED.values()))))
    return _new_pool(jobs, preload)


def iter_tasks(fn, tasks, jobs: int, preload: tuple[str, ...] = (), chunksize: int = 1):
    """``fn(t)`` for each of ``tasks``, yielded in task order as they are done: in a
    :func:`process_pool` of up to ``jobs`` workers when ``jobs`` > 1 and there is more
    than one task (``fn`` must be picklable), else here. The first error of a task, in
    task order, is raised; pending tasks are then cancelled."""
    tasks = list(tasks)
    if jobs <= 1 or len(tasks) <= 1:
        yield from map(fn, tasks)
        return
    pool = process_pool(min(jobs, len(tasks)), preload)
    try:
        yield from pool.map(fn, tasks, chunksize=chunksize)
    finally:
        pool.shutdown(cancel_futures=True)


def map_tasks(fn, tasks, jobs: int, preload: tuple[str, ...] = (),
              chunksize: int = 1) -> list:
    """The list of :func:`iter_tasks`."""
    return list(iter_tasks(fn, tasks, jobs, preload, chunksize))


def _new_pool(jobs: int, preload: tuple[str, ...] = ()):
    """A pool of its own for :func:`process_pool` and :func:`shared_pool`."""
    import concurrent.futures as cf
    import multiprocessing as mp
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
