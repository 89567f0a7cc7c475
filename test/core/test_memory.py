"""senfunet_core.memory and machine: giving freed memory back to the OS; what the process may use of the machine."""
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


def _cgroup(tmp_path: Path, membership: str, files: dict[str, str]) -> dict[str, Path]:
    """A /proc/self/cgroup and a cgroup mount as files, as the kernel shows them."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "cgroup").write_text(membership)
    for name, text in files.items():
        (tmp_path / "fs" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "fs" / name).write_text(text + "\n")
    return {"proc_cgroup": tmp_path / "cgroup", "root": tmp_path / "fs"}


def test_a_container_memory_limit_bounds_the_default_map(tmp_path):
    """In a container (docker --memory 4g) /proc/meminfo and sysconf show the host's memory: the
    default map bound took half of it, and past the container's limit the kernel kills the node, map
    and all. The tightest limit over the process's cgroup and its ancestors holds, less what the
    cgroup already uses; cgroup v2 and v1, with and without a cgroup namespace."""
    from senfunet_core.map_bound import memory_bound_blocks
    from senfunet_core.machine import cgroup_memory_limit, memory_budget

    gb = 1 << 30
    # v2 in a cgroup namespace: the container's cgroup is the mount's root
    v2 = _cgroup(tmp_path / "v2", "0::/\n", {"memory.max": str(4 * gb), "memory.current": str(gb)})
    assert cgroup_memory_limit(**v2) == (4 * gb, gb, tmp_path / "v2" / "fs" / "memory.max")
    # v2, a systemd unit whose slice holds the limit (its own says max)
    unit = _cgroup(tmp_path / "unit", "0::/robot.slice/senfunet.service\n", {
        "robot.slice/senfunet.service/memory.max": "max", "robot.slice/senfunet.service/memory.current": str(gb),
        "robot.slice/memory.max": str(2 * gb), "robot.slice/memory.current": str(gb // 2)})
    assert cgroup_memory_limit(**unit)[:2] == (2 * gb, gb // 2)
    # v1, the process's cgroup path as the host names it, under the memory controller
    v1 = _cgroup(tmp_path / "v1", "5:cpu,cpuacct:/docker/abc\n4:memory:/docker/abc\n0::/\n", {
        "memory/docker/abc/memory.limit_in_bytes": str(3 * gb), "memory/docker/abc/memory.usage_in_bytes": "0",
        "memory/memory.limit_in_bytes": "9223372036854771712"})
    assert cgroup_memory_limit(**v1)[:2] == (3 * gb, 0)
    # no limit anywhere (v1 writes a huge number, v2 "max"): the machine's memory
    free = _cgroup(tmp_path / "free", "4:memory:/\n", {"memory/memory.limit_in_bytes": "9223372036854771712",
                                                       "memory/memory.usage_in_bytes": str(gb)})
    assert cgroup_memory_limit(**free) is None and memory_budget(**free).limited_by == ""
    meminfo = tmp_path / "meminfo"
    meminfo.write_text(f"MemTotal: 1 kB\nMemAvailable: {64 * gb // 1024} kB\n")
    budget = memory_budget(**v2, meminfo=meminfo)
    assert (budget.total_bytes, budget.available_bytes) == (4 * gb, 3 * gb) and budget.limited_by.endswith("memory.max")
    assert memory_bound_blocks(1 << 20, budget=budget) == 2 * 1024  # half of 4 GB at 1 MB a block


def test_a_container_cpu_quota_bounds_the_threads(tmp_path):
    """docker --cpus 2 on a host of many cores: the affinity mask names every core, and the node ran as
    many weighting-net threads, which only waited for each other (and for integration's core)."""
    import os

    from senfunet_core.machine import usable_cpus

    cores = len(os.sched_getaffinity(0))
    v2 = _cgroup(tmp_path / "v2", "0::/\n", {"cpu.max": "150000 100000"})
    assert usable_cpus(**v2) == min(cores, 2)  # 1.5 CPUs: two threads may keep them busy
    v1 = _cgroup(tmp_path / "v1", "3:cpu,cpuacct:/docker/abc\n", {
        "cpu,cpuacct/docker/abc/cpu.cfs_quota_us": "100000", "cpu,cpuacct/docker/abc/cpu.cfs_period_us": "100000"})
    assert usable_cpus(**v1) == 1
    unlimited = _cgroup(tmp_path / "free", "0::/\n", {"cpu.max": "max 100000"})
    assert usable_cpus(**unlimited) == cores
