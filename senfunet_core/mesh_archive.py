"""The final meshes of blocks the map bound evicted: map data is never dropped silently.

When the map outgrows its bound, the engine evaluates the weighting net on the blocks it evicts,
meshes them (fused, filtered) and hands the meshes here before freeing the blocks. They stay part
of the fused mesh: in every snapshot (`SenFuNet.block_meshes`), in `extract_mesh("fused")` and in
saved engine states. When a sensor sees such a block again, the engine allocates it anew; an
archived triangle stays shown until all 8 corner blocks of its marching-cubes cell are in memory
again (the live mesh then has that cell: `prune`, `visible`), so seam cells whose other corners are
still on disk stay, and a block whose live mesh became empty shows no stale surface.
"""
from __future__ import annotations

import numpy as np

import torch

from .grid import BLOCK, block_keys
from .mesher import BlockMeshes, Mesh

__all__ = ["MeshArchive"]

BlockKey = tuple[int, int, int]


class MeshArchive:
    """Block key -> final fused mesh of an evicted block (world frame, metres)."""

    def __init__(self) -> None:
        self._meshes = BlockMeshes.concatenate([])
        self._row: dict[BlockKey, int] = {}  # key -> block index in _meshes

    def __len__(self) -> int:
        return len(self._row)

    def __contains__(self, key: BlockKey) -> bool:
        return key in self._row

    @property
    def n_faces(self) -> int:
        return int(self._meshes.face_offsets[-1])

    def add(self, meshes: BlockMeshes) -> None:
        """Archive these blocks' meshes (a block archived before is replaced)."""
        if len(meshes) == 0:
            return
        replaced = [self._row[key] for key in map(tuple, meshes.keys.tolist()) if key in self._row]
        keep = np.ones(len(self._meshes), bool)
        keep[replaced] = False
        self._meshes = BlockMeshes.concatenate([self._meshes.select(np.flatnonzero(keep)), meshes])
        self._reindex()

    def add_merged(self, meshes: BlockMeshes, in_memory: np.ndarray, voxel_size_m: float) -> None:
        """Archive these blocks' meshes; what was archived under the same keys for cells that are not
        all in memory now (`in_memory`: sorted keys of the blocks in memory, the evicted ones still
        among them) stays beside them: those cells are in none of the new meshes."""
        if len(meshes) == 0:
            return
        new_keys = {tuple(k) for k in meshes.keys.tolist()}
        old = [key for key in new_keys if key in self._row]
        if old:
            kept = self._meshes.select(np.array([self._row[key] for key in old], np.int64))
            kept = _drop_meshable(kept, in_memory, voxel_size_m)
            merged = {key: mesh for key, mesh in meshes.as_dict().items()}
            for key, mesh in kept.as_dict().items():
                merged[key] = _joined(merged[key], mesh)
            meshes = BlockMeshes.from_meshes(merged)
        self.add(meshes)

    def prune(self, keys: set[BlockKey], in_memory: np.ndarray, voxel_size_m: float) -> None:
        """Drop, from the archived meshes of these blocks, the triangles of cells whose 8 corners are all
        in blocks in memory (`in_memory`: their sorted keys): the live mesh has those cells."""
        rows = np.array(sorted(self._row[key] for key in keys if key in self._row), np.int64)
        if len(rows) == 0:
            return
        pruned = _drop_meshable(self._meshes.select(rows), in_memory, voxel_size_m)
        keep = np.ones(len(self._meshes), bool)
        keep[rows] = False
        self._meshes = BlockMeshes.concatenate([self._meshes.select(np.flatnonzero(keep)), pruned])
        self._reindex()

    def visible(self, in_memory: np.ndarray, voxel_size_m: float) -> BlockMeshes:
        """The archived meshes without the triangles of cells the live mesh has (all corners in memory)."""
        return _drop_meshable(self._meshes, in_memory, voxel_size_m)

    def get(self, key: BlockKey) -> Mesh | None:
        row = self._row.get(key)
        return None if row is None else self._meshes.mesh(row)

    def meshes(self) -> BlockMeshes:
        """Every archived block mesh."""
        return self._meshes

    def keys_near(self, coords: np.ndarray) -> set[BlockKey]:
        """The archived blocks among these blocks (B x 3) and their 26 neighbours."""
        if not len(self._row) or not len(coords):
            return set()
        offsets = np.array(list(np.ndindex(3, 3, 3)), np.int64) - 1
        around = np.unique((np.asarray(coords, np.int64)[:, None, :] + offsets[None]).reshape(-1, 3), axis=0)
        archived = np.sort(block_keys(torch.from_numpy(self._meshes.keys)).numpy())
        hits = np.isin(block_keys(torch.from_numpy(around)).numpy(), archived)
        return set(map(tuple, around[hits].tolist()))

    def clear(self) -> None:
        self._meshes = BlockMeshes.concatenate([])
        self._row = {}

    def state_dict(self) -> dict[str, np.ndarray]:
        m = self._meshes
        return {"keys": m.keys, "vertices": m.vertices, "colors": m.colors, "faces": m.faces,
                "vertex_offsets": m.vertex_offsets, "face_offsets": m.face_offsets}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self._meshes = BlockMeshes(*(np.asarray(state[name]) for name in (
            "keys", "vertices", "colors", "faces", "vertex_offsets", "face_offsets")))
        self._reindex()

    def _reindex(self) -> None:
        self._row = {key: row for row, key in enumerate(map(tuple, self._meshes.keys.tolist()))}


