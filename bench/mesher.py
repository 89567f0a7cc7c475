"""Per-block marching cubes: the numba kernel (`senfunet_core.mesher.marching_cubes_blocks`) against
the scikit-image path it replaced (kept below as `skimage_marching_cubes_blocks`, reference only).

Realistic batches: truncated TSDFs observed in a band around the surface (as the integrator leaves
them), with sensor-like noise, cut into 8^3-voxel blocks plus the +1 layer (B x 9^3): a sphere
(~3600 blocks) and the inside of a box room (noisy planes, ~4800 blocks). Prints ms per block
for both paths (CPU time of the calling thread, best of the repeats, so that other processes on a
shared machine disturb it less), the kernel's first-call time in a fresh process with an empty
numba cache (compile) and here (cache load), and how well the welded vertices agree.

    .venv/bin/python bench/mesher.py                 # ~15 s on 2 cores
    .venv/bin/python bench/mesher.py --noise 0.3     # noisier (more ambiguous cells)
    .venv/bin/python bench/mesher.py --write         # also write the section "Mesher" of docs/performance.md
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from senfunet_core.mesher import cell_mask, marching_cubes_blocks, weld  # noqa: E402

BLOCK = 8
N = BLOCK + 1


# -- the replaced implementation, for comparison only ----------------------------------------------

@dataclass
class OldBlockTriangles:
    """The former BlockTriangles."""

    vertices_vox: np.ndarray  # Vx3 float64 global voxel coordinates
    faces: np.ndarray  # Fx3 int64 into vertices_vox
    vertex_block: np.ndarray  # V index of each vertex's block in the batch
    face_block: np.ndarray  # F
    vertex_values: np.ndarray | None  # V interpolated extra value (e.g. alpha) or None


def skimage_marching_cubes_blocks(tsdf, observed, block_origin_vox, extra=None) -> OldBlockTriangles:
    """The former implementation: scikit-image's marching_cubes on blocks stacked along x, then
    every vertex recomputed from its grid edge in float64 and `extra` interpolated trilinearly."""
    from skimage.measure import marching_cubes

    n_blocks, n = tsdf.shape[0], tsdf.shape[1]
    empty = OldBlockTriangles(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64),
                              np.zeros(0, np.int64), None if extra is None else np.zeros(0))
    cells = cell_mask(observed)
    if n_blocks == 0 or not cells.any():
        return empty
    mask = np.zeros((n_blocks, n, n, n), dtype=bool)
    mask[:, 1:, 1:, 1:] = cells
    volume = np.ascontiguousarray(tsdf, dtype=np.float32).reshape(n_blocks * n, n, n)
    values = volume[mask.reshape(volume.shape)]
    if values.size == 0 or values.min() > 0 or values.max() < 0:
        return empty
    try:
        verts, faces, _, _ = marching_cubes(volume, level=0.0, mask=mask.reshape(volume.shape))
    except RuntimeError:
        return empty
    if len(faces) == 0:
        return empty
    vertex_block = np.floor(verts[:, 0] / n).astype(np.int64).clip(0, n_blocks - 1)
    local = verts.astype(np.float64)
    local[:, 0] -= vertex_block * n
    local = _exact_edge_positions(np.asarray(tsdf, dtype=np.float32), vertex_block, local)
    vertex_values = None
    if extra is not None:
        vertex_values = _interpolate(extra.astype(np.float32), vertex_block, local)
    global_vox = local + np.asarray(block_origin_vox, dtype=np.float64)[vertex_block]
    return OldBlockTriangles(global_vox, faces.astype(np.int64), vertex_block, vertex_block[faces[:, 0]],
                             vertex_values)


def _exact_edge_positions(volumes, block, local):
    n = volumes.shape[1]
    off_grid = np.abs(local - np.round(local))
    axis = np.argmax(off_grid, axis=1)
    on_edge = off_grid.max(axis=1) >= 1e-4
    rows = np.nonzero(on_edge)[0]
    if len(rows) == 0:
        return local
    ax = axis[rows]
    base = np.round(local[rows]).astype(np.int64)
    base[np.arange(len(rows)), ax] = np.floor(local[rows, ax]).astype(np.int64)
    base = base.clip(0, n - 1)
    upper = base.copy()
    upper[np.arange(len(rows)), ax] += 1
    inside = upper[np.arange(len(rows)), ax] <= n - 1
    rows, ax, base, upper = rows[inside], ax[inside], base[inside], upper[inside]
    b = block[rows]
    va = volumes[b, base[:, 0], base[:, 1], base[:, 2]].astype(np.float64)
    vb = volumes[b, upper[:, 0], upper[:, 1], upper[:, 2]].astype(np.float64)
    denom = va - vb
    ok = denom != 0
    t = np.zeros_like(va)
    t[ok] = np.clip(va[ok] / denom[ok], 0.0, 1.0)
    out = local.copy()
    exact = base.astype(np.float64)
    exact[np.arange(len(rows)), ax] += t
    out[rows[ok]] = exact[ok]
    return out


def _interpolate(volumes, block, local):
    n = volumes.shape[1]
    i0 = np.floor(local).astype(np.int64).clip(0, n - 2)
    t = local - i0
    out = np.zeros(len(local))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = ((t[:, 0] if dx else 1 - t[:, 0]) * (t[:, 1] if dy else 1 - t[:, 1])
                     * (t[:, 2] if dz else 1 - t[:, 2]))
                out += w * volumes[block, i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz]
    return out


# -- the batch --------------------------------------------------------------------------------------

def blocks_of(field, band_vox: float, noise_vox: float, coords: np.ndarray, seed: int = 0):
    """Blocks (B x 9^3 tsdf, observed, alpha; B x 3 origins) of a truncated TSDF `field` (a function
    of global voxel coordinates, N x 3 -> N) observed within band_vox of its zero set, among the
    candidate block coordinates `coords`; Gaussian noise of noise_vox on the samples."""
    rng = np.random.default_rng(seed)
    local = np.stack(np.meshgrid(*[np.arange(N)] * 3, indexing="ij"), -1).reshape(-1, 3)
    pts = coords[:, None, :] * BLOCK + local[None]  # B x 729 x 3 global voxel indices
    d = field(pts.reshape(-1, 3).astype(np.float64)).reshape(len(coords), -1)
    d += noise_vox * rng.standard_normal(d.shape)
    observed = np.abs(d) < band_vox
    keep = cell_mask(observed.reshape(-1, N, N, N)).reshape(len(coords), -1).any(1)
    tsdf = np.clip(d, -band_vox, band_vox).astype(np.float32)[keep]
    alpha = rng.random(tsdf.shape).astype(np.float32)
    return (tsdf.reshape(-1, N, N, N), observed[keep].reshape(-1, N, N, N), coords[keep] * BLOCK,
            alpha.reshape(-1, N, N, N))


def box_coords(lo, hi) -> np.ndarray:
    axes = [np.arange(a, b) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def sphere_batch(radius_vox: float, band_vox: float, noise_vox: float, seed: int = 0):
    """A sphere's truncated TSDF (positive outside) around the origin."""
    reach = int(np.ceil((radius_vox + band_vox) / BLOCK)) + 1
    return blocks_of(lambda p: np.linalg.norm(p, axis=1) - radius_vox, band_vox, noise_vox,
                     box_coords([-reach] * 3, [reach] * 3), seed)


