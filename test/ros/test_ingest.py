"""senfunet_ros.ingest: messages in, posed frames out, every drop counted; no node, no clock."""
from __future__ import annotations

import dataclasses

import math
import re
import threading

import time

import numpy as np
import torch
import pytest
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import CameraInfo, Image

from senfunet_ros import conversions as conv
from senfunet_ros.geometry import interpolate_pose
from senfunet_ros.ingest import Frame, Ingest, IngestConfig, TimeJump

MS = 1_000_000  # nanoseconds


def _stamp(msg, t_ns: int) -> None:
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)


def depth_msg(t_ns: int, value: float = 1.0, shape: tuple[int, int] = (8, 10), encoding: str = "32FC1") -> Image:
    h, w = shape
    msg = Image(height=h, width=w, encoding=encoding, step=w * 4)
    msg.data = np.full((h, w), value, "<f4").tobytes()
    _stamp(msg, t_ns)
    return msg


def color_msg(t_ns: int, value: int = 50, shape: tuple[int, int] = (8, 10)) -> Image:
    h, w = shape
    msg = Image(height=h, width=w, encoding="rgb8", step=w * 3)
    msg.data = np.full((h, w, 3), value, np.uint8).tobytes()
    _stamp(msg, t_ns)
    return msg


def info_msg(shape: tuple[int, int] = (8, 10)) -> CameraInfo:
    h, w = shape
    return CameraInfo(width=w, height=h, k=[10.0, 0, (w - 1) / 2, 0, 10.0, (h - 1) / 2, 0, 0, 1])


def pose_msg(t_ns: int, x: float = 0.0, yaw_rad: float = 0.0) -> PoseStamped:
    msg = PoseStamped()
    _stamp(msg, t_ns)
    msg.pose.position.x = x
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw_rad / 2), math.cos(yaw_rad / 2)
    return msg


def make(**kwargs) -> Ingest:
    ingest = Ingest(IngestConfig(sensors=("tof", "stereo"), **kwargs))
    for s in ("tof", "stereo"):
        assert ingest.add_camera_info(s, info_msg()) is None
    return ingest


def frames(items) -> list[Frame]:
    return [i for i in items if isinstance(i, Frame)]


def test_frame_waits_for_later_pose_then_is_interpolated() -> None:
    ingest = make()
    ingest.add_pose("tof", pose_msg(0, x=0.0, yaw_rad=0.0))
    assert ingest.add_depth("tof", depth_msg(25 * MS)) is None
    assert ingest.pop_ready() == []  # no pose after the frame yet
    assert ingest.ledger.queue_depths()["tof"] == 1
    ingest.add_pose("tof", pose_msg(100 * MS, x=1.0, yaw_rad=math.pi / 2))
    (frame,) = frames(ingest.pop_ready())
    assert frame.sensor == "tof" and frame.stamp_ns == 25 * MS
    np.testing.assert_allclose(frame.T_world_camera[:3, 3], [0.25, 0, 0])
    yaw = math.atan2(frame.T_world_camera[1, 0], frame.T_world_camera[0, 0])
    assert yaw == pytest.approx(math.pi / 8)  # slerp: a quarter of the way
    assert frame.depth_m.dtype == np.float32 and frame.rgb is None
    ingest.ledger.mark_integrated("tof")
    assert ingest.ledger.counters()["tof"]["integrated"] == 1 and ingest.ledger.counters()["tof"]["received"] == 1


