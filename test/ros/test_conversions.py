"""senfunet_ros.conversions: messages <-> numpy, without a node."""
from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, TransformStamped
from nav_msgs.msg import Odometry
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from visualization_msgs.msg import Marker, MarkerArray

from senfunet_core.mesher import Mesh
from senfunet_ros import conversions as conv


def image(array: np.ndarray, encoding: str, *, pad: int = 0, bigendian: bool = False) -> Image:
    """An Image with `pad` bytes of row padding."""
    h, w = array.shape[:2]
    a = array.astype(array.dtype.newbyteorder(">" if bigendian else "<"))
    rows = a.reshape(h, -1).view(np.uint8)
    padded = np.zeros((h, rows.shape[1] + pad), np.uint8)
    padded[:, : rows.shape[1]] = rows
    msg = Image(height=h, width=w, encoding=encoding, is_bigendian=int(bigendian), step=padded.shape[1])
    msg.data = padded.tobytes()
    return msg


@pytest.mark.parametrize("bigendian", [False, True])
def test_depth_32fc1_with_padding_and_invalid(bigendian: bool) -> None:
    depth = np.arange(12, dtype=np.float32).reshape(3, 4) * 0.5
    depth[0, 1], depth[1, 1], depth[2, 2], depth[2, 3] = np.nan, np.inf, -1.0, 0.0
    out = conv.depth_from_image(image(depth, "32FC1", pad=6, bigendian=bigendian))
    assert out.dtype == np.float32 and out.shape == (3, 4)
    expected = np.where(np.isfinite(depth) & (depth > 0), depth, 0)
    np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize("bigendian", [False, True])
def test_depth_16uc1_millimetres(bigendian: bool) -> None:
    mm = np.array([[0, 1000, 2500], [65535, 1, 300]], dtype=np.uint16)
    out = conv.depth_from_image(image(mm, "16UC1", pad=2, bigendian=bigendian))
    np.testing.assert_allclose(out, mm.astype(np.float32) / 1000, rtol=1e-6)
    assert out[0, 0] == 0


def test_depth_errors_say_what_to_do() -> None:
    with pytest.raises(ValueError, match="32FC1"):
        conv.depth_from_image(image(np.zeros((2, 2), np.uint8), "8UC1"))
    msg = image(np.ones((4, 4), np.float32), "32FC1")
    msg.data = bytes(msg.data)[:20]
    with pytest.raises(ValueError, match="truncated"):
        conv.depth_from_image(msg)
    msg = image(np.ones((4, 4), np.float32), "32FC1")
    msg.step = 8
    with pytest.raises(ValueError, match="step"):
        conv.depth_from_image(msg)


def test_colour_encodings() -> None:
    rgb = np.random.default_rng(0).integers(0, 255, (3, 5, 3), dtype=np.uint8)
    np.testing.assert_array_equal(conv.rgb_from_image(image(rgb, "rgb8", pad=1)), rgb)
    np.testing.assert_array_equal(conv.rgb_from_image(image(rgb[:, :, ::-1].copy(), "bgr8", pad=3)), rgb)
    grey = rgb[:, :, 0].copy()
    out = conv.rgb_from_image(image(grey, "mono8", pad=3))
    assert out.shape == (3, 5, 3) and np.all(out == grey[:, :, None])
    with pytest.raises(ValueError, match="rgb8"):
        conv.rgb_from_image(image(grey, "yuv422"))


