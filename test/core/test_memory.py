"""senfunet_core.memory: giving freed memory back to the operating system."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from senfunet_core.memory import large_allocations_outside_the_heap


def _rss_kb() -> int:
    """Resident memory, counted exactly (smaps_rollup walks the page tables; VmRSS in
    /proc/self/status may lag behind by per-CPU batches)."""
    rollup = Path("/proc/self/smaps_rollup")
    if not rollup.is_file():
        pytest.skip("no /proc/self/smaps_rollup")
    return int(rollup.read_text().split("\nRss:")[1].split()[0])


def test_large_allocations_are_given_back_when_freed():
    """With the node's malloc setting (`node.limit_malloc`), a large temporary is unmapped when
    freed: the resident memory falls back (glibc's default would keep such blocks in its heap once
    its threshold rose)."""
    if not large_allocations_outside_the_heap():
        pytest.skip("not glibc")
    np.ones(24 << 20, np.uint8)  # freed at once: glibc's default would now keep 16 MB blocks in its heap
    for _ in range(3):
        before = _rss_kb()
        block = np.ones(16 << 20, np.uint8)
        assert _rss_kb() - before > 12 << 10
        del block
        assert _rss_kb() - before < 4 << 10
