"""The map's store: the sparse grid and each block's scheduling state, and eviction.

`BlockStore` holds the `BlockGrid` (blocks, hash table, one pool per channel) and, per block slot,
the flags the engine schedules work by. It knows nothing of integration, the weighting net or
meshing: the engine and the alpha scheduler read and set the flags; whoever changes the store
holds the engine's data lock (see the threading model in `engine`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .grid import BLOCK, BlockGrid, kernel_view, neighbour_table

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


class BlockStore:
    """The grid and, per block slot (arrays as long as the grid's capacity):
    - alpha_pending: integrated into since the last alpha schedule;
    - stale: alpha to re-evaluate: 0 no, 1 inputs drifted, 2 new or sign-changed voxels, 3 never evaluated;
    - evaluated: alpha evaluated at least once;
    - no_targets: when last checked, the block held no voxel alpha matters for;
    - last_reached: the last alpha schedule that made it stale (the newest are served first);
    - mesh_pending: TSDF or alpha changed since it was meshed."""

    _FLAGS = {"alpha_pending": bool, "stale": np.int8, "evaluated": bool, "no_targets": bool,
              "last_reached": np.int64, "mesh_pending": bool}

    alpha_pending: np.ndarray
    stale: np.ndarray
    evaluated: np.ndarray
    no_targets: np.ndarray
    last_reached: np.ndarray
    mesh_pending: np.ndarray

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
                setattr(self, name, np.concatenate([getattr(self, name), np.zeros(grow, dtype)]))

    def views(self, *names: str) -> list[np.ndarray]:
        """Flat kernel views of pools (fetch them under the data lock: pools move when they grow)."""
        return [kernel_view(self.grid.pools[name]).reshape(-1) for name in names]

    def neighbours(self, slots: np.ndarray) -> np.ndarray:
        """B x 27 slots of the blocks around these (grid.neighbour_table)."""
        grid = self.grid
        return neighbour_table(grid.table_keys, grid.table_slots, grid.slot_keys, slots)

    def observed_voxels(self, weight_channels: list[str], chunk_blocks: int = 4096) -> int:
        """Voxels some sensor observed, counted a chunk of blocks at a time (masks of the whole map
        would be the largest allocation of a replay's end)."""
        n = self.grid.n_blocks
        total = 0
        for start in range(0, n, chunk_blocks):
            observed = self.grid.pools[weight_channels[0]][start:start + chunk_blocks] > 0
            for name in weight_channels[1:]:
                observed |= self.grid.pools[name][start:start + chunk_blocks] > 0
            total += int(observed.sum())
        return total

    def farthest(self, point_m: np.ndarray, *, keep: int, voxel_size_m: float) -> np.ndarray:
        """Slots of all blocks but the `keep` nearest to point_m (sorted)."""
        n = self.grid.n_blocks
        centres_m = (self.grid.coords[:n].numpy() * BLOCK + (BLOCK - 1) / 2) * voxel_size_m
        distance = np.linalg.norm(centres_m - point_m, axis=1)
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
        for flags in (*(getattr(self, name) for name in self._FLAGS), remesh):
            flags[moved_to] = flags[moved_from]
            flags[grid.n_blocks:n] = 0
        self.mesh_pending[: grid.n_blocks] |= remesh[: grid.n_blocks]
        return Eviction(victim_keys, new_slot)
