"""Pose messages -> `T_world_camera`, and the one table of accepted pose types (`PoseType`).

Messages are duck-typed (rclpy or rosbags objects). Every failure is a ValueError saying what was
wrong and what to do.
"""
from __future__ import annotations

import enum
from collections.abc import Callable
from typing import Any

import numpy as np

from senfunet_ros.conversions.stamps import stamp_to_ns
from senfunet_ros.geometry import check_within_map, transform_from_tq

__all__ = [
    "PoseType",
    "pose_from_msg",
    "pose_from_odometry",
    "pose_from_pose_stamped",
    "pose_from_transform_stamped",
    "transform_from_msg",
]


def transform_from_msg(translation: Any, rotation: Any, what: str) -> np.ndarray:
    """geometry_msgs Point/Vector3 and Quaternion -> 4x4; ValueError naming `what` if unusable."""
    return transform_from_tq((translation.x, translation.y, translation.z),
                             (rotation.x, rotation.y, rotation.z, rotation.w), what)


def pose_from_pose_stamped(msg: Any) -> tuple[int, np.ndarray]:
    """geometry_msgs/PoseStamped -> (stamp_ns, T_world_camera). The pose topics' messages are refused
    beyond the map's reach (`check_within_map`)."""
    return stamp_to_ns(msg.header.stamp), check_within_map(
        transform_from_msg(msg.pose.position, msg.pose.orientation, "PoseStamped"), "PoseStamped")


def pose_from_odometry(msg: Any) -> tuple[int, np.ndarray]:
    """nav_msgs/Odometry -> (stamp_ns, T_world_child) from its pose (the twist is ignored). The pose
    is the child_frame_id's (usually base_link): a sensor extrinsic turns it into the camera's."""
    pose = msg.pose.pose
    return stamp_to_ns(msg.header.stamp), check_within_map(
        transform_from_msg(pose.position, pose.orientation, "Odometry"), "Odometry")


def pose_from_transform_stamped(msg: Any) -> tuple[int, np.ndarray]:
    """geometry_msgs/TransformStamped -> (stamp_ns, T_world_camera)."""
    tf = msg.transform
    return stamp_to_ns(msg.header.stamp), check_within_map(
        transform_from_msg(tf.translation, tf.rotation, "TransformStamped"), "TransformStamped")


def pose_from_msg(msg: Any) -> tuple[int, np.ndarray]:
    """Any of the three accepted pose messages, recognised by its fields."""
    if hasattr(msg, "transform"):
        return pose_from_transform_stamped(msg)
    pose = getattr(msg, "pose", None)
    if pose is not None and hasattr(pose, "pose"):
        return pose_from_odometry(msg)
    if pose is not None and hasattr(pose, "position"):
        return pose_from_pose_stamped(msg)
    raise ValueError(
        f"{type(msg).__name__} is not a pose message; publish PoseStamped, Odometry or TransformStamped"
    )


class PoseType(str, enum.Enum):
    """Where poses come from (parameter `pose_type`): a pose topic of one of three types, or TF."""

    POSE_STAMPED = "pose_stamped"
    ODOMETRY = "odometry"
    TRANSFORM_STAMPED = "transform_stamped"
    TF = "tf"  # the depth image's frame_id looked up in the fixed frame (/tf, /tf_static)

    @property
    def msgtype(self) -> str | None:
        """The ROS 2 type of the pose topic (None for TF: no pose topic)."""
        return _MSGTYPES[self]

    @property
    def parse(self) -> Callable[[Any], tuple[int, np.ndarray]]:
        """The pose topic's message -> (stamp_ns, T_world_frame)."""
        return _PARSERS.get(self, pose_from_msg)

    @classmethod
    def from_msgtype(cls, msgtype: str) -> PoseType | None:
        return next((p for p in cls if p.msgtype == msgtype), None)


_MSGTYPES = {PoseType.POSE_STAMPED: "geometry_msgs/msg/PoseStamped", PoseType.ODOMETRY: "nav_msgs/msg/Odometry",
             PoseType.TRANSFORM_STAMPED: "geometry_msgs/msg/TransformStamped", PoseType.TF: None}
_PARSERS = {PoseType.POSE_STAMPED: pose_from_pose_stamped, PoseType.ODOMETRY: pose_from_odometry,
            PoseType.TRANSFORM_STAMPED: pose_from_transform_stamped}
