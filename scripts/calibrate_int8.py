"""Measure the int8 calibration of weighting-net weights (`senfunet_core.weighting_int8`) and write it
beside them as `<weights>.int8.json`.

Fuses a bag's frames (default: the bundled sample) with the weights at the node's default settings,
then runs G in float32 over every block that holds voxels alpha matters for and records its hidden
layers' largest outputs. Without --weights: the shipped weights files.

    .venv/bin/python scripts/calibrate_int8.py [--weights FILE ...] [--bag DIR]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    from senfunet_core.learning.int8_calibration import calibrate_weights_file
    from senfunet_core.networks import NAMED_WEIGHTS
    from senfunet_core.weighting_int8 import calibration_path
    from senfunet_ros.params_file import load_settings
    from senfunet_ros.replay import bag_frames, engine_config

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", nargs="+", default=[str(p) for p in NAMED_WEIGHTS.values() if p.is_file()])
    ap.add_argument("--bag", default=str(ROOT / "bags" / "sim_room"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    frames = bag_frames(Path(args.bag))
    config = engine_config(load_settings(None), alpha_dtype="float32", max_blocks=0)
    for weights in args.weights:
        calibration = calibrate_weights_file(weights, frames, config, source=Path(args.bag).name)
        print(f"{calibration_path(weights)}: hidden layers' largest outputs {calibration.layer_1_max:.3f}, "
              f"{calibration.layer_2_max:.3f}")


if __name__ == "__main__":
    main()