def test_interpolate_pose_endpoints_and_short_way() -> None:
    T0, T1 = np.eye(4), np.eye(4)
    T1[:3, :3] = [[-1, 0, 0], [0, -1, 0], [0, 0, 1]]  # 180 deg about z
    T1[:3, 3] = [2, 0, 0]
    np.testing.assert_allclose(interpolate_pose(T0, T1, 0.0), T0, atol=1e-12)
    np.testing.assert_allclose(interpolate_pose(T0, T1, 1.0), T1, atol=1e-12)
    R = interpolate_pose(T0, T1, 0.5)[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


def test_pose_timeout_and_gap() -> None:
    ingest = make(pose_max_wait_s=0.5, pose_tolerance_s=0.05)
    ingest.add_depth("tof", depth_msg(0))  # no pose stream at all
    ingest.add_depth("tof", depth_msg(600 * MS))  # stream time moves on past the limit
    assert ingest.pop_ready() == []
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["pose_timeout"] == 1
    # the error says which frame waited, until when, for what (the hint alone named none of it)
    error = counters["errors"]["pose_timeout"]
    assert "frame at 0.000 s" in error and "reached 0.600 s" in error and "no pose has come yet" in error, error
    ingest.add_pose("tof", pose_msg(400 * MS))
    ingest.add_pose("tof", pose_msg(800 * MS))  # both 200 ms from the frame: beyond the tolerance
    assert ingest.pop_ready() == []
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["pose_gap"] == 1
    assert "lie 200 ms before it and 200 ms after it" in counters["errors"]["pose_gap"], counters["errors"]
    assert ingest.ledger.queue_depths()["tof"] == 0


def test_a_pose_stream_that_jumps_is_not_interpolated_across_the_jump() -> None:
    """A localiser relocalising moves its pose topic 0.5 m and 20 degrees in one step. The frame between
    those two poses was posed halfway across the jump and fused, unsaid; it is now a pose_gap naming
    the jump (as TF links are: test_tf). Fast smooth motion (5 cm a step) is still interpolated."""
    ingest = make(pose_tolerance_s=0.05)
    period, fused = 33 * MS, []
    for k in range(40):
        x = 0.05 * k + (0.5 if k >= 20 else 0.0)
        ingest.add_pose("tof", pose_msg(k * period, x=x, yaw_rad=math.radians(20.0) if k >= 20 else 0.0))
        if k:  # frame k lies between poses k - 1 and k
            ingest.add_depth("tof", depth_msg(k * period - 16 * MS))
        fused += frames(ingest.pop_ready())
    assert len(fused) == 38 and 20 * period - 16 * MS not in [f.stamp_ns for f in fused]
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["pose_gap"] == 1, counters
    error = counters["errors"]["pose_gap"]
    assert "jumped 0.55 m, 20.0 deg between 0.627 s and 0.660 s" in error and "0.644 s" in error, error
    after = next(f for f in fused if f.stamp_ns == 21 * period - 16 * MS)
    assert after.T_world_camera[0, 3] == pytest.approx(0.05 * 20.5 + 0.5, abs=0.002)


def test_a_pose_stamped_ahead_by_a_glitch_costs_no_frame() -> None:
    """A pose a glitching driver stamped 0.5 s ahead (within time_jump_s, so taken) was the next pose
    of the frames before it: they were dropped as pose_gap at once, though the stream's own poses
    around them came a moment later. Now they wait for those while the far pose is the newest."""
    ingest = make(pose_max_wait_s=1.0, pose_tolerance_s=0.05)
    for k in range(5):
        ingest.add_pose("tof", pose_msg(k * 10 * MS, x=0.01 * k))
    ingest.add_pose("tof", pose_msg(540 * MS, x=9.0))  # the glitch
    ingest.add_depth("tof", depth_msg(45 * MS))
    assert ingest.pop_ready() == []  # waits: the pose after it is far, but the newest
    ingest.add_pose("tof", pose_msg(50 * MS, x=0.05))  # the stream's own next pose
    (frame,) = frames(ingest.pop_ready())
    assert frame.T_world_camera[0, 3] == pytest.approx(0.045)
    assert ingest.ledger.counters()["tof"]["dropped"]["pose_gap"] == 0
    # a real hole in the poses after 50 ms: a gap once the stream went on past the pose after it
    ingest.add_depth("tof", depth_msg(55 * MS))
    assert ingest.pop_ready() == [] and ingest.ledger.queue_depths()["tof"] == 1
    ingest.add_pose("tof", pose_msg(550 * MS, x=0.55))
    assert ingest.pop_ready() == [] and ingest.ledger.counters()["tof"]["dropped"]["pose_gap"] == 1


def test_extrapolate_pose_continues_the_motion_that_interpolate_pose_follows() -> None:
    """The pose halfway from T0 to T2 (slerp, lerp), extrapolated from T0 through it to twice as far,
    is T2: the same axis and rate of turn, a generic one well beyond the small-angle case."""
    from senfunet_ros.geometry import extrapolate_pose, transform_from_tq

    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    T0 = transform_from_tq([0.1, 0.2, 0.3], [0.0, 0.0, 0.0, 1.0], "T0")
    half = math.radians(70) / 2
    T2 = transform_from_tq([1.1, -0.4, 0.7], [*(axis * math.sin(half)), math.cos(half)], "T2")
    T1 = interpolate_pose(T0, T2, 0.5)
    np.testing.assert_allclose(extrapolate_pose(T0, T1, 2.0), T2, atol=1e-9)
    np.testing.assert_allclose(extrapolate_pose(T0, T1, 1.0), T1, atol=1e-12)
    with pytest.raises(ValueError, match="s >= 1"):
        extrapolate_pose(T0, T1, 0.5)


def test_at_the_end_of_a_stream_a_frame_past_the_newest_pose_is_posed_by_extrapolation() -> None:
    """The pose stream stops before the depth stream: the last frames, newer than the newest pose, waited
    for a pose that never comes (left in the queue, then dropped at the stop). Once the streams ended, a
    frame within pose_tolerance_s past the newest pose is posed by continuing the poses' motion at
    constant velocity (counted as extrapolated), one further is dropped as pose_timeout."""
    ingest = make(pose_max_wait_s=1.0, pose_tolerance_s=0.1)
    speed_m_s, turn_rad_s = 0.5, 1.0  # constant velocity: the extrapolation is exact
    for k in range(11):  # poses at 100 Hz up to 100 ms
        t_s = 0.01 * k
        ingest.add_pose("tof", pose_msg(10 * k * MS, x=speed_m_s * t_s, yaw_rad=turn_rad_s * t_s))
    ingest.add_depth("tof", depth_msg(130 * MS))  # 30 ms past the newest pose
    ingest.add_depth("tof", depth_msg(250 * MS))  # 150 ms past it: beyond pose_tolerance_s
    assert ingest.pop_ready() == [] and ingest.ledger.queue_depths()["tof"] == 2  # waiting for a later pose
    ingest.stream_ends.end()
    (frame,) = frames(ingest.pop_ready())
    assert frame.stamp_ns == 130 * MS
    T = frame.T_world_camera
    assert np.linalg.norm(T[:3, 3] - [speed_m_s * 0.13, 0, 0]) < 1e-3  # right to 1 mm
    assert math.atan2(T[1, 0], T[0, 0]) == pytest.approx(turn_rad_s * 0.13, abs=1e-6)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    counters = ingest.ledger.counters()["tof"]
    assert counters["extrapolated"] == 1 and counters["dropped"]["pose_timeout"] == 1
    assert "150 ms past the newest pose" in counters["errors"]["pose_timeout"]
    assert ingest.ledger.queue_depths()["tof"] == 0
    (sensor, end), = ingest.stream_ends.take().items()  # reported once
    assert sensor == "tof" and (end.extrapolated, end.timed_out) == (1, 1)
    assert (end.extrapolated_max_ns, end.timed_out_max_ns) == (30 * MS, 150 * MS)
    assert ingest.stream_ends.take() == {}


def test_a_stream_that_speaks_again_after_its_end_waits_for_its_poses_again() -> None:
    """The end holds until a message comes on the sensor's streams; `counts` taken when the sensor was
    found silent leaves one that spoke since as it is (a frame that arrived meanwhile waits for its pose)."""
    ingest = make(pose_tolerance_s=0.1)
    for k in range(3):
        ingest.add_pose("tof", pose_msg(10 * k * MS, x=0.01 * k))
    counts = ingest.stream_ends.message_counts()
    ingest.add_depth("tof", depth_msg(25 * MS))  # arrived after the silence was judged
    ingest.stream_ends.end(["tof"], counts=counts)
    assert ingest.pop_ready() == [] and ingest.ledger.queue_depths()["tof"] == 1
    ingest.stream_ends.end(["tof"])
    ingest.add_pose("tof", pose_msg(30 * MS, x=0.03))  # it speaks again: the frame takes the pose that came
    (frame,) = frames(ingest.pop_ready())
    assert frame.T_world_camera[0, 3] == pytest.approx(0.025)
    ingest.add_depth("tof", depth_msg(35 * MS))
    assert ingest.pop_ready() == []  # the streams go on: it waits for a later pose
    assert ingest.ledger.counters()["tof"]["extrapolated"] == 0


@pytest.mark.parametrize("case", ["bad_encoding", "size_mismatch", "all_invalid", "bad_pose", "bad_camera_info"])
def test_bad_inputs_are_counted(case: str) -> None:
    ingest = Ingest(IngestConfig(sensors=("tof", "stereo")))
    ingest.add_camera_info("tof", info_msg())
    if case == "bad_pose":
        msg = pose_msg(0)
        msg.pose.orientation.w = float("nan")
        assert ingest.add_pose("tof", msg) == "bad_pose"
    elif case == "bad_camera_info":  # after a good one, which stays in use (and the error says so)
        assert ingest.add_camera_info("tof", CameraInfo(width=10, height=8)) == "bad_camera_info"
        assert "go on with the last good camera_info's K" in ingest.ledger.counters()["tof"]["errors"][case]
        assert ingest.add_depth("tof", depth_msg(0)) is None and ingest.ledger.queue_depths()["tof"] == 1
        assert ingest.add_camera_info("stereo", CameraInfo(width=10, height=8)) == "bad_camera_info"
        assert "last good" not in ingest.ledger.counters()["stereo"]["errors"][case]  # it has none
        ingest.add_pose("tof", pose_msg(0))
        assert len(frames(ingest.pop_ready())) == 1
    else:
        msg = {
            "bad_encoding": depth_msg(0, encoding="rgb8"),
            "size_mismatch": depth_msg(0, shape=(4, 4)),
            "all_invalid": depth_msg(0, value=float("nan")),
        }[case]
        assert ingest.add_depth("tof", msg) == case
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"][case] == 1
    assert sum(counters["dropped"].values()) == 1 and counters["queue_depth"] == 0
    if case != "all_invalid":  # the others say what was wrong with the message
        assert len(counters["errors"][case]) > 20
    if case == "bad_camera_info":
        # a depth image of the refused camera_info's size is dropped for not matching the last good one, and
        # its error names the refusal, the cause to fix (it named the good one's size alone)
        refused = CameraInfo(width=7, height=3, k=[10.0, 0, 3, 0, float("nan"), 1, 0, 0, 1])
        assert ingest.add_camera_info("tof", refused) == "bad_camera_info"
        assert ingest.add_depth("tof", depth_msg(10 * MS, shape=(3, 7))) == "size_mismatch"
        error = ingest.ledger.counters()["tof"]["errors"]["size_mismatch"]
        assert "the newest camera_info was refused: " in error, error
        assert ingest.add_camera_info("tof", info_msg()) is None
        assert ingest.add_depth("tof", depth_msg(20 * MS, shape=(3, 7))) == "size_mismatch"
        assert "refused" not in ingest.ledger.counters()["tof"]["errors"]["size_mismatch"]


def test_depth_and_colour_that_both_fail_to_decode_are_both_named() -> None:
    """Depth in "32fc1" and colour in "yuv422": both dropped as bad_encoding, but the error (and so the
    warning and ~/status) named only the colour, which came last; fixing it left a node without a map
    and no word why."""
    from senfunet_ros.status import counter_warnings

    ingest = make()
    before = ingest.ledger.counters()
    for k in range(1, 4):
        ingest.add_color("tof", color_msg(k * 10 * MS))
        ingest.add_depth("tof", depth_msg(k * 10 * MS, encoding="32fc1"))
        bad_colour = color_msg(k * 10 * MS)
        bad_colour.encoding = "yuv422"
        ingest.add_color("tof", bad_colour)
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_encoding"] == 6
    error = counters["errors"]["bad_encoding"]
    assert "32fc1" in error and "yuv422" in error and error.index("32fc1") < error.index("colour: "), error
    from senfunet_ros.params_file import load_settings
    warnings = dict(counter_warnings(before, ingest.ledger.counters(), load_settings(None)))
    assert "32fc1" in warnings[("tof", "bad_encoding")], warnings


@pytest.mark.parametrize("x_m", [1e6, 1e9, 1e300])
def test_a_pose_beyond_the_maps_reach_is_refused_and_spoils_no_frame(x_m: float) -> None:
    """A pose kilometres away (a wrong unit, a glitch) was taken into the pose buffer: the good frame
    between it and the good poses was interpolated with it (and then refused by the engine, lost),
    and nothing counted the pose as bad."""
    ingest = make()
    ingest.add_camera_info("tof", info_msg())
    ingest.add_pose("tof", pose_msg(0))
    assert ingest.add_pose("tof", pose_msg(MS, x=x_m)) == "bad_pose"
    ingest.add_depth("tof", depth_msg(5 * MS))
    ingest.add_pose("tof", pose_msg(10 * MS))
    (frame,) = frames(ingest.pop_ready())
    np.testing.assert_allclose(frame.T_world_camera, np.eye(4), atol=1e-12)
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_pose"] == 1 and "km from the origin" in counters["errors"]["bad_pose"]


@pytest.mark.parametrize("stream", ["depth", "color", "pose"])
def test_a_stamp_whose_nanosec_is_not_below_one_second_is_a_bad_stamp(stream: str) -> None:
    """nanosec 1500000000 was read as 1.5 s later: a pose within time_jump_s ahead was taken, and the
    frames before it lost their poses (pose_gap); a depth image moved its timeline ahead."""
    ingest = make()
    ingest.add_camera_info("tof", info_msg())
    ingest.add_pose("tof", pose_msg(0))
    msg = {"depth": depth_msg(5 * MS), "color": color_msg(5 * MS), "pose": pose_msg(5 * MS)}[stream]
    msg.header.stamp.nanosec = 1_500_000_000
    add = {"depth": ingest.add_depth, "color": ingest.add_color, "pose": ingest.add_pose}[stream]
    assert add("tof", msg) == "bad_stamp"
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_stamp"] == 1 and "nanosec 1500000000" in counters["errors"]["bad_stamp"]
    ingest.add_depth("tof", depth_msg(10 * MS))
    ingest.add_pose("tof", pose_msg(20 * MS))
    assert [f.stamp_ns for f in frames(ingest.pop_ready())] == [10 * MS]


def test_odometry_of_a_body_frame_without_an_extrinsic_is_said_once() -> None:
    """nav_msgs/Odometry of base_link with T_body_camera left at identity: the camera was posed as the
    robot's body (a map from the wrong viewpoints, F 10 where 67 with the extrinsic), without a word.
    A child frame that does not look optical is now said once, unless the sensor has its extrinsic."""
    from nav_msgs.msg import Odometry

    def odometry(t_ns: int, child: str) -> Odometry:
        odom = Odometry(child_frame_id=child)
        odom.header = pose_msg(t_ns).header
        odom.header.frame_id = "map"
        odom.pose.pose.orientation.w = 1.0
        return odom

    body = np.eye(4)
    body[:3, 3] = (0.1, 0.0, 0.2)
    ingest = make(fixed_frame="map", T_body_camera={"stereo": body})
    for t_ns in (0, 10 * MS):
        assert ingest.add_pose("tof", odometry(t_ns, "base_link")) is None
        assert ingest.add_pose("stereo", odometry(t_ns, "base_link")) is None
    notes = ingest.ledger.counters()
    note = notes["tof"]["notes"]["pose_child_frame"]
    assert "poses are of frame 'base_link'" in note and "set tof.T_body_camera" in note, note
    assert "pose_child_frame" not in notes["stereo"]["notes"]  # it has its extrinsic
    optical = make(fixed_frame="map")
    assert optical.add_pose("tof", odometry(0, "tof_depth_optical_frame")) is None
    assert "pose_child_frame" not in optical.ledger.counters()["tof"]["notes"]


def test_poses_that_are_not_in_the_fixed_frame_are_fused_as_given_and_said_once() -> None:
    """A pose source in another frame (odom) or in none: its poses are taken as given, as the contract
    says, and the sensor's notes (logged once, in ~/status and replay's stats) say so, naming both
    frames; poses in the fixed frame give no note."""
    ingest = make(fixed_frame="map")
    for t_ns, frame in ((0, "odom"), (50_000_000, "base_link"), (100_000_000, "odom")):
        pose = pose_msg(t_ns)
        pose.header.frame_id = frame
        assert ingest.add_pose("tof", pose) is None
    assert ingest.add_depth("tof", depth_msg(50_000_000)) is None
    assert len(frames(ingest.pop_ready())) == 1
    note = ingest.ledger.counters()["tof"]["notes"]["pose_frame"]
    assert "in frame 'odom', not the fixed frame 'map'" in note and "set fixed_frame to 'odom'" in note
    unnamed = pose_msg(0)
    assert ingest.add_pose("stereo", unnamed) is None
    assert "have no frame_id" in ingest.ledger.counters()["stereo"]["notes"]["pose_frame"]
    in_map = make(fixed_frame="map")
    for t_ns, frame in ((0, "map"), (10 * MS, "/map")):  # '/map' is 'map' (a ROS 1 habit): advising it is no help
        pose = pose_msg(t_ns)
        pose.header.frame_id = frame
        assert in_map.add_pose("tof", pose) is None
    assert "pose_frame" not in in_map.ledger.counters()["tof"]["notes"]
    # an orientation never set says so; a K with skew is said, as the node does not apply it
    unset = pose_msg(20 * MS)
    unset.pose.orientation.w = 0.0
    assert in_map.add_pose("tof", unset) == "bad_pose"
    assert "all zero: the orientation was never set" in in_map.ledger.counters()["tof"]["errors"]["bad_pose"]
    skewed = info_msg()
    skewed.k = [10.0, 0.5, 4.5, 0, 10.0, 3.5, 0, 0, 1]
    assert in_map.add_camera_info("stereo", skewed) is None
    assert "skew 0.5" in in_map.ledger.counters()["stereo"]["notes"]["camera_info_skew"]


def test_a_principal_point_outside_the_image_is_fused_as_given_and_said_once() -> None:
    """A K whose principal point lies far outside its image (another camera's K, or a crop published
    without its roi) shifts every ray: fused as given, since a crop's can lie there, and said once."""
    ingest = make()
    far = CameraInfo(width=10, height=8, k=[10.0, 0, 500.0, 0, 10.0, 3.5, 0, 0, 1])
    assert ingest.add_camera_info("tof", far) is None
    for t_ns in (0, 100_000_000):
        ingest.add_pose("tof", pose_msg(t_ns))
    assert ingest.add_depth("tof", depth_msg(50_000_000)) is None
    assert len(frames(ingest.pop_ready())) == 1
    notes = ingest.ledger.counters()
    assert "(cx 500, cy 3.5) lies outside the 10x8 depth images" in notes["tof"]["notes"]["principal_point"]
    assert ingest.add_depth("stereo", depth_msg(50_000_000)) is None  # its K's principal point is the centre
    assert "principal_point" not in ingest.ledger.counters()["stereo"]["notes"]


def test_depth_images_whose_units_or_byte_order_look_wrong_are_said_once() -> None:
    """Little-endian depths with is_bigendian set decode to absurd depths, and metres written into a
    16UC1 image read as a few millimetres: both were dropped as out_of_range with a message about the
    depth range alone. The sensor's notes now name the flag or the units to fix."""
    ingest = make()
    swapped = depth_msg(0)
    swapped.data = np.linspace(0.5, 4.0, 80, dtype="<f4").tobytes()  # a driver's depths, its flag wrong
    swapped.is_bigendian = 1
    assert ingest.add_depth("tof", swapped) is None
    note = ingest.ledger.counters()["tof"]["notes"]["depth_units"]
    assert "is_bigendian set" in note and "fix the driver's is_bigendian" in note, note
    metres = Image(height=8, width=10, encoding="16UC1", step=20)
    metres.data = np.full((8, 10), 3, "<u2").tobytes()  # 3 m, as a whole number
    _stamp(metres, 0)
    assert ingest.add_depth("stereo", metres) is None
    note = ingest.ledger.counters()["stereo"]["notes"]["depth_units"]
    assert "hold at most 3, read as millimetres" in note and "metres in 32FC1" in note, note
    assert ingest.add_depth("stereo", depth_msg(10 * MS)) is None  # metres in 32FC1: nothing to say
    ingest2 = make()
    assert ingest2.add_depth("tof", depth_msg(0, value=2.5)) is None
    assert "depth_units" not in ingest2.ledger.counters()["tof"]["notes"]
    flat = depth_msg(10 * MS, value=1.5)  # a flat wall with the flag wrong: denormals of 1e-40 m, out of range
    flat.is_bigendian = 1
    ingest2.add_depth("tof", flat)
    assert "is_bigendian set" in ingest2.ledger.counters()["tof"]["notes"].get("depth_units", "")
    # millimetres with the flag wrong: byte-swapped, 0.8-2.8 m read as noise up to 65 m, fused without a word;
    # then said and still fused as noise; now refused, the flag named (a big-endian driver's images are fused)
    ramp_mm = np.linspace(800, 2800, 48 * 64).reshape(48, 64)
    for flag_wrong, order in ((True, "<u2"), (False, ">u2")):
        millimetres = Image(height=48, width=64, encoding="16UC1", step=128, is_bigendian=1)
        millimetres.data = ramp_mm.astype(order).tobytes()
        _stamp(millimetres, 0)
        ingest3 = Ingest(IngestConfig(sensors=("tof", "stereo")))
        ingest3.add_camera_info("tof", info_msg((48, 64)))
        assert ingest3.add_depth("tof", millimetres) == ("bad_encoding" if flag_wrong else None)
        error = ingest3.ledger.counters()["tof"]["errors"].get("bad_encoding", "")
        assert ("reads far smoother as little-endian" in error and "fix the driver's is_bigendian" in error) \
            == flag_wrong, error


def test_a_warning_whose_cause_keeps_coming_is_said_less_and_less_often() -> None:
    """A node behind for hours (or a bag looping) warned every 5 s per cause: over 700 lines an hour
    into each log, without bound. The period doubles while the cause recurs, up to 5 minutes, and
    starts again after a quiet spell."""
    from senfunet_ros.status import ThrottledWarnings

    now = [0.0]
    said: list[tuple[float, str]] = []
    warnings = ThrottledWarnings(lambda text: said.append((now[0], text)), period_s=5.0, clock=lambda: now[0])
    while now[0] < 3600.0:  # a cause that comes every second for an hour
        warnings.warn(("tof", "behind"), "tof: behind")
        now[0] += 1.0
    times = [t for t, _ in said]
    assert times[:5] == [0.0, 5.0, 15.0, 35.0, 75.0] and len(said) < 25, times
    assert max(b - a for a, b in zip(times, times[1:])) == 300.0
    assert said[0][1] == "tof: behind" and "said again in 10 s" in said[1][1]
    now[0] += 1000.0  # quiet for a while: said at once, and every 5 s again
    warnings.warn(("tof", "behind"), "tof: behind")
    assert said[-1] == (now[0], "tof: behind")


def test_the_pixel_spacing_note_reads_only_the_depths_that_are_fused() -> None:
    """A ToF's first frame with most pixels at its 0xFFFF "saturated" value: the note said its median
    depth was 65.54 m and advised voxels of 1.6 m, once and for good. The check now reads the pixels in
    the sensor's depth range, and a frame with too few of them leaves it to the next."""
    ingest = make(voxel_size_m=0.01, depth_range_m={"tof": (0.1, 5.0), "stereo": (0.1, 5.0)})
    first = Image(height=8, width=10, encoding="16UC1", step=20)
    values = np.full((8, 10), 0xFFFF, "<u2")
    values[:3] = 2000  # 2 m
    first.data = values.tobytes()
    _stamp(first, 0)
    assert ingest.add_depth("tof", first) is None
    assert "median depth 2.00 m" in ingest.ledger.counters()["tof"]["notes"]["pixel_spacing"]
    warming_up = Image(height=8, width=10, encoding="16UC1", step=20)
    values = np.full((8, 10), 0xFFFF, "<u2")
    values[0, :4] = 2000  # 4 pixels of 80 in range: too few to tell
    warming_up.data = values.tobytes()
    _stamp(warming_up, 0)
    assert ingest.add_depth("stereo", warming_up) is None
    assert "pixel_spacing" not in ingest.ledger.counters()["stereo"]["notes"]
    assert ingest.add_depth("stereo", depth_msg(10 * MS, value=3.0)) is None
    assert "median depth 3.00 m" in ingest.ledger.counters()["stereo"]["notes"]["pixel_spacing"]


def test_depth_images_missing_from_a_regular_stream_are_counted_and_warned() -> None:
    """A burst faster than the node takes images overflows its subscription's queue (DDS keeps the
    newest 30): the images it lost never reach the node, and nothing counted them. Gaps of several
    of the stream's periods between consecutive depth stamps are now counted as missing_depth and
    warned; a camera's jitter is none, and neither is the jump of a restart (a bag looping)."""
    from senfunet_ros import params as P
    from senfunet_ros.status import counter_warnings

    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02, queue_size=500)
    rng = np.random.default_rng(0)
    stamps = [1000 + 67 * i + int(rng.integers(-8, 9)) for i in range(40)]  # 15 Hz with 8 ms of jitter
    stamps = stamps[:20] + stamps[25:]  # 5 lost
    for t in stamps:
        assert ingest.add_depth("tof", depth_msg(t * MS)) is None
    before = ingest.ledger.counters()
    assert before["tof"]["missing_depth"] == 5, before["tof"]
    gap = f"{stamps[19] / 1000:.3f} s to {stamps[20] / 1000:.3f} s, 6 of the stream's"
    assert before["tof"]["missing_depth_gap"].startswith(gap), before["tof"]["missing_depth_gap"]
    for t in range(100, 1400, 67):  # the bag loops: back to 0.1 s, then on as before
        ingest.add_depth("tof", depth_msg(t * MS))
        ingest.add_depth("stereo", depth_msg(t * MS + 5 * MS))
    now = ingest.ledger.counters()
    assert now["tof"]["time_jumps"] + now["stereo"]["time_jumps"] == 1
    assert now["tof"]["missing_depth"] == 5 and now["stereo"]["missing_depth"] == 0
    settings = P.Settings.from_values({name: default for name, (default, _) in P.expanded_defaults().items()})
    warnings = dict(counter_warnings({}, before, settings))
    assert "tof: 5 depth image(s) missing on /tof/depth" in warnings[("tof", "missing_depth")]
    assert ("stereo", "missing_depth") not in warnings
    # with poses: a gap in the images while the poses went on lost images; the whole sensor pausing (its
    # poses too, for less than time_jump_s: no restart) lost none
    for t in range(1400, 3000, 10):
        if not 2000 < t < 2600:  # the sensor pauses for 0.6 s
            ingest.add_pose("stereo", pose_msg(t * MS))
    for t in range(1405, 3000, 67):
        if not 2000 < t < 2600:
            ingest.add_depth("stereo", depth_msg(t * MS))
    assert ingest.ledger.counters()["stereo"]["missing_depth"] == 0
    for t in range(3000, 4000, 10):
        ingest.add_pose("stereo", pose_msg(t * MS))
    for t in range(3005, 4000, 67):
        if not 3300 < t < 3600:  # the images alone: lost
            ingest.add_depth("stereo", depth_msg(t * MS))
    assert ingest.ledger.counters()["stereo"]["missing_depth"] == 4


