"""The paper's chunk rule: a chunk inside a frame's update box holding enough updated voxels."""
from __future__ import annotations

import numba
import numpy as np
import torch

from ..grid import BLOCK, BLOCK_VOXELS, keys_to_coords


def update_box(voxels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inclusive min and max voxel index (3,) of the updated voxels (U x 3)."""
    return voxels.min(dim=0).values, voxels.max(dim=0).values


@numba.njit(cache=True, nogil=True)
def _first_box_holding(voxels: np.ndarray, corners: np.ndarray, size: np.ndarray, min_voxels: int) -> int:
    """Index of the first corner whose box (size per axis) holds >= min_voxels of the voxels, -1 if none."""
    n_voxels = voxels.shape[0]
    for j in range(corners.shape[0]):
        c0, c1, c2 = corners[j, 0], corners[j, 1], corners[j, 2]
        count = 0
        for i in range(n_voxels):
            if count + (n_voxels - i) < min_voxels:
                break  # cannot reach the minimum any more
            x, y, z = voxels[i, 0] - c0, voxels[i, 1] - c1, voxels[i, 2] - c2
            if 0 <= x < size[0] and 0 <= y < size[1] and 0 <= z < size[2]:
                count += 1
                if count >= min_voxels:
                    return j
    return -1


def sample_chunk(voxels: torch.Tensor, *, chunk_size: int, min_voxels: int, max_tries: int,
                 generator: torch.Generator, batch: int = 32) -> tuple[torch.Tensor | None, torch.Tensor, int]:
    """A chunk inside the update box of `voxels` (U x 3 int64) holding >= min_voxels of them.

    The chunk is chunk_size per axis, shrunk to the box where the box is smaller; its corner is
    uniform inside the box. Returns (corner (3,) or None, size (3,), tries used).
    """
    lo, hi = update_box(voxels)
    extent = hi - lo + 1
    size = torch.clamp(extent, max=chunk_size)
    span = extent - size + 1  # possible corner positions per axis
    voxels_np = np.ascontiguousarray(voxels.numpy(), np.int64)
    size_np = size.numpy().astype(np.int64)
    tries = 0
    while tries < max_tries:
        n = min(batch, max_tries - tries)
        corners = lo + (torch.rand((n, 3), generator=generator) * span).to(torch.int64).clamp(max=span - 1)
        j = _first_box_holding(voxels_np, np.ascontiguousarray(corners.numpy()), size_np, int(min_voxels))
        if j >= 0:
            return corners[j], size, tries + j + 1
        tries += n
    return None, size, tries


def keys_to_voxels(keys: torch.Tensor) -> torch.Tensor:
    """Voxel keys (block_key*512 + local) -> U x 3 voxel indices."""
    blocks = keys_to_coords(torch.div(keys, BLOCK_VOXELS, rounding_mode="floor"))
    local = keys % BLOCK_VOXELS
    loc = torch.stack([local // 64, (local // 8) % 8, local % 8], dim=1)
    return blocks * BLOCK + loc
