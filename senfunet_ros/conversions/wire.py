"""Wire encoding: MarkerArray and PointCloud2 straight into CDR bytes with numpy/numba.

Filling hundreds of thousands of `geometry_msgs/Point` objects costs about a second; `rclpy`
publishers accept already-serialised bytes as they are (`senfunet_ros.dds.publish_serialized`).
"""
from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from senfunet_ros.conversions.stamps import ns_to_stamp

__all__ = [
    "MARKER_ADD",
    "MARKER_BYTES_PER_FACE",
    "MARKER_DELETE",
    "MARKER_DELETEALL",
    "MARKER_TRIANGLE_LIST",
    "MESH_MESSAGE_MAX_BYTES",
    "DecodedMarker",
    "block_marker_id",
    "block_marker_ids",
    "delete_all_marker_array_cdr",
    "marker_array_cdr",
    "marker_array_from_cdr",
    "marker_array_messages",
    "point_cloud2_cdr",
]

# visualization_msgs/Marker constants (from the message definition).
MARKER_TRIANGLE_LIST = 11
MARKER_ADD = 0
MARKER_DELETE = 2
MARKER_DELETEALL = 3
# sensor_msgs/PointField.FLOAT32
_POINTFIELD_FLOAT32 = 7


class _CdrWriter:
    """Appends CDR primitives; alignment is relative to the payload after the 4-byte header."""

    def __init__(self) -> None:
        self._chunks: list[bytes] = [b"\x00\x01\x00\x00"]  # encapsulation: CDR little endian
        self._offset = 0

    def _align(self, size: int) -> None:
        pad = -self._offset % size
        if pad:
            self._chunks.append(b"\x00" * pad)
            self._offset += pad

    def raw(self, data: bytes, align: int = 1) -> None:
        self._align(align)
        self._chunks.append(data)
        self._offset += len(data)

    def u8(self, value: int) -> None:
        self.raw(struct.pack("<B", value))

    def u32(self, value: int) -> None:
        self.raw(struct.pack("<I", value), 4)

    def i32(self, value: int) -> None:
        self.raw(struct.pack("<i", value), 4)

    def string(self, text: str) -> None:
        data = text.encode("utf-8") + b"\x00"
        self.u32(len(data))
        self.raw(data)

    def header(self, stamp_ns: int, frame_id: str) -> None:
        sec, nanosec = ns_to_stamp(stamp_ns)
        self.i32(sec)
        self.u32(nanosec)
        self.string(frame_id)

    def getvalue(self) -> bytes:
        return b"".join(self._chunks)


class _CdrReader:
    """Reads CDR primitives (either byte order, from the encapsulation header); alignment is
    relative to the payload after the 4-byte header. Arrays of numbers come as numpy views."""

    def __init__(self, data: bytes | bytearray | memoryview | np.ndarray) -> None:
        buffer = data.view(np.uint8).reshape(-1).data if isinstance(data, np.ndarray) else data
        self._data = memoryview(buffer).cast("B")
        if len(self._data) < 4 or self._data[0] != 0 or self._data[1] not in (0, 1):
            raise ValueError("not a plain CDR message (expected the encapsulation 00 00 or 00 01)")
        self._order = "<" if self._data[1] == 1 else ">"
        self._offset = 4

    def _take(self, size: int, align: int) -> int:
        start = self._offset + (-(self._offset - 4) % align)
        if start + size > len(self._data):
            raise ValueError(f"CDR message truncated: {start + size} bytes needed, {len(self._data)} given")
        self._offset = start + size
        return start

    def scalars(self, fmt: str) -> tuple[Any, ...]:
        """Consecutive scalars of one size (struct format characters, e.g. "iI" or "7d")."""
        size = struct.calcsize("<" + fmt)
        return struct.unpack_from(self._order + fmt, self._data, self._take(size, struct.calcsize("<" + fmt[-1])))

    def string(self) -> str:
        (length,) = self.scalars("I")
        return bytes(self._data[self._take(length, 1): self._offset]).rstrip(b"\x00").decode("utf-8", "replace")

    def sequence(self, dtype: str, width: int = 1) -> np.ndarray:
        """A sequence of structs of `width` numbers of one dtype (a numpy code without byte order,
        e.g. "f8"), as an (N, width) view of the message."""
        (count,) = self.scalars("I")
        item = np.dtype(dtype).itemsize
        start = self._take(count * width * item, item)
        return np.frombuffer(self._data, np.dtype(self._order + dtype), count * width, start).reshape(count, width)

    def skip_header(self) -> None:
        """std_msgs/Header: stamp and frame_id."""
        self.scalars("iI")
        self.string()


