"""Message handling shared by the live node and bag replay: messages in, ready frames out.

No rclpy Node here (only duck-typed message objects, via `conversions`), and no wall clock in any
decision (frames only carry their arrival time for latency statistics): every decision depends
on message stamps and arrival order alone, so the same message sequence
always gives the same frames, live or replayed.

Per sensor:
- `camera_info` is cached (the latest one wins);
- depth images that arrive before their sensor's first camera_info wait for it (drivers publish the
  two on separate topics, so either may arrive first), at most `pose_max_wait_s` of stream time;
- depth images are decoded on arrival (outside Ingest's lock, so that a large image holds up no
  other stream nor the consumer; so are those that waited, for their camera_info or for a restart to
  be confirmed), checked, resized to the working resolution and put in a bounded
  queue (the oldest frame is dropped when it is full);
- colour images wait in a short buffer and are matched to depth by the nearest stamp;
- poses go to a sorted buffer; a frame leaves the queue once a pose at or after its stamp
  exists, with the pose interpolated at the depth stamp (lerp + slerp). A frame is dropped when
  the sensor's stream time has moved more than `pose_max_wait_s` past it with no such pose. A pose
  (or dynamic TF transform) for a stamp already given keeps the first; a different one is dropped
  as `pose_conflict` (frames may have been posed with the first: keeping it, what the consumer gets
  does not depend on when it asked).
- when a sensor's streams have ended (`Ingest.stream_ends.end`: a bag's end, the node stopping, or its streams
  silent for pose_max_wait_s), no later pose will come: its frames newer than its newest pose are posed
  by continuing the two newest poses' motion at constant velocity when within `pose_tolerance_s` past
  it (counted as `extrapolated`), else dropped as `pose_timeout`; what it did is reported once
  (`Ingest.stream_ends.take`). A message on any of its streams starts them again.

Counters per sensor (`Ingest.ledger`, which also takes the consumer's reports): `received` (depth
images), `integrated` (reported back by the caller with `ledger.mark_integrated`), `dropped[reason]`
(messages of any stream discarded, by reason; see `DROP_REASONS`).

Time: each stream keeps a timeline (`timeline.Timelines`): a stamp off its stream's timeline is
dropped as `bad_stamp`; depth stamps that do not move forward as `duplicate` or `out_of_order`
(one between the sensor's two newest is taken: see `timeline`). When time restarts (a bag
looping, a robot restarting its clock) all queues and pose buffers are flushed and, if it went
back, a `TimeJump` item is reported ahead of the frames that follow, so the caller can reset its
map or keep it. `restart()` says so from outside (the /clock jumping back
under use_sim_time).

Typical use::

    ingest = Ingest(IngestConfig(sensors=("tof", "stereo")))
    ingest.add_camera_info("tof", info_msg)
    ingest.add_pose("tof", pose_msg)
    ingest.add_depth("tof", depth_msg)
    for item in ingest.pop_ready():
        if isinstance(item, TimeJump): ...          # reset or ignore
        else: engine.integrate(item.sensor, item.depth_m, item.K, item.T_world_camera, item.rgb)

or, with each next frame's feature net overlapping the current frame's integration,
`integrate_ready(engine, ingest.pop_ready(), on_time_jump, on_frame)`.
"""
from __future__ import annotations

import bisect
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any
from collections.abc import Callable, Collection, Iterable

import numpy as np

from senfunet_ros import conversions as conv
from senfunet_ros.matching import ALTERNATION_CHECK_EVERY, ColorBuffer, PoseBuffer
from senfunet_ros.tf import TfAdded, TfNotConnected, TfWait, extrapolate_tf
from senfunet_ros.timeline import Restart, StreamGaps, Timelines

__all__ = ["DROP_REASONS", "IngestConfig", "Frame", "TimeJump", "SensorCounters", "StreamEnd", "Ingest",
           "IngestLedger", "NoDepthInRange", "integrate_ready", "split_stream_errors"]

DROP_REASONS: tuple[str, ...] = (
    "no_camera_info",  # no camera_info of its sensor arrived within pose_max_wait_s of the depth image
    "bad_camera_info",  # camera_info without a usable K or size
    "bad_encoding",  # depth or colour encoding unsupported, or the image is malformed
    "size_mismatch",  # depth size differs from its camera_info size, and not as a resize of it (another aspect ratio)
    "all_invalid",  # no valid depth pixel at all
    "out_of_range",  # no depth pixel within the sensor's depth range inside the image border (reported by the caller)
    "bad_pose",  # pose message with NaN/inf or a non-unit quaternion
    "pose_conflict",  # a pose (or dynamic TF transform) for a stamp already given, another value: the first is kept
    "pose_timeout",  # no pose after the frame arrived within pose_max_wait_s of stream time
    "pose_gap",  # the poses around the frame are further than pose_tolerance_s from it
    "queue_full",  # the frame queue overflowed; the oldest frame goes (set aside instead if posed and it fits)
    "behind",  # more than max_lag_s older than its sensor's newest (the consumer fell behind), no room to set it aside
    "out_of_order",  # depth stamp older than the two newest of the same sensor
    "duplicate",  # depth stamp equal to one of the latest of the same sensor
    "bad_stamp",  # stamp 0 (unset), or far from its stream's timeline (past or future): the timeline does not move
    "time_jump",  # frames flushed because time went back, and a new timeline's first messages not held
    "engine_error",  # the engine rejected the frame (reported by the caller)
    "shutdown",  # taken for integration when the process stopped (reported by the caller), or set aside then
    "map_reset",  # waiting or set aside when the map was reset or replaced (it belonged to the old map)
)


@dataclass(frozen=True)
class IngestConfig:
    """How messages become frames. Times are seconds of message stamps, never wall time."""

    sensors: tuple[str, ...] = ("tof", "stereo")
    # (width, height) frames are resized to; both 0 = native size, one 0 = keep the aspect ratio
    working_size: tuple[int, int] = (0, 0)
    queue_size: int = 30  # frames waiting for a pose, per sensor
    pose_buffer_size: int = 2000  # poses kept per sensor (20 s at 100 Hz)
    pose_tolerance_s: float = 0.1  # max distance from a frame to the poses it is interpolated from
    pose_max_wait_s: float = 1.0  # a frame waits this long (stream time) for a later pose, or a first camera_info
    color_tolerance_s: float = 0.02  # max stamp distance of a colour image to its depth image
    time_jump_s: float = 1.0  # a stamp this far from its stream's timeline is off it (a stray, or a restart)
    restart_confirm_msgs: int = 5  # a new timeline is confirmed after this many messages on each stream
    restart_confirm_s: float = 0.5  # ... spanning at least this much of the new timeline
    max_lag_s: float = 0.0  # a ready frame this far behind its sensor's newest depth stamp is skipped; 0 = never
    # ... unless it fits in this many bytes of frames set aside: those are handed out when the sensors
    # pause or stop (see pop_ready), so a consumer behind for a while loses nothing; 0 = skip at once
    set_aside_bytes: int = 0
    # time going back resets the consumer's map (on_time_jump: reset): the frames set aside then go too (they
    # belong to the old map); else they stay, and are integrated into the kept map later
    reset_on_time_jump: bool = False
    # the map's voxel size: a sensor's first frame is checked for pixels further apart than 1.5 voxels at its
    # median depth (holes in the mesh), said once in its notes; 0 = no check
    voxel_size_m: float = 0.0
    # sensor -> (depth_min_m, depth_max_m) of what is fused: the pixels that check counts (absent: every depth > 0)
    depth_range_m: dict[str, tuple[float, float]] = field(default_factory=dict)
    # sensors whose depth topic names unrectified images (`image_raw`): their camera_info's K holds even
    # where its P would describe rectified ones (conversions.rectified_matrix)
    raw_depth: frozenset[str] = frozenset()
    pose_parser: Callable[[Any], tuple[int, np.ndarray]] = conv.pose_from_msg
    # sensor -> the camera in the frame its pose topic gives (an Odometry's base_link), or with tf in its depth
    # images' frame_id (a driver that names camera_link, x forward, not the optical frame); absent = identity
    T_body_camera: dict[str, np.ndarray] = field(default_factory=dict)
    # poses from TF instead of pose topics: an object with lookup(target, source, stamp_ns) -> 4x4 that
    # raises senfunet_ros.tf.TfWait (not yet) or TfError (never), and newest_common_ns(target, source) (see
    # senfunet_ros.tf.TfBuffer); each depth image's frame_id in fixed_frame
    tf: Any = None
    fixed_frame: str = "map"

    def __post_init__(self) -> None:
        if not self.sensors or len(set(self.sensors)) != len(self.sensors):
            raise ValueError(f"sensors must be distinct names, got {self.sensors}")
        if self.queue_size < 1 or self.pose_buffer_size < 2 or self.max_lag_s < 0 or self.set_aside_bytes < 0:
            raise ValueError("queue_size must be >= 1, pose_buffer_size >= 2, max_lag_s >= 0 and set_aside_bytes >= 0")
        if min(self.working_size) < 0:
            raise ValueError(f"working_size must be (width, height) >= 0, got {self.working_size}")


@dataclass
class Frame:
    """A depth frame ready for the engine (the engine's conventions: see docs/architecture.md)."""

    sensor: str
    stamp_ns: int
    depth_m: np.ndarray  # HxW float32 metres, 0 = invalid
    rgb: np.ndarray | None  # HxWx3 uint8 or None
    K: np.ndarray  # 3x3 float64 for this depth resolution
    T_world_camera: np.ndarray  # 4x4 float64
    arrival_s: float = 0.0  # time.monotonic() when its depth image arrived (for latency statistics)
    set_aside: bool = False  # set aside while the consumer was behind (Ingest.pop_ready), so handed out late


@dataclass(frozen=True)
class TimeJump:
    """Stamps of `stream` on `sensor` went back from `from_ns` to `to_ns`: all buffers were flushed."""

    sensor: str
    stream: str  # "depth", "color" or "pose"
    from_ns: int
    to_ns: int
    stray_start: bool = False  # the old timeline was only a stray first stamp or few (`timeline.Restart`)


