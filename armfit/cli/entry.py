"""The ``armfit`` console entry point: signal handling first, then the command group.

SIGINT (Ctrl-C) and SIGTERM are turned into exceptions in the main thread
(KeyboardInterrupt and :class:`armfit.errors.Terminated`), after every worker process is
killed, so that each atomic output being written removes its temporary on the way out.
The command group prints one line and exits 130 (SIGINT) or 143 (SIGTERM); a signal
that arrives while the command modules are still being imported gets the same
treatment. A second signal while stopping is ignored (cleanup is not cut short).

The process ends with :func:`os._exit` once the command has returned and its outputs
are flushed (:func:`_exit_now`). This module imports only ``signal`` and ``sys`` before
the handlers are in place, so they are installed before numpy, pandas or pyarrow load.
(A signal during the Python interpreter's own start-up, before any armfit code runs, is
beyond reach.)
"""

from __future__ import annotations

import signal
import sys

_stopping = False


def _on_signal(signum, frame) -> None:
    global _stopping
    if _stopping:
        return  # already stopping: let the cleanup finish
    _stopping = True
    import threading

    from armfit.errors import Terminated
    from armfit.workers import stop_workers
    # the pools' helper threads fail when their workers are killed: the user asked for
    # the stop, so their errors are not printed (the one line below is)
    threading.excepthook = lambda args: None
    stop_workers(final=True)
    if signum == signal.SIGTERM:
        raise Terminated()
    raise KeyboardInterrupt()


def install_signal_handlers() -> None:
    """Route SIGINT and SIGTERM through :func:`_on_signal` (main thread only)."""
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)


def _stop_line(exc: BaseException) -> int:
    from armfit.errors import EXIT_INTERRUPTED, EXIT_TERMINATED, Terminated
    term = isinstance(exc, Terminated)
    sys.stderr.write("armfit: terminated (SIGTERM)\n" if term else "armfit: interrupted\n")
    sys.stderr.flush()
    return EXIT_TERMINATED if term else EXIT_INTERRUPTED


def main() -> None:
    """Console entry point of ``armfit``."""
    install_signal_handlers()
    try:
        from armfit.cli.main import cli  # numpy, pandas, pyarrow, click, ...
    except KeyboardInterrupt as exc:  # signal while importing: one line, no traceback
        sys.exit(_stop_line(exc))
    try:
        cli.main(prog_name="armfit")
    except KeyboardInterrupt as exc:  # outside a subcommand (e.g. while parsing options)
        sys.exit(_stop_line(exc))
    except SystemExit as exc:  # click ends every command this way
        _exit_now(exc)


def _exit_now(exc: SystemExit) -> None:
    """End the process with ``exc``'s status without tearing the interpreter down.

    Every output is written, closed and renamed into place by then, and the worker
    pools are shut down; what remains is freeing some 10^5 objects (arrays, tables,
    figures, modules), which takes about half a second. Standard output and error are
    flushed first; if that fails (a closed pipe), the normal exit reports it. Worker
    processes still running are waited for (:func:`multiprocessing.active_children`);
    the fork server ends by itself when this process does."""
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
        sys.stderr.flush()
    except (OSError, ValueError):
        raise exc from None
    if _stopping:
        # after a signal the workers were killed with tasks in their queues: the normal
        # exit runs multiprocessing's exit handler, which releases the queues' semaphores
        # (else the resource tracker reports them as leaked)
        raise exc from None
    mp = sys.modules.get("multiprocessing")
    if mp is not None:
        for child in mp.active_children():
            child.join()
    import os
    os._exit(status)


__all__ = [
    "install_signal_handlers", "main",
]
