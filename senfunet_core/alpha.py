"""Where the sensor weighting alpha must be re-evaluated, and the weighting net's inputs there.

Alpha at a voxel depends on the weighting-net inputs [F_1, tanh(W_1), F_2, tanh(W_2)] within
2 voxels (receptive field 5^3). Integration collects, per block, the blocks within 2 voxels of
its voxels whose inputs changed since alpha was last scheduled (integrator.update_voxels); those
are stale (`reach_levels`); when a block's turn comes, the net is evaluated on the voxels of the
evaluated set (EngineConfig.alpha_voxels):
- "all": every voxel of the block, as blocks with a 2-voxel halo (`weighting_windows`): the exact,
  whole-grid result on every voxel;
- "surface": the corners of cells whose 8 corners are observed and whose sensor TSDFs (any
  sensor, where observed) include values <= 0 and >= 0 (`surface_targets`): only these cells can
  hold fused triangles, since the fused value lies between V_1 and V_2. Evaluated voxel by voxel
  (`target_gathers`, `evaluate_gathers`); alpha elsewhere may be stale.
Evaluating more than needed is always allowed: the result then still equals the whole-grid
evaluation on the evaluated set.

Numba kernels over blocks; each block's neighbourhood comes from a B x 27 neighbour table
(grid.neighbour_table). Pools are the grid's kernel views (float16 as int16 bits).
"""
from __future__ import annotations

import functools
from typing import Any

import numba
import numpy as np
import torch

from .grid import (F16_VALUES, as_stored, copy_features, f16_to_f32, feature_code_tables, features_per_voxel,
                   load_f32, load_features, packed_words)
from .integrator import TANH_OF_COUNT
from .networks import WEIGHTING_HALO

HALO = WEIGHTING_HALO  # alpha depends on inputs within 2 voxels (integrator.REACH_OF_VOXEL reads the same)
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


@numba.njit(inline="always")
def _z_run(run: int, halo: int) -> tuple[int, int]:
    """A window row along z around a block, with `halo` voxels each side, is three runs of
    consecutive voxels, each in one block: run 0 (the block below, local z 8 - halo..7), 1 (the
    block, 0..7), 2 (the block above, 0..halo - 1). Returns the run's (first local z, length)."""
    if run == 0:
        return 8 - halo, halo
    return 0, 8 if run == 1 else halo


