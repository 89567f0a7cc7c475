"""A small TF buffer without ROS: /tf and /tf_static transforms in, `T_target_source` at a stamp out.

Used by replay (bags carry /tf and /tf_static) and by the live node when tf2_ros cannot be
imported but tf2_msgs can. The tree is the usual one: each child frame has one parent; dynamic
links are interpolated at the stamp (lerp + slerp) between transforms at most `max_gap_s`, or 2.5 of
the link's typical intervals (a slowly published link), apart, but not across a jump (a step far
larger than the link's usual ones: a localiser relocalising); static ones hold at any time.

What breaks the tree is refused, transform by transform (the rest of its message is kept), with
an error naming the frames: NaN or a non-unit quaternion, a frame as its own parent or ancestor
(a cycle), and a second parent for a frame while its first is alive (two publishers of one
frame, e.g. a URDF and a static_transform_publisher both placing the camera: the first parent
stays; a dynamic link is taken over by another parent only after `REPARENT_AFTER_S` of silence in
the stream's stamps, a static link never). Of a static and a dynamic transform on the same
link, the newest kind holds. A dynamic transform for a stamp its link already has keeps the first
(`TfAdded.conflicts` says when the second differed).

Convention: `lookup(target, source, stamp_ns)` returns the 4x4 transform taking points in
`source` to `target` (`T_target_source`; with target = fixed frame and source = the camera's
optical frame, that is `T_world_camera`).
"""
from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass, field
from collections.abc import Iterable
from typing import Any

import numpy as np

from senfunet_ros.conversions.poses import transform_from_msg
from senfunet_ros.conversions.stamps import stamp_to_ns
from senfunet_ros.geometry import extrapolate_pose, interpolate_pose, invert_transform, pose_jump
from senfunet_ros.matching import ALTERNATION_CHECK_EVERY, alternation_m, pose_conflict

__all__ = ["REPARENT_AFTER_S", "TfAdded", "TfBuffer", "TfError", "TfNotConnected", "TfWait", "extrapolate_tf"]


class TfError(ValueError):
    """The transform cannot be had at that stamp: no path between the frames, or a gap in a link."""


class TfWait(TfError):
    """Not yet: a link has no transform at or after the stamp (it may still come)."""


class TfNotConnected(TfWait):
    """Not yet: no transforms join the two frames (those that would may still come). `unknown_frame`: one
    of them that no transform names (a typo, or a mount never published), when known."""

    def __init__(self, message: str, unknown_frame: str = "") -> None:
        super().__init__(message)
        self.unknown_frame = unknown_frame


# a link's transforms may be this many of its typical intervals apart around a lookup
_GAP_INTERVALS = 2.5
# a dynamic link silent this long (in stamps) may be taken over by another parent
REPARENT_AFTER_S = 1.0


def _typical_interval_ns(stamps: list[int], i: int) -> float:
    """The median interval of a link's (up to) 17 transforms up to index i, a lookup's right
    neighbour: its rate there (from its first two transforms on)."""
    recent = stamps[max(0, i - 16):i + 1]
    return float(np.median(np.diff(recent))) if len(recent) >= 2 else 0.0


class _Link:
    def __init__(self, parent: str) -> None:
        self.parent = parent
        self.static: np.ndarray | None = None
        self.stamps: list[int] = []  # sorted
        self.transforms: list[np.ndarray] = []
        self.added = 0  # dynamic transforms taken (at every ALTERNATION_CHECK_EVERY, checked for a zig-zag)
        self.zig_zag_said = False  # found zig-zagging (said once)


@dataclass(frozen=True)
class TfAdded:
    """What `TfBuffer.add_message` left out: dynamic transforms stamped too far ahead, behind their link or
    unset, the transforms it refused, each with the reason, and those that gave a stamp already given
    another value."""

    # dynamic transforms stamped after `latest_ns` (geometry_msgs/TransformStamped), as sent
    ahead: list[Any] = field(default_factory=list)
    # dynamic transforms stamped more than `behind_ns` before their link's newest (time went back?), as sent
    behind: list[Any] = field(default_factory=list)
    unstamped: list[str] = field(default_factory=list)  # dynamic transforms stamped 0 (unset): which link
    refused: list[str] = field(default_factory=list)
    # dynamic transforms for a stamp their link already had, with another value (the first is kept):
    # what differs, per transform
    conflicts: list[str] = field(default_factory=list)
    # dynamic links found zig-zagging between two places (two publishers interleaved: `matching.alternation_m`),
    # each said once: what, and the step
    alternating: list[str] = field(default_factory=list)