def test_camera_info() -> None:
    info = CameraInfo(width=640, height=480, k=[500.0, 0, 320, 0, 510, 240, 0, 0, 1])
    K, size = conv.intrinsics_from_camera_info(info)
    assert size == (640, 480) and K[1, 1] == 510 and K[0, 2] == 320
    with pytest.raises(ValueError, match="focal"):
        conv.intrinsics_from_camera_info(CameraInfo(width=640, height=480))  # all-zero K
    with pytest.raises(ValueError, match=r"not finite numbers \(500 0 nan, 0 510 240, 0 0 1\)"):
        conv.intrinsics_from_camera_info(CameraInfo(width=640, height=480, k=[500.0, 0, np.nan, 0, 510, 240, 0, 0, 1]))
    # written column-major (the principal point in the last row), or with K[2][2] = 0: every ray would
    # be off, and the frames would be fused into the map where they do not belong
    for k in ([500.0, 0, 0, 0, 510, 0, 320, 240, 1], [500.0, 0, 320, 0, 510, 240, 0, 0, 0]):
        with pytest.raises(ValueError, match="last row is .*, not 0 0 1"):
            conv.intrinsics_from_camera_info(CameraInfo(width=640, height=480, k=k))
    # a placeholder or mis-scaled K would smear each frame over the map: identity, millimetres, absurd
    for fx, fy in ((1.0, 1.0), (1.93, 1.93), (1e308, 500.0), (500.0, 1e-300)):
        with pytest.raises(ValueError, match="field of view"):
            conv.intrinsics_from_camera_info(CameraInfo(width=640, height=480, k=[fx, 0, 320, 0, fy, 240, 0, 0, 1]))
    wide = CameraInfo(width=640, height=480, k=[60.0, 0, 320, 0, 60.0, 240, 0, 0, 1])  # 158 x 152 degrees
    assert conv.intrinsics_from_camera_info(wide)[1] == (640, 480)


def test_camera_info_of_a_cropped_and_binned_image() -> None:
    """K and size of the image a camera_info with roi and binning describes (image_proc's crop and
    decimate keep the full camera's K and set those): a point lands on the pixel of the smaller
    image that covers the full-resolution pixels it lands on."""
    from sensor_msgs.msg import RegionOfInterest

    full = CameraInfo(width=640, height=480, k=[500.0, 0, 319.5, 0, 510, 239.5, 0, 0, 1])
    cropped = CameraInfo(width=640, height=480, k=list(full.k), binning_x=2, binning_y=4,
                         roi=RegionOfInterest(x_offset=100, y_offset=40, width=400, height=320))
    K_full, _ = conv.intrinsics_from_camera_info(full)
    K, size = conv.intrinsics_from_camera_info(cropped)
    assert size == (200, 80)
    for p in ([0.3, -0.2, 1.5], [-0.1, 0.15, 0.8]):
        u, v = (K_full @ np.array(p))[:2] / p[2]
        u2, v2 = (K @ np.array(p))[:2] / p[2]
        assert u2 == pytest.approx((u - 100 + 0.5) / 2 - 0.5) and v2 == pytest.approx((v - 40 + 0.5) / 4 - 0.5)
    binned = CameraInfo(width=640, height=480, k=list(full.k), binning_x=2, binning_y=2)  # roi all zero: whole
    assert conv.intrinsics_from_camera_info(binned)[1] == (320, 240)
    with pytest.raises(ValueError, match="roi"):
        conv.intrinsics_from_camera_info(CameraInfo(width=640, height=480, k=list(full.k), roi=RegionOfInterest(
            x_offset=600, y_offset=0, width=100, height=100)))


def test_resize_keeps_projection() -> None:
    K = np.array([[128.0, 0, 127.5], [0, 128.0, 127.5], [0, 0, 1]])
    K2 = conv.scale_intrinsics(K, (256, 256), (128, 64))
    p = np.array([0.3, -0.2, 1.5])
    u, v = (K @ p)[:2] / p[2]
    u2, v2 = (K2 @ p)[:2] / p[2]
    # the same point, in pixel-centre coordinates of the smaller image
    assert u2 == pytest.approx((u + 0.5) * 0.5 - 0.5) and v2 == pytest.approx((v + 0.5) * 0.25 - 0.5)
    depth = np.zeros((4, 4), np.float32)
    depth[:2, :2] = 1.0
    small = conv.resize_depth(depth, (2, 2))
    np.testing.assert_array_equal(small, [[1, 0], [0, 0]])  # nearest: no blended depths
    big = conv.resize_depth(depth, (8, 8))
    assert set(np.unique(big)) <= {0.0, 1.0}
    rgb = np.full((4, 4, 3), 200, np.uint8)
    assert conv.resize_rgb(rgb, (3, 2)).shape == (2, 3, 3)
    assert np.all(conv.resize_rgb(rgb, (3, 2)) == 200)