@dataclass
class SensorCounters:
    received: int = 0  # depth images received
    integrated: int = 0  # frames the caller integrated
    color_received: int = 0
    pose_received: int = 0
    time_jumps: int = 0  # time jumps first seen on this sensor's streams
    set_aside: int = 0  # frames set aside because the consumer fell behind (integrated later, or dropped)
    # frames newer than the newest pose when the sensor's streams ended, posed by extrapolating (Ingest.stream_ends.end)
    extrapolated: int = 0
    # frames handed out without colour although the sensor's colour stream spoke: none within color_tolerance_s,
    # or none of its images could be decoded
    without_color: int = 0
    color_usable: int = 0  # colour images decoded and buffered for matching
    # messages whose bytes do not deserialise, per stream (a bag's damaged messages: `Ingest.add_undecodable`)
    undecodable: dict[str, int] = field(default_factory=dict)
    # depth images missing from the stream's regular stamps (`timeline.StreamGaps`), and where the latest gap was
    missing_depth: int = 0
    missing_depth_gap: str = ""
    # the latest camera_info has non-zero distortion coefficients: the node takes the images as rectified
    distorted: bool = False
    # frames fused without colour because the colour images have another aspect ratio than the depth images
    color_refused: int = 0
    # what about this sensor's set-up the user should know, said once each (the node warns, replay prints):
    # "color_size" (colour of another aspect ratio), "camera_info_size" (a K taken as given although the
    # camera_info's size differs), "pixel_spacing" (pixels further apart than 1.5 voxels: holes)
    notes: dict[str, str] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=lambda: {reason: 0 for reason in DROP_REASONS})
    errors: dict[str, str] = field(default_factory=dict)  # drop reason -> what the last such message had wrong

    @property
    def messages_received(self) -> int:
        """Depth, colour and pose messages received (a sensor that speaks again moves it: `Ingest.stream_ends.end`)."""
        return self.received + self.color_received + self.pose_received

    def as_dict(self) -> dict[str, Any]:
        return {
            "received": self.received,
            "integrated": self.integrated,
            "color_received": self.color_received,
            "pose_received": self.pose_received,
            "time_jumps": self.time_jumps,
            "set_aside": self.set_aside,
            "extrapolated": self.extrapolated,
            "without_color": self.without_color,
            "color_usable": self.color_usable,
            "undecodable": dict(self.undecodable),
            "missing_depth": self.missing_depth,
            "missing_depth_gap": self.missing_depth_gap,
            "distorted": self.distorted,
            "color_refused": self.color_refused,
            "notes": dict(self.notes),
            "dropped": dict(self.dropped),
            "errors": dict(self.errors),
        }


@dataclass
class StreamEnd:
    """What the end of a sensor's streams (`Ingest.stream_ends.end`) did to its frames that no pose came
    after: posed by extrapolation (within pose_tolerance_s past the newest pose) or dropped."""

    extrapolated: int = 0
    extrapolated_max_ns: int = 0  # the furthest of them past the newest pose
    timed_out: int = 0  # dropped as pose_timeout: further past it, fewer than two poses, or (tf) none
    timed_out_max_ns: int = 0  # the furthest of them past the newest pose (0 when there was none)

    def __bool__(self) -> bool:
        return bool(self.extrapolated or self.timed_out)


@dataclass
class _Pending:
    stamp_ns: int
    depth_m: np.ndarray
    K: np.ndarray
    arrival_s: float  # time.monotonic() when the depth image arrived (statistics only)
    rgb: np.ndarray | None = None  # set, with T, for a posed frame put back by pop_ready
    T: np.ndarray | None = None
    frame_id: str = ""  # the depth image's optical frame (pose_type tf looks it up)
    source_size: tuple[int, int] = (0, 0)  # (width, height) of the depth image as published (colour must match)
    notes: tuple[tuple[str, str], ...] = ()  # (key, text) for SensorCounters.notes
    spacing_checked: bool = False  # its pixel spacing was checked against the voxel size


@dataclass(frozen=True)
class _Undecoded:
    """An image on time, to decode outside Ingest's lock (`_decode`), then queue (`_SensorInput.enqueue`
    or `take_color`)."""

    sensor: str
    stream: str  # "depth" or "color"
    stamp_ns: int
    msg: Any
    arrival_s: float  # depth: time.monotonic() when it arrived (statistics only)
    camera_info: tuple[np.ndarray, tuple[int, int]] | None  # depth: (K, (width, height)) to check it against
    working_size: tuple[int, int]  # depth: IngestConfig.working_size
    # depth: check its pixel spacing against this voxel size, over its pixels in this depth range (voxel size > 0: its
    # sensor's first frames; `_SensorInput.spacing_check`)
    spacing_check: tuple[float, float, float]
    cleared: int  # its sensor's _SensorInput.cleared when it was taken: a clear meanwhile takes it too


def _decode(image: _Undecoded) -> Any:
    """A depth image as `_decode_depth` gives it, a colour image as `_decode_color`."""
    if image.stream == "depth":
        assert image.camera_info is not None
        return _decode_depth(image.msg, image.stamp_ns, image.arrival_s, camera_info=image.camera_info,
                             working_size=image.working_size, spacing_check=image.spacing_check)
    return _decode_color(image.msg)


