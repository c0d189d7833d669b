"""Where armfit's parallel work runs: an executor passed in, or worker processes of its own.

Every parallel function of armfit (:func:`armfit.estimate`, :func:`armfit.fit_grip`,
:func:`armfit.fit_nominal`, :func:`armfit.fit_trials`, :func:`armfit.fit_uncertainty`,
:func:`armfit.run` and the engine functions under them) takes either

- ``executor=``: any :class:`concurrent.futures.Executor` — a
  :class:`~concurrent.futures.ProcessPoolExecutor` of the caller's, or a
  ``dask.distributed`` client's ``client.get_executor()`` to spread the work over a
  cluster. It is used as it is: armfit submits tasks to it (``map`` and ``submit``) and
  never shuts it down; or
- ``jobs=``: a number of worker processes. With ``jobs`` > 1 armfit starts a pool of
  its own for the call (:func:`process_pool`) and shuts it down when the call ends,
  cancelling what is pending if the call fails; with ``jobs`` 1 the tasks run one after
  the other in the calling process (the estimate reads the next trial meanwhile in a
  thread: :func:`read_ahead`).

An executor given wins over ``jobs``. The tasks are module-level functions of picklable
arguments, and each task's result depends only on its arguments, so the results are the
same, bit for bit, whatever runs them.

:func:`executor_for` turns "executor or jobs" into something with ``map`` and
``submit``; :func:`iter_tasks` and :func:`map_tasks` run a list of tasks on it.
:func:`giving_way` gives a pool's tasks that may wait a place behind the others: on a
pool of :func:`process_pool` they reach the workers only while one is free.

Start method. armfit's pools start their workers with the ``forkserver`` method where
Python offers it, except on macOS, and with ``spawn`` elsewhere (macOS, Windows): one
rule, whatever threads the caller has or what it imported. The fork server is a fresh
interpreter, started with the first pool of a process, that imports armfit's engine
modules once (:data:`PRELOAD`); each worker is then forked from it in milliseconds, with
those modules loaded, whichever pool of the process it serves. A command-line process
starts one pool: there the fork server imports only what that pool's tasks run
(:func:`preload_own_only`, :data:`POOL_PRELOAD`; ``estimate``'s workers are then ready
in about 0.35 s rather than 1.3 s), and a command given ``--jobs`` N > 1 starts the
server before it loads its own modules (:func:`start_fork_server`), so that the two
import at once. Forking the caller itself would be faster still at the first pool,
but it copies one thread of a process that may have others (``armfit run``'s background
stages, a dask client, a notebook) and can leave a lock of another thread held in the
child; Python 3.12 warns about it, and 3.14 made the fork server the default on Linux.
macOS keeps its own default, ``spawn`` (system libraries there are not safe to fork).

A pool starts all its workers at its first task, in one go (the caller waits until each
has run :func:`worker_start`), so that a pool is never half started when it is stopped.

Module path. The processes multiprocessing starts with ``python -c`` (the fork server,
the resource tracker, ``spawn`` workers) would put the working folder first on their
module path, so a ``signal.py`` or ``pickle.py`` lying there would run in them. armfit
starts them with ``PYTHONSAFEPATH=1`` in their environment (:func:`child_environment`;
Python 3.11 and later honour it), so they import only what the calling process could:
the only user code a worker runs is an ``--effects`` file named explicitly or an
installed entry point.

Stopping. Workers ignore SIGINT (:func:`ignore_sigint`): Ctrl-C at a terminal reaches
the whole process group, and only the main process decides what happens — it kills the
workers (:func:`stop_workers`, which first lets a pool being started finish starting)
and removes its partial outputs, so no worker prints a traceback of its own. The tasks
the killed workers held fail at once (``BrokenProcessPool``), so nothing waits for them,
and a pool is not waited for when it is shut down afterwards. The fork server and the
resource tracker are started with SIGINT blocked (the fork server ignores it only once
its imports are done), and end by themselves once the main process and the workers
have ended. A main process killed outright (SIGKILL, a crash) cannot stop its workers:
each worker watches a pipe that only the main process holds open (its lifeline,
:func:`worker_start`) and ends as soon as the pipe closes; the fork server and the
resource tracker then follow.

A script that uses ``jobs`` > 1 needs the ``if __name__ == "__main__":`` guard, as with
any pool whose workers do not fork the script's process.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import weakref
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING

from armfit._lazy import loaded

if TYPE_CHECKING:   # the pool's modules are imported with the first pool (armfit._pool)
    from concurrent.futures import Executor, Future, ProcessPoolExecutor

__all__ = ["BLAS_ONE_THREAD", "CHILD_ENVIRONMENT", "POOL_PRELOAD", "PRELOAD",
           "RUN_FIGURES_PRELOAD", "cancel_pools", "child_environment", "executor_for",
           "giving_way", "ignore_sigint", "is_process_pool", "iter_tasks", "let_go_sent",
           "map_tasks",
           "prepare_pool_folder", "preload_own_only", "read_ahead", "process_pool",
           "remove_pool_folder", "start_fork_server", "start_workers",
           "fork_server_running",
           "start_method", "stop_workers", "worker_start", "tune_allocator", "one_blas_thread",
           "system_arrow_pool", "ARROW_SYSTEM_POOL",
           "MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES"]

#: Every module whose functions armfit's tasks run (and the scipy modules they call): the
#: fork server imports them once, with a pool's own ``preload``, so that the workers of
#: every later pool of the process start with them loaded (see
#: :func:`preload_own_only` for a process that starts one pool).
PRELOAD: tuple[str, ...] = ("armfit.io.trials", "armfit.spectra", "armfit.fitting",
                            "armfit.uncertainty", "armfit.diagnosis.search",
                            "armfit.diagnosis.driver")
#: The modules the tasks of each kind of pool run, the ``preload`` of its pools: what
#: the fork server imports first for a command line's one pool (:func:`preload_own_only`,
#: :func:`start_fork_server`). Each is in :data:`PRELOAD`. No worker needs a scipy
#: package: the fits' solver is :mod:`armfit._trf` and their intervals' t quantiles are
#: :func:`armfit._student.t_quantile` (:mod:`scipy.special` cost the server 0.13 s of
#: CPU while the run read its first trials), the uncertainty's solvers are
#: :mod:`armfit._trf` and scipy's SLSQP kernel, which :mod:`armfit._slsqp` loads in
#: milliseconds, and the diagnosis's are armfit's own. The fits' and the diagnosis's
#: tasks take arrays: their modules import the spectra file's reader
#: (:mod:`armfit.spectra`, pyarrow) only where a function reads one, so that their fork
#: server does not (about 70 ms of CPU while the command starts).
POOL_PRELOAD: dict[str, tuple[str, ...]] = {
    "estimate": ("armfit.spectra", "armfit.io.trials"),
    "fit": ("armfit.fitting",),
    "uncertainty": ("armfit.uncertainty",),
    "diagnosis": ("armfit.diagnosis.search", "armfit.diagnosis.driver"),
}
#: What ``run``'s one pool preloads when the run draws figures: every engine module and
#: :mod:`armfit.figures` (matplotlib), imported once by the fork server rather than by
#: each worker at its first drawing.
RUN_FIGURES_PRELOAD: tuple[str, ...] = (*PRELOAD, "armfit.figures")
#: Set by :func:`preload_own_only`.
_OWN_ONLY = False
#: The fork server's last preload: its exit handler ends the server without tearing
#: its interpreter down (:mod:`armfit._server_exit`).
SERVER_EXIT = "armfit._server_exit"

#: The pools :func:`process_pool` made that are not shut down yet, each with the ident of
#: the thread that made it (see :func:`cancel_pools`). A record only: no pool is handed
#: out from here.
_OPEN: weakref.WeakKeyDictionary[ProcessPoolExecutor, int] = weakref.WeakKeyDictionary()
#: Reentrant: :func:`stop_workers` runs in a signal handler of a thread that may hold it.
_OPEN_LOCK = threading.RLock()
#: Held while a pool starts its workers; :func:`stop_workers` waits for it.
_STARTING = threading.Lock()
#: Set by ``stop_workers(final=True)``: no pool starts any more in this process.
_FINAL = False
#: Set once this process's fork server has started (:func:`fork_server_running`).
_SERVER_UP = False


#: The environment of every process armfit's pools start with ``python -c`` (fork
#: server, resource tracker, ``spawn`` workers): the working folder is not put on their
#: module path (PYTHONSAFEPATH, Python >= 3.11), the resource tracker does not warn
#: about the queues' semaphores it removes after the workers were killed (removing them
#: is its purpose; the notice would be a second line after the one line of a stopped
#: command), BLAS runs on one thread in each (:data:`BLAS_ONE_THREAD`) and Arrow takes
#: its buffers from the C library's allocator (:data:`ARROW_SYSTEM_POOL`). A variable
#: already set keeps its value.
CHILD_ENVIRONMENT: dict[str, str] = {
    "PYTHONSAFEPATH": "1",
    "PYTHONWARNINGS": "ignore::UserWarning:multiprocessing.resource_tracker",
}

#: BLAS (OpenBLAS, MKL, BLIS) on one thread: in every process armfit's pools start
#: (:data:`CHILD_ENVIRONMENT`), and in a command line's own process
#: (:func:`one_blas_thread`). armfit's BLAS calls are small (fits' Jacobians of a few
#: hundred rows, trust-region SVDs of 160 x 21), where a BLAS's threads cost more than
#: they save, and a pool's workers already share the cores out task by task. OpenBLAS
#: starts its threads when it loads, and they wait for work spinning: on the 2-core
#: machine they cost the fork server about 0.12 s of processor time and ``armfit run``'s
#: own process about 0.2 s, taken from the processes beside them. The results are the
#: same bits (the outputs of ``armfit run`` are).
BLAS_ONE_THREAD: dict[str, str] = {
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "BLIS_NUM_THREADS": "1",
}
CHILD_ENVIRONMENT.update(BLAS_ONE_THREAD)

#: Arrow's buffers from the C library's allocator rather than the mimalloc pyarrow
#: bundles: in every process armfit's pools start (:data:`CHILD_ENVIRONMENT`) and in a
#: command line's own process (:func:`system_arrow_pool`). After an ingest (trials read
#: by Arrow's threads, written by a thread of their own) and
#: :func:`armfit.memory.release_memory`, a process kept 6-12 MB of what mimalloc had
#: freed and 0.2 MB from the C library's one arena (:func:`tune_allocator`), which
#: ``release_memory`` gives back whole (``tests/test_fast_paths.py``): the peak of
#: ``armfit run --jobs 2`` summed over its processes fell from 347 to 324 MB on 81 trials
#: and from 434 to 394 MB on 4,050 (``benchmarks/bench_memory.py``; docs/methods.md).
ARROW_SYSTEM_POOL: dict[str, str] = {"ARROW_DEFAULT_MEMORY_POOL": "system"}
CHILD_ENVIRONMENT.update(ARROW_SYSTEM_POOL)

_ENV_LOCK = threading.Lock()
_ENV_USERS = 0
_ENV_SAVED: dict[str, str | None] = {}


@contextlib.contextmanager
def child_environment() -> Iterator[None]:
    """:data:`CHILD_ENVIRONMENT` in ``os.environ`` for the ``with`` block (the processes
    started in it inherit it), then the environment as it was.

    Nested and concurrent blocks (several threads starting pools) share one change. A
    variable already set keeps its value (PYTHONWARNINGS gets the filter appended).

    Yields
    ------
    None
    """
    global _ENV_USERS
    with _ENV_LOCK:
        if _ENV_USERS == 0:
            _ENV_SAVED.clear()
            for name, value in CHILD_ENVIRONMENT.items():
                old = os.environ.get(name)
                if old and name == "PYTHONWARNINGS":
                    if value in old.split(","):
                        continue
                    value = f"{old},{value}"
                elif old:
                    continue
                _ENV_SAVED[name] = old
                os.environ[name] = value
        _ENV_USERS += 1
    try:
        yield
    finally:
        with _ENV_LOCK:
            _ENV_USERS -= 1
            if _ENV_USERS == 0:
                for name, old in _ENV_SAVED.items():
                    if old is None:
                        os.environ.pop(name, None)
                    else:
                        os.environ[name] = old
                _ENV_SAVED.clear()


def ignore_sigint() -> None:
    """A worker leaves SIGINT to the main process (it ignores it, and unblocks it, as
    the thread that started the fork server had it blocked)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


