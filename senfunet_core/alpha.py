"""Which blocks need the sensor weighting alpha re-evaluated, and the weighting net's input windows.

Alpha at a voxel depends on the weighting-net inputs [F_1, tanh(W_1), F_2, tanh(W_2)] within
2 voxels (receptive field 5^3). Integration accumulates, per voxel, how much those inputs drifted
since alpha around the voxel was last evaluated (`drift`, see integrator.update_voxels). A voxel
is a *target* when some voxel within 2 of it drifted more than the tolerance, and it belongs to
the evaluated set (a block with a target is re-evaluated whole, all 512 voxels):
- "all": every voxel (the exact, whole-grid result on every voxel);
- "observed": voxels some sensor observed (all that fusion, the filter, meshes and clouds read);
- "surface": corners of cells whose 8 corners are observed and whose sensor TSDFs (any sensor,
  where observed) include values <= 0 and >= 0: only these cells can hold fused triangles, since
  the fused value lies between V_1 and V_2 (alpha elsewhere may be stale).

Numba kernels over blocks; each block's neighbourhood comes from a B x 27 neighbour table
(grid.neighbour_table). Pools are the grid's kernel views (float16 as int16 bits).
"""
from __future__ import annotations

import numba
import numpy as np

from .grid import f16_to_f32

MODES = {"all": 0, "observed": 1, "surface": 2}
HALO = 2  # alpha depends on inputs within 2 voxels
WINDOW = 8 + 2 * HALO  # input window per block: 12^3
_TANH_OF_COUNT = np.tanh(np.arange(2049, dtype=np.float64)).astype(np.float32)  # weight counters are integers


@numba.njit(inline="always")
def _neighbour_index(neighbours: np.ndarray, b: int, x: int, y: int, z: int) -> int:
    """Flat voxel index (slot*512 + local) of local coordinates x, y, z in -8..15 around block b,
    or -1 where that block does not exist."""
    bx, by, bz = (x + 8) // 8, (y + 8) // 8, (z + 8) // 8
    slot = neighbours[b, bx * 9 + by * 3 + bz]
    if slot < 0:
        return -1
    return slot * 512 + (x - (bx - 1) * 8) * 64 + (y - (by - 1) * 8) * 8 + (z - (bz - 1) * 8)