def _quat_z(angle_rad: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(angle_rad / 2), math.cos(angle_rad / 2))


def test_pose_messages() -> None:
    x, y, z, w = _quat_z(math.pi / 2)
    ps = PoseStamped()
    ps.header.stamp.sec, ps.header.stamp.nanosec = 3, 250
    ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = 1.0, 2.0, 3.0
    ps.pose.orientation.x, ps.pose.orientation.y, ps.pose.orientation.z, ps.pose.orientation.w = x, y, z, w
    stamp, T = conv.pose_from_pose_stamped(ps)
    assert stamp == 3_000_000_250
    np.testing.assert_allclose(T[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # 90 deg about z
    odom = Odometry()
    odom.header.stamp = ps.header.stamp
    odom.pose.pose = ps.pose
    tf = TransformStamped()
    tf.header.stamp = ps.header.stamp
    tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = 1.0, 2.0, 3.0
    tf.transform.rotation = ps.pose.orientation
    for msg in (odom, tf):
        s2, T2 = conv.pose_from_msg(msg)
        assert s2 == stamp
        np.testing.assert_allclose(T2, T)
    assert conv.pose_from_msg(ps)[0] == stamp

    ps.pose.position.x = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        conv.pose_from_pose_stamped(ps)
    ps.pose.position.x = 1.0
    ps.pose.orientation.w = 0.0
    ps.pose.orientation.z = 0.5
    with pytest.raises(ValueError, match="unit quaternion"):
        conv.pose_from_pose_stamped(ps)
    with pytest.raises(ValueError, match="not a pose"):
        conv.pose_from_msg(CameraInfo())


def _mesh(seed: int, n_vertices: int = 30, n_faces: int = 20) -> Mesh:
    rng = np.random.default_rng(seed)
    return Mesh(rng.random((n_vertices, 3), dtype=np.float32),
                rng.integers(0, n_vertices, (n_faces, 3)).astype(np.int32),
                rng.random((n_vertices, 3), dtype=np.float32))


def test_marker_array_round_trip() -> None:
    meshes = {(0, 1, 2): _mesh(0), (-3, 1025, 7): _mesh(1)}
    data = conv.marker_array_cdr(meshes, [(4, 4, 4)], stamp_ns=12_000_000_005, frame_id="map")
    assert isinstance(data, bytes)
    msg = deserialize_message(data, MarkerArray)
    actions = [m.action for m in msg.markers]
    assert actions.count(Marker.DELETE) == 1 and actions.count(Marker.ADD) == 2
    by_id = {(m.ns, m.id): m for m in msg.markers}
    for key, mesh in meshes.items():
        marker = by_id[conv.block_marker_id(key)]
        assert marker.type == Marker.TRIANGLE_LIST and marker.header.frame_id == "map"
        assert (marker.header.stamp.sec, marker.header.stamp.nanosec) == (12, 5)
        assert marker.pose.orientation.w == 1.0 and marker.scale.x == 1.0
        points = np.array([[p.x, p.y, p.z] for p in marker.points])
        np.testing.assert_allclose(points, mesh.vertices[mesh.faces.reshape(-1)], rtol=1e-6)
        colours = np.array([[c.r, c.g, c.b, c.a] for c in marker.colors])
        np.testing.assert_allclose(colours[:, :3], mesh.colors[mesh.faces.reshape(-1)], rtol=1e-6)
        assert np.all(colours[:, 3] == 1.0)
    # ids are a function of the key alone, and distinct
    ids = {conv.block_marker_id(k) for k in [(0, 0, 0), (1, 0, 0), (1024, 0, 0), (-1, 0, 0), (0, -1, 0)]}
    assert len(ids) == 5 and conv.block_marker_id((5, 6, 7)) == conv.block_marker_id((5, 6, 7))


def test_marker_array_reused_buffer_is_byte_exact() -> None:
    """Encoding into a reused buffer writes every byte, padding included: whatever the buffer held
    before, the same bytes (rclpy's own serialiser leaves padding as it finds it, so it is no reference)."""
    meshes = {(0, 1, 2): _mesh(0, n_faces=7), (5, -1, 2): _mesh(4, n_faces=3)}
    fresh = conv.marker_array_cdr(meshes, [(4, 4, 4)], stamp_ns=3, frame_id="odd")  # odd lengths: padding
    encoded = []
    for fill in (0x00, 0xFF):
        dirty = np.full(len(fresh) + 100, fill, np.uint8)
        reused = conv.marker_array_cdr(meshes, [(4, 4, 4)], stamp_ns=3, frame_id="odd", as_array=True, out=dirty)
        assert reused.base is dirty
        encoded.append(reused.tobytes())
    assert encoded[0] == encoded[1] == fresh
    assert len(deserialize_message(fresh, MarkerArray).markers) == 3
    small = np.zeros(10, np.uint8)  # too small: a new array, the old one untouched
    assert conv.marker_array_cdr(meshes, [], stamp_ns=3, frame_id="odd", as_array=True, out=small).base is not small


def test_marker_array_messages_split_an_update_into_parts() -> None:
    meshes = {(i, 0, -i): _mesh(i, n_faces=10 + 7 * i) for i in range(12)}
    meshes[(99, 0, 0)] = Mesh.empty()
    whole = deserialize_message(conv.marker_array_cdr(meshes, [(5, 5, 5)], stamp_ns=7, frame_id="map",
                                                      delete_all_first=True), MarkerArray)
    max_bytes = 60 * conv.MARKER_BYTES_PER_FACE  # about 60 triangles per part
    parts = [deserialize_message(data.tobytes(), MarkerArray) for data in conv.marker_array_messages(
        meshes, [(5, 5, 5)], stamp_ns=7, frame_id="map", delete_all_first=True, max_bytes=max_bytes)]
    assert len(parts) > 3
    assert parts[0].markers[0].action == Marker.DELETEALL
    assert all(m.action != Marker.DELETEALL for p in parts[1:] for m in p.markers)
    for part in parts:  # each part holds at most the budget, unless a single block exceeds it
        adds = [m for m in part.markers if m.action == Marker.ADD]
        assert len(adds) == 1 or sum(len(m.points) for m in adds) // 3 <= 60
    def key(m: Marker) -> tuple:
        return m.action, m.ns, m.id, len(m.points), tuple(round(p.x, 6) for p in m.points)

    assert sorted(map(key, (m for p in parts for m in p.markers))) == sorted(map(key, whole.markers))
    only_deletes = list(conv.marker_array_messages({}, [(1, 2, 3)], stamp_ns=7, frame_id="map"))
    assert len(only_deletes) == 1
    assert [m.action for m in deserialize_message(only_deletes[0].tobytes(), MarkerArray).markers] == [Marker.DELETE]


def test_marker_array_parts_stay_within_max_bytes_for_small_blocks() -> None:
    """A display mesh has tens of triangles a block: the parts were cut by their triangles alone, and
    each marker's fixed ~230 bytes made them a tenth larger than mesh_message_max_mb."""
    blocks = {(i, -i, 2000 * (i % 3)): _mesh(i, n_faces=8 + i % 30) for i in range(3000)}  # some far (long ns)
    removed = [(5000 + i, 0, 0) for i in range(200)]
    max_bytes = 256 << 10
    parts = [data.tobytes() for data in conv.marker_array_messages(
        blocks, removed, stamp_ns=7, frame_id="a_long_fixed_frame_name", delete_all_first=True, max_bytes=max_bytes)]
    assert len(parts) > 5
    assert max(map(len, parts)) <= max_bytes, [len(part) for part in parts]
    assert min(map(len, parts[:-1])) > max_bytes * 0.9  # not cut much smaller either
    whole = conv.marker_array_cdr(blocks, removed, stamp_ns=7, frame_id="a_long_fixed_frame_name",
                                  delete_all_first=True)
    assert sorted((m.ns, m.id, m.action, len(m.points_m)) for part in parts for m in conv.marker_array_from_cdr(part)) \
        == sorted((m.ns, m.id, m.action, len(m.points_m)) for m in conv.marker_array_from_cdr(whole))


def test_marker_delete_all_and_empty_block() -> None:
    msg = deserialize_message(conv.delete_all_marker_array_cdr(stamp_ns=0, frame_id="map"), MarkerArray)
    assert [m.action for m in msg.markers] == [Marker.DELETEALL]
    blocks = {(1, 1, 1): Mesh.empty(), (2, 2, 2): _mesh(2)}
    msg = deserialize_message(conv.marker_array_cdr(blocks, [], stamp_ns=1, frame_id="odom"), MarkerArray)
    assert [m.action for m in msg.markers] == [Marker.DELETE, Marker.ADD]
    assert msg.markers[0].id == conv.block_marker_id((1, 1, 1))[1]
    # a snapshot: after its DELETEALL, DELETEs of blocks without triangles or removed would clear nothing
    for parts in ([conv.marker_array_cdr(blocks, [(3, 3, 3)], stamp_ns=1, frame_id="odom", delete_all_first=True)],
                  list(conv.marker_array_messages(blocks, [(3, 3, 3)], stamp_ns=1, frame_id="odom",
                                                  delete_all_first=True, max_bytes=1))):
        markers = [m for data in parts for m in deserialize_message(bytes(data), MarkerArray).markers]
        assert [m.action for m in markers] == [Marker.DELETEALL, Marker.ADD]


def test_marker_array_decoder_reads_what_rclpy_writes() -> None:
    """marker_array_from_cdr against rclpy's own deserialisation: markers of another writer (every
    optional field filled, odd string lengths: padding) and our encoder's; a cut message is an error."""
    from geometry_msgs.msg import Point
    from std_msgs.msg import ColorRGBA
    from visualization_msgs.msg import UVCoordinate

    from rclpy.serialization import serialize_message

    rng = np.random.default_rng(5)
    msg = MarkerArray()
    for i in range(3):
        m = Marker(ns="n" * (i + 1), id=-7 + i, type=Marker.TRIANGLE_LIST, action=Marker.ADD, text="hi" * i,
                   texture_resource="tex" * i, mesh_resource="m" * i, frame_locked=bool(i % 2),
                   mesh_use_embedded_materials=True)
        m.header.frame_id = "odom" * i
        m.texture.format = "png" * i
        m.texture.data = list(range(i * 5))
        m.uv_coordinates = [UVCoordinate(u=0.5, v=0.25)] * i
        m.mesh_file.filename = "f" * (i + 2)
        m.mesh_file.data = list(range(i))
        m.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in rng.normal(size=(3 * i + 3, 3))]
        m.colors = [ColorRGBA(r=float(r), g=float(g), b=float(b), a=float(a))
                    for r, g, b, a in rng.random((len(m.points) if i != 1 else 0, 4))]
        msg.markers.append(m)
    ours = conv.marker_array_cdr({(0, 1, 2): _mesh(0), (3, 3, 3): Mesh.empty()}, [], stamp_ns=5, frame_id="map",
                                 delete_all_first=True)
    for data in (serialize_message(msg), ours):
        reference = deserialize_message(data, MarkerArray).markers
        decoded = conv.marker_array_from_cdr(data)
        assert len(decoded) == len(reference) > 0
        for ref, dec in zip(reference, decoded):
            assert (dec.ns, dec.id, dec.type, dec.action) == (ref.ns, ref.id, ref.type, ref.action)
            np.testing.assert_array_equal(dec.points_m, np.array([[p.x, p.y, p.z] for p in ref.points]).reshape(-1, 3))
            np.testing.assert_array_equal(dec.colors, np.array([[c.r, c.g, c.b, c.a] for c in ref.colors],
                                                               np.float32).reshape(-1, 4))
        with pytest.raises(ValueError, match="truncated"):
            conv.marker_array_from_cdr(data[: len(data) // 2])
    with pytest.raises(ValueError, match="CDR"):
        conv.marker_array_from_cdr(b"\x01\x02")


def test_point_cloud2_round_trip() -> None:
    rng = np.random.default_rng(3)
    pos = rng.random((7, 3), dtype=np.float32)
    alpha = rng.random(7, dtype=np.float32)
    weights = rng.random((7, 2), dtype=np.float32)
    data = conv.point_cloud2_cdr(pos, alpha, weights, ["tof", "stereo"], stamp_ns=2_000_000_000, frame_id="map")
    msg = deserialize_message(data, PointCloud2)
    assert [f.name for f in msg.fields] == ["x", "y", "z", "alpha", "weight_tof", "weight_stereo"]
    assert all(f.datatype == 7 and f.count == 1 for f in msg.fields)  # FLOAT32
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, 7, 24, 168)
    table = np.frombuffer(bytes(msg.data), "<f4").reshape(7, 6)
    np.testing.assert_array_equal(table[:, :3], pos)
    np.testing.assert_array_equal(table[:, 3], alpha)
    np.testing.assert_array_equal(table[:, 4:], weights)
    empty = deserialize_message(conv.point_cloud2_cdr(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2)),
                                                      ["a", "b"], stamp_ns=0, frame_id="map"), PointCloud2)
    assert empty.width == 0 and len(empty.data) == 0
    with pytest.raises(ValueError, match="weight column"):
        conv.point_cloud2_cdr(pos, alpha, weights[:, :1], ["tof", "stereo"], stamp_ns=0, frame_id="map")


