"""Where the diagnosis's tasks run: each task's result handed to a continuation as soon as
it arrives, so that an axis's next fits start while other axes are still busy.

The stepwise search is a chain of tasks per axis (base fit, screening fits, joint fits on
all trials, the next step's screening, ...). Run step by step over all axes at once, every
step waits for the slowest axis; here each task, when done, calls its continuation, which
may add the axis's next tasks at once. Every task's result depends only on its arguments,
so the results are the same whatever order the tasks run in, and on any executor.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, Future, wait

from armfit.workers import executor_for

__all__ = ["TaskQueue", "task_queue"]


class TaskQueue:
    """Tasks ``fn(args)`` with continuations, run on ``pool`` (an executor; None: here,
    one after the other).

    :meth:`add` queues a task with its priority (lower first; ties in the order added)
    and the continuation ``then(result)``, called in this thread; :meth:`run` runs until
    no task is left, continuations adding tasks as they go. At most ``capacity`` tasks
    are handed to the pool at once (the rest wait here, so that a task added later with
    a higher priority goes first; None: every task as soon as it is ready, for an
    executor that queues tasks itself). While the thread ``starting`` runs (it starts
    the pool's workers), the ready tasks run here instead, one at a time, so that this
    process works while the workers start. The first error of a task (or continuation)
    is raised after the tasks not yet started are cancelled.
    """

    def __init__(self, pool: Executor | None = None, capacity: int | None = None,
                 starting: threading.Thread | None = None):
        self.pool = pool
        self.capacity = capacity
        self.starting = starting
        self._ready: list = []
        self._running: dict[Future, tuple[int, Callable]] = {}
        self._order = itertools.count()

    def add(self, priority: tuple | int, fn: Callable, args, then: Callable) -> None:
        """Queue ``fn(args)``; ``then(result)`` is called with its result."""
        heapq.heappush(self._ready, (priority, next(self._order), fn, args, then))

    def run(self) -> None:
        """Run every queued task and those their continuations add."""
        try:
            while self._ready or self._running:
                if self.pool is None or (self._ready and self.starting is not None
                                         and self.starting.is_alive()):
                    _, _, fn, args, then = heapq.heappop(self._ready)
                    then(fn(args))
                    continue
                while self._ready and (self.capacity is None
                                       or len(self._running) < self.capacity):
                    _, order, fn, args, then = heapq.heappop(self._ready)
                    self._running[self.pool.submit(fn, args)] = (order, then)
                done, _ = wait(list(self._running), return_when=FIRST_COMPLETED)
                for fut in sorted(done, key=lambda f: self._running[f][0]):
                    _, then = self._running.pop(fut)
                    then(fut.result())
        except BaseException:
            for fut in self._running:
                fut.cancel()
            self._running.clear()
            self._ready.clear()
            raise

    def map(self, fn: Callable, items: Iterable, priority: tuple | int = 0) -> list:
        """``[fn(a) for a in items]``, the tasks run as :meth:`run` runs them (with any
        already queued)."""
        items = list(items)
        out: list = [None] * len(items)
        for i, a in enumerate(items):
            self.add(priority, fn, a, lambda r, i=i: out.__setitem__(i, r))
        self.run()
        return out


def _start(pool: Executor) -> None:
    """Start the workers of a pool of :func:`armfit.workers.process_pool` (they start at
    its first task); a failure shows again at the pool's next task."""
    with contextlib.suppress(BaseException):
        pool.submit(int)


@contextlib.contextmanager
def task_queue(jobs: int, executor: Executor | None = None,
               preload: tuple[str, ...] = ("armfit.diagnosis",)) -> Iterator[TaskQueue]:
    """A :class:`TaskQueue` for the ``with`` block: on ``executor`` when one is given
    (used as is, not shut down; every ready task handed to it at once), else on ``jobs``
    worker processes when ``jobs`` > 1 (one pool for the block, ``jobs`` tasks at a
    time, shut down on leaving), else here (:func:`armfit.workers.executor_for`).

    Called in the main thread (the command line's ``diagnose``), a pool of its own starts
    its workers in a thread at once (a new fork server imports armfit's modules first:
    about half a second) while the first tasks run here. Not in another thread: there
    the diagnosis may be stopped by shutting its pool down
    (:func:`armfit.workers.cancel_pools`, as ``armfit run`` does after a failure), which
    it notices at its next task in the pool, not while it runs one here."""
    with executor_for(executor, jobs, preload=preload) as pool:
        if pool is None or pool is executor:
            yield TaskQueue(pool)
            return
        if threading.current_thread() is not threading.main_thread():
            yield TaskQueue(pool, int(jobs))
            return
        starting = threading.Thread(target=_start, args=(pool,), daemon=True,
                                    name="armfit-diagnosis-start")
        starting.start()
        try:
            yield TaskQueue(pool, int(jobs), starting)
        finally:
            starting.join()