@dataclass(frozen=True)
class DecodedMarker:
    """What a mesh reader needs of one visualization_msgs/Marker."""

    ns: str
    id: int
    type: int
    action: int
    points_m: np.ndarray  # (N, 3) float64: geometry_msgs/Point, the triangle corners of a TRIANGLE_LIST
    colors: np.ndarray  # (N, 4) float32 RGBA, or (0, 4)


def marker_array_from_cdr(data: bytes | bytearray | memoryview | np.ndarray) -> list[DecodedMarker]:
    """A visualization_msgs/MarkerArray (ROS 2 Jazzy's Marker) from its CDR bytes, as a raw
    subscription (`create_subscription(..., raw=True)`) gets them: rclpy's own deserialisation makes
    a Python object per point, seconds for a room's mesh. Raises ValueError on a malformed message."""
    reader = _CdrReader(data)
    (count,) = reader.scalars("I")
    markers = []
    for _ in range(count):
        reader.skip_header()
        ns = reader.string()
        marker_id, marker_type, action = reader.scalars("iii")
        reader.scalars("10d")  # pose, scale
        reader.scalars("4f")  # color
        reader.scalars("iI")  # lifetime
        reader.scalars("B")  # frame_locked
        points = reader.sequence("f8", 3)
        colors = reader.sequence("f4", 4)
        reader.string()  # texture_resource
        reader.skip_header()  # texture: sensor_msgs/CompressedImage
        reader.string()
        reader.sequence("u1")
        reader.sequence("f4", 2)  # uv_coordinates
        reader.string()  # text
        reader.string()  # mesh_resource
        reader.string()  # mesh_file: filename, data
        reader.sequence("u1")
        reader.scalars("B")  # mesh_use_embedded_materials
        markers.append(DecodedMarker(ns, marker_id, marker_type, action, points, colors))
    return markers


def block_marker_id(key: Sequence[int]) -> tuple[str, int]:
    """A stable (ns, id) for a block key: 10 bits per axis in the id, the rest in the namespace.

    The id alone covers 1024 blocks per axis (82 m at 1 cm voxels); beyond that the namespace
    differs, so ids never collide and a block keeps its marker across updates.
    """
    names, ids = block_marker_ids(np.asarray([key], np.int64).reshape(1, 3))
    return names[0], int(ids[0])


def block_marker_ids(keys: np.ndarray) -> tuple[list[str], np.ndarray]:
    """block_marker_id for B x 3 block keys at once: (namespaces, ids)."""
    keys = np.asarray(keys, np.int64).reshape(-1, 3)
    low, high = keys & 0x3FF, keys >> 10
    ids = (low[:, 0] << 20) | (low[:, 1] << 10) | low[:, 2]
    names = ["senfunet_mesh"] * len(keys)
    for row in np.flatnonzero(high.any(axis=1)):  # beyond 1024 blocks from the origin: rare
        names[row] = "senfunet_mesh_{}_{}_{}".format(*high[row].tolist())
    return names, ids


@numba.njit(inline="always")
def _align(buf: np.ndarray, offset: int, size: int, write: bool) -> int:
    """The next offset aligned to `size`; the padding is written as zeros."""
    aligned = offset + (-offset % size)
    if write:
        buf[offset:aligned] = 0
    return aligned


@numba.njit(inline="always")
def _put(buf: np.ndarray, offset: int, value: int, size: int, write: bool) -> int:
    """Little-endian unsigned integer of `size` bytes at `offset`, aligned to `size`."""
    offset = _align(buf, offset, size, write)
    if write:
        for i in range(size):
            buf[offset + i] = (value >> (8 * i)) & 0xFF
    return offset + size


