"""senfunet_core.decimate: a coarser display mesh, per block, without cracks between blocks."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from senfunet_core.decimate import decimate_block_meshes
from senfunet_core.mesher import BlockMeshes, Mesh


def _sphere_blocks(radius_m: float = 0.5, voxel_m: float = 0.01, block_m: float = 0.08) -> BlockMeshes:
    """A marching-cubes sphere cut into blocks by face centroid (vertices copied per block)."""
    from skimage.measure import marching_cubes

    n = int(2.4 * radius_m / voxel_m)
    axis = (np.arange(n) - n / 2) * voxel_m
    x, y, z = np.meshgrid(axis, axis, axis, indexing="ij")
    vertices, faces, _, _ = marching_cubes(np.sqrt(x**2 + y**2 + z**2) - radius_m, 0.0, spacing=(voxel_m,) * 3)
    vertices = (vertices + axis[0]).astype(np.float32)
    keys = np.floor(vertices[faces].mean(axis=1) / block_m).astype(np.int64)
    meshes = {}
    for key in np.unique(keys, axis=0):
        block_faces = faces[(keys == key).all(axis=1)]
        used, local = np.unique(block_faces, return_inverse=True)
        colors = np.tile(np.float32([0.2, 0.4, 0.6]), (len(used), 1))
        meshes[tuple(int(k) for k in key)] = Mesh(vertices[used], local.reshape(-1, 3).astype(np.int32), colors)
    return BlockMeshes.from_meshes(meshes)


def test_decimation_reduces_faces_and_stays_on_the_surface() -> None:
    full = _sphere_blocks()
    coarse = decimate_block_meshes(full, 0.03)
    assert len(coarse) == len(full) and np.array_equal(coarse.keys, full.keys)
    assert len(coarse.faces) < len(full.faces) / 6  # cells of 3 voxels: about 9x fewer triangles
    radius = np.linalg.norm(coarse.vertices, axis=1)
    assert np.abs(radius - 0.5).max() < 0.03  # merged vertices stay within a cell of the surface
    assert np.allclose(coarse.colors, [0.2, 0.4, 0.6])
    for b in range(len(coarse)):  # faces index their own block's vertices
        mesh = coarse.mesh(b)
        assert len(mesh.faces) == 0 or (mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices))
    # no cracks: a vertex on one block's border is the same point in every block that uses it
    tree = cKDTree(coarse.vertices)
    pairs = tree.query_pairs(1e-4, output_type="ndarray")
    assert len(pairs) and np.abs(coarse.vertices[pairs[:, 0]] - coarse.vertices[pairs[:, 1]]).max() == 0.0


def test_cell_zero_keeps_the_mesh() -> None:
    full = _sphere_blocks(radius_m=0.2)
    assert decimate_block_meshes(full, 0.0) is full
