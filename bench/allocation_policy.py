"""Choosing EngineConfig.min_new_block_samples on the validation rooms (issue 13 item 1).

    .venv/bin/python bench/allocation_policy.py                       # rooms 900-905, a few thresholds
    .venv/bin/python bench/allocation_policy.py --seeds 900 901 --thresholds 0 32

For each validation room (never a held-out seed) and each threshold: the fused mesh's F at 2 cm
against the ground truth, cropped to what the engine without the policy observed (so a hole the
policy makes counts against it), the grid's bytes per observed voxel, the fraction of allocated
voxels that are observed, and the samples the policy dropped. Prints a table and the means; the
choice of the default is stated where it is set (EngineConfig, the node's parameter).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from senfunet_core.engine import EngineConfig, SenFuNet  # noqa: E402
from senfunet_core.learning.evaluation import (VALIDATION_SEEDS, EvaluationConfig, cached_gt_mesh_vertices,  # noqa: E402
                                               cached_sequence, integrate_frames, observed_gt_vertices)
from senfunet_core.metrics import mesh_metrics  # noqa: E402


def room_rows(seed: int, thresholds: list[int], config: EvaluationConfig) -> list[dict]:
    if seed >= 1000:
        raise SystemExit(f"seed {seed} is held out: choose defaults on validation rooms (< 1000) only")
    seq = cached_sequence(seed, duration_s=config.duration_s, tof_rate_hz=config.tof_rate_hz,
                          stereo_rate_hz=config.stereo_rate_hz, cache_dir=config.cache_dir, log=lambda *_: None,
                          room_size_m=config.room_size_m, image_size=config.image_size)
    gt_vertices = cached_gt_mesh_vertices(seq.scene, 0.01, config.cache_dir)
    stride = {"tof": config.frame_stride, "stereo": config.frame_stride}
    crop = None
    rows = []
    for threshold in sorted(thresholds):  # 0 first: its observed set crops the ground truth for all
        t0 = time.perf_counter()
        engine = SenFuNet(EngineConfig(min_new_block_samples=threshold))
        integrate_frames(engine, seq.frames, stride)
        if crop is None:
            crop = observed_gt_vertices(engine, gt_vertices)
        mesh = engine.extract_mesh("fused")
        stats = engine.stats()
        rows.append({"seed": seed, "threshold": threshold, "F": mesh_metrics(mesh.vertices, crop)["F"],
                     "bytes_per_observed_voxel": stats["bytes_per_observed_voxel"], "occupancy": stats["occupancy"],
                     "blocks": stats["blocks"], "dropped_samples": stats["sparse_dropped_samples"],
                     "seconds": time.perf_counter() - t0})
        r = rows[-1]
        print(f"room {seed} threshold {threshold:4d}: F {r['F']:.2f} B/observed {r['bytes_per_observed_voxel']:.1f} "
              f"occupancy {r['occupancy']:.3f} blocks {r['blocks']} dropped samples {r['dropped_samples']} "
              f"({r['seconds']:.0f} s)", flush=True)
        del engine
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=list(VALIDATION_SEEDS))
    parser.add_argument("--thresholds", type=int, nargs="+", default=[0, 8, 16, 32, 64])
    args = parser.parse_args()
    thresholds = sorted(set(args.thresholds) | {0})
    rows = [r for seed in args.seeds for r in room_rows(seed, thresholds, EvaluationConfig())]
    print("\nthreshold | mean F | mean bytes per observed voxel | mean occupancy | dropped samples")
    for t in thresholds:
        sel = [r for r in rows if r["threshold"] == t]
        n = len(sel)
        print(f"{t} | {sum(r['F'] for r in sel) / n:.2f} | {sum(r['bytes_per_observed_voxel'] for r in sel) / n:.1f}"
              f" | {sum(r['occupancy'] for r in sel) / n:.3f} | {sum(r['dropped_samples'] for r in sel)}")


if __name__ == "__main__":
    main()