@numba.njit(inline="always")
def _put_bytes(buf: np.ndarray, offset: int, data: np.ndarray, start: int, end: int, write: bool) -> int:
    """A CDR string: length (with the NUL) and the bytes data[start:end], then NUL."""
    offset = _put(buf, offset, end - start + 1, 4, write)
    if write:
        buf[offset:offset + end - start] = data[start:end]
        buf[offset + end - start] = 0
    return offset + end - start + 1


@numba.njit(inline="always")
def _put_float(scratch: np.ndarray, buf: np.ndarray, offset: int, value: float, write: bool) -> int:
    """value as the 1-element scratch array's float type (float32 or float64), aligned to its size."""
    size = scratch.itemsize
    offset = _align(buf, offset, size, write)
    if write:
        scratch[0] = value
        buf[offset:offset + size] = scratch.view(np.uint8)
    return offset + size


@numba.njit(cache=True, nogil=True)
def _encode_markers(buf: np.ndarray, write: bool, sec: int, nanosec: int, frame_id: np.ndarray,
                    names: np.ndarray, name_start: np.ndarray, ids: np.ndarray, actions: np.ndarray,
                    vertices: np.ndarray, colors: np.ndarray, faces: np.ndarray, vertex_start: np.ndarray,
                    face_start: np.ndarray) -> int:
    """visualization_msgs/MarkerArray (Jazzy field order) into buf (CDR after the 4-byte
    encapsulation header, so offsets are payload-relative); returns the payload size. With
    write=False nothing is written: the size only. Marker m has name names[name_start[m]:...],
    and, if it is an ADD, the triangles faces[face_start[m]:face_start[m+1]] (indices local to
    its vertices vertices[vertex_start[m]:...], float32 metres, colours RGB float32 0..1)."""
    b64 = np.zeros(1, np.float64)
    b32 = np.zeros(1, np.float32)
    body = buf[4:] if write else buf
    o = _put(body, 0, ids.shape[0], 4, write)
    empty = frame_id[:0]
    for m in range(ids.shape[0]):
        o = _put(body, o, sec & 0xFFFFFFFF, 4, write)
        o = _put(body, o, nanosec, 4, write)
        o = _put_bytes(body, o, frame_id, 0, frame_id.shape[0], write)
        o = _put_bytes(body, o, names, name_start[m], name_start[m + 1], write)
        o = _put(body, o, ids[m] & 0xFFFFFFFF, 4, write)
        o = _put(body, o, 11, 4, write)  # TRIANGLE_LIST
        o = _put(body, o, actions[m], 4, write)
        for value in (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0):  # pose (identity), scale 1
            o = _put_float(b64, body, o, value, write)
        for _ in range(4):  # color: used only where no per-vertex colour is given
            o = _put_float(b32, body, o, 1.0, write)
        o = _put(body, o, 0, 4, write)  # lifetime: forever
        o = _put(body, o, 0, 4, write)
        o = _put(body, o, 0, 1, write)  # frame_locked
        n_faces = face_start[m + 1] - face_start[m] if actions[m] == 0 else 0
        o = _put(body, o, 3 * n_faces, 4, write)  # points: geometry_msgs/Point, float64
        if n_faces:
            o = _align(body, o, 8, write)
            if write:
                points = body[o:o + 72 * n_faces].view(np.float64)
                for f in range(n_faces):
                    for corner in range(3):
                        v = vertex_start[m] + faces[face_start[m] + f, corner]
                        for axis in range(3):
                            points[9 * f + 3 * corner + axis] = vertices[v, axis]
            o += 72 * n_faces
        o = _put(body, o, 3 * n_faces, 4, write)  # colors: std_msgs/ColorRGBA, float32
        if n_faces and write:
            rgba = body[o:o + 48 * n_faces].view(np.float32)
            for f in range(n_faces):
                for corner in range(3):
                    v = vertex_start[m] + faces[face_start[m] + f, corner]
                    for c in range(3):
                        rgba[12 * f + 4 * corner + c] = colors[v, c]
                    rgba[12 * f + 4 * corner + 3] = 1.0
        o += 48 * n_faces
        o = _put_bytes(body, o, empty, 0, 0, write)  # texture_resource
        o = _put(body, o, 0, 4, write)  # texture: sensor_msgs/CompressedImage: stamp
        o = _put(body, o, 0, 4, write)
        o = _put_bytes(body, o, empty, 0, 0, write)  # frame_id
        o = _put_bytes(body, o, empty, 0, 0, write)  # format
        o = _put(body, o, 0, 4, write)  # data
        o = _put(body, o, 0, 4, write)  # uv_coordinates
        o = _put_bytes(body, o, empty, 0, 0, write)  # text
        o = _put_bytes(body, o, empty, 0, 0, write)  # mesh_resource
        o = _put_bytes(body, o, empty, 0, 0, write)  # mesh_file.filename
        o = _put(body, o, 0, 4, write)  # mesh_file.data
        o = _put(body, o, 0, 1, write)  # mesh_use_embedded_materials
    return o


