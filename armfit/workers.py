"""Worker processes: one way to start a pool, one way to stop every worker at once.

Pools use the ``forkserver`` start method where there is one (safe when the caller has
threads of its own), else ``spawn``. Workers ignore SIGINT: Ctrl-C at a terminal reaches
the whole process group, and only the main process decides what happens (it stops the
workers with :func:`stop_workers` and removes its partial outputs), so no worker prints
a traceback of its own.
"""

from __future__ import annotations

import signal
import sys


def ignore_sigint() -> None:
    """Pool initializer: a worker leaves SIGINT to the main process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def process_pool(jobs: int, preload: tuple[str, ...] = ()):
    """A ProcessPoolExecutor of ``jobs`` workers that ignore SIGINT (forkserver, else
    spawn); ``preload`` names modules the fork server imports once for every worker."""
    import concurrent.futures as cf
    import multiprocessing as mp
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
