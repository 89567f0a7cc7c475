"""Which blocks need the sensor weighting alpha re-evaluated, and the weighting net's input windows.

Alpha at a voxel depends on the weighting-net inputs [F_1, tanh(W_1), F_2, tanh(W_2)] within
2 voxels (receptive field 5^3). Integration accumulates, per voxel, how much those inputs drifted
since alpha around the voxel was last evaluated (`drift`, see integrator.update_voxels). A block
is re-evaluated (whole, all 512 voxels) when a voxel within 2 of it drifted more than the
tolerance (`take_drift`) and it holds a voxel of the evaluated set (`holds_targets`):
- "all": every voxel (the exact, whole-grid result on every voxel);
- "surface": corners of cells whose 8 corners are observed and whose sensor TSDFs (any sensor,
  where observed) include values <= 0 and >= 0: only these cells can hold fused triangles, since
  the fused value lies between V_1 and V_2 (alpha elsewhere may be stale).
Evaluating more than needed is always allowed: the result then still equals the whole-grid
evaluation on the evaluated set.

Numba kernels over blocks; each block's neighbourhood comes from a B x 27 neighbour table
(grid.neighbour_table). Pools are the grid's kernel views (float16 as int16 bits).
"""
from __future__ import annotations

import numba
import numpy as np

from .grid import f16_to_f32
from .integrator import TANH_OF_COUNT

MODES = {"all": 0, "surface": 2}
HALO = 2  # alpha depends on inputs within 2 voxels
WINDOW = 8 + 2 * HALO  # input window per block: 12^3


@numba.njit(inline="always")
def _neighbour_index(neighbours: np.ndarray, b: int, x: int, y: int, z: int) -> int:
    """Flat voxel index (slot*512 + local) of local coordinates x, y, z in -8..15 around block b,
    or -1 where that block does not exist."""
    x, y, z = x + 8, y + 8, z + 8  # >= 0: shifts and masks instead of floor division
    slot = neighbours[b, (x >> 3) * 9 + (y >> 3) * 3 + (z >> 3)]
    if slot < 0:
        return -1
    return slot * 512 + (x & 7) * 64 + (y & 7) * 8 + (z & 7)


@numba.njit(cache=True, nogil=True)
def take_drift(slots: np.ndarray, drift: np.ndarray, tolerance: float) -> np.ndarray:
    """Which neighbours the drift of these blocks reaches: B x 27 levels (neighbour code
    9*(dx+1) + 3*(dy+1) + (dz+1)), 2 where a voxel within 2 of that neighbour was first observed
    or changed sign (drift inf), else 1 where one drifted more than the tolerance, else 0. The
    drift of those voxels restarts: alpha around them is now scheduled. drift: float16 bits."""
    levels = np.zeros((slots.shape[0], 27), np.int8)
    words = drift.view(np.int64)  # 4 voxels a word: most voxels of a changed block did not drift at all
    for b in range(slots.shape[0]):
        base = slots[b] * 512
        for word in range(base >> 2, (base + 512) >> 2):
            if words[word] == 0:
                continue
            for voxel in range(word << 2, (word << 2) + 4):
                d = f16_to_f32(drift[voxel])
                if not d > tolerance:
                    continue
                drift[voxel] = 0
                level = 2 if d == np.inf else 1
                local = voxel - base
                x, y, z = local >> 6, (local >> 3) & 7, local & 7
                # neighbours within HALO voxels of this one, per axis: -1 (x < 2), 0, +1 (x > 5)
                for dx in range(-1 if x < HALO else 0, 2 if x >= 8 - HALO else 1):
                    for dy in range(-1 if y < HALO else 0, 2 if y >= 8 - HALO else 1):
                        for dz in range(-1 if z < HALO else 0, 2 if z >= 8 - HALO else 1):
                            code = 9 * (dx + 1) + 3 * (dy + 1) + dz + 1
                            if levels[b, code] < level:
                                levels[b, code] = level
    return levels


