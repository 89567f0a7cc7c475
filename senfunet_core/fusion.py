"""The fusion module and the learned outlier filter (paper eq. 1 and 2), on voxel arrays.

Sets: C12 = both sensors observed the voxel (W1 > 0 and W2 > 0), C1 = only sensor 1, C2 = only
sensor 2. Fused TSDF: alpha*V1 + (1-alpha)*V2 on C12, V1 on C1, V2 on C2. The filter drops a
C1 voxel when alpha < 0.5 and a C2 voxel when alpha > 0.5 (its weight becomes 0: it leaves the
mesh and the metrics).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch


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
    """Fuse two sensors' TSDFs with the sensor weighting alpha (all tensors of one shape)."""
    c12, c1, c2 = voxel_sets(weight_1, weight_2)
    blended = alpha * tsdf_1 + (1 - alpha) * tsdf_2
    tsdf = torch.where(c12, blended, torch.where(c1, tsdf_1, torch.where(c2, tsdf_2, torch.zeros_like(tsdf_1))))
    observed = c12 | c1 | c2
    if apply_filter:
        observed = observed & ~(c1 & (alpha < 0.5)) & ~(c2 & (alpha > 0.5))
    return Fused(tsdf, observed, c12, c1, c2)
