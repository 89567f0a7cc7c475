"""The map read out voxel by voxel: TSDF values of the observed voxels (evaluation against ground
truth) and the weight cloud (alpha and each sensor's weight counter: the node's ~/weights).

Functions over an engine's public parts. `voxel_values` brings the weighting net up to date first
(`SenFuNet.refresh_alpha`) and reads the grid under the update lock (no eviction moves blocks) and
the data lock (no frame changes them). `weight_cloud` holds neither for the whole map: it takes the
blocks' keys under the data lock, then reads them `CLOUD_SLICE_BLOCKS` at a time, each slice found
by key and read by a compiled kernel under the data lock, which it lets go between slices (a frame
integrated or an update's eviction goes on meanwhile; the update lock is never taken). Each block is
read whole at one moment: a block a frame changed between two slices shows the frame or not, a
block evicted meanwhile is left out, one allocated meanwhile comes with the next cloud.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch

from .block_mesher import FUSED
from .engine import SenFuNet
from .grid import BLOCK, BLOCK_VOXELS, block_keys, load_alpha, load_f32, voxel_centres

__all__ = ["CLOUD_SLICE_BLOCKS", "WeightCloud", "voxel_values", "warm_up", "weight_cloud"]

# blocks a weight cloud reads per hold of the data lock: 256 K voxels, a few milliseconds (what an
# integration or an eviction waiting for the lock waits at most)
CLOUD_SLICE_BLOCKS = 512
_CLOUD_CHANNELS = ("tsdf0", "weight0", "tsdf1", "weight1", "alpha")


@dataclass
class WeightCloud:
    positions_m: np.ndarray  # Nx3 float32 voxel centres
    alpha: np.ndarray  # N float32 sensor weighting (weight of sensor 1)
    weights: np.ndarray  # N x n_sensors float32 weight counters


@torch.inference_mode()
def voxel_values(engine: SenFuNet, which: str = FUSED, filtered: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N x 3, metres) and TSDF values (N) of the observed voxels of `which` ("fused", a
    sensor's name, "tsdf_fusion")."""
    engine.config.check_mesh_name(which)
    if which == FUSED:
        engine.refresh_alpha()
    with engine.update_lock.held(), engine.data_lock:
        slots = torch.arange(engine.grid.n_blocks)
        blocks = engine.mesher.whole_blocks(slots, engine.mesher.channels(which))
        tsdf, observed = engine.mesher.values(blocks, which, filtered)
        centres = voxel_centres(engine.grid.coords[slots], engine.config.voxel_size_m)
        return centres[observed].numpy(), tsdf[observed].numpy()


def weight_cloud(engine: SenFuNet, max_abs_tsdf_m: float | None = None, *, refresh_alpha: bool = True,
                 slice_blocks: int = CLOUD_SLICE_BLOCKS) -> WeightCloud:
    """Voxels observed by any sensor whose alpha is known: position, alpha and each sensor's weight
    counter, block by block in slot order, each block's voxels in their pool order. With
    max_abs_tsdf_m, only voxels whose unfiltered fused |TSDF| is at most that. Without refresh_alpha,
    alpha is as the last updates left it (voxels the net has not judged yet are left out).

    Reads `slice_blocks` blocks per hold of the data lock (see the module docstring); the fields
    are views of one N x (4 + n_sensors) table, each row x, y, z, alpha, the weights."""
    if refresh_alpha:
        engine.refresh_alpha()
    with engine.data_lock:  # only the blocks' keys: integration waits for this lock
        coords = engine.grid.coords[: engine.grid.n_blocks].numpy().copy()
    keys = block_keys(torch.from_numpy(coords))
    band = np.float32(-1.0 if max_abs_tsdf_m is None else max_abs_tsdf_m)  # compared in float32, as torch does
    size = np.float32(engine.config.voxel_size_m)
    n_sensors = len(engine.config.sensors)
    rows = np.empty((min(slice_blocks, len(coords)) * BLOCK_VOXELS, 4 + n_sensors), np.float32)
    parts: list[np.ndarray] = []
    for start in range(0, len(coords), slice_blocks):
        end = start + slice_blocks
        with engine.data_lock:  # the slots and pools as they are now (evictions move blocks, growth the pools)
            slots = engine.grid.lookup_keys(keys[start:end]).numpy()
            n = _cloud_rows(slots, coords[start:end], size, band, *engine.store.views(*_CLOUD_CHANNELS), rows)
        parts.append(rows[:n].copy())
    table = np.concatenate(parts) if parts else rows[:0]
    return WeightCloud(table[:, :3], table[:, 3], table[:, 4:])


def warm_up(engine: SenFuNet) -> None:
    """Compile (or load from numba's cache) the weight cloud's kernel for this engine's pools."""
    with engine.data_lock:
        views = engine.store.views(*_CLOUD_CHANNELS)
    _cloud_rows(np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.float32(0.01), np.float32(-1.0), *views,
                np.empty((0, 6), np.float32))


@numba.njit(cache=True, nogil=True)
def _cloud_rows(slots: np.ndarray, coords: np.ndarray, voxel_size_m: np.float32, band_m: np.float32,
                tsdf_1: np.ndarray, weight_1: np.ndarray, tsdf_2: np.ndarray, weight_2: np.ndarray,
                alpha: np.ndarray, out: np.ndarray) -> int:
    """The weight cloud's rows (x, y, z, alpha, weight 1, weight 2) of these blocks (slots, -1: gone;
    coords: their block coordinates) into `out`; returns how many. A voxel goes in when a sensor
    observed it and its alpha is known, and, with band_m >= 0, its unfiltered fused |TSDF| is at most
    band_m (`fusion.fuse`'s arithmetic, in float32). Positions are `grid.voxel_centres`'."""
    n = 0
    one = np.float32(1.0)
    for b in range(slots.shape[0]):
        slot = slots[b]
        if slot < 0:
            continue
        base = slot * BLOCK_VOXELS
        for v in range(BLOCK_VOXELS):
            w1 = load_f32(weight_1, base + v)
            w2 = load_f32(weight_2, base + v)
            if not (w1 > 0 or w2 > 0):
                continue
            a = load_alpha(alpha, base + v)
            if not np.isfinite(a):
                continue
            if band_m >= 0:
                if w1 > 0 and w2 > 0:
                    tsdf = a * load_f32(tsdf_1, base + v) + (one - a) * load_f32(tsdf_2, base + v)
                elif w1 > 0:
                    tsdf = load_f32(tsdf_1, base + v)
                else:
                    tsdf = load_f32(tsdf_2, base + v)
                if not abs(tsdf) <= band_m:
                    continue
            out[n, 0] = np.float32(coords[b, 0] * BLOCK + v // (BLOCK * BLOCK)) * voxel_size_m
            out[n, 1] = np.float32(coords[b, 1] * BLOCK + (v // BLOCK) % BLOCK) * voxel_size_m
            out[n, 2] = np.float32(coords[b, 2] * BLOCK + v % BLOCK) * voxel_size_m
            out[n, 3] = a
            out[n, 4] = w1
            out[n, 5] = w2
            n += 1
    return n