#: The lifeline of this process's workers: (read end, write end, pid) of a pipe. Only
#: this process holds the write end (a pipe's descriptors are not inherited by the
#: processes it starts); every worker gets the read end, which reaches end-of-file when
#: this process has ended, however it ended.
_LIFELINE: tuple | None = None
_LIFELINE_LOCK = threading.Lock()


def _lifeline():
    """The read end of this process's lifeline (made on first use)."""
    global _LIFELINE
    with _LIFELINE_LOCK:
        if _LIFELINE is None or _LIFELINE[2] != os.getpid():
            from multiprocessing import Pipe
            reader, writer = Pipe(duplex=False)
            _LIFELINE = (reader, writer, os.getpid())
        return _LIFELINE[0]


def _watch(lifeline) -> None:
    """A worker's watch of its lifeline: end the worker when the main process has ended
    (nothing is ever written to the pipe: it becomes readable at end-of-file only)."""
    with contextlib.suppress(OSError, EOFError):
        lifeline.poll(None)
    os._exit(1)


#: glibc's allocator settings for armfit's processes (see :func:`tune_allocator`): blocks
#: up to 32 MiB come from the heap, and up to 128 MiB of freed heap stays with the process.
MMAP_THRESHOLD_BYTES = 32 << 20
TRIM_THRESHOLD_BYTES = 128 << 20


