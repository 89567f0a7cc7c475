"""Training of the feature nets and the weighting net G (paper: Loss Function, Training Forward
Pass; supplementary C).

Per training scene a two-sensor sequence is simulated (cached under `cache_dir`), its frames are
shuffled and integrated one at a time into per-sensor sparse grids (TSDF, weight, features).
After each frame:
  1. the update box of the frame is the bounding box of the voxels it updated; a d^3 chunk
     (d = 64, shrinking along axes where the box is smaller) is placed uniformly inside it until
     it holds >= 2000 updated voxels (at most 600 tries; otherwise the next frame is integrated);
  2. the frame's features enter the feature grid through the running average at the updated
     voxels *with* gradients (the rest of the grid is detached), so the loss reaches the frame's
     feature net;
  3. G runs on the chunk with replicate padding, the fusion module fuses, and the loss
     L = L_f(C12) + lambda1 * sum_i L_in(C_i) + lambda2 * sum_i L_out(C_i)
     is computed on the chunk's updated voxels against the GT TSDF truncated at +-band/2;
  4. gradients are accumulated over `accumulate_frames` frames, clipped to norm 1.0, Adam steps;
  5. with probability 0.01 the grids are reset.
Periodically the current networks run in the engine on a held-out validation scene; the
checkpoint with the best fused F-score is saved with `networks.save_weights`.
"""
from __future__ import annotations

import copy
from fractions import Fraction
import math
import random
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from . import networks
from .fusion import fuse
from .grid import BLOCK, BLOCK_VOXELS, BlockGrid, keys_to_coords
from .integrator import (IntegratorConfig, aggregate_pixel_values, frame_samples, integrate_into, running_average,
                         valid_depth_mask, voxel_slots)

SENSORS = ("tof", "stereo")


@dataclass
class TrainConfig:
    seed: int = 0
    train_scenes: tuple[int, ...] = (0, 1, 2, 3, 4, 5)  # scene seeds (< 1000: held-out scenes use >= 1000)
    val_scene: int = 900
    duration_s: float = 6.0  # simulated seconds per training scene
    tof_rate_hz: float = 15.0
    stereo_rate_hz: float = 20.0
    val_duration_s: float = 4.0
    val_frame_stride: int = 2  # validation integrates every k-th frame of each sensor
    val_every: int = 150  # frames between validations (0: only at the end)
    sensor_uses_rgb: tuple[bool, ...] = (False, True)
    depth_min_m: tuple[float, ...] = (0.1, 0.1)
    depth_max_m: tuple[float, ...] = (5.0, 5.0)
    voxel_size_m: float = 0.01
    band_m: float = 0.1
    n_samples: int = 11
    n_samples_behind: int = 3
    w_max: float = 500.0
    border_px: int = 10
    chunk_size: int = 64
    min_update_voxels: int = 2000
    max_chunk_tries: int = 600
    lr: float = 1e-4
    accumulate_frames: int = 20
    clip_grad_norm: float = 1.0
    reset_probability: float = 0.01
    max_blocks: int = 60000  # memory cap: the grids are also reset when they hold more blocks (~1.9 GB)
    lambda1: float = 1 / 60
    lambda2: float = 1 / 600
    eta_m: float = 0.04
    steps: int = 1000  # training frames in total
    time_budget_s: float = 0.0  # stop (and validate a last time) after this much wall time; 0 = no limit
    threads: int = 2
    cache_dir: str = "~/.cache/senfunet"
    init_seed: int = 0  # network initialisation

    @property
    def integrator(self) -> IntegratorConfig:
        return IntegratorConfig(self.voxel_size_m, self.band_m, self.n_samples, self.n_samples_behind, self.w_max,
                                self.border_px)

    @classmethod
    def from_dict(cls, values: dict) -> "TrainConfig":
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise ValueError(f"unknown training config keys: {unknown}; known: {sorted(known)}")
        out = {}
        for k, v in values.items():
            if isinstance(v, list):
                v = tuple(v)
            if isinstance(v, str) and known[k].type in ("float", float):
                v = float(Fraction(v.replace(" ", "")))  # allow "1/60"
            out[k] = v
        return cls(**out)