class TfBuffer:
    """Thread-safe. `max_links_history` transforms are kept per dynamic link."""

    def __init__(self, *, max_gap_s: float = 0.1, history: int = 2000) -> None:
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.history = history
        self._links: dict[str, _Link] = {}  # child frame -> link to its parent
        self._lock = threading.Lock()
        # the newest stamp of a dynamic transform taken: TF goes on while a camera pauses, so its own
        # stamps, not only the images', tell a stamp far ahead (Ingest.add_tf)
        self.newest_ns: int | None = None

    def add_message(self, msg: Any, *, static: bool, latest_ns: int | None = None,
                    behind_ns: int | None = None) -> TfAdded:
        """Every transform of a tf2_msgs/TFMessage (duck-typed) that `add` takes (`add_transforms`)."""
        return self.add_transforms(msg.transforms, static=static, latest_ns=latest_ns, behind_ns=behind_ns)

    def add_transforms(self, transforms: Iterable[Any], *, static: bool, latest_ns: int | None = None,
                       behind_ns: int | None = None) -> TfAdded:
        """Every geometry_msgs/TransformStamped (duck-typed) that `add` takes, but dynamic ones stamped
        after `latest_ns` (a stamp far in the future would stay its link's newest, and every lookup until
        then would find a gap) or more than `behind_ns` before their link's newest (a clock that went
        back: mixed into the old time's transforms, they would be cleared with them)."""
        added = TfAdded()
        for tf in transforms:
            try:
                what = f"transform {tf.header.frame_id} -> {tf.child_frame_id}"
                T = transform_from_msg(tf.transform.translation, tf.transform.rotation, what)
                stamp_ns = stamp_to_ns(tf.header.stamp)
                if not static and latest_ns is not None and stamp_ns > latest_ns:
                    added.ahead.append(tf)
                    continue
                if not static and stamp_ns == 0:  # kept, every one would be "another value for the same stamp"
                    added.unstamped.append(what)
                    continue
                if not static and behind_ns is not None and stamp_ns < self._newest_of(tf.child_frame_id) - behind_ns:
                    added.behind.append(tf)
                    continue
                conflict = self.add(tf.header.frame_id, tf.child_frame_id, stamp_ns, T, static=static)
                if conflict is not None:
                    added.conflicts.append(f"{what} at {stamp_ns * 1e-9:.3f} s: {conflict}")
                elif not static:
                    step_m = self._zig_zag(tf.child_frame_id.lstrip("/"))
                    if step_m is not None:
                        added.alternating.append(f"{what} zig-zags by about {step_m * 100:.0f} cm between "
                                                 "consecutive transforms")
            except (ValueError, AttributeError, TypeError) as err:
                added.refused.append(str(err))
        return added

    def add(self, parent: str, child: str, stamp_ns: int, T_parent_child: np.ndarray, *, static: bool) -> str | None:
        """One transform; ValueError naming the frames if it would break the tree (see the module). A
        dynamic transform for a stamp its link already has keeps the first: returns what differs when
        the new one is another transform (`matching.pose_conflict`), else None."""
        parent, child = parent.lstrip("/"), child.lstrip("/")
        if not parent or not child:
            raise ValueError(f"transform '{parent}' -> '{child}' has an empty frame id; name both frames")
        with self._lock:
            link = self._links.get(child)
            # a link the tree already has cannot close a loop: the walk up is for a new one
            if (link is None or link.parent != parent) and child in self._chain(parent):
                relation = "parent" if parent == child else f"ancestor ({' -> '.join(self._chain(parent))})"
                raise ValueError(f"transform {parent} -> {child} would make '{child}' its own {relation}; TF needs a "
                                 "tree: fix the publisher of this transform")
            if link is not None and link.parent != parent:
                now_ns = self.newest_ns if static else stamp_ns  # a static transform's stamp tells no time
                alive = link.static is not None or bool(
                    link.stamps and now_ns is not None and abs(now_ns - link.stamps[-1]) < REPARENT_AFTER_S * 1e9)
                if alive:
                    kind = "static " if static else ""
                    raise ValueError(f"frame '{child}' has two parents, '{link.parent}' and '{parent}' ({kind}"
                                     f"{parent} -> {child} came second); TF needs a tree: make one publisher stop (the "
                                     f"transforms from '{parent}' are left out; if the tree changed for good, restart "
                                     "the node)")
                link = None  # the child moved to another parent
            if link is None:
                link = self._links[child] = _Link(parent)
            if static:  # the newest kind holds
                link.static = np.asarray(T_parent_child, np.float64)
                link.stamps.clear()
                link.transforms.clear()
                return None
            link.static = None
            self.newest_ns = stamp_ns if self.newest_ns is None else max(self.newest_ns, stamp_ns)
            i = bisect.bisect_left(link.stamps, stamp_ns)
            if i < len(link.stamps) and link.stamps[i] == stamp_ns:
                return pose_conflict(link.transforms[i], T_parent_child)
            link.stamps.insert(i, stamp_ns)
            link.transforms.insert(i, np.asarray(T_parent_child, np.float64))
            if len(link.stamps) > self.history:
                del link.stamps[0], link.transforms[0]
            return None

    def _newest_of(self, child: str) -> float:
        """The stamp of a dynamic link's newest transform (-inf for none)."""
        with self._lock:
            link = self._links.get(child.lstrip("/"))
            return link.stamps[-1] if link is not None and link.static is None and link.stamps else -math.inf

    def _zig_zag(self, child: str) -> float | None:
        """The step of a dynamic link whose transforms zig-zag (`matching.alternation_m`), checked at every
        ALTERNATION_CHECK_EVERY transforms and said once per link; else None."""
        with self._lock:
            link = self._links.get(child)
            if link is None or link.static is not None or link.zig_zag_said:
                return None
            link.added += 1
            if link.added % ALTERNATION_CHECK_EVERY:
                return None
            step_m = alternation_m(link.transforms)
            link.zig_zag_said = step_m is not None
            return step_m

    def clear(self) -> None:
        """Forget the dynamic transforms (time restarted); static ones stay."""
        with self._lock:
            self.newest_ns = None
            for link in self._links.values():
                link.stamps.clear()
                link.transforms.clear()

    def _link_at(self, child: str, link: _Link, stamp_ns: int) -> np.ndarray:
        if link.static is not None:
            return link.static
        stamps = link.stamps
        i = bisect.bisect_left(stamps, stamp_ns)
        if i == len(stamps):
            newest = "none has come"
            if stamps:
                interval_ns = _typical_interval_ns(stamps, i - 1)
                newest = f"its newest is at {stamps[-1] * 1e-9:.3f} s" + (
                    f", and one comes every {interval_ns * 1e-9:.2f} s" if interval_ns else "")
            raise TfWait(f"no transform {link.parent} -> {child} at or after {stamp_ns * 1e-9:.3f} s yet ({newest})")
        if stamps[i] == stamp_ns:
            return link.transforms[i]
        if i == 0:  # no interval can reach it: more transforms or a tolerance would not help
            raise TfError(f"{stamp_ns * 1e-9:.3f} s is before the first transform {link.parent} -> {child} held "
                          f"({stamps[0] * 1e-9:.3f} s): frames stamped before a link's publisher started (or before "
                          "the node heard it, or before the first stamp of a publisher that stamps ahead, as nav2's "
                          "amcl does by its transform_tolerance) cannot be posed")
        # a link published slowly (a localisation's map -> odom at 1 Hz) is interpolated over its own
        # interval: a gap is a missing transform, measured against the link's rate
        max_gap_ns = max(self.max_gap_ns, _GAP_INTERVALS * _typical_interval_ns(stamps, i))
        if stamp_ns - stamps[i - 1] <= max_gap_ns < stamps[i] - stamp_ns and i == len(stamps) - 1:
            # the next transform is far but the newest: nearer ones may still come (a transform a
            # glitching publisher stamped ahead stays the newest while the link fills in before it)
            raise TfWait(f"the transform {link.parent} -> {child} after {stamp_ns * 1e-9:.3f} s, its newest, is "
                         f"{(stamps[i] - stamp_ns) * 1e-9:.3f} s from it; waiting for nearer ones")
        if stamp_ns - stamps[i - 1] > max_gap_ns or stamps[i] - stamp_ns > max_gap_ns:
            raise TfError(f"the transforms {link.parent} -> {child} around {stamp_ns * 1e-9:.3f} s are more than "
                          f"{max_gap_ns * 1e-9:g} s from it; publish them more often or raise pose_tolerance_s")
        jump = pose_jump(link.transforms, i)
        if jump is not None:  # interpolated, the frame would lie on a smear between the old and the new place
            raise TfError(f"{link.parent} -> {child} jumped {jump[0]:.2f} m, {jump[1]:.1f} deg between its transforms "
                          f"at {stamps[i - 1] * 1e-9:.3f} s and {stamps[i] * 1e-9:.3f} s (a localiser relocalising?), "
                          f"far more than it moves between transforms otherwise: the frame at {stamp_ns * 1e-9:.3f} s "
                          "between them is not posed")
        s = (stamp_ns - stamps[i - 1]) / (stamps[i] - stamps[i - 1])
        return interpolate_pose(link.transforms[i - 1], link.transforms[i], s)

    def newest_common_ns(self, target: str, source: str) -> int | None:
        """The newest stamp at which every dynamic link between the two frames has a transform (the
        oldest of their newest stamps); None when the frames are not connected, a dynamic link has no
        transform, or every link is static (a lookup then holds at any stamp)."""
        target, source = target.lstrip("/"), source.lstrip("/")
        with self._lock:
            up_source, up_target = self._chain(source), self._chain(target)
            common = next((f for f in up_source if f in up_target), None)
            if common is None:
                return None
            links = [self._links[child] for chain in (up_source, up_target) for child in chain[: chain.index(common)]]
            dynamic = [link for link in links if link.static is None]
            if not dynamic or any(not link.stamps for link in dynamic):
                return None
            return min(link.stamps[-1] for link in dynamic)

    def _chain(self, frame: str) -> list[str]:
        chain = [frame]
        while chain[-1] in self._links and len(chain) < 100:
            chain.append(self._links[chain[-1]].parent)
        return chain

    def _no_path(self, target: str, up_source: list[str], up_target: list[str]) -> TfNotConnected:
        """Why target (the fixed frame) and source (a camera's frame) are not connected (yet): their
        chains, and a frame no transform names (what to set), or the two trees' roots."""
        source = up_source[0]
        text = (f"no transform path between '{target}' and '{source}' (yet): known chains "
                f"{' -> '.join(up_source)} and {' -> '.join(up_target)}")
        named = {frame for child, link in self._links.items() for frame in (child, link.parent)}
        if target not in named and len(up_source) > 1:
            return TfNotConnected(f"{text}; no transform names '{target}' (fixed_frame): set fixed_frame to the "
                                  f"root of the source's tree, '{up_source[-1]}', or another frame of its chain",
                                  target)
        if source not in named:
            return TfNotConnected(f"{text}; no transform names '{source}' (the depth image's header.frame_id): "
                                  "publish the camera's mount (a static transform from its parent frame), or set the "
                                  "driver's frame_id to the camera's frame in the tree", source)
        if target in named:
            text += (f"; they hang in two trees, whose roots are '{up_source[-1]}' and '{up_target[-1]}': a "
                     "transform joining them is missing")
        return TfNotConnected(text)

    def _to_ancestor(self, chain: list[str], ancestor: str, stamp_ns: int) -> np.ndarray:
        """T_ancestor_frame for chain[0], walking up to `ancestor`."""
        T = np.eye(4)
        for child in chain[: chain.index(ancestor)]:
            T = self._link_at(child, self._links[child], stamp_ns) @ T
        return T

    def lookup(self, target: str, source: str, stamp_ns: int) -> np.ndarray:
        """T_target_source at stamp_ns. TfWait while a link has nothing at or after the stamp yet,
        TfError when the frames are not connected or a link has a gap there."""
        target, source = target.lstrip("/"), source.lstrip("/")
        if not source:
            raise TfError("the depth image has no header.frame_id; the driver must name its optical frame")
        with self._lock:
            up_source, up_target = self._chain(source), self._chain(target)
            common = next((f for f in up_source if f in up_target), None)
            if common is None:
                raise self._no_path(target, up_source, up_target)
            T_common_source = self._to_ancestor(up_source, common, stamp_ns)
            T_common_target = self._to_ancestor(up_target, common, stamp_ns)
        return invert_transform(T_common_target) @ T_common_source


