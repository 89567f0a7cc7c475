"""PLY write/read: exact round trips, foreign variants, and clear errors."""
from __future__ import annotations

import numpy as np
import pytest

from senfunet_core.errors import InputError
from senfunet_core.mesher import Mesh
from senfunet_core.ply import read_ply, write_ply


def _mesh(with_colors: bool) -> Mesh:
    rng = np.random.default_rng(0)
    v = rng.normal(size=(50, 3)).astype(np.float32)
    f = rng.integers(0, 50, size=(80, 3)).astype(np.int32)
    c = rng.random((50, 3)).astype(np.float32) if with_colors else None
    return Mesh(v, f, c)


@pytest.mark.parametrize("with_colors", [False, True])
def test_round_trip_exact(tmp_path, with_colors):
    m = _mesh(with_colors)
    p = tmp_path / "m.ply"
    write_ply(p, m)
    r = read_ply(p)
    assert r.vertices.dtype == np.float32 and r.faces.dtype == np.int32
    np.testing.assert_array_equal(r.vertices, m.vertices)
    np.testing.assert_array_equal(r.faces, m.faces)
    if with_colors:
        assert r.colors is not None
        # Stored as uchar: within half a step of 1/255.
        assert np.max(np.abs(r.colors - m.colors)) <= 0.5 / 255 + 1e-7
    else:
        assert r.colors is None
    # Header layout is the documented one; no temp file left behind.
    head = p.read_bytes()[:300]
    assert b"format binary_little_endian 1.0" in head
    assert b"property list uchar int vertex_indices" in head
    assert [q.name for q in tmp_path.iterdir()] == ["m.ply"]


def test_empty_mesh_round_trip(tmp_path):
    write_ply(tmp_path / "e.ply", Mesh.empty())
    r = read_ply(tmp_path / "e.ply")
    assert r.n_vertices == 0 and r.n_faces == 0


def test_ascii_by_hand(tmp_path):
    text = """ply
format ascii 1.0
comment made by hand, with an extra property and ushort colours
element vertex 4
property double x
property double y
property double z
property float confidence
property ushort red
property ushort green
property ushort blue
element face 2
property list uchar uint vertex_indices
property uchar flags
end_header
0 0 0 0.5 65535 0 0
1 0 0 0.5 0 65535 0
0 1 0.25 0.5 0 0 65535
1 1 -1.5 0.5 0 0 0
3 0 1 2 7
3 2 1 3 7
"""
    p = tmp_path / "hand.ply"
    p.write_text(text)
    m = read_ply(p)
    np.testing.assert_array_equal(m.vertices, np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.25], [1, 1, -1.5]], np.float32))
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [2, 1, 3]])
    np.testing.assert_allclose(m.colors, [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]])


def test_binary_big_endian_foreign_variant(tmp_path):
    # Another tool's layout: big-endian, double coords, RGBA, an extra face property, int list
    # count, and an element after the faces that must be skipped.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    header = (b"ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\n"
              b"property double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
              b"property uchar alpha\n"
              b"element face 1\nproperty int valence_unused\nproperty list int int vertex_indices\n"
              b"element edge 1\nproperty int vertex1\nproperty int vertex2\nend_header\n")
    vrec = np.zeros(3, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("rgba", "u1", (4,))])
    vrec["x"], vrec["y"], vrec["z"] = v.T
    vrec["rgba"] = [[255, 0, 0, 255], [0, 255, 0, 255], [0, 0, 255, 255]]
    frec = np.zeros(1, dtype=[("val", ">i4"), ("n", ">i4"), ("idx", ">i4", (3,))])
    frec["n"], frec["idx"] = 3, [2, 0, 1]
    p = tmp_path / "be.ply"
    p.write_bytes(header + vrec.tobytes() + frec.tobytes() + np.array([0, 1], ">i4").tobytes())
    m = read_ply(p)
    np.testing.assert_array_equal(m.vertices, v.astype(np.float32))
    np.testing.assert_array_equal(m.faces, [[2, 0, 1]])
    np.testing.assert_allclose(m.colors, np.eye(3))


def test_truncated_file_names_file(tmp_path):
    p = tmp_path / "cut.ply"
    write_ply(p, _mesh(True))
    data = p.read_bytes()
    p.write_bytes(data[: len(data) - 7])
    with pytest.raises(InputError, match="cut.ply.*truncated"):
        read_ply(p)


def test_missing_and_not_ply(tmp_path):
    with pytest.raises(InputError, match="nope.ply"):
        read_ply(tmp_path / "nope.ply")
    q = tmp_path / "x.ply"
    q.write_bytes(b"solid stl\n")
    with pytest.raises(InputError, match="x.ply.*not a PLY"):
        read_ply(q)


def test_quads_rejected(tmp_path):
    p = tmp_path / "quad.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
                 "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                 "0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")
    with pytest.raises(InputError, match="quad.ply.*triangle"):
        read_ply(p)
    # The same mesh in binary: the face count check must catch it too.
    hdr = (b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
           b"property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n")
    body = np.zeros((4, 3), "<f4").tobytes() + bytes([3]) + np.array([0, 1, 2], "<i4").tobytes() \
        + bytes([4]) + np.array([0, 1, 2, 3], "<i4").tobytes()
    p.write_bytes(hdr + body)
    with pytest.raises(InputError, match="face 1 has 4 vertices"):
        read_ply(p)


def test_bad_face_index(tmp_path):
    p = tmp_path / "bad.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                 "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 5\n")
    with pytest.raises(InputError, match="bad.ply.*indices"):
        read_ply(p)


def test_writing_in_chunks_gives_the_same_bytes(tmp_path, monkeypatch):
    """write_ply writes its records a chunk at a time (memory): the file does not depend on the
    chunk size, colours rounded the same way."""
    from senfunet_core import ply

    rng = np.random.default_rng(5)
    mesh = Mesh(rng.normal(size=(1001, 3)).astype(np.float32), rng.integers(0, 1001, (2003, 3)).astype(np.int32),
                rng.uniform(0.0, 1.0, (1001, 3)).astype(np.float32))
    ply.write_ply(tmp_path / "whole.ply", mesh)
    monkeypatch.setattr(ply, "_CHUNK_ROWS", 7)
    ply.write_ply(tmp_path / "chunked.ply", mesh)
    whole = (tmp_path / "whole.ply").read_bytes()
    assert whole == (tmp_path / "chunked.ply").read_bytes()
    back = ply.read_ply(tmp_path / "chunked.ply")
    assert np.array_equal(back.vertices, mesh.vertices) and np.array_equal(back.faces, mesh.faces)
    assert np.abs(back.colors - mesh.colors).max() <= 0.5 / 255 + 1e-6
