"""Giving freed heap memory back to the operating system.

glibc's malloc keeps memory freed by small and medium allocations (and, once its mmap threshold
has grown, by large ones) in its arenas for reuse: after a phase that allocated and freed a lot of
temporaries (the weighting net over every block, the mesh of the whole map), the process's RSS
stays at that phase's peak, and the next phase's peak adds on top of it. `release_free_memory`
asks malloc to return what is free; elsewhere (other C libraries) it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


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
