"""Measure and write the int8 calibration of a weights file (`senfunet_core.weighting_int8`): what
`scripts/calibrate_int8.py` does for the shipped weights and `senfunet train` for the weights it makes."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm

from ..alpha_evaluator import surface_windows
from ..engine import EngineConfig, SenFuNet
from ..weighting_int8 import Int8Calibration, calibrate, calibration_path, file_sha256


def calibrate_weights_file(weights: str | Path, frames: Sequence[Any], config: EngineConfig, *, source: str,
                           progress: bool = True) -> Int8Calibration:
    """Fuse `frames` (each with sensor, depth_m, K, T_world_camera, rgb: as the node would get them)
    with these weights under `config` (G in float32), run G over every block that holds voxels alpha
    matters for, and write the hidden layers' largest outputs beside the weights
    (`calibration_path`). `source` names the frames in the file. Returns the calibration."""
    weights = Path(weights)
    engine = SenFuNet(config, weights=weights)
    for frame in tqdm(frames, desc=f"int8 calibration of {weights.name} on {source}", unit="frame",
                      disable=not progress):
        engine.integrate(frame.sensor, frame.depth_m, frame.K, frame.T_world_camera, frame.rgb)
    calibration = calibrate(engine.weighting_net, surface_windows(engine.alpha.evaluator),
                            weights_sha256=file_sha256(weights), calibrated_on=f"{source}, {len(frames)} frames")
    calibration.save(calibration_path(weights))
    return calibration
