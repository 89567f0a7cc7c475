"""Marching cubes over blocks (senfunet_core.mesher): closed and consistently oriented surfaces,
agreement with scikit-image, observed-cell masking, batch independence, ambiguous cases."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from senfunet_core.mesher import (_TABLES, BlockTriangles, Mesh, StreamingWeld, alpha_colors, marching_cubes_blocks,
                                  to_mesh, weld)

BLOCK = 8
N = BLOCK + 1


def grid_points(size: int) -> np.ndarray:
    """size^3 x 3 voxel coordinates (i, j, k) of a dense volume, float64."""
    a = np.arange(size, dtype=np.float64)
    return np.stack(np.meshgrid(a, a, a, indexing="ij"), axis=-1)


def sphere(size: int, centre, radius: float) -> np.ndarray:
    """Signed distance, positive outside (free space) as a TSDF."""
    return np.linalg.norm(grid_points(size) - np.asarray(centre), axis=-1) - radius


def torus(size: int, centre, major: float, minor: float) -> np.ndarray:
    p = grid_points(size) - np.asarray(centre)
    return np.hypot(np.hypot(p[..., 0], p[..., 1]) - major, p[..., 2]) - minor


def to_blocks(volume: np.ndarray, observed: np.ndarray | None = None, extra: np.ndarray | None = None):
    """A dense (8m+1)^3 volume as its m^3 blocks of 9^3 samples (each block's 8^3 voxels and the
    +x, +y, +z layer), their origins, and the same cut of `observed` and `extra`."""
    m = (volume.shape[0] - 1) // BLOCK
    assert volume.shape == (m * BLOCK + 1,) * 3
    if observed is None:
        observed = np.ones(volume.shape, bool)
    tsdf, obs, ext, origins = [], [], [], []
    for a in range(m):
        for b in range(m):
            for c in range(m):
                sl = np.s_[BLOCK * a:BLOCK * a + N, BLOCK * b:BLOCK * b + N, BLOCK * c:BLOCK * c + N]
                tsdf.append(volume[sl])
                obs.append(observed[sl])
                ext.append(np.zeros((N, N, N)) if extra is None else extra[sl])
                origins.append((BLOCK * a, BLOCK * b, BLOCK * c))
    return (np.array(tsdf, np.float32), np.array(obs), np.array(origins, np.int64),
            None if extra is None else np.array(ext, np.float32))


def mesh(volume: np.ndarray, observed: np.ndarray | None = None):
    tsdf, obs, origins, _ = to_blocks(volume, observed)
    return marching_cubes_blocks(tsdf, obs, origins)


def edge_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges of a triangle list and how many faces use each."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)


def assert_closed_and_oriented(faces: np.ndarray) -> int:
    """Every edge is used by exactly two faces, once in each direction; returns the edge count."""
    edges, counts = edge_counts(faces)
    assert len(faces) > 0
    assert np.all(counts == 2), f"edges by number of faces: {np.unique(counts, return_counts=True)}"
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed), "an edge is traversed twice in the same direction"
    return len(edges)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    v = vertices[faces]
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


# -- 1. closed surfaces ------------------------------------------------------------------------------

@pytest.mark.parametrize("field, euler", [
    (lambda: sphere(25, (12.56, 11.53, 12.24), 8.7), 2),
    (lambda: sphere(33, (15.02, 16.31, 17.22), 11.35), 2),
    (lambda: torus(33, (16.5, 15.59, 16.11), 9.2, 3.4), 0),
])
def test_closed_surfaces_after_welding(field, euler):
    volume = field()
    assert np.abs(volume).min() > 1e-3
    tris = mesh(volume)
    assert len(np.unique(tris.vertex_block)) > 1  # the surface really spans several blocks
    vertices, faces, _ = weld(tris.vertices_vox, tris.faces)
    assert len(faces) == len(tris.faces)  # nothing collapses: no sample sits on the surface
    n_edges = assert_closed_and_oriented(faces)
    assert len(vertices) - n_edges + len(faces) == euler


def test_exact_zero_samples_count_as_outside_and_stay_closed():
    """A sphere of integer radius around a sample: samples such as (5, 0, 0) lie exactly on it."""
    volume = sphere(25, (12, 12, 12), 5.0)
    assert np.sum(volume == 0) >= 6
    tris = mesh(volume)
    # a zero sample is outside: no vertex on an edge between a zero and a positive sample, and
    # the vertices on edges from a zero to an inside sample sit exactly on the zero sample
    zeros = np.argwhere(volume == 0).astype(np.float64)
    on_zero = (cKDTree(zeros).query(tris.vertices_vox)[0] == 0)
    assert on_zero.sum() > 0
    vertices, faces, _ = weld(tris.vertices_vox, tris.faces)
    n_edges = assert_closed_and_oriented(faces)
    assert len(vertices) - n_edges + len(faces) == 2
    # the same mesh, bit for bit, as with the zeros made tiny positive values
    nudged = mesh(np.where(volume == 0, 1e-30, volume))
    np.testing.assert_array_equal(nudged.vertices_vox, tris.vertices_vox)
    np.testing.assert_array_equal(nudged.faces, tris.faces)
    # ... and not as with tiny negative values
    assert len(mesh(np.where(volume == 0, -1e-30, volume)).faces) != len(tris.faces)


# -- 2. orientation ----------------------------------------------------------------------------------

def test_normals_point_towards_increasing_tsdf_like_scikit_image():
    from skimage.measure import marching_cubes

    centre, radius = np.array([12.56, 11.53, 12.24]), 8.7
    volume = sphere(25, centre, radius)
    tris = mesh(volume)
    normals = face_normals(tris.vertices_vox, tris.faces)
    outward = tris.vertices_vox[tris.faces].mean(axis=1) - centre  # the TSDF gradient direction
    area = np.linalg.norm(normals, axis=1)
    assert np.all(area > 0)
    assert np.all(np.einsum("ij,ij->i", normals, outward) > 0)
    # the convention of the scikit-image path this kernel replaced, on the same field
    sk_verts, sk_faces, _, _ = marching_cubes(volume.astype(np.float32), level=0.0)
    sk_normals = face_normals(sk_verts.astype(np.float64), sk_faces)
    sk_outward = sk_verts[sk_faces].mean(axis=1) - centre
    assert np.all(np.einsum("ij,ij->i", sk_normals, sk_outward) > 0)
    # enclosed volume (divergence theorem) is positive and close to the sphere's
    v = tris.vertices_vox[tris.faces]
    enclosed = np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6
    assert enclosed == pytest.approx(4 / 3 * np.pi * radius**3, rel=0.02)


def test_torus_normals_follow_the_gradient():
    centre = np.array([16.5, 15.59, 16.11])
    volume = torus(33, centre, 9.2, 3.4)
    tris = mesh(volume)
    c = tris.vertices_vox[tris.faces].mean(axis=1) - centre
    ring = np.hypot(c[:, 0], c[:, 1])
    gradient = np.stack([c[:, 0] * (1 - 9.2 / ring), c[:, 1] * (1 - 9.2 / ring), c[:, 2]], axis=1)
    assert np.all(np.einsum("ij,ij->i", face_normals(tris.vertices_vox, tris.faces), gradient) > 0)


def test_flipping_the_sign_reverses_the_orientation():
    """Inside and outside swapped (no zeros): the same vertices, normals now against the gradient."""
    centre = np.array([12.1, 11.74, 12.36])
    volume = torus(25, centre, 6.2, 2.4)
    a, b = mesh(volume), mesh(-volume)
    np.testing.assert_array_equal(np.unique(a.vertices_vox, axis=0), np.unique(b.vertices_vox, axis=0))
    for t, sign in ((a, 1), (b, -1)):
        c = t.vertices_vox[t.faces].mean(axis=1) - centre
        ring = np.hypot(c[:, 0], c[:, 1])
        gradient = np.stack([c[:, 0] * (1 - 6.2 / ring), c[:, 1] * (1 - 6.2 / ring), c[:, 2]], axis=1)
        assert np.all(sign * np.einsum("ij,ij->i", face_normals(t.vertices_vox, t.faces), gradient) > 0)
        assert_closed_and_oriented(weld(t.vertices_vox, t.faces)[1])


# -- 3. agreement with scikit-image ------------------------------------------------------------------

@pytest.mark.parametrize("field", [
    lambda: sphere(17, (8.49, 7.98, 7.99), 5.55),
    lambda: torus(17, (8.33, 7.56, 8.02), 4.7, 1.8),
])
def test_vertices_match_scikit_image(field):
    from skimage.measure import marching_cubes

    volume = field()
    assert np.abs(volume).min() > 1e-3  # no sample on (or nearly on) the surface
    tris = mesh(volume)
    vertices, _, _ = weld(tris.vertices_vox, tris.faces)
    sk_verts = np.unique(marching_cubes(volume.astype(np.float32), level=0.0)[0].astype(np.float64), axis=0)
    assert len(vertices) == len(sk_verts)
    d_ours, _ = cKDTree(sk_verts).query(vertices)
    d_sk, _ = cKDTree(vertices).query(sk_verts)
    assert d_ours.max() < 1e-6 and d_sk.max() < 1e-6


# -- 4. unobserved corners ---------------------------------------------------------------------------

def test_cells_with_an_unobserved_corner_produce_no_triangles():
    rng = np.random.default_rng(3)
    volume = sphere(25, (12.56, 11.53, 12.24), 8.7)
    observed = rng.random(volume.shape) > 0.08
    full, part = mesh(volume), mesh(volume, observed)
    o = observed
    complete = (o[:-1, :-1, :-1] & o[1:, :-1, :-1] & o[:-1, 1:, :-1] & o[:-1, :-1, 1:]
                & o[1:, 1:, :-1] & o[1:, :-1, 1:] & o[:-1, 1:, 1:] & o[1:, 1:, 1:])

    def cells(t: BlockTriangles) -> np.ndarray:
        return np.floor(t.vertices_vox[t.faces].mean(axis=1)).astype(np.int64)  # every face lies in one cell

    part_cells = cells(part)
    assert len(part.faces) > 0 and np.all(complete[tuple(part_cells.T)])
    # ... and exactly the full mesh's triangles in complete cells remain, bit for bit
    keep = complete[tuple(cells(full).T)]
    assert 0 < keep.sum() < len(full.faces)

    def triangles(t: BlockTriangles, rows) -> set:
        return {tuple(map(tuple, tri)) for tri in t.vertices_vox[t.faces[rows]]}

    assert triangles(part, slice(None)) == triangles(full, keep)


def test_nothing_observed_or_no_crossing_gives_empty_output():
    volume = sphere(17, (8.2, 7.6, 8.4), 5.5)
    tsdf, obs, origins, _ = to_blocks(volume)
    for t in (marching_cubes_blocks(tsdf, np.zeros_like(obs), origins),
              marching_cubes_blocks(np.abs(tsdf) + 1, obs, origins, np.ones_like(tsdf))):
        assert t.vertices_vox.shape == (0, 3) and t.faces.shape == (0, 3)
        np.testing.assert_array_equal(t.vertex_offsets, np.zeros(len(tsdf) + 1))
        np.testing.assert_array_equal(t.face_offsets, np.zeros(len(tsdf) + 1))
    empty = marching_cubes_blocks(tsdf[:0], obs[:0], origins[:0], tsdf[:0])
    assert empty.faces.shape == (0, 3) and empty.vertex_values.shape == (0,) and len(empty.face_offsets) == 1


# -- 5. batching -------------------------------------------------------------------------------------

def test_per_block_meshing_equals_one_batch_bit_for_bit():
    volume = torus(25, (12.1, 11.74, 12.36), 6.2, 2.4) + 0.3 * np.sin(grid_points(25).sum(-1))
    extra = grid_points(25) @ np.array([1.0, 2.0, -1.0]) + 3  # linear: exact along every edge
    tsdf, obs, origins, ext = to_blocks(volume, extra=extra)
    batch = marching_cubes_blocks(tsdf, obs, origins, ext)
    assert batch.vertices_vox.dtype == np.float64 and batch.faces.dtype == np.int64
    vo, fo = batch.vertex_offsets, batch.face_offsets
    assert vo[0] == 0 and vo[-1] == len(batch.vertices_vox) and np.all(np.diff(vo) >= 0)
    assert fo[0] == 0 and fo[-1] == len(batch.faces) and np.all(np.diff(fo) >= 0)
    np.testing.assert_array_equal(batch.vertex_block, np.repeat(np.arange(len(tsdf)), np.diff(vo)))
    np.testing.assert_array_equal(batch.face_block, np.repeat(np.arange(len(tsdf)), np.diff(fo)))
    # faces use only their own block's vertices; no degenerate faces
    assert np.all(batch.vertex_block[batch.faces] == batch.face_block[:, None])
    f = batch.faces
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    # one vertex per grid edge in a block
    for b in range(len(tsdf)):
        v = batch.vertices_vox[vo[b]:vo[b + 1]]
        assert len(np.unique(v, axis=0)) == len(v)
    # extra: linear interpolation along the vertex's edge
    np.testing.assert_allclose(batch.vertex_values, batch.vertices_vox @ np.array([1.0, 2.0, -1.0]) + 3, atol=1e-9)

    order = np.random.default_rng(0).permutation(len(tsdf))
    shuffled = marching_cubes_blocks(tsdf[order], obs[order], origins[order], ext[order])
    for pos, b in enumerate(order):
        single = marching_cubes_blocks(tsdf[b:b + 1], obs[b:b + 1], origins[b:b + 1], ext[b:b + 1])
        for other, ob in ((single, 0), (shuffled, pos)):
            v0, v1 = other.vertex_offsets[ob], other.vertex_offsets[ob + 1]
            f0, f1 = other.face_offsets[ob], other.face_offsets[ob + 1]
            np.testing.assert_array_equal(other.vertices_vox[v0:v1], batch.vertices_vox[vo[b]:vo[b + 1]])
            np.testing.assert_array_equal(other.vertex_values[v0:v1], batch.vertex_values[vo[b]:vo[b + 1]])
            np.testing.assert_array_equal(other.faces[f0:f1] - v0, batch.faces[fo[b]:fo[b + 1]] - vo[b])


def test_neighbouring_blocks_give_bit_identical_seam_vertices():
    volume = sphere(25, (12.56, 11.53, 12.24), 8.7)
    tris = mesh(volume)
    seam = np.any(np.mod(tris.vertices_vox, BLOCK) == 0, axis=1)  # on a block face: made by 2..4 blocks
    uniq, counts = np.unique(tris.vertices_vox[seam], axis=0, return_counts=True)
    assert len(uniq) > 50 and np.all(counts >= 2)


# -- 6. ambiguous cases ------------------------------------------------------------------------------

def noisy_field(size: int, seed: int) -> np.ndarray:
    """Random signs and magnitudes in [0.1, 1]: every kind of cell, many ambiguous faces, and no
    vertex near a sample (t in [1/11, 10/11])."""
    rng = np.random.default_rng(seed)
    return rng.choice([-1.0, 1.0], (size,) * 3) * rng.uniform(0.1, 1.0, (size,) * 3)


def ambiguous_face_count(volume: np.ndarray) -> int:
    inside = volume < 0
    count = 0
    for axis in range(3):
        v = np.moveaxis(inside, axis, 0)
        a, b, c, d = v[:, :-1, :-1], v[:, 1:, :-1], v[:, :-1, 1:], v[:, 1:, 1:]
        count += int(np.sum((a == d) & (b == c) & (a != b)))
    return count


def boundary_edges_ok(vertices: np.ndarray, edges: np.ndarray, complete: np.ndarray) -> bool:
    """Each edge lies on a cell face with a complete cell on exactly one side."""
    p, q = vertices[edges[:, 0]], vertices[edges[:, 1]]
    for a, b in zip(p, q):
        planes = [ax for ax in range(3) if a[ax] == b[ax] and a[ax] == np.round(a[ax])]
        mid = np.floor((a + b) / 2).astype(int)
        ok = False
        for ax in planes:
            lo, hi = mid.copy(), mid.copy()
            lo[ax], hi[ax] = int(a[ax]) - 1, int(a[ax])
            sides = [bool(complete[tuple(c)]) if np.all((c >= 0) & (c < complete.shape)) else False for c in (lo, hi)]
            ok |= sides[0] != sides[1]
        if not ok:
            return False
    return True


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_fields_are_watertight(seed):
    volume = noisy_field(25, seed)
    assert ambiguous_face_count(volume) > 1000
    tris = mesh(volume)
    # the kernel resolved ambiguous faces both ways
    assert len(tris.faces) > 10000
    vertices, faces, _ = weld(tris.vertices_vox, tris.faces)
    assert len(faces) == len(tris.faces)
    edges, counts = edge_counts(faces)
    assert counts.max() == 2
    # edges used once lie on the volume's boundary, in one of its faces
    once = edges[counts == 1]
    p, q = vertices[once[:, 0]], vertices[once[:, 1]]
    on_boundary = np.any(((p == 0) & (q == 0)) | ((p == 24) & (q == 24)), axis=1)
    assert len(once) > 0 and np.all(on_boundary)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)


def test_random_fields_with_holes_are_closed_except_at_unobserved_cells():
    rng = np.random.default_rng(7)
    volume = noisy_field(17, 7)
    observed = rng.random(volume.shape) > 0.03
    o = observed
    complete = (o[:-1, :-1, :-1] & o[1:, :-1, :-1] & o[:-1, 1:, :-1] & o[:-1, :-1, 1:]
                & o[1:, 1:, :-1] & o[1:, :-1, 1:] & o[:-1, 1:, 1:] & o[1:, 1:, 1:])
    vertices, faces, _ = weld(*[getattr(mesh(volume, observed), k) for k in ("vertices_vox", "faces")])
    edges, counts = edge_counts(faces)
    assert counts.max() == 2 and (counts == 1).sum() > 100
    assert boundary_edges_ok(vertices, edges[counts == 1], complete)


def test_ambiguous_face_rule_is_the_bilinear_saddle():
    """One face with inside corners (0,0) and (1,1): joined across the face iff their product
    exceeds the outside corners' product. Two cells share the face; the welded mesh is closed
    except at the volume boundary either way, and the triangles on the face's two sides agree."""
    for inside_product, joined in ((0.5 * 0.5, False), (0.9 * 0.9, True)):
        volume = np.ones((17, 17, 17))
        # face x = 8, corners (y, z) in {8, 9}^2, shared by the cells x = 7 and x = 8
        a = np.sqrt(inside_product)
        volume[8, 8, 8] = volume[8, 9, 9] = -a
        volume[8, 9, 8] = volume[8, 8, 9] = 0.7
        tris = mesh(volume)
        vertices, faces, _ = weld(tris.vertices_vox, tris.faces)
        assert_closed_and_oriented(faces)
        # joined: one surface around both inside samples; separated: two (Euler characteristic 2 each)
        n_edges = len(edge_counts(faces)[0])
        assert len(vertices) - n_edges + len(faces) == (2 if joined else 4)