# extrapolation continues the motion between the newest common stamp and this much before it
EXTRAPOLATION_BASE_NS = 50_000_000


def extrapolate_tf(tf: Any, target: str, source: str, stamp_ns: int, *, newest_ns: int | None,
                   tolerance_ns: int) -> np.ndarray | None:
    """T_target_source at a stamp past the newest one the frames' transforms share, for a frame no later
    transform will come for (its streams ended): the motion between the newest common stamp and
    EXTRAPOLATION_BASE_NS before it, continued at constant velocity (`extrapolate_pose`), as pose
    topics are (`PoseBuffer.extrapolate`). None when the stamp lies more than tolerance_ns past the
    newest common stamp, or not past it, or the transforms do not reach back that far. newest_ns: the
    frames' newest common stamp (`TfBuffer.newest_common_ns`); `tf`: anything with TfBuffer's `lookup`."""
    if newest_ns is None or not 0 < stamp_ns - newest_ns <= tolerance_ns:
        return None
    base_ns = newest_ns - EXTRAPOLATION_BASE_NS
    try:
        T0, T1 = tf.lookup(target, source, base_ns), tf.lookup(target, source, newest_ns)
    except TfError:
        return None
    return extrapolate_pose(T0, T1, (stamp_ns - base_ns) / EXTRAPOLATION_BASE_NS)
