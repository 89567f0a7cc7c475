"""The map's store: the sparse grid and each block's scheduling state, and eviction.

`BlockStore` holds the `BlockGrid` (blocks, hash table, one pool per channel) and, per block slot,
the flags the engine schedules work by. It knows nothing of integration, the weighting net or
meshing: the engine and the alpha scheduler read and set the flags; whoever changes the store
holds the engine's data lock (see the threading model in `engine`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch

from .grid import ALL_NEIGHBOURS, BLOCK, BlockGrid, kernel_view, masked_neighbours, neighbour_table

__all__ = ["BlockStore", "Eviction"]


@dataclass
class Eviction:
    """Blocks an eviction dropped, and where the others went (slots stay 0..n_blocks-1)."""

    dropped_keys: np.ndarray  # N int64 keys (grid.block_keys) of the dropped blocks
    new_slot: np.ndarray  # old slot -> new slot, -1 for a dropped block

    def follow(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The new slots of these blocks, without the dropped ones, and which of them were kept."""
        moved = self.new_slot[slots]
        kept = moved >= 0
        return moved[kept], kept

    def then(self, later: Eviction) -> Eviction:
        """This eviction followed by `later` (a later slice of the same eviction) as one: slots held
        from before this one are followed through both."""
        new_slot = self.new_slot.copy()
        kept = new_slot >= 0
        new_slot[kept] = later.new_slot[new_slot[kept]]
        return Eviction(np.concatenate([self.dropped_keys, later.dropped_keys]), new_slot)


