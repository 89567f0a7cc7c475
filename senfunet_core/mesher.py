"""Triangle meshes and marching cubes over sparse blocks."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Mesh:
    """A triangle mesh in world coordinates (metres)."""

    vertices: np.ndarray  # Nx3 float32
    faces: np.ndarray  # Mx3 int32, counter-clockwise seen from the free side
    colors: np.ndarray | None = None  # Nx3 float32 RGB in 0..1

    @staticmethod
    def empty() -> "Mesh":
        return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])


def cell_mask(observed: np.ndarray) -> np.ndarray:
    """B x n^3 observed corners -> B x (n-1)^3 cells whose 8 corners are all observed."""
    o = observed
    cells = o[:, :-1, :-1, :-1] & o[:, 1:, :-1, :-1] & o[:, :-1, 1:, :-1] & o[:, :-1, :-1, 1:]
    return cells & o[:, 1:, 1:, :-1] & o[:, 1:, :-1, 1:] & o[:, :-1, 1:, 1:] & o[:, 1:, 1:, 1:]


@dataclass
class BlockTriangles:
    """Marching-cubes output of a batch of blocks, before splitting or welding."""

    vertices_vox: np.ndarray  # Vx3 float64 global voxel coordinates
    faces: np.ndarray  # Fx3 int64 into vertices_vox
    vertex_block: np.ndarray  # V index of each vertex's block in the batch
    face_block: np.ndarray  # F
    vertex_values: np.ndarray | None  # V interpolated extra value (e.g. alpha) or None


def marching_cubes_blocks(tsdf: np.ndarray, observed: np.ndarray, block_origin_vox: np.ndarray,
                          extra: np.ndarray | None = None) -> BlockTriangles:
    """Marching cubes at level 0 over B blocks at once.

    tsdf, observed, extra: B x (s+1)^3 samples: each block's s^3 voxels plus one more layer from
    its +x, +y, +z neighbours, so every cell a block owns is complete and neighbouring blocks'
    meshes meet exactly (a vertex on a seam is computed from the same two samples by both).
    Only cells whose 8 corners are observed produce triangles. block_origin_vox: Bx3 int, the
    global voxel index of each block's local (0, 0, 0).
    """
    from skimage.measure import marching_cubes

    n_blocks, n = tsdf.shape[0], tsdf.shape[1]
    empty = BlockTriangles(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64),
                           None if extra is None else np.zeros(0))
    cells = cell_mask(observed)
    if n_blocks == 0 or not cells.any():
        return empty
    # Blocks are stacked along x; skimage visits a cell when the mask is set at the cell's far
    # corner (x+1, y+1, z+1), so the mask is the cell mask shifted by one. Cells straddling two
    # stacked blocks never get a mask bit.
    mask = np.zeros((n_blocks, n, n, n), dtype=bool)
    mask[:, 1:, 1:, 1:] = cells
    volume = np.ascontiguousarray(tsdf, dtype=np.float32).reshape(n_blocks * n, n, n)
    values = volume[mask.reshape(volume.shape)]
    if values.size == 0 or values.min() > 0 or values.max() < 0:
        return empty
    try:
        verts, faces, _, _ = marching_cubes(volume, level=0.0, mask=mask.reshape(volume.shape))
    except RuntimeError:  # skimage requires min < 0 < max strictly (e.g. values touch 0 but never cross)
        return empty
    if len(faces) == 0:
        return empty
    vertex_block = np.floor(verts[:, 0] / n).astype(np.int64).clip(0, n_blocks - 1)
    local = verts.astype(np.float64)
    local[:, 0] -= vertex_block * n
    local = _exact_edge_positions(np.asarray(tsdf, dtype=np.float32), vertex_block, local)
    vertex_values = None
    if extra is not None:
        vertex_values = _interpolate(extra.astype(np.float32), vertex_block, local)
    global_vox = local + np.asarray(block_origin_vox, dtype=np.float64)[vertex_block]
    return BlockTriangles(global_vox, faces.astype(np.int64), vertex_block, vertex_block[faces[:, 0]], vertex_values)


def _exact_edge_positions(volumes: np.ndarray, block: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Recompute each vertex from its grid edge's two samples in float64.

    skimage returns float32 positions in the stacked volume, whose last bits depend on where a
    block sat in the stack (up to ~1e-3 voxel for large batches): recomputing from the block's own
    samples makes a vertex independent of batching, so incremental and whole meshes agree exactly.
    """
    if len(local) == 0:
        return local
    n = volumes.shape[1]
    off_grid = np.abs(local - np.round(local))
    axis = np.argmax(off_grid, axis=1)
    on_edge = off_grid.max(axis=1) >= 1e-4
    rows = np.nonzero(on_edge)[0]
    if len(rows) == 0:
        return local
    ax = axis[rows]
    base = np.round(local[rows]).astype(np.int64)
    base[np.arange(len(rows)), ax] = np.floor(local[rows, ax]).astype(np.int64)
    base = base.clip(0, n - 1)
    upper = base.copy()
    upper[np.arange(len(rows)), ax] += 1
    inside = upper[np.arange(len(rows)), ax] <= n - 1
    rows, ax, base, upper = rows[inside], ax[inside], base[inside], upper[inside]
    b = block[rows]
    va = volumes[b, base[:, 0], base[:, 1], base[:, 2]].astype(np.float64)
    vb = volumes[b, upper[:, 0], upper[:, 1], upper[:, 2]].astype(np.float64)
    denom = va - vb
    ok = denom != 0
    t = np.zeros_like(va)
    t[ok] = np.clip(va[ok] / denom[ok], 0.0, 1.0)
    out = local.copy()
    exact = base.astype(np.float64)
    exact[np.arange(len(rows)), ax] += t
    out[rows[ok]] = exact[ok]
    return out


