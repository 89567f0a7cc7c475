"""Per-pixel pretraining of the feature nets (not the paper's training, which trains them end to end
through G's loss, too slow on a CPU): each sensor's feature net, with a small auxiliary head, learns
to tell from its image which of its pixels are trustworthy.

The training scenes' frames (every val_frame_stride-th of each sensor, as the block phase integrates
them) are paired with the true z-depth rendered from the frame's pose; a pixel is an inlier when
|depth - true depth| < eta_m (the loss's inlier threshold on TSDF values). The head is a 1x1
convolution from the net's learned (unit-norm) feature channels to one logit; the loss is binary
cross entropy, each class weighted to half the batch (outliers are the minority for ToF). Batches are
random crops; pixels closer to a crop's border than the net's receptive radius are left out of the
loss, so the net learns what it computes on whole images. The head is dropped afterwards: G reads the
features through the grids, as in the paper.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from .. import networks
from .config import SENSORS
from .raycast import render_view

# a pixel's features depend on the pixels within this radius (6 residual blocks of two 3x3 convolutions)
RADIUS_PX = 2 * networks.N_RESIDUAL_BLOCKS


@dataclass
class PixelFrames:
    """One sensor's frames: depth (N,H,W) float32 (0 = invalid), rgb (N,H,W,3) uint8 or None,
    inlier (N,H,W) bool and valid (N,H,W) bool."""

    depth_m: np.ndarray
    rgb: np.ndarray | None
    inlier: np.ndarray
    valid: np.ndarray


def pixel_frames(sequences, *, frame_stride: int, eta_m: float, depth_min_m: tuple[float, ...],
                 depth_max_m: tuple[float, ...], border_px: int) -> dict[str, PixelFrames]:
    """Per sensor: every frame_stride-th frame of each sequence with its per-pixel inlier label against
    the true depth rendered from the frame's pose."""
    parts: dict[str, dict[str, list]] = {s: {"depth": [], "rgb": [], "inlier": [], "valid": []} for s in SENSORS}
    for seq in sequences:
        counts = dict.fromkeys(SENSORS, 0)
        for frame in seq.frames:
            s = frame.sensor
            counts[s] += 1
            if (counts[s] - 1) % frame_stride:
                continue
            i = SENSORS.index(s)
            depth = np.nan_to_num(np.asarray(frame.depth_m, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
            h, w = depth.shape
            true = render_view(seq.scene, frame.T_world_camera, frame.K, w, h, with_rgb=False)["depth_m"]
            valid = (depth >= depth_min_m[i]) & (depth <= depth_max_m[i])
            valid[:border_px] = valid[h - border_px:] = False
            valid[:, :border_px] = valid[:, w - border_px:] = False
            part = parts[s]
            part["depth"].append(np.where(valid, depth, 0.0).astype(np.float32))
            part["rgb"].append(frame.rgb)
            part["inlier"].append(valid & (np.abs(depth - true) < eta_m))
            part["valid"].append(valid)
    out = {}
    for s, part in parts.items():
        if not part["depth"]:
            continue
        rgb = None if any(r is None for r in part["rgb"]) else np.stack(part["rgb"])
        out[s] = PixelFrames(np.stack(part["depth"]), rgb, np.stack(part["inlier"]), np.stack(part["valid"]))
    return out


def crop_batch(frames: PixelFrames, *, size: int, crop_px: int, rng: np.random.Generator
               ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor, torch.Tensor]:
    """`size` random crop_px x crop_px crops: depth Bx1xcxc, rgb01 Bx3xcxc (or None), inlier and the
    loss mask (valid pixels at least RADIUS_PX from the crop's border) Bxcxc."""
    n, h, w = frames.depth_m.shape
    crop = min(crop_px, h, w)
    idx = rng.integers(n, size=size)
    r0 = rng.integers(h - crop + 1, size=size)
    c0 = rng.integers(w - crop + 1, size=size)

    def cut(a: np.ndarray) -> np.ndarray:
        return np.stack([a[i, r:r + crop, c:c + crop] for i, r, c in zip(idx, r0, c0)])

    depth = torch.from_numpy(cut(frames.depth_m)).unsqueeze(1)
    rgb = None if frames.rgb is None else torch.from_numpy(cut(frames.rgb)).permute(0, 3, 1, 2).float() / 255.0
    inner = np.zeros((crop, crop), bool)
    inner[RADIUS_PX:crop - RADIUS_PX, RADIUS_PX:crop - RADIUS_PX] = True
    mask = torch.from_numpy(cut(frames.valid) & inner)
    return depth, rgb, torch.from_numpy(cut(frames.inlier)), mask


def balanced_bce(logit: torch.Tensor, inlier: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Binary cross entropy on the masked pixels, inliers and outliers each weighted to half (a class
    with no pixel in the batch leaves its half out)."""
    target = inlier.float()
    loss = nn.functional.binary_cross_entropy_with_logits(logit, target, reduction="none")
    terms = [loss[mask & cls].mean() for cls in (inlier, ~inlier) if bool((mask & cls).any())]
    return torch.stack(terms).mean() if terms else logit.sum() * 0.0


def pretrain_feature_nets(feature_nets: nn.ModuleList, frames: dict[str, PixelFrames], *, steps: int, lr: float,
                          batch: int, crop_px: int, seed: int, log=print) -> dict[str, dict[str, float]]:
    """Each sensor's feature net and a 1x1 head, `steps` Adam steps on the pixel labels; returns per
    sensor the balanced accuracy of the head and the mean loss over the first and the last tenth of the steps'
    batches, and the inlier share."""
    rng = np.random.default_rng([seed, 15])
    out = {}
    for s, data in frames.items():
        net = feature_nets[SENSORS.index(s)]
        torch.manual_seed(seed)
        head = nn.Conv2d(networks.N_FEATURE_CHANNELS, 1, 1)
        optimizer = torch.optim.Adam(list(net.parameters()) + list(head.parameters()), lr=lr)
        net.train()
        hits = {"in": [0, 0], "out": [0, 0]}
        losses = []
        for step in range(steps):
            depth, rgb, inlier, mask = crop_batch(data, size=batch, crop_px=crop_px, rng=rng)
            features = net(depth, rgb)[:, :networks.N_FEATURE_CHANNELS]
            logit = head(features)[:, 0]
            loss = balanced_bce(logit, inlier, mask)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
            if step >= steps - max(1, steps // 10):  # the last tenth: the head's balanced accuracy
                pred = logit.detach() > 0
                for key, cls in (("in", inlier), ("out", ~inlier)):
                    m = mask & cls
                    hits[key][0] += int((pred[m] == (key == "in")).sum())
                    hits[key][1] += int(m.sum())
            if (step + 1) % 250 == 0:
                log(f"feature net {s}: step {step + 1}, loss {np.mean(losses[-250:]):.4f}")
        recall = [hits[k][0] / max(hits[k][1], 1) for k in ("in", "out")]
        tenth = max(1, steps // 10)
        out[s] = {"balanced_accuracy": float(np.mean(recall)), "loss_first_tenth": float(np.mean(losses[:tenth])),
                  "loss_last_tenth": float(np.mean(losses[-tenth:])),
                  "inlier_share": float(data.inlier.sum() / max(int(data.valid.sum()), 1)),
                  "frames": int(len(data.depth_m))}
        log(f"feature net {s}: {len(data.depth_m)} frames, inliers {out[s]['inlier_share']:.2f} of valid pixels, "
            f"balanced accuracy of the head {out[s]['balanced_accuracy']:.3f} (last tenth of the steps)")
    return out
