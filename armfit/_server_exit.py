"""The last module of armfit's fork server's preload (see :func:`armfit.workers.process_pool`):
the server ends without tearing its interpreter down.

The server exits when the process that started it has ended. Its interpreter then frees
the modules it imported for its workers (numpy, armfit's engine, scipy's optimiser):
35-130 ms on a 2-core machine, while the server still holds the standard output and
error it inherited. A shell pipeline (``armfit estimate … | tee log``), or a program that
reads a command's output to its end, waited that long after ``armfit`` itself had ended
(``benchmarks/bench_pipe.py`` measures the wait).

Imported by the server's preload (``multiprocessing.forkserver.main`` is on the call
stack), this module registers an exit handler that runs first at the server's exit
(handlers run last registered first): it flushes the standard streams and ends the
process at once, with status 0, the status of the server's own exit (no process waits
for the server's status). Imported anywhere else it does nothing. The workers are
forked from the server and end by ``os._exit`` themselves: the handler never runs in
them.
"""

from __future__ import annotations

import atexit
import os
import sys

__all__: list[str] = []


def _exit_now() -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(0)


def _preloaded_by_fork_server() -> bool:
    """Whether this import runs inside ``multiprocessing.forkserver.main``."""
    frame = sys._getframe(1)
    while frame is not None:
        code = frame.f_code
        if code.co_name == "main" and \
                os.path.basename(code.co_filename) == "forkserver.py" and \
                os.path.basename(os.path.dirname(code.co_filename)) == "multiprocessing":
            return True
        frame = frame.f_back
    return False


if _preloaded_by_fork_server():
    atexit.register(_exit_now)
