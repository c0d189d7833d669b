"""The ``armfit`` console entry point: streams and signal handling first, then the group.

SIGINT (Ctrl-C) and SIGTERM are turned into exceptions in the main thread
(KeyboardInterrupt and :class:`armfit.errors.Terminated`), after every worker process is
killed, so that each atomic output being written removes its temporary on the way out.
The command group prints one line and exits 130 (SIGINT) or 143 (SIGTERM); a signal
that arrives while the command modules are still being imported gets the same
treatment.

Stopping always ends: once the way out has removed the partial outputs, the process
ends with :func:`os._exit` (no thread or pool of the stopped command is waited for); if
the way out itself has not ended within :data:`STOP_GRACE_S` seconds, or a second signal
arrives, the process ends at once with the same line and exit code. Either way every
temporary of its outputs still there is removed last
(:func:`armfit.io.atomic.remove_temporaries`), also one made just as the signal came.

The process ends with :func:`os._exit` also once the command has returned and its
outputs are flushed (:func:`_exit_now`). This module imports only ``signal``, ``sys``,
``_thread`` (all built in) and :mod:`armfit.errors` before the handlers are in place, so
they are installed before numpy, pandas or pyarrow load; the handler imports nothing
(a signal may come in the middle of an import). (A signal during the Python
interpreter's own start-up, before any armfit code runs, is beyond reach.) The standard
streams are made safe next (:mod:`armfit.cli.streams`): a closed or failing stream never
turns into a crash.
"""

from __future__ import annotations

import _thread
import signal
import sys

from armfit.errors import EXIT_INTERRUPTED, EXIT_TERMINATED, ArmfitError, Terminated

#: Seconds the way out of a stopped command may take before the process ends anyway.
STOP_GRACE_S = 5.0

_stopping = False
_finishing = False      # the command has ended: the process is about to exit
_stop_code = 0
_stop_said = False
#: Held while the stop line is written (taken without waiting: a signal handler may
#: run in the thread that holds it).
_SAY_LOCK = _thread.allocate_lock()


def _loaded(module: str, name: str):
    """``module.name`` if that module is imported (far enough to define it), else None.

    The handler runs wherever the main thread is, also in the middle of an import: it
    imports nothing itself (a module being imported is there only in part), and what is
    not imported yet has nothing to stop (no worker, no output).
    """
    return getattr(sys.modules.get(module), name, None)


def _on_signal(signum, frame) -> None:
    global _stopping, _stop_code
    code = EXIT_TERMINATED if signum == signal.SIGTERM else EXIT_INTERRUPTED
    if _stopping or _finishing:
        _stop_code = _stop_code or code
        _end_at_once()      # a second signal, or one while exiting: end now
    _stopping = True
    _stop_code = code
    # the pools' own threads fail when their workers are killed: the user asked for
    # the stop, so their errors are not printed (the one line below is)
    if sys.modules.get("threading") is not None:
        sys.modules["threading"].excepthook = lambda args: None
    _start_watchdog()
    stop_workers = _loaded("armfit.workers", "stop_workers")
    if stop_workers is not None:
        stop_workers(final=True)
    if signum == signal.SIGTERM:
        raise Terminated()
    raise KeyboardInterrupt()


def _start_watchdog() -> None:
    """Start :func:`_watchdog` in a thread that blocks SIGINT and SIGTERM.

    The kernel may hand a signal sent to the process to any thread that does not block
    it. One that lands on the watchdog only wakes the watchdog's sleep: the main thread,
    the only one that runs Python's handlers, sleeps on, and a second signal would wait
    for the grace to end. The new thread takes the mask in place when it starts, so the
    signals are blocked around its start (one that comes meanwhile waits, and reaches
    the main thread when its mask is put back).
    """
    block = getattr(signal, "pthread_sigmask", None)
    if block is None:   # pragma: no cover - Windows: no per-thread masks
        _thread.start_new_thread(_watchdog, ())
        return
    old = block(signal.SIG_BLOCK, (signal.SIGINT, signal.SIGTERM))
    try:
        _thread.start_new_thread(_watchdog, ())
    finally:
        block(signal.SIG_SETMASK, old)


