"""Working arrays kept between calls: a hot path that takes a fresh array of a few MB each time
pays for its page faults each time (the kernel zeroes every page it hands out).

    store: dict[str, np.ndarray] = {}
    samples = scratch(store, "samples", n, np.int64)   # store["samples"][:n], grown when too small

`ThreadScratch` keeps one store per thread, for code that several threads run side by side.
"""
from __future__ import annotations

import threading

import numpy as np

__all__ = ["ThreadScratch", "scratch"]


def scratch(store: dict[str, np.ndarray] | None, name: str, size: int, dtype: type) -> np.ndarray:
    """A working array of `size` elements (its contents undefined), reused from `store` when the
    one there is big enough and of this dtype; a fresh one without a store."""
    if store is None:
        return np.empty(size, dtype)
    array = store.get(name)
    if array is None or array.dtype != dtype or len(array) < size:
        array = store[name] = np.empty(size, dtype)
    return array[:size]


class ThreadScratch:
    """`scratch` stores, one per calling thread."""

    def __init__(self) -> None:
        self._local = threading.local()

    def array(self, name: str, size: int, dtype: type) -> np.ndarray:
        """The calling thread's working array `name` (see `scratch`)."""
        return scratch(self._local.__dict__, name, size, dtype)

    def release(self) -> None:
        """Let go of every thread's arrays (after a bulk job: the next call allocates again); a
        caller still using one keeps it until it is done."""
        self._local = threading.local()
