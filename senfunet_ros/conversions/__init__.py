"""Pure conversions between ROS messages and numpy: no node state, no rclpy Node.

One module per concern: `stamps`, `images` (raw and compressed images, camera info, resizing),
`poses` (pose messages, `PoseType`), `wire` (MarkerArray and PointCloud2 as CDR bytes). This
package re-exports their public names, so `from senfunet_ros import conversions as conv` reaches
all of them.

Message inputs are duck-typed (only attribute names are used), so the same functions accept
rclpy messages from a live subscription and the message objects `rosbags` deserialises from a
bag.

Convention: depth is float32 (H, W) metres with invalid pixels set to 0; RGB is uint8 (H, W, 3);
poses are `T_world_camera` (4x4 float64, camera optical frame to the fixed frame, metres);
stamps are integer nanoseconds. Every failure is a `ValueError` saying what was wrong and what
to do about it.
"""
from senfunet_ros.conversions.images import (
                                             color_for_depth,
                                             depth_from_image,
                                             depth_units_note,
                                             intrinsics_for_size,
                                             intrinsics_from_camera_info,
                                             intrinsics_text,
                                             names_raw_image,
                                             rectified_matrix,
                                             resize_depth,
                                             resize_rgb,
                                             rgb_from_image,
                                             scale_intrinsics,
                                             depth_from_compressed,
                                             rgb_from_compressed,
)
from senfunet_ros.conversions.poses import (
                                             PoseType,
                                             pose_from_msg,
                                             pose_from_odometry,
                                             pose_from_pose_stamped,
                                             pose_from_transform_stamped,
                                             transform_from_msg,
)
from senfunet_ros.conversions.stamps import ns_to_stamp, stamp_to_ns
from senfunet_ros.conversions.wire import (
                                             MARKER_ADD,
                                             MARKER_BYTES_PER_FACE,
                                             MARKER_DELETE,
                                             MARKER_DELETEALL,
                                             MARKER_TRIANGLE_LIST,
                                             MESH_MESSAGE_MAX_BYTES,
                                             DecodedMarker,
                                             block_marker_id,
                                             block_marker_ids,
                                             delete_all_marker_array_cdr,
                                             marker_array_cdr,
                                             marker_array_from_cdr,
                                             marker_array_messages,
                                             point_cloud2_cdr,
)
from senfunet_ros.geometry import QUATERNION_NORM_TOLERANCE

__all__ = [
    "depth_from_compressed",
    "rgb_from_compressed",
                                             "MARKER_ADD",
                                             "MARKER_BYTES_PER_FACE",
                                             "MARKER_DELETE",
                                             "MARKER_DELETEALL",
                                             "MARKER_TRIANGLE_LIST",
                                             "MESH_MESSAGE_MAX_BYTES",
                                             "DecodedMarker",
                                             "QUATERNION_NORM_TOLERANCE",
                                             "PoseType",
                                             "block_marker_id",
                                             "block_marker_ids",
                                             "delete_all_marker_array_cdr",
                                             "depth_from_image",
                                             "depth_units_note",
                                             "color_for_depth",
                                             "intrinsics_for_size",
                                             "intrinsics_from_camera_info",
                                             "intrinsics_text",
                                             "names_raw_image",
                                             "rectified_matrix",
                                             "marker_array_cdr",
                                             "marker_array_from_cdr",
                                             "marker_array_messages",
                                             "ns_to_stamp",
                                             "point_cloud2_cdr",
                                             "pose_from_msg",
                                             "pose_from_odometry",
                                             "pose_from_pose_stamped",
                                             "pose_from_transform_stamped",
                                             "resize_depth",
                                             "resize_rgb",
                                             "rgb_from_image",
                                             "scale_intrinsics",
                                             "stamp_to_ns",
                                             "transform_from_msg",
]
