"""senfunet_core.memory: giving freed memory back to the operating system."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

# Run in a fresh interpreter: in a process that already freed large blocks into its heap (earlier
# tests), a new large allocation may be served from those free chunks, whatever the threshold.
_CHECK = """
import numpy as np
from pathlib import Path
from senfunet_core.memory import large_allocations_outside_the_heap

def rss_kb():  # exact (smaps_rollup walks the page tables; VmRSS may lag by per-CPU batches)
    return int(Path("/proc/self/smaps_rollup").read_text().split("\\nRss:")[1].split()[0])

if not large_allocations_outside_the_heap():
    print("not glibc")
    raise SystemExit(0)
np.ones(24 << 20, np.uint8)  # freed at once: glibc's default would now keep 16 MB blocks in its heap
for _ in range(3):
    before = rss_kb()
    block = np.ones(16 << 20, np.uint8)
    grown = rss_kb() - before
    del block
    print(grown, rss_kb() - before)
"""


def test_large_allocations_are_given_back_when_freed():
    """With the node's malloc setting (`node.limit_malloc`), a large temporary is unmapped when
    freed: the resident memory falls back (glibc's default would keep such blocks in its heap once
    its threshold rose)."""
    if not Path("/proc/self/smaps_rollup").is_file():
        pytest.skip("no /proc/self/smaps_rollup")
    out = subprocess.run([sys.executable, "-c", _CHECK], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[2], check=True).stdout.split("\n")
    if out[0] == "not glibc":
        pytest.skip("not glibc")
    for line in filter(None, out):
        grown_kb, left_kb = map(int, line.split())
        assert grown_kb > 12 << 10 and left_kb < 4 << 10, out


def test_scratch_arrays_are_reused_per_thread_and_per_dtype_until_released():
    import threading

    import numpy as np

    from senfunet_core.scratch import ThreadScratch, scratch

    store: dict = {}
    first = scratch(store, "a", 100, np.int64)
    assert np.shares_memory(scratch(store, "a", 60, np.int64), first)  # big enough: the same memory
    assert len(scratch(store, "a", 60, np.int64)) == 60
    assert not np.shares_memory(scratch(store, "a", 200, np.int64), first)  # too small: grown
    assert scratch(store, "a", 10, np.float32).dtype == np.float32  # another dtype: a new array
    pool = ThreadScratch()
    mine = pool.array("w", 50, np.uint16)
    assert np.shares_memory(pool.array("w", 50, np.uint16), mine)
    theirs: list[np.ndarray] = []
    worker = threading.Thread(target=lambda: theirs.append(pool.array("w", 50, np.uint16)))
    worker.start()
    worker.join()
    assert not np.shares_memory(theirs[0], mine)  # another thread: its own
    pool.release()
    assert not np.shares_memory(pool.array("w", 50, np.uint16), mine)
