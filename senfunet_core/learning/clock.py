"""Active wall time of a training run: wall time minus the time the process was stopped."""
from __future__ import annotations

import time
from typing import Any, cast

_PAUSE_WATCHER = r"""
import os, struct, sys, time
from multiprocessing import shared_memory
parent, name, tick, gap = int(sys.argv[1]), sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
memory = shared_memory.SharedMemory(name=name)
try:  # attaching is not owning (Python < 3.13 would unlink it at exit)
    from multiprocessing import resource_tracker
    resource_tracker.unregister(memory._name, "shared_memory")
except Exception:
    pass
paused, last = 0.0, time.monotonic()
while True:
    time.sleep(tick)
    now = time.monotonic()
    try:
        with open(f"/proc/{parent}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        break  # the trainer is gone
    if now - last > gap:  # this watcher was stopped too (a script pausing every background job)
        paused += now - last - tick
    elif state in ("T", "t"):  # only the trainer was stopped
        paused += now - last
    last = now
    memory.buf[:8] = struct.pack("d", paused)
"""


class ActiveClock:
    """Wall time minus the time the training process was stopped (SIGSTOP, e.g. by a script that
    pauses background jobs while benchmarks run on a shared machine). A small watcher process
    (it does not share the trainer's GIL, so long computations are not mistaken for pauses) checks
    the trainer's state every 0.2 s and counts the stopped time; when the watcher is stopped along
    with the trainer, the gap in its own ticks counts."""

    def __init__(self, tick_s: float = 0.2, gap_s: float = 2.0) -> None:
        import atexit
        import os
        import subprocess
        import sys
        from multiprocessing import shared_memory

        self.start = time.monotonic()
        self._memory: Any = cast(Any, shared_memory.SharedMemory(create=True, size=8))  # None once stopped
        self._memory.buf[:8] = bytes(8)
        self._watcher = subprocess.Popen([sys.executable, "-c", _PAUSE_WATCHER, str(os.getpid()), self._memory.name,
                                          str(tick_s), str(gap_s)])
        atexit.register(self.stop)

    @property
    def paused_s(self) -> float:
        import struct

        return float(struct.unpack("d", bytes(self._memory.buf[:8]))[0]) if self._memory is not None else self._final

    def wall(self) -> float:
        return time.monotonic() - self.start

    def active(self) -> float:
        return self.wall() - self.paused_s

    def stop(self) -> None:
        if self._memory is None:
            return
        self._final = self.paused_s
        self._watcher.kill()
        self._watcher.wait()
        self._memory.close()
        self._memory.unlink()
        self._memory = None