def _watchdog() -> None:
    import time
    time.sleep(STOP_GRACE_S)
    _end_at_once()


def _remove_temporaries() -> None:
    """Remove the temporaries of this process's outputs that are still there (see
    :func:`armfit.io.atomic.remove_temporaries`)."""
    remove_temporaries = _loaded("armfit.io.atomic", "remove_temporaries")
    if remove_temporaries is None:
        return      # nothing was written
    try:
        remove_temporaries()
    except Exception:  # pragma: no cover - a folder that cannot be read any more
        pass


def _remove_pool_folder() -> None:
    """Remove the pools' temporary folder (:func:`armfit.workers.remove_pool_folder`):
    its own exit handler does not run when the process ends by ``os._exit``."""
    remove = _loaded("armfit.workers", "remove_pool_folder")
    if remove is None:
        return      # no pool was started
    try:
        remove()
    except Exception:  # pragma: no cover - interpreter state unknown
        pass


def _end_at_once() -> None:
    """End a stopping process now: kill the workers left (without waiting), remove the
    temporaries of its outputs, say the one line if not said yet, and exit with the
    stop's code."""
    import os
    active_children = _loaded("multiprocessing", "active_children")
    if active_children is not None:
        try:
            children = active_children()
        except Exception:  # pragma: no cover - interpreter state unknown
            children = []
        for child in children:
            try:
                child.kill()
            except Exception:  # pragma: no cover - already gone
                pass
    _remove_temporaries()
    _remove_pool_folder()
    try:
        _say_stop(_stop_code)
    except BaseException:  # pragma: no cover - the stream is gone
        pass
    os._exit(_stop_code)


def _on_unraisable(unraisable) -> None:
    """``sys.unraisablehook``: a signal's exception raised where Python cannot raise it
    (the handler ran inside a finaliser, ``__del__`` or a weakref callback, which the
    garbage collector may call in the middle of any import or computation) would be
    printed and dropped, and the command would go on as if no signal had come. The stop
    is carried out at once instead (:func:`_end_at_once`); anything else is printed as
    Python prints it."""
    if _stopping and isinstance(unraisable.exc_value, (KeyboardInterrupt, Terminated)):
        _end_at_once()
    sys.__unraisablehook__(unraisable)


def install_signal_handlers() -> None:
    """Route SIGINT and SIGTERM through :func:`_on_signal` (main thread only), and a
    signal's exception that Python could not raise through :func:`_on_unraisable`."""
    sys.unraisablehook = _on_unraisable
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)


def _say_stop(code: int) -> None:
    global _stop_said
    if _stopping:   # once, whichever of the way out, the watchdog, a second signal
        if _stop_said or not _SAY_LOCK.acquire(blocking=False):
            return
        _stop_said = True
    try:
        sys.stderr.write("armfit: terminated (SIGTERM)\n" if code == EXIT_TERMINATED
                         else "armfit: interrupted\n")
        sys.stderr.flush()
    finally:
        if _stopping:
            _SAY_LOCK.release()


def stop_line(exc: BaseException) -> int:
    """Say on stderr that the command was stopped by ``exc`` (KeyboardInterrupt, or
    :class:`armfit.errors.Terminated` for SIGTERM), once per process when a signal
    stopped it; return the exit code (130 or 143).

    Parameters
    ----------
    exc : BaseException

    Returns
    -------
    int
    """
    code = EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED
    _say_stop(code)
    return code


