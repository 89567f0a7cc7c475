"""The block phase (not the paper's training): G alone on whole blocks of integrated training grids.

The training scenes are integrated with the validation protocol (every val_frame_stride-th frame,
feature nets as they are); per scene up to block_scene_blocks blocks holding single-sensor voxels
are kept with their 12^3 input windows, and G takes block_steps Adam steps on batches of them with
the paper's loss on all 512 voxels of each block.
"""
from __future__ import annotations

import copy

import numpy as np
import torch

from .config import SENSORS
from .loss import cosine_lr, senfunet_loss


def block_batch(data: list[dict[str, torch.Tensor]], size: int, *, mixed: bool,
                rng: np.random.Generator) -> dict[str, torch.Tensor]:
    """A batch of blocks for the block phase, drawn without replacement: from one random scene
    (mixed False), or uniformly from all scenes' blocks (mixed True; in scene order). data: per scene,
    tensors with the blocks along the first axis."""
    if not mixed:
        d = data[int(rng.integers(len(data)))]
        idx = torch.from_numpy(rng.choice(len(d["x"]), size=min(size, len(d["x"])), replace=False))
        return {k: v[idx] for k, v in d.items()}
    counts = np.array([len(d["x"]) for d in data])
    starts = np.concatenate([[0], np.cumsum(counts)])
    picks = np.sort(rng.choice(starts[-1], size=min(size, int(starts[-1])), replace=False))
    scene = np.searchsorted(starts, picks, side="right") - 1
    parts = [(d, torch.from_numpy(picks[scene == i] - starts[i])) for i, d in enumerate(data) if (scene == i).any()]
    return {k: torch.cat([d[k][idx] for d, idx in parts]) for k in data[0]}


def collect_blocks(trainer, sequences, engine_config) -> tuple[list[dict[str, torch.Tensor]], np.random.Generator]:
    """Per scene: its kept blocks' G inputs "x" (B x C x 12^3), GT TSDF "gt" (B x 512) and the
    sensors' TSDF and weights ("tsdf0", "weight0", ...: B x 512), and the random stream the batches continue."""
    from ..engine import SenFuNet
    from ..grid import neighbour_table
    from .evaluation import integrate_frames
    from .geometry import gt_tsdf_blocks

    cfg = trainer.config
    rng = np.random.default_rng(cfg.seed)
    data = []
    for seq in sequences:
        engine = SenFuNet(engine_config, weights=None)
        engine.feature_nets.load_state_dict(copy.deepcopy(trainer.feature_nets.state_dict()))
        integrate_frames(engine, seq.frames, {name: cfg.val_frame_stride for name in SENSORS})
        g = engine.grid
        n = g.n_blocks
        w0, w1 = g.pools["weight0"][:n].float(), g.pools["weight1"][:n].float()
        candidates = np.flatnonzero((((w0 > 0) ^ (w1 > 0)).sum(1) > 10).numpy())
        if len(candidates) == 0:
            continue
        keep = np.sort(rng.choice(candidates, size=min(len(candidates), cfg.block_scene_blocks), replace=False))
        neighbours = neighbour_table(*g.hash_table, g.slot_keys, keep)
        x = engine.alpha.evaluator.windows(neighbours)
        gt = gt_tsdf_blocks(seq.scene, g.coords[keep].numpy(), cfg.voxel_size_m, cfg.band_m)
        data.append({"x": torch.from_numpy(x).permute(0, 4, 1, 2, 3).contiguous(), "gt": torch.from_numpy(gt),
                     **{f"{c}{i}": g.pools[f"{c}{i}"][keep].float().clone() for c in ("tsdf", "weight")
                        for i in (0, 1)}})
        del engine
    return data, rng


def train_on_blocks(trainer, sequences, engine_config, *, log=print) -> dict[str, float]:
    """The block phase on the trainer's G and optimizer; returns how many scenes and blocks it used."""
    cfg = trainer.config
    data, rng = collect_blocks(trainer, sequences, engine_config)
    terms_sum: dict[str, float] = {}
    params = list(trainer.weighting_net.parameters())
    for step in range(cfg.block_steps):
        trainer.set_lr(cosine_lr(cfg.block_lr or cfg.lr, cfg.block_lr_final_fraction, step / cfg.block_steps))
        d = block_batch(data, cfg.block_batch, mixed=cfg.block_mixed, rng=rng)
        n = len(d["x"])
        alpha = trainer.weighting_net(d["x"], pad=False).reshape(n, -1)
        flat = {k: d[k].reshape(n, -1) for k in ("tsdf0", "weight0", "tsdf1", "weight1")}
        loss, terms = senfunet_loss(flat["tsdf0"], flat["weight0"], flat["tsdf1"], flat["weight1"], alpha,
                                    d["gt"], torch.ones_like(alpha, dtype=torch.bool), lambda1=cfg.lambda1,
                                    lambda2=cfg.lambda2, eta_m=cfg.eta_m)
        trainer.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, cfg.clip_grad_norm)
        trainer.optimizer.step()
        trainer.optimizer_steps += 1
        for k, v in terms.items():
            terms_sum[k] = terms_sum.get(k, 0.0) + v
        if (step + 1) % 250 == 0:
            log(f"block step {step + 1}: " + ", ".join(f"{k} {v / 250:.3f}" for k, v in terms_sum.items()))
            terms_sum = {}
    trainer.optimizer.zero_grad(set_to_none=True)
    trainer.set_lr(cfg.lr)
    return {"scenes": len(data), "blocks": sum(len(d["x"]) for d in data)}
