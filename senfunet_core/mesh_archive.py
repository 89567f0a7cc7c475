"""The final meshes of blocks the map bound evicted: map data is never dropped silently.

When the map outgrows its bound, the engine evaluates the weighting net on the blocks it evicts,
meshes them (fused, filtered) and hands the meshes here before freeing the blocks. They stay part
of the fused mesh: in every snapshot (`SenFuNet.block_meshes`), in `extract_mesh("fused")` and in
saved engine states. When a sensor sees such a block again, the engine allocates it anew, and
its live mesh replaces the archived one as soon as it has triangles (`replace`).
"""
from __future__ import annotations

import numpy as np

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
        self.replace({tuple(k) for k in meshes.keys.tolist()})
        self._meshes = BlockMeshes.concatenate([self._meshes, meshes])
        self._reindex()

    def replace(self, live_keys: set[BlockKey]) -> list[BlockKey]:
        """Forget the archived meshes of these blocks (their live meshes take over); returns the keys
        that were archived."""
        gone = [key for key in live_keys if key in self._row]
        if gone:
            keep = np.ones(len(self._meshes), bool)
            keep[[self._row[key] for key in gone]] = False
            self._meshes = self._meshes.select(np.flatnonzero(keep))
            self._reindex()
        return gone

    def meshes(self, exclude: set[BlockKey] | None = None) -> BlockMeshes:
        """The archived block meshes, without the blocks in `exclude`."""
        if not exclude:
            return self._meshes
        keep = [row for key, row in self._row.items() if key not in exclude]
        return self._meshes.select(np.sort(np.asarray(keep, np.int64)))

    def mesh(self, exclude: set[BlockKey] | None = None) -> Mesh:
        """The archived meshes as one mesh (vertices not welded across blocks)."""
        meshes = self.meshes(exclude)
        if len(meshes) == 0:
            return Mesh.empty()
        block_of_face = np.repeat(np.arange(len(meshes)), np.diff(meshes.face_offsets))
        faces = meshes.faces + meshes.vertex_offsets[:-1][block_of_face, None].astype(np.int32)
        return Mesh(meshes.vertices, faces.astype(np.int32), meshes.colors)

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