def wrapped_stop(exc: BaseException) -> KeyboardInterrupt | None:
    """The signal's exception (KeyboardInterrupt or :class:`armfit.errors.Terminated`)
    that ``exc`` wraps, else None.

    Python wraps some exceptions raised while it runs library code: a signal that arrives
    while a class is created during an import surfaces as ``RuntimeError: Error calling
    __set_name__ ...`` whose cause is the KeyboardInterrupt. Such a stop is still a stop.

    Parameters
    ----------
    exc : BaseException

    Returns
    -------
    KeyboardInterrupt or None
    """
    seen: set[int] = set()
    cur: BaseException | None = exc
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return cur
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return None


def main() -> None:
    """Console entry point of ``armfit``."""
    install_signal_handlers()
    try:
        from armfit.cli import streams
        from armfit.workers import (
            one_blas_thread,
            preload_own_only,
            system_arrow_pool,
            tune_allocator,
        )
        streams.install()
        tune_allocator()
        one_blas_thread()    # before numpy loads
        system_arrow_pool()  # before pyarrow loads
        preload_own_only()   # a command starts one pool: its workers load what it runs
        from armfit.cli.main import cli  # numpy, pandas, pyarrow, click, ...
    except KeyboardInterrupt as exc:  # signal while importing: one line, no traceback
        _exit_now(SystemExit(stop_line(exc)))
    except Exception as exc:  # a signal Python wrapped while importing, else a bug
        stop = wrapped_stop(exc)
        if stop is None:
            raise
        _exit_now(SystemExit(stop_line(stop)))
    try:
        cli.main(prog_name="armfit")
    except KeyboardInterrupt as exc:  # outside a subcommand (e.g. while parsing options)
        _exit_now(SystemExit(stop_line(exc)))
    except ArmfitError as exc:  # outside a subcommand: --help or --version unwritable
        _exit_now(SystemExit(_error_line(exc)))
    except SystemExit as exc:  # click ends every command this way
        _exit_now(exc)


def _error_line(exc: BaseException) -> int:
    """One line on stderr for ``exc`` (an ArmfitError); its exit code."""
    sys.stderr.write(f"armfit: error: {exc}\n")
    sys.stderr.flush()
    return getattr(exc, "exit_code", 1)


def _exit_now(exc: SystemExit) -> None:
    """End the process with ``exc``'s status without tearing the interpreter down.

    Every output is written, closed and renamed into place by then (or, after a signal,
    removed), and the worker pools are shut down; what remains is freeing some 10^5
    objects (arrays, tables, figures, modules), which takes about half a second.
    Standard output and error are flushed first; standard output that cannot take what
    is left in its buffer is one more line and exit 73, unless the command failed
    already (:mod:`armfit.cli.streams`). A signal from here on ends the process at once
    (:func:`_end_at_once`). Worker processes still running are waited for
    (:func:`multiprocessing.active_children`), except after a signal (they were killed,
    and the pools' threads may wait forever for them); the fork server and the resource
    tracker end by themselves when this process and its workers have (the tracker
    removes the semaphores of the pools' queues then); the temporary folder of the pools
    is removed here (:func:`_remove_pool_folder`)."""
    import os
    global _finishing
    if _stopping and not exc.code:
        _end_at_once()   # a signal's exception caught and dropped on the way: still a stop
    _finishing = True
    code = exc.code
    if code is None:
        status = 0
    elif isinstance(code, int):
        status = code
    else:
        sys.stderr.write(f"{code}\n")
        status = 1
    try:
        sys.stdout.flush()
    except ArmfitError as failed:  # standard output refused the last of its data
        status = status or _error_line(failed)
    except (OSError, ValueError):  # pragma: no cover - not the stream of streams.install
        status = status or 1
    try:
        sys.stderr.flush()
    except (OSError, ValueError):  # pragma: no cover - not the stream of streams.install
        pass
    if _stopping:   # also a temporary made just as the signal came
        _remove_temporaries()
    mp = sys.modules.get("multiprocessing")
    if mp is not None and not _stopping:
        for child in mp.active_children():
            child.join()
    _remove_pool_folder()
    os._exit(status)


__all__ = [
    "STOP_GRACE_S", "install_signal_handlers", "main", "stop_line",
]