class BlockStore:
    """The grid and, per block slot (arrays as long as the grid's capacity):
    - alpha_pending: integrated into since the last alpha schedule;
    - reach_changed, reach_renewed: since then, the blocks within 2 voxels of its voxels whose
      weighting-net inputs changed, and of those first observed or whose TSDF changed sign
      (bits of neighbour codes, integrator.REACH_OF_VOXEL);
    - stale: alpha to re-evaluate: 0 no, 1 inputs changed, 2 new or sign-changed voxels, 3 never evaluated;
    - evaluated: alpha evaluated at least once;
    - no_targets: when last checked, the block held no voxel alpha matters for;
    - last_reached: the last alpha schedule that made it stale (the newest are served first);
    - touched_s: when integration last wrote its voxels (monotonic seconds; NaN: never);
    - last_change_s: the latest of those integrations, among the ones that schedule took, whose
      changes reach it (NaN: never made stale), so that the scheduler knows how long alpha has
      waited there since the block's last change;
    - mesh_pending: TSDF or alpha changed since it was meshed;
    - mesh_due: a block to re-mesh (its cells read a change) that an update with a meshing budget left
      for a later one: the number of the update that first left it (0: none), so the oldest go first;
    - meshed: its fused mesh had triangles when last meshed;
    - surface_voxels: its voxels near a sensor's surface when last counted (`alpha.near_surface_voxels`),
      -1 when made stale since: how much surface judging it may show, where it has no mesh."""

    _FLAGS = {"alpha_pending": bool, "reach_changed": np.int32, "reach_renewed": np.int32, "stale": np.int8,
              "evaluated": bool, "no_targets": bool, "last_reached": np.int64, "touched_s": np.float64,
              "last_change_s": np.float64, "mesh_pending": bool, "mesh_due": np.int64, "meshed": bool,
              "surface_voxels": np.int16}
    _FILL = {"touched_s": np.nan, "last_change_s": np.nan, "surface_voxels": -1}  # the others start at 0 (False)

    alpha_pending: np.ndarray
    reach_changed: np.ndarray
    reach_renewed: np.ndarray
    stale: np.ndarray
    evaluated: np.ndarray
    no_targets: np.ndarray
    last_reached: np.ndarray
    touched_s: np.ndarray
    last_change_s: np.ndarray
    mesh_pending: np.ndarray
    mesh_due: np.ndarray
    meshed: np.ndarray
    surface_voxels: np.ndarray

    def __init__(self, grid: BlockGrid) -> None:
        self.grid = grid
        self.clear_flags()

    @property
    def n_blocks(self) -> int:
        return self.grid.n_blocks

    def clear(self) -> None:
        """Forget every block."""
        self.grid.clear()
        self.clear_flags()

    def clear_flags(self) -> None:
        for name, dtype in self._FLAGS.items():
            setattr(self, name, np.zeros(0, dtype))
        self.grow_flags()

    def grow_flags(self) -> None:
        """Per-block flags as long as the grid's capacity (after the grid grew)."""
        grow = self.grid.capacity - len(self.stale)
        if grow > 0:
            for name, dtype in self._FLAGS.items():
                setattr(self, name, np.concatenate([getattr(self, name),
                                                    np.full(grow, self._FILL.get(name, 0), dtype)]))

    def nbytes(self) -> int:
        """Bytes of the map in memory: the grid's (`BlockGrid.nbytes`) and the per-block flags."""
        return self.grid.nbytes() + sum(getattr(self, name).nbytes for name in self._FLAGS)

    def views(self, *names: str) -> list[np.ndarray]:
        """Flat kernel views of pools (fetch them under the data lock: pools move when they grow)."""
        return [kernel_view(self.grid.pools[name]).reshape(-1) for name in names]

    def neighbours(self, slots: np.ndarray, codes: np.ndarray = ALL_NEIGHBOURS) -> np.ndarray:
        """B x 27 slots of the blocks around these (grid.neighbour_table: the neighbours `codes`, -1 for
        the others), committed blocks only. Safe
        without the data lock (alpha threads, meshing): the hash table is taken as one pair, which a
        growing grid replaces whole, and the blocks a frame is still allocating (past n_blocks, read
        first: the allocation policy may yet drop them or move them to other slots) count as absent,
        as do blocks added meanwhile (they are marked, and read by the next update)."""
        n_blocks = self.grid.n_blocks
        table_keys, table_slots = self.grid.hash_table
        table = neighbour_table(table_keys, table_slots, self.grid.slot_keys, slots, codes)
        table[table >= n_blocks] = -1
        return table

    def reached(self, slots: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The committed neighbours each block's 27-bit mask names (`grid.masked_neighbours`): (index
        into slots, neighbour code, the neighbour's slot). Safe without the data lock, as `neighbours`."""
        n_blocks = self.grid.n_blocks
        table_keys, table_slots = self.grid.hash_table
        sources, codes, targets = masked_neighbours(table_keys, table_slots, self.grid.slot_keys, slots, masks)
        committed = targets < n_blocks
        return sources[committed], codes[committed], targets[committed]

    def observed_voxels(self, weight_channels: list[str]) -> int:
        """Voxels with a positive weight in any of these channels (one or two), counted in place:
        the status asks for it while the node runs, and a stacked copy of the weight pools grows
        with the map."""
        n = self.grid.n_blocks * BLOCK**3
        first, *rest = (self.grid.pools[name] for name in weight_channels)
        if len(rest) > 1:
            raise ValueError(f"observed_voxels counts one or two weight channels, got {len(weight_channels)}")
        second = rest[0] if rest else first
        if first.dtype == second.dtype == torch.float16:  # float16 bits: positive exactly where > 0 as int16
            return int(_count_positive(kernel_view(first).reshape(-1)[:n], kernel_view(second).reshape(-1)[:n]))
        return int(((first.reshape(-1)[:n] > 0) | (second.reshape(-1)[:n] > 0)).sum())

    def farthest(self, point_m: np.ndarray, *, keep: int, voxel_size_m: float, touched_since_s: float = np.inf
                 ) -> np.ndarray:
        """Slots of all blocks but the `keep` to keep (sorted): first those touched at or after
        `touched_since_s` (what the latest frames see, wherever the camera looks), then the nearest
        to point_m."""
        n = self.grid.n_blocks
        if keep <= 0:  # a bound of one block keeps 90% of it: none (argpartition has no (n)th of n)
            return np.arange(n)
        centres_m = (self.grid.coords[:n].numpy() * BLOCK + (BLOCK - 1) / 2) * voxel_size_m
        distance = np.linalg.norm(centres_m - point_m, axis=1)
        recent = self.touched_s[:n] >= touched_since_s  # NaN (never touched) is not recent
        if recent.any():
            distance[recent] -= distance.max() + 1.0  # nearer than any other block
        return np.sort(np.argpartition(-distance, n - keep)[: n - keep])

    def remove(self, victims: np.ndarray) -> Eviction:
        """Drop these blocks (to the grid's spill, when it has one); the flags follow the blocks that
        move into the freed slots, and the neighbours of the dropped blocks are to be re-meshed
        (their cells read the dropped voxels)."""
        grid = self.grid
        n = grid.n_blocks
        victim_keys = grid.slot_keys[victims]
        if grid.spill is not None:
            grid.spill.put(victim_keys, [pool[torch.from_numpy(victims)].numpy() for pool in grid.pools.values()])
        around = self.neighbours(victims)
        remesh = np.zeros(n, bool)
        remesh[around[around >= 0]] = True
        moved_from, moved_to = grid.remove_blocks(victims)
        new_slot = np.arange(n)
        new_slot[victims] = -1
        new_slot[moved_from] = moved_to
        for name in (*self._FLAGS, None):
            flags = remesh if name is None else getattr(self, name)
            flags[moved_to] = flags[moved_from]
            flags[grid.n_blocks:n] = self._FILL.get(name or "", 0)
        self.mesh_pending[: grid.n_blocks] |= remesh[: grid.n_blocks]
        return Eviction(victim_keys, new_slot)


@numba.njit(cache=True, nogil=True)
def _count_positive(a: np.ndarray, b: np.ndarray) -> int:
    """How many i have a[i] > 0 or b[i] > 0."""
    count = 0
    for i in range(a.shape[0]):
        count += (a[i] > 0) | (b[i] > 0)
    return count