def room_batch(size_vox, band_vox: float, noise_vox: float, seed: int = 0):
    """The inside of a box room (floor, ceiling, 4 walls; free space inside, TSDF positive) seen
    from within: noisy planes."""
    size = np.asarray(size_vox, dtype=np.float64)
    lo, hi = np.array([3.3, 2.6, 4.1]), np.array([3.3, 2.6, 4.1]) + size
    field = lambda p: np.minimum(p - lo, hi - p).min(axis=1)  # noqa: E731
    return blocks_of(field, band_vox, noise_vox, box_coords([-1] * 3, (np.ceil(hi / BLOCK) + 1).astype(int)), seed)


def cpu_time(fn) -> float:
    t0 = time.thread_time()
    fn()
    return time.thread_time() - t0


COMPILE_SNIPPET = """
import time, numpy as np
t0 = time.perf_counter()
from senfunet_core import mesher
t1 = time.perf_counter()
g = np.mgrid[0:9, 0:9, 0:9].astype(np.float32)
tsdf = (np.sqrt(((g - 4) ** 2).sum(0)) - 3.0)[None]
mesher.marching_cubes_blocks(tsdf, np.ones_like(tsdf, bool), np.zeros((1, 3), np.int64), np.zeros_like(tsdf))
t2 = time.perf_counter()
print(f"{(t1 - t0) * 1e3:.1f} {(t2 - t1) * 1e3:.1f}")
"""


