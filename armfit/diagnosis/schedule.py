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

from armfit.memory import release_memory
from armfit.workers import POOL_PRELOAD, executor_for, fork_server_running, let_go_sent

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
    process works while the workers start; once they are up, that thread hands the
    ready tasks to the pool (:meth:`hand_over`) without waiting for the task running
    here to end. The first error of a task (or continuation) is raised after the tasks
    not yet started are cancelled.

    A task added as ``large`` (arguments of megabytes: an axis's trials) that is the
    last one a :meth:`_submit` hands to the pool is followed by
    :func:`armfit.workers.let_go_sent`: a pool of armfit's own would otherwise keep
    its pickled bytes while this process awaits and judges the results (on 4,050
    trials, 5 MB during the evidence of the last axis's base fit); once a large task's
    result is in, the memory freed is given back (:func:`armfit.memory.release_memory`).
    """

    def __init__(self, pool: Executor | None = None, capacity: int | None = None,
                 starting: threading.Thread | None = None):
        self.pool = pool
        self.capacity = capacity
        self.starting = starting
        self._ready: list = []
        self._running: dict[Future, tuple[int, Callable]] = {}
        self._order = itertools.count()
        # the queue is changed by this thread and, once, by the thread ``starting``
        self._lock = threading.Lock()

    def add(self, priority: tuple | int, fn: Callable, args, then: Callable, *,
            large: bool = False) -> None:
        """Queue ``fn(args)``; ``then(result)`` is called with its result. ``large``:
        its arguments take megabytes (see the class)."""
        with self._lock:
            heapq.heappush(self._ready, (priority, next(self._order), fn, args, then,
                                         large))

    def hand_over(self) -> None:
        """Hand the ready tasks to the pool, up to ``capacity`` running: called by the
        thread ``starting`` once the workers are up, while a task may still be running
        here (its continuation, and those of the tasks handed over, are called by
        :meth:`run` in its own thread, as always). A task the pool refuses stays ready:
        :meth:`run` submits it again and raises the pool's error."""
        with self._lock:
            self._submit()

    def start_ready(self) -> None:
        """Hand the ready tasks to the pool now, up to ``capacity`` running, so that they
        run while the caller prepares more (tasks added before :meth:`run`). Nothing
        without a pool, or while the thread ``starting`` starts it (it hands them over
        itself once the workers are up)."""
        if self.pool is None or (self.starting is not None and self.starting.is_alive()):
            return
        with self._lock:
            self._submit()

    def _submit(self) -> None:
        """Submit ready tasks, up to ``capacity`` running (the lock held)."""
        large = False
        while self._ready and (self.capacity is None or len(self._running) < self.capacity):
            item = heapq.heappop(self._ready)
            try:
                fut = self.pool.submit(item[2], item[3])
            except BaseException:
                heapq.heappush(self._ready, item)
                raise
            self._running[fut] = (item[1], item[4], item[5])
            large = item[5]
        if large:
            let_go_sent(self.pool)

    def run(self) -> None:
        """Run every queued task and those their continuations add."""
        try:
            while True:
                with self._lock:
                    if not (self._ready or self._running):
                        return
                    here = self.pool is None or (self._ready and self.starting is not None
                                                 and self.starting.is_alive())
                    if here:
                        _, _, fn, args, then, _ = heapq.heappop(self._ready)
                    else:
                        self._submit()
                        running = list(self._running)
                if here:
                    then(fn(args))
                    continue
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                with self._lock:
                    ended = [self._running.pop(f)[1:] + (f,) for f in
                             sorted(done, key=lambda f: self._running[f][0])]
                for then, _, fut in ended:
                    then(fut.result())
                self.start_ready()     # the workers' next tasks first, then the memory
                # the arguments sent and results received of a large task are let go by
                # now: a process that keeps what it frees (armfit.workers.tune_allocator)
                # gives them back (`armfit run` of 4,050 trials: its main process peaked
                # at 237-246 MB in the diagnosis, against 255 MB without); after small
                # tasks alone there is little to give back, and asking costs the C
                # library's walk of this process's heap (20 ms over sample_data/hidden's
                # 27 tasks, while the workers fit)
                if any(large for _, large, _ in ended):
                    release_memory()
        except BaseException:
            with self._lock:
                for fut in self._running:
                    fut.cancel()
                self._running.clear()
                self._ready.clear()
            raise

    def map(self, fn: Callable, items: Iterable, priority: tuple | int = 0, *,
            large: bool = False) -> list:
        """``[fn(a) for a in items]``, the tasks run as :meth:`run` runs them (with any
        already queued); ``large`` as :meth:`add`'s, for every item."""
        items = list(items)
        out: list = [None] * len(items)
        for i, a in enumerate(items):
            self.add(priority, fn, a, lambda r, i=i: out.__setitem__(i, r), large=large)
        self.run()
        return out


def _start(pool: Executor, queue: TaskQueue) -> None:
    """Start the workers of a pool of :func:`armfit.workers.process_pool` and hand them
    the queue's ready tasks; a failure shows again at the pool's next task, in the
    queue's own thread."""
    with contextlib.suppress(BaseException):
        pool.start()
        queue.hand_over()


#: Tasks handed to a pool of :func:`task_queue`'s own beyond one a worker.
AHEAD = 1


@contextlib.contextmanager
def task_queue(jobs: int, executor: Executor | None = None,
               preload: tuple[str, ...] = POOL_PRELOAD["diagnosis"]
               ) -> Iterator[TaskQueue]:
    """A :class:`TaskQueue` for the ``with`` block: on ``executor`` when one is given
    (used as is, not shut down; every ready task handed to it at once), else on ``jobs``
    worker processes when ``jobs`` > 1 (one pool for the block, shut down on leaving),
    else here (:func:`armfit.workers.executor_for`).

    A pool of its own is handed ``jobs`` + 1 tasks at a time (:data:`AHEAD`): a worker
    that ends a task finds the next one waiting in the pool's queue, instead of idling
    while this process receives the result, runs its continuation and submits the next
    task (1-8 ms a task, measured on ``sample_data/hidden``; 27 tasks of 10-50 ms). Only
    that one task is committed before a task of higher priority added later.

    Called in the main thread while no fork server runs (a script's first pool), a pool
    of its own starts its workers in a thread at once (the new fork server imports
    armfit's modules first: about half a second) while the first tasks run here; that
    thread hands the ready tasks to the workers as soon as they are up. Once a server
    runs (:func:`armfit.workers.fork_server_running`: the command line's ``diagnose``
    starts it before it loads its own modules) the workers are forked in milliseconds,
    and every task goes to them: a long task run here would hold back the
    continuations, and so the next tasks of the other axes, until it ended. Not in
    another thread: there the diagnosis may be stopped by shutting its pool down
    (:func:`armfit.workers.cancel_pools`, as ``armfit run`` does after a failure), which
    it notices at its next task in the pool, not while it runs one here."""
    with executor_for(executor, jobs, preload=preload) as pool:
        if pool is None or pool is executor:
            yield TaskQueue(pool)
            return
        if threading.current_thread() is not threading.main_thread() \
                or fork_server_running():
            yield TaskQueue(pool, int(jobs) + AHEAD)
            return
        queue = TaskQueue(pool, int(jobs) + AHEAD)
        starting = threading.Thread(target=_start, args=(pool, queue), daemon=True,
                                    name="armfit-diagnosis-start")
        queue.starting = starting
        starting.start()
        try:
            yield queue
        finally:
            starting.join()
