"""The engine's update lock, and integration's wait for an eviction (the engine's threading model:
see `senfunet_core.engine`).

One update, extraction, save or eviction holds the map at a time. Integration that outgrew the
map's hard bound (updates come too rarely to keep it) must not go on until blocks are evicted: it
evicts itself when the lock is free, or waits until the update holding it has evicted at its next
safe point (between two batches, not at its end, which can be a second away). Whoever ends an
eviction or releases the lock wakes the waiters. No thread polls.
"""
from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator

__all__ = ["UpdateLock"]


class UpdateLock:
    """Reentrant: an update's own steps (alpha, meshing, evictions) take it again."""

    def __init__(self) -> None:
        self._lock = threading.RLock()
        # reentrant too: a waiter that evicts notifies while it holds the condition
        self._eviction_done = threading.Condition(threading.RLock())

    @contextlib.contextmanager
    def held(self, *, wait: bool = True) -> Iterator[bool]:
        """Hold the lock for the block (yields True); with wait=False, only if it is free now (else
        yields False at once, not holding it). Leaving wakes an integration waiting for an eviction
        (it may now evict itself)."""
        if not self._lock.acquire(blocking=wait):
            yield False
            return
        try:
            yield True
        finally:
            self._lock.release()
            self.evicted()

    def evicted(self) -> None:
        """Blocks were evicted (or the lock released): wake the waiters to look at the bound again."""
        with self._eviction_done:
            self._eviction_done.notify_all()

    def wait_for_eviction(self, over_bound: Callable[[], bool], evict: Callable[[], object]) -> None:
        """Until `over_bound()` is False: `evict()` (under the lock) whenever the lock is free, else
        wait to be woken. The waiter holds the condition from the failed try to the wait, so no
        wake-up falls in between. Call without the engine's data lock."""
        with self._eviction_done:
            while over_bound():
                if self._lock.acquire(blocking=False):
                    try:
                        evict()
                    finally:
                        self._lock.release()
                else:
                    self._eviction_done.wait()
