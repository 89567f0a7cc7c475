"""Compiled helpers over one frame's ray samples (flat pool index slot*512 + local per sample)."""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from ..grid import coords_key, hash_find


@dataclass
class FrameSamples:
    """What the compiled integration of one frame leaves for the loss."""

    sample_flat: np.ndarray  # P*S flat pool index of every ray sample
    pixel_index: np.ndarray  # P flat image index of every integrated pixel
    updated_flat: np.ndarray  # U voxels the frame updated
    updated_voxels: np.ndarray  # U x 3


@numba.njit(cache=True, nogil=True)
def _frame_voxels(sample_flat: np.ndarray, sample_touched: np.ndarray, touched_slots: np.ndarray,
                  slot_coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The voxels a frame updated (each once): flat pool indices (U,) and voxel indices (U, 3)."""
    n_touched = touched_slots.shape[0]
    mark = np.zeros((n_touched, 512), np.bool_)
    for n in range(sample_flat.shape[0]):
        mark[sample_touched[n], sample_flat[n] & 511] = True
    total = 0
    for t in range(n_touched):
        for local in range(512):
            total += mark[t, local]
    flat = np.empty(total, np.int64)
    voxels = np.empty((total, 3), np.int64)
    k = 0
    for t in range(n_touched):
        slot = touched_slots[t]
        for local in range(512):
            if mark[t, local]:
                flat[k] = slot * 512 + local
                voxels[k, 0] = slot_coords[slot, 0] * 8 + (local >> 6)
                voxels[k, 1] = slot_coords[slot, 1] * 8 + ((local >> 3) & 7)
                voxels[k, 2] = slot_coords[slot, 2] * 8 + (local & 7)
                k += 1
    return flat, voxels


@numba.njit(cache=True, nogil=True)
def _samples_in_box(sample_flat: np.ndarray, samples_per_ray: int, pixel_index: np.ndarray, slot_coords: np.ndarray,
                    corner: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the samples that fall in the box corner..corner+size-1: their voxel's box-local index
    ((x * size_y + y) * size_z + z) and their pixel (flat image index)."""
    n = sample_flat.shape[0]
    local_out = np.empty(n, np.int64)
    pixel_out = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        f = sample_flat[i]
        slot = f >> 9
        local = f & 511
        x = slot_coords[slot, 0] * 8 + (local >> 6) - corner[0]
        if x < 0 or x >= size[0]:
            continue
        y = slot_coords[slot, 1] * 8 + ((local >> 3) & 7) - corner[1]
        if y < 0 or y >= size[1]:
            continue
        z = slot_coords[slot, 2] * 8 + (local & 7) - corner[2]
        if z < 0 or z >= size[2]:
            continue
        local_out[m] = (x * size[1] + y) * size[2] + z
        pixel_out[m] = pixel_index[i // samples_per_ray]
        m += 1
    return local_out[:m], pixel_out[:m]


@numba.njit(cache=True, nogil=True)
def _box_flat(corner: np.ndarray, size: np.ndarray, index: np.ndarray, table_keys: np.ndarray,
              table_slots: np.ndarray) -> np.ndarray:
    """Flat pool index of box voxels given by box-local index ((x * size_y + y) * size_z + z),
    -1 where the voxel's block does not exist."""
    out = np.empty(index.shape[0], np.int64)
    for k in range(index.shape[0]):
        i = index[k]
        x = corner[0] + i // (size[1] * size[2])
        y = corner[1] + (i // size[2]) % size[1]
        z = corner[2] + i % size[2]
        key = coords_key(x >> 3, y >> 3, z >> 3)
        slot = hash_find(table_keys, table_slots, key) if key >= 0 else -1
        out[k] = slot * 512 + ((x & 7) << 6) + ((y & 7) << 3) + (z & 7) if slot >= 0 else -1
    return out