def _interpolate(volumes: np.ndarray, block: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of B x n^3 volumes at per-vertex local coordinates."""
    n = volumes.shape[1]
    i0 = np.floor(local).astype(np.int64).clip(0, n - 2)
    t = local - i0
    out = np.zeros(len(local))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (t[:, 0] if dx else 1 - t[:, 0]) * (t[:, 1] if dy else 1 - t[:, 1]) * (t[:, 2] if dz else 1 - t[:, 2])
                out += w * volumes[block, i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz]
    return out


def weld(vertices_vox: np.ndarray, faces: np.ndarray, vertex_values: np.ndarray | None = None
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Merge the copies of a vertex made by neighbouring blocks and drop triangles that collapse.

    Every marching-cubes vertex lies on a grid edge: two of its voxel coordinates are integers.
    The edge (its lower end and axis) identifies the vertex; positions alone do not, since two
    blocks may interpolate the same edge from opposite ends and differ in the last bits.
    """
    if len(vertices_vox) == 0:
        return vertices_vox, faces, vertex_values
    off_grid = np.abs(vertices_vox - np.round(vertices_vox))
    axis = np.argmax(off_grid, axis=1)
    on_node = off_grid.max(axis=1) < 1e-4  # the surface passes through a sample exactly
    base = np.round(vertices_vox).astype(np.int64)
    rows = np.arange(len(base))
    base[rows, axis] = np.floor(vertices_vox[rows, axis]).astype(np.int64)
    base[on_node] = np.round(vertices_vox[on_node]).astype(np.int64)
    axis[on_node] = 3
    keys = np.concatenate([base, axis[:, None]], axis=1)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    faces = inverse[faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    values = None if vertex_values is None else vertex_values[first]
    return vertices_vox[first], faces[keep], values


def alpha_colors(alpha: np.ndarray) -> np.ndarray:
    """Sensor weighting as colour: alpha 1 (trust sensor 1) amber, alpha 0 (sensor 2) blue."""
    a = np.clip(np.asarray(alpha, dtype=np.float32), 0, 1)[:, None]
    sensor_1 = np.array([1.0, 0.72, 0.1], np.float32)
    sensor_2 = np.array([0.15, 0.4, 1.0], np.float32)
    return a * sensor_1 + (1 - a) * sensor_2


def to_mesh(vertices_vox: np.ndarray, faces: np.ndarray, voxel_size_m: float, vertex_alpha: np.ndarray | None) -> Mesh:
    colors = None if vertex_alpha is None else alpha_colors(vertex_alpha)
    return Mesh((vertices_vox * voxel_size_m).astype(np.float32), faces.astype(np.int32), colors)