@numba.njit(cache=True, nogil=True)
def holds_targets(neighbours: np.ndarray, tsdf_1: np.ndarray, weight_1: np.ndarray, tsdf_2: np.ndarray,
                  weight_2: np.ndarray, mode: int) -> np.ndarray:
    """Per block (neighbours[b, 13]): does it hold a voxel of the evaluated set (see MODES): any
    voxel ("all"), or a corner of a cell whose 8 corners are observed and whose sensor TSDFs
    include values <= 0 and >= 0 ("surface"). Weights: float16 bits (int16)."""
    n_blocks = neighbours.shape[0]
    out = np.zeros(n_blocks, np.bool_)
    if mode == 0:
        out[:] = True
        return out
    lo = np.empty((10, 10, 10), np.float32)
    hi = np.empty((10, 10, 10), np.float32)
    seen = np.empty((10, 10, 10), np.bool_)
    for b in range(n_blocks):
        # the 10^3 window (local -1..8): observed by any sensor, min and max TSDF
        window_lo, window_hi = np.float32(np.inf), np.float32(-np.inf)
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
                    window_lo, window_hi = min(window_lo, low), max(window_hi, high)
        if not (window_lo <= 0.0 and window_hi >= 0.0):  # no sign change near the block (most blocks)
            continue
        # each cell (lower corner at local -1..7, window 0..8) over its 8 corners, one axis at a
        # time in place: entry i becomes the reduction over i and i + 1 along that axis
        for x in range(10):
            for y in range(10):
                for z in range(9):
                    lo[x, y, z] = min(lo[x, y, z], lo[x, y, z + 1])
                    hi[x, y, z] = max(hi[x, y, z], hi[x, y, z + 1])
                    seen[x, y, z] = seen[x, y, z] and seen[x, y, z + 1]
        for x in range(10):
            for y in range(9):
                for z in range(9):
                    lo[x, y, z] = min(lo[x, y, z], lo[x, y + 1, z])
                    hi[x, y, z] = max(hi[x, y, z], hi[x, y + 1, z])
                    seen[x, y, z] = seen[x, y, z] and seen[x, y + 1, z]
        for x in range(9):
            for y in range(9):
                for z in range(9):
                    if seen[x, y, z] and seen[x + 1, y, z] and min(lo[x, y, z], lo[x + 1, y, z]) <= 0.0 \
                            and max(hi[x, y, z], hi[x + 1, y, z]) >= 0.0:
                        out[b] = True
                        break
                if out[b]:
                    break
            if out[b]:
                break
    return out


@numba.njit(cache=True, nogil=True)
def weighting_windows(neighbours: np.ndarray, features_1: np.ndarray, weight_1: np.ndarray, features_2: np.ndarray,
                      weight_2: np.ndarray, tsdf_1: np.ndarray, tsdf_2: np.ndarray, tsdf_scale: float) -> np.ndarray:
    """B x 12^3 x C weighting-net inputs of each block with its 2-voxel halo (channels last), zero
    where no block exists: [F_1 (5), tanh(W_1), F_2 (5), tanh(W_2)] (C = 12) and, unless tsdf_1 and
    tsdf_2 are empty, [V_1, V_2] * tsdf_scale (C = 14, the inputs of WeightingNet.tsdf_input).
    features_i: flat int16 bits."""
    n_blocks = neighbours.shape[0]
    n_features = features_1.shape[0] // weight_1.shape[0]
    with_tsdf = tsdf_1.shape[0] > 0
    first_tsdf = 2 * (n_features + 1)
    out = np.zeros((n_blocks, WINDOW, WINDOW, WINDOW, first_tsdf + 2 * with_tsdf), np.float32)
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
                    out[b, x, y, z, n_features] = TANH_OF_COUNT[int(f16_to_f32(weight_1[v]))]
                    out[b, x, y, z, first_tsdf - 1] = TANH_OF_COUNT[int(f16_to_f32(weight_2[v]))]
                    if with_tsdf:
                        out[b, x, y, z, first_tsdf] = tsdf_1[v] * tsdf_scale
                        out[b, x, y, z, first_tsdf + 1] = tsdf_2[v] * tsdf_scale
    return out