def preload_own_only() -> None:
    """Make the fork server import only the modules the first pool's tasks run (its
    ``preload``), not every engine module (:data:`PRELOAD`).

    For a process that starts one pool, as each ``armfit`` command does (``run``'s one
    pool serves every stage and preloads everything): ``estimate``'s workers are then
    ready in about 0.35 s instead of 1.3 s. A later pool's workers would import what
    else they need at their first task, so a script or notebook that starts several
    pools is better served by the default.
    """
    global _OWN_ONLY
    _OWN_ONLY = True


def one_blas_thread() -> None:
    """Run BLAS on one thread in this process and the processes it starts, unless the
    environment already says how many (:data:`BLAS_ONE_THREAD`): the command line's
    console entry point calls it before numpy loads, which is when BLAS reads it."""
    _set_unset(BLAS_ONE_THREAD)


def system_arrow_pool() -> None:
    """Allocate Arrow's buffers with the C library's allocator in this process and the
    processes it starts, unless the environment already names a pool
    (:data:`ARROW_SYSTEM_POOL`): the command line's console entry point calls it before
    pyarrow loads, which is when Arrow reads it."""
    _set_unset(ARROW_SYSTEM_POOL)


def _set_unset(values: Mapping[str, str]) -> None:
    """Set each environment variable of ``values`` that is not set already."""
    for name, value in values.items():
        os.environ.setdefault(name, value)


