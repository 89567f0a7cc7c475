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


def train(config: TrainConfig, out_path: str | Path, log=print, progress: bool = True) -> dict:
    """The whole training run; writes the best checkpoint to out_path and returns a summary."""
    from tqdm import tqdm

    from .evaluation import cached_sequence

    clock = ActiveClock()
    torch.set_num_threads(max(1, config.threads))
    trainer = Trainer(config)

    loaded: dict[int, object] = {}  # the few recordings in use (read back from the cache: ~1 s each)

    def sequence(seed: int):
        if seed not in loaded:
            while len(loaded) >= trainer.config.scene_slots + 2:
                loaded.pop(next(iter(loaded)))
            loaded[seed] = cached_sequence(seed, config.duration_s, config.tof_rate_hz, config.stereo_rate_hz,
                                           config.cache_dir, log)
        return loaded[seed]

    validator = Validator(config, log)

    def segments():
        """(scene, its frames of one segment, shuffled) for ever: epochs over all segments in random order."""
        parts = max(1, config.segments_per_scene)
        while True:
            order = [(seed, k) for seed in config.train_scenes for k in range(parts)]
            trainer.rng.shuffle(order)
            for seed, k in order:
                seq = sequence(seed)
                frames = list(seq.frames)  # in stamp order: part k is a stretch of the walk
                frames = frames[k * len(frames) // parts:(k + 1) * len(frames) // parts]
                trainer.rng.shuffle(frames)
                yield seq.scene, frames

    def frame_stream():
        """(slot, frame, scene): each slot trains on one segment in its own fresh grids; frames of the
        slots interleave at random so that an accumulated gradient spans several scenes."""
        source = segments()
        queues = []
        for slot in range(len(trainer.grids)):
            queues.append(next(source))
            trainer.reset_grids(slot)
        while True:
            slot = trainer.rng.randrange(len(queues))
            scene, frames = queues[slot]
            yield slot, frames.pop(), scene
            if not frames:
                queues[slot] = next(source)
                trainer.reset_grids(slot)

    best = {"margin": -math.inf}
    counts = {"chunk": 0}  # online frames whose loss reached the networks (for the checkpoint's record)
    history = []
    out_path = Path(out_path)

    def run_validation(step: int) -> None:
        t0 = time.perf_counter()
        v = validator.run(trainer.feature_nets, trainer.weighting_net)
        entry = {"step": step, "optimizer_steps": trainer.optimizer_steps, "seconds": clock.active(),
                 **{k: v[k] for k in ("F", "margin", "MAD", "tsdf_F", "tsdf_MAD", "best_single_F")}, **v["alpha"],
                 "per_scene_F": {seed: r["senfunet"]["F"] for seed, r in v["per_scene"].items()}}
        history.append(entry)
        msg = (f"[val frame {step}] fused F {v['F']:.2f} (margin over the better sensor {v['margin']:+.2f}, "
               f"TSDF Fusion {v['tsdf_F']:.2f}) | MAD cm {100 * v['MAD']:.3f} (TSDF Fusion {100 * v['tsdf_MAD']:.3f}) "
               f"| alpha: C12 mean {v['alpha']['c12_alpha_mean']:.2f}, ToF-weighted {v['alpha']['c12_tof_share']:.2f}, "
               f"kept ToF-only {v['alpha']['c1_kept']:.2f}, stereo-only {v['alpha']['c2_kept']:.2f} "
               f"({time.perf_counter() - t0:.0f} s)")
        if v["margin"] > best["margin"]:
            best.update(margin=v["margin"], F=v["F"], step=step, MAD=v["MAD"])
            trainer.save(out_path, meta={"trained_steps": step, "optimizer_steps": trainer.optimizer_steps,
                                         "ran": {"block_steps": max(0, config.block_steps),
                                                 "online_frames": step,
                                                 "online_optimizer_steps": trainer.optimizer_steps
                                                 - max(config.block_steps, 0),
                                                 "online_frames_with_chunk": counts["chunk"],
                                                 "random_resets": trainer.resets,
                                                 "memory_resets": trainer.memory_resets,
                                                 "init_weights": config.init_weights},
                                         "val_scenes": list(config.val_scenes), "val_F": v["F"],
                                         "val_margin": v["margin"], "val_MAD_m": v["MAD"],
                                         "val_tsdf_F": v["tsdf_F"], "val_best_single_F": v["best_single_F"],
                                         "config": {k: (list(x) if isinstance(x, tuple) else x)
                                                    for k, x in asdict(config).items()}})
            msg += " -> saved best"
        (tqdm.write if progress else log)(msg)

    def lr_at(step: int) -> float:
        progress_frac = step / max(config.steps, 1)
        if config.time_budget_s > 0:
            progress_frac = max(progress_frac, clock.active() / config.time_budget_s)
        return cosine_lr(config.lr, config.lr_final_fraction, progress_frac)

    if config.block_steps > 0:
        t0 = time.perf_counter()
        got = trainer.train_weighting_net_on_blocks(
            (cached_sequence(seed, config.duration_s, config.tof_rate_hz, config.stereo_rate_hz, config.cache_dir, log)
             for seed in config.train_scenes), validator.engine_config(), log)
        log(f"G on {got['blocks']} blocks of {got['scenes']} integrated scenes: {config.block_steps} steps "
            f"({time.perf_counter() - t0:.0f} s)")
        run_validation(0)

    stream = frame_stream()
    bar = tqdm(total=config.steps, disable=not progress, dynamic_ncols=True, desc="train")
    recent: list[float] = []
    losses: list[float] = []
    terms_sum: dict[str, float] = {}
    skipped = 0
    step = 0
    while step < config.steps:
        slot, frame, scene = next(stream)
        if trainer.frames_since_step == 0:
            trainer.set_lr(lr_at(step))
        res = trainer.train_frame(frame, scene, slot)
        step += 1
        if res.loss is None:
            skipped += 1
        else:
            recent.append(res.loss)
            counts["chunk"] += 1
            losses.append(res.loss)
            recent = recent[-50:]
            for k, val in res.terms.items():
                terms_sum[k] = terms_sum.get(k, 0.0) + val
        bar.update(1)
        bar.set_postfix(loss=f"{np.mean(recent):.4f}" if recent else "-", L_f=f"{res.terms.get('L_f', 0):.4f}",
                        skipped=skipped, steps=trainer.optimizer_steps)
        if not progress and step % 200 == 0:
            log(f"frame {step}: loss {np.mean(recent) if recent else float('nan'):.4f} (last 50), "
                f"{trainer.optimizer_steps} optimizer steps, {skipped} frames without a chunk, "
                f"{clock.active():.0f} s active ({clock.paused_s:.0f} s paused)")
        out_of_time = config.time_budget_s > 0 and clock.active() > config.time_budget_s
        if (config.val_every and step % config.val_every == 0) or out_of_time:
            run_validation(step)
        if out_of_time:
            log(f"time budget of {config.time_budget_s:.0f} s (active; {clock.paused_s:.0f} s paused besides) "
                f"reached after {step} frames")
            break
    bar.close()
    if not history or history[-1]["step"] != step:
        run_validation(step)
    clock.stop()
    return {"frames": step, "optimizer_steps": trainer.optimizer_steps, "skipped_frames": skipped,
            "resets": trainer.resets, "memory_resets": trainer.memory_resets, "best": best, "history": history,
            "losses": losses, "mean_terms": {k: v / max(len(losses), 1) for k, v in terms_sum.items()},
            "timings_s": dict(trainer.timings_s), "seconds": clock.active(), "paused_s": clock.paused_s,
            "wall_s": clock.wall()}
