"""Shape and feature integration of one depth frame (paper section 3 a, b and supplementary B).

Two paths compute the same update. The reference path is pure tensor functions (validity mask,
unprojection, ray samples, aggregation of one frame's samples per voxel); the tests hold the
compiled path to it. The compiled path is the engine's: `integrate_frame` runs two numba kernels
through typed wrappers, `locate_frame_samples` (snap every ray sample to its voxel, allocating
blocks) and `update_frame_voxels` (average each voxel's samples, apply the running averages).

Convention: `T_world_camera` maps camera (optical frame: z forward, x right, y down) to world,
metres; `K` is the pinhole matrix of the depth image; depth is z-depth in metres.
"""
from __future__ import annotations

import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from collections.abc import Callable

import numba
import numpy as np
import torch

from .errors import InputError
from .grid import (BlockGrid, blend_features, coords_key, drop_new_blocks, f16_to_f32, hash_find_or_add,
                   kernel_view, load_f32, prefetch, store_f32, voxel_keys)
from .networks import WEIGHTING_HALO
from .scratch import scratch as scratch_array


@dataclass(frozen=True)
class IntegratorConfig:
    voxel_size_m: float = 0.01  # voxel side length
    band_m: float = 0.1  # l: length of the sampled ray segment centred on the measured point
    n_samples: int = 11  # T: samples along the band, band_m / (T - 1) apart
    n_samples_behind: int = 3  # of those behind the surface, how many are written (authors' code: 3)
    w_max: float = 500.0  # weight counter clip
    border_px: int = 10  # image border masked out
    min_new_block_samples: int = 0  # a block not yet in the grid is allocated only when at least this many of
    #   one frame's ray samples fall in it (the rest are dropped and counted); 0 = every touched block

    def sample_offsets(self) -> torch.Tensor:
        """Signed sample offsets along the ray in steps (negative: towards the camera)."""
        half = (self.n_samples - 1) // 2
        return torch.arange(-half, self.n_samples_behind + 1, dtype=torch.float32)

    @property
    def step_m(self) -> float:
        return self.band_m / (self.n_samples - 1)


PAPER_SAMPLES_HALF = 5  # the paper's T = 11 samples: 5 in front of the surface, the surface, 5 behind ...
PAPER_SAMPLES_BEHIND = 3  # ... of which the authors' code writes 3


def samples_along_band(voxel_size_m: float, band_m: float) -> tuple[int, int]:
    """(n_samples, n_samples_behind) for a voxel size and band: the paper's 11 samples (3 written
    behind the surface) where they lie at most one voxel apart (its 1 cm voxels, 10 cm band), else
    as many as keep them one voxel apart, the same share behind. Samples further apart than a voxel
    skip voxels along every ray: the voxels between are never observed, and no cell with a skipped
    corner is meshed (5 mm voxels under a 10 cm band gave no mesh at all)."""
    half = max(PAPER_SAMPLES_HALF, math.ceil(band_m / (2.0 * voxel_size_m) - 1e-9))
    return 2 * half + 1, round(half * PAPER_SAMPLES_BEHIND / PAPER_SAMPLES_HALF)


def pixel_spacing_m(depth_m: np.ndarray, K: np.ndarray, *,
                    depth_range_m: tuple[float, float] = (0.0, math.inf)) -> tuple[float, float]:
    """(median depth of the valid pixels within depth_range_m (those that are fused), the distance
    between neighbouring pixels' rays at that depth along the coarser image axis), metres; (0, 0)
    without such a pixel. Where the spacing exceeds the voxel size, neighbouring rays skip voxels
    across the surface: those are never observed, and no cell with an unobserved corner is meshed
    (holes)."""
    depth = np.asarray(depth_m)
    valid = depth[np.isfinite(depth) & (depth > max(depth_range_m[0], 0.0)) & (depth <= depth_range_m[1])]
    if valid.size == 0:
        return 0.0, 0.0
    median_m = float(np.median(valid))
    return median_m, median_m / float(min(K[0, 0], K[1, 1]))


@dataclass
class FrameSamples:
    """One frame's ray samples, aggregated per voxel (sorted by voxel key)."""

    keys: torch.Tensor  # U int64 voxel keys (block_key*512 + local), sorted
    tsdf_m: torch.Tensor  # U mean TSDF sample values
    inverse: torch.Tensor  # P*S index of each ray sample into `keys` (for aggregating features)
    counts: torch.Tensor  # U number of samples per voxel
    pixel_index: torch.Tensor  # P flat pixel index of each valid pixel
    n_samples_per_ray: int


