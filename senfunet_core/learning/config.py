"""The training configuration (`senfunet train --config`): a dataclass read from YAML."""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from fractions import Fraction
from pathlib import Path

from ..files import yaml_error_text
from ..integrator import IntegratorConfig

SENSORS = ("tof", "stereo")


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
    # the feature nets' per-pixel pretraining before the block phase (not the paper's training; see
    # feature_pretrain.py): feature_pretrain_steps Adam steps per sensor on batches of feature_pretrain_batch
    # random crops of feature_pretrain_crop_px, learning which pixels lie within eta_m of the true depth
    feature_pretrain_steps: int = 0
    feature_pretrain_lr: float = 1e-3
    feature_pretrain_batch: int = 8
    feature_pretrain_crop_px: int = 64
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
    def from_dict(cls, values: dict) -> TrainConfig:
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(values) - set(known))
        if unknown:
            import difflib

            named = [key + "".join(f" (did you mean '{close}'?)" for close in difflib.get_close_matches(key, known, 1))
                     for key in unknown]
            raise ValueError(f"unknown training config key(s): {', '.join(named)}; the keys are the fields of "
                             f"TrainConfig in senfunet_core/learning/config.py: {', '.join(sorted(known))}")
        out = {}
        for k, v in values.items():
            if isinstance(v, list):
                v = tuple(v)
            if isinstance(v, str) and known[k].type in ("float", float):
                v = float(Fraction(v.replace(" ", "")))  # allow "1/60"
            out[k] = v
        return cls(**out)


def load_config(path: str | Path) -> TrainConfig:
    import yaml

    try:
        values = yaml.safe_load(Path(path).read_text()) or {}
    except yaml.YAMLError as err:  # a ValueError for the caller, like every other bad config
        raise ValueError(yaml_error_text(err)) from None
    if not isinstance(values, dict):
        raise ValueError(f"expected a mapping of training settings (key: value), got a {type(values).__name__}")
    return TrainConfig.from_dict(values)


# The paper's training settings (section 4 and supplementary C) as TrainConfig fields: a config whose
# value differs must say why in its `deviations` (docs/results.md lists any that does not).
PAPER_TRAINING = {"chunk_size": 64, "min_update_voxels": 2000, "max_chunk_tries": 600, "lr": 1e-4,
                  "accumulate_frames": 20, "clip_grad_norm": 1.0, "reset_probability": 0.01,
                  "lambda1": 1 / 60, "lambda2": 1 / 600, "eta_m": 0.04, "weighting_tsdf_input": False,
                  "block_steps": 0, "feature_pretrain_steps": 0, "feature_lr_factor": 1.0, "lr_final_fraction": 1.0,
                  "time_budget_s": 0.0}
