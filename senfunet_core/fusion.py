"""The fusion module and the learned outlier filter (paper eq. 1 and 2), on voxel arrays.

Sets: C12 = both sensors observed the voxel (W1 > 0 and W2 > 0), C1 = only sensor 1, C2 = only
sensor 2. Fused TSDF: alpha*V1 + (1-alpha)*V2 on C12, V1 on C1, V2 on C2. The filter drops a
C1 voxel when alpha < 0.5 and a C2 voxel when alpha > 0.5 (its weight becomes 0: it leaves the
mesh and the metrics). The live engine leaves alpha NaN where the weighting net has not run yet
(see engine.update's budget): those voxels count as alpha 0.5 on C12, and the filter holds their
C1 and C2 voxels back until the net has judged them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch

from .grid import load_alpha, load_f32


@dataclass
class Fused:
    tsdf_m: torch.Tensor  # fused TSDF (0 where unobserved)
    observed: torch.Tensor  # bool: voxel carries a surface hypothesis after the (optional) filter
    c12: torch.Tensor
    c1: torch.Tensor
    c2: torch.Tensor


def voxel_sets(weight_1: torch.Tensor, weight_2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    seen_1, seen_2 = weight_1 > 0, weight_2 > 0
    return seen_1 & seen_2, seen_1 & ~seen_2, ~seen_1 & seen_2


def fuse(tsdf_1: torch.Tensor, weight_1: torch.Tensor, tsdf_2: torch.Tensor, weight_2: torch.Tensor,
         alpha: torch.Tensor, apply_filter: bool = True) -> Fused:
    """Fuse two sensors' TSDFs with the sensor weighting alpha (all tensors of one shape).
    Alpha NaN means "not evaluated yet": C12 is averaged, and the filter drops C1 and C2."""
    c12, c1, c2 = voxel_sets(weight_1, weight_2)
    unknown = torch.isnan(alpha)
    a = torch.where(unknown, torch.full_like(alpha, 0.5), alpha)
    blended = a * tsdf_1 + (1 - a) * tsdf_2
    tsdf = torch.where(c12, blended, torch.where(c1, tsdf_1, torch.where(c2, tsdf_2, torch.zeros_like(tsdf_1))))
    observed = c12 | c1 | c2
    if apply_filter:
        observed = observed & ~(c1 & ((a < 0.5) | unknown)) & ~(c2 & ((a > 0.5) | unknown))
    return Fused(tsdf, observed, c12, c1, c2)


# Which surface a mesh window shows: the fused one, one sensor's, or the TSDF Fusion baseline.
WINDOW_FUSED, WINDOW_SENSOR, WINDOW_BASE = 0, 1, 2


def mesh_windows(neighbours: np.ndarray, which: int, apply_filter: bool, tsdf_1: np.ndarray, weight_1: np.ndarray,
                 tsdf_2: np.ndarray, weight_2: np.ndarray, alpha: np.ndarray, *,
                 out: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per block, the 9^3 samples marching cubes reads (its 8^3 voxels and one layer of its +x, +y,
    +z neighbours): TSDF, observed mask and alpha, each B x 9 x 9 x 9.

    which: WINDOW_FUSED (eq. 1, with the outlier filter when apply_filter; alpha NaN as in `fuse`,
    shown as 0.5), WINDOW_SENSOR or WINDOW_BASE (tsdf_1/weight_1 hold that surface's channels; the
    rest is ignored). Weights are float16 bits (int16); TSDFs and alpha float16 bits or float32.
    out: flat float32, bool and float32 buffers of at least B * 9^3 entries to write them to
    (reused between batches: fresh arrays of this size cost their page faults); default new ones."""
    size = neighbours.shape[0] * 9**3
    if out is None:
        out = (np.empty(size, np.float32), np.empty(size, np.bool_), np.empty(size, np.float32))
    tsdf, observed, alpha_out = (buffer[:size].reshape(-1, 9, 9, 9) for buffer in out)
    _fill_mesh_windows(neighbours, which, apply_filter, tsdf_1, weight_1, tsdf_2, weight_2, alpha, tsdf, observed,
                       alpha_out)
    return tsdf, observed, alpha_out


