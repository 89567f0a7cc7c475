"""The map read out voxel by voxel: TSDF values of the observed voxels (evaluation against ground
truth) and the weight cloud (alpha and each sensor's weight counter: the node's ~/weights).

Functions over an engine's public parts: the weighting net is brought up to date first
(`SenFuNet.refresh_alpha`), then the grid is read under the update lock (no eviction moves blocks)
and the data lock (no frame changes them).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .block_mesher import FUSED
from .engine import SenFuNet
from .grid import voxel_centres

__all__ = ["WeightCloud", "voxel_values", "weight_cloud"]


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


@torch.inference_mode()
def weight_cloud(engine: SenFuNet, max_abs_tsdf_m: float | None = None, *, refresh_alpha: bool = True
                 ) -> WeightCloud:
    """Voxels observed by any sensor whose alpha is known: position, alpha and each sensor's weight
    counter. With max_abs_tsdf_m, only voxels whose unfiltered fused |TSDF| is at most that.
    Without refresh_alpha, alpha is as the last updates left it (voxels the net has not judged yet
    are left out)."""
    if refresh_alpha:
        engine.refresh_alpha()
    with engine.update_lock.held(), engine.data_lock:
        slots = torch.arange(engine.grid.n_blocks)
        blocks = engine.mesher.whole_blocks(slots, engine.mesher.channels(FUSED))
        centres = voxel_centres(engine.grid.coords[slots], engine.config.voxel_size_m)
    weights = torch.stack([blocks[f"weight{i}"] for i in range(len(engine.config.sensors))], dim=-1)
    keep = (weights > 0).any(dim=-1) & torch.isfinite(blocks["alpha"])
    if max_abs_tsdf_m is not None:
        tsdf, _ = engine.mesher.values(blocks, FUSED, filtered=False)
        keep &= tsdf.abs() <= max_abs_tsdf_m
    return WeightCloud(centres[keep].numpy(), blocks["alpha"][keep].numpy().astype(np.float32),
                       weights[keep].numpy().astype(np.float32))
