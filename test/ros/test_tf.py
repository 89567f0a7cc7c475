"""Poses from TF: the buffer's lookups, and a bag whose poses exist only as /tf (a moving base)
plus /tf_static (the camera mounts) replays to the mesh of the same recording with pose topics."""
from __future__ import annotations

import math
from typing import Any
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from replays import replay_in_process

from senfunet_ros.bagio import open_bag, write_sequence_bag
from senfunet_ros.geometry import invert_transform, quat_from_matrix
from senfunet_ros.tf import TfBuffer, TfError, TfWait

PARAMS = "senfunet:\n  ros__parameters:\n    working_width: 64\n    voxel_size_m: 0.04\n    band_m: 0.4\n"
# the base's axes in an optical frame: x forward = optical z, y left = -optical x, z up = -optical y
T_BASE_OPTICAL = np.array([[0.0, 0, 1, 0.1], [-1, 0, 0, 0], [0, -1, 0, 0.5], [0, 0, 0, 1]])


def _rot_z(angle: float, t: tuple[float, float, float] = (0, 0, 0)) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    T[:3, 3] = t
    return T


def test_buffer_chains_interpolates_waits_and_refuses_gaps() -> None:
    tf = TfBuffer(max_gap_s=0.1)
    S = 1_000_000_000
    tf.add("map", "odom", 0, _rot_z(0.0, (1, 0, 0)), static=True)
    tf.add("odom", "base_link", 10 * S, _rot_z(0.0), static=False)
    tf.add("odom", "base_link", 10 * S + S // 20, _rot_z(0.2, (0.5, 0, 0)), static=False)
    tf.add("base_link", "cam", 0, T_BASE_OPTICAL, static=True)
    T = tf.lookup("map", "cam", 10 * S + S // 40)  # halfway: x 0.25 m, yaw 0.1 rad
    expected = _rot_z(0.0, (1, 0, 0)) @ _rot_z(0.1, (0.25, 0, 0)) @ T_BASE_OPTICAL
    assert np.abs(T - expected).max() < 1e-9
    assert np.abs(tf.lookup("cam", "map", 10 * S) - invert_transform(tf.lookup("map", "cam", 10 * S))).max() < 1e-9
    # nothing at or after it yet: may still come (and the wait says where the link stands: a frame that
    # timed out waiting for it said only "no transform ... yet")
    with pytest.raises(TfWait, match=r"odom -> base_link at or after 11.000 s yet \(its newest is at 10.050 s, "
                                     r"and one comes every 0.05 s\)"):
        tf.lookup("map", "cam", 11 * S)
    # before the first transform: said so, not "publish them more often or raise pose_tolerance_s", which
    # could not help (a node started after the images' first stamps told its users to)
    with pytest.raises(TfError, match="before the first transform odom -> base_link held"):
        tf.lookup("map", "cam", 9 * S)
    with pytest.raises(TfWait, match="no transform path") as waited:
        tf.lookup("map", "other_cam", 10 * S)
    # a camera not in the tree (yet): fixed_frame is right, the camera's frame is named
    assert "set fixed_frame" not in str(waited.value)
    assert "no transform names 'other_cam' (the depth image's header.frame_id)" in str(waited.value)
    # a fixed frame no transform names: the tree's root is named (the chains alone left it to the reader)
    with pytest.raises(TfWait, match=r"no transform names 'world' \(fixed_frame\): set fixed_frame to the root "
                                     r"of the source's tree, 'map', or another frame of its chain"):
        tf.lookup("world", "cam", 10 * S)
    with pytest.raises(TfWait) as waited:  # a frame some transform names, in another tree: no such advice
        tf.add("robot2", "cam2", 0, np.eye(4), static=True)
        tf.lookup("robot2", "cam", 10 * S)
    assert "set fixed_frame" not in str(waited.value)
    assert "they hang in two trees, whose roots are 'map' and 'robot2'" in str(waited.value)


def test_a_transform_stamped_ahead_by_a_glitch_costs_no_frame() -> None:
    """A dynamic transform a glitching publisher stamped 0.5 s ahead (within time_jump_s, so taken)
    was the next transform of the stamps before it: their lookups failed as a gap at once, though the
    link's own transforms came a moment later. Now they wait while the far one is the newest; a real
    hole is a gap once the link went on past it."""
    tf = TfBuffer(max_gap_s=0.1)
    MS = 1_000_000
    for k in range(5):
        tf.add("map", "cam", k * 20 * MS, _rot_z(0.0, (0.02 * k, 0, 0)), static=False)
    tf.add("map", "cam", 580 * MS, _rot_z(0.0, (9.0, 0, 0)), static=False)  # the glitch
    with pytest.raises(TfWait, match="its newest"):
        tf.lookup("map", "cam", 90 * MS)
    tf.add("map", "cam", 100 * MS, _rot_z(0.0, (0.1, 0, 0)), static=False)  # the link's own next one
    assert tf.lookup("map", "cam", 90 * MS)[0, 3] == pytest.approx(0.09)
    with pytest.raises(TfWait):  # a hole after 100 ms, while the far one is the newest
        tf.lookup("map", "cam", 150 * MS)
    tf.add("map", "cam", 600 * MS, _rot_z(0.0, (0.6, 0, 0)), static=False)  # the link went on past it
    with pytest.raises(TfError, match="more than"):
        tf.lookup("map", "cam", 150 * MS)


def test_a_slow_link_is_interpolated_over_its_interval_and_a_hole_in_a_fast_one_refused() -> None:
    """A localisation's map -> odom at 1 Hz under odom -> base_link at 20 Hz (a robot's usual tree):
    lookups between two map -> odom transforms interpolate, as tf2 does; a hole of 0.5 s in the 20 Hz
    link is a gap."""
    tf = TfBuffer(max_gap_s=0.1)
    S = 1_000_000_000
    for k in range(6):  # map -> odom drifts 1 cm per second
        tf.add("map", "odom", k * S, _rot_z(0.0, (0.01 * k, 0, 0)), static=False)
    for k in range(101):
        if not 40 <= k < 50:  # odom -> base_link at 20 Hz, none from 2.0 s to 2.5 s
            tf.add("odom", "base_link", k * S // 20, _rot_z(0.0, (0.1 * k / 20, 0, 0)), static=False)
    T = tf.lookup("map", "base_link", 3 * S + S // 2)
    assert T[0, 3] == pytest.approx(0.035 + 0.35)
    with pytest.raises(TfError, match="odom -> base_link"):
        tf.lookup("map", "base_link", 2 * S + S // 4)


def _tf_only_copy(src: Path, dst: Path, *, static_rig: bool = False, relative_names: bool = False,
                  camera_frame: str = "{}_optical_frame") -> None:
    """The recording with its pose topics replaced by /tf (map -> odom static, odom -> base_link
    moving, from each sensor's poses) and /tf_static (the camera mounts on base_link). static_rig: no
    /tf, the base held in /tf_static where the first pose put it (a fixed rig: the frames are posed
    there); relative_names: topics recorded without their leading '/' ('tof/depth'); camera_frame: the
    cameras' frame names (format of the sensor's name), in the tree and the depth images' frame_id."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from senfunet_core.learning.sequences import _sensor_offset  # the rig: where each camera sits on it

    store = get_typestore(Stores.ROS2_JAZZY)
    T_ = store.types
    mounts = {s: T_BASE_OPTICAL @ _sensor_offset(s) for s in ("tof", "stereo")}  # T_base_optical per camera

    def transform(parent: str, child: str, stamp: object, T: np.ndarray) -> object:
        q = quat_from_matrix(T[:3, :3])
        return T_["geometry_msgs/msg/TransformStamped"](
            header=T_["std_msgs/msg/Header"](stamp=stamp, frame_id=parent), child_frame_id=child,
            transform=T_["geometry_msgs/msg/Transform"](
                translation=T_["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                rotation=T_["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))

    from senfunet_ros.geometry import transform_from_tq

    def T_odom_base(msg: object) -> tuple[object, np.ndarray]:  # a pose message's stamp and base (map = odom)
        pose = store.deserialize_cdr(msg.data, msg.msgtype)
        p, o = pose.pose.position, pose.pose.orientation
        T_world_cam = transform_from_tq([p.x, p.y, p.z], [o.x, o.y, o.z, o.w], "pose")
        return pose.header.stamp, T_world_cam @ invert_transform(mounts[msg.topic.split("/")[1]])

    TFMessage = T_["tf2_msgs/msg/TFMessage"]
    with open_bag(src) as reader, Writer(dst, version=9) as writer:
        first_base = next(T_odom_base(m)[1] for m in reader.messages() if m.topic.endswith("/pose"))
        conns = {}
        for msg in reader.messages():
            if msg.topic.endswith("/pose"):
                if static_rig:
                    continue
                stamp, T = T_odom_base(msg)
                topic, out = "/tf", TFMessage(transforms=[transform("odom", "base_link", stamp, T)])
            else:
                topic, out = msg.topic, None
            data = msg.data
            if msg.topic.endswith("/depth") and camera_frame != "{}_optical_frame":
                image = store.deserialize_cdr(msg.data, msg.msgtype)
                image.header.frame_id = camera_frame.format(msg.topic.split("/")[1])
                data = store.serialize_cdr(image, msg.msgtype)
            if "/tf_static" not in conns:  # latched mounts, recorded first
                stamp = T_["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
                held = [transform("odom", "base_link", stamp, first_base)] if static_rig else []
                static = TFMessage(transforms=[transform("map", "odom", stamp, np.eye(4))] + held + [
                    transform("base_link", camera_frame.format(s), stamp, mounts[s]) for s in mounts])
                conns["/tf_static"] = writer.add_connection("tf_static" if relative_names else "/tf_static",
                                                            "tf2_msgs/msg/TFMessage", typestore=store)
                writer.write(conns["/tf_static"], msg.log_time_ns - 1,
                             store.serialize_cdr(static, "tf2_msgs/msg/TFMessage"))
            if topic not in conns:
                msgtype = "tf2_msgs/msg/TFMessage" if out is not None else msg.msgtype
                recorded = topic.lstrip("/") if relative_names else topic
                conns[topic] = writer.add_connection(recorded, msgtype, typestore=store)
            data = store.serialize_cdr(out, "tf2_msgs/msg/TFMessage") if out is not None else data
            writer.write(conns[topic], msg.log_time_ns, data)


def test_tf_only_bag_replays_to_the_pose_topic_mesh(tmp_path: Path) -> None:
    from senfunet_core.learning import simulator as sim
    from senfunet_core.ply import read_ply

    seq = sim.simulate_sequence(sim.make_scene(7), 7, duration_s=1.0, width=128, height=128, tof_rate_hz=8,
                                stereo_rate_hz=8)
    poses_bag = write_sequence_bag(seq, tmp_path / "poses")
    tf_bag = tmp_path / "tf_only"
    _tf_only_copy(poses_bag, tf_bag)
    with open_bag(tf_bag) as reader:
        assert not any(t.endswith("/pose") for t in reader.topics) and {"/tf", "/tf_static"} <= set(reader.topics)
    params = tmp_path / "p.yaml"
    params.write_text(PARAMS)
    tf_params = tmp_path / "tf.yaml"
    tf_params.write_text(PARAMS + "    pose_type: tf\n")
    # the third: without the mounts the bag cannot be posed
    broken_params = _write(tmp_path / "b.yaml", PARAMS + "    pose_type: tf\n    fixed_frame: world\n")
    # in this process: three replay processes spent most of their time loading torch and the kernels
    ref, got, broken = (replay_in_process(bag, tmp_path / out, p) for bag, out, p in (
        (poses_bag, "ref", params), (tf_bag, "got", tf_params), (tf_bag, "broken", broken_params)))
    assert ref.returncode == 0, ref.stderr
    assert got.returncode == 0, got.stderr
    assert ref.stdout.splitlines()[:2] == got.stdout.splitlines()[:2]  # the same frames fused
    a, b = read_ply(tmp_path / "ref" / "mesh.ply"), read_ply(tmp_path / "got" / "mesh.ply")
    assert a.n_faces > 100
    # The same mesh up to interpolation: the base is interpolated, then the mount applied.
    assert abs(a.n_faces - b.n_faces) <= 0.01 * a.n_faces
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(a.vertices).query(b.vertices)
    assert np.quantile(distance, 0.99) < 0.002  # metres, at 4 cm voxels
    # without the mounts the bag cannot be posed: every frame is dropped, and replay says so
    assert broken.returncode == 2 and "no frame could be fused" in broken.stderr


def test_a_fixed_rigs_static_tree_and_topics_recorded_without_their_slash_replay_and_warnings_are_kept(
        tmp_path: Path) -> None:
    """A fixed rig whose whole tree is on /tf_static was refused ("no messages on /tf"); topics a recorder
    wrote as 'tof/depth' could not be named at all (the parameter became /tof/depth again); the pipeline's
    warnings (a camera frame that is no optical frame, a restart) never reached replay's output."""
    import json

    from senfunet_core.learning import simulator as sim

    seq = sim.simulate_sequence(sim.make_scene(7), 7, duration_s=0.5, width=96, height=96, tof_rate_hz=8,
                                stereo_rate_hz=8)
    poses_bag = write_sequence_bag(seq, tmp_path / "poses")
    variants = {"slashes": {}, "static": {"static_rig": True}, "relative": {"relative_names": True},
                "links": {"camera_frame": "{}_link"}}
    for name, options in variants.items():
        _tf_only_copy(poses_bag, tmp_path / name, **options)
    tf_params = _write(tmp_path / "tf.yaml", PARAMS + "    pose_type: tf\n")
    runs = {name: replay_in_process(tmp_path / name, tmp_path / f"out_{name}", tf_params) for name in variants}
    for name, run in runs.items():
        assert run.returncode == 0, (name, run.stderr)
    stats = {name: json.loads((tmp_path / f"out_{name}" / "stats.json").read_text()) for name in variants}
    for name in variants:
        fused = {s: c["integrated"] for s, c in stats[name]["sensors"].items()}
        assert fused == {s: c["received"] for s, c in stats[name]["sensors"].items()} and min(fused.values()) > 0
    assert ((tmp_path / "out_relative" / "mesh.ply").read_bytes()
            == (tmp_path / "out_slashes" / "mesh.ply").read_bytes())
    assert stats["slashes"]["warnings"] == [] and "optical" not in runs["slashes"].stderr
    (warning,) = [w for w in stats["links"]["warnings"] if "'tof_link'" in w]
    assert "tof.T_body_camera" in warning and "'tof_link'" in runs["links"].stderr


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_live_node_says_at_start_when_tf_is_unavailable(ros_domain_id: int) -> None:
    import importlib.util

    if importlib.util.find_spec("tf2_ros") or importlib.util.find_spec("tf2_msgs"):
        pytest.skip("a ROS 2 install with tf2 is sourced here")
    proc = subprocess.run([sys.executable, "-m", "senfunet_ros.cli", "node", "--", "--ros-args", "-p", "pose_type:=tf"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "cannot start" in proc.stderr and "tf2_ros" in proc.stderr and "Traceback" not in proc.stderr


def test_the_live_node_looks_poses_up_in_its_fixed_frame() -> None:
    """The node hands Ingest a TF lookup of its own (tf2's buffer): the lookups still go to the
    fixed_frame parameter, as replay's do, not to the default 'map' (a robot whose fixed frame is
    'odom' got no pose at all)."""
    from senfunet_ros import params as P

    values = {name: default for name, (default, _) in P.expanded_defaults().items()}
    values.update(pose_type="tf", fixed_frame="odom")
    settings = P.Settings.from_values(values)
    live = P.ingest_config(settings, **P.live_lag(settings), tf=TfBuffer())  # as the node builds it
    assert live.fixed_frame == "odom" and P.ingest_config(settings).fixed_frame == "odom"


def test_a_transform_stamped_far_ahead_is_left_out_and_does_not_cut_its_link() -> None:
    """One /tf transform from a publisher with a wrong clock: left out as bad_stamp, so that the
    frames after the link's last good transform wait for the next one instead of finding a gap."""
    from types import SimpleNamespace

    from test_ingest import depth_msg, info_msg

    from senfunet_ros.ingest import Ingest, IngestConfig

    def tf_msg(t_ns: int, x: float) -> SimpleNamespace:
        sec, nanosec = divmod(t_ns, 1_000_000_000)
        return SimpleNamespace(transforms=[SimpleNamespace(
            header=SimpleNamespace(frame_id="map", stamp=SimpleNamespace(sec=sec, nanosec=nanosec)),
            child_frame_id="cam", transform=SimpleNamespace(translation=SimpleNamespace(x=x, y=0.0, z=0.0),
                                                            rotation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0)))])

    def depth(t_ns: int):
        msg = depth_msg(t_ns)
        msg.header.frame_id = "cam"
        return msg

    MS = 1_000_000
    ingest = Ingest(IngestConfig(sensors=("tof", "stereo"), tf=TfBuffer(max_gap_s=0.1), fixed_frame="map"))
    ingest.add_camera_info("tof", info_msg())
    assert ingest.add_tf(tf_msg(10_000 * MS, 0.0), static=False) is None
    assert ingest.add_depth("tof", depth(10_000 * MS)) is None
    assert ingest.add_tf(tf_msg(1_010_000 * MS, 5.0), static=False) == "bad_stamp"  # 1000 s ahead
    assert ingest.add_depth("tof", depth(10_080 * MS)) is None
    assert [f.stamp_ns for f in ingest.pop_ready()] == [10_000 * MS]  # the second waits for its transform
    assert ingest.add_tf(tf_msg(10_100 * MS, 1.0), static=False) is None
    (frame,) = ingest.pop_ready()
    assert frame.stamp_ns == 10_080 * MS and frame.T_world_camera[0, 3] == pytest.approx(0.8)
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_stamp"] == 1 and "ahead" in counters["errors"]["bad_stamp"]
    # a publisher that leaves its stamps unset (0): each is left out as a bad stamp, not taken at 0 s, where
    # every next one was "another value for a stamp already given" (pose_conflict: "two publishers?")
    for x in (0.5, 0.6):
        assert ingest.add_tf(tf_msg(0, x), static=False) == "bad_stamp"
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_stamp"] == 3 and counters["dropped"]["pose_conflict"] == 0
    assert "map -> cam stamped 0 (unset) was left out" in counters["errors"]["bad_stamp"]
    # a frame that times out waiting for the link (at 10 Hz here, then silent) says where the link stands and
    # what to change: it said only "no transform map -> cam at or after ... yet"
    assert ingest.add_depth("tof", depth(10_150 * MS)) is None
    for t in (10_650, 11_200):  # stream time past pose_max_wait_s (1 s)
        assert ingest.add_depth("tof", depth(t * MS)) is None
    assert ingest.pop_ready() == []
    error = ingest.ledger.counters()["tof"]["errors"]["pose_timeout"]
    assert "no transform map -> cam at or after 10.150 s yet (its newest is at 10.100 s" in error, error
    assert "pose_max_wait_s (1 s)" in error and "a fixed_frame below it" in error, error
    assert counters["dropped"]["pose_gap"] == 0


def test_what_breaks_the_tree_is_refused_transform_by_transform_and_the_rest_kept() -> None:
    """A NaN transform, a frame as its own parent or ancestor, and a second parent for a live frame
    are refused with the frames named; the other transforms of their messages are kept. A frame
    whose parent fell silent may move to another; of static and dynamic on one link, the newest holds."""
    from types import SimpleNamespace

    from test_ingest import info_msg

    from senfunet_ros.ingest import Ingest, IngestConfig

    S = 1_000_000_000

    def transform(parent: str, child: str, t_ns: int, x: float) -> SimpleNamespace:
        sec, nanosec = divmod(t_ns, S)
        return SimpleNamespace(header=SimpleNamespace(frame_id=parent, stamp=SimpleNamespace(sec=sec, nanosec=nanosec)),
                               child_frame_id=child, transform=SimpleNamespace(
                                   translation=SimpleNamespace(x=x, y=0.0, z=0.0),
                                   rotation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0)))

    tf = TfBuffer(max_gap_s=0.1)
    ingest = Ingest(IngestConfig(sensors=("tof",), tf=tf, fixed_frame="map"))
    ingest.add_camera_info("tof", info_msg())
    mixed = [transform("base", "cam2", 0, 0.2), transform("odom", "x", 0, float("nan")),
             transform("base", "cam3", 0, 0.3), transform("cam3", "cam3", 0, 0.0), transform("cam3", "base", 0, 0.0),
             transform("map", "base", 0, 1.0)]
    assert ingest.add_tf(SimpleNamespace(transforms=mixed), static=True) == "bad_pose"
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_pose"] == 3 and "odom -> x" in counters["errors"]["bad_pose"]
    assert tf.lookup("map", "cam3", 5 * S)[0, 3] == pytest.approx(1.3)  # kept: after the NaN, before the cycle
    assert tf.lookup("map", "cam2", 5 * S)[0, 3] == pytest.approx(1.2)
    with pytest.raises(ValueError, match="own parent"):
        tf.add("cam2", "cam2", 0, np.eye(4), static=True)
    with pytest.raises(ValueError, match="own ancestor"):
        tf.add("cam2", "map", 0, np.eye(4), static=True)
    # two publishers of one frame: the second parent is refused while the first is alive
    for k in range(10):
        tf.add("map", "arm", k * S // 30, _rot_z(0.0, (0.5, 0, 0)), static=False)
        with pytest.raises(ValueError, match="'arm' has two parents, 'map' and 'rig'"):
            tf.add("rig", "arm", k * S // 30 + S // 60, np.eye(4), static=False)
    assert tf.lookup("map", "arm", S // 4)[0, 3] == pytest.approx(0.5)
    # nor may a static transform take a frame from its live parent (it did, and the frames were fused
    # at the static chain's pose without a word: a URDF and a static_transform_publisher both placing
    # the camera, or a static base_footprint -> base_link beside the odometry's odom -> base_link)
    with pytest.raises(ValueError, match="'arm' has two parents, 'map' and 'rig' \\(static rig -> arm came second"):
        tf.add("rig", "arm", 0, np.eye(4), static=True)
    assert tf.lookup("map", "arm", S // 4)[0, 3] == pytest.approx(0.5)
    tf.add("mast", "camera", 0, _rot_z(0.0, (0, 0, 0.4)), static=True)
    with pytest.raises(ValueError, match="'camera' has two parents, 'mast' and 'base'"):
        tf.add("base", "camera", 0, np.eye(4), static=True)
    tf.add("map", "mast", 0, np.eye(4), static=True)
    assert tf.lookup("map", "camera", 0)[2, 3] == pytest.approx(0.4)
    tf.add("rig", "arm", 3 * S, np.eye(4), static=False)  # its parent silent for 2.7 s: it moved
    tf.add("map", "rig", 0, _rot_z(0.0, (0, 2, 0)), static=True)
    assert tf.lookup("map", "arm", 3 * S)[1, 3] == pytest.approx(2.0)
    # static, then dynamic on the same link: the dynamic transforms hold from then on, and back
    tf.add("map", "mast", 0, _rot_z(0.0, (1, 0, 0)), static=True)
    for k in range(3):
        tf.add("map", "mast", 4 * S + k * S // 30, _rot_z(0.0, (2, 0, 0)), static=False)
    assert tf.lookup("map", "mast", 4 * S + S // 60)[0, 3] == pytest.approx(2.0)
    tf.add("map", "mast", 0, _rot_z(0.0, (3, 0, 0)), static=True)
    assert tf.lookup("map", "mast", 9 * S)[0, 3] == pytest.approx(3.0)
    # a map hung off a UTM frame thousands of km away (a GPS-aided robot): a link, not a pose
    far = [transform("utm", "map", 0, 4.5e6), transform("map", "rover", 0, 2.0)]
    assert ingest.add_tf(SimpleNamespace(transforms=far), static=True) is None
    assert tf.lookup("map", "rover", 0)[0, 3] == pytest.approx(2.0)
    assert ingest.ledger.counters()["tof"]["dropped"]["bad_pose"] == 3


def test_a_slow_link_is_interpolated_from_its_second_transform() -> None:
    """map -> odom at 1 Hz: a lookup between its first two transforms interpolates (the interval
    of two transforms is the link's rate), before it waits for the second."""
    tf = TfBuffer(max_gap_s=0.1)
    S = 1_000_000_000
    tf.add("map", "odom", 0, _rot_z(0.0, (0.0, 0, 0)), static=False)
    for k in range(0, 60):
        tf.add("odom", "base", k * S // 50, np.eye(4), static=False)
    with pytest.raises(TfWait):
        tf.lookup("map", "base", S // 2)
    tf.add("map", "odom", S, _rot_z(0.0, (0.1, 0, 0)), static=False)
    assert tf.lookup("map", "base", S // 2)[0, 3] == pytest.approx(0.05)


def test_tf2_lookups_take_a_leading_slash_and_an_invalid_frame_drops_one_frame() -> None:
    """With tf2_ros (a sourced ROS 2 install), a depth image whose frame_id starts with '/' (a ROS 1
    habit of some drivers) or is empty made tf2 raise InvalidArgumentException out of pop_ready: every
    integration tick failed on that frame and the frames behind it were never posed. tf2 strips a
    leading '/' from the transforms it is sent; the lookup strips it too, and an empty frame_id drops
    its frame (pose_gap, saying what to fix)."""
    from types import SimpleNamespace

    from test_ingest import depth_msg, info_msg

    from senfunet_ros.ingest import Ingest, IngestConfig
    from senfunet_ros.node import _Tf2Lookup

    class TransformException(Exception):  # tf2_py's hierarchy
        pass

    class InvalidArgumentException(TransformException):
        pass

    class LookupException(TransformException):
        pass

    tf2_ros = SimpleNamespace(TransformException=TransformException, InvalidArgumentException=InvalidArgumentException,
                              LookupException=LookupException,
                              ConnectivityException=type("ConnectivityException", (TransformException,), {}),
                              ExtrapolationException=type("ExtrapolationException", (TransformException,), {}))

    class Buffer:  # tf2_ros.Buffer as tf2 validates frame ids: "map" -> "cam" known at any time
        def lookup_transform(self, target: str, source: str, time: object) -> object:
            for frame in (target, source):
                if not frame or frame.startswith("/"):
                    raise InvalidArgumentException(f'Invalid argument "{frame}" passed to lookupTransform: tf2 '
                                                   "frame_ids cannot start with a '/'")
            if (target, source) != ("map", "cam"):
                raise LookupException(f'"{source}" passed to lookupTransform argument source_frame does not exist.')
            zero = SimpleNamespace(x=0.0, y=0.0, z=0.0)
            return SimpleNamespace(transform=SimpleNamespace(translation=SimpleNamespace(x=1.0, y=0.0, z=0.0),
                                                             rotation=SimpleNamespace(**vars(zero), w=1.0)))

    MS = 1_000_000
    ingest = Ingest(IngestConfig(sensors=("tof",), tf=_Tf2Lookup(Buffer(), tf2_ros), fixed_frame="/map"))
    ingest.add_camera_info("tof", info_msg())
    for k, frame_id in enumerate(("/cam", "", "cam")):
        msg = depth_msg(10_000 * MS + k * 50 * MS)
        msg.header.frame_id = frame_id
        assert ingest.add_depth("tof", msg) is None
    frames = ingest.pop_ready()
    assert [f.stamp_ns for f in frames] == [10_000 * MS, 10_100 * MS]
    assert all(f.T_world_camera[0, 3] == pytest.approx(1.0) for f in frames)
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["pose_gap"] == 1 and "no header.frame_id" in counters["errors"]["pose_gap"]


def test_t_body_camera_corrects_an_image_frame_id_that_is_not_the_optical_frame() -> None:
    """A driver whose depth images name camera_link (x forward) instead of its optical frame (z forward):
    with pose_type tf, T_body_camera was ignored (applied to pose topics only), so there was no way to
    tell the node, and every frame was integrated turned by 90 degrees. It applies to TF lookups too."""
    from test_ingest import depth_msg, info_msg

    from senfunet_ros.geometry import transform_from_tq
    from senfunet_ros.ingest import Ingest, IngestConfig

    S = 1_000_000_000
    T_link_optical = transform_from_tq([0, 0, 0], [-0.5, 0.5, -0.5, 0.5], "camera_link -> optical")
    tf = TfBuffer()
    tf.add("map", "base_link", 0, _rot_z(0.3, (1.0, 2.0, 0.0)), static=True)
    tf.add("base_link", "camera_link", 0, _rot_z(0.0, (0.1, 0.0, 0.5)), static=True)
    tf.add("camera_link", "camera_depth_optical_frame", 0, T_link_optical, static=True)
    truth = tf.lookup("map", "camera_depth_optical_frame", 10 * S)
    for frame_id, extrinsic in (("camera_depth_optical_frame", {}), ("camera_link", {"tof": T_link_optical})):
        ingest = Ingest(IngestConfig(sensors=("tof",), tf=tf, fixed_frame="map", T_body_camera=extrinsic))
        ingest.add_camera_info("tof", info_msg())
        msg = depth_msg(10 * S)
        msg.header.frame_id = frame_id
        ingest.add_depth("tof", msg)
        (frame,) = ingest.pop_ready()
        assert np.abs(frame.T_world_camera - truth).max() < 1e-9, frame_id


def test_tf_that_goes_on_while_the_camera_pauses_is_kept() -> None:
    """The camera driver pauses for 2 s while the robot drives on and /tf goes on at 50 Hz. Each /tf
    transform more than time_jump_s ahead of the images' newest stamp was left out as bad_stamp ("check
    the clock of its publisher"), so once the camera resumed its frames found a 2 s hole in odom ->
    base_link and were dropped as pose_gap. A transform is judged against TF's own newest stamp too:
    a stray far ahead is still left out."""
    from types import SimpleNamespace

    from test_ingest import depth_msg, info_msg

    from senfunet_ros.ingest import Ingest, IngestConfig

    S, MS = 1_000_000_000, 1_000_000

    def tf_msg(t_ns: int, x: float) -> SimpleNamespace:
        sec, nanosec = divmod(t_ns, S)
        return SimpleNamespace(transforms=[SimpleNamespace(
            header=SimpleNamespace(frame_id="odom", stamp=SimpleNamespace(sec=sec, nanosec=nanosec)),
            child_frame_id="base_link", transform=SimpleNamespace(
                translation=SimpleNamespace(x=x, y=0.0, z=0.0), rotation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0)))])

    tf = TfBuffer(max_gap_s=0.1)
    tf.add("base_link", "cam", 0, np.eye(4), static=True)
    ingest = Ingest(IngestConfig(sensors=("tof",), tf=tf, fixed_frame="odom"))
    ingest.add_camera_info("tof", info_msg())
    posed = []
    for k in range(250):  # 5 s of /tf at 50 Hz, 0.1 m/s; images at 10 Hz but none from 1 s to 3 s
        t_ns = 10 * S + k * 20 * MS
        ingest.add_tf(tf_msg(t_ns, 0.1 * k * 0.02), static=False)
        if k % 5 == 1 and not 50 <= k < 150:
            msg = depth_msg(t_ns + 5 * MS)
            msg.header.frame_id = "cam"
            ingest.add_depth("tof", msg)
        posed += ingest.pop_ready()
    assert ingest.add_tf(tf_msg(1000 * S, 9.0), static=False) == "bad_stamp"  # a stray is still left out
    counters = ingest.ledger.counters()["tof"]
    assert {r: n for r, n in counters["dropped"].items() if n} == {"bad_stamp": 1}, counters["errors"]
    assert len(posed) == counters["received"] == 30
    for frame in posed:
        assert frame.T_world_camera[0, 3] == pytest.approx(0.1 * (frame.stamp_ns - 10 * S) / S, abs=1e-6)


def test_an_image_frame_id_that_is_not_an_optical_frame_is_warned_about_once() -> None:
    """With pose_type tf, depth images naming camera_link (x forward) are posed turned by 90 degrees
    unless T_body_camera turns them: the pipeline says so, once per sensor, naming the fix; not for
    an optical frame, nor once T_body_camera is set, nor with pose topics."""
    from test_ingest import depth_msg

    from senfunet_ros.ingest import Ingest, IngestConfig
    from senfunet_ros.pipeline import Pipeline

    def warnings(frame_id: str, **config) -> list[str]:
        lines: list[str] = []
        pipeline = Pipeline(None, Ingest(IngestConfig(sensors=("tof",), **config)),
                            log=lambda level, text: lines.append(text) if level == "warning" else None)
        for t in (1, 2):
            msg = depth_msg(t * 1_000_000)
            msg.header.frame_id = frame_id
            pipeline.dispatch("tof", "depth", msg)
        return lines

    (line,) = warnings("camera_link", tf=TfBuffer())
    assert "'camera_link'" in line and "tof.T_body_camera" in line and "-0.5 0.5 -0.5 0.5" in line
    assert warnings("camera_depth_optical_frame", tf=TfBuffer()) == []
    assert warnings("camera_link", tf=TfBuffer(), T_body_camera={"tof": np.eye(4)}) == []
    assert warnings("camera_link") == []


class _Tf2OverTfBuffer:
    """tf2_ros.Buffer's answers (what `_Tf2Lookup` reads of them) from a TfBuffer: tf2_ros is not in the
    test environment. A lookup at Time() (0) gives the latest common transform, stamped; a stamp past
    it raises ExtrapolationException ("... into the future")."""

    class TransformException(Exception):
        pass

    class ExtrapolationException(TransformException):
        pass

    LookupException = ConnectivityException = TransformException

    def __init__(self, tf: TfBuffer) -> None:
        self.tf = tf

    def lookup_transform(self, target: str, source: str, time: object):  # noqa: ANN201 (a message)
        from types import SimpleNamespace

        stamp_ns = time.nanoseconds or self.tf.newest_common_ns(target, source)  # type: ignore[attr-defined]
        try:
            T = self.tf.lookup(target, source, stamp_ns)
        except TfWait as err:
            raise self.ExtrapolationException(f"Lookup would require extrapolation into the future: {err}") from None
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        q = quat_from_matrix(T[:3, :3])
        return SimpleNamespace(
            header=SimpleNamespace(stamp=SimpleNamespace(sec=sec, nanosec=nanosec)),
            transform=SimpleNamespace(translation=SimpleNamespace(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                                      rotation=SimpleNamespace(x=q[0], y=q[1], z=q[2], w=q[3])))


@pytest.mark.parametrize("lookup", ["own buffer", "tf2"])
def test_at_the_end_of_a_stream_a_frame_past_the_newest_transform_is_posed_by_extrapolation(lookup: str) -> None:
    """With poses from TF, the frames after the newest transform were always dropped as pose_timeout at
    a stream's end (the lookups do not extrapolate). As with pose topics, one within pose_tolerance_s
    past the newest stamp its transforms share is now posed by continuing their motion at constant
    velocity (counted as extrapolated); one further is dropped as pose_timeout."""
    from test_ingest import depth_msg, info_msg

    from senfunet_ros.ingest import Ingest, IngestConfig
    from senfunet_ros.node import _Tf2Lookup

    MS = 1_000_000
    t0_ns = 10_000 * MS
    speed_m_s, turn_rad_s = 0.5, 1.0  # constant velocity: the extrapolation is exact
    buffer = TfBuffer(max_gap_s=0.1)
    buffer.add("base", "cam", 0, _rot_z(0.0, (0.0, 0.0, 0.5)), static=True)
    for k in range(11):  # map -> base at 100 Hz for 100 ms
        t_s = 0.01 * k
        buffer.add("map", "base", t0_ns + 10 * k * MS, _rot_z(turn_rad_s * t_s, (speed_m_s * t_s, 0, 0)), static=False)
    if lookup == "tf2":
        tf2 = _Tf2OverTfBuffer(buffer)
        tf = _Tf2Lookup(tf2, tf2)
    else:
        tf = buffer
    assert tf.newest_common_ns("map", "cam") == t0_ns + 100 * MS
    ingest = Ingest(IngestConfig(sensors=("tof",), tf=tf, fixed_frame="map", pose_tolerance_s=0.1))
    ingest.add_camera_info("tof", info_msg())
    for past_ms in (30, 150):  # 150 ms: beyond pose_tolerance_s
        msg = depth_msg(t0_ns + (100 + past_ms) * MS)
        msg.header.frame_id = "cam"
        assert ingest.add_depth("tof", msg) is None
    assert ingest.pop_ready() == [] and ingest.ledger.queue_depths()["tof"] == 2  # waiting for transforms
    ingest.stream_ends.end()
    (frame,) = ingest.pop_ready()
    assert frame.stamp_ns == t0_ns + 130 * MS
    T = frame.T_world_camera
    assert np.linalg.norm(T[:3, 3] - [speed_m_s * 0.13, 0, 0.5]) < 1e-3  # right to 1 mm
    assert math.atan2(T[1, 0], T[0, 0]) == pytest.approx(turn_rad_s * 0.13, abs=1e-6)
    counters = ingest.ledger.counters()["tof"]
    assert counters["extrapolated"] == 1 and counters["dropped"]["pose_timeout"] == 1
    assert "150 ms past the newest pose" in counters["errors"]["pose_timeout"]
    (end,) = ingest.stream_ends.take().values()
    assert (end.extrapolated, end.timed_out) == (1, 1)


def test_newest_common_stamp_is_the_oldest_newest_of_the_dynamic_links() -> None:
    """Between two frames, the newest stamp every dynamic link has a transform for; None for frames
    not connected or linked by static transforms alone."""
    tf = TfBuffer(max_gap_s=0.1)
    tf.add("map", "odom", 5, np.eye(4), static=False)
    tf.add("odom", "base", 9, np.eye(4), static=False)
    tf.add("base", "cam", 0, np.eye(4), static=True)
    tf.add("base", "lidar", 0, np.eye(4), static=True)
    assert tf.newest_common_ns("map", "cam") == 5
    assert tf.newest_common_ns("odom", "/cam") == 9
    assert tf.newest_common_ns("lidar", "cam") is None  # static alone: a lookup holds at any stamp
    assert tf.newest_common_ns("map", "elsewhere") is None


def test_a_frame_whose_camera_is_not_in_the_tree_at_a_streams_end_says_so() -> None:
    """A bag with /tf but without /tf_static (the recording started after the mounts were latched): at the
    stream's end every frame was dropped with "no pose had come at all", though /tf held transforms. The
    error now says what the lookup found: the camera's frame not connected, and the chains known."""
    from test_ingest import depth_msg, info_msg

    from senfunet_ros.ingest import Ingest, IngestConfig

    MS = 1_000_000
    buffer = TfBuffer(max_gap_s=0.1)
    for k in range(11):  # map -> base at 100 Hz, no base -> cam
        buffer.add("map", "base", 10_000 * MS + 10 * k * MS, _rot_z(0.0, (0.01 * k, 0, 0)), static=False)
    ingest = Ingest(IngestConfig(sensors=("tof",), tf=buffer, fixed_frame="map"))
    ingest.add_camera_info("tof", info_msg())
    msg = depth_msg(10_050 * MS)
    msg.header.frame_id = "cam"
    assert ingest.add_depth("tof", msg) is None
    ingest.stream_ends.end()
    assert ingest.pop_ready() == []
    error = ingest.ledger.counters()["tof"]["errors"]["pose_timeout"]
    assert "no pose had come at all" not in error and "tf: no transform path" in error, error


def test_a_camera_the_tree_does_not_join_for_pose_max_wait_s_is_not_blamed_on_a_slow_link() -> None:
    """A camera whose static transforms come late (a robot_state_publisher started after the drivers):
    its frames that waited pose_max_wait_s were dropped with advice for a slow localiser link; the
    error now says no transforms joined the frames."""
    from test_ingest import depth_msg, info_msg

    from senfunet_ros.ingest import Ingest, IngestConfig

    MS = 1_000_000
    buffer = TfBuffer(max_gap_s=0.1)
    ingest = Ingest(IngestConfig(sensors=("tof",), tf=buffer, fixed_frame="map", pose_max_wait_s=0.5))
    ingest.add_camera_info("tof", info_msg())
    for k in range(150):  # map -> base at 100 Hz for 1.5 s, a frame every 100 ms, no base -> cam
        buffer.add("map", "base", 10_000 * MS + 10 * k * MS, _rot_z(0.0, (0.01 * k, 0, 0)), static=False)
        if k % 10 == 5:
            msg = depth_msg(10_000 * MS + 10 * k * MS)
            msg.header.frame_id = "cam"
            assert ingest.add_depth("tof", msg) is None
            assert ingest.pop_ready() == []
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["pose_timeout"] >= 5, counters
    error = counters["errors"]["pose_timeout"]
    assert "for transforms that join the two frames: they came later than that or not at all" in error, error
    assert "a link published less often" not in error


@pytest.mark.parametrize("step_s", [3, -3])
def test_transforms_of_a_clock_that_stepped_are_taken_once_the_images_confirm_it(step_s: int) -> None:
    """The robot's clock steps 3 s ahead (chrony's makestep) or back: /tf comes on the new time before the
    images confirm it. Ahead, every such transform was left out for good as bad_stamp, with the frames
    needing them (0.7 s of frames in a recorded case); back, they were cleared with the old time's (0.55 s
    of frames). They are now held and taken with the confirmed restart; a stray far ahead stays out."""
    from test_ingest import depth_msg, info_msg

    from senfunet_ros.ingest import Frame, Ingest, IngestConfig

    S, MS = 1_000_000_000, 1_000_000
    ingest = Ingest(IngestConfig(sensors=("tof",), tf=TfBuffer(max_gap_s=0.1), fixed_frame="map", time_jump_s=1.0,
                                 restart_confirm_msgs=5, restart_confirm_s=0.5))
    ingest.add_camera_info("tof", info_msg())
    stray = _tf_message(10 * S + 60 * S, 0.0)  # a glitch, a minute ahead
    posed = []
    stepped = set()
    for k in range(200):  # /tf at 100 Hz, an image every 50 ms, the clock stepped from 1 s on
        t_ns = 10 * S + k * 10 * MS + (step_s * S if k >= 100 else 0)
        ingest.add_tf(_tf_message(t_ns, 0.01 * k), static=False)
        if k == 150:
            ingest.add_tf(stray, static=False)
        if k % 5 == 2:
            msg = depth_msg(t_ns)
            msg.header.frame_id = "cam"
            ingest.add_depth("tof", msg)
            stepped |= {t_ns} if k >= 100 else set()
        posed += [frame.stamp_ns for frame in ingest.pop_ready() if isinstance(frame, Frame)]
    after_step = stepped & set(posed)
    assert len(after_step) >= 18, (len(after_step), ingest.ledger.counters()["tof"])  # 20 images after the step
    counters = ingest.ledger.counters()["tof"]
    assert counters["dropped"]["bad_stamp"] == 1, counters  # the stray alone


def _tf_message(t_ns: int, x: float) -> Any:
    """A TFMessage (duck-typed) of map -> cam at t_ns, x metres along x."""
    from types import SimpleNamespace

    sec, nanosec = divmod(t_ns, 1_000_000_000)
    return SimpleNamespace(transforms=[SimpleNamespace(
        header=SimpleNamespace(frame_id="map", stamp=SimpleNamespace(sec=sec, nanosec=nanosec)), child_frame_id="cam",
        transform=SimpleNamespace(translation=SimpleNamespace(x=x, y=0.0, z=0.0),
                                  rotation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0)))])


def test_a_link_that_jumps_is_not_interpolated_across_the_jump() -> None:
    """A localiser relocalising: map -> odom jumps 2 m between two of its transforms. The frames between
    them were posed on a smear between the old and the new place (up to 1.9 m off at 1 Hz) without a
    word; they are now refused as a gap that names the jump. Smooth motion, even fast, is interpolated."""
    tf = TfBuffer(max_gap_s=0.5)
    S = 1_000_000_000
    tf.add("odom", "cam", 0, np.eye(4), static=True)
    for k in range(31):  # 10 Hz: still, then 2 m further at 2.1 s
        tf.add("map", "odom", 10 * S + k * S // 10, _rot_z(0.0, (2.0 if k >= 21 else 0.0, 0, 0)), static=False)
    assert tf.lookup("map", "cam", 10 * S + 195 * S // 100)[0, 3] == pytest.approx(0.0)
    with pytest.raises(TfError, match=r"map -> odom jumped 2.00 m, 0.0 deg between its transforms at 12.000 s and "
                                      r"12.100 s \(a localiser relocalising\?\)"):
        tf.lookup("map", "cam", 10 * S + 205 * S // 100)
    assert tf.lookup("map", "cam", 10 * S + 215 * S // 100)[0, 3] == pytest.approx(2.0)
    for k in range(31):  # 10 Hz at 3 m/s: 0.3 m a step, every step
        tf.add("map", "fast", 10 * S + k * S // 10, _rot_z(0.0, (0.3 * k, 0, 0)), static=False)
    assert tf.lookup("map", "fast", 10 * S + 205 * S // 100)[0, 3] == pytest.approx(6.15)


def test_two_publishers_of_one_link_interleaved_are_noted() -> None:
    """An EKF and raw odometry both publishing odom -> base_link, 10 cm apart and interleaved: every frame
    was posed between the two (the mesh 5 cm off) with nothing said; pose topics said so (pose_alternates).
    One publisher moving fast is no such thing."""
    from types import SimpleNamespace

    from senfunet_ros.ingest import Ingest, IngestConfig

    def tf_msg(t_ns: int, x: float) -> SimpleNamespace:
        sec, nanosec = divmod(t_ns, 1_000_000_000)
        return SimpleNamespace(transforms=[SimpleNamespace(
            header=SimpleNamespace(frame_id="odom", stamp=SimpleNamespace(sec=sec, nanosec=nanosec)),
            child_frame_id="base_link", transform=SimpleNamespace(
                translation=SimpleNamespace(x=x, y=0.0, z=0.0), rotation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0)))])

    def notes_after(xs: list[float]) -> dict[str, str]:
        ingest = Ingest(IngestConfig(sensors=("tof", "stereo"), tf=TfBuffer(max_gap_s=0.1), fixed_frame="odom"))
        for k, x in enumerate(xs):
            assert ingest.add_tf(tf_msg(10 * S + k * 10 * MS, x), static=False) is None
        return ingest.ledger.counters()["tof"]["notes"]

    S, MS = 1_000_000_000, 1_000_000
    note = notes_after([0.005 * k + (0.1 if k % 2 else 0.0) for k in range(40)]).get("tf_alternates", "")
    assert "odom -> base_link zig-zags by about 10 cm" in note and "two publishers" in note, note
    assert "tf_alternates" not in notes_after([0.03 * k for k in range(40)])  # 3 m/s at 100 Hz: one publisher