def tune_allocator() -> bool:
    """Keep the memory of large, short-lived arrays with the process (glibc only).

    Estimating a trial makes arrays of a few MB (Welch segments, their spectra) and frees
    them. By default glibc maps each one afresh from the system and returns it on free,
    so every trial pays the page faults again: a fifth of ``armfit estimate``'s time was
    spent in the kernel. With ``M_MMAP_THRESHOLD`` at :data:`MMAP_THRESHOLD_BYTES` and
    ``M_TRIM_THRESHOLD`` at :data:`TRIM_THRESHOLD_BYTES` (``mallopt(3)``) the pages are
    reused; the peak memory grows by about the size of one trial's arrays.

    With ``M_ARENA_MAX`` at 1 every thread allocates from the one arena that
    :func:`armfit.memory.release_memory` gives back whole. Otherwise each thread that
    allocates gets an arena of its own, and a pool's threads (those that pickle the tasks
    sent to the workers and unpickle their results) kept the freed memory of those
    transfers: 31 MB after 30 tasks of 4 MB, against 2 MB in one arena
    (``tests/test_fast_paths.py``). The peak of ``armfit run --jobs 2`` summed over its
    processes fell from 650 to 628 MB on 4,050 trials, from about 538 to 526 MB on 81.

    Returns
    -------
    bool
        True when the settings were applied (a glibc system), False otherwise.
    """
    import ctypes
    try:   # the process's own symbols, the C library's among them (no ldconfig search)
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):   # not glibc (musl, macOS, Windows)
        return False
    m_trim_threshold, m_mmap_threshold, m_arena_max = -1, -3, -8   # glibc's <malloc.h>
    return bool(mallopt(m_mmap_threshold, MMAP_THRESHOLD_BYTES)) and \
        bool(mallopt(m_trim_threshold, TRIM_THRESHOLD_BYTES)) and \
        bool(mallopt(m_arena_max, 1))


def worker_start(lifeline) -> None:
    """Pool initializer: :func:`ignore_sigint`, and a thread that ends the worker at
    once when the main process has ended (also when it was killed outright and could
    not stop its workers).

    Parameters
    ----------
    lifeline : multiprocessing.connection.Connection
        The read end of a pipe whose write end only the main process holds: it reaches
        end-of-file when the main process has ended.
    """
    ignore_sigint()
    tune_allocator()
    threading.Thread(target=_watch, args=(lifeline,), name="armfit-lifeline",
                     daemon=True).start()


