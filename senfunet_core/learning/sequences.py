"""Two-sensor recordings: asynchronous frames of both sensors along a trajectory, with one pose
stream per sensor."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .raycast import _translation, intrinsics, render_view
from .scenes import Scene
from .sensors import SENSORS, SGBM_BLOCK_SIZE, SGBM_NUM_DISPARITIES, TOF_OFFSET_X_M, _sgbm, _stereo_depth, _tof_depth
from .trajectory import Trajectory


@dataclass
class SensorFrame:
    """One depth image of one sensor. depth_m: 0 = invalid. T_world_camera: true pose at stamp_s."""

    sensor: str  # "tof" | "stereo"
    stamp_s: float
    depth_m: np.ndarray  # (H,W) float32
    rgb: np.ndarray | None  # (H,W,3) uint8 left colour image (stereo), None (tof)
    K: np.ndarray  # (3,3) float64
    T_world_camera: np.ndarray  # (4,4) float64


@dataclass
class Sequence:
    """A recording: frames of both sensors sorted by stamp, and one pose stream per sensor."""

    scene: Scene
    frames: list[SensorFrame] = field(default_factory=list)
    pose_stamps_s: dict[str, np.ndarray] = field(default_factory=dict)  # sensor -> (M,)
    pose_T_world_camera: dict[str, np.ndarray] = field(default_factory=dict)  # sensor -> (M,4,4)


def _sensor_offset(sensor: str) -> np.ndarray:
    return _translation(TOF_OFFSET_X_M, 0, 0) if sensor == "tof" else np.eye(4)


def _avoid(stamps: np.ndarray, others: np.ndarray, min_gap_s: float = 2e-4) -> np.ndarray:
    """Nudge stamps that come within min_gap_s of any of `others` (so they never coincide)."""
    stamps = stamps.copy()
    if len(others) == 0:
        return stamps
    srt = np.sort(others)
    for _ in range(4):
        j = np.clip(np.searchsorted(srt, stamps), 1, len(srt) - 1)
        near = np.minimum(np.abs(stamps - srt[j - 1]), np.abs(stamps - srt[j]))
        clash = near < min_gap_s
        if not np.any(clash):
            break
        stamps[clash] += 2.5 * min_gap_s
    return stamps


def simulate_sequence(scene: Scene, seed: int, *, duration_s: float = 10.0, tof_rate_hz: float = 15.0,
                      stereo_rate_hz: float = 20.0, pose_rate_hz: float = 100.0, width: int = 256,
                      height: int = 256, tof_prefix_frames: int | None = None) -> Sequence:
    """Simulate both sensors over duration_s seconds (stamps in [0, duration_s)).

    tof_prefix_frames = n: render only the first n ToF frames and no stereo frame; stamps and pose
    streams are the full recording's. The sensors' noise comes from one stream, ToF frames first,
    so these frames equal the full recording's first n ToF frames (a cheap check that a stored
    recording is what the simulator makes)."""
    if duration_s <= 0 or min(tof_rate_hz, stereo_rate_hz, pose_rate_hz) <= 0:
        raise InputError("duration_s and the rates must be > 0")
    if width < SGBM_NUM_DISPARITIES + SGBM_BLOCK_SIZE or height < 16:
        # SGBM needs the image wider than its disparity range plus half a block
        raise InputError(f"images must be at least {SGBM_NUM_DISPARITIES + SGBM_BLOCK_SIZE} x 16, "
                         f"got {width} x {height}")
    rng = np.random.default_rng([seed, 3])
    pose_margin = 2.0 / pose_rate_hz + 0.02
    traj = Trajectory(scene, seed, -pose_margin - 0.01, duration_s + pose_margin + 0.01)
    K = intrinsics(width, height)

    # asynchronous stamps: own rate, random phase, ~1 ms jitter, never equal to each other
    stamps: dict[str, np.ndarray] = {}
    for sensor, rate in (("tof", tof_rate_hz), ("stereo", stereo_rate_hz)):
        n = int(np.floor(duration_s * rate))
        st = (np.arange(n) + rng.uniform(0.05, 0.95)) / rate + rng.normal(0, 0.001, n)
        stamps[sensor] = np.sort(np.clip(st, 0, duration_s - 1e-3))
    stamps["stereo"] = _avoid(stamps["stereo"], stamps["tof"])
    all_frame_stamps = np.concatenate([stamps["tof"], stamps["stereo"]])

    seq = Sequence(scene=scene)
    for sensor in SENSORS:
        n = int(np.ceil((duration_s + 2 * pose_margin) * pose_rate_hz))
        ps = -pose_margin + (np.arange(n) + rng.uniform(0.1, 0.9)) / pose_rate_hz
        ps = _avoid(ps, all_frame_stamps)
        seq.pose_stamps_s[sensor] = ps
        seq.pose_T_world_camera[sensor] = traj(ps) @ _sensor_offset(sensor)

    sgbm = _sgbm(scene)
    frames = []
    limit = {} if tof_prefix_frames is None else {"tof": int(tof_prefix_frames), "stereo": 0}
    for sensor in SENSORS:
        n_frames = min(len(stamps[sensor]), limit.get(sensor, len(stamps[sensor])))
        poses = traj(stamps[sensor][:n_frames]) @ _sensor_offset(sensor)
        for st, T in zip(stamps[sensor][:n_frames], poses):
            if sensor == "tof":
                view = render_view(scene, T, K, width, height, with_rgb=False,
                                   with_other_distance=scene.tof_multipath_m > 0)
                depth, rgb = _tof_depth(view, K, scene, rng), None
            else:
                depth, rgb = _stereo_depth(scene, T, K, width, height, rng, sgbm)
            frames.append(SensorFrame(sensor, float(st), depth, rgb, K.copy(), T))
    frames.sort(key=lambda f: f.stamp_s)
    seq.frames = frames
    return seq