def _depth_with_poses(ingest: Ingest, stamps_ms: list[int]) -> dict:
    """tof's depth images at these stamps (in this order), with poses at 100 Hz around them; its counters."""
    poses = iter(range(min(stamps_ms) - 5, max(stamps_ms) + 20, 10))
    pose_ms = next(poses)
    for t in stamps_ms:
        while pose_ms < t + 5:
            ingest.add_pose("tof", pose_msg(pose_ms * MS))
            pose_ms = next(poses)
        ingest.add_depth("tof", depth_msg(t * MS))
    return ingest.ledger.counters()["tof"]


def test_a_depth_stream_whose_rate_goes_down_for_good_is_a_new_period_not_images_missing_forever() -> None:
    """A driver reconfigured from 30 Hz to 10 Hz (every image arriving): each 100 ms interval was a gap of
    3 periods of the old rate, never learnt as the new one, so two images were counted missing on every
    frame and ~/status warned for as long as the stream ran. Sixteen such gaps in a row (stamps cannot tell
    them from images lost steadily: they stay counted) now make the stream's new period, said once; a gap
    at the new rate is counted as such."""
    stamps = [1000 + 33 * i for i in range(30)] + [2000 + 100 * i for i in range(60)]
    stamps.remove(5000)  # one image lost at the new rate
    counters = _depth_with_poses(make(queue_size=500), stamps)
    assert counters["missing_depth"] == 16 * 2 + 1, counters
    assert counters["missing_depth_gap"].startswith("4.900 s to 5.100 s, 2 of the stream's 100 ms periods"), counters
    (note,) = [text for key, text in counters["notes"].items() if key.startswith("depth_period")]
    assert "came every 100 ms for a while (every 33 ms before)" in note, note


@pytest.mark.parametrize("swap_p", [1.0, 0.5])
def test_images_out_of_order_or_lost_for_a_while_are_no_new_rate(swap_p: float) -> None:
    """The rule above, audited: a 30 Hz stream whose frames come with neighbours swapped (nothing lost)
    was taken for a stream at half the rate, and images lost every other frame for a while, then no more,
    were taken back as a rate change. Swapped frames now break the run of gaps, and what was counted
    stays counted."""
    rng = np.random.default_rng(0)
    stamps = [1000 + 33 * i for i in range(200)]
    for i in range(40, 198, 2):
        if rng.random() < swap_p:
            stamps[i], stamps[i + 1] = stamps[i + 1], stamps[i]
    counters = _depth_with_poses(make(queue_size=500), stamps)
    assert counters["missing_depth"] == 0 and not [k for k in counters["notes"] if k.startswith("depth_period")], \
        counters
    lossy = [1000 + 33 * i for i in range(200) if not (40 <= i < 60 and i % 2)]  # 10 lost, then none
    counters = _depth_with_poses(make(queue_size=500), lossy)
    assert counters["missing_depth"] == 10, counters


def test_a_camera_info_that_changes_is_said_and_one_that_alternates_is_two_publishers() -> None:
    """Two camera_infos alternating on one topic (the depth and colour cameras' remapped onto one): each
    frame took whichever came last, fused with the wrong K every other time, and nothing said so. A
    resolution changed once and back is no such thing."""
    ingest = make()
    other = info_msg()
    other.k = [14.0, 0, 4.0, 0, 14.0, 3.0, 0, 0, 1]
    assert ingest.add_camera_info("tof", info_msg()) is None  # the same again: nothing to say
    assert ingest.add_camera_info("tof", other) is None
    notes = ingest.ledger.counters()["tof"]["notes"]
    assert "fx 10, fy 10, cx 4.5, cy 3.5 (10x8) to fx 14, fy 14, cx 4, cy 3 (10x8)" in notes["camera_info_changed"]
    assert "camera_info_alternates" not in notes
    assert ingest.add_camera_info("tof", info_msg()) is None  # back once: a driver set back, say
    assert "camera_info_alternates" not in ingest.ledger.counters()["tof"]["notes"]
    assert ingest.add_camera_info("tof", other) is None  # and again: two publishers
    note = ingest.ledger.counters()["tof"]["notes"]["camera_info_alternates"]
    assert "two publishers on one topic" in note and "fx 14" in note and "fx 10" in note, note
    assert ingest.ledger.counters()["stereo"]["notes"] == {}


def test_depth_before_camera_info_waits_for_it_within_limits() -> None:
    """Drivers publish camera_info and depth on separate topics, so the first depth image may come
    first: it waits for the camera_info, within the queue size and pose_max_wait_s of stream time."""
    ingest = Ingest(IngestConfig(sensors=("tof", "stereo"), queue_size=2, pose_max_wait_s=0.5))
    ingest.add_pose("tof", pose_msg(0))
    assert ingest.add_depth("tof", depth_msg(25 * MS, value=2.0)) is None
    assert ingest.pop_ready() == [] and ingest.ledger.queue_depths()["tof"] == 1
    assert ingest.add_camera_info("tof", info_msg()) is None
    ingest.add_pose("tof", pose_msg(100 * MS))
    (frame,) = frames(ingest.pop_ready())
    assert frame.stamp_ns == 25 * MS and np.all(frame.depth_m == 2.0)
    np.testing.assert_array_equal(frame.K, conv.intrinsics_from_camera_info(info_msg())[0])

    for t in (0, 100, 200):  # stereo's camera_info never comes; the third image overflows the wait
        assert ingest.add_depth("stereo", depth_msg(t * MS)) is None
    assert ingest.ledger.counters()["stereo"]["dropped"]["no_camera_info"] == 1
    ingest.add_pose("stereo", pose_msg(650 * MS))  # 550 ms past 100 ms: beyond pose_max_wait_s
    assert ingest.pop_ready() == []
    assert ingest.ledger.counters()["stereo"]["dropped"]["no_camera_info"] == 2
    assert ingest.ledger.queue_depths()["stereo"] == 1
    ingest.add_pose("stereo", pose_msg(750 * MS))
    ingest.pop_ready()
    counters = ingest.ledger.counters()["stereo"]
    assert counters["dropped"]["no_camera_info"] == 3 and counters["queue_depth"] == 0
    assert counters["received"] == 3 and counters["integrated"] == 0


def test_out_of_order_duplicate_and_queue_full() -> None:
    ingest = make(queue_size=2)
    assert ingest.add_depth("tof", depth_msg(100 * MS)) is None
    assert ingest.add_depth("tof", depth_msg(100 * MS)) == "duplicate"
    ingest.add_depth("tof", depth_msg(150 * MS))
    assert ingest.add_depth("tof", depth_msg(50 * MS)) == "out_of_order"  # older than the two newest
    assert ingest.add_depth("tof", depth_msg(100 * MS)) == "duplicate"  # not the newest, still seen
    ingest.add_depth("tof", depth_msg(200 * MS))  # third in a queue of two: the oldest goes
    dropped = ingest.ledger.counters()["tof"]["dropped"]
    assert (dropped["duplicate"], dropped["out_of_order"], dropped["queue_full"]) == (2, 1, 1)
    ingest.add_pose("tof", pose_msg(140 * MS))
    ingest.add_pose("tof", pose_msg(210 * MS))
    assert [f.stamp_ns for f in frames(ingest.pop_ready())] == [150 * MS, 200 * MS]


def test_a_depth_stamp_ahead_by_a_glitch_costs_no_frame() -> None:
    """A depth image a glitching driver stamped 0.4 s ahead (within time_jump_s, so taken) moved its
    stream's time there: every frame after it was out_of_order until the stream caught up with it.
    Now a frame between the two newest takes the stream's time back; frames still leave in stamp
    order, and one older than both is still out of order."""
    ingest = make(pose_tolerance_s=0.05)
    for t in range(0, 800, 10):
        ingest.add_pose("tof", pose_msg(t * MS, x=t / 1000))
    stamps = [500, 550, 1000, 600, 650, 700, 750]  # 1000: the glitch (poses end at 790 ms)
    assert [ingest.add_depth("tof", depth_msg(t * MS)) for t in stamps] == [None] * len(stamps)
    assert ingest.add_depth("tof", depth_msg(620 * MS)) == "out_of_order"  # before 700 and 750
    assert ingest.add_depth("tof", depth_msg(1000 * MS)) == "duplicate"
    assert [f.stamp_ns // MS for f in frames(ingest.pop_ready())] == [500, 550, 600, 650, 700, 750]
    counters = ingest.ledger.counters()["tof"]
    assert counters["queue_depth"] == 1  # the glitch waits for poses that reach its stamp
    assert sum(counters["dropped"].values()) == 2


def test_time_jump_flushes_and_is_reported_first() -> None:
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    ingest.add_depth("stereo", depth_msg(5050 * MS))
    # the bag restarted: every stream continues on the new timeline; its first messages are held
    # until that is confirmed (three per stream, spanning 20 ms), then taken
    for t in (10, 20, 30, 40, 50):
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
        ingest.add_depth("stereo", depth_msg(t * MS + 6 * MS))
    ingest.add_pose("tof", pose_msg(60 * MS))
    items = ingest.pop_ready()
    assert isinstance(items[0], TimeJump) and items[0].from_ns == 5100 * MS and items[0].to_ns == 10 * MS
    assert [f.stamp_ns for f in frames(items) if f.sensor == "tof"] == [15 * MS, 25 * MS, 35 * MS, 45 * MS, 55 * MS]
    c = ingest.ledger.counters()
    assert c["tof"]["time_jumps"] + c["stereo"]["time_jumps"] == 1  # counted on the stream that confirmed it
    assert c["tof"]["dropped"]["bad_stamp"] == 0 and c["stereo"]["dropped"]["bad_stamp"] == 0
    assert c["tof"]["dropped"]["time_jump"] == 1 and c["stereo"]["dropped"]["time_jump"] == 1  # flushed
    assert ingest.pop_ready() == []  # reported once


def _restarted_from_205_to_100_s(ingest: Ingest) -> None:
    """tof's depth and poses at 205 s, then on a new timeline from 100 s until a restart is confirmed."""
    ingest.add_pose("tof", pose_msg(205_000 * MS))
    ingest.add_depth("tof", depth_msg(205_000 * MS))
    for t in range(100_000, 100_040, 10):
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
    assert sum(isinstance(i, TimeJump) for i in ingest.pop_ready()) == 1


def test_after_a_restart_old_messages_in_flight_are_its_loss_and_an_unset_stamp_is_a_bad_stamp() -> None:
    """After a restart, a message of the old time that a busy reader hands over late is the restart's
    loss (time_jump); a stamp off both timelines (unset: 0) is a bad_stamp. Once the new timeline has
    gone on for time_jump_s, a message of the old time is a bad_stamp too (a glitch, or a new restart)."""
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    _restarted_from_205_to_100_s(ingest)
    assert ingest.add_depth("tof", depth_msg(205_010 * MS)) == "time_jump"
    assert ingest.add_pose("tof", pose_msg(204_500 * MS)) == "time_jump"
    assert ingest.add_depth("tof", depth_msg(0)) == "bad_stamp"
    dropped = ingest.ledger.counters()["tof"]["dropped"]
    assert dropped["time_jump"] == 3 and dropped["bad_stamp"] == 1  # the flushed frame, the two in flight; the 0
    for t in (100_600, 101_100):  # the new timeline goes on for 1.1 s
        assert ingest.add_pose("tof", pose_msg(t * MS)) is None
    assert ingest.add_depth("tof", depth_msg(205_020 * MS)) == "bad_stamp"


def test_a_restart_warns_none_of_what_it_cost_but_an_unset_stamp_right_after_it() -> None:
    """The restart's own line tells of what it cost (counted on ~/status as time_jump); a depth image
    with an unset stamp right after it is a bad stamp of its own and warned, once no restart is
    pending (it was counted and never logged)."""
    from senfunet_ros import params as P
    from senfunet_ros.status import CounterWarnings

    settings = P.Settings.from_values({name: default for name, (default, _) in P.expanded_defaults().items()})
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    warnings = CounterWarnings(ingest, hold_s=60.0)

    def stamp_warnings() -> list[tuple[tuple[str, ...], str]]:
        return [(key, text) for key, text in warnings.since_last(settings) if key[1] in ("time_jump", "bad_stamp")]

    _restarted_from_205_to_100_s(ingest)
    ingest.add_depth("tof", depth_msg(205_010 * MS))  # of the old time, in flight
    assert stamp_warnings() == []
    assert ingest.add_depth("tof", depth_msg(0)) == "bad_stamp"
    assert stamp_warnings() == []  # it may start a new timeline: held while that is open
    assert ingest.add_depth("tof", depth_msg(100_050 * MS)) is None  # the stream goes on: it was a stray
    (warning,) = stamp_warnings()
    assert warning[0] == ("tof", "bad_stamp") and "dropped 1 message(s): bad_stamp" in warning[1], warning


def test_every_resume_ahead_after_a_pause_is_taken_without_a_bad_stamp_warning() -> None:
    """The sensors paused and resumed ahead (a driver restarted), twice. Each resume's first messages are
    held as candidates, then taken back once the restart is confirmed: no warning. The second resume
    warned "bad_stamp ... check the driver's clock": the first resume's hold was remembered, so the
    second's counted as held for the whole time since."""
    from senfunet_ros import params as P
    from senfunet_ros.status import CounterWarnings

    settings = P.Settings.from_values({name: default for name, (default, _) in P.expanded_defaults().items()})
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    warnings = CounterWarnings(ingest, hold_s=0.05)
    said: list[tuple[str, ...]] = []
    for start in (1000, 9000, 17000):  # ms: a stream, then two resumes 8 s later
        ingest.add_pose("tof", pose_msg(start * MS))
        said += [key for key, _ in warnings.since_last(settings)]  # the first held while a restart is pending
        time.sleep(0.1)  # past hold_s: only a hold of this resume may count
        for t in range(start + 10, start + 60, 10):
            ingest.add_pose("tof", pose_msg(t * MS))
            ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
        said += [key for key, _ in warnings.since_last(settings)]
        ingest.pop_ready()
    assert ingest.ledger.counters()["tof"]["dropped"]["bad_stamp"] == 0
    assert ("tof", "bad_stamp") not in said, said


def test_a_stray_first_stamp_is_said_to_be_one_not_a_restart_of_a_bag() -> None:
    """A driver's very first pose stamped 1000 s ahead set the timeline, and the stream that followed
    was confirmed as time going back: the log said "time restarted, pass 2 (a bag looping or
    restarting?)". The restart still moves the streams, but it is said to be stray first stamps, and
    no pass is counted; a bag that loops is still a restart."""
    from senfunet_core.engine import EngineConfig, SenFuNet
    from senfunet_ros.pipeline import Pipeline

    logged: list[str] = []
    pipeline = Pipeline(SenFuNet(EngineConfig(), weights=None),
                        make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02),
                        log=lambda level, text: logged.append(text))
    ingest = pipeline.ingest
    ingest.add_pose("tof", pose_msg(1_001_000_000 * MS))  # the stray
    for t in range(1000, 3000, 10):
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
    pipeline.drain(ingest.pop_ready())
    assert pipeline.time_jumps == 0
    (line,) = [text for text in logged if "stray" in text or "restarted" in text]
    assert "first stamps (up to 1001000.000 s)" in line and "taken as stray stamps" in line, line
    for t in range(500, 700, 10):  # then the recording starts over from 0.5 s: a restart
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
    pipeline.drain(ingest.pop_ready())
    assert pipeline.time_jumps == 1 and "time restarted, pass 2" in logged[-1], logged


