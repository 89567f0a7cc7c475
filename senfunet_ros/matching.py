"""Matching a depth frame with its sensor's pose and colour: the buffers of pose and colour
messages, each looked up at a depth stamp.

Not thread-safe: their owner (`ingest.Ingest`) calls them under its lock.
"""
from __future__ import annotations

import bisect
import math
import statistics
from collections import deque

import numpy as np

from senfunet_ros.geometry import extrapolate_pose, interpolate_pose, pose_difference, pose_jump

__all__ = ["ALTERNATION_CHECK_EVERY", "ColorBuffer", "PoseBuffer", "alternation_m", "pose_conflict"]

# a pose republished at its stamp differs from the first beyond this (metres, and the rotation
# matrices' entries): float noise of a re-encoded message stays far below
_SAME_POSE_TOL = 1e-6
# poses that zig-zag (`alternation_m`): over this many of the newest, neighbours typically this far
# apart (motion between two poses of one stream is far less), each typically within this share of that step of
# the pose two before it (a stream moving on goes twice the step in two)
_ALTERNATION_POSES = 12
_ALTERNATION_MIN_STEP_M = 0.02
_ALTERNATION_RETURN_SHARE = 0.25
ALTERNATION_CHECK_EVERY = 8  # poses (a link's transforms) checked at every this many: they come by the hundred a second


def pose_conflict(first: np.ndarray, again: np.ndarray) -> str | None:
    """What differs between two poses (4x4) given for one stamp, or None when they are the same pose.

    The first is kept: frames may already have been posed with it, so keeping it makes the frames
    independent of when the consumer took them, and a stream cannot rewrite the trajectory behind
    the map (a driver bug, or two publishers on one topic)."""
    first, again = np.asarray(first, np.float64), np.asarray(again, np.float64)
    if np.abs(first - again).max() <= _SAME_POSE_TOL:
        return None
    moved_m, turned_deg = pose_difference(first, again)
    return (f"another pose for a stamp already given ({moved_m:.3f} m, {turned_deg:.2f} deg from the first, which "
            "is kept); check the driver: two publishers on one topic, or one that rewrites its past poses?")


def alternation_m(poses: list[np.ndarray]) -> float | None:
    """When the newest of these poses (4x4, in stamp order) zig-zag (each about where the one two before
    it was, and the typical step between neighbours at least _ALTERNATION_MIN_STEP_M): that step, in
    metres; else None. Two publishers of one pose or TF link give that (a localiser and an odometry,
    interleaved): interpolated between them, every frame lies on a smear between two trajectories, and
    no jump check sees it, as the same step comes every time."""
    if len(poses) < _ALTERNATION_POSES:
        return None
    # scalar maths: checked on every TF link, numpy's per-call cost on 12 points would be most of the time
    positions = [(float(T[0, 3]), float(T[1, 3]), float(T[2, 3])) for T in poses[-_ALTERNATION_POSES:]]
    step_m = statistics.median(math.dist(a, b) for a, b in zip(positions, positions[1:]))
    return_m = statistics.median(math.dist(a, b) for a, b in zip(positions, positions[2:]))
    alternates = step_m >= _ALTERNATION_MIN_STEP_M and return_m < _ALTERNATION_RETURN_SHARE * step_m
    return step_m if alternates else None


