"""What this process may use of the machine: memory (`memory_budget`) and CPUs (`usable_cpus`).

A process in a container (docker --memory/--cpus, a Kubernetes limit) or a systemd unit with
MemoryMax/CPUQuota sees the host's memory in /proc/meminfo and sysconf, and the host's CPUs in its
affinity mask, not its limits: past a memory limit the kernel kills it, and threads beyond a CPU
quota only wait for each other. Both take the tightest limit over the process's cgroup and its
ancestors (cgroup v2, else v1's memory and cpu controllers), as the kernel enforces them.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

__all__ = ["MemoryBudget", "cgroup_memory_limit", "memory_budget", "usable_cpus"]

_PROC_CGROUP = Path("/proc/self/cgroup")
_ROOT = Path("/sys/fs/cgroup")
# cgroup v1 writes "no limit" as a page-rounded 2**63 - 1
_V1_UNLIMITED = 1 << 62


def _read(path: Path) -> str | None:
    try:
        return path.read_text().strip()
    except OSError:
        return None


def _read_int(path: Path) -> int | None:
    text = _read(path)
    return int(text) if text is not None and text.lstrip("-").isdigit() else None  # v2 writes "max" for none


def _cgroup_folders(controller: str, *, proc_cgroup: Path, root: Path) -> tuple[list[Path], bool]:
    """This process's cgroup folder for `controller` and its ancestors up to the mount's root,
    deepest first (with a cgroup namespace, a container sees its own cgroup as the root; folders that
    do not exist here are left out), and whether they are cgroup v2. Empty when the process is in no
    such cgroup."""
    # "0::/path" (v2), "4:memory:/path" or "5:cpu,cpuacct:/path" (v1: mounted as cpu,cpuacct, or as cpu)
    for line in (_read(proc_cgroup) or "").splitlines():
        if line.count(":") < 2:
            continue
        _, controllers, path = line.split(":", 2)
        if controllers == "":
            base, v2 = root, True
        elif controller in controllers.split(","):
            mounted = [root / name for name in (controllers, controller) if (root / name).is_dir()]
            base = mounted[0] if mounted else root / controller
            v2 = False
        else:
            continue
        deepest = base / path.strip("/")
        folders = [deepest, *list(deepest.parents)[:len(deepest.relative_to(base).parts)]]
        return [folder for folder in folders if folder.is_dir()], v2
    return [], False


def cgroup_memory_limit(*, proc_cgroup: Path = _PROC_CGROUP, root: Path = _ROOT) -> tuple[int, int, Path] | None:
    """(limit, usage, the limit's file) of the tightest memory limit over this process's cgroup and
    its ancestors, or None without a limit. Usage is that of the cgroup the limit is set on
    (memory.current or memory.usage_in_bytes): everything it holds counts against the limit."""
    folders, v2 = _cgroup_folders("memory", proc_cgroup=proc_cgroup, root=root)
    limit_name, usage_name = ("memory.max", "memory.current") if v2 else ("memory.limit_in_bytes",
                                                                        "memory.usage_in_bytes")
    limits = [(value, folder) for folder in folders
              if (value := _read_int(folder / limit_name)) is not None and 0 <= value < _V1_UNLIMITED]
    if not limits:
        return None
    limit, folder = min(limits)
    return limit, _read_int(folder / usage_name) or 0, folder / limit_name


@dataclass(frozen=True)
class MemoryBudget:
    total_bytes: int  # the machine's memory, or the cgroup's limit when lower
    available_bytes: int  # of it, what is free now (MemAvailable; under a limit, the limit less the cgroup's usage)
    limited_by: str  # "" (the machine's memory), or the cgroup file whose limit holds


def memory_budget(*, proc_cgroup: Path = _PROC_CGROUP, root: Path = _ROOT,
                  meminfo: Path = Path("/proc/meminfo")) -> MemoryBudget:
    """How much memory this process may use: the machine's (sysconf, MemAvailable), or its cgroup's
    limit where that is lower (`cgroup_memory_limit`)."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    available = total
    for line in (_read(meminfo) or "").splitlines():
        if line.startswith("MemAvailable:"):
            available = int(line.split()[1]) * 1024
    limit = cgroup_memory_limit(proc_cgroup=proc_cgroup, root=root)
    if limit is None or limit[0] >= total:
        return MemoryBudget(total, available, "")
    limit_bytes, usage_bytes, file = limit
    return MemoryBudget(limit_bytes, min(available, max(0, limit_bytes - usage_bytes)), str(file))


def usable_cpus(*, proc_cgroup: Path = _PROC_CGROUP, root: Path = _ROOT) -> int:
    """The CPUs this process may keep busy: its affinity mask's, or fewer under a CPU quota over its
    cgroup or an ancestor (v2 cpu.max "quota period", v1 cpu.cfs_quota_us / cpu.cfs_period_us),
    rounded up; at least 1."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    folders, v2 = _cgroup_folders("cpu", proc_cgroup=proc_cgroup, root=root)
    for folder in folders:
        if v2:
            quota_text, _, period_text = (_read(folder / "cpu.max") or "max").partition(" ")
            quota = int(quota_text) if quota_text.isdigit() else None
            period = int(period_text) if period_text.isdigit() else None
        else:
            quota, period = _read_int(folder / "cpu.cfs_quota_us"), _read_int(folder / "cpu.cfs_period_us")
        if quota is not None and quota > 0 and period:
            cpus = min(cpus, math.ceil(quota / period))
    return max(1, cpus)
