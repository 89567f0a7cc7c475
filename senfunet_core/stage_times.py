"""Seconds spent per stage (integration, feature net, alpha, fusion, marching cubes, ...)."""
from __future__ import annotations

import threading

__all__ = ["StageTimes"]


class StageTimes:
    """Per stage: the seconds of its last run (`last_s`) and summed over all runs (`total_s`).
    Shared by the engine's parts, so that none of them keeps a reference back to the engine."""

    def __init__(self) -> None:
        self.last_s: dict[str, float] = {}
        self.total_s: dict[str, float] = {}
        self._lock = threading.Lock()  # integrating and meshing threads add at once

    def add(self, **stages: float) -> None:
        with self._lock:
            self.last_s.update(stages)
            for name, seconds in stages.items():
                self.total_s[name] = self.total_s.get(name, 0.0) + seconds
