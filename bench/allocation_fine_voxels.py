"""Whether min_new_block_samples means the same with voxels finer than 1 cm (its samples along the
band grow: samples_along_band), on one synthetic 256x256 frame (f 128 px, no noise):

    .venv/bin/python bench/allocation_fine_voxels.py                 # 1 cm, 5 mm, 2.5 mm; threshold 16
    .venv/bin/python bench/allocation_fine_voxels.py --voxels 0.01 0.004 --threshold 24

- flying pixels: isolated runs of 1, 2 or 3 pixels (a row, 20 px apart, random depths 0.8-3 m)
  alone in the frame: the blocks they touch and the blocks the threshold allocates for them;
- a surface: a slightly tilted wall at 1 m and 2 m: of the blocks holding its measured points, the
  share allocated, with the pixel spacing there in voxels.
Prints a table; the choice is stated where the default is set (EngineConfig.min_new_block_samples).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from senfunet_core.grid import BLOCK, BlockGrid  # noqa: E402
from senfunet_core.integrator import IntegratorConfig, integrate_frame, samples_along_band  # noqa: E402

SIZE, FOCAL_PX, BORDER_PX = 256, 128.0, 10
K = np.array([[FOCAL_PX, 0, (SIZE - 1) / 2], [0, FOCAL_PX, (SIZE - 1) / 2], [0, 0, 1.0]])


def allocated_blocks(depth_m: np.ndarray, voxel_size_m: float, threshold: int) -> set[tuple[int, ...]]:
    n_samples, behind = samples_along_band(voxel_size_m, 0.1)
    config = IntegratorConfig(voxel_size_m, 0.1, n_samples, behind, border_px=BORDER_PX,
                              min_new_block_samples=threshold)
    grid = BlockGrid({"tsdf0": (), "weight0": (), "feat0": (5,)}, initial_capacity=1 << 12,
                     dtypes={"weight0": torch.float16, "feat0": torch.float16})
    integrate_frame(grid, depth_m, np.ones((depth_m.size, 5), np.float32), K, np.eye(4), (0.1, 5.0), config,
                    ("tsdf0", "weight0", "feat0"))
    return {tuple(c) for c in grid.coords[: grid.n_blocks].tolist()}


def flying_pixels(run_px: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    depth = np.zeros((SIZE, SIZE), np.float32)
    for row in range(15, SIZE - 15, 20):
        for col in range(15, SIZE - 15, 20):
            depth[row, col:col + run_px] = rng.uniform(0.8, 3.0)
    return depth


def wall(distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth of a wall tilted a little, and its measured points inside the border (N, 3)."""
    v, u = np.mgrid[0:SIZE, 0:SIZE].astype(np.float64)
    depth = distance_m * (1.0 + 0.001 * u)
    points = np.stack([(u - K[0, 2]) / FOCAL_PX * depth, (v - K[1, 2]) / FOCAL_PX * depth, depth], axis=-1)
    return depth.astype(np.float32), points[BORDER_PX:-BORDER_PX, BORDER_PX:-BORDER_PX].reshape(-1, 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--voxels", type=float, nargs="+", default=[0.01, 0.005, 0.0025])
    parser.add_argument("--threshold", type=int, default=16)
    args = parser.parse_args()
    print(f"threshold {args.threshold} samples; {SIZE}x{SIZE} frame, f {FOCAL_PX:g} px")
    print("voxel_mm  written/ray  case                    touched  allocated")
    for voxel_size_m in args.voxels:
        n_samples, behind = samples_along_band(voxel_size_m, 0.1)
        written = (n_samples - 1) // 2 + behind + 1
        for run_px in (1, 2, 3):
            depth = flying_pixels(run_px)
            touched = len(allocated_blocks(depth, voxel_size_m, 0))
            kept = len(allocated_blocks(depth, voxel_size_m, args.threshold))
            print(f"{voxel_size_m * 1000:8.1f}  {written:11d}  flying pixels, runs of {run_px}  {touched:7d}  "
                  f"{kept:9d}")
        for distance_m in (1.0, 2.0):
            depth, points = wall(distance_m)
            surface = {tuple(b) for b in np.floor(points / (BLOCK * voxel_size_m)).astype(int).tolist()}
            kept_surface = surface & allocated_blocks(depth, voxel_size_m, args.threshold)
            spacing = distance_m / FOCAL_PX / voxel_size_m
            print(f"{voxel_size_m * 1000:8.1f}  {written:11d}  wall at {distance_m:g} m ({spacing:.2f} vox)   "
                  f"{len(surface):7d}  {len(kept_surface):9d} ({len(kept_surface) / len(surface):.1%})")


if __name__ == "__main__":
    main()
