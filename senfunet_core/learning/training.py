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

import copy
import math
import random
import time
from dataclasses import asdict, dataclass, field, fields
from fractions import Fraction
from pathlib import Path

import numba
import numpy as np
import torch

from .. import networks
from ..errors import InputError
from ..fusion import fuse
from ..grid import BLOCK, BLOCK_VOXELS, BlockGrid, coords_key, hash_find, kernel_view, keys_to_coords
from ..integrator import IntegratorConfig, locate_samples, update_voxels, valid_depth_mask

SENSORS = ("tof", "stereo")
# a pixel's features depend on the pixels within this radius (6 residual blocks of two 3x3 convolutions)
FEATURE_RADIUS_PX = 2 * networks.N_RESIDUAL_BLOCKS


@dataclass
class TrainConfig:
    seed: int = 0
    train_scenes: tuple[int, ...] = (0, 1, 2, 3, 4, 5)  # scene seeds (< 1000: held-out scenes use >= 1000)
    val_scenes: tuple[int, ...] = (900,)  # validation scenes (never trained on, never evaluated on)
    duration_s: float = 6.0  # simulated seconds per training scene
    tof_rate_hz: float = 15.0
    stereo_rate_hz: float = 20.0
    val_duration_s: float = 3.0
    val_tof_rate_hz: float = 15.0  # validation recordings: the evaluation's rates and frame stride
    val_stereo_rate_hz: float = 20.0
    val_frame_stride: int = 3  # validation integrates every k-th frame of each sensor (as the evaluation)
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
    scene_slots: int = 1  # scenes trained on at once, each in its own grids, their frames interleaved at random
    segments_per_scene: int = 1  # each scene's recording is cut into this many consecutive parts (fresh grids each)
    chunk_size: int = 64
    min_update_voxels: int = 2000
    max_chunk_tries: int = 600
    lr: float = 1e-4
    weighting_tsdf_input: bool = False  # G also reads the sensors' TSDFs (not the paper; networks.WeightingNet)
    # G on whole blocks of integrated grids before the online frames (not the paper's training): the training
    # scenes are integrated with the validation protocol (every val_frame_stride-th frame, feature nets as they
    # are), block_scene_blocks blocks with single-sensor voxels are kept per scene, and G alone takes
    # block_steps Adam steps on block_batch of them (their 12^3 windows, all 512 voxels) with the paper's loss
    block_steps: int = 0
    block_batch: int = 16
    block_scene_blocks: int = 1200
    block_mixed: bool = False  # a batch draws its blocks from all scenes (False: all from one random scene)
    block_lr: float = 0.0  # the block phase's learning rate (0: lr)
    block_lr_final_fraction: float = 1.0  # cosine decay of the block phase's learning rate to block_lr * this
    init_weights: str = ""  # start from this weights file's networks (e.g. after a block phase), not init_seed
    feature_lr_factor: float = 1.0  # the feature nets' learning rate is lr * this (1 = the paper's single rate)
    lr_final_fraction: float = 1.0  # cosine decay of the learning rate to lr * this over the run (1 = constant)
    accumulate_frames: int = 20
    clip_grad_norm: float = 1.0
    reset_probability: float = 0.01
    max_blocks: int = 60000  # memory cap: the grids are also reset when they hold more blocks (~1.2 GB)
    lambda1: float = 1 / 60
    lambda2: float = 1 / 600
    eta_m: float = 0.04
    steps: int = 1000  # training frames in total
    time_budget_s: float = 0.0  # stop (and validate a last time) after this much wall time; 0 = no limit
    threads: int = 2
    cache_dir: str = "~/.cache/senfunet"
    init_seed: int = 0  # network initialisation
    # departures from the paper's training, setting or topic -> reason (docs/results.md lists them)
    deviations: dict = field(default_factory=dict)

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


