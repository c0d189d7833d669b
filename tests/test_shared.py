"""Arrays handed to worker processes through shared-memory blocks (armfit._shared): the
values and memory order that come out are those that went in, blocks are reused and
removed, and only armfit's own process pools use them."""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from armfit import _shared

SHM = Path(_shared.SHM_FOLDER)
pytestmark = pytest.mark.skipif(not SHM.is_dir(), reason="Linux's POSIX shared memory")


def _exists(name: str) -> bool:
    """Whether the segment ``name`` still exists (Linux lists them in /dev/shm)."""
    return (SHM / name.lstrip("/")).exists()


def _arrays() -> list[np.ndarray]:
    rng = np.random.default_rng(5)
    f_order = np.asfortranarray(rng.normal(size=(1001, 3)))   # as read_trial makes them
    c_order = rng.normal(size=(3, 257))
    ints = np.arange(-7, 6, dtype=np.int32)
    strided = rng.normal(size=(40, 6))[::3, 1]               # neither C nor F contiguous
    special = np.array([np.nan, -0.0, np.inf, -np.inf, 5e-324, 1.7976931348623157e308])
    return [f_order, c_order, ints, strided, special]


def test_arrays_through_a_block_are_the_same_bits_in_the_same_order():
    # the reference: the arrays put in; a contiguous array keeps its memory order (a
    # computation on a Fortran-ordered column then runs as it did on the original)
    blocks = _shared.Blocks()
    try:
        arrays = _arrays()
        shared, block = blocks.put(arrays)
        got = shared.take()
        for a, b in zip(arrays, got, strict=True):
            assert b.dtype == a.dtype and b.shape == a.shape
            # bit for bit (NaN payloads, the sign of zero, subnormals)
            assert np.ascontiguousarray(b).tobytes() == np.ascontiguousarray(a).tobytes()
            assert not np.shares_memory(a, b)
        assert got[0].flags.f_contiguous and not got[0].flags.c_contiguous
        assert got[1].flags.c_contiguous
        blocks.release(block)
    finally:
        blocks.close()


def test_a_released_block_is_reused_and_one_too_small_is_replaced():
    blocks = _shared.Blocks()
    try:
        small = np.ones(1000)
        first, block = blocks.put([small])
        blocks.release(block)
        again, block = blocks.put([small * 2])
        assert again.name == first.name          # the free block, reused
        np.testing.assert_array_equal(again.take()[0], small * 2)
        other, block2 = blocks.put([small])      # the first is in flight: a second block
        assert other.name != first.name
        blocks.release(block)
        blocks.release(block2)
        # 3 MiB do not fit a block of 1 MiB: one free block is removed, a larger made
        big, block3 = blocks.put([np.zeros(3 * 2**20 // 8 + 1)])
        assert block3.size == 4 * 2**20           # whole MiB
        assert sum(_exists(n) for n in (first.name, other.name)) == 1
        blocks.release(block3)
    finally:
        blocks.close()
    assert not any(_exists(n) for n in (first.name, other.name, big.name))


def test_closing_removes_every_block_even_one_in_flight_and_refuses_more():
    blocks = _shared.Blocks()
    a, block_a = blocks.put([np.arange(10.0)])
    b, _ = blocks.put([np.arange(20.0)])          # never released
    blocks.release(block_a)
    blocks.close()
    assert not _exists(a.name) and not _exists(b.name)
    blocks.release(block_a)                       # a task ending after the close
    with pytest.raises(RuntimeError):
        blocks.put([np.arange(3.0)])
    with pytest.raises(FileNotFoundError):        # a task not started: its block is gone
        b.take()


def test_only_armfit_process_pools_get_blocks():
    from armfit.workers import process_pool
    pool = process_pool(1)
    try:
        assert isinstance(_shared.for_executor(pool), _shared.Blocks)
    finally:
        pool.shutdown()
    with ThreadPoolExecutor(1) as threads:
        assert _shared.for_executor(threads) is None
    assert _shared.for_executor(None) is None


def test_blocks_never_closed_go_with_their_owner():
    import gc
    blocks = _shared.Blocks()
    shared, block = blocks.put([np.arange(5.0)])
    del blocks, block
    gc.collect()
    assert not _exists(shared.name)


def test_a_full_shared_memory_gives_no_block_and_leaves_none(monkeypatch):
    # a tmpfs with no room (a container's /dev/shm): the pages reserved when the block
    # is made (posix_fallocate) fail with ENOSPC, the block is removed and put gives
    # None (the task then carries its arrays through the pipe), never a SIGBUS later
    import errno
    made: list[str] = []

    def full(fd, offset, size):
        made.append(os.readlink(f"/proc/self/fd/{fd}"))
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)
    blocks = _shared.Blocks()
    try:
        assert blocks.put([np.arange(100.0)]) is None
    finally:
        blocks.close()
    assert made and not Path(made[0]).exists()
