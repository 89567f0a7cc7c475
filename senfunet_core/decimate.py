"""A coarser display mesh from per-block meshes: vertex clustering on a grid of `cell_m`.

Every vertex falls in a cell of a global grid; a cell's vertices merge into one at their mean
position and colour, computed over all blocks of the batch, so the blocks of one batch meet
without cracks; triangles whose corners merge collapse and are dropped. Each block keeps its own
copy of the merged vertices it uses (in the order its faces first use them), so the result is
again one mesh per block (the markers stay per block). For display only: the map and saved meshes
keep full resolution.

One numba pass over the vertices (cells found in a hash table, not by sorting) and one over the
faces; it releases the GIL, so the node's integration runs meanwhile.
"""
from __future__ import annotations

import numba
import numpy as np

from senfunet_core.mesher import BlockMeshes

__all__ = ["decimate_block_meshes", "warm_up"]


@numba.njit(cache=True, nogil=True)
def _cluster_vertices(cells: np.ndarray) -> tuple[np.ndarray, int]:
    """Cluster id per vertex (V x 3 int64 cells -> V int64), numbered in order of first
    occurrence, and the number of clusters: an open-addressing hash table over the cells."""
    n = cells.shape[0]
    capacity = 1024
    while capacity < 2 * n:
        capacity *= 2
    mask = capacity - 1
    slot_cluster = np.full(capacity, -1, np.int64)
    cluster_cell = np.empty((n, 3), np.int64)
    cluster = np.empty(n, np.int64)
    n_clusters = 0
    for v in range(n):
        x, y, z = cells[v, 0], cells[v, 1], cells[v, 2]
        h = (x * 73856093) ^ (y * 19349669) ^ (z * 83492791)
        h ^= h >> 17
        i = h & mask
        while True:
            c = slot_cluster[i]
            if c < 0:
                slot_cluster[i] = n_clusters
                cluster_cell[n_clusters, 0], cluster_cell[n_clusters, 1], cluster_cell[n_clusters, 2] = x, y, z
                cluster[v] = n_clusters
                n_clusters += 1
                break
            if cluster_cell[c, 0] == x and cluster_cell[c, 1] == y and cluster_cell[c, 2] == z:
                cluster[v] = c
                break
            i = (i + 1) & mask
    return cluster, n_clusters


@numba.njit(cache=True, nogil=True)
def _decimate(vertices: np.ndarray, colors: np.ndarray, faces: np.ndarray, vertex_offsets: np.ndarray,
              face_offsets: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                                np.ndarray]:
    """(vertices, colours, faces, vertex offsets, face offsets) of the clustered per-block meshes."""
    n_vertices, n_blocks = vertices.shape[0], len(vertex_offsets) - 1
    cells = np.empty((n_vertices, 3), np.int64)
    for v in range(n_vertices):
        for a in range(3):
            cells[v, a] = np.int64(np.floor(vertices[v, a] / np.float32(cell_m)))
    cluster, n_clusters = _cluster_vertices(cells)
    # mean position and colour per cluster, summed in vertex order in float64
    sums = np.zeros((n_clusters, 6), np.float64)
    counts = np.zeros(n_clusters, np.float64)
    for v in range(n_vertices):
        c = cluster[v]
        counts[c] += 1.0
        for a in range(3):
            sums[c, a] += vertices[v, a]
            sums[c, 3 + a] += colors[v, a]
    # per block: the faces that keep three distinct clusters, their clusters numbered from 0 in the block
    out_faces = np.empty((faces.shape[0], 3), np.int32)
    used = np.empty(3 * faces.shape[0], np.int64)
    seen_in = np.full(n_clusters, -1, np.int64)  # the last block that numbered the cluster
    local = np.empty(n_clusters, np.int64)
    out_vertex_offsets = np.zeros(n_blocks + 1, np.int64)
    out_face_offsets = np.zeros(n_blocks + 1, np.int64)
    n_used = n_faces = 0
    for b in range(n_blocks):
        base, block_start = vertex_offsets[b], n_used
        for f in range(face_offsets[b], face_offsets[b + 1]):
            g0, g1, g2 = cluster[base + faces[f, 0]], cluster[base + faces[f, 1]], cluster[base + faces[f, 2]]
            if g0 == g1 or g1 == g2 or g0 == g2:
                continue  # collapsed
            for corner, g in enumerate((g0, g1, g2)):
                if seen_in[g] != b:
                    seen_in[g] = b
                    local[g] = n_used - block_start
                    used[n_used] = g
                    n_used += 1
                out_faces[n_faces, corner] = local[g]
            n_faces += 1
        out_vertex_offsets[b + 1] = n_used
        out_face_offsets[b + 1] = n_faces
    out_vertices = np.empty((n_used, 3), np.float32)
    out_colors = np.empty((n_used, 3), np.float32)
    for i in range(n_used):
        c = used[i]
        for a in range(3):
            out_vertices[i, a] = sums[c, a] / counts[c]
            out_colors[i, a] = sums[c, 3 + a] / counts[c]
    return out_vertices, out_colors, out_faces[:n_faces], out_vertex_offsets, out_face_offsets


def decimate_block_meshes(meshes: BlockMeshes, cell_m: float) -> BlockMeshes:
    """`meshes` with vertices clustered on a grid of `cell_m` metres (0 or less: unchanged)."""
    if cell_m <= 0 or len(meshes.faces) == 0:
        return meshes
    vertices, colors, faces, vertex_offsets, face_offsets = _decimate(
        np.ascontiguousarray(meshes.vertices, np.float32), np.ascontiguousarray(meshes.colors, np.float32),
        np.ascontiguousarray(meshes.faces), np.asarray(meshes.vertex_offsets, np.int64),
        np.asarray(meshes.face_offsets, np.int64), float(cell_m))
    return BlockMeshes(meshes.keys, vertices, colors, faces, vertex_offsets, face_offsets)


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernel now, not in the first mesh update."""
    from senfunet_core.mesher import Mesh

    triangle = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]], np.int32),
                    np.zeros((3, 3), np.float32))
    decimate_block_meshes(BlockMeshes.from_meshes({(0, 0, 0): triangle}), 0.5)
