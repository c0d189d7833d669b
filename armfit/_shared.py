"""Arrays handed to worker processes through shared memory rather than their pipes.

A task's arguments reach a worker of a process pool pickled and written through a pipe:
the bytes are copied into the pipe 64 KiB at a time, each piece waking the reader and
waiting for it, and read out again on the other side. For a trial's samples (a few MB
each, the whole study in `armfit run`, where the run's own process reads the trials
and its workers estimate them) the wake-ups cost more CPU time than the copies: on the
2-core machine, 81 trials of 2.7 MB handed from one process to another, both otherwise
idle, took 0.5-0.8 s of the sender's time and 0.3-0.4 s of the receiver's.

:class:`Blocks` keeps a few shared-memory blocks of this process and reuses them: an
array is copied into a free block (:meth:`Blocks.put`, no page fault once a block has
been used), the task carries the block's name and the arrays' layout (:class:`Shared`,
a few hundred bytes), and the worker copies them out (:meth:`Shared.take`) and closes
the block at once; the block is free again when the task is done
(:meth:`Blocks.release`). The same 81 trials then took 0.02 s of the sender's time and
about 0.1 s of the receiver's. In `armfit run -j2`, whose processes are busy anyway,
the gain is smaller: 810 trials of 60 s took 0.93 times as long as through the pipe
(median of 7 alternated pairs). The copies hold the same values, bit for bit: nothing
computed changes.

The blocks are :class:`multiprocessing.shared_memory.SharedMemory` segments: removed
by :meth:`Blocks.close`, and registered with multiprocessing's resource tracker, which
removes those of a process killed before it could. Their pages are reserved when they
are made: where the shared memory is full (a container's /dev/shm is 64 MiB by default)
a task carries its arrays through the pipe as before. Used only on Linux, with armfit's
own process pools (:func:`for_executor`); another executor (a pool of threads, a dask
cluster whose workers may run on other machines) gets the arrays through its own
channel.
"""

from __future__ import annotations

import errno
import os
import sys
import threading
import weakref
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Blocks", "Shared", "for_executor"]

_MIB = 1 << 20
#: Where Linux keeps POSIX shared memory (a tmpfs, 64 MiB in a default Docker container).
SHM_FOLDER = "/dev/shm"


@dataclass(frozen=True)
class Shared:
    """Arrays placed in a shared-memory block by :meth:`Blocks.put`, as a task carries
    them: the block's ``name`` and, per array, its shape, dtype (``dtype.str``), memory
    order ("C" or "F", the array's own) and byte offset in the block."""

    name: str
    layout: tuple[tuple[tuple[int, ...], str, str, int], ...]

    def take(self) -> list[np.ndarray]:
        """Copies of the arrays (in a worker process): the block is attached, copied
        from and closed."""
        from multiprocessing import shared_memory

        block = shared_memory.SharedMemory(name=self.name)
        try:
            return [np.ndarray(shape, np.dtype(dtype), buffer=block.buf, offset=offset,
                               order=order).copy(order=order)
                    for shape, dtype, order, offset in self.layout]
        finally:
            block.close()