class _SensorInput:
    """One sensor's camera_info, frame queues, colour and pose buffers and counters: what its messages
    do once their stamps are known to be on time. Not thread-safe: Ingest calls it under its lock."""

    def __init__(self, config: IngestConfig) -> None:
        self.counters = SensorCounters()
        self.camera_info: tuple[np.ndarray, tuple[int, int]] | None = None
        self.camera_info_before: tuple[np.ndarray, tuple[int, int]] | None = None  # the one before the last change
        self.camera_info_returns = 0  # changes in a row back to the one before the last change
        self.camera_info_refused = ""  # why the newest camera_info was refused ("": it was taken)
        self.queue: deque[_Pending] = deque()
        self.awaiting_info: deque[tuple[Any, int, float]] = deque()  # (depth msg, stamp_ns, arrival_s)
        self.colors = ColorBuffer(max(4, config.queue_size))
        self.color_failed = False  # colour came that could not be decoded: frames without colour are counted
        self.poses = PoseBuffer()
        # how often the frames and colours were cleared, and why the last time: an image decoded outside
        # Ingest's lock across a clear belonged to what was cleared
        self.cleared = 0
        self.cleared_by = ""
        self.spacing_checked = False  # a frame's pixel spacing was checked against the voxel size
        # the streams ended (Ingest.stream_ends.end): no later pose will come for what waits; a message clears it
        self.ended = False
        self.end = StreamEnd()  # what the end did, since the last Ingest.stream_ends.take
        self.depth_gaps = StreamGaps()
        self.unset_stamps: set[str] = set()  # its streams seen with header.stamp 0 (`unset_stamp`)
        self._latest_zero: set[str] = set()  # its streams whose latest message was stamped 0 (`stamped_zero_again`)

    def waiting(self) -> int:
        return len(self.queue) + len(self.awaiting_info)

    def drop(self, reason: str, error: str = "", n: int = 1) -> str:
        """Count n messages dropped for `reason` (with what the last one had wrong); returns the reason."""
        self.counters.dropped[reason] += n
        if error:
            self.counters.errors[reason] = _with_other_stream(self.counters.errors.get(reason, ""), error)
        return reason

    def stamped_zero_again(self, stream: str, stamp_ns: int) -> bool:
        """Whether a message of `stream` is stamped 0 right after another stamped 0: a driver that sets no
        stamps (`unset_stamp`). One 0 is taken: a simulation's clock starts there."""
        again = stamp_ns == 0 and stream in self._latest_zero
        if stamp_ns == 0:
            self._latest_zero.add(stream)
        else:
            self._latest_zero.discard(stream)
        return again

    def unset_stamp(self, stream: str) -> str:
        """Drop a depth, colour or pose message stamped 0 (again, or off the stream's timeline) as bad_stamp,
        saying the driver sets no stamps: a frame is posed and coloured at its stamp, and stamps of 0 would
        read as one instant (poses in conflict, images duplicates) or far off the other streams' time. A
        camera_info's stamp is used for nothing (a driver may fill it once): it is only named beside them."""
        self.unset_stamps.add(stream)
        if stream == "color":  # said beside the depth's or poses' error, which names every stream stamped 0
            return self.drop("bad_stamp", f"{_COLOUR}header.stamp is 0 (unset): its driver does not set stamps")
        *others, last = [label for key, label in _STREAM_LABELS.items() if key in self.unset_stamps]
        named = f"{', '.join(others)} and {last}" if others else last
        return self.drop("bad_stamp", (
            f"{stream}: header.stamp is 0 (unset), on its {named} messages: their driver does not set stamps, and a "
            "frame is posed and coloured at its stamp; fix the driver to stamp each message with the time it was "
            "taken"))

    def discard(self, reason: str) -> int:
        """Drop every frame waiting (counted as `reason`) and the colour images; poses and camera_info
        stay. Returns how many frames."""
        n = self.waiting()
        self.drop(reason, n=n)
        self.queue.clear()
        self.awaiting_info.clear()
        self.colors.clear()
        self.cleared, self.cleared_by = self.cleared + 1, reason
        return n

    def flush(self) -> int:
        """Forget everything that belongs to a timeline (time went back): frames, colours, poses.
        Returns how many frames (not counted)."""
        n = self.waiting()
        self.queue.clear()
        self.awaiting_info.clear()
        self.colors.clear()
        self.poses.clear()
        self.ended = False
        self.cleared, self.cleared_by = self.cleared + 1, "time_jump"
        return n

    def set_camera_info(self, name: str, msg: Any, config: IngestConfig) -> tuple[str | None, list[_Undecoded]]:
        """Cache K and the image size of sensor `name`. Returns the drop reason (or None when it was
        cached) and the depth images that waited for it, to decode outside Ingest's lock and queue."""
        try:
            raw = name in config.raw_depth
            intrinsics = conv.intrinsics_from_camera_info(msg, raw=raw)
            rectified = conv.rectified_matrix(msg, raw=raw) is not None
            self.counters.distorted = not rectified and bool(np.any(np.asarray(getattr(msg, "d", ()), np.float64) != 0))
            if rectified:
                self.counters.notes.setdefault("rectified_p", (
                    "its camera_info carries distortion coefficients and a projection matrix P other than K, as "
                    "image_proc publishes rectified images: the depth images are taken as rectified, with P's "
                    "intrinsics (as image_geometry and depth_image_proc read them)"))
        except (ValueError, AttributeError) as err:
            kept = "" if self.camera_info is None else "; the depth images go on with the last good camera_info's K"
            self.camera_info_refused = str(err)
            return self.drop("bad_camera_info", f"{err}{kept}"), []
        self.camera_info_refused = ""
        self._note_camera_info_change(intrinsics)
        self.camera_info = intrinsics
        K, (_, height) = intrinsics
        if abs(K[0, 1]) > 1e-6 * K[0, 0]:
            self.counters.notes.setdefault("camera_info_skew", (
                f"its camera_info's K has skew {K[0, 1]:g} (K[0][1]), which the node does not apply (it takes fx, fy, "
                f"cx, cy): rays are off by up to {abs(K[0, 1]) * height / 2 / K[1, 1]:.2g} pixels at the top and "
                "bottom edges; calibrate without skew (the usual pinhole model)"))
        waited = [_Undecoded(name, "depth", stamp_ns, depth_msg, arrival_s, self.camera_info, config.working_size,
                             self.spacing_check(config, name), self.cleared)
                  for depth_msg, stamp_ns, arrival_s in self.awaiting_info]
        self.awaiting_info.clear()
        return None, waited

    def _note_camera_info_change(self, intrinsics: tuple[np.ndarray, tuple[int, int]]) -> None:
        """Say once when the camera_info changes (K or size), and once when it goes back to the one
        before twice (A, B, A, B): two publishers on one topic, each frame taking whichever came last
        (once is a driver set back to its earlier resolution)."""
        now = self.camera_info
        if now is None or _same_intrinsics(now, intrinsics):
            return
        before, self.camera_info_before = self.camera_info_before, now
        notes = self.counters.notes
        returned = before is not None and _same_intrinsics(before, intrinsics)
        self.camera_info_returns = self.camera_info_returns + 1 if returned else 0
        if self.camera_info_returns >= 2 and before is not None:
            notes.setdefault("camera_info_alternates", (
                f"its camera_info alternates between {conv.intrinsics_text(now)} and {conv.intrinsics_text(before)}: "
                "two publishers on one topic (the depth and colour cameras' camera_info remapped onto one?); each "
                "depth image takes the one that came last, so frames are fused with the wrong K; make one stop"))
        else:
            notes.setdefault("camera_info_changed", (
                f"its camera_info changed from {conv.intrinsics_text(now)} to {conv.intrinsics_text(intrinsics)}; the "
                "depth images after it take the new one (a driver that changed its resolution or calibration)"))

    def accept(self, name: str, stream: str, stamp_ns: int, message: Any, config: IngestConfig
               ) -> str | _Undecoded | None:
        """Take a message of sensor `name` whose stamp is on time: a pose (4x4) is stored, a depth image
        ((msg, arrival time)) before the sensor's first camera_info waits for it; an image to decode is
        returned (`_Undecoded`: the caller decodes it outside Ingest's lock, then Ingest queues it). Returns
        the drop reason (counted), or what to decode, or None."""
        if stream == "pose":
            conflict = self.poses.add(stamp_ns, message, keep=config.pose_buffer_size)
            return None if conflict is None else self.drop("pose_conflict",
                                                           f"pose: stamp {stamp_ns * 1e-9:.3f} s: {conflict}")
        msg, arrival_s = message if stream == "depth" else (message, 0.0)
        gap = self.depth_gaps.add(stamp_ns) if stream == "depth" else None
        if gap is not None and gap.new_period_ns:
            to_ms = gap.new_period_ns * 1e-6
            self.counters.notes.setdefault(f"depth_period_{to_ms:.0f}ms", (
                f"its depth images came every {to_ms:.0f} ms for a while (every {gap.period_ns * 1e-6:.0f} ms "
                f"before), which is now taken as the stream's period: the driver's rate went down, or images are "
                "lost steadily on the way (the missing images counted until now stay counted; see ~/status)"))
        # poses that paused over the gap too (all but an image period at either end; over a gap of one image,
        # for a period or more) are a sensor that paused (a driver restarting): no image went missing
        if gap is not None and (not self.counters.pose_received or self.poses.longest_pause_ns(gap.from_ns, gap.to_ns)
                                < max(gap.to_ns - gap.from_ns - 2 * gap.period_ns, gap.period_ns)):
            self.counters.missing_depth += gap.missing
            self.counters.missing_depth_gap = (f"{gap.from_ns * 1e-9:.3f} s to {gap.to_ns * 1e-9:.3f} s, "
                                               f"{gap.missing + 1} of the stream's {gap.period_ns * 1e-6:.0f} ms "
                                               "periods")
            self.depth_gaps.count(gap)
        elif stream == "depth":
            self.late_depth(stamp_ns)
        if stream == "depth" and self.camera_info is None:
            if len(self.awaiting_info) >= config.queue_size:
                self.awaiting_info.popleft()
                self.drop("no_camera_info")
            self.awaiting_info.append((msg, stamp_ns, arrival_s))
            return None
        return _Undecoded(name, stream, stamp_ns, msg, arrival_s, self.camera_info, config.working_size,
                          self.spacing_check(config, name), self.cleared)

    def late_depth(self, stamp_ns: int) -> None:
        """A depth image older than the stream's newest came (taken between the two newest, or dropped as
        out of order): if a gap counted it as missing, it is not."""
        if self.depth_gaps.came_late(stamp_ns):
            self.counters.missing_depth -= 1

    def spacing_check(self, config: IngestConfig, name: str) -> tuple[float, float, float]:
        """The voxel size to check a depth image's pixel spacing against (0 once a frame was checked: a
        median per frame would cost every frame; the first frames tell), and the depth range of the
        pixels that count (the sensor's: a sentinel value, 0xFFFF mm for saturated, is no depth)."""
        depth_min_m, depth_max_m = config.depth_range_m.get(name, (0.0, math.inf))
        return 0.0 if self.spacing_checked else config.voxel_size_m, depth_min_m, depth_max_m

    def enqueue(self, decoded: _Pending | tuple[str, str], config: IngestConfig, *, cleared: int, name: str,
                set_aside: SetAside) -> str | None:
        """Queue a decoded depth image (`_decode_depth`) of sensor `name`, in stamp order, unless its
        decoding failed or the queue was cleared since `cleared` (then it belonged to what was cleared).
        A full queue's oldest frame is set aside where it can be (`_set_aside_instead`), else dropped.
        Returns the drop reason or None."""
        if not isinstance(decoded, _Pending):
            reason, error = decoded
            if reason == "size_mismatch" and self.camera_info_refused:  # the image may match the refused one
                error += f" (the newest camera_info was refused: {self.camera_info_refused})"
            return self.drop(reason, error)
        for key, text in decoded.notes:
            self.counters.notes.setdefault(key, text)
        self.spacing_checked = self.spacing_checked or decoded.spacing_checked
        if cleared != self.cleared:
            return self.drop(self.cleared_by)
        if len(self.queue) >= config.queue_size:
            oldest = self.queue.popleft()  # the oldest frame is the stalest: keep latency bounded
            if not self._set_aside_instead(name, oldest, config, set_aside):
                self.drop("queue_full")
                # what it waited for decides what to do: the consumer (integration is behind), or a pose (the
                # reason's hint names the pose topic)
                newest_pose_ns = self.poses.newest_ns()
                if oldest.T is not None or (config.tf is None and newest_pose_ns is not None
                                            and newest_pose_ns >= oldest.stamp_ns):
                    self.counters.errors["queue_full"] = (
                        "integration is behind: the oldest of queue_size images that had their poses and waited to "
                        "be integrated went; raise queue_size or behind_buffer_mb, so that the frames integration "
                        "falls behind on are set aside (max_lag_s) and integrated when the sensors pause, or lower "
                        "the sensors' rates or working_width")
                else:
                    self.counters.errors.pop("queue_full", None)
        if self.queue and self.queue[-1].stamp_ns > decoded.stamp_ns:  # two threads added this sensor's depth
            bisect.insort(self.queue, decoded, key=lambda pending: pending.stamp_ns)
        else:
            self.queue.append(decoded)
        return None

    def take_color(self, stamp_ns: int, decoded: np.ndarray | str, *, cleared: int) -> str | None:
        """Buffer a decoded colour image (`_decode_color`: RGB, or what was wrong) for matching, unless
        the colours were cleared since `cleared`. Returns the drop reason or None."""
        if isinstance(decoded, str):
            self.color_failed = True
            return self.drop("bad_encoding", _COLOUR + decoded)
        if cleared != self.cleared:
            return self.drop(self.cleared_by)
        self.colors.add(stamp_ns, decoded)
        self.counters.color_usable += 1
        return None

    def pose_at_end(self, pending: _Pending, config: IngestConfig) -> tuple[np.ndarray | None, str | None, str]:
        """The pose of a frame newer than the newest pose once the streams ended, as `PoseBuffer.at`
        answers with the reason's error: extrapolated within pose_tolerance_s past the newest pose
        (with TF: past the newest stamp the frame's transforms share, `tf.extrapolate_tf`), else
        pose_timeout. Counted in `end` (and `counters.extrapolated`)."""
        stamp_ns, tolerance_ns = pending.stamp_ns, int(config.pose_tolerance_s * 1e9)
        if config.tf is not None:
            newest_ns = config.tf.newest_common_ns(config.fixed_frame, pending.frame_id)
            T = extrapolate_tf(config.tf, config.fixed_frame, pending.frame_id, stamp_ns, newest_ns=newest_ns,
                               tolerance_ns=tolerance_ns)
            too_few = "the transforms did not reach back far enough to extrapolate from"
        else:
            newest_ns = self.poses.newest_ns()
            T = self.poses.extrapolate(stamp_ns, tolerance_ns=tolerance_ns)
            too_few = "only one pose had come, too few to extrapolate from"
        past_ns = 0 if newest_ns is None else stamp_ns - newest_ns
        if T is not None:
            self.counters.extrapolated += 1
            self.end.extrapolated += 1
            self.end.extrapolated_max_ns = max(self.end.extrapolated_max_ns, past_ns)
            return T, None, ""
        self.end.timed_out += 1
        self.end.timed_out_max_ns = max(self.end.timed_out_max_ns, past_ns)
        if newest_ns is None and config.tf is not None:  # the frames are not connected: the lookup says how
            why = "the camera's frame is not connected to the fixed frame"
            try:
                config.tf.lookup(config.fixed_frame, pending.frame_id, stamp_ns)
            except Exception as err:  # noqa: BLE001 (TfWait, TfError): its text names the chains known
                why = f"tf: {err}"
        elif newest_ns is None:
            why = "no pose had come at all"
        elif past_ns > tolerance_ns:
            why = (f"it is {past_ns * 1e-6:.0f} ms past the newest pose, more than pose_tolerance_s "
                   f"({config.pose_tolerance_s:g} s) to extrapolate its pose")
        else:
            why = too_few
        return None, "pose_timeout", (f"pose: the streams ended with the frame at {stamp_ns * 1e-9:.3f} s still "
                                      f"waiting for a pose: {why}")

    def pop(self, name: str, config: IngestConfig, *, now_ns: int | None, newest_depth_ns: int | None,
            depth_floor_ns: int | None, last_color_ns: int | None, set_aside: SetAside) -> list[Frame]:
        """The queued frames that can be posed (and coloured) now, oldest first; those that waited too
        long for a pose or a camera_info are dropped, those the consumer fell behind on (more than
        max_lag_s behind `newest_depth_ns`) set aside or dropped. `now_ns`: the sensor's stream time;
        `depth_floor_ns`: what a depth image yet to come must be newer than (its colour is kept)."""
        max_wait_ns = int(config.pose_max_wait_s * 1e9)
        lag_ns = int(config.max_lag_s * 1e9)
        while self.awaiting_info and now_ns is not None and now_ns - self.awaiting_info[0][1] > max_wait_ns:
            self.awaiting_info.popleft()
            self.drop("no_camera_info")
        out: list[Frame] = []
        while self.queue:
            pending = self.queue[0]
            t = pending.stamp_ns
            if pending.T is not None:  # posed before, put back by pop_ready(max_frames)
                self.queue.popleft()
                frame = Frame(name, t, pending.depth_m, pending.rgb, pending.K, pending.T, pending.arrival_s)
                # the consumer fell behind: keep latency bounded
                if lag_ns and newest_depth_ns is not None and newest_depth_ns - t > lag_ns:
                    if set_aside.put(frame, budget_bytes=config.set_aside_bytes):
                        self.counters.set_aside += 1
                    else:  # no room
                        self.drop("behind")
                else:
                    out.append(frame)
                continue
            # the streams ended: nothing more will come for it, a pose nor a colour image
            waited_too_long = self.ended or (now_ns is not None and now_ns - t > max_wait_ns)
            T, reason, error = self._pose(name, pending, config, now_ns=now_ns, waited_too_long=waited_too_long)
            if self.ended and reason == "pose_timeout":  # no pose at or after it, and none will come
                T, reason, error = self.pose_at_end(pending, config)
                if T is not None and config.tf is not None and name in config.T_body_camera:
                    T = T @ config.T_body_camera[name]
            if T is None:
                if reason is None:
                    break  # not yet: later frames are newer, they wait too
                self.queue.popleft()
                self.drop(reason, error)
                continue
            # colour is waited for only while it can still come in time: not once the depth stream ran
            # pose_max_wait_s past the colour stream's newest stamp (it stopped), nor once frames waiting
            # for it fill half the queue (else a fast sensor's queue overflows first: it drops every frame)
            colour_gone = (last_color_ns is not None and newest_depth_ns is not None
                           and newest_depth_ns - last_color_ns > max_wait_ns)
            crowded = 2 * len(self.queue) >= config.queue_size
            if not self.colors.ready(t, last_color_ns, waited_too_long or colour_gone or crowded):
                break
            self.queue.popleft()
            rgb = self._colour(pending, config, floor_ns=depth_floor_ns)
            out.append(Frame(name, t, pending.depth_m, rgb, pending.K, T, pending.arrival_s))
        return out

    def _pose(self, name: str, pending: _Pending, config: IngestConfig, *, now_ns: int | None,
              waited_too_long: bool) -> tuple[np.ndarray | None, str | None, str]:
        """T_world_camera of a queued frame from its pose stream or TF, or why not (None: not yet)."""
        if config.tf is not None:
            T, reason, error = _tf_pose(config, pending, waited_too_long=waited_too_long)
        else:
            T, reason = self.poses.at(pending.stamp_ns, tolerance_ns=int(config.pose_tolerance_s * 1e9),
                                      waited_too_long=waited_too_long)
            error = "" if reason is None else _pose_drop_error(reason, pending.stamp_ns, now_ns, self.poses, config)
        if T is not None and config.tf is not None and name in config.T_body_camera:
            T = T @ config.T_body_camera[name]  # the image's frame_id is not the optical frame
        return T, reason, error

    def _colour(self, pending: _Pending, config: IngestConfig, *, floor_ns: int | None) -> np.ndarray | None:
        """A frame's colour image from the buffer (None without one), counted where it lacks one;
        `floor_ns`: as `ColorBuffer.match` takes it."""
        rgb = self.colors.match(pending.stamp_ns, tolerance_ns=int(config.color_tolerance_s * 1e9), floor_ns=floor_ns)
        if rgb is not None:
            try:
                return conv.color_for_depth(rgb, depth_size=pending.source_size, shape=pending.depth_m.shape)
            except ValueError as err:  # not registered to the depth: fused without colour, said once
                self.counters.color_refused += 1
                self.counters.notes.setdefault("color_size", str(err))
                return None
        if self.colors.seen or self.color_failed:
            self.counters.without_color += 1
        return None

    def _set_aside_instead(self, name: str, pending: _Pending, config: IngestConfig, set_aside: SetAside) -> bool:
        """The oldest frame of a full queue, set aside rather than dropped where it can be posed now and
        set-aside memory has room: the queue fills while the consumer is held (an eviction, a save), when
        no one takes frames to set them aside (`pop`)."""
        if config.max_lag_s <= 0 or config.set_aside_bytes <= 0:
            return False
        T, rgb = pending.T, pending.rgb
        if T is None:
            T, _, _ = self._pose(name, pending, config, now_ns=None, waited_too_long=False)
            if T is None:
                return False
            rgb = self._colour(pending, config, floor_ns=None)  # the floor is the consumer's to judge
        frame = Frame(name, pending.stamp_ns, pending.depth_m, rgb, pending.K, T, pending.arrival_s)
        if not set_aside.put(frame, budget_bytes=config.set_aside_bytes):
            return False
        self.counters.set_aside += 1
        return True