def _check_meshes(meshes: Any) -> None:
    """Shapes and face indices of a BlockMeshes-like batch; ValueError saying what is wrong."""
    if meshes.vertices.ndim != 2 or meshes.vertices.shape[1] != 3 or meshes.faces.ndim != 2 \
            or meshes.faces.shape[1] != 3 or meshes.colors.shape != meshes.vertices.shape:
        raise ValueError(f"meshes need Nx3 vertices and colours and Mx3 faces, got {meshes.vertices.shape}, "
                         f"{meshes.colors.shape} and {meshes.faces.shape}")
    if len(meshes.faces):
        block_size = np.diff(meshes.vertex_offsets)
        per_face = np.repeat(block_size, np.diff(meshes.face_offsets))
        if meshes.faces.min() < 0 or np.any(meshes.faces.max(axis=1) >= per_face):
            raise ValueError("mesh faces index vertices that do not exist; the mesh is corrupt")


# CDR bytes per triangle of a TRIANGLE_LIST marker: 3 float64 points and 3 float32 RGBA colours
MARKER_BYTES_PER_FACE = 3 * 24 + 3 * 16
# the longest marker namespace: "senfunet_mesh_{}_{}_{}" of a block key's high bits (int64 keys >> 10)
_MAX_NS_BYTES = len("senfunet_mesh") + 3 * len(f"_{-(2 ** 53)}")


def _marker_bytes_without_faces(frame_id: str) -> int:
    """CDR bytes of one marker besides its triangles and its namespace, at most: a DELETE marker's
    (header, pose, the empty texture and mesh fields) with the padding that aligning its strings and
    its points can add."""
    one = marker_array_cdr({}, [(0, 0, 0)], stamp_ns=0, frame_id=frame_id)
    return len(one) - 8 - len("senfunet_mesh") + 3 + 3 + 7  # less the header and count; frame_id, ns, points padding


# ~/mesh messages are cut to about this size: the DDS writer keeps every sample of its history (and
# a spare) in buffers as large as the largest message, and a whole-room update is hundreds of MB.
MESH_MESSAGE_MAX_BYTES = 16 << 20


