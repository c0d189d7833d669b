"""Where the diagnosis's tasks run: each task's result handed to a continuation as soon as
it arrives (:class:`armfit.workers.TaskQueue`), so that an axis's next fits start while
other axes are still busy.

The stepwise search is a chain of tasks per axis (base fit, screening fits, joint fits on
all trials, the next step's screening, ...). Run step by step over all axes at once, every
step waits for the slowest axis; here each task, when done, calls its continuation, which
may add the axis's next tasks at once. Every task's result depends only on its arguments,
so the results are the same whatever order the tasks run in, and on any executor.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from concurrent.futures import Executor

from armfit.workers import POOL_PRELOAD, TaskQueue, executor_for

__all__ = ["TaskQueue", "task_queue"]


def _start(pool: Executor, queue: TaskQueue) -> None:
    """Start the workers of a pool of :func:`armfit.workers.process_pool` (they start at
    its first task) and hand them the queue's ready tasks; a failure shows again at the
    pool's next task, in the queue's own thread."""
    with contextlib.suppress(BaseException):
        pool.submit(int)
        queue.hand_over()


@contextlib.contextmanager
def task_queue(jobs: int, executor: Executor | None = None,
               preload: tuple[str, ...] = POOL_PRELOAD["diagnosis"]
               ) -> Iterator[TaskQueue]:
    """A :class:`TaskQueue` for the ``with`` block: on ``executor`` when one is given
    (used as is, not shut down; every ready task handed to it at once), else on ``jobs``
    worker processes when ``jobs`` > 1 (one pool for the block, ``jobs`` tasks at a
    time, shut down on leaving), else here (:func:`armfit.workers.executor_for`).

    Called in the main thread (the command line's ``diagnose``), a pool of its own starts
    its workers in a thread at once (a new fork server imports armfit's modules first:
    about half a second) while the first tasks run here; that thread hands the ready
    tasks to the workers as soon as they are up. Not in another thread: there
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
        queue = TaskQueue(pool, int(jobs))
        starting = threading.Thread(target=_start, args=(pool, queue), daemon=True,
                                    name="armfit-diagnosis-start")
        queue.starting = starting
        starting.start()
        try:
            yield queue
        finally:
            starting.join()