# transforms held while a clock that stepped is confirmed (`_StreamTime.tf_held`): seconds of a robot's tree
_TF_HELD = 10_000


class _StreamTime:
    """The streams' timelines, and what a restart does to the sensors' inputs: flushed (time went
    back, with a TimeJump to report), then the new timeline's held messages taken. Not thread-safe:
    Ingest calls it under its lock."""

    def __init__(self, config: IngestConfig, sensors: dict[str, _SensorInput], set_aside: SetAside) -> None:
        self.config = config
        self.timelines = Timelines(config.sensors, **_timeline_limits(config))
        self.jumps: list[TimeJump] = []  # seen since the last pop_ready
        self._sensors = sensors
        self.set_aside = set_aside
        # dynamic transforms left out as stamped ahead of the timelines or behind their link (`Ingest.add_tf`),
        # the newest _TF_HELD: a clock that stepped sends them before the images confirm the new timeline,
        # which takes them then
        self.tf_held: deque[Any] = deque(maxlen=_TF_HELD)

    def configure(self, config: IngestConfig) -> None:
        self.config = config
        self.timelines.configure(**_timeline_limits(config))

    def on_time(self, sensor: str, stream: str, stamp_ns: int, message: Any) -> tuple[str | None, list[_Undecoded]]:
        """Whether a message of `stream` is on its stream's timeline (`Timelines.check`): None, or the
        drop reason (counted). A restart it confirmed is carried out first: the images of the new
        timeline's held messages, to decode outside the lock, come second. `message` is what
        `_SensorInput.accept` takes for the stream, should the stamp turn out to start a new timeline
        (it is held until that is confirmed, then accepted)."""
        verdict = self.timelines.check(sensor, stream, stamp_ns, message)
        images = [] if verdict.restart is None else self.restarted(sensor, stream, verdict.restart)
        if verdict.reason == "bad_stamp" and stamp_ns == 0:  # not far off the timeline: unset
            return self._sensors[sensor].unset_stamp(stream), images
        if verdict.reason is not None:
            return self._sensors[sensor].drop(verdict.reason, verdict.error), images
        return None, images

    def _take_tf_held(self, to_ns: int) -> None:
        """Time restarted at to_ns: the held transforms of the new timeline (from time_jump_s before it on)
        go to the TF buffer, no longer counted as bad_stamp; those still ahead stay held, older ones were
        strays and stay counted."""
        jump_ns = int(self.config.time_jump_s * 1e9)
        now_ns = self.timelines.now_ns()
        if now_ns is None:  # the new time not known yet (a restart known from outside without its time)
            return
        latest_ns = max(now_ns, to_ns) + jump_ns
        new = [tf for tf in self.tf_held if conv.stamp_to_ns(tf.header.stamp) >= to_ns - jump_ns]
        self.tf_held.clear()
        if not new or self.config.tf is None or not hasattr(self.config.tf, "add_transforms"):
            return
        added = self.config.tf.add_transforms(new, static=False, latest_ns=latest_ns, behind_ns=jump_ns)
        self.tf_held.extend(added.ahead)
        taken = len(new) - len(added.ahead) - len(added.behind)
        self._sensors[self.config.sensors[0]].drop("bad_stamp", n=-taken)

    def restart(self, to_ns: int | None) -> list[_Undecoded]:
        """Time restarted, known from outside (see Ingest.restart); returns the images of the new time
        that came before the news, to decode outside the lock."""
        return self.restarted(self.config.sensors[0], "clock", self.timelines.restart(to_ns))

    def restarted(self, sensor: str, stream: str, restart: Restart) -> list[_Undecoded]:
        """Time restarted. Back: flush everything (with reset_on_time_jump the frames set aside too) and
        report a TimeJump. Ahead (every stream resumed
        after a pause longer than time_jump_s): what waits is older and stays. Then the new timeline's
        first messages, dropped as bad_stamp until now, are taken; returns their images, to decode
        outside the lock (a burst of up to a queue's worth per stream)."""
        sensors = self._sensors
        for state in sensors.values():
            state.depth_gaps.restart()
        if restart.went_back:
            assert restart.from_ns is not None
            self.jumps.append(TimeJump(sensor, stream, restart.from_ns, restart.to_ns, restart.stray_start))
            sensors[sensor].counters.time_jumps += 1
            if self.config.tf is not None and hasattr(self.config.tf, "clear"):
                self.config.tf.clear()
            for state in sensors.values():
                state.drop("time_jump", n=state.flush())
            if self.config.reset_on_time_jump:
                for name, n in self.set_aside.clear().items():
                    sensors[name].drop("time_jump", n=n)
        self._take_tf_held(restart.to_ns)
        for (name, _), n in restart.lost.items():  # bad_stamp until now, in fact lost to the restart
            sensors[name].drop("bad_stamp", n=-n)
            sensors[name].drop("time_jump", n=n)
        images = []
        for held in restart.held:
            state = sensors[held.sensor]
            state.drop("bad_stamp", n=-1)
            taken = state.accept(held.sensor, held.stream, held.stamp_ns, held.message, self.config)
            if isinstance(taken, _Undecoded):
                images.append(taken)
        for state in sensors.values():
            if state.counters.dropped["bad_stamp"] == 0:
                state.counters.errors.pop("bad_stamp", None)  # every one of them was the restart
        return images