def marker_array_messages(
    changed: Any,
    removed: Iterable[tuple[int, int, int]] = (),
    *,
    stamp_ns: int,
    frame_id: str,
    delete_all_first: bool = False,
    max_bytes: int = MESH_MESSAGE_MAX_BYTES,
) -> Iterator[np.ndarray]:
    """One mesh update (see `marker_array_cdr`) as MarkerArray CDR arrays of max_bytes at most (a
    single block larger than that goes alone), consecutive runs of whole blocks; the DELETEALL and
    the DELETEs of removed blocks go in the first. Applied in order they equal the single message.
    The arrays share one buffer: use (publish) each before taking the next."""
    from senfunet_core.mesher import BlockMeshes

    meshes = changed if isinstance(changed, BlockMeshes) else BlockMeshes.from_meshes(dict(changed))
    removed = list(removed)
    if delete_all_first:  # a snapshot: after the DELETEALL a DELETE (removed, or no triangles) clears nothing
        meshes, removed = meshes.select(np.flatnonzero(np.diff(meshes.face_offsets) > 0)), []
    # each marker's fixed part counts too: a display mesh has tens of triangles a block, and parts
    # cut by their triangles alone came out a tenth larger than max_bytes
    names, _ = block_marker_ids(meshes.keys)
    fixed = _marker_bytes_without_faces(frame_id)
    block_bytes = (np.diff(meshes.face_offsets) * MARKER_BYTES_PER_FACE + fixed
                   + np.fromiter((len(name) for name in names), np.int64, len(names)))
    bytes_before = np.concatenate([[0], np.cumsum(block_bytes)])  # B+1: bytes of the blocks before each block
    budget = max_bytes - 8  # the encapsulation header and the marker count
    # the first part also holds the DELETEALL and the removed blocks' DELETEs (namespaces up to _MAX_NS_BYTES)
    first_budget = budget - (len(removed) + int(delete_all_first)) * (fixed + _MAX_NS_BYTES)
    buffer = np.zeros(0, np.uint8)
    start, first = 0, True
    while first or start < len(meshes):
        limit = bytes_before[start] + (first_budget if first else budget)
        stop = int(np.searchsorted(bytes_before, limit, side="right")) - 1
        stop = min(max(stop, start + 1), len(meshes))
        data = marker_array_cdr(meshes.blocks(start, stop), removed if first else (), stamp_ns=stamp_ns,
                                frame_id=frame_id, delete_all_first=delete_all_first and first, as_array=True,
                                out=buffer)
        assert isinstance(data, np.ndarray)  # as_array
        if data.base is not buffer:
            buffer = data
        yield data
        start, first = stop, False


def marker_array_cdr(
    changed: Mapping[tuple[int, int, int], Any] | Any,
    removed: Iterable[tuple[int, int, int]] = (),
    *,
    stamp_ns: int,
    frame_id: str,
    delete_all_first: bool = False,
    as_array: bool = False,
    out: np.ndarray | None = None,
) -> bytes | np.ndarray:
    """visualization_msgs/MarkerArray as CDR bytes (or, with as_array, the uint8 array they were
    written into, for `senfunet_ros.dds.publish_serialized`: no copy; written into `out` when that
    uint8 array is big enough, as `marker_array_messages` does for the parts of one update): one
    TRIANGLE_LIST marker per changed block, a DELETE marker per removed block, optionally led by a
    DELETEALL (a full snapshot).

    `changed`: block keys -> meshes with `vertices` (N,3), `faces` (M,3) and optional `colors`
    (N,3) in 0..1 (white without), or a `senfunet_core.mesher.BlockMeshes` batch (the engine's
    update: encoded without a Python step per block). A block whose mesh has no faces becomes a
    DELETE. Triangle corners go out as float64 points with RGBA colours, as TRIANGLE_LIST wants.
    """
    from senfunet_core.mesher import BlockMeshes

    meshes = changed if isinstance(changed, BlockMeshes) else BlockMeshes.from_meshes(dict(changed))
    _check_meshes(meshes)
    has_faces = np.diff(meshes.face_offsets) > 0
    keep = np.flatnonzero(has_faces)
    deletes: set[tuple[int, ...]] = set()
    if not delete_all_first:  # after a DELETEALL a DELETE (removed, or no triangles) clears nothing
        deletes.update(tuple(int(v) for v in key) for key in removed)
        deletes.update(map(tuple, meshes.keys[~has_faces].tolist()))
    delete_keys = np.array(sorted(deletes), np.int64).reshape(-1, 3)
    # markers: [DELETEALL], DELETEs, then the ADDs, which use the kept blocks' ranges
    delete_names, delete_ids = block_marker_ids(delete_keys)
    add_names, add_ids = block_marker_ids(meshes.keys[keep])
    names = [""] * int(delete_all_first) + delete_names + add_names
    ids = np.concatenate([np.zeros(int(delete_all_first), np.int64), delete_ids, add_ids])
    actions = np.concatenate([np.full(int(delete_all_first), MARKER_DELETEALL), np.full(len(delete_ids), MARKER_DELETE),
                              np.full(len(add_ids), MARKER_ADD)]).astype(np.int64)
    n_plain = len(ids) - len(add_ids)
    name_start = np.cumsum([0] + [len(n) for n in names], dtype=np.int64)
    pad = np.zeros(n_plain, np.int64)
    vertex_start = np.concatenate([pad, meshes.vertex_offsets[keep], meshes.vertex_offsets[-1:]])
    face_start = np.concatenate([pad, meshes.face_offsets[keep], meshes.face_offsets[-1:]])
    sec, nanosec = ns_to_stamp(stamp_ns)
    args = (sec, nanosec, np.frombuffer(frame_id.encode("utf-8"), np.uint8),
            np.frombuffer("".join(names).encode("ascii"), np.uint8), name_start, ids, actions,
            np.ascontiguousarray(meshes.vertices, np.float32), np.ascontiguousarray(meshes.colors, np.float32),
            np.ascontiguousarray(meshes.faces, np.int64), vertex_start, face_start)
    size = _encode_markers(np.zeros(0, np.uint8), False, *args)
    buf = out[: 4 + size] if out is not None and len(out) >= 4 + size else np.empty(4 + size, np.uint8)
    buf[:4] = (0, 1, 0, 0)  # encapsulation: CDR little endian
    _encode_markers(buf, True, *args)  # writes every byte, padding included
    return buf if as_array else buf.tobytes()