def test_a_depth_image_sent_twice_while_a_restart_is_confirmed_is_fused_once() -> None:
    """The sensors paused and resumed ahead (a driver restarted) with a relay that sends every depth
    image twice: the copy of the image that confirmed the restart is a duplicate, not fused twice."""
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    ingest.add_pose("tof", pose_msg(1000 * MS))
    ingest.add_depth("tof", depth_msg(1000 * MS))
    ingest.add_depth("stereo", depth_msg(1000 * MS))
    assert [f.stamp_ns // MS for f in frames(ingest.pop_ready())] == [1000]
    verdicts = []
    for t in range(9000, 9050, 10):  # 8 s later
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_pose("stereo", pose_msg(t * MS))
        ingest.add_depth("stereo", depth_msg(t * MS + 4 * MS))
        verdicts += [ingest.add_depth("tof", depth_msg(t * MS + 5 * MS)) for _ in range(2)]
    ingest.add_pose("tof", pose_msg(9050 * MS))
    ingest.add_pose("stereo", pose_msg(9050 * MS))
    assert [f.stamp_ns // MS for f in frames(ingest.pop_ready()) if f.sensor == "tof"] == list(range(9005, 9050, 10))
    # held as candidates of the new timeline (their copies too, unheld), then each copy a duplicate
    assert verdicts == ["bad_stamp"] * 4 + [None, "duplicate"] * 3


def test_a_restart_ahead_loses_no_pose_that_came_out_of_order() -> None:
    """The sensors paused and resumed ahead, and two poses of the new timeline came swapped (two
    threads take a subscription's messages: its callback and the depth images' before them): the
    older one belongs to the new timeline too. It started the candidates over, which lost the poses
    held so far, and the frames between them as pose_gap."""
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02, pose_tolerance_s=0.05)
    ingest.add_pose("tof", pose_msg(1000 * MS))
    ingest.add_depth("tof", depth_msg(1000 * MS))
    ingest.add_depth("stereo", depth_msg(1000 * MS))
    assert len(frames(ingest.pop_ready())) == 1
    poses = list(range(9000, 9100, 10))
    poses[2], poses[3] = poses[3], poses[2]
    for i, t in enumerate(poses):  # 8 s later
        ingest.add_pose("tof", pose_msg(t * MS, x=t / 1000))
        if i % 2:
            ingest.add_depth("tof", depth_msg((9000 + 10 * i - 5) * MS))
            ingest.add_depth("stereo", depth_msg((9000 + 10 * i - 4) * MS))
    taken = [f for f in frames(ingest.pop_ready()) if f.sensor == "tof"]
    assert [f.stamp_ns // MS for f in taken] == list(range(9005, 9090, 20))
    for frame in taken:  # posed between the poses around its stamp
        assert frame.T_world_camera[0, 3] == pytest.approx(frame.stamp_ns / 1e9)
    counters = ingest.ledger.counters()["tof"]
    assert sum(counters["dropped"].values()) == 0, counters["dropped"]


@pytest.mark.parametrize("poses_ahead_s", [1.5, 2.5])
def test_a_burst_after_a_pause_that_brings_the_poses_first_costs_no_frame(poses_ahead_s: float) -> None:
    """Every stream paused 3 s, then resumed in a burst (a driver catching up, a bag played fast): the
    node takes all queued poses at once (TakingQueued), so the poses confirmed the restart ahead and
    ran seconds ahead of the images. The depth streams, not yet heard on the new timeline, had
    lost their timelines: their first images, more than time_jump_s behind the newest pose, were
    bad_stamp; beyond that, they became a restart back (a TimeJump) that flushed every pose, and
    the burst's frames timed out (pose_timeout)."""
    ingest = make()  # the node's defaults: time_jump_s 1, restart after 5 messages spanning 0.5 s
    t0_ms = 1_700_000_000_000  # a driver's wall-clock stamps

    def messages(start_ms: int, duration_ms: int) -> list[tuple[int, str, str]]:
        out = []
        for sensor, period_ms, phase_ms in (("tof", 67, 3), ("stereo", 50, 7)):
            out += [(t, sensor, "depth") for t in range(start_ms + phase_ms, start_ms + duration_ms, period_ms)]
            out += [(t, sensor, "pose") for t in range(start_ms, start_ms + duration_ms + 20, 10)]
        return sorted(out)

    def add(t_ms: int, sensor: str, stream: str) -> list[Frame | TimeJump]:
        if stream == "depth":
            ingest.add_depth(sensor, depth_msg(t_ms * MS))
        else:
            ingest.add_pose(sensor, pose_msg(t_ms * MS, x=(t_ms - t0_ms) / 1000))
        return ingest.pop_ready()

    for message in messages(t0_ms, 1000):
        add(*message)
    before = ingest.ledger.counters()
    burst = messages(t0_ms + 4000, 2500)  # after a pause of 3 s
    ahead_ms = poses_ahead_s * 1000
    items = [item for message in sorted(burst, key=lambda m: m[0] - (ahead_ms if m[2] == "pose" else 0))
             for item in add(*message)]
    assert not any(isinstance(i, TimeJump) for i in items)
    for sensor, counters in ingest.ledger.counters().items():
        taken = [f for f in frames(items) if f.sensor == sensor]
        assert len(taken) == sum(1 for _, s, stream in burst if (s, stream) == (sensor, "depth"))
        for frame in taken:  # posed between the poses around its stamp
            assert frame.T_world_camera[0, 3] == pytest.approx((frame.stamp_ns / MS - t0_ms) / 1000)
        assert counters["dropped"] == before[sensor]["dropped"], counters["dropped"]


def test_a_restart_loses_nothing_when_old_messages_of_one_stream_arrive_late() -> None:
    """A busy reader hands stereo's last depth images of the old time over after the new timeline's
    first messages: they are on the old timeline, and the restart waits for stereo to move too
    instead of starting over (which would leave the new timeline's first messages as bad_stamp)."""
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    ingest.add_depth("stereo", depth_msg(5050 * MS))
    for i, t in enumerate(range(10, 90, 10)):
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
        if i < 3:  # stereo: three of the old time still in flight (on its timeline), then the new time
            assert ingest.add_depth("stereo", depth_msg(5080 * MS + i * 30 * MS)) is None
        else:
            ingest.add_depth("stereo", depth_msg(t * MS + 6 * MS))
    ingest.add_pose("tof", pose_msg(90 * MS))
    items = ingest.pop_ready()
    assert sum(isinstance(i, TimeJump) for i in items) == 1
    assert [f.stamp_ns // MS for f in frames(items) if f.sensor == "tof"] == list(range(15, 90, 10))
    c = ingest.ledger.counters()
    assert c["tof"]["dropped"]["bad_stamp"] == 0 and c["stereo"]["dropped"]["bad_stamp"] == 0


def test_a_restart_goes_on_without_a_stream_that_stopped_on_the_old_timeline() -> None:
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    ingest.add_depth("stereo", depth_msg(5050 * MS))
    ingest.add_pose("tof", pose_msg(10 * MS))
    ingest.add_depth("stereo", depth_msg(5080 * MS))  # stereo's last message, of the old time
    jumps = []
    for t in range(20, 1400, 50):  # then only tof, on the new timeline
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
        jumps += [t for i in ingest.pop_ready() if isinstance(i, TimeJump)]
    # confirmed once the new timeline went on for longer than time_jump_s after stereo last spoke
    assert len(jumps) == 1 and 1000 < jumps[0] <= 1100


def test_a_stream_that_stays_on_the_old_timeline_is_not_left_behind_by_a_restart() -> None:
    """tof's driver moves to another clock while stereo's goes on: not a restart, however long tof
    keeps to its new clock."""
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    for t in range(0, 3000, 50):
        assert ingest.add_depth("tof", depth_msg(t * MS + 5 * MS)) == "bad_stamp"
        assert ingest.add_depth("stereo", depth_msg(5100 * MS + t * MS)) is None
    assert not any(isinstance(i, TimeJump) for i in ingest.pop_ready())
    assert ingest.ledger.counters()["tof"]["time_jumps"] == 0


def test_a_restart_holds_as_many_messages_as_a_queue_and_counts_the_rest_as_lost() -> None:
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=4, restart_confirm_s=0.02, queue_size=2)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    for t in (10, 20, 30, 40):  # four depth images confirm the restart: the first two are not held
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
    ingest.add_pose("tof", pose_msg(50 * MS))
    items = ingest.pop_ready()
    assert isinstance(items[0], TimeJump) and [f.stamp_ns for f in frames(items)] == [35 * MS, 45 * MS]
    c = ingest.ledger.counters()["tof"]
    assert c["dropped"]["bad_stamp"] == 0 and c["dropped"]["time_jump"] == 1 + 2  # the frame flushed, two lost


def test_a_held_message_that_turns_out_bad_is_counted_once() -> None:
    """The new timeline's held messages are taken as any other: one that cannot be decoded is one
    bad_encoding drop, counted where it is taken."""
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    for t in (10, 20, 30):
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS, encoding="rgb8" if t == 10 else "32FC1"))
        ingest.add_color("tof", color_msg(t * MS + 5 * MS) if t != 20 else depth_msg(t * MS + 5 * MS))
    c = ingest.ledger.counters()["tof"]
    assert c["time_jumps"] == 1 and c["dropped"]["bad_stamp"] == 0
    assert c["dropped"]["bad_encoding"] == 2  # the rgb8 depth image and the 32FC1 "colour" image, once each


@pytest.mark.parametrize("stray_s", [0.0, 2**31 - 1, 3.0, 9.0])
def test_a_stray_stamp_is_dropped_and_does_not_move_the_timeline(stray_s: float) -> None:
    ingest = make(time_jump_s=1.0)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    stray = int(stray_s * 1e9)
    assert ingest.add_depth("tof", depth_msg(stray)) == "bad_stamp"
    assert ingest.add_pose("tof", pose_msg(stray)) == "bad_stamp"
    assert ingest.add_color("tof", color_msg(stray)) == "bad_stamp"
    ingest.add_pose("tof", pose_msg(5120 * MS))
    ingest.add_depth("tof", depth_msg(5150 * MS))  # still on the timeline: not out of order, not a jump
    ingest.add_pose("tof", pose_msg(5200 * MS))
    items = ingest.pop_ready()
    assert not any(isinstance(i, TimeJump) for i in items)
    assert [f.stamp_ns for f in frames(items)] == [5100 * MS, 5150 * MS]
    c = ingest.ledger.counters()["tof"]
    assert c["dropped"]["bad_stamp"] == 3 and c["time_jumps"] == 0 and c["dropped"]["time_jump"] == 0
    assert "stamp" in c["errors"]["bad_stamp"]


