"""`senfunet train`: train the feature nets and the weighting net on simulated scenes."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

DEFAULT_OUT = "runs/tof_stereo.pt"  # runs/ is git-ignored: a training run never overwrites the shipped model by default
HELP = "train SenFuNet on simulated two-sensor scenes (progress bar, periodic validation, best checkpoint)"


def _error(text: str) -> int:
    """An error, on stderr; the exit code 2."""
    print(f"senfunet train: {text}", file=sys.stderr)
    return 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", default="config/train_tof_stereo.yaml", metavar="YAML",
                        help="training config (default: config/train_tof_stereo.yaml)")
    parser.add_argument("--out", default=DEFAULT_OUT, metavar="PATH",
                        help=f"where the best weights go (default: {DEFAULT_OUT}); the shipped model is replaced only "
                             "when this names it (senfunet_core/weights/tof_stereo.pt)")
    parser.add_argument("--steps", type=int, default=None, metavar="N", help="training frames (overrides the config)")
    parser.add_argument("--time-budget", type=float, default=None, metavar="S",
                        help="stop after S seconds of wall time (overrides the config; 0 = no limit)")
    parser.add_argument("--cache-dir", default=None, metavar="DIR",
                        help="simulated datasets cache (overrides the config; default ~/.cache/senfunet)")
    parser.add_argument("--init-weights", default=None, metavar="PATH",
                        help="start from this weights file (e.g. this recipe's block phase) and skip the feature-net "
                        "pretraining and the block phase")
    parser.add_argument("--val-every", type=int, default=None, metavar="N",
                        help="validate every N online frames (overrides the config; 0 = at the end only)")
    parser.add_argument("--seed", type=int, default=None, metavar="N",
                        help="training seed and network initialisation seed (overrides the config)")
    parser.add_argument("--block-steps", type=int, default=None, metavar="N",
                        help="Adam steps of the block phase (overrides the config: screens a recipe, file untouched)")
    parser.add_argument("--feature-pretrain-steps", type=int, default=None, metavar="N",
                        help="per-pixel pretraining steps of each feature net before the block phase (overrides the "
                             "config; 0 = none, the feature nets stay at their seeded initialisation)")
    parser.add_argument("--calibration-bag", default=None, metavar="BAG",
                        help="bag whose frames measure the trained weights' int8 calibration (<out>.int8.json, "
                             "without which the node runs the weighting net in float32; default: the sample bag "
                             "of this clone; '' = none)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (log lines only)")


def run(args: argparse.Namespace) -> int:
    import dataclasses
    import json
    import time

    from senfunet_core import networks
    from senfunet_core.errors import InputError
    from senfunet_core.learning.training import load_config, train

    path = Path(args.config)
    if not path.is_file():
        return _error(f"config {path} not found; pass e.g. --config config/train_tof_stereo.yaml")
    try:
        config = load_config(path)
    except (ValueError, TypeError) as err:
        return _error(f"bad config {path}: {err}")
    overrides = {}
    if args.steps is not None:
        overrides["steps"] = args.steps
    if args.time_budget is not None:
        overrides["time_budget_s"] = args.time_budget
    if args.cache_dir is not None:
        overrides["cache_dir"] = args.cache_dir
    if args.init_weights is not None:
        if not Path(args.init_weights).is_file():
            return _error(f"--init-weights {args.init_weights} not found; pass a weights file (.pt)")
        # its networks had their feature-net pretraining and block phase: both are skipped
        overrides.update(init_weights=args.init_weights, block_steps=0, feature_pretrain_steps=0)
    if args.val_every is not None:
        overrides["val_every"] = args.val_every
    if args.seed is not None:
        overrides.update(seed=args.seed, init_seed=args.seed)
    for option, field, phase in (("--block-steps", "block_steps", "is the block phase"),
                                 ("--feature-pretrain-steps", "feature_pretrain_steps", "runs before the block phase")):
        steps = getattr(args, field)
        if steps is None:
            continue
        if steps < 0 or (steps and args.init_weights is not None):
            return _error(f"{option} takes N >= 0 and {phase}, which --init-weights skips; pass one of them")
        overrides[field] = steps
    config = dataclasses.replace(config, **overrides)
    out = Path(args.out)
    shipped = out.resolve() == networks.DEFAULT_WEIGHTS.resolve()
    budget = f", at most {config.time_budget_s:.0f} s" if config.time_budget_s > 0 else ""
    print(f"senfunet train: {config.steps} frames{budget}, scenes {list(config.train_scenes)}, validation scenes "
          f"{list(config.val_scenes)}, lr {config.lr:g}, best weights -> {out}", flush=True)
    t0 = time.perf_counter()
    try:
        summary = train(config, out, progress=not args.no_progress)
    except InputError as err:
        return _error(str(err))
    best = summary["best"]
    print(f"senfunet train: {summary['frames']} frames ({summary['optimizer_steps']} optimizer steps, "
          f"{summary['skipped_frames']} frames without a chunk, {summary['resets']} random resets, "
          f"{summary['memory_resets']} memory resets) in {time.perf_counter() - t0:.0f} s wall time "
          f"({summary['paused_s']:.0f} s of it paused by SIGSTOP); best validation: fused F "
          f"{best.get('F', float('nan')):.2f}, {best.get('margin', float('nan')):+.2f} over the better sensor, at "
          f"frame {best.get('step')} -> {out}")
    print("seconds per stage: " + ", ".join(f"{k} {v:.0f}" for k, v in summary["timings_s"].items()))
    calibrated = _calibrate(out, args.calibration_bag, progress=not args.no_progress)
    history = out.with_suffix(".history.json")
    record = {k: summary[k] for k in ("history", "best", "frames", "optimizer_steps", "seconds", "paused_s", "wall_s",
                                      "timings_s", "mean_terms")}
    if not shipped:  # keep the repository clean when writing the shipped file
        history.write_text(json.dumps(record, indent=1))
    else:
        print(json.dumps(record, indent=1))
    return 0 if calibrated else 2


def _calibrate(weights: Path, bag_arg: str | None, *, progress: bool) -> bool:
    """The int8 calibration of the trained weights, measured on a bag's frames at the node's default
    settings and written beside them; False (with a message saying what to do) when it cannot be."""
    from senfunet_core.errors import InputError
    from senfunet_core.learning.int8_calibration import calibrate_weights_file
    from senfunet_core.weighting_int8 import calibration_path

    from ..params_file import load_settings
    from ..replay import bag_frames, engine_config
    from . import sample_bag

    if bag_arg == "":
        print(f"senfunet train: no int8 calibration (--calibration-bag ''): the node runs the weighting net of "
              f"{weights} in float32 until scripts/calibrate_int8.py --weights {weights} measures one")
        return True
    bag = Path(bag_arg) if bag_arg else sample_bag()
    try:
        frames = bag_frames(bag)
        if not frames:
            raise InputError("it holds no depth frame the node's default topics and poses give")
        calibration = calibrate_weights_file(weights, frames, engine_config(
            load_settings(None), alpha_dtype="float32", max_blocks=0), source=bag.name, progress=progress)
    except (InputError, ValueError, OSError) as err:
        _error(f"the weights are written, but their int8 calibration on {bag} failed: {err}; run "
               f"scripts/calibrate_int8.py --weights {weights} --bag BAG with a bag of the node's topics")
        return False
    print(f"senfunet train: int8 calibration of the weighting net on {calibration.calibrated_on} -> "
          f"{calibration_path(weights)} (hidden layers' largest outputs {calibration.layer_1_max:.3f}, "
          f"{calibration.layer_2_max:.3f})")
    return True