def test_generated_table():
    """Every entry: triangles use only the case's crossed edges, each crossed edge at least once,
    no repeated edge in a triangle, and every triangle side used once in each direction except
    the loop boundary (a cube face crossing), which is used once."""
    T = _TABLES
    lo, axis = T["edge_lo"], T["edge_axis"]
    hi = lo | (1 << axis)
    for case in range(256):
        crossed = {e for e in range(12) if (case >> lo[e] & 1) != (case >> hi[e] & 1)}
        for entry in range(T["case_offset"][case], T["case_offset"][case + 1]):
            tris = T["tri_edge"][entry, :3 * T["tri_count"][entry]].reshape(-1, 3)
            assert set(tris.ravel()) == crossed
            assert np.all((tris[:, 0] != tris[:, 1]) & (tris[:, 1] != tris[:, 2]) & (tris[:, 0] != tris[:, 2]))
            sides = [(t[i], t[(i + 1) % 3]) for t in tris for i in range(3)]
            assert len(set(sides)) == len(sides)
            boundary = [s for s in sides if (s[1], s[0]) not in set(sides)]
            assert len(boundary) == len(crossed)  # one segment per crossed edge start on the cube faces
    assert T["case_offset"][1] - T["case_offset"][0] == 1 and T["tri_count"][T["case_offset"][0]] == 0


