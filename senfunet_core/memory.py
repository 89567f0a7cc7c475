"""Memory: how much this process may use (`memory_budget`), and giving freed heap memory back to
the operating system.

A process in a container (docker --memory, a Kubernetes limit) or a systemd unit with MemoryMax
sees the host's memory in /proc/meminfo and sysconf, not its limit: past the limit the kernel kills
it. `memory_budget` takes the tightest memory limit of its cgroup and the cgroup's ancestors
(cgroup v2 memory.max, or v1 memory.limit_in_bytes) as well.

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
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


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


# cgroup v1 writes "no limit" as a page-rounded 2**63 - 1
_V1_UNLIMITED = 1 << 62


@dataclass(frozen=True)
class MemoryBudget:
    total_bytes: int  # the machine's memory, or the cgroup's limit when lower
    available_bytes: int  # of it, what is free now (MemAvailable; under a limit, the limit less the cgroup's usage)
    limited_by: str  # "" (the machine's memory), or the cgroup file whose limit holds


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None  # cgroup v2 writes "max" for no limit


def cgroup_memory_limit(*, proc_cgroup: Path = Path("/proc/self/cgroup"),
                        root: Path = Path("/sys/fs/cgroup")) -> tuple[int, int, Path] | None:
    """(limit, usage, the limit's file) of the tightest memory limit over this process's cgroup and
    its ancestors (cgroup v2, else v1's memory controller), or None without a limit. Usage is that of
    the cgroup the limit is set on (memory.current or memory.usage_in_bytes): everything it holds
    counts against the limit."""
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    for line in lines:  # "0::/path" (v2), "4:memory:/path" (v1)
        _, controllers, path = line.split(":", 2) if line.count(":") >= 2 else ("", "", "")
        if controllers == "":
            base, limit_name, usage_name = root, "memory.max", "memory.current"
        elif "memory" in controllers.split(","):
            base, limit_name, usage_name = root / "memory", "memory.limit_in_bytes", "memory.usage_in_bytes"
        else:
            continue
        # the process's cgroup as mounted here (with a cgroup namespace, a container sees its own as the root)
        deepest = base / path.strip("/")
        folders = [deepest, *deepest.parents[:len(deepest.relative_to(base).parts)]] if deepest != base else [base]
        limits = [(value, folder) for folder in folders
                  if (value := _read_int(folder / limit_name)) is not None and value < _V1_UNLIMITED]
        if limits:
            limit, folder = min(limits)
            return limit, _read_int(folder / usage_name) or 0, folder / limit_name
    return None


def memory_budget(*, proc_cgroup: Path = Path("/proc/self/cgroup"), root: Path = Path("/sys/fs/cgroup"),
                  meminfo: Path = Path("/proc/meminfo")) -> MemoryBudget:
    """How much memory this process may use: the machine's (sysconf, MemAvailable), or its cgroup's
    limit where that is lower (`cgroup_memory_limit`)."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    available = total
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = int(line.split()[1]) * 1024
    except OSError:
        pass
    limit = cgroup_memory_limit(proc_cgroup=proc_cgroup, root=root)
    if limit is None or limit[0] >= total:
        return MemoryBudget(total, available, "")
    limit_bytes, usage_bytes, file = limit
    return MemoryBudget(limit_bytes, min(available, max(0, limit_bytes - usage_bytes)), str(file))