def test_a_sensor_whose_clock_differs_from_the_others_is_told_so() -> None:
    """stereo's driver stamps on a clock 3 s behind tof's: its messages are bad stamps, and the error
    named "the stream's timeline" and a restart that could never be confirmed (tof goes on). It now
    says that stereo's clock differs from the other sensors'. A stray stamp of a sensor that keeps to
    the others' time is still one off its stream's timeline."""
    ingest = make(time_jump_s=1.0)
    for t in range(5000, 8000, 50):
        ingest.add_pose("tof", pose_msg(t * MS))
        ingest.add_depth("tof", depth_msg(t * MS + 5 * MS))
        assert ingest.add_pose("stereo", pose_msg((t - 3000) * MS)) == "bad_stamp"
        assert ingest.add_depth("stereo", depth_msg((t - 2995) * MS)) == "bad_stamp"
    assert not any(isinstance(i, TimeJump) for i in ingest.pop_ready())
    error = ingest.ledger.counters()["stereo"]["errors"]["bad_stamp"]
    assert "3.000 s behind the other sensors' time" in error and "stereo's clock differs" in error, error
    assert ingest.add_depth("tof", depth_msg(1000 * MS)) == "bad_stamp"
    error = ingest.ledger.counters()["tof"]["errors"]["bad_stamp"]
    assert "behind the stream's timeline" in error and "clock differs" not in error, error


def test_new_settings_reach_the_timelines() -> None:
    """A new config (the node's parameters changed at run time) changes how far is off the timeline."""
    ingest = make(time_jump_s=1.0)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    assert ingest.add_depth("tof", depth_msg(8000 * MS)) == "bad_stamp"  # 3 s on: off the timeline
    ingest.config = dataclasses.replace(ingest.config, time_jump_s=10.0)
    assert ingest.add_depth("tof", depth_msg(8000 * MS)) is None  # a pause of 3 s now
    with pytest.raises(ValueError, match="sensors"):
        ingest.config = dataclasses.replace(ingest.config, sensors=("tof",))


def test_a_burst_of_consistent_stray_stamps_on_one_stream_is_not_a_restart() -> None:
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.05)
    for i in range(20):  # tof's pose driver sends a burst on another clock while the others go on
        t = 5000 * MS + i * 10 * MS
        ingest.add_pose("tof", pose_msg(t))
        assert ingest.add_pose("tof", pose_msg(100 * MS + i * 10 * MS)) == "bad_stamp"
        ingest.add_depth("tof", depth_msg(t + 5 * MS))
    items = ingest.pop_ready()
    assert not any(isinstance(i, TimeJump) for i in items) and len(frames(items)) == 19
    assert ingest.ledger.counters()["tof"]["dropped"]["bad_stamp"] == 20


def test_restart_from_outside_the_streams() -> None:
    ingest = make(time_jump_s=1.0)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    ingest.restart(to_ns=0)  # the /clock went back
    assert ingest.add_depth("tof", depth_msg(10 * MS)) is None  # a new timeline starts at once
    ingest.add_pose("tof", pose_msg(5 * MS))
    ingest.add_pose("tof", pose_msg(15 * MS))
    items = ingest.pop_ready()
    assert isinstance(items[0], TimeJump) and [f.stamp_ns for f in frames(items)] == [10 * MS]
    assert ingest.ledger.counters()["tof"]["dropped"]["time_jump"] == 1


def test_messages_of_the_new_time_that_come_before_the_clock_says_it_restarted_are_taken() -> None:
    """A bag looping under use_sim_time: its first poses (100 Hz) reach the node before the /clock
    that says time went back (another callback). They were candidates of a new timeline, dropped as
    bad_stamp (4 per pass, warned every pass) and forgotten when the /clock's restart came. They are
    the new time's start: taken with the restart, and the frames between them posed."""
    ingest = make(time_jump_s=1.0)
    for k in range(5):
        ingest.add_pose("tof", pose_msg(4000 * MS + k * 10 * MS, x=0.01 * k))
    ingest.add_depth("tof", depth_msg(4035 * MS))
    assert len(frames(ingest.pop_ready())) == 1
    for k in range(4):  # the next pass's first poses, before the /clock
        assert ingest.add_pose("tof", pose_msg(k * 10 * MS, x=1.0 + 0.01 * k)) == "bad_stamp"
    ingest.restart(to_ns=0)
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_stamp"] == 0 and "bad_stamp" not in counters["errors"], counters
    assert ingest.add_depth("tof", depth_msg(15 * MS)) is None
    (frame,) = frames(ingest.pop_ready())
    assert frame.stamp_ns == 15 * MS and frame.T_world_camera[0, 3] == pytest.approx(1.015)


def test_a_camera_info_with_distortion_is_noted() -> None:
    """The node takes images as rectified: a camera_info with distortion coefficients is noted (and
    warned about by the node), one without clears it."""
    ingest = make()
    assert ingest.ledger.counters()["tof"]["distorted"] is False
    distorted = info_msg()
    distorted.distortion_model, distorted.d = "plumb_bob", [0.1, -0.05, 0.0, 0.0, 0.0]
    assert ingest.add_camera_info("tof", distorted) is None
    counters = ingest.ledger.counters()
    assert counters["tof"]["distorted"] is True and counters["stereo"]["distorted"] is False
    rectified = info_msg()
    rectified.d = [0.0] * 5
    ingest.add_camera_info("tof", rectified)
    assert ingest.ledger.counters()["tof"]["distorted"] is False


