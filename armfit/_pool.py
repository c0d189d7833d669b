"""The process pool of :func:`armfit.workers.process_pool` (imported with the first pool).

Kept apart from :mod:`armfit.workers` so that a command that runs its tasks in its own
process (one trial, ``--jobs 1``) never imports :mod:`concurrent.futures.process` and
:mod:`multiprocessing` (about 30 ms of its start-up). See :mod:`armfit.workers` for how
the pools start, stop and give way; the functions named here are its. What the pool
shares with that module (the lock held while workers start, the flag that no pool
starts any more, the workers' environment and start-up, the record of open pools) is
handed to it as a :class:`Hooks`, so that this module imports nothing of armfit's.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import os
import signal
import threading
import weakref
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import CancelledError, Executor, Future, ProcessPoolExecutor
from concurrent.futures import wait as _wait_futures
from concurrent.futures.process import BrokenProcessPool, _SafeQueue
from contextlib import AbstractContextManager
from dataclasses import dataclass
from multiprocessing import reduction
from multiprocessing.connection import Connection
from typing import Any

__all__ = ["GivingWay", "Hooks", "Pool", "WholeReads", "after_task", "whole_reads"]

#: A message through a pool's pipes of at least this many bytes is read into one buffer
#: of its size (:class:`WholeReads`); a shorter one as :mod:`multiprocessing` reads it.
WHOLE_READ_BYTES = 1 << 16

#: In a pool's worker: what :func:`after_task` was asked to run once the task now running
#: has ended; and whether this process is such a worker (it received the pool's queue of
#: tasks, :class:`_Tasks`).
_AFTER_TASK: list[Callable[[], None]] = []
_IN_WORKER = False


@dataclass(frozen=True)
class Hooks:
    """What a :class:`Pool` shares with :mod:`armfit.workers`.

    Attributes
    ----------
    initializer : callable
        Run by each worker at its start, with ``initargs``.
    initargs : tuple
    ready : callable
        The task (of no arguments, doing nothing) that starts a worker.
    starting : context manager
        Held while the pool starts its workers (a lock).
    stopped : callable
        True once no pool may start workers any more.
    environment : callable
        A context manager: the environment the processes started in it inherit.
    forget : callable
        Called with the pool when it is shut down (leaves the record of open pools).
    started : callable
        Called once the pool's workers have started.
    """

    initializer: Callable[..., None]
    initargs: tuple
    ready: Callable[[], None]
    starting: AbstractContextManager[Any]
    stopped: Callable[[], bool]
    environment: Callable[[], AbstractContextManager[None]]
    forget: Callable[[Any], None]
    started: Callable[[], None]


class Pool(ProcessPoolExecutor):
    """A ProcessPoolExecutor that starts all its workers at its first task and leaves the
    record of open pools when shut down.

    The workers are started by a thread of their own holding ``hooks.starting``, while the
    caller waits for it: a signal then reaches the caller (the main thread) in the wait,
    and :func:`stop_workers` in its handler waits until every worker is started, so it
    kills them all (a worker that is being started when the main process ends would
    fail, and print the failure, for want of its queues).

    The pool keeps its tasks' futures: when :func:`stop_workers` has killed its workers,
    those not done fail at once (:meth:`_armfit_stopped`), whatever the pool's own thread
    makes of the killed workers (a worker killed while it sent a result leaves that
    thread waiting for the rest of it), and :meth:`shutdown` no longer waits.

    Tasks that give way (:func:`giving_way`) wait in the pool's own queue and are handed
    to the workers only while fewer tasks than workers are unfinished; every task's end
    hands over the next. A task submitted to the pool itself is handed over at once, so
    it runs before every task still waiting there.
    """

    def __init__(self, jobs: int, mp_context, hooks: Hooks) -> None:
        super().__init__(max_workers=jobs, mp_context=mp_context,
                         initializer=hooks.initializer, initargs=hooks.initargs)
        # the tasks the workers receive and the results this process receives: read
        # whole (the workers' ends are made from these when they start)
        for reader in (self._call_queue._reader, self._result_queue._reader):
            whole_reads(reader)
        self._call_queue.__class__ = _Tasks
        self._armfit_hooks = hooks
        self._armfit_jobs = jobs
        self._armfit_lock = threading.Lock()
        self._armfit_shutting = threading.Lock()
        self._armfit_started = False
        self._armfit_killed = False
        self._armfit_futures: weakref.WeakSet = weakref.WeakSet()
        # the tasks that give way: (future, fn, args, kwargs) waiting, in order; the
        # tasks handed to the workers and not done; no task added once shutting down
        self._armfit_queue = threading.Lock()
        self._armfit_waiting: collections.deque = collections.deque()
        self._armfit_unfinished = 0
        self._armfit_closing = False

    def submit(self, fn, /, *args, **kwargs):
        with self._armfit_queue:
            self._armfit_unfinished += 1
        return self._armfit_hand(fn, args, kwargs)

    def _armfit_hand(self, fn, args, kwargs):
        """Hand ``fn(*args, **kwargs)`` to the workers, counted as unfinished already."""
        try:
            if not self._armfit_started:
                self._armfit_start()
            if self._armfit_killed:
                raise BrokenProcessPool("the worker processes were stopped")
            fut = super().submit(fn, *args, **kwargs)
        except BaseException:
            with self._armfit_queue:
                self._armfit_unfinished -= 1
            raise
        self._armfit_futures.add(fut)
        fut.add_done_callback(self._armfit_done)
        return fut

    def _armfit_done(self, fut) -> None:
        """A task handed to the workers has ended (or was cancelled): its place goes to
        the next task that gives way."""
        with self._armfit_queue:
            self._armfit_unfinished -= 1
        self._armfit_feed()

    def _armfit_submit_later(self, fn, args, kwargs) -> Future:
        """Queue ``fn(*args, **kwargs)`` as a task that gives way; its future."""
        if self._armfit_killed:
            raise BrokenProcessPool("the worker processes were stopped")
        proxy: Future = Future()
        with self._armfit_queue:
            if self._armfit_closing:
                raise RuntimeError("cannot schedule new futures after shutdown")
            self._armfit_waiting.append((proxy, fn, args, kwargs))
        self._armfit_feed()
        return proxy

    def _armfit_feed(self, every: bool = False) -> None:
        """Hand the waiting tasks to the workers while fewer than ``jobs`` are unfinished
        (``every``: all of them); a cancelled one is dropped, one the pool refuses fails."""
        while True:
            with self._armfit_queue:
                if not self._armfit_waiting or (
                        not every and self._armfit_unfinished >= self._armfit_jobs):
                    return
                proxy, fn, args, kwargs = self._armfit_waiting.popleft()
                if not proxy.set_running_or_notify_cancel():
                    continue
                self._armfit_unfinished += 1
            try:
                fut = self._armfit_hand(fn, args, kwargs)
            except BaseException as exc:
                proxy.set_exception(exc)
                continue
            fut.add_done_callback(lambda f, proxy=proxy: _settle(proxy, f))

    def _armfit_drop_waiting(self, exc: BaseException | None) -> None:
        """Cancel the tasks still waiting (``exc`` None), or fail them with ``exc``."""
        with self._armfit_queue:
            waiting = list(self._armfit_waiting)
            self._armfit_waiting.clear()
        for proxy, *_ in waiting:
            if exc is None:
                proxy.cancel()
            elif proxy.set_running_or_notify_cancel():
                proxy.set_exception(exc)

    def _armfit_stopped(self, grace: float = 1.0) -> None:
        """Its workers were killed: every task not done fails (BrokenProcessPool). The
        pool's own thread fails them as soon as it sees the workers gone; those it has
        not failed within ``grace`` seconds (it waits for the rest of a result) fail
        here."""
        self._armfit_killed = True
        self._armfit_drop_waiting(BrokenProcessPool("the worker processes were stopped"))
        for _ in range(3):  # another thread may add a task meanwhile
            try:
                futures = list(self._armfit_futures)
                break
            except RuntimeError:
                continue
        else:  # pragma: no cover
            futures = []
        _wait_futures(futures, timeout=grace)
        for fut in futures:
            if not fut.done():
                with contextlib.suppress(Exception):  # done meanwhile
                    fut.set_exception(BrokenProcessPool("the worker processes were stopped"))

    def let_go_sent(self) -> Future | None:
        """Hand the workers a task that does nothing (``hooks.ready``), so that this
        process lets go of the last task it sent.

        The thread that sends the tasks (the feeder of the pool's call queue,
        :class:`multiprocessing.Queue`) keeps the pickled bytes of the last task it
        sent until it sends the next one. A task that carries the responses of all an
        axis's trials (about 5 MB on 1,350 trials) so stays in this process while its
        results are judged. The empty task costs its worker a few hundred microseconds
        and is not counted among the pool's tasks. Returns its future; None (nothing
        sent) before the pool's first task, once it is shut down or its workers
        stopped."""
        if self._armfit_killed or not self._armfit_started:
            return None
        try:
            return super().submit(self._armfit_hooks.ready)
        except (RuntimeError, BrokenProcessPool):     # shut down meanwhile
            return None

    @property
    def started(self) -> bool:
        """Whether the workers have started (:meth:`start`, or the first task)."""
        return self._armfit_started

    def start(self) -> None:
        """Start the workers now, if they have not started (as the first task would):
        returns once every worker is up; raises what stopped them starting. Another
        thread that submits a task meanwhile waits for the same start."""
        self._armfit_start()

    def _armfit_start(self) -> None:
        with self._armfit_lock:
            if self._armfit_started:
                return
            failed: list[BaseException] = []
            starter = threading.Thread(target=self._armfit_start_all, args=(failed,),
                                       name="armfit-pool-start", daemon=True)
            starter.start()
            starter.join()
            if failed:
                raise failed[0]
            self._armfit_started = True
            self._armfit_hooks.started()

    def _armfit_start_all(self, failed: list) -> None:
        # SIGINT blocked in this thread, and so in the processes started from it (the
        # fork server, the resource tracker): Ctrl-C at a terminal reaches them too, and
        # the fork server ignores SIGINT only once it has imported its modules
        if hasattr(signal, "pthread_sigmask"):
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            hooks = self._armfit_hooks
            with hooks.starting, hooks.environment():
                if hooks.stopped():
                    raise BrokenProcessPool("the worker processes were stopped")
                # a task per worker (refused once the pool is shut down): a submit
                # starts a worker while none is idle. A worker that has already done its
                # task (a loaded machine may pause this thread between two submits)
                # takes the next one instead: the workers still missing are then
                # started outright, as the executor starts one for a task that finds
                # none idle
                submit = super().submit
                futures = [submit(hooks.ready) for _ in range(self._armfit_jobs)]
                with self._shutdown_lock:
                    while self._processes is not None \
                            and len(self._processes) < self._armfit_jobs:
                        self._spawn_process()
                for fut in futures:
                    fut.result()
        except BaseException as exc:  # raised in the caller's thread
            failed.append(exc)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """As :meth:`ProcessPoolExecutor.shutdown`; once :func:`stop_workers` has killed
        the workers, without waiting (what remained of the pool may never end).

        One call at a time: the thread that made the pool and :func:`cancel_pools` (a
        failing run stopping a stage in the background) may shut it down together, and
        two concurrent shutdowns of a ProcessPoolExecutor close its queues twice (EBADF).
        The second call finds the pool shut down and returns.

        The tasks that give way and still wait are cancelled with ``cancel_futures``,
        else handed to the workers now, to run before the pool ends."""
        self._armfit_hooks.forget(self)
        with self._armfit_queue:
            self._armfit_closing = True
        if cancel_futures or self._armfit_killed:
            self._armfit_drop_waiting(None)
        else:
            self._armfit_feed(every=True)
        with self._armfit_shutting:
            super().shutdown(wait=wait and not self._armfit_killed,
                             cancel_futures=cancel_futures)


class _Tasks(_SafeQueue):
    """The queue a :class:`Pool`'s tasks reach its workers through. In a worker, before
    it waits for its next task, it runs what the task before asked to run once it had
    ended (:func:`after_task`): the worker's loop has sent that task's result and let
    its arguments go by then."""

    def __setstate__(self, state):
        global _IN_WORKER
        _IN_WORKER = True        # only a pool's worker receives the queue
        super().__setstate__(state)

    def get(self, block=True, timeout=None):
        while _AFTER_TASK:
            with contextlib.suppress(Exception):    # never the worker's end
                _AFTER_TASK.pop(0)()
        return super().get(block, timeout)


class WholeReads(Connection):
    """The reading end of a pool's pipe, reading each message of
    :data:`WHOLE_READ_BYTES` or more into one buffer of the message's size.

    :class:`multiprocessing.connection.Connection` reads a message into an
    :class:`io.BytesIO` a pipe's worth (64 KiB) at a time: the buffer grows by an eighth
    at a time and is moved as it grows, past the block each read allocated. In a process
    that keeps what it frees (:func:`armfit.workers.tune_allocator`) three pickled
    messages of 8 MiB so grew the C library's heap by 2.8 times a message, against 2.0
    read whole: the message's buffer and the object unpickled from it
    (``tests/test_fast_paths.py``). In ``armfit run`` of 4,050 trials each base fit of
    the diagnosis (2.2 MB: the residuals of an axis's 1,350 trials) arrives while the
    next axis's rows are read; the main process's peak (``VmHWM``) fell from 183-185 MB
    to 176-177 MB (two runs each).

    Pickled to another process (a worker's end of the pool's queues) it stays a
    ``WholeReads``."""

    def _recv(self, size, read=None):
        if size < WHOLE_READ_BYTES:
            return super()._recv(size)
        buf = bytearray(size)
        with memoryview(buf) as view:
            got = 0
            while got < size:
                n = os.readv(self._handle, [view[got:]])
                if n == 0:
                    if got == 0:
                        raise EOFError
                    raise OSError("got end of file during message")
                got += n
        return _Message(buf)


class _Message:
    """A message :class:`WholeReads` received, as :class:`multiprocessing.connection.Connection`
    uses what its ``_recv`` returns (an :class:`io.BytesIO` written to its end)."""

    def __init__(self, buf: bytearray):
        self._buf = buf

    def getbuffer(self) -> memoryview:
        return memoryview(self._buf)

    def getvalue(self) -> bytes:
        return bytes(self._buf)

    def tell(self) -> int:
        return len(self._buf)

    def seek(self, pos: int, whence: int = 0) -> int:
        return pos

    def readinto(self, out) -> int:
        with memoryview(out) as m, m.cast("B") as b:
            b[:len(self._buf)] = self._buf
        return len(self._buf)


def whole_reads(conn) -> None:
    """Make ``conn``, the reading end of a pipe, a :class:`WholeReads` (nothing unless it
    is a :class:`multiprocessing.connection.Connection`: on Windows a pipe is another
    class)."""
    if type(conn) is Connection and conn.readable:
        conn.__class__ = WholeReads


def _reduce_whole(conn: WholeReads):
    return _rebuild_whole, (reduction.DupFd(conn.fileno()), conn.readable, conn.writable)


def _rebuild_whole(df, readable: bool, writable: bool) -> WholeReads:
    return WholeReads(df.detach(), readable, writable)


def after_task(fn: Callable[[], None]) -> bool:
    """In a pool's worker, have ``fn()`` run once the task now running has ended: after
    its result was sent and its arguments were let go, before the worker waits for its
    next task (:class:`_Tasks`). A task's own ``finally`` comes before both: the
    result is pickled, and the arguments freed, only after the task function returns.
    Returns False (and runs nothing) in any other process."""
    if not _IN_WORKER:
        return False
    _AFTER_TASK.append(fn)
    return True


reduction.register(WholeReads, _reduce_whole)


def _settle(proxy: Future, fut: Future) -> None:
    """Give ``proxy`` (a task that gave way) the outcome of ``fut``, the task the workers
    ran for it."""
    if fut.cancelled():
        proxy.set_exception(CancelledError())
    elif fut.exception() is not None:
        proxy.set_exception(fut.exception())
    else:
        proxy.set_result(fut.result())


def _run_chunk(fn: Callable, chunk: Sequence[tuple]) -> list:
    """Worker: ``[fn(*args) for args in chunk]`` (one task of :meth:`GivingWay.map`)."""
    return [fn(*args) for args in chunk]


def _flatten(results: Iterator[list]) -> Iterator:
    """The items of each list of ``results`` in turn; closing it closes ``results``."""
    try:
        for chunk in results:
            yield from chunk
    finally:
        results.close()


class GivingWay(Executor):
    """The tasks of a pool of :func:`process_pool` that give way (:func:`giving_way`)."""

    def __init__(self, pool: Pool):
        self.pool = pool

    def submit(self, fn, /, *args, **kwargs) -> Future:
        return self.pool._armfit_submit_later(fn, args, kwargs)

    def map(self, fn, *iterables, timeout=None, chunksize=1):
        """As :meth:`ProcessPoolExecutor.map`: ``chunksize`` calls per task."""
        if chunksize < 1:
            raise ValueError("chunksize must be >= 1.")
        pairs = zip(*iterables, strict=False)   # as map: to the shortest
        chunks = iter(lambda: tuple(itertools.islice(pairs, chunksize)), ())
        results = super().map(_run_chunk, itertools.repeat(fn), chunks, timeout=timeout)
        return _flatten(results)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Nothing: the pool belongs to its maker, who shuts it down."""