@numba.njit(cache=True, nogil=True)
def stale_levels(neighbours: np.ndarray, drift: np.ndarray, tsdf_1: np.ndarray, weight_1: np.ndarray,
                 tsdf_2: np.ndarray, weight_2: np.ndarray, tolerance: float, mode: int) -> np.ndarray:
    """Per block (neighbours[b, 13]): 0 when none of its voxels is a target, else 1, or 2 when a
    voxel in its input window was first observed or changed sign (drift inf: evaluate first).
    drift, weights: float16 bits (int16)."""
    n_blocks = neighbours.shape[0]
    levels = np.zeros(n_blocks, np.int8)
    dirty = np.zeros((WINDOW, WINDOW, WINDOW), np.bool_)
    near_x = np.zeros((8, WINDOW, WINDOW), np.bool_)
    near_xy = np.zeros((8, 8, WINDOW), np.bool_)
    lo = np.zeros((10, 10, 10), np.float32)
    hi = np.zeros((10, 10, 10), np.float32)
    seen = np.zeros((10, 10, 10), np.bool_)
    cells = np.zeros((9, 9, 9), np.bool_)
    for b in range(n_blocks):
        any_dirty, forced = False, False
        for x in range(WINDOW):
            for y in range(WINDOW):
                for z in range(WINDOW):
                    v = _neighbour_index(neighbours, b, x - HALO, y - HALO, z - HALO)
                    d = f16_to_f32(drift[v]) if v >= 0 else np.float32(0.0)
                    dirty[x, y, z] = d > tolerance
                    any_dirty = any_dirty or d > tolerance
                    forced = forced or d == np.inf
        if not any_dirty:
            continue
        # dilate by 5 along each axis in turn
        for x in range(8):
            for y in range(WINDOW):
                for z in range(WINDOW):
                    near_x[x, y, z] = (dirty[x, y, z] or dirty[x + 1, y, z] or dirty[x + 2, y, z]
                                       or dirty[x + 3, y, z] or dirty[x + 4, y, z])
        for x in range(8):
            for y in range(8):
                for z in range(WINDOW):
                    near_xy[x, y, z] = (near_x[x, y, z] or near_x[x, y + 1, z] or near_x[x, y + 2, z]
                                        or near_x[x, y + 3, z] or near_x[x, y + 4, z])
        if mode == 2:
            # per voxel of the 10^3 window (local -1..8): observed by any sensor, min and max TSDF
            for x in range(10):
                for y in range(10):
                    for z in range(10):
                        v = _neighbour_index(neighbours, b, x - 1, y - 1, z - 1)
                        low, high, observed = np.float32(np.inf), np.float32(-np.inf), False
                        if v >= 0:
                            if f16_to_f32(weight_1[v]) > 0:
                                low, high, observed = min(low, tsdf_1[v]), max(high, tsdf_1[v]), True
                            if f16_to_f32(weight_2[v]) > 0:
                                low, high, observed = min(low, tsdf_2[v]), max(high, tsdf_2[v]), True
                        lo[x, y, z], hi[x, y, z], seen[x, y, z] = low, high, observed
            for x in range(9):
                for y in range(9):
                    for z in range(9):
                        ok = True
                        low, high = np.float32(np.inf), np.float32(-np.inf)
                        for corner in range(8):
                            cx, cy, cz = x + (corner >> 2), y + ((corner >> 1) & 1), z + (corner & 1)
                            ok = ok and seen[cx, cy, cz]
                            low, high = min(low, lo[cx, cy, cz]), max(high, hi[cx, cy, cz])
                        cells[x, y, z] = ok and low <= 0.0 and high >= 0.0
        slot = neighbours[b, 13]
        found = False
        for x in range(8):
            for y in range(8):
                for z in range(8):
                    near = (near_xy[x, y, z] or near_xy[x, y, z + 1] or near_xy[x, y, z + 2]
                            or near_xy[x, y, z + 3] or near_xy[x, y, z + 4])
                    if not near:
                        continue
                    if mode == 1:
                        v = slot * 512 + x * 64 + y * 8 + z
                        near = f16_to_f32(weight_1[v]) > 0 or f16_to_f32(weight_2[v]) > 0
                    elif mode == 2:  # a corner of a surface cell: cells x..x+1 in the 9^3 cell grid
                        near = (cells[x, y, z] or cells[x + 1, y, z] or cells[x, y + 1, z] or cells[x, y, z + 1]
                                or cells[x + 1, y + 1, z] or cells[x + 1, y, z + 1] or cells[x, y + 1, z + 1]
                                or cells[x + 1, y + 1, z + 1])
                    if near:
                        found = True
                        break
                if found:
                    break
            if found:
                break
        if found:
            levels[b] = 2 if forced else 1
    return levels


@numba.njit(cache=True, nogil=True)
def consume_drift(slots: np.ndarray, drift: np.ndarray, tolerance: float) -> None:
    """Alpha around the drifted voxels of these blocks is scheduled: their drift restarts."""
    for b in range(slots.shape[0]):
        base = slots[b] * 512
        for local in range(512):
            if f16_to_f32(drift[base + local]) > tolerance:
                drift[base + local] = 0


@numba.njit(cache=True, nogil=True)
def weighting_windows(neighbours: np.ndarray, features_1: np.ndarray, weight_1: np.ndarray,
                      features_2: np.ndarray, weight_2: np.ndarray) -> np.ndarray:
    """B x 12^3 x 12 weighting-net inputs [F_1 (5), tanh(W_1), F_2 (5), tanh(W_2)] of each block
    with its 2-voxel halo (channels last), zero where no block exists. features_i: flat int16 bits."""
    n_blocks = neighbours.shape[0]
    n_features = features_1.shape[0] // weight_1.shape[0]
    n_channels = 2 * (n_features + 1)
    out = np.zeros((n_blocks, WINDOW, WINDOW, WINDOW, n_channels), np.float32)
    for b in range(n_blocks):
        for x in range(WINDOW):
            for y in range(WINDOW):
                for z in range(WINDOW):
                    v = _neighbour_index(neighbours, b, x - HALO, y - HALO, z - HALO)
                    if v < 0:
                        continue
                    for c in range(n_features):
                        out[b, x, y, z, c] = f16_to_f32(features_1[v * n_features + c])
                        out[b, x, y, z, n_features + 1 + c] = f16_to_f32(features_2[v * n_features + c])
                    out[b, x, y, z, n_features] = _TANH_OF_COUNT[int(f16_to_f32(weight_1[v]))]
                    out[b, x, y, z, n_channels - 1] = _TANH_OF_COUNT[int(f16_to_f32(weight_2[v]))]
    return out
