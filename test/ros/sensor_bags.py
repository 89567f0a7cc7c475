"""Small bags of sensor set-ups other than the sample's, written with rosbags: a known scene (a wall
facing the cameras, a box in front of it) seen by two depth cameras whose image size, intrinsics,
encodings, camera_info and rates are each chosen, so that a test can replay them and check the
mesh lies where the scene's surfaces are."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

START_NS = 1_700_000_000 * 1_000_000_000
WALL_Z_M = 2.0  # the wall: the plane z = WALL_Z_M of the map, facing the cameras
BOX_MIN_M = np.array([-0.3, -0.3, 1.4])  # an axis-aligned box in front of it
BOX_MAX_M = np.array([0.3, 0.3, 1.7])


@dataclass(frozen=True)
class Camera:
    """One sensor's set-up: what its driver publishes."""

    name: str
    width: int = 96
    height: int = 72
    fx: float = 60.0
    fy: float = 60.0
    cx: float | None = None  # None: the image centre
    cy: float | None = None
    rate_hz: float = 10.0
    encoding: str = "32FC1"  # 32FC1 | 16UC1 | mono16
    bigendian: bool = False
    row_padding_b: int = 0  # step = width * bytes + this
    color: str = ""  # colour encoding (rgb8, bgr8, mono8, rgba8, bgra8), "" = none
    color_size: tuple[int, int] | None = None  # (width, height) of the colour image; None: the depth's
    info_size: tuple[int, int] | None = None  # (width, height) camera_info says; None: the depth's
    info_k: tuple[float, ...] | None = None  # K camera_info says (row-major 9); None: from fx, fy, cx, cy
    distortion_model: str = "plumb_bob"
    d: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    depth_offset_m: float = 0.0  # added to every depth (a negative value makes negative depths)
    x_m: float = 0.0  # the camera's position along x (a stereo pair's second camera, say)

    def K(self) -> np.ndarray:
        cx = (self.width - 1) / 2 if self.cx is None else self.cx
        cy = (self.height - 1) / 2 if self.cy is None else self.cy
        return np.array([[self.fx, 0.0, cx], [0.0, self.fy, cy], [0.0, 0.0, 1.0]])


def depth_of_scene(K: np.ndarray, width: int, height: int, T_world_camera: np.ndarray) -> np.ndarray:
    """z-depth (H, W) float64 of the wall and box, as seen by a camera looking along the map's +z
    (rotation identity: the optical frame's axes are the map's), from T_world_camera's position."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)  # z = 1
    origin = T_world_camera[:3, 3]
    depth = np.full((height, width), WALL_Z_M - origin[2])
    # the box: slab intersection along each ray (t is the z-depth, as the rays have z = 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (BOX_MIN_M - origin) / rays
        t1 = (BOX_MAX_M - origin) / rays
    near = np.nanmax(np.minimum(t0, t1), axis=-1)
    far = np.nanmin(np.maximum(t0, t1), axis=-1)
    hit = (near <= far) & (near > 0)
    depth[hit] = near[hit]
    return depth


def surface_distance_m(points: np.ndarray) -> np.ndarray:
    """Distance of each point (N, 3) to the scene's surfaces (the wall and the box's faces)."""
    wall = np.abs(points[:, 2] - WALL_Z_M)
    outside = np.maximum(np.maximum(BOX_MIN_M - points, points - BOX_MAX_M), 0.0)
    inside = np.minimum(points - BOX_MIN_M, BOX_MAX_M - points).min(axis=1)
    box = np.where(np.any(outside > 0, axis=1), np.linalg.norm(outside, axis=1), inside)
    return np.minimum(wall, box)


@dataclass(frozen=True)
class Recording:
    cameras: tuple[Camera, ...]
    duration_s: float = 0.5
    pose_rate_hz: float = 50.0
    topics: dict[str, str] = field(default_factory=dict)  # "<sensor>/<stream>" -> topic; default /<sensor>/<stream>

    def topic(self, sensor: str, stream: str) -> str:
        return self.topics.get(f"{sensor}/{stream}", f"/{sensor}/{stream}")


def _pose(camera: Camera, stamp_s: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (camera.x_m + 0.1 * stamp_s, 0.02 * stamp_s, 0.0)  # a slow drift to the right
    return T


def _depth_payload(camera: Camera, depth_m: np.ndarray) -> tuple[np.ndarray, int]:
    """The image's data (uint8) and step."""
    order = ">" if camera.bigendian else "<"
    if camera.encoding == "32FC1":
        raw = depth_m.astype(order + "f4")
    else:
        raw = np.clip(np.rint(depth_m * 1000.0), 0, 65535).astype(order + "u2")
    rows = raw.view(np.uint8).reshape(camera.height, -1)
    if camera.row_padding_b:
        rows = np.concatenate([rows, np.full((camera.height, camera.row_padding_b), 0xAB, np.uint8)], axis=1)
    return np.ascontiguousarray(rows).reshape(-1), rows.shape[1]


def _color_payload(camera: Camera) -> tuple[np.ndarray, int, int, int]:
    width, height = camera.color_size or (camera.width, camera.height)
    channels = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}[camera.color]
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    pixels = np.stack([(u * 7 + v * 3) % 256] * channels, axis=-1).astype(np.uint8)
    return pixels.reshape(-1), width * channels, width, height


