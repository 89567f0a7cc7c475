"""Meshing the map's blocks: marching cubes over batches of blocks of one surface ("fused", a
sensor's, or "tsdf_fusion"), as per-block meshes (what the node sends) or as triangle batches (that
`extract_mesh` welds), and the seam triangles that go with blocks leaving memory (`map_bound`).

`BlockMesher` reads the grid and changes nothing; whoever calls it decides whether to hold the
engine's data lock (see the threading model in `engine`).
"""
from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import torch

from .block_store import BlockStore
from .fusion import WINDOW_BASE, WINDOW_FUSED, WINDOW_SENSOR, blocks_with_observed, fuse, mesh_windows
from .grid import BLOCK, block_keys, decode_alpha, keys_to_coords
from .mesher import BlockMeshes, BlockTriangles, Mesh, block_mesh_arrays, marching_cubes_blocks, to_mesh
from .scratch import ThreadScratch
from .stage_times import StageTimes

__all__ = ["FUSED", "MESH_READER_CODES", "MESH_READ_CODES", "TSDF_FUSION", "BlockMesher", "joined", "with_seams"]

TSDF_FUSION = "tsdf_fusion"
FUSED = "fused"
# Neighbour-table codes of the blocks whose marching-cubes cells read a block: itself and its
# -x, -y, -z neighbours (code 9*(dx+1) + 3*(dy+1) + (dz+1), offsets in {-1, 0}).
MESH_READER_CODES = np.array([9 * dx + 3 * dy + dz for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)])
# ... and of the blocks a block's cells read: itself and its +x, +y, +z neighbours
MESH_READ_CODES = np.array([9 * dx + 3 * dy + dz for dx in (1, 2) for dy in (1, 2) for dz in (1, 2)])


def joined(meshes: list[Mesh]) -> Mesh:
    """One mesh of several (vertices not shared between them)."""
    if len(meshes) == 1:
        return meshes[0]
    starts = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    colors = [m.colors if m.colors is not None else np.ones((len(m.vertices), 3), np.float32) for m in meshes]
    return Mesh(np.concatenate([m.vertices for m in meshes]),
                np.concatenate([m.faces + start for m, start in zip(meshes, starts)]).astype(np.int32),
                np.concatenate(colors))


def with_seams(archived: BlockMeshes, seams: dict[tuple[int, int, int], Mesh]) -> BlockMeshes:
    """The evicted blocks' meshes with the seam triangles that go with them (`BlockMesher.seam_meshes`)."""
    if not seams:
        return archived
    meshes = archived.as_dict()
    for block, seam in seams.items():
        meshes[block] = joined([meshes[block], seam]) if block in meshes else seam
    return BlockMeshes.from_meshes(meshes)