def as_mesh(meshes: BlockMeshes) -> Mesh:
    """Block meshes as one mesh (vertices not welded across blocks)."""
    if len(meshes) == 0:
        return Mesh.empty()
    block_of_face = np.repeat(np.arange(len(meshes)), np.diff(meshes.face_offsets))
    faces = meshes.faces + meshes.vertex_offsets[:-1][block_of_face, None].astype(np.int32)
    return Mesh(meshes.vertices, faces.astype(np.int32), meshes.colors)


def union(live: BlockMeshes, archived: BlockMeshes) -> BlockMeshes:
    """Per block key, the live mesh and the archived one joined (a block's marker shows both)."""
    if len(archived) == 0:
        return live
    if len(live) == 0:
        return archived
    live_row = {key: row for row, key in enumerate(map(tuple, live.keys.tolist()))}
    both: dict[BlockKey, Mesh] = {}
    only_archived = []
    for row, key in enumerate(map(tuple, archived.keys.tolist())):
        if key in live_row:
            both[key] = _joined(live.mesh(live_row[key]), archived.mesh(row))
        else:
            only_archived.append(row)
    only_live = [row for key, row in live_row.items() if key not in both]
    return BlockMeshes.concatenate([live.select(np.array(only_live, np.int64)),
                                    archived.select(np.array(only_archived, np.int64)),
                                    BlockMeshes.from_meshes(both)])


def _joined(a: Mesh, b: Mesh) -> Mesh:
    return Mesh(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.faces, b.faces + len(a.vertices)]),
                np.concatenate([a.colors, b.colors]) if a.colors is not None and b.colors is not None else None)


def meshable_faces(vertices_m: np.ndarray, faces: np.ndarray, in_memory: np.ndarray, voxel_size_m: float,
                   face_blocks: np.ndarray) -> np.ndarray:
    """Per triangle: whether the 8 corners of its marching-cubes cell (the floor of its centroid, in
    voxels) all lie in blocks whose keys are in the sorted array `in_memory`. A triangle on a face
    between two cells (its centroid on a voxel plane: either cell may have made it, and both may)
    counts as meshable when either cell is; a triangle without area (marching cubes at corners exactly
    0), whose cell cannot be told, when the block it is archived under (`face_blocks`: per triangle,
    that block's key) is in memory."""
    if len(faces) == 0 or len(in_memory) == 0:
        return np.zeros(len(faces), bool)
    corners = vertices_m[faces].astype(np.float64) / voxel_size_m
    centroid = corners.mean(axis=1)
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    meshable = np.zeros(len(faces), bool)
    for shift in (-1e-3, 1e-3):
        cell = np.floor(centroid + shift).astype(np.int64)
        all_in = np.ones(len(faces), bool)
        for corner in np.ndindex(2, 2, 2):
            keys = block_keys(torch.from_numpy(np.floor_divide(cell + np.array(corner), BLOCK))).numpy()
            at = np.minimum(np.searchsorted(in_memory, keys), len(in_memory) - 1)
            all_in &= in_memory[at] == keys
        meshable |= all_in
    flat = area <= 1e-6
    at = np.minimum(np.searchsorted(in_memory, face_blocks[flat]), len(in_memory) - 1)
    meshable[flat] = in_memory[at] == face_blocks[flat]
    return meshable


def _drop_meshable(meshes: BlockMeshes, in_memory: np.ndarray, voxel_size_m: float) -> BlockMeshes:
    """These block meshes without the triangles `meshable_faces` finds (blocks left empty go; unused
    vertices stay)."""
    if len(meshes) == 0:
        return meshes
    block_of_face = np.repeat(np.arange(len(meshes)), np.diff(meshes.face_offsets))
    global_faces = meshes.faces + meshes.vertex_offsets[:-1][block_of_face, None]
    face_blocks = block_keys(torch.from_numpy(meshes.keys)).numpy()[block_of_face]
    keep = ~meshable_faces(meshes.vertices, global_faces, in_memory, voxel_size_m, face_blocks)
    if keep.all():
        return meshes
    counts = np.bincount(block_of_face[keep], minlength=len(meshes))
    face_offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    out = BlockMeshes(meshes.keys, meshes.vertices, meshes.colors, meshes.faces[keep], meshes.vertex_offsets,
                      face_offsets)
    return out.select(np.flatnonzero(counts > 0))