def test_a_rectified_images_camera_info_gives_the_projection_matrix_intrinsics() -> None:
    """image_proc's rectified images carry their raw camera's K and D, and P for themselves: P's
    intrinsics are the images' (the raw K projected a recorded stereo stream's rectified depth, and its
    mesh lost 10 points of F, with advice to record the rectified topic it was). Without distortion
    coefficients, or with a P that is K or unset, K holds."""
    ingest = make()
    info = info_msg()
    info.distortion_model, info.d = "plumb_bob", [0.1, -0.05, 0.0, 0.0, 0.0]
    info.p = [12.0, 0.0, 4.0, 0.0, 0.0, 12.5, 3.5, 0.0, 0.0, 0.0, 1.0, 0.0]
    K, _ = conv.intrinsics_from_camera_info(info)
    np.testing.assert_array_equal(K, [[12.0, 0, 4.0], [0, 12.5, 3.5], [0, 0, 1]])
    assert ingest.add_camera_info("tof", info) is None
    counters = ingest.ledger.counters()["tof"]
    assert counters["distorted"] is False and "P's intrinsics" in counters["notes"]["rectified_p"]
    # an identity P (no image has it: a 179 degree view): K holds, not refused
    placeholder = CameraInfo(width=640, height=480, k=[500.0, 0, 320, 0, 500, 240, 0, 0, 1], d=info.d,
                             p=[1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    np.testing.assert_array_equal(conv.intrinsics_from_camera_info(placeholder)[0], np.reshape(placeholder.k, (3, 3)))
    for d, p in (([0.0] * 5, info.p), (info.d, [0.0] * 12),
                 (info.d, [*info_msg().k[:3], 0.0, *info_msg().k[3:6], 0.0, *info_msg().k[6:], 0.0])):
        other = info_msg()
        other.d, other.p = d, p
        np.testing.assert_array_equal(conv.intrinsics_from_camera_info(other)[0], np.reshape(info_msg().k, (3, 3)))


def test_a_depth_topic_named_raw_keeps_k_with_a_rectified_projection_matrix() -> None:
    """A driver's unrectified depth (`depth/image_raw`) with a full camera_info (K, D, and P for the
    rectified images image_proc would make): K is the raw image's, and the distortion is said; the
    names ROS gives rectified images keep P."""
    info = info_msg()
    info.distortion_model, info.d = "plumb_bob", [0.1, -0.05, 0.0, 0.0, 0.0]
    info.p = [12.0, 0.0, 4.0, 0.0, 0.0, 12.5, 3.5, 0.0, 0.0, 0.0, 1.0, 0.0]
    ingest = make(raw_depth=frozenset({"tof"}))
    assert ingest.add_camera_info("tof", info) is None
    counters = ingest.ledger.counters()["tof"]
    assert counters["distorted"] is True and "rectified_p" not in counters["notes"]
    np.testing.assert_array_equal(conv.intrinsics_from_camera_info(info, raw=True)[0], np.reshape(info.k, (3, 3)))
    raw = ("/cam/depth/image_raw", "/k4a/depth/image_raw/compressedDepth", "image_raw", "/cam/ir/image_raw/zstd")
    rectified = ("/cam/depth/image_rect_raw", "/cam/depth/image_rect", "/tof/depth", "/stereo/depth_registered/image",
                 "/cam/aligned_depth_to_color/image_rect_raw/compressedDepth", "/raw_camera/depth")
    assert [conv.names_raw_image(topic) for topic in raw + rectified] == [True] * len(raw) + [False] * len(rectified)
    from senfunet_ros import params as P

    defaults = {name: default for name, (default, _) in P.expanded_defaults().items()}
    settings = P.Settings.from_values({**defaults, "tof.depth_topic": raw[0]})
    assert P.ingest_config(settings).raw_depth == {"tof"}


def test_colour_matched_by_nearest_stamp_and_resized() -> None:
    ingest = make(color_tolerance_s=0.02, working_size=(5, 0))
    ingest.add_pose("stereo", pose_msg(0))
    ingest.add_pose("stereo", pose_msg(200 * MS))
    ingest.add_color("stereo", color_msg(90 * MS, value=1))
    ingest.add_depth("stereo", depth_msg(100 * MS))
    assert ingest.pop_ready() == []  # the colour stream has not reached the depth stamp: wait
    ingest.add_color("stereo", color_msg(103 * MS, value=2))
    (frame,) = frames(ingest.pop_ready())
    assert frame.rgb is not None and np.all(frame.rgb == 2)  # 3 ms beats 10 ms
    assert frame.depth_m.shape == (4, 5) and frame.rgb.shape == (4, 5, 3)  # aspect ratio kept
    assert frame.K[0, 0] == pytest.approx(5.0)
    assert ingest.ledger.counters()["stereo"]["without_color"] == 0
    ingest.add_pose("stereo", pose_msg(140 * MS))
    ingest.add_depth("stereo", depth_msg(150 * MS))
    ingest.add_color("stereo", color_msg(190 * MS, value=3))  # 40 ms off: beyond color_tolerance_s
    (frame,) = frames(ingest.pop_ready())
    assert frame.rgb is None and ingest.ledger.counters()["stereo"]["without_color"] == 1  # counted, not silent



def test_a_narrow_image_is_not_blown_up_to_the_working_width() -> None:
    """A 2 x 1000 depth image at working_width 256 became a 256 x 128000 frame (131 MB, seconds to fuse,
    GBs with a queue of them), with nothing said; images of usual shapes keep the working width."""
    ingest = make(working_size=(16, 0))
    ingest.add_camera_info("tof", info_msg((200, 2)))
    ingest.add_pose("tof", pose_msg(0))
    ingest.add_pose("tof", pose_msg(200 * MS))
    ingest.add_depth("tof", depth_msg(100 * MS, shape=(200, 2)))
    (frame,) = frames(ingest.pop_ready())
    height, width = frame.depth_m.shape
    assert height * width <= 4 * 16 * 16 and height / width == pytest.approx(100, rel=0.1)
    assert frame.K[0, 2] == pytest.approx(0.5 * (width - 1), abs=0.6)  # K scaled to the size fused
    notes = ingest.ledger.counters()["tof"]["notes"]
    assert "2x200" in notes["image_size"] and f"{width}x{height}" in notes["image_size"], notes
    ingest.add_camera_info("stereo", info_msg((24, 32)))
    ingest.add_pose("stereo", pose_msg(0))
    ingest.add_pose("stereo", pose_msg(200 * MS))
    ingest.add_depth("stereo", depth_msg(100 * MS, shape=(24, 32)))
    (frame,) = frames(ingest.pop_ready())
    assert frame.depth_m.shape == (12, 16) and "image_size" not in ingest.ledger.counters()["stereo"]["notes"]


@pytest.mark.parametrize("rate_hz", [15, 40])
def test_frames_go_on_without_colour_once_the_colour_stream_stops(rate_hz: int) -> None:
    """Colour seen once, every frame waited pose_max_wait_s for colour that stopped: at 40 Hz the queue
    (queue_size 30) overflowed first, dropping each frame about to go; no frame of the sensor fused."""
    ingest = make(queue_size=30, pose_max_wait_s=1.0)
    period_ns = 1_000_000_000 // rate_hz
    out: list[Frame] = []
    for i in range(4 * rate_hz):  # 4 s; colour for the first half second only
        t = i * period_ns
        ingest.add_pose("stereo", pose_msg(t))
        if i < rate_hz // 2:
            ingest.add_color("stereo", color_msg(t, value=7))
        ingest.add_depth("stereo", depth_msg(t))
        out += frames(ingest.pop_ready())
    counters = ingest.ledger.counters()["stereo"]
    assert sum(counters["dropped"].values()) == 0, counters["dropped"]
    assert [f.rgb is not None for f in out] == [i < rate_hz // 2 for i in range(len(out))]
    # once the depth stream ran pose_max_wait_s past the last colour, frames no longer wait: only the
    # newest few (their pose and colour not yet passed) are still queued
    assert len(out) >= 4 * rate_hz - 2 and counters["without_color"] == len(out) - rate_hz // 2

def test_frames_in_stamp_order_and_deterministic() -> None:
    def run() -> list[tuple[str, int, float]]:
        ingest = make()
        out = []
        rng = np.random.default_rng(7)
        for s in ("tof", "stereo"):
            ingest.add_pose(s, pose_msg(0))
        for i in range(40):
            for s, offset in (("tof", 3), ("stereo", 7)):
                t = (i * 33 + offset) * MS
                ingest.add_depth(s, depth_msg(t, value=1.0 + rng.random()))
                ingest.add_pose(s, pose_msg(t + 10 * MS, x=i * 0.01))
            if i % 5 == 0:
                out += [(f.sensor, f.stamp_ns, float(f.T_world_camera[0, 3])) for f in frames(ingest.pop_ready())]
        out += [(f.sensor, f.stamp_ns, float(f.T_world_camera[0, 3])) for f in frames(ingest.pop_ready())]
        return out

    first = run()
    assert first == run()
    assert len(first) == 80
    for s in ("tof", "stereo"):
        stamps = [t for name, t, _ in first if name == s]
        assert stamps == sorted(stamps)


@pytest.mark.parametrize("stream", ["depth", "color"])
def test_images_are_decoded_outside_the_lock_and_one_decoded_across_a_reset_is_counted_with_it(
        stream: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A large image takes long to decode: meanwhile the other streams' messages and the consumer are
    served. An image whose decoding outlasts a ~/reset belonged to the old map and is counted with it."""
    ingest = make()
    decoding, release = threading.Event(), threading.Event()
    name = "depth_from_image" if stream == "depth" else "rgb_from_image"
    decode = getattr(conv, name)

    def slow_decode(msg):  # noqa: ANN001, ANN202
        if threading.current_thread() is not threading.main_thread():  # the tof image under test
            decoding.set()
            assert release.wait(10)
        return decode(msg)

    monkeypatch.setattr(conv, name, slow_decode)

    def while_decoding(t_ms: int, during) -> str | None:  # noqa: ANN001
        image = depth_msg(t_ms * MS) if stream == "depth" else color_msg(t_ms * MS)
        result: list[str | None] = []
        worker = threading.Thread(target=lambda: result.append(getattr(ingest, f"add_{stream}")("tof", image)))
        decoding.clear()
        release.clear()
        worker.start()
        assert decoding.wait(10)
        during()
        release.set()
        worker.join(10)
        return result[0]

    def served() -> None:  # another stream, another sensor, the consumer, the counters
        assert ingest.add_pose("tof", pose_msg(0)) is None and ingest.add_pose("tof", pose_msg(50 * MS)) is None
        assert ingest.add_depth("stereo", depth_msg(20 * MS)) is None
        assert frames(ingest.pop_ready()) == [] and ingest.ledger.counters()["stereo"]["queue_depth"] == 1

    assert while_decoding(10, served) is None
    if stream == "color":
        assert ingest.add_depth("tof", depth_msg(10 * MS)) is None
    (frame,) = frames(ingest.pop_ready())
    assert frame.stamp_ns == 10 * MS and (frame.rgb is None) == (stream == "depth")

    def reset() -> None:
        assert ingest.ledger.discard_waiting("map_reset") == 1  # the stereo frame; the tof image is on its way

    assert while_decoding(30, reset) == "map_reset"
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["map_reset"] == 1 and counters["queue_depth"] == 0
    if stream == "color":  # the colour image decoded across the reset was not kept
        assert ingest.add_depth("tof", depth_msg(30 * MS)) is None
        (frame,) = frames(ingest.pop_ready())
        assert frame.rgb is None


def test_depth_of_one_sensor_added_by_two_threads_is_queued_in_stamp_order(monkeypatch: pytest.MonkeyPatch) -> None:
    """The older image's decoding ends after the newer one's: it still leaves the queue first."""
    ingest = make()
    decoding, release = threading.Event(), threading.Event()
    decode = conv.depth_from_image

    def slow_decode(msg):  # noqa: ANN001, ANN202
        if threading.current_thread() is not threading.main_thread():
            decoding.set()
            assert release.wait(10)
        return decode(msg)

    monkeypatch.setattr(conv, "depth_from_image", slow_decode)
    worker = threading.Thread(target=ingest.add_depth, args=("tof", depth_msg(10 * MS, value=1.0)))
    worker.start()
    assert decoding.wait(10)
    assert ingest.add_depth("tof", depth_msg(20 * MS, value=2.0)) is None
    release.set()
    worker.join(10)
    ingest.add_pose("tof", pose_msg(0))
    ingest.add_pose("tof", pose_msg(15 * MS))  # the older frame can be posed, the newer one waits
    assert [(f.stamp_ns, float(f.depth_m[0, 0])) for f in frames(ingest.pop_ready())] == [(10 * MS, 1.0)]
    assert ingest.ledger.queue_depths()["tof"] == 1


def test_depth_of_a_binned_camera_info_is_taken_at_its_size() -> None:
    from sensor_msgs.msg import RegionOfInterest

    ingest = Ingest(IngestConfig(sensors=("tof",)))
    info = CameraInfo(width=20, height=16, k=[10.0, 0, 9.5, 0, 10.0, 7.5, 0, 0, 1], binning_x=2, binning_y=2,
                      roi=RegionOfInterest(x_offset=0, y_offset=0, width=0, height=0))
    assert ingest.add_camera_info("tof", info) is None
    ingest.add_pose("tof", pose_msg(0))
    assert ingest.add_depth("tof", depth_msg(10 * MS)) is None  # 10 x 8: the binned size
    ingest.add_pose("tof", pose_msg(20 * MS))
    (frame,) = frames(ingest.pop_ready())
    assert frame.K[0, 0] == 5.0 and frame.K[0, 2] == pytest.approx(4.5) and frame.depth_m.shape == (8, 10)


def test_unknown_sensor_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="configured sensors"):
        make().add_depth("lidar", depth_msg(0))


def test_consumer_behind_skips_old_frames_and_pop_limit_keeps_the_rest() -> None:
    """A slow consumer (pop_ready(max_frames=1)) gets the oldest ready frame; with max_lag_s, frames
    that fell further behind their sensor's newest are skipped and counted as 'behind'."""
    def feed(ingest: Ingest) -> None:
        for t in range(0, 1000, 100):  # 10 frames over 0.9 s
            assert ingest.add_depth("tof", depth_msg(t * MS)) is None
        for t in range(0, 1050, 50):  # poses every 50 ms, x = t in metres per second
            ingest.add_pose("tof", pose_msg(t * MS, x=t / 1000))

    ingest = make(max_lag_s=0.25)
    feed(ingest)
    (first,) = frames(ingest.pop_ready(max_frames=1))
    assert first.stamp_ns == 0 and ingest.ledger.counters()["tof"]["dropped"]["behind"] == 0
    assert ingest.ledger.queue_depths()["tof"] == 9  # posed, waiting for the consumer
    (second,) = frames(ingest.pop_ready(max_frames=1))  # the consumer is back, and behind
    assert second.stamp_ns == 700 * MS  # 100..600 ms were more than 250 ms behind the newest (900 ms)
    assert ingest.ledger.counters()["tof"]["dropped"]["behind"] == 6
    rest = frames(ingest.pop_ready())
    assert [f.stamp_ns for f in rest] == [800 * MS, 900 * MS]
    np.testing.assert_allclose(rest[1].T_world_camera[:3, 3], [0.9, 0, 0])
    unlimited = make()  # max_lag_s 0: nothing is skipped
    feed(unlimited)
    assert len(frames(unlimited.pop_ready())) == 10


def test_frames_behind_are_set_aside_and_handed_out_when_nothing_newer_waits() -> None:
    """With room to set frames aside (set_aside_bytes), frames the consumer fell behind on are not
    lost: live frames come first, the set-aside ones (oldest first, posed as when they were ready)
    once no other frame is ready and no depth image came for max_lag_s (the sensors paused); past
    the room they are dropped as 'behind'; a map reset forgets them, counted, and so does a stop
    (pop_ready(set_aside=False), then discard_waiting)."""
    def feed(ingest: Ingest, start_ms: int = 0) -> None:
        for t in range(start_ms, start_ms + 1000, 100):  # 10 frames over 0.9 s
            assert ingest.add_depth("tof", depth_msg(t * MS)) is None
        for t in range(start_ms, start_ms + 1050, 50):
            ingest.add_pose("tof", pose_msg(t * MS, x=t / 1000))

    frame_bytes = 8 * 10 * 4
    ingest = make(max_lag_s=0.25, set_aside_bytes=4 * frame_bytes)  # room for 4 of the 6 behind
    feed(ingest)
    (first,) = frames(ingest.pop_ready(max_frames=1))
    (second,) = frames(ingest.pop_ready(max_frames=1))
    assert (first.stamp_ns, second.stamp_ns) == (0, 700 * MS)
    c = ingest.ledger.counters()["tof"]
    assert (c["set_aside"], c["set_aside_now"], c["dropped"]["behind"]) == (4, 4, 2)
    assert ingest.ledger.queue_depths()["tof"] == 2 + 4  # 800 and 900 ms ready, 4 set aside
    live = [f.stamp_ns for f in frames(ingest.pop_ready(max_frames=1)) + frames(ingest.pop_ready(max_frames=1))]
    assert live == [800 * MS, 900 * MS]  # what is newest goes first
    assert frames(ingest.pop_ready(max_frames=1)) == []  # images came just now: the sensors may go on
    time.sleep(0.3)  # no image for max_lag_s
    later = [frames(ingest.pop_ready(max_frames=1)) for _ in range(5)]
    assert [[f.stamp_ns for f in batch] for batch in later] == [[100 * MS], [200 * MS], [300 * MS], [400 * MS], []]
    np.testing.assert_allclose(later[2][0].T_world_camera[:3, 3], [0.3, 0, 0])
    assert ingest.ledger.counters()["tof"]["set_aside_now"] == 0 and ingest.ledger.queue_depths()["tof"] == 0

    feed(ingest, start_ms=1000)  # behind again, with room for all four again
    frames(ingest.pop_ready(max_frames=1)), frames(ingest.pop_ready(max_frames=1))
    assert ingest.ledger.counters()["tof"]["set_aside_now"] == 4
    ingest.ledger.discard_waiting("map_reset")  # ~/reset: they belonged to the old map
    c = ingest.ledger.counters()["tof"]
    assert c["set_aside_now"] == 0 and c["dropped"]["map_reset"] == 4 + 2 and ingest.ledger.queue_depths()["tof"] == 0

    feed(ingest, start_ms=2000)
    frames(ingest.pop_ready(max_frames=1)), frames(ingest.pop_ready(max_frames=1))
    assert len(frames(ingest.pop_ready(set_aside=False))) == 2  # a stop integrates what is ready, not what waits
    assert ingest.ledger.discard_waiting("shutdown") == 4
    assert ingest.ledger.counters()["tof"]["dropped"]["shutdown"] == 4


def test_frames_set_aside_of_a_sensor_that_stopped_go_while_the_other_streams() -> None:
    """The ToF stops (its driver died) with frames set aside while the stereo camera streams on: its
    frames waited for a pause of every sensor, which a robot streaming for hours never makes. They are
    handed out in the gaps between the stereo frames once the ToF was silent for max_lag_s; the
    stereo camera's own set-aside frames wait while it streams."""
    frame_bytes = 8 * 10 * 4
    ingest = make(max_lag_s=0.25, set_aside_bytes=20 * frame_bytes)
    for t in range(0, 1050, 50):
        ingest.add_pose("tof", pose_msg(t * MS, x=t / 1000))
        ingest.add_pose("stereo", pose_msg(t * MS, x=t / 1000))
    for t in range(0, 1000, 100):
        assert ingest.add_depth("tof", depth_msg(t * MS)) is None
        assert ingest.add_depth("stereo", depth_msg(t * MS)) is None
    for _ in range(3):  # the consumer was behind: the frames more than max_lag_s older than the newest set aside
        frames(ingest.pop_ready(max_frames=2))
    assert {name: c["set_aside_now"] for name, c in ingest.ledger.counters().items()} == {"tof": 6, "stereo": 6}
    t_ms, handed = 1000, []
    deadline = time.monotonic() + 0.6
    while time.monotonic() < deadline:  # the stereo camera streams at 20 Hz, each frame taken at once
        ingest.add_pose("stereo", pose_msg((t_ms + 50) * MS, x=t_ms / 1000))
        assert ingest.add_depth("stereo", depth_msg(t_ms * MS)) is None
        handed += frames(ingest.pop_ready(max_frames=1))
        handed += frames(ingest.pop_ready(max_frames=1))  # a gap: nothing new is ready
        t_ms += 50
        time.sleep(0.05)
    late_tof = [f.stamp_ns // MS for f in handed if f.set_aside]
    assert late_tof and {f.sensor for f in handed if f.set_aside} == {"tof"}, handed
    assert late_tof == sorted(late_tof) and late_tof[0] == 100  # oldest first
    assert ingest.ledger.counters()["stereo"]["set_aside_now"] == 6


def test_a_queue_that_fills_while_the_consumer_is_held_sets_its_oldest_frames_aside() -> None:
    """Frames are set aside when the consumer takes them (pop_ready); while it was held (an eviction of
    thousands of blocks, a save) nobody took any, the queue filled and its oldest frames were dropped as
    queue_full, with room to set them aside. They are set aside as the queue overflows; frames that
    cannot be posed yet still go as queue_full."""
    frame_bytes = 8 * 10 * 4
    ingest = make(max_lag_s=0.25, set_aside_bytes=4 * frame_bytes, queue_size=3)
    for t in range(0, 1050, 50):
        ingest.add_pose("tof", pose_msg(t * MS, x=t / 1000))
    for t in range(0, 800, 100):  # 8 frames, nobody taking them: 5 over the queue, room for 4
        assert ingest.add_depth("tof", depth_msg(t * MS)) is None
    c = ingest.ledger.counters()["tof"]
    assert (c["set_aside"], c["dropped"]["queue_full"]) == (4, 1), c
    assert [f.stamp_ns // MS for f in frames(ingest.pop_ready())] == [500, 600, 700]
    time.sleep(0.3)  # the sensor paused
    late = [f for _ in range(5) for f in frames(ingest.pop_ready())]  # one at a time
    assert [f.stamp_ns // MS for f in late] == [0, 100, 200, 300] and all(f.set_aside for f in late)
    np.testing.assert_allclose(late[2].T_world_camera[:3, 3], [0.2, 0, 0])
    unposed = make(max_lag_s=0.25, set_aside_bytes=4 * frame_bytes, queue_size=3)
    for t in range(0, 400, 100):  # no pose yet: nothing to set aside with
        assert unposed.add_depth("tof", depth_msg(t * MS)) is None
    c = unposed.ledger.counters()["tof"]
    assert (c["set_aside"], c["dropped"]["queue_full"]) == (0, 1), c


def test_integrate_ready_keeps_order_isolates_errors_and_flushes_before_a_time_jump() -> None:
    from senfunet_core.engine import EngineConfig, SenFuNet
    from senfunet_core.errors import InputError
    from senfunet_ros.ingest import integrate_ready

    K = np.array([[40.0, 0, 31.5], [0, 40.0, 23.5], [0, 0, 1]])
    v, u = np.mgrid[0:48, 0:64].astype(np.float32)

    def frame(sensor: str, i: int, depth: np.ndarray | None = None) -> Frame:
        T = np.eye(4)
        T[0, 3] = 0.02 * i
        if depth is None:
            depth = (1.0 + 0.003 * u + 0.02 * np.sin(v / 4.0 + i)).astype(np.float32)
        rgb = np.full((48, 64, 3), 90, np.uint8) if sensor == "stereo" else None
        return Frame(sensor, i * 10**8, depth, rgb, K, T, 0.0)

    good = [frame("tof", 0), frame("stereo", 1), frame("tof", 2), frame("stereo", 3)]
    bad = frame("tof", 9, depth=np.ones((48, 64), np.int32))  # rejected by the engine's checks
    jump = TimeJump("tof", "depth", 5 * 10**8, 0)
    engine = SenFuNet(EngineConfig(), weights=None)
    events: list[tuple] = []

    def on_frame(f: Frame, error: Exception | None, seconds: float) -> None:
        assert seconds >= 0
        events.append(("frame", f.stamp_ns, type(error).__name__ if error else None))

    def on_time_jump(j: TimeJump) -> None:  # every frame before the jump is in the map by now
        events.append(("jump", sum(engine.frames_integrated.values())))

    integrate_ready(engine, [good[0], good[1], bad, jump, good[2], good[3]], on_time_jump, on_frame)
    assert events == [("frame", 0, None), ("frame", 10**8, None), ("frame", 9 * 10**8, InputError.__name__),
                      ("jump", 2), ("frame", 2 * 10**8, None), ("frame", 3 * 10**8, None)]
    # the same map as integrating the good frames one by one
    reference = SenFuNet(EngineConfig(), weights=None)
    for f in good:
        reference.integrate(f.sensor, f.depth_m, f.K, f.T_world_camera, f.rgb)
    n = engine.grid.n_blocks
    assert n == reference.grid.n_blocks > 0
    for name in ("tsdf0", "weight0", "feat0", "tsdf1", "weight1", "feat1"):
        assert torch.equal(engine.grid.pools[name][:n], reference.grid.pools[name][:n]), name
    for flags in ("reach_changed", "reach_renewed"):  # the changes waiting for the weighting net
        assert np.array_equal(getattr(engine.store, flags)[:n], getattr(reference.store, flags)[:n]), flags


def test_pose_of_another_frame_goes_through_the_sensor_extrinsic() -> None:
    T_body_camera = np.eye(4)
    T_body_camera[:3, :3] = [[0, 0, 1], [-1, 0, 0], [0, -1, 0]]  # optical axes in a body frame
    T_body_camera[:3, 3] = [0.2, 0.0, 0.5]
    ingest = make(T_body_camera={"tof": T_body_camera})
    ingest.add_pose("tof", pose_msg(0, x=1.0))
    ingest.add_depth("tof", depth_msg(0))
    (frame,) = frames(ingest.pop_ready())
    T_world_body = np.eye(4)
    T_world_body[0, 3] = 1.0
    assert np.allclose(frame.T_world_camera, T_world_body @ T_body_camera)


def test_pipeline_tells_its_owner_under_its_lock_each_time_the_map_is_emptied_or_replaced(tmp_path) -> None:
    """What the node derives from integrated frames (camera colours) is cleared with the map, under
    the lock frames are integrated under: no frame lands between the two."""
    from senfunet_core.engine import EngineConfig, SenFuNet
    from senfunet_ros.pipeline import Pipeline

    calls: list[bool] = []

    def on_new_map() -> None:  # True: another thread cannot take the pipeline's lock now
        held: list[bool] = []
        probe = threading.Thread(target=lambda: held.append(not pipeline.lock.acquire(blocking=False)))
        probe.start()
        probe.join()
        calls.append(held[0])

    pipeline = Pipeline(SenFuNet(EngineConfig(), weights=None), make(), on_time_jump="keep", on_new_map=on_new_map)
    pipeline.drain([TimeJump("tof", "depth", 5 * 10**8, 0)])
    assert calls == []  # on_time_jump "keep": the map stays
    pipeline.on_time_jump = pipeline.on_time_jump.parse("reset")
    pipeline.drain([TimeJump("tof", "depth", 5 * 10**8, 0)])
    assert calls == [True]
    pipeline.reset()
    assert calls == [True] * 2
    pipeline.load_map(pipeline.save_map(tmp_path / "map.pt"))
    assert calls == [True] * 3
    pipeline.save_meshes(tmp_path, sensors=(), tsdf_fusion=False)
    assert calls == [True] * 3  # saving alone keeps the map
    pipeline.save_meshes(tmp_path, sensors=(), tsdf_fusion=False, then_reset=True)
    assert calls == [True] * 4


def test_pipeline_counts_rejected_and_empty_frames_with_the_reason_and_logs_none_of_them_itself() -> None:
    """The engine's rejections and frames with nothing to integrate are drops with their reason
    (the node warns once per cause and period, from the counters), not integrated frames nor one
    log line per frame."""
    from senfunet_core.engine import EngineConfig, SenFuNet
    from senfunet_ros.pipeline import Pipeline

    logged: list[str] = []
    pipeline = Pipeline(SenFuNet(EngineConfig(), weights=None), make(), log=lambda level, text: logged.append(text))
    K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    far = np.eye(4)
    far[0, 3] = 1e5  # 100 km from the origin: beyond the grid's key range
    rejected = [Frame("tof", i * 10**8, np.ones((48, 64), np.float32), None, K, far) for i in range(3)]
    assert pipeline.drain(rejected) == 0
    counters = pipeline.ingest.ledger.counters()["tof"]
    assert counters["dropped"]["engine_error"] == 3 and pipeline.frames_failed == 3
    assert counters["errors"]["engine_error"].startswith("frame at 0.200 s: ")
    # depth in millimetres in a 32FC1 image: every pixel beyond depth_max_m, nothing to integrate
    millimetres = [Frame("tof", (5 + i) * 10**8, np.full((48, 64), 1500.0, np.float32), None, K, np.eye(4))
                   for i in range(2)]
    assert pipeline.drain(millimetres) == 0
    counters = pipeline.ingest.ledger.counters()["tof"]
    assert counters["dropped"]["out_of_range"] == 2 and counters["integrated"] == 0 and pipeline.frames_failed == 3
    assert "1500.000 m: millimetres" in counters["errors"]["out_of_range"]
    # a 20x20 image: all of it within the engine's 10-pixel border (the depth itself is in range)
    assert pipeline.drain([Frame("tof", 9 * 10**8, np.ones((20, 20), np.float32), None, K, np.eye(4))]) == 0
    counters = pipeline.ingest.ledger.counters()["tof"]
    assert counters["dropped"]["out_of_range"] == 3 and "(20x20) is not larger than twice the 10-pixel border" in (
        counters["errors"]["out_of_range"])
    assert logged == []


def test_frames_are_integrated_and_stats_answered_while_meshes_are_saved(tmp_path, monkeypatch) -> None:
    """~/save_mesh during a stream: the pipeline keeps integrating (its queues would overflow
    otherwise), and the status gets the last statistics at once rather than wait for the save."""
    from senfunet_core.engine import EngineConfig, SenFuNet
    from senfunet_ros.pipeline import Pipeline

    engine = SenFuNet(EngineConfig(), weights=None)
    pipeline = Pipeline(engine, make())
    saving, release = threading.Event(), threading.Event()
    extract_mesh = engine.extract_mesh

    def held_extraction(*args, **kwargs):  # the save holds the map while this waits
        with engine.update_lock.held():
            saving.set()
            release.wait(30)
        return extract_mesh(*args, **kwargs)

    monkeypatch.setattr(engine, "extract_mesh", held_extraction)
    saver = threading.Thread(target=pipeline.save_meshes, args=(tmp_path,),
                             kwargs={"sensors": (), "tsdf_fusion": False})
    saver.start()
    try:
        assert saving.wait(30)
        K = np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
        frame = Frame("tof", 10**8, np.full((48, 64), 1.0, np.float32), None, K, np.eye(4))
        drained: list[int] = []
        feeder = threading.Thread(target=lambda: drained.append(pipeline.drain([frame])), daemon=True)
        feeder.start()
        feeder.join(30)
        assert drained == [1]  # integrated during the save
        assert engine.stats(wait=False) is None  # the map is held: no waiting
    finally:
        release.set()
        saver.join(60)
    assert (tmp_path / "mesh.ply").is_file() and engine.stats(wait=False)["frames_integrated"]["tof"] == 1


def test_a_time_jump_that_resets_the_map_during_a_save_waits_for_the_last_mesh(tmp_path, monkeypatch) -> None:
    """~/save_mesh makes its meshes one after the other while frames keep coming. A time jump that
    reset the map (on_time_jump reset: a bag looping) between two of them gave files of two maps:
    the per-sensor meshes of the map asked for, mesh.ply (made last) of the emptied one. The reset
    now waits for the save's last mesh; frames do not."""
    from senfunet_core.engine import EngineConfig, SenFuNet
    from senfunet_ros.pipeline import Pipeline

    engine = SenFuNet(EngineConfig(), weights=None)
    pipeline = Pipeline(engine, make(), on_time_jump="reset")
    K = np.array([[160.0, 0, 63.5], [0, 160.0, 63.5], [0, 0, 1]])
    for sensor in ("tof", "stereo"):  # a wall 0.5 m ahead, seen by both
        engine.integrate(sensor, np.full((128, 128), 0.5, np.float32), K, np.eye(4))
    extract_mesh, held = engine.extract_mesh, engine.update_lock.held
    settled = threading.Event()  # the reset ran, or it waits for the map
    resetter = threading.Thread(target=lambda: (pipeline.drain([TimeJump("tof", "depth", 2 * 10**9, 10**9)]),
                                                settled.set()))

    def watched_held(*args, **kwargs):
        if threading.current_thread() is resetter:
            if engine.update_lock._lock.acquire(blocking=False):
                engine.update_lock._lock.release()
            else:
                settled.set()  # the save holds the map: the reset waits for it
        return held(*args, **kwargs)

    def reset_after_the_first_mesh(*args, **kwargs):
        mesh = extract_mesh(*args, **kwargs)
        if resetter.ident is None:
            resetter.start()
            assert settled.wait(60)
        return mesh

    monkeypatch.setattr(engine.update_lock, "held", watched_held)
    monkeypatch.setattr(engine, "extract_mesh", reset_after_the_first_mesh)
    saved = pipeline.save_meshes(tmp_path, sensors=("tof", "stereo"), tsdf_fusion=False)
    resetter.join(60)
    assert not resetter.is_alive() and pipeline.time_jumps == 1 and engine.grid.n_blocks == 0  # reset after all
    assert [stem for stem in saved] == ["mesh", "tof", "stereo"]  # the fused mesh written first
    assert min(saved[stem].mesh.n_faces for stem in saved) > 1000, {stem: saved[stem].mesh.n_faces for stem in saved}


def test_a_pause_of_every_stream_keeps_what_waits_and_old_messages_in_flight_after_a_clock_restart_are_off() -> None:
    """Every stream resuming after a pause longer than time_jump_s is a restart ahead: nothing queued
    is flushed. After the /clock went back, a message of the old time still in flight does not start
    the new timeline."""
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5050 * MS))  # waits for a pose after it
    for i in range(3):  # all streams resume 5 s later (the pose stream is the one that spoke)
        ingest.add_pose("tof", pose_msg(10_000 * MS + i * 10 * MS))
        ingest.add_depth("tof", depth_msg(10_005 * MS + i * 10 * MS))
    items = ingest.pop_ready()
    assert not any(isinstance(i, TimeJump) for i in items)
    # the messages that confirmed the pause were held and taken: the last frame waits for a pose after it
    assert [f.stamp_ns for f in frames(items)] == [10_005 * MS, 10_015 * MS]
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["time_jump"] == 0 and counters["dropped"]["bad_stamp"] == 0
    # the frame queued before the pause was not flushed: the poses around it are 5 s apart
    assert counters["dropped"]["pose_gap"] == 1 and "bad_stamp" not in counters["errors"]
    ingest.restart(to_ns=0)  # the /clock went back to 0
    assert ingest.add_pose("tof", pose_msg(10_040 * MS)) == "time_jump"  # in flight from before: lost to it
    assert ingest.add_pose("tof", pose_msg(5 * MS)) is None
    assert ingest.add_depth("tof", depth_msg(10 * MS)) is None
    ingest.add_pose("tof", pose_msg(15 * MS))
    assert [f.stamp_ns for f in frames(ingest.pop_ready())] == [10 * MS]


def test_a_pose_republished_at_its_stamp_with_another_value_is_counted_and_the_first_kept() -> None:
    """A driver that republishes a stamp with another pose would silently bend the trajectory: the
    first pose stays (frames may have been posed with it already), the second is dropped as
    pose_conflict with what differs; the same pose again is no conflict."""
    ingest = make()
    assert ingest.add_pose("tof", pose_msg(0, x=0.0)) is None
    assert ingest.add_pose("tof", pose_msg(100 * MS, x=1.0)) is None
    assert ingest.add_pose("tof", pose_msg(100 * MS, x=1.0)) is None  # the same pose again: fine
    assert ingest.add_pose("tof", pose_msg(100 * MS, x=3.0)) == "pose_conflict"
    assert ingest.add_pose("tof", pose_msg(100 * MS, x=1.0, yaw_rad=0.5)) == "pose_conflict"
    ingest.add_depth("tof", depth_msg(50 * MS))
    (frame,) = frames(ingest.pop_ready())
    np.testing.assert_allclose(frame.T_world_camera[:3, 3], [0.5, 0, 0])  # between x 0 and the first x 1
    c = ingest.ledger.counters()["tof"]
    assert c["dropped"]["pose_conflict"] == 2 and c["pose_received"] == 5
    assert "28.65 deg from the first" in c["errors"]["pose_conflict"]


def test_a_tf_transform_republished_at_its_stamp_with_another_value_is_counted_and_the_first_kept() -> None:
    from geometry_msgs.msg import TransformStamped

    from senfunet_ros.tf import TfBuffer

    class TFMessage:  # tf2_msgs/TFMessage's one field (tf2_msgs is not on the package index)
        def __init__(self, transforms: list[TransformStamped]) -> None:
            self.transforms = transforms

    def transform(t_ns: int, x: float) -> TransformStamped:
        msg = TransformStamped()
        _stamp(msg, t_ns)
        msg.header.frame_id, msg.child_frame_id = "map", "cam"
        msg.transform.translation.x, msg.transform.rotation.w = x, 1.0
        return msg

    tf = TfBuffer()
    ingest = Ingest(IngestConfig(sensors=("tof", "stereo"), tf=tf))
    assert ingest.add_tf(TFMessage([transform(50 * MS, 0.0), transform(100 * MS, 1.0)]), static=False) is None
    assert ingest.add_tf(TFMessage([transform(100 * MS, 1.0)]), static=False) is None  # the same again
    assert ingest.add_tf(TFMessage([transform(100 * MS, 2.0), transform(200 * MS, 2.0)]), static=False) == \
        "pose_conflict"
    np.testing.assert_allclose(tf.lookup("map", "cam", 100 * MS)[:3, 3], [1.0, 0, 0])  # the first kept
    np.testing.assert_allclose(tf.lookup("map", "cam", 200 * MS)[:3, 3], [2.0, 0, 0])  # the rest of the message
    c = ingest.ledger.counters()["tof"]
    assert c["dropped"]["pose_conflict"] == 1 and "transform map -> cam at 0.100 s" in c["errors"]["pose_conflict"]


def test_the_images_a_confirmed_restart_takes_are_decoded_outside_the_lock(monkeypatch: pytest.MonkeyPatch) -> None:
    """The new timeline's held images (a queue's worth per stream) are decoded as any image is, with
    the lock released: meanwhile other streams and the consumer are served; counts stay exact."""
    ingest = make(time_jump_s=1.0, restart_confirm_msgs=3, restart_confirm_s=0.02)
    ingest.add_pose("tof", pose_msg(5000 * MS))
    ingest.add_depth("tof", depth_msg(5100 * MS))
    decoding, release = threading.Event(), threading.Event()
    decode = conv.depth_from_image

    def slow_decode(msg):  # noqa: ANN001, ANN202
        if threading.current_thread().name == "restart":  # the restart's burst
            decoding.set()
            assert release.wait(10)
        return decode(msg)

    monkeypatch.setattr(conv, "depth_from_image", slow_decode)
    for t in (10, 20):  # the new timeline: held until it is confirmed
        ingest.add_pose("tof", pose_msg(t * MS))
        assert ingest.add_depth("tof", depth_msg(t * MS + 5 * MS)) == "bad_stamp"
    ingest.add_pose("tof", pose_msg(30 * MS))
    result: list[str | None] = []
    worker = threading.Thread(target=lambda: result.append(ingest.add_depth("tof", depth_msg(35 * MS))),
                              name="restart")
    worker.start()  # the third depth image confirms the restart: the two held ones are decoded
    try:
        assert decoding.wait(10)
        served: list[bool] = []

        def serve() -> None:  # another sensor, the consumer, the counters
            assert ingest.add_depth("stereo", depth_msg(32 * MS)) is None
            items = ingest.pop_ready()
            assert isinstance(items[0], TimeJump) and frames(items) == []  # the tof frames are not queued yet
            served.append(ingest.ledger.counters()["tof"]["dropped"]["bad_stamp"] == 0)

        server = threading.Thread(target=serve, daemon=True)
        server.start()
        server.join(5)
        assert served == [True], "the lock was held while the restart's images were decoded"
    finally:
        release.set()
        worker.join(10)
    assert result == [None]
    ingest.add_pose("tof", pose_msg(40 * MS))
    assert [f.stamp_ns for f in frames(ingest.pop_ready()) if f.sensor == "tof"] == [15 * MS, 25 * MS, 35 * MS]
    c = ingest.ledger.counters()["tof"]
    assert c["dropped"]["bad_stamp"] == 0 and c["dropped"]["time_jump"] == 1 and c["time_jumps"] == 1
    assert c["received"] == 4 and c["queue_depth"] == 0


def test_a_full_queue_says_whether_its_frames_waited_for_poses_or_for_integration() -> None:
    """Under overload the queue fills with frames whose poses are there, waiting for integration: the
    drop was explained as images waiting for their poses (the warning sent users to the pose topic).
    A frame that goes while it waits for its pose keeps that explanation (the hint naming the topic)."""
    ingest = make(queue_size=2)
    for t_ms in (0, 500):
        ingest.add_pose("tof", pose_msg(t_ms * MS))
    for t_ms in (100, 200, 300):  # posable, but the consumer takes none: it is behind
        ingest.add_depth("tof", depth_msg(t_ms * MS))
    for t_ms in (100, 200, 300):  # no pose after them yet
        ingest.add_depth("stereo", depth_msg(t_ms * MS + 1))
    counters = ingest.ledger.counters()
    assert counters["tof"]["dropped"]["queue_full"] == counters["stereo"]["dropped"]["queue_full"] == 1
    why = counters["tof"]["errors"].get("queue_full", "")
    assert "integration is behind" in why and "queue_size" in why, why
    assert "queue_full" not in counters["stereo"]["errors"]  # the hint about poses holds


def test_a_consumer_behind_takes_frames_of_every_sensor() -> None:
    """A consumer that takes one frame while each sensor sends one (integration behind) was handed the
    oldest ready frame: always the sensor whose images come later after their stamps (stereo's, 25 ms
    against ToF's 8 ms in the sample bag), while the other's frames fell behind and were dropped: the
    live map was built from one sensor. It now takes the sensor it served longest ago."""
    ingest = make(max_lag_s=0.05)
    taken = {"tof": 0, "stereo": 0}
    for s in ("tof", "stereo"):
        ingest.add_pose(s, pose_msg(0))
    for i in range(1, 41):
        for s in ("tof", "stereo"):
            ingest.add_pose(s, pose_msg(100 * MS * i + 50 * MS))
        ingest.add_depth("tof", depth_msg(100 * MS * i))
        ingest.add_depth("stereo", depth_msg(100 * MS * i - 30 * MS))  # stamped earlier, arrives later
        for frame in frames(ingest.pop_ready(max_frames=1)):
            taken[frame.sensor] += 1
    assert min(taken.values()) >= 15, taken
    counters = ingest.ledger.counters()
    assert all(c["received"] == taken[s] + c["dropped"]["behind"] + c["queue_depth"] for s, c in counters.items())


def test_behind_buffer_lowered_at_run_time_lets_go_of_what_it_no_longer_holds() -> None:
    """`ros2 param set /senfunet behind_buffer_mb ...` lower than the frames set aside (a robot short
    of memory) kept them all until the sensors paused: the new bound held only for frames to come.
    The newest beyond it go at once, counted as behind."""
    frame_bytes = 8 * 10 * 4  # depth_msg's 8 x 10 float32
    ingest = make(max_lag_s=0.05, set_aside_bytes=100 * frame_bytes)
    for t_ms in range(50, 1100, 100):
        ingest.add_pose("tof", pose_msg(t_ms * MS))
    for t_ms in range(100, 1100, 100):
        ingest.add_depth("tof", depth_msg(t_ms * MS))
    for _ in range(2):  # a consumer that takes nothing: the first pass poses them, the second sets them aside
        ingest.pop_ready(max_frames=0)
    before = ingest.ledger.counters()["tof"]
    assert before["set_aside_now"] >= 5
    ingest.config = dataclasses.replace(ingest.config, set_aside_bytes=2 * frame_bytes)
    after = ingest.ledger.counters()["tof"]
    assert after["set_aside_now"] == 2
    assert after["dropped"]["behind"] == before["set_aside_now"] - 2


def test_one_stray_clock_going_back_restarts_nothing_and_a_loop_restarts_once() -> None:
    """Under use_sim_time one /clock of 0 (a second /clock publisher) in a running stream was taken as a
    restart at once: queued frames flushed, the next time_jump_s of frames lost, the map reset with
    on_time_jump reset. Only a /clock that goes on from where it went back is a restart."""
    from senfunet_ros.timeline import ClockTimeline

    s = 1_000_000_000
    clock = ClockTimeline()
    seen = [clock.observe(t, 1 * s) for t in (100 * s, 101 * s, 0, 102 * s, 103 * s)]
    assert seen == [None, None, None, ("stray", 101 * s, 0), None]
    seen = [clock.observe(t, 1 * s) for t in (10 * s, 10 * s + s // 40, 11 * s, 5 * s, 12 * s)]
    assert seen == [None, ("restart", 103 * s, 10 * s + s // 40), None, None, ("stray", 11 * s, 5 * s)]
    assert clock.observe(11_500_000_000, 1 * s) is None  # back by less than the jump: the same timeline
    clock.reset()
    assert clock.observe(0, 1 * s) is None and clock.last_ns == 0  # no reference after a reset


def test_poses_of_two_publishers_interleaved_on_one_topic_are_noted() -> None:
    """A second publisher on a pose topic, its poses 0.3 m off and stamped between the first's: every
    frame was posed between the two trajectories (72% of the mesh over 5 cm off), with nothing said;
    one stream moving fast, or standing still and noisy, is no such thing."""
    rng = np.random.default_rng(0)

    def notes_after(positions_m: list[float]) -> dict[str, str]:
        ingest = make()
        for i, x in enumerate(positions_m):
            ingest.add_pose("tof", pose_msg(i * 10 * MS, x=x))
        return ingest.ledger.counters()["tof"]["notes"]

    interleaved = [0.01 * i + (0.3 if i % 2 else 0.0) for i in range(40)]
    note = notes_after(interleaved).get("pose_alternates", "")
    assert re.search(r"about (29|30|31) cm", note) and "two publishers" in note, note
    assert "pose_alternates" not in notes_after([0.05 * i for i in range(40)])  # 5 cm a pose: fast, one stream
    assert "pose_alternates" not in notes_after(list(rng.normal(0, 0.005, 40)))  # still, 5 mm noise


def test_messages_stamped_0_are_a_driver_that_sets_no_stamps_and_a_camera_info_stamped_0_still_serves() -> None:
    """A driver that never sets header.stamp: every depth image and pose at 0 was diagnosed as two publishers
    on one topic (pose_conflict), duplicates, or a stamp far behind the stream's timeline. Now each is a
    bad_stamp saying the stamp is unset and which of the sensor's streams carry 0 (one 0 per stream is
    taken: a simulation's clock starts there); a camera_info stamped 0 (its stamp is used for nothing)
    beside stamped images is still taken."""
    ingest = make()  # info_msg() is stamped 0
    assert ingest.add_pose("tof", pose_msg(0)) is None
    assert ingest.add_depth("tof", depth_msg(0)) is None
    assert ingest.add_color("tof", color_msg(0)) is None
    for i in range(1, 4):
        assert ingest.add_pose("tof", pose_msg(0, x=0.1 * i)) == "bad_stamp"
        assert ingest.add_color("tof", color_msg(0)) == "bad_stamp"
        assert ingest.add_depth("tof", depth_msg(0, value=1.0 + i)) == "bad_stamp"
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_stamp"] == 9, counters["dropped"]
    assert counters["dropped"]["pose_conflict"] == counters["dropped"]["duplicate"] == 0, counters["dropped"]
    error = counters["errors"]["bad_stamp"]
    assert error.startswith("depth: header.stamp is 0 (unset), on its depth, colour, pose and camera_info messages: "
                            "their driver does not set stamps"), error
    assert error.endswith("; colour: header.stamp is 0 (unset): its driver does not set stamps"), error
    assert [(f.sensor, f.stamp_ns) for f in frames(ingest.pop_ready())] == [("tof", 0)]
    # images and poses stamped (far from 0), the camera_info not: fused; a depth image stamped 0 among them is
    # unset, not 1000 s behind the stream's timeline
    ingest = make()
    for t in (1000_000, 1000_100):
        assert ingest.add_pose("stereo", pose_msg(t * MS)) is None
    assert ingest.add_depth("stereo", depth_msg(1000_050 * MS)) is None
    assert ingest.add_depth("stereo", depth_msg(0)) == "bad_stamp"
    stereo = ingest.ledger.counters()["stereo"]
    assert stereo["errors"]["bad_stamp"].startswith("depth: header.stamp is 0 (unset), on its depth and camera_info "
                                                    "messages"), stereo["errors"]
    assert [(f.sensor, f.stamp_ns) for f in frames(ingest.pop_ready())] == [("stereo", 1000_050 * MS)]


def test_depth_frames_that_cross_keep_their_colour_and_are_no_missing_images() -> None:
    """Depth images logged or delivered slightly out of order (two frames crossed): the stream's first
    frame, coming after its second, was dropped as out_of_order; a frame taken between the two newest
    lost its colour (the colour buffer forgot images older than the newest frame matched); and the images
    that came late were counted as missing from the stream's regular stamps, even those dropped."""
    ingest = make(time_jump_s=5.0)  # every pose first
    period = 50 * MS
    for k in range(52):  # poses twice as often: a gap in the images is no pause of the sensor
        ingest.add_pose("stereo", pose_msg(k * period // 2))
    # 17 and 18 never come; 21 and 22 come after 23 and 24, older than both: out of order
    order = [1, 0, 2, 3, 5, 4, 6, 7, 8, 9, 10, 11, 14, 12, 13, 15, 16, 19, 20, 23, 24, 21, 22]
    reasons, fused = {}, []
    for k in order:
        ingest.add_color("stereo", color_msg(k * period, value=k))
        reasons[k] = ingest.add_depth("stereo", depth_msg(k * period))
        fused += frames(ingest.pop_ready())
    assert {k: r for k, r in reasons.items() if r is not None} == {21: "out_of_order", 22: "out_of_order"}, reasons
    counters = ingest.ledger.counters()["stereo"]
    assert counters["missing_depth"] == 2, counters  # 17 and 18
    assert counters["without_color"] == 0, counters
    assert sorted(f.stamp_ns // period for f in fused) == sorted(set(order) - {21, 22})
    for frame in fused:  # each with its own colour image
        assert frame.rgb is not None and int(frame.rgb[0, 0, 0]) == frame.stamp_ns // period, frame.stamp_ns
