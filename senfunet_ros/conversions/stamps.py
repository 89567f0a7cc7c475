"""Stamps: builtin_interfaces/Time <-> integer nanoseconds."""
from __future__ import annotations

from typing import Any

__all__ = ["ns_to_stamp", "stamp_to_ns"]


def stamp_to_ns(stamp: Any) -> int:
    """builtin_interfaces/Time -> integer nanoseconds. ValueError for a nanosec field outside
    0..999999999 (it would be read as up to 4.3 s later: a stamp ahead, yet within time_jump_s)."""
    nanosec = int(stamp.nanosec)
    if not 0 <= nanosec < 1_000_000_000:
        raise ValueError(f"stamp nanosec {nanosec} is not within 0..999999999; fix the driver's stamps "
                         "(sec carries the whole seconds)")
    return int(stamp.sec) * 1_000_000_000 + nanosec


def ns_to_stamp(stamp_ns: int) -> tuple[int, int]:
    """Integer nanoseconds -> (sec, nanosec) for builtin_interfaces/Time."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    return sec, nanosec