@numba.njit(cache=True, nogil=True)
def _fill_mesh_windows(neighbours: np.ndarray, which: int, apply_filter: bool, tsdf_1: np.ndarray,
                       weight_1: np.ndarray, tsdf_2: np.ndarray, weight_2: np.ndarray, alpha: np.ndarray,
                       tsdf: np.ndarray, observed: np.ndarray, alpha_out: np.ndarray) -> None:
    """`mesh_windows`' kernel: every entry of the outputs written (they may hold an earlier batch)."""
    for b in range(neighbours.shape[0]):
        # the window in 8 parts, one per block it reads (bx, by, bz: 0 = this block, 1 = the next one)
        for bx in range(2):
            for by in range(2):
                for bz in range(2):
                    slot = neighbours[b, (bx + 1) * 9 + (by + 1) * 3 + bz + 1]
                    if slot < 0:  # no block there: unobserved
                        tsdf[b, 8 * bx:8 + bx, 8 * by:8 + by, 8 * bz:8 + bz] = 0.0
                        observed[b, 8 * bx:8 + bx, 8 * by:8 + by, 8 * bz:8 + bz] = False
                        alpha_out[b, 8 * bx:8 + bx, 8 * by:8 + by, 8 * bz:8 + bz] = 0.0
                        continue
                    for x in range(8 * bx, 8 + bx):
                        for y in range(8 * by, 8 + by):
                            row = slot * 512 + (x - 8 * bx) * 64 + (y - 8 * by) * 8 - 8 * bz
                            tsdf_row, observed_row, alpha_row = tsdf[b, x, y], observed[b, x, y], alpha_out[b, x, y]
                            if which != WINDOW_FUSED:
                                for z in range(8 * bz, 8 + bz):
                                    v = row + z
                                    seen_1 = weight_1[v] > 0  # weights are >= 0: positive float16 bits
                                    tsdf_row[z] = load_f32(tsdf_1, v) if seen_1 else np.float32(0.0)
                                    observed_row[z] = seen_1
                                    alpha_row[z] = 0.0
                                continue
                            # every value computed and the results selected: no branch per voxel
                            # for the CPU to mispredict
                            for z in range(8 * bz, 8 + bz):
                                v = row + z
                                seen_1, seen_2 = weight_1[v] > 0, weight_2[v] > 0
                                a = load_alpha(alpha, v)
                                observed_row[z] = _fused_observed(seen_1, seen_2, a, apply_filter)
                                a = np.float32(0.5) if a != a else a  # NaN: not evaluated yet
                                alpha_row[z] = a
                                tsdf_a, tsdf_b = load_f32(tsdf_1, v), load_f32(tsdf_2, v)
                                blended = np.float32(a * tsdf_a + (1.0 - a) * tsdf_b)
                                tsdf_row[z] = (blended if seen_1 & seen_2
                                               else tsdf_a if seen_1 else tsdf_b if seen_2 else np.float32(0.0))


@numba.njit(inline="always")
def _fused_observed(seen_1: bool, seen_2: bool, alpha: np.float32, apply_filter: bool) -> bool:
    """Whether a voxel counts as observed in the fused surface (`fuse`'s rule; alpha NaN: not
    evaluated yet, so the filter holds its C1 and C2 voxels back)."""
    unknown = alpha != alpha
    a = np.float32(0.5) if unknown else alpha
    keep_1 = not (apply_filter & ((a < 0.5) | unknown))
    keep_2 = not (apply_filter & ((a > 0.5) | unknown))
    return (seen_1 & seen_2) | (seen_1 & keep_1) | (seen_2 & keep_2)


def blocks_with_observed(slots: np.ndarray, which: int, apply_filter: bool, weight_1: np.ndarray,
                         weight_2: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Per block, whether any of its own 8^3 voxels is observed as `mesh_windows` marks them (its
    arguments as there). Every marching-cubes cell of a block's window has its least corner among
    the block's own voxels, and only cells whose 8 corners are observed make triangles: a block
    without an observed voxel has no triangles, and its window need not be filled. The scan reads
    the block's own weights and alpha, a small part of what filling its window reads."""
    out = np.empty(len(slots), np.bool_)
    _blocks_with_observed(np.ascontiguousarray(slots, np.int64), which, apply_filter, weight_1, weight_2, alpha, out)
    return out


@numba.njit(cache=True, nogil=True)
def _blocks_with_observed(slots: np.ndarray, which: int, apply_filter: bool, weight_1: np.ndarray,
                          weight_2: np.ndarray, alpha: np.ndarray, out: np.ndarray) -> None:
    for b in range(slots.shape[0]):
        base = slots[b] * 512
        found = False
        for v in range(base, base + 512):
            seen_1 = weight_1[v] > 0
            if which != WINDOW_FUSED:
                found = seen_1
            else:
                found = _fused_observed(seen_1, weight_2[v] > 0, load_alpha(alpha, v), apply_filter)
            if found:
                break
        out[b] = found