class Ingest:
    """Messages in, frames out; thread-safe (callbacks add, a timer pops). One lock guards all of it,
    shared with `ledger` (the counters and the consumer's reports) and `stream_ends`; images are decoded with it
    released (`_SensorInput.cleared` says whether what they were meant for was cleared meanwhile)."""

    def __init__(self, config: IngestConfig) -> None:
        self._config = config
        self._lock = threading.Lock()
        self._sensors = {name: _SensorInput(config) for name in config.sensors}
        self._set_aside = SetAside(config.sensors)
        self._time = _StreamTime(config, self._sensors, self._set_aside)
        # sensor -> time.monotonic() of its newest depth image
        self._last_depth_arrival_s = {name: -float("inf") for name in config.sensors}
        self._served_ns: dict[str, int] = {}  # sensor -> stamp of its last frame handed out (pop_ready)
        self.ledger = IngestLedger(self._lock, self._sensors, self._set_aside)
        self.stream_ends = StreamEnds(self._lock, self._sensors)

    @property
    def config(self) -> IngestConfig:
        return self._config

    @config.setter
    def config(self, config: IngestConfig) -> None:
        """New settings (the node's parameters changed) for the same sensors."""
        if config.sensors != self._config.sensors:
            raise ValueError(f"sensors {config.sensors} differ from {self._config.sensors}: make a new Ingest")
        with self._lock:
            self._config = config
            self._time.configure(config)
            # a lowered behind_buffer_mb holds for the frames set aside already too (a robot short of memory)
            for name, n in self._set_aside.trim(config.set_aside_bytes).items():
                self._sensors[name].drop("behind", n=n)

    # -- inputs ---------------------------------------------------------------------------

    def restart(self, to_ns: int | None = None) -> None:
        """Time restarted, known from outside (the /clock went back to `to_ns`): flush everything, start
        the timelines again from `to_ns` (old messages still in flight are off them) and report a
        TimeJump. Messages of the new time that came before it (dropped as bad_stamp until now) are
        taken."""
        with self._lock:
            held = self._time.restart(to_ns)
        self._decode_and_put(held, None)

    def add_camera_info(self, sensor: str, msg: Any) -> str | None:
        """Cache K and the image size, and queue the depth images that waited for it. Returns the
        drop reason, or None when it was cached."""
        stamp_ns, _ = _header_stamp(msg, "camera_info")
        with self._lock:
            state = _sensor_input(self._sensors, sensor)
            if stamp_ns == 0:  # used for nothing (K is cached): only named if the depth or poses are stamped 0 too
                state.unset_stamps.add("camera_info")
            reason, waited = state.set_camera_info(sensor, msg, self.config)
        return self._decode_and_put(waited, reason)

    def add_depth(self, sensor: str, msg: Any) -> str | None:
        """Queue one depth image. Returns the drop reason, or None when it was queued (or, before the
        sensor's first camera_info, put aside to wait for it)."""
        stamp_ns, stamp_error = _header_stamp(msg, "depth")
        with self._lock:
            state = _sensor_input(self._sensors, sensor)
            state.counters.received += 1
            state.ended = False
            if stamp_ns is None:
                return state.drop("bad_stamp", stamp_error)
            if state.stamped_zero_again("depth", stamp_ns):
                return state.unset_stamp("depth")
            self._last_depth_arrival_s[sensor] = arrival_s = time.monotonic()
            reason, held = self._time.on_time(sensor, "depth", stamp_ns, (msg, arrival_s))
            if reason == "out_of_order":  # it came, late: not missing
                state.late_depth(stamp_ns)
            taken = reason or state.accept(sensor, "depth", stamp_ns, (msg, arrival_s), self.config)
        return self._decode_and_put(held, taken)

    def add_color(self, sensor: str, msg: Any) -> str | None:
        """Buffer one colour image for matching. Returns the drop reason, or None."""
        stamp_ns, stamp_error = _header_stamp(msg, "color")
        with self._lock:
            state = _sensor_input(self._sensors, sensor)
            state.counters.color_received += 1
            state.ended = False
            if stamp_ns is None:
                return state.drop("bad_stamp", stamp_error)
            if state.stamped_zero_again("color", stamp_ns):
                return state.unset_stamp("color")
            reason, held = self._time.on_time(sensor, "color", stamp_ns, msg)
            taken = reason or state.accept(sensor, "color", stamp_ns, msg, self.config)
        return self._decode_and_put(held, taken)

    def add_undecodable(self, sensor: str, stream: str) -> None:
        """A message of the sensor's `stream` ("depth", "color", ...) whose bytes do not deserialise: a bag's
        damaged message (replay reads it; a live subscription never delivers one). Counted per stream
        (`undecodable`); colour that came but cannot be decoded makes the frames without colour count as
        `without_color`."""
        with self._lock:
            state = _sensor_input(self._sensors, sensor)
            state.counters.undecodable[stream] = state.counters.undecodable.get(stream, 0) + 1
            state.color_failed = state.color_failed or stream == "color"

    def add_tf(self, msg: Any, *, static: bool) -> str | None:
        """A tf2_msgs/TFMessage from /tf or /tf_static into config.tf (a senfunet_ros.tf.TfBuffer).
        Returns the drop reason (bad_stamp for a dynamic transform more than time_jump_s ahead of
        the streams' newest stamp and of the newest dynamic transform taken, which is left out;
        bad_pose for a transform the buffer refused: NaN, a non-unit quaternion, a cycle, a second
        parent; pose_conflict for a dynamic transform
        that gave a stamp its link had another value, the first kept), or None. Each transform left
        out is counted, on the first sensor (a transform serves them all); the rest of the message is
        kept."""
        if self.config.tf is None or not hasattr(self.config.tf, "add_message"):
            return None
        with self._lock:
            now_ns = self._time.timelines.now_ns()
        # ahead of the streams' newest stamp or, while the cameras pause and TF goes on, of TF's own
        tf_newest_ns = getattr(self.config.tf, "newest_ns", None)
        if now_ns is not None and tf_newest_ns is not None:
            now_ns = max(now_ns, tf_newest_ns)
        jump_ns = int(self.config.time_jump_s * 1e9)
        latest_ns = None if now_ns is None else now_ns + jump_ns
        try:
            added = self.config.tf.add_message(msg, static=static, latest_ns=latest_ns, behind_ns=jump_ns)
        except AttributeError as err:  # not a TFMessage
            added = TfAdded(refused=[str(err)])
        drops = []
        if added.ahead:
            assert now_ns is not None
            ahead_ns = conv.stamp_to_ns(added.ahead[0].header.stamp)
            drops.append(("bad_stamp", len(added.ahead), (
                f"tf: a transform stamped {ahead_ns * 1e-9:.3f} s, {(ahead_ns - now_ns) * 1e-9:.3f} "
                "s ahead of the newest stamp of the streams and /tf, was left out; check the clock of its publisher (a "
                "localiser that stamps ahead, nav2's amcl by its transform_tolerance, needs time_jump_s above that)")))
        if added.behind:
            behind = added.behind[0]
            drops.append(("bad_stamp", len(added.behind), (
                f"tf: a transform {behind.header.frame_id} -> {behind.child_frame_id} stamped "
                f"{conv.stamp_to_ns(behind.header.stamp) * 1e-9:.3f} s, more than time_jump_s before the link's "
                "newest, was left out (held: taken if the streams confirm that time went back)")))
        if added.unstamped:
            drops.append(("bad_stamp", len(added.unstamped), f"tf: a dynamic {added.unstamped[0]} stamped 0 (unset) "
                          "was left out; its publisher must stamp its transforms (the clock's now)"))
        if added.refused:
            drops.append(("bad_pose", len(added.refused), f"tf: {added.refused[0]}"))
        if added.conflicts:
            drops.append(("pose_conflict", len(added.conflicts), f"tf: {added.conflicts[0]}"))
        with self._lock:
            self._time.tf_held.extend([*added.ahead, *added.behind])
            first = self._sensors[self.config.sensors[0]]
            for reason, count, error in drops:
                first.drop(reason, error, n=count)
            if added.alternating:  # said on the first sensor too (a transform serves them all)
                first.counters.notes.setdefault("tf_alternates", (
                    f"tf: {added.alternating[0]}, back where the one two before was, as when two publishers of "
                    "one link interleave (an EKF and raw odometry both publishing odom -> base_link?): frames are "
                    "posed between both and the map smears; make one stop"))
        return drops[0][0] if drops else None

    def add_pose(self, sensor: str, msg: Any) -> str | None:
        """Add one pose message (PoseStamped, Odometry or TransformStamped). Returns the drop reason
        (pose_conflict: its stamp had another pose, which is kept)."""
        with self._lock:
            state = _sensor_input(self._sensors, sensor)
            state.counters.pose_received += 1
            state.ended = False
            stamp_ns, stamp_error = _header_stamp(msg, "pose")  # before the parser, whose error says bad_pose
            if stamp_ns is None:
                return state.drop("bad_stamp", stamp_error)
            if state.stamped_zero_again("pose", stamp_ns):
                return state.unset_stamp("pose")
            try:
                stamp_ns, T = self.config.pose_parser(msg)
                if sensor in self.config.T_body_camera:
                    T = T @ self.config.T_body_camera[sensor]  # T_world_body -> T_world_camera
            except (ValueError, AttributeError) as err:
                return state.drop("bad_pose", str(err))
            frame = str(getattr(msg.header, "frame_id", ""))
            # '/map' is 'map' (a ROS 1 habit; tf2 strips the '/' too)
            if frame.strip().lstrip("/") != self.config.fixed_frame and "pose_frame" not in state.counters.notes:
                state.counters.notes["pose_frame"] = _pose_frame_note(frame, self.config.fixed_frame)
            child = str(getattr(msg, "child_frame_id", "")).strip()  # Odometry's, TransformStamped's
            if (child and "optical" not in child.lower() and sensor not in self.config.T_body_camera
                    and "pose_child_frame" not in state.counters.notes):
                state.counters.notes["pose_child_frame"] = (
                    f"its poses are of frame '{child}' (their child_frame_id), which does not look like the camera's "
                    f"optical frame (z forward, x right, y down; REP 103 names them '*_optical_frame'), and "
                    f"{sensor}.T_body_camera is not set: the camera is posed as '{child}' itself. If '{child}' is the "
                    f"robot's body (base_link), set {sensor}.T_body_camera to the optical frame's pose in it (x y z qx "
                    "qy qz qw), or the map is built from the wrong viewpoints; if it is the optical frame by another "
                    "name, nothing to do")
            reason, held = self._time.on_time(sensor, "pose", stamp_ns, T)
            taken = reason or state.accept(sensor, "pose", stamp_ns, T, self.config)
            if (state.counters.pose_received % ALTERNATION_CHECK_EVERY == 0
                    and "pose_alternates" not in state.counters.notes):
                step_m = state.poses.alternation_m()
                if step_m is not None:
                    state.counters.notes["pose_alternates"] = (
                        f"its poses zig-zag: each is about {step_m * 100:.0f} cm from the one before and back where "
                        "the one two before was, as when two publishers on its pose topic interleave (a localiser "
                        "and an odometry?): frames are posed between both trajectories and the map smears; make "
                        "one stop, or give each its own topic")
        return self._decode_and_put(held, taken)

    def _decode_and_put(self, held: list[_Undecoded], taken: str | _Undecoded | None) -> str | None:
        """Decode, with the lock released, the images that waited (`held`: the new timeline's first
        messages once a restart is confirmed, or the depth images that waited for their camera_info),
        then the message just added if it is an image (`taken`; else its drop reason or None), and
        queue or buffer them, in that order. Returns the added message's drop reason, or None."""
        images = [*held, taken] if isinstance(taken, _Undecoded) else held
        if not images:
            return None if isinstance(taken, _Undecoded) else taken
        # other streams' messages and the integration go on meanwhile
        decoded = [_decode(image) for image in images]
        with self._lock:  # queued (depth) or buffered (colour) unless decoding failed or what it was for was cleared
            reasons = [self._sensors[image.sensor].enqueue(result, self.config, cleared=image.cleared,
                                                           name=image.sensor, set_aside=self._set_aside)
                       if image.stream == "depth" else
                       self._sensors[image.sensor].take_color(image.stamp_ns, result, cleared=image.cleared)
                       for image, result in zip(images, decoded)]
        return reasons[-1] if isinstance(taken, _Undecoded) else taken

    def restart_pending(self) -> bool:
        """Whether stamps off their streams' timelines (dropped as bad_stamp so far) may yet turn out
        to start a new one: a restart not yet confirmed, or strays."""
        with self._lock:
            return self._time.timelines.pending()

    # -- outputs --------------------------------------------------------------------------

    def pop_ready(self, max_frames: int | None = None, *, set_aside: bool = True) -> list[Frame | TimeJump]:
        """Time jumps seen since the last call, then the frames that can be posed, in stamp order:
        all of them, or `max_frames` of them, each the oldest of the sensor served longest ago (the
        rest stay queued, where a full queue drops the oldest: a consumer that falls behind sees
        bounded latency, not a growing backlog, and every sensor's frames). Frames
        the consumer fell behind on (more than max_lag_s) are set aside while set_aside_bytes has
        room, and handed out, oldest first, once no other frame is ready and no depth image of their
        sensor arrived for max_lag_s (wall time: the sensor paused or stopped; while it streams, a
        set-aside frame would only push a newer one behind; a sensor that stopped while another
        streams has its frames taken in the gaps) unless `set_aside` is False; beyond that room
        they are dropped as "behind".

        Frames still waiting for a pose, a colour image or a camera_info stay queued; frames that
        waited too long are dropped and counted.
        """
        with self._lock:
            jumps, self._time.jumps = self._time.jumps, []
            timelines = self._time.timelines
            frames: list[Frame] = []
            for name, state in self._sensors.items():
                frames.extend(state.pop(name, self.config, now_ns=timelines.sensor_now_ns(name),
                                        newest_depth_ns=timelines.last_ns(name, "depth"),
                                        depth_floor_ns=timelines.depth_floor_ns(name),
                                        last_color_ns=timelines.last_ns(name, "color"),
                                        set_aside=self._set_aside))
            if not frames and set_aside:
                now_s = time.monotonic()
                quiet = {name for name, arrival_s in self._last_depth_arrival_s.items()
                         if now_s - arrival_s >= self.config.max_lag_s}
                frames = self._set_aside.take_oldest(1 if max_frames is None else max_frames, of=quiet)
            order = {name: i for i, name in enumerate(self.config.sensors)}
            frames.sort(key=lambda f: (f.stamp_ns, order[f.sensor]))
            if jumps:  # a new timeline: stamps of the old one say nothing about whom to serve
                self._served_ns.clear()
            if max_frames is not None and len(frames) > max_frames:
                frames, back = _fair_share(frames, max_frames, order, self._served_ns)
                for frame in reversed(back):  # back to the front of their queues, newest last
                    self._sensors[frame.sensor].queue.appendleft(
                        _Pending(frame.stamp_ns, frame.depth_m, frame.K, frame.arrival_s, frame.rgb,
                                 frame.T_world_camera))
            for frame in frames:
                self._served_ns[frame.sensor] = frame.stamp_ns
        return [*jumps, *frames]

    def pop_set_aside(self) -> list[Frame]:
        """Every frame set aside, oldest first (the node stopping, to save them with the map)."""
        with self._lock:
            return self._set_aside.take_oldest(sum(self._set_aside.count(name) for name in self.config.sensors))