def write_bag(recording: Recording, path: Path) -> Path:
    """The recording as an mcap rosbag2 folder: per camera its depth (and colour) images and a
    camera_info at its rate, and its poses (PoseStamped, the optical frame in map) at pose_rate_hz."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    T = store.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Image, CameraInfo, Roi = T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/CameraInfo"], \
        T["sensor_msgs/msg/RegionOfInterest"]
    PoseStamped, Pose = T["geometry_msgs/msg/PoseStamped"], T["geometry_msgs/msg/Pose"]
    Point, Quaternion = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]

    def header(stamp_ns: int, frame_id: str) -> Any:
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        return Header(stamp=Time(sec=sec, nanosec=nanosec), frame_id=frame_id)

    pending: list[tuple[int, str, str, Any]] = []
    for i, camera in enumerate(recording.cameras):
        frame_id = f"{camera.name}_optical_frame"
        for stamp_s in np.arange(0.0, recording.duration_s + 0.1, 1.0 / recording.pose_rate_hz) - 0.05:
            stamp = START_NS + int(round(stamp_s * 1e9)) + 100_000 * i
            t = _pose(camera, stamp_s)[:3, 3]
            pending.append((stamp, recording.topic(camera.name, "pose"), "geometry_msgs/msg/PoseStamped",
                            PoseStamped(header=header(stamp, "map"), pose=Pose(
                                position=Point(x=t[0], y=t[1], z=t[2]),
                                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)))))
        K = camera.K()
        info_size = camera.info_size or (camera.width, camera.height)
        info_k = np.asarray(camera.info_k if camera.info_k is not None else K.reshape(-1), np.float64)
        phase_s = 0.013 + 0.007 * i  # the sensors' stamps never coincide
        for stamp_s in np.arange(phase_s, recording.duration_s, 1.0 / camera.rate_hz):
            stamp = START_NS + int(round(stamp_s * 1e9))
            depth = depth_of_scene(K, camera.width, camera.height, _pose(camera, stamp_s)) + camera.depth_offset_m
            data, step = _depth_payload(camera, depth)
            pending.append((stamp + 3_000_000, recording.topic(camera.name, "depth"), "sensor_msgs/msg/Image",
                            Image(header=header(stamp, frame_id), height=camera.height, width=camera.width,
                                  encoding=camera.encoding, is_bigendian=int(camera.bigendian), step=step,
                                  data=data)))
            pending.append((stamp + 1_000_000, recording.topic(camera.name, "camera_info"),
                            "sensor_msgs/msg/CameraInfo",
                            CameraInfo(header=header(stamp, frame_id), height=info_size[1], width=info_size[0],
                                       distortion_model=camera.distortion_model, d=np.asarray(camera.d, np.float64),
                                       k=info_k, r=np.eye(3).reshape(-1), p=np.zeros(12), binning_x=0, binning_y=0,
                                       roi=Roi(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))))
            if camera.color:
                data, step, width, height = _color_payload(camera)
                pending.append((stamp + 2_000_000, recording.topic(camera.name, "color"), "sensor_msgs/msg/Image",
                                Image(header=header(stamp, frame_id), height=height, width=width,
                                      encoding=camera.color, is_bigendian=0, step=step, data=data)))
    pending.sort(key=lambda item: item[0])
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    connections: dict[str, Any] = {}
    last_ns = -1
    with writer:
        for log_ns, topic, msgtype, msg in pending:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=store)
            last_ns = log_ns = max(log_ns, last_ns + 1)
            writer.write(connections[topic], log_ns, store.serialize_cdr(msg, msgtype))
    return path


def params_file(path: Path, recording: Recording, **values: Any) -> Path:
    """A parameter file for the recording's cameras (names, topics) with `values` on top."""
    import yaml

    names = [camera.name for camera in recording.cameras]
    # the shipped weights: the second sensor's feature net takes colour
    params: dict[str, Any] = {"sensors": names, "rgb_sensors": names[1:],
                              "weights": "default", "working_width": 0}
    for camera in recording.cameras:
        for stream in ("depth", "color", "camera_info", "pose"):
            params[f"{camera.name}.{stream}_topic"] = recording.topic(camera.name, stream) if (
                stream != "color" or camera.color) else ""
    params.update(values)
    nested: dict[str, Any] = {}
    for name, value in params.items():
        head, _, tail = name.partition(".")
        if tail:
            nested.setdefault(head, {})[tail] = value
        else:
            nested[name] = value
    path.write_text(yaml.safe_dump({"senfunet": {"ros__parameters": nested}}))
    return path


def two(first: Camera | None = None, second: Camera | None = None, **recording: Any) -> Recording:
    """A recording of two cameras (defaults: a 32FC1 `tof` and a 32FC1 `stereo` 5 cm to its right)."""
    first = first or Camera("tof", rate_hz=15.0)
    second = second or Camera("stereo", x_m=0.05, color="rgb8")
    return Recording((first, second), **recording)


__all__ = ["Camera", "Recording", "depth_of_scene", "surface_distance_m", "write_bag", "params_file", "two",
           "WALL_Z_M"]