class PoseBuffer:
    """One sensor's stamped poses (T_world_camera), in stamp order."""

    def __init__(self) -> None:
        self._stamps: list[int] = []
        self._poses: list[np.ndarray] = []

    def add(self, stamp_ns: int, T: np.ndarray, *, keep: int) -> str | None:
        """Insert a pose, keeping the `keep` newest. A stamp already held keeps its first pose: returns
        what differs when the new one is another pose (`pose_conflict`), None otherwise."""
        i = bisect.bisect_left(self._stamps, stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == stamp_ns:
            return pose_conflict(self._poses[i], T)
        self._stamps.insert(i, stamp_ns)
        self._poses.insert(i, T)
        excess = len(self._stamps) - keep
        if excess > 0:
            del self._stamps[:excess]
            del self._poses[:excess]
        return None

    def newest_ns(self) -> int | None:
        """The newest pose's stamp, or None."""
        return self._stamps[-1] if self._stamps else None

    def alternation_m(self) -> float | None:
        """`alternation_m` of the newest poses."""
        return alternation_m(self._poses)

    def at(self, stamp_ns: int, *, tolerance_ns: int, waited_too_long: bool) -> tuple[np.ndarray | None, str | None]:
        """The pose at a depth stamp, interpolated between the poses around it: (T, None); or
        (None, None) when it must wait for a later pose (none yet, or only the newest, too far); or
        (None, reason) when it has none: "pose_timeout" (no later pose came in time), "pose_gap" (the
        poses around it are further than tolerance_ns from it, or the stream jumped between them:
        `jump_across`)."""
        stamps = self._stamps
        i = bisect.bisect_left(stamps, stamp_ns)
        if i == len(stamps):  # no pose at or after the frame yet
            return None, ("pose_timeout" if waited_too_long else None)
        if stamps[i] == stamp_ns:
            return self._poses[i], None
        if i == 0 or stamp_ns - stamps[i - 1] > tolerance_ns:
            return None, "pose_gap"
        if stamps[i] - stamp_ns > tolerance_ns:
            # the next pose is far but the newest: a nearer one may still come (a pose a glitching driver
            # stamped ahead stays the newest while the stream's poses fill in before it)
            return None, (None if i == len(stamps) - 1 and not waited_too_long else "pose_gap")
        if pose_jump(self._poses, i) is not None:  # interpolated, the frame would lie on a smear between two places
            return None, "pose_gap"
        s = (stamp_ns - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        return interpolate_pose(self._poses[i - 1], self._poses[i], s), None

    def jump_across(self, stamp_ns: int) -> tuple[int, int, float, float] | None:
        """When the poses either side of `stamp_ns` are a jump (`geometry.pose_jump`: a localiser
        relocalising), their stamps and the jump (metres, degrees); else None."""
        i = bisect.bisect_left(self._stamps, stamp_ns)
        if i == 0 or i == len(self._stamps):
            return None
        jump = pose_jump(self._poses, i)
        return None if jump is None else (self._stamps[i - 1], self._stamps[i], *jump)

    def around(self, stamp_ns: int) -> tuple[int | None, int | None]:
        """The stamps of the newest pose before `stamp_ns` and of the oldest at or after it (None: none)."""
        i = bisect.bisect_left(self._stamps, stamp_ns)
        return (self._stamps[i - 1] if i else None), (self._stamps[i] if i < len(self._stamps) else None)

    def longest_pause_ns(self, from_ns: int, to_ns: int) -> int:
        """The longest interval between consecutive poses over from_ns..to_ns (the poses around its ends
        included); the whole span when fewer than two poses cover it."""
        stamps = self._stamps
        lo, hi = max(bisect.bisect_left(stamps, from_ns) - 1, 0), bisect.bisect_right(stamps, to_ns) + 1
        window = stamps[lo:hi]
        if len(window) < 2:
            return to_ns - from_ns
        return max(b - a for a, b in zip(window, window[1:]))

    def extrapolate(self, stamp_ns: int, *, tolerance_ns: int) -> np.ndarray | None:
        """The pose at a depth stamp after the newest pose, continuing the two newest poses' motion at
        constant velocity (`extrapolate_pose`), when it lies within tolerance_ns past the newest; None
        when it lies further, there are fewer than two poses, or a pose at or after it exists. Only for
        frames no later pose will come for (the stream ended): a later pose gives a better one."""
        stamps = self._stamps
        if len(stamps) < 2 or stamp_ns <= stamps[-1] or stamp_ns - stamps[-1] > tolerance_ns:
            return None
        s = (stamp_ns - stamps[-2]) / (stamps[-1] - stamps[-2])
        return extrapolate_pose(self._poses[-2], self._poses[-1], s)

    def clear(self) -> None:
        self._stamps.clear()
        self._poses.clear()


class ColorBuffer:
    """One sensor's latest colour images (at most `size`), matched to depth by the nearest stamp."""

    def __init__(self, size: int) -> None:
        self._images: deque[tuple[int, np.ndarray]] = deque(maxlen=size)
        self.seen = False  # whether the sensor ever sent colour: then depth waits for it

    def add(self, stamp_ns: int, rgb: np.ndarray) -> None:
        self.seen = True
        self._images.append((stamp_ns, rgb))

    def ready(self, stamp_ns: int, newest_ns: int | None, waited_too_long: bool) -> bool:
        """Whether a depth frame can be matched now. Colour is published next to depth: give it the
        chance to arrive (until the colour stream's newest stamp `newest_ns` reaches the frame)
        unless waiting longer would exceed the limit (then the frame goes without colour)."""
        if self.seen and not waited_too_long:
            return newest_ns is not None and newest_ns >= stamp_ns
        return True

    def match(self, stamp_ns: int, *, tolerance_ns: int, floor_ns: int | None) -> np.ndarray | None:
        """The colour image nearest the depth stamp within tolerance_ns, as it came (the caller lays
        it on the depth: `conversions.color_for_depth`); None if there is none. Images too old for
        any later frame are forgotten: a later frame may be older than this one (two frames crossed),
        but newer than `floor_ns` (None: any may come; `timeline.Timelines.depth_floor_ns`)."""
        best: tuple[int, np.ndarray] | None = None
        for stamp, rgb in self._images:
            gap = abs(stamp - stamp_ns)
            if gap <= tolerance_ns and (best is None or gap < abs(best[0] - stamp_ns)):
                best = (stamp, rgb)
        if floor_ns is not None:
            while self._images and self._images[0][0] < min(stamp_ns, floor_ns) - tolerance_ns:
                self._images.popleft()
        return None if best is None else best[1]

    def clear(self) -> None:
        self._images.clear()