def delete_all_marker_array_cdr(*, stamp_ns: int, frame_id: str) -> bytes:
    """A MarkerArray holding one DELETEALL marker: clears every block in the subscriber."""
    data = marker_array_cdr({}, (), stamp_ns=stamp_ns, frame_id=frame_id, delete_all_first=True)
    assert isinstance(data, bytes)  # not as_array
    return data


def point_cloud2_cdr(
    positions_m: np.ndarray,
    alpha: np.ndarray,
    weights: np.ndarray,
    sensors: Sequence[str],
    *,
    stamp_ns: int,
    frame_id: str,
) -> bytes:
    """sensor_msgs/PointCloud2 as CDR bytes with float32 fields x, y, z, alpha, weight_<sensor>..."""
    positions_m = np.asarray(positions_m, dtype=np.float32)
    if positions_m.ndim != 2 or positions_m.shape[1] != 3:
        raise ValueError(f"cloud positions must be Nx3, got {positions_m.shape}")
    n = int(positions_m.shape[0])
    alpha = np.asarray(alpha, dtype=np.float32).reshape(-1)
    weights = np.asarray(weights, dtype=np.float32)
    if weights.ndim == 1:
        weights = weights.reshape(-1, 1)
    if alpha.shape[0] != n or weights.shape != (n, len(sensors)):
        raise ValueError(
            f"cloud has {n} points but alpha {alpha.shape} and weights {weights.shape} for sensors "
            f"{list(sensors)}; pass one alpha per point and one weight column per sensor"
        )
    names = ["x", "y", "z", "alpha"] + [f"weight_{s}" for s in sensors]
    point_step = 4 * len(names)
    table = np.empty((n, len(names)), dtype="<f4")  # one row per point, fields interleaved
    table[:, :3] = positions_m
    table[:, 3] = alpha
    table[:, 4:] = weights
    w = _CdrWriter()
    w.header(stamp_ns, frame_id)
    w.u32(1)  # height: unordered cloud
    w.u32(n)  # width
    w.u32(len(names))
    for i, name in enumerate(names):
        w.string(name)
        w.u32(4 * i)
        w.u8(_POINTFIELD_FLOAT32)
        w.u32(1)
    w.u8(0)  # is_bigendian
    w.u32(point_step)
    w.u32(point_step * n)
    w.u32(point_step * n)
    w.raw(table.tobytes())
    w.u8(1)  # is_dense: no invalid points
    return w.getvalue()