# --------------------------------------------------------------------------------------------
# Loss and chunk sampling (pure functions)
# --------------------------------------------------------------------------------------------
def senfunet_loss(tsdf_1: torch.Tensor, weight_1: torch.Tensor, tsdf_2: torch.Tensor, weight_2: torch.Tensor,
                  alpha: torch.Tensor, gt_tsdf: torch.Tensor, mask: torch.Tensor, lambda1: float, lambda2: float,
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


def update_box(voxels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inclusive min and max voxel index (3,) of the updated voxels (U x 3)."""
    return voxels.min(dim=0).values, voxels.max(dim=0).values


def sample_chunk(voxels: torch.Tensor, chunk_size: int, min_voxels: int, max_tries: int,
                 generator: torch.Generator, batch: int = 32) -> tuple[torch.Tensor | None, torch.Tensor, int]:
    """A chunk inside the update box of `voxels` (U x 3 int64) holding >= min_voxels of them.

    The chunk is chunk_size per axis, shrunk to the box where the box is smaller; its corner is
    uniform inside the box. Returns (corner (3,) or None, size (3,), tries used).
    """
    lo, hi = update_box(voxels)
    extent = hi - lo + 1
    size = torch.clamp(extent, max=chunk_size)
    span = extent - size + 1  # possible corner positions per axis
    order = torch.argsort(voxels[:, 0])
    xs = voxels[order, 0].contiguous()
    yz = voxels[order, 1:]
    tries = 0
    while tries < max_tries:
        n = min(batch, max_tries - tries)
        corners = lo + (torch.rand((n, 3), generator=generator) * span).to(torch.int64).clamp(max=span - 1)
        starts = torch.searchsorted(xs, corners[:, 0]).tolist()  # voxels with x in [cx, cx + sx): one run of xs
        ends = torch.searchsorted(xs, corners[:, 0] + size[0]).tolist()
        for j in range(n):
            if ends[j] - starts[j] < min_voxels:
                continue
            sub = yz[starts[j]:ends[j]]
            c = corners[j, 1:]
            count = int(((sub >= c) & (sub < c + size[1:])).all(dim=1).sum())
            if count >= min_voxels:
                return corners[j], size, tries + j + 1
        tries += n
    return None, size, tries


def keys_to_voxels(keys: torch.Tensor) -> torch.Tensor:
    """Voxel keys (block_key*512 + local) -> U x 3 voxel indices."""
    blocks = keys_to_coords(torch.div(keys, BLOCK_VOXELS, rounding_mode="floor"))
    local = keys % BLOCK_VOXELS
    loc = torch.stack([local // 64, (local // 8) % 8, local % 8], dim=1)
    return blocks * BLOCK + loc


def voxel_flat_index(grid: BlockGrid, voxels: torch.Tensor) -> torch.Tensor:
    """Flat pool index (slot*512 + local) of each voxel (N x 3), -1 where its block does not exist."""
    blocks = torch.div(voxels, BLOCK, rounding_mode="floor")
    local = voxels - blocks * BLOCK
    slots = grid.lookup(blocks)
    flat = slots * BLOCK_VOXELS + local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2]
    return torch.where(slots >= 0, flat, torch.full_like(flat, -1))


# --------------------------------------------------------------------------------------------
# The trainer
# --------------------------------------------------------------------------------------------
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
        self.feature_nets, self.weighting_net = networks.make_networks(config.sensor_uses_rgb, config.init_seed)
        self.feature_nets.train()
        self.weighting_net.train()
        params = list(self.feature_nets.parameters()) + list(self.weighting_net.parameters())
        self.optimizer = torch.optim.Adam(params, lr=config.lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=0)
        channels = {}
        for i in range(len(SENSORS)):
            channels.update({f"tsdf{i}": (), f"weight{i}": (), f"feat{i}": (networks.N_FEATURES,)})
        self.grid = BlockGrid(channels, "cpu")
        self.frames_since_step = 0
        self.optimizer_steps = 0
        self.resets = 0
        self.memory_resets = 0

    def reset_grids(self) -> None:
        self.grid.clear()

    def _pixel_features(self, s: int, depth: torch.Tensor, rgb: np.ndarray | None) -> torch.Tensor:
        net = self.feature_nets[s]
        rgb01 = None
        if net.uses_rgb:
            rgb01 = (torch.zeros((1, 3, *depth.shape)) if rgb is None
                     else torch.from_numpy(rgb).permute(2, 0, 1).unsqueeze(0).float() / 255.0)
        return net(depth.view(1, 1, *depth.shape), rgb01)[0]

    def train_frame(self, frame, scene) -> StepResult:
        """Integrate one frame, sample a chunk, accumulate the loss gradient; step every N frames."""
        from .simulator import gt_tsdf

        cfg = self.config
        s = SENSORS.index(frame.sensor)
        depth = torch.from_numpy(np.ascontiguousarray(frame.depth_m, dtype=np.float32))
        depth = torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0).clamp_(min=0.0)
        valid = valid_depth_mask(depth, cfg.border_px, cfg.depth_min_m[s], cfg.depth_max_m[s])
        result = StepResult(None)
        if bool(valid.any()):
            K = torch.as_tensor(np.asarray(frame.K, np.float64))
            T = torch.as_tensor(np.asarray(frame.T_world_camera, np.float64))
            with torch.no_grad():
                samples = frame_samples(depth, valid, K, T, cfg.integrator)
                flat = voxel_slots(self.grid, samples.keys)
            voxels = keys_to_voxels(samples.keys)
            result.updated = int(flat.numel())
            corner, size, result.tries = sample_chunk(voxels, cfg.chunk_size, cfg.min_update_voxels,
                                                      cfg.max_chunk_tries, self.generator)
            feat_name = f"feat{s}"
            if corner is None:  # integrate without gradients and move on
                with torch.no_grad():
                    pixel = self._pixel_features(s, depth, frame.rgb).flatten(1)[:, samples.pixel_index].T
                    integrate_into(self.grid, flat, f"tsdf{s}", f"weight{s}", samples.tsdf_m, cfg.w_max, feat_name,
                                   aggregate_pixel_values(samples, pixel))
            else:
                pixel = self._pixel_features(s, depth, frame.rgb).flatten(1)[:, samples.pixel_index].T  # P x 5
                voxel_features = aggregate_pixel_values(samples, pixel)
                old_weight = self.grid.pools[f"weight{s}"].view(-1)[flat].clone()
                old_features = self.grid.pools[feat_name].view(-1, networks.N_FEATURES)[flat].clone()
                new_features = running_average(old_features, old_weight, voxel_features)  # carries gradients
                with torch.no_grad():
                    integrate_into(self.grid, flat, f"tsdf{s}", f"weight{s}", samples.tsdf_m, cfg.w_max, feat_name,
                                   voxel_features.detach())
                loss, terms = self._chunk_loss(s, corner, size, flat, new_features, scene, gt_tsdf)
                if loss is not None:
                    (loss / cfg.accumulate_frames).backward()
                    result.loss, result.terms = float(loss.detach()), terms
        self.frames_since_step += 1
        if self.frames_since_step >= cfg.accumulate_frames:
            self._optimizer_step()
        if self.rng.random() < cfg.reset_probability:
            self.reset_grids()
            self.resets += 1
        elif self.grid.n_blocks > cfg.max_blocks:
            self.reset_grids()
            self.memory_resets += 1
        return result

    def _chunk_loss(self, s, corner, size, flat, new_features, scene, gt_tsdf_fn):
        cfg = self.config
        sx, sy, sz = (int(v) for v in size)
        axes = [torch.arange(int(corner[i]), int(corner[i]) + int(size[i])) for i in range(3)]
        gx, gy, gz = torch.meshgrid(*axes, indexing="ij")
        chunk_vox = torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3)
        chunk_flat = voxel_flat_index(self.grid, chunk_vox)
        present = chunk_flat >= 0
        index = chunk_flat.clamp(min=0)

        def channel(name: str) -> torch.Tensor:
            pool = self.grid.pools[name]
            values = pool.reshape(-1, *pool.shape[2:])[index]
            mask = present.reshape(-1, *([1] * (values.dim() - 1)))
            return torch.where(mask, values, torch.zeros((), dtype=values.dtype))

        # position of each chunk voxel in this frame's update list (-1: not updated by this frame)
        sorted_flat, order = torch.sort(flat)
        at = torch.searchsorted(sorted_flat, chunk_flat).clamp_(max=flat.numel() - 1)
        updated = present & (sorted_flat[at] == chunk_flat)
        chunk_pos = torch.where(updated, order[at], torch.full_like(at, -1))
        if int(updated.sum()) == 0:
            return None, {}
        features, weights, tsdfs = [], [], []
        for i in range(len(SENSORS)):
            f = channel(f"feat{i}")
            if i == s:
                f = f.clone()
                f[updated] = new_features[chunk_pos[updated]]
            features.append(f)
            weights.append(channel(f"weight{i}"))
            tsdfs.append(channel(f"tsdf{i}"))
        x = networks.weighting_input(features, weights).T.reshape(1, -1, sx, sy, sz)
        alpha = self.weighting_net(x, pad=True).reshape(-1)
        sel = updated
        centres = (chunk_vox[sel].to(torch.float64) * cfg.voxel_size_m).numpy()
        gt = torch.from_numpy(gt_tsdf_fn(scene, centres, cfg.band_m))
        return senfunet_loss(tsdfs[0][sel], weights[0][sel], tsdfs[1][sel], weights[1][sel], alpha[sel], gt,
                             torch.ones_like(gt, dtype=torch.bool), cfg.lambda1, cfg.lambda2, cfg.eta_m)

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

    def validate(self, frames, scene, gt_vertices) -> dict[str, dict[str, float]]:
        """Fused vs TSDF Fusion on the validation scene with the current networks (engine, eval mode)."""
        from .engine import EngineConfig, SenFuNet
        from .evaluation import integrate_frames, method_metrics, observed_gt_vertices

        cfg = self.config
        engine = SenFuNet(EngineConfig(sensors=SENSORS, sensor_uses_rgb=cfg.sensor_uses_rgb,
                                       depth_min_m=cfg.depth_min_m, depth_max_m=cfg.depth_max_m,
                                       voxel_size_m=cfg.voxel_size_m, band_m=cfg.band_m, n_samples=cfg.n_samples,
                                       n_samples_behind=cfg.n_samples_behind, w_max=cfg.w_max,
                                       border_px=cfg.border_px), weights=None)
        engine.feature_nets.load_state_dict(copy.deepcopy(self.feature_nets.state_dict()))
        engine.weighting_net.load_state_dict(copy.deepcopy(self.weighting_net.state_dict()))
        stride = {name: cfg.val_frame_stride for name in SENSORS}
        integrate_frames(engine, frames, stride)
        crop = observed_gt_vertices(engine, gt_vertices)
        return method_metrics(engine, scene, crop, methods=("tof", "stereo", "tsdf_fusion", "senfunet"))


def train(config: TrainConfig, out_path: str | Path, log=print, progress: bool = True) -> dict:
    """The whole training run; writes the best checkpoint to out_path and returns a summary."""
    from tqdm import tqdm

    from .evaluation import cached_gt_mesh_vertices, cached_sequence

    t_start = time.perf_counter()
    torch.set_num_threads(max(1, config.threads))
    trainer = Trainer(config)
    sequences: dict[int, object] = {}

    def sequence(seed: int):
        if seed not in sequences:
            sequences[seed] = cached_sequence(seed, config.duration_s, config.tof_rate_hz, config.stereo_rate_hz,
                                              config.cache_dir, log)
        return sequences[seed]

    val_seq = cached_sequence(config.val_scene, config.val_duration_s, config.tof_rate_hz, config.stereo_rate_hz,
                              config.cache_dir, log)
    val_gt = cached_gt_mesh_vertices(val_seq.scene, config.voxel_size_m, config.cache_dir)

    def frame_stream():
        while True:  # epochs: scenes in random order, each scene's frames shuffled, fresh grids per scene
            order = list(config.train_scenes)
            trainer.rng.shuffle(order)
            for seed in order:
                seq = sequence(seed)
                frames = list(seq.frames)
                trainer.rng.shuffle(frames)
                trainer.reset_grids()
                for frame in frames:
                    yield frame, seq.scene

    best = {"F": -math.inf}
    history = []
    out_path = Path(out_path)

    def run_validation(step: int) -> None:
        t0 = time.perf_counter()
        rows = trainer.validate(val_seq.frames, val_seq.scene, val_gt)
        entry = {"step": step, **{f"{m}_{k}": rows[m][k] for m in rows for k in ("F", "MAD")}}
        history.append(entry)
        msg = (f"[val step {step}] F: senfunet {rows['senfunet']['F']:.2f} tsdf_fusion {rows['tsdf_fusion']['F']:.2f} "
               f"tof {rows['tof']['F']:.2f} stereo {rows['stereo']['F']:.2f} | MAD cm: senfunet "
               f"{100 * rows['senfunet']['MAD']:.3f} tsdf_fusion {100 * rows['tsdf_fusion']['MAD']:.3f} "
               f"({time.perf_counter() - t0:.0f} s)")
        if rows["senfunet"]["F"] > best["F"]:
            best.update(F=rows["senfunet"]["F"], step=step, MAD=rows["senfunet"]["MAD"])
            trainer.save(out_path, meta={"trained_steps": step, "val_scene": config.val_scene,
                                         "val_F": rows["senfunet"]["F"], "val_MAD_m": rows["senfunet"]["MAD"],
                                         "config": {k: (list(v) if isinstance(v, tuple) else v)
                                                    for k, v in asdict(config).items()}})
            msg += " -> saved best"
        (tqdm.write if progress else log)(msg)

    stream = frame_stream()
    bar = tqdm(total=config.steps, disable=not progress, dynamic_ncols=True, desc="train")
    recent: list[float] = []
    losses: list[float] = []
    skipped = 0
    step = 0
    while step < config.steps:
        frame, scene = next(stream)
        res = trainer.train_frame(frame, scene)
        step += 1
        if res.loss is None:
            skipped += 1
        else:
            recent.append(res.loss)
            losses.append(res.loss)
            recent = recent[-50:]
        bar.update(1)
        bar.set_postfix(loss=f"{np.mean(recent):.4f}" if recent else "-", L_f=f"{res.terms.get('L_f', 0):.4f}",
                        skipped=skipped, steps=trainer.optimizer_steps)
        out_of_time = config.time_budget_s > 0 and time.perf_counter() - t_start > config.time_budget_s
        if (config.val_every and step % config.val_every == 0) or out_of_time:
            run_validation(step)
        if out_of_time:
            log(f"time budget of {config.time_budget_s:.0f} s reached after {step} frames")
            break
    bar.close()
    if not history or history[-1]["step"] != step:
        run_validation(step)
    return {"frames": step, "optimizer_steps": trainer.optimizer_steps, "skipped_frames": skipped,
            "resets": trainer.resets, "memory_resets": trainer.memory_resets, "best": best, "history": history, "losses": losses,
            "seconds": time.perf_counter() - t_start}


def load_config(path: str | Path) -> TrainConfig:
    import yaml

    values = yaml.safe_load(Path(path).read_text()) or {}
    return TrainConfig.from_dict(values)