def test_other_block_sizes_give_the_same_surface():
    """Blocks of 4^3 voxels (n = 5) and 8^3 (n = 9) over the same volume: the same welded vertices."""
    volume = torus(17, (8.33, 7.56, 8.02), 4.7, 1.8).astype(np.float32)
    nine = mesh(volume)
    tsdf, origins = [], []
    for a in range(4):
        for b in range(4):
            for c in range(4):
                tsdf.append(volume[4 * a:4 * a + 5, 4 * b:4 * b + 5, 4 * c:4 * c + 5])
                origins.append((4 * a, 4 * b, 4 * c))
    tsdf = np.array(tsdf)
    five = marching_cubes_blocks(tsdf, np.ones_like(tsdf, bool), np.array(origins))
    v9, f9, _ = weld(nine.vertices_vox, nine.faces)
    v5, f5, _ = weld(five.vertices_vox, five.faces)
    np.testing.assert_array_equal(np.unique(v9, axis=0), np.unique(v5, axis=0))
    assert len(f5) == len(f9)
    assert_closed_and_oriented(f5)
    with pytest.raises(ValueError):
        marching_cubes_blocks(np.zeros((2, 17, 17, 17), np.float32), np.ones((2, 17, 17, 17), bool), np.zeros((2, 3)))


