"""The mesh archive over a long bounded run: the cost of one eviction's archiving, and the archive's RAM,
as the archive grows (the map bound's evictions in a building much larger than the bound).

Each eviction archives `--blocks-per-eviction` blocks' final meshes (`--faces` triangles each, as
marching cubes makes on a surface block) the way `MapBound.evict` does (`held`, `prune`, `add`),
walking away from where it started, so nothing comes back. Printed per size: the archiving time per
eviction (its mean since the size before), beside the time of what one array of all the meshes costs
(joining the new meshes to it: the archive before it was chunked), their ratio, and the archive's
bytes in RAM and in its memory-mapped files. `--write` replaces the section of docs/performance.md.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as the node sets it (node.py): torch's workers sleep

from senfunet_core.mesh_archive import MeshArchive, blocks_around  # noqa: E402
from senfunet_core.mesher import BlockMeshes  # noqa: E402


def eviction(rng: np.random.Generator, start: int, n_blocks: int, n_faces: int) -> BlockMeshes:
    """n_blocks meshes of a corridor 20 x 20 blocks wide, from block `start` on along x."""
    index = np.arange(start, start + n_blocks)
    keys = np.stack([index // 400, (index // 20) % 20, index % 20], axis=1).astype(np.int64)
    n_vertices = n_faces // 2 + 2
    origin = np.repeat(keys * 0.08, n_vertices, axis=0)
    vertices = (origin + rng.uniform(0, 0.09, (n_blocks * n_vertices, 3))).astype(np.float32)
    return BlockMeshes(keys, vertices, rng.random((n_blocks * n_vertices, 3), dtype=np.float32),
                       rng.integers(0, n_vertices, (n_blocks * n_faces, 3)).astype(np.int32),
                       np.arange(n_blocks + 1, dtype=np.int64) * n_vertices,
                       np.arange(n_blocks + 1, dtype=np.int64) * n_faces)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--evictions", type=int, default=100)
    parser.add_argument("--blocks-per-eviction", type=int, default=2000)
    parser.add_argument("--faces", type=int, default=150)
    parser.add_argument("--write", action="store_true", help="replace the section of docs/performance.md")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    archive = MeshArchive()
    voxel_size_m = 0.01
    rows, window, one_array_window = [], [], []
    one_array = BlockMeshes.concatenate([])
    report_at = {1, 2, 5, 10, 20, 50, 100, 200, 500, 1000}
    for i in range(1, args.evictions + 1):
        meshes = eviction(rng, (i - 1) * args.blocks_per_eviction, args.blocks_per_eviction, args.faces)
        in_memory = np.zeros(0, np.int64)  # the evicted blocks' neighbours are gone too: nothing to prune
        t0 = time.perf_counter()
        near = archive.held(blocks_around(meshes.keys))
        archive.prune(near, in_memory, voxel_size_m)
        archive.add(meshes, in_memory, voxel_size_m)
        window.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        one_array = BlockMeshes.concatenate([one_array, meshes])
        one_array_window.append(time.perf_counter() - t0)
        if i in report_at or i == args.evictions:
            # merges and writes come in some evictions: the mean since the last row
            seconds, one_array_s = float(np.mean(window)), float(np.mean(one_array_window))
            window, one_array_window = [], []
            chunks = archive.chunks
            ratio = f"{seconds / one_array_s:.2f}" if one_array_s > 1e-3 else "-"  # the first join copies nothing
            rows.append(f"| {len(archive)} | {seconds * 1e3:.0f} | {one_array_s * 1e3:.0f} | {ratio} | "
                        f"{chunks.bytes_in_memory / 1e6:.0f} | {chunks.bytes_on_disk / 1e6:.0f} |")
            print(rows[-1], flush=True)
    t0 = time.perf_counter()
    snapshot = archive.visible(np.zeros(0, np.int64), voxel_size_m)
    snapshot_s = time.perf_counter() - t0
    table = "\n".join([
        "| archived blocks | archiving per eviction, mean since the row before (ms) | one array: joining the "
        "new meshes alone (ms) | ratio | archive in RAM (MB) | archive in files, memory-mapped (MB) |",
        "|---|---|---|---|---|---|", *rows])
    body = (f"{args.blocks_per_eviction} blocks of {args.faces} triangles per eviction, {args.evictions} evictions; "
            f"a snapshot of the whole archive (a late subscriber) then took {snapshot_s:.2f} s for "
            f"{len(snapshot)} blocks.\n\n{table}")
    print(body)
    if args.write:
        from _common import command, machine, write_section

        write_section("Mesh archive over a long bounded run",
                      f"Machine: {machine()}\n\nCommand: `{command()}`\n\n{body}")


if __name__ == "__main__":
    main()