def fresh_compile_ms() -> tuple[float, float]:
    """(import ms, first-call ms) of a new process with an empty numba cache."""
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=str(root))
        out = subprocess.run([sys.executable, "-c", COMPILE_SNIPPET], env=env, cwd=root, capture_output=True,
                             text=True, check=True).stdout.split()
    return float(out[0]), float(out[1])


def measure(name: str, batch, repeats: int) -> list[str]:
    """Both paths on one batch, interleaved (one scikit-image run every third kernel run) so that
    both see the same machine and allocator state; best of each."""
    tsdf, observed, origin, alpha = batch
    n_blocks = len(tsdf)
    times_new, times_old = [], []
    for r in range(repeats):
        times_new.append(cpu_time(lambda: marching_cubes_blocks(tsdf, observed, origin, alpha)))
        if r % 3 == 0:
            times_old.append(cpu_time(lambda: skimage_marching_cubes_blocks(tsdf, observed, origin, alpha)))
    t_new, t_old = min(times_new), min(times_old)
    new = marching_cubes_blocks(tsdf, observed, origin, alpha)
    old = skimage_marching_cubes_blocks(tsdf, observed, origin, alpha)
    v_new, f_new, _ = weld(new.vertices_vox, new.faces)
    v_old, f_old, _ = weld(old.vertices_vox, old.faces)
    close = np.nan
    if len(v_new) and len(v_old):
        from scipy.spatial import cKDTree

        close = float(np.mean(cKDTree(v_old).query(v_new)[0] < 1e-6))
    return [
        f"{name}: {n_blocks} blocks of {N}^3 samples, {len(new.faces)} triangles, {len(new.vertices_vox)} vertices "
        f"({len(new.faces) / n_blocks:.0f} triangles per block)",
        f"  numba kernel:  {t_new / n_blocks * 1e3:.4f} ms/block ({t_new * 1e3:.1f} ms per batch, best of {repeats})",
        f"  scikit-image:  {t_old / n_blocks * 1e3:.4f} ms/block ({t_old * 1e3:.1f} ms per batch, "
        f"best of {len(times_old)})",
        f"  speed-up:      {t_old / t_new:.1f}x",
        f"  welded: kernel {len(v_new)} vertices / {len(f_new)} faces, scikit-image {len(v_old)} / {len(f_old)}; "
        f"kernel vertices within 1e-6 of a scikit-image vertex: {close:.5f}",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--radius", type=float, default=92.0, help="sphere radius in voxels (92: ~3600 blocks)")
    parser.add_argument("--room", type=float, nargs=3, default=(260.0, 200.0, 90.0), help="room size, voxels")
    parser.add_argument("--band", type=float, default=4.0, help="observed band around the surface, voxels")
    parser.add_argument("--noise", type=float, default=0.05, help="Gaussian TSDF noise, voxels")
    parser.add_argument("--repeats", type=int, default=12)
    parser.add_argument("--write", action="store_true", help="write the section 'Mesher' of docs/performance.md")
    args = parser.parse_args()

    import_ms, compile_ms = fresh_compile_ms()
    sphere = sphere_batch(args.radius, args.band, args.noise)
    room = room_batch(args.room, args.band, args.noise)
    t0 = time.perf_counter()
    marching_cubes_blocks(*sphere)
    first_ms = (time.perf_counter() - t0) * 1e3
    lines = [
        "CPU time per call (time.thread_time), best of the repeats; ms per block = per call / blocks.",
        f"first call: {compile_ms:.0f} ms in a fresh process with an empty numba cache (compile), "
        f"{first_ms:.0f} ms here (numba cache load); import of senfunet_core.mesher {import_ms:.0f} ms "
        f"(incl. table generation); wall clock",
    ]
    lines += measure(f"sphere radius {args.radius:g} vox, band {args.band:g}, noise {args.noise:g}", sphere,
                     args.repeats)
    lines += measure(f"room {' x '.join(f'{x:g}' for x in args.room)} vox (noisy planes), band {args.band:g}, "
                     f"noise {args.noise:g}", room, args.repeats)
    print("\n".join(lines))
    if args.write:
        from _common import command, machine, write_section

        write_section("Mesher", f"{machine()}\n\n`{command()}`\n\n```\n" + "\n".join(lines) + "\n```")


if __name__ == "__main__":
    main()
