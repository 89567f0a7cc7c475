"""Rotation and pose maths for the ROS layer: quaternions, 4x4 transforms, interpolation.

Convention: quaternions are (x, y, z, w) as in geometry_msgs/Quaternion; transforms are 4x4
float64 `T_parent_child` (child frame to parent frame, metres). No message types here: the
conversions pass plain numbers in.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

__all__ = [
    "QUATERNION_NORM_TOLERANCE",
    "extrapolate_pose",
    "interpolate_pose",
    "invert_transform",
    "matrix_from_quat",
    "pose_difference",
    "pose_jump",
    "quat_from_matrix",
    "tq_from_transform",
    "check_within_map",
    "transform_from_tq",
]

# A quaternion whose norm is off by more than this is a driver bug, not rounding: reject it.
# Smaller deviations (float32 round trips) are renormalised.
QUATERNION_NORM_TOLERANCE = 1e-2
# The map reaches 5 km from the origin (senfunet_core.integrator refuses frames beyond): a pose
# farther is a wrong unit or frame, refused where it arrives, not interpolated into good frames.
# Not a limit on TF links: a robot's tree may hang its map off a UTM or earth frame far away.
MAX_TRANSLATION_M = 5000.0


def check_within_map(T: np.ndarray, what: str) -> np.ndarray:
    """T, if its position lies within MAX_TRANSLATION_M of the origin on every axis; else ValueError
    naming `what`."""
    t = T[:3, 3]
    if float(np.max(np.abs(t))) > MAX_TRANSLATION_M:
        raise ValueError(f"{what} position ({t[0]:.4g}, {t[1]:.4g}, {t[2]:.4g}) m is more than "
                         f"{MAX_TRANSLATION_M / 1000:g} km from the origin, beyond the map; check the pose's "
                         "units (metres) and frame")
    return T


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (x, y, z, w), numerically stable for any angle."""
    m = R
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    q: list[float]
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    quat = np.asarray(q, dtype=np.float64)
    return quat / np.linalg.norm(quat)


def matrix_from_quat(q: np.ndarray | Sequence[float]) -> np.ndarray:
    """Unit quaternion (x, y, z, w) -> 3x3 rotation matrix."""
    return np.array(_rotation_rows(*(float(v) for v in q)))


def _rotation_rows(x: float, y: float, z: float, w: float) -> list[list[float]]:
    return [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]


def transform_from_tq(t: np.ndarray | Sequence[float], q: np.ndarray | Sequence[float], what: str) -> np.ndarray:
    """Translation (3,) and quaternion (x, y, z, w) -> 4x4 transform. ValueError, naming `what`, for
    NaN/inf or a quaternion whose norm is not 1 (within QUATERNION_NORM_TOLERANCE). Scalar maths:
    a robot's TF tree brings thousands of transforms a second, and numpy's per-call cost on 4 numbers
    is most of the time."""
    tx, ty, tz = (float(v) for v in t)
    x, y, z, w = (float(v) for v in q)
    if not all(math.isfinite(v) for v in (tx, ty, tz, x, y, z, w)):
        raise ValueError(f"{what} contains NaN or inf; the localisation source lost track, fix it upstream")
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        unset = " (all zero: the orientation was never set; a position-only source needs one, e.g. w = 1)" \
            if norm == 0.0 else ""
        raise ValueError(f"{what} orientation quaternion has norm {norm:.4f}, not 1{unset}; publish a unit quaternion")
    r = _rotation_rows(x / norm, y / norm, z / norm, w / norm)
    return np.array([[*r[0], tx], [*r[1], ty], [*r[2], tz], [0.0, 0.0, 0.0, 1.0]])