class IngestLedger:
    """What became of each sensor's messages: the counters and queue depths, and what the consumer
    reports of the frames it took (integrated, dropped, the map reset under the frames still
    waiting). Thread-safe, under Ingest's lock (`Ingest.ledger`)."""

    def __init__(self, lock: threading.Lock, sensors: dict[str, _SensorInput], set_aside: SetAside) -> None:
        self._lock = lock
        self._sensors = sensors
        self._set_aside = set_aside

    def mark_integrated(self, sensor: str) -> None:
        with self._lock:
            _sensor_input(self._sensors, sensor).counters.integrated += 1

    def mark_dropped(self, sensor: str, reason: str, error: str = "") -> None:
        """The caller dropped one of the sensor's frames; `error` says what was wrong with it."""
        if reason not in DROP_REASONS:
            raise ValueError(f"unknown drop reason '{reason}'; use one of {DROP_REASONS}")
        with self._lock:
            _sensor_input(self._sensors, sensor).drop(reason, error)

    def counters(self) -> dict[str, dict[str, Any]]:
        """A snapshot: sensor -> SensorCounters.as_dict() plus `queue_depth` (frames waiting, set
        aside included) and `set_aside_now`."""
        with self._lock:
            return {
                name: {**state.counters.as_dict(), "queue_depth": state.waiting() + self._set_aside.count(name),
                       "set_aside_now": self._set_aside.count(name)}
                for name, state in self._sensors.items()
            }

    def queue_depths(self) -> dict[str, int]:
        """Frames waiting per sensor: for a pose, a colour image, the consumer or a camera_info, or set
        aside."""
        with self._lock:
            return {name: state.waiting() + self._set_aside.count(name) for name, state in self._sensors.items()}

    def discard_waiting(self, reason: str) -> int:
        """Drop every frame still waiting (queued, before its camera_info or set aside), counted as
        `reason` ("map_reset": they belong to the map that was reset or replaced), and the colour
        images; poses and camera_info stay. Returns how many frames."""
        with self._lock:
            n = 0
            for name, count in self._set_aside.clear().items():
                n += count
                self._sensors[name].drop(reason, n=count)
            for state in self._sensors.values():
                n += state.discard(reason)
            return n


