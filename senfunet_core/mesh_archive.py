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

from collections.abc import Iterable

import numpy as np
import torch

from .grid import BLOCK, keys_to_coords
from .mesh_chunks import FIELD_NAMES, SEAL_BYTES, MeshChunks, packed_keys
from .block_mesher import joined
from .mesher import BlockMeshes, Mesh

__all__ = ["MeshArchive"]

BlockKey = tuple[int, int, int]
_AROUND = np.array(list(np.ndindex(3, 3, 3)), np.int64) - 1  # a block and its 26 neighbours


class MeshArchive:
    """Block key -> final fused mesh of an evicted block (world frame, metres), stored in `chunks`
    (what is large on disk, memory-mapped: see mesh_chunks)."""

    def __init__(self, *, directory: str | None = None, seal_bytes: int = SEAL_BYTES) -> None:
        self.chunks = MeshChunks(directory=directory, seal_bytes=seal_bytes)

    def __len__(self) -> int:
        return len(self.chunks)

    def __contains__(self, key: BlockKey) -> bool:
        return bool(self.held([key]))

    def add(self, meshes: BlockMeshes, in_memory: np.ndarray, voxel_size_m: float) -> None:
        """Archive these blocks' meshes; what was archived under the same keys for cells that are not
        all in memory now (`in_memory`: sorted packed keys of the blocks in memory, the evicted ones
        still among them) stays beside them: those cells are in none of the new meshes."""
        if len(meshes) == 0:
            return
        kept = drop_meshable(self.chunks.select(packed_keys(meshes.keys)), in_memory, voxel_size_m)
        if len(kept):
            merged = meshes.as_dict()
            for key, mesh in kept.as_dict().items():
                merged[key] = joined([merged[key], mesh])
            meshes = BlockMeshes.from_meshes(merged)
        self.chunks.put(meshes)

    def prune(self, keys: set[BlockKey], in_memory: np.ndarray, voxel_size_m: float) -> None:
        """Drop, from the archived meshes of these blocks, the triangles of cells whose 8 corners are all
        in blocks in memory (`in_memory`: their sorted packed keys): the live mesh has those cells."""
        if not keys:
            return
        held = self.chunks.select(packed_keys(np.array(sorted(keys))))
        pruned = drop_meshable(held, in_memory, voxel_size_m)
        if pruned is not held:
            emptied = np.setdiff1d(packed_keys(held.keys), packed_keys(pruned.keys))
            self.chunks.put(pruned, removed=emptied)

    def visible(self, in_memory: np.ndarray, voxel_size_m: float) -> BlockMeshes:
        """The archived meshes without the triangles of cells the live mesh has (all corners in memory),
        looked for only in blocks next to one in memory."""
        parts = []
        for part in self.chunks.parts():
            near = _next_to(part.keys, in_memory)
            parts += [part.select(np.flatnonzero(~near)),
                      drop_meshable(part.select(np.flatnonzero(near)), in_memory, voxel_size_m)]
        return BlockMeshes.concatenate(parts)

    def select(self, keys: Iterable[BlockKey]) -> BlockMeshes:
        """The archived meshes of those of these blocks that have one."""
        return self.chunks.select(packed_keys(_as_coords(keys)))

    def held(self, keys: Iterable[BlockKey] | np.ndarray, *, around: bool = False) -> set[BlockKey]:
        """Those of these blocks (keys, or B x 3 coordinates), and with `around` of their 26 neighbours
        too, that have an archived mesh (with nothing archived, no bound reached: found at once)."""
        if not len(self.chunks):
            return set()
        coords = blocks_around(_as_coords(keys)) if around else _as_coords(keys)
        hits = np.zeros(len(coords), bool)
        for _, found, _ in self.chunks.find(packed_keys(coords)):
            hits |= found
        return set(map(tuple, coords[hits].tolist()))

    def meshes(self) -> BlockMeshes:
        """Every archived block mesh (read-only)."""
        return BlockMeshes.concatenate(list(self.chunks.parts()))

    def clear(self) -> None:
        self.chunks.clear()

    def state_dict(self) -> dict[str, np.ndarray]:
        m = self.meshes()  # (a chunk's own arrays when it is the only one: copied, writable, in RAM)
        return {name: np.array(getattr(m, name)) for name in FIELD_NAMES}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        self.chunks.clear()
        self.chunks.put(BlockMeshes(*(np.asarray(state[name]) for name in FIELD_NAMES)))


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
    live_keys, archived_keys = packed_keys(live.keys), packed_keys(archived.keys)
    in_archive, in_live = np.isin(live_keys, archived_keys), np.isin(archived_keys, live_keys)
    live_rows, archived_rows = np.flatnonzero(in_archive), np.flatnonzero(in_live)  # pairs in key order:
    live_rows = live_rows[np.argsort(live_keys[live_rows])]
    archived_rows = archived_rows[np.argsort(archived_keys[archived_rows])]
    both = {tuple(live.keys[a].tolist()): joined([live.mesh(a), archived.mesh(b)])
            for a, b in zip(live_rows.tolist(), archived_rows.tolist())}
    return BlockMeshes.concatenate([live.select(np.flatnonzero(~in_archive)),
                                    archived.select(np.flatnonzero(~in_live)), BlockMeshes.from_meshes(both)])