def reach_levels(renewed: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """The level at which a block's change reaches its neighbour `codes` (code 9*(dx+1) + 3*(dy+1)
    + (dz+1)), given the block's renewed reach bits (integrator.REACH_OF_VOXEL) and that the
    neighbour is reached: 2 where a voxel within 2 of it was first observed or changed sign, else 1
    (a voxel's inputs changed)."""
    return np.where((renewed.astype(np.int64) >> codes) & 1, 2, 1).astype(np.int8)


def window_channels(features_1: np.ndarray, weight_1: np.ndarray, tsdf_1: np.ndarray) -> int:
    """C, the weighting-net input channels per voxel (`weighting_windows`)."""
    return 2 * (features_per_voxel(features_1, weight_1.shape[0]) + 1) + (2 if tsdf_1.shape[0] > 0 else 0)


# the ranges the windows' values lie in, by kind (what 8-bit windows code, `grid.as_stored`)
_LEARNED_RANGE = (-1.0, 1.0)
_TANH_RANGE = (0.0, 1.0)
_TSDF_RANGE = (-1.0, 1.0)  # scaled by 2 / band


def window_value_ranges(n_features: int, *, with_tsdf: bool, depth_max_m: float) -> np.ndarray:
    """Per channel of the windows (`weighting_windows`' order), the range its values lie in (C x 2):
    learned features -1..1, depth 0..depth_max_m, tanh(weight) 0..1, the scaled TSDFs -1..1."""
    per_sensor = [_LEARNED_RANGE] * (n_features - 1) + [(0.0, depth_max_m), _TANH_RANGE]
    return np.array(per_sensor * 2 + [_TSDF_RANGE] * (2 if with_tsdf else 0), np.float64)


def weighting_windows(neighbours: np.ndarray, features_1: np.ndarray, weight_1: np.ndarray, features_2: np.ndarray,
                      weight_2: np.ndarray, tsdf_1: np.ndarray, tsdf_2: np.ndarray, tsdf_scale: float, *,
                      out: np.ndarray | None = None, depth_max_m: float = 1.0) -> np.ndarray:
    """B x 12^3 x C weighting-net inputs of each block with its 2-voxel halo (channels last), zero
    where no block exists: [F_1 (5), tanh(W_1), F_2 (5), tanh(W_2)] (C = 12) and, unless tsdf_1 and
    tsdf_2 are empty, [V_1, V_2] * tsdf_scale (C = 14, the inputs of WeightingNet.tsdf_input).
    features_i: flat feature-pool views (`grid.load_feature`); weights and TSDFs: the grid's float16
    pools as int16 bits (`grid.kernel_view`). out: a flat buffer of at least
    B * 12^3 * C entries to write them to (reused between batches: a fresh array of this size costs
    its page faults), float32, uint16 for bfloat16 bits, or uint8 for 8-bit codes (`grid.as_stored`
    in `window_value_ranges` with this depth_max_m; what the net computes in, no conversion pass);
    default a new float32 array."""
    shape = (neighbours.shape[0], WINDOW, WINDOW, WINDOW, window_channels(features_1, weight_1, tsdf_1))
    size = int(np.prod(shape))
    out = np.empty(size, np.float32) if out is None else out[:size]
    n_voxels = weight_1.shape[0]
    tables = _window_tables(out.dtype, float(tsdf_scale), features_per_voxel(features_1, n_voxels),
                            tsdf_1.shape[0] > 0, float(depth_max_m))
    _fill_windows(out, neighbours, packed_words(features_1, n_voxels), weight_1, packed_words(features_2, n_voxels),
                  weight_2, tsdf_1, tsdf_2, *tables)
    return out.reshape(shape)


@functools.lru_cache(maxsize=8)
def _window_tables(dtype: np.dtype, tsdf_scale: float, n_features: int, with_tsdf: bool, depth_max_m: float
                   ) -> tuple[np.ndarray, ...]:
    """The values the windows take from lookups, as a buffer of this dtype stores them (bfloat16
    bits or 8-bit codes: no conversion or rounding per value): a packed feature code's, a depth code's,
    per float16 bit pattern the tanh of the weight count it holds and the TSDF it holds times
    tsdf_scale (computed in float32, as the net's inputs are), and a voxel's channels where no block
    exists (all 0)."""
    counts = np.clip(np.nan_to_num(F16_VALUES, nan=0.0, posinf=0.0, neginf=0.0), 0, len(TANH_OF_COUNT) - 1)
    with np.errstate(invalid="ignore", over="ignore"):
        tsdf = F16_VALUES * np.float32(tsdf_scale)
    ranges = window_value_ranges(n_features, with_tsdf=with_tsdf, depth_max_m=depth_max_m)
    absent = np.concatenate([as_stored(np.zeros(1), dtype, value_range=tuple(r)) for r in ranges])
    return (*feature_code_tables(dtype, depth_range_m=(0.0, depth_max_m)),
            as_stored(TANH_OF_COUNT[counts.astype(np.int64)], dtype, value_range=_TANH_RANGE),
            as_stored(tsdf, dtype, value_range=_TSDF_RANGE), absent)


@numba.njit(cache=True, nogil=True)
def _fill_windows(out: np.ndarray, neighbours: np.ndarray, features_1: np.ndarray, weight_1: np.ndarray,
                  features_2: np.ndarray, weight_2: np.ndarray, tsdf_1: np.ndarray, tsdf_2: np.ndarray,
                  feature_of_code: np.ndarray, depth_of_code: np.ndarray, tanh_of_weight: np.ndarray,
                  scaled_tsdf: np.ndarray, absent: np.ndarray) -> None:
    """`weighting_windows`' kernel: every entry of out written (out may hold an earlier batch). Each
    window row along z is three runs of consecutive voxels (local z -2..-1 in the block below, 0..7,
    8..9 in the block above): one neighbour lookup per run. Weights and TSDFs (float16 bits) are
    looked up by their bits (`_window_tables`); `absent`: a voxel's channels where no block exists."""
    n_features = features_per_voxel(features_1, weight_1.shape[0])
    with_tsdf = tsdf_1.shape[0] > 0
    first_tsdf = 2 * (n_features + 1)
    channels = first_tsdf + 2 * with_tsdf
    i = 0  # out[i:i + channels]: the inputs at the next window position (b, x, y, z)
    for b in range(neighbours.shape[0]):
        for x in range(8 - HALO, 8 + 8 + HALO):  # local + 8, so that shifts and masks find the block
            for y in range(8 - HALO, 8 + 8 + HALO):
                for run in range(3):
                    first_z, length = _z_run(run, HALO)
                    slot = neighbours[b, (x >> 3) * 9 + (y >> 3) * 3 + run]
                    if slot < 0:
                        for _ in range(length):
                            out[i:i + channels] = absent
                            i += channels
                        continue
                    first = slot * 512 + (x & 7) * 64 + (y & 7) * 8 + first_z
                    for v in range(first, first + length):
                        copy_features(features_1, n_features, v, out, i, feature_of_code, depth_of_code)
                        copy_features(features_2, n_features, v, out, i + n_features + 1, feature_of_code,
                                      depth_of_code)
                        out[i + n_features] = tanh_of_weight[weight_1[v] & 0xFFFF]
                        out[i + first_tsdf - 1] = tanh_of_weight[weight_2[v] & 0xFFFF]
                        if with_tsdf:
                            out[i + first_tsdf] = scaled_tsdf[tsdf_1[v] & 0xFFFF]
                            out[i + first_tsdf + 1] = scaled_tsdf[tsdf_2[v] & 0xFFFF]
                        i += channels


# -- voxel-granular evaluation ("surface_voxels" mode) ------------------------------------------------
# G is three convolutions (3^3, 3^3, 1^3): alpha at a voxel reads layer-1 outputs at its 27
# neighbours, which read the inputs within 2 voxels. Instead of whole blocks with a 2-voxel halo,
# only the target voxels are evaluated: layer 1 at the union of their 3^3 neighbourhoods, layer 2
# at the targets, each as 27 gathered matrix products over tables of distinct positions.


@numba.njit(cache=True, nogil=True)
def surface_targets(neighbours: np.ndarray, tsdf_1: np.ndarray, weight_1: np.ndarray, tsdf_2: np.ndarray,
                    weight_2: np.ndarray) -> np.ndarray:
    """B x 512: the voxels of each block (neighbours[b, 13]) that are corners of a cell whose 8
    corners are observed (by any sensor) and whose sensor TSDFs include values <= 0 and >= 0: the
    only cells that can hold fused triangles, so the only voxels whose alpha the fused mesh, its
    filter and its colours read. Weights: float16 bits (int16)."""
    out = np.zeros((neighbours.shape[0], 512), np.bool_)
    scratch = _target_window()
    for b in range(neighbours.shape[0]):
        _block_targets(neighbours, b, tsdf_1, weight_1, tsdf_2, weight_2, scratch, out[b], False)
    return out


@numba.njit(cache=True, nogil=True)
def near_surface_voxels(slots: np.ndarray, tsdf_1: np.ndarray, weight_1: np.ndarray, tsdf_2: np.ndarray,
                        weight_2: np.ndarray, limit_m: float) -> np.ndarray:
    """Per block, its voxels that a sensor observed within limit_m of its surface: how much surface
    the block may show, at a fraction of `surface_targets`' cost (one pass over the block's own
    voxels, no neighbours). Weights: float16 bits (int16), positive where observed."""
    out = np.zeros(len(slots), np.int16)
    for i in range(len(slots)):
        count = 0
        for v in range(slots[i] * 512, slots[i] * 512 + 512):
            near_1 = (weight_1[v] > 0) & (abs(load_f32(tsdf_1, v)) < limit_m)
            near_2 = (weight_2[v] > 0) & (abs(load_f32(tsdf_2, v)) < limit_m)
            count += near_1 | near_2
        out[i] = count
    return out


@numba.njit(cache=True, nogil=True)
def holds_surface_targets(neighbours: np.ndarray, tsdf_1: np.ndarray, weight_1: np.ndarray, tsdf_2: np.ndarray,
                          weight_2: np.ndarray) -> np.ndarray:
    """B bools: whether each block holds any of `surface_targets` (each block's check ends at its
    first target: what evaluating whole blocks needs)."""
    holds = np.zeros(neighbours.shape[0], np.bool_)
    scratch = _target_window()
    row = np.zeros(512, np.bool_)
    for b in range(neighbours.shape[0]):
        holds[b] = _block_targets(neighbours, b, tsdf_1, weight_1, tsdf_2, weight_2, scratch, row, True)
    return holds


@numba.njit(inline="always")
def _target_window() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_block_targets`' scratch: per position of the 10^3 window, the lowest and highest sensor
    TSDF and whether any sensor observed it."""
    return (np.empty((10, 10, 10), np.float32), np.empty((10, 10, 10), np.float32),
            np.empty((10, 10, 10), np.bool_))


@numba.njit(cache=True, nogil=True)
def _block_targets(neighbours: np.ndarray, b: int, tsdf_1: np.ndarray, weight_1: np.ndarray, tsdf_2: np.ndarray,
                   weight_2: np.ndarray, scratch: tuple[np.ndarray, np.ndarray, np.ndarray], out: np.ndarray,
                   first_only: bool) -> bool:
    """`surface_targets` of block b into out (512 bools, set where a target); whether it holds any.
    first_only: stop at the first target found (out then holds only some)."""
    lo, hi, seen = scratch
    any_low, any_high = False, False
    for x in range(10):  # the 10^3 window (local -1..8): observed by any sensor, min and max TSDF
        for y in range(10):
            # a row along z is three runs (`_z_run`): one neighbour lookup per run, not per voxel
            row = ((x + 7) >> 3) * 9 + ((y + 7) >> 3) * 3
            row_first = ((x + 7) & 7) * 64 + ((y + 7) & 7) * 8
            window_z = 0
            for run in range(3):
                first_z, length = _z_run(run, 1)
                slot = neighbours[b, row + run]
                for k in range(length):
                    low, high, observed = np.float32(np.inf), np.float32(-np.inf), False
                    if slot >= 0:
                        v = slot * 512 + row_first + first_z + k
                        if f16_to_f32(weight_1[v]) > 0:
                            value = load_f32(tsdf_1, v)
                            low, high, observed = min(low, value), max(high, value), True
                        if f16_to_f32(weight_2[v]) > 0:
                            value = load_f32(tsdf_2, v)
                            low, high, observed = min(low, value), max(high, value), True
                    z = window_z + k
                    lo[x, y, z], hi[x, y, z], seen[x, y, z] = low, high, observed
                    any_low = any_low or bool(low <= 0.0)
                    any_high = any_high or bool(high >= 0.0)
                window_z += length
    if not (any_low and any_high):  # no sign change near the block (most blocks)
        return False
    found = False
    for x in range(9):  # cells with lower corner at window x, y, z (local x - 1 ...)
        for y in range(9):
            for z in range(9):
                cell_lo, cell_hi, cell_seen = np.float32(np.inf), np.float32(-np.inf), True
                for corner in range(8):
                    cx, cy, cz = x + (corner >> 2), y + ((corner >> 1) & 1), z + (corner & 1)
                    cell_seen &= seen[cx, cy, cz]
                    cell_lo = min(cell_lo, lo[cx, cy, cz])
                    cell_hi = max(cell_hi, hi[cx, cy, cz])
                if not (cell_seen and cell_lo <= 0.0 and cell_hi >= 0.0):
                    continue
                for corner in range(8):
                    lx, ly, lz = x - 1 + (corner >> 2), y - 1 + ((corner >> 1) & 1), z - 1 + (corner & 1)
                    if 0 <= lx < 8 and 0 <= ly < 8 and 0 <= lz < 8:
                        out[lx * 64 + ly * 8 + lz] = True
                        found = True
                if found and first_only:
                    return True
    return found


@numba.njit(cache=True, nogil=True)
def _number_positions(targets: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Rows for the layer-1 positions the targets (B x 512) read (window local -1..8, per block) and
    for the input positions those read (local -2..9): -1 where none; and how many of each."""
    n_blocks = targets.shape[0]
    l1_row = np.full((n_blocks, 10, 10, 10), -1, np.int64)
    in_row = np.full((n_blocks, WINDOW, WINDOW, WINDOW), -1, np.int64)
    n_l1, n_in = 0, 0
    for b in range(n_blocks):
        for local in range(512):
            if not targets[b, local]:
                continue
            x, y, z = local >> 6, (local >> 3) & 7, local & 7
            for d in range(27):
                px, py, pz = x + d // 9, y + (d // 3) % 3, z + d % 3
                if l1_row[b, px, py, pz] >= 0:
                    continue
                l1_row[b, px, py, pz] = n_l1
                n_l1 += 1
                for e in range(27):
                    qx, qy, qz = px + e // 9, py + (e // 3) % 3, pz + e % 3
                    if in_row[b, qx, qy, qz] < 0:
                        in_row[b, qx, qy, qz] = n_in
                        n_in += 1
    return l1_row, in_row, n_l1, n_in


@numba.njit(cache=True, nogil=True)
def target_gathers(neighbours: np.ndarray, targets: np.ndarray, features_1: np.ndarray, weight_1: np.ndarray,
                   features_2: np.ndarray, weight_2: np.ndarray, tsdf_1: np.ndarray, tsdf_2: np.ndarray,
                   tsdf_scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What the weighting net reads for the target voxels (targets: B x 512) of these blocks, as
    tables and row indices (per block: positions shared by several targets appear once):
    - inputs: V x C, the inputs (as in `weighting_windows`) at every position layer 1 reads;
    - gather_1: M x 27, per layer-1 position (the union of the targets' 3^3 neighbourhoods), the
      input rows of its 3^3 neighbourhood, offsets x-major (conv1's kernel order);
    - gather_2: N x 27, per target, the layer-1 rows of its 3^3 neighbourhood (the same order);
    - voxels: N flat voxel indices (slot * 512 + local) of the targets."""
    n_blocks = neighbours.shape[0]
    n_features = features_per_voxel(features_1, weight_1.shape[0])
    with_tsdf = tsdf_1.shape[0] > 0
    first_tsdf = 2 * (n_features + 1)
    n_channels = first_tsdf + 2 * with_tsdf
    l1_row, in_row, n_l1, n_in = _number_positions(targets)
    inputs = np.zeros((n_in, n_channels), np.float32)
    gather_1 = np.empty((n_l1, 27), np.int64)
    n_targets = int(targets.sum())
    gather_2 = np.empty((n_targets, 27), np.int64)
    voxels = np.empty(n_targets, np.int64)
    t = 0
    for b in range(n_blocks):
        for x in range(WINDOW):
            for y in range(WINDOW):
                for z in range(WINDOW):
                    row = in_row[b, x, y, z]
                    if row < 0:
                        continue
                    v = _neighbour_index(neighbours, b, x - HALO, y - HALO, z - HALO)
                    if v < 0:
                        continue
                    load_features(features_1, n_features, v, inputs[row, :n_features])
                    load_features(features_2, n_features, v, inputs[row, n_features + 1:2 * n_features + 1])
                    inputs[row, n_features] = TANH_OF_COUNT[int(f16_to_f32(weight_1[v]))]
                    inputs[row, first_tsdf - 1] = TANH_OF_COUNT[int(f16_to_f32(weight_2[v]))]
                    if with_tsdf:
                        inputs[row, first_tsdf] = load_f32(tsdf_1, v) * tsdf_scale
                        inputs[row, first_tsdf + 1] = load_f32(tsdf_2, v) * tsdf_scale
        for x in range(10):  # layer-1 position at window x + 1 reads inputs at window x .. x + 2
            for y in range(10):
                for z in range(10):
                    row = l1_row[b, x, y, z]
                    if row < 0:
                        continue
                    k = 0
                    for dx in range(3):
                        for dy in range(3):
                            for dz in range(3):
                                gather_1[row, k] = in_row[b, x + dx, y + dy, z + dz]
                                k += 1
        for local in range(512):
            if not targets[b, local]:
                continue
            x, y, z = local >> 6, (local >> 3) & 7, local & 7
            k = 0
            for dx in range(3):
                for dy in range(3):
                    for dz in range(3):
                        gather_2[t, k] = l1_row[b, x + dx, y + dy, z + dz]
                        k += 1
            voxels[t] = neighbours[b, 13] * 512 + local
            t += 1
    return inputs, gather_1, gather_2, voxels


def _gathered_conv(table: torch.Tensor, gather: np.ndarray, conv: Any, dtype: torch.dtype) -> torch.Tensor:
    """A 3^3 convolution at the rows of `gather` (R x 27 rows of `table`), one matrix product over
    the gathered neighbourhoods (R x 27*C): best for few channels (the net's inputs)."""
    weight = conv.weight.to(dtype).permute(0, 2, 3, 4, 1).reshape(conv.out_channels, -1)  # out x 27*C
    columns = table.index_select(0, torch.from_numpy(gather.reshape(-1))).reshape(len(gather), -1)
    return torch.addmm(conv.bias.to(dtype), columns, weight.t())


def _accumulated_conv(table: torch.Tensor, gather: np.ndarray, conv: Any, dtype: torch.dtype) -> torch.Tensor:
    """The same as `_gathered_conv`, as the bias plus one product per offset (its gathered rows times
    its weights): for many channels, where the R x 27*C matrix would not stay in cache."""
    weight = conv.weight.to(dtype)  # out x in x 3 x 3 x 3
    out = conv.bias.to(dtype).expand(len(gather), -1).clone()
    index = torch.from_numpy(gather)
    for k in range(27):
        out.addmm_(table.index_select(0, index[:, k]), weight[:, :, k // 9, (k // 3) % 3, k % 3].t())
    return out


def evaluate_gathers(net: Any, inputs: np.ndarray, gather_1: np.ndarray, gather_2: np.ndarray, *,
                     dtype: torch.dtype = torch.float32) -> np.ndarray:
    """Alpha of the targets of `target_gathers` with the weighting net's weights (networks.WeightingNet:
    conv1 3^3, ReLU, conv2 3^3, ReLU, conv3 1^3, sigmoid): the same values as the net on the whole
    grid, up to float rounding."""
    hidden_1 = torch.relu_(_gathered_conv(torch.from_numpy(inputs).to(dtype), gather_1, net.conv1, dtype))
    hidden_2 = torch.relu_(_accumulated_conv(hidden_1, gather_2, net.conv2, dtype))
    logits = torch.addmm(net.conv3.bias.to(dtype), hidden_2, net.conv3.weight.reshape(1, -1).t().to(dtype))
    return torch.sigmoid(logits.float()).reshape(-1).numpy()