class StreamEnds:
    """When a sensor's streams have ended (a bag's end, the node stopping, or their silence for
    pose_max_wait_s) and what that did to its frames waiting for a pose. Thread-safe, under Ingest's
    lock (`Ingest.stream_ends`)."""

    def __init__(self, lock: threading.Lock, sensors: dict[str, _SensorInput]) -> None:
        self._lock = lock
        self._sensors = sensors

    def message_counts(self) -> dict[str, int]:
        """Per sensor, the depth, colour and pose messages received so far (for `end`)."""
        with self._lock:
            return {name: state.counters.messages_received for name, state in self._sensors.items()}

    def end(self, sensors: Iterable[str] | None = None, *, counts: dict[str, int] | None = None) -> None:
        """The streams of `sensors` (default: all) ended. From the next `Ingest.pop_ready` on, their
        frames newer than their newest pose are posed by extrapolation within pose_tolerance_s, the
        rest dropped as pose_timeout, and none waits for a colour image. `counts`: `message_counts()`
        when the sensors were found silent; one that received a message since is left as it is (it
        spoke again). A message on a sensor's streams starts them again."""
        with self._lock:
            for name in self._sensors if sensors is None else sensors:
                state = _sensor_input(self._sensors, name)
                if counts is None or counts.get(name) == state.counters.messages_received:
                    state.ended = True

    def take(self) -> dict[str, StreamEnd]:
        """What the ends of streams did to the frames waiting for a pose, per sensor, since the last
        call (only sensors where it did something)."""
        with self._lock:
            out = {name: state.end for name, state in self._sensors.items() if state.end}
            for name in out:
                self._sensors[name].end = StreamEnd()
            return out


def _fair_share(frames: list[Frame], n: int, order: dict[str, int], served_ns: dict[str, int]
                ) -> tuple[list[Frame], list[Frame]]:
    """n of the ready frames (in stamp order) for a consumer that cannot take them all, and the rest:
    each the oldest of the sensor served longest ago (`served_ns`: the stamp of its last frame handed out).
    The oldest frame of all would always be the sensor whose images arrive latest after their
    stamps, and the other's would fall behind (max_lag_s) and be set aside or dropped."""
    ready = {name: deque(f for f in frames if f.sensor == name) for name in order}
    served = dict(served_ns)  # as if each frame taken so far were handed out (pop_ready records them)
    taken: list[Frame] = []
    while len(taken) < n:
        name = min((name for name, queue in ready.items() if queue),
                   key=lambda name: (served.get(name, -1), ready[name][0].stamp_ns, order[name]))
        taken.append(ready[name].popleft())
        served[name] = taken[-1].stamp_ns
    back = [f for name in order for f in ready[name]]
    back.sort(key=lambda f: (f.stamp_ns, order[f.sensor]))
    taken.sort(key=lambda f: (f.stamp_ns, order[f.sensor]))
    return taken, back


def _sensor_input(sensors: dict[str, _SensorInput], sensor: str) -> _SensorInput:
    try:
        return sensors[sensor]
    except KeyError:
        raise ValueError(f"unknown sensor '{sensor}'; configured sensors are {list(sensors)}") from None


def _timeline_limits(config: IngestConfig) -> dict[str, Any]:
    """Timelines' limits from the settings: it holds at most what the queues would."""
    hold_msgs = {"depth": config.queue_size, "color": max(4, config.queue_size), "pose": config.pose_buffer_size}
    return {"time_jump_s": config.time_jump_s, "restart_confirm_msgs": config.restart_confirm_msgs,
            "restart_confirm_s": config.restart_confirm_s, "hold_msgs": hold_msgs}


def _decode_depth(msg: Any, stamp_ns: int, arrival_s: float, *, camera_info: tuple[np.ndarray, tuple[int, int]],
                  working_size: tuple[int, int], spacing_check: tuple[float, float, float] = (0.0, 0.0, math.inf)
                  ) -> _Pending | tuple[str, str]:
    """A depth image decoded, checked against its camera_info (K, (width, height)) and resized to the
    working size (0 in either: keep the aspect ratio; both 0: native): a frame waiting for its
    pose, or (drop reason, error). spacing_check (voxel size, depth range): with a voxel size > 0, its
    pixel spacing is checked against it too, when enough of its pixels lie in the range."""
    K, info_size = camera_info
    try:
        depth_m = conv.depth_from_image(msg)
    except ValueError as err:
        return "bad_encoding", f"depth: {err}"
    height, width = depth_m.shape
    notes: list[tuple[str, str]] = []
    units = conv.depth_units_note(msg, depth_m)
    if units:
        notes.append(("depth_units", units))
    try:  # a resize of the camera_info's view (a decimating driver) takes its K scaled, as the contract says
        K, note = conv.intrinsics_for_size(K, info_size, (width, height))
    except ValueError as err:
        return "size_mismatch", str(err)
    if note:
        notes.append(("camera_info_size", note))
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if not (-0.5 <= cx <= width - 0.5 and -0.5 <= cy <= height - 0.5):
        notes.append(("principal_point", f"the principal point of its camera_info's K (cx {cx:g}, cy {cy:g}) lies "
                      f"outside the {width}x{height} depth images: the frames are fused as K says, but unless they "
                      "are a crop (roi) that leaves out the image centre, K is another camera's or resolution's "
                      "and every ray is off; check the driver's camera_info"))
    if not np.any(depth_m > 0.0):
        return "all_invalid", ""
    target_width, target_height = working_size
    if target_width and not target_height:
        target_height = max(1, round(height * target_width / width))
    elif target_height and not target_width:
        target_width = max(1, round(width * target_height / height))
    target = (target_width or width, target_height or height)
    if not (working_size[0] and working_size[1]):  # one side given, the other follows the image's aspect ratio
        target, note = _bounded_working_size(target, (width, height), max(working_size))
        if note:
            notes.append(("image_size", note))
    if target != (width, height):
        depth_m = conv.resize_depth(depth_m, target)
        K = conv.scale_intrinsics(K, (width, height), target)
    voxel_size_m, depth_min_m, depth_max_m = spacing_check
    # a frame with few pixels in range (a sensor warming up, saturated) tells little: the next one is checked
    in_range = np.count_nonzero((depth_m > depth_min_m) & (depth_m <= depth_max_m))
    checked = bool(voxel_size_m > 0 and in_range >= _SPACING_MIN_SHARE * depth_m.size)
    if checked:
        note = _pixel_spacing_note(depth_m, K, voxel_size_m, native_size=(width, height),
                                   depth_range_m=(depth_min_m, depth_max_m))
        if note:
            notes.append(("pixel_spacing", note))
    return _Pending(stamp_ns, depth_m, K, arrival_s, frame_id=str(getattr(msg.header, "frame_id", "")),
                    source_size=(width, height), notes=tuple(notes), spacing_checked=checked)


# pixels up to this many voxels apart at the median depth are not worth a note: a frame's rays still observe about
# half of a facing surface's voxels, and any camera motion fills the rest (the sample's are 1.04-1.1 voxels apart)
PIXEL_SPACING_NOTE_VOXELS = 1.5


# a frame is checked for its pixel spacing when at least this share of its pixels lie in the sensor's depth range
_SPACING_MIN_SHARE = 0.1

# an image resized to working_width (or working_height) takes at most this many times that size squared
# pixels, unless it has more itself: a 2 x 1000 image is no 256 x 128000 frame (131 MB, seconds to fuse)
_WORKING_PIXELS_PER_SQUARE = 4


def _bounded_working_size(target: tuple[int, int], native: tuple[int, int], working_px: int
                          ) -> tuple[tuple[int, int], str | None]:
    """The size a frame is resized to (`target`, one side from the working size, the other from the
    image's aspect ratio) within _WORKING_PIXELS_PER_SQUARE x working_px^2 pixels, or the native
    size's if larger; and a note when that bound shrank it."""
    limit = max(_WORKING_PIXELS_PER_SQUARE * working_px * working_px, native[0] * native[1])
    if target[0] * target[1] <= limit:
        return target, None
    scale = (limit / (target[0] * target[1])) ** 0.5
    bounded = (max(1, int(target[0] * scale)), max(1, int(target[1] * scale)))
    return bounded, (f"its {native[0]}x{native[1]} depth images would be {target[0]}x{target[1]} at the working "
                     f"size ({working_px} px): they are fused at {bounded[0]}x{bounded[1]}, to keep a frame "
                     f"within {_WORKING_PIXELS_PER_SQUARE} x {working_px}^2 pixels; an image this narrow is "
                     "seldom a depth camera's: check the driver's width and height")


def _pixel_spacing_note(depth_m: np.ndarray, K: np.ndarray, voxel_size_m: float, *, native_size: tuple[int, int],
                        depth_range_m: tuple[float, float]) -> str | None:
    """What to expect and change when a frame's pixels lie further apart than 1.5 voxels at its median
    depth within depth_range_m (neighbouring rays skip voxels: holes in the mesh), or None."""
    from senfunet_core.integrator import pixel_spacing_m

    median_m, spacing_m = pixel_spacing_m(depth_m, K, depth_range_m=depth_range_m)
    if spacing_m <= PIXEL_SPACING_NOTE_VOXELS * voxel_size_m:
        return None
    height, width = depth_m.shape
    # the width at which pixels would be a voxel apart there, if the camera has that many
    needed_width = int(np.ceil(width * spacing_m / voxel_size_m))
    more = (f"working_width {needed_width} (the images are {native_size[0]}x{native_size[1]}, fused at "
            f"{width}x{height})" if needed_width <= native_size[0] else
            f"a camera of at least {needed_width} pixels across (this one gives {native_size[0]})")
    return (f"its pixels lie {spacing_m * 1000:.1f} mm apart at its median depth {median_m:.2f} m (fx {K[0, 0]:.4g}, "
            f"fy {K[1, 1]:.4g} px at {width}x{height}), more than the {voxel_size_m * 1000:.1f} mm voxels: a frame's "
            f"rays observe about {(voxel_size_m / spacing_m) ** 2:.0%} of the voxels of a surface facing it there "
            "(fewer farther); the rest wait for other viewpoints' rays, so where the camera stays still the mesh "
            f"will have holes. Use voxels of at least {spacing_m * 1000:.1f} mm (voxel_size_m), or {more}")


def _header_stamp(msg: Any, stream: str) -> tuple[int | None, str]:
    """A message's header stamp in ns, or None and what was wrong with it (a bad_stamp)."""
    try:
        return conv.stamp_to_ns(msg.header.stamp), ""
    except ValueError as err:
        return None, f"{stream}: {err}"


def _decode_color(msg: Any) -> np.ndarray | str:
    """A colour image as HxWx3 RGB, or what was wrong with it."""
    try:
        return conv.rgb_from_image(msg)
    except ValueError as err:
        return str(err)