def blocks_around(coords: np.ndarray) -> np.ndarray:
    """These blocks (B x 3) and their 26 neighbours, each once (N x 3)."""
    # sorted and deduplicated by hand: np.unique hashes int64 keys, which is slower than sorting them
    around = np.sort(packed_keys(np.asarray(coords, np.int64)[:, None, :] + _AROUND[None]))
    around = around[np.flatnonzero(np.diff(around, prepend=around[:1] - 1))]
    return keys_to_coords(torch.from_numpy(around)).numpy()


def _as_coords(keys: Iterable[BlockKey] | np.ndarray) -> np.ndarray:
    return np.array(keys if isinstance(keys, np.ndarray) else list(keys), np.int64).reshape(-1, 3)


def _next_to(coords: np.ndarray, in_memory: np.ndarray) -> np.ndarray:
    """Per block (B x 3): whether it or one of its 26 neighbours is in memory (sorted packed keys)."""
    near = np.zeros(len(coords), bool)
    if not len(in_memory) or not len(coords):
        return near
    for offset in _AROUND:
        keys = packed_keys(coords + offset)
        at = np.minimum(np.searchsorted(in_memory, keys), len(in_memory) - 1)
        near |= in_memory[at] == keys
    return near


def meshable_faces(vertices_m: np.ndarray, faces: np.ndarray, in_memory: np.ndarray, voxel_size_m: float,
                   face_blocks: np.ndarray) -> np.ndarray:
    """Per triangle: whether the 8 corners of its marching-cubes cell (the floor of its centroid, in
    voxels) all lie in blocks whose keys are in the sorted array `in_memory`. A triangle on a face
    between two cells (its centroid on a voxel plane: either cell may have made it, and both may)
    counts as meshable when the cell in the block it is archived under is (either cell, when both lie
    in that block); a triangle without area (marching cubes at corners exactly
    0), whose cell cannot be told, when the block it is archived under (`face_blocks`: per triangle,
    that block's key) is in memory."""
    if len(faces) == 0 or len(in_memory) == 0:
        return np.zeros(len(faces), bool)
    corners = vertices_m[faces].astype(np.float64) / voxel_size_m
    centroid = corners.mean(axis=1)
    area = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    meshable = np.zeros(len(faces), bool)
    cells = [np.floor(centroid + shift).astype(np.int64) for shift in (-1e-3, 1e-3)]
    # A triangle is archived under the block its cell lies in: where the two cells lie in different
    # blocks, that tells which one made it (the other cell, in memory, need not have made the same
    # triangle: an evicted block's face triangle went when its neighbour across the face left later)
    made_it = [packed_keys(np.floor_divide(cell, BLOCK)) == face_blocks for cell in cells]
    either = made_it[0] == made_it[1]  # same block (or neither): either cell may have made it
    for cell, made in zip(cells, made_it):
        all_in = np.ones(len(faces), bool)
        for corner in np.ndindex(2, 2, 2):
            keys = packed_keys(np.floor_divide(cell + np.array(corner), BLOCK))
            at = np.minimum(np.searchsorted(in_memory, keys), len(in_memory) - 1)
            all_in &= in_memory[at] == keys
        meshable |= all_in & (made | either)
    flat = area <= 1e-6
    at = np.minimum(np.searchsorted(in_memory, face_blocks[flat]), len(in_memory) - 1)
    meshable[flat] = in_memory[at] == face_blocks[flat]
    return meshable


def drop_meshable(meshes: BlockMeshes, in_memory: np.ndarray, voxel_size_m: float) -> BlockMeshes:
    """These block meshes without the triangles `meshable_faces` finds (blocks left empty go), and a
    block that lost some without the vertices only those used: `MeshArchive.add` joins what is kept of
    a block's archived mesh with its new one, so a block evicted again and again beside one that stays
    on disk would otherwise carry every earlier mesh's vertices along, growing with each eviction."""
    if len(meshes) == 0:
        return meshes
    block_of_face = np.repeat(np.arange(len(meshes)), np.diff(meshes.face_offsets))
    global_faces = meshes.faces + meshes.vertex_offsets[:-1][block_of_face, None]
    face_blocks = packed_keys(meshes.keys)[block_of_face]
    keep = ~meshable_faces(meshes.vertices, global_faces, in_memory, voxel_size_m, face_blocks)
    if keep.all():
        return meshes
    lost_faces = np.zeros(len(meshes), bool)
    lost_faces[block_of_face[~keep]] = True
    block_of_face, global_faces = block_of_face[keep], global_faces[keep]
    block_of_vertex = np.repeat(np.arange(len(meshes)), np.diff(meshes.vertex_offsets))
    used = ~lost_faces[block_of_vertex]  # the blocks that lost no triangle stay as they are
    used[global_faces.ravel()] = True
    vertex_offsets = np.concatenate([[0], np.cumsum(np.bincount(block_of_vertex[used], minlength=len(meshes)))])
    new_index = np.cumsum(used) - 1  # a used vertex's row among the used ones
    faces = new_index[global_faces] - vertex_offsets[block_of_face, None]
    counts = np.bincount(block_of_face, minlength=len(meshes))
    face_offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    out = BlockMeshes(meshes.keys, np.asarray(meshes.vertices)[used], np.asarray(meshes.colors)[used],
                      faces.astype(np.int32), vertex_offsets.astype(np.int64), face_offsets)
    return out.select(np.flatnonzero(counts > 0))