def start_method() -> str:
    """The start method of armfit's worker processes: ``"forkserver"`` where Python
    offers it, except on macOS; ``"spawn"`` elsewhere (see the module docstring).

    Returns
    -------
    str
    """
    from multiprocessing import get_all_start_methods
    if sys.platform != "darwin" and "forkserver" in get_all_start_methods():
        return "forkserver"
    return "spawn"


def _ready() -> None:
    """The task that starts a worker (see :class:`armfit._pool.Pool`)."""


def giving_way(executor: Executor | None) -> Executor | None:
    """An executor for tasks that may wait while others run first.

    Parameters
    ----------
    executor : concurrent.futures.Executor or None
        The executor the tasks run on.

    Returns
    -------
    concurrent.futures.Executor or None
        For a pool of :func:`process_pool`: an executor of the same workers whose tasks
        wait in the pool's queue and are handed to the workers only while fewer tasks
        than workers are unfinished, so every task submitted to the pool itself meanwhile
        runs first (``armfit run`` gives the per-trial fits and the figures this place,
        behind the fits that the next stages wait for); the tasks that give way run in the
        order submitted, and a pool shut down without ``cancel_futures`` runs those still
        waiting first. Any other executor, or None, is returned as it is. Where a task
        runs never changes its result.
    """
    if not is_process_pool(executor):
        return executor
    return sys.modules["armfit._pool"].GivingWay(executor)


def start_workers(executor: Executor | None) -> threading.Thread | None:
    """Start the workers of a pool of :func:`process_pool` that has not started them, in
    a thread of its own, so that the caller works meanwhile.

    A pool's workers start at its first task, which waits until they are up: forked from
    the fork server once it has imported its modules (with ``armfit run``'s figures,
    matplotlib and pandas: about a second). A caller that has other work to do until then
    (``armfit run`` reading its trials) starts them here.

    Parameters
    ----------
    executor : concurrent.futures.Executor or None
        Any executor.

    Returns
    -------
    threading.Thread or None
        The thread, running while the workers start (a failure is dropped there and
        raised by the pool's next task); None for any other executor, or a pool whose
        workers have started.
    """
    if not is_process_pool(executor) or executor.started:
        return None
    thread = threading.Thread(target=_start_quietly, args=(executor,), daemon=True,
                              name="armfit-workers-start")
    thread.start()
    return thread


def _start_quietly(pool) -> None:
    """Start ``pool``'s workers; a failure shows again at its next task."""
    with contextlib.suppress(BaseException):
        pool.start()


def is_process_pool(executor: Executor | None) -> bool:
    """Whether ``executor`` is a pool of :func:`process_pool` (its workers on this
    machine, forked from this process's fork server)."""
    pools = loaded("armfit._pool")    # not imported: no pool of process_pool
    return pools is not None and isinstance(executor, pools.Pool)


def let_go_sent(executor: Executor | None) -> Future | None:
    """Let this process free the last task it sent to ``executor``'s workers.

    A pool of :func:`process_pool` keeps the pickled bytes of the last task it sent
    until it sends another (:meth:`armfit._pool.Pool.let_go_sent` sends one that does
    nothing). A caller that has just handed over a task of large arguments and will
    now wait, or compute, calls this. Any other executor, or None: nothing.

    Parameters
    ----------
    executor : concurrent.futures.Executor or None
        The executor the task went to (a :func:`giving_way` executor: its pool's).

    Returns
    -------
    concurrent.futures.Future or None
        The empty task's; None when nothing was sent.
    """
    pools = loaded("armfit._pool")    # not imported: no pool of process_pool
    if pools is None:
        return None
    if isinstance(executor, pools.GivingWay):
        executor = executor.pool
    return executor.let_go_sent() if isinstance(executor, pools.Pool) else None


#: The longest path a Unix socket may have (its address less the final NUL byte).
SOCKET_PATH_MAX = 107 if sys.platform.startswith("linux") else 103
#: What multiprocessing adds to the path of its temporary folder's parent for the fork
#: server's socket: ``/pymp-XXXXXXXX/listener-XXXXXXXX``.
_SOCKET_SUFFIX = 33
#: Short folders for the pools' temporary folder when that of TMPDIR is too long.
SHORT_TEMP_FOLDERS = ("/tmp", "/var/tmp", "/usr/tmp")
_POOL_FOLDER_LOCK = threading.Lock()