def test_a_malformed_compressed_image_raises_without_opencv_printing(capfd: pytest.CaptureFixture) -> None:
    """OpenCV's own lines for a broken image would reach stderr unthrottled, once per message; the
    error raised here is what the node counts and logs, rate-limited."""
    from sensor_msgs.msg import CompressedImage

    msg = CompressedImage(format="16UC1; compressedDepth png")
    msg.data = b"\x00" * 12 + b"\x89PNG\r\n\x1a\n" + bytes(range(200))  # a png signature, then garbage
    with pytest.raises(ValueError, match="not a readable png"):
        conv.depth_from_image(msg)
    assert capfd.readouterr().err == ""


def test_a_corrupt_png_or_jpeg_payload_prints_nothing_of_its_own(capfd: pytest.CaptureFixture) -> None:
    """A byte flipped inside the compressed data (not just a broken signature): OpenCV's libpng and
    libjpeg printed "libpng error: IDAT: incorrect data check" / "Corrupt JPEG data: ..." to stderr
    for each such message, unthrottled; the decode must only raise (png) or return (jpeg)."""
    import cv2
    from sensor_msgs.msg import CompressedImage

    rng = np.random.default_rng(0)
    depth = (1000 + rng.integers(0, 3000, (32, 32))).astype(np.uint16)
    png = bytearray(cv2.imencode(".png", depth)[1].tobytes())
    png[len(png) // 2] ^= 0xFF  # inside IDAT
    msg = CompressedImage(format="16UC1; compressedDepth png")
    msg.data = bytes(12) + bytes(png)
    with pytest.raises(ValueError, match="not a readable png"):
        conv.depth_from_image(msg)
    rgb = rng.integers(0, 256, (32, 32, 3)).astype(np.uint8)
    jpg = bytearray(cv2.imencode(".jpg", rgb)[1].tobytes())
    jpg[2 * len(jpg) // 3] ^= 0xFF  # inside the entropy-coded data
    msg = CompressedImage(format="rgb8; jpeg compressed bgr8")
    msg.data = bytes(jpg)
    try:
        assert conv.rgb_from_image(msg).shape == (32, 32, 3)
    except ValueError as err:
        assert "not a readable" in str(err)
    assert capfd.readouterr().err == ""



def test_a_compressed_image_larger_than_any_camera_is_refused_from_its_header(capfd: pytest.CaptureFixture) -> None:
    """A 144 Mpx png was decoded whole (GBs, seconds) before its size was refused, Pillow printing its
    decompression-bomb warning; the header's size is checked before decoding."""
    import struct
    import warnings
    import zlib

    import cv2
    from sensor_msgs.msg import CompressedImage

    png = bytearray(cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes())
    ihdr = png.index(b"IHDR")
    png[ihdr + 4:ihdr + 12] = struct.pack(">II", 12000, 12000)  # its header claims 144 Mpx
    png[ihdr + 17:ihdr + 21] = struct.pack(">I", zlib.crc32(bytes(png[ihdr:ihdr + 17])))
    msg = CompressedImage(format="rgb8; png compressed bgr8")
    msg.data = bytes(png)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # Pillow's DecompressionBombWarning would raise here
        with pytest.raises(ValueError, match="12000x12000 pixels, more than any camera's"):
            conv.rgb_from_image(msg)
        msg = CompressedImage(format="16UC1; compressedDepth png")
        msg.data = bytes(12) + bytes(png)
        with pytest.raises(ValueError, match="12000x12000 pixels"):
            conv.depth_from_image(msg)
    assert capfd.readouterr().err == ""

def test_compressed_png_and_jpeg_decode_as_published() -> None:
    import cv2
    from sensor_msgs.msg import CompressedImage

    depth = np.arange(32 * 24, dtype=np.uint16).reshape(24, 32) * 7
    msg = CompressedImage(format="16UC1; compressedDepth png")
    msg.data = bytes(12) + cv2.imencode(".png", depth)[1].tobytes()
    np.testing.assert_array_equal(conv.depth_from_image(msg), depth.astype(np.float32) * np.float32(1e-3))
    rgb = np.zeros((24, 32, 3), np.uint8)
    rgb[..., 0] = 200  # red
    msg = CompressedImage(format="rgb8; png compressed bgr8")
    msg.data = cv2.imencode(".png", rgb[:, :, ::-1])[1].tobytes()
    np.testing.assert_array_equal(conv.rgb_from_image(msg), rgb)
    msg.data = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    decoded = conv.rgb_from_image(msg)
    assert np.abs(decoded.astype(int) - rgb).max() <= 3
    assert decoded.flags.writeable  # a frame's user may write into it (torch.from_numpy warns otherwise)


def test_a_compressed_depth_format_without_its_encoding_is_read_by_its_header() -> None:
    """Format 'compressedDepth' alone (older publishers): refused as "encoding 'compressedDepth'", though
    the header's quantisation tells 16UC1 (none) from 32FC1."""
    import cv2

    depth = (1000 + np.arange(24 * 32)).astype(np.uint16).reshape(24, 32)
    msg = _compressed_depth("compressedDepth", cv2.imencode(".png", depth)[1].tobytes())
    np.testing.assert_array_equal(conv.depth_from_image(msg), depth.astype(np.float32) * np.float32(1e-3))


def test_a_16_bit_png_on_a_colour_topic_is_refused_not_fused_white() -> None:
    """image_transport's compressed plugin keeps 16 bits in a PNG (an IR camera's mono16): converted to
    RGB, Pillow clipped its values to 255, and the stereo feature net got a white image, unsaid. A
    payload Pillow cannot identify named a memory address, new in every message."""
    import cv2
    from sensor_msgs.msg import CompressedImage

    ir = (200 + np.arange(24 * 32) * 5).astype(np.uint16).reshape(24, 32)
    msg = CompressedImage(format="mono16; png compressed mono16")
    msg.data = cv2.imencode(".png", ir)[1].tobytes()
    with pytest.raises(ValueError, match="16-bit or float.*not 8-bit colour"):
        conv.rgb_from_image(msg)
    msg.data = b"not an image at all"
    with pytest.raises(ValueError, match="not a readable png/jpeg") as raised:
        conv.rgb_from_image(msg)
    assert "0x" not in str(raised.value), raised.value


def _compressed_depth(fmt: str, payload: bytes, depth_a: float = 0.0, depth_b: float = 0.0) -> object:
    from sensor_msgs.msg import CompressedImage

    msg = CompressedImage(format=fmt)
    msg.data = np.array([0], "<i4").tobytes() + np.array([depth_a, depth_b], "<f4").tobytes() + payload
    return msg


def test_compressed_depth_rvl_16uc1_and_32fc1() -> None:
    from rvl_encoder import rvl_payload

    rng = np.random.default_rng(5)
    mm = rng.integers(300, 5000, (37, 53)).astype(np.uint16)
    mm[rng.random(mm.shape) < 0.3] = 0  # holes: runs of zeros between runs of depth
    mm[:3] = 0  # a long run at the start
    mm[10, 20:] = 65535  # a jump across the whole 16-bit range, both ways (wraps in 16 bits)
    mm[-1, -5:] = 0  # the image ends in zeros
    got = conv.depth_from_image(_compressed_depth("16UC1; compressedDepth rvl", rvl_payload(mm)))
    np.testing.assert_array_equal(got, mm.astype(np.float32) * np.float32(1e-3))
    # 32FC1: quantised inverse depth, depth = a / (q - b), as for png
    a, b = 100.0, -20.0
    got = conv.depth_from_image(_compressed_depth("32FC1; compressedDepth rvl", rvl_payload(mm), a, b))
    want = np.where(mm > 0, np.float32(a) / (mm.astype(np.float32) - np.float32(b)), 0).astype(np.float32)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert (got[mm == 0] == 0).all()
    # a header whose quantisation gives no depth (every pixel NaN or negative): said, not "all invalid"
    for bad_a, bad_b in ((float("nan"), b), (-a, b), (a, float("inf"))):
        with pytest.raises(ValueError, match=r"header's quantisation \(depthParam"):
            conv.depth_from_image(_compressed_depth("32FC1; compressedDepth rvl", rvl_payload(mm), bad_a, bad_b))


def test_malformed_rvl_depth_raises_saying_what_is_wrong() -> None:
    from rvl_encoder import rvl_payload

    mm = np.arange(1, 401, dtype=np.uint16).reshape(20, 20)
    good = rvl_payload(mm)
    with pytest.raises(ValueError, match="truncated"):
        conv.depth_from_image(_compressed_depth("16UC1; compressedDepth rvl", good[: len(good) // 2]))
    too_wide = np.array([1 << 20, 1 << 20], "<u4").tobytes() + good[8:]
    with pytest.raises(ValueError, match="corrupt"):
        conv.depth_from_image(_compressed_depth("16UC1; compressedDepth rvl", too_wide))
    smaller = np.array([10, 10], "<u4").tobytes() + good[8:]  # the runs overrun a 10x10 image
    with pytest.raises(ValueError, match="overruns"):
        conv.depth_from_image(_compressed_depth("16UC1; compressedDepth rvl", smaller))
    endless = good[:8] + b"\xff" * 64  # every nibble says "more digits follow"
    with pytest.raises(ValueError, match="too many digits"):
        conv.depth_from_image(_compressed_depth("16UC1; compressedDepth rvl", endless))
    with pytest.raises(ValueError, match="codec 'zstd'"):
        conv.depth_from_image(_compressed_depth("16UC1; compressedDepth zstd", good))
    # older publishers write plain 'compressedDepth': png
    with pytest.raises(ValueError, match="not a readable png"):
        conv.depth_from_image(_compressed_depth("16UC1; compressedDepth", good))


def test_a_camera_info_of_another_size_takes_the_k_its_principal_point_fits() -> None:
    """K for a 320x240 image from a camera_info of 640x480: a full-resolution K (principal point at the
    centre of 640x480) is scaled, without a note; a K already made for 320x240 (only width and height
    left wrong) is taken as given, with a note naming both; a resize by a few percent keeps the
    contract's scaling without a note, whichever principal point lies nearer the centre (they differ
    by a pixel or two: a warning would only puzzle)."""
    full = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    K, note = conv.intrinsics_for_size(full, (640, 480), (320, 240))
    np.testing.assert_allclose(K, [[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
    assert note is None
    half = np.array([[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
    K, note = conv.intrinsics_for_size(half, (640, 480), (320, 240))
    np.testing.assert_array_equal(K, half)
    assert note is not None and "says 640x480 but the depth images are 320x240" in note and "fx 125" in note
    off_centre = np.array([[500.0, 0, 310.0], [0, 500.0, 236.0], [0, 0, 1]])  # a real camera's principal point
    K, note = conv.intrinsics_for_size(off_centre, (640, 480), (632, 474))  # a 1.25% resize
    np.testing.assert_allclose(K, conv.scale_intrinsics(off_centre, (640, 480), (632, 474)))
    assert note is None