@pytest.mark.parametrize("spread", [50, 2**40])
def test_unique_edges_equals_numpy_unique_over_rows(spread):
    """The packed one-dimensional unique gives np.unique(axis=0)'s order, first rows and inverse;
    an extent too large to pack takes the row-wise path with the same result."""
    from senfunet_core.mesher import _unique_edges

    rng = np.random.default_rng(3)
    base = rng.integers(-spread, spread, (4000, 3))
    base = np.concatenate([base, base[::3]])  # repeated edges
    axis = np.concatenate([rng.integers(0, 4, 4000), rng.integers(0, 4, 4000)[::3]])
    axis[4000:] = axis[:4000][::3]
    first, inverse = _unique_edges(base, axis)
    _, first_rows, inverse_rows = np.unique(np.concatenate([base, axis[:, None]], axis=1), axis=0,
                                           return_index=True, return_inverse=True)
    np.testing.assert_array_equal(first, first_rows)
    np.testing.assert_array_equal(inverse, inverse_rows.reshape(-1))
    assert len(first) < len(base)


@pytest.mark.parametrize("span", [50, 3 << 20])  # packed into one int64 key; too wide to pack: by rows
def test_edge_keys_are_unique_like_rows(span):
    from senfunet_core.mesher import _unique_edges

    rng = np.random.default_rng(span)
    base = rng.integers(-span // 2, span // 2, (20_000, 3))
    base[rng.random(len(base)) < 0.5] = base[0]  # many repeats
    base[: 1000] = base[1000:2000]
    axis = rng.integers(0, 4, len(base))
    _, first, inverse = np.unique(np.concatenate([base, axis[:, None]], axis=1), axis=0, return_index=True,
                                  return_inverse=True)
    got_first, got_inverse = _unique_edges(base, axis)
    np.testing.assert_array_equal(got_first, first)
    np.testing.assert_array_equal(got_inverse, inverse.reshape(-1))


def _assert_same_mesh(got: Mesh, want: Mesh) -> None:
    assert got.vertices.dtype == want.vertices.dtype == np.float32 and got.faces.dtype == want.faces.dtype == np.int32
    assert got.vertices.tobytes() == want.vertices.tobytes() and got.faces.tobytes() == want.faces.tobytes()
    assert (got.colors is None) == (want.colors is None)
    if want.colors is not None:
        assert got.colors.tobytes() == want.colors.tobytes()


@pytest.mark.parametrize("bounds", ["blocks", "too small"])
def test_streaming_weld_equals_weld_of_all_batches_byte_for_byte(bounds):
    """Batches welded as they come (compact keys, float32 metres) give the mesh `weld` + `to_mesh`
    make of all batches at once: same vertex order, faces and colours; also past the given block
    bounds (keys then kept as rows) and with a coloured mesh in metres (an archive) added last."""
    volume = torus(25, (12.1, 11.74, 12.36), 6.2, 2.4) + 0.3 * np.sin(grid_points(25).sum(-1))
    volume[np.abs(volume) < 0.05] = 0.0  # samples exactly on the surface: vertices on grid nodes
    extra = np.clip(grid_points(25) @ np.array([0.01, 0.02, -0.01]) + 0.4, 0.0, 1.0)
    tsdf, obs, origins, ext = to_blocks(volume, extra=extra)
    origins = origins - np.array([80, 8, -16])  # negative block coordinates too
    voxel_size_m = 0.01
    coords = origins // BLOCK
    low, high = (coords.min(axis=0), coords.max(axis=0)) if bounds == "blocks" else (coords[0], coords[0])
    welder = StreamingWeld(voxel_size_m, low, high)
    batches = [marching_cubes_blocks(tsdf[i:i + 5], obs[i:i + 5], origins[i:i + 5], ext[i:i + 5])
               for i in range(0, len(tsdf), 5)]
    for b in batches:
        welder.add(b.vertices_vox, b.faces, b.vertex_values)
    offsets = np.cumsum([0] + [len(b.vertices_vox) for b in batches])
    vertices = np.concatenate([b.vertices_vox for b in batches])
    faces = np.concatenate([b.faces + o for b, o in zip(batches, offsets)]).astype(np.int32)
    values = np.concatenate([b.vertex_values for b in batches])
    welded, welded_faces, welded_values = weld(vertices, faces, values)
    assert len(welded) < len(vertices) and np.any(np.abs(welded - np.round(welded)).max(axis=1) < 1e-4)
    want = to_mesh(welded, welded_faces, voxel_size_m, welded_values)
    # the same batches and a coloured mesh in metres elsewhere (sharing some vertices with them)
    far = Mesh((vertices[:300] * voxel_size_m + np.array([0.0, 0.0, 0.96])).astype(np.float32),
               faces[faces.max(axis=1) < 300][:100], np.full((300, 3), 0.5, np.float32))
    far.vertices[:50] = (vertices[:50] * voxel_size_m).astype(np.float32)
    with_far = StreamingWeld(voxel_size_m, low, high)
    for b in batches:
        with_far.add(b.vertices_vox, b.faces, b.vertex_values)
    with_far.add_colored_m(far.vertices, far.faces, far.colors)
    _assert_same_mesh(welder.mesh(), want)
    both_v = np.concatenate([vertices, far.vertices / voxel_size_m])
    both_f = np.concatenate([faces, far.faces + len(vertices)])
    w, f, c = weld(both_v, both_f, np.concatenate([alpha_colors(values), far.colors]))
    _assert_same_mesh(with_far.mesh(), Mesh((w * voxel_size_m).astype(np.float32), f.astype(np.int32), c))
    assert welder.mesh().n_faces == 0  # emptied


def test_block_mesh_arrays_equal_to_mesh_per_block_to_the_bit():
    """The one-pass kernel the live mesh uses makes what `to_mesh` makes of each block's triangles
    (faces local to the block), alpha outside 0..1 and NaN included."""
    from senfunet_core.mesher import block_mesh_arrays

    volume = torus(25, (12.1, 11.74, 12.36), 6.2, 2.4)
    tsdf, obs, origins, ext = to_blocks(volume, extra=np.zeros_like(volume))
    tris = marching_cubes_blocks(tsdf, obs, origins - np.array([80, 8, -16]), ext)
    values = np.linspace(-0.5, 1.5, len(tris.vertices_vox))  # below 0 and above 1 too
    values[::97] = np.nan
    vertices, faces, colors = block_mesh_arrays(tris.vertices_vox, tris.faces, values, tris.vertex_offsets,
                                                tris.face_offsets, 0.013)
    blocks = [b for b in range(len(tris.vertex_offsets) - 1) if tris.face_offsets[b + 1] > tris.face_offsets[b]]
    assert len(blocks) > 3
    for b in blocks:
        v0, v1 = tris.vertex_offsets[b], tris.vertex_offsets[b + 1]
        f0, f1 = tris.face_offsets[b], tris.face_offsets[b + 1]
        want = to_mesh(tris.vertices_vox[v0:v1], tris.faces[f0:f1] - v0, 0.013, values[v0:v1])
        np.testing.assert_array_equal(vertices[v0:v1], want.vertices)
        np.testing.assert_array_equal(faces[f0:f1], want.faces)
        np.testing.assert_array_equal(colors[v0:v1], want.colors)
