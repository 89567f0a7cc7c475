"""Giving freed heap memory back to the operating system.

glibc's malloc keeps memory freed by small and medium allocations (and, once its mmap threshold
has grown, by large ones) in its arenas for reuse: after a phase that allocated and freed a lot of
temporaries (the weighting net over every block, the mesh of the whole map), the process's RSS
stays at that phase's peak, and the next phase's peak adds on top of it. `release_free_memory`
asks malloc to return what is free; elsewhere (other C libraries) it does nothing.

`large_allocations_outside_the_heap` stops that at the source for large blocks: glibc raises its
mmap threshold each time a large mapped block is freed, so that the weighting net's per-batch
tensors end up in the arenas, where two threads' batches leave a heap several batches deep behind
them. A fixed threshold keeps every allocation above it in its own mapping, returned when freed,
at the price of page faults each time such a block is allocated again. The live node sets it (a
long run's memory matters most there: `node.limit_malloc`); replay, a batch job, does not (on the
sample bag it cost replay a third more time for a tenth less peak memory).
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


_M_MMAP_THRESHOLD = -3  # glibc's mallopt parameter number


@functools.cache
def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name) if name else None
    except OSError:
        return None


@functools.cache
def large_allocations_outside_the_heap(threshold_bytes: int = 4 << 20) -> bool:
    """Process-wide, once: allocations of at least threshold_bytes get their own mapping, given
    back to the OS when freed (glibc `mallopt(M_MMAP_THRESHOLD)`, which also stops the threshold
    from rising). Returns whether it was set (False where the C library is not glibc)."""
    libc = _libc()
    mallopt = getattr(libc, "mallopt", None) if libc is not None else None
    return bool(mallopt is not None and mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)) == 1)


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        return None if libc is None else libc.malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None


def release_free_memory() -> None:
    """Return the heap's free memory to the OS (glibc `malloc_trim`; elsewhere a no-op)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)