def cosine_lr(lr: float, final_fraction: float, progress: float) -> float:
    """Cosine decay from lr (progress 0) to lr * final_fraction (progress >= 1); constant when the fraction is 1."""
    if final_fraction == 1.0:
        return lr
    low = lr * final_fraction
    return low + 0.5 * (lr - low) * (1 + math.cos(math.pi * min(max(progress, 0.0), 1.0)))


def block_batch(data: list[dict[str, torch.Tensor]], size: int, mixed: bool,
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


def update_box(voxels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inclusive min and max voxel index (3,) of the updated voxels (U x 3)."""
    return voxels.min(dim=0).values, voxels.max(dim=0).values


@numba.njit(cache=True, nogil=True)
def _first_box_holding(voxels: np.ndarray, corners: np.ndarray, size: np.ndarray, min_voxels: int) -> int:
    """Index of the first corner whose box (size per axis) holds >= min_voxels of the voxels, -1 if none."""
    n_voxels = voxels.shape[0]
    for j in range(corners.shape[0]):
        c0, c1, c2 = corners[j, 0], corners[j, 1], corners[j, 2]
        count = 0
        for i in range(n_voxels):
            if count + (n_voxels - i) < min_voxels:
                break  # cannot reach the minimum any more
            x, y, z = voxels[i, 0] - c0, voxels[i, 1] - c1, voxels[i, 2] - c2
            if 0 <= x < size[0] and 0 <= y < size[1] and 0 <= z < size[2]:
                count += 1
                if count >= min_voxels:
                    return j
    return -1


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
    voxels_np = np.ascontiguousarray(voxels.numpy(), np.int64)
    size_np = size.numpy().astype(np.int64)
    tries = 0
    while tries < max_tries:
        n = min(batch, max_tries - tries)
        corners = lo + (torch.rand((n, 3), generator=generator) * span).to(torch.int64).clamp(max=span - 1)
        j = _first_box_holding(voxels_np, np.ascontiguousarray(corners.numpy()), size_np, int(min_voxels))
        if j >= 0:
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
# Compiled helpers over one frame's ray samples (flat pool index slot*512 + local per sample)
# --------------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _frame_voxels(sample_flat: np.ndarray, sample_touched: np.ndarray, touched_slots: np.ndarray,
                  slot_coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The voxels a frame updated (each once): flat pool indices (U,) and voxel indices (U, 3)."""
    n_touched = touched_slots.shape[0]
    mark = np.zeros((n_touched, 512), np.bool_)
    for n in range(sample_flat.shape[0]):
        mark[sample_touched[n], sample_flat[n] & 511] = True
    total = 0
    for t in range(n_touched):
        for local in range(512):
            total += mark[t, local]
    flat = np.empty(total, np.int64)
    voxels = np.empty((total, 3), np.int64)
    k = 0
    for t in range(n_touched):
        slot = touched_slots[t]
        for local in range(512):
            if mark[t, local]:
                flat[k] = slot * 512 + local
                voxels[k, 0] = slot_coords[slot, 0] * 8 + (local >> 6)
                voxels[k, 1] = slot_coords[slot, 1] * 8 + ((local >> 3) & 7)
                voxels[k, 2] = slot_coords[slot, 2] * 8 + (local & 7)
                k += 1
    return flat, voxels


@numba.njit(cache=True, nogil=True)
def _samples_in_box(sample_flat: np.ndarray, samples_per_ray: int, pixel_index: np.ndarray, slot_coords: np.ndarray,
                    corner: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For the samples that fall in the box corner..corner+size-1: their voxel's box-local index
    ((x * size_y + y) * size_z + z) and their pixel (flat image index)."""
    n = sample_flat.shape[0]
    local_out = np.empty(n, np.int64)
    pixel_out = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        f = sample_flat[i]
        slot = f >> 9
        local = f & 511
        x = slot_coords[slot, 0] * 8 + (local >> 6) - corner[0]
        if x < 0 or x >= size[0]:
            continue
        y = slot_coords[slot, 1] * 8 + ((local >> 3) & 7) - corner[1]
        if y < 0 or y >= size[1]:
            continue
        z = slot_coords[slot, 2] * 8 + (local & 7) - corner[2]
        if z < 0 or z >= size[2]:
            continue
        local_out[m] = (x * size[1] + y) * size[2] + z
        pixel_out[m] = pixel_index[i // samples_per_ray]
        m += 1
    return local_out[:m], pixel_out[:m]


@numba.njit(cache=True, nogil=True)
def _box_flat(corner: np.ndarray, size: np.ndarray, index: np.ndarray, table_keys: np.ndarray,
              table_slots: np.ndarray) -> np.ndarray:
    """Flat pool index of box voxels given by box-local index ((x * size_y + y) * size_z + z),
    -1 where the voxel's block does not exist."""
    out = np.empty(index.shape[0], np.int64)
    for k in range(index.shape[0]):
        i = index[k]
        x = corner[0] + i // (size[1] * size[2])
        y = corner[1] + (i // size[2]) % size[1]
        z = corner[2] + i % size[2]
        key = coords_key(x >> 3, y >> 3, z >> 3)
        slot = hash_find(table_keys, table_slots, key) if key >= 0 else -1
        out[k] = slot * 512 + ((x & 7) << 6) + ((y & 7) << 3) + (z & 7) if slot >= 0 else -1
    return out


_OFFSETS_27 = torch.tensor([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)])


def _neighbours_27(index: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """Box-local indices (K,) -> their 3^3 neighbourhoods (K, 27), clamped to the box (replicate padding),
    in the order of a Conv3d kernel's (kx, ky, kz) taps."""
    sx, sy, sz = size
    ix, iy, iz = index // (sy * sz), (index // sz) % sy, index % sz
    nx = (ix.unsqueeze(1) + _OFFSETS_27[:, 0]).clamp_(0, sx - 1)
    ny = (iy.unsqueeze(1) + _OFFSETS_27[:, 1]).clamp_(0, sy - 1)
    nz = (iz.unsqueeze(1) + _OFFSETS_27[:, 2]).clamp_(0, sz - 1)
    return (nx * sy + ny) * sz + nz


def _compact(index: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sorted unique values of `index` (all in 0..n-1) and each entry's position among them
    (torch.unique with return_inverse, by marking a dense table: no sort)."""
    flat = index.reshape(-1).numpy()
    mark = np.zeros(n, np.bool_)
    mark[flat] = True
    unique = np.flatnonzero(mark)
    position = np.empty(n, np.int64)
    position[unique] = np.arange(len(unique))
    return torch.from_numpy(unique), torch.from_numpy(position[flat]).reshape(index.shape)


@dataclass
class SparsePlan:
    """Where G must run to give alpha at `out` voxels of a box (replicate padding)."""

    inputs: torch.Tensor  # (K,) box-local indices of the input voxels conv1 reads
    conv1_taps: torch.Tensor  # (M1, 27) positions in `inputs` read by each conv1 output
    conv2_taps: torch.Tensor  # (M, 27) positions among the conv1 outputs read by each conv2 output


def sparse_plan(out_index: torch.Tensor, size: tuple[int, int, int]) -> SparsePlan:
    n = int(np.prod(size))
    middle, conv2_taps = _compact(_neighbours_27(out_index, size), n)  # conv1 outputs conv2 reads
    inputs, conv1_taps = _compact(_neighbours_27(middle, size), n)
    return SparsePlan(inputs, conv1_taps, conv2_taps)


def sparse_alpha_planned(net: networks.WeightingNet, x_inputs: torch.Tensor, plan: SparsePlan) -> torch.Tensor:
    """G at the plan's output voxels from its inputs x_inputs (K, C) (the box voxels plan.inputs)."""
    conv1, conv2, conv3 = net.conv1, net.conv2, net.conv3
    w1 = conv1.weight.permute(2, 3, 4, 1, 0).reshape(-1, conv1.out_channels)  # (27 * C, 32), tap-major
    h1 = torch.relu(x_inputs.index_select(0, plan.conv1_taps.reshape(-1)).reshape(len(plan.conv1_taps), -1) @ w1
                    + conv1.bias)
    w2 = conv2.weight.permute(2, 3, 4, 1, 0).reshape(-1, conv2.out_channels)
    h2 = torch.relu(h1.index_select(0, plan.conv2_taps.reshape(-1)).reshape(len(plan.conv2_taps), -1) @ w2
                    + conv2.bias)
    return torch.sigmoid(h2 @ conv3.weight.reshape(conv3.out_channels, -1).T + conv3.bias).reshape(-1)


def sparse_alpha(net: networks.WeightingNet, x: torch.Tensor, size: tuple[int, int, int],
                 out_index: torch.Tensor) -> torch.Tensor:
    """G with replicate padding on a box, evaluated only at the voxels `out_index` (M,).

    x: (N, C) inputs of the box's voxels in box-local order ((x * size_y + y) * size_z + z).
    Equals `net(x as 1 x C x box, pad=True)` at those voxels: every 3^3 convolution reads its
    input at box-clamped neighbours (what replicate padding does), conv1 runs only where conv2
    reads it, and only the inputs conv1 reads are touched. A frame updates ~5% of a 64^3 chunk, so
    this is several times cheaper than the dense pass, and gradients flow the same way."""
    size = tuple(int(v) for v in size)
    plan = sparse_plan(out_index, size)
    return sparse_alpha_planned(net, x.index_select(0, plan.inputs), plan)


class GTCache:
    """GT TSDF of one scene, computed block by block (8^3 voxels) on first use and kept."""

    _OFFSET = 1 << 16

    def __init__(self, voxel_size_m: float, band_m: float) -> None:
        self.voxel_size_m = voxel_size_m
        self.band_m = band_m
        self.scene_seed: int | None = None
        self.blocks: dict[int, np.ndarray] = {}

    def values(self, scene, voxels: np.ndarray) -> np.ndarray:
        """GT TSDF (N,) float32 at voxel indices (N, 3)."""
        from .simulator import gt_tsdf_blocks

        if scene.seed != self.scene_seed:
            self.scene_seed, self.blocks = scene.seed, {}
        blocks = voxels >> 3
        local = voxels & 7
        keys = (((blocks[:, 0] + self._OFFSET) << 34) | ((blocks[:, 1] + self._OFFSET) << 17)
                | (blocks[:, 2] + self._OFFSET))
        unique, inverse = np.unique(keys, return_inverse=True)
        missing = [i for i, k in enumerate(unique.tolist()) if k not in self.blocks]
        if missing:
            some = np.empty(len(unique), np.int64)
            some[inverse.reshape(-1)] = np.arange(len(keys))  # a voxel of each block
            coords = blocks[some[missing]]
            values = gt_tsdf_blocks(scene, coords, self.voxel_size_m, self.band_m)
            for i, row in zip(missing, values):
                self.blocks[int(unique[i])] = row
        table = np.stack([self.blocks[k] for k in unique.tolist()])
        return table[inverse.reshape(-1), local[:, 0] * 64 + local[:, 1] * 8 + local[:, 2]]


# --------------------------------------------------------------------------------------------
# The trainer
# --------------------------------------------------------------------------------------------
@dataclass
class StepResult:
    loss: float | None  # None when no chunk with enough updated voxels was found
    terms: dict[str, float] = field(default_factory=dict)
    tries: int = 0
    updated: int = 0


@dataclass
class _FrameSamples:
    """What the compiled integration of one frame leaves for the loss."""

    sample_flat: np.ndarray  # P*S flat pool index of every ray sample
    pixel_index: np.ndarray  # P flat image index of every integrated pixel
    updated_flat: np.ndarray  # U voxels the frame updated
    updated_voxels: np.ndarray  # U x 3


class Trainer:
    def __init__(self, config: TrainConfig) -> None:
        self.config = config
        torch.manual_seed(config.seed)
        self.rng = random.Random(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.feature_nets, self.weighting_net = networks.make_networks(config.sensor_uses_rgb, config.init_seed,
                                                                       config.weighting_tsdf_input)
        if config.init_weights:
            path = Path(config.init_weights)
            if networks.weights_tsdf_input(path) != config.weighting_tsdf_input:
                raise InputError(f"init_weights {path}: its weighting net's TSDF input differs from "
                                 f"weighting_tsdf_input = {config.weighting_tsdf_input}; match them in the config")
            networks.load_weights(path, self.feature_nets, self.weighting_net)
        self.feature_nets.train()
        self.weighting_net.train()
        groups = [{"params": list(self.feature_nets.parameters()), "lr_factor": config.feature_lr_factor},
                  {"params": list(self.weighting_net.parameters()), "lr_factor": 1.0}]
        for group in groups:
            group["lr"] = config.lr * group["lr_factor"]
        self.optimizer = torch.optim.Adam(groups, lr=config.lr, betas=(0.9, 0.999), eps=1e-8, weight_decay=0)
        # the engine's grid layout: features, weight counters (and the unused drift) in half precision
        channels: dict[str, tuple[int, ...]] = {"tsdf_base": (), "weight_base": (), "drift": ()}
        for i in range(len(SENSORS)):
            channels.update({f"tsdf{i}": (), f"weight{i}": (), f"feat{i}": (networks.N_FEATURES,)})
        dtypes = {name: torch.float16 for name in channels if name.startswith(("feat", "weight", "drift"))}
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
                   T_world_camera: np.ndarray) -> _FrameSamples:
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
            state = np.array([grid.n_blocks, min(grid.max_blocks_before_rehash(), grid.capacity)], np.int64)
            n_pixels, n_touched, ok = locate_samples(
                depth, cfg.depth_min_m[s], cfg.depth_max_m[s], cfg.border_px, K64, T64, self.offsets_m,
                cfg.voxel_size_m, grid.table_keys, grid.table_slots, state, grid.slot_keys, slot_to_touched,
                touched_slots, sample_flat, sample_touched, pixel_index)
            grid.commit_new_blocks(int(state[0]))
            if ok:
                break
            if state[0] < state[1]:
                raise InputError("points lie more than 5 km from the origin; check the pose's units (metres) and frame")
            grid.reserve(max(int(grid.capacity * grid.growth) + 1, grid.n_blocks + 1024))
        n_samples = n_pixels * len(self.offsets_m)
        features = np.ascontiguousarray(pixel_features.reshape(pixel_features.shape[0], -1).T, np.float32)
        views = [kernel_view(grid.pools[name]).reshape(-1) for name in
                 (f"tsdf{s}", f"weight{s}", f"feat{s}", "tsdf_base", "weight_base", "drift")]
        update_voxels(n_pixels, n_touched, sample_flat, sample_touched, -self.offsets_m, pixel_index, features,
                      touched_slots, views[0], views[1], views[2], views[3], views[4], views[5], cfg.w_max)
        touched = touched_slots[:n_touched]
        updated_flat, updated_voxels = _frame_voxels(sample_flat[:n_samples], sample_touched[:n_samples], touched,
                                                     grid.coords.numpy())
        return _FrameSamples(sample_flat[:n_samples], pixel_index[:n_pixels], updated_flat, updated_voxels)

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
            net = self.feature_nets[s]
            rgb01 = self._rgb01(net.uses_rgb, frame.rgb, depth.shape)
            with torch.no_grad():
                pixel = net(depth_t.view(1, 1, *depth.shape), rgb01)[0]
            t0 = self._timed("feature_net", t0)
            samples = self._integrate(s, depth, pixel.numpy(), frame.K, frame.T_world_camera)
            result.updated = len(samples.updated_flat)
            t0 = self._timed("integrate", t0)
            if result.updated:
                corner, size, result.tries = sample_chunk(torch.from_numpy(samples.updated_voxels), cfg.chunk_size,
                                                          cfg.min_update_voxels, cfg.max_chunk_tries, self.generator)
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

    def _chunk_loss(self, s: int, corner: np.ndarray, size: np.ndarray, samples: _FrameSamples,
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
        box = tuple(int(v) for v in size)
        upd = torch.from_numpy(updated)
        plan = sparse_plan(upd, box)  # G's inputs: the voxels within 2 of an updated one (box-clamped)
        chunk_flat = torch.from_numpy(_box_flat(corner, size, plan.inputs.numpy(), grid.table_keys, grid.table_slots))
        present = chunk_flat >= 0
        index = chunk_flat.clamp(min=0)

        def channel(name: str) -> torch.Tensor:
            pool = grid.pools[name]
            values = pool.reshape(-1, *pool.shape[2:])[index].float()
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
                             torch.ones_like(gt, dtype=torch.bool), cfg.lambda1, cfg.lambda2, cfg.eta_m)

    def train_weighting_net_on_blocks(self, sequences, engine_config, log=print) -> dict[str, float]:
        """G alone on whole blocks of the integrated training scenes (see TrainConfig.block_steps)."""
        from ..engine import SenFuNet
        from .evaluation import integrate_frames
        from ..grid import neighbour_table
        from .simulator import gt_tsdf_blocks

        cfg = self.config
        rng = np.random.default_rng(cfg.seed)
        data = []
        for seq in sequences:
            engine = SenFuNet(engine_config, weights=None)
            engine.feature_nets.load_state_dict(copy.deepcopy(self.feature_nets.state_dict()))
            integrate_frames(engine, seq.frames, {name: cfg.val_frame_stride for name in SENSORS})
            g = engine.grid
            n = g.n_blocks
            w0, w1 = g.pools["weight0"][:n].float(), g.pools["weight1"][:n].float()
            candidates = np.flatnonzero((((w0 > 0) ^ (w1 > 0)).sum(1) > 10).numpy())
            if len(candidates) == 0:
                continue
            keep = np.sort(rng.choice(candidates, size=min(len(candidates), cfg.block_scene_blocks), replace=False))
            neighbours = neighbour_table(g.table_keys, g.table_slots, g.slot_keys, keep)
            x = engine._weighting_windows(neighbours)
            data.append({"x": torch.from_numpy(x).permute(0, 4, 1, 2, 3).contiguous(),
                         "gt": torch.from_numpy(gt_tsdf_blocks(seq.scene, g.coords[keep].numpy(), cfg.voxel_size_m,
                                                               cfg.band_m)),
                         **{f"{c}{i}": g.pools[f"{c}{i}"][keep].float().clone() for c in ("tsdf", "weight") for i in (0, 1)}})
            del engine
        terms_sum: dict[str, float] = {}
        params = list(self.weighting_net.parameters())
        for step in range(cfg.block_steps):
            self.set_lr(cosine_lr(cfg.block_lr or cfg.lr, cfg.block_lr_final_fraction, step / cfg.block_steps))
            d = block_batch(data, cfg.block_batch, cfg.block_mixed, rng)
            n = len(d["x"])
            alpha = self.weighting_net(d["x"], pad=False).reshape(n, -1)
            flat = {k: d[k].reshape(n, -1) for k in ("tsdf0", "weight0", "tsdf1", "weight1")}
            loss, terms = senfunet_loss(flat["tsdf0"], flat["weight0"], flat["tsdf1"], flat["weight1"], alpha,
                                        d["gt"], torch.ones_like(alpha, dtype=torch.bool), cfg.lambda1,
                                        cfg.lambda2, cfg.eta_m)
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, cfg.clip_grad_norm)
            self.optimizer.step()
            self.optimizer_steps += 1
            for k, v in terms.items():
                terms_sum[k] = terms_sum.get(k, 0.0) + v
            if (step + 1) % 250 == 0:
                log(f"block step {step + 1}: " + ", ".join(f"{k} {v / 250:.3f}" for k, v in terms_sum.items()))
                terms_sum = {}
        self.optimizer.zero_grad(set_to_none=True)
        self.set_lr(cfg.lr)
        return {"scenes": len(data), "blocks": sum(len(d["x"]) for d in data)}

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


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------
ALPHA_STATISTICS = ("c12_alpha_mean", "c12_tof_share", "c1_kept", "c2_kept")


def alpha_statistics(engine) -> dict[str, float]:
    """How an engine's alpha splits the work: mean alpha and the share of alpha > 0.5 on voxels both
    sensors saw, and the share of single-sensor voxels the outlier filter keeps (a collapsed net
    shows alpha = 1 everywhere: all ToF, every stereo-only voxel dropped). Call it after the fused
    grid was read (`voxel_values("fused")` or a fused mesh): alpha is up to date then."""
    grid = engine.grid
    n = grid.n_blocks
    w0 = grid.pools["weight0"][:n].reshape(-1).float()
    w1 = grid.pools["weight1"][:n].reshape(-1).float()
    alpha = grid.pools["alpha"][:n].reshape(-1)
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
            seq = cached_sequence(seed, config.val_duration_s, config.val_tof_rate_hz, config.val_stereo_rate_hz,
                                  config.cache_dir, log)
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


_PAUSE_WATCHER = r"""
import os, struct, sys, time
from multiprocessing import shared_memory
parent, name, tick, gap = int(sys.argv[1]), sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
memory = shared_memory.SharedMemory(name=name)
try:  # attaching is not owning (Python < 3.13 would unlink it at exit)
    from multiprocessing import resource_tracker
    resource_tracker.unregister(memory._name, "shared_memory")
except Exception:
    pass
paused, last = 0.0, time.monotonic()
while True:
    time.sleep(tick)
    now = time.monotonic()
    try:
        with open(f"/proc/{parent}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        break  # the trainer is gone
    if now - last > gap:  # this watcher was stopped too (a script pausing every background job)
        paused += now - last - tick
    elif state in ("T", "t"):  # only the trainer was stopped
        paused += now - last
    last = now
    memory.buf[:8] = struct.pack("d", paused)
"""


class ActiveClock:
    """Wall time minus the time the training process was stopped (SIGSTOP, e.g. by a script that
    pauses background jobs while benchmarks run on a shared machine). A small watcher process
    (it does not share the trainer's GIL, so long computations are not mistaken for pauses) checks
    the trainer's state every 0.2 s and counts the stopped time; when the watcher is stopped along
    with the trainer, the gap in its own ticks counts."""

    def __init__(self, tick_s: float = 0.2, gap_s: float = 2.0) -> None:
        import atexit
        import os
        import subprocess
        import sys
        from multiprocessing import shared_memory

        self.start = time.monotonic()
        self._memory = shared_memory.SharedMemory(create=True, size=8)
        self._memory.buf[:8] = bytes(8)
        self._watcher = subprocess.Popen([sys.executable, "-c", _PAUSE_WATCHER, str(os.getpid()), self._memory.name,
                                          str(tick_s), str(gap_s)])
        atexit.register(self.stop)

    @property
    def paused_s(self) -> float:
        import struct

        return float(struct.unpack("d", bytes(self._memory.buf[:8]))[0]) if self._memory is not None else self._final

    def wall(self) -> float:
        return time.monotonic() - self.start

    def active(self) -> float:
        return self.wall() - self.paused_s

    def stop(self) -> None:
        if self._memory is None:
            return
        self._final = self.paused_s
        self._watcher.kill()
        self._watcher.wait()
        self._memory.close()
        self._memory.unlink()
        self._memory = None


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
                                         "ran": {"block_steps": config.block_steps if config.block_steps > 0 else 0,
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


def load_config(path: str | Path) -> TrainConfig:
    import yaml

    values = yaml.safe_load(Path(path).read_text()) or {}
    return TrainConfig.from_dict(values)
