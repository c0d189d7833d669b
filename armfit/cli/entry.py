"""The ``armfit`` console entry point: signal handling first, then the command group.

SIGINT (Ctrl-C) and SIGTERM are turned into exceptions in the main thread
(KeyboardInterrupt and :class:`armfit.errors.Terminated`), after every worker process is
killed, so that each atomic output being written removes its temporary on the way out.
The command group prints one line and exits 130 (SIGINT) or 143 (SIGTERM); a signal
that arrives while the command modules are still being imported gets the same
treatment. A second signal while stopping is ignored (cleanup is not cut short).

This module imports only ``signal`` and ``sys`` before the handlers are in place, so they
are installed before numpy, pandas or pyarrow load. (A signal during the Python
interpreter's own start-up, before any armfit code runs, is beyond reach.)
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
    from armfit.errors import Terminated
    from armfit.workers import stop_workers
    stop_workers()
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
