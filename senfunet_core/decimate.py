"""A coarser display mesh from per-block meshes: vertex clustering on a grid of `cell_m`.

Every vertex falls in a cell of a global grid; a cell's vertices merge into one at their mean
position and colour, computed over all blocks of the batch, so the blocks of one batch meet
without cracks; triangles whose corners merge collapse and are dropped. Each block keeps its own
copy of the merged vertices it uses, so the result is again one mesh per block (the markers stay
per block). For display only: the map and saved meshes keep full resolution.

Pure numpy, no Python loop over vertices or blocks.
"""
from __future__ import annotations

import numpy as np

from senfunet_core.mesher import BlockMeshes

__all__ = ["decimate_block_meshes"]


def decimate_block_meshes(meshes: BlockMeshes, cell_m: float) -> BlockMeshes:
    """`meshes` with vertices clustered on a grid of `cell_m` metres (0 or less: unchanged)."""
    if cell_m <= 0 or len(meshes.faces) == 0:
        return meshes
    n_blocks = len(meshes)
    face_block = np.repeat(np.arange(n_blocks), np.diff(meshes.face_offsets))  # F
    cells = np.floor(meshes.vertices / np.float32(cell_m)).astype(np.int64)  # V x 3
    _, cluster = np.unique(cells, axis=0, return_inverse=True)
    cluster = cluster.reshape(-1)
    n_clusters = int(cluster.max()) + 1
    counts = np.bincount(cluster, minlength=n_clusters).astype(np.float64)[:, None]
    positions = np.stack([np.bincount(cluster, meshes.vertices[:, a], n_clusters) for a in range(3)], 1) / counts
    colors = np.stack([np.bincount(cluster, meshes.colors[:, a], n_clusters) for a in range(3)], 1) / counts
    # faces as global cluster ids; collapsed ones go
    global_faces = cluster[meshes.faces + meshes.vertex_offsets[face_block][:, None]]  # F x 3
    keep = ((global_faces[:, 0] != global_faces[:, 1]) & (global_faces[:, 1] != global_faces[:, 2])
            & (global_faces[:, 0] != global_faces[:, 2]))
    global_faces, face_block = global_faces[keep], face_block[keep]
    # per block, the clusters its faces use, numbered from 0 in the block
    pair = face_block[:, None].astype(np.int64) * n_clusters + global_faces  # F x 3, sorted by block
    used, local = np.unique(pair.reshape(-1), return_inverse=True)
    used_block, used_cluster = used // n_clusters, used % n_clusters
    vertex_offsets = np.searchsorted(used_block, np.arange(n_blocks + 1)).astype(np.int64)
    faces = (local.reshape(-1, 3) - vertex_offsets[face_block][:, None]).astype(np.int32)
    face_offsets = np.searchsorted(face_block, np.arange(n_blocks + 1)).astype(np.int64)
    return BlockMeshes(meshes.keys, positions[used_cluster].astype(np.float32),
                       colors[used_cluster].astype(np.float32), faces, vertex_offsets, face_offsets)