class Blocks:
    """Shared-memory blocks of this process, each holding one task's arrays at a time,
    reused from task to task (thread-safe: a block is released by the pool's thread
    that completes the task's future)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._free: list = []
        self._all: dict[str, object] = {}
        self._closed = False
        # blocks of an owner that forgot to close them go with it (at the latest when
        # the interpreter ends), not with the resource tracker's warning
        weakref.finalize(self, _remove_all, self._all)

    def put(self, arrays: Sequence[np.ndarray]) -> tuple[Shared, object] | None:
        """Copy ``arrays`` into a free block, the smallest large enough (a new one, of
        whole MiB, when none is free or large enough; a free block too small is removed
        first, so that their number stays that of the tasks in flight). Returns what the
        task carries and the block, to hand to :meth:`release` once the task is done;
        None when the shared memory has no room for a new block (the task then carries
        the arrays themselves): its pages are reserved when the block is made, so that a
        full tmpfs is an error here rather than a crash (SIGBUS) when the block is
        written."""
        arrays = [np.asarray(a) for a in arrays]
        offsets, size = [], 0
        for a in arrays:
            offsets.append(size)
            size += -(-a.nbytes // 64) * 64      # each array on a 64-byte boundary
        with self._lock:
            if self._closed:
                raise RuntimeError("the shared-memory blocks are closed")
            fits = [b for b in self._free if b.size >= size]
            block = min(fits, key=lambda b: b.size) if fits else (
                self._free[0] if self._free else None)
            if block is not None:
                self._free.remove(block)
        if block is not None and block.size < size:
            self._remove(block)
            block = None
        if block is None:
            # whole MiB: trials of a study differ in length, and a block replaced by a
            # larger one costs a page fault per page of the new block at its first use
            block = _new_block(-(-max(size, 1) // _MIB) * _MIB)
            if block is None:
                return None
            with self._lock:
                self._all[block.name] = block
        orders = ["F" if a.flags.f_contiguous and not a.flags.c_contiguous else "C"
                  for a in arrays]
        for a, order, offset in zip(arrays, orders, offsets, strict=True):
            np.ndarray(a.shape, a.dtype, buffer=block.buf, offset=offset, order=order)[...] = a
        layout = tuple((a.shape, a.dtype.str, order, offset)
                       for a, order, offset in zip(arrays, orders, offsets, strict=True))
        return Shared(block.name, layout), block

    def release(self, block) -> None:
        """The task that carried ``block``'s arrays is done: the block is free again
        (removed if the blocks were closed meanwhile)."""
        with self._lock:
            if not self._closed:
                self._free.append(block)
                return
        self._remove(block)

    def close(self) -> None:
        """Remove every block (a worker still copying from one keeps its copy of the
        mapping; a task not yet started then fails, as its future is not waited for)."""
        with self._lock:
            self._closed = True
            blocks = list(self._all.values())
            self._free.clear()
        for block in blocks:
            self._remove(block)

    def _remove(self, block) -> None:
        with self._lock:
            if self._all.pop(block.name, None) is None:
                return
        _discard(block)


def _new_block(size: int):
    """A new shared-memory block of ``size`` bytes whose pages are reserved, or None
    when the shared memory has no room for them."""
    from multiprocessing import shared_memory

    block = shared_memory.SharedMemory(create=True, size=size)
    fd = os.open(os.path.join(SHM_FOLDER, block.name.lstrip("/")), os.O_RDWR)
    try:
        os.posix_fallocate(fd, 0, size)
    except OSError as exc:
        _discard(block)
        if exc.errno in (errno.ENOSPC, errno.ENOMEM, errno.EFBIG):
            return None
        raise
    finally:
        os.close(fd)
    return block


def _discard(block) -> None:
    """Close and remove ``block``."""
    try:
        block.close()
    except BufferError:     # pragma: no cover - an array still views it
        pass
    try:
        block.unlink()
    except FileNotFoundError:   # pragma: no cover - removed by the tracker
        pass


def _remove_all(blocks: dict) -> None:
    """Close and remove the blocks of a :class:`Blocks` no longer referenced."""
    for block in list(blocks.values()):
        _discard(block)
    blocks.clear()


def for_executor(executor) -> Blocks | None:
    """:class:`Blocks` for tasks handed to ``executor`` when it is one of armfit's own
    process pools on Linux (its workers run on this machine and attach the blocks, kept
    in :data:`SHM_FOLDER`); None otherwise."""
    from armfit.workers import is_process_pool
    if (not sys.platform.startswith("linux") or not os.path.isdir(SHM_FOLDER)
            or not is_process_pool(executor)):
        return None
    return Blocks()
