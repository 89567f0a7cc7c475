"""Training of the feature nets and the weighting net G (paper: Loss Function, Training Forward
Pass; supplementary C).

Per training scene a two-sensor sequence is simulated (cached under `cache_dir`), its frames are
shuffled and integrated one at a time into per-sensor sparse grids (TSDF, weight, features), the
same grids and compiled integration kernels the engine uses (features and weight counters in half
precision, as at run time). After each frame:
  1. the update box of the frame is the bounding box of the voxels it updated; a d^3 chunk
     (shrinking along axes where the box is smaller) is placed uniformly inside it until it holds
     >= 2000 updated voxels (at most 600 tries; otherwise the next frame is integrated);
  2. the frame's features enter the feature grid through the running average; at the chunk's
     updated voxels the new value carries the gradient of the running average with respect to
     this frame's pixel features, (mean of the voxel's pixel features) / (W_old + 1), so the loss
     reaches the frame's feature net (the rest of the grid is detached, as in the paper). The
     feature net runs with gradients only on the image window those pixels need (their bounding
     box plus the net's 12-pixel receptive radius: the same features, a fraction of the cost);
  3. G runs on the chunk with replicate padding, the fusion module fuses, and the loss
     L = L_f(C12) + lambda1 * sum_i L_in(C_i) + lambda2 * sum_i L_out(C_i)
     is computed on the chunk's updated voxels against the GT TSDF truncated at +-band/2 (cached
     per scene block by block);
  4. gradients are accumulated over `accumulate_frames` frames, clipped to norm 1.0, Adam steps;
  5. with probability 0.01 the grids are reset (and when they exceed `max_blocks`).
Periodically the current networks run in the engine on held-out validation scenes with the
evaluation's protocol; the checkpoint with the best mean fused F-score margin over the better
single sensor is saved with `networks.save_weights`.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from .block_phase import block_batch
from .chunks import keys_to_voxels, sample_chunk, update_box
from .clock import ActiveClock
from .config import SENSORS, TrainConfig, load_config
from .gt_cache import GTCache
from .loss import cosine_lr, senfunet_loss
from .sparse_conv import SparsePlan, sparse_alpha, sparse_alpha_planned, sparse_plan
from .trainer import FEATURE_RADIUS_PX, StepResult, Trainer
from .validation import ALPHA_STATISTICS, Validator, alpha_statistics

__all__ = [
    "ALPHA_STATISTICS",
    "FEATURE_RADIUS_PX",
    "SENSORS",
    "ActiveClock",
    "GTCache",
    "SparsePlan",
    "StepResult",
    "TrainConfig",
    "Trainer",
    "Validator",
    "alpha_statistics",
    "block_batch",
    "cosine_lr",
    "keys_to_voxels",
    "load_config",
    "sample_chunk",
    "senfunet_loss",
    "sparse_alpha",
    "sparse_alpha_planned",
    "sparse_plan",
    "train",
    "update_box",
]


class _SceneFrames:
    """The training scenes' frames: their recordings read back from the cache when needed (the few in
    use kept), cut into segments and handed out shuffled, slot by slot."""

    def __init__(self, config: TrainConfig, trainer: Trainer, log) -> None:
        self.config, self.trainer, self.log = config, trainer, log
        self.loaded: dict[int, object] = {}  # the few recordings in use (read back from the cache: ~1 s each)

    def sequence(self, seed: int):
        from .evaluation import cached_sequence

        cfg = self.config
        if seed not in self.loaded:
            while len(self.loaded) >= cfg.scene_slots + 2:
                self.loaded.pop(next(iter(self.loaded)))
            self.loaded[seed] = cached_sequence(seed, duration_s=cfg.duration_s, tof_rate_hz=cfg.tof_rate_hz,
                                                stereo_rate_hz=cfg.stereo_rate_hz, cache_dir=cfg.cache_dir,
                                                log=self.log)
        return self.loaded[seed]

    def segments(self):
        """(scene, its frames of one segment, shuffled) for ever: epochs over all segments in random order."""
        parts = max(1, self.config.segments_per_scene)
        rng = self.trainer.rng
        while True:
            order = [(seed, k) for seed in self.config.train_scenes for k in range(parts)]
            rng.shuffle(order)
            for seed, k in order:
                seq = self.sequence(seed)
                frames = list(seq.frames)  # in stamp order: part k is a stretch of the walk
                frames = frames[k * len(frames) // parts:(k + 1) * len(frames) // parts]
                rng.shuffle(frames)
                yield seq.scene, frames

    def stream(self):
        """(slot, frame, scene): each slot trains on one segment in its own fresh grids; frames of the
        slots interleave at random so that an accumulated gradient spans several scenes."""
        source = self.segments()
        queues = []
        for slot in range(len(self.trainer.grids)):
            queues.append(next(source))
            self.trainer.reset_grids(slot)
        while True:
            slot = self.trainer.rng.randrange(len(queues))
            scene, frames = queues[slot]
            yield slot, frames.pop(), scene
            if not frames:
                queues[slot] = next(source)
                self.trainer.reset_grids(slot)


def _history_record(history: list[dict]) -> list[dict]:
    """The validations as a checkpoint records them."""
    keys = ("step", "F", "margin", "MAD", "tsdf_F", "best_single_F", "source")
    return [{k: e[k] for k in keys if k in e} for e in history]


class _Run:
    """One training run: the optional block phase, the online frames (from `_SceneFrames`), the
    periodic validation and the best checkpoint."""

    def __init__(self, config: TrainConfig, out_path: Path, log, progress: bool) -> None:
        self.config, self.out_path, self.log, self.progress = config, out_path, log, progress
        self.clock = ActiveClock()
        torch.set_num_threads(max(1, config.threads))
        self.trainer = Trainer(config)
        self.validator = Validator(config, log)
        self.scenes = _SceneFrames(config, self.trainer, log)
        self.best: dict = {"margin": -math.inf}
        self.history: list[dict] = []
        self.chunk_frames = 0  # online frames whose loss reached the networks
        self.block_phase: dict = {}

    def ran(self, step: int) -> dict:
        """What actually ran up to online frame `step` (the checkpoint's record; docs/results.md reads it)."""
        trainer, cfg = self.trainer, self.config
        return {"block_steps": max(0, cfg.block_steps), **self.block_phase, "online_frames": step,
                "online_optimizer_steps": trainer.optimizer_steps - max(0, cfg.block_steps),
                "online_frames_with_chunk": self.chunk_frames, "random_resets": trainer.resets,
                "memory_resets": trainer.memory_resets, "init_weights": cfg.init_weights,
                "active_seconds": round(self.clock.active())}

    def validate(self, step: int) -> None:
        from tqdm import tqdm

        t0 = time.perf_counter()
        v = self.validator.run(self.trainer.feature_nets, self.trainer.weighting_net)
        entry = {"step": step, "optimizer_steps": self.trainer.optimizer_steps, "seconds": self.clock.active(),
                 **{k: v[k] for k in ("F", "margin", "MAD", "tsdf_F", "tsdf_MAD", "best_single_F")}, **v["alpha"],
                 "per_scene_F": {seed: r["senfunet"]["F"] for seed, r in v["per_scene"].items()}}
        self.history.append(entry)
        a = v["alpha"]
        msg = (f"[val frame {step}] fused F {v['F']:.2f} (margin over the better sensor {v['margin']:+.2f}, "
               f"TSDF Fusion {v['tsdf_F']:.2f}) | MAD cm {100 * v['MAD']:.3f} (TSDF Fusion {100 * v['tsdf_MAD']:.3f}) "
               f"| alpha: C12 mean {a['c12_alpha_mean']:.2f}, ToF-weighted {a['c12_tof_share']:.2f}, "
               f"kept ToF-only {a['c1_kept']:.2f}, stereo-only {a['c2_kept']:.2f} "
               f"({time.perf_counter() - t0:.0f} s)")
        if v["margin"] > self.best["margin"]:
            self.save_best(step, v)
            msg += " -> saved best"
        (tqdm.write if self.progress else self.log)(msg)

    def save_best(self, step: int, v: dict) -> None:
        """The networks as they are become the checkpoint (v: the validation summary that chose them)."""
        cfg = self.config
        self.best.update(margin=v["margin"], F=v["F"], step=step, MAD=v["MAD"])
        per_scene = {str(seed): {m: r[m] for m in ("tof", "stereo", "tsdf_fusion", "senfunet")}
                     for seed, r in v.get("per_scene", {}).items()}
        self.trainer.save(self.out_path, meta={
            "trained_steps": step, "optimizer_steps": self.trainer.optimizer_steps, "ran": self.ran(step),
            "init": {"path": cfg.init_weights, "meta": self.trainer.init_meta} if cfg.init_weights else None,
            "validation_history": _history_record(self.history),
            "val_scenes": list(cfg.val_scenes), "val_F": v["F"], "val_margin": v["margin"], "val_MAD_m": v["MAD"],
            "val_tsdf_F": v["tsdf_F"], "val_best_single_F": v["best_single_F"], "val_per_scene": per_scene,
            "config": {k: (list(x) if isinstance(x, tuple) else x) for k, x in asdict(cfg).items()}})

    def adopt_init_validation(self) -> None:
        """Frame 0 of a run started from a checkpoint: that checkpoint's own validation (the same rooms
        and protocol), so the online frames are kept only if they beat it."""
        m = self.trainer.init_meta or {}
        if "val_margin" not in m or list(m.get("config", {}).get("val_scenes", [])) != list(self.config.val_scenes):
            self.validate(0)
            return
        v = {"F": m["val_F"], "margin": m["val_margin"], "MAD": m.get("val_MAD_m", math.nan),
             "tsdf_F": m.get("val_tsdf_F", math.nan), "best_single_F": m.get("val_best_single_F", math.nan)}
        self.history.append({"step": 0, **v, "source": "the starting checkpoint's record"})
        self.save_best(0, v)
        self.log(f"[val frame 0] from the starting checkpoint's record: fused F {v['F']:.2f}, margin "
                 f"{v['margin']:+.2f}")

    def finalize(self) -> None:
        """The kept checkpoint records every validation, including those after it, and what ran in total."""
        if not self.out_path.is_file():
            return
        state = torch.load(self.out_path, map_location="cpu", weights_only=True)
        state["meta"]["validation_history"] = _history_record(self.history)
        state["meta"]["ran_in_total"] = self.ran(self.history[-1]["step"] if self.history else 0)
        torch.save(state, self.out_path)

    def lr_at(self, step: int) -> float:
        cfg = self.config
        progress_frac = step / max(cfg.steps, 1)
        if cfg.time_budget_s > 0:
            progress_frac = max(progress_frac, self.clock.active() / cfg.time_budget_s)
        return cosine_lr(cfg.lr, cfg.lr_final_fraction, progress_frac)

    def run_feature_pretrain(self) -> None:
        """The feature nets' per-pixel pretraining (feature_pretrain.py) on the training scenes' frames."""
        from .feature_pretrain import pixel_frames, pretrain_feature_nets

        cfg = self.config
        t0 = time.perf_counter()
        frames = pixel_frames((self.scenes.sequence(seed) for seed in cfg.train_scenes),
                              frame_stride=cfg.val_frame_stride, eta_m=cfg.eta_m, depth_min_m=cfg.depth_min_m,
                              depth_max_m=cfg.depth_max_m, border_px=cfg.border_px)
        got = pretrain_feature_nets(self.trainer.feature_nets, frames, steps=cfg.feature_pretrain_steps,
                                    lr=cfg.feature_pretrain_lr, batch=cfg.feature_pretrain_batch,
                                    crop_px=cfg.feature_pretrain_crop_px, seed=cfg.seed, log=self.log)
        self.block_phase["feature_pretrain"] = {"steps": cfg.feature_pretrain_steps, **got}
        self.log(f"feature nets pretrained per pixel: {cfg.feature_pretrain_steps} steps per sensor "
                 f"({time.perf_counter() - t0:.0f} s)")

    def run_block_phase(self) -> None:
        cfg = self.config
        t0 = time.perf_counter()
        got = self.trainer.train_weighting_net_on_blocks((self.scenes.sequence(seed) for seed in cfg.train_scenes),
                                                         self.validator.engine_config(), self.log)
        self.block_phase.update(block_scenes=got["scenes"], blocks=got["blocks"])
        self.log(f"G on {got['blocks']} blocks of {got['scenes']} integrated scenes: {cfg.block_steps} steps "
                 f"({time.perf_counter() - t0:.0f} s)")
        self.validate(0)

    def online(self) -> dict:
        """The paper's online training until `steps` frames or the time budget; returns counts."""
        from tqdm import tqdm

        cfg, trainer = self.config, self.trainer
        stream = self.scenes.stream()
        bar = tqdm(total=cfg.steps, disable=not self.progress, dynamic_ncols=True, desc="train")
        recent: list[float] = []
        losses: list[float] = []
        terms_sum: dict[str, float] = {}
        step = 0
        while step < cfg.steps:
            slot, frame, scene = next(stream)
            if trainer.frames_since_step == 0:
                trainer.set_lr(self.lr_at(step))
            res = trainer.train_frame(frame, scene, slot)
            step += 1
            if res.loss is not None:
                self.chunk_frames += 1
                recent = [*recent[-49:], res.loss]
                losses.append(res.loss)
                for k, val in res.terms.items():
                    terms_sum[k] = terms_sum.get(k, 0.0) + val
            bar.update(1)
            bar.set_postfix(loss=f"{np.mean(recent):.4f}" if recent else "-", L_f=f"{res.terms.get('L_f', 0):.4f}",
                            skipped=step - self.chunk_frames, steps=trainer.optimizer_steps)
            if not self.progress and step % 200 == 0:
                self.log(f"frame {step}: loss {np.mean(recent) if recent else float('nan'):.4f} (last 50), "
                         f"{trainer.optimizer_steps} optimizer steps, {step - self.chunk_frames} frames without a "
                         f"chunk, {self.clock.active():.0f} s active ({self.clock.paused_s:.0f} s paused)")
            out_of_time = cfg.time_budget_s > 0 and self.clock.active() > cfg.time_budget_s
            if (cfg.val_every and step % cfg.val_every == 0) or out_of_time:
                self.validate(step)
            if out_of_time:
                self.log(f"time budget of {cfg.time_budget_s:.0f} s (active; {self.clock.paused_s:.0f} s paused "
                         f"besides) reached after {step} frames")
                break
        bar.close()
        if not self.history or self.history[-1]["step"] != step:
            self.validate(step)
        return {"frames": step, "losses": losses,
                "mean_terms": {k: v / max(len(losses), 1) for k, v in terms_sum.items()}}


def train(config: TrainConfig, out_path: str | Path, *, log=print, progress: bool = True) -> dict:
    """The whole training run; writes the best checkpoint to out_path and returns a summary."""
    if config.feature_pretrain_steps > 0 and config.block_steps <= 0:
        raise InputError("feature_pretrain_steps > 0 changes the features G reads: it needs the block phase "
                         "(block_steps > 0, no --init-weights)")
    run = _Run(config, Path(out_path), log, progress)
    if config.feature_pretrain_steps > 0:
        run.run_feature_pretrain()
    if config.block_steps > 0:
        run.run_block_phase()
    elif config.init_weights:
        run.adopt_init_validation()
    online = run.online()
    run.finalize()
    run.clock.stop()
    trainer = run.trainer
    return {"frames": online["frames"], "optimizer_steps": trainer.optimizer_steps,
            "skipped_frames": online["frames"] - run.chunk_frames, "resets": trainer.resets,
            "memory_resets": trainer.memory_resets, "best": run.best, "history": run.history,
            "losses": online["losses"], "mean_terms": online["mean_terms"], "timings_s": dict(trainer.timings_s),
            "seconds": run.clock.active(), "paused_s": run.clock.paused_s, "wall_s": run.clock.wall()}
