"""The paper's loss (L_f on voxels both sensors saw, L_in and L_out on single-sensor voxels) and the
learning-rate schedule."""
from __future__ import annotations

import math

import torch

from ..fusion import fuse


def senfunet_loss(tsdf_1: torch.Tensor, weight_1: torch.Tensor, tsdf_2: torch.Tensor, weight_2: torch.Tensor,
                  alpha: torch.Tensor, gt_tsdf: torch.Tensor, mask: torch.Tensor, *, lambda1: float, lambda2: float,
                  eta_m: float) -> tuple[torch.Tensor, dict[str, float]]:
    """The paper's loss on the voxels in `mask` (all tensors of one shape).

    L_f: mean |V - V_gt| on C12; L_in(C_i): mean |alpha_i - 1| on C_i voxels whose |V - V_gt| < eta;
    L_out(C_i): mean |alpha_i| on C_i voxels whose |V - V_gt| > eta; alpha_1 = alpha, alpha_2 = 1 - alpha.
    A term over an empty set is 0. Returns the total and the terms (floats) for logging.
    """
    fused = fuse(tsdf_1, weight_1, tsdf_2, weight_2, alpha, apply_filter=False)
    err = (fused.tsdf_m - gt_tsdf).abs()
    zero = alpha.sum() * 0.0

    def mean(values: torch.Tensor, where: torch.Tensor) -> torch.Tensor:
        n = int(where.sum())
        return values[where].sum() / n if n else zero

    c12, c1, c2 = fused.c12 & mask, fused.c1 & mask, fused.c2 & mask
    l_f = mean(err, c12)
    alphas = (alpha, 1 - alpha)
    terms = {"L_f": l_f}
    total = l_f
    for i, ci in enumerate((c1, c2), start=1):
        a = alphas[i - 1]
        l_in = mean((a - 1).abs(), ci & (err < eta_m))
        l_out = mean(a.abs(), ci & (err > eta_m))
        terms[f"L_in{i}"], terms[f"L_out{i}"] = l_in, l_out
        total = total + lambda1 * l_in + lambda2 * l_out
    return total, {k: float(v.detach()) for k, v in terms.items()}


def cosine_lr(lr: float, final_fraction: float, progress: float) -> float:
    """Cosine decay from lr (progress 0) to lr * final_fraction (progress >= 1); constant when the fraction is 1."""
    if final_fraction == 1.0:
        return lr
    low = lr * final_fraction
    return low + 0.5 * (lr - low) * (1 + math.cos(math.pi * min(max(progress, 0.0), 1.0)))