def tq_from_transform(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 transform -> (translation (3,), quaternion (x, y, z, w))."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, 3].copy(), quat_from_matrix(T[:3, :3])


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    out = np.eye(4, dtype=np.float64)
    R = np.asarray(T, dtype=np.float64)[:3, :3]
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ np.asarray(T, dtype=np.float64)[:3, 3]
    return out


def pose_difference(T0: np.ndarray, T1: np.ndarray) -> tuple[float, float]:
    """How far apart two poses (4x4) are: metres between their origins, degrees of the rotation between them."""
    cos = (np.trace(T0[:3, :3].T @ T1[:3, :3]) - 1.0) / 2.0
    return float(np.linalg.norm(T1[:3, 3] - T0[:3, 3])), float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


# a step between two consecutive poses of a stream (or transforms of a TF link) this many times its typical
# step, and at least JUMP_MIN_M or JUMP_MIN_DEG, is a jump (a localiser relocalising): no pose is interpolated
# across it, the frame would lie on a smear between the old and the new place
JUMP_STEPS = 10.0
JUMP_MIN_M = 0.25
JUMP_MIN_DEG = 15.0
JUMP_HISTORY = 8  # steps before it that tell the typical one, at least


def pose_jump(poses: Sequence[np.ndarray], i: int) -> tuple[float, float] | None:
    """The step (metres, degrees) from poses[i-1] to poses[i] (4x4, in stamp order) when it is a jump
    against the typical step before it (the median of its last 16), else None (also with too little
    history to tell)."""
    if i - 1 < JUMP_HISTORY:
        return None
    metres, degrees = pose_difference(poses[i - 1], poses[i])
    if metres < JUMP_MIN_M and degrees < JUMP_MIN_DEG:
        return None
    history = [pose_difference(a, b) for a, b in zip(poses[max(0, i - 17):i - 1], poses[max(1, i - 16):i])]
    typical_m, typical_deg = (float(np.median(values)) for values in zip(*history))
    if (metres >= JUMP_MIN_M and metres > JUMP_STEPS * typical_m) or (
            degrees >= JUMP_MIN_DEG and degrees > JUMP_STEPS * typical_deg):
        return metres, degrees
    return None


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose at fraction s in [0, 1] from T0 to T1: lerp of translation, slerp of rotation."""
    q0 = quat_from_matrix(T0[:3, :3])
    q1 = quat_from_matrix(T1[:3, :3])
    dot = float(np.dot(q0, q1))
    if dot < 0.0:  # take the short way round
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: lerp is exact enough and avoids dividing by sin(~0)
        q = q0 + s * (q1 - q0)
    else:
        theta = np.arccos(dot)
        q = (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)
    T = np.eye(4)
    T[:3, :3] = matrix_from_quat(q / np.linalg.norm(q))
    T[:3, 3] = (1 - s) * T0[:3, 3] + s * T1[:3, 3]
    return T


def extrapolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose at fraction s >= 1 along the motion from T0 to T1 continued at constant velocity: the
    translation linear, the rotation on about the same axis at the same rate (axis-angle of
    R1 R0^T, scaled; exact at small angles, where `interpolate_pose` lerps). For a frame stamped after
    the newest pose when no later pose will come (a stream ended)."""
    if s < 1.0:
        raise ValueError(f"extrapolate_pose takes s >= 1 (past T1), got {s}; use interpolate_pose within T0..T1")
    R0, R1 = np.asarray(T0, np.float64)[:3, :3], np.asarray(T1, np.float64)[:3, :3]
    step = _rotvec_from_matrix(R1 @ R0.T)  # the world-frame turn from T0 to T1
    T = np.eye(4)
    T[:3, :3] = _matrix_from_rotvec((s - 1.0) * step) @ R1
    T[:3, 3] = T1[:3, 3] + (s - 1.0) * (T1[:3, 3] - T0[:3, 3])
    return T


def _rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> axis * angle (radians), through the quaternion (stable at 0 and near pi)."""
    x, y, z, w = quat_from_matrix(R)
    if w < 0:  # the short way round
        x, y, z, w = -x, -y, -z, -w
    sin_half = float(np.sqrt(x * x + y * y + z * z))
    angle = 2.0 * np.arctan2(sin_half, w)
    scale = angle / sin_half if sin_half > 1e-12 else 2.0  # angle / sin(angle / 2) -> 2 at 0
    return np.array([x, y, z]) * scale


def _matrix_from_rotvec(rotvec: np.ndarray) -> np.ndarray:
    """Axis * angle (radians) -> rotation matrix."""
    angle = float(np.linalg.norm(rotvec))
    half = 0.5 * angle
    scale = np.sin(half) / angle if angle > 1e-12 else 0.5
    x, y, z = rotvec * scale
    return matrix_from_quat(np.array([x, y, z, np.cos(half)]))
