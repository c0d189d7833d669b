"""The standard streams of the ``armfit`` process, made safe before anything is written.

:func:`install` (called first thing by the console entry point) puts every standard
stream on a footing where no way it is set up can turn a finished command into a crash:

- A standard stream closed when armfit starts (``>&-``, ``2>&-``) gets ``/dev/null`` in
  its place, so no file armfit opens later takes its number (a data file that would
  receive the messages) and every process armfit starts inherits valid streams.
- **Standard output** carries data (tables, ``--json``). When it cannot be written —
  closed at start, disk full (``> /dev/full``), the reader gone (a broken pipe), any
  other refusal of the system — the write raises :class:`~armfit.errors.OutputError`
  (exit 73) saying "standard output" and the reason; the command line reports it in one
  line like any output that cannot be written. The files the command wrote before are
  kept. What is left buffered is dropped (the stream is pointed at ``/dev/null``), so
  nothing fails a second time on the way out.
- **Standard error** carries messages only. When it cannot be written (closed, full, a
  broken pipe), the messages are dropped and the command goes on to its normal exit
  code.
- A character the streams' encoding cannot represent (``PYTHONIOENCODING=ascii``, a C
  locale) is written as a backslash escape (``µ`` as ``\\xb5``) instead of failing.
"""

from __future__ import annotations

import codecs
import errno
import io
import os
import select
import sys

from armfit.errors import OutputError

#: How a character the encoding lacks is written on both streams.
ERRORS = "backslashreplace"


def _devnull_at(fd: int) -> None:
    """Point file descriptor ``fd`` at /dev/null (it is closed, or its writes fail)."""
    null = os.open(os.devnull, os.O_RDWR)
    try:
        if null != fd:
            os.dup2(null, fd)
    finally:
        if null != fd:
            os.close(null)


def _is_open(fd: int) -> bool:
    try:
        os.fstat(fd)
    except OSError:
        return False
    return True


class _StreamWriter(io.RawIOBase):
    """The raw writer under a standard stream: ``os.write`` on its descriptor, with the
    stream's answer to a failure (see the module docstring).

    Parameters
    ----------
    fd : int
        1 (standard output: a failure raises OutputError) or 2 (standard error: a
        failure drops the message).
    closed_at_start : bool
        The descriptor was closed when armfit started: the first write fails.
    """

    def __init__(self, fd: int, closed_at_start: bool) -> None:
        super().__init__()
        self._fd = fd
        self._closed_at_start = closed_at_start
        self.failed = False      # after the first failure every write is dropped

    @property
    def name(self) -> str:
        return "<stdout>" if self._fd == 1 else "<stderr>"

    def writable(self) -> bool:
        return True

    def fileno(self) -> int:
        return self._fd

    def isatty(self) -> bool:
        return not self.failed and not self._closed_at_start and os.isatty(self._fd)

    def write(self, data) -> int:
        n = len(memoryview(data).cast("B"))
        if self.failed:
            return n
        if self._closed_at_start:
            self._fail(OSError(errno.EBADF, "it was closed when armfit started"))
            return n
        while True:
            try:
                return os.write(self._fd, data)
            except BlockingIOError:      # a non-blocking descriptor shared with others
                select.select([], [self._fd], [], 1.0)
            except OSError as exc:
                self._fail(exc)
                return n

    def _fail(self, exc: OSError) -> None:
        self.failed = True
        try:
            _devnull_at(self._fd)
        except OSError:  # pragma: no cover - no /dev/null
            pass
        if self._fd == 1:
            reason = exc.strerror or os.strerror(exc.errno or errno.EIO)
            raise OutputError(f"standard output: cannot be written: {reason}")


class _AsciiText(io.TextIOWrapper):
    """A text stream of an ASCII encoding that shows no binary ``buffer``: click writes
    UTF-8 bytes to the buffer of a stream it finds ASCII-encoded, which would bypass
    :data:`ERRORS`; without a buffer it writes the text here, as everyone else does."""

    @property
    def buffer(self):
        return None


def _text_stream(fd: int, like, closed_at_start: bool) -> io.TextIOWrapper:
    raw = _StreamWriter(fd, closed_at_start)
    encoding = getattr(like, "encoding", None) or "utf-8"
    # standard error line by line, as Python sets it up; standard output as it was
    line_buffering = fd == 2 or bool(getattr(like, "line_buffering", False))
    ascii_only = codecs.lookup(encoding).name == "ascii"
    return (_AsciiText if ascii_only else io.TextIOWrapper)(
        io.BufferedWriter(raw), encoding=encoding, errors=ERRORS,
        line_buffering=line_buffering)


def install() -> None:
    """Make the standard streams safe (see the module docstring): ``/dev/null`` on a
    closed descriptor 0, 1 or 2, and new ``sys.stdout`` and ``sys.stderr`` over
    descriptors 1 and 2 that answer a failure as described there and degrade the
    characters their encoding lacks. Call once, before anything is written."""
    closed = {fd: not _is_open(fd) for fd in (0, 1, 2)}
    for fd in (0, 1, 2):
        if closed[fd]:
            _devnull_at(fd)
    for fd, attr in ((1, "stdout"), (2, "stderr")):
        old = getattr(sys, attr)
        if old is not None:
            try:
                old.flush()
            except (OSError, ValueError):
                pass
        setattr(sys, attr, _text_stream(fd, old, closed[fd]))


__all__ = [
    "ERRORS", "install",
]