def prepare_pool_folder() -> str | None:
    """Make this process's ``multiprocessing`` temporary folder (``pymp-*``, where the fork
    server's socket lies) in a short folder when the path of TMPDIR's is too long for a
    Unix socket.

    The socket's path is the folder's plus 33 characters, and a socket's path may not
    exceed :data:`SOCKET_PATH_MAX` bytes: with a longer TMPDIR (a deep scratch folder on
    a cluster), the first pool failed with ``AF_UNIX path too long``. The folder is then
    made in the first writable of :data:`SHORT_TEMP_FOLDERS` instead (only the socket
    lies there), and removed when the process ends. Nothing is done when the folder
    exists already or TMPDIR's path is short enough.

    Returns
    -------
    str or None
        The folder made, or None.
    """
    import tempfile
    from multiprocessing import process
    config = process.current_process()._config
    with _POOL_FOLDER_LOCK:     # two threads starting pools make one folder
        if config.get("tempdir") is not None or \
                len(os.fsencode(tempfile.gettempdir())) + _SOCKET_SUFFIX <= SOCKET_PATH_MAX:
            return None
        folder = _short_pool_folder()
        if folder is not None:
            config["tempdir"] = folder
        return folder


def remove_pool_folder() -> None:
    """Remove this process's ``multiprocessing`` temporary folder (``pymp-*``, made in
    TMPDIR or by :func:`prepare_pool_folder`), if one was made. Its own exit handler
    removes it too, but not in a process that ends by ``os._exit`` (the command line).
    The fork server keeps the socket it listens on open; no process connects to it any
    more."""
    process = sys.modules.get("multiprocessing.process")
    folder = process.current_process()._config.get("tempdir") if process else None
    if folder:
        import shutil
        shutil.rmtree(folder, ignore_errors=True)


def _short_pool_folder() -> str | None:
    """A new ``pymp-*`` folder in the first writable of :data:`SHORT_TEMP_FOLDERS`,
    removed when the process ends (as :mod:`multiprocessing` removes its own); None when
    none can take it."""
    import shutil
    import tempfile
    from multiprocessing import util
    for short in SHORT_TEMP_FOLDERS:
        if len(short) + _SOCKET_SUFFIX <= SOCKET_PATH_MAX and os.path.isdir(short) \
                and os.access(short, os.W_OK | os.X_OK):
            try:
                folder = tempfile.mkdtemp(prefix="pymp-", dir=short)
            except OSError:
                continue
            util.Finalize(None, shutil.rmtree, args=(folder,),
                          kwargs={"ignore_errors": True}, exitpriority=-100)
            return folder
    return None


def _set_preload(ctx, preload: Sequence[str]) -> None:
    """What the fork server imports when it starts: ``preload`` after
    :func:`preload_own_only`, else :data:`PRELOAD` and ``preload``; then
    :mod:`armfit._server_exit`, so that the server ends at once when this process has
    ended."""
    modules = tuple(preload) if _OWN_ONLY and preload else (*PRELOAD, *preload)
    ctx.set_forkserver_preload(list(dict.fromkeys((*modules, SERVER_EXIT))))


def start_fork_server(preload: Sequence[str] = ()) -> None:
    """Start this process's fork server now, importing what :func:`process_pool` would
    have it import for a pool with ``preload``, and return at once.

    The server imports its modules alongside whatever this process does meanwhile (the
    command line imports the command's own modules and reads its inputs), so the first
    pool's workers are ready sooner: they are forked from the server once it has its
    modules. Started as :func:`process_pool` starts it (from a thread with SIGINT
    blocked, in :func:`child_environment`). Does nothing where pools start their workers
    otherwise (``spawn``), once the server runs, or after ``stop_workers(final=True)``;
    a server that fails to start is started again by the first pool, which reports it.

    Parameters
    ----------
    preload : sequence of str
        As :func:`process_pool`'s.
    """
    if start_method() != "forkserver" or _FINAL:
        return
    from multiprocessing import get_context
    _set_preload(get_context("forkserver"), preload)
    prepare_pool_folder()
    starter = threading.Thread(target=_start_server, name="armfit-fork-server", daemon=True)
    starter.start()
    starter.join()


def fork_server_running() -> bool:
    """Whether this process's fork server has started (by :func:`start_fork_server`, or
    with the workers of a pool of :func:`process_pool`): a new pool's workers are then
    forked from it in milliseconds, its modules imported, instead of waiting for a new
    server to import them. False where pools do not start their workers by a fork
    server, and after ``stop_workers(final=True)``.

    Returns
    -------
    bool
    """
    return _SERVER_UP and not _FINAL


