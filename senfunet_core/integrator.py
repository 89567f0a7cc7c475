"""Shape and feature integration of one depth frame (paper section 3 a, b and supplementary B).

Pure tensor functions: validity mask, unprojection, ray samples, aggregation of one frame's
samples per voxel, and the running-average update. `integrate_samples` applies them to a
`BlockGrid`.

Convention: `T_world_camera` maps camera (optical frame: z forward, x right, y down) to world,
metres; `K` is the pinhole matrix of the depth image; depth is z-depth in metres.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .errors import InputError
from .grid import BLOCK_VOXELS, BlockGrid, voxel_keys


@dataclass(frozen=True)
class IntegratorConfig:
    voxel_size_m: float = 0.01  # voxel side length
    band_m: float = 0.1  # l: length of the sampled ray segment centred on the measured point
    n_samples: int = 11  # T: samples along the band, band_m / (T - 1) apart
    n_samples_behind: int = 3  # of those behind the surface, how many are written (authors' code: 3)
    w_max: float = 500.0  # weight counter clip
    border_px: int = 10  # image border masked out

    def sample_offsets(self) -> torch.Tensor:
        """Signed sample offsets along the ray in steps (negative: towards the camera)."""
        half = (self.n_samples - 1) // 2
        return torch.arange(-half, self.n_samples_behind + 1, dtype=torch.float32)

    @property
    def step_m(self) -> float:
        return self.band_m / (self.n_samples - 1)


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


def valid_depth_mask(depth_m: torch.Tensor, border_px: int, min_m: float, max_m: float) -> torch.Tensor:
    """Pixels to integrate: finite, inside [min_m, max_m], not in the image border."""
    valid = torch.isfinite(depth_m) & (depth_m >= min_m) & (depth_m <= max_m) & (depth_m > 0)
    if border_px > 0:
        valid[:border_px] = False
        valid[-border_px:] = False
        valid[:, :border_px] = False
        valid[:, -border_px:] = False
    return valid


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


def running_average(old: torch.Tensor, old_weight: torch.Tensor, update: torch.Tensor) -> torch.Tensor:
    """(W * old + update) / (W + 1), broadcasting W over trailing channels."""
    w = old_weight.reshape(*old_weight.shape, *([1] * (old.dim() - old_weight.dim())))
    return (w * old + update) / (w + 1)


def voxel_slots(grid: BlockGrid, keys: torch.Tensor) -> torch.Tensor:
    """Flat pool indices (slot*512 + local) of sorted voxel keys, allocating missing blocks."""
    block = keys // BLOCK_VOXELS
    unique_blocks, block_inverse = torch.unique_consecutive(block, return_inverse=True)
    slots = grid.allocate_keys(unique_blocks)
    return slots[block_inverse] * BLOCK_VOXELS + (keys % BLOCK_VOXELS)


def integrate_into(grid: BlockGrid, flat: torch.Tensor, tsdf_name: str, weight_name: str, tsdf_update: torch.Tensor,
                   w_max: float, feature_name: str | None = None, feature_update: torch.Tensor | None = None) -> None:
    """Running-average update of one TSDF (and optional feature) channel at flat voxel indices."""
    tsdf = grid.pools[tsdf_name].view(-1)
    weight = grid.pools[weight_name].view(-1)
    old_weight = weight[flat]
    if feature_name is not None:
        feature = grid.pools[feature_name].view(-1, grid.pools[feature_name].shape[-1])
        feature[flat] = running_average(feature[flat], old_weight, feature_update)
    tsdf[flat] = running_average(tsdf[flat], old_weight, tsdf_update)
    weight[flat] = torch.clamp(old_weight + 1, max=w_max)
