"""Validation during training: the evaluation's protocol on validation scenes with the networks
being trained, and how their alpha splits the work."""
from __future__ import annotations

import copy
import math

import numpy as np
import torch

from ..grid import decode_alpha
from .config import SENSORS, TrainConfig

ALPHA_STATISTICS = ("c12_alpha_mean", "c12_tof_share", "c1_kept", "c2_kept")


def alpha_statistics(engine) -> dict[str, float]:
    """How an engine's alpha splits the work: mean alpha and the share of alpha > 0.5 on voxels both
    sensors saw, and the share of single-sensor voxels the outlier filter keeps (a collapsed net
    shows alpha = 1 everywhere: all ToF, every stereo-only voxel dropped). Call it after the fused
    grid was read (`readout.voxel_values(engine, "fused")` or a fused mesh): alpha is up to date then."""
    grid = engine.grid
    n = grid.n_blocks
    w0 = grid.pools["weight0"][:n].reshape(-1).float()
    w1 = grid.pools["weight1"][:n].reshape(-1).float()
    alpha = decode_alpha(grid.pools["alpha"][:n].reshape(-1))
    c12, c1, c2 = (w0 > 0) & (w1 > 0), (w0 > 0) & (w1 == 0), (w0 == 0) & (w1 > 0)

    def share(mask: torch.Tensor) -> float:
        return float(mask.float().mean()) if mask.numel() else math.nan

    return {"c12_alpha_mean": float(alpha[c12].mean()) if bool(c12.any()) else math.nan,
            "c12_tof_share": share(alpha[c12] > 0.5), "c1_kept": share(alpha[c1] >= 0.5),
            "c2_kept": share(alpha[c2] <= 0.5)}


class Validator:
    """The evaluation's protocol on validation scenes, with the networks being trained.

    What does not depend on the networks (the single-sensor and TSDF Fusion rows, the observed GT
    crop) is computed once; each validation re-integrates the frames (the features come from the
    feature nets) and scores the fused grid only."""

    def __init__(self, config: TrainConfig, log=print) -> None:
        from .evaluation import cached_gt_mesh_vertices, cached_sequence

        self.config = config
        self.scenes = []
        for seed in config.val_scenes:
            seq = cached_sequence(seed, duration_s=config.val_duration_s, tof_rate_hz=config.val_tof_rate_hz,
                                  stereo_rate_hz=config.val_stereo_rate_hz, cache_dir=config.cache_dir, log=log)
            self.scenes.append((seed, seq, cached_gt_mesh_vertices(seq.scene, config.voxel_size_m, config.cache_dir)))
        self.baselines: dict[int, dict] = {}
        self.crops: dict[int, np.ndarray] = {}

    def engine_config(self):
        from ..engine import EngineConfig

        cfg = self.config
        return EngineConfig(sensors=SENSORS, sensor_uses_rgb=cfg.sensor_uses_rgb, depth_min_m=cfg.depth_min_m,
                            depth_max_m=cfg.depth_max_m, voxel_size_m=cfg.voxel_size_m, band_m=cfg.band_m,
                            n_samples=cfg.n_samples, n_samples_behind=cfg.n_samples_behind, w_max=cfg.w_max,
                            border_px=cfg.border_px, torch_threads=0,
                            weighting_tsdf_input=cfg.weighting_tsdf_input)

    def run(self, feature_nets: torch.nn.ModuleList, weighting_net: torch.nn.Module) -> dict:
        """Per scene the rows {method: metrics} and the summary: mean fused F, MAD, and the mean
        margin of the fused F over the better single sensor (the checkpoint score)."""
        from ..engine import SenFuNet
        from .evaluation import integrate_frames, method_metrics, observed_gt_vertices

        stride = {name: self.config.val_frame_stride for name in SENSORS}
        per_scene = {}
        for seed, seq, gt_vertices in self.scenes:
            engine = SenFuNet(self.engine_config(), weights=None)
            engine.feature_nets.load_state_dict(copy.deepcopy(feature_nets.state_dict()))
            engine.weighting_net.load_state_dict(copy.deepcopy(weighting_net.state_dict()))
            integrate_frames(engine, seq.frames, stride)
            if seed not in self.crops:
                self.crops[seed] = observed_gt_vertices(engine, gt_vertices)
                self.baselines[seed] = method_metrics(engine, seq.scene, self.crops[seed],
                                                      methods=("tof", "stereo", "tsdf_fusion"))
            rows = dict(self.baselines[seed])
            rows.update(method_metrics(engine, seq.scene, self.crops[seed], methods=("senfunet",)))
            rows["alpha"] = alpha_statistics(engine)
            per_scene[seed] = rows
            del engine
        fused_f = [r["senfunet"]["F"] for r in per_scene.values()]
        margin = [r["senfunet"]["F"] - max(r["tof"]["F"], r["stereo"]["F"]) for r in per_scene.values()]
        alpha = {k: float(np.mean([r["alpha"][k] for r in per_scene.values()])) for k in ALPHA_STATISTICS}
        return {"per_scene": per_scene, "F": float(np.mean(fused_f)), "margin": float(np.mean(margin)), "alpha": alpha,
                "MAD": float(np.mean([r["senfunet"]["MAD"] for r in per_scene.values()])),
                "tsdf_F": float(np.mean([r["tsdf_fusion"]["F"] for r in per_scene.values()])),
                "tsdf_MAD": float(np.mean([r["tsdf_fusion"]["MAD"] for r in per_scene.values()])),
                "best_single_F": float(np.mean([max(r["tof"]["F"], r["stereo"]["F"]) for r in per_scene.values()]))}