def _server_started() -> None:
    """A pool's workers have started: by the fork server, where that is the start method."""
    global _SERVER_UP
    if start_method() == "forkserver":
        _SERVER_UP = True


def _start_server() -> None:
    from multiprocessing import forkserver, resource_tracker
    with contextlib.suppress(Exception), _STARTING, child_environment():
        if _FINAL:
            return
        # the resource tracker first: starting it unblocks SIGINT in the calling thread
        # (it blocks the signal only while it spawns its own process), and the server
        # must start with SIGINT blocked
        resource_tracker.ensure_running()
        if hasattr(signal, "pthread_sigmask"):
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        forkserver.ensure_running()
        _server_started()


def process_pool(jobs: int, preload: Sequence[str] = ()) -> ProcessPoolExecutor:
    """A new pool of ``jobs`` worker processes that ignore SIGINT, started by
    :func:`start_method` (all at its first task); the caller shuts it down.

    Parameters
    ----------
    jobs : int
        Worker processes (at least 1).
    preload : sequence of str
        Modules the fork server imports for its workers besides :data:`PRELOAD`, or
        instead of it after :func:`preload_own_only` (only when this pool is the one
        that starts the server).

    Returns
    -------
    concurrent.futures.ProcessPoolExecutor
    """
    from multiprocessing import get_context

    from armfit._pool import Hooks, Pool
    ctx = get_context(start_method())
    if ctx.get_start_method() == "forkserver":
        _set_preload(ctx, preload)
        prepare_pool_folder()
    hooks = Hooks(initializer=worker_start, initargs=(_lifeline(),), ready=_ready,
                  starting=_STARTING, stopped=lambda: _FINAL, environment=child_environment,
                  forget=_forget, started=_server_started)
    with child_environment():   # its queues start the resource tracker
        pool = Pool(max(1, int(jobs)), ctx, hooks)
    with _OPEN_LOCK:
        _OPEN[pool] = threading.get_ident()
    return pool


def _forget(pool) -> None:
    """A pool of :func:`process_pool` is shut down: out of the record of open pools."""
    with _OPEN_LOCK:
        _OPEN.pop(pool, None)


@contextlib.contextmanager
def executor_for(executor: Executor | None = None, jobs: int = 1, *,
                 tasks: int | None = None, preload: Sequence[str] = ()
                 ) -> Iterator[Executor | None]:
    """The executor to run tasks on, for the ``with`` block.

    Parameters
    ----------
    executor : concurrent.futures.Executor, optional
        Yielded as it is, and not shut down at the end of the block.
    jobs : int
        Without ``executor``: with ``jobs`` > 1 (and more than one task), a new
        :func:`process_pool` of ``min(jobs, tasks)`` workers, shut down at the end of the
        block (pending tasks cancelled; waited for). Else None: run the tasks here.
    tasks : int, optional
        How many tasks will run, when known.
    preload : sequence of str
        See :func:`process_pool`.

    Yields
    ------
    concurrent.futures.Executor or None
    """
    if executor is not None:
        yield executor
        return
    n = int(jobs) if tasks is None else min(int(jobs), int(tasks))
    if n <= 1:
        yield None
        return
    pool = process_pool(n, preload)
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def iter_tasks(fn: Callable, tasks: Iterable, jobs: int = 1, preload: Sequence[str] = (),
               chunksize: int = 1, *, executor: Executor | None = None) -> Iterator:
    """``fn(t)`` for each of ``tasks``, yielded in task order as they are done.

    Parameters
    ----------
    fn : callable
        A module-level function (picklable) of one argument.
    tasks : iterable
        Its arguments.
    jobs, preload
        Without ``executor``: see :func:`executor_for` (with one task or none, it runs
        here).
    chunksize : int
        Tasks sent to a process pool at a time (other executors may ignore it).
    executor : concurrent.futures.Executor, optional
        Runs every task (even a single one); never shut down here.

    Yields
    ------
    object
        ``fn(t)``, in the order of ``tasks``. The first error of a task, in task order,
        is raised; pending tasks are then cancelled (also when the caller stops early
        and closes the generator).

    Notes
    -----
    No task is held here once it has run (here) or been handed to the executor (which
    lets it go when it is done): a caller that keeps no task of its own holds the
    memory of those not yet done only.
    """
    tasks = list(tasks)
    if executor is None and (jobs <= 1 or len(tasks) <= 1):
        tasks.reverse()
        while tasks:
            yield fn(tasks.pop())
        return
    with executor_for(executor, jobs, tasks=len(tasks), preload=preload) as ex:
        results = ex.map(fn, tasks, chunksize=chunksize)   # every task submitted
        del tasks
        try:
            yield from results
        finally:
            close = getattr(results, "close", None)   # cancels what is pending
            if close is not None:
                close()