def _pose_frame_note(frame: str, fixed_frame: str) -> str:
    """What a sensor's notes say of poses that are not in the fixed frame: the node takes them as given."""
    given = "have no frame_id" if not frame else f"are in frame '{frame}'"
    fix = "set the pose source's frame_id" if not frame else f"set fixed_frame to '{frame.strip().lstrip('/')}'"
    return (f"its poses {given}, not the fixed frame '{fixed_frame}' (parameter fixed_frame): they are fused as "
            f"given, as poses in '{fixed_frame}', where the mesh is published; {fix}, or use pose_type tf, "
            "which looks the camera up in the fixed frame")


def _same_intrinsics(a: tuple[np.ndarray, tuple[int, int]], b: tuple[np.ndarray, tuple[int, int]]) -> bool:
    """Whether two camera_infos (K, size) are one (a republished one may differ by float noise)."""
    return a[1] == b[1] and bool(np.allclose(a[0], b[0], rtol=1e-6, atol=1e-6))


_COLOUR = "colour: "  # how a colour image's error starts (the others are of depth, pose, camera_info messages)
_STREAM_LABELS = {"depth": "depth", "color": "colour", "pose": "pose", "camera_info": "camera_info"}  # in texts


def split_stream_errors(text: str) -> tuple[str, str]:
    """A reason's error text (`SensorCounters.errors`) as (the depth, pose or camera_info message's
    part, the colour image's part starting with "colour: "); either may be empty."""
    if text.startswith(_COLOUR):
        return "", text
    other, separator, colour = text.partition("; " + _COLOUR)
    return other, (_COLOUR + colour if separator else "")


def _with_other_stream(last: str, error: str) -> str:
    """A reason's error text after `error`: it replaces the last error of its own stream but keeps the
    colour stream's beside the others' (a sensor whose depth and colour both fail to decode needs both
    named, not the one that came last)."""
    other, colour = split_stream_errors(last)
    if error.startswith(_COLOUR):
        return f"{other}; {error}" if other else error
    return f"{error}; {colour}" if colour else error


def _pose_drop_error(reason: str, stamp_ns: int, now_ns: int | None, poses: PoseBuffer, config: IngestConfig) -> str:
    """What a frame that gets no pose from the pose topic met (`PoseBuffer.at`'s reason), and what to check."""
    before_ns, after_ns = poses.around(stamp_ns)
    if reason == "pose_timeout":
        newest = "no pose has come yet" if before_ns is None else f"the newest pose is at {before_ns * 1e-9:.3f} s"
        now = "" if now_ns is None else f", until the sensor's newest stamp reached {now_ns * 1e-9:.3f} s"
        return (f"pose: the frame at {stamp_ns * 1e-9:.3f} s waited for a pose at or after its stamp for more than "
                f"pose_max_wait_s ({config.pose_max_wait_s:g} s) of stream time{now}, and {newest}; check that poses "
                "arrive and are stamped on the depth images' clock, or raise pose_max_wait_s if they come later")
    jump = poses.jump_across(stamp_ns)
    if jump is not None:
        return (f"pose: the poses jumped {jump[2]:.2f} m, {jump[3]:.1f} deg between {jump[0] * 1e-9:.3f} s and "
                f"{jump[1] * 1e-9:.3f} s (a localiser relocalising?), far more than they move between poses otherwise: "
                f"the frame at {stamp_ns * 1e-9:.3f} s between them is not posed")
    before = "none before it" if before_ns is None else f"{(stamp_ns - before_ns) * 1e-6:.0f} ms before it"
    after = "none after it" if after_ns is None else f"{(after_ns - stamp_ns) * 1e-6:.0f} ms after it"
    return (f"pose: the poses nearest the frame at {stamp_ns * 1e-9:.3f} s lie {before} and {after}, farther than "
            f"pose_tolerance_s ({config.pose_tolerance_s * 1e3:g} ms) on one side; publish poses more often or raise "
            "pose_tolerance_s")


def _tf_pose(config: IngestConfig, pending: _Pending, *, waited_too_long: bool
             ) -> tuple[np.ndarray | None, str | None, str]:
    """T_world_camera of a queued frame from TF (config.tf, in config.fixed_frame), as `PoseBuffer.at`
    answers, with the reason's error."""
    try:
        return config.tf.lookup(config.fixed_frame, pending.frame_id, pending.stamp_ns), None, ""
    except TfWait as err:
        if not waited_too_long:
            return None, None, ""
        waited = f"tf: {err}; the frame waited pose_max_wait_s ({config.pose_max_wait_s:g} s) of stream time"
        if isinstance(err, TfNotConnected) and err.unknown_frame == config.fixed_frame.lstrip("/"):
            return None, "pose_timeout", waited  # the error says what to set
        if isinstance(err, TfNotConnected):
            return None, "pose_timeout", (
                f"{waited} for transforms that join the two frames: they came later than that or not at all (a "
                "robot_state_publisher or static_transform_publisher started after the cameras, or not running?)")
        return None, "pose_timeout", (
            f"{waited}: a link published less often than that (a localiser's map -> odom) needs a larger "
            "pose_max_wait_s (above its interval and latency) or a fixed_frame below it (odom); a link whose "
            "publisher stopped needs it back")
    except ValueError as err:  # TfError: a gap, or no frame_id
        return None, "pose_gap", f"tf: {err}"


class SetAside:
    """Posed frames the consumer fell behind on, per sensor, oldest first, within a byte budget
    for all sensors. Not thread-safe: Ingest calls it under its lock."""

    def __init__(self, sensors: tuple[str, ...]) -> None:
        self._frames: dict[str, deque[Frame]] = {name: deque() for name in sensors}
        self._nbytes = 0

    def put(self, frame: Frame, *, budget_bytes: int) -> bool:
        """Keep a frame for later if the budget has room; False (not kept) if not."""
        size = _frame_bytes(frame)
        if self._nbytes + size > budget_bytes:
            return False
        frame.set_aside = True
        self._frames[frame.sensor].append(frame)
        self._nbytes += size
        return True

    def take_oldest(self, n: int, *, of: Collection[str] | None = None) -> list[Frame]:
        """The n oldest frames of these sensors (None: all)."""
        out: list[Frame] = []
        while len(out) < n:
            waiting = [frames for name, frames in self._frames.items() if frames and (of is None or name in of)]
            if not waiting:
                break
            frame = min(waiting, key=lambda frames: frames[0].stamp_ns).popleft()
            self._nbytes -= _frame_bytes(frame)
            out.append(frame)
        return out

    def trim(self, budget_bytes: int) -> dict[str, int]:
        """Forget the newest frames, all sensors, until the rest fit in budget_bytes (as `put` keeps the
        oldest when full); returns how many per sensor."""
        dropped = {name: 0 for name in self._frames}
        while self._nbytes > budget_bytes:
            frames = max((frames for frames in self._frames.values() if frames), key=lambda f: f[-1].stamp_ns)
            frame = frames.pop()
            self._nbytes -= _frame_bytes(frame)
            dropped[frame.sensor] += 1
        return dropped

    def count(self, sensor: str) -> int:
        return len(self._frames[sensor])

    def clear(self) -> dict[str, int]:
        """Forget every frame; returns how many per sensor."""
        counts = {name: len(frames) for name, frames in self._frames.items()}
        for frames in self._frames.values():
            frames.clear()
        self._nbytes = 0
        return counts


def _frame_bytes(frame: Frame) -> int:
    return frame.depth_m.nbytes + (0 if frame.rgb is None else frame.rgb.nbytes)


class NoDepthInRange(ValueError):
    """A frame with no depth pixel the engine keeps: none within its sensor's depth range inside the
    image border. Nothing was integrated."""


def _no_depth_in_range(depth_m: np.ndarray, border_px: int) -> NoDepthInRange:
    """Why a frame had no depth the engine keeps: too small for the image border it leaves out, or
    (with the deepest pixel inside that border) out of the sensor's range."""
    height, width = depth_m.shape
    if min(height, width) <= 2 * border_px:
        return NoDepthInRange(f"the image ({width}x{height}) is not larger than twice the {border_px}-pixel border "
                              "the engine leaves out, so none of it is used; publish larger images (or raise "
                              "working_width)")
    inner = depth_m[border_px:height - border_px, border_px:width - border_px]
    deepest = float(np.max(inner, where=np.isfinite(inner), initial=0.0))
    return NoDepthInRange(f"no depth pixel within the sensor's depth_min_m..depth_max_m inside the image border "
                          f"(the deepest is {deepest:.3f} m" + (": millimetres in a 32FC1 image?)" if deepest > 100
                                                                  else ")"))


def integrate_ready(engine: Any, items: Iterable[Frame | TimeJump], on_time_jump: Callable[[TimeJump], None],
                    on_frame: Callable[[Frame, Exception | None, float], None]) -> None:
    """Hand ready items to the engine in order, one frame ahead: each frame is prepared (checked, its
    feature net started) before the frame before it is integrated, so that the feature net runs while
    the integration kernels do. A time jump is handled once every frame before it is integrated.

    on_frame(frame, error, seconds) follows each frame: error is None once it is integrated, or what
    the engine raised (the frame is lost, the map is not), or NoDepthInRange (nothing to integrate);
    seconds is the engine time it took."""
    from senfunet_core.engine import prepare_frame

    ahead: tuple[Frame, Any, float] | None = None

    def finish() -> None:
        nonlocal ahead
        if ahead is None:
            return
        (frame, prepared, seconds), ahead = ahead, None
        error = prepared if isinstance(prepared, Exception) else None
        if error is None and prepared.empty:
            error = _no_depth_in_range(frame.depth_m, int(engine.config.border_px))
        elif error is None:
            start = time.perf_counter()
            try:
                engine.integrate_prepared(prepared)
            except Exception as err:  # noqa: BLE001 (the caller decides what is fatal)
                error = err
            seconds += time.perf_counter() - start
        on_frame(frame, error, seconds)

    for item in items:
        if isinstance(item, TimeJump):
            finish()
            on_time_jump(item)
            continue
        start = time.perf_counter()
        prepared: Any
        try:
            prepared = prepare_frame(engine, item.sensor, item.depth_m, item.K, item.T_world_camera, item.rgb)
        except Exception as err:  # noqa: BLE001
            prepared = err
        seconds = time.perf_counter() - start
        finish()
        ahead = (item, prepared, seconds)
    finish()