def _compact_offsets(offsets: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Offsets of the kept blocks' ranges when the dropped blocks' ranges are empty."""
    return np.concatenate([[offsets[0]], offsets[keep + 1]]).astype(np.int64)


class BlockMesher:
    """Marching cubes over a `BlockStore`'s blocks, in batches of `mesh_batch_blocks`.

    `which` names a surface: FUSED (the two sensors fused with alpha, optionally filtered), a
    sensor's name (its own TSDF), or TSDF_FUSION (the plain baseline's grid). `times` receives the
    seconds spent fusing windows and in marching cubes."""

    def __init__(self, store: BlockStore, *, sensors: tuple[str, ...], voxel_size_m: float, mesh_batch_blocks: int,
                 times: StageTimes) -> None:
        self.store = store
        self.sensors = sensors
        self.voxel_size_m = voxel_size_m
        self.batch_blocks = mesh_batch_blocks
        self.times = times
        self._scratch = ThreadScratch()  # per meshing thread: its mesh windows' buffers

    def channels(self, which: str) -> list[str]:
        """The channels `values` reads for `which`."""
        if which == FUSED:
            return ["tsdf0", "weight0", "tsdf1", "weight1", "alpha"]
        if which == TSDF_FUSION:
            return ["tsdf_base", "weight_base"]
        s = self.sensors.index(which)
        return [f"tsdf{s}", f"weight{s}"]

    def whole_blocks(self, slots: torch.Tensor, names: list[str]) -> dict[str, torch.Tensor]:
        """The channels of whole blocks, as float32 (the pools hold float16, alpha 8-bit codes)."""
        pools = self.store.grid.pools
        return {name: decode_alpha(pools[name][slots]) if name == "alpha" else pools[name][slots].float()
                for name in names}

    def values(self, blocks: dict[str, torch.Tensor], which: str, filtered: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """TSDF and observed mask of `which` from per-voxel channel tensors (`whole_blocks`)."""
        if which == FUSED:
            fused = fuse(blocks["tsdf0"], blocks["weight0"], blocks["tsdf1"], blocks["weight1"], blocks["alpha"],
                         apply_filter=filtered)
            return fused.tsdf_m, fused.observed
        if which == TSDF_FUSION:
            return blocks["tsdf_base"], blocks["weight_base"] > 0
        s = self.sensors.index(which)
        return blocks[f"tsdf{s}"], blocks[f"weight{s}"] > 0

    def triangles(self, slots: np.ndarray, which: str, filtered: bool) -> BlockTriangles:
        """Marching cubes over the given blocks of `which`, in one batch."""
        t0 = time.perf_counter()
        if which == FUSED:
            mode, names = WINDOW_FUSED, ("tsdf0", "weight0", "tsdf1", "weight1", "alpha")
        else:
            mode = WINDOW_BASE if which == TSDF_FUSION else WINDOW_SENSOR
            tsdf, weight = self.channels(which)
            names = (tsdf, weight, tsdf, weight, "alpha")
        views = self.store.views(*names)
        # only the blocks that can have triangles get a window (most of those an update re-meshes have none)
        meshable = np.flatnonzero(blocks_with_observed(slots, mode, filtered, views[1], views[3], views[4]))
        neighbours = self.store.neighbours(slots[meshable], MESH_READ_CODES)  # what the mesh windows read
        size = len(meshable) * 9**3
        out = (self._scratch.array("tsdf", size, np.float32), self._scratch.array("observed", size, np.bool_),
               self._scratch.array("alpha", size, np.float32))  # kept per thread between batches
        tsdf_m, observed, alpha = mesh_windows(neighbours, mode, filtered, *views, out=out)
        origins = self.store.grid.coords[slots[meshable]].numpy() * BLOCK
        t1 = time.perf_counter()
        triangles = marching_cubes_blocks(tsdf_m, observed, origins, alpha if which == FUSED else None)
        self.times.add(fusion=t1 - t0, marching_cubes=time.perf_counter() - t1)
        return triangles.spread(meshable, len(slots))

    def release_buffers(self) -> None:
        """Let go of every thread's window buffers (after a bulk extraction)."""
        self._scratch.release()

    def batches(self, slots: np.ndarray, which: str, filtered: bool) -> Iterator[BlockTriangles]:
        """`triangles` over any number of blocks, one batch at a time (a caller that keeps only
        what it needs of each holds one batch's buffers at once)."""
        for start in range(0, len(slots), self.batch_blocks):
            yield self.triangles(slots[start:start + self.batch_blocks], which, filtered)

    def block_meshes(self, slots: np.ndarray, coords: np.ndarray) -> BlockMeshes:
        """Fused, filtered per-block meshes in metres of one batch of blocks (coords: their block
        keys); blocks without triangles are left out. Timed as `block_meshes` per thread, as fusion
        and marching cubes are (the update's `mesh` time is its wall time, over every thread)."""
        t0 = time.perf_counter()
        tris = self.triangles(slots, FUSED, filtered=True)
        v_start, f_start = tris.vertex_offsets, tris.face_offsets
        assert tris.vertex_values is not None  # the fused mesh interpolates alpha (its colours)
        # the whole batch at once; blocks without triangles have empty ranges
        vertices, faces, colors = block_mesh_arrays(tris.vertices_vox, tris.faces, tris.vertex_values, v_start, f_start,
                                                    self.voxel_size_m)
        keep = np.flatnonzero(np.diff(f_start) > 0)
        meshes = BlockMeshes(coords[keep], vertices, colors, faces, _compact_offsets(v_start, keep),
                             _compact_offsets(f_start, keep))
        self.times.add(block_meshes=time.perf_counter() - t0)
        return meshes

    def seam_meshes(self, readers: np.ndarray, victim_coords: np.ndarray) -> dict[tuple[int, int, int], Mesh]:
        """The fused triangles of the cells of blocks staying (`readers`) that read blocks about to
        be evicted, by the evicted block they go with (the least key among those a cell reads):
        once the readers are re-meshed without the evicted voxels, the archive shows these instead
        (call before the removal)."""
        victim_keys = np.sort(block_keys(torch.from_numpy(victim_coords)).numpy())
        seams: dict[tuple[int, int, int], list[Mesh]] = {}
        for tris in self.batches(readers, FUSED, filtered=True):
            if len(tris.faces) == 0:
                continue
            # a triangle's cell: the floor of its centroid (strictly inside the cell it came from)
            cell = np.floor(tris.vertices_vox[tris.faces].mean(axis=1)).astype(np.int64)
            owner = np.full(len(cell), np.iinfo(np.int64).max)
            for corner in np.ndindex(2, 2, 2):  # the blocks of the cell's 8 corners
                key = block_keys(torch.from_numpy(np.floor_divide(cell + np.array(corner), BLOCK))).numpy()
                evicted = np.isin(key, victim_keys)
                owner[evicted] = np.minimum(owner[evicted], key[evicted])
            seam = np.flatnonzero(owner < np.iinfo(np.int64).max)
            owners = np.unique(owner[seam])
            for key, block in zip(owners.tolist(), keys_to_coords(torch.from_numpy(owners)).tolist()):
                faces = tris.faces[seam[owner[seam] == key]]
                used, local = np.unique(faces, return_inverse=True)
                values = tris.vertex_values[used] if tris.vertex_values is not None else None
                mesh = to_mesh(tris.vertices_vox[used], local.reshape(-1, 3), self.voxel_size_m, values)
                seams.setdefault(tuple(block), []).append(mesh)
        return {block: joined(parts) for block, parts in seams.items()}

    def mesh_readers(self, changed: np.ndarray) -> np.ndarray:
        """The blocks whose cells read any of these blocks: those to re-mesh when they changed."""
        if len(changed) == 0:
            return changed
        readers = self.store.neighbours(changed, MESH_READER_CODES)[:, MESH_READER_CODES]
        return np.unique(readers[readers >= 0])