def map_tasks(fn: Callable, tasks: Iterable, jobs: int = 1, preload: Sequence[str] = (),
              chunksize: int = 1, *, executor: Executor | None = None) -> list:
    """The list of :func:`iter_tasks` (same parameters).

    Returns
    -------
    list
        ``[fn(t) for t in tasks]``.
    """
    return list(iter_tasks(fn, tasks, jobs, preload, chunksize, executor=executor))


def read_ahead(fn: Callable, items: Iterable, *, name: str = "armfit-read") -> Iterator:
    """``fn(item)`` for each of ``items``, yielded in order, each computed in one thread
    of its own while the caller works on the one before: reading the next trial file
    (pyarrow decodes and numpy checks without Python's lock) overlaps computing on this
    one, in the one process of ``--jobs 1``.

    Parameters
    ----------
    fn : callable
        Of one argument; its work should release the interpreter's lock for long
        stretches (file reading, decoding, numpy on whole arrays), or nothing is gained.
    items : iterable
        Its arguments.
    name : str
        The thread's name prefix.

    Yields
    ------
    object
        ``fn(item)``, in the order of ``items``; the error ``fn`` raised for an item is
        raised in its turn. At most two results exist at a time: the one yielded and the
        next, computed meanwhile. Closing the generator (or an error) waits for the call
        under way and drops its outcome. With one item or none, ``fn`` runs here.
    """
    items = list(items)
    if len(items) <= 1:
        yield from map(fn, items)
        return
    from concurrent.futures import ThreadPoolExecutor
    pool = ThreadPoolExecutor(1, thread_name_prefix=name)
    try:
        pending = pool.submit(fn, items[0])
        for item in items[1:]:
            value = pending.result()
            pending = pool.submit(fn, item)
            yield value
            del value        # the caller is done with it: one result waits, not two
        yield pending.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def cancel_pools(thread: int) -> None:
    """Shut down every open pool of :func:`process_pool` made in the thread whose ident
    is ``thread``, cancelling its pending tasks and waiting for those running: the
    function running in that thread (e.g. a stage run in the background) then fails at
    its next task instead of finishing its work.

    Parameters
    ----------
    thread : int
        A :func:`threading.get_ident` value.
    """
    with _OPEN_LOCK:
        pools = [p for p, t in _OPEN.items() if t == thread]
    for pool in pools:
        pool.shutdown(wait=True, cancel_futures=True)


def stop_workers(final: bool = False) -> None:
    """Kill every child process of this process started by :mod:`multiprocessing` (every
    worker of every pool; the command line's answer to SIGINT and SIGTERM) and reap them.

    A pool being started is let finish starting first (at most 30 s), so none of its
    workers is missed. Uses only the public :class:`multiprocessing.Process` objects of
    :func:`multiprocessing.active_children`; safe in a signal handler of the main thread
    (pools start their workers from threads of their own), and does nothing when no
    worker was ever started. Every open pool of :func:`process_pool` then fails the tasks
    it has not finished, at once, and is not waited for when shut down (its owner shuts
    it down on the way out).

    Parameters
    ----------
    final : bool
        The process is ending: no pool starts workers any more (a stage still running in
        another thread fails at once instead of starting new ones).
    """
    global _FINAL
    mp = sys.modules.get("multiprocessing")
    got = _STARTING.acquire(timeout=30.0)
    try:
        if final:
            _FINAL = True
        if mp is None:
            return
        try:
            children = mp.active_children()
        except Exception:  # pragma: no cover - interpreter shutting down
            children = []
        for p in children:
            with contextlib.suppress(Exception):   # already gone
                p.kill()
        for p in children:
            with contextlib.suppress(Exception):
                p.join(timeout=2.0)
        with _OPEN_LOCK:
            pools = list(_OPEN)
        for pool in pools:     # each of process_pool (an armfit._pool.Pool)
            pool._armfit_stopped()
    finally:
        if got:
            _STARTING.release()