def check_frame(depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, rgb: np.ndarray | None) -> None:
    """Raise InputError naming the problem when a frame cannot be integrated."""
    if not isinstance(depth_m, np.ndarray) or depth_m.ndim != 2 or depth_m.size == 0:
        raise InputError(f"depth_m must be a 2-D (H, W) array, got {getattr(depth_m, 'shape', type(depth_m))}")
    if depth_m.dtype not in (np.float32, np.float64):
        raise InputError(f"depth_m must be float32 metres, got dtype {depth_m.dtype}; convert millimetres with /1000")
    K = np.asarray(K)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InputError(f"K must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"K has non-positive focal lengths fx={K[0, 0]}, fy={K[1, 1]}; check the camera_info")
    T = np.asarray(T_world_camera)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError("T_world_camera must be a finite 4x4 matrix")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise InputError("T_world_camera is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    if rgb is not None:
        if not isinstance(rgb, np.ndarray) or rgb.shape != (*depth_m.shape, 3) or rgb.dtype != np.uint8:
            raise InputError(f"rgb must be uint8 of shape {(*depth_m.shape, 3)} like the depth, got "
                             f"{getattr(rgb, 'dtype', type(rgb))} {getattr(rgb, 'shape', '')}")


def check_key_range(max_depth_m: float, K: np.ndarray, T_world_camera: np.ndarray, shape: tuple[int, int],
                    band_m: float, limit_m: float = 5000.0) -> None:
    """Raise InputError when a frame's samples could leave the grid's key range (+-5 km at 1 cm
    voxels, checked at 5 km whatever the voxel size) -- before anything is allocated."""
    h, w = shape
    half_fov = np.hypot(max(K[0, 2], w - K[0, 2]) / K[0, 0], max(K[1, 2], h - K[1, 2]) / K[1, 1])
    reach = float(max_depth_m) * float(np.sqrt(1.0 + half_fov ** 2)) + band_m
    position_m = float(np.abs(np.asarray(T_world_camera)[:3, 3]).max())
    if position_m + reach > limit_m:
        if position_m > limit_m / 2:
            raise InputError(f"points lie more than 5 km from the origin (the camera is {position_m:.4g} m from it); "
                             "check the pose's units (metres) and frame")
        raise InputError(f"points lie more than 5 km from the origin: rays up to {max_depth_m:.3g} m deep fan out "
                         f"{half_fov:.3g} times as wide under K (fx {K[0, 0]:.4g}, fy {K[1, 1]:.4g}, cx {K[0, 2]:.4g}, "
                         f"cy {K[1, 2]:.4g} for {w}x{h} images); check the camera_info's K")


def valid_depth_mask(depth_m: torch.Tensor, border_px: int, min_m: float, max_m: float) -> torch.Tensor:
    """Pixels to integrate: finite, inside [min_m, max_m], not in the image border."""
    valid = torch.isfinite(depth_m) & (depth_m >= min_m) & (depth_m <= max_m) & (depth_m > 0)
    if border_px > 0:
        valid[:border_px] = False
        valid[-border_px:] = False
        valid[:, :border_px] = False
        valid[:, -border_px:] = False
    return valid


@numba.njit(cache=True, nogil=True)
def clean_depth(depth_m: np.ndarray, border_px: int, min_m: float, max_m: float) -> tuple[np.ndarray, np.float32]:
    """One pass over a frame's depth: a float32 copy with NaN and inf set to 0, and the largest
    depth of the pixels `valid_depth_mask` keeps (-1 when it keeps none)."""
    h, w = depth_m.shape
    clean = np.empty((h, w), np.float32)
    lo, hi = np.float32(min_m), np.float32(max_m)  # compared in float32, as the mask compares them
    deepest = np.float32(-1.0)
    for y in range(h):
        inner_row = border_px <= y < h - border_px
        for x in range(w):
            d = np.float32(depth_m[y, x])
            if not np.isfinite(d):
                d = np.float32(0.0)
            clean[y, x] = d
            if inner_row and border_px <= x < w - border_px and d > 0 and lo <= d <= hi and d > deepest:
                deepest = d
    return clean, deepest


def unproject(depth_m: torch.Tensor, valid: torch.Tensor, K: torch.Tensor, T_world_camera: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (Px3) of the valid pixels, and their flat pixel indices (P)."""
    h, w = depth_m.shape
    pixel_index = torch.nonzero(valid.reshape(-1)).squeeze(1)
    v = torch.div(pixel_index, w, rounding_mode="floor").to(K.dtype)
    u = (pixel_index % w).to(K.dtype)
    z = depth_m.reshape(-1)[pixel_index].to(K.dtype)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    points_c = torch.stack([x, y, z], dim=1)
    points_w = points_c @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
    return points_w, pixel_index


def ray_samples(points_w: torch.Tensor, camera_centre_w: torch.Tensor, config: IntegratorConfig
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Samples along each camera ray centred on the measured point: positions (P x S x 3) and the
    TSDF value of each sample (S): +band/2 in front of the surface, falling one step per sample."""
    offsets = config.sample_offsets().to(points_w.device, points_w.dtype)
    directions = points_w - camera_centre_w
    directions = directions / directions.norm(dim=1, keepdim=True).clamp(min=1e-9)
    positions = points_w.unsqueeze(1) + (offsets * config.step_m).view(1, -1, 1) * directions.unsqueeze(1)
    return positions, -offsets * config.step_m


def frame_samples(depth_m: torch.Tensor, valid: torch.Tensor, K: torch.Tensor, T_world_camera: torch.Tensor,
                  config: IntegratorConfig) -> FrameSamples:
    """Unproject, sample the rays, snap to the nearest voxel and average the samples per voxel."""
    points_w, pixel_index = unproject(depth_m, valid, K, T_world_camera)
    positions, values = ray_samples(points_w, T_world_camera[:3, 3], config)
    n_rays, n_per_ray = positions.shape[:2]
    voxels = torch.round(positions.reshape(-1, 3) / config.voxel_size_m).to(torch.int64)
    keys, inverse, counts = torch.unique(voxel_keys(voxels), return_inverse=True, return_counts=True)
    sums = torch.zeros(keys.numel(), dtype=torch.float32, device=keys.device)
    sums.index_add_(0, inverse, values.to(torch.float32).repeat(n_rays))
    return FrameSamples(keys, sums / counts, inverse, counts, pixel_index, n_per_ray)


def aggregate_pixel_values(samples: FrameSamples, pixel_values: torch.Tensor) -> torch.Tensor:
    """Per-voxel mean of per-pixel values (P x C) repeated along each ray (the paper's "repeat T times")."""
    repeated = pixel_values.repeat_interleave(samples.n_samples_per_ray, dim=0)
    sums = torch.zeros((samples.keys.numel(), pixel_values.shape[1]), dtype=pixel_values.dtype,
                       device=pixel_values.device)
    sums = sums.index_add(0, samples.inverse, repeated)
    return sums / samples.counts.unsqueeze(1).to(pixel_values.dtype)


# ------------------------------------------------------------------------------------------------
# Compiled integration (the engine's path): the same computation as the functions above, as two
# numba kernels over one frame, without sorting. `locate_samples` snaps every ray sample to its
# voxel (allocating blocks in the hash table) and groups the samples by block; `update_voxels`
# averages each voxel's samples of this frame and applies the running averages block by block.
# Both keep the flat signatures numba compiles; callers use the typed wrappers
# `locate_frame_samples` and `update_frame_voxels` below them.
# ------------------------------------------------------------------------------------------------


_RECENT_BITS = 12  # entries of locate_samples' table of recent blocks: 2^12


@numba.njit(cache=True, nogil=True)
def locate_samples(depth_m: np.ndarray, depth_min_m: float, depth_max_m: float, border_px: int, K: np.ndarray,
                   T_world_camera: np.ndarray, offsets_m: np.ndarray, voxel_size_m: float, table_keys: np.ndarray,
                   table_slots: np.ndarray, state: np.ndarray, slot_keys: np.ndarray, slot_to_touched: np.ndarray,
                   touched_slots: np.ndarray, sample_flat: np.ndarray, sample_touched: np.ndarray,
                   pixel_index: np.ndarray) -> tuple[int, int, bool]:
    """Voxel of every sample of every valid pixel (P pixels x S samples, flat pool index
    slot*512 + local) and the frame's touched blocks. Returns (P, number of touched blocks, ok);
    ok is False when the hash table or the slot arrays ran full (grow them and call again: the
    blocks added so far stay valid). The kernel: call it through `locate_frame_samples`."""
    h, w = depth_m.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R = T_world_camera[:3, :3]
    t = T_world_camera[:3, 3]
    n_samples = offsets_m.shape[0]
    n_pixels = 0
    n_touched = 0
    inv_voxel = 1.0 / voxel_size_m
    # consecutive samples mostly share a block (-2: no block's key, nor coords_key's -1 out of range)
    last_key, last_slot, touched = np.int64(-2), np.int64(-1), np.int64(-1)
    ray_keys = np.empty(n_samples, np.int64)  # one pixel's samples: block key, voxel in the block
    ray_locals = np.empty(n_samples, np.int64)
    # the blocks met lately (direct-mapped by key): neighbouring rays cross the same blocks, and this
    # small table stays in the core's first cache where the hash table and slot_to_touched do not
    recent_keys = np.full(1 << _RECENT_BITS, -2, np.int64)
    recent_slots = np.zeros(1 << _RECENT_BITS, np.int64)
    recent_touched = np.zeros(1 << _RECENT_BITS, np.int64)
    for v in range(border_px, h - border_px):
        for u in range(border_px, w - border_px):
            z = np.float64(depth_m[v, u])
            if not (z > 0.0 and z >= depth_min_m and z <= depth_max_m):  # NaN fails every comparison
                continue
            x = (u - cx) / fx * z
            y = (v - cy) / fy * z
            px = x * R[0, 0] + y * R[0, 1] + z * R[0, 2] + t[0]
            py = x * R[1, 0] + y * R[1, 1] + z * R[1, 2] + t[1]
            pz = x * R[2, 0] + y * R[2, 1] + z * R[2, 2] + t[2]
            dx, dy, dz = px - t[0], py - t[1], pz - t[2]
            norm = max(np.sqrt(dx * dx + dy * dy + dz * dz), 1e-9)
            dx, dy, dz = dx / norm, dy / norm, dz / norm
            base = n_pixels * n_samples
            for k in range(n_samples):  # arithmetic only: this loop vectorises
                o = offsets_m[k]
                i = np.int64(np.rint((px + o * dx) * inv_voxel))
                j = np.int64(np.rint((py + o * dy) * inv_voxel))
                k_ = np.int64(np.rint((pz + o * dz) * inv_voxel))
                ray_keys[k] = coords_key(i >> 3, j >> 3, k_ >> 3)
                ray_locals[k] = ((i & 7) << 6) + ((j & 7) << 3) + (k_ & 7)
            for k in range(n_samples):
                key = ray_keys[k]
                if key != last_key:
                    if key < 0:
                        return n_pixels, n_touched, False
                    c = int((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - _RECENT_BITS))
                    if recent_keys[c] != key:
                        slot = hash_find_or_add(table_keys, table_slots, key, state, slot_keys)
                        if slot < 0:
                            return n_pixels, n_touched, False
                        touched = slot_to_touched[slot]
                        if touched < 0:
                            touched = np.int64(n_touched)
                            slot_to_touched[slot] = touched
                            touched_slots[touched] = slot
                            n_touched += 1
                        recent_keys[c], recent_slots[c], recent_touched[c] = key, slot, touched
                    last_key, last_slot, touched = key, recent_slots[c], recent_touched[c]
                sample_flat[base + k] = last_slot * 512 + ray_locals[k]
                sample_touched[base + k] = touched
            pixel_index[n_pixels] = v * w + u
            n_pixels += 1
    return n_pixels, n_touched, True


@numba.njit(cache=True, nogil=True)
def drop_sparse_new_blocks(n_before: int, n_after: int, min_samples: int, n_samples_total: int, n_touched: int,
                           touched_slots: np.ndarray, slot_to_touched: np.ndarray, sample_touched: np.ndarray,
                           table_keys: np.ndarray, table_slots: np.ndarray, slot_keys: np.ndarray,
                           on_disk: np.ndarray) -> tuple[int, int, int, int, np.ndarray]:
    """The allocation policy, after `locate_samples` ran: of the blocks it added (slots
    n_before..n_after-1, not committed yet), those that received fewer than min_samples of the
    frame's samples are taken out of the hash table again (flying pixels and far noise scatter
    a few samples over many blocks that would stay nearly empty). Kept blocks close up their
    slots, and touched_slots follows; the samples are not rewritten (a pass over all of them):
    the returned touched_map takes their sample_touched to the kept touched blocks (-1: dropped;
    empty when nothing was dropped), and their voxel in the block stays sample_flat & 511.
    Blocks that existed before the frame take every sample, and so do blocks coming back from
    disk (on_disk: per added block, whether the grid's spill holds it).
    Returns (blocks now in the grid, touched blocks kept, samples dropped, blocks dropped, touched_map)."""
    count = np.zeros(n_touched, np.int64)
    for n in range(n_samples_total):
        count[sample_touched[n]] += 1
    keep = np.empty(n_after - n_before, np.bool_)
    dropped_samples = 0
    for slot in range(n_before, n_after):
        c = count[slot_to_touched[slot]]
        keep[slot - n_before] = c >= min_samples or on_disk[slot - n_before]
        if not keep[slot - n_before]:
            dropped_samples += c
    n_kept_new = int(keep.sum())
    if n_kept_new == n_after - n_before:
        return n_after, n_touched, 0, 0, np.zeros(0, np.int32)
    new_slot = drop_new_blocks(table_keys, table_slots, slot_keys, n_before, keep)
    touched_map = np.empty(n_touched, np.int32)
    kept = 0
    for b in range(n_touched):
        slot = touched_slots[b]
        target = slot if slot < n_before else new_slot[slot - n_before]
        if target < 0:
            touched_map[b] = -1
        else:
            touched_map[b] = kept
            touched_slots[kept] = target
            kept += 1
    return n_before + n_kept_new, kept, dropped_samples, n_after - n_before - n_kept_new, touched_map


# weight counters are integers 0..2048 (w_max): their float16 bits and tanh (a weighting-net input) by table
_F16_OF_COUNT = np.arange(2049, dtype=np.float16).view(np.int16)
TANH_OF_COUNT = np.tanh(np.arange(2049, dtype=np.float64)).astype(np.float32)


def _reach_of_voxel(halo: int) -> np.ndarray:
    """Per local voxel index (64 x + 8 y + z), the blocks within `halo` voxels of it, as bits of their
    neighbour codes 9 (dx + 1) + 3 (dy + 1) + (dz + 1) (the block itself: code 13)."""
    x, y, z = np.unravel_index(np.arange(512), (8, 8, 8))
    reach = np.zeros(512, np.int32)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                near = np.ones(512, bool)
                for d, c in ((dx, x), (dy, y), (dz, z)):
                    near &= (c < halo) if d < 0 else (c >= 8 - halo) if d > 0 else True
                reach[near] |= 1 << (9 * (dx + 1) + 3 * (dy + 1) + dz + 1)
    return reach


# A change of the weighting-net inputs at a voxel can move alpha within WEIGHTING_HALO voxels of it:
# in the blocks these bits name (`update_voxels` collects them per block)
REACH_OF_VOXEL = _reach_of_voxel(WEIGHTING_HALO)
REACH_ALL = (1 << 27) - 1


@numba.njit(cache=True, nogil=True)
def _group_by_block(n_pixels: int, n_samples: int, n_touched: int, sample_flat: np.ndarray,
                    sample_touched: np.ndarray, touched_map: np.ndarray, pixel_index: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Counting sort of the samples by touched block (sample_touched through touched_map where it
    is not empty, see `drop_sparse_new_blocks`; -1: dropped): start (n_touched + 1) and, in block
    order, each sample's voxel in its block, image pixel and step along the ray. Walking pixels and
    steps in two loops spares the per-sample division the accumulation would otherwise need."""
    total = n_pixels * n_samples
    mapped = touched_map.shape[0] > 0
    start = np.zeros(n_touched + 1, np.int64)
    for n in range(total):
        b = touched_map[sample_touched[n]] if mapped else sample_touched[n]
        if b >= 0:
            start[b + 1] += 1
    for b in range(n_touched):
        start[b + 1] += start[b]
    fill = start[:-1].copy()
    local = np.empty(total, np.int16)
    pixel = np.empty(total, np.int32)
    step = np.empty(total, np.int8)
    n = 0
    for p in range(n_pixels):
        image_pixel = pixel_index[p]
        for k in range(n_samples):
            b = touched_map[sample_touched[n]] if mapped else sample_touched[n]
            if b < 0:
                n += 1
                continue
            m = fill[b]
            fill[b] = m + 1
            local[m] = sample_flat[n] & 511  # slot * 512 + local
            pixel[m] = image_pixel
            step[m] = k
            n += 1
    return start, local, pixel, step


@numba.njit(cache=True, nogil=True)
def _update_blocks(order: np.ndarray, start: np.ndarray, sample_local: np.ndarray, sample_pixel: np.ndarray,
                   sample_step: np.ndarray, sample_tsdf_m: np.ndarray, pixel_features: np.ndarray,
                   touched_slots: np.ndarray, tsdf: np.ndarray, weight: np.ndarray, features: np.ndarray,
                   tsdf_base: np.ndarray, weight_base: np.ndarray, reach: np.ndarray, w_max: float) -> int:
    """update_voxels' per-block work on the touched blocks `order` names, in that order (blocks are
    independent of each other)."""
    n_channels = pixel_features.shape[1]
    feature_stride = features.shape[0] // max(weight.shape[0], 1)  # a voxel's feature-pool entries
    updated = 0
    count = np.zeros(512, np.int64)  # per block: zero again after use
    block_voxels = np.empty(512, np.int64)  # per block: its voxels with samples, as first met
    sum_tsdf = np.empty(512, np.float32)
    sum_features = np.empty((512, n_channels), np.float32)
    for b in order:
        base_index = touched_slots[b] * 512
        n_voxels = 0
        changed = np.int32(0)  # the block's reach bits (REACH_OF_VOXEL) of voxels whose inputs changed
        renewed = np.int32(0)  # ... of voxels first observed or whose TSDF changed sign
        for m in range(start[b], start[b + 1]):
            local = sample_local[m]
            if count[local] == 0:
                block_voxels[n_voxels] = local
                n_voxels += 1
                sum_tsdf[local] = 0.0
                sum_features[local, :] = 0.0
                # the voxel's scattered pool entries, needed below: fetched while the samples are summed
                voxel = base_index + local
                prefetch(features, voxel * feature_stride)
                prefetch(tsdf, voxel)
                prefetch(weight, voxel)
            count[local] += 1
            sum_tsdf[local] += sample_tsdf_m[sample_step[m]]
            p = sample_pixel[m]
            for c in range(n_channels):
                sum_features[local, c] += pixel_features[p, c]
        for i in range(n_voxels):  # a frame reaches a fraction of a block: no scan of all 512
            local = block_voxels[i]
            cnt = count[local]
            count[local] = 0
            updated += 1
            voxel = base_index + local
            inv_count = np.float32(1.0) / np.float32(cnt)
            old_weight = f16_to_f32(weight[voxel])
            keep = old_weight / (old_weight + np.float32(1.0))  # running average: keep*old + add*update
            add = np.float32(1.0) / (old_weight + np.float32(1.0))
            # averaged in float32, rounded to the pool's storage on store
            change = blend_features(features, n_channels, voxel, keep, add, sum_features[local], inv_count)
            mean_tsdf = sum_tsdf[local] * inv_count
            old_tsdf = load_f32(tsdf, voxel)
            store_f32(tsdf, voxel, keep * old_tsdf + add * mean_tsdf)
            new_tsdf = load_f32(tsdf, voxel)  # as stored: the change and the sign test see what readers will
            new_weight = min(old_weight + np.float32(1.0), w_max)
            weight[voxel] = _F16_OF_COUNT[int(new_weight)]
            change = max(change, TANH_OF_COUNT[int(new_weight)] - TANH_OF_COUNT[int(old_weight)])
            if old_weight == 0.0 or (new_tsdf < 0.0) != (old_tsdf < 0.0):
                renewed |= REACH_OF_VOXEL[local]  # the voxel may join the observed or the surface set
            elif change > 0.0 or new_tsdf != old_tsdf:
                changed |= REACH_OF_VOXEL[local]
            if tsdf_base.shape[0]:
                base_weight = f16_to_f32(weight_base[voxel])
                base_add = np.float32(1.0) / (base_weight + np.float32(1.0))
                store_f32(tsdf_base, voxel,
                          (np.float32(1.0) - base_add) * load_f32(tsdf_base, voxel) + base_add * mean_tsdf)
                weight_base[voxel] = _F16_OF_COUNT[int(min(base_weight + np.float32(1.0), w_max))]
        reach[b, 0] = changed
        reach[b, 1] = renewed
    return updated


_NO_MAP = np.zeros(0, np.int32)

# update_voxels shares a frame's blocks with this worker from this many samples on
SPLIT_MIN_SAMPLES = 50_000
SPLIT_CHUNKS = 8  # shares of about equal samples, taken from both ends of the block order
_UPDATE_WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="senfunet-update")


class _Chunks:
    """The chunks of one frame's blocks, taken by two threads from either end under a lock (each
    chunk's kernel runs without the GIL): a worker that waits for a core leaves its chunks to the
    integrating thread instead of making it wait."""

    def __init__(self, n: int) -> None:
        self._lock = threading.Lock()
        self._front, self._back = 0, n - 1

    def take(self, *, from_front: bool) -> int | None:
        with self._lock:
            if self._front > self._back:
                return None
            if from_front:
                self._front += 1
                return self._front - 1
            self._back -= 1
            return self._back + 1


def update_voxels(n_pixels: int, n_touched: int, sample_flat: np.ndarray, sample_touched: np.ndarray,
                  sample_tsdf_m: np.ndarray, pixel_index: np.ndarray, pixel_features: np.ndarray,
                  touched_slots: np.ndarray, tsdf: np.ndarray, weight: np.ndarray, features: np.ndarray,
                  tsdf_base: np.ndarray, weight_base: np.ndarray, reach: np.ndarray, w_max: float, *,
                  touched_map: np.ndarray | None = None) -> int:
    """Per voxel: the mean of this frame's samples (TSDF value and the pixel's features), then the
    running averages of the sensor's TSDF, weight and features and of the TSDF Fusion baseline
    (skipped when tsdf_base is empty).
    reach (n_touched x 2 int32, written): per touched block, the blocks whose alpha its changes can
    move (REACH_OF_VOXEL bits): [0] of voxels whose weighting-net inputs (features, tanh(weight),
    TSDF) changed, [1] of voxels first observed or whose TSDF changed sign.
    Weights are float16 bit patterns (int16), TSDFs float16 bits or float32
    (`grid.load_f32`), features float16 bits or packed int8 (`grid.load_feature`); pixel_features:
    (H*W) x C float32; touched_map: as `drop_sparse_new_blocks` returns it (None: none).
    Returns the number of voxels updated.

    Blocks are independent: a frame of at least SPLIT_MIN_SAMPLES samples is cut into SPLIT_CHUNKS
    chunks of blocks, which this thread takes from the front and a worker thread from the back
    until none is left (bit-identical to one pass; below that, handing over costs more than it
    saves). This is the integration thread's longest step, and it waits on memory more than it
    computes. The flat form: call it through `update_frame_voxels`."""
    start, local, pixel, step = _group_by_block(n_pixels, sample_tsdf_m.shape[0], n_touched, sample_flat,
                                                sample_touched, _NO_MAP if touched_map is None else touched_map,
                                                pixel_index)

    # blocks in slot order, which is pool-memory order: the scattered rows come in ascending addresses
    order = np.argsort(touched_slots[:start.shape[0] - 1], kind="stable")

    def blocks(block_order: np.ndarray) -> int:
        return _update_blocks(block_order, start, local, pixel, step, sample_tsdf_m, pixel_features, touched_slots,
                              tsdf, weight, features, tsdf_base, weight_base, reach, w_max)

    if start[-1] < max(SPLIT_MIN_SAMPLES, 1):
        return blocks(order)
    bounds = np.searchsorted(np.cumsum(np.diff(start)[order]), start[-1] * np.arange(1, SPLIT_CHUNKS) // SPLIT_CHUNKS)
    chunks = np.split(order, bounds)
    shared = _Chunks(len(chunks))

    def take_all(*, from_front: bool) -> int:
        updated = 0
        while (i := shared.take(from_front=from_front)) is not None:
            updated += blocks(chunks[i])
        return updated

    worker = _UPDATE_WORKER.submit(take_all, from_front=False)
    return take_all(from_front=True) + worker.result()


@dataclass
class LocatedSamples:
    """Where one frame's ray samples fell (`locate_frame_samples`): P valid pixels x S samples.

    The arrays may be longer than used (scratch buffers): the first P * S samples, P pixels and
    n_touched slots are this frame's.
    """

    n_pixels: int  # P
    n_touched: int  # blocks touched by the samples
    sample_flat: np.ndarray  # int64 pool index (slot * 512 + local voxel) of each sample, pixel-major
    sample_touched: np.ndarray  # int32 index into touched_slots of each sample's block (through touched_map)
    pixel_index: np.ndarray  # int64 flat image index (v * W + u) of each valid pixel
    touched_slots: np.ndarray  # int64 slots of the touched blocks, in the order first touched
    dropped_samples: int = 0  # samples in new blocks the allocation policy did not allocate
    dropped_blocks: int = 0  # those blocks
    # when the policy dropped blocks: sample_touched -> index into touched_slots (-1: dropped), and
    # sample_flat's slot part is the one before the policy (see drop_sparse_new_blocks); else None
    touched_map: np.ndarray | None = None


def locate_frame_samples(grid: BlockGrid, depth_m: np.ndarray, K: np.ndarray, T_world_camera: np.ndarray, *,
                         depth_range_m: tuple[float, float], border_px: int, offsets_m: np.ndarray,
                         voxel_size_m: float, min_new_block_samples: int = 0,
                         scratch: dict[str, np.ndarray] | None = None) -> LocatedSamples:
    """Snap every sample of every valid pixel to its voxel, allocating the blocks it needs in `grid`
    (grown as needed). depth_m: H x W metres (invalid pixels outside depth_range_m, NaN or inf);
    offsets_m: S float64 signed offsets along each ray (negative: towards the camera);
    min_new_block_samples: a block the grid does not hold yet is allocated only when at least this
    many of the frame's samples fall in it; the others' samples are dropped and counted
    (`drop_sparse_new_blocks`). Raises InputError (grid untouched but for empty blocks already
    allocated) when samples fall outside the key range. `scratch` as in `integrate_frame`."""
    h, w = depth_m.shape
    n_max = h * w * len(offsets_m)
    sample_flat = scratch_array(scratch, "sample_flat", n_max, np.int64)
    sample_touched = scratch_array(scratch, "sample_touched", n_max, np.int32)
    pixel_index = scratch_array(scratch, "pixel_index", h * w, np.int64)
    depth = np.ascontiguousarray(depth_m, np.float32)
    K64 = np.ascontiguousarray(K, np.float64)
    T64 = np.ascontiguousarray(T_world_camera, np.float64)
    offsets = np.ascontiguousarray(offsets_m, np.float64)
    n_before = grid.n_blocks
    n_blocks = n_before  # and the blocks this frame added so far (slots n_before..), committed at the end
    while True:
        slot_to_touched = scratch_array(scratch, "slot_to_touched", grid.capacity, np.int32)
        slot_to_touched.fill(-1)
        touched_slots = scratch_array(scratch, "touched_slots", grid.capacity, np.int64)
        state = np.array([n_blocks, min(grid.hash_table.max_blocks(), grid.capacity)], np.int64)
        n_pixels, n_touched, ok = locate_samples(
            depth, depth_range_m[0], depth_range_m[1], border_px, K64, T64, offsets, voxel_size_m,
            *grid.hash_table, state, grid.slot_keys, slot_to_touched, touched_slots, sample_flat,
            sample_touched, pixel_index)
        n_blocks = int(state[0])
        if ok:
            break
        if n_blocks < state[1]:  # not full: a sample left the key range
            grid.commit_new_blocks(n_blocks)  # the table holds the blocks added so far: they stay (empty)
            raise InputError("points lie more than 5 km from the origin; check the pose's units (metres) and frame")
        # grown with the blocks added so far still uncommitted: readers without the lock do not see
        # them, the allocation policy below judges them all, and spilled ones stay on disk until then
        grid.reserve(n_blocks + 1024, added=n_blocks - n_before)
    dropped_samples, dropped_blocks, touched_map = 0, 0, None
    if min_new_block_samples > 1 and n_blocks > n_before:
        n_blocks, n_touched, dropped_samples, dropped_blocks, touched_map = drop_sparse_new_blocks(
            n_before, n_blocks, min_new_block_samples, n_pixels * len(offsets_m), n_touched, touched_slots,
            slot_to_touched, sample_touched, *grid.hash_table, grid.slot_keys,
            grid.on_disk(grid.slot_keys[n_before:n_blocks]))
        touched_map = touched_map if len(touched_map) else None
    grid.commit_new_blocks(int(n_blocks))
    return LocatedSamples(int(n_pixels), int(n_touched), sample_flat, sample_touched, pixel_index, touched_slots,
                          int(dropped_samples), int(dropped_blocks), touched_map)


def update_frame_voxels(grid: BlockGrid, located: LocatedSamples, pixel_features: np.ndarray, *,
                        sample_tsdf_m: np.ndarray, channels: tuple[str, str, str],
                        w_max: float) -> tuple[int, np.ndarray]:
    """Running averages of one sensor's TSDF, weight and features (and of the TSDF Fusion baseline
    "tsdf_base"/"weight_base" when the grid has those channels) from the located samples.
    pixel_features: (H*W) x C float32; sample_tsdf_m: S TSDF value of each sample step (metres);
    channels: the sensor's (tsdf, weight, feature) pool names.
    Returns the number of voxels updated and each touched block's reach (as in `update_voxels`)."""
    tsdf, weight, feature = (kernel_view(grid.pools[name]).reshape(-1) for name in channels)
    if "tsdf_base" in grid.pools:
        tsdf_base, weight_base = (kernel_view(grid.pools[name]).reshape(-1) for name in ("tsdf_base", "weight_base"))
    else:
        tsdf_base, weight_base = np.zeros(0, np.float32), np.zeros(0, np.int16)
    reach = np.zeros((located.n_touched, 2), np.int32)
    updated = update_voxels(located.n_pixels, located.n_touched, located.sample_flat, located.sample_touched,
                            sample_tsdf_m, located.pixel_index, pixel_features, located.touched_slots, tsdf, weight,
                            feature, tsdf_base, weight_base, reach, w_max, touched_map=located.touched_map)
    return updated, reach


@dataclass
class FrameUpdate:
    """What one compiled integration changed."""

    voxels_updated: int
    touched_slots: np.ndarray  # int64 slots of the blocks the frame's samples touched
    reach: np.ndarray  # per touched block, the blocks whose alpha its changes can move (`update_voxels`)
    waited_s: float = 0.0  # time spent waiting for pixel_features()
    dropped_samples: int = 0  # samples the allocation policy dropped (IntegratorConfig.min_new_block_samples)
    dropped_blocks: int = 0  # the new blocks they fell in, not allocated


def integrate_frame(grid: BlockGrid, depth_m: np.ndarray, pixel_features: np.ndarray | Callable[[], np.ndarray],
                    K: np.ndarray, T_world_camera: np.ndarray, depth_range_m: tuple[float, float],
                    config: IntegratorConfig, channels: tuple[str, str, str],
                    scratch: dict[str, np.ndarray] | None = None) -> FrameUpdate:
    """Integrate one frame into `grid` with the compiled kernels.

    depth_m: H x W float32 (invalid pixels anything outside depth_range_m, NaN, inf);
    pixel_features: (H*W) x C float32 (pixel v * W + u's features in row v * W + u) or C x H x W, or
    a callable returning them, called once the samples are located (so a feature net running in
    another thread overlaps that first kernel);
    channels: the sensor's (tsdf, weight, feature) pool names;
    the TSDF Fusion baseline goes to "tsdf_base"/"weight_base" when the grid has those channels.
    Raises InputError (grid untouched but for empty blocks that may have been allocated) when
    samples fall outside the key range. `scratch`: working arrays kept between calls (a dict the
    caller owns and never shares between threads), so frames do not pay for fresh allocations.
    """
    offsets_m = config.sample_offsets().numpy().astype(np.float64) * config.step_m
    located = locate_frame_samples(grid, depth_m, K, T_world_camera, depth_range_m=depth_range_m,
                                   border_px=config.border_px, offsets_m=offsets_m,
                                   voxel_size_m=config.voxel_size_m,
                                   min_new_block_samples=config.min_new_block_samples, scratch=scratch)
    waited_s = time.perf_counter()
    if callable(pixel_features):
        pixel_features = pixel_features()
    waited_s = time.perf_counter() - waited_s
    features = (pixel_features if pixel_features.ndim == 2  # HW x C
                else pixel_features.reshape(pixel_features.shape[0], -1).T)
    features = np.ascontiguousarray(features, np.float32)
    updated, reach = update_frame_voxels(grid, located, features, sample_tsdf_m=-offsets_m, channels=channels,
                                         w_max=config.w_max)
    return FrameUpdate(int(updated), located.touched_slots[:located.n_touched].copy(), reach, waited_s,
                       located.dropped_samples, located.dropped_blocks)
