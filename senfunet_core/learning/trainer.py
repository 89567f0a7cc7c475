"""The online training step (paper: Training Forward Pass): integrate one frame, sample a chunk,
G on the chunk's updated voxels, the paper's loss with gradients into G and the frame's feature
net, accumulated over frames."""
from __future__ import annotations

import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch

from .. import networks
from ..errors import InputError
from ..grid import BlockGrid, decode_features, kernel_view
from ..integrator import locate_samples, update_voxels, valid_depth_mask
from .chunks import sample_chunk
from .config import SENSORS, TrainConfig
from .frame_samples import FrameSamples, _box_flat, _frame_voxels, _samples_in_box
from .gt_cache import GTCache
from .loss import senfunet_loss
from .sparse_conv import sparse_alpha_planned, sparse_plan

# a pixel's features depend on the pixels within this radius (6 residual blocks of two 3x3 convolutions)
FEATURE_RADIUS_PX = 2 * networks.N_RESIDUAL_BLOCKS


@dataclass
class StepResult:
    loss: float | None  # None when no chunk with enough updated voxels was found
    terms: dict[str, float] = field(default_factory=dict)
    tries: int = 0
    updated: int = 0


class Trainer:
    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        torch.manual_seed(config.seed)
        self.rng = random.Random(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.feature_nets, self.weighting_net = networks.make_networks(config.sensor_uses_rgb, config.init_seed,
                                                                       config.weighting_tsdf_input)
        self.init_meta: dict | None = None
        if config.init_weights:
            path = Path(config.init_weights)
            if networks.weights_tsdf_input(path) != config.weighting_tsdf_input:
                raise InputError(f"init_weights {path}: its weighting net's TSDF input differs from "
                                 f"weighting_tsdf_input = {config.weighting_tsdf_input}; match them in the config")
            meta = networks.load_weights(path, self.feature_nets, self.weighting_net)
            # what produced the starting point (docs/results.md describes the whole chain)
            self.init_meta = {k: meta[k] for k in ("trained_steps", "optimizer_steps", "ran", "config", "init",
                                                   "val_F", "val_margin") if k in meta}
        self.feature_nets.train()
        self.weighting_net.train()
        groups: list[dict[str, Any]] = [
            {"params": list(self.feature_nets.parameters()), "lr_factor": config.feature_lr_factor},
            {"params": list(self.weighting_net.parameters()), "lr_factor": 1.0}]
        for group in groups:
            group["lr"] = config.lr * group["lr_factor"]
        self.optimizer = torch.optim.Adam(groups, lr=config.lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=0)
        # the engine's grid layout: every channel in half precision
        channels: dict[str, tuple[int, ...]] = {"tsdf_base": (), "weight_base": ()}
        for i in range(len(SENSORS)):
            channels.update({f"tsdf{i}": (), f"weight{i}": (), f"feat{i}": (networks.N_FEATURES,)})
        dtypes = {name: torch.float16 for name in channels}
        # one set of grids (and GT cache) per scene slot
        self.grids = [BlockGrid(channels, "cpu", dtypes=dtypes) for _ in range(max(1, config.scene_slots))]
        self.gts = [GTCache(config.voxel_size_m, config.band_m) for _ in self.grids]
        self.slot = 0
        self.offsets_m = config.integrator.sample_offsets().numpy().astype(np.float64) * config.integrator.step_m
        self.frames_since_step = 0
        self.optimizer_steps = 0
        self.resets = 0
        self.memory_resets = 0
        self.timings_s: dict[str, float] = {}

    @property
    def grid(self) -> BlockGrid:
        """The grids of the scene slot being trained on."""
        return self.grids[self.slot]

    def reset_grids(self, slot: int | None = None) -> None:
        for i, grid in enumerate(self.grids):
            if slot is None or i == slot:
                grid.clear()

    def set_lr(self, lr: float) -> None:
        for group in self.optimizer.param_groups:
            group["lr"] = lr * group.get("lr_factor", 1.0)

    def _timed(self, name: str, t0: float) -> float:
        t1 = time.perf_counter()
        self.timings_s[name] = self.timings_s.get(name, 0.0) + t1 - t0
        return t1

    @staticmethod
    def _rgb01(uses_rgb: bool, rgb: np.ndarray | None, shape: tuple[int, int]) -> torch.Tensor | None:
        if not uses_rgb:
            return None
        if rgb is None:
            return torch.zeros((1, 3, *shape))
        return torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).unsqueeze(0).float() / 255.0

    def _integrate(self, s: int, depth: np.ndarray, pixel_features: np.ndarray, K: np.ndarray,
                   T_world_camera: np.ndarray) -> FrameSamples:
        """Integrate one frame with the engine's compiled kernels (no gradients), keeping its samples."""
        cfg = self.config
        grid = self.grid
        h, w = depth.shape
        n_max = h * w * len(self.offsets_m)
        sample_flat = np.empty(n_max, np.int64)
        sample_touched = np.empty(n_max, np.int32)
        pixel_index = np.empty(h * w, np.int64)
        K64 = np.ascontiguousarray(K, np.float64)
        T64 = np.ascontiguousarray(T_world_camera, np.float64)
        while True:
            slot_to_touched = np.full(grid.capacity, -1, np.int32)
            touched_slots = np.empty(grid.capacity, np.int64)
            state = np.array([grid.n_blocks, min(grid.hash_table.max_blocks(), grid.capacity)], np.int64)
            n_pixels, n_touched, ok = locate_samples(
                depth, cfg.depth_min_m[s], cfg.depth_max_m[s], cfg.border_px, K64, T64, self.offsets_m,
                cfg.voxel_size_m, *grid.hash_table, state, grid.slot_keys, slot_to_touched,
                touched_slots, sample_flat, sample_touched, pixel_index)
            grid.commit_new_blocks(int(state[0]))
            if ok:
                break
            if state[0] < state[1]:
                raise InputError("points lie more than 5 km from the origin; check the pose's units (metres) and frame")
            grid.reserve(grid.n_blocks + 1024)
        n_samples = n_pixels * len(self.offsets_m)
        features = np.ascontiguousarray(pixel_features.reshape(pixel_features.shape[0], -1).T, np.float32)
        views = [kernel_view(grid.pools[name]).reshape(-1) for name in
                 (f"tsdf{s}", f"weight{s}", f"feat{s}", "tsdf_base", "weight_base")]
        unused_reach = np.zeros((n_touched, 2), np.int32)
        update_voxels(n_pixels, n_touched, sample_flat, sample_touched, -self.offsets_m, pixel_index, features,
                      touched_slots, views[0], views[1], views[2], views[3], views[4], unused_reach, cfg.w_max)
        touched = touched_slots[:n_touched]
        updated_flat, updated_voxels = _frame_voxels(sample_flat[:n_samples], sample_touched[:n_samples], touched,
                                                     grid.coords.numpy())
        return FrameSamples(sample_flat[:n_samples], pixel_index[:n_pixels], updated_flat, updated_voxels)

    def train_frame(self, frame, scene, slot: int = 0) -> StepResult:
        """Integrate one frame into the grids of `slot`, sample a chunk, accumulate the loss
        gradient; step every N frames."""
        cfg = self.config
        self.slot = slot
        t0 = time.perf_counter()
        s = SENSORS.index(frame.sensor)
        depth = np.nan_to_num(np.asarray(frame.depth_m, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        depth = np.ascontiguousarray(np.maximum(depth, 0.0), np.float32)
        depth_t = torch.from_numpy(depth)
        valid = valid_depth_mask(depth_t, cfg.border_px, cfg.depth_min_m[s], cfg.depth_max_m[s])
        result = StepResult(None)
        if bool(valid.any()):
            net = cast(networks.FeatureNet, self.feature_nets[s])
            rgb01 = self._rgb01(net.uses_rgb, frame.rgb, depth.shape)
            with torch.no_grad():
                pixel = net(depth_t.view(1, 1, *depth.shape), rgb01)[0]
            t0 = self._timed("feature_net", t0)
            samples = self._integrate(s, depth, pixel.numpy(), frame.K, frame.T_world_camera)
            result.updated = len(samples.updated_flat)
            t0 = self._timed("integrate", t0)
            if result.updated:
                corner, size, result.tries = sample_chunk(
                    torch.from_numpy(samples.updated_voxels), chunk_size=cfg.chunk_size,
                    min_voxels=cfg.min_update_voxels, max_tries=cfg.max_chunk_tries, generator=self.generator)
                t0 = self._timed("chunk", t0)
                if corner is not None:
                    loss, terms = self._chunk_loss(s, corner.numpy(), size.numpy(), samples, depth_t, rgb01, scene)
                    if loss is not None:
                        t0 = time.perf_counter()
                        (loss / cfg.accumulate_frames).backward()
                        t0 = self._timed("backward", t0)
                        result.loss, result.terms = float(loss.detach()), terms
        self.frames_since_step += 1
        if self.frames_since_step >= cfg.accumulate_frames:
            self._optimizer_step()
        if self.rng.random() < cfg.reset_probability:
            self.reset_grids(slot)
            self.resets += 1
        elif self.grid.n_blocks > cfg.max_blocks:
            self.reset_grids(slot)
            self.memory_resets += 1
        return result

    def _chunk_loss(self, s: int, corner: np.ndarray, size: np.ndarray, samples: FrameSamples,
                    depth: torch.Tensor, rgb01: torch.Tensor | None, scene):
        cfg = self.config
        grid = self.grid
        t0 = time.perf_counter()
        corner = corner.astype(np.int64)
        size = size.astype(np.int64)
        n_chunk = int(np.prod(size))
        sample_local, sample_pixel = _samples_in_box(samples.sample_flat, len(self.offsets_m), samples.pixel_index,
                                                     grid.coords.numpy(), corner, size)
        counts = np.bincount(sample_local, minlength=n_chunk)
        updated = np.flatnonzero(counts)  # chunk voxels this frame updated (box-local indices)
        if len(updated) == 0:
            return None, {}
        box = (int(size[0]), int(size[1]), int(size[2]))
        upd = torch.from_numpy(updated)
        plan = sparse_plan(upd, box)  # G's inputs: the voxels within 2 of an updated one (box-clamped)
        chunk_flat = torch.from_numpy(_box_flat(corner, size, plan.inputs.numpy(), *grid.hash_table))
        present = chunk_flat >= 0
        index = chunk_flat.clamp(min=0)

        def channel(name: str) -> torch.Tensor:
            pool = grid.pools[name]
            values = decode_features(pool.reshape(-1, *pool.shape[2:])[index])  # float32 (float16 or packed)
            mask = present.reshape(-1, *([1] * (values.dim() - 1)))
            return torch.where(mask, values, torch.zeros((), dtype=values.dtype))

        features = [channel(f"feat{i}") for i in range(len(SENSORS))]
        weights = [channel(f"weight{i}") for i in range(len(SENSORS))]
        tsdfs = [channel(f"tsdf{i}") for i in range(len(SENSORS))]
        at_upd = torch.from_numpy(np.searchsorted(plan.inputs.numpy(), updated))  # updated voxels among the inputs
        t0 = self._timed("gather", t0)
        # gradient path: this frame's pixel features, recomputed with gradients on the image window
        # the chunk's samples come from (plus the receptive radius, so the values are the same)
        h, w = depth.shape
        rows, cols = sample_pixel // w, sample_pixel % w
        r0, r1 = max(int(rows.min()) - FEATURE_RADIUS_PX, 0), min(int(rows.max()) + FEATURE_RADIUS_PX + 1, h)
        c0, c1 = max(int(cols.min()) - FEATURE_RADIUS_PX, 0), min(int(cols.max()) + FEATURE_RADIUS_PX + 1, w)
        net = self.feature_nets[s]
        crop_rgb = None if rgb01 is None else rgb01[:, :, r0:r1, c0:c1]
        crop = net(depth[r0:r1, c0:c1].unsqueeze(0).unsqueeze(0), crop_rgb)[0]  # 5 x h' x w'
        at = torch.from_numpy((rows - r0) * (c1 - c0) + (cols - c0))
        per_sample = crop.reshape(crop.shape[0], -1)[:, at].T  # M x 5
        sums = torch.zeros((n_chunk, per_sample.shape[1])).index_add_(0, torch.from_numpy(sample_local), per_sample)
        mean = sums[upd] / torch.from_numpy(counts[updated]).float().unsqueeze(1)
        # d(running average)/d(this frame's voxel feature) = 1 / (W_old + 1) = 1 / W_new (W below w_max)
        f = features[s].clone()
        f[at_upd] = f[at_upd] + (mean - mean.detach()) / weights[s][at_upd].clamp(min=1.0).unsqueeze(1)
        features[s] = f
        t0 = self._timed("feature_grad", t0)
        x = networks.weighting_input(features, weights, tsdfs if cfg.weighting_tsdf_input else None,
                                     cfg.band_m)  # K x 12 (G's inputs; 14 with the TSDFs)
        alpha = sparse_alpha_planned(self.weighting_net, x, plan)  # at the updated voxels
        t0 = self._timed("weighting_net", t0)
        voxels = corner + np.stack(np.unravel_index(updated, box), axis=1)
        gt = torch.from_numpy(self.gts[self.slot].values(scene, voxels))
        t0 = self._timed("gt", t0)
        return senfunet_loss(tsdfs[0][at_upd], weights[0][at_upd], tsdfs[1][at_upd], weights[1][at_upd], alpha, gt,
                             torch.ones_like(gt, dtype=torch.bool), lambda1=cfg.lambda1, lambda2=cfg.lambda2,
                             eta_m=cfg.eta_m)

    def train_weighting_net_on_blocks(self, sequences, engine_config, log=print) -> dict[str, float]:
        """G alone on whole blocks of the integrated training scenes (see TrainConfig.block_steps)."""
        from .block_phase import train_on_blocks

        return train_on_blocks(self, sequences, engine_config, log=log)

    def _optimizer_step(self) -> None:
        params = list(self.feature_nets.parameters()) + list(self.weighting_net.parameters())
        if any(p.grad is not None for p in params):
            torch.nn.utils.clip_grad_norm_(params, self.config.clip_grad_norm)
            self.optimizer.step()
            self.optimizer_steps += 1
        self.optimizer.zero_grad(set_to_none=True)
        self.frames_since_step = 0

    def save(self, path: str | Path, meta: dict | None = None) -> None:
        networks.save_weights(path, SENSORS, self.feature_nets, self.weighting_net, meta)
